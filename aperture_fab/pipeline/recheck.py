"""Checking and viewing an existing part: `aperture-fab validate` and `aperture-fab render`.

A part is a saved design (design.npz, quantized and built for the process as `export` does), a
hole table (holes.csv, built as given) or a mesh (an STL, its holes recovered from the mesh);
the last two may have been edited by hand. A hand-made layout that breaks the process's rules
is validated anyway, with the broken rules listed. The display is software and follows the
plate: by default its content is re-fitted to the part (as `design` does for the part it
makes), starting from the design's content when a design.npz lies beside the config.

Like aperture_fab.pipeline.design_job, this module reads and writes files; the stages it calls do
not.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from aperture_fab.config.config import Config, parse_toml, resolve
from aperture_fab.fabrication.layout import HoleLayout
from aperture_fab.fabrication.mesh import PlateMesh, check_mesh
from aperture_fab.fabrication.part import (
    FabricationSettings,
    Part,
    build_part,
    fabrication_settings,
    make_part,
)
from aperture_fab.fabrication.process import Process
from aperture_fab.fabrication.quantize import quantize
from aperture_fab.fabrication.rules import layout_violations
from aperture_fab.io.images import encode_png, is_grey, resample
from aperture_fab.metrics import gain
from aperture_fab.optics.model import Renderer, render_open
from aperture_fab.optics.scene import Eye, Scene
from aperture_fab.optimize.optimizer import fit_display, psnr_db, resolve_device
from aperture_fab.pipeline.design_job import (
    FIT_SHARE,
    MIN_FIT_ITERATIONS,
    load_targets,
    output_folder,
    write_atomic,
)
from aperture_fab.validation.validate import Validation, layout_fractions, validate

__all__ = [
    "PartKind",
    "SavedDesign",
    "RecheckResult",
    "RenderedView",
    "part_kind",
    "read_config",
    "read_design",
    "load_part",
    "run_validate",
    "run_render",
    "DisplayFrame",
    "run_display",
]

PartKind = Literal["design", "holes", "mesh"]
PART_KINDS: dict[str, PartKind] = {".npz": "design", ".csv": "holes", ".stl": "mesh"}
DESIGN_NAME = "design.npz"
CONFIG_NAME = "design.toml"
#: A mesh's thickness may differ from the config's by this share (float32 STL rounding).
THICKNESS_RTOL = 1e-4
#: A view without a target is scaled so that this percentile of its values maps to 1.
RENDER_PERCENTILE = 99.5
#: Display content: fitted to the part, kept from the design, or the targets themselves.
DisplaySource = Literal["fitted", "kept", "targets"]


@dataclass(frozen=True)
class SavedDesign:
    """A design.npz written by `aperture-fab design`.

    path: where it was read.
    open_fraction: (rows, cols) float64, the design before quantization.
    displays: (T, C, H, W) float64 linear, the display content optimized with the plate.
    built_displays: (T, C, H, W) float64, the content re-fitted to the part, or None.
    loss_history: (N,) float64.
    names: the design's target names.
    """

    path: Path
    open_fraction: np.ndarray
    displays: np.ndarray
    built_displays: np.ndarray | None
    loss_history: np.ndarray
    names: tuple[str, ...]


@dataclass(frozen=True)
class RecheckResult:
    """What `run_validate` did.

    folder: where report.json, report.html, views.npz and display_<target>.png were written.
    kind: the part's kind. names: (T,) target names. part: the part checked (layout, mesh).
    validation: views and metrics. display_source: where the display content came from.
    """

    folder: Path
    kind: PartKind
    names: tuple[str, ...]
    part: Part
    validation: Validation
    display_source: DisplaySource


@dataclass(frozen=True)
class RenderedView:
    """What `run_render` drew.

    view: (C, ny, nx) float64 linear light, as the eye sees it (not scaled).
    scale: the factor applied before writing the PNG (gain to the target, else 1 / percentile).
    psnr_db: PSNR of the gain-scaled view to the target, or None without one.
    light_efficiency: view mean / the open display's mean level at the same eye position.
    eye_mm: (x, y) lateral eye position. path: the PNG written.
    """

    view: np.ndarray
    scale: float
    psnr_db: float | None
    light_efficiency: float
    eye_mm: tuple[float, float]
    path: Path


# -- reading ------------------------------------------------------------------------------------


def part_kind(path: Path) -> PartKind:
    """The kind of part a file holds, from its suffix; ValueError when it is none of them."""
    kind = PART_KINDS.get(path.suffix.lower())
    if kind is None:
        raise ValueError(f"part {path}: {path.suffix or 'no suffix'} is not a part file; give a "
                         "design.npz, a holes.csv or an STL (.stl).")
    if not path.is_file():
        raise ValueError(f"part {path} does not exist or is not a file; check the path.")
    return kind


def read_config(path: Path) -> Config:
    """The resolved config of a design.toml (its own preset key, no flags)."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ValueError(f"config {path} does not exist; give the design's design.toml with "
                         "--config.") from None
    except OSError as err:
        raise ValueError(f"config {path}: cannot read it ({err.strerror}).") from err
    return resolve(None, parse_toml(text, str(path)), file_source=str(path))


def read_design(path: Path) -> SavedDesign:
    """Read a design.npz; ValueError naming the file when it is not one."""
    try:
        with np.load(path) as data:
            open_fraction = np.asarray(data["open_fraction"], dtype=np.float64)
            displays = np.asarray(data["displays"], dtype=np.float64)
            built = (np.asarray(data["built_displays"], dtype=np.float64)
                     if "built_displays" in data.files else None)
            history = (np.asarray(data["loss_history"], dtype=np.float64).ravel()
                       if "loss_history" in data.files else np.zeros(0))
            names = (tuple(str(n) for n in data["names"]) if "names" in data.files
                     else tuple(f"target{i}" for i in range(len(displays))))
    except (OSError, KeyError, ValueError) as err:
        raise ValueError(f"{path}: not a design.npz written by `aperture-fab design` ({err}); "
                         "give the design folder's design.npz.") from err
    if open_fraction.ndim != 2 or displays.ndim != 4:
        raise ValueError(f"{path}: open_fraction has shape {open_fraction.shape} and displays "
                         f"{displays.shape}; expected (rows, cols) and (T, C, H, W).")
    return SavedDesign(path, open_fraction, displays, built, history, names)


def _check_design(design: SavedDesign, config: Config, config_path: Path) -> None:
    """The design must belong to the config's plate and display."""
    plate, display = config.scene.plate, config.scene.display
    cells = (plate.cells[1], plate.cells[0])
    pixels = (display.pixels[1], display.pixels[0])
    if design.open_fraction.shape != cells or design.displays.shape[2:] != pixels:
        raise ValueError(
            f"{design.path} has {design.open_fraction.shape} cells and {design.displays.shape[2:]}"
            f" display pixels (rows, cols) but the config {config_path} has {cells} and {pixels};"
            " give the config the design was made with (its design.toml).")


def _converge_mm(scene: Scene) -> tuple[float, float, float] | None:
    """The point chief-ray holes aim at (ex, ey, D), as make_part places it; None if straight."""
    if scene.plate.hole_axis != "chief_ray":
        return None
    ex, ey = scene.eye.positions_mm[0]
    return (float(ex), float(ey), scene.eye.eye_relief_mm + scene.plate.thickness_mm / 2)


def _blank_layout(scene: Scene, process: Process) -> HoleLayout:
    """A layout without holes that has the outline and hole axes make_part would give."""
    converge = _converge_mm(scene)
    cells = (scene.plate.cells[1], scene.plate.cells[0])
    return quantize(np.zeros(cells), scene.plate, process,
                    tilt_target_mm=scene.eye.positions_mm[0],
                    eye_distance_mm=None if converge is None else converge[2], force=True)


def _layout_from_mesh(mesh: PlateMesh, path: Path, scene: Scene, config_path: Path
                      ) -> HoleLayout:
    from aperture_fab.fabrication.mesh_holes import hole_layout_from_mesh

    plate = scene.plate
    try:
        try:
            layout = hole_layout_from_mesh(mesh, plate.pitch_mm, plate.cells,
                                           converge_mm=_converge_mm(scene))
        except ValueError:
            # Hand-tilted holes no longer aim at the eye point: keep the axes as measured.
            layout = hole_layout_from_mesh(mesh, plate.pitch_mm, plate.cells)
    except ValueError as err:
        raise ValueError(
            f"{path} is not a plate of the config's grid ({plate.cells[0]} x {plate.cells[1]} "
            f"cells of {plate.pitch_mm[0]:g} x {plate.pitch_mm[1]:g} mm, from {config_path}): "
            f"{err} Give the config the part was made with (--config).") from err
    t = plate.thickness_mm
    if not math.isclose(layout.thickness_mm, t, rel_tol=THICKNESS_RTOL):
        raise ValueError(
            f"{path} is {layout.thickness_mm:.6g} mm thick but the config {config_path} has "
            f"plate.thickness_mm = {t:g}; set plate.thickness_mm = {layout.thickness_mm:.6g} in "
            "the config, or give the config the part was made with.")
    return layout


def load_part(path: Path, kind: PartKind, config: Config, fabrication: FabricationSettings,
              config_path: Path) -> Part:
    """The part a file holds, for the config's scene and the process.

    design: quantized and built by make_part (its violations are those quantize resolved).
    holes: read_holes_csv and built as given; mesh: read_stl, the holes recovered from the mesh
    and the mesh itself kept. For both, layout.violations lists the process rules the holes
    break (layout_violations), none of them resolved.
    """
    from aperture_fab.io.formats import read_holes_csv, read_stl

    scene, process = config.scene, fabrication.process
    if kind == "design":
        design = read_design(path)
        _check_design(design, config, config_path)
        return make_part(design.open_fraction, scene, fabrication)
    if kind == "holes":
        blank = _blank_layout(scene, process)
        try:
            text = path.read_text()
        except (OSError, UnicodeDecodeError) as err:
            raise ValueError(f"{path}: cannot read the hole table ({err}).") from err
        layout = read_holes_csv(text, scene.plate, outline_mm=blank.outline_mm,
                                converge_mm=blank.converge_mm, source=str(path))
        try:
            part = build_part(layout, fabrication, min_web_mm=0.0)
        except ValueError as err:
            raise ValueError(f"{path}: the holes cannot be built into a plate ({err}); keep "
                             "every hole inside its cell.") from err
    else:
        mesh = read_stl(path.read_bytes())
        layout = _layout_from_mesh(mesh, path, scene, config_path)
        part = Part(layout, mesh, check_mesh(mesh), 0.0)
    broken = layout_violations(part.layout, scene.plate, process)
    return replace(part, layout=replace(part.layout, violations=broken))


# -- targets and display content ----------------------------------------------------------------


def _prepare(config: Config, images: Sequence[np.ndarray], channels: int | None
             ) -> tuple[np.ndarray, np.ndarray]:
    """Targets on the view grid (T, C, ny, nx) and the display grid (T, C, H, W); one channel
    when every target is grey (as `design` does), or `channels` when a design fixes it."""
    grey = all(is_grey(im) for im in images)
    want = channels if channels is not None else (1 if grey else 3)
    if want == 1 and not grey:
        raise ValueError("the design's display is grey (one channel) but a target has colour; "
                         "give grey targets, or design again with colour targets.")
    prepared = [im[:1] if want == 1 else np.broadcast_to(im, (3, *im.shape[1:]))
                for im in images]
    eye, display = config.scene.eye, config.scene.display
    return (np.stack([resample(np.ascontiguousarray(im), eye.view_pixels) for im in prepared]),
            np.stack([resample(np.ascontiguousarray(im), display.pixels) for im in prepared]))


def _display_content(config: Config, targets: np.ndarray, on_display: np.ndarray,
                     as_built: np.ndarray, design: SavedDesign | None, keep: bool,
                     progress: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, DisplaySource]:
    """(designed, shown, fit loss history, source): the content the design was optimized with
    and the content shown with the part (both (T, C, H, W))."""
    settings = config.optimizer
    if settings.display == "target":
        return on_display, on_display, np.zeros(0), "targets"
    if design is None:
        if keep:
            raise ValueError(f"--keep-display needs the design's display content, but there is "
                             f"no {DESIGN_NAME} beside the config; drop --keep-display to fit "
                             "the display to the part.")
        designed = start = on_display
    else:
        designed = design.displays
        start = design.built_displays if design.built_displays is not None else design.displays
    if keep:
        return designed, start, np.zeros(0), "kept"
    iterations = max(MIN_FIT_ITERATIONS, settings.iterations // FIT_SHARE)
    fitted, history = fit_display(config.scene, targets, as_built, start, settings, iterations,
                                  progress=progress)
    return designed, fitted, history, "fitted"


def _design_beside(config_path: Path, part: Path, kind: PartKind) -> SavedDesign | None:
    if kind == "design":
        return read_design(part)
    path = config_path.parent / DESIGN_NAME
    return read_design(path) if path.is_file() else None


# -- validate -----------------------------------------------------------------------------------


def run_validate(
    part: Path,
    targets: Sequence[Path],
    *,
    config_path: Path | None = None,
    out: Path | None = None,
    process: str | None = None,
    keep_display: bool = False,
    tolerance_samples: int | None = None,
    mesh_samples: int | None = None,
    progress: bool = False,
) -> RecheckResult:
    """The `aperture-fab validate` job: validate a part (design.npz, holes.csv or STL) for the
    config and targets; write report.json, report.html, views.npz and display_<target>.png
    into `out` (default: validate_<part stem> beside the part).

    config_path: default design.toml beside the part. process: overrides the config's
    [process] name. keep_display: show design.npz's display content unchanged instead of
    re-fitting it to the part. tolerance_samples, mesh_samples: override [validation].
    """
    from aperture_fab.validation.evidence import assemble
    from aperture_fab.validation.report import report_json
    from aperture_fab.validation.validate import validation_settings

    start = time.perf_counter()
    kind = part_kind(part)
    config_path = config_path if config_path is not None else part.parent / CONFIG_NAME
    config = read_config(config_path)
    fabrication = fabrication_settings(config.extra, {"process": process})
    settings = validation_settings(config.extra, {"tolerance_samples": tolerance_samples,
                                                  "mesh_samples": mesh_samples})
    images, names = load_targets(targets)
    design = _design_beside(config_path, part, kind)
    if design is not None:
        _check_design(design, config, config_path)
        if len(design.displays) != len(images):
            raise ValueError(
                f"{design.path} was designed for {len(design.displays)} target(s) "
                f"({', '.join(design.names)}) but {len(images)} were given; give "
                f"{len(design.displays)} target(s) in the design's order.")
    loaded = load_part(part, kind, config, fabrication, config_path)
    folder = output_folder(out if out is not None else part.parent / f"validate_{part.stem}")
    view_targets, on_display = _prepare(
        config, images, None if design is None else design.displays.shape[1])
    as_built = layout_fractions(loaded.layout, fabrication.process.radius_bias_mm)
    timings = {"load_s": time.perf_counter() - start}
    start = time.perf_counter()
    designed, shown, fit_history, source = _display_content(
        config, view_targets, on_display, as_built, design, keep_display, progress)
    timings["fit_display_s"] = time.perf_counter() - start
    open_fraction = (design.open_fraction if design is not None
                     else layout_fractions(loaded.layout))
    checked = validate(config, view_targets, designed, open_fraction, loaded,
                       fabrication.process, tuple(names), settings, loaded.mesh,
                       built_displays=shown)
    history = (design.loss_history if design is not None and design.loss_history.size
               else fit_history)
    if history.size == 0:  # nothing was optimized here: the loss of the part as it is
        history = np.array([checked.metrics["as_built"][names[0]]["mse"]])
    start = time.perf_counter()
    evidence = assemble(config, tuple(names), view_targets, shown, history, loaded,
                        fabrication.process, checked, timings)
    report = dict(evidence.report)
    report["timings_s"] = {**report["timings_s"], "report_s": time.perf_counter() - start}
    report["checked_part"] = {"path": str(part), "kind": kind, "config": str(config_path),
                              "display": source,
                              "design": None if design is None else str(design.path)}
    write_atomic(folder / "views.npz", evidence.views_npz)
    write_atomic(folder / "report.html", evidence.html)
    write_atomic(folder / "report.json", report_json(report))
    for name, content in zip(names, shown, strict=True):
        write_atomic(folder / f"display_{name}.png", encode_png(np.clip(content, 0, 1)))
    return RecheckResult(folder, kind, tuple(names), loaded, checked, source)


# -- render -------------------------------------------------------------------------------------


def _view_scene(scene: Scene, eye_mm: tuple[float, float] | None, pupil_mm: float | None,
                focus_mm: float | Literal["infinity"] | None) -> Scene:
    """The scene with two eye positions: the nominal one first (chief-ray holes stay aimed at
    it, as in the tolerance analysis), the one to render second."""
    eye = scene.eye
    nominal = eye.positions_mm[0]
    where = nominal if eye_mm is None else (float(eye_mm[0]), float(eye_mm[1]))
    focus = eye.focus_mm if focus_mm is None else (None if focus_mm == "infinity"
                                                   else float(focus_mm))
    moved = Eye(eye.pupil_mm if pupil_mm is None else float(pupil_mm), eye.eye_relief_mm,
                eye.fov_deg, eye.view_pixels, focus, (nominal, where), (1.0, 1.0))
    return Scene(scene.display, scene.plate, moved)


def _design_display(design: SavedDesign, target_index: int) -> np.ndarray:
    """The display content (C, H, W) a design shows for target number target_index: its
    content fitted to the part when it has one."""
    shown = design.built_displays if design.built_displays is not None else design.displays
    if not (isinstance(target_index, int) and 0 <= target_index < len(shown)):
        raise ValueError(
            f"--target-index {target_index} is out of range; {design.path} has "
            f"{len(shown)} display(s) ({', '.join(design.names)}): allowed 0 to "
            f"{len(shown) - 1}.")
    return np.asarray(shown[target_index])


def run_render(
    part: Path,
    *,
    config_path: Path | None = None,
    target: Path | None = None,
    target_index: int = 0,
    eye_mm: tuple[float, float] | None = None,
    pupil_mm: float | None = None,
    focus_mm: float | Literal["infinity"] | None = None,
    mesh: bool = False,
    mesh_samples: int | None = None,
    process: str | None = None,
    out: Path | None = None,
) -> RenderedView:
    """The `aperture-fab render` job: the view through a part with the design's display
    content, for one eye position, written as an sRGB PNG.

    The display content is design.npz's (built_displays, else displays) number target_index,
    or the target itself when the config shows targets (optimizer.display = "target").
    eye_mm: lateral eye position (default the config's nominal one); pupil_mm, focus_mm
    override the config's eye. mesh: trace the part's mesh (Monte Carlo, mesh_samples rays
    per (view pixel, hole) pair, default retrace.DEFAULT_SAMPLES) instead of the exact model
    with the holes as made (radius bias applied).
    The PNG is the view times its least-squares gain to the target when one is given, else
    scaled so that its RENDER_PERCENTILE-th percentile is 1. out: default view_<part stem>.png
    beside the part.
    """
    kind = part_kind(part)
    config_path = config_path if config_path is not None else part.parent / CONFIG_NAME
    config = read_config(config_path)
    fabrication = fabrication_settings(config.extra, {"process": process})
    design = _design_beside(config_path, part, kind)
    if design is not None:
        _check_design(design, config, config_path)
    view_target = on_display = None
    if target is not None:
        images, _ = load_targets([target])
        channels = None if design is None else design.displays.shape[1]
        view_targets, on_displays = _prepare(config, images, channels)
        view_target, on_display = view_targets[0], on_displays[0]
    if config.optimizer.display == "target" and on_display is not None:
        display = on_display
    elif design is not None:
        display = _design_display(design, target_index)
    else:
        raise ValueError(
            f"no display content: there is no {DESIGN_NAME} beside {config_path}. Give the "
            "design's folder (its design.toml), or a TARGET when the display shows the target "
            "(optimizer.display = \"target\").")
    loaded = load_part(part, kind, config, fabrication, config_path)
    scene = _view_scene(config.scene, eye_mm, pupil_mm, focus_mm)
    position = 1
    device = resolve_device(config.optimizer.device)
    dtype = torch.float64 if config.optimizer.precision == "float64" else torch.float32
    display_t = torch.as_tensor(display, dtype=dtype, device=device)
    if mesh:
        from aperture_fab.optics.retrace import trace_mesh_view

        view = trace_mesh_view(loaded.mesh, scene, display, position, mesh_samples).view
    else:
        a = layout_fractions(loaded.layout, fabrication.process.radius_bias_mm)
        with torch.no_grad():
            view = Renderer(scene, device=device, dtype=dtype).render(
                torch.as_tensor(a, dtype=dtype, device=device), display_t, position
            ).cpu().double().numpy()
    with torch.no_grad():
        open_level = float(render_open(scene, display_t, position).mean())
    efficiency = float(view.mean() / open_level) if open_level > 0 else math.nan
    psnr = None
    if view_target is not None:
        scale = gain(view, view_target)
        psnr = psnr_db(float(np.mean((scale * view - view_target) ** 2)))
    else:
        level = float(np.percentile(view, RENDER_PERCENTILE))
        scale = 1.0 / level if level > 0 else 1.0
    path = out if out is not None else part.parent / f"view_{part.stem}.png"
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(f"cannot create the folder {path.parent}: {err.strerror}; choose "
                         "another --out.") from err
    write_atomic(path, encode_png(np.clip(view * scale, 0, 1)))
    return RenderedView(view, scale, psnr, efficiency, scene.eye.positions_mm[1], path)


# -- display (tracked) --------------------------------------------------------------------------


@dataclass(frozen=True)
class DisplayFrame:
    """What `run_display` solved and wrote.

    display: (C, H, W) float64 linear in [0, 1], the display frame for the eye state.
    start_psnr_db: PSNR after gain of the view with the untracked display (the design's).
    psnr_db: the same with the solved (tracked) frame.
    solve_s: seconds of the solve alone (renderer built; the first solve of a process also
        loads the CPU kernels). iterations: solver iterations.
    eye_mm, pupil_mm, focus_mm (None: infinity): the eye state. path: the PNG written.
    """

    display: np.ndarray
    start_psnr_db: float
    psnr_db: float
    solve_s: float
    iterations: int
    eye_mm: tuple[float, float]
    pupil_mm: float
    focus_mm: float | None
    path: Path


#: Most solver iterations `display` accepts (each costs a forward and a backward pass).
MAX_DISPLAY_ITERATIONS = 1000


def _check_eye_state(scene: Scene, eye_mm: tuple[float, float], pupil_mm: float,
                     focus_mm: float | Literal["infinity"] | None) -> float | None:
    """The focus distance in mm (None: infinity) of a valid eye state, else ValueError."""
    from aperture_fab.optics.eyes import MAX_PUPIL_MM
    from aperture_fab.optics.model import FOCUS_MARGIN

    if not (len(eye_mm) == 2 and all(math.isfinite(float(v)) for v in eye_mm)):
        raise ValueError(f"--eye {eye_mm!r}: give two finite numbers in mm as X,Y, e.g. 1.5,0.")
    if not (math.isfinite(pupil_mm) and 0 < pupil_mm <= MAX_PUPIL_MM):
        raise ValueError(f"--pupil {pupil_mm:g} is out of range; allowed: 0 < pupil <= "
                         f"{MAX_PUPIL_MM:g} mm. Give the tracked pupil's diameter in mm (a human "
                         "pupil is about 2 to 8 mm across).")
    focus = scene.eye.focus_mm if focus_mm is None else (
        None if focus_mm == "infinity" else float(focus_mm))
    nearest = scene.plate_distance_mm * FOCUS_MARGIN
    if focus is not None and not (math.isfinite(focus) and focus > nearest):
        raise ValueError(f"--focus {focus:g} is out of range; allowed: a distance beyond "
                         f"{nearest:.3g} mm (past the plate, measured from the pupil) or "
                         "'infinity'. Give the eye's focus distance in mm.")
    return focus


def run_display(
    part: Path,
    target: Path,
    *,
    eye_mm: tuple[float, float],
    pupil_mm: float,
    focus_mm: float | Literal["infinity"] | None = None,
    iterations: int | None = None,
    config_path: Path | None = None,
    target_index: int = 0,
    process: str | None = None,
    out: Path,
) -> DisplayFrame:
    """The `aperture-fab display` job: the display frame for one tracked eye state, with the
    plate as made (the holes of the part, the process's radius bias applied), written as an
    sRGB PNG at the display's pixel count.

    The solve (aperture_fab.optimize.tracking.solve_display, MLEM) starts from the design's display
    content (design.npz beside the config: built_displays, else displays, number
    target_index), or the target itself when the config shows targets; it fits the view to
    TARGET. eye_mm: the pupil centre (x, y) in mm in the scene frame; pupil_mm: its diameter;
    focus_mm: "infinity", a distance in mm, or None for the config's. iterations: default
    tracking.DEFAULT_ITERATIONS.
    """
    from aperture_fab.optics.eyes import EyeStates
    from aperture_fab.optimize.tracking import DEFAULT_ITERATIONS, tracked_views

    kind = part_kind(part)
    config_path = config_path if config_path is not None else part.parent / CONFIG_NAME
    config = read_config(config_path)
    scene = config.scene
    focus = _check_eye_state(scene, eye_mm, pupil_mm, focus_mm)
    iterations = DEFAULT_ITERATIONS if iterations is None else iterations
    if not (isinstance(iterations, int) and not isinstance(iterations, bool)
            and 0 <= iterations <= MAX_DISPLAY_ITERATIONS):
        raise ValueError(f"--iterations {iterations!r} is out of range; allowed: a whole number "
                         f"from 0 to {MAX_DISPLAY_ITERATIONS} (0 shows the untracked display). "
                         f"A few are enough: the default is {DEFAULT_ITERATIONS}.")
    fabrication = fabrication_settings(config.extra, {"process": process})
    design = _design_beside(config_path, part, kind)
    if design is not None:
        _check_design(design, config, config_path)
    images, _ = load_targets([target])
    view_targets, on_displays = _prepare(
        config, images, None if design is None else design.displays.shape[1])
    if config.optimizer.display == "target" or design is None:
        start = on_displays[0]
    else:
        start = _design_display(design, target_index)
    loaded = load_part(part, kind, config, fabrication, config_path)
    device = resolve_device(config.optimizer.device)
    dtype = torch.float64 if config.optimizer.precision == "float64" else torch.float32
    renderer = Renderer(scene, device=device, dtype=dtype)
    a = layout_fractions(loaded.layout, fabrication.process.radius_bias_mm)
    state = EyeStates(np.array([eye_mm], dtype=np.float64), np.array([float(pupil_mm)]),
                      np.array([0.0 if focus is None else 1000.0 / focus]), np.zeros((1, 2)),
                      np.ones(1))
    began = time.perf_counter()
    solved = tracked_views(renderer, a, view_targets[0], state, start, iterations)
    solve_s = time.perf_counter() - began
    frame = solved.displays[0].detach().cpu().double().numpy()
    path = out
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(f"cannot create the folder {path.parent}: {err.strerror}; choose "
                         "another --out.") from err
    write_atomic(path, encode_png(np.clip(frame, 0, 1)))
    return DisplayFrame(frame, float(solved.start_psnr_db[0]), float(solved.psnr_db[0]),
                        solve_s, iterations, (float(eye_mm[0]), float(eye_mm[1])),
                        float(pupil_mm), focus, path)
