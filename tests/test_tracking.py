"""Tracked displays: `aperture_fab.optimize.tracking` (the display solved per eye state, the plate
fixed) and the `aperture-fab display` command."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import tiny_config
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from aperture_fab.cli import EXIT_BAD_INPUT, main
from aperture_fab.io.images import resample
from aperture_fab.metrics import gain_mse_states, psnr_db
from aperture_fab.optics.baselines import elemental_display, regular_pinholes
from aperture_fab.optics.eyes import EyeStates
from aperture_fab.optics.model import Renderer
from aperture_fab.optimize.tracking import _brighten, solve_display, tracked_views
from aperture_fab.targets import natural
from tests.test_imports import CHILD, run_child

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def eye(x: float, y: float, pupil: float = 4.0, diopters: float = 0.0) -> EyeStates:
    return EyeStates(np.array([[x, y]]), np.array([pupil]), np.array([diopters]),
                     np.zeros((1, 2)), np.ones(1))


@pytest.fixture(scope="module")
def tiny() -> dict:
    """The tiny scene in float64, its regular pinhole plate, a natural target on the view grid
    and the plate's untracked (elemental, nominal eye) display."""
    scene = tiny_config().scene
    renderer = Renderer(scene, dtype=torch.float64)
    target = torch.as_tensor(resample(natural(64), scene.eye.view_pixels))
    plate = regular_pinholes(scene)
    start = elemental_display(scene, plate, target).clamp(0, 1)
    return {"renderer": renderer, "plate": torch.as_tensor(plate.open_fraction),
            "target": target, "start": start}


def psnr_of(tiny: dict, display: torch.Tensor, state: EyeStates) -> float:
    r = tiny["renderer"]
    with torch.no_grad():
        view = r.render_states(tiny["plate"], r.display_stack(display), state)
    return psnr_db(float(gain_mse_states(view, tiny["target"])[0]))


# --- the solver --------------------------------------------------------------------------------


def test_tracking_an_off_nominal_eye_beats_the_untracked_display(tiny: dict) -> None:
    state = eye(0.5, 0.0)
    solved = solve_display(tiny["renderer"], tiny["plate"], tiny["target"], state,
                           tiny["start"], iterations=3)
    before, after = psnr_of(tiny, tiny["start"], state), psnr_of(tiny, solved[0], state)
    assert after > before + 10  # measured: 21.8 -> 59 dB
    assert solved.shape == (1, *tiny["start"].shape)


def test_the_result_is_in_unit_range_and_deterministic(tiny: dict) -> None:
    args = (tiny["renderer"], tiny["plate"], tiny["target"], eye(-0.4, 0.3, 3.0),
            tiny["start"])
    first, second = solve_display(*args, iterations=2), solve_display(*args, iterations=2)
    assert torch.equal(first, second)
    assert float(first.min()) >= 0 and float(first.max()) == pytest.approx(1.0)


def test_solving_works_under_no_grad_and_detaches_its_inputs(tiny: dict) -> None:
    plate = tiny["plate"].clone().requires_grad_(True)
    start = tiny["start"].clone().requires_grad_(True)
    args = (tiny["renderer"], plate, tiny["target"], eye(0.5, 0.0), start)
    with torch.no_grad():
        quiet = solve_display(*args, iterations=2)
    loud = solve_display(*args, iterations=2)
    assert torch.equal(quiet, loud) and not loud.requires_grad
    assert plate.grad is None and start.grad is None


def test_a_display_already_optimal_is_not_made_worse(tiny: dict) -> None:
    nominal = eye(0.0, 0.0)
    args = (tiny["renderer"], tiny["plate"], tiny["target"], nominal)
    optimal = solve_display(*args, tiny["start"], iterations=20)[0]
    best = psnr_of(tiny, optimal, nominal)
    for method in ("mlem", "adam"):
        again = tracked_views(*args, optimal, iterations=3, method=method)
        assert again.start_psnr_db[0] == pytest.approx(best, abs=1e-9)
        assert psnr_of(tiny, again.displays[0], nominal) >= best - 1e-9
        assert again.psnr_db[0] >= again.start_psnr_db[0]


def test_tracked_views_report_the_views_they_solved(tiny: dict) -> None:
    states = EyeStates(np.array([[0.0, 0.0], [0.5, 0.0]]), np.array([4.0, 3.0]), np.zeros(2),
                       np.zeros((2, 2)), np.array([0.5, 0.5]))
    solved = tracked_views(tiny["renderer"], tiny["plate"], tiny["target"], states,
                           tiny["start"], iterations=2)
    assert solved.displays.shape == (2, *tiny["start"].shape)
    assert solved.views.shape == (2, *tiny["target"].shape)
    assert solved.history_db.shape == (2, 3)  # the start, 1 iterate, and the last one judged
    for s in range(2):
        one = states.subset(s)
        np.testing.assert_allclose(psnr_of(tiny, solved.displays[s], one), solved.psnr_db[s],
                                   atol=1e-9)
        np.testing.assert_allclose(psnr_of(tiny, tiny["start"], one), solved.start_psnr_db[s],
                                   atol=1e-9)
        # Each state of a batch is solved as it would be alone.
        alone = solve_display(tiny["renderer"], tiny["plate"], tiny["target"], one,
                              tiny["start"], iterations=2)
        torch.testing.assert_close(alone[0], solved.displays[s])
        r = tiny["renderer"]
        with torch.no_grad():
            view = r.render_states(tiny["plate"], r.display_stack(solved.displays[s]), one)[0]
        torch.testing.assert_close(view, solved.views[s])


def test_mlem_converges_faster_than_projected_adam(tiny: dict) -> None:
    args = (tiny["renderer"], tiny["plate"], tiny["target"], eye(0.5, 0.0), tiny["start"])
    mlem = tracked_views(*args, iterations=2).psnr_db[0]
    adam = tracked_views(*args, iterations=2, method="adam").psnr_db[0]
    assert mlem > adam + 5


def test_zero_iterations_keep_the_start(tiny: dict) -> None:
    start = 0.5 * tiny["start"]
    solved = solve_display(tiny["renderer"], tiny["plate"], tiny["target"], eye(0.3, 0.0),
                           start, iterations=0)
    torch.testing.assert_close(solved[0], tiny["start"] / tiny["start"].max())


def light_of(tiny: dict, display: torch.Tensor, state: EyeStates) -> float:
    r = tiny["renderer"]
    with torch.no_grad():
        return float(r.render_states(tiny["plate"], r.display_stack(display), state).mean())


@pytest.mark.parametrize("floor", [0.9, 1.0])
def test_the_light_floor_keeps_the_start_light_and_still_sharpens(tiny: dict, floor: float
                                                                  ) -> None:
    state = eye(0.5, 0.0)
    args = (tiny["renderer"], tiny["plate"], tiny["target"], state, tiny["start"])
    free = solve_display(*args, iterations=3)[0]
    held = solve_display(*args, iterations=3, light_floor=floor)[0]
    start_light = light_of(tiny, tiny["start"], state)
    # Unfloored MLEM darkens the view; the floor holds it (the renderer's view is linear in
    # the display, so the solve's light A^T 1 . d is the rendered mean, to rounding).
    assert light_of(tiny, free, state) < 0.85 * start_light
    assert light_of(tiny, held, state) >= floor * start_light * (1 - 1e-9)
    assert float(held.min()) >= 0 and float(held.max()) == pytest.approx(1.0)
    assert psnr_of(tiny, held, state) > psnr_of(tiny, tiny["start"], state) + 1


def test_a_floor_below_the_free_solves_light_changes_nothing(tiny: dict) -> None:
    args = (tiny["renderer"], tiny["plate"], tiny["target"], eye(0.5, 0.0), tiny["start"])
    torch.testing.assert_close(solve_display(*args, iterations=2, light_floor=1e-6),
                               solve_display(*args, iterations=2), rtol=0, atol=0)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), share=st.floats(0.0, 1.0))
def test_brighten_takes_the_smallest_scale_that_reaches_the_goal(seed: int, share: float
                                                                  ) -> None:
    rng = np.random.default_rng(seed)
    d = torch.as_tensor(rng.random((1, 6, 7)) ** 3)
    column = torch.as_tensor(rng.random((1, 6, 7)))
    seen = torch.ones_like(d, dtype=torch.bool)
    goal = share * float(column.sum())  # at most every pixel at 1
    out = _brighten(d, column, seen, goal)
    peak_one = d / d.max()

    def light(x: torch.Tensor) -> float:
        return float((column * x).sum())

    assert float(out.min()) >= 0 and float(out.max()) <= 1
    if light(peak_one) >= goal:
        torch.testing.assert_close(out, peak_one)
    else:  # exactly the goal (bisection), by scaling and saturating the peak-1 content
        assert light(out) == pytest.approx(goal, rel=1e-6)
        lit = out < 1
        if bool(lit.any()):
            k = float(out[lit].max() / peak_one[lit].max())
            torch.testing.assert_close(out, (peak_one * k).clamp(max=1))
        else:  # every pixel saturated
            torch.testing.assert_close(out, torch.ones_like(out))


@pytest.mark.parametrize(("change", "message"), [
    ({"light_floor": 1.5}, "light_floor = 1.5 is out of range"),
    ({"light_floor": 0.5, "method": "adam"}, "light_floor = 0.5 needs method = 'mlem'"),
    ({"iterations": -1}, "iterations = -1 is out of range"),
    ({"iterations": 2.5}, "iterations = 2.5"),
    ({"method": "newton"}, "method = 'newton' is not allowed"),
    ({"start": torch.zeros(1, 8, 8)}, r"start has shape \(1, 8, 8\)"),
    ({"target": torch.zeros(3, 16, 16)}, "not all black"),
    ({"target": torch.ones(3, 4, 4)}, r"target has shape \(3, 4, 4\)"),
    ({"state": "eye"}, "EyeStates"),
])
def test_bad_arguments_are_named(tiny: dict, change: dict, message: str) -> None:
    kwargs = {"renderer": tiny["renderer"], "open_fraction": tiny["plate"],
              "target": tiny["target"], "state": eye(0.0, 0.0), "start": tiny["start"],
              "iterations": 1, **change}
    with pytest.raises((ValueError, TypeError), match=message):
        solve_display(**kwargs)


def test_an_eye_that_sees_nothing_is_refused(tiny: dict) -> None:
    with pytest.raises(ValueError, match=r"eye at \(60, 0\) mm .* sees no light"):
        solve_display(tiny["renderer"], tiny["plate"], tiny["target"], eye(60.0, 0.0),
                      tiny["start"], iterations=1)


# --- aperture-fab display ---------------------------------------------------------------------


def test_display_writes_the_frame_and_prints_both_psnrs(
        designed: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "frames" / "frame.png"
    code = main(["display", str(designed / "holes.csv"), str(designed / "marker.png"),
                 "--eye", "0.5,-0.25", "--pupil", "3", "--iterations", "3", "--out", str(out)])
    text = capsys.readouterr().out
    assert code == 0, text
    with Image.open(out) as im:
        assert im.size == (32, 32)  # the display's pixels (TINY)
    match = re.search(r"PSNR after gain: ([\d.]+) dB untracked -> ([\d.]+) dB tracked "
                      r"\(3 iterations, solved in [\d.]+ s\); light at the eye ([\d.]+) of "
                      r"the untracked display's \(floor 1\)", text)
    assert match is not None, text
    assert float(match[2]) >= float(match[1])
    assert float(match[3]) >= 1 - 0.005  # the default floor keeps the untracked light
    assert "eye at (0.5, -0.25) mm, pupil 3 mm, focus infinity" in text


@pytest.mark.parametrize("part", ["design.npz", "plate.stl"])
def test_display_takes_every_kind_of_part(designed: Path, tmp_path: Path, part: str) -> None:
    out = tmp_path / "frame.png"
    assert main(["display", str(designed / part), str(designed / "marker.png"), "--eye", "0,0",
                 "--pupil", "4", "--focus", "500", "--iterations", "1", "--out", str(out)]) == 0
    assert out.is_file()


@pytest.mark.parametrize(("argv", "named"), [
    (["{d}/gone.csv", "{d}/marker.png", "--eye", "0,0", "--pupil", "4"], "gone.csv"),
    (["{d}/holes.csv", "{d}/missing.png", "--eye", "0,0", "--pupil", "4"], "missing.png"),
    (["{d}/holes.csv", "{d}/marker.png", "--eye", "1", "--pupil", "4"], "--eye '1'"),
    (["{d}/holes.csv", "{d}/marker.png", "--eye", "a,b", "--pupil", "4"], "X,Y"),
    (["{d}/holes.csv", "{d}/marker.png", "--eye", "60,0", "--pupil", "4"], "sees no light"),
    (["{d}/holes.csv", "{d}/marker.png", "--eye", "0,0", "--pupil", "0"],
     "--pupil 0 is out of range; allowed: 0 < pupil"),
    (["{d}/holes.csv", "{d}/marker.png", "--eye", "0,0", "--pupil", "-3"], "--pupil -3"),
    (["{d}/holes.csv", "{d}/marker.png", "--eye", "0,0", "--pupil", "4", "--focus", "5"],
     "--focus 5 is out of range"),
    (["{d}/holes.csv", "{d}/marker.png", "--eye", "0,0", "--pupil", "4", "--focus", "near"],
     "--focus 'near'"),
    (["{d}/holes.csv", "{d}/marker.png", "--eye", "0,0", "--pupil", "4", "--iterations", "-1"],
     "--iterations -1 is out of range"),
    (["{d}/holes.csv", "{d}/marker.png", "--eye", "0,0", "--pupil", "4",
      "--target-index", "2"], "--target-index 2"),
    (["{d}/holes.csv", "{d}/marker.png", "--eye", "0,0", "--pupil", "4",
      "--light-floor", "2"], "--light-floor 2.0 is out of range"),
    (["{d}/holes.csv", "{d}/marker.png", "--eye", "0,0", "--pupil", "4", "--config",
      "{d}/none.toml"], "none.toml"),
])
def test_display_bad_inputs_exit_three_with_a_clear_message(
        designed: Path, tmp_path: Path, argv: list[str], named: str,
        capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "frame.png"
    code = main(["display", *(a.format(d=designed) for a in argv), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == EXIT_BAD_INPUT
    assert named in err, err
    assert not out.exists()


def test_display_help_is_light() -> None:
    result = run_child(CHILD, "display", "--help")
    assert result["loaded"] == [] and result["code"] == 0 and result["printed"] > 0
