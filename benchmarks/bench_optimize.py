"""Speed and peak memory of the optimizer (aperture_fab.optimize.optimize) on reference scenes.

Run: .venv/bin/python benchmarks/bench_optimize.py [--device auto|cpu|cuda] [--repeats 3]
     [--quick] [--large] [--json PATH]

Cases (each in a fresh child process, so peak memory belongs to that case alone):

- seed-28: the `seed` preset (28 x 28 cells, the dissertation's scene), target digit-3,
  300 iterations: seconds per design, median of --repeats (after one untimed 1-iteration warm-up).
- seed-100: the seed scene with 100 x 100 cells and display pixels (view stays 28 x 28),
  600 iterations: seconds per design.
- near-eye: the `near-eye` preset (80 x 80 cells, 128 x 128 view, display content optimized),
  target natural: seconds per iteration, the median of 10 iterations after 2 warm-up ones, timed
  from one optimize run with a checkpoint callback after every iteration.
- large (--large only, meant for a GPU): 512 x 512 cells at 0.05 mm on a 25.6 mm, 1024 x 1024
  pixel display, 512 x 512 view: seconds per iteration.

Renderer setup (blur kernels and the (view pixel, hole) pair table) is timed on its own; the
design time is the optimize call alone (which builds its own renderer). Peak memory: the increase
of the child's peak RSS (ru_maxrss) over its value before the case, and on CUDA
torch.cuda.max_memory_allocated. --quick runs few iterations (the smoke test); its per-design
figures are then projected to the nominal iteration count from the per-iteration time.
"""

from __future__ import annotations

import argparse
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
        or "iteration" (median seconds of `iterations` iterations after `warmup` ones, one run).
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
        # The near-eye physics at four times the resolution: 50 um cells (a photo-etched foil,
        # hence 0.1 mm thick) over a 25 um pixel (~1000 ppi) display of the same 25.6 mm width.
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
    """The case's resolved config: every iteration runs (no plateau stop), checkpoint callback
    after every iteration (used by the per-iteration timing only)."""
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


def _timed_optimize(config: Config, views: np.ndarray, shown: np.ndarray,
                    device: torch.device) -> tuple[float, list[float]]:
    """Seconds of one optimize call and the seconds of its iterations 2, 3, ... (a checkpoint
    callback after every iteration stamps the time; it costs a state copy, well under 1 %)."""
    stamps: list[float] = []
    start = time.perf_counter()
    optimize(config.scene, views, shown, config.optimizer, progress=False,
             on_checkpoint=lambda _state: stamps.append(time.perf_counter()))
    _sync(device)
    total = time.perf_counter() - start
    return total, np.diff(stamps).tolist()


def measure(case: Case, device_name: str, repeats: int, quick: bool) -> dict[str, Any]:
    """Run one case in this process; its figures (see the module docstring)."""
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
    result: dict[str, Any] = {}
    if case.metric == "design":
        # Untimed: thread pools, lazy kernel loading and allocator warm-up.
        optimize(config.scene, views, shown, dataclasses.replace(settings, iterations=1),
                 progress=False)
        setups, designs, steps = [], [], []
        for _ in range(repeats):
            seconds, pairs = _setup_seconds(config, device, dtype)
            setups.append(seconds)
            total, intervals = _timed_optimize(config, views, shown, device)
            designs.append(total)
            steps.extend(intervals)  # iterations 2.. of each repeat: steady state
        design_s = statistics.median(designs)
        iteration_s = statistics.median(steps)
        # A short (--quick) run extended to the nominal count at the steady-state rate.
        measured_s = design_s + (case.iterations - iterations) * iteration_s
        result.update(design_s=design_s, design_s_runs=designs, repeats=repeats)
    else:
        setup, pairs = _setup_seconds(config, device, dtype)
        setups = [setup]
        _, intervals = _timed_optimize(config, views, shown, device)
        steps = intervals[warmup - 1:]
        iteration_s = measured_s = statistics.median(steps)
        result.update(warmup=warmup, repeats=1)
    cuda_peak = (torch.cuda.max_memory_allocated(device) / MIB if device.type == "cuda"
                 else None)
    result.update(
        case=case.name,
        description=case.description,
        metric=case.metric,
        device=str(device),
        threads=torch.get_num_threads(),
        iteration_s_runs=steps,
        iterations=iterations,
        nominal_iterations=case.iterations,
        projected=case.metric == "design" and iterations != case.iterations,
        pairs=pairs,
        setup_s=statistics.median(setups),
        iteration_s=iteration_s,
        measured_s=measured_s,
        goal_s=case.goal_s,
        ratio_to_goal=None if case.goal_s is None else measured_s / case.goal_s,
        reference_s=case.reference_s,
        speedup_vs_reference=None if case.reference_s is None else case.reference_s / measured_s,
        peak_rss_increase_mib=_peak_rss_mib() - rss_before,
        cuda_peak_mib=cuda_peak,
    )
    return result


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


HEADER = (f"{'case':<9} {'iters':>6} {'pairs':>11} {'setup s':>8} {'measured':>10} {'unit':<6} "
          f"{'goal':>6} {'x goal':>7} {'ref':>7} {'vs ref':>7} {'RSS MiB':>8} {'CUDA MiB':>9}")


def table_row(r: Mapping[str, Any]) -> str:
    """One line of the results table; `*` marks per-design times projected from few iterations."""
    unit = "s/des" if r["metric"] == "design" else "s/it"
    iters = f"{r['iterations']}" + (f"+{r['warmup']}w" if r["metric"] == "iteration" else "")
    measured = _number(r["measured_s"], ".3f") + ("*" if r["projected"] else "")
    return (f"{r['case']:<9} {iters:>6} {r['pairs']:>11,} {r['setup_s']:>8.2f} {measured:>10} "
            f"{unit:<6} {_number(r['goal_s'], '.2f'):>6} {_number(r['ratio_to_goal'], '.2f'):>7} "
            f"{_number(r['reference_s'], '.0f'):>7} "
            f"{_number(r['speedup_vs_reference'], '.1f'):>7} "
            f"{r['peak_rss_increase_mib']:>8.0f} {_number(r['cuda_peak_mib'], '.0f'):>9}")


NOTES = f"""\
measured: seconds per design (median of the repeats) or per iteration (median after warm-up);
  * = projected to the nominal iteration count from a --quick run.
x goal: measured / goal (below 1 meets it). Goals: seed-28 300 iterations < {GOAL_SEED_28_S} s,
  seed-100 600 iterations < {GOAL_SEED_100_S:.0f} s, near-eye < {GOAL_NEAR_EYE_ITERATION_S} s per \
iteration.
ref / vs ref: the dissertation's odak-based code, ~0.10 s/iteration at 28 x 28 ({REFERENCE_SEED_28_S:.0f} s \
for 300),
  ~3.6 s/iteration at 100 x 100 ({REFERENCE_SEED_100_S / 60:.0f} min for 600); vs ref = its time / ours.
setup: Renderer construction plus the pair table (also inside the design time).
RSS MiB: increase of the case's peak resident memory; CUDA MiB: torch.cuda.max_memory_allocated."""


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
