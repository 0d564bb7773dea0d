"""Speed, profile and peak memory of the optimizer (aperture_fab.optimize.optimizer.optimize).

Run: .venv/bin/python benchmarks/bench_optimize.py [--device auto|cpu|cuda] [--repeats 3]
     [--quick] [--large] [--json PATH]

Cases (each repeat in a fresh child process, so peak memory belongs to that case alone; the
repeats of all cases run round-robin, so that a change in the machine's load falls on every case
alike and the ratios between cases stay fair):

- seed-28: the `seed` preset (28 x 28 cells, the dissertation's scene), target digit-3,
  300 iterations: seconds per design (each child makes one untimed 1-iteration run first:
  thread pools, lazy kernel loading, allocator).
- seed-100: the seed scene with 100 x 100 cells and display pixels (view stays 28 x 28),
  600 iterations: seconds per design, likewise.
- near-eye: the `near-eye` preset on issue 20's plate (80 x 80 cells of 0.25 mm, the preset's
  until 2026-11-29; it now has 40 x 40 of 0.5 mm), 128 x 128 view, RGB, display content
  optimized, its eye distribution, with STATES = 16 eye states drawn afresh per iteration
  (issue 9's figure, whatever the preset's own count), renderer backend "auto" (the fused CPU
  kernels on a CPU), target natural: seconds per iteration.
- near-eye-1: near-eye with one eye state drawn per iteration (a random pupil position, size and
  focus: the kernels' per-state path).
- nominal: the `near-eye-nominal` preset (near-eye at its one nominal eye state, the behaviour
  before eye distributions; issue 20's plate), backend "auto": the single-state iteration.
- nominal-torch: the same with backend "torch": the previous code path (pair tables and
  grid_sample, which is what ran before the CPU kernels and is still the CUDA path), the
  reference the single-state and 16-state goals are measured against, side by side in this run.
- large (--large only, meant for a GPU): the nominal eye with 512 x 512 cells at 0.05 mm on a
  25.6 mm, 1024 x 1024 pixel display, 512 x 512 view: seconds per iteration (3 after 1
  warm-up). A case whose estimated memory (`aperture_fab.optimize.budget`) is over the budget is
  refused before any work and reported as such (the refusal message in the table).

Every timed run is one `optimize` call without checkpoints; each iteration is timed from the
start of its loss to the start of the next one (the GPU synchronized at each stamp), so an
iteration case runs one iteration more than it times. (Stamps in a checkpoint callback, less
an estimate of a checkpoint's cost, read 0 s per iteration for the nominal case on an H200,
the estimate as long as an iteration, and called its goal met.) Per iteration, the loss's
forward and backward are timed separately: `optimize`'s `_design_loss` is wrapped (in the
child only) to stamp the forward, and identity autograd nodes on its output and on its plate
and display inputs stamp the start and the end of the backward; the renderer kernels
(`aperture_fab.optics.kernels.view_forward` / `view_backward`) are timed on
their own too. The rest of an iteration (Adam step, drawing eye states) is the remainder. The
backend of a case is forced by handing `optimize` a Renderer with that backend (patched in the
child). s/iter: the median over the repeats of the iterations after the warm-up ones (the first
builds the pair table on the torch path).

Bytes read per iteration (kernel path), the model: the kernel reads a stack sample for P
(view pixel, hole) pairs per pass (counted in numpy by a mirror of the kernels' hole walk and
area test, `kernel_pairs`, for the eye states of the first timed iteration and the initial
plate: the sum over the states, or, when every state focuses at infinity, the pairs of the
union, which the states share; it also counts the (state, pair) evaluations, the arithmetic),
and each sample is trilinear: 8 taps x C channels x the stack's element size. Forward: P x 8 x
C x isz read, the views S x C x N x 8 (float64) written. Backward: the same samples read again,
the views' gradient (S x C x N x 8) read, and, when the display is optimized, the scatter of
each pair's gradient into the per-thread grad stacks (8 x C x isz read and written per pair)
and their sum (B x stack bytes read). Per target. Achieved GB/s = bytes read / kernel seconds
(forward + backward kernels); beside it the machine's copy bandwidth measured at the start of
the run (numpy copy, one thread, and torch copy_, all threads; STREAM "copy" counts read +
written bytes). The stack (a few MB) mostly stays in cache, so the kernel can beat the memory
copy; a kernel far below it is bound by arithmetic, not memory.

Peak memory: the increase of the child's peak RSS (VmHWM, reset before the case; ru_maxrss
where /proc is absent) over its RSS before the case, and on CUDA torch.cuda.max_memory_allocated;
beside it the estimate of `aperture_fab.optimize.budget.estimate_bytes` for the case.
--quick runs a few iterations (the smoke test), with the near-eye cases at a 32 x 32 view; a
quick design is extended to the nominal iteration count at its per-iteration rate.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal
from unittest import mock

import numpy as np
import torch

import aperture_fab.optimize.optimizer as optimize_module
from aperture_fab.config.config import Config, resolve
from aperture_fab.io.images import prepare_targets, resample
from aperture_fab.optics import kernels
from aperture_fab.optics.device import resolve_device
from aperture_fab.optics.eyes import EyeStates, distribution_of
from aperture_fab.optics.fused_views import MAX_GRAD_BLOCKS_BYTES
from aperture_fab.optics.model import Backend, Renderer, backend_for
from aperture_fab.optimize import budget
from aperture_fab.optimize.optimizer import optimize, training_states
from aperture_fab.optimize.start import initial_design
from aperture_fab.targets import EXAMPLES

DEVICES = ("auto", "cpu", "cuda")
#: Backends whose fused kernels are timed on their own (CPU kernels, GPU kernels).
FUSED = ("kernel", "triton")
#: ru_maxrss is in KiB on Linux and in bytes on macOS.
RSS_UNIT_BYTES = 1 if sys.platform == "darwin" else 1024
MIB = 2**20
GB = 1e9
#: The dissertation's odak-based code (UCL MSc, 2022): 33 s for a 300-epoch 28 x 28 design
#: (about 0.10 s per iteration), 36 min for 600 epochs at 100 x 100 (about 3.6 s per iteration).
REFERENCE_SEED_28_S = 33.0
REFERENCE_SEED_100_S = 36 * 60.0
#: Goals: a seed design in under 1.5 s, a 100 x 100 design in under 20 s, a single-state
#: near-eye iteration in under 0.2 s.
GOAL_SEED_28_S = 1.5
GOAL_SEED_100_S = 20.0
GOAL_NEAR_EYE_ITERATION_S = 0.2
#: Issue 9's goals, against the reference (the torch path, single state, in the same run):
#: a single-state iteration at least this many times faster ...
GOAL_SINGLE_SPEEDUP = 3.0
#: ... and a 16-state iteration at most this many times the reference's single-state one.
GOAL_STATES_RATIO = 2.0
#: Issue 20's goals on one GPU (H100/H200), per case: seconds per iteration (near-eye with 16
#: states, nominal, large) or per design (seed-28, 300 iterations); large also within
#: GOAL_GPU_LARGE_GB of GPU memory.
GOAL_GPU_S = {"near-eye": 0.005, "nominal": 0.001, "seed-28": 0.3, "large": 0.5}
GOAL_GPU_LARGE_GB = 16.0
#: Eye states per iteration of the near-eye case (the goal's figure).
STATES = 16
REFERENCE_CASE = "nominal-torch"
SINGLE_CASE = "nominal"
STATES_CASE = "near-eye"
#: The near-eye cases' plate: issue 20's table was measured on it (the near-eye preset's until
#: 2026-11-29), so the figures stay comparable.
DENSE_PLATE = {"plate.cells": [80, 80], "plate.pitch_mm": [0.25, 0.25]}
#: View of the near-eye cases under --quick (a smoke test, not figures).
QUICK_VIEW = [32, 32]
#: Copy-bandwidth arrays (MiB each) for the STREAM-like copy; smaller under --quick.
COPY_MIB, QUICK_COPY_MIB = 512, 64


@dataclass(frozen=True)
class Case:
    """One benchmark scene.

    metric: "design" (seconds for a whole design of `iterations` iterations, median of repeats)
        or "iteration" (median seconds per iteration of `iterations` iterations after `warmup`
        ones, over the repeats).
    quick_iterations, quick_warmup: the same under --quick.
    goal_s, reference_s: the goal and the dissertation's figure in the case's metric (None: none).
    backend: the renderer backend `optimize` is handed ("auto": its own choice).
    """

    name: str
    description: str
    preset: str
    target: str
    metric: Literal["design", "iteration"]
    iterations: int
    quick_iterations: int
    goal_s: float | None
    reference_s: float | None
    overrides: Mapping[str, Any] = field(default_factory=dict)
    warmup: int = 0
    quick_warmup: int = 0
    backend: Backend = "auto"

    def __post_init__(self) -> None:
        least = 2 if self.metric == "design" else 1  # a design needs a steady-state interval
        if min(self.iterations, self.quick_iterations) < least:
            raise ValueError(f"case {self.name}: iterations = {self.iterations} and "
                             f"quick_iterations = {self.quick_iterations} must be >= {least}.")
        if self.metric == "iteration" and min(self.warmup, self.quick_warmup) < 1:
            raise ValueError(f"case {self.name}: warmup = {self.warmup} and quick_warmup = "
                             f"{self.quick_warmup} must be >= 1: the first iteration builds the "
                             "pair table.")


CASES: dict[str, Case] = {
    case.name: case
    for case in (
        Case("seed-28", "seed preset, 28 x 28 cells, 28 x 28 view", "seed", "digit-3", "design",
             iterations=300, quick_iterations=10, goal_s=GOAL_SEED_28_S,
             reference_s=REFERENCE_SEED_28_S),
        Case("seed-100", "seed scene, 100 x 100 cells and display pixels, 28 x 28 view", "seed",
             "digit-3", "design", iterations=600, quick_iterations=5, goal_s=GOAL_SEED_100_S,
             reference_s=REFERENCE_SEED_100_S,
             overrides={"plate.cells": [100, 100], "plate.pitch_mm": [0.1, 0.15],
                        "display.pixels": [100, 100]}),
        Case("near-eye", "near-eye preset, 80 x 80 cells, 128 x 128 view, RGB, 16 eye states",
             "near-eye", "natural", "iteration", iterations=3, quick_iterations=1, warmup=1,
             quick_warmup=1, goal_s=None, reference_s=None,
             overrides={**DENSE_PLATE, "optimizer.eye_states": STATES}),
        Case("near-eye-1", "near-eye, 1 eye state drawn per iteration", "near-eye", "natural",
             "iteration", iterations=6, quick_iterations=1, warmup=1, quick_warmup=1,
             goal_s=None, reference_s=None, overrides={**DENSE_PLATE, "optimizer.eye_states": 1}),
        Case(SINGLE_CASE, "near-eye-nominal preset (1 nominal state)", "near-eye-nominal",
             "natural", "iteration", iterations=8, quick_iterations=1, warmup=2, quick_warmup=1,
             goal_s=GOAL_NEAR_EYE_ITERATION_S, reference_s=None, overrides=DENSE_PLATE),
        Case(REFERENCE_CASE, "near-eye-nominal, backend torch (the previous code path)",
             "near-eye-nominal", "natural", "iteration", iterations=8, quick_iterations=1,
             warmup=2, quick_warmup=1, goal_s=None, reference_s=None, backend="torch",
             overrides=DENSE_PLATE),
        # The near-eye optics (gap, eye) at a finer scale: 50 um cells (holes that small need a
        # photo-etched foil, hence 0.1 mm thick), a 25 um pixel (~1000 ppi) display as wide as
        # the plate, and a 512 x 512 view; the nominal eye (one state), as before eye
        # distributions.
        Case("large", "512 x 512 cells at 0.05 mm, 1024^2 px 25.6 mm display, 512^2 view",
             "near-eye-nominal", "natural", "iteration", iterations=3, quick_iterations=1,
             warmup=1, quick_warmup=1, goal_s=None, reference_s=None,
             overrides={"plate.cells": [512, 512], "plate.pitch_mm": [0.05, 0.05],
                        "plate.thickness_mm": 0.1, "display.width_mm": 25.6,
                        "display.height_mm": 25.6, "display.pixels": [1024, 1024],
                        "eye.view_pixels": [512, 512]}),
    )
}
DEFAULT_CASES = ("seed-28", "seed-100", STATES_CASE, "near-eye-1", SINGLE_CASE, REFERENCE_CASE)


def case_config(case: Case, device: str, iterations: int, quick: bool = False) -> Config:
    """The case's resolved config: every iteration runs (no plateau stop). quick: the near-eye
    cases at QUICK_VIEW."""
    small = ({"eye.view_pixels": QUICK_VIEW}
             if quick and case.preset.startswith("near-eye") and case.name != "large" else {})
    return resolve(case.preset, None, {
        **case.overrides,
        **small,
        "optimizer.device": device,
        "optimizer.iterations": iterations,
        "optimizer.plateau_patience": 0,
    })


# -- memory ---------------------------------------------------------------------------------------


def _proc_status(key: str) -> int | None:
    """A /proc/self/status figure in bytes (VmRSS, VmHWM), None without /proc."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) * 1024
    except OSError:
        return None
    return None


def _reset_peak_rss() -> bool:
    """Reset the peak RSS (VmHWM) to the current RSS (Linux); whether that worked."""
    try:
        with open("/proc/self/clear_refs", "w") as refs:
            refs.write("5")
        return True
    except OSError:
        return False


def _peak_rss_bytes() -> int:
    peak = _proc_status("VmHWM")
    if peak is not None:
        return peak
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * RSS_UNIT_BYTES


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def copy_bandwidth(mib: int, repeats: int = 5) -> dict[str, float]:
    """STREAM-like copy bandwidth (GB/s, read + written bytes, median of `repeats`) of a
    float64 array of `mib` MiB: numpy (one thread) and torch copy_ (all threads)."""
    n = mib * MIB // 8
    src = np.ones(n)
    dst = np.empty_like(src)
    np.copyto(dst, src)  # touch the pages
    numpy_s = []
    for _ in range(repeats):
        start = time.perf_counter()
        np.copyto(dst, src)
        numpy_s.append(time.perf_counter() - start)
    a, b = torch.from_numpy(src), torch.from_numpy(dst)
    torch_s = []
    for _ in range(repeats):
        start = time.perf_counter()
        b.copy_(a)
        torch_s.append(time.perf_counter() - start)
    moved = 2 * n * 8
    return {"array_mib": float(mib), "numpy_gbs": moved / statistics.median(numpy_s) / GB,
            "torch_gbs": moved / statistics.median(torch_s) / GB,
            "threads": float(torch.get_num_threads())}


# -- the kernel path's pairs and bytes ----------------------------------------------------------


def kernel_pairs(renderer: Renderer, open_fraction: np.ndarray, states: EyeStates,
                 chunk: int = 1024) -> tuple[int, int]:
    """(samples, evaluations): the (view pixel, hole) pairs for which the CPU kernel reads a
    stack sample in one pass over `states`, and the (state, view pixel, hole) triples it
    evaluates (a pupil share and a weighted sum each). Both count the holes of the kernel's
    walk (`aperture_fab.optics.kernels._span`, mirrored here: at infinite focus the hole axes within
    R_b + margin of the footprint centre moved by -t v / 2, margin the largest hole radius;
    otherwise within keep + extra of the footprint centre; per row a chord) whose lens has area
    (open_fraction: (rows, cols)). Samples are per state, or, when every state focuses at
    infinity (the states share them), those of the union over the states. Hole offsets are not
    modelled (none here)."""
    scene = renderer.scene
    plate, eye = scene.plate, scene.eye
    ncx, ncy = plate.cells
    px, py = plate.pitch_mm
    t = plate.thickness_mm
    chief = plate.hole_axis == "chief_ray"
    ex, ey = eye.positions_mm[0]
    axis = eye.eye_relief_mm + t / 2
    s_b, s_t = scene.plate_distance_mm, eye.eye_relief_mm
    radius = np.sqrt(np.clip(open_fraction, 0, None).reshape(-1) * (px * py / math.pi) + 1e-12)
    margin = float(radius.max())
    rows = renderer.state_rows(states)
    extra = renderer.search_extra_mm
    shared = bool(np.all(rows[:, 3] == 1.0) and np.all(rows[:, 4] == 1.0))
    vx, vy = eye.view_directions()
    gy, gx = np.meshgrid(vy, vx, indexing="ij")
    views_x, views_y = gx.ravel(), gy.ravel()
    samples = evaluations = 0
    for start in range(0, views_x.size, chunk):
        v_x = views_x[start:start + chunk, None, None]
        v_y = views_y[start:start + chunk, None, None]
        union = np.zeros((v_x.shape[0], ncx * ncy), dtype=bool) if shared else None
        for cx, cy, pupil_b, m, _, _, _, keep in rows:
            fx, fy = cx + s_b * v_x, cy + s_b * v_y
            if shared:
                ox, oy, outer = fx - t * v_x / 2, fy - t * v_y / 2, pupil_b + margin
            else:
                ox, oy, outer = fx, fy, keep + extra
            span = math.floor(2 * outer / min(px, py)) + 2
            steps = np.arange(span)
            i = np.ceil((ncy - 1) / 2 - (oy + outer) / py).astype(np.int64) + steps[:, None]
            j = np.ceil((ox - outer) / px + (ncx - 1) / 2).astype(np.int64) + steps[None, :]
            hx = (j - (ncx - 1) / 2) * px
            hy = ((ncy - 1) / 2 - i) * py
            dy2 = (hy - oy) ** 2
            walked = ((i >= 0) & (i < ncy) & (j >= 0) & (j < ncx) & (dy2 < outer * outer)
                      & ((hx - ox) ** 2 + dy2 <= outer * outer))
            ax = (ex - hx) / axis if chief else np.zeros_like(hx)
            ay = (ey - hy) / axis if chief else np.zeros_like(hy)
            k = np.clip(i, 0, ncy - 1) * ncx + np.clip(j, 0, ncx - 1)
            r = radius[k]
            if shared:
                lit = walked & (t * np.hypot(ax + v_x, ay + v_y) < 2 * r)
            else:
                bx, by = hx - t / 2 * ax, hy - t / 2 * ay
                ctx = fx + m * (hx + t / 2 * ax - cx - s_t * v_x)
                cty = fy + m * (hy + t / 2 * ay - cy - s_t * v_y)
                lit = walked & (np.hypot(ctx - bx, cty - by) < r * (1 + abs(m)))
            count = int(lit.sum())
            evaluations += count
            if union is not None:
                view = np.broadcast_to(np.arange(v_x.shape[0])[:, None, None], lit.shape)
                union[view[lit], k[lit]] = True
            else:
                samples += count
        if union is not None:
            samples += int(union.sum())
    return samples, evaluations


def kernel_bytes(pairs: int, states: int, channels: int, views: int, itemsize: int,
                 stack_bytes: int, blocks: int, targets: int, display_optimized: bool
                 ) -> dict[str, int]:
    """The kernel path's bytes per iteration (the model of the module docstring)."""
    sample = 8 * channels * itemsize
    forward_read = pairs * sample
    forward_written = states * channels * views * 8
    backward_read = pairs * sample + states * channels * views * 8
    backward_written = 0
    if display_optimized:
        backward_read += pairs * sample + blocks * stack_bytes
        backward_written += pairs * sample + stack_bytes
    return {"forward_read": targets * forward_read,
            "forward_written": targets * forward_written,
            "backward_read": targets * backward_read,
            "backward_written": targets * backward_written,
            "read": targets * (forward_read + backward_read)}


# -- timing ---------------------------------------------------------------------------------------


class _Mark(torch.autograd.Function):
    """Identity whose backward stamps the time into a list (the loss: backward start; the
    loss's inputs: backward end)."""

    @staticmethod
    def forward(ctx: Any, x: torch.Tensor, stamps: list[float], device: torch.device
                ) -> torch.Tensor:
        ctx.stamps, ctx.device = stamps, device
        return x.clone()

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor, None, None]:
        _sync(ctx.device)
        ctx.stamps.append(time.perf_counter())
        return grad, None, None


class _Profile:
    """Per iteration: when its loss started, forward seconds, backward seconds of the loss,
    and the kernel's."""

    def __init__(self, device: torch.device) -> None:
        self.device = device
        self.loss_starts: list[float] = []
        self.forward: list[float] = []
        self.starts: list[list[float]] = []
        self.ends: list[list[float]] = []
        self.kernel_forward: list[float] = []
        self.kernel_backward: list[float] = []

    def design_loss(self, original: Callable[..., torch.Tensor]) -> Callable[..., torch.Tensor]:
        def timed(renderer: Renderer, a: torch.Tensor, displays: torch.Tensor,
                  *args: Any, **kwargs: Any) -> torch.Tensor:
            start_list: list[float] = []
            end_list: list[float] = []
            self.starts.append(start_list)
            self.ends.append(end_list)
            self.kernel_forward.append(0.0)
            self.kernel_backward.append(0.0)
            _sync(self.device)
            start = time.perf_counter()
            self.loss_starts.append(start)
            if a.requires_grad:
                a = _Mark.apply(a, end_list, self.device)
            if displays.requires_grad:
                displays = _Mark.apply(displays, end_list, self.device)
            loss = original(renderer, a, displays, *args, **kwargs)
            _sync(self.device)
            self.forward.append(time.perf_counter() - start)
            return _Mark.apply(loss, start_list, self.device)
        return timed

    def kernel(self, original: Callable[..., Any], into: str) -> Callable[..., Any]:
        def timed(*args: Any) -> Any:
            _sync(self.device)
            start = time.perf_counter()
            result = original(*args)
            _sync(self.device)
            seconds = getattr(self, into)
            if seconds:  # inside a timed loss
                seconds[-1] += time.perf_counter() - start
            return result
        return timed

    def backward(self) -> list[float]:
        return [max(end) - start[0] if start and end else math.nan
                for start, end in zip(self.starts, self.ends, strict=True)]


def _timed_optimize(config: Config, views: np.ndarray, shown: np.ndarray, device: torch.device,
                    backend: str) -> tuple[float, list[float], _Profile]:
    """Seconds of one optimize call, seconds of each of its iterations but the last (from its
    loss's start to the next one's), and the per-iteration profile."""
    profile = _Profile(device)
    renderer = functools.partial(Renderer, backend=backend)
    fused: Any = kernels
    if backend == "triton":
        from aperture_fab.optics import gpu_walk as fused
    with mock.patch.object(optimize_module, "Renderer", renderer), \
            mock.patch.object(optimize_module, "_design_loss",
                              profile.design_loss(optimize_module._design_loss)), \
            mock.patch.object(fused, "view_forward",
                              profile.kernel(fused.view_forward, "kernel_forward")), \
            mock.patch.object(fused, "view_backward",
                              profile.kernel(fused.view_backward, "kernel_backward")):
        start = time.perf_counter()
        optimize(config.scene, views, shown, config.optimizer, progress=False)
        _sync(device)
        total = time.perf_counter() - start
    return total, np.diff(profile.loss_starts).tolist(), profile


def _backend_of(case: Case, device: torch.device) -> str:
    return backend_for(case.backend, device)


def measure(case: Case, device_name: str, quick: bool, count_pairs: bool) -> dict[str, Any]:
    """Run one repeat of a case in this process; its raw figures (see the module docstring)."""
    device = resolve_device(device_name)
    backend = _backend_of(case, device)
    iterations = case.quick_iterations if quick else case.iterations
    warmup = case.quick_warmup if quick else case.warmup
    # An iteration case runs one iteration more: the last timed one ends when its next starts.
    extra = 1 if case.metric == "iteration" else 0
    config = case_config(case, str(device), warmup + iterations + extra, quick)
    scene, settings = config.scene, config.optimizer
    dtype = torch.float64 if settings.precision == "float64" else torch.float32
    views, shown = prepare_targets([EXAMPLES[case.target]()], config.scene.eye.view_pixels,
                                   config.scene.display.pixels)
    states = training_states(scene, settings, warmup)
    estimate = budget.estimate(scene, len(states), backend,
                               settings.precision, channels=views.shape[1],
                               targets=views.shape[0],
                               display_optimized=settings.display == "optimized",
                               fresh_states=not distribution_of(scene.eye).is_point)
    raw: dict[str, Any] = {
        "case": case.name, "device": str(device), "backend": backend,
        "threads": torch.get_num_threads(), "kernel_threads": kernels.thread_count(),
        "states": len(states), "channels": int(views.shape[1]),
        "view_pixels": list(scene.eye.view_pixels), "iterations": iterations, "warmup": warmup,
        "estimate_bytes": estimate.peak,
        "estimate_terms": estimate.terms,
    }
    if device.type == "cuda" and backend == "kernel":
        return {**raw, "skipped": "the kernel backend runs on the CPU only"}
    try:
        budget.check_budget(scene, settings, views.shape, device=device)  # as optimize does
        limit, why = budget.default_budget(device)
        if estimate.peak > limit:  # a backend other than optimize's own choice
            raise ValueError(f"the {backend} renderer would need about {estimate.peak / GB:.1f} "
                             f"GB per iteration, more than the budget of {limit / GB:.1f} GB "
                             f"({why}).")
    except ValueError as refusal:
        return {**raw, "refused": str(refusal)}
    # Untimed, before the memory baseline: thread pools, lazy kernel loading (Numba's compiled
    # kernels, LLVM), allocator. A design: one iteration of it; an iteration case: one on an
    # 8 x 8 view (its warm-up iterations then warm the rest).
    warm = config if case.metric == "design" else case_config(case, str(device), 1, quick)
    if case.metric != "design":
        warm = dataclasses.replace(warm, scene=dataclasses.replace(
            scene, eye=dataclasses.replace(scene.eye, view_pixels=(8, 8))))
    warm_views = views if case.metric == "design" else resample(
        EXAMPLES[case.target]()[:views.shape[1]], (8, 8))[None]
    with mock.patch.object(optimize_module, "Renderer",
                           functools.partial(Renderer, backend=backend)):
        optimize(warm.scene, warm_views, shown,
                 dataclasses.replace(warm.optimizer, iterations=1), progress=False)
    rss_before = _proc_status("VmRSS") if _reset_peak_rss() else None
    if rss_before is None:
        rss_before = _peak_rss_bytes()
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    total, intervals, profile = _timed_optimize(config, views, shown, device, backend)
    peak_rss = _peak_rss_bytes() - rss_before
    cuda_peak = torch.cuda.max_memory_allocated(device) if device.type == "cuda" else None
    start = time.perf_counter()  # warm setup, after a run
    renderer = Renderer(scene, device=device, dtype=dtype, backend=backend)
    table_pairs = None
    if backend == "torch":
        table_pairs = sum(renderer.pair_count(p) for p in range(len(scene.eye.positions_mm)))
    _sync(device)
    setup_s = time.perf_counter() - start
    # Skip the warm-up iterations (a design: the first iteration).
    skip = max(warmup, 1)
    steps = intervals[skip:]
    timed = slice(skip, skip + len(steps))
    forward, backward = profile.forward[timed], profile.backward()[timed]
    raw.update({
        "design_s": total,
        "steps": steps,
        "other": [s - f - b for s, f, b in zip(steps, forward, backward, strict=True)],
        "forward": forward,
        "backward": backward,
        "kernel_forward": profile.kernel_forward[timed],
        "kernel_backward": profile.kernel_backward[timed],
        "setup_s": setup_s,
        "peak_rss_bytes": peak_rss,
        "cuda_peak_bytes": cuda_peak,
        "table_pairs": table_pairs,
    })
    if count_pairs and backend == "kernel":
        a0, _ = initial_design(scene, views, shown, settings)
        pairs, evaluations = kernel_pairs(renderer, a0, states)
        raw["evaluations"] = evaluations
        shape = renderer.shape
        isz = torch.empty((), dtype=dtype).element_size()
        stack = raw["channels"] * shape.levels * shape.height * shape.width * isz
        ny = scene.eye.view_pixels[1]
        blocks = max(1, min(ny, kernels.thread_count(), MAX_GRAD_BLOCKS_BYTES // max(1, stack)))
        raw["pairs"] = pairs
        raw["bytes"] = kernel_bytes(pairs, len(states), raw["channels"],
                                    scene.eye.view_pixels[0] * ny, isz, stack, blocks,
                                    int(views.shape[0]), settings.display == "optimized")
    return raw


def _median(values: Sequence[float]) -> float | None:
    finite = [v for v in values if math.isfinite(v)]
    return statistics.median(finite) if finite else None


def summarize(case: Case, raws: Sequence[Mapping[str, Any]], quick: bool) -> dict[str, Any]:
    """One case's figures from its repeats (each a child's raw figures)."""
    first = raws[0]
    base = {"case": case.name, "description": case.description, "metric": case.metric,
            "device": first["device"], "backend": first["backend"],
            "threads": first["threads"], "kernel_threads": first["kernel_threads"],
            "states": first["states"], "view_pixels": first["view_pixels"],
            "repeats": len(raws), "iterations": first["iterations"],
            "warmup": first["warmup"], "nominal_iterations": case.iterations,
            "goal_s": case.goal_s, "reference_s": case.reference_s,
            "estimate_mib": first["estimate_bytes"] / MIB,
            "estimate_terms_mib": {k: v / MIB for k, v in first["estimate_terms"].items()}}
    for reason in ("refused", "skipped"):
        if reason in first:
            return {**base, reason: first[reason]}
    steps = [s for r in raws for s in r["steps"]]
    iteration_s = statistics.median(steps)
    totals = [r["design_s"] for r in raws]
    if case.metric == "design":
        design_s = statistics.median(totals)
        # A short (--quick) run extended to the nominal count at the steady-state rate.
        measured_s = design_s + (case.iterations - first["iterations"]) * iteration_s
    else:
        design_s = None
        measured_s = iteration_s
    forward_s = _median([s for r in raws for s in r["forward"]])
    backward_s = _median([s for r in raws for s in r["backward"]])
    other_s = _median([s for r in raws for s in r["other"]])
    kernel_fwd = _median([s for r in raws for s in r["kernel_forward"]])
    kernel_bwd = _median([s for r in raws for s in r["kernel_backward"]])
    counted = next((r for r in raws if "pairs" in r), None)
    pairs = counted["pairs"] if counted else first["table_pairs"]
    evaluations = counted["evaluations"] if counted else None
    bytes_model = counted["bytes"] if counted else None
    kernel_s = (kernel_fwd or 0.0) + (kernel_bwd or 0.0)
    achieved = (bytes_model["read"] / kernel_s / GB if bytes_model and kernel_s > 0 else None)
    cuda_peaks = [r["cuda_peak_bytes"] for r in raws if r["cuda_peak_bytes"] is not None]
    return {
        **base,
        "projected": case.metric == "design" and first["iterations"] != case.iterations,
        "pairs": pairs,
        "pairs_counted": "kernel" if counted else ("table" if pairs is not None else None),
        "evaluations": evaluations,
        "ns_per_evaluation": (kernel_s / evaluations * 1e9 if evaluations and kernel_s > 0
                              else None),
        "setup_s": statistics.median(r["setup_s"] for r in raws),
        "design_s": design_s,
        "design_s_runs": totals,
        "iteration_s": iteration_s,
        "iteration_s_runs": steps,
        "forward_s": forward_s,
        "backward_s": backward_s,
        "other_s": other_s,
        "kernel_forward_s": kernel_fwd if first["backend"] in FUSED else None,
        "kernel_backward_s": kernel_bwd if first["backend"] in FUSED else None,
        "measured_s": measured_s,
        "ratio_to_goal": None if case.goal_s is None else measured_s / case.goal_s,
        "speedup_vs_reference": (None if case.reference_s is None
                                 else case.reference_s / measured_s),
        "bytes": bytes_model,
        "read_gb": None if bytes_model is None else bytes_model["read"] / GB,
        "achieved_gbs": achieved,
        "peak_rss_increase_mib": max(r["peak_rss_bytes"] for r in raws) / MIB,
        "cuda_peak_mib": max(cuda_peaks) / MIB if cuda_peaks else None,
        "quick": quick,
    }


def environment(device: torch.device) -> dict[str, Any]:
    """Versions, threads, CPUs, device and machine load (timings on a busy machine are noisy)."""
    return {
        "torch": torch.__version__,
        "python": platform.python_version(),
        "threads": torch.get_num_threads(),
        "kernel_threads": kernels.thread_count(),
        # The cases run in child processes, which take it from here (aperture_fab sets it).
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "unset"),
        "cpu_count": os.cpu_count(),
        "cpus_usable": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "memory_available_gb": budget.available_bytes(device) / GB,
        "device": str(device),
        "device_name": (torch.cuda.get_device_name(device) if device.type == "cuda"
                        else platform.processor() or platform.machine()),
    }


def run_child(name: str, device: str, quick: bool, count_pairs: bool) -> dict[str, Any]:
    """Measure one repeat of one case in a fresh Python process (its own peak RSS)."""
    command = [sys.executable, str(Path(__file__).resolve()), "--child", name, "--device", device]
    if quick:
        command.append("--quick")
    if count_pairs:
        command.append("--count-pairs")
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"benchmark case {name!r} failed (exit {done.returncode}):\n"
                           f"{done.stderr[-4000:]}")
    lines = [line for line in done.stdout.splitlines() if line.strip()]
    figures: dict[str, Any] = json.loads(lines[-1])
    return figures


def _number(value: float | None, spec: str) -> str:
    return "-" if value is None else format(value, spec)


HEADER = (f"{'case':<13} {'backend':>7} {'S':>3} {'iters':>6} {'pairs/iter':>11} {'setup s':>8} "
          f"{'s/iter':>8} {'s/design':>9} {'goal s':>6} {'x goal':>7} {'ref s':>6} "
          f"{'vs ref':>7} {'RSS MiB':>8} {'est MiB':>8} {'CUDA MiB':>9}")
PROFILE_HEADER = (f"{'case':<13} {'fwd s':>8} {'bwd s':>8} {'other s':>8} {'kfwd s':>8} "
                  f"{'kbwd s':>8} {'evals/iter':>11} {'ns/eval':>7} {'GB read':>8} {'GB/s':>7} "
                  f"{'x copy':>7}")


def table_row(r: Mapping[str, Any]) -> str:
    """One line of the results table; `*` marks a design time extended from a --quick run."""
    head = f"{r['case']:<13} {r['backend']:>7} {r['states']:>3}"
    for reason in ("refused", "skipped"):
        if reason in r:
            return f"{head} {reason} (estimate {r['estimate_mib']:.0f} MiB): {r[reason]}"
    iters = f"{r['iterations']}" + (f"+{r['warmup']}w" if r["metric"] == "iteration" else "")
    design = "-" if r["metric"] != "design" else (
        f"{r['measured_s']:.2f}" + ("*" if r["projected"] else ""))
    pairs = "-" if r["pairs"] is None else f"{r['pairs']:,}"
    return (f"{head} {iters:>6} {pairs:>11} {r['setup_s']:>8.2f} "
            f"{r['iteration_s']:>8.4f} {design:>9} {_number(r['goal_s'], '.2f'):>6} "
            f"{_number(r['ratio_to_goal'], '.2f'):>7} {_number(r['reference_s'], '.0f'):>6} "
            f"{_number(r['speedup_vs_reference'], '.1f'):>7} "
            f"{r['peak_rss_increase_mib']:>8.0f} {r['estimate_mib']:>8.0f} "
            f"{_number(r['cuda_peak_mib'], '.0f'):>9}")


def profile_row(r: Mapping[str, Any], copy_gbs: float) -> str | None:
    if "iteration_s" not in r:
        return None
    fwd, bwd, other = r["forward_s"], r["backward_s"], r["other_s"]
    achieved = r["achieved_gbs"]
    return (f"{r['case']:<13} {_number(fwd, '.4f'):>8} {_number(bwd, '.4f'):>8} "
            f"{_number(other, '.4f'):>8} {_number(r['kernel_forward_s'], '.4f'):>8} "
            f"{_number(r['kernel_backward_s'], '.4f'):>8} "
            f"{'-' if r['evaluations'] is None else format(r['evaluations'], ','):>11} "
            f"{_number(r['ns_per_evaluation'], '.1f'):>7} {_number(r['read_gb'], '.3f'):>8} "
            f"{_number(achieved, '.2f'):>7} "
            f"{_number(None if achieved is None else achieved / copy_gbs, '.2f'):>7}")


def goals(results: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """Issue 9's goals from this run's medians: the single-state speedup over the reference
    and the 16-state iteration over the reference's single-state one."""
    reference = results.get(REFERENCE_CASE, {}).get("iteration_s")
    single = results.get(SINGLE_CASE, {}).get("iteration_s")
    states = results.get(STATES_CASE, {}).get("iteration_s")
    speedup = reference / single if reference and single else None
    ratio = states / reference if reference and states else None
    return {
        "reference_case": REFERENCE_CASE,
        "single_speedup": speedup,
        "single_speedup_goal": GOAL_SINGLE_SPEEDUP,
        "single_speedup_met": None if speedup is None else speedup >= GOAL_SINGLE_SPEEDUP,
        "states_ratio": ratio,
        "states_ratio_goal": GOAL_STATES_RATIO,
        "states_ratio_met": None if ratio is None else ratio <= GOAL_STATES_RATIO,
    }


def gpu_goal_lines(results: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """Issue 20's GPU goals beside this run's figures (a CUDA run)."""
    lines = []
    for name, goal in GOAL_GPU_S.items():
        if name not in results:
            continue
        r = results[name]
        figure = r.get("design_s") if CASES[name].metric == "design" else r.get("iteration_s")
        unit = "s/design" if CASES[name].metric == "design" else "s/iteration"
        met = None if figure is None else figure <= goal
        line = (f"GPU goal: {name} <= {goal:g} {unit} ({r.get('backend')}): "
                f"{_number(figure, '.4f')} [{_verdict(met)}]")
        if name == "large" and r.get("cuda_peak_mib") is not None:
            gb = r["cuda_peak_mib"] * MIB / GB
            line += (f"; memory <= {GOAL_GPU_LARGE_GB:g} GB: {gb:.1f} GB "
                     f"[{_verdict(gb <= GOAL_GPU_LARGE_GB)}]")
        if "refused" in r or "skipped" in r:
            line += f" ({r.get('refused') or r.get('skipped')})"
        lines.append(line)
    return lines


def _verdict(met: bool | None) -> str:
    return "n/a" if met is None else ("met" if met else "NOT met")


def goal_lines(g: Mapping[str, Any], results: Mapping[str, Mapping[str, Any]]) -> list[str]:
    verdict = _verdict
    states = results.get(STATES_CASE, {}).get("states", "?")
    return [
        f"goal: single-state iteration >= {GOAL_SINGLE_SPEEDUP:g}x faster than the reference "
        f"({REFERENCE_CASE} / {SINGLE_CASE}): {_number(g['single_speedup'], '.2f')}x "
        f"[{verdict(g['single_speedup_met'])}]",
        f"goal: {STATES_CASE} ({states} states) <= {GOAL_STATES_RATIO:g}x the reference's "
        f"single-state iteration ({STATES_CASE} / {REFERENCE_CASE}): "
        f"{_number(g['states_ratio'], '.2f')}x [{verdict(g['states_ratio_met'])}]",
    ]


NOTES = "\n".join([
    "S: eye states per iteration. pairs/iter: (view pixel, hole) pairs the kernel reads a stack",
    "  sample for per pass (kernel cases, counted; states focused at infinity share them) or",
    "  the pair-table entries (torch, padded).",
    "s/iter: median seconds per iteration after the warm-up ones, pooled over the repeats;",
    "s/design: median over the repeats of the optimize call; * = a --quick run extended to the",
    "  nominal iteration count at its s/iter. goal s and ref s: per design for the seed cases,",
    "  per iteration for nominal.",
    f"x goal: our time / goal (below 1 meets it). Goals: seed-28 300 iterations < "
    f"{GOAL_SEED_28_S} s,",
    f"  seed-100 600 iterations < {GOAL_SEED_100_S:.0f} s, nominal < "
    f"{GOAL_NEAR_EYE_ITERATION_S} s per iteration.",
    f"ref / vs ref: the dissertation's odak-based code, ~0.10 s/iteration at 28 x 28 "
    f"({REFERENCE_SEED_28_S:.0f} s for 300),",
    f"  ~3.6 s/iteration at 100 x 100 ({REFERENCE_SEED_100_S / 60:.0f} min for 600); "
    "vs ref = its time / ours.",
    "setup: Renderer construction (torch: plus the pair table), warm, after a run.",
    "RSS MiB: increase of the case's peak resident memory (max over repeats); est MiB:",
    "  aperture_fab.optimize.budget's estimate; CUDA MiB: torch.cuda.max_memory_allocated.",
    "fwd / bwd s: the loss's forward and backward (medians); other: the rest of an iteration",
    "  (Adam step, eye states, bookkeeping; median of s/iter - fwd - bwd per iteration);",
    "  kfwd / kbwd: the CPU kernels alone. evals/iter: (state, view pixel, hole) triples the",
    "  kernel evaluates per pass (counted); ns/eval: (kfwd + kbwd) / evals. GB read: the",
    "  kernel path's bytes read per iteration (model: module docstring); GB/s: GB read /",
    "  (kfwd + kbwd); x copy: that over the machine's copy bandwidth measured in this run.",
])


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value} must be a whole number >= 1")
    return value


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--device", choices=DEVICES, default="auto")
    parser.add_argument("--repeats", type=_positive_int, default=3,
                        help="repeats of every case, each in its own process (medians reported)")
    parser.add_argument("--quick", action="store_true",
                        help="few iterations per case and a 32 x 32 near-eye view (smoke test); "
                             "design times are projected")
    parser.add_argument("--large", action="store_true",
                        help="add the 512 x 512 case (meant for a GPU; very slow on a CPU)")
    parser.add_argument("--cases", nargs="+", choices=list(CASES), default=None,
                        help="run only these cases")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    parser.add_argument("--child", choices=list(CASES), default=None, help=argparse.SUPPRESS)
    parser.add_argument("--count-pairs", action="store_true", help=argparse.SUPPRESS)
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the benchmark; print the tables and return (and optionally write) the figures."""
    args = parse_args(argv)
    if args.device == "cuda" and not torch.cuda.is_available():
        print("no CUDA device here: the GPU figures are skipped (run with --device cpu or auto).")
        return {"skipped": "no CUDA device"}
    device = resolve_device(args.device)
    if args.child is not None:
        print(json.dumps(measure(CASES[args.child], str(device), args.quick, args.count_pairs)))
        return {}
    env = environment(device)
    bandwidth = copy_bandwidth(QUICK_COPY_MIB if args.quick else COPY_MIB)
    copy_gbs = max(bandwidth["numpy_gbs"], bandwidth["torch_gbs"])
    print(f"torch {env['torch']}, {env['threads']} threads (kernels {env['kernel_threads']}, "
          f"OpenMP wait policy {env['omp_wait_policy']}), "
          f"{env['cpu_count']} CPUs ({env['cpus_usable']} usable), device {env['device']} "
          f"({env['device_name']}), load average "
          f"{_number(env['load_average'][0] if env['load_average'] else None, '.1f')}, "
          f"{env['memory_available_gb']:.1f} GB available"
          + (", --quick (near-eye cases at a 32 x 32 view)" if args.quick else ""))
    print(f"copy bandwidth ({bandwidth['array_mib']:.0f} MiB float64, read + written): numpy "
          f"{bandwidth['numpy_gbs']:.1f} GB/s (1 thread), torch copy_ "
          f"{bandwidth['torch_gbs']:.1f} GB/s ({bandwidth['threads']:.0f} threads)")
    names = list(args.cases) if args.cases else [*DEFAULT_CASES,
                                                 *(["large"] if args.large else [])]
    if "large" in names and device.type != "cuda":
        print("warning: the large case is meant for a GPU; on a CPU it takes very long.",
              file=sys.stderr)
    raws: dict[str, list[dict[str, Any]]] = {name: [] for name in names}
    for repeat in range(args.repeats):  # round-robin: a change of load hits every case alike
        for name in names:
            if raws[name] and ("refused" in raws[name][0] or "skipped" in raws[name][0]):
                continue
            raws[name].append(run_child(name, str(device), args.quick, count_pairs=repeat == 0))
        print(f"  repeat {repeat + 1}/{args.repeats} done", file=sys.stderr, flush=True)
    results = {name: summarize(CASES[name], raws[name], args.quick) for name in names}
    print(HEADER)
    for name in names:
        print(table_row(results[name]))
    print()
    print(PROFILE_HEADER)
    for name in names:
        row = profile_row(results[name], copy_gbs)
        if row is not None:
            print(row)
    print()
    reached = goals(results)
    for line in goal_lines(reached, results):
        print(line)
    if device.type == "cuda":
        for line in gpu_goal_lines(results):
            print(line)
    load_end = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    print(f"load average at the end: {_number(load_end[0] if load_end else None, '.1f')}")
    print(NOTES)
    figures = {"environment": {**env, "load_average_end": load_end}, "quick": args.quick,
               "repeats": args.repeats, "copy_bandwidth": bandwidth, "goals": reached,
               "cases": results}
    if args.json is not None:
        args.json.write_text(json.dumps(figures, indent=2) + "\n")
    return figures


if __name__ == "__main__":
    main()
