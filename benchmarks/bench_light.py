"""The brightness floor's price: what a part gives up in image quality for light (issue 11).

Run: .venv/bin/python benchmarks/bench_light.py [--target natural] [--floors 0 0.005 0.01 0.02]
     [--iterations N] [--states 32] [--quick] [--json PATH]

For each floor (optimizer.min_efficiency), a default design (`near-eye` preset, resin) for one
target, judged as built (quantized holes, the process's radius bias, the display content fitted
to the part) over the default eye distribution (32 Halton states, PSNR after gain), and its
light budget (aperture_fab.optics.photometry): the light efficiency at the nominal eye (view
mean / the open display's with the same content), the view's luminance on a 500 cd/m2 panel
showing the content, the regime and the pupil that light implies (Watson and Yellott 2012).
The "cost" column is the 10th-percentile PSNR given up against the design without a floor.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from aperture_fab.config.config import resolve
from aperture_fab.config.stages import FabricationSettings, PhotometrySettings
from aperture_fab.fabrication.process import PROCESSES
from aperture_fab.io.images import prepare_targets
from aperture_fab.optics.model import Renderer
from aperture_fab.optics.open_view import render_open
from aperture_fab.optics.photometry import light_budget
from aperture_fab.pipeline.design_job import design
from aperture_fab.targets import EXAMPLES
from aperture_fab.validation.robustness import Variant, judge_eyes
from aperture_fab.validation.validate import layout_fractions

PRESET, PROCESS = "near-eye", "resin"
#: The resin plate these figures were measured on, with the loss they were measured with (the
#: presets now design photomask film as made: benchmarks/bench_made_part.py).
RESIN_PLATE = {"plate.thickness_mm": 0.3, "optimizer.quantize_share": 0.4,
               "optimizer.eye_states": 16}
DEFAULT_FLOORS = (0.0, 0.005, 0.01, 0.02)
QUICK = {"floors": [0.0, 0.01], "iterations": 20, "states": 8, "target": "digit-3"}


def measure(target: str, floor: float, iterations: int | None, states: int) -> dict[str, Any]:
    overrides: dict[str, Any] = {"optimizer.min_efficiency": floor}
    if iterations is not None:
        overrides["optimizer.iterations"] = iterations
    config = resolve(PRESET, None, {**RESIN_PLATE, **overrides})
    scene, process = config.scene, PROCESSES[PROCESS]
    image = EXAMPLES[target]()
    views, _ = prepare_targets([image], scene.eye.view_pixels, scene.display.pixels)
    start = time.perf_counter()
    result = design([image], config, names=[target], fabrication=FabricationSettings(process))
    seconds = time.perf_counter() - start
    assert result.part is not None
    shown = result.design.displays if result.built_displays is None else result.built_displays
    built = layout_fractions(result.part.layout, process.radius_bias_mm)
    quality = judge_eyes(scene, views, {"as_built": Variant(built, shown)}, count=states,
                         map_size=3)
    psnr = {q: float(v[0]) for q, v in quality.percentiles("as_built").items()}
    renderer = Renderer(scene, dtype=torch.float64)
    content = torch.as_tensor(shown[0], dtype=torch.float64)
    with torch.no_grad():
        view = renderer.render(torch.as_tensor(built), content, 0)
        efficiency = float(view.mean() / render_open(scene, content, 0).mean())
    budget = light_budget(efficiency, float(np.mean(shown[0])), PhotometrySettings(),
                          scene.eye.pupil_mm, scene.eye.fov_deg)
    return {"floor": floor, "efficiency": efficiency, "view_cd_m2": budget.view_cd_m2,
            "regime": budget.regime, "implied_pupil_mm": budget.implied_pupil_mm,
            "psnr_db": psnr, "seconds": seconds}


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--target", default="natural", choices=sorted(EXAMPLES))
    parser.add_argument("--floors", type=float, nargs="+", default=list(DEFAULT_FLOORS),
                        help="optimizer.min_efficiency values (0: no floor)")
    parser.add_argument("--iterations", type=int, help="design iterations (default: preset's)")
    parser.add_argument("--states", type=int, default=32, help="evaluation eye states")
    parser.add_argument("--quick", action="store_true", help="two floors, a short smoke run")
    parser.add_argument("--json", type=Path, help="also write the figures as JSON")
    args = parser.parse_args(argv)
    if args.quick:
        for key, value in QUICK.items():
            setattr(args, key, value)
    return args


def main(argv: Sequence[str] | None = None) -> list[dict[str, Any]]:
    args = parse_args(argv)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; {PRESET}, {PROCESS}, "
          f"target {args.target}, as built over {args.states} eye states; panel 500 cd/m2")
    print(f"{'floor':>7} {'efficiency':>11} {'cd/m2':>8} {'regime':>9} {'pupil mm':>9} "
          f"{'p10 dB':>7} {'median':>7} {'cost dB':>8} {'design s':>9}")
    rows = []
    for floor in args.floors:
        row = measure(args.target, floor, args.iterations, args.states)
        rows.append(row)
        cost = rows[0]["psnr_db"]["p10"] - row["psnr_db"]["p10"]
        print(f"{floor:>7.2%} {row['efficiency']:>11.3%} {row['view_cd_m2']:>8.3g} "
              f"{row['regime']:>9} {row['implied_pupil_mm']:>9.1f} {row['psnr_db']['p10']:>7.1f} "
              f"{row['psnr_db']['p50']:>7.1f} {cost:>8.1f} {row['seconds']:>9.1f}", flush=True)
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=2))
    return rows


if __name__ == "__main__":
    main()
    sys.exit(0)
