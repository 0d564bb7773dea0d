"""The display stack's filter bank (`optics.stack_filter`) against the same convolutions left
to autograd, and its written-out backward against finite differences (float64)."""

from __future__ import annotations

import pytest
import torch
from test_model import make_scene

from aperture_fab.optics.model import Renderer
from aperture_fab.optics.stack_filter import filter_levels, filter_levels_into


def reference_levels(padded: torch.Tensor, kernels: torch.Tensor,
                     fft_shape: tuple[int, int]) -> torch.Tensor:
    """Each level as autograd sees plain torch ops: rfft2, product, irfft2, crop."""
    spectrum = torch.fft.rfft2(padded, s=fft_shape).permute(1, 2, 0).contiguous()
    height, width = padded.shape[1:]
    return torch.stack([torch.fft.irfft2(spectrum * k, s=fft_shape, dim=(0, 1))[:height, :width]
                        for k in kernels])


def case(seed: int, channels: int, kernel_channels: int, dtype: torch.dtype):
    generator = torch.Generator().manual_seed(seed)
    height, width, levels, size = 9, 7, 3, 5
    fft_shape = (height + size - 1, width + size - 1)
    padded = torch.rand(channels, height, width, generator=generator, dtype=dtype)
    kernels = torch.fft.rfft2(torch.rand(levels, size, size, kernel_channels,
                                         generator=generator, dtype=dtype),
                              s=fft_shape, dim=(1, 2))
    return padded, kernels, fft_shape


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize(("channels", "kernel_channels"), [(1, 1), (3, 1), (3, 3)])
def test_matches_autograd_through_plain_ops(seed: int, channels: int, kernel_channels: int):
    padded, kernels, fft_shape = case(seed, channels, kernel_channels, torch.float64)
    mine = padded.clone().requires_grad_(True)
    theirs = padded.clone().requires_grad_(True)
    got = filter_levels(mine, kernels, fft_shape)
    want = reference_levels(theirs, kernels, fft_shape)
    assert got.shape == (kernels.shape[0], *padded.shape[1:], channels)
    assert torch.equal(got, want)  # the same transforms in the same order
    weights = torch.rand(got.shape, generator=torch.Generator().manual_seed(seed + 7),
                         dtype=torch.float64)
    (got * weights).sum().backward()
    (want * weights).sum().backward()
    assert mine.grad is not None and theirs.grad is not None
    torch.testing.assert_close(mine.grad, theirs.grad, rtol=1e-12, atol=1e-12)


def test_gradient_against_finite_differences():
    padded, kernels, fft_shape = case(3, 3, 1, torch.float64)
    assert torch.autograd.gradcheck(lambda p: filter_levels(p, kernels, fft_shape),
                                    (padded.requires_grad_(True),))


def test_into_a_view_writes_only_its_channels():
    padded, kernels, fft_shape = case(4, 3, 1, torch.float32)
    joined = torch.full((kernels.shape[0], *padded.shape[1:], 4), -1.0)
    filter_levels_into(joined[..., :3], padded, kernels, fft_shape)
    assert torch.equal(joined[..., :3], filter_levels(padded, kernels, fft_shape))
    assert torch.all(joined[..., 3] == -1.0)


@pytest.mark.parametrize("oversample", [1, 2])
def test_the_short_transform_wraps_nothing_into_the_stack(oversample: int):
    """`stack_shape`'s transforms are the padded display's length, not that plus the kernel's:
    the same stack as from transforms long enough for a full linear convolution."""
    scene = make_scene(cells=(6, 6), pitch=1.0, pixels=(40, 30), size=12.0)
    renderer = Renderer(scene, dtype=torch.float64, oversample=oversample)
    shape = renderer.shape
    assert shape.fft_height < shape.height + shape.kernel_size - 1
    display = torch.rand(3, 30, 40, generator=torch.Generator().manual_seed(5),
                         dtype=torch.float64)
    short = renderer.display_stack(display)
    wide = Renderer(scene, dtype=torch.float64, oversample=oversample)
    wide._fft_shape = (shape.height + shape.kernel_size - 1,
                       shape.width + shape.kernel_size - 1)
    torch.testing.assert_close(short, wide.display_stack(display), rtol=0, atol=1e-13)
