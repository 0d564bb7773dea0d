"""Fused GPU kernels (Triton) for the view through a plate: the CPU kernels' hole walk on CUDA.

The same model and arithmetic as `aperture_fab.optics.kernels` (its docstring gives the layouts
and the meaning of `states`, `geometry`, `extra`, `margin` and `closed`), written for a GPU: one
lane per (eye state, view pixel), lanes in blocks of adjacent view pixels, each walking the box
of holes its footprint can reach and computing every pair's geometry on the fly. Nothing per pair
is stored, so memory is linear in the plate, the display and the view, never in their product,
and every eye state of an iteration runs in one launch (`aperture_fab.optics.gpu_walk`
launches them).

Forward: one lane per (state, view pixel) writes its view value. Backward: the radius and stack
gradients are sums over pairs, added with atomics (float64). When every state focuses at
infinity (`shared`), a pair's geometry and display sample do not depend on the state, so the
backward walks each view pixel's union of the states' hole windows once and sums the states'
pupil shares per pair before its single scatter into the stack's gradient: the scatter, which
bounds the backward, is paid once per pair instead of once per (state, pair).

Geometry and sums are float64, as on the CPU; the stack is read in its own dtype. Atomic sums
are not bit-reproducible from run to run (the order of the additions varies): GPU results
match the CPU's to rounding, not bit for bit.

CPU-testable form: with TRITON_INTERPRET=1 set before this module is imported, Triton runs the
kernels on CPU tensors in numpy (slowly: small cases only); the interpreter has no libdevice,
so acos and asin come from numpy there. tests/test_gpu_kernels.py compares these kernels with
the CPU kernels that way, and on CUDA where there is one.
"""

from __future__ import annotations

import math
import os
from typing import Any

import numpy as np
import triton
import triton.language as tl
from triton.language.extra import libdevice as _cuda_libdevice

__all__ = ["BLOCK", "INTERPRETED", "NUM_WARPS", "backward_kernel", "forward_kernel"]

#: Triton's interpreter runs the kernels (TRITON_INTERPRET=1, read at import as Triton does).
INTERPRETED = os.environ.get("TRITON_INTERPRET", "0") == "1"
#: View pixels per program (one lane each) and the warps that run them. Small blocks keep a
#: block's lanes walking alike windows: on an H200 (benchmarks/probe_gpu_blocks.py, near-eye,
#: 16 states) 32 x 1 ran the forward and backward in 4.6 + 10.0 ms, 64 x 2 in 4.9 + 11.6 ms,
#: 128 x 4 in 4.9 + 12.1 ms (and, before the boxes were sized per state, 256 x 8 in 7.8 +
#: 14.4 ms).
BLOCK = 32
NUM_WARPS = 1
#: Constants the kernels read (Triton admits only constexpr globals).
_EPS = tl.constexpr(1e-12)
_PI = tl.constexpr(math.pi)


class _NumpyLibdevice:
    """acos and asin for the interpreter, which lowers no libdevice call."""

    @staticmethod
    def _unary(x: Any, fn: Any) -> Any:
        from triton.runtime.interpreter import TensorHandle

        return tl.core.tensor(TensorHandle(fn(x.handle.data), x.handle.dtype.scalar), x.type)

    @staticmethod
    def acos(x: Any) -> Any:
        return _NumpyLibdevice._unary(x, np.arccos)

    @staticmethod
    def asin(x: Any) -> Any:
        return _NumpyLibdevice._unary(x, np.arcsin)


def _interpreted_bound(x: Any) -> int:
    """A loop bound as a Python int under the interpreter, whose scalar arguments are arrays
    of shape (1,) that NumPy 2.4 no longer converts with int()."""
    data = x.handle.data if hasattr(x, "handle") else x
    return int(np.asarray(data).reshape(-1)[0])


@triton.jit
def _compiled_bound(x):
    return x


# The kernels call `libdevice.acos` through this module global, which Triton maps to CUDA's
# libdevice when it compiles them.
libdevice: Any = _NumpyLibdevice() if INTERPRETED else _cuda_libdevice
_bound: Any = _interpreted_bound if INTERPRETED else _compiled_bound


@triton.jit
def _lens_equal(r1, d):
    """`_lens` of two equal disks (infinite focus): one acos."""
    half = tl.minimum(d / (2.0 * r1), 1.0)
    theta = libdevice.acos(half)
    area = 2.0 * r1 * r1 * theta - d * r1 * tl.sqrt(tl.maximum(1.0 - half * half, 0.0))
    apart = d >= 2.0 * r1
    return tl.where(apart, 0.0, area), tl.where(apart, 0.0, 4.0 * r1 * theta)


@triton.jit
def _lens(r1, m, d):
    """Area of two disks (radii r1 and |m| r1, centres d apart) and its derivative in r1."""
    eq_area, eq_darea = _lens_equal(r1, d)
    am = tl.abs(m)
    r2 = am * r1
    small = tl.minimum(r1, r2)
    ds = tl.maximum(d, _EPS)
    c1 = tl.minimum(1.0, tl.maximum(-1.0, (ds * ds + r1 * r1 - r2 * r2) / (2.0 * ds * r1)))
    c2 = tl.minimum(1.0, tl.maximum(-1.0, (ds * ds + r2 * r2 - r1 * r1) / (2.0 * ds * r2)))
    t1 = libdevice.acos(c1)
    t2 = libdevice.acos(c2)
    area = r1 * r1 * t1 + r2 * r2 * t2 - r1 * tl.sin(t1) * ds
    darea = 2.0 * r1 * t1 + 2.0 * am * r2 * t2
    inside = d <= tl.abs(r1 - r2)
    area = tl.where(inside, _PI * small * small, area)
    darea = tl.where(inside, 2.0 * _PI * small * small / r1, darea)
    outside = d >= r1 + r2
    area = tl.where(outside, 0.0, area)
    darea = tl.where(outside, 0.0, darea)
    equal = m == 1.0
    return tl.where(equal, eq_area, area), tl.where(equal, eq_darea, darea)


@triton.jit
def _share(pupil_b, lens_r, po):
    """A lens's share inside the pupil footprint's edge, and d (area x share) / d area."""
    x = (pupil_b - po) / lens_r
    xs = tl.minimum(tl.maximum(x, -1.0), 1.0)
    root = tl.sqrt(tl.maximum(1.0 - xs * xs, 0.0))
    share = 0.5 + (libdevice.asin(xs) + xs * root) / _PI
    slope = share - xs * root / _PI
    share = tl.where(x >= 1.0, 1.0, tl.where(x <= -1.0, 0.0, share))
    slope = tl.where(x >= 1.0, 1.0, tl.where(x <= -1.0, 0.0, slope))
    return share, slope


@triton.jit
def _level(level_scale, offset, area, darea):
    """Stack level coordinate in [-1, 1] of a window of `area` (the stack's lowest level
    `offset` above a window of no area's), and d / d r."""
    level = 2.0 * level_scale * area - 1.0 - offset
    inside = (level < 1.0) & (level > -1.0)
    return tl.minimum(tl.maximum(level, -1.0), 1.0), tl.where(inside, 2.0 * level_scale * darea,
                                                              0.0)


@triton.jit
def _display_optics(geom_ptr, wx, wy, sx, sy):
    """Cover glass shift and cos^k emission weight at a chief ray of slope (sx, sy)."""
    t_g = tl.load(geom_ptr + 17)
    n_glass = tl.load(geom_ptr + 18)
    power = tl.load(geom_ptr + 19)
    tan2 = sx * sx + sy * sy
    n2 = n_glass * n_glass
    loss = tl.where(t_g > 0.0, t_g * (1.0 - 1.0 / tl.sqrt(n2 + (n2 - 1.0) * tan2)), 0.0)
    emission = tl.where(power > 0.0, tl.exp(-power / 2.0 * tl.log(1.0 + tan2)), 1.0)
    return wx - loss * sx, wy - loss * sy, emission


@triton.jit
def _pair(geom_ptr, r, hx, hy, ax, ay, vx, vy, cx, cy, m, mu, level_scale,
          SHARED: tl.constexpr, OPTICS: tl.constexpr):
    """A (view direction, hole) pair for one eye state: bottom-face centre, lens centre, area,
    d area / d r, equal-area lens radius, stack column, row, level, d level / d r, emission
    (as `aperture_fab.optics.kernel_pair.pair_geometry`)."""
    t = tl.load(geom_ptr + 4)
    s_b = tl.load(geom_ptr + 9)
    s_t = tl.load(geom_ptr + 10)
    s_d = tl.load(geom_ptr + 11)
    bx = hx - t / 2.0 * ax
    by = hy - t / 2.0 * ay
    gap = s_d - s_b
    if SHARED:
        # The top-face disk seen along v lands t (a + v) away from the bottom one.
        dx = t * (ax + vx)
        dy = t * (ay + vy)
        area, darea = _lens_equal(r, tl.sqrt(dx * dx + dy * dy))
        lx = bx + dx / 2.0
        ly = by + dy / 2.0
        wx = lx + gap * vx
        wy = ly + gap * vy
        sx = vx
        sy = vy
    else:
        fx = cx + s_b * vx
        fy = cy + s_b * vy
        ctx = fx + m * (hx + t / 2.0 * ax - cx - s_t * vx)
        cty = fy + m * (hy + t / 2.0 * ay - cy - s_t * vy)
        area, darea = _lens(r, m, tl.sqrt((ctx - bx) * (ctx - bx) + (cty - by) * (cty - by)))
        lx = (bx + ctx) / 2.0
        ly = (by + cty) / 2.0
        wx = cx + s_d * vx + mu * (lx - fx)
        wy = cy + s_d * vy + mu * (ly - fy)
        sx = (wx - lx) / gap
        sy = (wy - ly) / gap
    emission = tl.full(wx.shape, 1.0, tl.float64)
    if OPTICS:
        wx, wy, emission = _display_optics(geom_ptr, wx, wy, sx, sy)
    col = (wx + tl.load(geom_ptr + 12)) / tl.load(geom_ptr + 14) - 0.5 + tl.load(geom_ptr + 16)
    row = (tl.load(geom_ptr + 13) - wy) / tl.load(geom_ptr + 15) - 0.5 + tl.load(geom_ptr + 16)
    level, dlevel = _level(level_scale, tl.load(geom_ptr + 20), area, darea)
    lens_r = tl.sqrt(tl.maximum(area / _PI, _EPS))
    return bx, by, lx, ly, area, darea, lens_r, col, row, level, dlevel, emission


@triton.jit
def _hole(geom_ptr, offsets_ptr, i, j, ok):
    """Hole (i, j) (int rows, columns; masked by ok): flat index, undisplaced axis point x, y
    at mid-thickness, the displaced one, and the axis slope ax, ay (chief-ray axes from the
    undisplaced hole)."""
    ncx = tl.load(geom_ptr + 0)
    ncy = tl.load(geom_ptr + 1)
    hx = (j.to(tl.float64) - (ncx - 1.0) / 2.0) * tl.load(geom_ptr + 2)
    hy = ((ncy - 1.0) / 2.0 - i.to(tl.float64)) * tl.load(geom_ptr + 3)
    chief = tl.load(geom_ptr + 5) > 0.0
    axis = tl.load(geom_ptr + 8)
    ax = tl.where(chief, (tl.load(geom_ptr + 6) - hx) / axis, 0.0)
    ay = tl.where(chief, (tl.load(geom_ptr + 7) - hy) / axis, 0.0)
    k = tl.where(ok, i * ncx.to(tl.int32) + j, 0)
    dx = tl.load(offsets_ptr + 2 * k, mask=ok, other=0.0)
    dy = tl.load(offsets_ptr + 2 * k + 1, mask=ok, other=0.0)
    return k, hx, hy, hx + dx, hy + dy, ax, ay


@triton.jit
def _taps(col, row, level, L, H, W):
    """Trilinear taps: level l0 and its weight toward l0 + 1, the clamped corners' flat
    offsets (l0 level; add H W for l0 + 1) and the four corner weights (0 off the stack)."""
    lf = (level + 1.0) * (L - 1) / 2.0
    l0 = tl.minimum(lf.to(tl.int32), L - 2)
    wl = lf - l0.to(tl.float64)
    xf = tl.floor(col)
    yf = tl.floor(row)
    wx = col - xf
    wy = row - yf
    x0 = xf.to(tl.int32)
    y0 = yf.to(tl.int32)
    ax0 = tl.where((x0 >= 0) & (x0 < W), 1.0 - wx, 0.0)
    ax1 = tl.where((x0 + 1 >= 0) & (x0 + 1 < W), wx, 0.0)
    ay0 = tl.where((y0 >= 0) & (y0 < H), 1.0 - wy, 0.0)
    ay1 = tl.where((y0 + 1 >= 0) & (y0 + 1 < H), wy, 0.0)
    x0c = tl.minimum(tl.maximum(x0, 0), W - 1)
    x1c = tl.minimum(tl.maximum(x0 + 1, 0), W - 1)
    y0c = tl.minimum(tl.maximum(y0, 0), H - 1)
    y1c = tl.minimum(tl.maximum(y0 + 1, 0), H - 1)
    base = l0.to(tl.int64) * H * W
    o00 = base + (y0c * W + x0c).to(tl.int64)
    o01 = base + (y0c * W + x1c).to(tl.int64)
    o10 = base + (y1c * W + x0c).to(tl.int64)
    o11 = base + (y1c * W + x1c).to(tl.int64)
    return wl, o00, o01, o10, o11, ay0 * ax0, ay0 * ax1, ay1 * ax0, ay1 * ax1


@triton.jit
def _corner(k: tl.constexpr, o00, o01, o10, o11, w00, w01, w10, w11):
    """Corner k (0 to 3, unrolled) of `_taps`: its offset and weight."""
    if k == 0:
        off, w = o00, w00
    elif k == 1:
        off, w = o01, w01
    elif k == 2:
        off, w = o10, w10
    else:
        off, w = o11, w11
    return off, w


@triton.jit
def _sample(stack_ptr, col, row, level, ok, L, H, W, C: tl.constexpr, CP: tl.constexpr):
    """Trilinear stack sample (BLOCK, CP) float64 and its slope along the level index."""
    wl, o00, o01, o10, o11, w00, w01, w10, w11 = _taps(col, row, level, L, H, W)
    cs = tl.arange(0, CP)
    mask = ok[:, None] & (cs < C)[None, :]
    plane = H.to(tl.int64) * W
    lo = tl.zeros(mask.shape, tl.float64)
    hi = tl.zeros(mask.shape, tl.float64)
    for corner in tl.static_range(4):
        off, w = _corner(corner, o00, o01, o10, o11, w00, w01, w10, w11)
        ptr = stack_ptr + off[:, None] * C + cs[None, :]
        lo += w[:, None] * tl.load(ptr, mask=mask, other=0.0).to(tl.float64)
        hi += w[:, None] * tl.load(ptr + plane * C, mask=mask, other=0.0).to(tl.float64)
    return lo + wl[:, None] * (hi - lo), hi - lo


@triton.jit
def _scatter(grad_ptr, col, row, level, g, ok, L, H, W, C: tl.constexpr, CP: tl.constexpr):
    """Adjoint of `_sample`: add g (BLOCK, CP) at the sample's taps."""
    wl, o00, o01, o10, o11, w00, w01, w10, w11 = _taps(col, row, level, L, H, W)
    cs = tl.arange(0, CP)
    mask = ok[:, None] & (cs < C)[None, :]
    plane = H.to(tl.int64) * W
    g_lo = (1.0 - wl)[:, None] * g
    g_hi = wl[:, None] * g
    for corner in tl.static_range(4):
        off, w = _corner(corner, o00, o01, o10, o11, w00, w01, w10, w11)
        ptr = grad_ptr + off[:, None] * C + cs[None, :]
        tl.atomic_add(ptr, w[:, None] * g_lo, mask=mask, sem="relaxed")
        tl.atomic_add(ptr + plane * C, w[:, None] * g_hi, mask=mask, sem="relaxed")


@triton.jit
def _span(geom_ptr, states_ptr, s, vx, vy, margin, extra, SHARED: tl.constexpr):
    """Where state s's pairs lie for view directions (vx, vy): footprint centre fx, fy; the
    centre ox, oy and radius of the disk of hole axes to walk (as the CPU kernels' `_span`)."""
    t = tl.load(geom_ptr + 4)
    s_b = tl.load(geom_ptr + 9)
    row = states_ptr + s * 8
    fx = tl.load(row + 0) + s_b * vx
    fy = tl.load(row + 1) + s_b * vy
    if SHARED:
        ox = fx - t * vx / 2.0
        oy = fy - t * vy / 2.0
        outer = tl.load(row + 2) + margin + 0.0 * vx
    else:
        ox = fx
        oy = fy
        outer = tl.load(row + 7) + extra + 0.0 * vx
    return fx, fy, ox, oy, outer


@triton.jit
def _origin(geom_ptr, ox, oy, outer):
    """First row and column (int32) of the box of holes around a disk (centre ox, oy)."""
    ncx = tl.load(geom_ptr + 0)
    ncy = tl.load(geom_ptr + 1)
    r0 = tl.ceil((ncy - 1.0) / 2.0 - (oy + outer) / tl.load(geom_ptr + 3))
    c0 = tl.ceil((ox - outer) / tl.load(geom_ptr + 2) + (ncx - 1.0) / 2.0)
    return r0.to(tl.int32), c0.to(tl.int32)


@triton.jit
def _state_box(geom_ptr, states_ptr, s, margin, extra, SHARED: tl.constexpr):
    """Holes per axis (rows, columns; int32) of the box around state s's walk disk (`_span`'s
    radius: the pupil footprint and the margin when shared, else the keep radius and the
    search's extra), from `_origin`: the disk spans 2 outer / pitch of them, and 2 more of
    slack."""
    row = states_ptr + s * 8
    if SHARED:
        outer = tl.load(row + 2) + margin
    else:
        outer = tl.load(row + 7) + extra
    rows = tl.floor(2.0 * outer / tl.load(geom_ptr + 3)).to(tl.int32) + 2
    cols = tl.floor(2.0 * outer / tl.load(geom_ptr + 2)).to(tl.int32) + 2
    return rows, cols


@triton.jit
def _in_plate(geom_ptr, i, j, live):
    ncx = tl.load(geom_ptr + 0).to(tl.int32)
    ncy = tl.load(geom_ptr + 1).to(tl.int32)
    return live & (i >= 0) & (i < ncy) & (j >= 0) & (j < ncx)


@triton.jit
def _open_hole(geom_ptr, offsets_ptr, radius_ptr, i, j, live, closed):
    """Hole (i, j) of each lane: whether it is on the plate and open (radius above `closed`),
    its flat index and radius, and `_hole`'s axis points and slopes."""
    ok = _in_plate(geom_ptr, i, j, live)
    k, ux, uy, hx, hy, ax, ay = _hole(geom_ptr, offsets_ptr, i, j, ok)
    r = tl.load(radius_ptr + k, mask=ok, other=1.0)
    return ok & (r > closed), k, r, ux, uy, hx, hy, ax, ay


@triton.jit
def _any(mask):
    """Whether any lane of the block has `mask`: a branch on it skips work no lane uses (the
    lanes of a block are adjacent view pixels, whose windows lie alike in their boxes)."""
    return tl.max(mask.to(tl.int32), axis=0) > 0


@triton.jit
def _lanes(vx_ptr, vy_ptr, nx, ny, BLOCK: tl.constexpr):
    p = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = p < nx * ny
    ix = p % nx
    iy = p // nx
    vx = tl.load(vx_ptr + ix, mask=live, other=0.0)
    vy = tl.load(vy_ptr + iy, mask=live, other=0.0)
    return live, ix, iy, vx, vy


#: Integer arguments that Triton would otherwise compile a variant for when they equal 1.
_SIZES = ["nx", "ny", "L", "H", "W"]


@triton.jit(do_not_specialize=_SIZES)
def forward_kernel(radius_ptr, offsets_ptr, stack_ptr, vx_ptr, vy_ptr, states_ptr, geom_ptr,
                    margin_ptr, out_ptr, extra, closed, nx, ny, L, H, W,
                    C: tl.constexpr, CP: tl.constexpr, BLOCK: tl.constexpr,
                    SHARED: tl.constexpr, OPTICS: tl.constexpr):
    """out[s, c, iy, ix] for state s = program_id(1) and a block of view pixels. margin_ptr:
    the walk's margin (mm), read on the device, so the host never waits for the plate; each
    state walks the box of its own disk."""
    s = tl.program_id(1)
    margin = tl.load(margin_ptr)
    box_r, box_c = _state_box(geom_ptr, states_ptr, s, margin, extra, SHARED)
    live, ix, iy, vx, vy = _lanes(vx_ptr, vy_ptr, nx, ny, BLOCK)
    row = states_ptr + s * 8
    cx = tl.load(row + 0)
    cy = tl.load(row + 1)
    pupil_b = tl.load(row + 2)
    m = tl.load(row + 3)
    mu = tl.load(row + 4)
    level_scale = tl.load(row + 5)
    norm = tl.load(row + 6)
    keep = tl.load(row + 7)
    fx, fy, ox, oy, outer = _span(geom_ptr, states_ptr, s, vx, vy, margin, extra, SHARED)
    r_start, c_start = _origin(geom_ptr, ox, oy, outer)
    acc = tl.zeros((BLOCK, CP), tl.float64)
    for dr in range(0, _bound(box_r)):
        i = r_start + dr
        for dc in range(0, _bound(box_c)):
            j = c_start + dc
            ok, _, r, ux, uy, hx, hy, ax, ay = _open_hole(geom_ptr, offsets_ptr, radius_ptr,
                                                          i, j, live, closed)
            # The walk's disk, around the undisplaced axis (as the CPU kernels' chords).
            ok = ok & ((ux - ox) * (ux - ox) + (uy - oy) * (uy - oy) <= outer * outer)
            if _any(ok):  # the box's corners, closed holes
                # Names, not `_`: a value a Triton branch assigns keeps one type.
                bx, by, lx, ly, area, _darea, lens_r, col, rw, level, _dlevel, emission = _pair(
                    geom_ptr, r, hx, hy, ax, ay, vx, vy, cx, cy, m, mu, level_scale, SHARED,
                    OPTICS)
                if not SHARED:
                    ok = ok & ((bx - fx) * (bx - fx) + (by - fy) * (by - fy) < keep * keep)
                ok = ok & (area > 0.0)
                po = tl.sqrt((lx - fx) * (lx - fx) + (ly - fy) * (ly - fy))
                share, _slope = _share(pupil_b, lens_r, po)
                w = tl.where(ok, area * share * norm * emission, 0.0)
                value, _level_slope = _sample(stack_ptr, col, rw, level, ok & (w != 0.0), L, H,
                                              W, C, CP)
                acc += w[:, None] * value
    cs = tl.arange(0, CP)
    out = out_ptr + ((s * C + cs[None, :]) * ny + iy[:, None]) * nx + ix[:, None]
    tl.store(out, acc, mask=live[:, None] & (cs < C)[None, :])


@triton.jit(do_not_specialize=[*_SIZES, "n_states"])
def backward_kernel(radius_ptr, offsets_ptr, stack_ptr, vx_ptr, vy_ptr, states_ptr, geom_ptr,
                     margin_ptr, alive_ptr, grad_out_ptr, grad_radius_ptr, grad_stack_ptr,
                     extra, closed, nx, ny, L, H, W, n_states,
                     C: tl.constexpr, CP: tl.constexpr, BLOCK: tl.constexpr,
                     SHARED: tl.constexpr, OPTICS: tl.constexpr, WANT_STACK: tl.constexpr):
    """Gradients of sum(grad_out * view) into grad_radius (K,) and grad_stack (L, H, W, C).

    Not shared: program_id(1) is the state, walked as in the forward. Shared: program_id(1) is
    0 and each lane walks the union of all states' windows, summing the states' shares per
    pair before one scatter. alive_ptr: (S,) int32, 0 for a state whose views get no gradient
    (a tail loss's best ones): its pairs are not walked (read on the device: no host wait)."""
    live, ix, iy, vx, vy = _lanes(vx_ptr, vy_ptr, nx, ny, BLOCK)
    cs = tl.arange(0, CP)
    cmask = live[:, None] & (cs < C)[None, :]
    lscale = (L - 1) / 2.0
    margin = tl.load(margin_ptr)
    if SHARED:
        s_first = 0
        s_last = n_states
    else:
        s_first = tl.program_id(1)
        s_last = s_first + 1
    # The box: from the smallest origin over the lane's live states to the farthest end of
    # their boxes, as many holes as the block's widest needs (a loop bound is the block's).
    r_start = tl.full((BLOCK,), 1 << 29, tl.int32)
    c_start = tl.full((BLOCK,), 1 << 29, tl.int32)
    r_end = tl.full((BLOCK,), -(1 << 29), tl.int32)
    c_end = tl.full((BLOCK,), -(1 << 29), tl.int32)
    for s in range(_bound(s_first), _bound(s_last)):
        alive = tl.load(alive_ptr + s) != 0
        _, _, ox, oy, outer = _span(geom_ptr, states_ptr, s, vx, vy, margin, extra, SHARED)
        r0, c0 = _origin(geom_ptr, ox, oy, outer)
        rows, cols = _state_box(geom_ptr, states_ptr, s, margin, extra, SHARED)
        r_start = tl.where(alive, tl.minimum(r_start, r0), r_start)
        c_start = tl.where(alive, tl.minimum(c_start, c0), c_start)
        r_end = tl.where(alive, tl.maximum(r_end, r0 + rows), r_end)
        c_end = tl.where(alive, tl.maximum(c_end, c0 + cols), c_end)
    box_r = tl.maximum(tl.max(tl.where(live, r_end - r_start, 0), axis=0), 0)
    box_c = tl.maximum(tl.max(tl.where(live, c_end - c_start, 0), axis=0), 0)
    row0 = states_ptr + s_first * 8
    m = tl.load(row0 + 3)
    mu = tl.load(row0 + 4)
    level_scale = tl.load(row0 + 5)
    for dr in range(0, _bound(box_r)):
        i = r_start + dr
        for dc in range(0, _bound(box_c)):
            j = c_start + dc
            ok, k, r, ux, uy, hx, hy, ax, ay = _open_hole(geom_ptr, offsets_ptr, radius_ptr,
                                                          i, j, live, closed)
            # Whether some state's disk holds the hole: the union box's corners hold none.
            inside = tl.zeros((BLOCK,), tl.int1)
            for s in range(_bound(s_first), _bound(s_last)):
                _, _, ox, oy, outer = _span(geom_ptr, states_ptr, s, vx, vy, margin, extra,
                                            SHARED)
                inside = inside | ((tl.load(alive_ptr + s) != 0)
                                   & ((ux - ox) * (ux - ox) + (uy - oy) * (uy - oy)
                                      <= outer * outer))
            ok = ok & inside
            if _any(ok):
                # Shared: the pair does not depend on the state (cx, cy unused).
                bx, by, lx, ly, area, darea, lens_r, col, rw, level, dlevel, emission = _pair(
                    geom_ptr, r, hx, hy, ax, ay, vx, vy, tl.load(row0 + 0), tl.load(row0 + 1),
                    m, mu, level_scale, SHARED, OPTICS)
                ok = ok & (area > 0.0)
                # Per state: the weight's and the pupil share's coefficients on the sample.
                g_w = tl.zeros((BLOCK, CP), tl.float64)  # sum_s g_s area share_s norm_s
                g_a = tl.zeros((BLOCK, CP), tl.float64)  # sum_s g_s slope_s norm_s
                for s in range(_bound(s_first), _bound(s_last)):
                    fx, fy, ox, oy, outer = _span(geom_ptr, states_ptr, s, vx, vy, margin,
                                                  extra, SHARED)
                    srow = states_ptr + s * 8
                    seen = ok & ((ux - ox) * (ux - ox) + (uy - oy) * (uy - oy) <= outer * outer)
                    seen = seen & (tl.load(alive_ptr + s) != 0)
                    if not SHARED:
                        keep = tl.load(srow + 7)
                        seen = seen & ((bx - fx) * (bx - fx) + (by - fy) * (by - fy)
                                       < keep * keep)
                    if _any(seen):  # in a shared walk, most states see few of the union's holes
                        po = tl.sqrt((lx - fx) * (lx - fx) + (ly - fy) * (ly - fy))
                        share, slope = _share(tl.load(srow + 2), lens_r, po)
                        norm = tl.load(srow + 6)
                        g = tl.load(grad_out_ptr + ((s * C + cs[None, :]) * ny + iy[:, None]) * nx
                                    + ix[:, None], mask=cmask & seen[:, None], other=0.0)
                        g_w += g * tl.where(seen, area * share * norm, 0.0)[:, None]
                        g_a += g * tl.where(seen, slope * norm, 0.0)[:, None]
                used = ok & (tl.sum(tl.abs(g_w) + tl.abs(g_a), axis=1) != 0.0)
                if _any(used):
                    value, level_slope = _sample(stack_ptr, col, rw, level, used, L, H, W, C, CP)
                    # The sample read is the stack's times the emission weight.
                    value = value * emission[:, None]
                    level_slope = level_slope * emission[:, None]
                    g_area = tl.sum(g_a * value, axis=1)
                    g_level = tl.sum(g_w * level_slope, axis=1)
                    tl.atomic_add(grad_radius_ptr + k, g_area * darea + g_level * lscale * dlevel,
                                  mask=used, sem="relaxed")
                    if WANT_STACK:
                        _scatter(grad_stack_ptr, col, rw, level, g_w * emission[:, None], used,
                                 L, H, W, C, CP)


