"""Which block of view pixels per program, and how many warps, run the GPU kernels fastest?
(issue 20)

Run: python benchmarks/probe_gpu_blocks.py [--case near-eye] [--variants 128x4 64x2 ...]

The fused GPU kernels (`aperture_fab.optics.gpu_kernels`) run one lane per (eye state, view
pixel), BLOCK lanes per program on NUM_WARPS warps. For a bench_optimize case (its plate at the
start of a design, its first iteration's eye states and displays), each variant's forward
and backward kernels alone are timed with `triton.testing.do_bench` (median milliseconds), and
its views and gradients compared with the first variant's (they differ only by the order of
the backward's atomic sums). Needs CUDA.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Sequence

import numpy as np
import torch
import triton.testing
from bench_optimize import CASES, case_config

from aperture_fab.io.images import prepare_targets
from aperture_fab.optics import gpu_kernels, gpu_walk
from aperture_fab.optics.fused_views import _gpu_constants, _walk_plan
from aperture_fab.optics.model import Renderer
from aperture_fab.optics.planes import EPS
from aperture_fab.optimize.optimizer import training_states
from aperture_fab.optimize.start import initial_design
from aperture_fab.targets import EXAMPLES

DEVICE = "cuda" if torch.cuda.is_available() else "cpu"  # the CPU only in Triton's interpreter
#: (BLOCK, NUM_WARPS) variants timed by default; the library's first.
VARIANTS = ("32x1", "64x2", "128x4", "256x8")


def _walk(case_name: str) -> tuple[gpu_walk.Walk, torch.Tensor]:
    """The case's walk for its first iteration's states, and a gradient of its views."""
    config = case_config(CASES[case_name], DEVICE, 1)
    scene = config.scene
    renderer = Renderer(scene, device=DEVICE, dtype=torch.float32, backend="triton")
    views, shown = prepare_targets([EXAMPLES[CASES[case_name].target]()],
                                   scene.eye.view_pixels, scene.display.pixels)
    plate, displays = initial_design(scene, views, shown, config.optimizer)
    a = torch.as_tensor(plate, dtype=torch.float64, device=DEVICE).reshape(-1)
    px, py = scene.plate.pitch_mm
    radius = (a * (px * py / np.pi)).add(EPS).sqrt().contiguous()  # as Renderer.render_states
    rows = renderer.state_rows(training_states(scene, config.optimizer, 0))
    stack = renderer.display_stack(torch.as_tensor(displays[0], dtype=torch.float32,
                                                   device=DEVICE))
    _, extra, _, shared, offset_mm, closed = _walk_plan(renderer, radius, rows, True)
    vx, vy, offsets, geometry = _gpu_constants(renderer)
    walk = gpu_walk.Walk(radius, stack[0].permute(1, 2, 3, 0).contiguous(), vx, vy, rows,
                         renderer.kernel_geometry(), geometry, offsets, extra, shared,
                         offset_mm, closed)
    nx, ny = scene.eye.view_pixels
    grad = torch.rand((len(rows), stack.shape[1], ny, nx), dtype=torch.float64, device=DEVICE)
    return walk, grad


def _wall_ms(fn: Callable[[], object]) -> float:
    """One call's wall milliseconds (the interpreter's smoke test: do_bench needs a GPU)."""
    start = time.perf_counter()
    fn()
    return 1e3 * (time.perf_counter() - start)


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--case", choices=list(CASES), default="near-eye")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS))
    args = parser.parse_args(argv)
    if not (torch.cuda.is_available() or gpu_kernels.INTERPRETED):
        raise SystemExit("probe_gpu_blocks needs CUDA (or TRITON_INTERPRET=1 for a smoke test).")
    walk, grad = _walk(args.case)
    print(f"{args.case}: {len(walk.states)} states, shared {walk.shared}, "
          f"{torch.cuda.get_device_name() if DEVICE == 'cuda' else 'interpreter'}")
    first = None
    for variant in args.variants:
        block, warps = (int(v) for v in variant.split("x"))
        gpu_walk.BLOCK, gpu_walk.NUM_WARPS = block, warps
        views = gpu_walk.view_forward(walk)
        grad_radius, grad_stack = gpu_walk.view_backward(walk, grad, True)
        assert grad_stack is not None
        grads = (grad_radius, grad_stack)
        bench = triton.testing.do_bench if DEVICE == "cuda" else _wall_ms
        forward_ms = bench(lambda: gpu_walk.view_forward(walk))
        backward_ms = bench(lambda: gpu_walk.view_backward(walk, grad, True))
        if first is None:
            first = (views, *grads)
        change = max(float((g - f).abs().max() / f.abs().max().clamp_min(1e-300))
                     for g, f in zip((views, *grads), first, strict=True))
        print(f"BLOCK {block:4d} x {warps} warps: forward {forward_ms:7.3f} ms, backward "
              f"{backward_ms:7.3f} ms; largest change against the first {change:.1e}",
              flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
