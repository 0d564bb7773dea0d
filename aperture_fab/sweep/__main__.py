"""`python -m aperture_fab.sweep SWEEP.toml ...`: the sweep command on its own."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from aperture_fab.sweep.command import add_parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m aperture_fab.sweep")
    sub = parser.add_subparsers(dest="command")
    add_parser(sub)
    args = parser.parse_args(["sweep", *(sys.argv[1:] if argv is None else argv)])
    try:
        return int(args.func(args))
    except (ValueError, TypeError, FileNotFoundError) as err:
        print(f"aperture-fab: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
