"""The `aperture-fab assembly` job: the assembly sheet of a design folder with the calibration
coupon as a part, and the plate's geometry as built, for the cad/ scripts.

A design folder holds design.toml (the config, the process and the fabrication settings as used)
and design.npz (the plate); the part is re-made from them exactly as `export` does, so the sheet
describes the part the folder's files hold.

The sheet's set is assembly.html, coupon.stl, coupon.svg and coupon_holes.csv (`sheet_files`).
The design job stages them with the rest of its set; `run_assembly` adds them to a design
folder's published set (aperture_fab.io.manifest.publish with add=True), so the folder still
matches its manifest. The sheet's commands run in that folder (`command_setup`).
"""

from __future__ import annotations

import shlex
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import aperture_fab
from aperture_fab.config.config import Config
from aperture_fab.config.stages import FabricationSettings
from aperture_fab.fabrication.coupon import calibration_coupon, coupon_part
from aperture_fab.fabrication.part import Part
from aperture_fab.io.atomic import write_atomic
from aperture_fab.io.formats import holes_csv, stl_bytes, svg_text
from aperture_fab.io.manifest import MANIFEST_NAME, publish, refuse_overwrite, staging
from aperture_fab.optics.scene import Scene
from aperture_fab.pipeline.saved import (
    CONFIG_NAME,
    DESIGN_NAME,
    check_sources,
    read_config,
    read_design,
    saved_part,
)
from aperture_fab.report.assembly import (
    CAD_EXTRA,
    COUPON_CSV,
    COUPON_STL,
    COUPON_SVG,
    CommandSetup,
    assembly_html,
)

__all__ = ["ASSEMBLY_NAME", "SHEET_NAMES", "DesignPart", "PlateGeometry", "display_pngs",
           "command_setup", "load_design_part", "plate_geometry", "run_assembly", "sheet_files"]

ASSEMBLY_NAME = "assembly.html"
#: Every file of the sheet's set, written into the design folder.
SHEET_NAMES = (ASSEMBLY_NAME, COUPON_STL, COUPON_SVG, COUPON_CSV)
#: The source tree holding this package, where the cad/ scripts and pyproject.toml are (an
#: installation from a wheel has neither).
SOURCE_TREE = Path(aperture_fab.__file__).resolve().parent.parent
CAD_FOLDER_NAME = "cad"
#: The manifest's command when the sheet's files start a folder's set (a folder without one).
ASSEMBLY_COMMAND = ("aperture-fab", "assembly")


@dataclass(frozen=True)
class DesignPart:
    """A design folder read back: its config, fabrication settings, target names and the part
    re-made from design.npz."""

    folder: Path
    config: Config
    fabrication: FabricationSettings
    names: tuple[str, ...]
    part: Part


@dataclass(frozen=True)
class PlateGeometry:
    """The plate as the cad/ scripts need it, mm: outline (width, height) centred on the axis,
    thickness, the gap from the display to its display-side face, the legs of the alignment
    chamfer on its top-left corner seen from the eye (0: none), and the hole grid's size at
    the display-side face (clear_mm: what a frame's window must leave open)."""

    width_mm: float
    height_mm: float
    thickness_mm: float
    gap_mm: float
    corner_cut_mm: float
    clear_mm: tuple[float, float]


def load_design_part(folder: Path) -> DesignPart:
    """Read a design folder (design.toml and design.npz, checked against its manifest) and
    re-make its part; ValueError naming the folder and the fix when it is not one."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"design folder {folder} does not exist or is not a folder; give the "
                         "folder `aperture-fab design --out` wrote.")
    config_path, design_path = folder / CONFIG_NAME, folder / DESIGN_NAME
    missing = [p.name for p in (config_path, design_path) if not p.is_file()]
    if missing:
        raise ValueError(f"{folder} is not a design folder: it lacks {' and '.join(missing)}; "
                         "give the folder `aperture-fab design --out` wrote, or design first.")
    check_sources(config_path, design_path, "design")
    config = read_config(config_path)
    design = read_design(design_path)
    part = saved_part(design, config, config.fabrication, config_path)
    return DesignPart(folder, config, config.fabrication, design.names, part)


def plate_geometry(folder: Path) -> PlateGeometry:
    """The plate's outline, thickness, gap and chamfer as the design folder's part has them."""
    loaded = load_design_part(folder)
    layout = loaded.part.layout
    width, height = layout.outline_mm
    plate = loaded.config.scene.plate
    # Chief-ray holes spread toward the display: the grid is widest at the display-side face.
    xs, ys = layout.cell_edges_mm(-layout.thickness_mm / 2)
    clear = (2 * float(np.abs(xs).max()), 2 * float(np.abs(ys).max()))
    return PlateGeometry(float(width), float(height), plate.thickness_mm, plate.gap_mm,
                         float(loaded.part.corner_cut_mm), clear)


def command_setup(design_folder: Path) -> CommandSetup:
    """Where the sheet's commands run and with what: the design folder (absolute), this Python
    (it has aperture-fab) and this source tree's cad/ scripts; where aperture-fab was installed
    without its source, "cad" and the sheet says where the scripts come from."""
    python = sys.executable or "python"
    cad = SOURCE_TREE / CAD_FOLDER_NAME
    if (SOURCE_TREE / "pyproject.toml").is_file() and cad.is_dir():
        target = shlex.quote(f"{SOURCE_TREE}[{CAD_EXTRA}]")
        return CommandSetup(Path(design_folder).resolve(), python, cad,
                            f"{shlex.quote(python)} -m pip install -e {target}")
    return CommandSetup(Path(design_folder).resolve(), python, Path(CAD_FOLDER_NAME),
                        f"{shlex.quote(python)} -m pip install 'aperture-fab[{CAD_EXTRA}]'")


def display_pngs(folder: Path, names: Sequence[str]) -> dict[str, bytes]:
    """The display PNGs (display_<name>.png) a design folder holds, name -> bytes."""
    return {name: (folder / f"display_{name}.png").read_bytes() for name in names
            if (folder / f"display_{name}.png").is_file()}


def sheet_files(part: Part, scene: Scene, fabrication: FabricationSettings,
                names: Sequence[str], design_folder: Path, displays: Mapping[str, bytes]
                ) -> dict[str, bytes]:
    """The sheet's set, name -> bytes: assembly.html, for a part made for `scene` whose design
    is published to design_folder (its commands run there), the display PNGs `displays` (name
    -> bytes) its thumbnails; and the calibration coupon as a part, built by the plate's mesh
    builder and written by the plate's formats (mm): coupon.stl, coupon.svg (the design's SVG
    polarity), coupon_holes.csv."""
    process = fabrication.process
    coupon = coupon_part(calibration_coupon(process, scene.plate), process)
    sheet = assembly_html(part, scene, process, list(names),
                          design_name=Path(design_folder).resolve().name, displays=displays,
                          commands=command_setup(design_folder))
    return {
        ASSEMBLY_NAME: sheet.encode(),
        COUPON_STL: stl_bytes(coupon.mesh),
        COUPON_SVG: svg_text(coupon.layout, fabrication.svg_polarity,
                             corner_cut_mm=coupon.corner_cut_mm).encode(),
        COUPON_CSV: holes_csv(coupon.layout).encode(),
    }


def _add_to_set(folder: Path, files: dict[str, bytes]) -> None:
    """Put the sheet's files into a design folder: nothing when they are there already; added to
    its published set through a staging folder when it has a manifest (the folder then still
    matches it), else written one by one (a folder from before manifests is not checked)."""
    changed = {name: data for name, data in files.items()
               if not ((folder / name).is_file() and (folder / name).read_bytes() == data)}
    if not changed:
        return
    if not (folder / MANIFEST_NAME).is_file():
        for name, data in changed.items():
            write_atomic(folder / name, data)
        return
    with staging(folder) as stage:
        for name, data in files.items():
            write_atomic(stage / name, data)
        publish(stage, folder, [*ASSEMBLY_COMMAND, str(folder)], add=True)


def run_assembly(folder: Path, out: Path | None = None) -> Path:
    """The `assembly` command: the sheet's set of a design folder (sheet_files) brought up to
    date there, added to its published set; with out, the sheet is also written there (a folder
    given as out gets assembly.html). Returns the sheet's path (out's, when given)."""
    target = None if out is None else Path(out)
    if target is not None and target.is_dir():
        target = target / ASSEMBLY_NAME
    if target is not None and target.suffix.lower() not in (".html", ".htm"):
        raise ValueError(f"--out {target}: the sheet is an HTML page; give a name ending in "
                         f".html, e.g. {target.with_suffix('.html')}.")
    if target is not None and not target.parent.is_dir():
        raise ValueError(f"--out {target}: the folder {target.parent} does not exist; create it "
                         "or choose another --out.")
    loaded = load_design_part(folder)
    design_folder = loaded.folder.resolve()
    files = sheet_files(loaded.part, loaded.config.scene, loaded.fabrication, loaded.names,
                        design_folder, display_pngs(design_folder, loaded.names))
    _add_to_set(design_folder, files)
    sheet = design_folder / ASSEMBLY_NAME
    if target is None or target.resolve() == sheet:
        return sheet
    text = files[ASSEMBLY_NAME]
    if target.is_file() and target.read_bytes() == text:
        return target  # the same sheet: leave the file (and a manifest that lists it) alone
    refuse_overwrite(target.parent, [target.name])
    write_atomic(target, text)
    return target
