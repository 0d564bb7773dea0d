"""Write the project's example targets (aperture_fab.targets.EXAMPLES) as sRGB PNG files.

Usage: python examples/make_targets.py [--out DIR]   (default: examples/targets beside this file)
Each file is written to a temporary name in the same folder, then renamed over the old one, so
an interrupted run never leaves a half-written PNG.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from aperture_fab.io.atomic import write_atomic
from aperture_fab.io.images import encode_png
from aperture_fab.targets import EXAMPLES

DEFAULT_OUT = Path(__file__).resolve().parent / "targets"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Write the example target images as PNG.")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT,
                        help=f"folder to write into (default: {DEFAULT_OUT})")
    args = parser.parse_args(argv)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    for name, make in EXAMPLES.items():
        path = out / f"{name}.png"
        write_atomic(path, encode_png(make()))
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
