"""Viewing an existing part: `aperture-fab render` (what the eye sees at one eye state, with
the design's display content) and `aperture-fab display` (the display frame solved for one
tracked eye state).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from aperture_fab.config.stages import MAX_COUNTS
from aperture_fab.io.atomic import write_atomic
from aperture_fab.io.files import load_targets
from aperture_fab.io.images import TargetOptions, encode_png, prepare_targets
from aperture_fab.io.manifest import refuse_overwrite
from aperture_fab.metrics import gain, psnr_db
from aperture_fab.optics.device import resolve_device, torch_dtype
from aperture_fab.optics.model import Renderer
from aperture_fab.optics.open_view import render_open
from aperture_fab.optics.scene import Eye, Scene
from aperture_fab.pipeline.saved import (
    CONFIG_NAME,
    DESIGN_NAME,
    check_design,
    design_beside,
    design_display,
    load_part,
    part_kind,
    read_config,
)
from aperture_fab.validation.validate import layout_fractions

__all__ = ["DisplayFrame", "RenderedView", "run_display", "run_render"]

#: A view without a target is scaled so that this percentile of its values maps to 1.
RENDER_PERCENTILE = 99.5
#: The suffix of the images render and display write.
PNG_SUFFIX = ".png"
#: The fewest --mesh-samples the re-trace takes: retrace.REPLICATES estimates of 2 rays each
#: (written out: retrace loads the ray tracer, which render needs only with --mesh).
MESH_LEAST_SAMPLES = 8


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


def _png_out(path: Path, inputs: Sequence[Path | None] = ()) -> Path:
    """An --out for a PNG, checked before any work: a file name ending in .png that is none of
    `inputs` (the target images read) and no file of a design set (its manifest.json lists
    it): writing over either would destroy it."""
    if path.is_dir():
        raise ValueError(f"--out {path} is a folder; give a PNG file name in it, e.g. --out "
                         f"{path / 'view.png'}.")
    if path.suffix.lower() != PNG_SUFFIX:
        raise ValueError(f"--out {path}: {path.suffix or 'no suffix'} is not allowed; the image "
                         f"is written as a PNG, so give a name ending in {PNG_SUFFIX}, e.g. "
                         f"--out {path.with_suffix(PNG_SUFFIX)}.")
    for given in inputs:
        if given is not None and path.exists() and given.exists() and path.samefile(given):
            raise ValueError(f"--out {path} is the target image {given} this command reads; "
                             "writing the PNG over it would destroy it. Give another --out, "
                             f"e.g. --out {path.with_name(f'view_{path.name}')}.")
    if path.parent.is_dir():
        refuse_overwrite(path.parent, [path.name])
    return path


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


def run_render(
    part: Path,
    *,
    config_path: Path | None = None,
    target: Path | None = None,
    target_options: TargetOptions | None = None,
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
    path = _png_out(out if out is not None else part.parent / f"view_{part.stem}.png", [target])
    if mesh and mesh_samples is not None and not (
            isinstance(mesh_samples, int) and MESH_LEAST_SAMPLES <= mesh_samples
            <= MAX_COUNTS["mesh_samples"]):
        raise ValueError(f"--mesh-samples {mesh_samples} is out of range; allowed: a whole "
                         f"number from {MESH_LEAST_SAMPLES} to {MAX_COUNTS['mesh_samples']} "
                         "(rays per view pixel and hole; the default is 12).")
    config_path = config_path if config_path is not None else part.parent / CONFIG_NAME
    config = read_config(config_path)
    eye = config.scene.eye
    # The flags' values are checked (and named as flags) before any work.
    _check_eye_state(config.scene, eye_mm or eye.positions_mm[0],
                     eye.pupil_mm if pupil_mm is None else float(pupil_mm), focus_mm)
    fabrication = config.fabrication.with_flags(process=process)
    design = design_beside(config_path, part, kind)
    if design is not None:
        check_design(design, config, config_path)
    view_target = on_display = None
    if target is not None:
        images, _ = load_targets([target], config.scene.display.pixels, target_options)
        channels = None if design is None else design.displays.shape[1]
        view_targets, on_displays = prepare_targets(
            images, config.scene.eye.view_pixels, config.scene.display.pixels, channels,
            names=[str(target)])
        view_target, on_display = view_targets[0], on_displays[0]
    if config.optimizer.display == "target" and on_display is not None:
        display = on_display
    elif design is not None:
        display = design_display(design, target_index)
    else:
        raise ValueError(
            f"no display content: there is no {DESIGN_NAME} beside {config_path}. Give the "
            "design's folder (its design.toml), or a TARGET when the display shows the target "
            "(optimizer.display = \"target\").")
    loaded = load_part(part, kind, config, fabrication, config_path)
    scene = _view_scene(config.scene, eye_mm, pupil_mm, focus_mm)
    position = 1
    device = resolve_device(config.optimizer.device)
    dtype = torch_dtype(config.optimizer.precision)
    display_t = torch.as_tensor(display, dtype=dtype, device=device)
    if mesh:
        from aperture_fab.validation.retrace import trace_mesh_view

        view = trace_mesh_view(loaded.mesh, scene, display, position, mesh_samples).view
    else:
        a = layout_fractions(loaded.layout, fabrication.process.radius_bias_mm)
        with torch.no_grad():
            view = Renderer(scene, device=device, dtype=dtype).render(
                torch.as_tensor(a, dtype=dtype, device=device), display_t, position
            ).cpu().double().numpy()
    with torch.no_grad():
        open_level = float(render_open(scene, display_t, position).mean())
    if not open_level > 0:
        # Not even the open display reaches the pupil: any view here is black, its light
        # efficiency 0 / 0. Say so rather than print nan.
        x, y = scene.eye.positions_mm[1]
        eye = config.scene.eye
        nominal = eye.positions_mm[0]
        raise ValueError(
            f"--eye {x:g},{y:g}: the eye sees no light from the display at that position (it "
            f"is outside the cone of light the display sends through the plate). The config's "
            f"eye is at ({nominal[0]:g}, {nominal[1]:g}) mm with an eyebox of "
            f"{eye.eyebox_mm[0]:g} x {eye.eyebox_mm[1]:g} mm around it; give an --eye near it.")
    efficiency = float(view.mean() / open_level)
    psnr = None
    if view_target is not None:
        scale = gain(view, view_target)
        psnr = psnr_db(float(np.mean((scale * view - view_target) ** 2)))
    else:
        level = float(np.percentile(view, RENDER_PERCENTILE))
        scale = 1.0 / level if level > 0 else 1.0
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
    light_share: the frame's light at the eye (the mean of its view) over the untracked
        display's; light_floor: the floor the solve held it at (0: none).
    eye_mm, pupil_mm, focus_mm (None: infinity): the eye state. path: the PNG written.
    """

    display: np.ndarray
    start_psnr_db: float
    psnr_db: float
    solve_s: float
    iterations: int
    light_share: float
    light_floor: float
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
    target_options: TargetOptions | None = None,
    eye_mm: tuple[float, float],
    pupil_mm: float,
    focus_mm: float | Literal["infinity"] | None = None,
    iterations: int | None = None,
    light_floor: float | None = None,
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
    tracking.DEFAULT_ITERATIONS. light_floor: the share of the untracked display's light at the
    eye the frame keeps (default DISPLAY_LIGHT_FLOOR; 0: none, the frame scaled to a peak of 1).
    """
    from aperture_fab.optics.eyes import EyeStates
    from aperture_fab.optimize.tracking import (
        DEFAULT_ITERATIONS,
        DISPLAY_LIGHT_FLOOR,
        tracked_views,
    )

    kind = part_kind(part)
    path = _png_out(out, [target])
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
    light_floor = DISPLAY_LIGHT_FLOOR if light_floor is None else light_floor
    if not (isinstance(light_floor, (int, float)) and not isinstance(light_floor, bool)
            and 0 <= light_floor <= 1):
        raise ValueError(f"--light-floor {light_floor!r} is out of range; allowed: a share from "
                         "0 (no floor: the sharpest frame, scaled to a peak of 1, often much "
                         "darker) to 1 (the untracked display's light kept, the default).")
    fabrication = config.fabrication.with_flags(process=process)
    design = design_beside(config_path, part, kind)
    if design is not None:
        check_design(design, config, config_path)
    images, _ = load_targets([target], scene.display.pixels, target_options)
    view_targets, on_displays = prepare_targets(
        images, scene.eye.view_pixels, scene.display.pixels,
        None if design is None else design.displays.shape[1], names=[str(target)])
    if config.optimizer.display == "target" or design is None:
        start = on_displays[0]
    else:
        start = design_display(design, target_index)
    loaded = load_part(part, kind, config, fabrication, config_path)
    device = resolve_device(config.optimizer.device)
    dtype = torch_dtype(config.optimizer.precision)
    renderer = Renderer(scene, device=device, dtype=dtype)
    a = layout_fractions(loaded.layout, fabrication.process.radius_bias_mm)
    state = EyeStates(np.array([eye_mm], dtype=np.float64), np.array([float(pupil_mm)]),
                      np.array([0.0 if focus is None else 1000.0 / focus]), np.zeros((1, 2)),
                      np.ones(1))
    began = time.perf_counter()
    solved = tracked_views(renderer, a, view_targets[0], state, start, iterations,
                           light_floor=float(light_floor))
    solve_s = time.perf_counter() - began
    with torch.no_grad():
        start_view = renderer.render_states(torch.as_tensor(a, dtype=dtype, device=device),
                                            renderer.display_stack(torch.as_tensor(
                                                start, dtype=dtype, device=device).clamp(0, 1)),
                                            state)
    light_share = float(solved.views[0].mean()) / float(start_view.mean())
    frame = solved.displays[0].detach().cpu().double().numpy()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(f"cannot create the folder {path.parent}: {err.strerror}; choose "
                         "another --out.") from err
    write_atomic(path, encode_png(np.clip(frame, 0, 1)))
    return DisplayFrame(frame, float(solved.start_psnr_db[0]), float(solved.psnr_db[0]),
                        solve_s, iterations, light_share, float(light_floor),
                        (float(eye_mm[0]), float(eye_mm[1])), float(pupil_mm), focus, path)
