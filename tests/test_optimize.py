"""The optimizer: it lowers the loss, keeps to its bounds, stops, diverges loudly, and resumes
exactly from checkpoints and interruptions."""

from __future__ import annotations

import copy
import dataclasses
import math
import re
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import torch
from conftest import interrupt_at_call, tiny_config
from hypothesis import given, settings
from hypothesis import strategies as st

import aperture_fab.optimize.optimizer as optimize_module
from aperture_fab.config.config import Config
from aperture_fab.fabrication.part import made_optics
from aperture_fab.fabrication.process import resolve_process
from aperture_fab.io.images import resample
from aperture_fab.metrics import gain_mse, psnr_db
from aperture_fab.optics.as_made import MadeOptics, draw_errors
from aperture_fab.optics.model import Renderer
from aperture_fab.optimize.budget import OPTIMIZER_OVERSAMPLE
from aperture_fab.optimize.optimizer import DivergedError, Interrupted, MaskDesign, optimize
from aperture_fab.optimize.start import initial_design
from aperture_fab.targets import asymmetric_marker, checker

pytestmark = pytest.mark.usefixtures("one_torch_thread")

MakeConfig = Callable[..., Config]

#: The design wavelength of the pinhole baseline (green, 550 nm), in mm.
GREEN_MM = 550e-6

# float64 runs on the CPU are bit-for-bit repeatable; this only absorbs printing-level noise.
EXACT_RTOL, EXACT_ATOL = 1e-6, 1e-9


def assert_exact(actual: Any, expected: Any) -> None:
    np.testing.assert_allclose(actual, expected, rtol=EXACT_RTOL, atol=EXACT_ATOL)


def prepare(config: Config, images: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Grey targets on the view grid (T, 1, ny, nx) and on the display grid (T, 1, H, W)."""
    scene = config.scene
    views = np.stack([resample(im[:1], scene.eye.view_pixels) for im in images])
    shown = np.stack([resample(im[:1], scene.display.pixels) for im in images])
    return views, shown


def run(config: Config, images: list[np.ndarray] | None = None, **kwargs: Any) -> MaskDesign:
    targets, shown = prepare(config, images or [asymmetric_marker(32)])
    return optimize(config.scene, targets, shown, config.optimizer, progress=False, **kwargs)


def closed_form_gain_mse(view: np.ndarray, target: np.ndarray) -> float:
    """min over g of mean((g view - target)^2) = mean(t^2) - (v.t)^2 / (|v|^2 N)."""
    v, t = view.ravel(), target.ravel()
    vv = float(v @ v)
    if vv == 0:
        return float(t @ t) / t.size
    return (float(t @ t) - float(v @ t) ** 2 / vv) / t.size


def rendered_loss(config: Config, open_fraction: np.ndarray, display: np.ndarray,
                  target: np.ndarray) -> float:
    """The loss of a plate and display, rendered afresh (as the optimizer renders) and judged
    by the closed form."""
    renderer = Renderer(config.scene, device="cpu", dtype=torch.float64,
                        oversample=OPTIMIZER_OVERSAMPLE)
    view = renderer.render(torch.as_tensor(open_fraction), torch.as_tensor(display)).numpy()
    return closed_form_gain_mse(view, target)


# --- gain_mse and psnr_db --------------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), gain=st.floats(1e-3, 1e3))
def test_gain_mse_ignores_the_view_level_and_matches_the_closed_form(seed: int,
                                                                     gain: float) -> None:
    rng = np.random.default_rng(seed)
    view, target = rng.random((2, 3, 5, 7))
    base = float(gain_mse(torch.as_tensor(view), torch.as_tensor(target)))
    scaled = float(gain_mse(torch.as_tensor(gain * view), torch.as_tensor(target)))
    assert scaled == pytest.approx(base, rel=1e-9)
    assert base == pytest.approx(closed_form_gain_mse(view, target), rel=1e-9)
    assert 0 < base <= float(np.mean(target**2))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), gain=st.floats(1e-3, 1e3))
def test_gain_mse_is_zero_for_a_scaled_copy_of_the_target(seed: int, gain: float) -> None:
    target = np.random.default_rng(seed).random((1, 6, 4)) + 0.01
    loss = float(gain_mse(torch.as_tensor(gain * target), torch.as_tensor(target)))
    assert loss == pytest.approx(0.0, abs=1e-12 * float(np.mean(target**2)))


def test_gain_mse_of_a_black_view_is_the_target_power_not_nan() -> None:
    # An all-closed plate must give a finite loss the optimizer can climb out of.
    target = np.random.default_rng(1).random((1, 4, 4))
    loss = float(gain_mse(torch.zeros(1, 4, 4, dtype=torch.float64), torch.as_tensor(target)))
    assert loss == pytest.approx(float(np.mean(target**2)), rel=1e-12)


@pytest.mark.parametrize(("mse", "expected_db"), [(1.0, 0.0), (1e-2, 20.0), (1e-3, 30.0),
                                                  (2.5e-4, 10 * math.log10(4000))])
def test_psnr_db_for_a_unit_peak(mse: float, expected_db: float) -> None:
    assert psnr_db(mse) == pytest.approx(expected_db, abs=1e-12)


def test_psnr_db_of_a_perfect_match_is_finite() -> None:
    assert math.isfinite(psnr_db(0.0))
    assert psnr_db(0.0) >= psnr_db(1e-12)


# --- the loss goes down, within bounds -------------------------------------------------------


def test_adam_with_optimized_display_lowers_the_loss(make_config: MakeConfig) -> None:
    config = make_config(**{"optimizer.iterations": 15, "optimizer.precision": "float64"})
    # Black and white: the display content must move even from pixels at exactly 0 or 1.
    images = [asymmetric_marker(32)]
    targets, shown = prepare(config, images)
    result = run(config, images)
    assert result.stopped == "completed"
    assert result.loss_history.shape == (15,)
    assert result.loss_history[-1] < 0.7 * result.loss_history[0]
    # Judged afresh, not by the optimizer's bookkeeping: the result beats its starting point.
    a0, d0 = initial_design(config.scene, targets, shown, config.optimizer)
    before = rendered_loss(config, a0, d0[0], targets[0])
    after = rendered_loss(config, result.open_fraction, result.displays[0], targets[0])
    assert before == pytest.approx(result.loss_history[0], rel=1e-6)
    assert after < 0.7 * before
    # The display content was optimized: it moved away from its (elemental image) start.
    assert np.abs(result.displays - d0).max() > 0.05


def test_sgd_with_the_target_shown_from_a_random_mask_lowers_the_loss(
        make_config: MakeConfig) -> None:
    config = make_config(**{"optimizer.method": "sgd", "optimizer.learning_rate": 0.8,
                            "optimizer.schedule": "constant", "optimizer.init": "random",
                            "optimizer.display": "target", "optimizer.iterations": 15})
    targets, shown = prepare(config, [asymmetric_marker(32)])
    result = run(config)
    assert result.loss_history[-1] < 0.95 * result.loss_history[0]
    # Display mode "target": the display shows the target, untouched.
    np.testing.assert_array_equal(result.displays, shown)
    after = rendered_loss(config, result.open_fraction, shown[0], targets[0])
    assert after < 0.95 * result.loss_history[0]


@pytest.mark.parametrize("bounds", [None, (0.05, 0.3), (0.2, 0.21)])
@pytest.mark.parametrize("init", ["pinholes", "random", "uniform"])
def test_every_open_fraction_stays_within_the_bounds(bounds: tuple[float, float] | None,
                                                      init: str, make_config: MakeConfig) -> None:
    config = make_config(**{"optimizer.init": init, "optimizer.learning_rate": 0.5,
                            "optimizer.iterations": 4})
    result = run(config, bounds=bounds)
    lo, hi = bounds if bounds is not None else (0.0, config.scene.plate.max_open_fraction)
    assert result.bounds == (lo, hi)
    assert result.open_fraction.shape == (16, 16)
    assert result.open_fraction.dtype == np.float64
    assert np.all(result.open_fraction >= lo)
    assert np.all(result.open_fraction <= hi)
    assert np.all((result.displays >= 0) & (result.displays <= 1))


def test_default_upper_bound_is_the_largest_hole_a_cell_takes(make_config: MakeConfig) -> None:
    config = make_config()
    assert config.scene.plate.max_open_fraction == pytest.approx(math.pi / 4)
    assert run(config, bounds=None).bounds == pytest.approx((0.0, math.pi / 4))


@pytest.mark.parametrize("bounds", [(0.3, 0.2), (-0.1, 0.5), (0.1, 1.5), (0.2, 0.2)])
def test_bad_bounds_are_refused(bounds: tuple[float, float], make_config: MakeConfig) -> None:
    with pytest.raises(ValueError, match="bounds"):
        run(make_config(), bounds=bounds)


def test_targets_off_the_view_grid_are_refused(make_config: MakeConfig) -> None:
    config = make_config()
    _, shown = prepare(config, [asymmetric_marker(32)])
    wrong = np.zeros((1, 1, 8, 16))
    with pytest.raises(ValueError, match=r"\(T, C, \*\(16, 16\)\)"):
        optimize(config.scene, wrong, shown, config.optimizer, progress=False)


@pytest.mark.parametrize("init", ["pinholes", "random", "uniform"])
@pytest.mark.parametrize("display", ["optimized", "target"])
def test_every_init_and_display_mode_runs(init: str, display: str, make_config: MakeConfig) -> None:
    config = make_config(**{"optimizer.init": init, "optimizer.display": display,
                            "optimizer.iterations": 3})
    targets, shown = prepare(config, [asymmetric_marker(32)])
    result = run(config)
    assert np.all(np.isfinite(result.loss_history)) and result.loss_history.shape == (3,)
    assert result.displays.shape == shown.shape
    a0, _ = initial_design(config.scene, targets, shown, config.optimizer)
    if init == "uniform":  # every hole half way between the bounds
        np.testing.assert_allclose(a0, config.scene.plate.max_open_fraction / 2, rtol=1e-6)
    if init == "pinholes":  # diffraction-optimal pinholes, sqrt(2 lambda h) across
        height_mm = config.scene.plate.gap_mm + config.scene.plate.thickness_mm / 2
        diameter_mm = math.sqrt(2 * GREEN_MM * height_mm)
        pinhole = math.pi * (diameter_mm / 2) ** 2 / 0.25**2
        assert a0.max() == pytest.approx(pinhole, rel=1e-5)
        assert 1 < np.count_nonzero(a0 > pinhole / 2) < a0.size / 10
    if init == "random":
        assert np.unique(np.round(a0, 6)).size > 100


@pytest.mark.parametrize("diameter_mm", [0.1, 0.2])
def test_a_sized_pinhole_start_has_that_hole_in_every_cell(diameter_mm: float,
                                                          make_config: MakeConfig) -> None:
    """optimizer.init_diameter_mm (the design job's start on a rival's lattice): every cell
    holds a hole of that diameter, and the display starts as that array's elemental images."""
    config = make_config(**{"optimizer.init_diameter_mm": diameter_mm})
    targets, shown = prepare(config, [asymmetric_marker(32)])
    a0, d0 = initial_design(config.scene, targets, shown, config.optimizer)
    hole = math.pi * (diameter_mm / 2) ** 2 / math.prod(config.scene.plate.pitch_mm)
    np.testing.assert_allclose(a0, hole, rtol=1e-4)
    plain, d_plain = initial_design(config.scene, targets, shown,
                                    dataclasses.replace(config.optimizer, init_diameter_mm=0.0))
    assert np.count_nonzero(plain > plain.max() / 2) < a0.size / 10
    assert np.abs(d0 - d_plain).max() > 0.1  # other holes, other elemental images


@pytest.mark.parametrize(("overrides", "message"), [
    ({"optimizer.init_diameter_mm": -0.1}, "init_diameter_mm = -0.1 is out of range"),
    ({"optimizer.init_diameter_mm": float("nan")}, "init_diameter_mm = nan is out of range"),
    ({"optimizer.init_diameter_mm": 0.2, "optimizer.init": "random"},
     'init = "random"; use init = "pinholes"')])
def test_a_sized_start_out_of_range_is_refused(overrides: dict, message: str,
                                              make_config: MakeConfig) -> None:
    with pytest.raises(ValueError, match=re.escape(message)):
        make_config(**overrides)


def test_random_init_depends_on_the_seed_only(make_config: MakeConfig) -> None:
    images = [asymmetric_marker(32)]
    config = make_config(**{"optimizer.init": "random"})
    targets, shown = prepare(config, images)
    a0, _ = initial_design(config.scene, targets, shown, config.optimizer)
    a0_again, _ = initial_design(config.scene, targets, shown, config.optimizer)
    other = make_config(**{"optimizer.init": "random", "optimizer.seed": 1})
    a1, _ = initial_design(other.scene, targets, shown, other.optimizer)
    np.testing.assert_array_equal(a0, a0_again)
    assert np.abs(a0 - a1).max() > 0.1


@pytest.mark.parametrize("init", ["pinholes", "random"])
def test_same_seed_gives_the_same_design(init: str, make_config: MakeConfig) -> None:
    config = make_config(**{"optimizer.init": init, "optimizer.iterations": 5})
    first, second = run(config), run(config)
    np.testing.assert_array_equal(first.open_fraction, second.open_fraction)
    np.testing.assert_array_equal(first.displays, second.displays)
    np.testing.assert_array_equal(first.loss_history, second.loss_history)


def test_several_targets_share_one_plate_and_get_one_display_each(make_config: MakeConfig) -> None:
    config = make_config(**{"optimizer.iterations": 3, "optimizer.precision": "float64"})
    images = [asymmetric_marker(32), checker(32, 4)]
    both = run(config, images)
    assert both.open_fraction.shape == (16, 16)
    assert both.displays.shape == (2, 1, 32, 32)
    assert np.abs(both.displays[0] - both.displays[1]).max() > 0.1
    # The loss is the mean over targets: at the shared start, the mean of each alone.
    alone = [run(config, [im]).loss_history[0] for im in images]
    assert both.loss_history[0] == pytest.approx(np.mean(alone), rel=1e-9)


def test_eyebox_positions_are_weighted(make_config: MakeConfig) -> None:
    # Straight holes, a random mask and the target shown: the plate and the display do not
    # depend on the eye positions, so only the loss's weighting links the three runs.
    # The weighted mean over the positions (tail_share 1), not a tail of them.
    common = {"plate.hole_axis": "straight", "optimizer.init": "random",
              "optimizer.display": "target", "optimizer.iterations": 1,
              "optimizer.precision": "float64", "optimizer.tail_share": 1.0}
    nominal = run(make_config(**common, **{"eye.positions_mm": [[0.0, 0.0]]}))
    shifted = run(make_config(**common, **{"eye.positions_mm": [[0.6, 0.0]]}))
    both = run(make_config(**common, **{"eye.positions_mm": [[0.0, 0.0], [0.6, 0.0]],
                                        "eye.weights": [3.0, 1.0]}))
    assert nominal.loss_history[0] != pytest.approx(shifted.loss_history[0], rel=1e-3)
    expected = (3 * nominal.loss_history[0] + shifted.loss_history[0]) / 4
    assert both.loss_history[0] == pytest.approx(expected, rel=1e-9)


def test_efficiency_weight_adds_a_term_proportional_to_the_weight(make_config: MakeConfig) -> None:
    common = {"optimizer.iterations": 1, "optimizer.precision": "float64"}
    plain = run(make_config(**common)).loss_history[0]
    light = [run(make_config(**common, **{"optimizer.efficiency_weight": w})).loss_history[0]
             for w in (0.1, 0.3)]
    # The plate passes less light than the open display: the term (1 - efficiency) is positive.
    assert light[0] > plain
    assert (light[1] - plain) / (light[0] - plain) == pytest.approx(3.0, rel=1e-6)


# --- stopping and divergence -----------------------------------------------------------------


def test_plateau_stops_early(make_config: MakeConfig) -> None:
    patience = 2
    config = make_config(**{"optimizer.learning_rate": 1e-9, "optimizer.iterations": 20,
                            "optimizer.plateau_patience": patience,
                            "optimizer.plateau_tolerance": 1e-3})
    result = run(config)
    assert result.stopped == "plateau"
    # The first iteration sets the best; `patience` more without progress stop the run.
    assert result.loss_history.shape == (patience + 1,)


def test_zero_patience_never_stops_early(make_config: MakeConfig) -> None:
    config = make_config(**{"optimizer.learning_rate": 1e-9, "optimizer.iterations": 6,
                            "optimizer.plateau_patience": 0})
    result = run(config)
    assert result.stopped == "completed"
    assert result.loss_history.shape == (6,)


def test_a_nan_target_raises_diverged_error_naming_the_learning_rate(
        make_config: MakeConfig) -> None:
    config = make_config(**{"optimizer.learning_rate": 0.07})
    targets, shown = prepare(config, [asymmetric_marker(32)])
    targets[0, 0, 3, 3] = np.nan
    with pytest.raises(DivergedError, match=r"learning rate.*0\.07") as info:
        optimize(config.scene, targets, shown, config.optimizer, progress=False)
    assert isinstance(info.value, FloatingPointError)  # the CLI reports those as errors
    assert "iteration 0" in str(info.value)


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_a_loss_that_turns_non_finite_mid_run_raises_diverged_error(
        monkeypatch: pytest.MonkeyPatch, bad: float, make_config: MakeConfig) -> None:
    calls = {"n": 0}
    real = optimize_module.gain_mse_states

    def failing(view: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        calls["n"] += 1
        loss = real(view, target)
        return loss * bad if calls["n"] == 3 else loss

    monkeypatch.setattr(optimize_module, "gain_mse_states", failing)
    with pytest.raises(DivergedError, match=r"iteration 2.*lower the learning rate"):
        run(make_config())


# --- checkpoints, interruption and resume ----------------------------------------------------


def assert_same_design(a: MaskDesign, b: MaskDesign) -> None:
    assert_exact(a.open_fraction, b.open_fraction)
    assert_exact(a.displays, b.displays)
    assert a.loss_history.shape == b.loss_history.shape
    assert_exact(a.loss_history, b.loss_history)
    assert a.stopped == b.stopped


RESUMABLE: dict[str, dict[str, Any]] = {
    # Adam on plate and display under a cosine schedule: the lr depends on the iteration.
    "adam": {},
    # SGD with momentum on the plate alone, the target shown as is.
    "sgd": {"optimizer.method": "sgd", "optimizer.learning_rate": 0.8,
            "optimizer.display": "target", "optimizer.init": "random"},
}


@pytest.fixture
def resumable_config(make_config: MakeConfig) -> MakeConfig:
    """make_config for 12 float64 iterations, checkpoints every 4, of a RESUMABLE method."""

    def config(method: str, **extra: Any) -> Config:
        return make_config(**{"optimizer.iterations": 12, "optimizer.checkpoint_every": 4,
                          "optimizer.precision": "float64", **RESUMABLE[method],
                              **extra})

    return config


@pytest.mark.parametrize("method", list(RESUMABLE))
def test_resuming_from_a_checkpoint_equals_an_uninterrupted_run(
        method: str, resumable_config: MakeConfig, monkeypatch: pytest.MonkeyPatch) -> None:
    config = resumable_config(method)
    whole = run(config)
    saved: list[dict[str, Any]] = []
    run(config, on_checkpoint=saved.append)
    assert [s["iteration"] for s in saved] == [4, 8, 12]
    assert [len(s["history"]) for s in saved] == [4, 8, 12]
    assert_exact(saved[1]["history"], whole.loss_history[:8])
    calls = count_calls(monkeypatch)
    assert_same_design(run(config, state=saved[0]), whole)
    assert calls["n"] == 12 - 4  # it went on from the checkpoint, not from the start


def test_resuming_from_the_last_checkpoint_runs_nothing_more(
        resumable_config: MakeConfig, monkeypatch: pytest.MonkeyPatch) -> None:
    config = resumable_config("adam")
    whole = run(config)
    saved: list[dict[str, Any]] = []
    run(config, on_checkpoint=saved.append)
    calls = count_calls(monkeypatch)
    assert_same_design(run(config, state=saved[-1]), whole)
    assert calls["n"] == 0


def test_resuming_leaves_the_state_untouched_so_it_can_be_resumed_again(
        resumable_config: MakeConfig) -> None:
    config = resumable_config("adam")
    whole = run(config)
    saved: list[dict[str, Any]] = []
    run(config, on_checkpoint=saved.append)
    state = saved[0]
    pristine = copy.deepcopy(state)
    assert_same_design(run(config, state=state), whole)
    assert state["history"] == pristine["history"]
    assert_same_design(run(config, state=state), whole)


def count_calls(monkeypatch: pytest.MonkeyPatch) -> dict[str, int]:
    """Count the loss evaluations (one per iteration for one target and one eye position)."""
    calls = {"n": 0}
    real = optimize_module.gain_mse_states

    def counted(view: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        calls["n"] += 1
        return real(view, target)

    monkeypatch.setattr(optimize_module, "gain_mse_states", counted)
    return calls


@pytest.mark.parametrize("method", list(RESUMABLE))
@pytest.mark.parametrize("at_call", [1, 6])
def test_interrupted_run_resumes_to_the_same_result(
        monkeypatch: pytest.MonkeyPatch, method: str, at_call: int,
        resumable_config: MakeConfig) -> None:
    config = resumable_config(method)
    whole = run(config)
    interrupt_at_call(monkeypatch, at_call)
    with pytest.raises(Interrupted) as info:
        run(config)
    state = info.value.state
    # The iteration in flight did not step: the state holds the ones completed before it.
    assert state["iteration"] == at_call - 1
    assert len(state["history"]) == at_call - 1
    assert_exact(state["history"], whole.loss_history[:at_call - 1])
    assert f"iteration {at_call - 1}" in str(info.value)
    monkeypatch.undo()
    calls = count_calls(monkeypatch)
    assert_same_design(run(config, state=state), whole)
    assert calls["n"] == 12 - (at_call - 1)


def test_interrupted_state_can_be_interrupted_and_resumed_again(
        monkeypatch: pytest.MonkeyPatch, resumable_config: MakeConfig) -> None:
    config = resumable_config("adam")
    whole = run(config)
    interrupt_at_call(monkeypatch, 4)
    with pytest.raises(Interrupted) as first:
        run(config)
    interrupt_at_call(monkeypatch, 5)
    with pytest.raises(Interrupted) as second:
        run(config, state=first.value.state)
    assert second.value.state["iteration"] == 3 + 4
    monkeypatch.undo()
    calls = count_calls(monkeypatch)
    assert_same_design(run(config, state=second.value.state), whole)
    assert calls["n"] == 12 - 7


# --- the eye distribution --------------------------------------------------------------------


def test_each_iteration_draws_its_own_eye_states_reproducibly(make_config: MakeConfig) -> None:
    """States come from (seed, iteration): fresh each iteration, the same on every run."""
    from aperture_fab.optimize.optimizer import training_states

    config = make_config("near-eye")
    scene, settings = config.scene, config.optimizer
    first, second = (training_states(scene, settings, i) for i in (0, 1))
    assert len(first) == settings.eye_states == 8
    assert not np.array_equal(first.offset_mm, second.offset_mm)
    np.testing.assert_array_equal(training_states(scene, settings, 0).offset_mm, first.offset_mm)
    point = make_config()  # near-eye-nominal: the scene's fixed positions
    assert len(training_states(point.scene, point.optimizer, 5)) == 1


def test_a_run_over_the_eye_distribution_resumes_exactly(make_config: MakeConfig) -> None:
    config = make_config("near-eye", **{"optimizer.iterations": 6, "optimizer.eye_states": 4,
                                        "optimizer.checkpoint_every": 3,
                                        "optimizer.precision": "float64"})
    whole = run(config)
    saved: list[dict[str, Any]] = []
    run(config, on_checkpoint=saved.append)
    assert_same_design(run(config, state=saved[0]), whole)


def test_tail_share_weights_the_worst_states(make_config: MakeConfig) -> None:
    """A tail loss (worst 25 % of the states) is at least the expected loss at the start."""
    settings = {"optimizer.iterations": 1, "optimizer.eye_states": 8}
    mean = run(make_config("near-eye", **settings)).loss_history[0]
    tail = run(make_config("near-eye", **settings, **{"optimizer.tail_share": 0.25}))
    assert tail.loss_history[0] >= mean


def test_a_tracked_design_lowers_the_tracked_loss(make_config: MakeConfig) -> None:
    """tracking = "tracked": each state sees its own solved display; the loss reported is the
    tracked one, below the untracked loss of the same start, and it goes down."""
    config = make_config("near-eye", **{"optimizer.iterations": 6, "optimizer.eye_states": 3,
                                        "optimizer.tracking": "tracked"})
    untracked = run(make_config("near-eye", **{"optimizer.iterations": 1,
                                               "optimizer.eye_states": 3}))
    tracked = run(config)
    assert tracked.loss_history[0] < untracked.loss_history[0]
    assert tracked.loss_history[-1] < tracked.loss_history[0]
    assert np.all((tracked.displays >= 0) & (tracked.displays <= 1))


@pytest.mark.parametrize("floor", [0.0, 0.9])  # 0.9: the floor binds
def test_the_tracked_loss_without_solves_is_the_untracked_loss_as_made(
        monkeypatch: pytest.MonkeyPatch, floor: float) -> None:
    """With no MLEM iteration each state's frame is the untracked content (scaled to a peak of
    1, which the gain-corrected loss and the veil ignore), so the tracked loss, its plate
    gradient and its display gradient are the untracked design loss's: the same made copy,
    diffraction and veil, and the same light floor on the plate."""
    monkeypatch.setattr(optimize_module, "TRACKED_SOLVE_ITERATIONS", 0)
    config = tiny_config("near-eye")
    scene = config.scene
    renderer = Renderer(scene, dtype=torch.float64)
    optics = made_optics(scene, resolve_process("photomask"))
    rng = np.random.default_rng(5)
    cells = (scene.plate.cells[1], scene.plate.cells[0])
    draw = draw_errors(cells, MadeOptics(radius_sigma_mm=0.002, position_sigma_mm=0.003), rng)
    states = optimize_module.training_states(scene, config.optimizer, 3)
    targets = torch.as_tensor(rng.uniform(0, 1, (1, 3, *scene.eye.view_pixels[::-1])))
    plate = torch.as_tensor(rng.uniform(0.05, 0.4, cells))
    shown = torch.as_tensor(rng.uniform(0.1, 0.6, (1, 3, *scene.display.pixels[::-1])))
    grads = []
    for tracked_loss in (True, False):
        a, display = plate.clone().requires_grad_(True), shown.clone().requires_grad_(True)
        if tracked_loss:
            loss = optimize_module._tracked_loss(renderer, a, display, targets, states, 0.5,
                                                 optics, draw, floor)
        else:
            loss = optimize_module._design_loss(renderer, a, display, targets, states, 0.0, 0.5,
                                                floor, optics, draw)
        loss.backward()
        grads.append((float(loss.detach()), a.grad, display.grad))
    (tracked, a_tracked, d_tracked), (untracked, a_untracked, d_untracked) = grads
    assert tracked == pytest.approx(untracked, rel=1e-9)
    torch.testing.assert_close(a_tracked, a_untracked, rtol=1e-7, atol=1e-12)
    torch.testing.assert_close(d_tracked, d_untracked, rtol=1e-7, atol=1e-12)


def test_tracking_needs_an_optimized_display(make_config: MakeConfig) -> None:
    with pytest.raises(ValueError, match=r"tracking.*optimized"):
        make_config(**{"optimizer.tracking": "tracked", "optimizer.display": "target"})
