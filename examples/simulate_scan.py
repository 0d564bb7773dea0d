"""Write a simulated back-lit scan of a design folder's plate as made, to try `aperture-fab
measure` without a scanner (the simulator of aperture_fab.measure.simulate).

    python examples/simulate_scan.py outputs/x --dpi 4800 --out scan.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import png

from aperture_fab.measure.job import read_design_part
from aperture_fab.measure.simulate import ScanSettings, simulate_scan


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
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    part = read_design_part(args.design)
    settings = ScanSettings(dpi=args.dpi, rotation_deg=args.rotation_deg, mirror=args.mirror,
                            blocked=args.blocked, dust_open=args.dust, dust_dark=args.dust,
                            bits=args.bits, seed=args.seed)
    scan = simulate_scan(part.layout, settings, part.corner_cut_mm)
    height, width = scan.image.shape
    with args.out.open("wb") as f:
        png.Writer(width, height, greyscale=True, bitdepth=args.bits).write(f, scan.image)
    print(f"wrote {args.out}: {width} x {height} px at {args.dpi:g} dpi, "
          f"{int(scan.truth.blocked.sum())} hole(s) blocked")


if __name__ == "__main__":
    main()
