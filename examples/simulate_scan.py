"""Write a simulated back-lit scan of a design folder's plate as made, to try `aperture-fab
measure` without a scanner (the simulator of aperture_fab.measure.simulate). The plate is made
with the design's process errors (its radius bias and sigma, its position sigma) unless the
flags say otherwise.

    python examples/simulate_scan.py outputs/x --dpi 4800 --out scan.png
    python examples/simulate_scan.py outputs/x --coupon --dpi 4800 --out coupon.png

With --coupon it scans the design folder's calibration coupon instead (coupon.stl), whose
holes under 70 % of the process's smallest radius (as made) stay closed unless
--closed-below-um says otherwise.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import png

from aperture_fab.measure.job import read_design_coupon, read_design_part
from aperture_fab.measure.simulate import ScanSettings, simulate_scan
from aperture_fab.pipeline.saved import CONFIG_NAME, read_config

#: Micrometres per millimetre (the flags take um).
UM = 1000.0
#: A simulated coupon's holes stay closed under this share of the process's smallest radius.
COUPON_CLOSED_SHARE = 0.7


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("design", type=Path, help="a design folder (design.toml, holes.csv)")
    parser.add_argument("--out", type=Path, required=True, help="the PNG to write")
    parser.add_argument("--dpi", type=float, default=4800.0)
    parser.add_argument("--rotation-deg", type=float, default=7.0)
    parser.add_argument("--mirror", action="store_true", help="scan it from the wrong side")
    parser.add_argument("--blocked", type=int, default=1, help="holes that did not open")
    parser.add_argument("--dust", type=int, default=2, help="specks of each kind")
    parser.add_argument("--bits", type=int, choices=(8, 16), default=16)
    parser.add_argument("--radius-bias-um", type=float, default=None,
                        help="made radius - drawn, um (default: the design's process's)")
    parser.add_argument("--radius-sigma-um", type=float, default=None,
                        help="random radius error, um (default: the process's)")
    parser.add_argument("--position-sigma-um", type=float, default=None,
                        help="random position error per axis, um (default: the process's)")
    parser.add_argument("--coupon", action="store_true",
                        help="scan the design's calibration coupon instead of its plate")
    parser.add_argument("--closed-below-um", type=float, default=None,
                        help="holes under this made radius stay closed, um (default: 0 for "
                        "the plate, 70 %% of the process's smallest radius for the coupon)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    config = read_config(args.design / CONFIG_NAME)
    process = config.fabrication.process
    part = read_design_coupon(args.design)[1] if args.coupon else read_design_part(args.design)
    smallest_r = process.min_hole_for(config.scene.plate.thickness_mm) / 2

    def mm(flag: float | None, default_mm: float) -> float:
        return default_mm if flag is None else flag / UM

    settings = ScanSettings(dpi=args.dpi, rotation_deg=args.rotation_deg, mirror=args.mirror,
                            blocked=args.blocked, dust_open=args.dust, dust_dark=args.dust,
                            bits=args.bits, seed=args.seed,
                            radius_bias_mm=mm(args.radius_bias_um, process.radius_bias_mm),
                            radius_sigma_mm=mm(args.radius_sigma_um, process.radius_sigma_mm),
                            position_sigma_mm=mm(args.position_sigma_um,
                                                 process.position_sigma_mm),
                            closed_below_mm=mm(args.closed_below_um, COUPON_CLOSED_SHARE
                                               * smallest_r if args.coupon else 0.0))
    scan = simulate_scan(part.layout, settings, part.corner_cut_mm)
    height, width = scan.image.shape
    with args.out.open("wb") as f:
        png.Writer(width, height, greyscale=True, bitdepth=args.bits).write(f, scan.image)
    print(f"wrote {args.out}: {width} x {height} px at {args.dpi:g} dpi, "
          f"{int(scan.truth.blocked.sum())} hole(s) blocked")


if __name__ == "__main__":
    main()
