"""The calibration coupon of docs/processes.md as a part: a small plate with a block of holes per
drawn diameter, made before the plate to measure what the process really makes.

The coupon is a hole grid like the plate's, at the design's pitch and thickness: blocks of
repeat x repeat holes, left to right from the smallest diameter, with whole empty cells between
blocks, a solid margin and the plate's alignment chamfer on its top-left corner. Because it is a
`HoleLayout`, it is built by the plate's own mesh builder (`fabrication.mesh.build_mesh`) and
written by the plate's own formats (STL, SVG, hole table): no CAD kernel is needed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from aperture_fab.fabrication.layout import HoleLayout
from aperture_fab.fabrication.mesh import build_mesh
from aperture_fab.fabrication.mesh_checks import check_mesh
from aperture_fab.fabrication.part import CORNER_CUT_SHARE, Part, chord_tolerance_mm
from aperture_fab.fabrication.process import Process
from aperture_fab.optics.scene import Plate

__all__ = ["Coupon", "calibration_coupon", "coupon_layout", "coupon_part"]

#: Holes per block side.
COUPON_REPEAT = 5
#: Solid between blocks, at least (mm): whole empty cells of the pitch, rounded up.
COUPON_BLOCK_GAP_MM = 1.0
#: Solid at the edge (mm).
COUPON_MARGIN_MM = 1.0
#: Drawn diameters of the resin coupon in printer pixels (docs/processes.md: 2 to 10 pixels).
COUPON_PIXELS = tuple(range(2, 11))
#: Without a pixel grid: drawn diameters as multiples of the process's smallest hole.
COUPON_SHARES = (0.5, 0.625, 0.75, 0.875, 1.0, 1.25, 1.5, 1.75, 2.0)
#: Slack when rounding the block gap up to whole cells (1.0 mm at a 0.25 mm pitch is 4 cells).
CELL_ROUNDING_SLACK = 1e-9


@dataclass(frozen=True)
class Coupon:
    """A calibration plate: a block of repeat x repeat holes per drawn diameter, left to right
    from the smallest, at the design's pitch and thickness; the top-left corner chamfered.

    diameters_mm: drawn hole diameters, ascending, each below pitch_mm. pitch_mm: the cell
    pitch. repeat: holes per block side. gap_cells: empty cells between blocks. margin_mm:
    solid at the edge. thickness_mm: the design's plate thickness.
    """

    diameters_mm: tuple[float, ...]
    pitch_mm: float
    repeat: int
    gap_cells: int
    margin_mm: float
    thickness_mm: float

    def __post_init__(self) -> None:
        if not self.diameters_mm or not all(0 < d < self.pitch_mm for d in self.diameters_mm):
            raise ValueError(f"Coupon.diameters_mm = {self.diameters_mm} must be non-empty and "
                             f"each between 0 and the pitch {self.pitch_mm:g} mm (a web between "
                             "holes); use calibration_coupon, which spaces them.")
        if self.repeat < 1 or self.gap_cells < 0 or self.margin_mm <= 0 or self.thickness_mm <= 0:
            raise ValueError(f"Coupon: repeat = {self.repeat} (>= 1), gap_cells = "
                             f"{self.gap_cells} (>= 0), margin_mm = {self.margin_mm:g} (> 0) and "
                             f"thickness_mm = {self.thickness_mm:g} (> 0) are out of range.")

    @property
    def block_mm(self) -> float:
        """One block's width (its cells)."""
        return self.repeat * self.pitch_mm

    @property
    def block_gap_mm(self) -> float:
        """Solid between two blocks' cells."""
        return self.gap_cells * self.pitch_mm

    @property
    def grid(self) -> tuple[int, int]:
        """(columns, rows) of the coupon's cell grid, empty cells between blocks included."""
        n = len(self.diameters_mm)
        return n * self.repeat + (n - 1) * self.gap_cells, self.repeat

    @property
    def outline_mm(self) -> tuple[float, float]:
        nx, ny = self.grid
        return nx * self.pitch_mm + 2 * self.margin_mm, ny * self.pitch_mm + 2 * self.margin_mm

    @property
    def corner_cut_mm(self) -> float:
        """The alignment chamfer's legs, the plate's share of the margin."""
        return CORNER_CUT_SHARE * self.margin_mm

    def block_centre_x_mm(self, block: int) -> float:
        """x of block `block`'s centre (outline centred on the axis)."""
        nx, _ = self.grid
        first = block * (self.repeat + self.gap_cells)
        return (first + self.repeat / 2 - nx / 2) * self.pitch_mm

    def holes(self) -> list[tuple[int, int, float, float, float]]:
        """(block, index in the block, x_mm, y_mm, radius_mm) of every hole, outline centred on
        the axis, block by block, each row by row from the top."""
        layout = coupon_layout(self)
        per_block = self.repeat * self.repeat
        return [(k // per_block, k % per_block, x, y, r) for k, ((x, y), r) in
                enumerate(zip(layout.centres_mm.tolist(), layout.radii_mm.tolist(), strict=True))]


def calibration_coupon(process: Process, plate: Plate) -> Coupon:
    """The calibration plate of docs/processes.md at the design's pitch and thickness: drawn
    diameters from 2 to 10 printer pixels for a process with a pixel grid (a radius step), the
    process's own sizes when it has discrete ones, else 0.5 to 2 times its smallest hole. Sizes
    that would not leave a web at the pitch are left out."""
    pitch = min(plate.pitch_mm)
    if process.hole_sizes_mm:
        wanted = tuple(process.hole_sizes_mm)
    elif process.radius_step_mm > 0:
        wanted = tuple(2 * process.radius_step_mm * k for k in COUPON_PIXELS)
    else:
        smallest = process.min_hole_for(plate.thickness_mm)
        wanted = tuple(round(smallest * share, 4) for share in COUPON_SHARES)
    fits = tuple(d for d in wanted if d < pitch)
    if not fits:  # the design's pitch holds none of them: space them at the process's web
        pitch = max(wanted) + process.min_web_for(plate.thickness_mm)
        fits = wanted
    gap_cells = math.ceil(COUPON_BLOCK_GAP_MM / pitch - CELL_ROUNDING_SLACK)
    return Coupon(fits, pitch, COUPON_REPEAT, gap_cells, COUPON_MARGIN_MM, plate.thickness_mm)


def coupon_layout(coupon: Coupon) -> HoleLayout:
    """The coupon's straight holes on its cell grid (HoleLayout conventions: cell (row, col)
    centred at x = (col - (nx - 1) / 2) p, y = ((ny - 1) / 2 - row) p)."""
    nx, ny = coupon.grid
    rows, cols, radii = [], [], []
    for block, diameter in enumerate(coupon.diameters_mm):
        first = block * (coupon.repeat + coupon.gap_cells)
        for i in range(coupon.repeat):
            for j in range(coupon.repeat):
                rows.append(i)
                cols.append(first + j)
                radii.append(diameter / 2)
    cells = np.column_stack([rows, cols]).astype(np.int64)
    p = coupon.pitch_mm
    centres = np.column_stack([(cells[:, 1] - (nx - 1) / 2) * p,
                               ((ny - 1) / 2 - cells[:, 0]) * p]).astype(np.float64)
    return HoleLayout(cells=cells, centres_mm=centres, radii_mm=np.asarray(radii, np.float64),
                      axes=np.zeros_like(centres), pitch_mm=(p, p), grid=(nx, ny),
                      outline_mm=coupon.outline_mm, thickness_mm=coupon.thickness_mm)


def coupon_part(coupon: Coupon, process: Process) -> Part:
    """The coupon as a checked solid (mm, watertight, one through-hole per hole), built like the
    plate: polygons as fine as the process's radius tolerance asks, the alignment chamfer."""
    layout = coupon_layout(coupon)
    mesh = build_mesh(layout, chord_tolerance_mm(process), corner_cut_mm=coupon.corner_cut_mm)
    report = check_mesh(mesh)
    if not (report.ok and report.genus == layout.count):
        raise RuntimeError(f"the built calibration coupon failed its own checks ({report}); this "
                           "is a bug, please report it with the design.")
    return Part(layout, mesh, report, coupon.corner_cut_mm)
