"""The calibration coupon measured (issue 17, item 4): from a measurement of the coupon's scan,
what the process really makes, as the [process] values `design` takes.

The coupon (aperture_fab.fabrication.coupon) holds a block of holes per drawn diameter. Per
docs/processes.md ("Calibration print"): the smallest drawn size whose holes all came through
(and every larger one's) is the smallest hole the process makes, `min_hole_mm`, a drawn
diameter, as the process's rules bound drawn holes; over those blocks, the mean of made minus
drawn radius is `radius_bias_mm`, the spread of radii within a block (pooled over the blocks)
`radius_sigma_mm`, and the centres' scatter about the registered grid `position_sigma_mm`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from aperture_fab.fabrication.coupon import Coupon
from aperture_fab.fabrication.process import MAX_OPTICAL_DENSITY
from aperture_fab.measure.measure import Measurement

__all__ = ["COUPON_MIN_MATCH_SHARE", "CouponBlock", "CouponCalibration", "calibrate_coupon",
           "process_overrides"]

#: Share of the coupon's holes the registration must match: its smallest blocks may all stay
#: closed (that is what the coupon measures), so less than a plate's MIN_MATCH_SHARE.
COUPON_MIN_MATCH_SHARE = 0.3
#: Decimals (mm) of the values written into the [process] table: 10 nm, far below what a scan
#: measures, so the file shows the measurement and not its rounding.
PROCESS_DECIMALS = 5


class CouponError(ValueError):
    """The coupon's scan does not give the process's values (no block came through whole)."""


@dataclass(frozen=True)
class CouponBlock:
    """One block of the coupon as made.

    drawn_diameter_mm: the block's drawn diameter. holes: its holes. opened: those that came
    through (measured, merged or partly blocked: light passes). measured: those measured
    ("ok"). radius_mean_mm, radius_sigma_mm: mean and standard deviation of their made radii
    (NaN without any, sigma NaN with one).
    """

    drawn_diameter_mm: float
    holes: int
    opened: int
    measured: int
    radius_mean_mm: float
    radius_sigma_mm: float

    @property
    def complete(self) -> bool:
        return self.opened == self.holes


@dataclass(frozen=True)
class CouponCalibration:
    """What the coupon says of the process.

    blocks: every block, smallest drawn diameter first. min_hole_mm: the smallest drawn
    diameter from which every block came through whole. radius_bias_mm: mean made - drawn
    radius over those blocks' measured holes. radius_sigma_mm: pooled within-block standard
    deviation of their radii. position_sigma_mm: per-axis RMS of their centres' deviation from
    the registered grid. holes_used: how many holes those figures rest on. optical_density: the
    solid's, or None when the scan could not resolve it (at its noise floor).
    """

    blocks: tuple[CouponBlock, ...]
    min_hole_mm: float
    radius_bias_mm: float
    radius_sigma_mm: float
    position_sigma_mm: float
    holes_used: int
    optical_density: float | None

    def as_json(self) -> dict[str, Any]:
        def num(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None

        return {"min_hole_mm": self.min_hole_mm, "radius_bias_mm": self.radius_bias_mm,
                "radius_sigma_mm": num(self.radius_sigma_mm),
                "position_sigma_mm": num(self.position_sigma_mm),
                "holes_used": self.holes_used, "optical_density": self.optical_density,
                "blocks": [{"drawn_diameter_mm": b.drawn_diameter_mm, "holes": b.holes,
                            "opened": b.opened, "measured": b.measured,
                            "radius_mean_mm": num(b.radius_mean_mm),
                            "radius_sigma_mm": num(b.radius_sigma_mm)} for b in self.blocks]}


def calibrate_coupon(m: Measurement, coupon: Coupon) -> CouponCalibration:
    """The process's values from a measurement `m` of `coupon` (its design is
    coupon_layout(coupon), holes block by block). CouponError when no block came through
    whole, or the whole blocks hold fewer than two measured holes."""
    per_block = coupon.repeat * coupon.repeat
    block_of = np.arange(m.design.count) // per_block
    opened_state = m.state != "blocked"
    ok = m.state == "ok"
    blocks = []
    for b, diameter in enumerate(coupon.diameters_mm):
        mine = block_of == b
        radii = m.radii_mm[mine & ok]
        blocks.append(CouponBlock(
            float(diameter), int(mine.sum()), int((mine & opened_state).sum()), int(radii.size),
            float(radii.mean()) if radii.size else math.nan,
            float(radii.std(ddof=1)) if radii.size > 1 else math.nan))
    first = len(blocks)
    while first > 0 and blocks[first - 1].complete:
        first -= 1
    if first == len(blocks):
        raise CouponError(
            f"no block of the coupon came through whole (the largest, {blocks[-1].opened} of "
            f"{blocks[-1].holes} holes of {blocks[-1].drawn_diameter_mm * 1000:.1f} um drawn, "
            "opened): the process does not make the coupon's holes, or the scan does not "
            "resolve them. Scan at a finer resolution (--scale-mm-per-px from a microscope), or "
            "make the coupon again.")
    used = (block_of >= first) & ok
    drawn_r = m.design.radii_mm[used]
    dr = m.radii_mm[used] - drawn_r
    if dr.size < 2:
        raise CouponError(f"only {dr.size} hole(s) of the coupon's whole blocks were measured; "
                          "at least 2 are needed for a spread. Scan the coupon again (clean, "
                          "flat on the glass).")
    residual = m.radii_mm[used] - np.array([blocks[b].radius_mean_mm for b in block_of[used]])
    dof = dr.size - (len(blocks) - first)
    sigma = float(np.sqrt(np.sum(residual ** 2) / dof)) if dof > 0 else math.nan
    dc = m.centres_mm[used] - m.design.centres_mm[used]
    return CouponCalibration(
        tuple(blocks), blocks[first].drawn_diameter_mm, float(dr.mean()), sigma,
        float(np.sqrt(np.mean(dc ** 2))), int(dr.size),
        None if m.solid_at_floor else float(m.optical_density))


def process_overrides(cal: CouponCalibration) -> dict[str, float]:
    """The [process] values the coupon measured, rounded to PROCESS_DECIMALS (a spread that
    could not be estimated is left out: the process keeps its own). min_hole_per_thickness is
    0: the coupon was made at the design's thickness, so its smallest hole is the one there."""
    values = {"min_hole_mm": cal.min_hole_mm, "min_hole_per_thickness": 0.0,
              "radius_bias_mm": cal.radius_bias_mm, "radius_sigma_mm": cal.radius_sigma_mm,
              "position_sigma_mm": cal.position_sigma_mm}
    if cal.optical_density is not None and 0 < cal.optical_density <= MAX_OPTICAL_DENSITY:
        values["optical_density"] = cal.optical_density
    return {k: round(v, PROCESS_DECIMALS) for k, v in values.items() if math.isfinite(v)}
