"""The assembly sheet's drawings: inline SVG to scale, one user unit = 1 mm.

Every drawing is seen from the eye (looking toward -z, the display behind the plate), so x is to
the right and y up as in the scene (docs/design.md, "Conventions"); SVG's y runs down, so points
are drawn at (x, -y). A drawing's physical size is its viewBox times its scale: its `width` and
`height` attributes are in millimetres, so a page printed at 100 % holds the part to that scale.
"""

from __future__ import annotations

import html
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from aperture_fab.fabrication.coupon import Coupon
from aperture_fab.fabrication.layout import HoleLayout
from aperture_fab.fabrication.mesh import outline_points_mm

__all__ = [
    "Coupon",
    "StackSizes",
    "coupon_drawing",
    "drawing_scale",
    "plate_drawing",
    "placement_drawing",
    "scale_bar",
    "scale_label",
    "stack_drawing",
]

#: Printable width and height of an A4 page less its margins (mm on paper).
PAPER_WIDTH_MM = 180.0
PAPER_HEIGHT_MM = 150.0
#: Drawing scales tried, largest first (paper mm per part mm).
DRAWING_SCALES = (10.0, 5.0, 4.0, 2.0, 1.0, 0.5, 0.2, 0.1, 0.05)
#: Room on paper around a drawing for its dimensions and labels (mm on paper).
PAD_MM = 16.0
#: Text height and line width on paper (mm).
TEXT_MM = 2.8
LINE_MM = 0.25
#: Dimension tick half-length on paper (mm).
TICK_MM = 1.2


def drawing_scale(width_mm: float, height_mm: float, pad_mm: float = PAD_MM) -> float:
    """The largest of DRAWING_SCALES at which a part of this size, plus pad_mm of paper each
    side, fits the printable A4 area."""
    for scale in DRAWING_SCALES:
        if (width_mm * scale + 2 * pad_mm <= PAPER_WIDTH_MM
                and height_mm * scale + 2 * pad_mm <= PAPER_HEIGHT_MM):
            return scale
    return DRAWING_SCALES[-1]


def scale_label(scale: float) -> str:
    """"4:1", "1:1", "1:2"."""
    return f"{scale:g}:1" if scale >= 1 else f"1:{1 / scale:g}"


@dataclass(frozen=True)
class _Pen:
    """Sizes in user units (part mm) for a drawing at `scale`."""

    scale: float

    @property
    def text(self) -> float:
        return TEXT_MM / self.scale

    @property
    def line(self) -> float:
        return LINE_MM / self.scale

    @property
    def tick(self) -> float:
        return TICK_MM / self.scale

    @property
    def pad(self) -> float:
        return PAD_MM / self.scale


def _f(value: float) -> str:
    return f"{value:.4f}".rstrip("0").rstrip(".") or "0"


def _svg(x0: float, y0: float, width: float, height: float, scale: float, label: str,
         body: Sequence[str], kind: str) -> str:
    """An <svg> whose viewBox is in part mm and whose printed size is that times scale; its
    scale is written in its bottom-left corner."""
    pen = _Pen(scale)
    body = [*body, _text(pen, x0 + pen.text, y0 + height - pen.text, f"scale {scale_label(scale)}",
                         "start", "scale")]
    return (
        f'<svg xmlns="http://www.w3.org/2000/svg" class="drawing {kind}" '
        f'viewBox="{_f(x0)} {_f(y0)} {_f(width)} {_f(height)}" '
        f'width="{_f(width * scale)}mm" height="{_f(height * scale)}mm" '
        f'data-scale="{_f(scale)}" role="img" aria-label="{html.escape(label)}">\n'
        + "\n".join(body) + "\n</svg>"
    )


def _text(pen: _Pen, x: float, y: float, text: str, anchor: str = "middle",
          css: str = "", rotate: float = 0.0) -> str:
    extra = f' class="{css}"' if css else ""
    if rotate:
        extra += f' transform="rotate({_f(rotate)} {_f(x)} {_f(y)})"'
    return (f'<text x="{_f(x)}" y="{_f(y)}" font-size="{_f(pen.text)}" '
            f'text-anchor="{anchor}"{extra}>{html.escape(text)}</text>')


def _line(pen: _Pen, x1: float, y1: float, x2: float, y2: float, css: str = "dim") -> str:
    return (f'<line class="{css}" x1="{_f(x1)}" y1="{_f(y1)}" x2="{_f(x2)}" y2="{_f(y2)}" '
            f'stroke-width="{_f(pen.line)}"/>')


def _dimension(pen: _Pen, a: tuple[float, float], b: tuple[float, float], offset: float,
               text: str) -> list[str]:
    """A dimension between SVG points a and b, its line `offset` away (to the left of a->b),
    with extension lines and 45-degree ticks, the text centred beside it."""
    dx, dy = b[0] - a[0], b[1] - a[1]
    length = math.hypot(dx, dy)
    nx, ny = dy / length, -dx / length  # to the left of a->b in SVG coordinates
    pa = (a[0] + nx * offset, a[1] + ny * offset)
    pb = (b[0] + nx * offset, b[1] + ny * offset)
    parts = [_line(pen, a[0], a[1], pa[0] + nx * pen.tick, pa[1] + ny * pen.tick, "ext"),
             _line(pen, b[0], b[1], pb[0] + nx * pen.tick, pb[1] + ny * pen.tick, "ext"),
             _line(pen, pa[0], pa[1], pb[0], pb[1])]
    t = pen.tick * math.sqrt(0.5)
    for px, py in (pa, pb):
        parts.append(_line(pen, px - t * (dx + nx * length) / length,
                           py - t * (dy + ny * length) / length,
                           px + t * (dx + nx * length) / length,
                           py + t * (dy + ny * length) / length))
    mx, my = (pa[0] + pb[0]) / 2 + nx * pen.text * 0.9, (pa[1] + pb[1]) / 2 + ny * pen.text * 0.9
    angle = math.degrees(math.atan2(dy, dx))
    if angle > 90 or angle <= -90:
        angle -= 180
    parts.append(f'<text x="{_f(mx)}" y="{_f(my)}" font-size="{_f(pen.text)}" '
                 f'text-anchor="middle" dominant-baseline="middle" '
                 f'transform="rotate({_f(angle)} {_f(mx)} {_f(my)})">{html.escape(text)}</text>')
    return parts


def _polygon(points: Sequence[tuple[float, float]], pen: _Pen, css: str) -> str:
    text = " ".join(f"{_f(x)},{_f(-y)}" for x, y in points)
    return f'<polygon class="{css}" points="{text}" stroke-width="{_f(pen.line)}"/>'


def _rect(x: float, y_top: float, width: float, height: float, pen: _Pen, css: str) -> str:
    """A rectangle given in part coordinates: left x, top y (y up)."""
    return (f'<rect class="{css}" x="{_f(x)}" y="{_f(-y_top)}" width="{_f(width)}" '
            f'height="{_f(height)}" stroke-width="{_f(pen.line)}"/>')


def plate_drawing(layout: HoleLayout, corner_cut_mm: float) -> str:
    """The plate seen from the eye: the outline with its alignment chamfer (top-left), the cell
    grid, every hole at the eye-side face, and the outline's dimensions."""
    width, height = layout.outline_mm
    scale = drawing_scale(width, height)
    pen = _Pen(scale)
    nx, ny = layout.grid
    px, py = layout.pitch_mm
    body = [_polygon(outline_points_mm(layout, corner_cut_mm), pen, "outline")]
    body.append(_rect(-nx * px / 2, ny * py / 2, nx * px, ny * py, pen, "grid"))
    top = layout.centres_mm + layout.thickness_mm / 2 * layout.axes
    body.append('<g class="holes">' + "".join(
        f'<circle cx="{_f(x)}" cy="{_f(-y)}" r="{_f(r)}"/>'
        for (x, y), r in zip(top.tolist(), layout.radii_mm.tolist(), strict=True)) + "</g>")
    left, right, up, down = -width / 2, width / 2, -height / 2, height / 2  # SVG y
    body += _dimension(pen, (left, down), (right, down), -pen.pad * 0.35, f"{width:g} mm")
    body += _dimension(pen, (right, down), (right, up), -pen.pad * 0.35, f"{height:g} mm")
    if corner_cut_mm > 0:
        cx, cy = left + corner_cut_mm / 2, up + corner_cut_mm / 2
        body.append(_line(pen, cx, cy, cx - pen.pad * 0.35, cy - pen.pad * 0.45, "leader"))
        body.append(_text(pen, cx - pen.pad * 0.35, cy - pen.pad * 0.5,
                          f"key: {corner_cut_mm:.2f} mm chamfer", "start", "key"))
    body.append(_text(pen, 0, up - pen.pad * 0.15, "top (image row 0)"))
    body.append(_text(pen, left - pen.pad * 0.15, 0, "left (column 0)", rotate=-90))
    x0, y0 = left - pen.pad, up - pen.pad
    label = (f"plate seen from the eye, {width:g} x {height:g} mm, scale {scale_label(scale)}")
    return _svg(x0, y0, width + 2 * pen.pad, height + 2 * pen.pad, scale, label, body, "plate")


@dataclass(frozen=True)
class StackSizes:
    """Side-view sizes (mm): display active width, plate outline width, gap, thickness, eye
    relief, pupil diameter, eyebox width, the frame's ledge under the plate."""

    display_mm: float
    plate_mm: float
    gap_mm: float
    thickness_mm: float
    eye_relief_mm: float
    pupil_mm: float
    eyebox_mm: float
    ledge_mm: float


def stack_drawing(s: StackSizes) -> str:
    """The device in section (x to the right, z up toward the eye): display, frame, plate, eye."""
    z_plate, z_top = s.gap_mm, s.gap_mm + s.thickness_mm
    z_eye = z_top + s.eye_relief_mm
    half = max(s.display_mm, s.plate_mm) / 2 + 2.0  # room for the frame's walls
    scale = drawing_scale(2 * half, z_eye)
    pen = _Pen(scale)
    wall = 1.5
    body = [_rect(-s.display_mm / 2, 0, s.display_mm, max(0.6, 2 * pen.line), pen, "display"),
            _text(pen, 0, max(0.6, 2 * pen.line) + 1.2 * pen.text,
                  "display, emitting surface (z = 0), "
                  f"{s.display_mm:g} mm active")]
    for side in (-1, 1):  # the frame: a wall and the ledge the plate lies on
        outer = side * (s.plate_mm / 2 + wall)
        x_wall = min(outer, side * s.plate_mm / 2)
        body.append(_rect(x_wall, z_top, wall, z_top, pen, "frame"))
        x_ledge = min(side * s.plate_mm / 2, side * (s.plate_mm / 2 - s.ledge_mm))
        body.append(_rect(x_ledge, z_plate, s.ledge_mm, z_plate, pen, "frame"))
    body.append(_rect(-s.plate_mm / 2, z_top, s.plate_mm, s.thickness_mm, pen, "plate-section"))
    body.append(_line(pen, -s.pupil_mm / 2, -z_eye, s.pupil_mm / 2, -z_eye, "pupil"))
    body.append(_line(pen, -s.eyebox_mm / 2, -z_eye - pen.tick, s.eyebox_mm / 2,
                      -z_eye - pen.tick, "eyebox"))
    body.append(_text(pen, 0, -z_eye - 2.2 * pen.tick - pen.text * 0.4,
                      f"eye pupil {s.pupil_mm:g} mm; eyebox {s.eyebox_mm:g} mm"))
    body.append(_text(pen, 0, -z_top - pen.text * 0.6, "plate, eye side up"))
    x = -half
    body += _dimension(pen, (x, 0), (x, -z_plate), pen.pad * 0.3, f"gap {s.gap_mm:g} mm")
    body += _dimension(pen, (x, -z_top), (x, -z_eye), pen.pad * 0.3,
                       f"eye relief {s.eye_relief_mm:g} mm")
    body.append(_text(pen, half + pen.pad * 0.1, -z_top, f"t = {s.thickness_mm:g} mm", "start"))
    x0, y0 = -half - pen.pad, -z_eye - pen.pad
    label = f"section through the device, scale {scale_label(scale)}"
    return _svg(x0, y0, 2 * half + 2 * pen.pad, z_eye + 2 * pen.pad, scale, label, body, "stack")


def placement_drawing(display_mm: tuple[float, float], pixels: tuple[int, int],
                      layout: HoleLayout, corner_cut_mm: float) -> str:
    """The display's active area seen from the eye with the image on it: pixel (row 0,
    column 0) at the top-left, the plate's outline and key over it, centres on the axis."""
    width, height = display_mm
    span_w, span_h = max(width, layout.outline_mm[0]), max(height, layout.outline_mm[1])
    scale = drawing_scale(span_w, span_h)
    pen = _Pen(scale)
    body = [_rect(-width / 2, height / 2, width, height, pen, "image")]
    pixel = (width / pixels[0], height / pixels[1])
    body.append(_rect(-width / 2, height / 2, max(pixel[0], pen.tick), max(pixel[1], pen.tick),
                      pen, "first-pixel"))
    body.append(_text(pen, -width / 2 + pen.tick, -height / 2 + 1.8 * pen.text,
                      "pixel (row 0, column 0)", "start"))
    body.append(_polygon(outline_points_mm(layout, corner_cut_mm), pen, "plate-over"))
    body.append(_line(pen, -pen.tick * 2, 0, pen.tick * 2, 0, "axis"))
    body.append(_line(pen, 0, -pen.tick * 2, 0, pen.tick * 2, "axis"))
    body.append(_text(pen, pen.tick * 2.5, -pen.tick, "image centre = plate centre", "start"))
    left, up, down = -span_w / 2, -span_h / 2, span_h / 2
    body += _dimension(pen, (-width / 2, down), (width / 2, down), -pen.pad * 0.35,
                       f"{width:g} mm = {pixels[0]} px")
    body += _dimension(pen, (width / 2, height / 2), (width / 2, -height / 2), -pen.pad * 0.35,
                       f"{height:g} mm = {pixels[1]} px")
    body.append(_text(pen, 0, up - pen.pad * 0.15, "up"))
    label = f"the display image on the panel, seen from the eye, scale {scale_label(scale)}"
    return _svg(left - pen.pad, up - pen.pad, span_w + 2 * pen.pad, span_h + 2 * pen.pad, scale,
                label, body, "placement")


def coupon_drawing(coupon: Coupon) -> str:
    """The coupon seen from above, to scale, each block labelled with its drawn diameter."""
    width, height = coupon.outline_mm
    scale = drawing_scale(width, height)
    pen = _Pen(scale)
    w2, h2 = width / 2, height / 2
    cut = coupon.corner_cut_mm
    points = [(w2, h2), (-w2 + cut, h2), (-w2, h2 - cut), (-w2, -h2), (w2, -h2)]
    body = [_polygon(points, pen, "outline")]
    holes = np.array([(x, y, r) for _, _, x, y, r in coupon.holes()])
    body.append('<g class="holes">' + "".join(
        f'<circle cx="{_f(x)}" cy="{_f(-y)}" r="{_f(r)}"/>' for x, y, r in holes.tolist())
        + "</g>")
    for b, d in enumerate(coupon.diameters_mm):
        body.append(_text(pen, coupon.block_centre_x_mm(b), h2 + 1.4 * pen.text,
                          f"{d * 1000:.0f}"))
    body.append(_text(pen, -w2, h2 + 3.0 * pen.text, "drawn hole diameter, um", "start"))
    body += _dimension(pen, (-w2, -h2), (w2, -h2), pen.pad * 0.3, f"{width:.2f} mm")
    label = f"calibration coupon, {width:.2f} x {height:.2f} mm, scale {scale_label(scale)}"
    return _svg(-w2 - pen.pad, -h2 - pen.pad, width + 2 * pen.pad, height + 2 * pen.pad, scale,
                label, body, "coupon")


def scale_bar(length_mm: float = 50.0) -> str:
    """A 1:1 bar of length_mm with 10 mm ticks: measure it on the printout."""
    pen = _Pen(1.0)
    pad = 4.0
    body = [_line(pen, 0, 0, length_mm, 0, "bar")]
    for k in range(int(length_mm // 10) + 1):
        body.append(_line(pen, 10 * k, -1.5, 10 * k, 0, "bar"))
        body.append(_text(pen, 10 * k, -2.2, f"{10 * k}"))
    body.append(_text(pen, length_mm + 2, 1, "mm (1:1)", "start"))
    return _svg(-pad, -pad - 2, length_mm + 4 * pad + 10, 2 * pad + 2, 1.0,
                f"scale bar, {length_mm:g} mm at 1:1", body, "scale-bar")
