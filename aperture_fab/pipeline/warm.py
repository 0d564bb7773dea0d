"""Compile every Numba kernel a design job uses ahead of its first use.

Numba compiles a kernel on its first call and caches it on disk (`__pycache__` beside the
source, the user's cache folder where that is read-only, or NUMBA_CACHE_DIR). Uncompiled, a
fresh clone's first design waits about a minute for the renderer's kernels before it optimizes
and another minute for the mesh re-trace's (measured on 2 cores). `./dev setup` runs this once:

    python -m aperture_fab.pipeline.warm

It renders a tiny plate forward and backward (`aperture_fab.optics.warm`) and traces a tiny
written part for each hole axis, which compiles (or loads) exactly the signatures a design uses.
"""

from __future__ import annotations

import time

import numpy as np

from aperture_fab.optics.warm import warm_kernels

__all__ = ["warm_retrace", "warm_all"]

#: A part small enough that tracing it costs nothing next to the compile: cells per side,
#: display pixels per side and view pixels per side.
_CELLS = 4
_PIXELS = 24
_VIEW = 4
_DISPLAY_MM = 1.2
#: Each cell's open fraction: a hole every process of the default preset makes.
_OPEN_FRACTION = 0.3


def warm_retrace() -> float:
    """Compile (or load) the mesh re-trace's kernels: trace a tiny part, read back from its
    STL as the design job traces it, for each hole axis (straight and tilted holes take
    different paths). Returns seconds."""
    from aperture_fab.config.config import resolve
    from aperture_fab.fabrication.part import make_part
    from aperture_fab.io.formats import read_stl, stl_bytes
    from aperture_fab.optics.scene import HOLE_AXES
    from aperture_fab.validation.retrace import trace_mesh_view

    start = time.perf_counter()
    for axis in HOLE_AXES:
        config = resolve("near-eye-nominal", None, {
            "plate.cells": [_CELLS, _CELLS], "plate.hole_axis": axis,
            "display.pixels": [_PIXELS, _PIXELS], "display.width_mm": _DISPLAY_MM,
            "display.height_mm": _DISPLAY_MM, "eye.view_pixels": [_VIEW, _VIEW]})
        scene = config.scene
        part = make_part(np.full((_CELLS, _CELLS), _OPEN_FRACTION), scene, config.fabrication)
        display = np.full((3, _PIXELS, _PIXELS), 0.5)
        trace_mesh_view(read_stl(stl_bytes(part.mesh)), scene, display)
    return time.perf_counter() - start


def warm_all() -> dict[str, float]:
    """Compile every kernel: seconds per group ("renderer", "re-trace")."""
    return {"renderer": warm_kernels(), "re-trace": warm_retrace()}


if __name__ == "__main__":
    seconds = warm_all()
    print("aperture-fab: kernels ready ("
          + ", ".join(f"{name} {s:.1f} s" for name, s in seconds.items()) + ")")
