"""Judging a plate over the eye distribution (aperture_fab.validation.robustness)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import tiny_config

from aperture_fab.io.images import resample
from aperture_fab.metrics import gain_mse, psnr_db
from aperture_fab.optics.baselines import elemental_display, regular_pinholes
from aperture_fab.optics.model import Renderer
from aperture_fab.optics.scene import Eye, Scene
from aperture_fab.targets import asymmetric_marker
from aperture_fab.validation import robustness
from aperture_fab.validation.judged_cache import MemoryCache
from aperture_fab.validation.robustness import PERCENTILES, Variant, judge_eyes

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def judged():
    config = tiny_config("near-eye")
    scene = config.scene
    image = asymmetric_marker(32)[:1]
    target = resample(image, scene.eye.view_pixels)[None]
    shown = resample(image, scene.display.pixels)[None]
    array = regular_pinholes(scene)
    pinhole_display = elemental_display(scene, array, torch.as_tensor(target[0]))
    variants = {  # the first is the part
        "pinholes": Variant(array.open_fraction, pinhole_display.numpy()[None]),
        "open": Variant(None, shown),
    }
    return scene, target, variants, judge_eyes(scene, target, variants, dtype=torch.float64,
                                               count=12, map_size=5)


def test_percentiles_are_ordered_and_cover_every_variant(judged):
    _, _, variants, quality = judged
    assert set(quality.psnr_db) == set(variants)
    for name in variants:
        table = quality.percentiles(name)
        assert list(table) == [f"p{q}" for q in PERCENTILES]
        p10, p50, p90 = (table[f"p{q}"][0] for q in PERCENTILES)
        assert p10 <= p50 <= p90
        assert np.all(np.isfinite(quality.psnr_db[name]))
        assert np.all((quality.ssim[name] > -1) & (quality.ssim[name] <= 1))
    summary = quality.summary()
    assert summary["states"] == 12
    assert summary["distribution"]["eyebox_mm"] == [2.0, 2.0]


def test_eyebox_map_agrees_with_rendering_each_position_alone(judged):
    """Each map entry is the PSNR of the view rendered for that pupil position by itself (the
    way `aperture-fab render --eye X,Y` renders it: the nominal position first, then X, Y)."""
    scene, target, variants, quality = judged
    variant = variants["pinholes"]
    rows, cols = np.nonzero(quality.map_inside)
    assert np.all(np.isnan(quality.map_psnr_db["pinholes"][0][~quality.map_inside]))
    assert "open" not in quality.map_psnr_db
    for r, c in list(zip(rows, cols, strict=True))[::3]:
        where = tuple(float(v) for v in quality.map_offsets_mm[r, c])
        eye = scene.eye
        moved = Scene(scene.display, scene.plate,
                      Eye(eye.pupil_mm, eye.eye_relief_mm, eye.fov_deg, eye.view_pixels,
                          eye.focus_mm, (eye.positions_mm[0], where), (1.0, 1.0)))
        view = Renderer(moved, dtype=torch.float64).render(
            torch.as_tensor(variant.open_fraction), torch.as_tensor(variant.displays[0]), 1)
        alone = psnr_db(float(gain_mse(view, torch.as_tensor(target[0]))))
        assert quality.map_psnr_db["pinholes"][0, r, c] == pytest.approx(alone, abs=1e-6)


def test_sweeps_hold_the_nominal_state(judged):
    """The pupil sweep at the nominal pupil equals the nominal PSNR."""
    _, _, _, quality = judged
    nominal = 4.0
    assert quality.pupil_mm[0] <= nominal <= quality.pupil_mm[-1]
    curve = np.interp(nominal, quality.pupil_mm, quality.pupil_psnr_db["pinholes"][0])
    step = np.diff(quality.pupil_psnr_db["pinholes"][0]).__abs__().max()
    assert curve == pytest.approx(quality.nominal_psnr_db["pinholes"][0], abs=step + 1e-9)
    assert quality.thumbnails.shape[:2] == (1, 4)
    assert 0 <= quality.thumbnails.min() and quality.thumbnails.max() <= 1


def test_judging_is_deterministic(judged):
    scene, target, variants, quality = judged
    again = judge_eyes(scene, target, {"pinholes": variants["pinholes"]}, dtype=torch.float64,
                       count=12, map_size=5)
    np.testing.assert_array_equal(again.psnr_db["pinholes"], quality.psnr_db["pinholes"])


def test_cached_variants_are_judged_once_and_read_back_equal(judged, monkeypatch):
    """With a cache, every variant but the part (the first) is judged once and read back to
    the bit; another input misses."""
    scene, target, variants, quality = judged
    cache = MemoryCache()
    first = judge_eyes(scene, target, variants, dtype=torch.float64, count=12, map_size=5,
                       cache=cache)
    assert len(cache.kept) == 1  # "open"; the part is not kept

    def refuse(*args, **kwargs):  # type: ignore[no-untyped-def]
        raise AssertionError("judged again")

    monkeypatch.setattr(robustness, "_judge", refuse)
    again = judge_eyes(scene, target, variants, dtype=torch.float64, count=12, map_size=5,
                       cache=cache)
    for got in (first, again):
        for figures in ("psnr_db", "ssim", "nominal_psnr_db", "pupil_psnr_db"):
            for name in variants:
                np.testing.assert_array_equal(getattr(got, figures)[name],
                                              getattr(quality, figures)[name])
    monkeypatch.undo()
    judge_eyes(scene, target, variants, dtype=torch.float64, count=8, map_size=5, cache=cache)
    assert len(cache.kept) == 2


def test_judging_nothing_is_refused(judged):
    scene, target, _, _ = judged
    with pytest.raises(ValueError, match="no variants"):
        judge_eyes(scene, target, {})
