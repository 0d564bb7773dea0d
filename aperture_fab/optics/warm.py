"""Compile the renderer's Numba kernels ahead of their first use.

The kernels (`aperture_fab.optics.kernels`) are compiled on first call, about 30 s per stack
dtype on 2 cores, and cached on disk (Numba's cache: `__pycache__` beside the source, or the
user's cache folder where that is read-only, or NUMBA_CACHE_DIR). `./dev setup` runs this once,
so a fresh clone's first design starts optimizing at once:

    python -m aperture_fab.optics.warm

It renders a tiny plate forward and backward for each precision the optimizer offers, which
compiles (or loads) exactly the signatures a design uses.
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
    """Compile (or load from the cache) the kernels for each stack dtype; returns seconds."""
    from aperture_fab.config.config import resolve
    from aperture_fab.optics.model import Renderer

    config = resolve("near-eye-nominal", None, {
        "plate.cells": [_CELLS, _CELLS], "display.pixels": [_PIXELS, _PIXELS],
        "display.width_mm": 1.2, "display.height_mm": 1.2, "eye.view_pixels": [_VIEW, _VIEW]})
    start = time.perf_counter()
    for dtype in dtypes:
        renderer = Renderer(config.scene, device="cpu", dtype=dtype, backend="kernel")
        a = torch.full((_CELLS, _CELLS), 0.1, dtype=dtype, requires_grad=True)
        display = torch.full((3, _PIXELS, _PIXELS), 0.5, dtype=dtype, requires_grad=True)
        renderer.render(a, display).sum().backward()
    return time.perf_counter() - start


if __name__ == "__main__":
    print(f"aperture-fab: renderer kernels ready ({warm_kernels():.1f} s)")
