"""The `aperture-fab sweep` subcommand: argparse wiring and the run, kept apart from cli.py so
the heavy optional parts (Ray, Optuna, pyarrow) load only when a sweep runs."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

__all__ = ["add_parser", "run", "EPILOG"]

DEFAULT_OUT = Path("outputs/sweep")
#: Exit statuses: some points failed (recorded; the tables are written); interrupted (Ctrl-C).
EXIT_FAILED_POINTS = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130

EPILOG = """\
a sweep file (TOML; paths relative to it):

  [sweep]
  mode = "grid"                         # or "search": Optuna's NSGA-II multi-objective sampler
  targets = ["targets/natural.png"]
  objectives = ["maximize eye_p10_psnr_db", "maximize light_efficiency"]
  preset = "near-eye"                   # optional; config = "base.toml" for a base config
  # search only: trials = 40, seed = 0, population = 16 (points per generation)

  [base]                                # fixed dotted config keys, as in a config file
  "optimizer.iterations" = 300
  "validation.tolerance_samples" = 8

  [grid]                                # mode = "grid": every combination
  "plate.gap_mm" = [8.0, 10.0, 12.0]
  "plate.cells" = [[24, 24], [32, 32]]  # a pair-valued key takes a list of pairs
  "process.name" = ["resin", "etched-foil"]
  "eye.eyebox_mm" = [4.0, 6.0]

  [space]                               # mode = "search" instead of [grid]
  "plate.gap_mm" = { low = 6.0, high = 14.0 }
  "plate.pitch_mm" = { low = 0.2, high = 0.6, log = true }
  "process.name" = { choices = ["resin", "etched-foil"] }

Keys are any config key (`aperture-fab design` docs: [display] [plate] [eye] [optimizer]) plus
process.name and the [process], [fabrication] and [validation] tables' keys. Objectives:
maximize or minimize one of eye_p10_psnr_db eye_p50_psnr_db eye_p90_psnr_db nominal_psnr_db
light_efficiency luminance_cd_m2 retinal_illuminance_td contrast_ratio fov_x_deg fov_y_deg
hole_count rule_violations seconds. Every point is checked before anything runs.

examples:
  aperture-fab sweep examples/sweep.toml --out outputs/sweep
  aperture-fab sweep sweep.toml --workers 2 --out outputs/sweep        # local Ray, 2 CPUs
  aperture-fab sweep sweep.toml --address auto --out /shared/sweep     # on this Ray cluster
  aperture-fab sweep sweep.toml --dry-run                              # check and list points

Each point is a full design job in OUT/points/<id>/ (id: a hash of its settings); its
point.json, written last, marks it finished. Resuming is automatic: run the same command again
and finished points are skipped (failed ones too, unless --retry-failed), a search replays its
seed and continues where it stopped. A failed point is recorded with its error and never stops
the sweep. Ctrl-C keeps every finished point. Results: OUT/results.csv, results.parquet,
pareto.csv and sweep.html (the Pareto plot; click a point for its report). Exit status 0; 1
when some points failed (recorded); 2 when Ray, Optuna or pyarrow is missing; 3 for an error in
the sweep file (nothing ran); 130 when interrupted. Cluster set-up: docs/sweep.md.
"""


def add_parser(subparsers: Any) -> None:
    """Register `sweep` on an argparse subparsers object."""
    p = subparsers.add_parser(
        "sweep", help="sweep design settings (grid or search), on Ray",
        description="Run a design job for each point of a grid or a multi-objective search "
        "over config keys, in parallel on a local Ray instance (started by this command) or an "
        "existing Ray cluster (--address), and rank the points: the table of every point's "
        "figures, the Pareto front over the objectives, and an HTML page.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("sweep_file", type=Path, metavar="SWEEP.toml", help="the sweep file")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, metavar="FOLDER",
                   help=f"the sweep's folder (default {DEFAULT_OUT}); on a cluster, a folder "
                   "every node sees, or use --gather")
    p.add_argument("--address", metavar="ADDRESS",
                   help="an existing Ray cluster: 'auto' (this node's), HOST:6379, or "
                   "ray://HOST:10001 (Ray client); default: start a local instance")
    p.add_argument("--workers", type=int, metavar="N",
                   help="local: CPUs of the local Ray instance (default: all cores); with "
                   "--address: the most points running at once (default: as the cluster fits)")
    p.add_argument("--cpus-per-point", type=int, default=1, metavar="N",
                   help="CPUs per point: its torch and numba threads (default 1)")
    p.add_argument("--retry-failed", action="store_true",
                   help="run failed points again (finished ok points are always skipped)")
    p.add_argument("--gather", action="store_true",
                   help="workers send each point's files back to this machine (for clusters "
                   "without a shared folder)")
    p.add_argument("--serial", action="store_true",
                   help="run the points one after another in this process, without Ray")
    p.add_argument("--dry-run", action="store_true",
                   help="check the sweep file and every point, list them, run nothing")
    p.add_argument("-q", "--quiet", action="store_true", help="no line per finished point")
    p.set_defaults(func=run)


def _positive(value: int | None, flag: str) -> None:
    if value is not None and value < 1:
        raise ValueError(f"{flag} {value}: give a whole number >= 1.")


def run(args: argparse.Namespace) -> int:
    """Run the sweep; errors in the sweep file raise ValueError (the CLI prints them)."""
    from aperture_fab.sweep.results import write_results
    from aperture_fab.sweep.run import RunOptions, require, resolve_point, run_sweep
    from aperture_fab.sweep.spec import check_points, grid_points, load_spec

    _positive(args.workers, "--workers")
    _positive(args.cpus_per_point, "--cpus-per-point")
    spec = load_spec(args.sweep_file)
    if args.dry_run:
        points = grid_points(spec) if spec.mode == "grid" else []
        check_points(spec, points,
                     lambda o: resolve_point(spec.preset, spec.base_file, o))
        for n, point in enumerate(points, 1):
            print(f"{n:>4}  {point.id}  {point.label()}")
        what = f"{len(points)} grid points" if points else (
            f"a search of {spec.trials} trials over {', '.join(spec.swept_keys)}")
        print(f"{args.sweep_file}: ok, {what}; objectives "
              f"{', '.join(str(o) for o in spec.objectives)}")
        return 0
    try:
        if not args.serial:
            require("ray")
        if spec.mode == "search":
            require("optuna")
        require("pyarrow")
    except ImportError as err:
        print(f"aperture-fab sweep: {err}", file=sys.stderr)
        return EXIT_USAGE
    options = RunOptions(out=args.out, backend="serial" if args.serial else "ray",
                         address=args.address, workers=args.workers,
                         cpus_per_point=args.cpus_per_point, retry_failed=args.retry_failed,
                         gather=args.gather)

    def log(line: str) -> None:
        if not args.quiet:
            print(line, flush=True)

    outcome = run_sweep(spec, options, log)
    paths = write_results(args.out, spec, outcome.points, outcome.records)
    ok = sum(r["status"] == "ok" for r in outcome.records.values())
    print(f"{len(outcome.points)} points: {ok} ok, {outcome.failed} failed, "
          f"{len(outcome.points) - len(outcome.records)} not run; {outcome.ran} ran now, "
          f"{outcome.skipped} finished before; wrote {paths['sweep.html']}")
    if outcome.interrupted:
        print("interrupted: the finished points are recorded; run the same command again to "
              "continue.", file=sys.stderr)
        return EXIT_INTERRUPTED
    if outcome.failed:
        print(f"{outcome.failed} point(s) failed; their errors are in results.csv and "
              "points/<id>/point.json (--retry-failed runs them again).", file=sys.stderr)
        return EXIT_FAILED_POINTS
    return 0
