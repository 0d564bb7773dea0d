"""The warm-up (`python -m aperture_fab.pipeline.warm`, run by `./dev setup`) compiles every
Numba signature a design job uses: after it, rendering and re-tracing plates of other sizes,
both hole axes, compile nothing more."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

# Runs in a fresh interpreter: a dispatcher's signatures are those compiled or loaded from the
# disk cache in this process, so earlier tests cannot have filled them.
_PROBE = r"""
import json, sys
import numpy as np, torch
from numba.core.registry import CPUDispatcher
from aperture_fab.pipeline.warm import warm_all

def signatures():
    out = {}
    for name, module in list(sys.modules.items()):
        if not name.startswith("aperture_fab."):
            continue
        for attr, value in vars(module).items():
            if isinstance(value, CPUDispatcher):
                out[f"{name}.{attr}"] = sorted(str(s) for s in value.signatures)
    return out

seconds = warm_all()
warmed = signatures()

from aperture_fab.config.config import resolve
from aperture_fab.fabrication.part import make_part
from aperture_fab.io.formats import read_stl, stl_bytes
from aperture_fab.optics.model import Renderer
from aperture_fab.validation.retrace import trace_mesh_view

for axis in ("straight", "chief_ray"):
    config = resolve("near-eye-nominal", None, {
        "plate.cells": [12, 12], "plate.hole_axis": axis, "display.pixels": [60, 60],
        "display.width_mm": 3.0, "display.height_mm": 3.0, "eye.view_pixels": [10, 10]})
    scene = config.scene
    rng = np.random.default_rng(0)
    fraction = rng.uniform(0.05, 0.5, (12, 12)) * (rng.random((12, 12)) < 0.5)
    part = make_part(fraction, scene, config.fabrication)
    trace_mesh_view(read_stl(stl_bytes(part.mesh)), scene, rng.random((3, 60, 60)))
    for dtype in (torch.float32, torch.float64):
        renderer = Renderer(scene, dtype=dtype)
        a = torch.full((12, 12), 0.2, dtype=dtype, requires_grad=True)
        display = torch.rand((3, 60, 60), dtype=dtype, requires_grad=True)
        renderer.render(a, display).sum().backward()
        with torch.no_grad():
            renderer.render(a, display)
print(json.dumps({"seconds": seconds, "warmed": warmed, "after": signatures()}))
"""


@pytest.mark.slow
def test_the_warm_up_compiles_every_signature_a_design_uses() -> None:
    done = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True,
                          check=True, timeout=900)
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert set(result["seconds"]) == {"renderer", "re-trace"}
    warmed, after = result["warmed"], result["after"]
    # The warm-up reached both groups of kernels ...
    assert any(name.startswith("aperture_fab.optics.kernels") and sigs
               for name, sigs in warmed.items())
    assert any(name.startswith("aperture_fab.validation.retrace") and sigs
               for name, sigs in warmed.items())
    # ... and what came after it compiled nothing new.
    new = {name: sorted(set(sigs) - set(warmed.get(name, [])))
           for name, sigs in after.items() if set(sigs) - set(warmed.get(name, []))}
    assert not new, f"compiled after the warm-up: {new}"
