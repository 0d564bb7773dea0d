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

from aperture_fab.kernel_sources import check_inlined
from aperture_fab.optics import kernel_pair, kernel_stack
from aperture_fab.optics.kernel_pair import (
    CACHE_FIELDS,
    EMISSION,
    FAST_MATH,
    LENS_R,
    fill_pair,
    inline_jit,
    pair_chord,
    pair_window,
    pupil_share,
)
from aperture_fab.optics.kernel_stack import (
    add_gradient,
    add_weighted,
    pixel_grads,
    sample_stack,
    scatter_stack,
    store_sums,
)

#: kernel_pair.py's and kernel_stack.py's digest: these kernels inline their functions, and
#: Numba's cache does not see a change there (`aperture_fab.kernel_sources`).
INLINED_DIGEST = "08a746cd2037d232"
check_inlined(__name__, INLINED_DIGEST, kernel_pair, kernel_stack)

__all__ = [
    "GEOMETRY_FIELDS",
    "STATE_FIELDS",
    "open_index",
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


def open_index(radius: np.ndarray, cells: tuple[int, int], closed: float) -> np.ndarray:
    """The kernels' table of open holes, (rows, cols) int64: entry (i, j) is the first column
    j' >= j of row i whose hole radius (radius: (rows * cols,) mm, row-major) exceeds `closed`
    (mm), or cols where none does. The walk steps from one open hole to the next through it,
    so closed cells cost nothing (a regular array's plate is mostly closed)."""
    cols, rows = cells
    columns = np.broadcast_to(np.arange(cols, dtype=np.int64), (rows, cols))
    marked = np.where(radius.reshape(rows, cols) > closed, columns, cols)
    # The least open column at or after j: a running minimum from the row's end.
    return np.ascontiguousarray(np.minimum.accumulate(marked[:, ::-1], axis=1)[:, ::-1])


def thread_count() -> int:
    """Threads the parallel kernels use (NUMBA_NUM_THREADS, by default the CPU count)."""
    return int(get_num_threads())


_parallel = njit(cache=True, error_model="numpy", fastmath=FAST_MATH, parallel=True)


@_parallel
def view_forward(radius, stack, vx, vy, states, geometry, offsets, extra, box, shared, margin,
                 next_open, out):
    """out[s, c, iy, ix]: the view of each eye state (see the module docstring).

    box: holes per axis that the union of the states' hole windows can span (the size of the
    per-view pair cache). shared: every state focuses at infinity, so each pair's geometry and
    display sample are computed once per view pixel and reused by every state, and a lens
    centre is its hole's axis point moved by t v / 2, so the holes whose lens lies wholly
    inside the pupil are a chord of each row, found without testing them. margin: the largest
    lens radius plus the largest hole displacement (mm), which that chord keeps clear of the
    pupil's edge. next_open: `open_index`'s table; the walk visits only the holes it lists as
    open, so a sparse plate's closed cells cost nothing."""
    channels = stack.shape[3]
    size = box * box
    for iy in prange(vy.shape[0]):
        seen = np.zeros(size, dtype=np.bool_)
        cache = np.zeros((size, CACHE_FIELDS))
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
                sums = (0.0, 0.0, 0.0, 0.0)
                acc[:] = 0.0
                for i in range(r0, r1 + 1):
                    c0, c1 = pair_chord(geometry, ox, oy, outer, i)
                    ci0, ci1 = _inner_chord(geometry, ox, oy, inner, i)
                    j = c0 - 1
                    while j < c1:  # the open holes of columns c0 to c1
                        j = next_open[i, j + 1]
                        if j > c1:
                            break
                        n = (i - origin_r) * box + (j - origin_c)
                        if not (shared and seen[n]):
                            seen[n] = True
                            fill_pair(cache, n, radius, geometry, offsets, states, s, v_x, v_y,
                                      i, j, shared)
                            if cache[n, 4] > 0.0:
                                sample_stack(stack, cache[n, 6], cache[n, 7], cache[n, 8], samples,
                                        slopes, n, cache[n, EMISSION])
                        area = cache[n, 4]
                        if area <= 0.0:
                            continue
                        if ci0 <= j <= ci1:  # wholly inside the pupil
                            sums = add_weighted(sums, acc, area * norm, samples, n)
                            continue
                        if not shared and (cache[n, 0] - fx) ** 2 + (cache[n, 1] - fy) ** 2 \
                                >= keep * keep:
                            continue
                        po = math.sqrt((cache[n, 2] - fx) ** 2 + (cache[n, 3] - fy) ** 2)
                        share, _ = pupil_share(pupil_b, cache[n, LENS_R], po)
                        sums = add_weighted(sums, acc, area * share * norm, samples, n)
                store_sums(out, s, iy, ix, sums, acc)


@_parallel
def view_backward(radius, stack, vx, vy, states, geometry, offsets, extra, box, shared, margin,
                  next_open, grad_out, grad_radius, grad_stack, want_stack):
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
        cache = np.zeros((size, CACHE_FIELDS))
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
                    grads = pixel_grads(grad_out, s, iy, ix)
                    fx = states[s, 0] + geometry[9] * v_x
                    fy = states[s, 1] + geometry[9] * v_y
                    ox, oy, outer, inner, r0, r1 = _span(geometry, fx, fy, v_x, v_y, keep,
                                                         pupil_b, margin, extra, shared)
                    for i in range(r0, r1 + 1):
                        c0, c1 = pair_chord(geometry, ox, oy, outer, i)
                        ci0, ci1 = _inner_chord(geometry, ox, oy, inner, i)
                        j = c0 - 1
                        while j < c1:  # the open holes of columns c0 to c1
                            j = next_open[i, j + 1]
                            if j > c1:
                                break
                            n = (i - origin_r) * box + (j - origin_c)
                            if not (shared and seen[n]):
                                seen[n] = True
                                fill_pair(cache, n, radius, geometry, offsets, states, s, v_x, v_y,
                                      i, j, shared)
                                if cache[n, 4] > 0.0:
                                    sample_stack(stack, cache[n, 6], cache[n, 7], cache[n, 8],
                                            samples, slopes, n, cache[n, EMISSION])
                                    if shared:
                                        touched[count] = n
                                        count += 1
                            area = cache[n, 4]
                            if area <= 0.0:
                                continue
                            if ci0 <= j <= ci1:  # wholly inside the pupil: share 1
                                g_area[n] += add_gradient(g_sample, grads, grad_out, s, iy, ix,
                                                          area, norm, samples, n) * norm
                                continue
                            if not shared and (cache[n, 0] - fx) ** 2 \
                                    + (cache[n, 1] - fy) ** 2 >= keep * keep:
                                continue
                            po = math.sqrt((cache[n, 2] - fx) ** 2 + (cache[n, 3] - fy) ** 2)
                            share, slope = pupil_share(pupil_b, cache[n, LENS_R], po)
                            if slope == 0.0:
                                continue
                            w = area * share * norm
                            g_area[n] += add_gradient(g_sample, grads, grad_out, s, iy, ix, w,
                                                      1.0, samples, n) * slope * norm
                            if not shared:  # the pair is this state's alone: settle it now
                                _settle(grad_radius, grad_stack, want_stack, b, cache, samples,
                                        slopes, g_sample, g_area, lscale, geometry, i, j, n)
                for t in range(count):  # shared: every pair the states reached, settled once
                    n = touched[t]
                    _settle(grad_radius, grad_stack, want_stack, b, cache, samples, slopes,
                            g_sample, g_area, lscale, geometry, origin_r + n // box,
                            origin_c + n % box, n)


@inline_jit
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
        emission = cache[n, EMISSION]
        if emission != 1.0:  # the sample was the stack's times the emission weight
            for c in range(samples.shape[1]):
                g_sample[n, c] *= emission
        scatter_stack(grad_stack, b, cache[n, 6], cache[n, 7], cache[n, 8], g_sample, n)
    g_area[n] = 0.0
    for c in range(samples.shape[1]):
        g_sample[n, c] = 0.0


@inline_jit
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


@inline_jit
def _inner_chord(geometry, ox, oy, inner, i):
    if inner <= 0.0:
        return 0, -1
    return pair_chord(geometry, ox, oy, inner, i)


@inline_jit
def _origin(geometry, states, vx, vy, extra):
    """First row and column of the union of the states' hole windows for one view direction
    (widened by t |v| / 2, the shared spans' shift)."""
    r_min = 1 << 30
    c_min = 1 << 30
    slack = geometry[4] * math.sqrt(vx * vx + vy * vy) / 2
    for s in range(states.shape[0]):
        r0, _, fx, _ = pair_window(geometry, states[s, 0], states[s, 1], states[s, 7] + slack, vx,
                               vy, extra)
        c0 = math.ceil((fx - states[s, 7] - slack - extra) / geometry[2]
                       + (geometry[0] - 1) / 2)
        r_min = min(r_min, r0)
        c_min = min(c_min, max(0, int(c0)))
    return r_min, c_min
