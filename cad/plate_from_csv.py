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

The outline may carry the alignment key: a 45-degree chamfer of corner_cut_mm legs on its
top-left corner (-x, +y) seen from the eye, as aperture-fab builds it, so the plate fits its
frame (cad/mount_frame.py) one way round only.

Command line, from a design folder (outline, thickness and key read from the design):
    python cad/plate_from_csv.py --design outputs/x --out plate.step
or with every size given (mm):
    python cad/plate_from_csv.py holes.csv --width 22 --height 22 --thickness 0.3 \
        --corner-cut 0.6 --out plate.step
(--out ending in .stl writes a mesh instead.) --design needs aperture-fab installed. In
CQ-editor: open this file, set the parameters under "CQ-editor parameters" below and press Render.
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
#: Largest outline accepted (mm): beyond it a size is almost surely in the wrong unit.
MAX_SIZE_MM = 2000.0

# CQ-editor parameters (used only when run inside CQ-editor): the near-eye preset's plate.
CSV_PATH = "outputs/demo/holes.csv"
WIDTH_MM = 22.0
HEIGHT_MM = 22.0
THICKNESS_MM = 0.3
CORNER_CUT_MM = 0.6


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


def outline_points(width_mm: float, height_mm: float, corner_cut_mm: float = 0.0
                   ) -> list[tuple[float, float]]:
    """The outline counter-clockwise from the top-right corner, the top-left corner cut by a
    45-degree chamfer of corner_cut_mm legs (aperture_fab.fabrication.mesh.outline_points_mm)."""
    w, h = width_mm / 2, height_mm / 2
    corner = [(-w, h)] if corner_cut_mm == 0 else [(-w + corner_cut_mm, h), (-w, h - corner_cut_mm)]
    return [(w, h), *corner, (-w, -h), (w, -h)]


def check_sizes(holes: list[Hole], width_mm: float, height_mm: float, thickness_mm: float,
                corner_cut_mm: float = 0.0) -> None:
    """ValueError naming the value, the allowed range and the fix, for sizes that do not make a
    plate around these holes."""
    for flag, value, upper in (("--width", width_mm, MAX_SIZE_MM),
                               ("--height", height_mm, MAX_SIZE_MM),
                               ("--thickness", thickness_mm, min(width_mm, height_mm))):
        if not (isinstance(value, (int, float)) and 0 < value <= upper):
            raise ValueError(f"{flag} {value!r} is out of range; allowed: 0 < {flag[2:]} <= "
                             f"{upper:g} mm. Give millimetres (the design's design.toml has "
                             "them), or use --design.")
    if not (isinstance(corner_cut_mm, (int, float)) and
            0 <= corner_cut_mm < min(width_mm, height_mm) / 2):
        raise ValueError(f"--corner-cut {corner_cut_mm!r} is out of range; allowed: 0 (no key) "
                         f"to below {min(width_mm, height_mm) / 2:g} mm (half the shorter side). "
                         "Give the design's chamfer (its assembly sheet has it), or use --design.")
    w, h = width_mm / 2, height_mm / 2
    for hole in holes:
        for dz in (-thickness_mm / 2, thickness_mm / 2):  # both faces
            x, y = hole.x_mm + dz * hole.axis_x, hole.y_mm + dz * hole.axis_y
            inside = abs(x) + hole.radius_mm < w and abs(y) + hole.radius_mm < h
            # distance from the hole's centre to the chamfer's line, inward positive
            clear = ((x + w) + (h - y) - corner_cut_mm) / 2**0.5
            if not inside or (corner_cut_mm > 0 and clear <= hole.radius_mm):
                need_w = 2 * (abs(x) + hole.radius_mm)
                need_h = 2 * (abs(y) + hole.radius_mm)
                raise ValueError(
                    f"the hole at ({hole.x_mm:g}, {hole.y_mm:g}) mm, radius {hole.radius_mm:g} "
                    f"mm, crosses the outline {width_mm:g} x {height_mm:g} mm with corner cut "
                    f"{corner_cut_mm:g} mm; allowed: an outline of at least {need_w:.4g} x "
                    f"{need_h:.4g} mm that clears every hole. Give the design's outline (larger "
                    "than its hole grid by a margin) or use --design.")


def make_plate(holes: list[Hole], width_mm: float, height_mm: float, thickness_mm: float,
               corner_cut_mm: float = 0.0) -> Any:
    """The plate as a CadQuery Workplane holding one solid; corner_cut_mm > 0 chamfers the
    top-left corner (the alignment key)."""
    import cadquery as cq

    check_sizes(holes, width_mm, height_mm, thickness_mm, corner_cut_mm)
    plate = (cq.Workplane("XY").polyline(outline_points(width_mm, height_mm, corner_cut_mm))
             .close().extrude(thickness_mm))
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


def design_sizes(folder: Path) -> tuple[Path, float, float, float, float]:
    """(holes.csv, width, height, thickness, corner cut) of a design folder, the outline and
    key as aperture-fab builds the part."""
    try:
        from aperture_fab.pipeline.assembly_job import plate_geometry
    except ImportError as err:
        raise ValueError(f"--design needs aperture-fab importable ({err}); run this script with "
                         "the project's Python (.venv/bin/python), or give --width, --height, "
                         "--thickness and --corner-cut.") from err
    g = plate_geometry(folder)
    return folder / "holes.csv", g.width_mm, g.height_mm, g.thickness_mm, g.corner_cut_mm


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Rebuild the plate from holes.csv in CadQuery.")
    parser.add_argument("csv", type=Path, nargs="?",
                        help="hole table written by aperture-fab (default with --design: the "
                        "design's holes.csv)")
    parser.add_argument("--design", type=Path, metavar="FOLDER",
                        help="a design folder: outline, thickness and key from its design")
    parser.add_argument("--width", type=float, help="plate outline width, mm")
    parser.add_argument("--height", type=float, help="plate outline height, mm")
    parser.add_argument("--thickness", type=float, help="plate thickness, mm")
    parser.add_argument("--corner-cut", type=float, default=None,
                        help="legs of the top-left alignment chamfer, mm (default 0, or the "
                        "design's)")
    parser.add_argument("--out", type=Path, default=Path("plate.step"), help=".step or .stl")
    args = parser.parse_args(argv)
    try:
        csv_path, width, height, thickness, cut = resolve_sizes(args)
        try:
            text = csv_path.read_text()
        except OSError as err:
            raise ValueError(f"cannot read the hole table {csv_path} ({err.strerror}); check "
                             "the path.") from err
        holes = parse_holes(text)
        export(make_plate(holes, width, height, thickness, cut), args.out)
    except ValueError as err:
        parser.exit(2, f"{parser.prog}: error: {err}\n")
    print(f"wrote {args.out} ({len(holes)} holes, outline {width:g} x {height:g} mm, thickness "
          f"{thickness:g} mm, corner cut {cut:g} mm)")


def resolve_sizes(args: argparse.Namespace) -> tuple[Path, float, float, float, float]:
    """(hole table, width, height, thickness, corner cut): the flags, else the design's."""
    given = {"width": args.width, "height": args.height, "thickness": args.thickness,
             "corner_cut": args.corner_cut}
    csv_path = args.csv
    if args.design is not None:
        table, *found = design_sizes(args.design)
        csv_path = csv_path or table
        for key, value in zip(given, found, strict=True):
            given[key] = value if given[key] is None else given[key]  # flags win
    missing = [f"--{k}" for k in ("width", "height", "thickness") if given[k] is None]
    if csv_path is None or missing:
        raise ValueError(f"give --design FOLDER, or the hole table and {' '.join(missing)} "
                         "(mm); see --help.")
    return (csv_path, float(given["width"]), float(given["height"]), float(given["thickness"]),
            float(given["corner_cut"] or 0.0))


if __name__ == "__main__":
    main()
elif "show_object" in globals():  # CQ-editor runs the file with show_object defined
    show_object(  # type: ignore[name-defined]  # noqa: F821
        make_plate(parse_holes(Path(CSV_PATH).read_text()), WIDTH_MM, HEIGHT_MM, THICKNESS_MM,
                   CORNER_CUT_MM),
        name="plate",
    )
