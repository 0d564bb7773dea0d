"""Compile the renderer's Numba kernels ahead of their first use.

The kernels (`aperture_fab.optics.kernels`) are compiled on first call, about 30 s per stack
dtype on 2 cores, and cached on disk (Numba's cache: `__pycache__` beside the source, or the
user's cache folder where that is read-only, or NUMBA_CACHE_DIR). `./dev setup` runs this once,
with the mesh re-trace's (`python -m aperture_fab.pipeline.warm`), so a fresh clone's first
design starts optimizing at once.

It renders a tiny plate forward and backward for each precision the optimizer offers, which
compiles (or loads) exactly the signatures a design uses; on a machine with CUDA and Triton,
the GPU kernels as well.
"""

from __future__ import annotations

import time

import torch

__all__ = ["warm_kernels"]

#: A plate, display and view small enough that the warm-up's render costs nothing next to the
#: compile.
_CELLS = 4
_PIXELS = 24
_VIEW = 4


def warm_kernels(dtypes: tuple[torch.dtype, ...] = (torch.float32, torch.float64)) -> float:
    """Compile (or load from the cache) the kernels for each stack dtype; returns seconds.
    Where CUDA and Triton are present, the GPU kernels too (Triton's cache, ~/.triton): an RGB
    and a one-channel (light efficiency) display, forward and backward."""
    from aperture_fab.config.config import resolve
    from aperture_fab.optics.model import Renderer, backend_for
    from aperture_fab.optics.open_view import render_open

    config = resolve("near-eye-nominal", None, {
        "plate.cells": [_CELLS, _CELLS], "display.pixels": [_PIXELS, _PIXELS],
        "display.width_mm": 1.2, "display.height_mm": 1.2, "eye.view_pixels": [_VIEW, _VIEW]})
    where = ["cpu"]
    if torch.cuda.is_available() and backend_for("auto", torch.device("cuda")) == "triton":
        where.append("cuda")
    start = time.perf_counter()
    for device in where:
        for dtype in dtypes:
            renderer = Renderer(config.scene, device=device, dtype=dtype)
            for channels in (3, 1):
                a = torch.full((_CELLS, _CELLS), 0.1, dtype=dtype, device=device,
                               requires_grad=True)
                display = torch.full((channels, _PIXELS, _PIXELS), 0.5, dtype=dtype,
                                     device=device, requires_grad=True)
                renderer.render(a, display).sum().backward()
                if device == "cpu":  # the open display's quadrature (kernel_open)
                    render_open(config.scene, display.detach(), backend="kernel")
    return time.perf_counter() - start

