"""Where an optimizer iteration's time goes: torch.profiler over a few iterations of a
bench_optimize case, its operators and GPU kernels by self time, and launches per iteration.

    python benchmarks/profile_iteration.py --device cuda --cases near-eye nominal seed-28

A tool for finding what bounds a case (launch overhead, one kernel, host bookkeeping); the
figures to quote are bench_optimize's, as the profiler slows what it watches.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Sequence

import torch
from bench_optimize import CASES, DEVICES, case_config
from torch.profiler import ProfilerActivity, profile

from aperture_fab.io.images import prepare_targets
from aperture_fab.optics.device import resolve_device
from aperture_fab.optimize.optimizer import optimize
from aperture_fab.targets import EXAMPLES

#: Iterations profiled after one untimed warm-up design (kernels compiled, allocator warm).
ITERATIONS = 5
#: Operator rows printed per case.
ROWS = 15


def profile_case(name: str, device_name: str, iterations: int) -> None:
    case = CASES[name]
    device = resolve_device(device_name)
    config = case_config(case, str(device), iterations)
    views, shown = prepare_targets([EXAMPLES[case.target]()], config.scene.eye.view_pixels,
                                   config.scene.display.pixels)
    warm = dataclasses.replace(config.optimizer, iterations=2)
    optimize(config.scene, views, shown, warm, progress=False)
    activities = [ProfilerActivity.CPU]
    if device.type == "cuda":
        activities.append(ProfilerActivity.CUDA)
        torch.cuda.synchronize(device)
    with profile(activities=activities) as prof:
        optimize(config.scene, views, shown, config.optimizer, progress=False)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
    events = prof.key_averages()
    sort = "self_cuda_time_total" if device.type == "cuda" else "self_cpu_time_total"
    print(f"== {name} on {device}: {iterations} iterations")
    print(events.table(sort_by=sort, row_limit=ROWS, max_name_column_width=60))
    if device.type == "cuda":
        launches = sum(e.count for e in events if e.key in ("cudaLaunchKernel", "cuLaunchKernel",
                                                           "cuLaunchKernelEx"))
        print(f"kernel launches per iteration: {launches / iterations:.1f}")


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--device", choices=DEVICES, default="auto")
    parser.add_argument("--cases", nargs="+", choices=list(CASES), default=["near-eye"])
    parser.add_argument("--iterations", type=int, default=ITERATIONS)
    args = parser.parse_args(argv)
    for name in args.cases:
        profile_case(name, args.device, args.iterations)


if __name__ == "__main__":
    main()
