"""A parametric frame that holds the pinhole plate at the design gap over a display (CadQuery).

Coordinates (mm): the display's emitting surface is z = 0, centred on the origin; x right, y up;
light goes toward +z (as in aperture-fab's scene). The frame:

- rests on the display's bezel, whose top stands bezel_height_mm above the emitting surface;
- locates itself on the display with a skirt that hugs the display's sides down to skirt_mm
  below the bezel top (clearance_mm all round);
- carries the plate in a pocket on its top: the plate lies on a ledge at z = gap_mm (the plate's
  bottom face, aperture-fab's `plate.gap_mm`) and its top is flush with the frame's top at
  z = gap_mm + plate_thickness_mm;
- leaves a window for the light: the plate outline less ledge_mm on each side. Keep ledge_mm no
  wider than the plate's margin (outline minus hole grid) or the ledge covers outer holes;
- keys the pocket to the plate: the plate's top-left corner (seen from the eye) is chamfered
  with key_mm legs, and the pocket's top-left corner is filled to match, so the plate seats only
  the right way round and the right face up.

Command line, from a design folder (plate outline, thickness, gap and key from the design):
    python cad/mount_frame.py --design outputs/x --display 70 40 --bezel-height 0.5 \
        --out frame.step     (or frame.stl)
or with every size given (mm):
    python cad/mount_frame.py --display 70 40 --bezel-height 0.5 --gap 10 \
        --plate 22 22 --plate-thickness 0.3 --key 0.6 --out frame.step
--design needs aperture-fab installed. In CQ-editor: open this file, edit FrameSpec's defaults
or the spec below, press Render.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

#: Thinnest printable wall or floor (mm): about two FDM perimeters or four resin layers.
MIN_WALL_MM = 0.8
#: Largest size accepted (mm): beyond it a value is almost surely in the wrong unit.
MAX_SIZE_MM = 2000.0
#: Chamfer legs grow by this times the clearance when the chamfered outline is offset by it.
CHAMFER_OFFSET_GROWTH = 2 - 2**0.5
#: A ledge narrowed for a design is rounded down to 1 / LEDGE_STEPS mm.
LEDGE_STEPS = 100


@dataclass(frozen=True)
class FrameSpec:
    """Frame parameters, millimetres.

    display_width_mm, display_height_mm: the display module's outer outline (the skirt hugs it).
    display_thickness_mm: module thickness; the skirt reaches at most this far down.
    bezel_height_mm: how far the bezel top stands above the emitting surface (0 if flush).
    gap_mm: emitting surface to the plate's bottom face (aperture-fab's plate.gap_mm).
    plate_width_mm, plate_height_mm, plate_thickness_mm: the plate's outline and thickness.
    wall_mm: frame wall thickness outside the display outline.
    skirt_mm: how far the skirt reaches down the display's sides below the bezel top.
    ledge_mm: width of the ledge the plate lies on.
    clearance_mm: gap left around the display and around the plate for a slip fit.
    key_mm: legs of the 45-degree chamfer on the plate's top-left corner seen from the eye
        (aperture-fab's alignment cut); the pocket gets a matching key. 0: no key.
    clear_width_mm, clear_height_mm: the hole grid's size at the plate's display-side face;
        the window must leave it open (0: not checked).
    """

    display_width_mm: float = 70.0
    display_height_mm: float = 40.0
    display_thickness_mm: float = 3.0
    bezel_height_mm: float = 0.5
    gap_mm: float = 10.0
    plate_width_mm: float = 30.0
    plate_height_mm: float = 30.0
    plate_thickness_mm: float = 0.3
    wall_mm: float = 2.0
    skirt_mm: float = 2.0
    ledge_mm: float = 1.0
    clearance_mm: float = 0.15
    key_mm: float = 0.0
    clear_width_mm: float = 0.0
    clear_height_mm: float = 0.0

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            if not (isinstance(value, (int, float)) and 0 <= value <= MAX_SIZE_MM):
                raise ValueError(f"FrameSpec.{name} = {value!r} is out of range; allowed: 0 to "
                                 f"{MAX_SIZE_MM:g} mm. Give millimetres.")
        for name in ("display_width_mm", "display_height_mm", "plate_width_mm",
                     "plate_height_mm", "plate_thickness_mm", "ledge_mm"):
            if not getattr(self, name) > 0:
                raise ValueError(f"FrameSpec.{name} = {getattr(self, name)!r} is out of range; "
                                 f"allowed: > 0 mm (up to {MAX_SIZE_MM:g}). Give the size in mm.")
        if self.wall_mm < MIN_WALL_MM:
            raise ValueError(f"FrameSpec.wall_mm = {self.wall_mm} must be >= {MIN_WALL_MM}.")
        if self.skirt_mm > self.display_thickness_mm:
            raise ValueError(
                f"FrameSpec.skirt_mm = {self.skirt_mm} reaches past the display's back "
                f"(display_thickness_mm = {self.display_thickness_mm}); make it shorter."
            )
        floor = self.gap_mm - self.bezel_height_mm
        if floor < MIN_WALL_MM:
            raise ValueError(
                f"FrameSpec.gap_mm = {self.gap_mm} leaves a {floor:g} mm floor under the plate "
                f"above the bezel (bezel_height_mm = {self.bezel_height_mm}); allowed: gap >= "
                f"bezel height + {MIN_WALL_MM} mm. Use a larger gap or a thinner bezel."
            )
        for axis in ("width", "height"):
            pocket = getattr(self, f"plate_{axis}_mm") + 2 * self.clearance_mm
            outer = self.outer_mm[0 if axis == "width" else 1]
            if pocket + 2 * MIN_WALL_MM > outer:
                raise ValueError(
                    f"FrameSpec.plate_{axis}_mm = {getattr(self, f'plate_{axis}_mm')} does not "
                    f"fit: the pocket ({pocket:g} mm) needs {MIN_WALL_MM} mm walls inside the "
                    f"frame's {outer:g} mm outline. Use a smaller plate or a larger wall_mm."
                )
            window = getattr(self, f"plate_{axis}_mm") - 2 * self.ledge_mm
            if window <= 0:
                raise ValueError(f"FrameSpec.ledge_mm = {self.ledge_mm} closes the window.")
            if window >= getattr(self, f"display_{axis}_mm"):
                raise ValueError(
                    f"FrameSpec: the window ({window:g} mm {axis}) is not smaller than the "
                    "display, so the frame has nothing to rest on. Use a wider ledge_mm or a "
                    "smaller plate."
                )
            clear = getattr(self, f"clear_{axis}_mm")
            if window < clear:
                widest = (getattr(self, f"plate_{axis}_mm") - clear) / 2
                raise ValueError(
                    f"FrameSpec.ledge_mm = {self.ledge_mm:g} covers the outer holes: the window "
                    f"is {window:g} mm ({axis}) but the hole grid spans {clear:.4g} mm at the "
                    f"plate's display-side face; allowed: ledge_mm <= {widest:.3f}. Use a "
                    "narrower ledge (--ledge).")
        self._check_key()

    def _check_key(self) -> None:
        if self.key_mm == 0:
            return
        shorter = min(self.plate_width_mm, self.plate_height_mm)
        least = self.clearance_mm * 2**0.5  # a square corner must not slip past the key
        if not least < self.key_mm < shorter / 2:
            raise ValueError(
                f"FrameSpec.key_mm = {self.key_mm:g} is out of range; allowed: above "
                f"{least:.3f} mm (clearance_mm x sqrt 2, or a plate turned round still seats) and "
                f"below {shorter / 2:g} mm (half the plate's shorter side). Give the plate's own "
                "chamfer (--design reads it), or a smaller clearance.")

    @property
    def outer_mm(self) -> tuple[float, float]:
        """Frame outline (width, height)."""
        grow = 2 * (self.clearance_mm + self.wall_mm)
        return self.display_width_mm + grow, self.display_height_mm + grow

    @property
    def top_mm(self) -> float:
        """Height of the frame's top (= the plate's top face) above the emitting surface."""
        return self.gap_mm + self.plate_thickness_mm


def make_frame(spec: FrameSpec) -> Any:
    """The frame as a CadQuery Workplane holding one solid."""
    import cadquery as cq

    outer_w, outer_h = spec.outer_mm
    bottom = spec.bezel_height_mm - spec.skirt_mm
    frame = (
        cq.Workplane("XY", origin=(0, 0, bottom))
        .rect(outer_w, outer_h)
        .extrude(spec.top_mm - bottom)
    )
    # The skirt's inside: the display outline plus clearance, up to the bezel top.
    display = (
        cq.Workplane("XY", origin=(0, 0, bottom))
        .rect(spec.display_width_mm + 2 * spec.clearance_mm,
              spec.display_height_mm + 2 * spec.clearance_mm)
        .extrude(spec.skirt_mm)
    )
    window = (
        cq.Workplane("XY", origin=(0, 0, bottom))
        .rect(spec.plate_width_mm - 2 * spec.ledge_mm, spec.plate_height_mm - 2 * spec.ledge_mm)
        .extrude(spec.top_mm - bottom)
    )
    pocket = (
        cq.Workplane("XY", origin=(0, 0, spec.gap_mm))
        .polyline(pocket_points(spec)).close()
        .extrude(spec.plate_thickness_mm)
    )
    return frame.cut(display).cut(window).cut(pocket)


def pocket_points(spec: FrameSpec) -> list[tuple[float, float]]:
    """The pocket's outline, counter-clockwise from the top-right: the plate's outline grown by
    the clearance, its top-left corner (seen from the eye) filled by the key when key_mm > 0
    (the plate's chamfer offset outward by the clearance)."""
    w = spec.plate_width_mm / 2 + spec.clearance_mm
    h = spec.plate_height_mm / 2 + spec.clearance_mm
    if spec.key_mm == 0:
        return [(w, h), (-w, h), (-w, -h), (w, -h)]
    leg = spec.key_mm + spec.clearance_mm * CHAMFER_OFFSET_GROWTH
    return [(w, h), (-w + leg, h), (-w, h - leg), (-w, -h), (w, -h)]


def export(frame: Any, path: Path) -> None:
    """Write STEP (.step/.stp) or STL (.stl), millimetres."""
    import cadquery as cq

    kinds: dict[str, Literal["STEP", "STL"]] = {".step": "STEP", ".stp": "STEP", ".stl": "STL"}
    suffix = path.suffix.lower()
    if suffix not in kinds:
        raise ValueError(f"--out {path}: unknown suffix {suffix!r}; use .step, .stp or .stl.")
    cq.exporters.export(frame, str(path), kinds[suffix], tolerance=0.01, angularTolerance=0.1)


def design_plate(folder: Path) -> dict[str, float]:
    """The plate's outline, thickness, gap, key and clear hole grid from a design folder, as
    FrameSpec fields."""
    try:
        from aperture_fab.pipeline.assembly_job import plate_geometry
    except ImportError as err:
        raise ValueError(f"--design needs aperture-fab importable ({err}); run this script with "
                         "the project's Python (.venv/bin/python), or give --plate, "
                         "--plate-thickness, --gap and --key.") from err
    g = plate_geometry(folder)
    return {"plate_width_mm": g.width_mm, "plate_height_mm": g.height_mm,
            "plate_thickness_mm": g.thickness_mm, "gap_mm": g.gap_mm, "key_mm": g.corner_cut_mm,
            "clear_width_mm": g.clear_mm[0], "clear_height_mm": g.clear_mm[1]}


def default_ledge(plate: dict[str, float]) -> float:
    """FrameSpec's ledge, narrowed (to 0.01 mm) so the window leaves a design's hole grid open."""
    ledge = FrameSpec.ledge_mm
    for axis in ("width", "height"):
        clear = plate.get(f"clear_{axis}_mm", 0.0)
        size = plate.get(f"plate_{axis}_mm", getattr(FrameSpec, f"plate_{axis}_mm"))
        if clear > 0:
            ledge = min(ledge, math.floor((size - clear) / 2 * LEDGE_STEPS) / LEDGE_STEPS)
    return ledge


def main(argv: list[str] | None = None) -> None:
    defaults = FrameSpec()
    parser = argparse.ArgumentParser(description="Mounting frame for the pinhole plate.")
    parser.add_argument("--design", type=Path, metavar="FOLDER",
                        help="a design folder: plate outline, thickness, gap and key from it "
                        "(flags given as well win)")
    parser.add_argument("--display", type=float, nargs=2, metavar=("W", "H"),
                        default=(defaults.display_width_mm, defaults.display_height_mm),
                        help="display module outline, mm")
    parser.add_argument("--display-thickness", type=float, default=defaults.display_thickness_mm)
    parser.add_argument("--bezel-height", type=float, default=defaults.bezel_height_mm,
                        help="bezel top above the emitting surface, mm")
    parser.add_argument("--gap", type=float,
                        help=f"emitting surface to the plate's bottom face, mm (default: the "
                        f"design's, else {defaults.gap_mm:g})")
    parser.add_argument("--plate", type=float, nargs=2, metavar=("W", "H"),
                        help="plate outline, mm (default: the design's, else "
                        f"{defaults.plate_width_mm:g} {defaults.plate_height_mm:g})")
    parser.add_argument("--plate-thickness", type=float,
                        help="plate thickness, mm (default: the design's, else "
                        f"{defaults.plate_thickness_mm:g})")
    parser.add_argument("--key", type=float,
                        help="legs of the plate's top-left chamfer, mm (default: the design's, "
                        "else 0: no key)")
    parser.add_argument("--wall", type=float, default=defaults.wall_mm)
    parser.add_argument("--skirt", type=float, default=defaults.skirt_mm)
    parser.add_argument("--ledge", type=float,
                        help=f"ledge under the plate's edge, mm (default {defaults.ledge_mm:g}, "
                        "narrowed to leave the design's outer holes open)")
    parser.add_argument("--clearance", type=float, default=defaults.clearance_mm)
    parser.add_argument("--out", type=Path, default=Path("frame.step"), help=".step or .stl")
    args = parser.parse_args(argv)
    try:
        plate = {} if args.design is None else design_plate(args.design)
        given = {"gap_mm": args.gap, "plate_thickness_mm": args.plate_thickness,
                 "key_mm": args.key}
        if args.plate is not None:
            given.update(plate_width_mm=args.plate[0], plate_height_mm=args.plate[1])
        plate.update({k: v for k, v in given.items() if v is not None})
        ledge = args.ledge if args.ledge is not None else default_ledge(plate)
        spec = FrameSpec(
            display_width_mm=args.display[0],
            display_height_mm=args.display[1],
            display_thickness_mm=args.display_thickness,
            bezel_height_mm=args.bezel_height,
            wall_mm=args.wall,
            skirt_mm=args.skirt,
            ledge_mm=ledge,
            clearance_mm=args.clearance,
            **plate,
        )
        export(make_frame(spec), args.out)
    except ValueError as err:
        parser.exit(2, f"{parser.prog}: error: {err}\n")
    print(f"wrote {args.out} (plate {spec.plate_width_mm:g} x {spec.plate_height_mm:g} x "
          f"{spec.plate_thickness_mm:g} mm at gap {spec.gap_mm:g} mm, key {spec.key_mm:g} mm, "
          f"ledge {spec.ledge_mm:g} mm)")


if __name__ == "__main__":
    main()
elif "show_object" in globals():  # CQ-editor runs the file with show_object defined
    show_object(make_frame(FrameSpec()), name="frame")  # type: ignore[name-defined]  # noqa: F821
