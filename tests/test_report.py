"""The validation report: JSON structure, views archive, figures, HTML page and verdicts."""

from __future__ import annotations

import base64
import copy
import hashlib
import io
import json
import math
import re
import subprocess
from collections.abc import Mapping
from dataclasses import replace
from html.parser import HTMLParser
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import require_tool, tiny_config
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from aperture_fab.config.stages import PhotometrySettings
from aperture_fab.config.written import to_dict
from aperture_fab.metrics import METRIC_KEYS
from aperture_fab.report.figures import (
    figure_eyebox_map,
    figure_histogram,
    figure_loss,
    figure_mesh_disagreement,
    figure_sweep,
    figure_thumbnails,
    figure_views,
)
from aperture_fab.report.page import SECTION_TITLES, WINDOW_WIDTH_PX, report_html
from aperture_fab.report.part_figures import (
    figure_errors,
    figure_hole_map,
    figure_made_front,
)
from aperture_fab.validation.light import photometry_block
from aperture_fab.validation.report import (
    FIGURE_KEYS,
    REPORT_VARIANTS,
    SCHEMA_VERSION,
    Report,
    Verdict,
    build_report,
    report_json,
    scene_dict,
    validate_report,
    views_npz,
)
from aperture_fab.validation.verdicts import (
    MADE_TOPIC,
    FixPlan,
    fix_plan,
    verdicts,
    with_tried_lattice,
)


def judged(data: Mapping[str, Any], *args: Any) -> Report:
    """report.json's structure read back as a Report, judged: its verdicts computed (args:
    the verdicts' diffraction figures), as aperture_fab.validation.judge.judge does."""
    report = Report.from_json(data)
    return replace(report, verdicts=tuple(verdicts(report, *args)))


#: PSNR (dB) by variant for the fabricated report; the verdict tests derive their numbers from it.
PSNR = {"open": 21.4, "regular_pinholes": 25.1, "random": 18.0, "optimized": 31.8,
        "quantized": 31.5, "as_built": 31.2, "as_built_mesh": 31.1, "as_built_diffraction": 29.0}
TARGETS = ("letter", "grid")
EVIL = "<script>alert('x')</script>"


def metric(psnr: float, offset: float = 0.0) -> dict[str, Any]:
    return {"mse": 10 ** (-(psnr + offset) / 10), "psnr_db": np.float64(psnr + offset),
            "ssim": 0.9 + offset / 100, "light_efficiency": np.float32(0.125)}


#: 10th-percentile PSNR (dB) over the eye distribution by variant; median and 90th sit 2 and
#: 3 dB above it.
EYE_P10 = {"as_built": 24.0, "optimized": 25.0, "open": 20.5, "regular_pinholes": 19.0}


def eye_block(targets: tuple[str, ...] = TARGETS) -> dict[str, Any]:
    """A hand-written report "eye_distribution" block (3 x 3 map, 3-point sweeps)."""
    count = len(targets)

    def per_target(value: float) -> list[float]:
        return [np.float64(value)] * count

    inside = np.array([[False, True, False], [True, True, True], [False, True, False]])
    grid = np.where(inside, 22.0, np.nan)
    return {
        "states": 32, "percentiles": [10, 50, 90], "targets": list(targets),
        "distribution": {"centre_mm": [0.0, 0.0], "eyebox_mm": [4.0, 4.0],
                         "eyebox_shape": "ellipse", "pupil_range_mm": [3.0, 6.0],
                         "focus_range_diopters": [0.0, 0.5], "gaze_deg": 0.0,
                         "rotation_mm": 11.0},
        "variants": {v: {"psnr_db": {"p10": per_target(p), "p50": per_target(p + 2),
                                     "p90": per_target(p + 3)},
                         "ssim": {"p10": per_target(0.8), "p50": per_target(0.85),
                                  "p90": per_target(0.9)},
                         "nominal_psnr_db": per_target(p + 4)}
                     for v, p in EYE_P10.items()},
        "eyebox_map": {"offsets_mm": np.stack(np.meshgrid([-1.3, 0, 1.3], [1.3, 0, -1.3]), -1),
                       "inside": inside, "psnr_db": {"as_built": np.stack([grid] * count)}},
        "pupil": {"pupil_mm": [3.0, 4.5, 6.0],
                  "psnr_db": {v: [[p, p, p]] * count for v, p in EYE_P10.items()}},
        "focus": {"focus_diopters": [0.0, 0.25, 0.5],
                  "psnr_db": {v: [[p, p, p]] * count for v, p in EYE_P10.items()}},
        "thumbnails": {"variant": "as_built", "offsets_mm": [[0.0, 0.0], [1.0, 0.0]],
                       "psnr_db": [[25.0, 23.0]] * count},
    }


def complete_inputs(targets: tuple[str, ...] = TARGETS) -> dict[str, Any]:
    """Every input of build_report, as the pipeline would give them (numpy scalars included).
    The two targets sit +-0.5 dB around PSNR, so each variant's mean PSNR is PSNR[variant]."""
    offsets = np.linspace(-0.5, 0.5, len(targets)) if len(targets) > 1 else [0.0]
    config = tiny_config()
    return {
        "eye_distribution": eye_block(targets),
        "metrics": {v: {t: metric(p, float(o)) for t, o in zip(targets, offsets, strict=True)}
                    for v, p in PSNR.items()},
        "fabrication": {"process": "resin", "holes": 240, "smallest_hole_diameter_mm": 0.08,
                        "smallest_web_mm": 0.05, "largest_hole_diameter_mm": 0.2,
                        "violations": [{"rule": "min_hole", "cell": (3, 4), "value_mm": 0.03,
                                        "limit_mm": 0.05, "resolution": "closed"},
                                       {"rule": "min_web", "cell": None, "value_mm": 0.01,
                                        "limit_mm": 0.05, "resolution": "shrunk"}]},
        "mesh": {"watertight": True, "genus": 240, "volume_mm3": np.float64(1.5),
                 "triangles": 10_000},
        "tolerance": {"samples": 64, "psnr_percentiles": {"5": 27.3, "50": 30.1, "95": 31.0},
                      "yield": 0.92, "threshold_db": 25.0},
        "timings_s": {"optimize": 12.5, "build": 3.25},
        "scene": scene_dict(config.scene),
        "config": to_dict(config),
        "versions": {"aperture-fab": "0.1.0", "numpy": np.__version__},
    }


def made_block(count: int = len(TARGETS)) -> dict[str, Any]:
    """A "made_part" block as made_part_block gives it: the part 5 dB above its best rival."""
    family = {"pitch_mm": [0.5, 1.0, 1.0], "diameter_mm": [0.06, 0.06, 0.1],
              "efficiency": [0.011, 0.003, 0.008], "eye_level": [0.004, 0.001, 0.003],
              "p10_db": [16.0, 17.0, 16.5],
              "p50_db": [17.0, 18.0, 17.5]}
    figures = {"efficiency": 0.01, "eye_level": 0.002, "p10_db": [21.0] * count,
               "p50_db": [23.0] * count, "p90_db": [25.0] * count}
    best = {"pitch_mm": 0.5, "diameter_mm": 0.06, "efficiency": 0.011, "eye_level": 0.004,
            "p10_db": [16.0] * count,
            "p50_db": [17.0] * count, "p90_db": [18.0] * count}
    return {"copies": 4, "states": 32, "neglected": ["wall scatter"], "part": figures,
            "regular": {"family": family, "fitted": family, "best": best},
            "margin_db": [5.0] * count, "margin_interval_db": [[4.2, 5.9]] * count}


@pytest.fixture(scope="module")
def report() -> dict[str, Any]:
    return build_report(**complete_inputs()).as_json()


def png_size(data: bytes) -> tuple[int, int]:
    with Image.open(io.BytesIO(data)) as image:
        assert image.format == "PNG"
        image.load()
        return image.size


# ---------------------------------------------------------------------------------------------
# report.json


def test_build_report_structure(report: dict[str, Any]) -> None:
    assert report["schema_version"] == SCHEMA_VERSION == 3
    assert list(report)[:5] == ["schema_version", "eye_distribution", "verdicts", "photometry",
                                "metrics"]
    eyes = report["eye_distribution"]
    assert eyes["eyebox_map"]["psnr_db"]["as_built"][0][0] == [None, 22.0, None]  # NaN: null
    assert eyes["eyebox_map"]["inside"][1] == [True, True, True]
    assert list(report["metrics"]) == list(REPORT_VARIANTS)
    for variant, block in report["metrics"].items():
        assert set(block["per_target"]) == set(TARGETS)
        for key in METRIC_KEYS:
            values = [block["per_target"][t][key] for t in TARGETS]
            assert block["mean"][key] == pytest.approx(sum(values) / len(values))
            assert type(block["mean"][key]) is float
        assert block["mean"]["psnr_db"] == pytest.approx(PSNR[variant])
    assert report["fabrication"]["violations"][0]["cell"] == [3, 4]  # tuples become lists
    assert report["fabrication"]["largest_hole_diameter_mm"] == 0.2  # extra keys are kept
    scene = tiny_config().scene
    assert report["scene"]["display"]["pixels"] == list(scene.display.pixels)
    assert report["scene"]["plate"]["pitch_mm"] == list(scene.plate.pitch_mm)
    assert report["scene"]["eye"]["focus_mm"] is None  # infinity
    assert report["scene"]["eye"]["positions_mm"] == [list(p) for p in scene.eye.positions_mm]


def test_nan_becomes_null_and_mean_is_null() -> None:
    inputs = complete_inputs()
    inputs["metrics"]["open"]["letter"]["ssim"] = math.nan
    inputs["timings_s"]["mesh"] = math.inf
    built = build_report(**inputs).as_json()
    assert built["metrics"]["open"]["per_target"]["letter"]["ssim"] is None
    assert built["metrics"]["open"]["mean"]["ssim"] is None
    assert built["metrics"]["open"]["mean"]["psnr_db"] == pytest.approx(PSNR["open"])
    assert built["timings_s"]["mesh"] is None
    text = report_json(Report.from_json(built))
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == built


def test_json_round_trip(report: dict[str, Any]) -> None:
    text = report_json(Report.from_json(report))
    assert json.loads(text) == report
    assert text.startswith('{\n  "schema_version": 3,\n  "eye_distribution": {')


@settings(max_examples=30, deadline=None)
@given(values=st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=4, max_size=4))
def test_json_round_trip_any_metric_values(values: list[float]) -> None:
    """Any float survives as itself, or as null when JSON cannot hold it."""
    inputs = complete_inputs()
    inputs["metrics"] = {"as_built": {"only": dict(zip(METRIC_KEYS, values, strict=True))}}
    built = build_report(**inputs).as_json()
    again = json.loads(report_json(Report.from_json(built)))
    assert again == built
    expected = [v if math.isfinite(v) else None for v in values]
    assert list(again["metrics"]["as_built"]["per_target"]["only"].values()) == expected
    assert list(again["metrics"]["as_built"]["mean"].values()) == expected


#: Every key the schema requires, as a path into the report.
REQUIRED = [
    ("schema_version",), ("eye_distribution",), ("verdicts",), ("metrics",), ("fabrication",),
    ("mesh",), ("tolerance",), ("timings_s",), ("scene",), ("config",), ("versions",),
    *[("eye_distribution", k) for k in ("states", "percentiles", "targets", "distribution",
                                         "variants", "eyebox_map", "pupil", "focus",
                                         "thumbnails")],
    *[("eye_distribution", "variants", "open", k) for k in ("psnr_db", "ssim",
                                                            "nominal_psnr_db")],
    *[("eye_distribution", "variants", "as_built", "psnr_db", k) for k in ("p10", "p50", "p90")],
    ("eye_distribution", "eyebox_map", "inside"), ("eye_distribution", "pupil", "pupil_mm"),
    ("eye_distribution", "focus", "focus_diopters"),
    ("eye_distribution", "thumbnails", "offsets_mm"),
    ("metrics", "as_built", "per_target"), ("metrics", "as_built", "mean"),
    *[("metrics", "open", "per_target", "grid", k) for k in METRIC_KEYS],
    *[("metrics", "quantized", "mean", k) for k in METRIC_KEYS],
    *[("fabrication", k) for k in ("process", "holes", "smallest_hole_diameter_mm",
                                   "smallest_web_mm", "violations")],
    *[("fabrication", "violations", 1, k) for k in ("rule", "cell", "value_mm", "limit_mm",
                                                      "resolution")],
    *[("mesh", k) for k in ("watertight", "genus", "volume_mm3", "triangles")],
    *[("tolerance", k) for k in ("samples", "psnr_percentiles", "yield", "threshold_db")],
    *[("tolerance", "psnr_percentiles", k) for k in ("5", "50", "95")],
    ("scene", "display"), ("scene", "plate"), ("scene", "eye"),
    *[("scene", "display", k) for k in ("width_mm", "height_mm", "pixels")],
    *[("scene", "plate", k) for k in ("gap_mm", "thickness_mm", "pitch_mm", "cells")],
    *[("scene", "eye", k) for k in ("pupil_mm", "eye_relief_mm", "focus_mm", "fov_deg",
                                    "view_pixels", "positions_mm")],
]


@pytest.mark.parametrize("path", REQUIRED, ids=lambda p: ".".join(map(str, p)))
def test_each_missing_key_raises(report: dict[str, Any], path: tuple[Any, ...]) -> None:
    broken = copy.deepcopy(report)
    parent = broken
    for key in path[:-1]:
        parent = parent[key]
    del parent[path[-1]]
    with pytest.raises(ValueError, match=rf"missing \S*\b{re.escape(str(path[-1]))}\b"):
        validate_report(broken)


@pytest.mark.parametrize(
    ("path", "value"),
    [
        (("mesh", "watertight"), "yes"),
        (("mesh", "genus"), 2.5),
        (("scene", "display", "pixels"), [1.5, 2]),
        (("scene", "eye", "positions_mm"), [[0.0]]),
        (("fabrication", "violations", 0, "cell"), [1]),
        (("metrics", "open", "mean", "psnr_db"), "high"),
        (("timings_s", "optimize"), "fast"),
        (("versions", "numpy"), 2),
        (("config",), []),
        (("tolerance",), [1]),
        (("metrics", "open", "per_target"), [1]),
        (("metrics", "open", "per_target", "grid"), 0.5),
        (("eye_distribution", "variants", "open", "psnr_db", "p10"), [20.0]),  # one of two
        (("eye_distribution", "variants", "open", "nominal_psnr_db"), [20.0, "x"]),
        (("eye_distribution", "pupil", "psnr_db", "open"), [1.0, 2.0]),
        (("eye_distribution", "states"), 3.5),
        (("verdicts",), {}),
    ],
)
def test_wrong_types_raise(report: dict[str, Any], path: tuple[Any, ...], value: Any) -> None:
    broken = copy.deepcopy(report)
    parent = broken
    for key in path[:-1]:
        parent = parent[key]
    parent[path[-1]] = value
    with pytest.raises(TypeError):
        validate_report(broken)


def test_other_invalid_reports(report: dict[str, Any]) -> None:
    validate_report({**report, "tolerance": None})  # not computed is allowed
    validate_report({**report, "eye_distribution": None})  # not judged is allowed
    eyes = report["eye_distribution"]
    changes: list[tuple[dict[str, Any], str]] = [
        ({"schema_version": 1}, "schema_version"),
        ({"eye_distribution": {**eyes, "variants": {}}}, "variants is empty"),
        ({"eye_distribution": {**eyes, "targets": []}}, "target names"),
        ({"verdicts": [{"topic": "x", "level": "red", "text": "t"}]}, "level"),
        ({"metrics": {}}, "metrics is empty"),
        ({"metrics": {"ideal": report["metrics"]["open"]}}, "not a known variant"),
        ({"metrics": {"open": {"per_target": {}, "mean": {}}}}, "per_target is empty"),
        ({"tolerance": {**report["tolerance"], "yield": 92}}, "fraction"),
    ]
    for change, message in changes:
        with pytest.raises(ValueError, match=message):
            validate_report({**report, **change})


def test_build_report_rejects_bad_metrics() -> None:
    inputs = complete_inputs()
    del inputs["metrics"]["as_built"]["grid"]["ssim"]
    with pytest.raises(ValueError, match=r"metrics\.as_built\.per_target\.grid\.ssim"):
        build_report(**inputs).as_json()
    inputs = complete_inputs()
    inputs["metrics"]["ideal"] = inputs["metrics"]["open"]
    with pytest.raises(ValueError, match="ideal"):
        build_report(**inputs).as_json()
    inputs = complete_inputs()
    inputs["config"] = {"when": object()}
    with pytest.raises(TypeError, match=r"config\.when"):
        build_report(**inputs).as_json()


# ---------------------------------------------------------------------------------------------
# views.npz


def test_views_npz_round_trip() -> None:
    rng = np.random.default_rng(0)
    views: dict[str, np.ndarray] = {
        "as_built/letter": rng.uniform(0, 1, (3, 8, 8)),
        "open/letter/pos2": rng.uniform(0, 1, (3, 8, 8)).astype(np.float32),
        "optimized/letter <a> & b.png": rng.uniform(0, 1, (1, 4, 5)),
    }
    with np.load(io.BytesIO(views_npz(views))) as archive:
        assert sorted(archive.files) == sorted(views)
        for key, view in views.items():
            assert archive[key].dtype == view.dtype
            np.testing.assert_array_equal(archive[key], view)


@pytest.mark.parametrize("key", ["as_built", "ideal/letter", "as_built/letter/3", "a/b/pos1/x",
                                 "as_built//pos1"])
def test_views_npz_bad_keys(key: str) -> None:
    with pytest.raises(ValueError, match="views key"):
        views_npz({key: np.zeros((1, 2, 2))})


def test_views_npz_bad_values() -> None:
    with pytest.raises(ValueError, match="float"):
        views_npz({"open/a": np.zeros((1, 2, 2), dtype=np.uint8)})
    with pytest.raises(ValueError, match="finite"):
        views_npz({"open/a": np.full((1, 2, 2), np.nan)})


# ---------------------------------------------------------------------------------------------
# Figures


def test_figures_are_pngs() -> None:
    rng = np.random.default_rng(0)
    target = rng.uniform(0, 1, (3, 16, 16))
    assert png_size(figure_views([("target", target), ("view", 0.3 * target),
                                  ("grey", target[:1])], "views")) > (100, 100)
    many = [(f"pos{k}", target) for k in range(9)]  # wraps onto two lines
    assert png_size(figure_views(many, "eyebox"))[1] > png_size(figure_views(many[:3], "x"))[1]
    assert png_size(figure_views([("display", target)], "display", gain_to_first=False))
    assert png_size(hole_map(rng))
    assert png_size(figure_errors(target, [("view", 0.3 * target), ("grey", target[:1])]))
    assert png_size(figure_loss(np.geomspace(1, 1e-3, 50)))
    assert png_size(figure_loss(np.array([0.5, 0.0, -0.1])))  # not log-scalable: linear axis
    assert png_size(figure_histogram(rng.normal(30, 2, 64), 25.0))
    assert png_size(figure_histogram(np.array([30.0]), None))
    block = eye_block()
    offsets = np.asarray(block["eyebox_map"]["offsets_mm"])
    grid = np.asarray(block["eyebox_map"]["psnr_db"]["as_built"])
    one = png_size(figure_eyebox_map(grid[:1], offsets, (4.0, 4.0)))
    assert png_size(figure_eyebox_map(grid, offsets, (4.0, 4.0), shape="rect",
                                      names=TARGETS))[0] > one[0]  # a panel per target
    assert png_size(figure_eyebox_map(grid, offsets, (4.0, 0.0)))  # a line of positions
    curves = {v: rng.normal(p, 1, (2, 5)) for v, p in EYE_P10.items()}
    assert png_size(figure_sweep(np.linspace(3, 6, 5), curves, xlabel="pupil (mm)",
                                 shaded=(3.0, 6.0), nominal=4.0, names=TARGETS))
    assert png_size(figure_sweep(np.linspace(0, 2, 5), curves, xlabel="focus (D)",
                                 shaded=(0.0, 0.0)))  # a point range: a line, no shading
    views = rng.uniform(0, 1, (2, 3, 1, 8, 8))
    assert png_size(figure_thumbnails(views[:, 0], views, np.zeros((3, 2)), np.ones((2, 3)),
                                      TARGETS))


def test_figure_views_scales_by_gain() -> None:
    """A view at half the target's level shows exactly like the target itself."""
    target = np.random.default_rng(2).uniform(0, 1, (3, 12, 12))
    same = figure_views([("target", target), ("view", target)], "t")
    assert figure_views([("target", target), ("view", 0.5 * target)], "t") == same
    assert figure_views([("target", target), ("view", 0.5 * target)], "t",
                        gain_to_first=False) != same


#: A 2 x 2.5 mm plate outline with its top-left corner cut (fabrication.mesh.outline_points_mm).
OUTLINE = [(1.0, 1.25), (-0.8, 1.25), (-1.0, 1.05), (-1.0, -1.25), (1.0, -1.25)]


def hole_map(rng: np.random.Generator, count: int = 12) -> bytes:
    centres = rng.uniform(-0.8, 0.8, (count, 2))
    return figure_hole_map(centres, rng.uniform(0.02, 0.09, count), OUTLINE)


def test_hole_map_draws_the_holes_to_scale_in_the_outline() -> None:
    rng = np.random.default_rng(3)
    assert hole_map(rng) != hole_map(np.random.default_rng(4))
    # no holes (a blank plate) and holes of one size still draw
    assert png_size(figure_hole_map(np.zeros((0, 2)), np.zeros(0), OUTLINE))
    assert png_size(figure_hole_map(np.zeros((1, 2)), np.array([0.1]), OUTLINE))
    wide = png_size(figure_hole_map(np.zeros((1, 2)), np.array([0.1]),
                                    [(4.0, 1.0), (-4.0, 1.0), (-4.0, -1.0), (4.0, -1.0)]))
    assert wide[0] > 1.5 * wide[1]  # drawn to scale: a wide plate gives a wide figure


def test_error_maps_compare_shapes_not_levels() -> None:
    target = np.random.default_rng(2).uniform(0, 1, (3, 12, 12))
    zero = figure_errors(target, [("view", target)])
    assert figure_errors(target, [("view", 0.5 * target)]) == zero  # the gain takes the level
    assert figure_errors(target, [("view", target[::-1].copy())]) != zero


def test_figure_errors() -> None:
    with pytest.raises(ValueError, match="no images"):
        figure_views([], "t")
    with pytest.raises(ValueError, match="gain_to_first"):
        figure_views([("a", np.ones((3, 4, 4))), ("b", np.ones((3, 5, 4)))], "t")
    with pytest.raises(ValueError, match="C = 1 or 3"):
        figure_views([("a", np.ones((2, 4, 4)))], "t")
    with pytest.raises(ValueError, match="radii > 0"):
        figure_hole_map(np.zeros((1, 2)), -np.ones(1), OUTLINE)
    with pytest.raises(ValueError, match="one radius per hole"):
        figure_hole_map(np.zeros((2, 2)), np.ones(1), OUTLINE)
    with pytest.raises(ValueError, match="closed loop"):
        figure_hole_map(np.zeros((1, 2)), np.ones(1), OUTLINE[:2])
    with pytest.raises(ValueError, match="no views"):
        figure_errors(np.ones((3, 4, 4)), [])
    with pytest.raises(ValueError, match="has shape"):
        figure_errors(np.ones((3, 4, 4)), [("b", np.ones((3, 5, 4)))])
    with pytest.raises(ValueError, match="N >= 1"):
        figure_loss(np.array([]))
    with pytest.raises(ValueError, match="finite"):
        figure_histogram(np.array([np.nan]), 25.0)
    offsets = np.zeros((3, 3, 2))
    with pytest.raises(ValueError, match="NaN everywhere"):
        figure_eyebox_map(np.full((1, 3, 3), np.nan), offsets, (4.0, 4.0))
    with pytest.raises(ValueError, match="a point has no map"):
        figure_eyebox_map(np.ones((1, 3, 3)), offsets, (0.0, 0.0))
    with pytest.raises(ValueError, match="do not match"):
        figure_eyebox_map(np.ones((1, 3, 3)), np.zeros((2, 2, 2)), (4.0, 4.0))
    with pytest.raises(ValueError, match="no curves"):
        figure_sweep(np.arange(3.0), {}, xlabel="x", shaded=(0.0, 1.0))
    with pytest.raises(ValueError, match="3 points but x has 4"):
        figure_sweep(np.arange(4.0), {"a": np.ones((1, 3))}, xlabel="x", shaded=(0.0, 1.0))
    with pytest.raises(ValueError, match="expected"):
        figure_thumbnails(np.ones((1, 1, 4, 4)), np.ones((1, 2, 1, 4, 4)), np.zeros((3, 2)),
                          np.ones((1, 2)))


# ---------------------------------------------------------------------------------------------
# Verdicts


def texts(report: dict[str, Any], *args: Any) -> list[str]:
    return [v.text for v in verdicts(Report.from_json(report), *args)]


def test_the_tolerance_verdict_states_the_gap_scale(report: dict[str, Any]) -> None:
    """A report whose tolerance draws were judged at their pictures' size says so, with the
    size error; an older one (no gap_scale_sigma_percent) reads as before."""
    scaled = copy.deepcopy(report)
    scaled["tolerance"].update(gap_scale_sigma_percent=1.0, gap_sigma_mm=0.1)
    found = next(v for v in verdicts(Report.from_json(scaled)) if v.topic == "tolerance")
    assert ("A gap error scales the picture (1.0 % at its 1 sigma, 0.1 mm) and does not blur "
            "it: each part is judged at its picture's size") in found.text
    older = next(v for v in verdicts(Report.from_json(report)) if v.topic == "tolerance")
    assert "gap error" not in older.text


def test_verdicts_hand_written(report: dict[str, Any]) -> None:
    found = verdicts(Report.from_json(report), diffraction_blur_px=1.34)
    lines = [v.text for v in found]
    # The eye distribution leads, the tolerance yield follows, then the nominal eye point.
    assert [v.topic for v in found[:3]] == ["eye distribution", "tolerance", "nominal"]
    assert found[0].level == "pass"
    assert lines[0].startswith(
        "Over the eye distribution (32 states: eyebox 4 x 4 mm ellipse, pupil 3 to 6 mm, focus "
        "0 to 0.5 D), the part as built scores 24.0 dB PSNR at the 10th percentile for target "
        "'letter' (median 26.0, 90th 27.0; 28.0 at the nominal eye point), against 20.5 dB for "
        "the open display (+3.5 dB) and 19.0 dB for the regular pinhole array (+5.0 dB).")
    assert lines[1].startswith("92 % of 64 parts drawn with the process's tolerances score "
                               "above 25.0 dB (90 % interval of the yield 85 to 96 %; more "
                               "draws narrow it: [validation] tolerance_samples). Median 30.1 "
                               "dB")
    assert found[1].level == "pass"
    assert lines[2] == ("At the nominal eye point, as built, the view scores 31.2 dB PSNR (SSIM "
                        "0.90), 9.8 dB better than the open display and 6.1 dB better than a "
                        "regular pinhole array.")
    assert lines[3] == "Quantization and fabrication cost 0.6 dB."
    assert "The eye sees 12 % of the light of the open display." in lines
    assert ("Traced through the written mesh (the holes as drawn), the view scores 31.1 dB "
            "(-0.4 dB from the hole layout's).") in lines
    assert "Holes of 0.080 mm: diffraction blurs them by about 1.3 view pixels." in lines
    assert any(line.startswith("2 fabrication rule violations of the resin process")
               for line in lines)
    assert "The mesh is watertight, genus 240 (one per hole), 10000 triangles." in lines
    assert not any("diffraction blurs" in line for line in texts(report))
    assert all(v.level == "info" for v in found[2:])


def test_verdicts_without_as_built_and_with_worse_results(report: dict[str, Any]) -> None:
    partial = copy.deepcopy(report)
    for variant in ("as_built", "as_built_mesh", "as_built_diffraction", "regular_pinholes"):
        del partial["metrics"][variant]
    partial["metrics"]["open"]["mean"]["psnr_db"] = 40.0
    partial["metrics"]["optimized"]["mean"]["psnr_db"] = 31.0
    partial["tolerance"] = None
    partial["eye_distribution"] = None
    partial["fabrication"]["violations"] = []
    partial["mesh"]["watertight"] = False
    found = verdicts(Report.from_json(partial))
    lines = [v.text for v in found]
    assert found[0].topic == "eye distribution" and found[0].level == "info"
    assert lines[0].startswith("Not judged over the eye distribution (validation.eye_states = "
                               "0): every figure below is for the nominal eye point only")
    assert lines[1] == ("At the nominal eye point, after quantization, the view scores 31.5 dB "
                        "PSNR (SSIM 0.90), 8.5 dB worse than the open display.")
    assert lines[2] == ("Quantization cost nothing: the view is 0.5 dB better than the optimized "
                        "design's.")
    assert "The 240 holes meet every rule of the resin process." in lines
    assert [v.level for v in found if "NOT watertight" in v.text] == ["fail"]
    assert not any("Yield" in line or "mesh, the view" in line for line in lines)


# ---------------------------------------------------------------------------------------------
# Fixes: one recommended, then the others, none already applied

#: A light budget that warns (mesopic, the pupil wider than assumed) and a plate that leaks
#: (optical density 2): photometry_block's arguments.
DIM = {"efficiency": 0.0016, "level": 1.0, "assumed_pupil_mm": 4.0, "fov_deg": (20.0, 20.0),
       "efficiency_weight": 0.0, "optical_density": 2.0, "optical_density_note": "estimate",
       "open_share": 0.2}


def failing_report(changes: dict[str, Any]) -> dict[str, Any]:
    """A report whose judged checks all fail or warn: the part below the open display over the
    eye distribution, the part as made below the best regular array, a low yield, a dim view
    and a plate that leaks; with `changes` ("optimizer.<key>" or "process.name") applied to its
    config, as the design had them."""
    inputs = complete_inputs()
    for p10 in (inputs["eye_distribution"]["variants"]["as_built"]["psnr_db"]["p10"],):
        p10[:] = [EYE_P10["open"] - 2.0] * len(p10)
    inputs["tolerance"]["yield"] = 0.2
    made = made_block()
    made["margin_db"] = [-2.0] * len(TARGETS)
    config = inputs["config"]
    for key, value in changes.items():
        section, name = key.split(".")
        config[section][name] = value
    inputs["fabrication"]["process"] = config["process"]["name"]
    floor = float(config["optimizer"]["min_efficiency"])
    photometry = photometry_block(settings=PhotometrySettings(), min_efficiency=floor, **DIM)
    return build_report(**inputs, made_part=made, photometry=photometry).as_json()


def all_fixes(report: dict[str, Any]) -> list[str]:
    return [fix for verdict in verdicts(Report.from_json(report)) for fix in verdict.fixes]


#: (what the design already does, the config that does it, the config that does not, a fix
#: that only the second may propose).
APPLIED = [
    ("designed for the eye distribution", {"optimizer.eye_states": 8},
     {"optimizer.eye_states": 1}, "optimizer.eye_states > 1"),
    ("tracked display", {"optimizer.tracking": "tracked"},
     {"optimizer.tracking": "untracked"}, 'optimizer.tracking = "tracked"'),
    ("fabrication-aware design", {"optimizer.quantize_share": 1.0},
     {"optimizer.quantize_share": 0.0}, "optimizer.quantize_share > 0"),
    ("photomask film", {"process.name": "photomask"}, {"process.name": "resin"},
     'name = "photomask"'),
    ("a light floor", {"optimizer.min_efficiency": 0.001},
     {"optimizer.min_efficiency": 0.0}, "set optimizer.min_efficiency"),
]


@pytest.mark.parametrize(("applied", "not_applied", "fix"),
                         [case[1:] for case in APPLIED], ids=[case[0] for case in APPLIED])
def test_no_fix_the_design_already_applied_is_proposed(applied: dict[str, Any],
                                                       not_applied: dict[str, Any],
                                                       fix: str) -> None:
    def proposes(report: dict[str, Any]) -> bool:
        return any(fix.lower() in f.lower() for f in all_fixes(report))

    assert proposes(failing_report(not_applied))
    done = failing_report(applied)
    assert not proposes(done)
    page = report_html(judged(done), {})
    assert html_escaped(fix).lower() not in page.lower()


def test_the_default_designs_fixes_leave_out_everything_it_does() -> None:
    """The near-eye preset samples the eye distribution, designs for the process, sets a
    light floor, on photomask film: none of that is proposed, and every check still has a fix."""
    report = failing_report({"optimizer.eye_states": 8, "optimizer.quantize_share": 1.0,
                             "optimizer.min_efficiency": 0.001, "process.name": "photomask"})
    fixes = all_fixes(report)
    for _, _, _, fix in APPLIED[:1] + APPLIED[2:]:
        assert not any(fix.lower() in f.lower() for f in fixes), fix
    acting = [v for v in verdicts(Report.from_json(report)) if v.level in ("fail", "warn")]
    assert judged(report).level == "fail"
    assert {v.topic for v in acting} == {"eye distribution", "made part", "tolerance", "light",
                                         "contrast"}
    assert all(v.fixes for v in acting)
    assert all("Fix" not in v.text and "What to change" not in v.text for v in acting)


def test_the_page_recommends_one_fix_first_then_lists_the_others() -> None:
    report = failing_report({"optimizer.eye_states": 8})
    lines = verdicts(Report.from_json(report))
    plan = fix_plan(lines)
    # the deciding verdict: the first failing one, the eye distribution; its first fix
    assert plan.deciding is lines[0] and lines[0].level == "fail"
    assert plan.recommended == lines[0].fixes[0]
    assert plan.recommended.startswith("Design again with a smaller pitch")
    others = [fix for _, fix in plan.alternatives]
    assert plan.recommended not in others and len(set(others)) == len(others)
    assert set(others) | {plan.recommended} == {f for v in lines for f in v.fixes}
    # the tracked display, proposed for two checks, is listed once
    assert sum("tracked" in fix for fix in others) == 1
    page = report_html(judged(report), {})
    verdict = page[page.index('<section id="verdict">'):page.index('<section id="made">')]
    recommended = verdict.index('id="recommended-fix"')
    assert recommended < verdict.index('class="verdict verdict-') < verdict.index(
        'id="other-fixes"')
    assert verdict.index('class="overall') < recommended
    assert html_escaped(plan.recommended) in verdict[recommended:verdict.index("</div>",
                                                                                recommended)]
    for fix in [plan.recommended, *others]:
        assert page.count(html_escaped(fix)) == 1, fix  # each fix once, in the verdict section


def test_a_passing_report_recommends_nothing(report: dict[str, Any]) -> None:
    lines = verdicts(Report.from_json(report))
    assert fix_plan(lines) == FixPlan(None, None, ())
    assert judged(report).level == "pass" and Report.from_json(report).level == "info"
    page = report_html(judged(report), {})
    assert 'id="recommended-fix"' not in page and 'id="other-fixes"' not in page


# ---------------------------------------------------------------------------------------------
# The HTML page


class PageParser(HTMLParser):
    """Collects headings, <img> sources, every URL-bearing attribute and the tags used."""

    def __init__(self) -> None:
        super().__init__()
        self.headings: list[str] = []
        self.images: list[str] = []
        self.image_ids: list[str] = []
        self.urls: list[str] = []
        self.tags: set[str] = set()
        self._heading: list[str] | None = None

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.tags.add(tag)
        if tag in ("h2", "h3"):
            self._heading = []
        for name, value in attrs:
            if name in ("src", "href", "srcset", "data", "action", "poster"):
                self.urls.append(value or "")
            if tag == "img" and name == "src":
                self.images.append(value or "")
            if tag == "img" and name == "id":
                self.image_ids.append(value or "")

    def handle_endtag(self, tag: str) -> None:
        if tag in ("h2", "h3") and self._heading is not None:
            self.headings.append("".join(self._heading))
            self._heading = None

    def handle_data(self, data: str) -> None:
        if self._heading is not None:
            self._heading.append(data)


def all_figures() -> dict[str, bytes]:
    rng = np.random.default_rng(4)
    target = rng.uniform(0, 1, (3, 16, 16))
    views = figure_views([("target", target), ("as built", 0.2 * target)], "views")
    block = eye_block(("letter",))
    sweep = figure_sweep(np.arange(3.0), {"as built": np.ones((1, 3))}, xlabel="x",
                         shaded=(0.0, 1.0))
    return {"eye_map": figure_eyebox_map(np.asarray(block["eyebox_map"]["psnr_db"]["as_built"]),
                                         np.asarray(block["eyebox_map"]["offsets_mm"]),
                                         (4.0, 4.0)),
            "eye_pupil": sweep, "eye_focus": figure_loss(np.geomspace(1, 1e-2, 5)),
            "eye_thumbnails": figure_thumbnails(target[None], target[None, None],
                                                np.zeros((1, 2)), np.ones((1, 1))),
            "views": views, "hole_map": hole_map(rng),
            "errors": figure_errors(target, [("as built", 0.2 * target)]),
            "loss": figure_loss(np.geomspace(1, 1e-2, 20)), "eyebox": views,
            "tolerance": figure_histogram(rng.normal(30, 2, 64), 25.0),
            "made_front": figure_made_front(made_block()),
            "mesh_retrace": figure_mesh_disagreement(target + 1e-3, target, 1e-3)}


@pytest.fixture(scope="module")
def evil_report() -> dict[str, Any]:
    """A complete report whose second target is named like a script."""
    return build_report(**complete_inputs(("letter", EVIL)), made_part=made_block(2)).as_json()


def test_html_sections_and_images(evil_report: dict[str, Any]) -> None:
    figures = all_figures()
    page = report_html(judged(evil_report, 1.3), figures)
    parser = PageParser()
    parser.feed(page)
    for _, heading in SECTION_TITLES:
        assert heading in parser.headings
    order = [parser.headings.index(h) for _, h in SECTION_TITLES]
    assert order == sorted(order)  # reads top to bottom in the documented order
    assert len(parser.images) == len(FIGURE_KEYS) == len(figures)
    decoded = []
    for src in parser.images:
        prefix = "data:image/png;base64,"
        assert src.startswith(prefix)
        data = base64.b64decode(src[len(prefix):], validate=True)
        assert png_size(data)
        decoded.append(data)
    assert sorted(decoded) == sorted(figures.values())
    # self-contained: no script, stylesheet link or frame; every URL is data: or a local anchor
    assert not {"script", "link", "iframe", "object", "embed"} & parser.tags
    assert all(u.startswith(("data:image/png;base64,", "#")) for u in parser.urls)
    assert "http://" not in page and "https://" not in page
    assert "Quantization and fabrication cost 0.6 dB." in page
    # the verdict leads, then the part as made and its figure, light and contrast, then the
    # eye distribution's figures
    assert parser.headings[:4] == ["Verdict", "The part as made", "Light and contrast",
                                   "Over the eye distribution"]
    assert parser.image_ids[:5] == ["fig-made_front", "fig-eye_map", "fig-eye_pupil",
                                    "fig-eye_focus", "fig-eye_thumbnails"]
    assert "Margin over it (at equal or more light at the eye): <b>+5.0 / +5.0 dB</b>" in page


def test_html_escapes_names(evil_report: dict[str, Any]) -> None:
    inputs = complete_inputs(("letter", EVIL))
    inputs["fabrication"]["violations"][0]["resolution"] = "<b>closed</b> & done"
    inputs["config"]["notes"] = "</pre><img src=x onerror=alert(1)>"
    page = report_html(replace(build_report(**inputs),
                               verdicts=(Verdict("", "info", f"verdict with {EVIL}"),)), {})
    assert "<script" not in page
    assert "<img src=x" not in page and "&lt;img src=x onerror=alert(1)&gt;" in page
    assert html_escaped(EVIL) in page
    assert "&lt;b&gt;closed&lt;/b&gt; &amp; done" in page
    parser = PageParser()
    parser.feed(page)
    assert parser.images == [] and "script" not in parser.tags


def html_escaped(text: str) -> str:
    return (text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
            .replace("'", "&#x27;").replace('"', "&quot;"))


def test_html_missing_figures_say_not_computed(report: dict[str, Any]) -> None:
    page = report_html(Report.from_json({**report, "tolerance": None}),
                       {"loss": figure_loss(np.ones(3))})
    parser = PageParser()
    parser.feed(page)
    assert len(parser.images) == 1
    # the tolerance and the part as made say why they are missing in their own words; the
    # section of the eye positions, with nothing to show, is left out (and out of the contents),
    # and so is the mesh re-trace's map when the mesh was not traced
    assert page.count("Figure not computed.") == len(FIGURE_KEYS) - 5
    assert 'id="fig-mesh_retrace"' not in page
    assert 'id="eyebox"' not in page and 'href="#eyebox"' not in page
    assert "The part as made not computed" in page
    assert "Tolerance analysis not computed." in page


def test_html_rejects_bad_figures(report: dict[str, Any]) -> None:
    with pytest.raises(ValueError, match="not one the page places"):
        report_html(Report.from_json(report), {"lossy": figure_loss(np.ones(3))})
    with pytest.raises(ValueError, match="not PNG"):
        report_html(Report.from_json(report), {"loss": b"GIF89a"})
    with pytest.raises(ValueError, match="missing"):
        Report.from_json({k: v for k, v in report.items() if k != "mesh"})


#: Appended by the browser test only: counts the images that decoded once the page has loaded,
#: and measures the page's height (CSS px) in the window.
HOOK = ("window.addEventListener('load', () => { const images = [...document.images]; "
        "document.body.dataset.imagesTotal = images.length; "
        "document.body.dataset.imagesOk = images.filter("
        "i => i.complete && i.naturalWidth > 0).length; "
        "document.body.dataset.pageHeight = document.body.scrollHeight; });")
#: The browser window's height (CSS px) when a page is loaded; its width is the page's
#: WINDOW_WIDTH_PX.
WINDOW_HEIGHT_PX = 900
CHROMIUM = "/usr/bin/chromium"


def chromium() -> str:
    """The headless Chromium executable; skips the test when there is none."""
    return require_tool("chromium", CHROMIUM, install="Debian: apt-get install -y chromium")


def chromium_image_counts(page: str, folder: Path) -> tuple[int, int]:
    """Load `page` in headless Chromium with HOOK appended: (images decoded, images)."""
    ok, total, _ = chromium_dom(page, folder)
    return ok, total


def chromium_dom(page: str, folder: Path) -> tuple[int, int, str]:
    """Load `page` in headless Chromium with HOOK appended, in a window WINDOW_WIDTH_PX wide:
    (images decoded, images, the DOM after loading; `page_height` reads the page's height from
    it)."""
    browser = chromium()
    # The page's Content-Security-Policy forbids scripts; let exactly this hook run, so the
    # images are also checked to load under the page's own policy.
    digest = base64.b64encode(hashlib.sha256(HOOK.encode()).digest()).decode()
    assert "default-src 'none';" in page
    hooked = page.replace("default-src 'none';",
                          f"default-src 'none'; script-src 'sha256-{digest}';")
    hooked = hooked.replace("</body>", f"<script>{HOOK}</script>\n</body>")
    path = folder / "report.html"
    path.write_text(hooked, encoding="utf-8")
    result = subprocess.run(
        [browser, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
         "--no-first-run", "--disable-background-networking", "--disable-component-update",
         "--disable-sync", f"--user-data-dir={folder / 'profile'}",
         f"--window-size={WINDOW_WIDTH_PX},{WINDOW_HEIGHT_PX}",
         "--virtual-time-budget=5000", "--dump-dom", path.as_uri()],
        capture_output=True, text=True, timeout=120, check=False,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert "Uncaught" not in result.stderr, result.stderr[-2000:]
    # the malicious target name arrived as text, not as a script element
    assert "alert('x')" not in result.stdout.replace(
        "&lt;script&gt;alert('x')&lt;/script&gt;", "")
    ok = re.search(r'data-images-ok="(\d+)"', result.stdout)
    total = re.search(r'data-images-total="(\d+)"', result.stdout)
    assert ok and total, f"the hook did not run; stderr: {result.stderr[-2000:]}"
    return int(ok[1]), int(total[1]), result.stdout


def page_height(dom: str) -> int:
    """The page's height (document.body.scrollHeight, CSS px) that HOOK recorded in `dom`."""
    found = re.search(r'data-page-height="(\d+)"', dom)
    assert found, "the hook did not record the page's height"
    return int(found[1])


@pytest.mark.slow
@pytest.mark.parametrize("broken", [False, True], ids=["intact", "one-corrupt-figure"])
def test_html_renders_in_headless_chromium(evil_report: dict[str, Any], tmp_path: Path,
                                           broken: bool) -> None:
    figures = all_figures()
    if broken:  # a PNG signature over garbage: the browser must fail to decode exactly that one
        figures["loss"] = figures["loss"][:8] + b"x" * 300
    page = report_html(judged(evil_report), figures)
    ok, total = chromium_image_counts(page, tmp_path)
    assert total == len(FIGURE_KEYS)
    assert ok == total - broken


@pytest.mark.parametrize("share, samples, lo, hi", [(15 / 16, 16, 0.762, 0.986),
                                                    (1.0, 16, 0.855, 1.0), (0.0, 16, 0.0, 0.145),
                                                    (0.86, 64, 0.774, 0.917)])
def test_the_yield_carries_its_wilson_interval(share, samples, lo, hi):
    """Wilson's score interval at 90 %, against values computed apart from its formula:
    a 16-draw yield of 94 % is compatible with the 86 % measured over 64 draws."""
    from aperture_fab.validation.verdicts import tolerance_verdict, yield_interval

    got = yield_interval(share, samples)
    assert got == pytest.approx((lo, hi), abs=2e-3)
    assert got[0] <= share <= got[1]
    text = tolerance_verdict({"samples": samples, "yield": share, "threshold_db": 20.0,
                              "psnr_percentiles": {"5": None, "50": None}}).text
    assert f"90 % interval of the yield {100 * lo:.0f} to {100 * hi:.0f} %" in text


def test_a_report_amended_with_the_tried_lattice_says_so_and_round_trips() -> None:
    """The design job keeps its first part over the one on its rival's lattice: run["tried"]
    and the made-part verdict say so, the other verdicts stay, and the report reads back."""
    built = build_report(**complete_inputs(), made_part=made_block(),
                         run={"part": "plate.stl", "process": "resin", "date": "2026-11-29",
                              "command": None})
    judged = replace(built, verdicts=tuple(verdicts(built)))
    tried = {"pitch_mm": [2.5, 2.5], "cells": [8, 8], "margin_db": [-1.0, -1.5]}
    amended = with_tried_lattice(judged, tried)
    assert amended.run == {**judged.run, "tried": tried}
    assert [v.topic for v in amended.verdicts] == [v.topic for v in judged.verdicts]
    changed = [(a, b) for a, b in zip(judged.verdicts, amended.verdicts, strict=True) if a != b]
    assert len(changed) == 1 and changed[0][0].topic == MADE_TOPIC
    assert changed[0][1].text == changed[0][0].text + (
        " The design job also designed on the lattice of the best regular array (8 x 8 "
        "cells of 2.5 mm; optimizer.lattice = \"rival\"): its part there reached -1.5 dB over "
        "its own best regular array, so it kept this one.")
    assert json.loads(report_json(Report.from_json(amended.as_json()))) == amended.as_json()


def test_evidence_for_an_amended_report_draws_its_page_again() -> None:
    """`Evidence.with_report`: the amended report's page from the same figures and views."""
    from aperture_fab.report.evidence import Evidence

    run = {"part": "plate.stl", "process": "resin", "date": "2026-11-29", "command": None}
    built = build_report(**complete_inputs(), made_part=made_block(), run=run)
    judged = replace(built, verdicts=tuple(verdicts(built)))
    evidence = Evidence(judged, report_html(judged, {}), b"views")
    tried = {"pitch_mm": [2.5, 2.5], "cells": [8, 8], "margin_db": None}
    again = evidence.with_report(with_tried_lattice(judged, tried))
    assert "its part there was not judged" in again.html
    assert "also designed on the lattice" not in evidence.html
    assert again.report.run == {**run, "tried": tried} and again.views_npz == b"views"
    with pytest.raises(ValueError, match="no run block"):
        with_tried_lattice(replace(judged, run=None), tried)


def test_the_made_part_margin_carries_its_interval_in_the_verdict_page_and_schema() -> None:
    """The margin's bootstrap interval (made_part "margin_interval_db") is in the made-part
    verdict and on the page; the schema checks it and accepts a report from before it."""
    built = build_report(**complete_inputs(), made_part=made_block())
    judged = replace(built, verdicts=tuple(verdicts(built)))
    made = next(v for v in judged.verdicts if v.topic == MADE_TOPIC)
    assert "+5.0 dB (95 % interval +4.2 to +5.9 dB over other made copies and eye states)" \
        in made.text
    assert "95 % interval +4.2 to +5.9 / +4.2 to +5.9 dB" in report_html(judged, {})
    report = judged.as_json()
    validate_report(report)
    older = copy.deepcopy(report)
    del older["made_part"]["margin_interval_db"]
    validate_report(older)
    assert "interval" not in next(v for v in verdicts(Report.from_json(older))
                                  if v.topic == MADE_TOPIC).text
    for broken, error in (([[5.9, 4.2]] * len(TARGETS), ValueError), ([[4.2, 5.9]], TypeError)):
        bad = copy.deepcopy(report)
        bad["made_part"]["margin_interval_db"] = broken
        with pytest.raises(error, match="margin_interval_db"):
            validate_report(bad)


@pytest.mark.parametrize(("margin", "interval", "level", "says"), [
    (0.7, [-0.1, 1.3], "warn", True),    # the default digit's part (README)
    (1.5, [0.9, 1.9], "warn", False),    # the default photo's
    (-0.3, [-0.9, 0.2], "fail", True),
    (-1.0, [-1.6, -0.4], "fail", False),
    (5.0, [4.2, 5.9], "pass", False),
])
def test_the_made_part_verdict_says_when_the_margins_interval_holds_zero(
        margin: float, interval: list[float], level: str, says: bool) -> None:
    """A margin whose bootstrap interval holds 0 is not surely on its side of the regular
    array, and the verdict says so; the interval is the smallest margin's."""
    from aperture_fab.validation.verdicts import made_verdict

    block = made_block(2)
    block["margin_db"] = [margin + 2.0, margin]
    block["margin_interval_db"] = [[interval[0] + 2.0, interval[1] + 2.0], interval]
    verdict = made_verdict(block)
    assert verdict.level == level
    assert f"interval {interval[0]:+.1f} to {interval[1]:+.1f} dB" in verdict.text
    assert ("The interval holds 0" in verdict.text) is says


@pytest.mark.parametrize(("eyebox_mm", "proposed"), [(4.0, True), (1.0, False)])
def test_the_made_part_fixes_propose_a_fitted_eyebox_and_no_tracked_display(
        eyebox_mm: float, proposed: bool) -> None:
    """A tracked display lifts the regular arrays too (it narrowed the margin on two of the
    four default targets), so the made part's fixes leave it to the eye distribution's; a
    fitted device's 1 mm eyebox is what raised the margin, proposed only when the eyebox is
    wider."""
    report = failing_report({})
    report["eye_distribution"]["distribution"]["eyebox_mm"] = [eyebox_mm, eyebox_mm]
    found = {v.topic: v.fixes for v in verdicts(Report.from_json(report))}
    assert not any("tracked" in fix for fix in found[MADE_TOPIC])
    assert any("tracked" in fix for fix in found["eye distribution"])
    assert any("eyebox_mm = [1, 1]" in fix for fix in found[MADE_TOPIC]) is proposed
