"""`import aperture_fab` and the light commands stay light: no torch, no plotting or mesh code.

`aperture-fab --help`, every subcommand's `--help`, `presets` and `processes` should print at
once (issue 9), so they must not import the heavy libraries that designing needs. Each check
runs in a fresh interpreter (sys.executable), since this test process has them imported already
(conftest imports torch). The public names of the package load on first use (PEP 562).
"""

from __future__ import annotations

import importlib.util
import inspect
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import aperture_fab

ROOT = Path(__file__).resolve().parents[1]

#: Libraries that the light commands must not import.
HEAVY = ("torch", "matplotlib", "scipy", "skimage", "ezdxf", "lxml", "manifold3d", "embreex",
         "tqdm", "PIL")

#: Runs `aperture_fab.cli.main(argv)` (argv from sys.argv), then prints the heavy modules loaded.
CHILD = f"""\
import contextlib, io, json, sys
import aperture_fab
from aperture_fab.cli import build_parser, main
build_parser()
out = io.StringIO()
code = None
with contextlib.redirect_stdout(out):
    try:
        code = main(sys.argv[1:]) if len(sys.argv) > 1 else None
    except SystemExit as exit:
        code = exit.code
loaded = sorted(name for name in {HEAVY!r} if name in sys.modules)
print(json.dumps({{"code": code, "printed": len(out.getvalue()), "loaded": loaded}}))
"""

LIGHT_COMMANDS = [
    [],  # the import and the parser alone
    ["--help"],
    ["design", "--help"],
    ["export", "--help"],
    ["validate", "--help"],
    ["render", "--help"],
    ["presets", "--help"],
    ["processes", "--help"],
    ["presets"],
    ["processes"],
]


def run_child(code: str, *argv: str) -> dict:
    result = subprocess.run([sys.executable, "-c", code, *argv], cwd=ROOT, capture_output=True,
                            text=True, check=False, timeout=120)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("argv", LIGHT_COMMANDS, ids=lambda argv: " ".join(argv) or "import")
def test_light_commands_do_not_import_heavy_libraries(argv: list[str]) -> None:
    result = run_child(CHILD, *argv)
    assert result["loaded"] == [], f"aperture-fab {' '.join(argv)} imported {result['loaded']}"
    if argv:
        assert result["code"] == 0
        assert result["printed"] > 0  # the command did print its help or table


def test_light_public_names_do_not_import_torch() -> None:
    """Config, resolve, the scene classes and targets load without the optimizer."""
    code = (
        "import json, sys\n"
        "import aperture_fab as af\n"
        "names = [af.Config, af.resolve, af.Display, af.Eye, af.Plate, af.Scene, af.targets]\n"
        "assert af.__version__\n"
        "print(json.dumps({'torch': 'torch' in sys.modules}))\n"
    )
    assert run_child(code) == {"torch": False}


@pytest.mark.parametrize(("given", "expected"), [(None, "PASSIVE"), ("ACTIVE", "ACTIVE")])
def test_import_sets_openmp_wait_policy_unless_given(given: str | None, expected: str) -> None:
    """aperture_fab sets OMP_WAIT_POLICY before torch loads (its spinning OpenMP threads held
    the cores from the Numba kernels); a value the user set is kept."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if given is not None:
        env["OMP_WAIT_POLICY"] = given
    code = "import aperture_fab, os; print(os.environ['OMP_WAIT_POLICY'])"
    result = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env,
                            capture_output=True, text=True, check=True, timeout=120)
    assert result.stdout.strip() == expected


def test_lazy_public_names_resolve_to_their_definitions() -> None:
    from aperture_fab import config, pipeline, targets
    from aperture_fab.optics import scene

    assert callable(aperture_fab.design) and aperture_fab.design is pipeline.design
    assert inspect.isclass(aperture_fab.DesignResult)
    assert aperture_fab.DesignResult is pipeline.DesignResult
    assert aperture_fab.Config is config.Config and aperture_fab.resolve is config.resolve
    assert (aperture_fab.Display, aperture_fab.Eye, aperture_fab.Plate, aperture_fab.Scene) == (
        scene.Display, scene.Eye, scene.Plate, scene.Scene)
    assert aperture_fab.targets is targets
    from aperture_fab.validation import report

    assert (aperture_fab.Report, aperture_fab.Verdict) == (report.Report, report.Verdict)
    assert set(aperture_fab.__all__) <= set(dir(aperture_fab))
    assert all(hasattr(aperture_fab, name) for name in aperture_fab.__all__)
    assert isinstance(aperture_fab.__version__, str)
    namespace: dict[str, object] = {}
    exec("from aperture_fab import *", namespace)
    assert set(aperture_fab.__all__) <= set(namespace)


def test_unknown_attribute_raises_a_clear_attribute_error() -> None:
    with pytest.raises(AttributeError, match=r"has no attribute 'no_such_name'.*design"):
        aperture_fab.no_such_name  # noqa: B018
    with pytest.raises(ImportError):
        exec("from aperture_fab import no_such_name", {})
    assert not hasattr(aperture_fab, "no_such_name")


def test_bench_cli_runs(tmp_path: Path) -> None:
    """benchmarks/bench_cli.py times every command once and writes consistent figures."""
    spec = importlib.util.spec_from_file_location("bench_cli", ROOT / "benchmarks" / "bench_cli.py")
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    out = tmp_path / "cli.json"
    figures = bench.main(["--repeats", "1", "--json", str(out)])
    assert json.loads(out.read_text()) == json.loads(json.dumps(figures))
    assert figures["goal_s"] == 0.5 and figures["repeats"] == 1
    assert set(figures["commands"]) == set(bench.cases())
    for label, case in figures["commands"].items():
        assert case["median_s"] > 0 and len(case["runs_s"]) == 1, label
        assert case["ratio_to_goal"] == pytest.approx(case["median_s"] / 0.5)
