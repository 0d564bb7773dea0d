"""One point's design job as a worker runs it: where its files go, where its targets come from.

A job is a small plain value (its point, the config layers, the sweep folder's path and token):
it travels to a Ray worker with every task, so it holds no file contents. The target images go
to the cluster once (Ray's object store, `run_point`'s second argument) and each worker process
keeps them in a temporary folder named by their digest.

Where the files go: the driver writes a marker file holding a random token into the sweep
folder before the first task. A worker that reads that token at the same path shares the
driver's disk (one machine, or a shared filesystem) and writes the point's folder in place;
one that does not works in a temporary folder and returns the files, which the driver writes
under --out (so no shared storage is needed). files = "gather" always returns them.
"""

from __future__ import annotations

import json
import shutil
import socket
import tempfile
import time
import traceback
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from aperture_fab.io.atomic import write_atomic
from aperture_fab.io.manifest import remove_listed
from aperture_fab.sweep.results import figures_from_report
from aperture_fab.sweep.spec import Point

__all__ = ["Job", "FilesMode", "run_point", "clear_attempt", "plain", "base_record",
           "POINT_FILE", "MARKER_FILE", "SCHEMA_VERSION"]

FilesMode = Literal["auto", "gather"]
POINT_FILE = "point.json"
#: In the sweep folder: the token a worker reads to know it sees the driver's disk.
MARKER_FILE = ".sweep-marker"
SCHEMA_VERSION = 2
#: Lines of a failed point's traceback kept in point.json.
TRACEBACK_LINES = 25
#: Where a worker process keeps the targets it got from the object store.
TARGET_CACHE_PREFIX = "aperture-fab-targets-"
#: Hex digits of the targets' digest in the cache folder's name.
CACHE_DIGITS = 16

TargetFiles = tuple[tuple[str, bytes], ...]


@dataclass(frozen=True)
class Job:
    """One point's design job as a task sees it (plain values: it travels to Ray workers).

    out: the sweep's folder on the driver; token: the marker file's content there (see the
    module doc). attempt: 1 for the first run; lost: what happened to earlier attempts whose
    worker or node went away (the driver retries them).
    """

    point: Point
    preset: str | None
    base_file: Mapping[str, Any] | None
    targets: tuple[Path, ...]
    target_digest: str
    out: Path
    token: str
    cpus: int = 1
    files: FilesMode = "auto"
    attempt: int = 1
    lost: tuple[str, ...] = ()

    @property
    def folder(self) -> Path:
        return self.out / "points" / self.point.id


def plain(value: Any) -> Any:
    """Tuples as lists (JSON)."""
    return [plain(v) for v in value] if isinstance(value, (tuple, list)) else value


def base_record(job: Job) -> dict[str, Any]:
    """The fields every point.json has, whatever happened to the point."""
    return {"schema_version": SCHEMA_VERSION, "id": job.point.id,
            "settings": {k: plain(v) for k, v in job.point.settings},
            "overrides": {k: plain(v) for k, v in job.point.overrides},
            "attempts": job.attempt, "lost": list(job.lost)}


def shares_out(job: Job) -> bool:
    """Whether this process sees the driver's sweep folder (the marker holds the token)."""
    if job.files == "gather":
        return False
    try:
        return (job.out / MARKER_FILE).read_text() == job.token
    except OSError:
        return False


def _cached_targets(job: Job, files: TargetFiles) -> list[Path]:
    """The targets from the object store, written once per worker machine and digest."""
    cache = Path(tempfile.gettempdir()) / f"{TARGET_CACHE_PREFIX}{job.target_digest[:CACHE_DIGITS]}"
    cache.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, data in files:
        path = cache / name
        if not (path.is_file() and path.stat().st_size == len(data)):
            write_atomic(path, data)  # another worker may write the same bytes: both whole
        paths.append(path)
    return paths


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


def run_point(job: Job, target_files: TargetFiles | None = None
              ) -> tuple[dict[str, Any], dict[str, bytes]]:
    """Run one design job; return its record (point.json) and, when this process does not see
    the driver's folder, its files. target_files: the targets' (name, bytes) from the object
    store (None: read job.targets, this process sees them). Errors become a failed record;
    Ctrl-C propagates."""
    from aperture_fab.pipeline import run_design
    from aperture_fab.sweep.settings import resolve_point

    start, cpu_start = time.perf_counter(), time.process_time()
    shared = shares_out(job)
    folder = job.folder if shared else Path(tempfile.mkdtemp(prefix=f"sweep-{job.point.id}-"))
    if shared:
        clear_attempt(folder)  # a failed attempt's files: never mix them with this run's
    folder.mkdir(parents=True, exist_ok=True)
    record = base_record(job) | {"host": socket.gethostname(), "shared_out": shared}
    threads = _set_threads(job.cpus)
    try:
        targets = list(job.targets) if target_files is None else \
            _cached_targets(job, target_files)
        config, fabrication, validation = resolve_point(job.preset, job.base_file,
                                                        dict(record["overrides"]))
        result = run_design(targets, folder / "plate.stl", config, fabrication=fabrication,
                            validation=validation, progress=False)
        if result.report is None:  # resolve_point always gives validation settings
            raise ValueError("the design job returned no report: it did not validate the part")
        record.update(status="ok", figures=figures_from_report(result.report.as_json()),
                      error=None, traceback=None)
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
    record["finished_at"] = time.time()
    write_atomic(folder / POINT_FILE, json.dumps(record, indent=2))
    files: dict[str, bytes] = {}
    if not shared:
        files = {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()
                 and not p.name.startswith(".")}
        shutil.rmtree(folder, ignore_errors=True)
    return record, files


def clear_attempt(folder: Path) -> None:
    """Remove an earlier attempt's files from a point's folder: its point.json, its checkpoint
    and the set its manifest.json lists. Only those: anything else there is not the sweep's."""
    from aperture_fab.pipeline.design_job import CHECKPOINT_NAME

    if not folder.is_dir():
        return
    remove_listed(folder)
    for name in (POINT_FILE, CHECKPOINT_NAME):
        (folder / name).unlink(missing_ok=True)
