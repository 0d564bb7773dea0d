"""The display stack's build and backward (`Renderer.display_stack`, `optics/stack_filter.py`):
the FFT filter bank every optimizer iteration and every rival display fit runs.

Run: .venv/bin/python benchmarks/bench_stack.py [--pitch-mm 3] [--diameter-mm 2.26]
     [--oversample 1] [--repeats 9] [--quick]

The preset's scene and process; the regular array of the report's family (`regular_arrays`)
at that lattice pitch whose hole is nearest --diameter-mm, its stack sized to its holes as a
rival's is (--oversample 1: the optimizer's and a fit's; 2: the judgement's), filtered at the
levels its holes read as a rival's is (`RegularArray.min_radius_mm`) and at every level. One
random RGB display; forward and backward (the gradient in the stack's own layout, as the fused
kernels give it) timed apart, medians of --repeats after one untimed pair.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from collections.abc import Sequence

import torch

from aperture_fab.config.config import resolve
from aperture_fab.optics.model import Renderer
from aperture_fab.validation.regular import regular_arrays


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="near-eye")
    parser.add_argument("--pitch-mm", type=float, default=3.0)
    parser.add_argument("--diameter-mm", type=float, default=2.26)
    parser.add_argument("--oversample", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--quick", action="store_true", help="0.5 mm lattice, 2 repeats")
    args = parser.parse_args(argv)
    if args.quick:
        args.pitch_mm, args.diameter_mm, args.repeats = 0.5, 0.1, 2
    return args


def timed(renderer: Renderer, display: torch.Tensor, repeats: int) -> tuple[float, float]:
    """Medians (ms) of the stack's forward and backward over `repeats`, after one untimed."""
    forward, backward = [], []
    for repeat in range(repeats + 1):
        start = time.perf_counter()
        stack = renderer.display_stack(display)
        built = time.perf_counter()
        stack.backward(torch.ones_like(stack))
        done = time.perf_counter()
        if repeat > 0:
            forward.append(built - start)
            backward.append(done - built)
    return 1000 * statistics.median(forward), 1000 * statistics.median(backward)


def main(argv: Sequence[str] | None = None) -> dict[str, float]:
    args = parse_args(argv)
    config = resolve(args.preset)
    arrays = [r for r in regular_arrays(config.scene, config.fabrication.process)
              if math.isclose(r.pitch_mm, args.pitch_mm)]
    if not arrays:
        raise SystemExit(f"--pitch-mm {args.pitch_mm}: the family has no such lattice pitch; "
                         "use a multiple of the plate's cell pitch up to 3 mm.")
    rival = min(arrays, key=lambda r: abs(r.array.diameter_mm - args.diameter_mm))
    pixels = config.scene.display.pixels
    display = torch.rand(3, pixels[1], pixels[0], generator=torch.Generator().manual_seed(0),
                         requires_grad=True)
    renderers = {name: Renderer(rival.scene, oversample=args.oversample,
                                max_radius_mm=rival.max_radius_mm, min_radius_mm=smallest)
                 for name, smallest in (("", rival.min_radius_mm), ("all_levels_", None))}
    figures: dict[str, float] = {}
    for name, renderer in renderers.items():
        figures[f"{name}forward_ms"], figures[f"{name}backward_ms"] = timed(
            renderer, display, args.repeats)
    shape, first = renderers[""].shape, renderers[""].first_level
    print(f"{rival.pitch_mm:g} mm array of {rival.array.diameter_mm * 1000:.0f} um holes, "
          f"oversample {args.oversample}: {shape.levels} levels x {shape.height} x {shape.width}"
          f" x 3, transforms {shape.fft_height} x {shape.fft_width}; torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads")
    print(f"  levels {first} to {shape.levels - 1} filtered (the holes' from "
          f"{(rival.min_radius_mm or 0) * 1000:.0f} um): forward {figures['forward_ms']:.1f} "
          f"ms, backward {figures['backward_ms']:.1f} ms (medians of {args.repeats})")
    print(f"  every level filtered: forward {figures['all_levels_forward_ms']:.1f} ms, backward "
          f"{figures['all_levels_backward_ms']:.1f} ms")
    return figures


if __name__ == "__main__":
    main(sys.argv[1:])
