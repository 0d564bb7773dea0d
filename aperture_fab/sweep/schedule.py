"""Running jobs on an executor: a bounded number in flight, lost ones again, slow ones stopped.

The Scheduler keeps at most `executor.slots` jobs in flight (a 1000-point sweep does not put
1000 tasks and their arguments into the cluster at once), takes the next job only when a slot
is free (so a search can ask for its next point knowing every result so far), and sorts what
comes back:

- a record: the design job ran (ok, or failed with its message);
- a lost task (its worker process or node went away: cluster.classify): run again, up to
  `lost_retries` more times, the point's record saying what was lost ("lost, retried"); after
  that the point is "lost", which a rerun retries with --retry-lost;
- a point that runs past `timeout_s`: cancelled and recorded as failed, saying so.

The retries are counted here, not by Ray's own max_retries, because Ray does not tell the
driver that a task was retried: the table could not say which points were lost.

Executors: SerialExecutor (this process, one at a time) and RayExecutor (a Ray session).
"""

from __future__ import annotations

import dataclasses
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from aperture_fab.sweep.cluster import classify
from aperture_fab.sweep.worker import Job, base_record, run_point

__all__ = ["Executor", "SerialExecutor", "RayExecutor", "Scheduler", "lost_record",
           "DEFAULT_LOST_RETRIES", "TICK_S"]

#: More runs of a point whose worker or node was lost (--lost-retries).
DEFAULT_LOST_RETRIES = 2
#: The longest wait for a result before the scheduler looks at timeouts and progress again.
TICK_S = 1.0
#: Characters of a Ray error kept in a record (its first line; Ray's dumps are long).
ERROR_CHARS = 300

Result = tuple[dict[str, Any], dict[str, bytes]]
Done = Callable[[Job, dict[str, Any], dict[str, bytes]], None]


class Executor(Protocol):
    """Where jobs run. slots: how many may be in flight at once."""

    slots: int
    bytes_sent: int

    def submit(self, job: Job) -> Any: ...

    def wait(self, handles: list[Any], timeout_s: float) -> list[Any]: ...

    def result(self, handle: Any) -> Result: ...

    def cancel(self, handle: Any) -> None: ...


class SerialExecutor:
    """Runs each job in this process when waited for: one slot, no timeouts."""

    slots = 1
    bytes_sent = 0

    def __init__(self) -> None:
        self.jobs: dict[int, Job] = {}
        self.results: dict[int, Result] = {}

    def submit(self, job: Job) -> int:
        handle = len(self.jobs) + len(self.results) + 1
        self.jobs[handle] = job
        return handle

    def wait(self, handles: list[Any], timeout_s: float) -> list[Any]:
        handle = handles[0]
        self.results[handle] = run_point(self.jobs.pop(handle))
        return [handle]

    def result(self, handle: Any) -> Result:
        return self.results.pop(handle)

    def cancel(self, handle: Any) -> None:
        self.jobs.pop(handle, None)


class RayExecutor:
    """Jobs as Ray tasks of `cpus` CPUs each. The targets go into the object store once (one
    copy per node, read by every task there), not with every task; bytes_sent counts what
    went to the workers (the targets once, then each job's pickled size)."""

    def __init__(self, ray: Any, cpus: int, slots: int, targets: tuple[tuple[str, bytes], ...]
                 ) -> None:
        self.ray, self.slots = ray, slots
        self.pickle = ray.cloudpickle.dumps  # Ray's own copy: what it sends is what we count
        # max_retries=0: the Scheduler retries lost tasks itself (it must know which were).
        self.remote = ray.remote(num_cpus=cpus, max_retries=0, retry_exceptions=False)(run_point)
        self.targets = ray.put(targets)
        self.bytes_sent = sum(len(name) + len(data) for name, data in targets)

    def submit(self, job: Job) -> Any:
        self.bytes_sent += len(self.pickle(job))
        return self.remote.remote(job, self.targets)

    def wait(self, handles: list[Any], timeout_s: float) -> list[Any]:
        ready, _ = self.ray.wait(handles, num_returns=1, timeout=timeout_s)
        return list(ready)

    def result(self, handle: Any) -> Result:
        record, files = self.ray.get(handle)
        return record, files

    def cancel(self, handle: Any) -> None:
        try:
            self.ray.cancel(handle, force=True)
        except Exception:  # already finished or its node is gone: nothing to stop
            pass


def _first_line(err: BaseException) -> str:
    text = str(err).strip()
    line = text.splitlines()[0] if text else ""
    return f"{type(err).__name__}: {line}"[:ERROR_CHARS]


def lost_record(job: Job, status: str, error: str) -> dict[str, Any]:
    """The record of a point whose task never returned a record (lost, or stopped)."""
    return base_record(job) | {"status": status, "figures": {}, "error": error,
                               "traceback": None, "seconds": None, "cpu_seconds": None,
                               "host": None, "finished_at": time.time()}


@dataclass(frozen=True)
class _Running:
    job: Job
    submitted: float


class Scheduler:
    """Runs the jobs `take` hands out on `executor`; calls `done` once per job with its final
    record. timeout_s: a point's longest run (None: no limit), from its submission: the
    scheduler submits no more than the executor's slots, so a submitted job is running."""

    def __init__(self, executor: Executor, done: Done, *, lost_retries: int = DEFAULT_LOST_RETRIES,
                 timeout_s: float | None = None, tick: Callable[[], None] = lambda: None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.executor, self.done, self.tick, self.clock = executor, done, tick, clock
        self.lost_retries, self.timeout_s = lost_retries, timeout_s
        self.pending: dict[Any, _Running] = {}
        self.retry: deque[Job] = deque()

    def run(self, take: Callable[[], Job | None]) -> None:
        """Until `take` has nothing more and nothing is in flight. Ctrl-C (KeyboardInterrupt)
        cancels what is in flight and propagates."""
        try:
            while True:
                self._fill(take)
                if not self.pending:
                    return
                for handle in self.executor.wait(list(self.pending), self._wait_s()):
                    self._finish(handle)
                self._expire()
                self.tick()
        except BaseException:
            for handle in list(self.pending):
                self.executor.cancel(handle)
            self.pending.clear()
            raise

    def _fill(self, take: Callable[[], Job | None]) -> None:
        while len(self.pending) < self.executor.slots:
            job = self.retry.popleft() if self.retry else take()
            if job is None:
                return
            self.pending[self.executor.submit(job)] = _Running(job, self.clock())

    def _wait_s(self) -> float:
        if self.timeout_s is None:
            return TICK_S
        first = min(r.submitted for r in self.pending.values()) + self.timeout_s
        return max(0.0, min(TICK_S, first - self.clock()))

    def _finish(self, handle: Any) -> None:
        job = self.pending.pop(handle).job
        try:
            record, files = self.executor.result(handle)
        except KeyboardInterrupt:
            raise
        except Exception as err:
            what = _first_line(err)
            if classify(err) == "lost":
                self._lost(job, what)
            else:
                self.done(job, lost_record(job, "failed", f"the task failed: {what}"), {})
            return
        record.update(attempts=job.attempt, lost=list(job.lost))
        self.done(job, record, files)

    def _lost(self, job: Job, what: str) -> None:
        job = dataclasses.replace(job, lost=(*job.lost, what))
        if job.attempt <= self.lost_retries:
            self.retry.append(dataclasses.replace(job, attempt=job.attempt + 1))
            return
        self.done(job, lost_record(job, "lost", f"lost {job.attempt} time(s), the last: "
                                   f"{what}; --retry-lost runs it again"), {})

    def _expire(self) -> None:
        if self.timeout_s is None:
            return
        now = self.clock()
        for handle, running in list(self.pending.items()):
            if now - running.submitted > self.timeout_s:
                self.executor.cancel(handle)
                del self.pending[handle]
                self.done(running.job, lost_record(
                    running.job, "failed", f"TimedOut: ran longer than --point-timeout "
                    f"{self.timeout_s:g} s and was stopped; raise --point-timeout, or make the "
                    "point smaller"), {})
