"""Fused CPU kernels (Numba) for the view through a plate: the model's hot path.

The model (see `aperture_fab.optics.model` and docs/model.md) sums, for each view pixel and eye
state, over the holes whose light can reach the pupil: (pupil share of the rays through the hole) x
(the display's mean over the hole's window, read from the pre-filtered stack). These kernels do that
for a batch of eye states in one pass over the view, computing each (view pixel, hole) pair's
geometry on the fly from the plate's grid instead of storing a pair table: nothing per pair is
written to memory, so the cost is arithmetic and reads of a stack that stays in cache, and memory
does not grow with the plate or the eyebox.

Each view pixel goes in three steps: a walk over the holes each eye state's pupil can see
(`_walk`: each pair listed once, and per state which pairs it sums), the pairs' geometry and
stack samples in one loop (`_fill`), then each state's sum over its list. When every state
focuses at infinity the pairs are shared by the states and their geometry is a loop LLVM runs
in SIMD lanes (`_shared_geometry`); apart from the walk, it cost 40 ns a pair one by one
(benchmarks/README.md, "What bounds the CPU kernels").

The arithmetic is the same as `aperture_fab.optics.model`'s torch path (which is kept as the
reference and for CUDA); the tests compare the two, values and gradients. Geometry is in float64;
the stack is read in its own dtype; sums are kept in float64.

Layouts: the stack is (L, H, W, C) (channels last, so a tap reads C adjacent values); views are
(S, C, ny, nx). `states` rows hold, per eye state: pupil-centre x, y (mm), pupil radius at the
plate's bottom face (mm), top-to-bottom scale m, window scale mu, level scale (mu^2 / pi / w^2,
w the stack's largest window radius; times (L - 1) / (L' - 1) for a stack that holds the upper
L' of its L levels), 1 / (pi R_b^2), and the distance from the footprint
centre within which a hole's bottom disk must lie, R_b + 2 r_max (mm); `extra` widens the hole
search by the chief-ray tilt and the largest hole displacement.
`geometry` holds the scene's constants in the order of GEOMETRY_FIELDS; fields 17 to 19 are
the display-side optics (cover glass thickness and index, emission exponent k; 0 thickness and
0 k: off, and then nothing changes): the glass moves a pair's window by its refraction shift,
the falloff weighs its sample by cos^k, both at the pair's chief ray (docs/model.md). The last
is the level offset of a stack that holds only its upper levels (`Renderer`'s min_radius_mm):
a window's level coordinate is 2 (level scale) area - 1 - offset, clamped to [-1, 1].
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
    asin_ratio,
    inline_jit,
    lens_radius,
    pair_geometry,
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
INLINED_DIGEST = "6acff65a9ceb675b"
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
    "pixel_x", "pixel_y", "pad", "cover_glass", "glass_index", "emission_power", "level_offset",
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
_serial = njit(cache=True, error_model="numpy", fastmath=FAST_MATH)


@_parallel
def view_forward(radius, stack, vx, vy, states, geometry, offsets, extra, box, shared, margin,
                 next_open, out):
    """out[s, c, iy, ix]: the view of each eye state (see the module docstring).

    box: holes per axis that the union of the states' hole windows can span (the size of a
    view pixel's pair lists). shared: every state focuses at infinity, so each pair's geometry
    and display sample are computed once per view pixel and reused by every state, and a lens
    centre is its hole's axis point moved by t v / 2, so the holes whose lens lies wholly
    inside the pupil are a chord of each row, found without testing them. margin: the largest
    lens radius plus the largest hole displacement (mm), which that chord keeps clear of the
    pupil's edge. next_open: `open_index`'s table; the walk visits only the holes it lists as
    open, so a sparse plate's closed cells cost nothing."""
    channels = stack.shape[3]
    size = box * box
    count = states.shape[0]
    groups = 1 if shared else count
    width = count if shared else 1
    for iy in prange(vy.shape[0]):
        slot = np.empty(size, dtype=np.int64)
        pairs = np.empty((size, 3), dtype=np.int64)
        inputs = np.empty((_INPUTS, size))
        geo = np.empty((CACHE_FIELDS, size))
        samples = np.zeros((size, channels))
        slopes = np.zeros((size, channels))
        evals = np.empty((width, size), dtype=np.int64)
        lengths = np.empty(width, dtype=np.int64)
        spans = np.empty((_SPAN, width))
        chords = np.empty((_CHORD, width), dtype=np.int64)
        acc = np.zeros(channels)
        v_y = vy[iy]
        for ix in range(vx.shape[0]):
            v_x = vx[ix]
            origin_r, origin_c = _origin(geometry, states, v_x, v_y, extra)
            for g in range(groups):
                s0 = 0 if shared else g
                filled = _walk(geometry, states, s0, s0 + width, v_x, v_y, margin, extra, shared,
                               next_open, box, origin_r, origin_c, slot, pairs, evals, lengths,
                               spans, chords)
                _fill(geo, samples, slopes, inputs, stack, radius, geometry, offsets, states, s0,
                      v_x, v_y, shared, pairs, filled)
                for s in range(s0, s0 + width):
                    keep = states[s, 7]
                    pupil_b = states[s, 2]
                    norm = states[s, 6]
                    fx = states[s, 0] + geometry[9] * v_x
                    fy = states[s, 1] + geometry[9] * v_y
                    sums = (0.0, 0.0, 0.0, 0.0)
                    acc[:] = 0.0
                    for e in range(lengths[s - s0]):
                        code = evals[s - s0, e]
                        p = code >> 1
                        area = geo[4, p]
                        if area <= 0.0:
                            continue
                        if code & 1:  # wholly inside the pupil
                            sums = add_weighted(sums, acc, area * norm, samples, p)
                            continue
                        if not shared and (geo[0, p] - fx) ** 2 + (geo[1, p] - fy) ** 2 \
                                >= keep * keep:
                            continue
                        po = math.sqrt((geo[2, p] - fx) ** 2 + (geo[3, p] - fy) ** 2)
                        share, _ = pupil_share(pupil_b, geo[LENS_R, p], po)
                        sums = add_weighted(sums, acc, area * share * norm, samples, p)
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
    count = states.shape[0]
    groups = 1 if shared else count
    width = count if shared else 1
    blocks = grad_radius.shape[0]
    ny = vy.shape[0]
    for b in prange(blocks):
        slot = np.empty(size, dtype=np.int64)
        pairs = np.empty((size, 3), dtype=np.int64)
        inputs = np.empty((_INPUTS, size))
        geo = np.empty((CACHE_FIELDS, size))
        samples = np.zeros((size, channels))
        slopes = np.zeros((size, channels))
        evals = np.empty((width, size), dtype=np.int64)
        lengths = np.empty(width, dtype=np.int64)
        spans = np.empty((_SPAN, width))
        chords = np.empty((_CHORD, width), dtype=np.int64)
        g_sample = np.zeros((size, channels))  # d loss / d sample, summed over states
        g_area = np.zeros(size)  # d loss / d area through the pupil shares
        used = np.zeros(size, dtype=np.bool_)
        for iy in range(b * ny // blocks, (b + 1) * ny // blocks):
            v_y = vy[iy]
            for ix in range(vx.shape[0]):
                v_x = vx[ix]
                origin_r, origin_c = _origin(geometry, states, v_x, v_y, extra)
                for g in range(groups):
                    s0 = 0 if shared else g
                    filled = _walk(geometry, states, s0, s0 + width, v_x, v_y, margin, extra,
                                   shared, next_open, box, origin_r, origin_c, slot, pairs,
                                   evals, lengths, spans, chords)
                    _fill(geo, samples, slopes, inputs, stack, radius, geometry, offsets, states,
                          s0, v_x, v_y, shared, pairs, filled)
                    for s in range(s0, s0 + width):
                        keep = states[s, 7]
                        pupil_b = states[s, 2]
                        norm = states[s, 6]
                        grads = pixel_grads(grad_out, s, iy, ix)
                        fx = states[s, 0] + geometry[9] * v_x
                        fy = states[s, 1] + geometry[9] * v_y
                        for e in range(lengths[s - s0]):
                            code = evals[s - s0, e]
                            p = code >> 1
                            area = geo[4, p]
                            if area <= 0.0:
                                continue
                            if code & 1:  # wholly inside the pupil: share 1
                                g_area[p] += add_gradient(g_sample, grads, grad_out, s, iy, ix,
                                                          area, norm, samples, p) * norm
                                used[p] = True
                                continue
                            if not shared and (geo[0, p] - fx) ** 2 \
                                    + (geo[1, p] - fy) ** 2 >= keep * keep:
                                continue
                            po = math.sqrt((geo[2, p] - fx) ** 2 + (geo[3, p] - fy) ** 2)
                            share, slope = pupil_share(pupil_b, geo[LENS_R, p], po)
                            if slope == 0.0:
                                continue
                            w = area * share * norm
                            g_area[p] += add_gradient(g_sample, grads, grad_out, s, iy, ix, w,
                                                      1.0, samples, p) * slope * norm
                            used[p] = True
                    for p in range(filled):  # every pair the states used, settled once
                        if used[p]:
                            used[p] = False
                            _settle(grad_radius, grad_stack, want_stack, b, geo, samples, slopes,
                                    g_sample, g_area, lscale, pairs[p, 2], p)


#: Rows of the walk's per-state spans (`_span`: centre x, y, outer and inner radius, first and
#: last row) and of a row's chords (outer first and last column, inner first and last).
_SPAN = 6
_CHORD = 4

#: Rows of a view pixel's gathered pair inputs (`_fill`): the undisplaced hole centre x, y,
#: its displacement x, y (mm) and its radius (mm).
_INPUTS = 5


@inline_jit
def _walk(geometry, states, s0, s1, v_x, v_y, margin, extra, shared, next_open, box, origin_r,
          origin_c, slot, pairs, evals, lengths, spans, chords):
    """The pairs states s0 to s1 - 1 reach for one view direction. Each pair once, in walk
    order, as pairs[p] = (row i, column j, hole index k); each state's in
    evals[s - s0, :lengths[s - s0]] as 2 p + 1 when its lens lies wholly inside the pupil,
    else 2 p, row by row. The states' chords of a row come from one SIMD loop (`_row_chords`:
    state by state they cost about a tenth of a 32-state forward). spans (_SPAN, S) and chords
    (_CHORD, S): scratch. Returns the number of pairs."""
    slot[:] = -1
    filled = 0
    n = s1 - s0
    r_lo = 1 << 30
    r_hi = -1
    for s in range(s0, s1):
        fx = states[s, 0] + geometry[9] * v_x
        fy = states[s, 1] + geometry[9] * v_y
        ox, oy, outer, inner, r0, r1 = _span(geometry, fx, fy, v_x, v_y, states[s, 7],
                                             states[s, 2], margin, extra, shared)
        k = s - s0
        spans[0, k] = ox
        spans[1, k] = oy
        spans[2, k] = outer
        spans[3, k] = inner
        spans[4, k] = r0
        spans[5, k] = r1
        lengths[k] = 0
        r_lo = min(r_lo, r0)
        r_hi = max(r_hi, r1)
    for i in range(r_lo, r_hi + 1):
        _row_chords(geometry, spans, n, i, chords)
        for k in range(n):
            if i < spans[4, k] or i > spans[5, k]:
                continue
            c0 = chords[0, k]
            c1 = chords[1, k]
            ci0 = chords[2, k]
            ci1 = chords[3, k]
            length = lengths[k]
            j = c0 - 1
            while j < c1:  # the open holes of columns c0 to c1
                j = next_open[i, j + 1]
                if j > c1:
                    break
                m = (i - origin_r) * box + (j - origin_c)
                p = slot[m]
                if p < 0:
                    p = filled
                    slot[m] = p
                    pairs[p, 0] = i
                    pairs[p, 1] = j
                    pairs[p, 2] = int(i * geometry[0] + j)
                    filled += 1
                evals[k, length] = 2 * p + (1 if ci0 <= j <= ci1 else 0)
                length += 1
            lengths[k] = length
    return filled


@_serial
def _row_chords(geometry, spans, n, i, chords):
    """Columns (first, last) of hole row i within each of n states' spans (`_span`): whose axis
    lies within the outer radius (chords[0:2]) and within the inner one (chords[2:4]; none when
    it is not positive), as `kernel_pair.pair_chord` gives them one by one (empty: 0, -1), in
    one loop LLVM runs in SIMD lanes."""
    ncx = geometry[0]
    dy0 = ((geometry[1] - 1) / 2 - i) * geometry[3]
    mid = (ncx - 1) / 2
    last = ncx - 1
    for k in range(n):
        ox = spans[0, k]
        dy = dy0 - spans[1, k]
        outer = spans[2, k]
        inner = spans[3, k]
        ho = outer * outer - dy * dy
        hi = inner * inner - dy * dy
        so = math.sqrt(max(ho, 0.0))
        si = math.sqrt(max(hi, 0.0))
        a0 = max(0.0, math.ceil((ox - so) / geometry[2] + mid))
        a1 = min(last, math.floor((ox + so) / geometry[2] + mid))
        b0 = max(0.0, math.ceil((ox - si) / geometry[2] + mid))
        b1 = min(last, math.floor((ox + si) / geometry[2] + mid))
        okay = ho > 0.0
        inside = (inner > 0.0) & (hi > 0.0)
        chords[0, k] = int(a0) if okay else 0
        chords[1, k] = int(a1) if okay else -1
        chords[2, k] = int(b0) if inside else 0
        chords[3, k] = int(b1) if inside else -1


@inline_jit
def _fill(geo, samples, slopes, inputs, stack, radius, geometry, offsets, states, s, v_x, v_y,
          shared, pairs, filled):
    """geo[:, p]: pair p's geometry (`pair_geometry`'s values, the lens's equal-area radius and the
    emission weight, as CACHE_FIELDS), and samples[p], slopes[p] its stack sample, for the
    pairs[:filled] of state s (any state when shared). Shared pairs without display optics
    go through `_shared_geometry`, a loop LLVM vectorizes; the others `pair_geometry` one by
    one."""
    if shared and geometry[17] <= 0.0 and geometry[19] <= 0.0:
        cx0 = (geometry[0] - 1) / 2
        cy0 = (geometry[1] - 1) / 2
        for p in range(filled):  # gather the pairs' holes
            k = pairs[p, 2]
            inputs[0, p] = (pairs[p, 1] - cx0) * geometry[2]
            inputs[1, p] = (cy0 - pairs[p, 0]) * geometry[3]
            inputs[2, p] = offsets[k, 0]
            inputs[3, p] = offsets[k, 1]
            inputs[4, p] = radius[k]
        _shared_geometry(inputs, filled, geometry, states[0, 5], v_x, v_y, geo)
    else:
        for p in range(filled):
            bx, by, lx, ly, area, darea, col, row, level, dlevel, emission = pair_geometry(
                radius, geometry, offsets, states, s, v_x, v_y, pairs[p, 0], pairs[p, 1], shared)
            geo[0, p] = bx
            geo[1, p] = by
            geo[2, p] = lx
            geo[3, p] = ly
            geo[4, p] = area
            geo[5, p] = darea
            geo[6, p] = col
            geo[7, p] = row
            geo[8, p] = level
            geo[9, p] = dlevel
            geo[LENS_R, p] = lens_radius(area)
            geo[EMISSION, p] = emission
    for p in range(filled):
        if geo[4, p] > 0.0:
            sample_stack(stack, geo[6, p], geo[7, p], geo[8, p], samples, slopes, p,
                         geo[EMISSION, p])


@_serial
def _shared_geometry(inputs, filled, geometry, level_scale, v_x, v_y, geo):
    """`pair_geometry`'s shared case (every state focused at infinity) without display optics, for
    the gathered pairs inputs[:, :filled] (`_INPUTS`), into geo[:, :filled]: the same
    arithmetic with every branch a selection, so that LLVM runs it in SIMD lanes (8 pairs per
    AVX-512 instruction: about 4 ns a pair against 40 ns by `pair_geometry`)."""
    t = geometry[4]
    chief = geometry[5] > 0
    eye_x = geometry[6]
    eye_y = geometry[7]
    axis = geometry[8]
    gap = geometry[11] - geometry[9]
    half_w = geometry[12]
    half_h = geometry[13]
    pixel_x = geometry[14]
    pixel_y = geometry[15]
    pad = geometry[16]
    offset = geometry[20]
    for p in range(filled):
        hx = inputs[0, p]
        hy = inputs[1, p]
        r1 = inputs[4, p]
        # Chief-ray axes point at the nominal eye from the undisplaced hole.
        ax = (eye_x - hx) / axis if chief else 0.0
        ay = (eye_y - hy) / axis if chief else 0.0
        bx = hx + inputs[2, p] - t / 2 * ax
        by = hy + inputs[3, p] - t / 2 * ay
        dx = t * (ax + v_x)
        dy = t * (ay + v_y)
        # _lens of equal disks: fast_acos of d / 2 r (>= 0) with both of its branches
        # computed and one selected; 0 where the disks miss each other.
        d = math.sqrt(dx * dx + dy * dy)
        far = d >= 2.0 * r1
        half = min(d / (2.0 * r1), 1.0)
        small = half < 0.5
        u = half * half if small else (1.0 - half) * 0.5
        ratio = asin_ratio(u)
        root = math.sqrt(u)
        theta = (math.pi / 2 - (half + half * ratio)) if small else 2.0 * (root + root * ratio)
        area = 0.0 if far else 2.0 * r1 * r1 * theta - d * r1 * math.sqrt(1.0 - half * half)
        darea = 0.0 if far else 4.0 * r1 * theta
        lx = bx + dx / 2
        ly = by + dy / 2
        # _level
        level = 2.0 * level_scale * area - 1.0 - offset
        inside = (level > -1.0) & (level < 1.0)
        # The stores are `_fill`'s written out: through a helper taking the pair as a tuple,
        # LLVM did not vectorize this loop (forward 98.6 against 80.1 ms).
        geo[0, p] = bx
        geo[1, p] = by
        geo[2, p] = lx
        geo[3, p] = ly
        geo[4, p] = area
        geo[5, p] = darea
        geo[6, p] = (lx + gap * v_x + half_w) / pixel_x - 0.5 + pad  # _pixel
        geo[7, p] = (half_h - (ly + gap * v_y)) / pixel_y - 0.5 + pad
        geo[8, p] = min(max(level, -1.0), 1.0)
        geo[9, p] = 2.0 * level_scale * darea if inside else 0.0
        geo[LENS_R, p] = lens_radius(area)
        geo[EMISSION, p] = 1.0


@inline_jit
def _settle(grad_radius, grad_stack, want_stack, b, geo, samples, slopes, g_sample, g_area,
            lscale, k, p):
    """Turn pair p's d loss / d sample and d loss / d area into gradients of its hole's
    radius (hole k) and (want_stack) the stack."""
    gl = 0.0
    for c in range(samples.shape[1]):
        gl += g_sample[p, c] * slopes[p, c]
    grad_radius[b, k] += g_area[p] * geo[5, p] + gl * lscale * geo[9, p]
    if want_stack:
        emission = geo[EMISSION, p]
        if emission != 1.0:  # the sample was the stack's times the emission weight
            for c in range(samples.shape[1]):
                g_sample[p, c] *= emission
        scatter_stack(grad_stack, b, geo[6, p], geo[7, p], geo[8, p], g_sample, p)
    g_area[p] = 0.0
    for c in range(samples.shape[1]):
        g_sample[p, c] = 0.0


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
