"""The mesh re-trace (trace_mesh_view): seconds per view of a default-sized plate, and its
agreement with the exact model.

Run: .venv/bin/python benchmarks/bench_retrace.py [--repeats 3] [--samples N] [--seed 0]
     [--target natural|star|...] [--design DIR] [--json PATH]

The case is the default design job's (`aperture-fab design`: preset near-eye, process photomask):
an 80 x 80 plate of 0.005 mm film with random open fractions within the process's bounds (seed
0), made with make_part, written to STL and read back as the job traces it, behind an example
target (--target: natural by default; star, a Siemens star's dense edges) on the 400 x 400
display, seen on the 128 x 128 view from the nominal eye point with the default samples (the
chord budget: 8 per pair here). With --design DIR, a folder
written by `aperture-fab design` instead: its plate.stl, design.toml and the display content it
was judged with (design.npz), against its views.npz.

It prints the median wall and CPU (all threads) seconds of trace_mesh_view over --repeats
calls, after one untimed call that loads (or, on a fresh install, compiles: ~10 s) its Numba
kernels, whose seconds it also prints; the rays and (view pixel, hole) pairs traced; and the
PSNR of the traced view against the exact model's view of the same holes (the closed-form model
of the holes as drawn, aperture_fab.optics.model, float64; peak: the model view's maximum), with
the PSNR the tracer's own standard errors predict (the Monte Carlo noise alone; the rest is the
polygons against circles and the model's approximations).

Measured on 2 shared cores (AMD EPYC, busy with other jobs), rays (12 per pair) before chords
-> chords (8 per pair), median CPU s: star 44.9 -> 47.1 dB (7.9 -> 6.4 s), natural 55.6 -> 56.4
dB (6.8 -> 7.2 s); wall s, less loaded: star 5.7 -> 6.3, natural 6.9 -> 7.0. On near-eye
designs (the display content optimized for the target) the chords matter most: a Siemens star
30.0 -> 37.3 dB, the natural photo 46.0 -> 47.8 dB (docs/validation.md). Earlier, before its
Numba kernels and clear cylinders, the tracer took 20.9 s for the natural design's view.
Timings depend on the machine and its load:
compare figures only from one machine, e.g. as
`taskset -c 0,1 .venv/bin/python benchmarks/bench_retrace.py` on a quiet one.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numba
import numpy as np
import torch

from aperture_fab.config.config import resolve
from aperture_fab.config.presets import DEFAULT_PRESET
from aperture_fab.fabrication.mesh import PlateMesh
from aperture_fab.fabrication.part import design_bounds, make_part
from aperture_fab.io.formats import read_stl, stl_bytes
from aperture_fab.io.images import prepare_targets
from aperture_fab.optics.model import Renderer
from aperture_fab.optics.scene import Scene
from aperture_fab.targets import EXAMPLES
from aperture_fab.validation.retrace import trace_mesh_view
from aperture_fab.validation.validate import layout_fractions

TARGET = "natural"


def default_case(seed: int, target: str) -> tuple[Scene, PlateMesh, np.ndarray, np.ndarray]:
    """(scene, mesh read back from STL, display (C, H, W), exact model view (C, ny, nx))."""
    config = resolve(DEFAULT_PRESET)
    scene = config.scene
    process = config.fabrication.process
    low, high = design_bounds(scene, process)
    fractions = np.random.default_rng(seed).uniform(low, high, scene.plate.cells[::-1])
    part = make_part(fractions, scene, config.fabrication)
    _, on_display = prepare_targets([EXAMPLES[target]()], scene.eye.view_pixels,
                                    scene.display.pixels)
    display = on_display[0]
    with torch.no_grad():
        exact = Renderer(scene, dtype=torch.float64).render(
            torch.as_tensor(layout_fractions(part.layout)), torch.as_tensor(display)).numpy()
    return scene, read_stl(stl_bytes(part.mesh)), display, exact


def design_case(folder: Path) -> tuple[Scene, PlateMesh, np.ndarray, np.ndarray]:
    """The same from a folder `aperture-fab design` wrote (its first target)."""
    from aperture_fab.pipeline.saved import read_config, read_design

    config = read_config(folder / "design.toml")
    design = read_design(folder / "design.npz")
    shown = design.displays if design.built_displays is None else design.built_displays
    with np.load(folder / "views.npz") as views:
        exact = views[f"quantized/{design.names[0]}"]
    return (config.scene, read_stl((folder / "plate.stl").read_bytes()), shown[0],
            exact.reshape(shown[0].shape[0], *exact.shape[-2:]))


def psnr(view: np.ndarray, reference: np.ndarray, mse: float | None = None) -> float:
    error = float(np.mean((view - reference) ** 2)) if mse is None else mse
    return 10 * math.log10(float(reference.max()) ** 2 / error)


def measure(case: tuple[Scene, PlateMesh, np.ndarray, np.ndarray], repeats: int,
            samples: int | None, seed: int) -> dict[str, Any]:
    scene, mesh, display, exact = case
    start = time.perf_counter()
    traced = trace_mesh_view(mesh, scene, display, 0, samples, seed)
    first = time.perf_counter() - start
    seconds, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        traced = trace_mesh_view(mesh, scene, display, 0, samples, seed)
        seconds.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return {"median_s": statistics.median(seconds), "seconds": seconds,
            "median_cpu_s": statistics.median(cpu), "first_call_s": first,
            "samples_per_pair": traced.samples_per_pixel, "rays": traced.rays_cast,
            "pairs": traced.pairs, "psnr_vs_exact_db": psnr(traced.view, exact),
            "noise_psnr_db": psnr(traced.view, exact, float(np.mean(traced.stderr**2))),
            "stderr_rms": math.sqrt(float(np.mean(traced.stderr**2)))}


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="timed calls; the median is quoted")
    parser.add_argument("--samples", type=int, default=None,
                        help="rays per (view pixel, hole) pair (default: the ray budget's)")
    parser.add_argument("--seed", type=int, default=0, help="plate and tracer seed")
    parser.add_argument("--target", default=TARGET, choices=sorted(EXAMPLES),
                        help="example target shown on the display (default case)")
    parser.add_argument("--design", type=Path, default=None,
                        help="a folder `aperture-fab design` wrote, instead of the default case")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    args = parse_args(argv)
    case = design_case(args.design) if args.design is not None else default_case(args.seed,
                                                                               args.target)
    scene = case[0]
    print(f"numba {numba.__version__}, {numba.get_num_threads()} threads; "
          f"{'design ' + str(args.design) if args.design else DEFAULT_PRESET + ' default case'}: "
          f"{scene.plate.cells[0]} x {scene.plate.cells[1]} cells, "
          f"{scene.plate.thickness_mm:g} mm, view {scene.eye.view_pixels[0]} x "
          f"{scene.eye.view_pixels[1]}")
    row = measure(case, args.repeats, args.samples, args.seed)
    print(f"trace_mesh_view: {row['median_s']:.2f} s median of {args.repeats} "
          f"({', '.join(f'{s:.2f}' for s in row['seconds'])}; first call "
          f"{row['first_call_s']:.2f} s); CPU {row['median_cpu_s']:.2f} s median, all threads")
    print(f"  {row['rays']:,} rays, {row['pairs']:,} pairs, {row['samples_per_pair']} per pair")
    print(f"  traced vs exact model: {row['psnr_vs_exact_db']:.2f} dB (Monte Carlo noise alone: "
          f"{row['noise_psnr_db']:.2f} dB, stderr rms {row['stderr_rms']:.3g})")
    if args.json is not None:
        args.json.write_text(json.dumps(row, indent=2))
    return row


if __name__ == "__main__":
    main()
    sys.exit(0)
