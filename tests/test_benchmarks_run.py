"""The benchmark scripts run end to end (quickest settings) and write the figures they print.

Not timing tests: the figures only have to exist, be finite and positive, and be consistent with
each other. The case definitions are checked fast against the scenes they claim to build.
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
    # Registered first: dataclasses look their module up in sys.modules.
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def _positive(value: object) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value) and value > 0


@pytest.fixture(scope="module")
def bench_optimize() -> ModuleType:
    return _load("bench_optimize")


@pytest.fixture(scope="module")
def bench_quality() -> ModuleType:
    return _load("bench_quality")


@pytest.mark.parametrize(
    ("name", "cells", "display_pixels", "view_pixels", "pitch_mm"),
    [
        ("seed-28", (28, 28), (28, 28), (28, 28), (10 / 28, 15 / 28)),
        ("seed-100", (100, 100), (100, 100), (28, 28), (0.1, 0.15)),
        ("near-eye", (80, 80), (400, 400), (128, 128), (0.25, 0.25)),
        ("near-eye-1", (80, 80), (400, 400), (128, 128), (0.25, 0.25)),
        ("nominal", (80, 80), (400, 400), (128, 128), (0.25, 0.25)),
        ("nominal-torch", (80, 80), (400, 400), (128, 128), (0.25, 0.25)),
        ("large", (512, 512), (1024, 1024), (512, 512), (0.05, 0.05)),
    ],
)
def test_case_scenes(bench_optimize: ModuleType, name: str, cells: tuple[int, int],
                     display_pixels: tuple[int, int], view_pixels: tuple[int, int],
                     pitch_mm: tuple[float, float]) -> None:
    case = bench_optimize.CASES[name]
    config = bench_optimize.case_config(case, "cpu", 7)
    scene = config.scene
    assert scene.plate.cells == cells
    assert scene.display.pixels == display_pixels
    assert scene.eye.view_pixels == view_pixels
    assert scene.plate.pitch_mm == pytest.approx(pitch_mm)
    # Every scene's plate covers its display exactly.
    assert scene.plate.size_mm == pytest.approx((scene.display.width_mm, scene.display.height_mm))
    assert config.optimizer.iterations == 7
    assert config.optimizer.plateau_patience == 0  # timed runs never stop early


def test_case_eye_states_and_backends(bench_optimize: ModuleType) -> None:
    """The issue-9 cases: 16 drawn states, one drawn state, the nominal state on the default
    backend and on the torch path (the reference), side by side on the same scene."""
    from aperture_fab.optics.eyes import distribution_of

    cases = bench_optimize.CASES
    configs = {name: bench_optimize.case_config(cases[name], "cpu", 1)
               for name in ("near-eye", "near-eye-1", "nominal", "nominal-torch", "large")}
    assert configs["near-eye"].optimizer.eye_states == 16
    assert configs["near-eye-1"].optimizer.eye_states == 1
    assert not distribution_of(configs["near-eye-1"].scene.eye).is_point
    for name in ("nominal", "nominal-torch", "large"):
        assert distribution_of(configs[name].scene.eye).is_point, name
    assert configs["nominal"].scene == configs["nominal-torch"].scene
    assert cases["nominal-torch"].backend == "torch" and cases["nominal"].backend == "auto"
    quick = bench_optimize.case_config(cases["near-eye"], "cpu", 1, quick=True)
    assert quick.scene.eye.view_pixels == (32, 32)
    assert bench_optimize.case_config(cases["large"], "cpu", 1, quick=True).scene.eye \
        .view_pixels == (512, 512)


def test_kernel_pairs_and_bytes(bench_optimize: ModuleType) -> None:
    """The pair count of the bytes model: every state's own pairs, or the union when the
    states share them (all focused at infinity)."""
    import numpy as np

    from aperture_fab.optics.eyes import EyeStates
    from aperture_fab.optics.model import Renderer

    config = bench_optimize.case_config(bench_optimize.CASES["nominal"], "cpu", 1, quick=True)
    renderer = Renderer(config.scene)
    open_fraction = np.full((80, 80), 0.3)
    one = renderer.nominal_states()
    pairs, evaluations = bench_optimize.kernel_pairs(renderer, open_fraction, one)
    assert evaluations == pairs  # one state: one evaluation per sample
    assert 0 < pairs < 32 * 32 * 80 * 80
    twice = EyeStates.concat([one, one])
    # Shared (infinite focus): one sample per pair, one evaluation per state and pair.
    assert bench_optimize.kernel_pairs(renderer, open_fraction, twice) == (pairs, 2 * pairs)
    near = EyeStates(one.offset_mm, one.pupil_mm, np.array([0.25]), one.gaze_deg, one.weight)
    unshared, both = bench_optimize.kernel_pairs(renderer, open_fraction,
                                                 EyeStates.concat([one, near]))
    assert unshared == both and pairs < unshared <= 3 * pairs
    assert bench_optimize.kernel_pairs(renderer, np.zeros((80, 80)), one)[0] == 0
    model = bench_optimize.kernel_bytes(pairs, 1, 3, 1024, 4, 10**6, 2, 1, True)
    assert model["read"] == model["forward_read"] + model["backward_read"]
    assert model["forward_read"] == pairs * 8 * 3 * 4


@pytest.mark.slow
def test_bench_optimize_quick(bench_optimize: ModuleType, tmp_path: Path,
                              capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "optimize.json"
    returned = bench_optimize.main(["--quick", "--repeats", "1", "--device", "cpu",
                                    "--json", str(out)])
    figures = json.loads(out.read_text())
    assert figures == json.loads(json.dumps(returned))
    assert figures["quick"] is True
    env = figures["environment"]
    assert env["torch"] and env["device"] == "cpu" and _positive(env["threads"])
    assert set(figures["cases"]) == {"seed-28", "seed-100", "near-eye", "near-eye-1",
                                     "nominal", "nominal-torch"}
    assert _positive(figures["copy_bandwidth"]["numpy_gbs"])
    assert _positive(figures["copy_bandwidth"]["torch_gbs"])
    for name, case in figures["cases"].items():
        for key in ("setup_s", "iteration_s", "measured_s", "pairs", "forward_s", "backward_s",
                    "estimate_mib"):
            assert _positive(case[key]), (name, key, case[key])
        # A small case can stay within the memory the imports already took.
        assert math.isfinite(case["peak_rss_increase_mib"]) and case["peak_rss_increase_mib"] >= 0
        if case["goal_s"] is not None:
            assert case["ratio_to_goal"] == pytest.approx(case["measured_s"] / case["goal_s"])
        assert case["cuda_peak_mib"] is None
        assert all(_positive(s) for s in case["iteration_s_runs"])
        # An iteration spans its loss's forward and backward (the rest is never negative).
        assert case["other_s"] >= 0, (name, case["other_s"])
        if case["backend"] == "kernel":
            for key in ("kernel_forward_s", "kernel_backward_s", "read_gb", "achieved_gbs"):
                assert _positive(case[key]), (name, key, case[key])
        else:
            assert case["achieved_gbs"] is None
    assert figures["cases"]["nominal-torch"]["backend"] == "torch"
    assert figures["cases"]["near-eye"]["states"] == 16
    goals = figures["goals"]
    cases = figures["cases"]
    assert goals["single_speedup"] == pytest.approx(
        cases["nominal-torch"]["iteration_s"] / cases["nominal"]["iteration_s"])
    assert goals["states_ratio"] == pytest.approx(
        cases["near-eye"]["iteration_s"] / cases["nominal-torch"]["iteration_s"])
    seed = figures["cases"]["seed-28"]
    # A quick design is extended to 300 iterations at its steady-state rate.
    assert seed["projected"] is True and seed["nominal_iterations"] == 300
    assert seed["measured_s"] == pytest.approx(
        seed["design_s"] + (300 - seed["iterations"]) * seed["iteration_s"])
    assert seed["speedup_vs_reference"] == pytest.approx(33.0 / seed["measured_s"])
    assert figures["cases"]["near-eye"]["metric"] == "iteration"
    printed = capsys.readouterr().out
    assert all(name in printed for name in figures["cases"])
    assert "goal: single-state iteration >= 3x faster" in printed


@pytest.mark.slow
def test_bench_optimize_refuses_over_budget(bench_optimize: ModuleType, tmp_path: Path,
                                            monkeypatch: pytest.MonkeyPatch,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    """A case over the memory budget is reported as refused, with the estimate, not run."""
    monkeypatch.setenv("APERTURE_FAB_MEMORY_GB", "0.001")
    figures = bench_optimize.main(["--quick", "--repeats", "1", "--device", "cpu",
                                   "--cases", "large"])
    large = figures["cases"]["large"]
    assert "budget" in large["refused"] and large["estimate_mib"] > 1
    assert "refused" in capsys.readouterr().out


def test_bench_optimize_skips_cuda_without_a_gpu(bench_optimize: ModuleType) -> None:
    import torch

    if torch.cuda.is_available():
        pytest.skip("a GPU is present")
    assert bench_optimize.main(["--device", "cuda"]) == {"skipped": "no CUDA device"}


@pytest.mark.slow
def test_bench_quality_quick(bench_quality: ModuleType, tmp_path: Path) -> None:
    out = tmp_path / "quality.json"
    bench_quality.main(["--iterations", "2", "--targets", "digit-3", "--device", "cpu",
                        "--json", str(out)])
    figures = json.loads(out.read_text())
    assert figures["preset"] == "near-eye" and figures["iterations"] == 2
    assert set(figures["targets"]) == {"digit-3"}
    result = figures["targets"]["digit-3"]
    assert set(result["psnr_db"]) == {"open", "regular_pinholes", "initial", "optimized",
                                      "as_built"}
    assert all(_positive(v) for v in result["psnr_db"].values())
    assert result["iterations_run"] == 2 and _positive(result["seconds"])
    psnr = result["psnr_db"]
    assert result["loss_db"] == pytest.approx(psnr["optimized"] - psnr["as_built"])
    assert result["beats_baselines"] == (psnr["as_built"] > max(psnr["open"],
                                                                psnr["regular_pinholes"]))
    assert _positive(result["final_loss"])


@pytest.mark.slow
@pytest.mark.parametrize("cache", ["cold", "warm"])
def test_bench_end_to_end_quick(tmp_path: Path, cache: str) -> None:
    bench = _load("bench_end_to_end")
    out = tmp_path / "e2e.json"
    figures = bench.main(["--preset", "seed", "--iterations", "2", "--target", "digit-3",
                          "--cache", cache, "--json", str(out)])
    assert json.loads(out.read_text()) == figures and figures["cache"] == cache
    stages = figures["median_stages_s"]
    for stage in ("optimize_s", "quantize_build_s", "export_s", "render_s", "report_s"):
        assert stage in stages and stages[stage] >= 0, stage
    assert figures["median_wall_s"] >= sum(stages.values())  # the stages run one after another
    after = sum(v for k, v in stages.items() if k != "optimize_s")
    assert figures["after_optimizer_s"] == pytest.approx(after)
    assert 0 < figures["after_optimizer_share"] < 1


@pytest.mark.slow
def test_bench_light_quick_prices_the_floor(tmp_path: Path) -> None:
    bench = _load("bench_light")
    out = tmp_path / "light.json"
    rows = bench.main(["--quick", "--json", str(out)])
    assert json.loads(out.read_text()) == json.loads(json.dumps(rows))
    assert [row["floor"] for row in rows] == bench.QUICK["floors"]
    assert rows[1]["efficiency"] > rows[0]["efficiency"]  # the floor bought light
    for row in rows:
        assert row["regime"] in ("photopic", "mesopic", "scotopic")
        assert row["psnr_db"]["p10"] <= row["psnr_db"]["p50"] <= row["psnr_db"]["p90"]


@pytest.mark.slow
def test_bench_display_quick_runs_and_writes_its_figures(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bench = _load("bench_display")
    out = tmp_path / "display.json"
    figures = bench.main(["--quick", "--device", "cpu", "--light-floors", "0", "1", "--json",
                          str(out)])
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
    assert len(cpu["light_floors"]) == len(bench.QUICK_QUALITY)
    for row in cpu["light_floors"]:
        free, held = row["floors"]
        assert (free["light_floor"], held["light_floor"]) == (0, 1)
        assert held["light_share"] >= 1 - 1e-4 and _positive(free["light_share"])  # float32
        assert held["psnr_db"] >= row["untracked_psnr_db"]  # keep_best


def test_bench_display_arguments() -> None:
    bench = _load("bench_display")
    args = bench.parse_args(["--iterations", "1", "3", "--repeats", "2"])
    assert args.iterations == [1, 3] and args.repeats == 2 and args.device == "all"
    with pytest.raises(SystemExit):
        bench.parse_args(["--iterations", "0"])
    assert bench.parse_args(["--light-floors", "0", "0.5"]).light_floors == [0.0, 0.5]
    with pytest.raises(SystemExit):
        bench.parse_args(["--light-floors", "1.5"])


@pytest.mark.slow
def test_bench_eyes_quick_runs_and_writes_its_figures(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "eyes.json"
    figures = _load("bench_eyes").main(["--quick", "--json", str(out)])
    assert json.loads(out.read_text()) == json.loads(json.dumps(figures))
    (result,) = figures["targets"].values()
    for key in ("as_built", "nominal_design", "open", "regular_pinholes"):
        p = result["untracked"][key]
        assert p["p10"] <= p["p50"] <= p["p90"]
    assert set(result["tracked"]) == {"as_built", "regular_pinholes"}
    assert "untracked p10 margin" in capsys.readouterr().out


@pytest.mark.slow
def test_bench_gap_scale_quick(tmp_path: Path) -> None:
    """A gap error's view, taken at its picture's size, is the nominal view to well above the
    PSNR scale of a made part (31.6 dB measured in the quick run), and its figures are written."""
    out = tmp_path / "gap.json"
    results = _load("bench_gap_scale").main(["--quick", "--json", str(out)])
    assert json.loads(out.read_text()) == results
    for row in results:
        assert _positive(row["nominal_psnr_db"])
        for e in row["errors"]:
            assert e["scaled_vs_nominal_view_db"] > 25


@pytest.mark.slow
def test_bench_made_part_quick(tmp_path: Path) -> None:
    """The part as made against the regular family: the figures are written, the light at the
    eye is in cd/m2 for the panel, and the best rival is at least as bright at the eye; so
    with a tracked display (--tracked) holding the untracked light (--tracked-light 1)."""
    out = tmp_path / "made.json"
    rows = _load("bench_made_part").main(["--quick", "--json", str(out), "--plot",
                                          str(tmp_path), "--tracked", "1",
                                          "--tracked-light", "1", "--tracked-states", "2"])
    assert json.loads(out.read_text()) == rows
    for row in rows:
        for key in ("p10_db", "efficiency", "eye_level", "eye_cd_m2", "optimizer_db"):
            assert _positive(row[key]), key
        assert row["eye_cd_m2"] == pytest.approx(row["eye_level"] * row["panel_cd_m2"])
        assert row["eye_level"] < row["efficiency"]  # the content is darker than white
        if row.get("margin_db") is not None:
            assert row["best_eye_level"] >= row["eye_level"] * (1 - 1e-9)
            assert row["margin_db"] == pytest.approx(row["p10_db"] - row["best_p10_db"])
            low, high = row["margin_interval_db"]
            assert low <= high
        assert (tmp_path / f"made_part_{row['target']}.png").stat().st_size > 0
        tracked = row["tracked"]
        assert tracked["iterations"] == 1 and tracked["searched"] >= 1
        assert _positive(tracked["part"]["p10_db"])
        # The floor holds the untracked light in the solve's model (the made copies' veil
        # and diffraction move it a little); unfloored, MLEM's content is several times darker.
        assert tracked["light_floor"] == 1
        assert tracked["part"]["eye_level"] >= 0.9 * row["eye_level"]
        if tracked["best"] is not None:
            # chosen at least as bright over the search's states (judged again over all, it
            # may come out a little darker: the bench prints so)
            assert _positive(tracked["best"]["eye_level"])
            assert tracked["margin_db"] == pytest.approx(
                tracked["part"]["p10_db"] - tracked["best"]["p10_db"])
            assert tracked["margin_interval_db"][0] <= tracked["margin_interval_db"][1]


@pytest.mark.slow
def test_probe_cuda_graph_runs(bench_optimize: ModuleType) -> None:
    """Without CUDA the probe times the eager iteration on the CPU kernels (the capture needs a
    GPU)."""
    found = _load("probe_cuda_graph").main(["--iterations", "3"])
    assert _positive(found["eager_s"]) and "graph_s" not in found


@pytest.mark.slow
def test_bench_refit_quick(tmp_path: Path) -> None:
    """The refit's figures per made copy, and the summary of those that lose, as printed."""
    out = tmp_path / "refit.json"
    result = _load("bench_refit").main(["--quick", "--json", str(out)])
    assert json.loads(out.read_text()) == result
    assert [row["seed"] for row in result["copies"]] == [11, 12]
    losing = [row for row in result["copies"] if row["tolerance_loss_db"] > 0]
    assert result["summary"]["losing"] == len(losing)
    for row in losing:
        assert row["refit_psnr_db"] >= row["made_psnr_db"]
    if losing:
        shares = [row["recovered_share"] for row in losing]
        assert result["summary"]["lowest_share"] == min(shares)
        assert result["summary"]["at_goal"] == sum(share >= 0.5 for share in shares)


@pytest.mark.slow
def test_bench_rival_fit_quick(tmp_path: Path) -> None:
    """A rival's p10 and light at the eye per fit length, as printed: the elemental images and
    a short fit."""
    out = tmp_path / "rival.json"
    rows = _load("bench_rival_fit").main(["--quick", "--json", str(out)])
    assert json.loads(out.read_text()) == rows
    assert [row["fit_iterations"] for row in rows] == [0, 2]
    for row in rows:
        assert _positive(row["p10_db"]) and _positive(row["eye_level"])
        assert row["p50_db"] >= row["p10_db"]


def test_bench_stack_quick() -> None:
    """The display stack's forward and backward times, as printed; an unknown pitch refused."""
    figures = _load("bench_stack").main(["--quick"])
    for name in ("forward_ms", "backward_ms", "all_levels_forward_ms", "all_levels_backward_ms"):
        assert _positive(figures[name])
    with pytest.raises(SystemExit, match="no such lattice pitch"):
        _load("bench_stack").main(["--pitch-mm", "0.3"])
