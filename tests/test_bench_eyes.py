"""The eye-distribution benchmark runs end to end (a smoke run: one target, a few states)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_bench_eyes_quick_run(tmp_path: Path) -> None:
    out = tmp_path / "eyes.json"
    run = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_eyes.py"), "--quick",
                          "--json", str(out)], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    figures = json.loads(out.read_text())
    (result,) = figures["targets"].values()
    for key in ("as_built", "nominal_design", "open", "regular_pinholes"):
        p = result["untracked"][key]
        assert p["p10"] <= p["p50"] <= p["p90"]
    assert set(result["tracked"]) == {"as_built", "regular_pinholes"}
    assert "untracked p10 margin" in run.stdout
