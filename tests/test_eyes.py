"""The eye distribution: its batches of states, their sampling and the weighted percentiles."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from aperture_fab.config.config import resolve
from aperture_fab.optics.eyes import (
    EyeDistribution,
    EyeStates,
    distribution_of,
    iteration_seed,
    percentiles,
)
from aperture_fab.optics.scene import Eye

NEAR_EYE = EyeDistribution(eyebox_mm=(4.0, 4.0), pupil_range_mm=(3.0, 6.0), nominal_pupil_mm=4.0,
                           focus_range_diopters=(0.0, 0.5))


def states_of(count: int) -> EyeStates:
    return EyeStates(np.zeros((count, 2)), np.full(count, 4.0), np.zeros(count),
                     np.zeros((count, 2)), np.full(count, 1 / count))


def box_offsets(dist: EyeDistribution, states: EyeStates) -> np.ndarray:
    """The eyebox part of each offset: the offset less the centre and the gaze shift."""
    gaze = dist.rotation_mm * np.sin(np.radians(states.gaze_deg))
    return states.offset_mm - np.asarray(dist.centre_mm) - gaze


def inside_eyebox(dist: EyeDistribution, box: np.ndarray) -> np.ndarray:
    half = np.asarray(dist.eyebox_mm) / 2 + 1e-9  # 1 pm of rounding slack
    if dist.eyebox_shape == "rect":
        return np.all(np.abs(box) <= half, axis=-1)
    return np.sum((box / half) ** 2, axis=-1) <= 1


ordered_pair = st.tuples(st.floats(0.0, 1.0), st.floats(0.0, 1.0)).map(sorted)


@st.composite
def distributions(draw: st.DrawFn) -> EyeDistribution:
    p = draw(ordered_pair)
    pupil_lo, pupil_hi = 1.0 + 7.0 * p[0], 1.0 + 7.0 * p[1]
    f = draw(ordered_pair)
    focus_lo, focus_hi = 10.0 * f[0], 10.0 * f[1]
    return EyeDistribution(
        centre_mm=(draw(st.floats(-5, 5)), draw(st.floats(-5, 5))),
        eyebox_mm=(draw(st.floats(0, 50)), draw(st.floats(0, 50))),
        eyebox_shape=draw(st.sampled_from(["ellipse", "rect"])),
        pupil_range_mm=(pupil_lo, pupil_hi),
        nominal_pupil_mm=pupil_lo + (pupil_hi - pupil_lo) * draw(st.floats(0, 1)),
        focus_range_diopters=(focus_lo, focus_hi),
        nominal_focus_diopters=focus_lo + (focus_hi - focus_lo) * draw(st.floats(0, 1)),
        gaze_deg=draw(st.floats(0, 45)),
        rotation_mm=draw(st.floats(0, 30)),
    )


# --- EyeStates --------------------------------------------------------------------------------


def test_states_are_read_only_float64_and_renormalised() -> None:
    states = EyeStates([[0, 0], [1, 2]], [3, 4], [0, 0.5], [[0, 0], [0, 0]], [0.25, 0.75 + 1e-9])
    assert len(states) == 2
    for array in (states.offset_mm, states.pupil_mm, states.focus_diopters, states.gaze_deg,
                  states.weight):
        assert array.dtype == np.float64 and not array.flags.writeable
    assert states.weight.sum() == pytest.approx(1.0, abs=1e-15)
    assert states.focus_mm(0) is None and states.focus_mm(1) == 2000.0


@pytest.mark.parametrize("change, fragments", [
    ({"offset_mm": np.zeros((3, 3))}, ["offset_mm", "(3, 3)", "(S, 2)"]),
    ({"offset_mm": np.zeros((0, 2))}, ["offset_mm", "S >= 1"]),
    ({"pupil_mm": np.ones(2)}, ["pupil_mm", "(2,)", "(3,)"]),
    ({"pupil_mm": np.array([4.0, 0.0, 4.0])}, ["pupil_mm", "> 0"]),
    ({"focus_diopters": np.array([0.0, -1.0, 0.0])}, ["focus_diopters", ">= 0"]),
    ({"gaze_deg": np.zeros(3)}, ["gaze_deg", "(3, 2)"]),
    ({"weight": np.array([0.5, 0.5, 0.5])}, ["weight", "sums to", "1"]),
    ({"weight": np.array([1.5, -0.5, 0.0])}, ["weight", ">= 0"]),
    ({"offset_mm": np.array([[0, 0], [np.nan, 0], [0, 0]])}, ["offset_mm", "finite"]),
])
def test_bad_states_give_clear_errors(change: dict[str, Any], fragments: list[str]) -> None:
    base = states_of(3)
    fields = {k: getattr(base, k) for k in ("offset_mm", "pupil_mm", "focus_diopters",
                                            "gaze_deg", "weight")}
    with pytest.raises(ValueError) as info:
        EyeStates(**{**fields, **change})
    for fragment in fragments:
        assert fragment in str(info.value), (fragment, str(info.value))


def test_subset_and_concat() -> None:
    states = NEAR_EYE.sample(10, 1)
    part = states.subset([2, 5])
    assert len(part) == 2 and np.allclose(part.weight, 0.5)
    np.testing.assert_array_equal(part.offset_mm, states.offset_mm[[2, 5]])
    assert len(states.subset(3)) == 1
    assert len(states.subset(states.pupil_mm > 4.5)) == int(np.sum(states.pupil_mm > 4.5))
    both = EyeStates.concat([states, NEAR_EYE.nominal()])
    assert len(both) == 11 and np.allclose(both.weight, 1 / 11)
    np.testing.assert_array_equal(both.pupil_mm[:10], states.pupil_mm)
    with pytest.raises(ValueError, match="subset"):
        states.subset([])


# --- the distribution -------------------------------------------------------------------------


def test_sampling_is_deterministic_per_seed_and_iteration() -> None:
    a, b = NEAR_EYE.sample(32, 7), NEAR_EYE.sample(32, 7)
    for name in ("offset_mm", "pupil_mm", "focus_diopters", "gaze_deg", "weight"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.array_equal(a.offset_mm, NEAR_EYE.sample(32, 8).offset_mm)
    seeds = [iteration_seed(0, i) for i in range(50)]
    assert len(set(seeds)) == 50 and seeds == [iteration_seed(0, i) for i in range(50)]
    assert iteration_seed(0, 3) != iteration_seed(1, 3)
    first, second = (NEAR_EYE.sample(16, iteration_seed(0, i)) for i in (0, 1))
    assert not np.array_equal(first.pupil_mm, second.pupil_mm)
    assert np.allclose(first.weight, 1 / 16)
    with pytest.raises(ValueError, match="iteration"):
        iteration_seed(0, -1)


def test_stratified_sets_are_random_draws_that_spread_evenly() -> None:
    """The optimizer's per-iteration set: deterministic per seed, a fresh set per seed, and
    unbiased (pooled over seeds its pupil sizes and positions have the distribution's means),
    while the mean over a set of 8 is much less noisy than over 8 independent draws."""
    a, b = NEAR_EYE.stratified(8, 5), NEAR_EYE.stratified(8, 5)
    np.testing.assert_array_equal(a.offset_mm, b.offset_mm)
    assert not np.array_equal(a.offset_mm, NEAR_EYE.stratified(8, 6).offset_mm)
    assert np.allclose(a.weight, 1 / 8)
    seeds = [iteration_seed(0, i) for i in range(400)]
    pooled = EyeStates.concat([NEAR_EYE.stratified(8, s) for s in seeds])
    independent = EyeStates.concat([NEAR_EYE.sample(100_000, 1)])
    assert abs(pooled.pupil_mm.mean() - independent.pupil_mm.mean()) < 0.02
    assert np.all(np.abs(pooled.offset_mm.mean(0)) < 0.03)

    def noise(draw: Any) -> np.ndarray:  # std over seeds of a set's mean x, y and pupil
        means = [np.append(states.offset_mm.mean(0), states.pupil_mm.mean())
                 for states in (draw(8, s) for s in seeds)]
        return np.std(means, axis=0)

    # Measured: 0.46, 0.45 and 0.66 of the independent draws' noise.
    assert np.all(noise(NEAR_EYE.stratified) < [0.6, 0.6, 0.8] * noise(NEAR_EYE.sample))


@settings(max_examples=60, deadline=None)
@given(dist=distributions(), seed=st.integers(0, 2**32 - 1))
def test_samples_lie_inside_the_eyebox_and_the_ranges(dist: EyeDistribution, seed: int) -> None:
    for states in (dist.sample(64, seed), dist.evaluation_states(64, seed % 5),
                   dist.stratified(16, seed)):
        assert inside_eyebox(dist, box_offsets(dist, states)).all()
        assert np.all(np.hypot(*states.gaze_deg.T) <= dist.gaze_deg * (1 + 1e-12))
        lo, hi = dist.pupil_range_mm
        assert np.all((states.pupil_mm >= lo) & (states.pupil_mm <= hi))
        f_lo, f_hi = dist.focus_range_diopters
        assert np.all((states.focus_diopters >= f_lo) & (states.focus_diopters <= f_hi))
        assert states.weight.sum() == pytest.approx(1.0)


def test_gaze_moves_the_pupil_by_rotation_times_sine() -> None:
    dist = EyeDistribution(gaze_deg=30.0, rotation_mm=11.0, centre_mm=(0.5, -1.0))
    states = dist.sample(200, 3)
    expected = np.asarray(dist.centre_mm) + 11.0 * np.sin(np.radians(states.gaze_deg))
    np.testing.assert_array_equal(states.offset_mm, expected)
    assert np.abs(states.gaze_deg).max() > 20  # the disk is used, not only its centre


def test_ellipse_moments_converge_to_the_uniform_disk() -> None:
    dist = EyeDistribution(eyebox_mm=(4.0, 2.0))  # semi-axes 2 and 1
    box = dist.sample(200_000, 11).offset_mm
    # Uniform over an ellipse of semi-axes a, b: E[x] = E[y] = 0, E[x^2] = a^2/4, E[y^2] = b^2/4,
    # and E[(x/a)^2 + (y/b)^2] = 1/2 (the disk's E[r^2] = R^2 / 2).
    tolerance = 4 / math.sqrt(200_000)  # about 4 standard errors, in units of the semi-axis
    assert np.abs(box.mean(axis=0)).max() < tolerance * 2
    assert np.mean(box[:, 0] ** 2) == pytest.approx(1.0, abs=tolerance * 4)
    assert np.mean(box[:, 1] ** 2) == pytest.approx(0.25, abs=tolerance)
    assert np.mean((box[:, 0] / 2) ** 2 + box[:, 1] ** 2) == pytest.approx(0.5, abs=tolerance)


def test_rect_and_ranges_moments_converge_to_uniform() -> None:
    dist = EyeDistribution(eyebox_mm=(3.0, 1.0), eyebox_shape="rect", pupil_range_mm=(2.0, 8.0),
                           nominal_pupil_mm=4.0, focus_range_diopters=(0.0, 2.0))
    states = dist.sample(200_000, 5)
    tol = 4 / math.sqrt(200_000)
    # Uniform on [-w/2, w/2]: variance w^2 / 12.
    assert np.var(states.offset_mm[:, 0]) == pytest.approx(9 / 12, abs=9 / 12 * tol * 2)
    assert np.var(states.offset_mm[:, 1]) == pytest.approx(1 / 12, abs=1 / 12 * tol * 2)
    assert states.pupil_mm.mean() == pytest.approx(5.0, abs=6 * tol)
    assert np.var(states.pupil_mm) == pytest.approx(36 / 12, abs=3 * tol * 2)
    assert states.focus_diopters.mean() == pytest.approx(1.0, abs=2 * tol)
    # Gaze: uniform over a disk of angles, E[r^2] = R^2 / 2.
    gaze = EyeDistribution(gaze_deg=20.0).sample(200_000, 9).gaze_deg
    assert np.mean(np.sum(gaze**2, axis=-1)) == pytest.approx(200.0, abs=400 * tol)


@pytest.mark.parametrize("shape", ["ellipse", "rect"])
def test_evaluation_states_cover_the_eyebox_evenly(shape: str) -> None:
    dist = EyeDistribution(eyebox_mm=(4.0, 6.0), eyebox_shape=shape,  # type: ignore[arg-type]
                           pupil_range_mm=(3.0, 6.0), nominal_pupil_mm=4.0)
    for seed in (0, 1):
        states = dist.evaluation_states(64, seed)
        assert len(states) == 64 and np.allclose(states.weight, 1 / 64)
        x, y = states.offset_mm.T
        counts = np.array([np.sum(((x >= 0) == right) & ((y >= 0) == top))
                           for right in (True, False) for top in (True, False)])
        assert np.all(np.abs(counts - 16) <= 3), counts  # random draws: about +-4 (1 sigma)
        halves = np.histogram(states.pupil_mm, bins=4, range=(3.0, 6.0))[0]
        assert np.all(np.abs(halves - 16) <= 2), halves
    again = dist.evaluation_states(64)
    np.testing.assert_array_equal(again.offset_mm, dist.evaluation_states(64).offset_mm)
    # Low discrepancy: the mean of x^2 converges much faster than random sampling would.
    many = dist.evaluation_states(1024).offset_mm
    exact = 1.0 if shape == "ellipse" else 16 / 12  # E[x^2]: a^2 / 4 (a = 2) or w^2 / 12
    assert np.mean(many[:, 0] ** 2) == pytest.approx(exact, rel=0.01)  # random: ~4 %


def test_nominal_grid_and_sweeps() -> None:
    dist = EyeDistribution(centre_mm=(1.0, 0.0), eyebox_mm=(4.0, 2.0), pupil_range_mm=(3.0, 6.0),
                           nominal_pupil_mm=4.0, focus_range_diopters=(0.0, 0.5),
                           nominal_focus_diopters=0.25)
    nominal = dist.nominal()
    assert len(nominal) == 1 and nominal.offset_mm.tolist() == [[1.0, 0.0]]
    assert (nominal.pupil_mm[0], nominal.focus_diopters[0]) == (4.0, 0.25)
    assert nominal.focus_mm(0) == 4000.0

    states, inside = dist.eyebox_grid(5)
    grid = states.offset_mm.reshape(5, 5, 2)
    assert grid[0, 0].tolist() == pytest.approx([1.0 - 1.6, 0.8])  # row 0 at +y, column 0 at -x
    assert grid[4, 4].tolist() == pytest.approx([1.0 + 1.6, -0.8])
    assert inside.shape == (5, 5) and inside[2, 2] and not inside[0, 0]
    assert inside.tolist() == np.flipud(inside).tolist() == np.fliplr(inside).tolist()
    assert np.allclose(states.weight.reshape(5, 5)[inside], 1 / inside.sum())
    assert np.all(states.weight.reshape(5, 5)[~inside] == 0)
    assert np.all(states.pupil_mm == 4.0) and np.all(states.focus_diopters == 0.25)
    rect_states, rect_inside = EyeDistribution(eyebox_mm=(2.0, 2.0),
                                               eyebox_shape="rect").eyebox_grid(3)
    assert rect_inside.all() and len(rect_states) == 9
    point_states, point_inside = EyeDistribution().eyebox_grid(3)
    assert point_inside.all() and np.all(point_states.offset_mm == 0)


def test_is_point() -> None:
    assert EyeDistribution().is_point
    assert EyeDistribution(centre_mm=(1.0, 2.0), nominal_pupil_mm=5.0,
                           pupil_range_mm=(5.0, 5.0)).is_point
    assert not NEAR_EYE.is_point
    assert not EyeDistribution(gaze_deg=5.0).is_point
    assert not EyeDistribution(eyebox_mm=(0.0, 1.0)).is_point


@pytest.mark.parametrize("kwargs, fragments", [
    ({"eyebox_mm": (-1.0, 1.0)}, ["eyebox_mm", "0 to 50"]),
    ({"eyebox_mm": (60.0, 1.0)}, ["eyebox_mm", "0 to 50"]),
    ({"eyebox_shape": "square"}, ["eyebox_shape", "ellipse, rect"]),
    ({"pupil_range_mm": (6.0, 3.0)}, ["pupil_range_mm", "lo <= hi"]),
    ({"pupil_range_mm": (0.0, 6.0)}, ["pupil_range_mm", "0 < lo"]),
    ({"pupil_range_mm": (3.0, 25.0)}, ["pupil_range_mm", "20"]),
    ({"pupil_range_mm": (5.0, 6.0)}, ["nominal_pupil_mm", "outside", "pupil_range_mm"]),
    ({"nominal_pupil_mm": 0.0}, ["nominal_pupil_mm", "0 < nominal_pupil_mm"]),
    ({"focus_range_diopters": (0.0, 12.0)}, ["focus_range_diopters", "10"]),
    ({"focus_range_diopters": (-1.0, 0.0)}, ["focus_range_diopters", "0 <= lo"]),
    ({"focus_range_diopters": (1.0, 2.0)}, ["nominal_focus_diopters", "outside"]),
    ({"gaze_deg": 50.0}, ["gaze_deg", "0 to 45"]),
    ({"gaze_deg": -1.0}, ["gaze_deg", "0 to 45"]),
    ({"rotation_mm": 40.0}, ["rotation_mm", "0 to 30"]),
    ({"centre_mm": (math.nan, 0.0)}, ["centre_mm", "finite"]),
])
def test_bad_distributions_give_clear_errors(kwargs: dict[str, Any],
                                              fragments: list[str]) -> None:
    with pytest.raises(ValueError) as info:
        EyeDistribution(**kwargs)
    for fragment in fragments:
        assert fragment in str(info.value), (fragment, str(info.value))


def test_a_fixed_near_focus_is_allowed_beyond_accommodation() -> None:
    fixed = EyeDistribution(focus_range_diopters=(50.0, 50.0), nominal_focus_diopters=50.0)
    assert fixed.is_point and fixed.nominal().focus_mm(0) == 20.0


def test_bad_counts_and_seeds() -> None:
    for call in (lambda: NEAR_EYE.sample(0, 1), lambda: NEAR_EYE.sample(4, -1),
                 lambda: NEAR_EYE.evaluation_states(4, -2),
                 lambda: NEAR_EYE.evaluation_states(0), lambda: NEAR_EYE.eyebox_grid(0)):
        with pytest.raises(ValueError):
            call()


# --- from the scene's Eye ---------------------------------------------------------------------


def test_distribution_of_an_eye() -> None:
    plain = Eye(4.0, 10.0, (40.0, 40.0), (8, 8), 500.0, ((1.0, -0.5),), (1.0,))
    point = distribution_of(plain)
    assert point.is_point and point.centre_mm == (1.0, -0.5)
    assert point.nominal_focus_diopters == 2.0 and point.pupil_range_mm == (4.0, 4.0)
    moving = Eye(4.0, 10.0, (40.0, 40.0), (8, 8), None, eyebox_mm=(4.0, 3.0), eyebox_shape="rect",
                 pupil_range_mm=(3.0, 6.0), focus_range_diopters=(0.0, 0.5), gaze_deg=10.0,
                 rotation_mm=12.0)
    dist = distribution_of(moving)
    assert (dist.eyebox_mm, dist.eyebox_shape, dist.pupil_range_mm, dist.focus_range_diopters,
            dist.gaze_deg, dist.rotation_mm) == ((4.0, 3.0), "rect", (3.0, 6.0), (0.0, 0.5),
                                                 10.0, 12.0)
    assert not dist.is_point and dist.nominal_focus_diopters == 0.0
    # A nominal focus on a range end survives 1000 / mm rounding.
    third = Eye(4.0, 10.0, (40.0, 40.0), (8, 8), 3000.0, focus_range_diopters=(1 / 3, 1.0))
    assert distribution_of(third).nominal_focus_diopters == 1 / 3


@pytest.mark.parametrize("kwargs, fragments", [
    ({"pupil_range_mm": (5.0, 6.0)}, ["eye.pupil_mm", "outside", "eye.pupil_range_mm"]),
    ({"focus_mm": 500.0, "focus_range_diopters": (0.0, 0.5)},
     ["eye.focus_mm", "2 diopters", "eye.focus_range_diopters"]),
    ({"eyebox_mm": (4.0, 60.0)}, ["eye.eyebox_mm", "0 to 50"]),
    ({"gaze_deg": 90.0}, ["eye.gaze_deg"]),
    ({"eyebox_shape": "circle"}, ["eye.eyebox_shape", "ellipse, rect"]),
])
def test_eye_validates_its_distribution(kwargs: dict[str, Any], fragments: list[str]) -> None:
    with pytest.raises(ValueError) as info:
        Eye(**{"pupil_mm": 4.0, "eye_relief_mm": 10.0, "fov_deg": (40.0, 40.0),
               "view_pixels": (8, 8), **kwargs})
    for fragment in fragments:
        assert fragment in str(info.value), (fragment, str(info.value))


def test_presets_distributions() -> None:
    near = distribution_of(resolve("near-eye").scene.eye)
    assert not near.is_point
    assert (near.eyebox_mm, near.eyebox_shape, near.pupil_range_mm, near.nominal_pupil_mm,
            near.focus_range_diopters, near.gaze_deg, near.rotation_mm) == (
        (4.0, 4.0), "ellipse", (3.0, 6.0), 4.0, (0.0, 0.0), 0.0, 11.0)
    for name in ("near-eye-nominal", "seed"):
        assert distribution_of(resolve(name).scene.eye).is_point, name


# --- percentiles ------------------------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(values=st.lists(st.floats(-1e3, 1e3), min_size=1, max_size=40))
def test_equal_weight_percentiles_match_numpy(values: list[float]) -> None:
    qs = (0, 5, 10, 50, 90, 100)
    mine = percentiles(values, None, qs)
    np.testing.assert_allclose(mine, np.percentile(values, qs, method="hazen"), atol=1e-9)
    np.testing.assert_allclose(percentiles(values, np.full(len(values), 3.0), qs), mine)
    # Within one gap between neighbouring sorted values of numpy's default ("linear").
    ordered = np.sort(values)
    gap = np.max(np.diff(ordered)) if len(values) > 1 else 0.0
    assert np.all(np.abs(mine - np.percentile(values, qs)) <= gap + 1e-9)


def test_weighted_percentiles() -> None:
    # Each value sits at the middle of its share of the weight: 0 at 5 %, 1 at 55 %.
    np.testing.assert_allclose(percentiles([0.0, 1.0], [0.1, 0.9], (0, 5, 30, 55, 90)),
                               [0.0, 0.0, 0.5, 1.0, 1.0])
    assert percentiles([0.0, 1.0], [0.5, 0.5], (50,))[0] == pytest.approx(0.5)
    repeated = np.repeat([1.0, 2.0, 5.0], [1, 3, 2])
    # Zero weights are ignored, and order does not matter.
    assert percentiles([5.0, 9.0, 1.0], [1.0, 0.0, 1.0], (50,))[0] == pytest.approx(3.0)
    many = percentiles(repeated, None, (10, 50, 90))
    assert many[1] == pytest.approx(2.0)
    with pytest.raises(ValueError):
        percentiles([1.0, 2.0], [0.0, 0.0])
    with pytest.raises(ValueError):
        percentiles([1.0, 2.0], [1.0])
    with pytest.raises(ValueError):
        percentiles([1.0], None, (101,))
