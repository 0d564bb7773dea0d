"""Fabrication benchmark: mesh build and STL / 3MF / DXF export time and peak memory.

Each plate size runs in its own subprocess so its peak resident memory (ru_maxrss) is its own.
Times are the median of --repeats runs. Usage:

    .venv/bin/python benchmarks/bench_fabrication.py [--repeats 3] [--chord-tolerance-mm 0.002]
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from typing import TypeVar

import numpy as np

from aperture_fab.fabrication.layout import HoleLayout
from aperture_fab.fabrication.mesh import build_mesh
from aperture_fab.io.formats import dxf_bytes, stl_bytes, threemf_bytes

#: Square grids: 784, 10,000 and 90,000 holes (every cell open).
SIDES = (28, 100, 300)
PITCH_MM = 0.3
RADIUS_RANGE_MM = (0.03, 0.12)
MIN_WEB_MM = 0.05
THICKNESS_MM = 1.0
MARGIN_MM = 2.0
SEED = 0

T = TypeVar("T")


def plate_layout(side: int, seed: int) -> HoleLayout:
    """side x side cells, all with straight holes of random radius."""
    rows, cols = np.divmod(np.arange(side * side), side)
    centres = np.stack([(cols - (side - 1) / 2) * PITCH_MM, ((side - 1) / 2 - rows) * PITCH_MM], 1)
    radii = np.random.default_rng(seed).uniform(*RADIUS_RANGE_MM, side * side)
    extent = side * PITCH_MM + 2 * MARGIN_MM
    return HoleLayout(
        cells=np.stack([rows, cols], axis=1).astype(np.int64),
        centres_mm=centres,
        radii_mm=radii,
        axes=np.zeros((side * side, 2)),
        pitch_mm=(PITCH_MM, PITCH_MM),
        grid=(side, side),
        outline_mm=(extent, extent),
        thickness_mm=THICKNESS_MM,
    )


def peak_mib() -> float:
    """Peak resident memory of this process so far, MiB (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def median_seconds(work: Callable[[], T], repeats: int) -> tuple[float, T]:
    """Median wall time of `repeats` calls (at least one) and the last call's result."""
    start = time.perf_counter()
    result = work()
    times = [time.perf_counter() - start]
    for _ in range(repeats - 1):
        start = time.perf_counter()
        result = work()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


def run_one(side: int, repeats: int, tolerance_mm: float) -> dict[str, float]:
    """Time each stage for one plate; peak memory is recorded after each stage."""
    layout = plate_layout(side, SEED)
    row: dict[str, float] = {"holes": layout.count}
    build_s, mesh = median_seconds(
        lambda: build_mesh(layout, tolerance_mm, min_web_mm=MIN_WEB_MM), repeats
    )
    row.update(build_s=build_s, faces=len(mesh.faces), build_peak_mib=peak_mib())
    exports: tuple[tuple[str, Callable[[], bytes]], ...] = (
        ("stl", lambda: stl_bytes(mesh)),
        ("3mf", lambda: threemf_bytes(mesh)),
        ("dxf", lambda: dxf_bytes(layout)),
    )
    for name, export in exports:
        seconds, data = median_seconds(export, repeats)
        row[f"{name}_s"] = seconds
        row[f"{name}_mib"] = len(data) / 2**20
        row[f"{name}_peak_mib"] = peak_mib()
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--chord-tolerance-mm", type=float, default=0.002)
    parser.add_argument("--side", type=int, help="run one size in this process (internal)")
    args = parser.parse_args()
    if args.side is not None:
        print(json.dumps(run_one(args.side, args.repeats, args.chord_tolerance_mm)))
        return
    print(
        f"pitch {PITCH_MM} mm, radii {RADIUS_RANGE_MM} mm, chord tolerance "
        f"{args.chord_tolerance_mm} mm, median of {args.repeats}; peak RSS after each stage"
    )
    header = (
        f"{'holes':>7} {'faces':>10} {'build s':>8} {'peak MiB':>8} | {'STL s':>6} {'MiB':>6} "
        f"{'peak':>6} | {'3MF s':>6} {'MiB':>6} {'peak':>6} | {'DXF s':>6} {'MiB':>6} {'peak':>6}"
    )
    print(header)
    for side in SIDES:
        command = [sys.executable, __file__, "--side", str(side), "--repeats", str(args.repeats),
                   "--chord-tolerance-mm", str(args.chord_tolerance_mm)]
        done = subprocess.run(command, capture_output=True, text=True, check=True)
        r = json.loads(done.stdout.strip().splitlines()[-1])
        print(
            f"{r['holes']:>7.0f} {r['faces']:>10.0f} {r['build_s']:>8.3f} "
            f"{r['build_peak_mib']:>8.0f} | "
            + " | ".join(
                f"{r[f'{k}_s']:>6.2f} {r[f'{k}_mib']:>6.1f} {r[f'{k}_peak_mib']:>6.0f}"
                for k in ("stl", "3mf", "dxf")
            )
        )


if __name__ == "__main__":
    main()
