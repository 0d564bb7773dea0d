"""A regular rival's judged p10 and light at the eye against the length of its display fit
(issue 22: the measurement behind `validation.made_part.RIVAL_FIT_SHARES`).

Run: .venv/bin/python benchmarks/bench_rival_fit.py [--target natural] [--pitch-mm 1.75]
     [--fits 0 10 20 40 80] [--states 32] [--copies 4] [--quick] [--json PATH]

The preset's scene and process; the regular array of that lattice pitch with the largest hole
the process makes in a cell that large (`regular_arrays`, the report's family); its display
fitted from the
elemental images (`fit_display` on the as-made loss, as the report fits a rival) for each
length in --fits (0: the elemental images), each a separate fit, then judged as the report
judges the made part (`regular_front`: --copies made copies x --states eye states). A fit lowers
the mean loss over eye states; the table shows what that does to the 10th percentile and to
the light at the eye, by which the part and its rivals are compared.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from aperture_fab.config.config import resolve
from aperture_fab.io.images import prepare_targets
from aperture_fab.optics.eyes import distribution_of
from aperture_fab.optimize.optimizer import fit_display
from aperture_fab.targets import EXAMPLES
from aperture_fab.validation.regular import RegularArray, regular_arrays, regular_front

QUICK = {"fits": [0, 2], "states": 4, "copies": 1}


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--target", choices=sorted(EXAMPLES), default="natural")
    parser.add_argument("--preset", default="near-eye")
    parser.add_argument("--pitch-mm", type=float, default=1.75)
    parser.add_argument("--fits", type=int, nargs="+", default=[0, 10, 20, 40, 80])
    parser.add_argument("--states", type=int, default=32)
    parser.add_argument("--copies", type=int, default=4)
    parser.add_argument("--quick", action="store_true", help="fits 0 and 2, 4 states, 1 copy")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = parser.parse_args(argv)
    if args.quick:
        vars(args).update(QUICK)
    return args


def main(argv: Sequence[str] | None = None) -> list[dict[str, Any]]:
    args = parse_args(argv)
    config = resolve(args.preset)
    scene, settings, process = config.scene, config.optimizer, config.fabrication.process
    targets, _ = prepare_targets([EXAMPLES[args.target]()], scene.eye.view_pixels,
                                 scene.display.pixels, names=[args.target])
    arrays = [r for r in regular_arrays(scene, process) if math.isclose(r.pitch_mm, args.pitch_mm)]
    if not arrays:
        raise SystemExit(f"--pitch-mm {args.pitch_mm}: the family has no such lattice pitch; "
                         "use a multiple of the plate's cell pitch up to 3 mm.")
    rival = max(arrays, key=lambda r: r.array.diameter_mm)
    states = distribution_of(scene.eye).evaluation_states(args.states)
    print(f"{args.target}, {process.name}: the {rival.pitch_mm:g} mm array of "
          f"{rival.array.diameter_mm * 1000:.0f} um holes, {args.copies} made copies x "
          f"{args.states} eye states; torch {torch.__version__}, {torch.get_num_threads()} "
          "threads")
    rows = []
    for iterations in args.fits:
        def fit(regular: RegularArray, shown: np.ndarray, n: int = iterations
                ) -> list[np.ndarray]:
            return [fit_display(regular.scene, targets, regular.array.open_fraction, shown,
                                settings, n, optics=regular.optics,
                                max_radius_mm=regular.max_radius_mm,
                                min_radius_mm=regular.min_radius_mm)[0]]

        front = regular_front(targets, [rival], states, args.copies,
                              fit=fit if iterations > 0 else None)
        row = {"fit_iterations": iterations, "p10_db": float(front.p10[0].mean()),
               "p50_db": float(front.p50[0].mean()), "eye_level": float(front.eye_level[0])}
        rows.append(row)
        print(f"  fit {iterations:4d}: p10 {row['p10_db']:.2f} dB, p50 {row['p50_db']:.2f} dB, "
              f"light at the eye {row['eye_level']:.3%}", flush=True)
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=2))
    return rows


if __name__ == "__main__":
    main(sys.argv[1:])
