"""The design-space sweep: the sweep file and its errors, grid points and ids, the Pareto front,
resuming, failed points, the result files, and a real small sweep on a local Ray instance.

Fast tests replace the design job with a fake that writes a report.json at once (counting its
calls); the slow ones run real tiny design jobs."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from aperture_fab.sweep.command import add_parser
from aperture_fab.sweep.command import run as run_command
from aperture_fab.sweep.results import (
    dominates,
    figures_from_report,
    pareto_mask,
    write_results,
)
from aperture_fab.sweep.run import POINT_FILE, RunOptions, load_record, run_sweep
from aperture_fab.sweep.settings import resolve_point
from aperture_fab.sweep.spec import (
    Choice,
    FloatRange,
    IntRange,
    grid_points,
    load_spec,
)

TINY_BASE = """\
[base]
"display.width_mm" = 4.0
"display.height_mm" = 4.0
"display.pixels" = [32, 32]
"plate.cells" = [16, 16]
"plate.pitch_mm" = 0.25
"eye.view_pixels" = [16, 16]
"eye.eyebox_mm" = 2.0
"optimizer.iterations" = 6
"optimizer.device" = "cpu"
"validation.tolerance_samples" = 2
"validation.mesh_samples" = 8
"""

GRID = """\
[sweep]
targets = ["marker.png"]
preset = "near-eye"

[grid]
"plate.gap_mm" = [8.0, 10.0, 12.0]
"process.name" = ["resin", "etched-foil"]

[base]                                 # a plate both processes make (checked before running)
"plate.thickness_mm" = 0.3
"plate.pitch_mm" = 0.8
"plate.cells" = [25, 25]
"""


def write_sweep(folder: Path, text: str, name: str = "sweep.toml") -> Path:
    path = folder / name
    path.write_text(text)
    return path


@pytest.fixture
def sweep_dir(tmp_path: Path, marker_png: Path) -> Path:
    """A folder holding marker.png (the sweep files name it relative to themselves)."""
    assert marker_png.parent == tmp_path
    return tmp_path


# -- the sweep file ------------------------------------------------------------------------------


def test_grid_spec_parses(sweep_dir: Path) -> None:
    spec = load_spec(write_sweep(sweep_dir, GRID))
    assert spec.mode == "grid"
    assert spec.targets == ((sweep_dir / "marker.png").resolve(),)
    assert [str(o) for o in spec.objectives] == ["maximize eye_p10_psnr_db",
                                                  "maximize light_efficiency"]
    assert spec.swept_keys == ("plate.gap_mm", "process.name")


def test_nested_tables_are_dotted_keys(sweep_dir: Path) -> None:
    text = GRID.replace('"plate.gap_mm" = [8.0, 10.0, 12.0]', "plate.gap_mm = [8.0, 10.0]") \
        .replace('"plate.thickness_mm" = 0.3', "optimizer.iterations = 3")
    spec = load_spec(write_sweep(sweep_dir, text))
    assert dict(spec.grid)["plate.gap_mm"] == (8.0, 10.0)
    assert dict(spec.base)["optimizer.iterations"] == 3


def test_search_spec_parses(sweep_dir: Path) -> None:
    spec = load_spec(write_sweep(sweep_dir, """
[sweep]
mode = "search"
targets = ["marker.png"]
trials = 5
objectives = ["maximize eye_p50_psnr_db", "minimize hole_count"]
[space]
"plate.gap_mm" = { low = 6.0, high = 14.0 }
"plate.pitch_mm" = { low = 0.2, high = 0.6, log = true }
"optimizer.iterations" = { low = 10, high = 40 }
"plate.cells" = { choices = [[16, 16], [24, 24]] }
"""))
    assert spec.space == (FloatRange("plate.gap_mm", 6.0, 14.0),
                          FloatRange("plate.pitch_mm", 0.2, 0.6, log=True),
                          IntRange("optimizer.iterations", 10, 40),
                          Choice("plate.cells", ((16, 16), (24, 24))))
    assert spec.population == 5  # capped by the trials


BAD_SPECS = [
    ("[sweep]\ntargets = ['marker.png']\n[grids]\n'plate.gap_mm' = [8.0]\n", "Did you mean 'grid'"),
    ("[sweep]\ntargets = ['marker.png']\nmodes = 'grid'\n[grid]\n'plate.gap_mm' = [8.0]\n",
     "Did you mean 'mode'"),
    ("[sweep]\ntargets = ['marker.png']\nmode = 'random'\n", "choose one of grid, search"),
    ("[sweep]\n[grid]\n'plate.gap_mm' = [8.0]\n", "give the target images"),
    ("[sweep]\ntargets = ['nothere.png']\n[grid]\n'plate.gap_mm' = [8.0]\n", "does not exist"),
    ("[sweep]\ntargets = ['marker.png']\nobjectives = ['maximize sharpness']\n"
     "[grid]\n'plate.gap_mm' = [8.0]\n", "unknown figure 'sharpness'"),
    ("[sweep]\ntargets = ['marker.png']\nobjectives = ['increase light_efficiency']\n"
     "[grid]\n'plate.gap_mm' = [8.0]\n", "is not an objective"),
    ("[sweep]\ntargets = ['marker.png']\nobjectives = []\n[grid]\n'plate.gap_mm' = [8.0]\n",
     "non-empty list"),
    ("[sweep]\ntargets = ['marker.png']\n[grid]\n", "[grid]: is empty"),
    ("[sweep]\ntargets = ['marker.png']\n[grid]\n'plate.gap_mm' = []\n", "non-empty list"),
    ("[sweep]\ntargets = ['marker.png']\n[grid]\n'plate.gap_mm' = 8.0\n", "non-empty list"),
    ("[sweep]\ntargets = ['marker.png']\n[grid]\n'plate.gap_mm' = [8.0, 8.0]\n",
     "repeats a value"),
    ("[sweep]\ntargets = ['marker.png']\n[grid]\n'gap_mm' = [8.0]\n", "must be dotted"),
    ("[sweep]\ntargets = ['marker.png']\n[grid]\n'plates.gap_mm' = [8.0]\n",
     "Did you mean 'plate'"),
    ("[sweep]\ntargets = ['marker.png']\n[base]\n'plate.gap_mm' = 9.0\n"
     "[grid]\n'plate.gap_mm' = [8.0]\n", "also swept"),
    ("[sweep]\ntargets = ['marker.png']\n[space]\n'plate.gap_mm' = {low = 6.0, high = 9.0}\n",
     'is for mode = "search"'),
    ("[sweep]\nmode = 'search'\ntargets = ['marker.png']\n[space]\n", "[space]: is empty"),
    ("[sweep]\nmode = 'search'\ntargets = ['marker.png']\n[space]\n"
     "'plate.gap_mm' = {low = 9.0, high = 6.0}\n", "must be below high"),
    ("[sweep]\nmode = 'search'\ntargets = ['marker.png']\n[space]\n"
     "'plate.gap_mm' = {low = 0.0, high = 6.0, log = true}\n", "needs low > 0"),
    ("[sweep]\nmode = 'search'\ntargets = ['marker.png']\n[space]\n"
     "'plate.gap_mm' = {low = 1.0, top = 6.0}\n", "a range has keys low, high"),
    ("[sweep]\nmode = 'search'\ntargets = ['marker.png']\n[space]\n"
     "'plate.gap_mm' = [6.0, 9.0]\n", "is not a range or choices"),
    ("[sweep]\nmode = 'search'\ntargets = ['marker.png']\n[space]\n"
     "'process.name' = {choices = []}\n", "non-empty"),
    ("[sweep]\nmode = 'search'\ntargets = ['marker.png']\ntrials = 0\n[space]\n"
     "'plate.gap_mm' = {low = 6.0, high = 9.0}\n", "trials"),
    ("[sweep]\ntargets = ['marker.png']\nconfig = 'missing.toml'\n[grid]\n'plate.gap_mm' = [8.0]\n",
     "cannot read"),
    ("[sweep\n", "TOML syntax error"),
]


@pytest.mark.parametrize(("text", "fragment"), BAD_SPECS)
def test_bad_sweep_files_are_refused(sweep_dir: Path, text: str, fragment: str) -> None:
    path = write_sweep(sweep_dir, text)
    with pytest.raises(ValueError, match=r"sweep\.toml") as info:
        load_spec(path)
    assert fragment in str(info.value)


BAD_VALUES = [
    ('"plate.gapmm" = [8.0]', ["[grid] plate.gapmm = 8.0", "Did you mean 'gap_mm'"]),
    ('"plate.gap_mm" = [8.0, "wide"]', ["[grid] plate.gap_mm = wide", "8.0, wide",
                                        "a number"]),
    ('"process.name" = ["resin", "wood"]', ["process.name = wood", "resin, fdm, laser"]),
    ('"validation.tolerance_sample" = [2]', ["validation.tolerance_sample", "unknown key(s)"]),
]


@pytest.mark.parametrize(("grid", "fragments"), BAD_VALUES)
def test_bad_values_are_refused_before_running(sweep_dir: Path, grid: str,
                                               fragments: list[str]) -> None:
    spec = load_spec(write_sweep(sweep_dir, "[sweep]\ntargets = ['marker.png']\n[grid]\n"
                                 + grid + "\n"))
    with pytest.raises(ValueError, match=r"sweep\.toml") as info:
        run_sweep(spec, RunOptions(out=sweep_dir / "out", backend="serial"))
    for fragment in fragments:
        assert fragment in str(info.value)
    assert not (sweep_dir / "out").exists()  # nothing ran, nothing was written


def test_points_that_do_not_go_together_are_named(sweep_dir: Path) -> None:
    spec = load_spec(write_sweep(sweep_dir, "[sweep]\ntargets = ['marker.png']\n"
                                 "[grid]\n'eye.pupil_range_mm' = [[3.0, 6.0]]\n"
                                 "'eye.pupil_mm' = [4.0, 20.0]\n"))
    with pytest.raises(ValueError, match=r"sweep\.toml") as info:
        run_sweep(spec, RunOptions(out=sweep_dir / "out", backend="serial"))
    assert "20.0" in str(info.value)


# -- points and ids ---------------------------------------------------------------------------


def test_grid_expansion_and_stable_ids(sweep_dir: Path) -> None:
    spec = load_spec(write_sweep(sweep_dir, GRID))
    points = grid_points(spec)
    assert [p.settings for p in points][:2] == [
        (("plate.gap_mm", 8.0), ("process.name", "resin")),
        (("plate.gap_mm", 8.0), ("process.name", "etched-foil"))]
    assert len(points) == 6 and len({p.id for p in points}) == 6
    assert [p.id for p in grid_points(load_spec(spec.source))] == [p.id for p in points]
    # The key order in the file does not change a point's id; the base does.
    swapped = GRID.replace('"plate.gap_mm" = [8.0, 10.0, 12.0]\n', "").replace(
        '"process.name" = ["resin", "etched-foil"]\n',
        '"process.name" = ["resin", "etched-foil"]\n"plate.gap_mm" = [8.0, 10.0, 12.0]\n')
    other = grid_points(load_spec(write_sweep(sweep_dir, swapped, "b.toml")))
    assert {p.id for p in other} == {p.id for p in points}
    based = grid_points(load_spec(write_sweep(sweep_dir, GRID.replace(
        '"plate.thickness_mm" = 0.3', '"plate.thickness_mm" = 0.4'), "c.toml")))
    assert not {p.id for p in based} & {p.id for p in points}
    (sweep_dir / "marker.png").write_bytes((sweep_dir / "marker.png").read_bytes() + b"\0")
    edited = grid_points(load_spec(spec.source))  # another target image: other points
    assert not {p.id for p in edited} & {p.id for p in points}


# -- the Pareto front -------------------------------------------------------------------------


def brute_front(values: np.ndarray, maximize: list[bool]) -> list[bool]:
    signed = values * np.where(maximize, 1.0, -1.0)
    return [not bool(np.any(np.all(signed >= row, axis=1) & np.any(signed > row, axis=1)))
            for row in signed]


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 3).flatmap(lambda k: st.tuples(
    st.lists(st.lists(st.integers(-4, 4).map(float), min_size=k, max_size=k), min_size=1,
             max_size=25),
    st.lists(st.booleans(), min_size=k, max_size=k))))
def test_pareto_matches_brute_force(case: tuple[list[list[float]], list[bool]]) -> None:
    values, maximize = case
    mask = pareto_mask(values, maximize)
    assert mask == brute_front(np.array(values), maximize)
    assert any(mask)
    front = [v for v, m in zip(values, mask, strict=True) if m]
    for v, m in zip(values, mask, strict=True):  # every dominated point: by one on the front
        assert m or any(dominates(f, v, maximize) for f in front)


def test_dominates() -> None:
    assert dominates([2, 1], [1, 1], [True, True])
    assert not dominates([1, 1], [1, 1], [True, True])
    assert dominates([1, 1], [2, 1], [False, True])
    assert not dominates([2, 0], [1, 1], [True, True])


# -- running: resume, failures, search (with a fake design job) --------------------------------


def fake_report(gap_mm: float, pitch_mm: float, process: str) -> dict[str, Any]:
    """A report.json with the figures the sweep reads: sharper with a larger gap, brighter
    with a smaller one."""
    p10 = 10.0 + gap_mm + (0.5 if process == "resin" else 0.0)
    return {
        "eye_distribution": {"variants": {"as_built": {"psnr_db": {
            "p10": [p10, p10 + 1], "p50": [p10 + 1, p10 + 2], "p90": [p10 + 2, p10 + 3]}}}},
        "metrics": {"as_built": {"mean": {"psnr_db": p10 + 1.5,
                                          "light_efficiency": 0.1 / gap_mm / pitch_mm}}},
        "scene": {"eye": {"fov_deg": [30.0, 20.0]}},
        "photometry": {"view_luminance_cd_m2": 50.0 / gap_mm, "retinal_illuminance_td": 80.0,
                       "leakage": {"contrast_ratio": float("inf")}},
        "fabrication": {"holes": 100, "violations": [{"rule": "min_web"}]},
        "made_part": {"part": {"efficiency": 0.02, "p10_db": [p10 - 1, p10],
                               "p50_db": [p10, p10]},
                      "regular": {"best": {"p10_db": [p10 - 4, p10 - 3]}},
                      "margin_db": [3.0, 3.0]},
    }


@pytest.fixture
def fake_design(monkeypatch: pytest.MonkeyPatch) -> list[dict[str, Any]]:
    """Replace run_design by a fake that writes report.json and returns the result's report
    (its `as_json` gives report.json's content), as run_design does; returns the list of its
    calls.
    A gap of exactly 12 mm raises, like a point the process cannot make."""
    return install_fake_design(monkeypatch)


def install_fake_design(monkeypatch: pytest.MonkeyPatch) -> list[dict[str, Any]]:
    """fake_design's work (other test modules' fixtures call it)."""
    import aperture_fab.pipeline

    calls: list[dict[str, Any]] = []

    def run_design(paths: list[Path], out: Path, config: Any, **kwargs: Any) -> Any:
        plate = config.scene.plate
        process = kwargs["fabrication"].process.name
        calls.append({"gap_mm": plate.gap_mm, "process": process})
        assert all(Path(p).is_file() for p in paths)
        if plate.gap_mm == 12.0:
            raise ValueError("cannot make this one")
        report = fake_report(plate.gap_mm, plate.pitch_mm[0], process)
        (out.parent / "report.json").write_text(json.dumps(report))
        return SimpleNamespace(report=SimpleNamespace(as_json=lambda: report))

    monkeypatch.setattr(aperture_fab.pipeline, "run_design", run_design)
    return calls


def test_figures_from_report() -> None:
    figures = figures_from_report(fake_report(10.0, 0.5, "resin"))
    assert figures == {"eye_p10_psnr_db": 21.0, "eye_p50_psnr_db": 22.0,
                       "eye_p90_psnr_db": 23.0, "nominal_psnr_db": 22.0,
                       "light_efficiency": pytest.approx(0.02), "luminance_cd_m2": 5.0,
                       "retinal_illuminance_td": 80.0, "contrast_ratio": float("inf"),
                       "made_p10_psnr_db": 20.0, "made_p50_psnr_db": 20.5,
                       "made_light_efficiency": 0.02, "regular_p10_psnr_db": 17.0,
                       "made_margin_db": 3.0, "fov_x_deg": 30.0,
                       "fov_y_deg": 20.0, "hole_count": 100, "rule_violations": 1}
    bare = figures_from_report({"eye_distribution": None, "photometry": None})
    assert bare["eye_p10_psnr_db"] is None and bare["luminance_cd_m2"] is None
    assert bare["made_p10_psnr_db"] is None and bare["made_margin_db"] is None


def test_resume_skips_finished_and_records_failures(sweep_dir: Path,
                                                    fake_design: list[dict[str, Any]]) -> None:
    spec = load_spec(write_sweep(sweep_dir, GRID))
    out = sweep_dir / "out"
    lines: list[str] = []
    outcome = run_sweep(spec, RunOptions(out=out, backend="serial"), lines.append)
    assert len(fake_design) == 6 and outcome.ran == 6 and outcome.failed == 2
    failed = [r for r in outcome.records.values() if r["status"] == "failed"]
    assert all("cannot make this one" in r["error"] and "Traceback" in r["traceback"]
               for r in failed)
    assert sum("FAILED" in line for line in lines) == 2
    ok = next(p for p in outcome.points if outcome.records[p.id]["status"] == "ok")
    record = load_record(out / "points" / ok.id)
    assert record is not None and record["settings"] == dict(ok.settings)

    again = run_sweep(spec, RunOptions(out=out, backend="serial"), lines.append)
    assert len(fake_design) == 6 and again.ran == 0 and again.skipped == 6
    (out / "points" / ok.id / POINT_FILE).unlink()  # as if interrupted while it ran
    third = run_sweep(spec, RunOptions(out=out, backend="serial"), lines.append)
    assert len(fake_design) == 7 and third.ran == 1
    retried = run_sweep(spec, RunOptions(out=out, backend="serial", retry_failed=True),
                        lines.append)
    assert len(fake_design) == 9 and retried.ran == 2 and retried.failed == 2


def test_result_files(sweep_dir: Path, fake_design: list[dict[str, Any]]) -> None:
    import pyarrow.parquet as pq

    spec = load_spec(write_sweep(sweep_dir, GRID))
    out = sweep_dir / "out"
    outcome = run_sweep(spec, RunOptions(out=out, backend="serial"), lambda line: None)
    paths = write_results(out, spec, outcome.points, outcome.records)
    table = pq.read_table(paths["results.parquet"]).to_pylist()
    assert [row["id"] for row in table] == [p.id for p in outcome.points]
    assert [row["status"] for row in table].count("failed") == 2
    csv_lines = paths["results.csv"].read_text().splitlines()
    assert csv_lines[0].startswith("id,status,plate.gap_mm,process.name,eye_p10_psnr_db")
    assert len(csv_lines) == 7
    # Sharper with a larger gap, brighter with a smaller one: the ok points at 8 and 10 mm
    # with resin trade against each other; etched-foil is dominated at either gap.
    front = paths["pareto.csv"].read_text().splitlines()[1:]
    assert len(front) == 2 and all(",resin," in line for line in front)
    page = paths["sweep.html"].read_text()
    assert "<svg" in page and page.count('class="front"') == 2
    for point in outcome.points:
        ok = outcome.records[point.id]["status"] == "ok"
        assert f"points/{point.id}/{'report.html' if ok else 'point.json'}" in page


SEARCH = """\
[sweep]
mode = "search"
targets = ["marker.png"]
trials = {trials}
population = 3
seed = 7
[space]
"plate.gap_mm" = {{ low = 6.0, high = 11.0 }}
"process.name" = {{ choices = ["resin", "etched-foil"] }}
[base]
"plate.thickness_mm" = 0.3
"plate.pitch_mm" = 0.8
"plate.cells" = [25, 25]
"""


def test_search_is_seeded_and_resumes(sweep_dir: Path,
                                      fake_design: list[dict[str, Any]]) -> None:
    full = run_sweep(load_spec(write_sweep(sweep_dir, SEARCH.format(trials=9))),
                     RunOptions(out=sweep_dir / "full", backend="serial"), lambda line: None)
    # NSGA-II may propose a point twice (crossover of equal parents); it runs once.
    unique = len(full.points)
    assert 6 <= unique <= 9 and len(fake_design) == unique
    again = run_sweep(load_spec(write_sweep(sweep_dir, SEARCH.format(trials=9), "again.toml")),
                      RunOptions(out=sweep_dir / "again", backend="serial"), lambda line: None)
    assert [p.id for p in again.points] == [p.id for p in full.points]  # serial: seeded
    # The same search stopped after 3 trials, then run again to 9: the 3 finished points are
    # told to the study first and not run again; 6 more trials are asked.
    part = run_sweep(load_spec(write_sweep(sweep_dir, SEARCH.format(trials=3), "part.toml")),
                     RunOptions(out=sweep_dir / "split", backend="serial"), lambda line: None)
    assert [p.id for p in part.points] == [p.id for p in full.points[:3]]
    calls = len(fake_design)
    rest = run_sweep(load_spec(write_sweep(sweep_dir, SEARCH.format(trials=9), "rest.toml")),
                     RunOptions(out=sweep_dir / "split", backend="serial"), lambda line: None)
    assert [p.id for p in rest.points][:3] == [p.id for p in part.points]
    assert rest.skipped == 3 and rest.ran == len(rest.points) - 3 == len(fake_design) - calls
    assert len(rest.points) <= 9


# -- the command ------------------------------------------------------------------------------


def parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers())
    return parser.parse_args(["sweep", *argv])


def test_dry_run_lists_points(sweep_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write_sweep(sweep_dir, GRID)
    assert run_command(parse([str(path), "--dry-run"])) == 0
    out = capsys.readouterr().out
    assert "6 grid points" in out and "plate.gap_mm=12.0, process.name=etched-foil" in out


def test_module_entry_point_reports_errors(sweep_dir: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    from aperture_fab.sweep.__main__ import main

    path = write_sweep(sweep_dir, "[sweep]\ntargets = ['marker.png']\n[grid]\n")
    assert main([str(path)]) == 3  # bad input, as `aperture-fab` says it
    assert "[grid]: is empty" in capsys.readouterr().err


def test_command_serial_exit_status(sweep_dir: Path, fake_design: list[dict[str, Any]],
                                    capsys: pytest.CaptureFixture[str]) -> None:
    path = write_sweep(sweep_dir, GRID)
    out = sweep_dir / "out"
    assert run_command(parse([str(path), "--serial", "--out", str(out)])) == 1  # 2 failed
    captured = capsys.readouterr()
    assert "6 points: 4 ok, 2 failed" in captured.out and "--retry-failed" in captured.err
    assert (out / "sweep.html").is_file() and (out / "results.parquet").is_file()


def test_example_sweep_file_checks() -> None:
    """The example's 24 points pass the file's checks and both processes' rules (every point
    makeable). Its whole --dry-run, the rendered checks too (15 s of near-eye renders), runs
    in tests/test_docs_commands.py, as docs/sweep.md gives it."""
    from aperture_fab.fabrication.rules import check_plate
    from aperture_fab.sweep.preflight import Resolver
    from aperture_fab.sweep.spec import check_points
    from aperture_fab.sweep.worker import plain

    spec = load_spec(Path(__file__).parent.parent / "examples" / "sweep.toml")
    points = grid_points(spec)
    resolve = Resolver(spec)
    check_points(spec, points, resolve)
    assert len(points) == 24
    for point in points:
        config, fabrication, _ = resolve({k: plain(v) for k, v in point.overrides})
        check_plate(fabrication.process, config.scene.plate, config.scene.eye.eye_relief_mm)


def test_cli_main_runs_sweep(sweep_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from aperture_fab.cli import main

    path = write_sweep(sweep_dir, GRID)
    assert main(["sweep", str(path), "--dry-run"]) == 0
    assert "6 grid points" in capsys.readouterr().out
    assert main(["sweep", str(write_sweep(sweep_dir, "[sweep]\n", "bad.toml"))]) == 3


# -- real design jobs --------------------------------------------------------------------------


REAL = """\
[sweep]
targets = ["marker.png"]
preset = "near-eye"
objectives = ["maximize eye_p10_psnr_db", "maximize light_efficiency"]

[grid]
"plate.gap_mm" = [8.0, 10.0]

""" + TINY_BASE


@pytest.mark.slow
def test_real_sweep_on_local_ray(sweep_dir: Path, capsys: pytest.CaptureFixture[str],
                                 monkeypatch: pytest.MonkeyPatch) -> None:
    import pyarrow.parquet as pq

    path = write_sweep(sweep_dir, REAL)
    out = sweep_dir / "out"
    monkeypatch.chdir(sweep_dir)  # a relative --out: the workers must still find it
    assert run_command(parse(["sweep.toml", "--workers", "2", "--out", "out"])) == 0
    printed = capsys.readouterr().out
    assert "local Ray instance with 2 CPU(s)" in printed and "2 points: 2 ok" in printed
    rows = pq.read_table(out / "results.parquet").to_pylist()
    assert [r["plate.gap_mm"] for r in rows] == [8.0, 10.0]
    for row in rows:
        assert row["status"] == "ok" and row["hole_count"] > 0
        assert row["eye_p10_psnr_db"] <= row["eye_p50_psnr_db"] <= row["eye_p90_psnr_db"]
        assert 0 < row["light_efficiency"] < 1 and row["fov_x_deg"] > 0
        assert row["luminance_cd_m2"] > 0 and row["contrast_ratio"] > 1
        assert (out / "points" / row["id"] / "report.html").is_file()
    assert len((out / "pareto.csv").read_text().splitlines()) >= 2
    page = (out / "sweep.html").read_text()
    assert all(f"points/{r['id']}/report.html" in page for r in rows)
    # A rerun finds both points finished and runs nothing (serial: no second Ray start).
    assert run_command(parse([str(path), "--serial", "--out", str(out)])) == 0
    assert "0 ran now (0 lost and retried), 2 finished before" in capsys.readouterr().out


@pytest.mark.slow
def test_real_sweep_gathers_files(sweep_dir: Path) -> None:
    """--gather: the task works in a temporary folder and sends the files back."""
    spec = load_spec(write_sweep(sweep_dir, REAL.replace("[8.0, 10.0]", "[9.0]")))
    out = sweep_dir / "out"
    outcome = run_sweep(spec, RunOptions(out=out, backend="serial", files="gather"),
                        lambda line: None)
    (point,) = outcome.points
    assert outcome.records[point.id]["status"] == "ok"
    assert {"report.html", "report.json", "plate.stl", POINT_FILE} <= \
        {p.name for p in (out / "points" / point.id).iterdir()}


@pytest.mark.parametrize(("base_file", "overrides", "lattice"), [
    (None, {}, "fixed"), (None, {"optimizer.lattice": "rival"}, "rival"),
    ({"optimizer": {"lattice": "rival"}}, {}, "rival")])
def test_a_point_keeps_its_plate_unless_the_sweep_sets_the_lattice(base_file, overrides,
                                                                    lattice):
    """A sweep over the plate compares the plates it asked for: the design job's redesign on a
    regular array's lattice (optimizer.lattice = "rival", the preset's) is off unless set."""
    config, _, _ = resolve_point("near-eye", base_file, overrides)
    assert config.optimizer.lattice == lattice
