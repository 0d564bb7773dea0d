"""Rebuild the pinhole plate in CadQuery from aperture-fab's hole table (holes.csv).

For CAD users who want to edit the plate (add tabs, change the outline, fillet corners) in
CadQuery or CQ-editor. It cuts the holes with CadQuery's general booleans: simple and exact but
slow for big plates (about 10 s for 900 holes, growing faster than the hole count);
aperture-fab's own STEP export is the fast path for big plates.

Coordinates (mm): x right, y up, plate outline centred on the origin, bottom face at z = 0, top at
z = thickness. holes.csv columns: row, col, x_mm, y_mm, radius_mm, axis_x, axis_y, where (x_mm,
y_mm) is the hole centre at mid-thickness and (axis_x, axis_y) the sideways shift of the hole
centre per mm of +z (0 for straight holes). A tilted hole is the exact oblique cylinder: a circle
of radius_mm in every z-plane.

Command line:
    python cad/plate_from_csv.py holes.csv --width 20 --height 20 --thickness 0.3 --out plate.step
(--out ending in .stl writes a mesh instead.) In CQ-editor: open this file, set the parameters
under "CQ-editor parameters" below and press Render.
"""

from __future__ import annotations

import argparse
import csv
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

#: Holes are cut this far past both faces so no skin of zero thickness is left (mm).
OVERSHOOT_MM = 0.01
COLUMNS = ("row", "col", "x_mm", "y_mm", "radius_mm", "axis_x", "axis_y")

# CQ-editor parameters (used only when run inside CQ-editor).
CSV_PATH = "outputs/holes.csv"
WIDTH_MM = 20.0
HEIGHT_MM = 20.0
THICKNESS_MM = 0.3


@dataclass(frozen=True)
class Hole:
    """One hole: centre (x_mm, y_mm) at mid-thickness, radius, axis shift per mm of z."""

    x_mm: float
    y_mm: float
    radius_mm: float
    axis_x: float
    axis_y: float


def parse_holes(text: str) -> list[Hole]:
    """Holes from the text of holes.csv (header row required; '#' comment lines, such as the
    outline line aperture-fab writes last, are skipped)."""
    reader = csv.DictReader(line for line in text.splitlines()
                            if not line.lstrip().startswith("#"))
    missing = [name for name in COLUMNS if name not in (reader.fieldnames or [])]
    if missing:
        raise ValueError(f"holes.csv lacks columns {missing}; expected {list(COLUMNS)}.")
    holes = []
    for line, record in enumerate(reader, start=2):
        hole = Hole(*(float(record[name]) for name in COLUMNS[2:]))
        if not hole.radius_mm > 0:
            raise ValueError(f"holes.csv line {line}: radius_mm = {hole.radius_mm} must be > 0.")
        holes.append(hole)
    return holes


def make_plate(holes: list[Hole], width_mm: float, height_mm: float, thickness_mm: float) -> Any:
    """The plate as a CadQuery Workplane holding one solid."""
    import cadquery as cq

    for name, value in (("width_mm", width_mm), ("height_mm", height_mm),
                        ("thickness_mm", thickness_mm)):
        if not value > 0:
            raise ValueError(f"{name} = {value} must be > 0 (millimetres).")
    plate = cq.Workplane("XY").box(width_mm, height_mm, thickness_mm, centered=(True, True, False))
    if not holes:
        return plate
    cutters = []
    for hole in holes:
        # Start below the bottom face on the hole axis and sweep the circle along the axis:
        # every z-section is then a circle of the hole's radius.
        z0 = -OVERSHOOT_MM
        dz = z0 - thickness_mm / 2
        centre = cq.Vector(hole.x_mm + dz * hole.axis_x, hole.y_mm + dz * hole.axis_y, z0)
        circle = cq.Wire.makeCircle(hole.radius_mm, centre, cq.Vector(0, 0, 1))
        length = thickness_mm + 2 * OVERSHOOT_MM
        sweep = cq.Vector(hole.axis_x * length, hole.axis_y * length, length)
        cutters.append(cq.Solid.extrudeLinear(circle, [], sweep))
    return plate.cut(cq.Compound.makeCompound(cutters))


def export(plate: Any, path: Path) -> None:
    """Write STEP (.step/.stp) or STL (.stl), millimetres."""
    import cadquery as cq

    suffix = path.suffix.lower()
    kinds: dict[str, Literal["STEP", "STL"]] = {".step": "STEP", ".stp": "STEP", ".stl": "STL"}
    if suffix not in kinds:
        raise ValueError(f"--out {path}: unknown suffix {suffix!r}; use .step, .stp or .stl.")
    # A fine tessellation: holes are a fraction of a millimetre across.
    cq.exporters.export(plate, str(path), kinds[suffix], tolerance=0.002, angularTolerance=0.1)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Rebuild the plate from holes.csv in CadQuery.")
    parser.add_argument("csv", type=Path, help="hole table written by aperture-fab")
    parser.add_argument("--width", type=float, required=True, help="plate outline width, mm")
    parser.add_argument("--height", type=float, required=True, help="plate outline height, mm")
    parser.add_argument("--thickness", type=float, required=True, help="plate thickness, mm")
    parser.add_argument("--out", type=Path, default=Path("plate.step"), help=".step or .stl")
    args = parser.parse_args(argv)
    holes = parse_holes(args.csv.read_text())
    plate = make_plate(holes, args.width, args.height, args.thickness)
    export(plate, args.out)
    print(f"wrote {args.out} ({len(holes)} holes)")


if __name__ == "__main__":
    main()
elif "show_object" in globals():  # CQ-editor runs the file with show_object defined
    show_object(  # type: ignore[name-defined]  # noqa: F821
        make_plate(parse_holes(Path(CSV_PATH).read_text()), WIDTH_MM, HEIGHT_MM, THICKNESS_MM),
        name="plate",
    )
