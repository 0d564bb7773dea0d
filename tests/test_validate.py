"""Validation inside the design job: variants, metrics, tolerance, the written report."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from aperture_fab.cli import main
from aperture_fab.images import encode_png
from aperture_fab.layout import HoleLayout
from aperture_fab.report import REPORT_VARIANTS, validate_report
from aperture_fab.targets import digit
from aperture_fab.validate import ValidationSettings, layout_fractions, validation_settings


def test_layout_fractions_place_each_hole_in_its_cell():
    layout = HoleLayout(
        cells=np.array([[0, 1], [2, 0]]), centres_mm=np.zeros((2, 2)),
        radii_mm=np.array([0.1, 0.05]), axes=np.zeros((2, 2)), pitch_mm=(0.3, 0.25),
        grid=(3, 3), outline_mm=(2.0, 2.0), thickness_mm=0.2,
    )
    a = layout_fractions(layout)
    assert a.shape == (3, 3)
    assert a[0, 1] == pytest.approx(math.pi * 0.01 / 0.075)
    assert a[2, 0] == pytest.approx(math.pi * 0.0025 / 0.075)
    assert np.count_nonzero(a) == 2
    biased = layout_fractions(layout, bias_mm=-0.06)
    assert biased[2, 0] == 0.0 and biased[0, 1] == pytest.approx(math.pi * 0.04**2 / 0.075)


def test_validation_settings_are_checked():
    with pytest.raises(ValueError, match="tolerance_samples"):
        ValidationSettings(tolerance_samples=-1)
    with pytest.raises(ValueError, match="unknown keys"):
        validation_settings({"validation": {"samples": 3}})
    assert validation_settings({}, {"mesh_samples": 8, "tolerance_samples": None}).mesh_samples == 8


@pytest.fixture(scope="module")
def validated(tmp_path_factory):
    folder = tmp_path_factory.mktemp("validated")
    target = folder / "t.png"
    target.write_bytes(encode_png(digit("3")))
    out = folder / "out"
    flags = ["design", str(target), "--out", str(out / "plate.stl"), "--quiet", "--process",
             "photomask", "--thickness-mm", "0.1", "--cells", "16", "16", "--view-pixels", "16",
             "16", "--iterations", "3", "--device", "cpu", "--tolerance-samples", "3",
             "--mesh-samples", "512"]
    assert main(flags) == 0
    return out


def test_report_json_has_every_variant_and_measured_values(validated):
    report = json.loads((validated / "report.json").read_text())
    validate_report(report)
    assert set(report["metrics"]) == set(REPORT_VARIANTS)
    for variant in REPORT_VARIANTS:
        mean = report["metrics"][variant]["mean"]
        assert 0 < mean["mse"] < 1 and math.isfinite(mean["psnr_db"]), variant
    assert report["mesh"]["watertight"] and report["mesh"]["genus"] == report["fabrication"][
        "holes"]
    assert report["tolerance"]["samples"] == 3 and 0 <= report["tolerance"]["yield"] <= 1
    for stage in ("optimize_s", "quantize_build_s", "export_s", "render_s", "report_s"):
        assert report["timings_s"][stage] >= 0, stage
    assert report["scene"]["plate"]["cells"] == [16, 16]


def test_views_archive_and_html(validated):
    with np.load(validated / "views.npz") as views:
        keys = set(views.files)
        assert {f"{v}/t" for v in REPORT_VARIANTS} <= keys
        assert views["as_built/t"].shape == (1, 16, 16)
    html = (validated / "report.html").read_text()
    assert html.count("data:image/png;base64,") >= 4


def test_mesh_retrace_agrees_with_the_model_within_its_noise(validated):
    """The written STL, re-read and ray traced, matches the as-built model up to Monte Carlo
    noise (its RMS difference is about its RMS standard error)."""
    report = json.loads((validated / "report.json").read_text())
    with np.load(validated / "views.npz") as views:
        # The model's as-built view uses the process's bias; photomask has none.
        diff = views["as_built_mesh/t"] - views["quantized/t"]
    stderr = report["mesh_retrace_stderr_rms"]
    assert np.sqrt(np.mean(diff**2)) <= 2 * stderr


def test_fit_display_adapts_the_content_to_a_fixed_plate():
    """Re-fitting the display to the quantized plate lowers the loss from the design's content."""
    import torch

    from aperture_fab.config import resolve
    from aperture_fab.model import Renderer
    from aperture_fab.optimize import fit_display, gain_mse
    from aperture_fab.pipeline import _prepare

    config = resolve("near-eye", overrides={
        "display.width_mm": 4.0, "display.height_mm": 4.0, "display.pixels": [32, 32],
        "plate.cells": [16, 16], "eye.view_pixels": [16, 16], "optimizer.device": "cpu",
        "optimizer.precision": "float64"})
    targets, shown = _prepare(config, [digit("3")])
    rng = np.random.default_rng(0)
    plate = np.where(rng.random((16, 16)) < 0.3, 0.2, 0.0)
    fitted, history = fit_display(config.scene, targets, plate, shown, config.optimizer, 30)
    assert fitted.shape == shown.shape and fitted.min() >= 0 and fitted.max() <= 1
    renderer = Renderer(config.scene, dtype=torch.float64)

    def loss(display):
        view = renderer.render(torch.as_tensor(plate), torch.as_tensor(display[0]))
        return float(gain_mse(view, torch.as_tensor(targets[0])))

    assert loss(fitted) < 0.7 * loss(shown)
    assert history[-1] < history[0]


def test_the_display_written_is_fitted_to_the_part(validated):
    with np.load(validated / "design.npz") as design:
        assert design["built_displays"].shape == design["displays"].shape
        assert not np.allclose(design["built_displays"], design["displays"])
