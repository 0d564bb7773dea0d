"""Time and peak memory of STEP export (aperture_fab.fabrication.step.step_bytes) against the hole
count.

Run: .venv/bin/python benchmarks/bench_step.py [--repeats 3] [--sides 28 50 100] [--tilted]

Each size runs in a fresh child process so that peak memory (ru_maxrss) belongs to that size
alone ("of which imports": the peak before the first export: Python, numpy, OCCT and whatever
the aperture_fab package imports); the time is the median of the repeats (one run for 10,000
holes unless asked).
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time

import numpy as np

from aperture_fab.fabrication.layout import HoleLayout

#: Cell pitch and plate thickness of the benchmark plates (typical resin print), mm.
PITCH_MM = 0.5
THICKNESS_MM = 0.3
MARGIN_MM = 1.0
#: Hole radii are drawn uniformly in this range, mm (web >= 0.1 mm at this pitch).
RADIUS_RANGE_MM = (0.05, 0.2)
#: Chief-ray tilt of the tilted variant: lateral shift per mm of z per mm off axis.
TILT_PER_MM = 0.05
#: Above this many holes, one run per size unless --repeats says otherwise explicitly.
CHEAP_HOLES = 3000


def grid_layout(side: int, tilted: bool, seed: int = 0) -> HoleLayout:
    """A side x side grid of holes with random radii; straight or chief-ray tilted."""
    rng = np.random.default_rng(seed)
    rows, cols = np.meshgrid(np.arange(side), np.arange(side), indexing="ij")
    cells = np.stack([rows.ravel(), cols.ravel()], axis=1).astype(np.int64)
    centres = np.stack(
        [(cells[:, 1] - (side - 1) / 2) * PITCH_MM, ((side - 1) / 2 - cells[:, 0]) * PITCH_MM],
        axis=1,
    )
    radii = rng.uniform(*RADIUS_RANGE_MM, size=len(cells))
    axes = centres * TILT_PER_MM if tilted else np.zeros_like(centres)
    size = side * PITCH_MM + 2 * MARGIN_MM
    return HoleLayout(
        cells=cells,
        centres_mm=centres,
        radii_mm=radii,
        axes=axes,
        pitch_mm=(PITCH_MM, PITCH_MM),
        grid=(side, side),
        outline_mm=(size, size),
        thickness_mm=THICKNESS_MM,
    )


def measure(side: int, repeats: int, tilted: bool) -> dict[str, float]:
    """Run step_bytes `repeats` times in this process; median seconds, peak RSS, file size."""
    from OCP import STEPControl  # noqa: F401  # the kernel's own footprint belongs to the baseline

    from aperture_fab.fabrication.step import step_bytes

    layout = grid_layout(side, tilted)
    baseline_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: KiB
    times, size = [], 0
    for _ in range(repeats):
        start = time.perf_counter()
        size = len(step_bytes(layout))
        times.append(time.perf_counter() - start)
    peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: KiB
    return {
        "holes": layout.count,
        "seconds": statistics.median(times),
        "runs": repeats,
        "peak_mib": peak_mib,
        "baseline_mib": baseline_mib,
        "file_mb": size / 1e6,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sides", type=int, nargs="+", default=[28, 50, 100])
    parser.add_argument("--repeats", type=int, default=None)
    parser.add_argument("--tilted", action="store_true", help="chief-ray tilted holes")
    parser.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child is not None:
        print(json.dumps(measure(args.child, args.repeats or 1, args.tilted)))
        return
    print(f"{'holes':>7} {'seconds':>8} {'runs':>4} {'peak MiB':>9} {'of which imports':>17} "
          f"{'file MB':>8}")
    for side in args.sides:
        repeats = args.repeats or (3 if side * side <= CHEAP_HOLES else 1)
        command = [sys.executable, __file__, "--child", str(side), "--repeats", str(repeats)]
        if args.tilted:
            command.append("--tilted")
        result = json.loads(subprocess.run(command, check=True, capture_output=True,
                                           text=True).stdout)
        print(f"{result['holes']:>7} {result['seconds']:>8.2f} {result['runs']:>4} "
              f"{result['peak_mib']:>9.0f} {result['baseline_mib']:>17.0f} "
              f"{result['file_mb']:>8.1f}")


if __name__ == "__main__":
    main()
