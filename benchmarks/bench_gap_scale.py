"""Is a gap error a loss of sharpness or a change of the picture's size? (issue 22's yield).

Run: .venv/bin/python benchmarks/bench_gap_scale.py [--targets natural line-pairs]
     [--errors-mm -0.2 0.2] [--states 8] [--quick] [--json PATH]

For each target: the design job's `design` with the default preset and process (as
bench_made_part), then the part as built (its process bias applied) rendered over --states
states of the eye distribution at the display-to-plate gap g + d for each error d, (a) over the
nominal field of view and (b) over the field whose view directions are scaled by g / (g + d).
Through every hole, direction v at gap g + d meets the display where v (1 + d / g) meets it at
g, so (b) should be the nominal view up to the display filter's change with the gap, while (a)
is the picture (g + d) / g larger. Printed per error: PSNR against the target of (a) and (b)
(mean over states, after gain; `aperture_fab.validation.validate.tolerance_analysis` judges (b))
and the signal-to-error of (b) against the nominal view, which measures what the gap error does
besides the size change.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from aperture_fab.config.config import resolve
from aperture_fab.metrics import gain_psnr_db
from aperture_fab.optics.eyes import distribution_of
from aperture_fab.optics.model import Renderer
from aperture_fab.pipeline.design_job import design
from aperture_fab.targets import EXAMPLES
from aperture_fab.validation.validate import layout_fractions, scaled_field_deg

DEFAULT_TARGETS = ("natural", "line-pairs")
#: Gap errors (mm): 2 sigma of validation's default gap_sigma_mm (0.1 mm), either way.
DEFAULT_ERRORS_MM = (-0.2, 0.2)
#: Eye states each view is averaged over (tolerance_analysis's TOLERANCE_EYE_STATES).
STATES = 8
#: --quick: one target, a 3-iteration design, 2 eye states (a smoke run, not figures).
QUICK_TARGETS, QUICK_ITERATIONS, QUICK_STATES = ["digit-3"], 3, 2


def measure(name: str, errors_mm: Sequence[float], states: int, iterations: int | None
            ) -> dict[str, Any]:
    overrides = {} if iterations is None else {"optimizer.iterations": iterations}
    config = resolve("near-eye", None, overrides)
    fabrication = config.fabrication
    result = design([EXAMPLES[name]()], config, names=[name], fabrication=fabrication)
    assert result.part is not None
    shown = result.design.displays if result.built_displays is None else result.built_displays
    scene = config.scene
    batch = distribution_of(scene.eye).evaluation_states(states)
    made = torch.as_tensor(layout_fractions(result.part.layout,
                                            fabrication.process.radius_bias_mm))
    display = torch.as_tensor(shown[0])
    gap = scene.plate.gap_mm

    def views(gap_mm: float, scale: float) -> np.ndarray:
        moved = replace(scene, plate=replace(scene.plate, gap_mm=gap_mm), eye=replace(
            scene.eye, fov_deg=scaled_field_deg(scene.eye.fov_deg, scale)))
        renderer = Renderer(moved, dtype=torch.float64)
        with torch.no_grad():
            return renderer.render_states(made, renderer.display_stack(display),
                                          batch).numpy()

    def psnr(view: np.ndarray) -> float:
        return float(np.mean(gain_psnr_db(view[None], result.targets[:1])))

    nominal = views(gap, 1.0)
    rows = []
    for error in errors_mm:
        unsized = views(gap + error, 1.0)
        sized = views(gap + error, gap / (gap + error))
        agreement = 10 * math.log10(float(np.mean(nominal**2))
                                    / float(np.mean((sized - nominal) ** 2)))
        rows.append({"error_mm": error, "scale": (gap + error) / gap,
                     "psnr_nominal_field_db": psnr(unsized), "psnr_scaled_field_db": psnr(sized),
                     "scaled_vs_nominal_view_db": agreement})
    return {"target": name, "gap_mm": gap, "states": states, "nominal_psnr_db": psnr(nominal),
            "errors": rows}


def main(argv: Sequence[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--targets", nargs="+", default=list(DEFAULT_TARGETS),
                        choices=sorted(EXAMPLES))
    parser.add_argument("--errors-mm", nargs="+", type=float, default=list(DEFAULT_ERRORS_MM))
    parser.add_argument("--states", type=int, default=STATES)
    parser.add_argument("--quick", action="store_true", help="a smoke run: one target, tiny")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    targets, states, iterations = args.targets, args.states, None
    if args.quick:
        targets, states, iterations = QUICK_TARGETS, QUICK_STATES, QUICK_ITERATIONS
    results = []
    for name in targets:
        row = measure(name, args.errors_mm, states, iterations)
        results.append(row)
        print(f"{name}: gap {row['gap_mm']:g} mm, nominal {row['nominal_psnr_db']:.2f} dB "
              f"({states} eye states)")
        for e in row["errors"]:
            print(f"  gap error {e['error_mm']:+.2f} mm (picture x{e['scale']:.3f}): "
                  f"{e['psnr_nominal_field_db']:.2f} dB over the nominal field, "
                  f"{e['psnr_scaled_field_db']:.2f} dB at the picture's size; that view "
                  f"against the nominal one: {e['scaled_vs_nominal_view_db']:.1f} dB",
                  flush=True)
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=2) + "\n")
    return results


if __name__ == "__main__":
    main(sys.argv[1:])
