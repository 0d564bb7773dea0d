"""Image quality of near-eye designs against the baselines, per example target.

Run: .venv/bin/python benchmarks/bench_quality.py [--iterations N] [--targets digit-3 natural]
     [--device auto|cpu|cuda] [--json PATH]

For each target, one `aperture_fab.pipeline.design_job.design` run with the `near-eye` preset (its
iterations and plateau stop unless --iterations is given) for the resin process, then the PSNR
after the least-squares gain (dB, nominal eye position) of: the open display showing the target
(no plate), a regular pinhole array showing elemental images, the optimizer's start, the
optimized design before quantization, and the part as built (quantized holes, the process's
radius bias, the display content written). "loss" is optimized minus as built: the cost of
fabrication. "beats" says whether the part as built beats both the open display and the
pinholes.
One run per target, seeded: the same figures every run on a CPU (on CUDA the hole-gradient
scatter uses atomics, so the last digits can differ). Time per target is the whole design call
(optimize and evaluate).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from aperture_fab.config.config import resolve
from aperture_fab.config.stages import FabricationSettings
from aperture_fab.fabrication.process import PROCESSES
from aperture_fab.metrics import gain_mse, psnr_db
from aperture_fab.optics.device import resolve_device
from aperture_fab.optics.model import Renderer
from aperture_fab.pipeline.design_job import design
from aperture_fab.targets import EXAMPLES
from aperture_fab.validation.validate import layout_fractions

PRESET = "near-eye"
PROCESS = "resin"
#: The resin plate these figures were measured on, with the loss they were measured with (the
#: presets now design photomask film as made: benchmarks/bench_made_part.py).
RESIN_PLATE = {"plate.thickness_mm": 0.3, "optimizer.quantize_share": 0.4,
               "optimizer.eye_states": 16, "optimizer.min_efficiency": 0.0}
DEVICES = ("auto", "cpu", "cuda")
#: The examples with structure worth designing for (checker and marker-F are test patterns).
DEFAULT_TARGETS = ("digit-3", "letter-A", "pixel-art", "natural")
#: Columns of the table: pipeline metric name, column title.
VARIANTS = (("open", "open"), ("regular_pinholes", "pinholes"), ("initial", "initial"),
            ("optimized", "optimized"), ("as_built", "as built"))


def measure(name: str, device: str, iterations: int | None) -> dict[str, Any]:
    """Design for one example target; PSNRs (dB) per variant, whether it beats both baselines,
    seconds, iterations run and why it stopped."""
    overrides: dict[str, Any] = {"optimizer.device": device, "optimizer.iterations": iterations}
    config = resolve(PRESET, None, {**RESIN_PLATE, **overrides})
    image = EXAMPLES[name]()
    process = PROCESSES[PROCESS]
    start = time.perf_counter()
    result = design([image], config, names=[name], fabrication=FabricationSettings(process))
    seconds = time.perf_counter() - start
    assert result.part is not None
    renderer = Renderer(config.scene, device=resolve_device(device), dtype=torch.float64)
    made = torch.as_tensor(layout_fractions(result.part.layout, process.radius_bias_mm))
    shown = (result.design.displays if result.built_displays is None
             else result.built_displays)[0]
    with torch.no_grad():
        view = renderer.render(made, torch.as_tensor(shown))
    psnr = {key: result.metrics[key]["psnr_db"][0] for key, _ in VARIANTS if key != "as_built"}
    psnr["as_built"] = psnr_db(float(gain_mse(view.cpu(), torch.as_tensor(result.targets[0]))))
    return {
        "psnr_db": psnr,
        "loss_db": psnr["optimized"] - psnr["as_built"],
        "beats_baselines": psnr["as_built"] > max(psnr["open"], psnr["regular_pinholes"]),
        "seconds": seconds,
        "iterations_run": len(result.design.loss_history),
        "stopped": result.design.stopped,
        "final_loss": float(result.design.loss_history[-1]),
    }


def environment(device: torch.device) -> dict[str, Any]:
    return {
        "torch": torch.__version__,
        "python": platform.python_version(),
        "threads": torch.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "device": str(device),
        "device_name": (torch.cuda.get_device_name(device) if device.type == "cuda"
                        else platform.processor() or platform.machine()),
    }


HEADER = (f"{'target':<10} " + " ".join(f"{title:>9}" for _, title in VARIANTS)
          + f" {'loss':>6} {'beats':>6} {'iters':>6} {'stopped':>9} {'seconds':>8}")


def table_row(name: str, r: Mapping[str, Any]) -> str:
    cells = " ".join(f"{r['psnr_db'][key]:>9.2f}" for key, _ in VARIANTS)
    beats = "yes" if r["beats_baselines"] else "no"
    return (f"{name:<10} {cells} {r['loss_db']:>6.2f} {beats:>6} {r['iterations_run']:>6} "
            f"{r['stopped']:>9} "
            f"{r['seconds']:>8.1f}")


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value} must be a whole number >= 1")
    return value


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--iterations", type=_positive_int, default=None,
                        help=f"optimizer iterations (default: the {PRESET} preset's)")
    parser.add_argument("--targets", nargs="+", choices=list(EXAMPLES),
                        default=list(DEFAULT_TARGETS), metavar="NAME",
                        help=f"example targets, from {', '.join(EXAMPLES)}")
    parser.add_argument("--device", choices=DEVICES, default="auto")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the benchmark; print the table and return (and optionally write) the figures."""
    args = parse_args(argv)
    device = resolve_device(args.device)
    env = environment(device)
    iterations = args.iterations or resolve(PRESET).optimizer.iterations
    print(f"{PRESET} preset, process {PROCESS}, {iterations} iterations"
          + ("" if args.iterations else " (the preset's, with its plateau stop)")
          + f"; torch {env['torch']}, {env['threads']} threads, {env['cpu_count']} CPUs, "
          f"device {env['device']} ({env['device_name']})")
    print("PSNR after gain (dB), nominal eye position:")
    print(HEADER, flush=True)
    results = {}
    for name in args.targets:
        results[name] = measure(name, str(device), args.iterations)
        print(table_row(name, results[name]), flush=True)
    print("open: no plate, display showing the target; pinholes: regular pinhole array showing "
          "elemental images;\ninitial: the optimizer's start; optimized: before quantization; "
          "loss: optimized - as built;\nbeats: as built above both open and pinholes.")
    figures = {"environment": env, "preset": PRESET, "iterations": iterations,
               "targets": results}
    if args.json is not None:
        args.json.write_text(json.dumps(figures, indent=2) + "\n")
    return figures


if __name__ == "__main__":
    main(sys.argv[1:])
