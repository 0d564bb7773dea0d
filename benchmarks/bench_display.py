"""Latency and quality of tracked displays (aperture_fab.optimize.tracking.solve_display) per frame.

Run: .venv/bin/python benchmarks/bench_display.py [--device all|cpu|cuda] [--repeats 5]
     [--iterations 1 2 5 10] [--compare] [--light-floors 0 0.5 1] [--quick] [--json PATH]

Scene: the `near-eye` preset (400 x 400 display, 80 x 80 cells, 128 x 128 view), its regular
pinhole plate (`baselines.regular_pinholes`), target `natural` (RGB) resampled to the view grid;
the untracked display, and the warm start of every solve, is the plate's elemental display for
the nominal eye (`baselines.elemental_display`).

- latency: seconds per frame of `solve_display` for one eye state ((1, 0) mm, 4 mm pupil) at
  each iteration count, the median of --repeats after one untimed warm-up solve (kernel loading,
  thread pools, allocator), the renderer built beforehand (a device builds it once). Two
  figures: `frame`, keep_best=False (the last iterate, the lowest latency), and `checked`, the
  default keep_best=True (one more forward pass judges the last iterate; never worse than the
  start). Goal: 33 ms per frame (video rate, 30 frames/s); `x goal` = frame / goal.
- quality: PSNR after gain (dB) of the untracked display and the tracked one (the default
  iterations, keep_best) for eye offsets (0, 0), (1, 0), (2, 0) mm and pupils 3 and 6 mm.
- --compare: PSNR after gain of every iterate, 0 to 10 iterations, for MLEM and projected Adam
  at a few eye states (the measurement behind the solver choice in
  aperture_fab/optimize/tracking.py).
- --light-floors F ...: at the same eye states, the default iterations, PSNR after gain and the
  view's light at the eye as a share of the untracked display's for each light floor F
  (`solve_display(light_floor=F)`: 0, each frame scaled to a peak of 1; 1, the untracked light
  kept, as `aperture-fab display` does).

Devices: the CPU (fused Numba kernels) and, when torch.cuda.is_available(), CUDA (the torch
path; a new eye state builds its pair table, which is inside the frame time). --quick (the
smoke test) times 1 and 2 iterations once each after the warm-up and judges two eye states.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from aperture_fab.config.config import resolve
from aperture_fab.io.images import resample
from aperture_fab.optics.baselines import elemental_display, regular_pinholes
from aperture_fab.optics.eyes import EyeStates
from aperture_fab.optics.model import Renderer
from aperture_fab.optimize.tracking import DEFAULT_ITERATIONS, solve_display, tracked_views
from aperture_fab.targets import natural

#: Video rate: one frame in 33 ms (30 frames per second).
GOAL_FRAME_S = 0.033
#: The eye state the latency is measured at: off nominal, so the solve has work to do.
LATENCY_STATE = ((1.0, 0.0), 4.0)
QUALITY_OFFSETS_MM = ((0.0, 0.0), (1.0, 0.0), (2.0, 0.0))
QUALITY_PUPILS_MM = (3.0, 6.0)
COMPARE_STATES = (((0.0, 0.0), 4.0), ((1.0, 0.0), 4.0), ((2.0, 0.0), 4.0), ((1.5, 1.5), 6.0))
COMPARE_ITERATIONS = 10
COMPARE_SHOWN = (0, 1, 2, 5, 10)
QUICK_ITERATIONS = (1, 2)
QUICK_QUALITY = (((0.0, 0.0), 3.0), ((1.0, 0.0), 6.0))


def eye_state(offset_mm: tuple[float, float], pupil_mm: float) -> EyeStates:
    """One eye state at an offset with a pupil, focused at infinity."""
    return EyeStates(np.array([offset_mm], dtype=np.float64), np.array([pupil_mm]),
                     np.zeros(1), np.zeros((1, 2)), np.ones(1))


def setup(device: torch.device) -> dict[str, Any]:
    """The near-eye scene's renderer, plate, target on the view grid and untracked display."""
    scene = resolve("near-eye").scene
    renderer = Renderer(scene, device=device, dtype=torch.float32)
    target = torch.as_tensor(resample(natural(), scene.eye.view_pixels), dtype=torch.float32,
                             device=device)
    plate = regular_pinholes(scene)
    start = elemental_display(scene, plate, target.cpu()).clamp(0, 1).to(device)
    return {"renderer": renderer, "plate": torch.as_tensor(plate.open_fraction,
                                                           dtype=torch.float32, device=device),
            "target": target, "start": start}


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def latency(case: dict[str, Any], device: torch.device, iterations: int, repeats: int,
            keep_best: bool) -> list[float]:
    """Seconds of `repeats` solves at the latency state, after one untimed warm-up solve."""
    state = eye_state(*LATENCY_STATE)
    args = (case["renderer"], case["plate"], case["target"], state, case["start"])
    solve_display(*args, iterations=iterations, keep_best=keep_best)
    times = []
    for _ in range(repeats):
        _sync(device)
        start = time.perf_counter()
        solve_display(*args, iterations=iterations, keep_best=keep_best)
        _sync(device)
        times.append(time.perf_counter() - start)
    return times


def quality(case: dict[str, Any], states: Sequence[tuple[tuple[float, float], float]],
            iterations: int) -> list[dict[str, Any]]:
    """PSNR of the untracked and the tracked display at each eye state."""
    rows = []
    for offset, pupil in states:
        solved = tracked_views(case["renderer"], case["plate"], case["target"],
                               eye_state(offset, pupil), case["start"], iterations)
        rows.append({"offset_mm": list(offset), "pupil_mm": pupil, "iterations": iterations,
                     "untracked_psnr_db": float(solved.start_psnr_db[0]),
                     "tracked_psnr_db": float(solved.psnr_db[0])})
    return rows


def compare(case: dict[str, Any]) -> list[dict[str, Any]]:
    """PSNR of every iterate, 0 to COMPARE_ITERATIONS, for each solver and compared state."""
    rows = []
    for offset, pupil in COMPARE_STATES:
        for method in ("mlem", "adam"):
            solved = tracked_views(case["renderer"], case["plate"], case["target"],
                                   eye_state(offset, pupil), case["start"], COMPARE_ITERATIONS,
                                   method=method)
            rows.append({"offset_mm": list(offset), "pupil_mm": pupil, "method": method,
                         "psnr_db": [float(v) for v in solved.history_db[0]]})
    return rows


def light_floors(case: dict[str, Any], floors: Sequence[float], states: Sequence[
        tuple[tuple[float, float], float]]) -> list[dict[str, Any]]:
    """PSNR after gain and the light at the eye (over the untracked display's) per floor."""
    renderer, plate = case["renderer"], case["plate"]
    rows = []
    for offset, pupil in states:
        state = eye_state(offset, pupil)
        with torch.no_grad():
            untracked = renderer.render_states(plate, renderer.display_stack(case["start"]),
                                               state)
        row: dict[str, Any] = {"offset_mm": list(offset), "pupil_mm": pupil,
                               "iterations": DEFAULT_ITERATIONS, "floors": []}
        for floor in floors:
            solved = tracked_views(renderer, plate, case["target"], state, case["start"],
                                   DEFAULT_ITERATIONS, light_floor=floor)
            row["untracked_psnr_db"] = float(solved.start_psnr_db[0])
            row["floors"].append({"light_floor": floor, "psnr_db": float(solved.psnr_db[0]),
                                  "light_share": float(solved.views[0].mean())
                                  / float(untracked.mean())})
        rows.append(row)
    return rows


def environment() -> dict[str, Any]:
    """Versions, threads, CPUs and machine load (timings on a busy machine are noisy)."""
    return {
        "torch": torch.__version__,
        "python": platform.python_version(),
        "threads": torch.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "processor": platform.processor() or platform.machine(),
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
    }


def measure_device(device: torch.device, iteration_counts: Sequence[int], repeats: int,
                   quick: bool, with_compare: bool, floors: Sequence[float]
                   ) -> dict[str, Any]:
    """Every figure for one device, printing its tables as they come."""
    start = time.perf_counter()
    case = setup(device)
    setup_s = time.perf_counter() - start
    print(f"\n{device}: renderer setup {setup_s:.2f} s (once per device)")
    print(f"{'iterations':>10} {'frame ms':>9} {'checked ms':>11} {'goal ms':>8} {'x goal':>7} "
          f"{'runs':>5}", flush=True)
    rows = []
    for n in iteration_counts:
        frame = latency(case, device, n, repeats, keep_best=False)
        checked = latency(case, device, n, repeats, keep_best=True)
        row = {"iterations": n, "frame_s": statistics.median(frame),
               "checked_s": statistics.median(checked), "frame_runs_s": frame,
               "checked_runs_s": checked, "goal_s": GOAL_FRAME_S,
               "ratio_to_goal": statistics.median(frame) / GOAL_FRAME_S}
        rows.append(row)
        print(f"{n:>10} {1000 * row['frame_s']:>9.1f} {1000 * row['checked_s']:>11.1f} "
              f"{1000 * GOAL_FRAME_S:>8.0f} {row['ratio_to_goal']:>7.1f} {repeats:>5}",
              flush=True)
    states = QUICK_QUALITY if quick else [(o, p) for p in QUALITY_PUPILS_MM
                                          for o in QUALITY_OFFSETS_MM]
    iterations = QUICK_ITERATIONS[-1] if quick else DEFAULT_ITERATIONS
    print(f"\nPSNR after gain (dB), untracked -> tracked ({iterations} iterations):")
    print(f"{'eye x,y mm':>11} {'pupil mm':>9} {'untracked':>10} {'tracked':>8}")
    judged = quality(case, states, iterations)
    for q in judged:
        x, y = q["offset_mm"]
        print(f"{f'{x:g},{y:g}':>11} {q['pupil_mm']:>9g} {q['untracked_psnr_db']:>10.2f} "
              f"{q['tracked_psnr_db']:>8.2f}", flush=True)
    compared = None
    if with_compare:
        compared = compare(case)
        print(f"\nPSNR after gain (dB) after 0 ... {COMPARE_ITERATIONS} iterations:")
        print(f"{'eye x,y mm':>11} {'pupil':>6} {'solver':>6} "
              + " ".join(f"{n:>6}" for n in COMPARE_SHOWN))
        for c in compared:
            x, y = c["offset_mm"]
            print(f"{f'{x:g},{y:g}':>11} {c['pupil_mm']:>6g} {c['method']:>6} "
                  + " ".join(f"{c['psnr_db'][n]:>6.2f}" for n in COMPARE_SHOWN), flush=True)
    lit = None
    if floors:
        lit = light_floors(case, floors, QUICK_QUALITY if quick else COMPARE_STATES)
        print(f"\nPSNR after gain (dB) at the light at the eye (a share of the untracked "
              f"display's), {DEFAULT_ITERATIONS} iterations, per light floor:")
        print(f"{'eye x,y mm':>11} {'pupil':>6} {'untracked':>10} "
              + " ".join(f"{f'floor {f:g}':>16}" for f in floors))
        for row in lit:
            x, y = row["offset_mm"]
            print(f"{f'{x:g},{y:g}':>11} {row['pupil_mm']:>6g} {row['untracked_psnr_db']:>10.2f} "
                  + " ".join(f"{f['psnr_db']:>8.2f} at {f['light_share']:>4.2f}"
                             for f in row["floors"]), flush=True)
    return {"device": str(device), "setup_s": setup_s, "latency": rows, "quality": judged,
            "compare": compared, "light_floors": lit}


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value} must be a whole number >= 1")
    return value


def _share(text: str) -> float:
    value = float(text)
    if not 0 <= value <= 1:
        raise argparse.ArgumentTypeError(f"{value:g} must be a share from 0 to 1")
    return value


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--device", choices=("all", "cpu", "cuda"), default="all",
                        help="all: the CPU, and CUDA when available (default)")
    parser.add_argument("--repeats", type=_positive_int, default=5,
                        help="timed solves per figure (median reported)")
    parser.add_argument("--iterations", type=_positive_int, nargs="+", default=[1, 2, 5, 10],
                        help="solver iterations per frame to time")
    parser.add_argument("--compare", action="store_true",
                        help="also PSNR per iteration for MLEM and projected Adam")
    parser.add_argument("--light-floors", type=_share, nargs="+", default=[], metavar="F",
                        help="also PSNR and light at the eye per light floor (0 to 1)")
    parser.add_argument("--quick", action="store_true",
                        help="smoke run: 1 and 2 iterations, one timed solve, two eye states")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the benchmark; print the tables and return (and optionally write) the figures."""
    args = parse_args(argv)
    if args.device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda: CUDA is not available here; use --device cpu or all.")
    devices = [torch.device(d) for d in (["cpu"] if args.device == "cpu" else ["cuda"]
                                         if args.device == "cuda" else
                                         ["cpu", *(["cuda"] if torch.cuda.is_available()
                                                   else [])])]
    env = environment()
    load = env["load_average"][0] if env["load_average"] else float("nan")
    print(f"torch {env['torch']}, {env['threads']} threads, {env['cpu_count']} CPUs, "
          f"CUDA: {env['cuda'] or 'none'}, load average {load:.1f}"
          + (", --quick" if args.quick else ""))
    print("near-eye preset: 400 x 400 display, 80 x 80 cells, 128 x 128 view; regular pinhole "
          "plate; target natural; start: the untracked (elemental) display")
    counts = list(QUICK_ITERATIONS) if args.quick else args.iterations
    repeats = 1 if args.quick else args.repeats
    results = [measure_device(device, counts, repeats, args.quick, args.compare and not
                              args.quick, args.light_floors) for device in devices]
    print(f"\nframe: keep_best=False (the last iterate); checked: keep_best=True (one more "
          f"forward pass). Goal {1000 * GOAL_FRAME_S:.0f} ms per frame (30 frames/s); x goal = "
          "frame / goal (below 1 meets it). Medians of the timed solves after a warm-up one.")
    figures = {"environment": env, "quick": args.quick, "repeats": repeats,
               "goal_frame_s": GOAL_FRAME_S, "devices": results}
    if args.json is not None:
        args.json.write_text(json.dumps(figures, indent=2) + "\n")
    return figures


if __name__ == "__main__":
    main()
