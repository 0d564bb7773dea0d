"""The structure of report.json (aperture_fab.validation.report): its schema version, the kinds of
value each block holds, and `validate_report`, which checks a report against them before it is
written or after it is read."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Literal

from aperture_fab.metrics import METRIC_KEYS
from aperture_fab.validation.variants import VARIANTS

__all__ = ["FABRICATION_KEYS", "LEVELS", "METRICS_SPEC", "PERCENTILES", "REGIMES",
           "REPORT_VARIANTS", "SCHEMA_VERSION", "Kind", "check_block", "validate_report"]


SCHEMA_VERSION = 3


# Views of the registry (aperture_fab.validation.variants) in the forms the report uses.
REPORT_VARIANTS: tuple[str, ...] = tuple(VARIANTS)


#: Verdict levels: fail (red), warn (amber), pass (green), info (a finding, no judgement).
LEVELS: tuple[str, ...] = ("fail", "warn", "pass", "info")


#: The keys of tolerance.psnr_percentiles.
PERCENTILES: tuple[str, ...] = ("5", "50", "95")


Kind = Literal["number", "number or null", "int", "bool", "bool or null", "str",
               "str or null", "dict", "list", "int pair", "int pair or null", "number pair"]


METRICS_SPEC: dict[str, Kind] = {key: "number or null" for key in METRIC_KEYS}


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


_MADE_FIGURES_SPEC: dict[str, Kind] = {"efficiency": "number", "eye_level": "number",
                                       "p10_db": "list", "p50_db": "list", "p90_db": "list"}


_RUN_SPEC: dict[str, Kind] = {"part": "str", "process": "str", "date": "str",
                              "command": "str or null"}


_PHOTOMETRY_SPEC: dict[str, Kind] = {
    "panel_luminance_cd_m2": "number", "light_efficiency": "number", "content_level": "number",
    "view_luminance_cd_m2": "number", "retinal_illuminance_td": "number",
    "assumed_pupil_mm": "number", "implied_pupil_mm": "number", "pupil_source": "str",
    "field_area_deg2": "number", "observer_age_years": "number", "adapted_eyes": "int",
    "regime": "str", "photopic_efficiency": "number or null", "min_efficiency": "number",
    "efficiency_weight": "number", "meets_min_efficiency": "bool or null",
    "photopic_eye_level": "number", "min_eye_level": "number",
    "meets_min_eye_level": "bool or null", "warnings": "list",
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


def check_block(block: Any, spec: Mapping[str, Kind], where: str) -> None:
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
    check_block(report, _TOP_SPEC, "")
    if report["schema_version"] != SCHEMA_VERSION:
        raise ValueError(f"report.schema_version = {report['schema_version']}; this code reads "
                         f"version {SCHEMA_VERSION}.")
    _get(report, "tolerance", "")
    if report.get("run") is not None:
        check_block(report["run"], _RUN_SPEC, "run")
    if report.get("photometry") is not None:
        _check_photometry(report["photometry"])
    if _get(report, "eye_distribution", "") is not None:
        _check_eye_distribution(report["eye_distribution"])
    if report.get("made_part") is not None:
        _check_made_part(report["made_part"])
    for i, verdict in enumerate(report["verdicts"]):
        check_block(verdict, _VERDICT_SPEC, f"verdicts[{i}]")
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
        check_block(block, {"per_target": "dict", "mean": "dict"}, where)
        if not block["per_target"]:
            raise ValueError(f"report.{where}.per_target is empty; give at least one target.")
        for name, values in block["per_target"].items():
            check_block(values, METRICS_SPEC, f"{where}.per_target.{name}")
        check_block(block["mean"], METRICS_SPEC, f"{where}.mean")
    check_block(report["fabrication"], _FABRICATION_SPEC, "fabrication")
    for i, violation in enumerate(report["fabrication"]["violations"]):
        check_block(violation, _VIOLATION_SPEC, f"fabrication.violations[{i}]")
    check_block(report["mesh"], _MESH_SPEC, "mesh")
    tolerance = report["tolerance"]
    if tolerance is not None:
        check_block(tolerance, _TOLERANCE_SPEC, "tolerance")
        check_block(tolerance["psnr_percentiles"], dict.fromkeys(PERCENTILES, "number or null"),
               "tolerance.psnr_percentiles")
        if not 0 <= tolerance["yield"] <= 1:
            raise ValueError(f"report tolerance.yield = {tolerance['yield']} must be a fraction "
                             "from 0 to 1.")
    check_block(report["timings_s"], dict.fromkeys(report["timings_s"], "number or null"),
                "timings_s")
    scene = report["scene"]
    check_block(scene, {"display": "dict", "plate": "dict", "eye": "dict"}, "scene")
    check_block(scene["display"], _DISPLAY_SPEC, "scene.display")
    check_block(scene["plate"], _PLATE_SPEC, "scene.plate")
    check_block(scene["eye"], _EYE_SPEC, "scene.eye")
    for i, position in enumerate(scene["eye"]["positions_mm"]):
        if not _is_pair(position, _is_number):
            raise TypeError(f"report scene.eye.positions_mm[{i}] = {position!r} must be [x, y].")
    check_block(report["versions"], dict.fromkeys(report["versions"], "str"), "versions")


def _check_made_part(block: Any) -> None:
    check_block(block, _MADE_PART_SPEC, "made_part")
    check_block(block["part"], _MADE_FIGURES_SPEC, "made_part.part")
    count = len(block["part"]["p10_db"])
    best = block["regular"].get("best")
    if best is not None:
        check_block(best, {"pitch_mm": "number", "diameter_mm": "number", **_MADE_FIGURES_SPEC},
               "made_part.regular.best")
        _check_per_target(block.get("margin_db"), count, "made_part.margin_db", "number")
        interval = block.get("margin_interval_db")
        if interval is not None:  # reports before 2026-12-07 have none
            _check_per_target(interval, count, "made_part.margin_interval_db", "list")
            for i, ends in enumerate(interval):
                if not (_is_pair(ends, _is_number) and ends[0] <= ends[1]):
                    raise ValueError(f"report made_part.margin_interval_db[{i}] = {ends!r:.80} "
                                     "must be [low, high] dB with low <= high.")


def _check_photometry(block: Any) -> None:
    check_block(block, _PHOTOMETRY_SPEC, "photometry")
    check_block(block["leakage"], _LEAKAGE_SPEC, "photometry.leakage")
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
    check_block(block, _EYE_DISTRIBUTION_SPEC, where)
    targets = block["targets"]
    if not targets or not all(isinstance(t, str) for t in targets):
        raise ValueError(f"report {where}.targets = {targets!r:.80} must list the target names.")
    count = len(targets)
    if not block["variants"]:
        raise ValueError(f"report {where}.variants is empty; give at least the part.")
    for variant, values in block["variants"].items():
        here = f"{where}.variants.{variant}"
        check_block(values, {"psnr_db": "dict", "ssim": "dict", "nominal_psnr_db": "list"}, here)
        for metric in ("psnr_db", "ssim"):
            check_block(values[metric], dict.fromkeys(_EYE_PERCENTILE_KEYS, "list"),
                   f"{here}.{metric}")
            for key in _EYE_PERCENTILE_KEYS:
                _check_per_target(values[metric][key], count, f"{here}.{metric}.{key}")
        _check_per_target(values["nominal_psnr_db"], count, f"{here}.nominal_psnr_db")
    check_block(block["eyebox_map"], {"offsets_mm": "list", "inside": "list", "psnr_db": "dict"},
           f"{where}.eyebox_map")
    for variant, values in block["eyebox_map"]["psnr_db"].items():
        _check_per_target(values, count, f"{where}.eyebox_map.psnr_db.{variant}", "list")
    for sweep, axis in (("pupil", "pupil_mm"), ("focus", "focus_diopters")):
        check_block(block[sweep], {axis: "list", "psnr_db": "dict"}, f"{where}.{sweep}")
        for variant, values in block[sweep]["psnr_db"].items():
            _check_per_target(values, count, f"{where}.{sweep}.psnr_db.{variant}", "list")
    check_block(block["thumbnails"], {"variant": "str", "offsets_mm": "list", "psnr_db": "list"},
           f"{where}.thumbnails")
    _check_per_target(block["thumbnails"]["psnr_db"], count, f"{where}.thumbnails.psnr_db",
                      "list")
