"""`python -m aperture_fab.sweep SWEEP.toml ...`: the sweep command on its own."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from aperture_fab.sweep.cluster import ClusterUnreachable
from aperture_fab.sweep.command import add_parser

#: The exit statuses of `aperture-fab` (cli/status.py) for these errors.
EXIT_BAD_INPUT = 3
EXIT_CANNOT_WRITE = 4
EXIT_NO_CLUSTER = 7


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="aperture-fab")  # usage reads "aperture-fab sweep"
    sub = parser.add_subparsers(dest="command")
    add_parser(sub)
    args = parser.parse_args(["sweep", *(sys.argv[1:] if argv is None else argv)])
    try:
        return int(args.func(args))
    except (ValueError, TypeError, FileNotFoundError) as err:  # as `aperture-fab` reports them
        print(f"aperture-fab: error: {err}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except ClusterUnreachable as err:  # a ConnectionError: not a file error
        print(f"aperture-fab: error: {err}", file=sys.stderr)
        return EXIT_NO_CLUSTER
    except OSError as err:
        print(f"aperture-fab: error: {err}", file=sys.stderr)
        return EXIT_CANNOT_WRITE


if __name__ == "__main__":
    sys.exit(main())
