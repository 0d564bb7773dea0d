"""Fused CPU kernels (Numba) for the view through a plate: the model's hot path.

The model (see `aperture_fab.optics.model` and docs/model.md) sums, for each view pixel and eye
state, over the holes whose light can reach the pupil: (pupil share of the rays through the hole) x
(the display's mean over the hole's window, read from the pre-filtered stack). These kernels do that
for a batch of eye states in one pass over the view, computing each (view pixel, hole) pair's
geometry on the fly from the plate's grid instead of storing a pair table: nothing per pair is
written to memory, so the cost is arithmetic and reads of a stack that stays in cache, and memory
does not grow with the plate or the eyebox.

The arithmetic is the same as `aperture_fab.optics.model`'s torch path (which is kept as the
reference and for CUDA); the tests compare the two, values and gradients. Geometry is in float64;
the stack is read in its own dtype; sums are kept in float64.

Layouts: the stack is (L, H, W, C) (channels last, so a tap reads C adjacent values); views are
(S, C, ny, nx). `states` rows hold, per eye state: pupil-centre x, y (mm), pupil radius at the
plate's bottom face (mm), top-to-bottom scale m, window scale mu, level scale (mu^2 / pi / w^2,
w the stack's largest window radius), 1 / (pi R_b^2), and the distance from the footprint
centre within which a hole's bottom disk must lie, R_b + 2 r_max (mm); `extra` widens the hole
search by the chief-ray tilt and the largest hole displacement.
`geometry` holds the scene's constants in the order of GEOMETRY_FIELDS; its last three are the
display-side optics (cover glass thickness and index, emission exponent k; 0 thickness and 0 k:
off, and then nothing changes): the glass moves a pair's window by its refraction shift, the
falloff weighs its sample by cos^k, both at the pair's chief ray (docs/model.md).
"""

from __future__ import annotations

import math

import numpy as np
from numba import get_num_threads, njit, prange

__all__ = [
    "GEOMETRY_FIELDS",
    "STATE_FIELDS",
    "thread_count",
    "view_backward",
    "view_forward",
]

GEOMETRY_FIELDS = (
    "cells_x", "cells_y", "pitch_x", "pitch_y", "thickness", "chief_ray", "eye_x", "eye_y",
    "axis_length", "s_bottom", "s_top", "s_display", "half_width", "half_height",
    "pixel_x", "pixel_y", "pad", "cover_glass", "glass_index", "emission_power",
)
STATE_FIELDS = ("cx", "cy", "pupil_bottom", "top_scale", "window_scale", "level_scale", "norm",
                "keep")

_EPS = 1e-12
#: Fast-math flags that keep NaN and infinity semantics (no "nnan"/"ninf"): reassociation and
#: contraction let LLVM vectorize the sums; approximate functions are not used ("afn" off).
_FAST = {"nsz", "arcp", "contract", "reassoc"}


def thread_count() -> int:
    """Threads the parallel kernels use (NUMBA_NUM_THREADS, by default the CPU count)."""
    return int(get_num_threads())


_inline = njit(cache=True, error_model="numpy", fastmath=_FAST, inline="always")
_parallel = njit(cache=True, error_model="numpy", fastmath=_FAST, parallel=True)
#: Columns of the per-view pair cache: `_pair`'s first ten values, the lens's equal-area radius
#: and the pair's emission weight (`_pair`'s last value).
_CACHE_FIELDS = 12
_LENS_R = 10
_EMISSION = 11


@_inline
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


@_inline
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


@_inline
def _share(pupil_bottom, lens_r, po):
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


@_inline
def _level(level_scale, area, darea):
    """Stack level coordinate in [-1, 1] of a window of `area` (times mu^2), and d / d r."""
    level = 2.0 * level_scale * area - 1.0
    if level >= 1.0:
        return 1.0, 0.0
    if level <= -1.0:
        return -1.0, 0.0
    return level, 2.0 * level_scale * darea


@_inline
def _pixel(geometry, wx, wy):
    """Display point (mm) to the padded stack's (column, row)."""
    return ((wx + geometry[12]) / geometry[14] - 0.5 + geometry[16],
            (geometry[13] - wy) / geometry[15] - 0.5 + geometry[16])


@_inline
def _window(geometry, cx, cy, keep, vx, vy, extra):
    """Rows (inclusive) of the holes that can reach the footprint, and its centre."""
    reach = keep + extra
    fx = cx + geometry[9] * vx
    fy = cy + geometry[9] * vy
    ncy = geometry[1]
    r0 = max(0, math.ceil((ncy - 1) / 2 - (fy + reach) / geometry[3]))
    r1 = min(int(ncy) - 1, math.floor((ncy - 1) / 2 - (fy - reach) / geometry[3]))
    return int(r0), int(r1), fx, fy


@_inline
def _chord(geometry, fx, fy, reach, i):
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


@_inline
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


@_inline
def _sample(stack, col, row, level, samples, slopes, n, scale):
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


@_inline
def _scatter(grad_stack, b, col, row, level, g, n):
    """Adjoint of `_sample` for the stack: add g[n] (C,) at the sample's taps of block b."""
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


@_inline
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


@_inline
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


@_inline
def _fill(cache, n, radius, geometry, offsets, states, s, vx, vy, i, j, shared):
    pair = _pair(radius, geometry, offsets, states, s, vx, vy, i, j, shared)
    for f in range(_LENS_R):
        cache[n, f] = pair[f]
    cache[n, _LENS_R] = math.sqrt(max(pair[4] / math.pi, _EPS))
    cache[n, _EMISSION] = pair[10]


@_parallel
def view_forward(radius, stack, vx, vy, states, geometry, offsets, extra, box, shared, margin,
                 closed, out):
    """out[s, c, iy, ix]: the view of each eye state (see the module docstring).

    box: holes per axis that the union of the states' hole windows can span (the size of the
    per-view pair cache). shared: every state focuses at infinity, so each pair's geometry and
    display sample are computed once per view pixel and reused by every state, and a lens
    centre is its hole's axis point moved by t v / 2, so the holes whose lens lies wholly
    inside the pupil are a chord of each row, found without testing them. margin: the largest
    lens radius plus the largest hole displacement (mm), which that chord keeps clear of the
    pupil's edge. closed: holes of this radius (mm) or less are skipped, as if there were none
    (0: none skipped; a sparse plate's closed cells then cost a read each)."""
    channels = stack.shape[3]
    size = box * box
    for iy in prange(vy.shape[0]):
        seen = np.zeros(size, dtype=np.bool_)
        cache = np.zeros((size, _CACHE_FIELDS))
        samples = np.zeros((size, channels))
        slopes = np.zeros((size, channels))
        acc = np.zeros(channels)
        v_y = vy[iy]
        for ix in range(vx.shape[0]):
            v_x = vx[ix]
            seen[:] = False
            origin_r, origin_c = _origin(geometry, states, v_x, v_y, extra)
            for s in range(states.shape[0]):
                keep = states[s, 7]
                pupil_b = states[s, 2]
                norm = states[s, 6]
                fx = states[s, 0] + geometry[9] * v_x
                fy = states[s, 1] + geometry[9] * v_y
                ox, oy, outer, inner, r0, r1 = _span(geometry, fx, fy, v_x, v_y, keep, pupil_b,
                                                     margin, extra, shared)
                for c in range(channels):
                    acc[c] = 0.0
                for i in range(r0, r1 + 1):
                    c0, c1 = _chord(geometry, ox, oy, outer, i)
                    ci0, ci1 = _inner_chord(geometry, ox, oy, inner, i)
                    for j in range(c0, c1 + 1):
                        if radius[int(i * geometry[0] + j)] <= closed:
                            continue
                        n = (i - origin_r) * box + (j - origin_c)
                        if not (shared and seen[n]):
                            seen[n] = True
                            _fill(cache, n, radius, geometry, offsets, states, s, v_x, v_y, i, j,
                                  shared)
                            if cache[n, 4] > 0.0:
                                _sample(stack, cache[n, 6], cache[n, 7], cache[n, 8], samples,
                                        slopes, n, cache[n, _EMISSION])
                        area = cache[n, 4]
                        if area <= 0.0:
                            continue
                        if ci0 <= j <= ci1:  # wholly inside the pupil
                            w = area * norm
                            for c in range(channels):
                                acc[c] += w * samples[n, c]
                            continue
                        if not shared and (cache[n, 0] - fx) ** 2 + (cache[n, 1] - fy) ** 2 \
                                >= keep * keep:
                            continue
                        po = math.sqrt((cache[n, 2] - fx) ** 2 + (cache[n, 3] - fy) ** 2)
                        share, _ = _share(pupil_b, cache[n, _LENS_R], po)
                        w = area * share * norm
                        for c in range(channels):
                            acc[c] += w * samples[n, c]
                for c in range(channels):
                    out[s, c, iy, ix] = acc[c]


@_parallel
def view_backward(radius, stack, vx, vy, states, geometry, offsets, extra, box, shared, margin,
                  closed, grad_out, grad_radius, grad_stack, want_stack):
    """Gradients of sum(grad_out * view) (as `view_forward`) into per-block buffers:
    grad_radius (B, K) and, when want_stack, grad_stack (B, L, H, W, C). Block b handles a
    band of view rows, so no two threads write one buffer; the caller sums over B."""
    channels = stack.shape[3]
    lscale = (stack.shape[0] - 1) / 2.0
    size = box * box
    blocks = grad_radius.shape[0]
    ny = vy.shape[0]
    for b in prange(blocks):
        seen = np.zeros(size, dtype=np.bool_)
        cache = np.zeros((size, _CACHE_FIELDS))
        samples = np.zeros((size, channels))
        slopes = np.zeros((size, channels))
        g_sample = np.zeros((size, channels))  # d loss / d sample, summed over states
        g_area = np.zeros(size)  # d loss / d area through the pupil shares
        touched = np.zeros(size, dtype=np.int64)
        for iy in range(b * ny // blocks, (b + 1) * ny // blocks):
            v_y = vy[iy]
            for ix in range(vx.shape[0]):
                v_x = vx[ix]
                seen[:] = False
                count = 0
                origin_r, origin_c = _origin(geometry, states, v_x, v_y, extra)
                for s in range(states.shape[0]):
                    keep = states[s, 7]
                    pupil_b = states[s, 2]
                    norm = states[s, 6]
                    fx = states[s, 0] + geometry[9] * v_x
                    fy = states[s, 1] + geometry[9] * v_y
                    ox, oy, outer, inner, r0, r1 = _span(geometry, fx, fy, v_x, v_y, keep,
                                                         pupil_b, margin, extra, shared)
                    for i in range(r0, r1 + 1):
                        c0, c1 = _chord(geometry, ox, oy, outer, i)
                        ci0, ci1 = _inner_chord(geometry, ox, oy, inner, i)
                        for j in range(c0, c1 + 1):
                            if radius[int(i * geometry[0] + j)] <= closed:
                                continue
                            n = (i - origin_r) * box + (j - origin_c)
                            if not (shared and seen[n]):
                                seen[n] = True
                                _fill(cache, n, radius, geometry, offsets, states, s, v_x, v_y,
                                      i, j, shared)
                                if cache[n, 4] > 0.0:
                                    _sample(stack, cache[n, 6], cache[n, 7], cache[n, 8],
                                            samples, slopes, n, cache[n, _EMISSION])
                                    if shared:
                                        touched[count] = n
                                        count += 1
                            area = cache[n, 4]
                            if area <= 0.0:
                                continue
                            if ci0 <= j <= ci1:  # wholly inside the pupil: share 1
                                dot = 0.0
                                for c in range(channels):
                                    g = grad_out[s, c, iy, ix]
                                    g_sample[n, c] += g * area * norm
                                    dot += g * samples[n, c]
                                g_area[n] += dot * norm
                                continue
                            if not shared and (cache[n, 0] - fx) ** 2 \
                                    + (cache[n, 1] - fy) ** 2 >= keep * keep:
                                continue
                            po = math.sqrt((cache[n, 2] - fx) ** 2 + (cache[n, 3] - fy) ** 2)
                            share, slope = _share(pupil_b, cache[n, _LENS_R], po)
                            if slope == 0.0:
                                continue
                            w = area * share * norm
                            dot = 0.0
                            for c in range(channels):
                                g = grad_out[s, c, iy, ix]
                                g_sample[n, c] += g * w
                                dot += g * samples[n, c]
                            g_area[n] += dot * slope * norm
                            if not shared:  # the pair is this state's alone: settle it now
                                _settle(grad_radius, grad_stack, want_stack, b, cache, samples,
                                        slopes, g_sample, g_area, lscale, geometry, i, j, n)
                for t in range(count):  # shared: every pair the states reached, settled once
                    n = touched[t]
                    _settle(grad_radius, grad_stack, want_stack, b, cache, samples, slopes,
                            g_sample, g_area, lscale, geometry, origin_r + n // box,
                            origin_c + n % box, n)


@_inline
def _settle(grad_radius, grad_stack, want_stack, b, cache, samples, slopes, g_sample, g_area,
            lscale, geometry, i, j, n):
    """Turn a pair's d loss / d sample and d loss / d area into gradients of the hole radius
    and (want_stack) the stack."""
    gl = 0.0
    for c in range(samples.shape[1]):
        gl += g_sample[n, c] * slopes[n, c]
    k = int(i * geometry[0] + j)
    grad_radius[b, k] += g_area[n] * cache[n, 5] + gl * lscale * cache[n, 9]
    if want_stack:
        emission = cache[n, _EMISSION]
        if emission != 1.0:  # the sample was the stack's times the emission weight
            for c in range(samples.shape[1]):
                g_sample[n, c] *= emission
        _scatter(grad_stack, b, cache[n, 6], cache[n, 7], cache[n, 8], g_sample, n)
    g_area[n] = 0.0
    for c in range(samples.shape[1]):
        g_sample[n, c] = 0.0


@_inline
def _span(geometry, fx, fy, vx, vy, keep, pupil_b, margin, extra, shared):
    """Where state's pairs lie for one view direction: the centre (x, y) and radius of the disk
    of hole axes to walk, the radius within which a lens lies wholly inside the pupil (share 1;
    negative: none), and the rows (inclusive) the outer disk covers.

    Shared (infinite focus): a lens centre is its hole's axis point moved by t v / 2, so the
    disk is centred there: radius R_b + margin holds every lens that reaches the pupil, R_b -
    margin those wholly inside (margin: the largest lens radius plus hole displacement).
    Otherwise: hole axes within keep + extra of the footprint centre, each tested."""
    if shared:
        t = geometry[4]
        ox = fx - t * vx / 2
        oy = fy - t * vy / 2
        outer = pupil_b + margin
        inner = pupil_b - margin
    else:
        ox = fx
        oy = fy
        outer = keep + extra
        inner = -1.0
    ncy = geometry[1]
    r0 = max(0, math.ceil((ncy - 1) / 2 - (oy + outer) / geometry[3]))
    r1 = min(int(ncy) - 1, math.floor((ncy - 1) / 2 - (oy - outer) / geometry[3]))
    return ox, oy, outer, inner, int(r0), int(r1)


@_inline
def _inner_chord(geometry, ox, oy, inner, i):
    if inner <= 0.0:
        return 0, -1
    return _chord(geometry, ox, oy, inner, i)


@_inline
def _origin(geometry, states, vx, vy, extra):
    """First row and column of the union of the states' hole windows for one view direction
    (widened by t |v| / 2, the shared spans' shift)."""
    r_min = 1 << 30
    c_min = 1 << 30
    slack = geometry[4] * math.sqrt(vx * vx + vy * vy) / 2
    for s in range(states.shape[0]):
        r0, _, fx, _ = _window(geometry, states[s, 0], states[s, 1], states[s, 7] + slack, vx,
                               vy, extra)
        c0 = math.ceil((fx - states[s, 7] - slack - extra) / geometry[2]
                       + (geometry[0] - 1) / 2)
        r_min = min(r_min, r0)
        c_min = min(c_min, max(0, int(c0)))
    return r_min, c_min
