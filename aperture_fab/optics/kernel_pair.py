"""One (view pixel, hole) pair in the fused CPU kernels (aperture_fab.optics.kernels), inlined into
them: the hole, its lens and pupil share, the display window it sees, and the values the kernels
keep per pair of a view pixel. How a window reads the display stack:
`aperture_fab.optics.kernel_stack`."""

from __future__ import annotations

import math

from numba import njit

__all__ = ["CACHE_FIELDS", "EMISSION", "FAST_MATH", "LENS_R", "asin_ratio", "fast_acos",
           "fast_asin", "inline_jit", "lens_radius", "pair_chord", "pair_geometry", "pair_window",
           "pupil_share"]


_EPS = 1e-12
#: Fast-math flags that keep NaN and infinity semantics (no "nnan"/"ninf"): reassociation and
#: contraction let LLVM vectorize the sums; approximate functions are not used ("afn" off).
FAST_MATH = {"nsz", "arcp", "contract", "reassoc"}
inline_jit = njit(cache=True, error_model="numpy", fastmath=FAST_MATH, inline="always")
#: Rows of a view pixel's pair geometry in the kernels: `pair_geometry`'s first ten values, the
#: lens's equal-area radius (`lens_radius`) and the pair's emission weight (its last value).
CACHE_FIELDS = 12
LENS_R = 10
EMISSION = 11


# fdlibm's rational approximation of (asin(x) - x) / x^3 in t = x^2 (e_asin.c), on 0 <= t <=
# 0.25: with it, asin and acos below are within 2 ulp of libm's and about twice as fast (the
# pair walk takes one acos per pair and one asin per lens on the pupil's edge).
_P = (1.66666666666666657415e-01, -3.25565818622400915405e-01, 2.01212532134862925881e-01,
      -4.00555345006794114027e-02, 7.91534994289814532176e-04, 3.47933107596021167570e-05)
_Q = (-2.40339491173441421878e+00, 2.02094576023350569471e+00, -6.88283971605453293030e-01,
      7.70381505559019352791e-02)


@inline_jit
def asin_ratio(t):
    """(asin(x) - x) / x^3 for t = x^2, 0 <= t <= 0.25 (fdlibm's rational form)."""
    p = t * (_P[0] + t * (_P[1] + t * (_P[2] + t * (_P[3] + t * (_P[4] + t * _P[5])))))
    q = 1.0 + t * (_Q[0] + t * (_Q[1] + t * (_Q[2] + t * _Q[3])))
    return p / q


@inline_jit
def fast_asin(x):
    """asin(x) for -1 <= x <= 1, within 2 ulp."""
    a = abs(x)
    if a < 0.5:
        return x + x * asin_ratio(x * x)
    t = (1.0 - a) * 0.5
    s = math.sqrt(t)
    y = math.pi / 2 - 2.0 * (s + s * asin_ratio(t))
    return y if x > 0.0 else -y


@inline_jit
def fast_acos(x):
    """acos(x) for -1 <= x <= 1, within 2 ulp."""
    if abs(x) < 0.5:
        return math.pi / 2 - (x + x * asin_ratio(x * x))
    t = (1.0 - abs(x)) * 0.5
    s = math.sqrt(t)
    y = 2.0 * (s + s * asin_ratio(t))
    return y if x > 0.0 else math.pi - y


@inline_jit
def _hole(geometry, offsets, i, j):
    """Hole (i, j): its axis point at mid-thickness (x, y) and its axis slope (ax, ay)."""
    ncx = geometry[0]
    ncy = geometry[1]
    hx = (j - (ncx - 1) / 2) * geometry[2]
    hy = ((ncy - 1) / 2 - i) * geometry[3]
    ax = 0.0
    ay = 0.0
    if geometry[5] > 0:  # chief-ray axes point at the nominal eye from the undisplaced hole
        ax = (geometry[6] - hx) / geometry[8]
        ay = (geometry[7] - hy) / geometry[8]
    k = int(i * ncx + j)
    return hx + offsets[k, 0], hy + offsets[k, 1], ax, ay, k


@inline_jit
def _lens(r1, m, d):
    """Area of two disks (radii r1 and |m| r1, centres d apart) and its derivative in r1."""
    if m == 1.0:  # equal disks (infinite focus): one acos
        if d >= 2.0 * r1:
            return 0.0, 0.0
        half = d / (2.0 * r1)
        theta = fast_acos(half)
        return 2.0 * r1 * r1 * theta - d * r1 * math.sqrt(1.0 - half * half), 4.0 * r1 * theta
    r2 = abs(m) * r1
    if d >= r1 + r2:
        return 0.0, 0.0
    small = min(r1, r2)
    if d <= abs(r1 - r2):
        return math.pi * small * small, 2.0 * math.pi * small * small / r1
    ds = max(d, _EPS)
    c1 = min(1.0, max(-1.0, (ds * ds + r1 * r1 - r2 * r2) / (2.0 * ds * r1)))
    c2 = min(1.0, max(-1.0, (ds * ds + r2 * r2 - r1 * r1) / (2.0 * ds * r2)))
    t1 = fast_acos(c1)
    t2 = fast_acos(c2)
    area = r1 * r1 * t1 + r2 * r2 * t2 - r1 * math.sin(t1) * ds
    return area, 2.0 * r1 * t1 + 2.0 * abs(m) * r2 * t2


@inline_jit
def pupil_share(pupil_bottom, lens_r, po):
    """The share of a lens (equal-area radius lens_r), centred `po` from the pupil footprint's
    centre, inside the footprint's (locally straight) edge, and d (area x share) / d area /
    share: the lens is an equal-area disk, its share a circular segment."""
    x = (pupil_bottom - po) / lens_r
    if x >= 1.0:
        return 1.0, 1.0
    if x <= -1.0:
        return 0.0, 0.0
    root = math.sqrt(max(1.0 - x * x, 0.0))
    share = 0.5 + (fast_asin(x) + x * root) / math.pi
    return share, share - x * root / math.pi


@inline_jit
def _level(level_scale, offset, area, darea):
    """Stack level coordinate in [-1, 1] of a window of `area` (times mu^2) in a stack whose
    lowest level sits `offset` above the level of a window of no area, and d / d r."""
    level = 2.0 * level_scale * area - 1.0 - offset
    if level >= 1.0:
        return 1.0, 0.0
    if level <= -1.0:
        return -1.0, 0.0
    return level, 2.0 * level_scale * darea


@inline_jit
def _pixel(geometry, wx, wy):
    """Display point (mm) to the padded stack's (column, row)."""
    return ((wx + geometry[12]) / geometry[14] - 0.5 + geometry[16],
            (geometry[13] - wy) / geometry[15] - 0.5 + geometry[16])


@inline_jit
def pair_window(geometry, cx, cy, keep, vx, vy, extra):
    """Rows (inclusive) of the holes that can reach the footprint, and its centre."""
    reach = keep + extra
    fx = cx + geometry[9] * vx
    fy = cy + geometry[9] * vy
    ncy = geometry[1]
    r0 = max(0, math.ceil((ncy - 1) / 2 - (fy + reach) / geometry[3]))
    r1 = min(int(ncy) - 1, math.floor((ncy - 1) / 2 - (fy - reach) / geometry[3]))
    return int(r0), int(r1), fx, fy


@inline_jit
def pair_chord(geometry, fx, fy, reach, i):
    """Columns (inclusive) of hole row i whose axis lies within `reach` of (fx, fy)."""
    ncx = geometry[0]
    dy = ((geometry[1] - 1) / 2 - i) * geometry[3] - fy
    half = reach * reach - dy * dy
    if half <= 0.0:
        return 0, -1
    half = math.sqrt(half)
    c0 = max(0, math.ceil((fx - half) / geometry[2] + (ncx - 1) / 2))
    c1 = min(int(ncx) - 1, math.floor((fx + half) / geometry[2] + (ncx - 1) / 2))
    return int(c0), int(c1)


@inline_jit
def _display_optics(geometry, wx, wy, sx, sy):
    """The window centre (wx, wy) mm on the emitting surface moved by the cover glass, and the
    emission weight cos^k, for a chief ray of slope (sx, sy) in air (docs/model.md): in glass
    of index n the slope is w / sqrt(n^2 + (n^2 - 1) |w|^2) (Snell), so the ray lands short of
    its straight continuation by t_g w (1 - that factor)."""
    tan2 = sx * sx + sy * sy
    t_g = geometry[17]
    if t_g > 0.0:
        n2 = geometry[18] * geometry[18]
        loss = t_g * (1.0 - 1.0 / math.sqrt(n2 + (n2 - 1.0) * tan2))
        wx -= loss * sx
        wy -= loss * sy
    emission = 1.0
    if geometry[19] > 0.0:
        emission = (1.0 + tan2) ** (-geometry[19] / 2.0)
    return wx, wy, emission


@inline_jit
def pair_geometry(radius, geometry, offsets, states, s, vx, vy, i, j, shared):
    """Pair (view direction v, hole (i, j)) for eye state s: (bottom-face
    centre x, y, lens centre x, y, area, d area / d r, stack column, row, level, d level / d r,
    emission weight). With `shared` (every state focused at infinity: m = mu = 1) nothing here
    depends on the state: the lens and its window are the same for every pupil position.
    Display-side optics (cover glass, emission falloff) act at the pair's chief ray, of slope
    (window - lens centre) / gap in air: v itself when shared."""
    hx, hy, ax, ay, k = _hole(geometry, offsets, i, j)
    t = geometry[4]
    bx = hx - t / 2 * ax
    by = hy - t / 2 * ay
    if shared:
        # The top-face disk seen along v lands t (a + v) away from the bottom one.
        dx = t * (ax + vx)
        dy = t * (ay + vy)
        area, darea = _lens(radius[k], 1.0, math.sqrt(dx * dx + dy * dy))
        lx = bx + dx / 2
        ly = by + dy / 2
        gap = geometry[11] - geometry[9]
        wx = lx + gap * vx
        wy = ly + gap * vy
        emission = 1.0
        if geometry[17] > 0.0 or geometry[19] > 0.0:
            wx, wy, emission = _display_optics(geometry, wx, wy, vx, vy)
        col, row = _pixel(geometry, wx, wy)
        level, dlevel = _level(states[0, 5], geometry[20], area, darea)
        return bx, by, lx, ly, area, darea, col, row, level, dlevel, emission
    cx = states[s, 0]
    cy = states[s, 1]
    m = states[s, 3]
    mu = states[s, 4]
    fx = cx + geometry[9] * vx
    fy = cy + geometry[9] * vy
    # The top-face disk mapped to the bottom face through the eye's lens, for this v.
    ctx = fx + m * (hx + t / 2 * ax - cx - geometry[10] * vx)
    cty = fy + m * (hy + t / 2 * ay - cy - geometry[10] * vy)
    area, darea = _lens(radius[k], m, math.sqrt((ctx - bx) ** 2 + (cty - by) ** 2))
    lx = (bx + ctx) / 2
    ly = (by + cty) / 2
    wx = cx + geometry[11] * vx + mu * (lx - fx)
    wy = cy + geometry[11] * vy + mu * (ly - fy)
    emission = 1.0
    if geometry[17] > 0.0 or geometry[19] > 0.0:
        gap = geometry[11] - geometry[9]
        wx, wy, emission = _display_optics(geometry, wx, wy, (wx - lx) / gap, (wy - ly) / gap)
    col, row = _pixel(geometry, wx, wy)
    level, dlevel = _level(states[s, 5], geometry[20], area, darea)
    return bx, by, lx, ly, area, darea, col, row, level, dlevel, emission


@inline_jit
def lens_radius(area):
    """The radius of a disk of `area` (mm^2), at least sqrt(1e-12) mm: a lens's equal-area
    radius, its pupil share's scale."""
    return math.sqrt(max(area / math.pi, _EPS))
