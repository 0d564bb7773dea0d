"""The display stack's filter bank as one autograd function: a padded display pre-filtered
through every level's window kernel by FFT, forward and backward written out.

Every level is the same linear map, a circular convolution by the level's kernel, so the
backward is its adjoint, a correlation: the display's gradient is the inverse transform of
the sum over levels of each level's gradient spectrum times its kernel's conjugate spectrum,
one transform per level and one for the sum. Left to autograd, each level's backward made a
zero-filled copy of the FFT shape, its own product and an accumulation; here the levels'
gradients go through one zero-bordered buffer into one spectrum sum (a 3 mm lattice's 24-level
RGB stack: backward 55 against 73 ms, `benchmarks/bench_stack.py`).
"""

from __future__ import annotations

from typing import Any

import torch

__all__ = ["filter_levels", "filter_levels_into"]


def filter_levels(padded: torch.Tensor, kernels: torch.Tensor,
                  fft_shape: tuple[int, int]) -> torch.Tensor:
    """The levels (L, H, W, C) (channels last: the layout the fused kernels read) of a padded
    display (C, H, W) (real), each circularly convolved over fft_shape = (Hf, Wf) (at least
    (H, W)) with one of `kernels` (L, Hf, Wf // 2 + 1, K) (rfft2 spectra, channels last; K = 1
    or C) and cut to its first H x W samples. Differentiable in `padded` (not in the
    kernels)."""
    return _FilterLevels.apply(padded, kernels, fft_shape)


def filter_levels_into(out: torch.Tensor, padded: torch.Tensor, kernels: torch.Tensor,
                       fft_shape: tuple[int, int]) -> torch.Tensor:
    """`filter_levels` written into out (L, H, W, C), which may be a view (a judged stack's
    first C channels, beside the white display's); not differentiable. Returns out."""
    # Channels last: the inverse transforms over the first two axes then give each level in
    # the kernels' layout at once, and faster than channels first (4.4 against 7.7 ms for a
    # float32 RGB level of 864^2, bit-identical).
    spectrum = torch.fft.rfft2(padded, s=fft_shape).permute(1, 2, 0).contiguous()
    height, width = out.shape[1:3]
    # One level at a time: the product spectrum of every level at once is as large as the
    # stack's inverse transforms, and the batched transform took twice as long.
    for level in range(kernels.shape[0]):
        out[level] = torch.fft.irfft2(spectrum * kernels[level], s=fft_shape,
                                      dim=(0, 1))[:height, :width]
    return out


class _FilterLevels(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, padded: torch.Tensor, kernels: torch.Tensor,
                fft_shape: tuple[int, int]) -> torch.Tensor:
        ctx.save_for_backward(kernels)
        ctx.fft_shape = fft_shape
        levels = padded.new_empty((kernels.shape[0], *padded.shape[1:], padded.shape[0]))
        return filter_levels_into(levels, padded, kernels, fft_shape)

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        (kernels,) = ctx.saved_tensors
        fft_shape = ctx.fft_shape
        height, width = grad.shape[1:3]
        buffer = grad.new_zeros((*fft_shape, grad.shape[-1]))  # its border stays zero
        total = None
        for level in range(kernels.shape[0]):
            buffer[:height, :width] = grad[level]
            term = torch.fft.rfft2(buffer, dim=(0, 1)).mul_(kernels[level].conj())
            total = term if total is None else total.add_(term)
        assert total is not None
        full = torch.fft.irfft2(total.permute(2, 0, 1), s=fft_shape)
        return full[:, :height, :width], None, None
