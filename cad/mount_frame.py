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
  wider than the plate's margin (outline minus hole grid) or the ledge covers outer holes.

Command line:
    python cad/mount_frame.py --display 70 40 --bezel-height 0.5 --gap 10 \
        --plate 30 30 --plate-thickness 0.3 --out frame.step     (or frame.stl)
In CQ-editor: open this file, edit FrameSpec's defaults or the spec below, press Render.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

#: Thinnest printable wall or floor (mm): about two FDM perimeters or four resin layers.
MIN_WALL_MM = 0.8


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

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            if not (isinstance(value, (int, float)) and value >= 0):
                raise ValueError(f"FrameSpec.{name} = {value!r} must be a number >= 0 (mm).")
        for name in ("display_width_mm", "display_height_mm", "plate_width_mm",
                     "plate_height_mm", "plate_thickness_mm", "ledge_mm"):
            if not getattr(self, name) > 0:
                raise ValueError(f"FrameSpec.{name} must be > 0 (mm).")
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
        .rect(spec.plate_width_mm + 2 * spec.clearance_mm,
              spec.plate_height_mm + 2 * spec.clearance_mm)
        .extrude(spec.plate_thickness_mm)
    )
    return frame.cut(display).cut(window).cut(pocket)


def export(frame: Any, path: Path) -> None:
    """Write STEP (.step/.stp) or STL (.stl), millimetres."""
    import cadquery as cq

    kinds: dict[str, Literal["STEP", "STL"]] = {".step": "STEP", ".stp": "STEP", ".stl": "STL"}
    suffix = path.suffix.lower()
    if suffix not in kinds:
        raise ValueError(f"--out {path}: unknown suffix {suffix!r}; use .step, .stp or .stl.")
    cq.exporters.export(frame, str(path), kinds[suffix], tolerance=0.01, angularTolerance=0.1)


def main(argv: list[str] | None = None) -> None:
    defaults = FrameSpec()
    parser = argparse.ArgumentParser(description="Mounting frame for the pinhole plate.")
    parser.add_argument("--display", type=float, nargs=2, metavar=("W", "H"),
                        default=(defaults.display_width_mm, defaults.display_height_mm),
                        help="display module outline, mm")
    parser.add_argument("--display-thickness", type=float, default=defaults.display_thickness_mm)
    parser.add_argument("--bezel-height", type=float, default=defaults.bezel_height_mm,
                        help="bezel top above the emitting surface, mm")
    parser.add_argument("--gap", type=float, default=defaults.gap_mm,
                        help="emitting surface to the plate's bottom face, mm")
    parser.add_argument("--plate", type=float, nargs=2, metavar=("W", "H"),
                        default=(defaults.plate_width_mm, defaults.plate_height_mm))
    parser.add_argument("--plate-thickness", type=float, default=defaults.plate_thickness_mm)
    parser.add_argument("--wall", type=float, default=defaults.wall_mm)
    parser.add_argument("--skirt", type=float, default=defaults.skirt_mm)
    parser.add_argument("--ledge", type=float, default=defaults.ledge_mm)
    parser.add_argument("--clearance", type=float, default=defaults.clearance_mm)
    parser.add_argument("--out", type=Path, default=Path("frame.step"), help=".step or .stl")
    args = parser.parse_args(argv)
    spec = FrameSpec(
        display_width_mm=args.display[0],
        display_height_mm=args.display[1],
        display_thickness_mm=args.display_thickness,
        bezel_height_mm=args.bezel_height,
        gap_mm=args.gap,
        plate_width_mm=args.plate[0],
        plate_height_mm=args.plate[1],
        plate_thickness_mm=args.plate_thickness,
        wall_mm=args.wall,
        skirt_mm=args.skirt,
        ledge_mm=args.ledge,
        clearance_mm=args.clearance,
    )
    export(make_frame(spec), args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
elif "show_object" in globals():  # CQ-editor runs the file with show_object defined
    show_object(make_frame(FrameSpec()), name="frame")  # type: ignore[name-defined]  # noqa: F821
