"""One (view pixel, hole) pair in the fused CPU kernels (aperture_fab.optics.kernels), inlined into
them: the hole, its lens and pupil share, the display window it sees, the stack taps that window
reads and their adjoint, and the row a pair takes in the kernels' per-view cache."""

from __future__ import annotations

import math

from numba import njit

__all__ = ["CACHE_FIELDS", "EMISSION", "FAST_MATH", "LENS_R", "fill_pair", "inline_jit",
           "pair_chord", "pair_window", "pupil_share", "sample_stack", "scatter_stack"]


_EPS = 1e-12
#: Fast-math flags that keep NaN and infinity semantics (no "nnan"/"ninf"): reassociation and
#: contraction let LLVM vectorize the sums; approximate functions are not used ("afn" off).
FAST_MATH = {"nsz", "arcp", "contract", "reassoc"}
inline_jit = njit(cache=True, error_model="numpy", fastmath=FAST_MATH, inline="always")
#: Columns of the per-view pair cache: `_pair`'s first ten values, the lens's equal-area radius
#: and the pair's emission weight (`_pair`'s last value).
CACHE_FIELDS = 12
LENS_R = 10
EMISSION = 11


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
        theta = math.acos(half)
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
    t1 = math.acos(c1)
    t2 = math.acos(c2)
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
    share = 0.5 + (math.asin(x) + x * root) / math.pi
    return share, share - x * root / math.pi


@inline_jit
def _level(level_scale, area, darea):
    """Stack level coordinate in [-1, 1] of a window of `area` (times mu^2), and d / d r."""
    level = 2.0 * level_scale * area - 1.0
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
def _taps(shape, col, row, level):
    """Trilinear taps of a sample: level l0 and its weight toward l0 + 1, the clamped corner
    indices (x0, x1, y0, y1) and the four corner weights (0 where a corner is off the stack,
    which reads as 0: zero padding)."""
    levels, height, width = shape[0], shape[1], shape[2]
    lf = (level + 1.0) * (levels - 1) / 2.0
    l0 = min(int(lf), levels - 2)
    x0 = math.floor(col)
    y0 = math.floor(row)
    wx = col - x0
    wy = row - y0
    ax0 = (1.0 - wx) if 0 <= x0 < width else 0.0
    ax1 = wx if 0 <= x0 + 1 < width else 0.0
    ay0 = (1.0 - wy) if 0 <= y0 < height else 0.0
    ay1 = wy if 0 <= y0 + 1 < height else 0.0
    x0c = min(max(x0, 0), width - 1)
    x1c = min(max(x0 + 1, 0), width - 1)
    y0c = min(max(y0, 0), height - 1)
    y1c = min(max(y0 + 1, 0), height - 1)
    return (l0, lf - l0, x0c, x1c, y0c, y1c, ay0 * ax0, ay0 * ax1, ay1 * ax0, ay1 * ax1)


@inline_jit
def sample_stack(stack, col, row, level, samples, slopes, n, scale):
    """Trilinear stack sample into samples[n] (C,) and its slope along the level axis (per unit
    level index) into slopes[n], both times `scale` (the pair's emission weight)."""
    l0, wl, x0, x1, y0, y1, w00, w01, w10, w11 = _taps(stack.shape, col, row, level)
    for c in range(stack.shape[3]):
        lo = (w00 * stack[l0, y0, x0, c] + w01 * stack[l0, y0, x1, c]
              + w10 * stack[l0, y1, x0, c] + w11 * stack[l0, y1, x1, c])
        hi = (w00 * stack[l0 + 1, y0, x0, c] + w01 * stack[l0 + 1, y0, x1, c]
              + w10 * stack[l0 + 1, y1, x0, c] + w11 * stack[l0 + 1, y1, x1, c])
        samples[n, c] = lo + wl * (hi - lo)
        slopes[n, c] = hi - lo
    if scale != 1.0:
        for c in range(stack.shape[3]):
            samples[n, c] *= scale
            slopes[n, c] *= scale


@inline_jit
def scatter_stack(grad_stack, b, col, row, level, g, n):
    """Adjoint of `sample_stack` for the stack: add g[n] (C,) at the sample's taps of block b."""
    l0, wl, x0, x1, y0, y1, w00, w01, w10, w11 = _taps(grad_stack.shape[1:], col, row, level)
    for c in range(grad_stack.shape[4]):
        lo = (1.0 - wl) * g[n, c]
        hi = wl * g[n, c]
        grad_stack[b, l0, y0, x0, c] += w00 * lo
        grad_stack[b, l0, y0, x1, c] += w01 * lo
        grad_stack[b, l0, y1, x0, c] += w10 * lo
        grad_stack[b, l0, y1, x1, c] += w11 * lo
        grad_stack[b, l0 + 1, y0, x0, c] += w00 * hi
        grad_stack[b, l0 + 1, y0, x1, c] += w01 * hi
        grad_stack[b, l0 + 1, y1, x0, c] += w10 * hi
        grad_stack[b, l0 + 1, y1, x1, c] += w11 * hi


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
def _pair(radius, geometry, offsets, states, s, vx, vy, i, j, shared):
    """Pair (view direction v, hole (i, j)) for eye state s, into a cache row: (bottom-face
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
        level, dlevel = _level(states[0, 5], area, darea)
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
    level, dlevel = _level(states[s, 5], area, darea)
    return bx, by, lx, ly, area, darea, col, row, level, dlevel, emission


@inline_jit
def fill_pair(cache, n, radius, geometry, offsets, states, s, vx, vy, i, j, shared):
    pair = _pair(radius, geometry, offsets, states, s, vx, vy, i, j, shared)
    for f in range(LENS_R):
        cache[n, f] = pair[f]
    cache[n, LENS_R] = math.sqrt(max(pair[4] / math.pi, _EPS))
    cache[n, EMISSION] = pair[10]
