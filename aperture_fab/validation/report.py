"""The validation report's data: the report.json structure, its checks, and the views archive.

Pure functions, values in and bytes or text out; the pipeline writes the files. The figures are
in aperture_fab.validation.figures, the verdicts in aperture_fab.validation.verdicts, the HTML
page in aperture_fab.validation.report_html.

report.json (`build_report`, checked by `validate_report`, written by `report_json`):

    schema_version  2
    run             (optional) {"part": the part's file name, "process", "date" (ISO 8601 UTC),
                    "command": the command line, or null when called from Python}
    photometry      (optional) the light budget of the part as built, or null when its light
                    efficiency was not computed; see PHOTOMETRY below
    eye_distribution  the headline: the part and the baselines judged over the eye distribution
                    (aperture_fab.validation.robustness), or null when not judged
                    (validation.eye_states
                    = 0); see EYE_DISTRIBUTION below
    made_part       (optional) the part as made (process errors drawn per made copy, diffraction,
                    the material's veil) over made copies x eye states beside the best regular
                    array at least as bright: {"copies", "states", "neglected", "part":
                    {"efficiency", "p10_db", "p50_db", "p90_db", "mean_mse_psnr_db" (per target;
                    the last: the PSNR of the mean squared error, the optimizer's figure)},
                    "regular":
                    {"family", "fitted": per array lists, "best": {"pitch_mm", "diameter_mm",
                    "efficiency", "p10_db", ...} or null}, "margin_db": per target or null}
                    (aperture_fab.validation.made_part.made_part_block), or null
    verdicts        [{"topic", "level" (one of LEVELS), "text", "fixes" (what to change, most
                    effective first, none already applied; absent in older reports)}], most
                    important first; the first is topic EYE_TOPIC
                    (aperture_fab.validation.verdicts.verdicts); may be empty
    metrics         {variant: {"per_target": {name: METRICS}, "mean": METRICS}}, variants from
                    REPORT_VARIANTS (any subset, at least one); METRICS = {"mse", "psnr_db",
                    "ssim", "light_efficiency"} (see aperture_fab.metrics), each a number or null
    fabrication     {"process", "holes", "smallest_hole_diameter_mm", "smallest_web_mm" (null
                    with fewer than two holes), "violations": [{"rule", "cell" ([row, col] or
                    null), "value_mm", "limit_mm", "resolution"}]}, other keys kept
    mesh            {"watertight", "genus", "volume_mm3", "triangles"}
    tolerance       {"samples", "psnr_percentiles": {"5", "50", "95"}, "yield" (0 to 1),
                    "threshold_db"} or null when not computed
    timings_s       {stage: seconds}
    scene           `scene_dict(scene)`: display, plate, eye (focus_mm null = infinity; the eye
                    distribution's keys as in the config, its ranges resolved to [lo, hi])
    config          the resolved config (aperture_fab.config.config.to_dict)
    versions        {package: version}

EYE_DISTRIBUTION (every per-target list in the order of "targets"):

    states          how many eye states were judged (the evaluation set)
    percentiles     [10, 50, 90]: the percentiles reported (aperture_fab.optics.eyes.percentiles)
    targets         [target name]
    distribution    {"centre_mm", "eyebox_mm", "eyebox_shape", "pupil_range_mm",
                    "focus_range_diopters", "gaze_deg", "rotation_mm"}
    variants        {variant: {"psnr_db": {"p10", "p50", "p90": [per target]}, "ssim": same,
                    "nominal_psnr_db": [per target]}}, the part ("as_built") first
    eyebox_map      {"offsets_mm": n x n x [x, y] (row 0 at +y), "inside": n x n bools,
                    "psnr_db": {variant: [per target: n x n, null outside the eyebox]}} at the
                    nominal pupil and focus
    pupil           {"pupil_mm": [m], "psnr_db": {variant: [per target: [m]]}}, nominal
                    position and focus
    focus           {"focus_diopters": [m], "psnr_db": {variant: [per target: [m]]}},
                    nominal position and pupil
    thumbnails      {"variant", "offsets_mm": [[x, y]], "psnr_db": [per target: [per offset]]}

PHOTOMETRY (aperture_fab.validation.light; cd/m2, trolands, mm):

    panel_luminance_cd_m2, light_efficiency (the part as built, mean over targets, nominal
    eye), content_level (mean linear luminance of the content shown, 0 to 1),
    view_luminance_cd_m2, retinal_illuminance_td (with the assumed pupil), assumed_pupil_mm,
    implied_pupil_mm (Watson and Yellott 2012, cited in pupil_source), pupil_source,
    field_area_deg2, observer_age_years, adapted_eyes, regime (photopic, mesopic, scotopic),
    photopic_efficiency (the efficiency that keeps this panel and content photopic, or null),
    min_efficiency (optimizer.min_efficiency, 0 = no floor), efficiency_weight,
    meets_min_efficiency (null without a floor), warnings [str],
    leakage {optical_density, optical_density_note, open_share, leakage_share (light through the
    material over the light through the holes; null: unbounded), contrast_ratio (null:
    unlimited)}

Non-finite numbers (NaN, infinity) are written as null: JSON has no NaN, and a reader should see
"not computed" rather than fail to parse the file. Missing keys raise ValueError naming the key;
wrong types raise TypeError.
"""

from __future__ import annotations

import copy
import datetime
import io
import json
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from aperture_fab.metrics import METRIC_KEYS, summarize
from aperture_fab.optics.eyes import distribution_of
from aperture_fab.optics.scene import Scene
from aperture_fab.validation.variants import EYE_VARIANTS, SHOWN_VARIANTS, VARIANTS

__all__ = [
    "SCHEMA_VERSION",
    "EYE_TOPIC",
    "EYE_VARIANTS",
    "EYE_VARIANT_LABELS",
    "LEVELS",
    "Verdict",
    "eye_headline",
    "REPORT_VARIANTS",
    "VARIANT_LABELS",
    "FIGURE_KEYS",
    "PERCENTILES",
    "FABRICATION_KEYS",
    "build_report",
    "validate_report",
    "scene_dict",
    "report_json",
    "views_npz",
    "json_ready",
]

SCHEMA_VERSION = 2
# Views of the registry (aperture_fab.validation.variants) in the forms the report uses.
REPORT_VARIANTS: tuple[str, ...] = tuple(VARIANTS)
VARIANT_LABELS: dict[str, str] = {name: v.label for name, v in VARIANTS.items()}
EYE_VARIANT_LABELS: dict[str, str] = {name: str(VARIANTS[name].short) for name in EYE_VARIANTS}
#: The topic of the leading verdict: the part over the eye distribution.
EYE_TOPIC = "eye distribution"
#: Verdict levels: fail (red), warn (amber), pass (green), info (a finding, no judgement).
LEVELS: tuple[str, ...] = ("fail", "warn", "pass", "info")
#: The view panels of the "views" and "errors" figures, in the order drawn (their titles).
_SHOWN = ", ".join(VARIANTS[v].title for v in SHOWN_VARIANTS)
#: Figures report_html places, and the caption of each: the one place captions are written.
#: Each says what its figure draws (tests/test_report_page.py holds them to the drawings).
FIGURE_KEYS: dict[str, str] = {
    "eye_map": "PSNR of the part as built over the eyebox: one cell per pupil centre offset "
               "(x, y), at the nominal pupil and focus, labelled with its PSNR when the grid is "
               "small; the red line is the eyebox, grey cells lie outside it.",
    "eye_pupil": "PSNR against pupil diameter (nominal position and focus), one line per "
                 "variant judged over the eye distribution; shaded: the distribution's range of "
                 "pupils (a dashed line where it is one value).",
    "eye_focus": "PSNR of the part as built against focus in diopters (0 = infinity; nominal "
                 "position and pupil); shaded: the distribution's range of focus (a dashed line "
                 "where it is one value).",
    "eye_thumbnails": "The target, then what the eye sees through the part as built at chosen "
                      "pupil offsets (nominal pupil and focus), each scaled by its least-squares "
                      "gain and titled with its offset and the PSNR of the view as shown "
                      "(clipped to the display's range).",
    "views": "The target, then what the eye sees at the nominal eye point: " + _SHOWN + " (each "
             "view scaled by its least-squares gain), each titled with its PSNR and SSIM.",
    "errors": "Error maps |gain x view - target| per pixel (mean over colour channels) of "
              + _SHOWN + ", on one scale, each titled with its PSNR, SSIM and mean error.",
    "hole_map": "The plate as seen from the eye, mm from the axis: each hole a circle of its "
                "made diameter (colour), the outline with its alignment chamfer. Holes too small "
                "to see at this scale are drawn enlarged, to the width the title gives.",
    "loss": "The optimizer's loss per iteration (the image loss after gain, with the design's "
            "light and eye-state terms).",
    "made_front": "The part as made (star) and the regular pinhole arrays the same process "
                  "makes, judged the same way (made copies x eye states, diffraction, the "
                  "material's veil): 10th-percentile PSNR against light efficiency for a white "
                  "display. Dots: every array with elemental images (colour: pitch); dashed: "
                  "their front; squares: the rivals at the part's light with the display fitted "
                  "like the part's.",
    "eyebox": "What the eye sees through the part as built from each of the scene's eye "
              "positions (eye.positions_mm), titled with the position and its PSNR.",
    "mesh_retrace": "The independent ray trace through the written mesh against the exact model "
                    "of the holes as drawn, per view pixel at the nominal eye point (first "
                    "target): mesh re-trace - exact model, mean over colour channels, in linear "
                    "light, on a colour scale symmetric about 0; titled with the PSNR of the "
                    "trace against the model and its RMS Monte Carlo noise. Speckle at the noise "
                    "is the trace's sampling; structure would be a real difference.",
    "tolerance": "Histogram of PSNR over the tolerance samples (parts drawn with the process's "
                 "errors, the gap's and the tilt's); the red line marks the yield threshold.",
}
#: The keys of tolerance.psnr_percentiles.
PERCENTILES: tuple[str, ...] = ("5", "50", "95")
#: A views.npz key: "<variant>/<target>" or "<variant>/<target>/pos<k>".
VIEW_KEY = re.compile(r"(?P<variant>[a-z_]+)/(?P<target>[^/]+)(/pos(?P<pos>\d+))?")

# ---------------------------------------------------------------------------------------------
# Checking the report's structure

Kind = Literal["number", "number or null", "int", "bool", "bool or null", "str",
               "str or null", "dict", "list", "int pair", "int pair or null", "number pair"]

_METRICS_SPEC: dict[str, Kind] = {key: "number or null" for key in METRIC_KEYS}
_FABRICATION_SPEC: dict[str, Kind] = {
    "process": "str", "holes": "int", "smallest_hole_diameter_mm": "number or null",
    "smallest_web_mm": "number or null", "violations": "list",
}
#: The keys every report's "fabrication" block has (others are kept after them).
FABRICATION_KEYS: tuple[str, ...] = tuple(_FABRICATION_SPEC)
_VIOLATION_SPEC: dict[str, Kind] = {
    "rule": "str", "cell": "int pair or null", "value_mm": "number", "limit_mm": "number",
    "resolution": "str",
}
_MESH_SPEC: dict[str, Kind] = {
    "watertight": "bool", "genus": "int", "volume_mm3": "number", "triangles": "int",
}
_TOLERANCE_SPEC: dict[str, Kind] = {
    "samples": "int", "psnr_percentiles": "dict", "yield": "number", "threshold_db": "number",
}
_DISPLAY_SPEC: dict[str, Kind] = {"width_mm": "number", "height_mm": "number", "pixels": "int pair"}
_PLATE_SPEC: dict[str, Kind] = {
    "gap_mm": "number", "thickness_mm": "number", "pitch_mm": "number pair", "cells": "int pair",
}
_EYE_SPEC: dict[str, Kind] = {
    "pupil_mm": "number", "eye_relief_mm": "number", "focus_mm": "number or null",
    "fov_deg": "number pair", "view_pixels": "int pair", "positions_mm": "list",
}
_TOP_SPEC: dict[str, Kind] = {
    "schema_version": "int", "verdicts": "list", "metrics": "dict", "fabrication": "dict",
    "mesh": "dict", "timings_s": "dict", "scene": "dict", "config": "dict", "versions": "dict",
}
_EYE_DISTRIBUTION_SPEC: dict[str, Kind] = {
    "states": "int", "percentiles": "list", "targets": "list", "distribution": "dict",
    "variants": "dict", "eyebox_map": "dict", "pupil": "dict", "focus": "dict",
    "thumbnails": "dict",
}
_VERDICT_SPEC: dict[str, Kind] = {"topic": "str", "level": "str", "text": "str"}
_MADE_PART_SPEC: dict[str, Kind] = {"copies": "int", "states": "int", "neglected": "list",
                                    "part": "dict", "regular": "dict"}
_MADE_FIGURES_SPEC: dict[str, Kind] = {"efficiency": "number", "p10_db": "list",
                                       "p50_db": "list", "p90_db": "list"}
_RUN_SPEC: dict[str, Kind] = {"part": "str", "process": "str", "date": "str",
                              "command": "str or null"}
_PHOTOMETRY_SPEC: dict[str, Kind] = {
    "panel_luminance_cd_m2": "number", "light_efficiency": "number", "content_level": "number",
    "view_luminance_cd_m2": "number", "retinal_illuminance_td": "number",
    "assumed_pupil_mm": "number", "implied_pupil_mm": "number", "pupil_source": "str",
    "field_area_deg2": "number", "observer_age_years": "number", "adapted_eyes": "int",
    "regime": "str", "photopic_efficiency": "number or null", "min_efficiency": "number",
    "efficiency_weight": "number", "meets_min_efficiency": "bool or null", "warnings": "list",
    "leakage": "dict",
}
_LEAKAGE_SPEC: dict[str, Kind] = {
    "optical_density": "number", "optical_density_note": "str", "open_share": "number",
    "leakage_share": "number or null", "contrast_ratio": "number or null",
}
#: The light regimes photometry names (aperture_fab.optics.photometry.regime).
REGIMES: tuple[str, ...] = ("photopic", "mesopic", "scotopic")
_EYE_PERCENTILE_KEYS = ("p10", "p50", "p90")


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_pair(value: Any, item: Any) -> bool:
    return isinstance(value, (list, tuple)) and len(value) == 2 and all(map(item, value))


_KIND_CHECKS = {
    "number": _is_number,
    "number or null": lambda v: v is None or _is_number(v),
    "int": _is_int,
    "bool": lambda v: isinstance(v, bool),
    "bool or null": lambda v: v is None or isinstance(v, bool),
    "str": lambda v: isinstance(v, str),
    "str or null": lambda v: v is None or isinstance(v, str),
    "dict": lambda v: isinstance(v, Mapping),
    "list": lambda v: isinstance(v, (list, tuple)),
    "int pair": lambda v: _is_pair(v, _is_int),
    "int pair or null": lambda v: v is None or _is_pair(v, _is_int),
    "number pair": lambda v: _is_pair(v, _is_number),
}


def _path(where: str, key: str) -> str:
    return f"{where}.{key}" if where else key


def _get(block: Mapping[str, Any], key: str, where: str) -> Any:
    if key not in block:
        raise ValueError(f"report is missing {_path(where, key)}; build it with build_report().")
    return block[key]


def _check(block: Any, spec: Mapping[str, Kind], where: str) -> None:
    """Each key of spec is present in block with a value of its kind (extra keys are kept)."""
    if not isinstance(block, Mapping):
        raise TypeError(f"report {where} = {block!r:.80} must be a dict.")
    for key, kind in spec.items():
        value = _get(block, key, where)
        if not _KIND_CHECKS[kind](value):
            raise TypeError(f"report {_path(where, key)} = {value!r:.80} must be a {kind}.")


def validate_report(report: Mapping[str, Any]) -> None:
    """Raise ValueError (a missing key, named with its path) or TypeError unless `report` has
    the structure described in this module's docstring."""
    if not isinstance(report, Mapping):
        raise TypeError(f"report must be a dict, got {type(report).__name__}.")
    _check(report, _TOP_SPEC, "")
    if report["schema_version"] != SCHEMA_VERSION:
        raise ValueError(f"report.schema_version = {report['schema_version']}; this code reads "
                         f"version {SCHEMA_VERSION}.")
    _get(report, "tolerance", "")
    if report.get("run") is not None:
        _check(report["run"], _RUN_SPEC, "run")
    if report.get("photometry") is not None:
        _check_photometry(report["photometry"])
    if _get(report, "eye_distribution", "") is not None:
        _check_eye_distribution(report["eye_distribution"])
    if report.get("made_part") is not None:
        _check_made_part(report["made_part"])
    for i, verdict in enumerate(report["verdicts"]):
        _check(verdict, _VERDICT_SPEC, f"verdicts[{i}]")
        if verdict["level"] not in LEVELS:
            raise ValueError(f"report verdicts[{i}].level = {verdict['level']!r}; allowed: "
                             f"{', '.join(LEVELS)}.")
        fixes = verdict.get("fixes", [])
        if not (isinstance(fixes, list) and all(isinstance(f, str) for f in fixes)):
            raise TypeError(f"report verdicts[{i}].fixes = {fixes!r:.80} must be a list of "
                            "strings.")
    if not report["metrics"]:
        raise ValueError("report.metrics is empty; give at least one variant.")
    for variant, block in report["metrics"].items():
        where = f"metrics.{variant}"
        if variant not in REPORT_VARIANTS:
            raise ValueError(f"report.{where} is not a known variant; allowed: {REPORT_VARIANTS}.")
        _check(block, {"per_target": "dict", "mean": "dict"}, where)
        if not block["per_target"]:
            raise ValueError(f"report.{where}.per_target is empty; give at least one target.")
        for name, values in block["per_target"].items():
            _check(values, _METRICS_SPEC, f"{where}.per_target.{name}")
        _check(block["mean"], _METRICS_SPEC, f"{where}.mean")
    _check(report["fabrication"], _FABRICATION_SPEC, "fabrication")
    for i, violation in enumerate(report["fabrication"]["violations"]):
        _check(violation, _VIOLATION_SPEC, f"fabrication.violations[{i}]")
    _check(report["mesh"], _MESH_SPEC, "mesh")
    tolerance = report["tolerance"]
    if tolerance is not None:
        _check(tolerance, _TOLERANCE_SPEC, "tolerance")
        _check(tolerance["psnr_percentiles"], dict.fromkeys(PERCENTILES, "number or null"),
               "tolerance.psnr_percentiles")
        if not 0 <= tolerance["yield"] <= 1:
            raise ValueError(f"report tolerance.yield = {tolerance['yield']} must be a fraction "
                             "from 0 to 1.")
    _check(report["timings_s"], dict.fromkeys(report["timings_s"], "number or null"), "timings_s")
    scene = report["scene"]
    _check(scene, {"display": "dict", "plate": "dict", "eye": "dict"}, "scene")
    _check(scene["display"], _DISPLAY_SPEC, "scene.display")
    _check(scene["plate"], _PLATE_SPEC, "scene.plate")
    _check(scene["eye"], _EYE_SPEC, "scene.eye")
    for i, position in enumerate(scene["eye"]["positions_mm"]):
        if not _is_pair(position, _is_number):
            raise TypeError(f"report scene.eye.positions_mm[{i}] = {position!r} must be [x, y].")
    _check(report["versions"], dict.fromkeys(report["versions"], "str"), "versions")


def _check_made_part(block: Any) -> None:
    _check(block, _MADE_PART_SPEC, "made_part")
    _check(block["part"], _MADE_FIGURES_SPEC, "made_part.part")
    count = len(block["part"]["p10_db"])
    best = block["regular"].get("best")
    if best is not None:
        _check(best, {"pitch_mm": "number", "diameter_mm": "number", **_MADE_FIGURES_SPEC},
               "made_part.regular.best")
        _check_per_target(block.get("margin_db"), count, "made_part.margin_db", "number")


def _check_photometry(block: Any) -> None:
    _check(block, _PHOTOMETRY_SPEC, "photometry")
    _check(block["leakage"], _LEAKAGE_SPEC, "photometry.leakage")
    if block["regime"] not in REGIMES:
        raise ValueError(f"report photometry.regime = {block['regime']!r}; allowed: "
                         f"{', '.join(REGIMES)}.")
    if not all(isinstance(w, str) for w in block["warnings"]):
        raise TypeError(f"report photometry.warnings = {block['warnings']!r:.80} must be a list "
                        "of strings.")


def _check_per_target(values: Any, count: int, where: str, item: str = "number or null"
                      ) -> None:
    """A list of one entry per target, each an `item` (or, for item "list", a list)."""
    if not isinstance(values, (list, tuple)) or len(values) != count:
        raise TypeError(f"report {where} = {values!r:.80} must be a list of {count} values, one "
                        "per target.")
    for i, value in enumerate(values):
        if not _KIND_CHECKS[item](value):
            raise TypeError(f"report {where}[{i}] = {value!r:.80} must be a {item}.")


def _check_eye_distribution(block: Any) -> None:
    where = "eye_distribution"
    _check(block, _EYE_DISTRIBUTION_SPEC, where)
    targets = block["targets"]
    if not targets or not all(isinstance(t, str) for t in targets):
        raise ValueError(f"report {where}.targets = {targets!r:.80} must list the target names.")
    count = len(targets)
    if not block["variants"]:
        raise ValueError(f"report {where}.variants is empty; give at least the part.")
    for variant, values in block["variants"].items():
        here = f"{where}.variants.{variant}"
        _check(values, {"psnr_db": "dict", "ssim": "dict", "nominal_psnr_db": "list"}, here)
        for metric in ("psnr_db", "ssim"):
            _check(values[metric], dict.fromkeys(_EYE_PERCENTILE_KEYS, "list"),
                   f"{here}.{metric}")
            for key in _EYE_PERCENTILE_KEYS:
                _check_per_target(values[metric][key], count, f"{here}.{metric}.{key}")
        _check_per_target(values["nominal_psnr_db"], count, f"{here}.nominal_psnr_db")
    _check(block["eyebox_map"], {"offsets_mm": "list", "inside": "list", "psnr_db": "dict"},
           f"{where}.eyebox_map")
    for variant, values in block["eyebox_map"]["psnr_db"].items():
        _check_per_target(values, count, f"{where}.eyebox_map.psnr_db.{variant}", "list")
    for sweep, axis in (("pupil", "pupil_mm"), ("focus", "focus_diopters")):
        _check(block[sweep], {axis: "list", "psnr_db": "dict"}, f"{where}.{sweep}")
        for variant, values in block[sweep]["psnr_db"].items():
            _check_per_target(values, count, f"{where}.{sweep}.psnr_db.{variant}", "list")
    _check(block["thumbnails"], {"variant": "str", "offsets_mm": "list", "psnr_db": "list"},
           f"{where}.thumbnails")
    _check_per_target(block["thumbnails"]["psnr_db"], count, f"{where}.thumbnails.psnr_db",
                      "list")


# ---------------------------------------------------------------------------------------------
# Verdicts


@dataclass(frozen=True)
class Verdict:
    """One finding of the report: its topic, level (one of LEVELS), plain-language text (what
    was found and why it matters) and the fixes it proposes, most effective first (each one
    change, none already applied; aperture_fab.validation.verdicts.recommended_fix picks the
    page's recommended one)."""

    topic: str
    level: str
    text: str
    fixes: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.level not in LEVELS:
            raise ValueError(f"verdict level {self.level!r}; allowed: {', '.join(LEVELS)}.")

    def as_dict(self) -> dict[str, Any]:
        return {"topic": self.topic, "level": self.level, "text": self.text,
                "fixes": list(self.fixes)}


def eye_headline(report: Mapping[str, Any]) -> dict[str, Any] | None:
    """The eye distribution's numbers without the maps and sweeps, with its verdict: for
    design.json and the terminal. None when the report did not judge the eye distribution."""
    block = report.get("eye_distribution")
    if block is None:
        return None
    verdict = next((dict(v) for v in report.get("verdicts", ()) if v["topic"] == EYE_TOPIC),
                   None)
    keys = ("states", "percentiles", "targets", "distribution", "variants")
    return {**{k: copy.deepcopy(block[k]) for k in keys}, "verdict": verdict}


# ---------------------------------------------------------------------------------------------
# Building and writing the report


def json_ready(value: Any, where: str = "report") -> Any:
    """JSON-ready copy: numpy values to Python, tuples to lists, NaN and infinities to None."""
    if isinstance(value, Mapping):
        return {str(k): json_ready(v, f"{where}.{k}") for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return json_ready(value.tolist(), where)
    if isinstance(value, (list, tuple)):
        return [json_ready(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, np.generic):
        return json_ready(value.item(), where)
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, (datetime.date, datetime.time)):  # TOML dates in config extras
        return value.isoformat()
    raise TypeError(f"{where} = {value!r:.80} ({type(value).__name__}) cannot go into JSON.")


def scene_dict(scene: Scene) -> dict[str, Any]:
    """The report's "scene" block from the dataclasses (focus_mm None means infinity)."""
    display, plate, eye = scene.display, scene.plate, scene.eye
    distribution = distribution_of(eye)
    return {
        "display": {"width_mm": display.width_mm, "height_mm": display.height_mm,
                    "pixels": list(display.pixels)},
        "plate": {"gap_mm": plate.gap_mm, "thickness_mm": plate.thickness_mm,
                  "pitch_mm": list(plate.pitch_mm), "cells": list(plate.cells),
                  "hole_axis": plate.hole_axis},
        "eye": {"pupil_mm": eye.pupil_mm, "eye_relief_mm": eye.eye_relief_mm,
                "focus_mm": eye.focus_mm, "fov_deg": list(eye.fov_deg),
                "view_pixels": list(eye.view_pixels),
                "positions_mm": [list(p) for p in eye.positions_mm],
                "weights": list(eye.weights),
                # The eye distribution, ranges resolved ("nominal" is [nominal, nominal]).
                "eyebox_mm": list(eye.eyebox_mm), "eyebox_shape": eye.eyebox_shape,
                "pupil_range_mm": list(distribution.pupil_range_mm),
                "focus_range_diopters": list(distribution.focus_range_diopters),
                "gaze_deg": eye.gaze_deg, "rotation_mm": eye.rotation_mm},
    }


def build_report(
    *,
    metrics: Mapping[str, Mapping[str, Mapping[str, float]]],
    fabrication: Mapping[str, Any],
    mesh: Mapping[str, Any],
    tolerance: Mapping[str, Any] | None,
    timings_s: Mapping[str, float],
    scene: Mapping[str, Any],
    config: Mapping[str, Any],
    versions: Mapping[str, str],
    eye_distribution: Mapping[str, Any] | None = None,
    verdicts: Sequence[Verdict | Mapping[str, Any]] = (),
    run: Mapping[str, Any] | None = None,
    photometry: Mapping[str, Any] | None = None,
    made_part: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The report.json structure, checked (see the module docstring).

    eye_distribution: the EYE_DISTRIBUTION block (aperture_fab.validation.evidence builds it from
        robustness.EyeQuality), or None when the eye distribution was not judged.
    verdicts: Verdicts (or their dicts), most important first; usually added afterwards, since
        aperture_fab.validation.verdicts.verdicts reads the report.
    run: the RUN block (part file, process, date, command), or None to leave it out.
    photometry: the PHOTOMETRY block (aperture_fab.validation.light.photometry_block), or None.
    made_part: the MADE_PART block (aperture_fab.validation.made_part.made_part_block), or None.

    metrics: {variant: {target name: metrics dict (aperture_fab.metrics.metrics)}}; each
        variant's mean over targets is added, and variants are listed in REPORT_VARIANTS order.
    """
    unknown = [v for v in metrics if v not in REPORT_VARIANTS]
    if unknown:
        raise ValueError(f"metrics has unknown variants {unknown}; allowed: {REPORT_VARIANTS}.")
    blocks: dict[str, Any] = {}
    for variant in (v for v in REPORT_VARIANTS if v in metrics):
        per_target = json_ready(metrics[variant], f"metrics.{variant}")
        for name, values in per_target.items():
            _check(values, _METRICS_SPEC, f"metrics.{variant}.per_target.{name}")
        # summarize sees NaN for a metric that is null (not computed), so its mean is null too
        with_nan = [{k: math.nan if v is None else v for k, v in values.items()}
                    for values in per_target.values()]
        mean = summarize(with_nan) if with_nan else {}
        blocks[variant] = {"per_target": per_target, "mean": mean}
    report = json_ready({
        "schema_version": SCHEMA_VERSION,
        **({} if run is None else {"run": run}),
        "eye_distribution": eye_distribution,
        **({} if made_part is None else {"made_part": made_part}),
        "verdicts": [v.as_dict() if isinstance(v, Verdict) else v for v in verdicts],
        "photometry": photometry,
        "metrics": blocks,
        "fabrication": fabrication,
        "mesh": mesh,
        "tolerance": tolerance,
        "timings_s": timings_s,
        "scene": scene,
        "config": config,
        "versions": versions,
    })
    validate_report(report)
    return dict(report)


def report_json(report: Mapping[str, Any]) -> str:
    """report.json text: checked, indent 2, NaN and infinities as null (strict JSON)."""
    plain = json_ready(report)
    validate_report(plain)
    return json.dumps(plain, indent=2, allow_nan=False) + "\n"


def views_npz(views: Mapping[str, np.ndarray]) -> bytes:
    """A compressed .npz of views in linear light, keyed "<variant>/<target>" or
    "<variant>/<target>/pos<k>" (variant from REPORT_VARIANTS, k the eyebox position)."""
    arrays: dict[str, np.ndarray] = {}
    for key, view in views.items():
        match = VIEW_KEY.fullmatch(key)
        if match is None or match["variant"] not in REPORT_VARIANTS:
            raise ValueError(
                f"views key {key!r} must be '<variant>/<target>' or '<variant>/<target>/pos<k>' "
                f"with a variant from {REPORT_VARIANTS}."
            )
        array = np.asarray(view)
        if not np.issubdtype(array.dtype, np.floating) or not np.all(np.isfinite(array)):
            raise ValueError(f"views[{key!r}] must be a finite float array of linear light, "
                             f"got dtype {array.dtype}.")
        arrays[key] = array
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)  # type: ignore[arg-type]
    return buffer.getvalue()
