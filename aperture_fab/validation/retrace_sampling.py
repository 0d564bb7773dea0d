"""Sampling for the mesh re-trace (aperture_fab.validation.retrace): how many samples a view
pixel gets (the budgets), and the Numba helpers that place stratified points in a disk and in
the lens of two disks, with their numpy forms for tests."""

from __future__ import annotations

import math
from typing import Any, Literal

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

#: Intervals of the table that inverts a cap's area (cap_theta): theta and d theta / d t at
#: equal steps of t = cbrt(1.5 area) (theta ~ t near 0), interpolated by cubic Hermite
#: polynomials: the area theta - sin theta cos theta is met within 3e-15 (float64 rounding).
CAP_TABLE = 8192


def strata(n: int) -> tuple[np.ndarray, np.ndarray]:
    """n equal-area strata of the unit square: lower corners (n, 2) and sizes (n, 2).

    About sqrt(n) columns; column j holds b_j strata and is b_j / n wide, so every stratum has
    area 1 / n and an aspect ratio near 1, for any n.
    """
    columns = max(1, round(math.sqrt(n)))
    counts = np.full(columns, n // columns) + (np.arange(columns) < n % columns)
    column = np.repeat(np.arange(columns), counts)
    row = np.arange(n) - np.repeat(np.cumsum(counts) - counts, counts)
    left = np.concatenate([[0], np.cumsum(counts)])[:-1] / n
    corner = np.stack([left[column], row / counts[column]], axis=1)
    size = np.stack([counts[column] / n, 1.0 / counts[column]], axis=1)
    return corner, size


#: Fast-math flags that keep NaN and infinity semantics, as aperture_fab.optics.kernels: the
#: geometry's tests all keep margins far above the rounding this can change.
_FAST = {"nsz", "arcp", "contract", "reassoc"}


fast_jit = njit(cache=True, error_model="numpy", fastmath=_FAST)


#: Per-ray helpers, inlined into the kernels (a call would cut the pipeline's overlap).
inline_jit = njit(cache=True, error_model="numpy", fastmath=_FAST, inline="always")


parallel_jit = njit(cache=True, error_model="numpy", fastmath=_FAST, parallel=True)


def _cap_area(theta: np.ndarray) -> np.ndarray:
    """theta - sin(theta) cos(theta) = (phi - sin phi) / 2, phi = 2 theta, to float64 precision:
    by its series where the difference would cancel (phi < 1; terms to phi^21)."""
    phi = 2 * theta
    series = np.full_like(phi, 1 / math.factorial(21))
    for k in range(9, 0, -1):  # 1 / 3! - phi^2 / 5! + phi^4 / 7! - ..., by Horner
        series = 1 / math.factorial(2 * k + 1) - phi**2 * series
    return np.where(phi < 1, 0.5 * phi**3 * series, 0.5 * (phi - np.sin(phi)))


def _cap_table() -> np.ndarray:
    """(CAP_TABLE + 1, 4): at equal steps of t = cbrt(1.5 g) from 0 to cbrt(0.75 pi), theta in
    [0, pi / 2] with theta - sin theta cos theta = g (bisection, then Newton steps to float64
    precision), d theta / d t = t^2 / sin^2 theta (1 at 0), sin theta and cos theta. The nodes
    are at most 3e-4 rad apart."""
    t = np.linspace(0.0, (0.75 * math.pi) ** (1 / 3), CAP_TABLE + 1)
    g = t**3 / 1.5
    lo, hi = np.zeros_like(t), np.full_like(t, math.pi / 2)
    for _ in range(64):
        mid = 0.5 * (lo + hi)
        below = _cap_area(mid) < g
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    theta = 0.5 * (lo + hi)
    for _ in range(3):
        sin = np.sin(theta)
        theta = theta - (_cap_area(theta) - g) / np.maximum(2 * sin * sin, 1e-300)
    sin = np.sin(theta)
    slope = np.where(t > 0, t * t / np.maximum(sin * sin, 1e-300), 1.0)
    return np.stack([theta, slope, sin, np.cos(theta)], axis=1)


CAP_LOOKUP = _cap_table()


CAP_LOOKUP_SCALE = CAP_TABLE / (0.75 * math.pi) ** (1 / 3)  # table steps per unit of t


def _float_bits_typer(typingctx, x):
    """The bits of a float64 as an int64 (a bit cast, as C's memcpy)."""
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))
    return types.int64(types.float64), codegen


def _bits_float_typer(typingctx, i):
    """The float64 of an int64's bits."""
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())
    return types.float64(types.int64), codegen


_float_bits: Any = intrinsic(_float_bits_typer)


_bits_float: Any = intrinsic(_bits_float_typer)


@inline_jit
def _cbrt(y):
    """The cube root of y >= 0 (y below 1e-200 as 1e-200), to 2 float64 steps, without a call:
    the exponent divided by 3 in the bits (within 4 %), then 3 Halley steps (cubic: 4e-2,
    1e-4, 1e-12, exact). libm's cbrt is a call, which spills registers and stops the kernels'
    overlap of samples."""
    y = max(y, 1e-200)
    t = _bits_float(_float_bits(y) // 3 + 0x2A9F7893782DA1CE)
    for _ in range(3):
        t3 = t * t * t
        t = t * (t3 + 2.0 * y) / (2.0 * t3 + y)
    return t


@inline_jit
def _rotate(sin, cos, step):
    """(sin, cos) of theta + step from theta's, for |step| <= 1e-3 (the table's steps are
    3e-4): the series of sin(step) and cos(step) to step^5 are exact to float64 there."""
    s2 = step * step
    c_step = 1.0 - s2 * (0.5 - s2 / 24.0)
    s_step = step * (1.0 - s2 * (1.0 / 6.0 - s2 / 120.0))
    return sin * c_step + cos * s_step, cos * c_step - sin * s_step


@inline_jit
def cap_theta(g, table, table_scale):
    """(theta, sin theta, cos theta), theta in [0, pi] with theta - sin(theta) cos(theta) = g
    (g in [0, pi]): the cap {x <= -cos(theta)} of the unit disk has area g. On the half below
    pi / 2 (the rest by symmetry): the table (_cap_table) interpolated in t = cbrt(1.5 g) by
    a cubic Hermite polynomial, to float64 precision, and the node's sine and cosine turned by
    the rest of the angle (_rotate). No sin or cos is called and nothing branches: the kernels
    are latency-bound, and a mispredicted branch would stop the next sample's overlap."""
    flip = g > 0.5 * math.pi
    g = max(min(g, math.pi - g), 0.0)
    size = table.shape[0] - 1
    t = _cbrt(1.5 * g) * table_scale
    i = min(int(t), size - 1)
    f = t - i
    h = 1.0 / table_scale
    f1 = 1.0 - f
    theta = (f1 * f1 * ((1.0 + 2.0 * f) * table[i, 0] + f * h * table[i, 1])
             + f * f * ((3.0 - 2.0 * f) * table[i + 1, 0] - f1 * h * table[i + 1, 1]))
    sin, cos = _rotate(table[i, 2], table[i, 3], theta - table[i, 0])
    return (math.pi - theta if flip else theta), sin, (-cos if flip else cos)


@inline_jit
def _concentric_point(a, b):
    """Shirley-Chiu area-preserving map of the unit square's (a, b) onto the unit disk."""
    a = 2.0 * a - 1.0
    b = 2.0 * b - 1.0
    if abs(a) > abs(b):
        radius = a
        angle = math.pi / 4 * (b / a)
    else:
        radius = b
        angle = math.pi / 2 - math.pi / 4 * (a / (b if b != 0.0 else 1.0))
    return radius * math.cos(angle), radius * math.sin(angle)


@inline_jit
def lens_setup(ax, ay, r, bx, by, s):
    """The lens of disks (a, r) and (b, s): (kind, unit x, unit y, d, area of B's cap, lens
    area). kind 1: the circles cross; 2: one disk holds the other (area: the smaller one's);
    0: empty (area 0). unit: a to b (x axis when d = 0), d: their distance."""
    ox = bx - ax
    oy = by - ay
    d = math.hypot(ox, oy)
    ux, uy = (ox / d, oy / d) if d > 0 else (1.0, 0.0)
    if abs(r - s) < d < r + s:
        chord = (d * d + r * r - s * s) / (2 * d)
        theta_b = math.acos(min(max((d - chord) / s, -1.0), 1.0))
        theta_a = math.acos(min(max(chord / r, -1.0), 1.0))
        area_b = s * s * (theta_b - math.sin(theta_b) * math.cos(theta_b))
        total = area_b + r * r * (theta_a - math.sin(theta_a) * math.cos(theta_a))
        return 1, ux, uy, d, area_b, total
    if d <= abs(r - s):
        small = min(r, s)
        return 2, ux, uy, d, 0.0, math.pi * small * small
    return 0, ux, uy, d, 0.0, 0.0


@inline_jit
def lens_point(kind, ax, ay, r, bx, by, s, ux, uy, d, area_b, total, a, b, table, table_scale):
    """The point of the lens (`lens_setup`) for the unit square's (a, b) (see lens_sample)."""
    if kind == 1:
        target = a * total
        in_b = target < area_b
        radius = s if in_b else r
        g = min(max((target if in_b else total - target) / (radius * radius), 0.0), math.pi)
        _, sin, cos = cap_theta(g, table, table_scale)
        x = d - s * cos if in_b else r * cos
        y = (2 * b - 1) * radius * sin
        return ax + x * ux - y * uy, ay + x * uy + y * ux
    px, py = _concentric_point(a, b)
    if r <= s:
        return ax + r * px, ay + r * py
    return bx + s * px, by + s * py


@fast_jit
def _cap_kernel(area, table, table_scale, out):
    for i in range(area.size):
        out[i] = cap_theta(area[i], table, table_scale)[0]


@fast_jit
def _concentric_kernel(a, b, x, y):
    for i in range(a.size):
        x[i], y[i] = _concentric_point(a[i], b[i])


@fast_jit
def _lens_kernel(a, r, b, s, square, table, table_scale, points, area):
    for p in range(r.size):
        kind, ux, uy, d, area_b, total = lens_setup(a[p, 0], a[p, 1], r[p], b[p, 0], b[p, 1],
                                                     s[p])
        area[p] = total
        for k in range(square.shape[1]):
            points[p, k, 0], points[p, k, 1] = lens_point(
                kind, a[p, 0], a[p, 1], r[p], b[p, 0], b[p, 1], s[p], ux, uy, d, area_b, total,
                square[p, k, 0], square[p, k, 1], table, table_scale)


def cap_angle(area: np.ndarray) -> np.ndarray:
    """theta in [0, pi] with theta - sin(theta) cos(theta) = area (area in [0, pi]): the cap
    {x <= -cos(theta)} of the unit disk has that area (`cap_theta`)."""
    flat = np.ascontiguousarray(area, dtype=np.float64).ravel()
    out = np.empty_like(flat)
    _cap_kernel(flat, CAP_LOOKUP, CAP_LOOKUP_SCALE, out)
    return out.reshape(np.shape(area))


def concentric_disk(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shirley-Chiu area-preserving map of the unit square onto the unit disk."""
    a, b = np.broadcast_arrays(np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64))
    x, y = np.empty(a.size), np.empty(a.size)
    _concentric_kernel(np.ascontiguousarray(a).ravel(), np.ascontiguousarray(b).ravel(), x, y)
    return x.reshape(a.shape), y.reshape(a.shape)


def lens_sample(a: np.ndarray, r: np.ndarray, b: np.ndarray, s: np.ndarray,
                 square: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points uniform in the lens (intersection) of disks (a (P, 2), r (P,)) and (b, s): m
    points per lens (P, m, 2) from points `square` (P, m, 2) of the unit square, and the lens's
    area (P,) (0 when empty; the smaller disk when one holds the other).

    Along the line of centres (a at 0, b at d) the lens is B's cap x <= X then A's cap x >= X,
    X the common chord. The first square coordinate is the area fraction from B's end, so x
    solves a cap-area equation (cap_angle); the second places y uniformly across the lens at
    x. The map is monotone in both, so strata of the square stay compact in the lens. One disk
    inside the other: the smaller one, by the concentric map."""
    def c64(x: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(x, dtype=np.float64)

    square = c64(square)
    points = np.empty(square.shape)
    area = np.empty(len(r))
    _lens_kernel(c64(a), c64(r), c64(b), c64(s), square, CAP_LOOKUP, CAP_LOOKUP_SCALE, points, area)
    return points, area


#: How a view pixel is sampled: rays per (view pixel, hole) pair, or over the pupil.
Sampling = Literal["holes", "pupil"]
SAMPLINGS: tuple[Sampling, ...] = ("holes", "pupil")
#: Default samples_per_pixel: rays per (view pixel, hole) pair ("holes"), per view pixel
#: ("pupil").
DEFAULT_SAMPLES: dict[Sampling, int] = {"holes": 12, "pupil": 256}
#: With samples_per_pixel None, hole sampling spends about this many rays (~3 s on 2 cores for
#: the default 0.005 mm photomask plate, whose rays nearly all pass through clear cylinders;
#: more for a thick plate, whose rays near a wall are cast) and at most MOST_SAMPLES per pair,
#: never fewer than DEFAULT_SAMPLES["holes"].
RAY_BUDGET = 30_000_000
MOST_SAMPLES = 256
#: With samples_per_pixel None, chord sampling spends about this many chords, at least
#: LEAST_CHORDS per pair (2 per replicate) and at most MOST_SAMPLES.
CHORD_BUDGET = 16_000_000
LEAST_CHORDS = 8
#: Independent estimates per view pixel; their spread gives the standard error (REPLICATES - 1
#: degrees of freedom per pixel).
REPLICATES = 4


def sample_budget(pairs: int, chords: bool) -> int:
    """Samples per (view pixel, hole) pair: about CHORD_BUDGET chords (chord sampling) or
    RAY_BUDGET rays (hole sampling) over the view's `pairs`, at least LEAST_CHORDS or
    DEFAULT_SAMPLES["holes"], at most MOST_SAMPLES: a sparse plate, with few holes behind each
    view pixel, gets more per pair."""
    budget, least = (CHORD_BUDGET, LEAST_CHORDS) if chords else (RAY_BUDGET,
                                                                DEFAULT_SAMPLES["holes"])
    return int(min(MOST_SAMPLES, max(least, budget // max(pairs, 1))))
