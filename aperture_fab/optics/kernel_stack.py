"""The display stack in the fused CPU kernels (aperture_fab.optics.kernels), inlined into them: a
pair's trilinear sample of the stack and its adjoint, and a view pixel's sums and gradients over
the channels.

The first UNROLLED_CHANNELS channels are read and summed with constant indices, a view pixel's
sums kept in registers; further channels loop. On the default near-eye plate (8 eye states, 3
channels, 2 cores) this took 12 % off the forward and 10 % off the backward against a loop over
the channels (benchmarks/README.md, "What bounds the CPU kernels").
"""

from __future__ import annotations

import math

from aperture_fab.optics.kernel_pair import inline_jit

__all__ = ["UNROLLED_CHANNELS", "add_gradient", "add_weighted", "pixel_grads", "sample_stack",
           "scatter_stack", "store_sums"]

#: Channels the kernels unroll: RGB, and the white display
#: `Renderer.display_stack(..., with_white=True)` adds.
UNROLLED_CHANNELS = 4


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
def _blend(stack, taps, c):
    """Channel c of a trilinear sample at `taps` (`_taps`): its value and its slope along the
    level axis (per unit level index)."""
    l0, wl, x0, x1, y0, y1, w00, w01, w10, w11 = taps
    lo = (w00 * stack[l0, y0, x0, c] + w01 * stack[l0, y0, x1, c]
          + w10 * stack[l0, y1, x0, c] + w11 * stack[l0, y1, x1, c])
    hi = (w00 * stack[l0 + 1, y0, x0, c] + w01 * stack[l0 + 1, y0, x1, c]
          + w10 * stack[l0 + 1, y1, x0, c] + w11 * stack[l0 + 1, y1, x1, c])
    return lo + wl * (hi - lo), hi - lo


@inline_jit
def _put(samples, slopes, n, c, scale, blended):
    samples[n, c] = scale * blended[0]
    slopes[n, c] = scale * blended[1]


@inline_jit
def sample_stack(stack, col, row, level, samples, slopes, n, scale):
    """Trilinear stack sample into samples[n] (C,) and its slope along the level axis (per unit
    level index) into slopes[n], both times `scale` (the pair's emission weight)."""
    taps = _taps(stack.shape, col, row, level)
    channels = stack.shape[3]
    _put(samples, slopes, n, 0, scale, _blend(stack, taps, 0))
    if channels > 1:  # the first UNROLLED_CHANNELS with constant indices
        _put(samples, slopes, n, 1, scale, _blend(stack, taps, 1))
    if channels > 2:
        _put(samples, slopes, n, 2, scale, _blend(stack, taps, 2))
    if channels > 3:
        _put(samples, slopes, n, 3, scale, _blend(stack, taps, 3))
    for c in range(UNROLLED_CHANNELS, channels):
        _put(samples, slopes, n, c, scale, _blend(stack, taps, c))


@inline_jit
def add_weighted(sums, acc, w, samples, n):
    """A view pixel's channel sums plus w x samples[n]: `sums` holds the first
    UNROLLED_CHANNELS (a tuple, kept in registers), acc[c] the others'."""
    channels = samples.shape[1]
    a0, a1, a2, a3 = sums
    a0 += w * samples[n, 0]
    if channels > 1:
        a1 += w * samples[n, 1]
    if channels > 2:
        a2 += w * samples[n, 2]
    if channels > 3:
        a3 += w * samples[n, 3]
    for c in range(UNROLLED_CHANNELS, channels):
        acc[c] += w * samples[n, c]
    return a0, a1, a2, a3


@inline_jit
def store_sums(out, s, iy, ix, sums, acc):
    """out[s, :, iy, ix] = a view pixel's channel sums (`add_weighted`)."""
    channels = out.shape[1]
    out[s, 0, iy, ix] = sums[0]
    if channels > 1:
        out[s, 1, iy, ix] = sums[1]
    if channels > 2:
        out[s, 2, iy, ix] = sums[2]
    if channels > 3:
        out[s, 3, iy, ix] = sums[3]
    for c in range(UNROLLED_CHANNELS, channels):
        out[s, c, iy, ix] = acc[c]


@inline_jit
def pixel_grads(grad_out, s, iy, ix):
    """The first UNROLLED_CHANNELS of grad_out[s, :, iy, ix] (0 past its channels)."""
    channels = grad_out.shape[1]
    g0 = grad_out[s, 0, iy, ix]
    g1 = grad_out[s, 1, iy, ix] if channels > 1 else 0.0
    g2 = grad_out[s, 2, iy, ix] if channels > 2 else 0.0
    g3 = grad_out[s, 3, iy, ix] if channels > 3 else 0.0
    return g0, g1, g2, g3


@inline_jit
def add_gradient(g_sample, grads, grad_out, s, iy, ix, w, norm, samples, n):
    """g_sample[n] += the view pixel's gradient (`pixel_grads`; further channels read from
    grad_out) x w x norm; returns that gradient's dot product with samples[n]."""
    channels = samples.shape[1]
    g0, g1, g2, g3 = grads
    g_sample[n, 0] += g0 * w * norm
    dot = g0 * samples[n, 0]
    if channels > 1:
        g_sample[n, 1] += g1 * w * norm
        dot += g1 * samples[n, 1]
    if channels > 2:
        g_sample[n, 2] += g2 * w * norm
        dot += g2 * samples[n, 2]
    if channels > 3:
        g_sample[n, 3] += g3 * w * norm
        dot += g3 * samples[n, 3]
    for c in range(UNROLLED_CHANNELS, channels):
        g = grad_out[s, c, iy, ix]
        g_sample[n, c] += g * w * norm
        dot += g * samples[n, c]
    return dot


@inline_jit
def _spread(grad_stack, b, taps, c, g):
    """Adjoint of `_blend`'s value for channel c: add g at its taps of block b."""
    l0, wl, x0, x1, y0, y1, w00, w01, w10, w11 = taps
    lo = (1.0 - wl) * g
    hi = wl * g
    grad_stack[b, l0, y0, x0, c] += w00 * lo
    grad_stack[b, l0, y0, x1, c] += w01 * lo
    grad_stack[b, l0, y1, x0, c] += w10 * lo
    grad_stack[b, l0, y1, x1, c] += w11 * lo
    grad_stack[b, l0 + 1, y0, x0, c] += w00 * hi
    grad_stack[b, l0 + 1, y0, x1, c] += w01 * hi
    grad_stack[b, l0 + 1, y1, x0, c] += w10 * hi
    grad_stack[b, l0 + 1, y1, x1, c] += w11 * hi


@inline_jit
def scatter_stack(grad_stack, b, col, row, level, g, n):
    """Adjoint of `sample_stack` for the stack: add g[n] (C,) at the sample's taps of block b."""
    taps = _taps(grad_stack.shape[1:], col, row, level)
    channels = grad_stack.shape[4]
    _spread(grad_stack, b, taps, 0, g[n, 0])
    if channels > 1:
        _spread(grad_stack, b, taps, 1, g[n, 1])
    if channels > 2:
        _spread(grad_stack, b, taps, 2, g[n, 2])
    if channels > 3:
        _spread(grad_stack, b, taps, 3, g[n, 3])
    for c in range(UNROLLED_CHANNELS, channels):
        _spread(grad_stack, b, taps, c, g[n, c])
