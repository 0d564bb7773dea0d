"""Speed and peak memory of the optimizer (aperture_fab.optimize.optimize) on reference scenes.

Run: .venv/bin/python benchmarks/bench_optimize.py [--device auto|cpu|cuda] [--repeats 3]
     [--quick] [--large] [--json PATH]

Cases (each in a fresh child process, so peak memory belongs to that case alone):

- seed-28: the `seed` preset (28 x 28 cells, the dissertation's scene), target digit-3,
  300 iterations: seconds per design, the median of --repeats after one untimed 1-iteration
  run (thread pools, lazy kernel loading, allocator).
- seed-100: the seed scene with 100 x 100 cells and display pixels (view stays 28 x 28),
  600 iterations: seconds per design, likewise.
- near-eye: the `near-eye` preset (80 x 80 cells, 128 x 128 view, display content optimized),
  target natural: seconds per iteration, the median over the repeats of 10 iterations each
  after 2 warm-up ones.
- large (--large only, meant for a GPU): 512 x 512 cells at 0.05 mm on a 25.6 mm, 1024 x 1024
  pixel display, 512 x 512 view: seconds per iteration (3 after 1 warm-up).

Every timed run is one `optimize` call with a checkpoint callback after every iteration that
stamps the time; the cost of making a checkpoint (estimated by copying the last one) is taken
out. The design time is the optimize call alone (which builds its own renderer); the renderer
setup (blur kernels and the (view pixel, hole) pair table) is timed on its own as well,
after each run, warm.
Peak memory: the increase of the child's peak RSS (ru_maxrss) over its value before the case
and, on CUDA, torch.cuda.max_memory_allocated. --quick runs a few iterations (the smoke test);
a quick design is extended to the nominal iteration count at its per-iteration rate.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from aperture_fab.config import Config, resolve
from aperture_fab.images import is_grey, resample
from aperture_fab.model import Renderer
from aperture_fab.optimize import optimize, resolve_device
from aperture_fab.targets import EXAMPLES

DEVICES = ("auto", "cpu", "cuda")
#: ru_maxrss is in KiB on Linux and in bytes on macOS.
RSS_UNIT_BYTES = 1 if sys.platform == "darwin" else 1024
MIB = 2**20
#: The dissertation's odak-based code (UCL MSc, 2022): 33 s for a 300-epoch 28 x 28 design
#: (about 0.10 s per iteration), 36 min for 600 epochs at 100 x 100 (about 3.6 s per iteration).
REFERENCE_SEED_28_S = 33.0
REFERENCE_SEED_100_S = 36 * 60.0
#: Goals: a seed design in under 1.5 s, a 100 x 100 design in under 20 s, a near-eye iteration
#: in under 0.2 s.
GOAL_SEED_28_S = 1.5
GOAL_SEED_100_S = 20.0
GOAL_NEAR_EYE_ITERATION_S = 0.2


@dataclass(frozen=True)
class Case:
    """One benchmark scene.

    metric: "design" (seconds for a whole design of `iterations` iterations, median of repeats)
        or "iteration" (median seconds per iteration of `iterations` iterations after `warmup`
        ones, over the repeats).
    quick_iterations, quick_warmup: the same under --quick.
    goal_s, reference_s: the goal and the dissertation's figure in the case's metric (None: none).
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
        Case("near-eye", "near-eye preset, 80 x 80 cells, 128 x 128 view, RGB", "near-eye",
             "natural", "iteration", iterations=10, quick_iterations=1, warmup=2, quick_warmup=1,
             goal_s=GOAL_NEAR_EYE_ITERATION_S, reference_s=None),
        # The near-eye optics (gap, eye) at a finer scale: 50 um cells (holes that small need a
        # photo-etched foil, hence 0.1 mm thick), a 25 um pixel (~1000 ppi) display as wide as
        # the plate, and a 512 x 512 view.
        Case("large", "512 x 512 cells at 0.05 mm, 1024^2 px 25.6 mm display, 512^2 view",
             "near-eye", "natural", "iteration", iterations=3, quick_iterations=1, warmup=1,
             quick_warmup=1, goal_s=None, reference_s=None,
             overrides={"plate.cells": [512, 512], "plate.pitch_mm": [0.05, 0.05],
                        "plate.thickness_mm": 0.1, "display.width_mm": 25.6,
                        "display.height_mm": 25.6, "display.pixels": [1024, 1024],
                        "eye.view_pixels": [512, 512]}),
    )
}
DEFAULT_CASES = ("seed-28", "seed-100", "near-eye")


def case_config(case: Case, device: str, iterations: int) -> Config:
    """The case's resolved config: every iteration runs (no plateau stop) and a checkpoint
    follows every iteration (the timing hook)."""
    return resolve(case.preset, None, {
        **case.overrides,
        "optimizer.device": device,
        "optimizer.iterations": iterations,
        "optimizer.plateau_patience": 0,
        "optimizer.checkpoint_every": 1,
    })


def prepare_target(config: Config, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One target on the view grid (1, C, ny, nx) and on the display grid (1, C, H, W), one
    channel when grey: what aperture_fab.pipeline does before optimizing."""
    im = image[:1] if is_grey(image) else image
    scene = config.scene
    return (resample(im, scene.eye.view_pixels)[None],
            resample(im, scene.display.pixels)[None])


def _peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * RSS_UNIT_BYTES / MIB


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _setup_seconds(config: Config, device: torch.device, dtype: torch.dtype) -> tuple[float, int]:
    """Seconds to build a renderer and its pair table for the nominal eye position; pair count."""
    start = time.perf_counter()
    renderer = Renderer(config.scene, device=device, dtype=dtype)
    pairs = renderer.pair_count(0)
    _sync(device)
    return time.perf_counter() - start, pairs


class _Stopwatch:
    """Checkpoint callback: stamps the time after every iteration. After the last one it also
    times a copy of the checkpoint, an estimate of what optimize spent making each checkpoint,
    which the figures leave out (a few ms for near-eye on a CPU, tens of us for seed)."""

    def __init__(self, last_iteration: int, device: torch.device) -> None:
        self.last_iteration = last_iteration
        self.device = device
        self.stamps: list[float] = []
        self.snapshot_s = 0.0

    def __call__(self, state: dict[str, Any]) -> None:
        self.stamps.append(time.perf_counter())
        if state["iteration"] == self.last_iteration:  # no interval left to disturb
            start = time.perf_counter()
            copy.deepcopy(state)
            _sync(self.device)
            self.snapshot_s = time.perf_counter() - start


def _timed_optimize(config: Config, views: np.ndarray, shown: np.ndarray,
                    device: torch.device) -> tuple[float, list[float], float]:
    """Seconds of one optimize call, seconds of each of its iterations 2, 3, ..., and the
    checkpoint cost taken out of both."""
    iterations = config.optimizer.iterations
    watch = _Stopwatch(iterations, device)
    start = time.perf_counter()
    optimize(config.scene, views, shown, config.optimizer, progress=False, on_checkpoint=watch)
    _sync(device)
    total = time.perf_counter() - start - iterations * watch.snapshot_s
    intervals = (np.diff(watch.stamps) - watch.snapshot_s).tolist()
    return total, intervals, watch.snapshot_s


def measure(case: Case, device_name: str, repeats: int, quick: bool) -> dict[str, Any]:
    """Run one case `repeats` times in this process; its figures (see the module docstring)."""
    device = resolve_device(device_name)
    iterations = case.quick_iterations if quick else case.iterations
    warmup = case.quick_warmup if quick else case.warmup
    config = case_config(case, str(device), warmup + iterations)
    settings = config.optimizer
    dtype = torch.float64 if settings.precision == "float64" else torch.float32
    views, shown = prepare_target(config, EXAMPLES[case.target]())
    rss_before = _peak_rss_mib()
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    if case.metric == "design":
        # Untimed: thread pools, lazy kernel loading, allocator (per-iteration cases have
        # warm-up iterations instead).
        optimize(config.scene, views, shown, dataclasses.replace(settings, iterations=1),
                 progress=False)
    setups, totals, steps, snapshots = [], [], [], []
    for _ in range(repeats):
        total, intervals, snapshot_s = _timed_optimize(config, views, shown, device)
        seconds, pairs = _setup_seconds(config, device, dtype)  # warm, after a run
        setups.append(seconds)
        totals.append(total)
        snapshots.append(snapshot_s)
        # Intervals start at iteration 2 (the first builds the pair table); skip warm-up ones.
        steps.extend(intervals[max(warmup - 1, 0):])
    iteration_s = statistics.median(steps)
    if case.metric == "design":
        design_s = statistics.median(totals)
        # A short (--quick) run extended to the nominal count at the steady-state rate.
        measured_s = design_s + (case.iterations - iterations) * iteration_s
    else:
        design_s = None
        measured_s = iteration_s
    cuda_peak = (torch.cuda.max_memory_allocated(device) / MIB if device.type == "cuda"
                 else None)
    return {
        "case": case.name,
        "description": case.description,
        "metric": case.metric,
        "device": str(device),
        "threads": torch.get_num_threads(),
        "repeats": repeats,
        "iterations": iterations,
        "warmup": warmup,
        "nominal_iterations": case.iterations,
        "projected": case.metric == "design" and iterations != case.iterations,
        "pairs": pairs,
        "setup_s": statistics.median(setups),
        "design_s": design_s,
        "design_s_runs": totals,
        "iteration_s": iteration_s,
        "iteration_s_runs": steps,
        "snapshot_s": statistics.median(snapshots),
        "measured_s": measured_s,
        "goal_s": case.goal_s,
        "ratio_to_goal": None if case.goal_s is None else measured_s / case.goal_s,
        "reference_s": case.reference_s,
        "speedup_vs_reference": (None if case.reference_s is None
                                 else case.reference_s / measured_s),
        "peak_rss_increase_mib": _peak_rss_mib() - rss_before,
        "cuda_peak_mib": cuda_peak,
    }


def environment(device: torch.device) -> dict[str, Any]:
    """Versions, threads, CPUs, device and machine load (timings on a busy machine are noisy)."""
    return {
        "torch": torch.__version__,
        "python": platform.python_version(),
        "threads": torch.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "cpus_usable": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "device": str(device),
        "device_name": (torch.cuda.get_device_name(device) if device.type == "cuda"
                        else platform.processor() or platform.machine()),
    }


def run_child(name: str, device: str, repeats: int, quick: bool) -> dict[str, Any]:
    """Measure one case in a fresh Python process (its own peak RSS); the child's figures."""
    command = [sys.executable, str(Path(__file__).resolve()), "--child", name, "--device", device,
               "--repeats", str(repeats)]
    if quick:
        command.append("--quick")
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"benchmark case {name!r} failed (exit {done.returncode}):\n"
                           f"{done.stderr[-4000:]}")
    lines = [line for line in done.stdout.splitlines() if line.strip()]
    figures: dict[str, Any] = json.loads(lines[-1])
    return figures


def _number(value: float | None, spec: str) -> str:
    return "-" if value is None else format(value, spec)


HEADER = (f"{'case':<9} {'iters':>6} {'pairs':>11} {'setup s':>8} {'s/iter':>8} {'s/design':>9} "
          f"{'goal s':>6} {'x goal':>7} {'ref s':>6} {'vs ref':>7} {'RSS MiB':>8} {'CUDA MiB':>9}")


def table_row(r: Mapping[str, Any]) -> str:
    """One line of the results table; `*` marks a design time extended from a --quick run."""
    iters = f"{r['iterations']}" + (f"+{r['warmup']}w" if r["metric"] == "iteration" else "")
    design = "-" if r["metric"] != "design" else (
        f"{r['measured_s']:.2f}" + ("*" if r["projected"] else ""))
    return (f"{r['case']:<9} {iters:>6} {r['pairs']:>11,} {r['setup_s']:>8.2f} "
            f"{r['iteration_s']:>8.4f} {design:>9} {_number(r['goal_s'], '.2f'):>6} "
            f"{_number(r['ratio_to_goal'], '.2f'):>7} {_number(r['reference_s'], '.0f'):>6} "
            f"{_number(r['speedup_vs_reference'], '.1f'):>7} "
            f"{r['peak_rss_increase_mib']:>8.0f} {_number(r['cuda_peak_mib'], '.0f'):>9}")


NOTES = "\n".join([
    "s/iter: median seconds per iteration after the first (near-eye: after the warm-up ones);",
    "s/design: median over the repeats of the optimize call; * = a --quick run extended to the",
    "  nominal iteration count at its s/iter. goal s and ref s: per design for the seed cases,",
    "  per iteration for near-eye.",
    f"x goal: our time / goal (below 1 meets it). Goals: seed-28 300 iterations < "
    f"{GOAL_SEED_28_S} s,",
    f"  seed-100 600 iterations < {GOAL_SEED_100_S:.0f} s, near-eye < "
    f"{GOAL_NEAR_EYE_ITERATION_S} s per iteration.",
    f"ref / vs ref: the dissertation's odak-based code, ~0.10 s/iteration at 28 x 28 "
    f"({REFERENCE_SEED_28_S:.0f} s for 300),",
    f"  ~3.6 s/iteration at 100 x 100 ({REFERENCE_SEED_100_S / 60:.0f} min for 600); "
    "vs ref = its time / ours.",
    "setup: Renderer construction plus the pair table (also inside the design time).",
    "RSS MiB: increase of the case's peak resident memory; CUDA MiB: "
    "torch.cuda.max_memory_allocated.",
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
                        help="repeats of the per-design cases (median reported)")
    parser.add_argument("--quick", action="store_true",
                        help="few iterations per case (smoke test); design times are projected")
    parser.add_argument("--large", action="store_true",
                        help="add the 512 x 512 case (meant for a GPU; very slow on a CPU)")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    parser.add_argument("--child", choices=list(CASES), default=None, help=argparse.SUPPRESS)
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the benchmark; print the table and return (and optionally write) the figures."""
    args = parse_args(argv)
    device = resolve_device(args.device)
    if args.child is not None:
        print(json.dumps(measure(CASES[args.child], str(device), args.repeats, args.quick)))
        return {}
    env = environment(device)
    print(f"torch {env['torch']}, {env['threads']} threads, {env['cpu_count']} CPUs "
          f"({env['cpus_usable']} usable), device {env['device']} ({env['device_name']}), "
          f"load average {_number(env['load_average'][0] if env['load_average'] else None, '.1f')}"
          + (", --quick" if args.quick else ""))
    names = [*DEFAULT_CASES, *(["large"] if args.large else [])]
    if args.large and device.type != "cuda":
        print("warning: the large case is meant for a GPU; on a CPU it takes very long and "
              "needs tens of GB of memory.", file=sys.stderr)
    print(HEADER, flush=True)
    results = {}
    for name in names:
        results[name] = run_child(name, str(device), args.repeats, args.quick)
        print(table_row(results[name]), flush=True)
    print(NOTES)
    figures = {"environment": env, "quick": args.quick, "repeats": args.repeats,
               "cases": results}
    if args.json is not None:
        args.json.write_text(json.dumps(figures, indent=2) + "\n")
    return figures


if __name__ == "__main__":
    main()
