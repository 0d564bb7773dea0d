"""A scan of a made plate measured against its design: every design hole's made centre and
radius (or what is wrong with it), the openings that should not be there, the process's bias
and scatter on this plate, and the solid's transmission."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from aperture_fab.fabrication.layout import HoleLayout
from aperture_fab.measure.detect import detect_blobs
from aperture_fab.measure.fit import CircleFits, LightField, fit_circles, light_field
from aperture_fab.measure.register import MIN_MATCH_SHARE, Registration, register

__all__ = ["HOLE_STATES", "HoleState", "Measurement", "NoHolesError", "measure_plate"]

#: What became of a design hole: measured; blocked (no light where it should be); merged with a
#: neighbour (one opening covers both); partly blocked (dust or debris over part of it: its
#: light falls short of its fitted edge's).
HoleState = Literal["ok", "blocked", "merged", "partly_blocked"]
HOLE_STATES: tuple[HoleState, ...] = ("ok", "blocked", "merged", "partly_blocked")
#: A hole whose light-equivalent radius falls short of its edge's by more than this share (and
#: PARTLY_BLOCKED_PX) is partly blocked.
PARTLY_BLOCKED_SHARE = 0.08
PARTLY_BLOCKED_PX = 0.5
#: An opening is part of the plate only if it is no larger than this many times the largest
#: design hole's area (a larger bright region is the light around the plate).
MAX_OPENING_AREA_RATIO = 30.0
#: The solid's level is "at the noise floor" below this many noise sigmas: its transmission
#: (and optical density) is then a bound, not a measurement.
FLOOR_SIGMAS = 3.0


class NoHolesError(ValueError):
    """The scan shows no openings to measure."""


@dataclass(frozen=True)
class Measurement:
    """What a scan shows of a plate made from `design`.

    design: the design's holes (drawn). registration: the scan on the design. light: the back
    light and blur. fits: the circles of the openings (N of them, scan order).
    state: (K,) str, a HoleState per design hole. centres_mm: (K, 2) float64, measured centre
    in the design's frame (NaN for blocked). radii_mm: (K,) float64, measured radius (NaN for
    blocked; for merged holes the radius of a disk passing half the merged opening's light).
    extra_index: (E,) int64, the openings (indices into fits) that are no design hole.
    extra_centres_mm (E, 2), extra_radii_mm (E,): where they are and how large, mm.
    bias_mm, sigma_mm: mean and standard deviation of (measured - drawn radius) over the "ok"
    holes; position_sigma_mm: the per-axis sigma of their centre deviations.
    solid_transmission: the solid's light over the open light; solid_at_floor: it is at the
    scan's noise floor (the value is an upper bound, the optical density a lower one).
    mm_per_px: the nominal pixel size used for sizes.
    """

    design: HoleLayout
    registration: Registration
    light: LightField
    fits: CircleFits
    state: np.ndarray
    centres_mm: np.ndarray
    radii_mm: np.ndarray
    extra_index: np.ndarray
    extra_centres_mm: np.ndarray
    extra_radii_mm: np.ndarray
    bias_mm: float
    sigma_mm: float
    position_sigma_mm: float
    solid_transmission: float
    solid_at_floor: bool
    mm_per_px: float

    @property
    def optical_density(self) -> float:
        """-log10 of the solid's transmission (a lower bound when solid_at_floor)."""
        return -math.log10(max(self.solid_transmission, 1e-12))

    def count(self, state: HoleState) -> int:
        return int(np.sum(self.state == state))


def _openings(image: np.ndarray, design: HoleLayout, mm_per_px: float
              ) -> tuple[CircleFits, LightField, np.ndarray, np.ndarray, float]:
    """(fits, light, the blob label of each fit, the label image, the solid's noise)."""
    blobs = detect_blobs(image)
    if blobs is None:
        raise NoHolesError("no openings: the image is one level (or its bright part is only "
                           "noise)")
    largest_px = math.pi * (float(design.radii_mm.max(initial=0)) / mm_per_px) ** 2
    inside = np.flatnonzero(~blobs.touches_edge
                            & (blobs.pixels <= MAX_OPENING_AREA_RATIO * max(largest_px, 1.0)))
    if inside.size == 0:
        raise NoHolesError("no openings inside the plate: only light around it (regions that "
                           "reach the image's edge)")
    first = fit_circles(image, blobs, inside)
    light = light_field(first, image.shape)
    fits = fit_circles(image, blobs, inside, light)
    return fits, light, inside + 1, blobs.labels, blobs.noise


def measure_plate(image: np.ndarray, design: HoleLayout, mm_per_px: float,
                  min_match_share: float = MIN_MATCH_SHARE) -> Measurement:
    """Measure a grey transmission scan (H, W) float64 in [0, 1] of a plate made from
    `design` (drawn holes), at a nominal pixel size of mm_per_px. NoHolesError when the scan
    shows no openings; RegistrationError when it does not fit the design (fewer than
    min_match_share of its holes matched, among other checks: register)."""
    fits, light, fit_labels, labels, noise = _openings(image, design, mm_per_px)
    reg = register(fits.centres_px, fits.radii_px, design.centres_mm, design.radii_mm,
                   mm_per_px, min_match_share)
    k = design.count
    state = np.full(k, "blocked", dtype=object)
    centres = np.full((k, 2), np.nan)
    radii = np.full(k, np.nan)
    where = np.round(reg.transform.to_image(design.centres_mm)).astype(np.int64)
    height, width = image.shape
    inside = (where[:, 0] >= 0) & (where[:, 0] < width) & (where[:, 1] >= 0) & \
        (where[:, 1] < height)
    label_at = np.zeros(k, dtype=np.int64)
    label_at[inside] = labels[where[inside, 1], where[inside, 0]]
    # One opening over two or more design holes' centres: merged.
    owners = np.bincount(label_at[label_at > 0], minlength=labels.max() + 1)
    fit_of_label = {int(lab): i for i, lab in enumerate(fit_labels)}
    used = set()
    for s, d in zip(reg.scan_index.tolist(), reg.design_index.tolist(), strict=True):
        if owners[fit_labels[s]] >= 2:
            continue
        used.add(s)
        state[d] = "ok"
        centres[d] = reg.transform.to_design(fits.centres_px[s:s + 1])[0]
        radii[d] = fits.radii_px[s] * mm_per_px
        short = fits.radii_px[s] - fits.area_radius_px[s]
        if short > max(PARTLY_BLOCKED_SHARE * fits.radii_px[s], PARTLY_BLOCKED_PX):
            state[d] = "partly_blocked"
    for d in np.flatnonzero((label_at > 0) & (owners[label_at] >= 2)):
        i = fit_of_label.get(int(label_at[d]))
        state[d] = "merged"
        centres[d] = design.centres_mm[d]
        if i is not None:
            used.add(i)
            radii[d] = fits.area_radius_px[i] * mm_per_px / math.sqrt(owners[label_at[d]])
    extra = np.array(sorted(set(range(len(fit_labels))) - used), dtype=np.int64)
    good = state == "ok"
    dr = radii[good] - design.radii_mm[good]
    dc = centres[good] - design.centres_mm[good]
    solid = float(np.median(fits.solid_level))
    floor = solid <= FLOOR_SIGMAS * noise
    transmission = max(solid, FLOOR_SIGMAS * noise) / float(np.median(fits.open_level))
    return Measurement(
        design=design, registration=reg, light=light, fits=fits, state=state.astype(str),
        centres_mm=centres, radii_mm=radii, extra_index=extra,
        extra_centres_mm=reg.transform.to_design(fits.centres_px[extra]),
        extra_radii_mm=fits.radii_px[extra] * mm_per_px,
        bias_mm=float(dr.mean()) if dr.size else math.nan,
        sigma_mm=float(dr.std(ddof=1)) if dr.size > 1 else math.nan,
        position_sigma_mm=float(np.sqrt(np.mean(dc ** 2))) if dc.size else math.nan,
        solid_transmission=transmission, solid_at_floor=floor, mm_per_px=mm_per_px)
