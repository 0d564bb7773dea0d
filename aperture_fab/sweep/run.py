"""Running a sweep's points: each a full design job, in parallel on Ray, resumable.

Each point is an independent task with its own folder, out/points/<id>/. Its point.json (the
settings, the figures or the error, the seconds) is written atomically and last, so its presence
marks the point finished: a rerun skips ok points (and failed ones unless retry_failed), and an
interrupted sweep loses at most the points that were running. A failing point is recorded with
its error and traceback tail and never stops the sweep.

Search mode asks Optuna's NSGA-II sampler for one generation (`population` points) at a time and
tells it the results in trial order once the generation is done; a rerun replays the same asks
from the same seed and tells finished points from their point.json without running them, so it
continues the search exactly where it stopped.

Ray is optional: without it, backend "serial" runs the points one after another in this process.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import socket
import tempfile
import time
import traceback
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from aperture_fab.io.files import write_atomic
from aperture_fab.io.manifest import remove_listed
from aperture_fab.sweep.results import figures_from_report, summary_line
from aperture_fab.sweep.spec import (
    Choice,
    FloatRange,
    Point,
    SweepSpec,
    check_points,
    grid_points,
    make_point,
)

__all__ = ["Backend", "RunOptions", "Job", "SweepOutcome", "run_sweep", "run_point",
           "load_record", "require"]

Backend = Literal["ray", "serial"]
Status = Literal["ok", "failed"]
POINTS_DIR = "points"
POINT_FILE = "point.json"
SCHEMA_VERSION = 1
#: Lines of a failed point's traceback kept in point.json.
TRACEBACK_LINES = 25
EXTRA = "pip install 'aperture-fab[sweep]'"


def require(module: str) -> Any:
    """Import an optional dependency, or say which extra installs it."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as err:
        raise ImportError(f"the sweep needs {module.split('.')[0]}, which is not installed: "
                          f"{EXTRA}") from err


def _stage_settings(extra: Any) -> tuple[Any, Any]:
    """Fabrication and validation settings from a config's extra tables ([process],
    [fabrication], [validation])."""
    from aperture_fab.fabrication.part import fabrication_settings
    from aperture_fab.validation.validate import validation_settings

    return fabrication_settings(extra), validation_settings(extra)


def resolve_point(preset: str | None, base_file: Mapping[str, Any] | None,
                  overrides: Mapping[str, Any]) -> tuple[Any, Any, Any]:
    """(Config, FabricationSettings, ValidationSettings) of a point; raises what resolve does."""
    from aperture_fab.config import resolve

    config = resolve(preset, base_file, overrides, file_source="the [sweep] config file")
    fabrication, validation = _stage_settings(config.extra)
    return config, fabrication, validation


@dataclass(frozen=True)
class Job:
    """One point's design job as a task sees it (plain values: it travels to Ray workers)."""

    point: Point
    preset: str | None
    base_file: Mapping[str, Any] | None
    targets: tuple[Path, ...]
    folder: Path
    cpus: int = 1
    gather: bool = False
    #: The targets' bytes by file name when gathering: workers without the driver's disk.
    target_files: tuple[tuple[str, bytes], ...] = ()


def _set_threads(cpus: int) -> tuple[int, int | None]:
    import torch

    before: tuple[int, int | None] = (torch.get_num_threads(), None)
    torch.set_num_threads(cpus)
    try:
        import numba

        before = (before[0], numba.get_num_threads())
        most = int(numba.config.NUMBA_NUM_THREADS)  # type: ignore[attr-defined]
        numba.set_num_threads(min(cpus, most))
    except (ImportError, ValueError):
        pass
    return before


def _restore_threads(before: tuple[int, int | None]) -> None:
    import torch

    torch.set_num_threads(before[0])
    if before[1] is not None:
        import numba

        numba.set_num_threads(before[1])


def run_point(job: Job) -> tuple[dict[str, Any], dict[str, bytes]]:
    """Run one design job; return its record (point.json) and, when job.gather, its files.

    Writes into job.folder (or a temporary folder when gathering, whose files come back to the
    driver); point.json goes last. Errors become a failed record; Ctrl-C propagates.
    """
    from aperture_fab.pipeline import run_design

    start, cpu_start = time.perf_counter(), time.process_time()
    folder = Path(tempfile.mkdtemp(prefix=f"sweep-{job.point.id}-")) if job.gather else job.folder
    if not job.gather:
        _clear_attempt(folder)  # a failed attempt's files: never mix them with this run's
    folder.mkdir(parents=True, exist_ok=True)
    threads = _set_threads(job.cpus)
    record: dict[str, Any] = {
        "schema_version": SCHEMA_VERSION, "id": job.point.id,
        "settings": {k: _plain(v) for k, v in job.point.settings},
        "overrides": {k: _plain(v) for k, v in job.point.overrides},
        "host": socket.gethostname(),
    }
    targets = list(job.targets)
    if job.target_files:
        (folder / "targets").mkdir()
        targets = [folder / "targets" / name for name, _ in job.target_files]
        for path, (_, data) in zip(targets, job.target_files, strict=True):
            path.write_bytes(data)
    try:
        config, fabrication, validation = resolve_point(job.preset, job.base_file,
                                                        dict(record["overrides"]))
        run_design(targets, folder / "plate.stl", config, fabrication=fabrication,
                   validation=validation, progress=False)
        report = json.loads((folder / "report.json").read_text())
        record.update(status="ok", figures=figures_from_report(report), error=None,
                      traceback=None)
    except Exception as err:  # a point's failure is data, not the sweep's end
        if type(err).__name__ == "Interrupted":  # the optimizer's Ctrl-C: stop the sweep
            raise KeyboardInterrupt from err
        tail = traceback.format_exc().rstrip().splitlines()[-TRACEBACK_LINES:]
        record.update(status="failed", figures={}, error=f"{type(err).__name__}: {err}",
                      traceback="\n".join(tail))
    finally:
        _restore_threads(threads)
    record["seconds"] = time.perf_counter() - start
    record["cpu_seconds"] = time.process_time() - cpu_start  # this worker process, all threads
    record["figures"]["seconds"] = record["seconds"]
    write_atomic(folder / POINT_FILE, json.dumps(record, indent=2))
    files: dict[str, bytes] = {}
    if job.gather:
        files = {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()
                 and not p.name.startswith(".")}
        shutil.rmtree(folder, ignore_errors=True)
    return record, files


def _clear_attempt(folder: Path) -> None:
    """Remove an earlier attempt's files from a point's folder: its point.json, its checkpoint
    and the set its manifest.json lists. Only those: anything else there is not the sweep's."""
    from aperture_fab.pipeline.design_job import CHECKPOINT_NAME

    if not folder.is_dir():
        return
    remove_listed(folder)
    for name in (POINT_FILE, CHECKPOINT_NAME):
        (folder / name).unlink(missing_ok=True)


def _plain(value: Any) -> Any:
    return [_plain(v) for v in value] if isinstance(value, (tuple, list)) else value


def load_record(folder: Path) -> dict[str, Any] | None:
    """A point's point.json, or None when it has not finished (or the file is unreadable)."""
    try:
        record = json.loads((folder / POINT_FILE).read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) and record.get("status") in ("ok", "failed") \
        else None


@dataclass(frozen=True)
class RunOptions:
    """How to run a sweep.

    out: the sweep's folder (points/<id>/ per point, the tables, sweep.html).
    backend: "ray" (a local instance, or the cluster at `address`) or "serial" (this process).
    workers: local Ray CPUs (points at once at 1 CPU each); with an address, the most points
        in flight (None: all of them; Ray queues them).
    cpus_per_point: CPUs each point's task holds; its torch and numba threads.
    retry_failed: run failed points again (finished ok points are always skipped).
    gather: tasks send their files back to the driver, for clusters without shared storage.
    """

    out: Path
    backend: Backend = "ray"
    address: str | None = None
    workers: int | None = None
    cpus_per_point: int = 1
    retry_failed: bool = False
    gather: bool = False


@dataclass(frozen=True)
class SweepOutcome:
    """points: every point of the sweep, in order; records: point.json by id (finished ones)."""

    points: tuple[Point, ...]
    records: Mapping[str, dict[str, Any]]
    ran: int
    skipped: int
    interrupted: bool

    @property
    def failed(self) -> int:
        return sum(r["status"] == "failed" for r in self.records.values())


Runner = Callable[[list[Job], Callable[[Job, dict[str, Any], dict[str, bytes]], None]], None]


def _serial_runner(jobs: list[Job], done: Callable[[Job, dict[str, Any], dict[str, bytes]],
                                                   None]) -> None:
    for job in jobs:
        record, files = run_point(job)
        done(job, record, files)


@contextmanager
def _ray_runner(options: RunOptions, log: Callable[[str], None]) -> Iterator[Runner]:
    """A local Ray instance (or a connection to the cluster at options.address) for the
    duration of the sweep, shut down however the sweep ends."""
    ray = require("ray")
    if options.address is None:
        cpus = options.workers or os.cpu_count() or 1
        ray.init(num_cpus=cpus, include_dashboard=False, log_to_driver=False,
                 logging_level="warning", configure_logging=False)
        log(f"started a local Ray instance with {cpus} CPU(s)")
    else:
        ray.init(address=options.address, log_to_driver=False, logging_level="warning",
                 configure_logging=False)
        log(f"connected to the Ray cluster at {options.address} "
            f"({ray.cluster_resources().get('CPU', 0):g} CPUs)")
    remote = ray.remote(num_cpus=options.cpus_per_point, max_retries=0)(run_point)
    limit = options.workers if options.address is not None else None

    def runner(jobs: list[Job], done: Callable[[Job, dict[str, Any], dict[str, bytes]],
                                               None]) -> None:
        queue = list(jobs)
        pending: dict[Any, Job] = {}
        try:
            while queue or pending:
                while queue and (limit is None or len(pending) < limit):
                    job = queue.pop(0)
                    pending[remote.remote(job)] = job
                ready, _ = ray.wait(list(pending), num_returns=1)
                job = pending.pop(ready[0])
                try:
                    record, files = ray.get(ready[0])
                except Exception as err:  # the worker died (memory, signal)
                    record, files = _lost(job, err), {}
                done(job, record, files)
        except KeyboardInterrupt:
            for ref in pending:
                ray.cancel(ref, force=True)
            raise

    try:
        yield runner
    finally:
        ray.shutdown()


def _lost(job: Job, err: Exception) -> dict[str, Any]:
    """The record of a point whose task never returned."""
    return {"schema_version": SCHEMA_VERSION, "id": job.point.id, "status": "failed",
            "settings": {k: _plain(v) for k, v in job.point.settings},
            "overrides": {k: _plain(v) for k, v in job.point.overrides},
            "figures": {}, "error": f"the task was lost: {type(err).__name__}: {err}",
            "traceback": None, "seconds": None, "host": None}


def _checker(spec: SweepSpec) -> Callable[[Mapping[str, Any]], None]:
    def check(overrides: Mapping[str, Any]) -> None:
        resolve_point(spec.preset, spec.base_file, overrides)
    return check


class _Sweep:
    """The bookkeeping of one run: which points are finished, progress lines, counts."""

    def __init__(self, spec: SweepSpec, options: RunOptions, runner: Runner,
                 log: Callable[[str], None]) -> None:
        self.spec, self.options, self.runner, self.log = spec, options, runner, log
        self.points: dict[str, Point] = {}
        self.records: dict[str, dict[str, Any]] = {}
        self.ran = self.skipped = 0
        self.total = 0
        self.target_files = tuple((p.name, p.read_bytes()) for p in spec.targets) \
            if options.gather else ()

    def folder(self, point: Point) -> Path:
        return self.options.out / POINTS_DIR / point.id

    def run(self, points: list[Point]) -> None:
        """Run the points not finished yet; afterwards every one has a record."""
        todo: list[Job] = []
        for point in points:
            if point.id in self.points:
                continue  # a search can propose a point twice
            self.points[point.id] = point
            record = load_record(self.folder(point))
            if record is not None and (record["status"] == "ok" or not self.options.retry_failed):
                self.records[point.id] = record
                self.skipped += 1
                continue
            todo.append(Job(point, self.spec.preset, self.spec.base_file, self.spec.targets,
                            self.folder(point), self.options.cpus_per_point, self.options.gather,
                            self.target_files))
        self.total += len(todo)
        if todo:
            self.runner(todo, self.done)

    def done(self, job: Job, record: dict[str, Any], files: dict[str, bytes]) -> None:
        folder = self.folder(job.point)
        if files:
            _clear_attempt(folder)  # the gathered set replaces an earlier attempt's
        folder.mkdir(parents=True, exist_ok=True)
        for name, data in files.items():
            if name != POINT_FILE:
                write_atomic(folder / name, data)
        write_atomic(folder / POINT_FILE, json.dumps(record, indent=2))  # last: finished
        self.records[job.point.id] = record
        self.ran += 1
        self.log(f"[{self.ran}/{self.total}] {summary_line(record, job.point.label())}")


def _search(sweep: _Sweep, spec: SweepSpec) -> None:
    optuna = require("optuna")
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    sampler = optuna.samplers.NSGAIISampler(population_size=spec.population, seed=spec.seed)
    study = optuna.create_study(directions=[o.direction for o in spec.objectives],
                                sampler=sampler)
    dists: dict[str, Any] = {}
    for dim in spec.space:
        if isinstance(dim, Choice):
            dists[dim.key] = optuna.distributions.CategoricalDistribution(
                [json.dumps(_plain(c)) for c in dim.choices])
        elif isinstance(dim, FloatRange):
            dists[dim.key] = optuna.distributions.FloatDistribution(dim.low, dim.high, log=dim.log)
        else:
            dists[dim.key] = optuna.distributions.IntDistribution(dim.low, dim.high, log=dim.log)
    asked = 0
    while asked < spec.trials:
        trials = [study.ask(dists) for _ in range(min(spec.population, spec.trials - asked))]
        asked += len(trials)
        points = [make_point(spec, tuple(
            (dim.key, _choice(trial.params[dim.key]) if isinstance(dim, Choice)
             else trial.params[dim.key]) for dim in spec.space)) for trial in trials]
        sweep.run(points)
        for trial, point in zip(trials, points, strict=True):  # in trial order: deterministic
            values = _objective_values(spec, sweep.records[point.id])
            if values is None:
                study.tell(trial, state=optuna.trial.TrialState.FAIL)
            else:
                study.tell(trial, values)


def _choice(text: str) -> Any:
    value = json.loads(text)
    return tuple(value) if isinstance(value, list) else value


def _objective_values(spec: SweepSpec, record: dict[str, Any]) -> list[float] | None:
    if record["status"] != "ok":
        return None
    values = [record["figures"].get(o.figure) for o in spec.objectives]
    return None if any(v is None for v in values) else [float(v) for v in values]


def run_sweep(spec: SweepSpec, options: RunOptions,
              log: Callable[[str], None] = print) -> SweepOutcome:
    """Check every point, run the unfinished ones, and return what is recorded. Ctrl-C stops
    it (SweepOutcome.interrupted); the finished points stay recorded."""
    # Absolute: Ray workers do not share this process's working folder.
    options = dataclasses.replace(options, out=options.out.resolve())
    points = grid_points(spec) if spec.mode == "grid" else []
    check_points(spec, points, _checker(spec))  # before any job starts (and before Ray)
    (options.out / POINTS_DIR).mkdir(parents=True, exist_ok=True)
    write_atomic(options.out / "sweep.toml", spec.source.read_bytes())
    interrupted = False
    with _runner(options, log) as runner:
        sweep = _Sweep(spec, options, runner, log)
        try:
            if spec.mode == "grid":
                sweep.run(points)
            else:
                _search(sweep, spec)
        except KeyboardInterrupt:
            interrupted = True
    order = points or list(sweep.points.values())
    return SweepOutcome(tuple(order), dict(sweep.records), sweep.ran, sweep.skipped, interrupted)


@contextmanager
def _runner(options: RunOptions, log: Callable[[str], None]) -> Iterator[Runner]:
    if options.backend == "serial":
        yield _serial_runner
    else:
        with _ray_runner(options, log) as runner:
            yield runner
