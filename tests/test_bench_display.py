"""benchmarks/bench_display.py runs end to end (--quick) and writes the figures it prints.

Not a timing test: the figures only have to exist, be finite and positive, and be consistent.
Slow-marked like the other benchmark smoke tests (the near-eye scene: about 15 s on 2 cores).
"""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path
from types import ModuleType

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def _load(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def _positive(value: object) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value) and value > 0


@pytest.mark.slow
def test_bench_display_quick_runs_and_writes_its_figures(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bench = _load("bench_display")
    out = tmp_path / "display.json"
    figures = bench.main(["--quick", "--device", "cpu", "--json", str(out)])
    assert json.loads(out.read_text()) == json.loads(json.dumps(figures))
    text = capsys.readouterr().out
    assert "Goal 33 ms per frame" in text and "untracked" in text
    assert figures["quick"] and figures["goal_frame_s"] == pytest.approx(0.033)
    (cpu,) = figures["devices"]
    assert cpu["device"] == "cpu" and _positive(cpu["setup_s"])
    assert [row["iterations"] for row in cpu["latency"]] == list(bench.QUICK_ITERATIONS)
    for row in cpu["latency"]:
        assert _positive(row["frame_s"]) and _positive(row["checked_s"])
        assert row["ratio_to_goal"] == pytest.approx(row["frame_s"] / 0.033)
        assert len(row["frame_runs_s"]) == figures["repeats"] == 1
    assert len(cpu["quality"]) == len(bench.QUICK_QUALITY)
    for row in cpu["quality"]:
        # keep_best: the tracked display is never worse than the untracked one.
        assert row["tracked_psnr_db"] >= row["untracked_psnr_db"] > 0
    assert cpu["compare"] is None


def test_bench_display_arguments() -> None:
    bench = _load("bench_display")
    args = bench.parse_args(["--iterations", "1", "3", "--repeats", "2"])
    assert args.iterations == [1, 3] and args.repeats == 2 and args.device == "all"
    with pytest.raises(SystemExit):
        bench.parse_args(["--iterations", "0"])
