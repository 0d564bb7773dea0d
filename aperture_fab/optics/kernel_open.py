"""The open display's pupil quadrature as a fused CPU kernel (Numba).

`aperture_fab.optics.open_view.render_open` averages, for each view pixel, the display's
bilinear interpolation over `subpixels`^2 points of the pixel times a sunflower of pupil
points. Its torch form builds each view row's sample grid and calls `grid_sample` (the
reference, and the path for CUDA and for gradients); this kernel takes the same samples without
building them: it was 2.75 s of a `validate`'s 20 (by cProfile; 44 views, about 100 eye
states). The arithmetic is torch's `grid_sample` (bilinear, zeros outside,
align_corners=False) in float64, summed in float64: the two agree to rounding
(tests/test_open_view.py).
"""

from __future__ import annotations

import math

from numba import njit, prange

__all__ = ["LANES", "open_quadrature"]


#: The renderer's fast-math flags (kernel_pair.FAST_MATH: NaN and infinity kept), written out
#: here because Numba's cache of this kernel sees only this file.
FAST_MATH = {"nsz", "arcp", "contract", "reassoc"}
#: Channels per kernel call: the display is padded (or split) to this many, so that a view
#: pixel's sums stay in registers (a tap's channels are adjacent).
LANES = 4


@njit(cache=True, error_model="numpy", fastmath=FAST_MATH, inline="always")
def _bilinear(display, row, col, c, weights):
    """Channel c of the display between pixel (row, col) and its three neighbours toward +1,
    with the corners' weights (w00, w01, w10, w11)."""
    w00, w01, w10, w11 = weights
    return (w00 * display[row, col, c] + w01 * display[row, col + 1, c]
            + w10 * display[row + 1, col, c] + w11 * display[row + 1, col + 1, c])


@njit(cache=True, error_model="numpy", fastmath=FAST_MATH, parallel=True)
def open_quadrature(display, fx, fy, px, py, out):
    """Fill out (LANES, ny, nx) float64 with the mean of the display's bilinear samples.

    display: (H, W, LANES) float64 channel values, channels last. fx: (nx, s) float64, each
    view column's sub-column centres on the display without the pupil offset, in display
    pixels from the first pixel's centre (grid_sample's unnormalized x); fy: (ny, s) the same
    for rows. px, py: (n,) the pupil points' offsets, in display pixels. Sample (i, j, k) of
    view pixel (r, c) reads the display at (fx[c, i] + px[k], fy[r, j] + py[k]); outside the
    display it reads 0.
    """
    height, width = display.shape[0], display.shape[1]
    nx, subs = fx.shape
    ny = fy.shape[0]
    count = px.shape[0]
    scale = 1.0 / (subs * subs * count)
    for r in prange(ny):
        for c in range(nx):
            a0 = a1 = a2 = a3 = 0.0
            for j in range(subs):
                for i in range(subs):
                    for k in range(count):
                        x = fx[c, i] + px[k]
                        y = fy[r, j] + py[k]
                        col, row = math.floor(x), math.floor(y)
                        wx, wy = x - col, y - row
                        if 0 <= col < width - 1 and 0 <= row < height - 1:
                            w00 = (1.0 - wx) * (1.0 - wy)
                            w01 = wx * (1.0 - wy)
                            w10 = (1.0 - wx) * wy
                            w11 = wx * wy
                            weights = (w00, w01, w10, w11)
                            a0 += _bilinear(display, row, col, 0, weights)
                            a1 += _bilinear(display, row, col, 1, weights)
                            a2 += _bilinear(display, row, col, 2, weights)
                            a3 += _bilinear(display, row, col, 3, weights)
                            continue
                        # At the edge: only the taps on the display (zeros padding).
                        for dy in range(2):
                            yy = row + dy
                            if yy < 0 or yy >= height:
                                continue
                            weight_y = wy if dy else 1.0 - wy
                            for dx in range(2):
                                xx = col + dx
                                if xx < 0 or xx >= width:
                                    continue
                                weight = weight_y * (wx if dx else 1.0 - wx)
                                a0 += weight * display[yy, xx, 0]
                                a1 += weight * display[yy, xx, 1]
                                a2 += weight * display[yy, xx, 2]
                                a3 += weight * display[yy, xx, 3]
            out[0, r, c] = a0 * scale
            out[1, r, c] = a1 * scale
            out[2, r, c] = a2 * scale
            out[3, r, c] = a3 * scale
