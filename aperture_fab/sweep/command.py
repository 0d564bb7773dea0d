"""The `aperture-fab sweep` subcommand: argparse wiring and the run, kept apart from cli/ so
the heavy optional parts (Ray, Optuna, pyarrow) load only when a sweep runs."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

__all__ = ["add_parser", "run", "EPILOG"]

DEFAULT_OUT = Path("outputs/sweep")
#: Exit statuses: some points failed or were lost (recorded; the tables are written); a
#: missing package; stopped by a signal: 128 + its number (130 Ctrl-C, 143 SIGTERM).
#: The cluster out of reach is cli.EXIT_NO_CLUSTER (7), from cluster.ClusterUnreachable.
EXIT_FAILED_POINTS = 1
EXIT_USAGE = 2
EXIT_SIGNAL_BASE = 128
#: --dry-run lists every point up to this many, else the first LIST_HEAD of them.
LIST_ALL_UP_TO = 50
LIST_HEAD = 20
MB = 1e6
GB = 1e9

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
point.json, written last, marks it finished, and results.csv gains its row at once. Resuming is
automatic: run the same command again and finished points are skipped (failed ones unless
--retry-failed, lost ones unless --retry-lost); a search tells Optuna what finished and asks
for the rest. A point the checks `design` runs first refuse, or whose job fails, is "failed"
with its error; one whose worker or node went away runs again (--lost-retries), "lost" if it
never comes back. Ctrl-C or SIGTERM keep every finished point and write the tables. Results:
OUT/results.csv, results.parquet, pareto.csv and sweep.html (the Pareto plot; click a point for
its report). Exit status 0; 1 when some points failed or were lost (recorded), or when
--dry-run finds points the checks refuse; 2 when Ray, Optuna or pyarrow is missing; 3 for an
error in the sweep file (nothing ran); 7 when the cluster at --address cannot be reached
within --connect-timeout; 130 (Ctrl-C) or 143 (SIGTERM) when stopped. Cluster set-up and
token authentication: docs/sweep.md.
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
                   help=f"the sweep's folder (default {DEFAULT_OUT}); workers that do not see "
                   "it send their points' files back here")
    p.add_argument("--address", metavar="ADDRESS",
                   help="an existing Ray cluster: 'auto' (this node's), HOST:6379, or "
                   "ray://HOST:10001 (Ray client); default: start a local instance")
    p.add_argument("--connect-timeout", type=float, default=30.0, metavar="SECONDS",
                   help="with --address: give up (exit status 7) when the cluster does not "
                   "answer within this time (default 30)")
    p.add_argument("--workers", type=int, metavar="N",
                   help="local: CPUs of the local Ray instance (default: all cores); with "
                   "--address: the most points running at once (default: the cluster's CPUs "
                   "/ --cpus-per-point)")
    p.add_argument("--cpus-per-point", type=int, default=1, metavar="N",
                   help="CPUs per point: its torch and numba threads (default 1)")
    p.add_argument("--point-timeout", type=float, metavar="SECONDS",
                   help="stop a point that runs longer and record it as failed (default: no "
                   "limit; not with --serial)")
    p.add_argument("--lost-retries", type=int, default=2, metavar="N",
                   help="run a point again up to N times when its worker or node is lost "
                   "(default 2); after that it is recorded as lost")
    p.add_argument("--retry-failed", action="store_true",
                   help="run failed points again (finished ok points are always skipped)")
    p.add_argument("--retry-lost", action="store_true",
                   help="run lost points again (their worker or node went away every time)")
    p.add_argument("--gather", action="store_true",
                   help="always send each point's files back to this machine (by default only "
                   "workers that do not see --out do)")
    p.add_argument("--serial", action="store_true",
                   help="run the points one after another in this process, without Ray")
    p.add_argument("--dry-run", action="store_true",
                   help="check the sweep file and every point (the checks `design` runs "
                   "first), print the count, memory and estimated CPU time; run nothing "
                   "(exit status 1 when some point is refused)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=run)


def _positive(value: float | None, flag: str, whole: bool = True) -> None:
    if value is not None and not value > 0:
        kind = "a whole number >= 1" if whole else "a number of seconds > 0"
        raise ValueError(f"{flag} {value}: give {kind}.")


def _check_args(args: argparse.Namespace) -> None:
    _positive(args.workers, "--workers")
    _positive(args.cpus_per_point, "--cpus-per-point")
    _positive(args.connect_timeout, "--connect-timeout", whole=False)
    _positive(args.point_timeout, "--point-timeout", whole=False)
    if args.lost_retries < 0:
        raise ValueError(f"--lost-retries {args.lost_retries}: give a whole number >= 0.")


def dry_run(args: argparse.Namespace) -> int:
    """Check every point as the run would (config, then the checks `design` runs first) and
    print the count, the largest memory estimate and the estimated CPU time."""
    from aperture_fab.sweep.estimate import estimate_points
    from aperture_fab.sweep.preflight import Resolver
    from aperture_fab.sweep.spec import check_points, grid_points, load_spec

    start = time.perf_counter()
    spec = load_spec(args.sweep_file)
    points = grid_points(spec) if spec.mode == "grid" else []
    resolve = Resolver(spec)
    check_points(spec, points, resolve)
    shown = points if len(points) <= LIST_ALL_UP_TO else points[:LIST_HEAD]
    for n, point in enumerate(shown, 1):
        print(f"{n:>4}  {point.id}  {point.label()}")
    if len(shown) < len(points):
        print(f"      ... and {len(points) - len(shown)} more")
    found = estimate_points(spec, points, args.out, resolve)
    for point, error in found.refused:
        print(f"refused: {point.id}  {point.label()}: {error}")
    what = f"{len(points)} grid points" if points else (
        f"a search of {spec.trials} trials over {', '.join(spec.swept_keys)}")
    count = len(points) or spec.trials
    print(f"{args.sweep_file}: {'ok' if not found.refused else 'checked'}, {what}; objectives "
          f"{', '.join(str(o) for o in spec.objectives)}")
    print(f"{len(found.refused)} refused by the checks `design` runs first; optimizer memory "
          f"up to {found.peak_bytes / GB:.2f} GB per point; estimated CPU time "
          f"{found.cpu_seconds * count / 3600:.2f} CPU-hours ({found.cpu_seconds:.0f} s per "
          f"point, {found.basis}); checked in {time.perf_counter() - start:.1f} s")
    if found.refused:
        # A plan with points that cannot be made is not ready: say so, and exit as the run
        # would (1: some points failed), so a script that checks first does not go on.
        print(f"{len(found.refused)} of {count} points cannot be made as set (the 'refused:' "
              "lines above say why and what to change); change the [grid] or [base] values, "
              "or run the sweep anyway: they are recorded as failed and the rest run.",
              file=sys.stderr)
        return EXIT_FAILED_POINTS
    return 0


def run(args: argparse.Namespace) -> int:
    """Run the sweep; errors in the sweep file raise ValueError (the CLI prints them)."""
    from aperture_fab.sweep.run import RunOptions, run_sweep
    from aperture_fab.sweep.settings import require
    from aperture_fab.sweep.spec import load_spec

    _check_args(args)
    if args.dry_run:
        return dry_run(args)
    spec = load_spec(args.sweep_file)
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
                         retry_lost=args.retry_lost, files="gather" if args.gather else "auto",
                         connect_timeout_s=args.connect_timeout,
                         point_timeout_s=args.point_timeout, lost_retries=args.lost_retries,
                         terminal=sys.stderr.isatty() and not args.quiet)

    def log(line: str) -> None:
        if not args.quiet:
            print(line, flush=True)

    outcome = run_sweep(spec, options, log)
    ok, lost = outcome.count("ok"), outcome.lost
    retried = sum(bool(r.get("lost")) and r["status"] != "lost"
                  for r in outcome.records.values())
    print(f"{len(outcome.points)} points: {ok} ok, {outcome.failed} failed, {lost} lost, "
          f"{len(outcome.points) - len(outcome.records)} not run; {outcome.ran} ran now "
          f"({retried} lost and retried), {outcome.skipped} finished before; "
          f"{outcome.bytes_sent / MB:.2f} MB sent to the workers; wrote "
          f"{outcome.paths.get('sweep.html')}")
    if outcome.stopped_by is not None:
        print("stopped: the finished points are recorded (results.csv); run the same command "
              "again to continue.", file=sys.stderr)
        return EXIT_SIGNAL_BASE + outcome.stopped_by
    if outcome.failed or lost:
        flags = " and ".join(f for f, n in (("--retry-failed", outcome.failed),
                                            ("--retry-lost", lost)) if n)
        print(f"{outcome.failed} point(s) failed, {lost} lost; their errors are in results.csv "
              f"and points/<id>/point.json ({flags} runs them again).", file=sys.stderr)
        return EXIT_FAILED_POINTS
    return 0
