"""Running a sweep's points: each a full design job, in parallel on Ray, resumable.

Each point is an independent task with its own folder, out/points/<id>/. Its point.json (the
settings, the figures or the error, the seconds) is written atomically and last, so its presence
marks the point finished: a rerun skips ok points (failed ones unless retry_failed, lost ones
unless retry_lost), and an interrupted or killed sweep loses at most the points that were
running. results.csv grows by a row as each point finishes.

Before a point is sent anywhere, the driver runs the checks `aperture-fab design` runs before
its work (the process's rules, the light floor, that the eye sees the display): a point they
refuse is recorded as failed at once (`preflight`); --dry-run runs the same checks on every
point. A failing point is recorded with its error and traceback tail and never stops the sweep;
a lost one (its worker or node went away) runs again (schedule.Scheduler).

Search mode is asynchronous: Optuna's NSGA-II sampler is asked for a point whenever a slot is
free and told each result as it comes, with no wait for a whole generation. A rerun first tells
the study every point of this search already finished (in the order they finished), then asks
for the rest; with one worker (--serial) the search is deterministic for its seed.

SIGTERM stops a sweep like Ctrl-C; once stopping, further Ctrl-C or SIGTERM are ignored until the
tables of the finished points are written.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import secrets
import signal
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from aperture_fab.io.atomic import write_atomic
from aperture_fab.sweep.preflight import Preflight, Resolver
from aperture_fab.sweep.progress import Progress
from aperture_fab.sweep.results import TableLog, write_results
from aperture_fab.sweep.schedule import (
    DEFAULT_LOST_RETRIES,
    Executor,
    RayExecutor,
    Scheduler,
    SerialExecutor,
    lost_record,
)
from aperture_fab.sweep.settings import require
from aperture_fab.sweep.spec import (
    Choice,
    FloatRange,
    Point,
    SweepSpec,
    check_points,
    grid_points,
    make_point,
)
from aperture_fab.sweep.worker import (
    MARKER_FILE,
    POINT_FILE,
    FilesMode,
    Job,
    clear_attempt,
    plain,
)

__all__ = ["Backend", "RunOptions", "Job", "SweepOutcome", "run_sweep", "load_record",
           "POINT_FILE"]

Backend = Literal["ray", "serial"]
Status = Literal["ok", "failed", "lost"]
STATUSES: tuple[Status, ...] = ("ok", "failed", "lost")
POINTS_DIR = "points"
#: Every table (with the page's plot) is rewritten at most this often while a sweep runs.
REFRESH_S = 60.0


def load_record(folder: Path) -> dict[str, Any] | None:
    """A point's point.json, or None when it has not finished (or the file is unreadable)."""
    try:
        record = json.loads((folder / POINT_FILE).read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) and record.get("status") in STATUSES else None


@dataclass(frozen=True)
class RunOptions:
    """How to run a sweep.

    out: the sweep's folder (points/<id>/ per point, the tables, sweep.html).
    backend: "ray" (a local instance, or the cluster at `address`) or "serial" (this process).
    workers: local Ray CPUs; with an address, the most points in flight (None: the
        cluster's CPUs / cpus_per_point).
    cpus_per_point: CPUs each point's task holds; its torch and numba threads.
    retry_failed, retry_lost: run failed / lost points again (ok points are always skipped).
    files: "auto" (points come back to the driver from workers that do not see `out`) or
        "gather" (always).
    connect_timeout_s: how long to wait for the cluster at `address`.
    point_timeout_s: a point's longest run (None: no limit; Ray only).
    lost_retries: more runs of a point whose worker or node was lost.
    terminal: draw a progress bar on stderr (else plain lines through `log`).
    """

    out: Path
    backend: Backend = "ray"
    address: str | None = None
    workers: int | None = None
    cpus_per_point: int = 1
    retry_failed: bool = False
    retry_lost: bool = False
    files: FilesMode = "auto"
    connect_timeout_s: float = 30.0
    point_timeout_s: float | None = None
    lost_retries: int = DEFAULT_LOST_RETRIES
    terminal: bool = False

    def __post_init__(self) -> None:
        if self.point_timeout_s is not None and self.backend == "serial":
            raise ValueError("--point-timeout needs Ray (a point in this process cannot be "
                             "stopped safely); drop --serial or --point-timeout.")

    def skips(self, record: Mapping[str, Any]) -> bool:
        """Whether a finished point stays as it is on a rerun."""
        return not ((record["status"] == "failed" and self.retry_failed)
                    or (record["status"] == "lost" and self.retry_lost))


@dataclass(frozen=True)
class SweepOutcome:
    """points: every point of the sweep, in order; records: point.json by id (finished ones).
    stopped_by: the signal that stopped the sweep (None: it ran to the end). bytes_sent: what
    went to the workers (targets and jobs). paths: the tables written."""

    points: tuple[Point, ...]
    records: Mapping[str, dict[str, Any]]
    ran: int
    skipped: int
    stopped_by: int | None = None
    bytes_sent: int = 0
    paths: Mapping[str, Path] = dataclasses.field(default_factory=dict)

    @property
    def interrupted(self) -> bool:
        return self.stopped_by is not None

    def count(self, status: Status) -> int:
        return sum(r["status"] == status for r in self.records.values())

    @property
    def failed(self) -> int:
        return self.count("failed")

    @property
    def lost(self) -> int:
        return self.count("lost")


class _Stop(KeyboardInterrupt):
    """SIGTERM (or SIGINT), raised in the main thread to stop the sweep like Ctrl-C."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


@contextmanager
def _signals(log: Callable[[str], None]) -> Iterator[Callable[[], None]]:
    """SIGINT and SIGTERM stop the sweep (_Stop); the yielded `shield()` makes later ones
    print a note instead, so that the tables are written. Outside the main thread (where
    Python cannot set handlers) nothing changes."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield lambda: None
        return
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}

    def stop(signum: int, frame: Any) -> None:
        raise _Stop(signum)

    def note(signum: int, frame: Any) -> None:
        log("stopping: writing the tables of the finished points first (a moment)")

    def shield() -> None:
        for s in before:
            signal.signal(s, note)

    for s in before:
        signal.signal(s, stop)
    try:
        yield shield
    finally:
        for s, handler in before.items():
            signal.signal(s, handler)


class _Sweep:
    """The bookkeeping of one run: which points are finished, jobs, records, the tables."""

    def __init__(self, spec: SweepSpec, options: RunOptions, progress: Progress,
                 table: TableLog, log: Callable[[str], None],
                 resolver: Resolver | None = None) -> None:
        self.spec, self.options, self.progress, self.table, self.log = \
            spec, options, progress, table, log
        self.resolve = resolver or Resolver(spec)
        self.points: dict[str, Point] = {}
        self.records: dict[str, dict[str, Any]] = {}
        self.ran = self.skipped = 0
        self.token = secrets.token_hex(16)
        self.listeners: list[Callable[[Point, dict[str, Any]], None]] = []
        self.told_gathered = False
        self.preflight = Preflight()

    def folder(self, point: Point) -> Path:
        return self.options.out / POINTS_DIR / point.id

    def add(self, point: Point) -> bool:
        """Register a point; True when it is to run (not finished, or to be retried)."""
        if point.id in self.points:
            return False
        self.points[point.id] = point
        record = load_record(self.folder(point))
        if record is not None and self.options.skips(record):
            self.records[point.id] = record
            self.skipped += 1
            return False
        return True

    def job(self, point: Point) -> Job | None:
        """The point's job, or None when the checks `design` runs first refuse it (recorded
        as failed at once, never sent to a worker)."""
        job = Job(point, self.spec.preset, self.spec.base_file, self.spec.targets,
                  self.spec.target_digest, self.options.out, self.token,
                  self.options.cpus_per_point, self.options.files)
        try:
            config, fabrication, _ = self.resolve({k: plain(v) for k, v in point.overrides})
            self.preflight(config, fabrication, len(self.spec.targets))
        except ValueError as err:
            self.done(job, lost_record(job, "failed", f"refused before running: {err}"), {})
            return None
        return job

    def done(self, job: Job, record: dict[str, Any], files: dict[str, bytes]) -> None:
        folder = self.folder(job.point)
        if files:
            clear_attempt(folder)  # the gathered set replaces an earlier attempt's
            self._tell_gathered(record)
        folder.mkdir(parents=True, exist_ok=True)
        for name, data in files.items():
            if name != POINT_FILE:
                write_atomic(folder / name, data)
        write_atomic(folder / POINT_FILE, json.dumps(record, indent=2))  # last: finished
        self.records[job.point.id] = record
        self.ran += 1
        self.table.append(job.point, record)
        self.progress.done(record, job.point.label())
        for listener in self.listeners:
            listener(job.point, record)
        self.table.refresh(list(self.points.values()), self.records)

    def _tell_gathered(self, record: Mapping[str, Any]) -> None:
        if not self.told_gathered and self.options.files == "auto":
            self.log(f"the worker on {record.get('host')} does not see {self.options.out}: its "
                     "points' files come back to this machine through Ray's object store "
                     "(this --out is then their only copy)")
            self.told_gathered = True


def _grid_take(sweep: _Sweep, points: list[Point]) -> Callable[[], Job | None]:
    """The points' jobs one by one (points: registered with sweep.add, to run)."""
    queue = iter(points)

    def take() -> Job | None:
        for point in queue:
            job = sweep.job(point)
            if job is not None:
                return job
        return None
    return take


class _Search:
    """Asynchronous NSGA-II: ask when a slot is free, tell each result as it comes."""

    def __init__(self, sweep: _Sweep, spec: SweepSpec) -> None:
        optuna = require("optuna")
        optuna.logging.set_verbosity(optuna.logging.WARNING)
        self.optuna, self.sweep, self.spec = optuna, sweep, spec
        sampler = optuna.samplers.NSGAIISampler(population_size=spec.population, seed=spec.seed)
        self.study = optuna.create_study(directions=[o.direction for o in spec.objectives],
                                         sampler=sampler)
        self.dists = {dim.key: _distribution(optuna, dim) for dim in spec.space}
        self.asked = 0
        self.waiting: dict[str, list[Any]] = {}  # point id: its trials, until it finishes
        sweep.listeners.append(self._finished)
        for record in _finished_records(sweep, spec):  # a rerun: what is known first
            self.study.enqueue_trial({k: json.dumps(v) if isinstance(d, Choice) else v
                                      for (k, v), d in zip(record["settings"].items(),
                                                           spec.space, strict=True)})

    def take(self) -> Job | None:
        while self.asked < self.spec.trials:
            trial = self.study.ask(self.dists)
            self.asked += 1
            point = make_point(self.spec, tuple(
                (dim.key, _choice(trial.params[dim.key]) if isinstance(dim, Choice)
                 else trial.params[dim.key]) for dim in self.spec.space))
            if point.id in self.waiting:  # proposed again while it runs (crossover of equals)
                self.waiting[point.id].append(trial)
                continue
            self.waiting[point.id] = [trial]
            if not self.sweep.add(point):
                record = self.sweep.records.get(point.id)
                if record is not None:  # finished before: told now, not run
                    self._finished(point, record)
                continue
            job = self.sweep.job(point)
            if job is not None:
                return job
        return None

    def _finished(self, point: Point, record: Mapping[str, Any]) -> None:
        values = _objective_values(self.spec, record)
        for trial in self.waiting.pop(point.id, []):
            if values is None:
                self.study.tell(trial, state=self.optuna.trial.TrialState.FAIL)
            else:
                self.study.tell(trial, values)


def _distribution(optuna: Any, dim: Any) -> Any:
    if isinstance(dim, Choice):
        return optuna.distributions.CategoricalDistribution(
            [json.dumps(plain(c)) for c in dim.choices])
    if isinstance(dim, FloatRange):
        return optuna.distributions.FloatDistribution(dim.low, dim.high, log=dim.log)
    return optuna.distributions.IntDistribution(dim.low, dim.high, log=dim.log)


def _finished_records(sweep: _Sweep, spec: SweepSpec) -> list[dict[str, Any]]:
    """Finished points of this search in --out (their settings make their own id again), in
    the order they finished; at most spec.trials of them."""
    from aperture_fab.sweep.spec import _freeze

    keys = [dim.key for dim in spec.space]
    found = []
    for folder in sorted((sweep.options.out / POINTS_DIR).glob("*")):
        record = load_record(folder)
        if record is None or list(record.get("settings", {})) != keys:
            continue
        settings = tuple((k, _freeze(v)) for k, v in record["settings"].items())
        if make_point(spec, settings).id == record["id"] and _inside(spec, record["settings"]):
            found.append(record)
    found.sort(key=lambda r: (r.get("finished_at") or 0.0, r["id"]))
    return found[:spec.trials]


def _inside(spec: SweepSpec, settings: Mapping[str, Any]) -> bool:
    for dim in spec.space:
        value = settings[dim.key]
        if isinstance(dim, Choice):
            if json.dumps(value) not in {json.dumps(plain(c)) for c in dim.choices}:
                return False
        elif not (isinstance(value, (int, float)) and dim.low <= value <= dim.high):
            return False
    return True


def _choice(text: str) -> Any:
    value = json.loads(text)
    return tuple(value) if isinstance(value, list) else value


def _objective_values(spec: SweepSpec, record: Mapping[str, Any]) -> list[float] | None:
    if record["status"] != "ok":
        return None
    values = [record["figures"].get(o.figure) for o in spec.objectives]
    if any(v is None or (isinstance(v, float) and math.isnan(v)) for v in values):
        return None
    return [float(v) for v in values]


@contextmanager
def _executor(spec: SweepSpec, options: RunOptions, log: Callable[[str], None]
              ) -> Iterator[Executor]:
    if options.backend == "serial":
        yield SerialExecutor()
        return
    from aperture_fab.sweep.cluster import connect

    ray = require("ray")
    quiet = {"log_to_driver": False, "logging_level": "warning", "configure_logging": False}
    try:
        if options.address is None:
            cpus = options.workers or os.cpu_count() or 1
            ray.init(num_cpus=cpus, include_dashboard=False, **quiet)
            log(f"started a local Ray instance with {cpus} CPU(s)")
            slots = max(1, cpus // options.cpus_per_point)
        else:
            connect(ray, options.address, options.connect_timeout_s, **quiet)
            cluster_cpus = ray.cluster_resources().get("CPU", 0)
            slots = options.workers or max(1, int(cluster_cpus) // options.cpus_per_point)
            log(f"connected to the Ray cluster at {options.address} ({cluster_cpus:g} CPUs; "
                f"up to {slots} point(s) at once)")
        yield RayExecutor(ray, options.cpus_per_point, slots,
                          tuple((p.name, p.read_bytes()) for p in spec.targets))
    finally:
        if ray.is_initialized():
            ray.shutdown()


def run_sweep(spec: SweepSpec, options: RunOptions,
              log: Callable[[str], None] = print) -> SweepOutcome:
    """Check every point, run the unfinished ones, write the tables (as points finish and at
    the end) and return what is recorded. Ctrl-C or SIGTERM stops it
    (SweepOutcome.stopped_by); the finished points stay recorded, in the tables too."""
    # Absolute: Ray workers do not share this process's working folder.
    options = dataclasses.replace(options, out=options.out.resolve())
    points = grid_points(spec) if spec.mode == "grid" else []
    resolver = Resolver(spec)
    check_points(spec, points, resolver)  # before any job starts (and before Ray)
    (options.out / POINTS_DIR).mkdir(parents=True, exist_ok=True)
    write_atomic(options.out / "sweep.toml", spec.source.read_bytes())
    progress = Progress(len(points) or spec.trials, log, options.terminal)
    table = TableLog(options.out, spec, REFRESH_S)
    sweep = _Sweep(spec, options, progress, table, log, resolver)
    write_atomic(options.out / MARKER_FILE, sweep.token)
    stopped_by: int | None = None
    bytes_sent = 0
    with _signals(log) as shield:
        try:
            search = None if spec.mode == "grid" else _Search(sweep, spec)
            todo = [p for p in points if sweep.add(p)]
            progress.add(len(todo) - len(points))  # a grid: only what runs now counts
            take = _grid_take(sweep, todo) if search is None else search.take
            table.start(points, {p.id: r for p in points if (r := load_record(
                sweep.folder(p))) is not None})
            with _executor(spec, options, log) as executor:
                scheduler = Scheduler(executor, sweep.done, lost_retries=options.lost_retries,
                                      timeout_s=options.point_timeout_s, tick=progress.tick)
                try:
                    scheduler.run(take)
                finally:
                    bytes_sent = executor.bytes_sent
        except KeyboardInterrupt as stop:
            stopped_by = stop.signum if isinstance(stop, _Stop) else signal.SIGINT
        finally:
            shield()  # from here, the tables are written whatever the user presses
            progress.close()
            order = points or list(sweep.points.values())
            paths = write_results(options.out, spec, order, sweep.records)
    return SweepOutcome(tuple(order), dict(sweep.records), sweep.ran, sweep.skipped,
                        stopped_by, bytes_sent, paths)
