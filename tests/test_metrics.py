"""Metrics against hand-computed values and an SSIM written out from its definition."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from aperture_fab.metrics import METRIC_KEYS, gain, metrics, summarize

#: SSIM constants from Wang et al. (2004) with data range 1.
K1, K2 = 0.01, 0.03


def ssim_one_window(x: np.ndarray, y: np.ndarray) -> float:
    """SSIM of two 7 x 7 images taken as a single window (sample covariance), as written in the
    paper: skimage's 7 x 7 uniform window on a 7 x 7 image sees exactly this one window."""
    c1, c2 = K1**2, K2**2
    mx, my = x.mean(), y.mean()
    n = x.size
    vx = x.var() * n / (n - 1)
    vy = y.var() * n / (n - 1)
    cov = ((x - mx) * (y - my)).sum() / (n - 1)
    return float(((2 * mx * my + c1) * (2 * cov + c2))
                 / ((mx**2 + my**2 + c1) * (vx + vy + c2)))


def test_gain_hand_values() -> None:
    assert gain(np.array([1.0, 2.0]), np.array([2.0, 4.0])) == pytest.approx(2.0)
    # <v,t>/<v,v> = (1*1 + 1*0) / 2
    assert gain(np.array([1.0, 1.0]), np.array([1.0, 0.0])) == pytest.approx(0.5)
    assert gain(np.zeros(3), np.ones(3)) == 0.0


def test_mse_psnr_efficiency_hand_values() -> None:
    view = np.array([[[1.0, 1.0]]])  # (1, 1, 2)
    target = np.array([[[1.0, 0.0]]])
    m = metrics(view, target, open_level=4.0)
    # gain 0.5 -> scaled (0.5, 0.5); errors (-0.5, 0.5): mse 0.25
    assert m["mse"] == pytest.approx(0.25)
    assert m["psnr_db"] == pytest.approx(10 * math.log10(4))
    assert m["light_efficiency"] == pytest.approx(1.0 / 4.0)
    assert math.isnan(m["ssim"])  # a 1 x 2 view has no 3 x 3 window
    assert tuple(m) == METRIC_KEYS


def test_identical_images_score_perfectly() -> None:
    rng = np.random.default_rng(1)
    for channels in (1, 3):
        target = rng.uniform(0, 1, (channels, 16, 16))
        m = metrics(target, target, open_level=float(target.mean()))
        assert m["ssim"] == pytest.approx(1.0)
        assert m["mse"] == pytest.approx(0.0, abs=1e-24)
        assert m["light_efficiency"] == pytest.approx(1.0)


@settings(max_examples=25, deadline=None)
@given(scale=st.floats(1e-3, 1e3), seed=st.integers(0, 2**16))
def test_gain_invariance(scale: float, seed: int) -> None:
    """Only the view's shape matters for mse, psnr and ssim; efficiency follows the level."""
    rng = np.random.default_rng(seed)
    target = rng.uniform(0, 1, (3, 9, 9))
    view = np.clip(target + rng.normal(0, 0.1, target.shape), 0, None)
    a = metrics(view, target, open_level=1.0)
    b = metrics(scale * view, target, open_level=1.0)
    for key in ("mse", "psnr_db", "ssim"):
        assert b[key] == pytest.approx(a[key], rel=1e-9, abs=1e-12)
    assert b["light_efficiency"] == pytest.approx(scale * a["light_efficiency"], rel=1e-12)


@pytest.mark.parametrize("channels", [1, 3])
def test_ssim_matches_the_definition(channels: int) -> None:
    rng = np.random.default_rng(channels)
    target = rng.uniform(0, 1, (channels, 7, 7))
    view = 3.0 * np.clip(target + rng.normal(0, 0.2, target.shape), 0, None)
    view[0, 0, 0] = 10.0  # gain-scaled, this pixel exceeds 1 and is clipped
    g = float((view * target).sum() / (view * view).sum())
    scaled = np.clip(g * view, 0, 1)
    assert (g * view).max() > 1
    expected = np.mean([ssim_one_window(scaled[c], target[c]) for c in range(channels)])
    assert metrics(view, target, open_level=1.0)["ssim"] == pytest.approx(expected, rel=1e-9)


def test_black_view() -> None:
    target = np.full((1, 8, 8), 0.5)
    m = metrics(np.zeros_like(target), target, open_level=1.0)
    assert m["mse"] == pytest.approx(0.25)
    assert m["light_efficiency"] == 0.0


@pytest.mark.parametrize(
    ("view_shape", "target_shape", "message"),
    [
        ((3, 8, 8), (3, 8, 9), "but target has"),
        ((8, 8), (8, 8), r"\(C, ny, nx\)"),
        ((3, 0, 8), (3, 0, 8), "no empty axis"),
    ],
)
def test_shape_errors(view_shape: tuple[int, ...], target_shape: tuple[int, ...],
                      message: str) -> None:
    with pytest.raises(ValueError, match=message):
        metrics(np.ones(view_shape), np.ones(target_shape), open_level=1.0)


def test_value_errors() -> None:
    ok = np.full((1, 8, 8), 0.5)
    with pytest.raises(ValueError, match="NaN"):
        metrics(np.full((1, 8, 8), np.nan), ok, open_level=1.0)
    with pytest.raises(ValueError, match="target holds values"):
        metrics(ok, 3 * ok, open_level=1.0)
    for level in (0.0, -1.0, math.inf, math.nan):
        with pytest.raises(ValueError, match="open_level"):
            metrics(ok, ok, open_level=level)
    with pytest.raises(ValueError, match="must match"):
        gain(np.ones(3), np.ones(4))


def test_summarize() -> None:
    a = {"mse": 0.1, "psnr_db": 10.0, "ssim": 0.5, "light_efficiency": 0.2}
    b = {"mse": 0.3, "psnr_db": 20.0, "ssim": 0.7, "light_efficiency": 0.4}
    assert summarize([a, b]) == pytest.approx(
        {"mse": 0.2, "psnr_db": 15.0, "ssim": 0.6, "light_efficiency": 0.3})
    assert summarize([a]) == pytest.approx(a)
    with pytest.raises(ValueError, match="no metrics"):
        summarize([])
    with pytest.raises(ValueError, match="keys"):
        summarize([a, {"mse": 0.1}])
