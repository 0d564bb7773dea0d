"""The open display's view: the fused CPU kernel (kernel_open) against the torch quadrature."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from aperture_fab.config.config import resolve
from aperture_fab.optics.open_view import render_open

#: A small near-eye scene: 60 x 60 display pixels over 12 mm, a 12 x 10 view.
OVERRIDES = {"display.pixels": [60, 60], "display.width_mm": 12.0, "display.height_mm": 12.0,
             "eye.view_pixels": [12, 10]}


def scene():
    return resolve("near-eye", None, OVERRIDES).scene


@pytest.mark.parametrize("channels", [1, 3, 4, 5])
@pytest.mark.parametrize("where", [
    {},
    {"pupil_samples": 16, "subpixels": 3},
    # Off centre, defocused and a wide pupil: samples fall off the display (zeros there).
    {"offset_mm": (2.5, -1.5), "pupil_mm": 6.0, "focus_diopters": 2.0},
    # A pupil of no size: one pupil point.
    {"pupil_mm": 0.0},
])
def test_the_kernel_takes_the_torch_quadrature(channels: int, where: dict) -> None:
    display = torch.as_tensor(np.random.default_rng(channels).random((channels, 60, 60)))
    reference = render_open(scene(), display, backend="torch", **where)
    view = render_open(scene(), display, backend="kernel", **where)
    assert view.dtype == display.dtype and view.shape == (channels, 10, 12)
    torch.testing.assert_close(view, reference, rtol=1e-12, atol=1e-14)


def test_the_kernel_reads_zeros_off_the_display() -> None:
    """An eye off to the side sees past the display's edge: with the display all ones, each
    view pixel is the share of its samples that land on the display, 1 inside, 0 beyond."""
    display = torch.ones(1, 60, 60, dtype=torch.float64)
    view = render_open(scene(), display, offset_mm=(3.0, 0.0), backend="kernel")
    reference = render_open(scene(), display, offset_mm=(3.0, 0.0), backend="torch")
    torch.testing.assert_close(view, reference, rtol=1e-12, atol=1e-14)
    assert float(view.max()) == pytest.approx(1.0)
    assert 0 < float(view.min()) < 0.5


def test_auto_keeps_gradients_and_float32() -> None:
    display = torch.rand(3, 60, 60, requires_grad=True)
    render_open(scene(), display).sum().backward()  # "auto" takes torch for a gradient
    assert display.grad is not None and float(display.grad.abs().sum()) > 0
    view = render_open(scene(), display.detach())
    assert view.dtype == torch.float32
    torch.testing.assert_close(view, render_open(scene(), display.detach(), backend="torch"),
                               rtol=1e-4, atol=1e-6)
