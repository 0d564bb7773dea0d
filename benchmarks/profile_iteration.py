"""Where an optimizer iteration's time goes: torch.profiler over a few iterations of a
bench_optimize case, its operators and GPU kernels by self time, and launches per iteration.

    python benchmarks/profile_iteration.py --device cuda --cases near-eye nominal seed-28
    python benchmarks/profile_iteration.py --device cuda --syncs --cases nominal

A tool for finding what bounds a case (launch overhead, one kernel, host bookkeeping); the
figures to quote are bench_optimize's, as the profiler slows what it watches. --syncs lists
instead where an iteration waits for the GPU (torch's sync debug mode: each synchronizing
operation, by the project's innermost line that called it, per iteration): every such wait
drains the GPU's queue, so the host's work after it is not overlapped with the GPU's.
"""

from __future__ import annotations

import argparse
import dataclasses
import traceback
import warnings
from collections import Counter
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

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


@contextmanager
def counting_syncs() -> Iterator[Counter[str]]:
    """Count the synchronizing CUDA operations run inside, by the project's innermost line
    that called each (torch's sync debug mode)."""
    sites: Counter[str] = Counter()
    package = str(Path(__file__).resolve().parents[1] / "aperture_fab")

    def record(message, category, filename, lineno, file=None, line=None):
        if "synchroniz" not in str(message):
            return
        ours = [f for f in traceback.extract_stack() if f.filename.startswith(package)]
        where = ours[-1] if ours else traceback.extract_stack()[-3]
        sites[f"{Path(where.filename).name}:{where.lineno} ({where.name})"] += 1

    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = record
        torch.cuda.set_sync_debug_mode("warn")
        try:
            yield sites
        finally:
            torch.cuda.set_sync_debug_mode("default")


def _print_sites(sites: Counter[str], per: int, rows: int = 25) -> None:
    for where, count in sites.most_common(rows):
        print(f"{count / per:8.2f}  {where}")
    print(f"{sum(sites.values()) / per:8.2f}  in all")


def sync_sites(name: str, device_name: str, iterations: int) -> None:
    """Print where `iterations` optimizer iterations of a case synchronize with the GPU."""
    case = CASES[name]
    device = resolve_device(device_name)
    if device.type != "cuda":
        raise SystemExit("--syncs needs CUDA: only a GPU's queue can be waited for.")
    config = case_config(case, str(device), iterations)
    views, shown = prepare_targets([EXAMPLES[case.target]()], config.scene.eye.view_pixels,
                                   config.scene.display.pixels)
    optimize(config.scene, views, shown, dataclasses.replace(config.optimizer, iterations=2),
             progress=False)
    with counting_syncs() as sites:
        optimize(config.scene, views, shown, config.optimizer, progress=False)
    print(f"== {name} on {device}: synchronizations per iteration ({iterations} iterations)")
    _print_sites(sites, iterations)


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--device", choices=DEVICES, default="auto")
    parser.add_argument("--cases", nargs="+", choices=list(CASES), default=["near-eye"])
    parser.add_argument("--iterations", type=int, default=ITERATIONS)
    parser.add_argument("--syncs", action="store_true",
                        help="list where an iteration waits for the GPU instead of profiling")
    args = parser.parse_args(argv)
    for name in args.cases:
        (sync_sites if args.syncs else profile_case)(name, args.device, args.iterations)


if __name__ == "__main__":
    main()
