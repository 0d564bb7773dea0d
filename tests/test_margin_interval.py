"""The made-part margin's bootstrap interval (`validation.margin_interval`)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import norm

from aperture_fab.validation.margin_interval import margin_interval_db
from aperture_fab.validation.regular import RegularFront


def p10(samples: np.ndarray) -> np.ndarray:
    return np.percentile(samples.reshape(samples.shape[0], -1), 10, axis=1, method="hazen")


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(-5.0, 5.0), st.integers(1, 3), st.integers(2, 40))
def test_a_shifted_copy_of_the_part_has_the_shift_as_its_whole_interval(seed, shift, targets,
                                                                        states):
    """One copy each, judged at the same states: every resample draws the same states for
    both, so each resampled margin is the shift itself."""
    part = np.random.default_rng(seed).normal(20.0, 2.0, (targets, 1, states))
    interval = margin_interval_db(part, part - shift, seed=seed)
    np.testing.assert_allclose(interval, np.full((targets, 2), shift), atol=1e-9)


def test_the_interval_covers_the_true_margin_of_normal_samples():
    """Part N(0, 1), rival N(-1, 2^2) dB, 128 states each: the true p10 margin,
    Phi^-1(0.1) (1 - 2) + 1, lies in the 95 % interval of about 95 of 100 draws."""
    truth = norm.ppf(0.1) * (1.0 - 2.0) + 1.0
    hits = 0
    for trial in range(100):
        rng = np.random.default_rng(trial)
        part, rival = rng.normal(0.0, 1.0, (1, 1, 128)), rng.normal(-1.0, 2.0, (1, 1, 128))
        low, high = margin_interval_db(part, rival, resamples=1000, seed=trial)[0]
        assert low <= (p10(part) - p10(rival))[0] <= high  # around the estimate
        hits += low <= truth <= high
    assert 88 <= hits <= 100


def test_more_copies_and_states_narrow_the_interval():
    rng = np.random.default_rng(3)
    widths = []
    for copies, states in ((2, 16), (4, 32), (8, 128)):
        part = rng.normal(20.0, 1.5, (1, copies, states))
        rival = rng.normal(19.0, 1.5, (1, copies, states))
        low, high = margin_interval_db(part, rival)[0]
        widths.append(high - low)
    assert widths[0] > widths[1] > widths[2] > 0


def test_the_interval_is_deterministic_in_its_seed():
    rng = np.random.default_rng(4)
    part, rival = rng.normal(20, 1, (2, 4, 32)), rng.normal(19, 1, (2, 4, 32))
    first = margin_interval_db(part, rival, seed=7)
    assert np.array_equal(first, margin_interval_db(part, rival, seed=7))
    assert not np.array_equal(first, margin_interval_db(part, rival, seed=8))
    assert first.shape == (2, 2) and (first[:, 0] <= first[:, 1]).all()


@pytest.mark.parametrize(("part", "rival", "kwargs", "message"), [
    ((1, 4, 32), (1, 4, 16), {}, "the same targets and states"),
    ((2, 4, 32), (1, 4, 32), {}, "the same targets and states"),
    ((4, 32), (4, 32), {}, "(targets, copies, states)"),
    ((1, 4, 32), (1, 4, 32), {"coverage": 1.0}, "coverage = 1.0"),
    ((1, 4, 32), (1, 4, 32), {"resamples": 0}, "resamples = 0"),
])
def test_bad_arguments_are_named(part, rival, kwargs, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        margin_interval_db(np.zeros(part), np.zeros(rival), **kwargs)


def test_nan_psnr_is_refused():
    part = np.zeros((1, 2, 4))
    part[0, 1, 2] = np.nan
    with pytest.raises(ValueError, match="NaN or infinite"):
        margin_interval_db(part, np.zeros((1, 2, 4)))


def test_a_front_keeps_its_samples_through_subset_and_join():
    def front(count: int, start: float) -> RegularFront:
        values = np.arange(count, dtype=np.float64)[:, None] + start
        samples = tuple(np.full((1, 2, 3), v) for v in values[:, 0])
        return RegularFront(values[:, 0], values[:, 0], values[:, 0], values[:, 0], values,
                            values, values, samples)

    joined = RegularFront.joined([front(2, 0.0), front(3, 10.0)])
    assert [float(s[0, 0, 0]) for s in joined.psnr_db] == [0.0, 1.0, 10.0, 11.0, 12.0]
    picked = joined.subset([4, 1])
    assert [float(s[0, 0, 0]) for s in picked.psnr_db] == [12.0, 1.0]
    bare = RegularFront(*(np.zeros((1, 1)) if i >= 4 else np.zeros(1) for i in range(7)))
    assert RegularFront.joined([joined, bare]).psnr_db == ()
    assert bare.subset([0]).psnr_db == ()
