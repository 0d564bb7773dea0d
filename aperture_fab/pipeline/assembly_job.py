"""The `aperture-fab assembly` job: the assembly sheet of a design folder, and the plate's
geometry as built, for the cad/ scripts.

A design folder holds design.toml (the config, the process and the fabrication settings as used)
and design.npz (the plate); the part is re-made from them exactly as `export` does, so the sheet
describes the part the folder's files hold.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from aperture_fab.config.config import Config
from aperture_fab.fabrication.part import FabricationSettings, Part, fabrication_settings, make_part
from aperture_fab.io.files import write_atomic
from aperture_fab.io.manifest import refuse_overwrite
from aperture_fab.pipeline.saved import (
    CONFIG_NAME,
    DESIGN_NAME,
    check_design,
    check_sources,
    read_config,
    read_design,
)

__all__ = ["ASSEMBLY_NAME", "DesignPart", "PlateGeometry", "assembly_text", "load_design_part",
           "plate_geometry", "run_assembly", "write_assembly"]

ASSEMBLY_NAME = "assembly.html"


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
    check_design(design, config, config_path)
    fabrication = fabrication_settings(config.extra)
    part = make_part(design.open_fraction, config.scene, fabrication)
    return DesignPart(folder, config, fabrication, design.names, part)


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


def assembly_text(folder: Path, part: Part, config: Config, fabrication: FabricationSettings,
                  names: Sequence[str], design_name: str) -> str:
    """The sheet for a part; the display PNGs in `folder`, when there, become its
    thumbnails."""
    from aperture_fab.validation.assembly import assembly_html

    displays = {}
    for name in names:
        png = folder / f"display_{name}.png"
        if png.is_file():
            displays[name] = png.read_bytes()
    return assembly_html(part, config, fabrication.process, list(names),
                         design_name=design_name, displays=displays)


def write_assembly(folder: Path, part: Part, config: Config, fabrication: FabricationSettings,
                   names: Sequence[str], design_name: str) -> Path:
    """Write assembly.html into `folder` (a design job's staging folder) for its part;
    design_name: the folder the design is published to, as the sheet names it."""
    path = folder / ASSEMBLY_NAME
    write_atomic(path, assembly_text(folder, part, config, fabrication, names, design_name))
    return path


def run_assembly(folder: Path, out: Path | None = None) -> Path:
    """The `assembly` command: the sheet of a design folder, to out (default: assembly.html in
    the folder; a folder given as out gets assembly.html)."""
    target = Path(folder) / ASSEMBLY_NAME if out is None else Path(out)
    if target.is_dir():
        target = target / ASSEMBLY_NAME
    if target.suffix.lower() not in (".html", ".htm"):
        raise ValueError(f"--out {target}: the sheet is an HTML page; give a name ending in "
                         f".html, e.g. {target.with_suffix('.html')}.")
    if out is not None and not target.parent.is_dir():
        raise ValueError(f"--out {target}: the folder {target.parent} does not exist; create it "
                         "or choose another --out.")
    loaded = load_design_part(folder)
    text = assembly_text(loaded.folder, loaded.part, loaded.config, loaded.fabrication,
                         loaded.names, loaded.folder.resolve().name)
    if target.is_file() and target.read_text(errors="replace") == text:
        return target  # the same sheet: leave the file (and a manifest that lists it) alone
    refuse_overwrite(target.parent, [target.name])
    write_atomic(target, text)
    return target
