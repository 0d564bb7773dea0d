"""Which display stack levels holes of a known smallest size can read: the lowest level a
renderer for them must hold (`Renderer`'s min_radius_mm; the kernels reach the levels held
through a level offset, `kernels.GEOMETRY_FIELDS`).

A pair (view direction v, hole of radius r) reads the stack at the level of its lens: the
overlap of the hole's two faces seen along v, in the kernels' shared case (every eye state
focused at infinity) two disks of radius r whose centres lie d = t |a + v| apart (t the
plate's thickness, a the hole's axis slope). The level index is (L - 1) area / (pi w^2),
w the stack's largest window radius, and it only falls as r shrinks or d grows, so the
smallest hole at the largest d bounds from below every level a hole at least that large
reads. d is bounded by t (|a| + |v|) at the plate's far corner and the view's corner.
"""

from __future__ import annotations

import math

from aperture_fab.optics.planes import EPS
from aperture_fab.optics.scene import Scene

__all__ = ["lowest_level", "lens_area_mm2"]

#: Levels kept below the bound: the kernels' lens areas use fast approximations of acos
#: (within a few ulp), and the torch path computes them in its own dtype.
MARGIN_LEVELS = 1


def lens_area_mm2(radius_mm: float, distance_mm: float) -> float:
    """The overlap area (mm^2) of two disks of radius_mm whose centres are distance_mm apart."""
    if distance_mm >= 2 * radius_mm:
        return 0.0
    half = distance_mm / (2 * radius_mm)
    return 2 * radius_mm**2 * math.acos(half) - distance_mm * radius_mm * math.sqrt(1 - half**2)


def lowest_level(scene: Scene, levels: int, window_max_mm: float, min_radius_mm: float) -> int:
    """The lowest level (0 to levels - 2) of a stack of `levels` up to window_max_mm that a
    hole of radius at least min_radius_mm (mm, > 0) reads for an eye focused at infinity,
    less MARGIN_LEVELS: every level below it is read only by smaller holes (or by closed
    ones, whose light is 0)."""
    if not (math.isfinite(min_radius_mm) and min_radius_mm > 0):
        raise ValueError(f"min_radius_mm = {min_radius_mm!r}; allowed: above 0 (mm), or None "
                         "for a renderer of holes of any size.")
    plate, eye = scene.plate, scene.eye
    slope = 0.0
    if plate.hole_axis == "chief_ray":
        ex, ey = eye.positions_mm[0]
        corner = math.hypot(abs(ex) + plate.size_mm[0] / 2, abs(ey) + plate.size_mm[1] / 2)
        slope = corner / scene.mid_plane_distance_mm
    distance = plate.thickness_mm * (slope + math.hypot(*eye.view_tan_half))
    area = lens_area_mm2(min_radius_mm, distance)
    index = (levels - 1) * area / (math.pi * max(window_max_mm**2, EPS))
    return max(0, min(math.floor(index) - MARGIN_LEVELS, levels - 2))
