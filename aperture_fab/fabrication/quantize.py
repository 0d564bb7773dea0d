"""Quantization: optimized open-area fractions to holes a fabrication process can make.

Each cell's wanted open area A = a px py (mm^2) becomes a hole of the same area, snapped in area
to the nearest size the process allows: 0 (closed) or a radius in [r_min, r_max] (continuous,
on a radius step, or one of a list of diameters). Snapping errors, including cells that ask
for less than the smallest hole, are not dropped: they are diffused to neighbouring cells
(Floyd–Steinberg on open area, serpentine scan, weights renormalized at the plate's border), so
the local open area is preserved. Diffusion alone loses only the error carried out of the last
cell, but near the border a cell can receive more than one cell's worth of error, so that error
is not bounded by one step; a balance pass then steps single cells (those whose own error points
the same way) by one allowed size until

    |made area - wanted area| <= E,  E = half the largest gap between neighbouring sizes
                                        in {0} U allowed areas (A_min / 2 for continuous radii),

where the wanted area is first clipped to the largest allowed hole in each cell (what the design
asked beyond that cannot be made; it is recorded as a violation, not diffused).

Hole axes. "straight" holes run along z. "chief_ray" holes point from their cell centre at the
plate's mid-thickness to the eye: axis = (E_xy - c_xy) / D, where E_xy is the lateral eye
position (tilt_target_mm) and D = eye_distance_mm the distance from the plate's mid-thickness
to the pupil (eye relief + thickness / 2); the layout records converge_mm = (E_xy, D). A tilted
hole is a circle of radius r swept along its axis (circular in every plane z = const). All axes
meet at the eye, so at height z the hole centres are the mid-plane grid scaled about E_xy by
1 - z / D: each hole stays centred in its cell of that scaled grid (HoleLayout.cell_edges_mm).
Every hole keeps half a web inside its cell at both faces, so

    r <= min(px, py) s / 2 - web / 2,   s = 1 - t / (2 D) (the top face, the smaller grid),

which keeps the web between any two holes, diagonals included. The outermost holes keep the
web to the outline at both faces: the margin must cover how far the bottom face's grid (scaled
by 1 + t / 2D) reaches past the mid-plane grid, plus half a web.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import numpy as np

from aperture_fab.fabrication.layout import HoleLayout, Violation
from aperture_fab.fabrication.process import PROCESSES, Process, UnmakeableError
from aperture_fab.fabrication.rules import (
    MAX_CELL_VIOLATIONS,
    check_plate,
    hole_radius_bounds,
    makeable_processes,
    radius_range,
    resolve_margin_mm,
)
from aperture_fab.optics.scene import Plate, open_fraction_of

__all__ = ["MadeSizes", "made_sizes", "quantize"]

#: A design losing more than this share of its open area is refused (unless forced).
MAX_LOST_FRACTION = 0.5
#: The eye (where chief-ray axes meet) must be this many plate thicknesses from mid-thickness.
MIN_EYE_DISTANCE_THICKNESSES = 1.0
#: Geometric slack for rounding (mm); far below any process tolerance.
EPS_MM = 1e-9
#: Floyd–Steinberg weights: (row offset, column offset along the scan direction, weight).
FS_WEIGHTS = ((0, 1, 7 / 16), (1, -1, 3 / 16), (1, 0, 5 / 16), (1, 1, 1 / 16))


@dataclass(frozen=True)
class _Sizes:
    """The radii allowed in every cell: continuous [lo, hi] when radii is None, else the list."""

    lo_mm: float
    hi_mm: float
    radii_mm: tuple[float, ...] | None


def _allowed_sizes(process: Process, r_lo: float, r_hi: float) -> _Sizes:
    if process.hole_sizes_mm:
        radii = tuple(d / 2 for d in process.hole_sizes_mm if r_lo - EPS_MM <= d / 2 <= r_hi)
        return _Sizes(r_lo, r_hi, radii)
    step = process.radius_step_mm
    if step > 0:
        k_lo = math.ceil(r_lo / step - 1e-9)
        k_hi = math.floor(r_hi / step + 1e-9)
        radii = tuple(k * step for k in range(k_lo, k_hi + 1) if k * step <= r_hi + EPS_MM)
        return _Sizes(r_lo, r_hi, radii)
    return _Sizes(r_lo, r_hi, None)


def _largest_size(sizes: _Sizes, r_max: float, r_lo: float) -> float:
    """The largest allowed radius <= r_max (mm), 0 when none is."""
    if sizes.radii_mm is None:
        return r_max if r_max >= r_lo - EPS_MM else 0.0
    k = bisect.bisect_right(sizes.radii_mm, r_max + EPS_MM)
    return sizes.radii_mm[k - 1] if k else 0.0


def _check_fractions(open_fraction: np.ndarray, plate: Plate) -> np.ndarray:
    a = np.asarray(open_fraction, dtype=np.float64)
    want = (plate.cells[1], plate.cells[0])
    if a.shape != want:
        raise ValueError(
            f"open_fraction has shape {a.shape}; expected (ny, nx) = {want} for plate.cells "
            f"{plate.cells}."
        )
    if not np.all(np.isfinite(a)):
        raise ValueError("open_fraction holds NaN or infinite values; give fractions in [0, 1].")
    if a.min() < -1e-6 or a.max() > 1 + 1e-6:
        raise ValueError(
            f"open_fraction spans {a.min():.3g} to {a.max():.3g}; allowed: 0 to 1 "
            "(a = pi r^2 / (px py))."
        )
    return np.clip(a, 0.0, 1.0)


def _cell_violations(rule: str, cells: list[tuple[int, int, float, float]], what: str,
                     resolution: str) -> list[Violation]:
    """One Violation per (row, col, value, limit), or one aggregate when there are many."""
    if len(cells) <= MAX_CELL_VIOLATIONS:
        return [Violation(rule, (i, j), v, lim, resolution) for i, j, v, lim in cells]
    values = [c[2] for c in cells]
    limits = [c[3] for c in cells]
    return [Violation(rule, None, max(values), min(limits),
                      f"{len(cells)} cells {what}: {resolution}")]


def _clip_loss(a: np.ndarray, process: Process, plate: Plate, scale: float) -> float:
    """Share of the open area lost to the largest-hole limit with the pitch scaled by `scale`.

    Straight holes only (an estimate for tilted ones); 1.0 when no hole fits.
    """
    total = float(a.sum())
    if total <= 0:
        return 0.0
    px, py = plate.pitch_mm[0] * scale, plate.pitch_mm[1] * scale
    r_lo, r_hi = hole_radius_bounds(process, plate, scale)
    if r_hi < r_lo:
        return 1.0
    a_hi = float(open_fraction_of(r_hi, (px, py)))
    return float(np.maximum(a - a_hi, 0.0).sum()) / total


def _scale_to_make(a: np.ndarray, process: Process, plate: Plate) -> float | None:
    """Smallest pitch scale (>= 1) at which the clip loss is at most MAX_LOST_FRACTION."""
    hi = 1e4
    if _clip_loss(a, process, plate, hi) > MAX_LOST_FRACTION:
        return None
    lo = 1.0
    for _ in range(60):
        mid = math.sqrt(lo * hi)
        lo, hi = (lo, mid) if _clip_loss(a, process, plate, mid) <= MAX_LOST_FRACTION else (mid, hi)
    return hi


def _lost_area_error(a: np.ndarray, process: Process, plate: Plate, lost: float,
                     smallest_mm: float) -> str:
    """Why the design loses `lost` of its open area, and what to change. The loss comes from
    holes larger than the web allows or, when those alone lose too little, from holes below
    the smallest the process makes (smallest_mm, a radius) that error diffusion could not
    gather into whole holes."""
    if _clip_loss(a, process, plate, 1.0) <= MAX_LOST_FRACTION:
        d = 2 * smallest_mm
        return (
            f"{process.name} would lose {lost:.0%} of the design's open area (more than "
            f"{MAX_LOST_FRACTION:.0%}): it asks for holes smaller than the smallest "
            f"{process.name} makes ({d:.3g} mm), and too few of them to gather into holes that "
            f"size. Give a design with more open area (a larger optimizer.min_efficiency), or a "
            "process with a smaller minimum hole (aperture-fab processes). Pass force=True to "
            "get the layout anyway."
        )
    others = [
        n for n in makeable_processes(plate, exclude=process.name)
        if _clip_loss(a, PROCESSES[n], plate, 1.0) <= MAX_LOST_FRACTION
    ]
    scale = _scale_to_make(a, process, plate)
    fix = (f"scaling the plate's pitch by {scale:.3g}x (pitch "
           f"{min(plate.pitch_mm) * scale:.3g} mm) would make it makeable with {process.name}"
           if scale is not None else f"no pitch scale makes it makeable with {process.name}")
    return (
        f"{process.name} would lose {lost:.0%} of the design's open area (more than "
        f"{MAX_LOST_FRACTION:.0%}): holes larger than the web allows "
        f"({process.min_web_for(plate.thickness_mm):.3g} mm web) are cut down. {fix}; "
        f"processes that could make it: {', '.join(others) if others else 'none of the presets'}."
        " Pass force=True to get the layout anyway."
    )


@dataclass(frozen=True)
class MadeSizes:
    """The open-area fractions a process makes in a cell of a plate: what a design can ask for.

    levels: (K,) float64, sorted, starting at 0 (closed): the made open fractions
        pi (r + bias)^2 / (px py) of every allowed drawn radius r (process step or list), or
        None when the process draws any radius in a range.
    lo, hi: smallest and largest made open fraction (continuous processes; also the ends of
        `levels`, 0 excluded).
    """

    levels: np.ndarray | None
    lo: float
    hi: float

    def snap(self, a: np.ndarray) -> np.ndarray:
        """The nearest makeable fraction (in area) of each of `a`."""
        a = np.asarray(a, dtype=np.float64)
        if self.levels is None:
            return np.where(a < self.lo / 2, 0.0, np.clip(a, self.lo, self.hi))
        index = np.clip(np.searchsorted(self.levels, a), 1, len(self.levels) - 1)
        below, above = self.levels[index - 1], self.levels[index]
        return np.where(a - below <= above - a, below, above)


def made_sizes(plate: Plate, process: Process, eye_distance_mm: float | None = None
               ) -> MadeSizes:
    """The open fractions `quantize` can produce, as made (the process's radius bias applied).

    eye_distance_mm: plate mid-thickness to the pupil (chief-ray holes lose room at the top
    face, as in `quantize`). Raises UnmakeableError when the process cannot make the plate.
    """
    check_plate(process, plate)  # says why no hole fits
    rng = radius_range(process, plate)
    r_lo = rng.lo_mm
    top_scale = 1.0
    if plate.hole_axis == "chief_ray" and eye_distance_mm is not None:
        top_scale = 1.0 - plate.thickness_mm / (2 * eye_distance_mm)
    sizes = _allowed_sizes(process, r_lo, rng.hi_mm)
    top = _largest_size(sizes, rng.cell_max_mm(plate, top_scale), r_lo)
    cell = plate.pitch_mm[0] * plate.pitch_mm[1]

    def made(r: np.ndarray) -> np.ndarray:
        return math.pi * np.clip(r + process.radius_bias_mm, 0, None) ** 2 / cell

    if sizes.radii_mm is None:
        if top <= 0:  # check_plate passed at mid-plane: the tilted top face has less room
            need = (2 * r_lo + rng.web_mm) / top_scale
            raise UnmakeableError(
                f"process {process.name!r}: no hole of {2 * r_lo:.3g} mm or more fits a "
                f"{min(plate.pitch_mm):g} mm cell at the plate's top face (chief-ray holes: the "
                f"grid there is {top_scale:.4g} x the mid-plane's) with its {rng.web_mm:.3g} mm "
                f"web; give plate.pitch_mm above {need:.4g} mm, or hole_axis = \"straight\".")
        lo, hi = made(np.array([r_lo, top]))
        return MadeSizes(None, float(lo), float(hi))
    radii = np.array([r for r in sizes.radii_mm if r <= top + EPS_MM])
    if radii.size == 0:
        raise UnmakeableError(f"process {process.name!r}: no allowed hole size fits a "
                              f"{min(plate.pitch_mm):g} mm cell.")
    levels = np.concatenate([[0.0], made(radii)])
    return MadeSizes(levels, float(levels[1]), float(levels[-1]))


def quantize(
    open_fraction: np.ndarray,
    plate: Plate,
    process: Process,
    outline_margin_mm: float | None = None,
    tilt_target_mm: tuple[float, float] = (0.0, 0.0),
    eye_distance_mm: float | None = None,
    force: bool = False,
) -> HoleLayout:
    """Holes that `process` can make, preserving the local open area of `open_fraction`.

    open_fraction: (ny, nx) float, open-area fraction per cell (row 0 at +y), in [0, 1].
    outline_margin_mm: solid margin around the (mid-plane) cell grid on each side; default
        max(1 mm, 2 x min web + overhang), overhang being how far a face's scaled grid reaches
        past the mid-plane grid (0 for straight holes).
    tilt_target_mm: (x, y) lateral eye position that chief-ray holes point at.
    eye_distance_mm: plate mid-thickness to the pupil, > thickness; required for hole_axis
        "chief_ray".
    force: return the layout even when the process cannot make the design, with violations.

    Raises UnmakeableError (a ValueError) when the design cannot be made at all with this
    process (thickness out of range, no hole fits the pitch, or more than half the open area
    would be lost), naming the numbers, other processes and the scale that would work.
    """
    a = _check_fractions(open_fraction, plate)
    t = plate.thickness_mm
    px, py = plate.pitch_mm
    ny, nx = a.shape
    violations: list[Violation] = []

    try:
        check_plate(process, plate)
    except UnmakeableError as err:
        if not force:
            raise
        violations.append(Violation("process", None, t, 0.0, f"forced despite: {err}"))

    rng = radius_range(process, plate)
    r_lo, r_hi, min_web = rng.lo_mm, rng.hi_mm, rng.web_mm
    sizes = _allowed_sizes(process, r_lo, r_hi)

    # Hole axes, and the largest radius each cell allows at both faces.
    xs, ys = plate.cell_centres_mm()
    cx, cy = np.meshgrid(xs, ys)
    converge: tuple[float, float, float] | None = None
    overhang = 0.0
    top_scale = 1.0
    if plate.hole_axis == "chief_ray":
        if eye_distance_mm is None or not (
            math.isfinite(eye_distance_mm) and eye_distance_mm > MIN_EYE_DISTANCE_THICKNESSES * t
        ):
            raise ValueError(
                f"eye_distance_mm = {eye_distance_mm!r}: chief_ray holes need the distance from "
                "the plate's mid-thickness to the pupil (eye relief + thickness / 2), > the "
                f"thickness {t:g} mm."
            )
        ex, ey = float(tilt_target_mm[0]), float(tilt_target_mm[1])
        converge = (ex, ey, float(eye_distance_mm))
        ax = (ex - cx) / eye_distance_mm
        ay = (ey - cy) / eye_distance_mm
        # Each face's grid is the mid-plane grid scaled about E by 1 -+ t / 2D.
        half_scale = t / (2 * eye_distance_mm)
        top_scale = 1.0 - half_scale
        half_w, half_h = nx * px / 2, ny * py / 2
        overhang = half_scale * max(half_w + abs(ex), half_h + abs(ey))
    else:
        ax = np.zeros_like(cx)
        ay = np.zeros_like(cy)
    r_cell = rng.cell_max_mm(plate, top_scale)
    margin = resolve_margin_mm(min_web, overhang, outline_margin_mm)

    # Clip what the design asks to what each cell can hold; record the rule breaks.
    cell_area = px * py
    wanted = a * cell_area
    want_r = np.sqrt(wanted / math.pi)
    clipped_web: list[tuple[int, int, float, float]] = []
    clipped_tilt: list[tuple[int, int, float, float]] = []
    clipped_size: list[tuple[int, int, float, float]] = []
    # The largest allowed hole in every cell, and what it would be without the tilt rule.
    top = _largest_size(sizes, r_cell, r_lo)
    top_straight = _largest_size(sizes, r_hi, r_lo)
    cap_area = np.full_like(wanted, math.pi * top**2)
    for i, j in zip(*np.nonzero(want_r > top + EPS_MM), strict=True):
        wr = float(want_r[i, j])
        if wr > r_hi + EPS_MM:
            clipped_web.append((int(i), int(j), wr, r_hi))
        elif top < top_straight - EPS_MM:
            clipped_tilt.append((int(i), int(j), wr, top))
        else:
            clipped_size.append((int(i), int(j), wr, top))
    violations += _cell_violations(
        "min_web", clipped_web, f"wanted holes larger than r = {r_hi:.4g} mm",
        f"radius cut to {r_hi:.4g} mm to keep a {min_web:.3g} mm web")
    violations += _cell_violations(
        "tilt", clipped_tilt,
        f"had chief-ray holes larger than their cell at the top face (pitch x {top_scale:.4g})",
        f"radius cut (or the cell closed) to keep the {min_web:.3g} mm web at both faces of a "
        f"{t:g} mm plate")
    largest = sizes.radii_mm[-1] if sizes.radii_mm else 0.0
    violations += _cell_violations(
        "max_size", clipped_size, f"wanted holes larger than the largest size r = {largest:.4g} mm",
        f"radius cut to {largest:.4g} mm, the largest the process's sizes allow")
    target = np.minimum(wanted, cap_area)

    made_r = _diffuse(target, cap_area, sizes)

    # Count the cells that asked for less than the smallest hole.
    smallest = sizes.lo_mm if sizes.radii_mm is None else (
        sizes.radii_mm[0] if sizes.radii_mm else 0.0)
    below = (wanted > 0) & (wanted < math.pi * smallest**2 * (1 - 1e-12))
    n_below = int(below.sum())
    if n_below:
        n_open = int((below & (made_r > 0)).sum())
        d = 2 * smallest
        violations.append(Violation(
            "min_hole", None, float(2 * want_r[below].min()), 2 * r_lo,
            f"{n_below} cells below {d:.4g} mm: error-diffused: {n_open} opened at "
            f"{d:.4g} mm or more, {n_below - n_open} closed"))

    total = float(wanted.sum())
    lost = (total - float(np.sum(math.pi * made_r**2))) / total if total > 0 else 0.0
    if lost > MAX_LOST_FRACTION:
        message = _lost_area_error(a, process, plate, lost, smallest)
        if not force:
            raise UnmakeableError(message)
        violations.append(Violation("open_area", None, math.sqrt(total / math.pi),
                                    math.sqrt(total * (1 - lost) / math.pi), f"forced: {message}"))

    rows, cols = np.nonzero(made_r > 0)
    cells = np.stack([rows, cols], axis=1).astype(np.int64)
    return HoleLayout(
        cells=cells,
        centres_mm=np.stack([cx[rows, cols], cy[rows, cols]], axis=1).astype(np.float64),
        radii_mm=made_r[rows, cols].astype(np.float64),
        axes=np.stack([ax[rows, cols], ay[rows, cols]], axis=1).astype(np.float64),
        pitch_mm=(px, py),
        grid=(nx, ny),
        outline_mm=(nx * px + 2 * margin, ny * py + 2 * margin),
        thickness_mm=t,
        violations=tuple(violations),
        converge_mm=converge,
    )


def _diffuse(target: np.ndarray, cap_area: np.ndarray, sizes: _Sizes) -> np.ndarray:
    """Radii (ny, nx) mm from wanted areas by serpentine Floyd–Steinberg on open area.

    target: (ny, nx) wanted area, already <= cap_area (the largest allowed hole per cell).
    Errors that would leave the plate's sides go to the remaining neighbours (renormalized
    weights); a final balance pass then brings the total within E (see the module docstring).
    """
    ny, nx = target.shape
    err_in = [[0.0] * nx for _ in range(ny)]
    made = np.zeros((ny, nx))
    err = np.zeros((ny, nx))  # each cell's own error v - m, used by the balance pass
    lo_area = math.pi * sizes.lo_mm**2
    radii = () if sizes.radii_mm is None else sizes.radii_mm
    areas = [0.0] + [math.pi * r * r for r in radii]
    index = np.zeros((ny, nx), dtype=np.int64)  # into areas, for listed sizes
    top = np.zeros((ny, nx), dtype=np.int64)  # largest index each cell allows
    for i in range(ny):
        step = 1 if i % 2 == 0 else -1
        for j in range(nx) if step == 1 else range(nx - 1, -1, -1):
            v = float(target[i, j]) + err_in[i][j]
            cap = float(cap_area[i, j])
            if cap <= 0:
                m = 0.0
            elif sizes.radii_mm is None:
                m = cap if v >= cap else v if v >= lo_area else lo_area if v >= lo_area / 2 else 0.0
            else:
                kmax = top[i, j] = bisect.bisect_right(areas, cap * (1 + 1e-12)) - 1
                k = min(bisect.bisect_left(areas, v, hi=kmax + 1), kmax)
                if k > 0 and v - areas[k - 1] < areas[k] - v:
                    k -= 1
                index[i, j] = k
                m = areas[k]
            made[i, j] = m
            e = err[i, j] = v - m
            spots = [(i + di, j + dj * step, w) for di, dj, w in FS_WEIGHTS
                     if i + di < ny and 0 <= j + dj * step < nx]
            norm = sum(w for _, _, w in spots)
            for ii, jj, w in spots:
                err_in[ii][jj] += e * w / norm
    total = float(target.sum())
    if sizes.radii_mm is None:
        _balance_continuous(made, err, cap_area, total, lo_area)
        return np.sqrt(made / math.pi)
    _balance_listed(index, top, err, np.array(areas), total)
    return np.concatenate([[0.0], radii])[index]


# The balance passes: E is half the largest gap between allowed areas (0 included). While the
# total is off by more than E, step one cell by one allowed size (at most 2E), so the total
# always lands within E. The cell stepped is the one whose own diffusion error points the same
# way (rounded up most when there is too much open area), which keeps the local pattern.


def _balance_continuous(made: np.ndarray, err: np.ndarray, cap_area: np.ndarray, total: float,
                        lo_area: float) -> None:
    m, e, cap = made.reshape(-1), err.reshape(-1), cap_area.reshape(-1)
    for _ in range(2 * m.size + 1):
        delta = float(m.sum()) - total
        if abs(delta) <= lo_area / 2:
            return
        if delta > 0:
            k = int(np.argmin(np.where(m > 0, e, np.inf)))
            new = 0.0 if m[k] <= lo_area * (1 + 1e-12) else max(lo_area, m[k] - delta)
        else:
            room = (m < cap * (1 - 1e-12)) & (cap >= lo_area * (1 - 1e-12))
            if not room.any():
                return
            k = int(np.argmax(np.where(room, e, -np.inf)))
            new = lo_area if m[k] == 0 else min(float(cap[k]), m[k] - delta)
        e[k] += m[k] - new
        m[k] = new


def _balance_listed(index: np.ndarray, top: np.ndarray, err: np.ndarray, areas: np.ndarray,
                    total: float) -> None:
    half_gap = float(np.diff(areas).max()) / 2 if len(areas) > 1 else 0.0
    k_all, top_all, e = index.reshape(-1), top.reshape(-1), err.reshape(-1)
    for _ in range(k_all.size * len(areas) + 1):
        delta = float(areas[k_all].sum()) - total
        if abs(delta) <= half_gap:
            return
        room = k_all > 0 if delta > 0 else k_all < top_all
        if not room.any():
            return
        if delta > 0:
            k = int(np.argmin(np.where(room, e, np.inf)))
            e[k] += areas[k_all[k]] - areas[k_all[k] - 1]
            k_all[k] -= 1
        else:
            k = int(np.argmax(np.where(room, e, -np.inf)))
            e[k] -= areas[k_all[k] + 1] - areas[k_all[k]]
            k_all[k] += 1
