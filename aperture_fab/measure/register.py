"""Registration: which design hole each found opening is, and the transform (rotation, mirror,
scale, translation) that puts the scan on the design.

The search: the hole grid's direction (mod 90 degrees) from the openings' nearest-neighbour
vectors; for each of its four turns, mirrored or not, the translation most pairs of (opening,
design hole) vote for; each candidate scored by how many openings land on a design hole with a
radius that agrees (after the plate's common bias). The design's hole sizes differ from cell to
cell, so the wrong turn or side scores low. A least-squares similarity through the matched
centres, with outliers dropped, gives the transform and its residual. A registration that does
not fit well is refused (`RegistrationError`), never reported as good.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from aperture_fab.measure.transform import ScanTransform

__all__ = ["Registration", "RegistrationError", "register"]

#: Openings and design holes that vote for the translation, at most (a spread subset).
MAX_VOTERS = 400
#: Translation vote bin, as a share of the design's hole spacing.
VOTE_BIN_SHARE = 0.25
#: Translation peaks tried per candidate turn.
PEAKS_TRIED = 6
#: A vote bin (i, j) is coded i * BIN_CODE + j (far more bins than any plate spans), and its
#: eight neighbours and itself differ from it by NEIGHBOUR_SHIFTS.
BIN_CODE = 1 << 24
NEIGHBOUR_SHIFTS = np.array([di * BIN_CODE + dj for di in (-1, 0, 1) for dj in (-1, 0, 1)])
#: An opening matches a design hole within this share of the hole spacing.
MATCH_SHARE = 0.33
#: Radius agreement of a match: within this share of the median design radius (or MIN_TOL_PX).
RADIUS_TOL_SHARE = 0.15
MIN_TOL_PX = 1.5
#: A candidate scoring at least this share of the best one is a tie the radii cannot break.
TIE_SHARE = 0.9
#: Refinement rounds (refit, re-match, drop outliers beyond OUTLIER_SIGMAS robust sigmas).
REFINE_ROUNDS = 4
OUTLIER_SIGMAS = 5.0
#: What a good registration must show: a share of the design's holes matched, a centre residual
#: (RMS) within a share of the hole spacing, radii that agree after their bias, and a scale
#: within MAX_SCALE_ERROR of the one given.
MIN_MATCH_SHARE = 0.6
MAX_RESIDUAL_SHARE = 0.1
MAX_RADIUS_MISMATCH_SHARE = 0.25
MAX_SCALE_ERROR = 0.05
MAD_SIGMA = 1.4826


class RegistrationError(ValueError):
    """The scan does not fit the design well enough to be measured against it."""


@dataclass(frozen=True)
class Registration:
    """The scan on the design.

    transform: design mm -> image px. scan_index, design_index: (M,) int64 matched pairs (an
    opening, the design hole it is). residual_mm: RMS distance of matched centres after the fit.
    scale_ratio: fitted px/mm over the nominal one (the scanner's scale error and the plate's
    shrinkage together). radius_mismatch_mm: RMS of the radius differences after their median.
    tied: the radii could not tell this turn or side from another (a symmetric design).
    """

    transform: ScanTransform
    scan_index: np.ndarray
    design_index: np.ndarray
    residual_mm: float
    scale_ratio: float
    radius_mismatch_mm: float
    tied: bool


def _grid_angle(points: np.ndarray) -> float:
    """The direction (rad, mod pi/2) of the points' nearest-neighbour vectors."""
    if len(points) < 2:
        return 0.0
    _, nearest = cKDTree(points).query(points, k=2)
    d = points[nearest[:, 1]] - points
    return float(np.angle(np.sum(np.exp(4j * np.arctan2(d[:, 1], d[:, 0]))))) / 4


def _rotation(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]])


def _similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, float, np.ndarray]:
    """Least-squares dst ~ k R(angle) src + t (Umeyama, no reflection): (k, angle, t)."""
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - ms, dst - md
    u, sv, vt = np.linalg.svd(b.T @ a / len(src))
    d = np.diag([1.0, float(np.sign(np.linalg.det(u @ vt)) or 1.0)])
    r = u @ d @ vt
    k = float(np.trace(np.diag(sv) @ d)) / max(float(np.mean(np.sum(a * a, axis=1))), 1e-300)
    return k, math.atan2(r[1, 0], r[0, 0]), md - k * r @ ms


def _spread(n: int) -> np.ndarray:
    return np.unique(np.linspace(0, n - 1, min(n, MAX_VOTERS)).round().astype(np.int64))


def _score(mapped: np.ndarray, scan_r: np.ndarray, design: cKDTree, design_r: np.ndarray,
           reach: float, tol: float) -> tuple[float, np.ndarray, np.ndarray]:
    """(score, scan indices, design indices) of the openings within reach of a design hole."""
    dist, nearest = design.query(mapped, distance_upper_bound=reach)
    hit = np.isfinite(dist)
    si, di = np.flatnonzero(hit), nearest[hit]
    if si.size == 0:
        return 0.0, si, di
    dr = scan_r[si] - design_r[di]
    weight = np.exp(-0.5 * ((dr - np.median(dr)) / tol) ** 2)
    return float(weight.sum()), si, di


def _candidates(scan_mm: np.ndarray, scan_r: np.ndarray, design_mm: np.ndarray,
                design_r: np.ndarray, spacing: float, tol: float
                ) -> list[tuple[float, bool, float, np.ndarray]]:
    """(score, mirror, angle, translation) of every turn and side, best first."""
    tree = cKDTree(design_mm)
    scan_angle = _grid_angle(scan_mm)
    voters_s, voters_d = _spread(len(scan_mm)), _spread(len(design_mm))
    found = []
    for mirror in (False, True):
        flipped = design_mm * ([-1.0, 1.0] if mirror else [1.0, 1.0])
        base = scan_angle - _grid_angle(flipped)
        for turn in range(4):
            angle = base + turn * math.pi / 2
            placed = flipped @ _rotation(angle).T
            votes = (scan_mm[voters_s, None, :] - placed[None, voters_d, :]).reshape(-1, 2)
            bins = np.floor(votes / (VOTE_BIN_SHARE * spacing)).astype(np.int64)
            codes = bins[:, 0] * BIN_CODE + bins[:, 1]
            keys, counts = np.unique(codes, return_counts=True)
            # Each bin's votes with its eight neighbours': a cluster that straddles bin edges
            # is counted whole (the next cluster is a whole hole spacing, four bins, away).
            near = np.zeros(len(keys), dtype=np.int64)
            for shift in NEIGHBOUR_SHIFTS:
                at = np.clip(np.searchsorted(keys, keys + shift), 0, len(keys) - 1)
                near += np.where(keys[at] == keys + shift, counts[at], 0)
            best_score, best_t = -1.0, np.zeros(2)
            for peak in np.argsort(near)[::-1][:PEAKS_TRIED]:
                close = np.isin(codes, keys[peak] + NEIGHBOUR_SHIFTS)
                t = np.median(votes[close], axis=0)
                # Score in the design's frame: openings mapped back onto the design holes.
                back = ((scan_mm - t) @ _rotation(angle)) * ([-1.0, 1.0] if mirror else 1.0)
                score, _, _ = _score(back, scan_r, tree, design_r, MATCH_SHARE * spacing, tol)
                if score > best_score:
                    best_score, best_t = score, t
            found.append((best_score, mirror, angle, best_t))
    return sorted(found, key=lambda c: -c[0])


def register(centres_px: np.ndarray, radii_px: np.ndarray, design_mm: np.ndarray,
             design_radii_mm: np.ndarray, mm_per_px: float,
             min_match_share: float = MIN_MATCH_SHARE) -> Registration:
    """Register openings (centres (N, 2) px, radii (N,) px) to design holes (centres (K, 2)
    mm, radii (K,) mm) at a nominal pixel size of mm_per_px (module docstring); at least
    min_match_share of the design's holes must be matched (a calibration coupon, whose
    smallest holes may all stay closed, asks for fewer than a plate)."""
    k = len(design_mm)
    if len(centres_px) < 3 or k < 3:
        raise RegistrationError(f"{len(centres_px)} opening(s) found for {k} design holes; "
                                "at least 3 of each are needed to place the scan on the design.")
    scan_mm = np.column_stack([centres_px[:, 0], -centres_px[:, 1]]) * mm_per_px
    scan_r = radii_px * mm_per_px
    spacing = float(np.median(cKDTree(design_mm).query(design_mm, k=2)[0][:, 1]))
    tol = max(RADIUS_TOL_SHARE * float(np.median(design_radii_mm)), MIN_TOL_PX * mm_per_px)
    ranked = _candidates(scan_mm, scan_r, design_mm, design_radii_mm, spacing, tol)
    score, mirror, angle, t = ranked[0]
    tied = ranked[1][0] >= TIE_SHARE * score
    sign = np.array([-1.0, 1.0]) if mirror else np.array([1.0, 1.0])
    scale, tree = 1.0, cKDTree(design_mm)
    keep_s = keep_d = np.zeros(0, dtype=np.int64)
    for _ in range(REFINE_ROUNDS):
        back = ((scan_mm - t) @ _rotation(angle)) / scale * sign
        _, si, di = _score(back, scan_r, tree, design_radii_mm, MATCH_SHARE * spacing, tol)
        if si.size < 3:
            break
        miss = np.hypot(*(back[si] - design_mm[di]).T)
        spread = MAD_SIGMA * float(np.median(miss)) + 1e-12
        ok = miss <= max(OUTLIER_SIGMAS * spread, 2 * mm_per_px)
        keep_s, keep_d = si[ok], di[ok]
        scale, angle, t = _similarity(design_mm[keep_d] * sign, scan_mm[keep_s])
    return _checked(keep_s, keep_d, scale, angle, t, mirror, tied, scan_mm, scan_r, design_mm,
                    design_radii_mm, mm_per_px, spacing, min_match_share)


def _checked(si: np.ndarray, di: np.ndarray, scale: float, angle: float, t: np.ndarray,
             mirror: bool, tied: bool, scan_mm: np.ndarray, scan_r: np.ndarray,
             design_mm: np.ndarray, design_r: np.ndarray, mm_per_px: float, spacing: float,
             min_match_share: float) -> Registration:
    """The registration, or RegistrationError saying which check it fails."""
    k = len(design_mm)
    if si.size < max(3, min_match_share * k):
        raise RegistrationError(
            f"only {si.size} of the design's {k} holes have an opening where the scan, best "
            f"placed, puts them (at least {math.ceil(min_match_share * k)} needed): this scan "
            "is not of this design's plate, or its scale is wrong. Check --design (the folder "
            "the plate was made from) and --dpi / --scale-mm-per-px.")
    sign = np.array([-1.0, 1.0]) if mirror else np.array([1.0, 1.0])
    back = ((scan_mm[si] - t) @ _rotation(angle)) / scale * sign
    residual = float(np.sqrt(np.mean(np.sum((back - design_mm[di]) ** 2, axis=1))))
    dr = scan_r[si] / scale - design_r[di]
    mismatch = float(np.sqrt(np.mean((dr - np.median(dr)) ** 2)))
    limit_r = max(MAX_RADIUS_MISMATCH_SHARE * float(np.median(design_r)), 2 * mm_per_px)
    problems = []
    if residual > max(MAX_RESIDUAL_SHARE * spacing, 3 * mm_per_px):
        problems.append(f"the matched centres miss the design's by {residual * 1000:.1f} um RMS "
                        f"(at most {MAX_RESIDUAL_SHARE * spacing * 1000:.1f} um, a tenth of the "
                        "hole spacing)")
    if mismatch > limit_r:
        problems.append(f"the hole radii differ from the design's by {mismatch * 1000:.1f} um "
                        f"RMS after their common bias (at most {limit_r * 1000:.1f} um)")
    if abs(scale - 1) > MAX_SCALE_ERROR:
        problems.append(f"the scan's scale is {scale:.3f} times the one given (at most "
                        f"{MAX_SCALE_ERROR:.0%} off)")
    if problems:
        raise RegistrationError(
            "the scan does not fit the design: " + "; ".join(problems) + ". This is another "
            "plate than the design's, or the scale is wrong. Check --design (the folder the "
            "plate was made from) and --dpi / --scale-mm-per-px.")
    transform = ScanTransform(mirror, angle, scale / mm_per_px, (t[0] / mm_per_px,
                                                                 -t[1] / mm_per_px))
    return Registration(transform, si, di, residual, scale, mismatch, tied)
