"""Reading what a design job wrote: its config, its design.npz and a part (design.npz, a hole
table or an STL), each checked against the config, with errors that name the file and the fix.

A part may have been edited by hand: a layout that breaks the process's rules is read anyway,
with the broken rules listed (`load_part`).
"""

from __future__ import annotations

import json
import math
import zipfile
import zlib
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np

from aperture_fab.config.config import Config, parse_toml, resolve
from aperture_fab.config.stages import FabricationSettings
from aperture_fab.fabrication.layout import HoleLayout
from aperture_fab.fabrication.mesh import PlateMesh
from aperture_fab.fabrication.mesh_checks import check_mesh
from aperture_fab.fabrication.part import Part, build_part, make_part
from aperture_fab.fabrication.process import Process
from aperture_fab.fabrication.quantize import quantize
from aperture_fab.fabrication.rules import layout_violations
from aperture_fab.io.files import read_text
from aperture_fab.io.manifest import check_folder
from aperture_fab.optics.scene import Scene

__all__ = [
    "CONFIG_NAME",
    "DESIGN_NAME",
    "MEASURED_NAME",
    "PartKind",
    "SavedDesign",
    "check_design",
    "check_sources",
    "validations_of",
    "design_beside",
    "design_display",
    "load_part",
    "measured_scan",
    "part_kind",
    "read_config",
    "read_design",
    "saved_part",
]

PartKind = Literal["design", "holes", "mesh"]

#: Largest array a design.npz may hold, in bytes, as its header declares it: far above any
#: design (a 4K display's content for five colour targets is 1.2 GB), and checked before
#: numpy allocates it, so that a damaged or hostile file whose header claims terabytes (or a
#: zip bomb) is refused at once rather than exhausting memory.
MAX_DESIGN_ARRAY_BYTES = 4 << 30
PART_KINDS: dict[str, PartKind] = {".npz": "design", ".csv": "holes", ".stl": "mesh"}
DESIGN_NAME = "design.npz"
CONFIG_NAME = "design.toml"
#: What `aperture-fab measure` writes beside the plate as made (issue 17): its folder reads as
#: a design folder (design.toml with no process errors, design.npz, holes.csv as measured).
MEASURED_NAME = "measured.json"
#: A mesh's thickness may differ from the config's by this share (float32 STL rounding).
THICKNESS_RTOL = 1e-4


@dataclass(frozen=True)
class SavedDesign:
    """A design.npz written by `aperture-fab design`.

    path: where it was read.
    open_fraction: (rows, cols) float64, the design the part is made from (snapped to the
        process's holes when the optimizer saw them).
    displays: (T, C, H, W) float64 linear, the display content optimized with the plate.
    built_displays: (T, C, H, W) float64, the content shown with the part, or None.
    loss_history: (N,) float64.
    names: the design's target names.
    continuous: (open fractions, displays) of the design before its plate was snapped, when
        one was kept (optimizer.quantize_share < 1), else None.
    """

    path: Path
    open_fraction: np.ndarray
    displays: np.ndarray
    built_displays: np.ndarray | None
    loss_history: np.ndarray
    names: tuple[str, ...]
    continuous: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def optimum(self) -> tuple[np.ndarray, np.ndarray]:
        """The optimized design before quantization: (open fractions, displays)."""
        return self.continuous if self.continuous is not None else (self.open_fraction,
                                                                      self.displays)


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
        text = read_text(path, "config", "give the design's design.toml with --config.")
    except FileNotFoundError:
        raise ValueError(f"config {path} does not exist; give the design's design.toml with "
                         "--config.") from None
    except OSError as err:
        raise ValueError(f"config {path}: cannot read it ({err.strerror}).") from err
    return resolve(None, parse_toml(text, str(path)), file_source=str(path))


def read_design(path: Path) -> SavedDesign:
    """Read a design.npz; ValueError naming the file when it is not one."""
    if path.is_file() and not zipfile.is_zipfile(path):
        raise ValueError(f"{path}: not a design.npz written by `aperture-fab design`, or "
                         "truncated (it is not a whole .npz archive of arrays); give the design "
                         "folder's design.npz, or design again.")
    try:
        _check_array_sizes(path)
        with np.load(path) as data:
            open_fraction = np.asarray(data["open_fraction"], dtype=np.float64)
            displays = np.asarray(data["displays"], dtype=np.float64)
            built = (np.asarray(data["built_displays"], dtype=np.float64)
                     if "built_displays" in data.files else None)
            history = (np.asarray(data["loss_history"], dtype=np.float64).ravel()
                       if "loss_history" in data.files else np.zeros(0))
            names = (tuple(str(n) for n in data["names"]) if "names" in data.files
                     else tuple(f"target{i}" for i in range(len(displays))))
            continuous = None
            if "continuous_open_fraction" in data.files:
                continuous = (np.asarray(data["continuous_open_fraction"], dtype=np.float64),
                              np.asarray(data["continuous_displays"], dtype=np.float64))
    except OversizedArrayError:
        raise  # its own message: which array, how large
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile, zlib.error,
            MemoryError) as err:
        # A truncated file (an interrupted copy) fails in zipfile or zlib, not with OSError.
        raise ValueError(f"{path}: not a design.npz written by `aperture-fab design`, or "
                         f"truncated ({type(err).__name__}: {err}); give the design folder's "
                         "design.npz, or design again.") from err
    if open_fraction.ndim != 2 or displays.ndim != 4:
        raise ValueError(f"{path}: open_fraction has shape {open_fraction.shape} and displays "
                         f"{displays.shape}; expected (rows, cols) and (T, C, H, W).")
    if open_fraction.size and not (np.all(np.isfinite(open_fraction))
                                   and 0 <= open_fraction.min() and open_fraction.max() <= 1):
        # Refused, not clipped: values out of range mean the file was edited or is not ours.
        raise ValueError(f"{path}: open_fraction holds values from {np.nanmin(open_fraction):g} "
                         f"to {np.nanmax(open_fraction):g}; allowed: finite values from 0 to 1 "
                         "(the open share of each cell). Fix the array, or design again.")
    if continuous is not None and (continuous[0].shape != open_fraction.shape
                                   or continuous[1].shape != displays.shape):
        raise ValueError(f"{path}: its continuous design has shapes {continuous[0].shape} and "
                         f"{continuous[1].shape}, unlike the design's {open_fraction.shape} and "
                         f"{displays.shape}; design again.")
    return SavedDesign(path, open_fraction, displays, built, history, names, continuous)


class OversizedArrayError(ValueError):
    """A design.npz declares an array larger than MAX_DESIGN_ARRAY_BYTES."""


def _check_array_sizes(path: Path) -> None:
    """Refuse (ValueError) a design.npz an array of which its header declares larger than
    MAX_DESIGN_ARRAY_BYTES, reading only the headers."""
    with zipfile.ZipFile(path) as archive:
        for info in archive.infolist():
            with archive.open(info) as member:
                version = np.lib.format.read_magic(member)
                read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                               else np.lib.format.read_array_header_2_0)
                shape, _, dtype = read_header(member)
            size = math.prod(shape) * dtype.itemsize
            if size > MAX_DESIGN_ARRAY_BYTES:
                raise OversizedArrayError(
                    f"{path}: its array {info.filename} declares shape {shape} "
                    f"({size / 2**30:.3g} GiB), more than any design holds (at most "
                    f"{MAX_DESIGN_ARRAY_BYTES / 2**30:g} GiB); the file is damaged or not a "
                    "design.npz. Give the design folder's design.npz, or design again.")


def check_design(design: SavedDesign, config: Config, config_path: Path) -> None:
    """The design must belong to the config's plate and display."""
    plate, display = config.scene.plate, config.scene.display
    cells = (plate.cells[1], plate.cells[0])
    pixels = (display.pixels[1], display.pixels[0])
    if design.open_fraction.shape != cells or design.displays.shape[2:] != pixels:
        raise ValueError(
            f"{design.path} has {design.open_fraction.shape} cells and {design.displays.shape[2:]}"
            f" display pixels (rows, cols) but the config {config_path} has {cells} and {pixels};"
            " give the config the design was made with (its design.toml).")


def saved_part(design: SavedDesign, config: Config, fabrication: FabricationSettings,
               config_path: Path) -> Part:
    """The part a saved design makes with the process, once it is checked to belong to the
    config (`check_design`): quantized and built by make_part (its violations are those
    quantize resolved)."""
    check_design(design, config, config_path)
    return make_part(design.open_fraction, config.scene, fabrication)


def _converge_mm(scene: Scene) -> tuple[float, float, float] | None:
    """The point chief-ray holes aim at (ex, ey, D), as make_part places it; None if straight."""
    if scene.plate.hole_axis != "chief_ray":
        return None
    ex, ey = scene.eye.positions_mm[0]
    return (float(ex), float(ey), scene.mid_plane_distance_mm)


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


def validations_of(folder: Path) -> list[Path]:
    """The validation folders inside a design folder that judged one of its parts: sub-folders
    holding a report.json with a "checked_part" naming a file of `folder` (what `validate`
    writes, by default validate_<part> beside the part; the path is as the user gave it)."""
    if not folder.is_dir():
        return []
    found = []
    for child in sorted(folder.iterdir()):
        report = child / "report.json"
        if not (child.is_dir() and not child.is_symlink() and report.is_file()):
            continue
        try:
            checked = json.loads(report.read_text()).get("checked_part") or {}
            part = Path(str(checked["path"]))
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            continue
        if (folder / part.name).is_file():
            found.append(child)
    return found


def check_sources(config_path: Path, part: Path, kind: PartKind) -> None:
    """Refuse a design folder (the config's, the part's) whose files do not match its
    manifest.json: a stale or partial set (aperture_fab.io.manifest.check_folder). A hole table
    or mesh given as the part may differ from its listing: it may have been edited by hand."""
    edited_ok = {part.name} if kind in ("holes", "mesh") else set()
    folders = {config_path.parent.resolve(): set(), part.parent.resolve(): edited_ok}
    if config_path.parent.resolve() == part.parent.resolve():
        folders = {part.parent.resolve(): edited_ok}
    for folder, names in folders.items():
        check_folder(folder, edited_ok=names)


def load_part(path: Path, kind: PartKind, config: Config, fabrication: FabricationSettings,
              config_path: Path) -> Part:
    """The part a file holds, for the config's scene and the process; its folder and the
    config's are first checked against their manifests (check_sources).

    design: quantized and built by make_part (its violations are those quantize resolved).
    holes: read_holes_csv and built as given; mesh: read_stl, the holes recovered from the mesh
    and the mesh itself kept. For both, layout.violations lists the process rules the holes
    break (layout_violations), none of them resolved.
    """
    from aperture_fab.io.formats import read_holes_csv, read_stl

    check_sources(config_path, path, kind)
    scene, process = config.scene, fabrication.process
    if kind == "design":
        return saved_part(read_design(path), config, fabrication, config_path)
    if kind == "holes":
        blank = _blank_layout(scene, process)
        try:
            text = read_text(path, "hole table", "save it as UTF-8 text (CSV), as holes_csv "
                             "writes it.")
        except OSError as err:
            raise ValueError(f"{path}: cannot read the hole table ({err}).") from err
        layout = read_holes_csv(text, scene.plate, outline_mm=blank.outline_mm,
                                converge_mm=blank.converge_mm, source=str(path))
        try:
            part = build_part(layout, fabrication, min_web_mm=0.0)
        except ValueError as err:
            raise ValueError(f"{path}: the holes cannot be built into a plate ({err}); keep "
                             "every hole inside its cell.") from err
    else:
        try:
            mesh = read_stl(path.read_bytes())
        except ValueError as err:
            raise ValueError(f"{path}: {err}") from err  # read_stl sees bytes, not the name
        layout = _layout_from_mesh(mesh, path, scene, config_path)
        part = Part(layout, mesh, check_mesh(mesh), 0.0)
    broken = layout_violations(part.layout, scene.plate, process)
    return replace(part, layout=replace(part.layout, violations=broken))


def measured_scan(folder: Path) -> str | None:
    """The scan a measured plate's folder was measured from (its measured.json's "scan", as
    `aperture-fab measure` recorded it), or None when the folder is no measured plate's."""
    try:
        scan = json.loads((folder / MEASURED_NAME).read_text(encoding="utf-8")).get("scan")
    except (OSError, ValueError, AttributeError):
        return None
    return scan if isinstance(scan, str) and scan else None


def design_beside(config_path: Path, part: Path, kind: PartKind) -> SavedDesign | None:
    """The design a part belongs to: the part itself when it is a design.npz, else the
    design.npz beside its config, or None."""
    if kind == "design":
        return read_design(part)
    path = config_path.parent / DESIGN_NAME
    return read_design(path) if path.is_file() else None


def design_display(design: SavedDesign, target_index: int) -> np.ndarray:
    """The display content (C, H, W) a design shows for target number target_index: its
    content fitted to the part when it has one."""
    shown = design.built_displays if design.built_displays is not None else design.displays
    if not (isinstance(target_index, int) and 0 <= target_index < len(shown)):
        raise ValueError(
            f"--target-index {target_index} is out of range; {design.path} has "
            f"{len(shown)} display(s) ({', '.join(design.names)}): allowed 0 to "
            f"{len(shown) - 1}.")
    return np.asarray(shown[target_index])
