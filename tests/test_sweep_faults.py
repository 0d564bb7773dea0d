"""Sweeps on a real cluster (issue 18): connecting, lost and failed points, timeouts, the
tables as points finish, stopping, the dry run; and (slow) a real two-node local Ray cluster
whose worker node is killed mid-sweep.

The fast tests run the Scheduler on a fake executor (no Ray) and the sweep with a fake design
job (tests/test_sweep.py's fake_design)."""

from __future__ import annotations

import csv
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from test_sweep import GRID, TINY_BASE, install_fake_design, parse, write_sweep

from aperture_fab.sweep.cluster import (
    ClusterUnreachable,
    classify,
    connect,
    parse_address,
    probe,
)
from aperture_fab.sweep.command import run as run_command
from aperture_fab.sweep.progress import Progress, duration
from aperture_fab.sweep.results import note
from aperture_fab.sweep.run import RunOptions, load_record, run_sweep
from aperture_fab.sweep.schedule import Scheduler
from aperture_fab.sweep.spec import grid_points, load_spec
from aperture_fab.sweep.worker import Job


@pytest.fixture
def sweep_dir(tmp_path: Path, marker_png: Path) -> Path:
    """A folder holding marker.png (the sweep files name it relative to themselves)."""
    return tmp_path


@pytest.fixture
def fake_design(monkeypatch: pytest.MonkeyPatch) -> list[dict[str, Any]]:
    """run_design replaced by test_sweep's fake (a gap of 12 mm fails); its calls."""
    return install_fake_design(monkeypatch)


# -- connecting -------------------------------------------------------------------------------


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_wrong_address_fails_fast_with_a_connection_error() -> None:
    port = _closed_port()
    start = time.monotonic()
    with pytest.raises(ClusterUnreachable) as info:
        connect(None, f"127.0.0.1:{port}", 1.0)
    assert time.monotonic() - start < 5
    text = str(info.value)
    assert f"--address 127.0.0.1:{port}" in text and "ray start --head" in text
    assert "--connect-timeout" in text
    assert isinstance(info.value, ConnectionError)


def test_cli_exit_status_for_an_unreachable_cluster(sweep_dir: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("ray")
    from aperture_fab.cli import EXIT_CANNOT_WRITE, EXIT_NO_CLUSTER, main

    path = write_sweep(sweep_dir, GRID)
    code = main(["sweep", str(path), "--address", f"127.0.0.1:{_closed_port()}",
                 "--connect-timeout", "1", "--out", str(sweep_dir / "out")])
    assert code == EXIT_NO_CLUSTER != EXIT_CANNOT_WRITE
    err = capsys.readouterr().err
    assert "no Ray cluster answered" in err and "cannot write" not in err


def test_silent_port_hints_token_authentication(monkeypatch: pytest.MonkeyPatch) -> None:
    """A port that answers while Ray never does (as with a token the cluster refuses)."""
    monkeypatch.delenv("RAY_AUTH_MODE", raising=False)
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        port = server.getsockname()[1]

        class Hanging:
            def init(self, **kwargs: Any) -> None:
                time.sleep(30)

        with pytest.raises(ClusterUnreachable, match="RAY_AUTH_MODE=token"):
            connect(Hanging(), f"127.0.0.1:{port}", 0.5)


def test_addresses() -> None:
    assert parse_address("auto").host is None
    assert parse_address("head:6380").port == 6380
    assert parse_address("ray://head").port == 10001 and parse_address("ray://head").client
    assert parse_address("head").port == 6379
    for bad in ("head:port", "ray://", "head:70000"):
        with pytest.raises(ValueError, match="not a Ray address"):
            parse_address(bad)
    probe(parse_address("auto"), 0.1)  # nothing to probe


# -- lost and failed points -------------------------------------------------------------------


class NodeDiedError(Exception):
    """Named as Ray's: the node running the task went away."""


class WorkerCrashedError(Exception):
    """Named as Ray's: the worker process died."""


def test_classify() -> None:
    assert classify(NodeDiedError("node gone")) == "lost"
    assert classify(WorkerCrashedError()) == "lost"
    assert classify(ValueError("bad design")) == "failed"

    class Sub(NodeDiedError):
        pass

    assert classify(Sub()) == "lost"


class FakeExecutor:
    """Runs nothing: each job's attempt answers from `script` (point index, attempt) -> an
    exception to raise, "hang" (never finishes) or a status for its record."""

    slots = 2
    bytes_sent = 0

    def __init__(self, script: dict[tuple[int, int], Any], order: list[str]) -> None:
        self.script, self.order = script, order
        self.jobs: dict[int, Job] = {}
        self.cancelled: list[int] = []
        self.n = 0

    def submit(self, job: Job) -> int:
        self.n += 1
        self.jobs[self.n] = job
        return self.n

    def _what(self, handle: int) -> Any:
        job = self.jobs[handle]
        return self.script.get((self.order.index(job.point.id), job.attempt), "ok")

    def wait(self, handles: list[Any], timeout_s: float) -> list[Any]:
        ready = [h for h in handles if self._what(h) != "hang"]
        if not ready:
            time.sleep(timeout_s)
        return ready[:1]

    def result(self, handle: int) -> tuple[dict[str, Any], dict[str, bytes]]:
        what, job = self._what(handle), self.jobs[handle]
        if isinstance(what, BaseException):
            raise what
        return {"id": job.point.id, "status": what, "figures": {},
                "error": None if what == "ok" else "design failed"}, {}

    def cancel(self, handle: Any) -> None:
        self.cancelled.append(handle)


def _jobs(sweep_dir: Path, count: int = 4) -> list[Job]:
    spec = load_spec(write_sweep(sweep_dir, GRID))
    return [Job(p, spec.preset, spec.base_file, spec.targets, spec.target_digest,
                sweep_dir, "token") for p in grid_points(spec)[:count]]


def _schedule(jobs: list[Job], script: dict[tuple[int, int], Any], **kwargs: Any
              ) -> tuple[dict[str, dict[str, Any]], FakeExecutor]:
    executor = FakeExecutor(script, [j.point.id for j in jobs])
    records: dict[str, dict[str, Any]] = {}
    queue = list(jobs)
    Scheduler(executor, lambda job, record, files: records.__setitem__(job.point.id, record),
              **kwargs).run(lambda: queue.pop(0) if queue else None)
    return records, executor


def test_lost_points_are_retried_and_failures_are_not(sweep_dir: Path) -> None:
    jobs = _jobs(sweep_dir)
    records, executor = _schedule(jobs, {
        (0, 1): NodeDiedError("the node running this task died"),      # lost once, then ok
        (1, 1): "failed",                                              # a design failure
        (2, 1): WorkerCrashedError("gone"), (2, 2): WorkerCrashedError("gone"),
        (2, 3): WorkerCrashedError("gone"),                            # lost every time
        (3, 1): RuntimeError("unpicklable"),                           # not a lost node
    }, lost_retries=2)
    first, design, lost, other = (records[j.point.id] for j in jobs)
    assert first["status"] == "ok" and first["attempts"] == 2
    assert note(first) is not None and note(first).startswith("lost, retried (1 time")
    assert design["status"] == "failed" and design["attempts"] == 1 and not design["lost"]
    assert lost["status"] == "lost" and lost["attempts"] == 3 and "--retry-lost" in lost["error"]
    assert note(lost) is not None and note(lost).startswith("lost (3 times")
    assert other["status"] == "failed" and "RuntimeError: unpicklable" in other["error"]
    assert executor.n == 2 + 1 + 3 + 1  # submissions: retries are bounded


def test_point_timeout(sweep_dir: Path) -> None:
    jobs = _jobs(sweep_dir, 2)
    records, executor = _schedule(jobs, {(0, 1): "hang"}, timeout_s=0.3)
    assert records[jobs[0].point.id]["status"] == "failed"
    assert "--point-timeout 0.3 s" in records[jobs[0].point.id]["error"]
    assert records[jobs[1].point.id]["status"] == "ok" and executor.cancelled == [1]


def test_in_flight_is_bounded(sweep_dir: Path) -> None:
    jobs = _jobs(sweep_dir, 6)
    seen: list[int] = []
    executor = FakeExecutor({}, [j.point.id for j in jobs])
    queue = list(jobs)
    scheduler = Scheduler(executor, lambda *a: seen.append(len(scheduler.pending)))
    scheduler.run(lambda: queue.pop(0) if queue else None)
    assert len(seen) == 6 and max(seen) < executor.slots  # one finished: at most slots - 1 left


def test_timeout_needs_ray(sweep_dir: Path) -> None:
    with pytest.raises(ValueError, match="--point-timeout needs Ray"):
        RunOptions(out=sweep_dir, backend="serial", point_timeout_s=5.0)


# -- retry flags, tables as points finish ------------------------------------------------------


def test_retry_failed_and_retry_lost_are_separate(sweep_dir: Path,
                                                  fake_design: list[dict[str, Any]]) -> None:
    import json

    spec = load_spec(write_sweep(sweep_dir, GRID))
    out = sweep_dir / "out"
    first = run_sweep(spec, RunOptions(out=out, backend="serial"), lambda line: None)
    assert first.failed == 2 and len(fake_design) == 6
    ok = next(p for p in first.points if first.records[p.id]["status"] == "ok")
    record = load_record(out / "points" / ok.id)
    assert record is not None
    record.update(status="lost", error="lost 3 time(s)")  # as if its node died every time
    (out / "points" / ok.id / "point.json").write_text(json.dumps(record))
    run_sweep(spec, RunOptions(out=out, backend="serial", retry_failed=True), lambda line: None)
    assert len(fake_design) == 8  # the 2 failed ones only
    again = run_sweep(spec, RunOptions(out=out, backend="serial", retry_lost=True),
                      lambda line: None)
    assert len(fake_design) == 9 and again.records[ok.id]["status"] == "ok"


def test_results_csv_grows_as_points_finish(sweep_dir: Path,
                                            fake_design: list[dict[str, Any]],
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """After each point, results.csv holds every finished point: a driver killed then has
    lost nothing finished (the rows are appended and flushed, not written at the end)."""
    import aperture_fab.sweep.run as run_module

    spec = load_spec(write_sweep(sweep_dir, GRID))
    out = sweep_dir / "out"
    seen: list[int] = []

    def spy(point: Any, record: Any) -> None:
        rows = list(csv.DictReader((out / "results.csv").open()))
        seen.append(len(rows))
        assert rows[-1]["id"] == point.id and rows[-1]["status"] == record["status"]

    real = run_module._Sweep.__init__

    def init(self: Any, *args: Any) -> None:
        real(self, *args)
        self.listeners.append(spy)

    monkeypatch.setattr(run_module._Sweep, "__init__", init)
    run_sweep(spec, RunOptions(out=out, backend="serial"), lambda line: None)
    assert seen == [1, 2, 3, 4, 5, 6]
    header = (out / "results.csv").read_text().splitlines()[0]
    assert header.endswith("attempts,note,error,report")


#: A driver that runs GRID serially with the fake design and kills itself (SIGKILL: no
#: handler, no finally) as the third point starts.
_KILLED_DRIVER = """
import os, signal, sys
from pathlib import Path
sys.path.insert(0, sys.argv[1])
import aperture_fab.pipeline
from test_sweep import install_fake_design
from aperture_fab.sweep.run import RunOptions, run_sweep
from aperture_fab.sweep.spec import load_spec

class Patch:
    def setattr(self, owner, name, value):
        setattr(owner, name, value)

calls = install_fake_design(Patch())
fake = aperture_fab.pipeline.run_design

def killing(paths, out, config, **kwargs):
    if len(calls) == 2:
        os.kill(os.getpid(), signal.SIGKILL)
    return fake(paths, out, config, **kwargs)

aperture_fab.pipeline.run_design = killing
run_sweep(load_spec(Path(sys.argv[2])), RunOptions(out=Path(sys.argv[3]), backend="serial"),
          lambda line: None)
"""


def test_a_killed_drivers_rerun_completes_every_table(sweep_dir: Path,
                                                      fake_design: list[dict[str, Any]]
                                                      ) -> None:
    """SIGKILL as the third of 6 points starts: results.csv holds the 2 finished (appended as
    they finished; results.parquet is rewritten only every REFRESH_S and at the end, so it is
    not there yet). The same command again runs only the 4 others and writes every table,
    Parquet too, from the points' point.json files: all 6 rows, the first 2 not redone."""
    tiny = TINY_BASE.replace('"plate.pitch_mm" = 0.25', '"plate.pitch_mm" = 0.8')
    path = write_sweep(sweep_dir, GRID.split("[base]")[0] + tiny + '"plate.thickness_mm" = 0.3\n')
    out = sweep_dir / "out"
    killed = subprocess.run([sys.executable, "-c", _KILLED_DRIVER, str(Path(__file__).parent),
                             str(path), str(out)], capture_output=True, text=True, timeout=120)
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    rows = list(csv.DictReader((out / "results.csv").open()))
    assert [r["status"] for r in rows] == ["ok", "ok"]
    assert not (out / "results.parquet").exists()
    outcome = run_sweep(load_spec(path), RunOptions(out=out, backend="serial"), lambda line: None)
    assert outcome.skipped == 2 and len(fake_design) == 4  # nothing finished is redone
    pq = pytest.importorskip("pyarrow.parquet")
    table = pq.read_table(out / "results.parquet").to_pylist()
    rows = list(csv.DictReader((out / "results.csv").open()))
    assert [r["id"] for r in table] == [r["id"] for r in rows]
    assert [r["status"] for r in table] == ["ok"] * 4 + ["failed"] * 2
    (out / "results.parquet").unlink()  # nothing left to run: the tables are still rebuilt
    run_sweep(load_spec(path), RunOptions(out=out, backend="serial"), lambda line: None)
    assert len(fake_design) == 4 and len(pq.read_table(out / "results.parquet")) == 6


def test_sigterm_writes_the_tables(sweep_dir: Path, fake_design: list[dict[str, Any]],
                                   monkeypatch: pytest.MonkeyPatch,
                                   capsys: pytest.CaptureFixture[str]) -> None:
    """SIGTERM while the second point runs: the sweep stops, writes the tables of the finished
    point (the running one is not finished) and exits 143."""
    import aperture_fab.pipeline

    real = aperture_fab.pipeline.run_design

    def stopping(paths: list[Path], out: Path, config: Any, **kwargs: Any) -> Any:
        result = real(paths, out, config, **kwargs)
        if len(fake_design) == 2:
            os.kill(os.getpid(), signal.SIGTERM)
        return result

    monkeypatch.setattr(aperture_fab.pipeline, "run_design", stopping)
    path = write_sweep(sweep_dir, GRID)
    out = sweep_dir / "out"
    assert run_command(parse([str(path), "--serial", "--out", str(out)])) == 128 + 15
    rows = list(csv.DictReader((out / "results.csv").open()))
    assert [r["status"] for r in rows] == ["ok"] + ["pending"] * 5
    assert (out / "sweep.html").is_file() and (out / "results.parquet").is_file()
    assert signal.getsignal(signal.SIGTERM) is not None
    assert "stopped" in capsys.readouterr().err


def test_progress_bar_and_lines() -> None:
    import io

    clock = iter(range(0, 10_000, 10))
    lines: list[str] = []
    stream = io.StringIO()
    bar = Progress(4, lines.append, terminal=True, stream=stream, clock=lambda: next(clock))
    bar.done({"id": "a", "status": "ok", "figures": {}, "seconds": 1.0}, "x=1")
    bar.done({"id": "b", "status": "failed", "error": "boom"}, "x=2")
    bar.close()
    assert "per min" in stream.getvalue() and "left" in stream.getvalue()
    assert len(lines) == 1 and "FAILED: boom" in lines[0]  # ok points: only the bar
    assert duration(3725) == "1 h 02 min" and duration(42) == "42 s"
    log: list[str] = []
    many = Progress(1000, log.append, clock=lambda: next(clock))
    many.done({"id": "a", "status": "ok", "figures": {}, "seconds": 1.0}, "x=1")
    for _ in range(3):  # 10 s per reading of the clock: a line once 30 s have passed
        many.tick()
    assert len(log) == 1 and log[0].startswith("1/1000 points (1 ok)")


# -- dry run ----------------------------------------------------------------------------------


def test_dry_run_refuses_an_unmakeable_point(sweep_dir: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    """resin cannot make a 0.1 mm plate: --dry-run says so before any work, and exits 1 (as
    the run would: some points fail), so a script that checks first stops there."""
    path = write_sweep(sweep_dir, "[sweep]\ntargets = ['marker.png']\npreset = 'near-eye'\n"
                       "[grid]\n'plate.thickness_mm' = [0.1, 0.3]\n'process.name' = ['resin']\n"
                       + TINY_BASE.replace('"plate.pitch_mm" = 0.25', '"plate.pitch_mm" = 0.8'))
    assert run_command(parse([str(path), "--dry-run"])) == 1
    captured = capsys.readouterr()
    out = captured.out
    assert "refused:" in out and "plate.thickness_mm=0.1" in out and "resin range" in out
    assert "1 refused" in out and "estimated CPU time" in out and "GB per point" in out
    assert "1 of 2 points cannot be made" in captured.err and "recorded as failed" in captured.err


def test_dry_run_of_many_points_is_quick(sweep_dir: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    """1000 tiny points, each its own scene (1000 gaps), each resolved and checked: the rule
    checks and both rendered checks (the light floor, that the eye sees the display) run on
    every one (from the command line, imports included: 9.7 s, median of 3 on 2 shared cores)."""
    gaps = ", ".join(f"{8 + 0.01 * n:.2f}" for n in range(1000))
    path = write_sweep(sweep_dir, "[sweep]\ntargets = ['marker.png']\npreset = 'near-eye'\n"
                       f"[grid]\n'plate.gap_mm' = [{gaps}]\n" + TINY_BASE
                       + '"process.name" = "photomask"\n')
    start = time.perf_counter()
    assert run_command(parse([str(path), "--dry-run"])) == 0
    seconds = time.perf_counter() - start
    out = capsys.readouterr().out
    assert "1000 grid points" in out and "... and 980 more" in out and "0 refused" in out
    assert seconds < 30  # the goal is 10 s; shared CI machines are slower


def test_cpu_model_matches_its_calibration() -> None:
    """The one-core model against design jobs measured for it (docs/sweep.md): a tiny job
    (16 x 16 view, 10 iterations: 6.6 CPU s), a small one (64 x 64, 60 iterations: 43 s), and
    the default near-eye job at about 4.5 minutes (the README's "about five")."""
    from aperture_fab.config import resolve
    from aperture_fab.sweep.estimate import model_cpu_seconds

    tiny = {"display.width_mm": 4.0, "display.height_mm": 4.0, "display.pixels": [32, 32],
            "plate.cells": [16, 16], "plate.pitch_mm": 0.25, "eye.eyebox_mm": 2.0}
    for view, iterations, measured in (([16, 16], 10, 6.63), ([64, 64], 60, 42.78)):
        config = resolve("near-eye", None, tiny | {"eye.view_pixels": view,
                                                   "optimizer.iterations": iterations})
        assert model_cpu_seconds(config, 1) == pytest.approx(measured, rel=0.11)
    assert 240 < model_cpu_seconds(resolve("near-eye", None, {}), 1) < 300


def test_light_floor_screen_is_a_lower_bound(sweep_dir: Path) -> None:
    """check_light_floor's sparse plates pass no more light than the brightest plate: a view
    is a sum of one term per open hole, so the stride x stride phases of a sparse plate add
    up to the full plate exactly, and each is at most the whole."""
    import torch

    from aperture_fab.optics.as_made import white_transmission
    from aperture_fab.optics.model import Renderer
    from aperture_fab.optimize.optimizer import training_states
    from aperture_fab.pipeline.design_job import FLOOR_SCREEN_STRIDES, _white_reach
    from aperture_fab.sweep.preflight import Resolver

    spec = load_spec(write_sweep(sweep_dir, "[sweep]\ntargets = ['marker.png']\n"
                                 "[grid]\n'plate.gap_mm' = [8.0]\n" + TINY_BASE))
    config, _, _ = Resolver(spec)(dict(spec.base))
    scene, settings = config.scene, config.optimizer
    renderer = Renderer(scene, dtype=torch.float64)
    full = _white_reach(renderer, scene, settings, 0.5)
    for stride in FLOOR_SCREEN_STRIDES:
        sparse = _white_reach(renderer, scene, settings, 0.5, stride)
        assert 0 < sparse < full
    phases = 0.0
    for row in range(2):
        for col in range(2):
            open_fraction = torch.zeros(scene.plate.cells[1], scene.plate.cells[0],
                                        dtype=torch.float64)
            open_fraction[row::2, col::2] = 0.5
            phases += float(white_transmission(renderer, open_fraction,
                                               training_states(scene, settings, 0)).mean())
    assert phases == pytest.approx(full, rel=1e-9)


# -- a real two-node cluster ------------------------------------------------------------------


def _ray_bin() -> str | None:
    return shutil.which("ray", path=str(Path(sys.executable).parent)) or shutil.which("ray")


#: Seconds the two-node test waits for the first point, and twice that for the rest (about
#: 70 s in all on 2 quiet cores).
CLUSTER_WAIT_S = 240


def _free_port() -> int:
    return _closed_port()


@pytest.mark.slow
def test_two_node_cluster_survives_a_lost_worker_node(sweep_dir: Path) -> None:
    """A head node (1 CPU) and a worker node (1 CPU) on this machine, token authentication on;
    6 tiny points; the worker node is killed once the first point has finished: every point
    ends ok (the lost ones ran again on the head), exit status 0."""
    pytest.importorskip("ray", reason="ray is not installed (pip install 'aperture-fab[sweep]')")
    ray = _ray_bin()
    if ray is None:
        pytest.skip("ray is installed but its `ray` command is not on the path")
    port = _free_port()
    env = os.environ | {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": "aperture-fab-test-token-0",
                        "RAY_USAGE_STATS_ENABLED": "0"}
    head = [ray, "start", "--head", f"--port={port}", "--num-cpus=1", "--include-dashboard=false",
            "--disable-usage-stats"]
    worker: subprocess.Popen[bytes] | None = None
    try:
        started = subprocess.run(head, env=env, capture_output=True, text=True, timeout=90)
        assert started.returncode == 0, started.stdout + started.stderr
        worker = subprocess.Popen([ray, "start", f"--address=127.0.0.1:{port}", "--num-cpus=1",
                                   "--block", "--disable-usage-stats"], env=env,
                                  start_new_session=True, stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL)
        text = "[sweep]\ntargets = ['marker.png']\npreset = 'near-eye'\n" \
               "[grid]\n'plate.gap_mm' = [8.0, 9.0, 10.0, 11.0, 12.0, 13.0]\n" + TINY_BASE \
               + '"process.name" = "photomask"\n"optimizer.min_efficiency" = 0.0\n'
        path = write_sweep(sweep_dir, text)
        out = sweep_dir / "out"
        driver = subprocess.Popen(
            [sys.executable, "-m", "aperture_fab.sweep", str(path), "--address",
             f"127.0.0.1:{port}", "--out", str(out), "--workers", "2"], env=env,
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        # Generous waits: a loaded 2-core machine runs two raylets, the driver and the points.
        deadline = time.monotonic() + CLUSTER_WAIT_S
        while time.monotonic() < deadline:  # the first point finished: kill the worker node
            if (out / "results.csv").is_file() and \
                    len((out / "results.csv").read_text().splitlines()) > 1:
                break
            time.sleep(0.2)
        os.killpg(worker.pid, signal.SIGKILL)
        output, _ = driver.communicate(timeout=2 * CLUSTER_WAIT_S)
        rows = list(csv.DictReader((out / "results.csv").open()))
        assert driver.returncode == 0, output
        assert [r["status"] for r in rows] == ["ok"] * 6, output
        assert "6 points: 6 ok" in output
        print(output)  # with -s: which points were lost and ran again ("lost, retried")
    finally:
        if worker is not None and worker.poll() is None:
            os.killpg(worker.pid, signal.SIGKILL)
        subprocess.run([ray, "stop", "--force"], env=env, capture_output=True, timeout=60)
