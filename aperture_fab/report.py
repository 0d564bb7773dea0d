"""The validation report: report.json for machines, report.html (with PNG figures) for people.

Pure functions, values in and bytes or text out; the pipeline writes the files.

report.json (`build_report`, checked by `validate_report`, written by `report_json`):

    schema_version  1
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
    scene           `scene_dict(scene)`: display, plate, eye (focus_mm null = infinity)
    config          the resolved config (aperture_fab.config.to_dict)
    versions        {package: version}

Non-finite numbers (NaN, infinity) are written as null: JSON has no NaN, and a reader should see
"not computed" rather than fail to parse the file. Missing keys raise ValueError naming the key;
wrong types raise TypeError.
"""

from __future__ import annotations

import base64
import datetime
import hashlib
import html
import io
import json
import math
import re
from collections.abc import Mapping
from typing import Any, Literal

import numpy as np

from aperture_fab.images import linear_to_srgb
from aperture_fab.metrics import METRIC_KEYS, gain, summarize
from aperture_fab.scene import Scene

__all__ = [
    "SCHEMA_VERSION",
    "REPORT_VARIANTS",
    "FIGURE_KEYS",
    "SECTION_TITLES",
    "build_report",
    "validate_report",
    "scene_dict",
    "report_json",
    "views_npz",
    "figure_views",
    "figure_hole_map",
    "figure_loss",
    "figure_histogram",
    "verdicts",
    "report_html",
]

SCHEMA_VERSION = 1
REPORT_VARIANTS: tuple[str, ...] = (
    "open", "regular_pinholes", "random", "optimized", "quantized", "as_built", "as_built_mesh",
    "as_built_diffraction",
)
#: What each variant is, in words, for tables and verdicts.
VARIANT_LABELS: dict[str, str] = {
    "open": "open display (no plate)",
    "regular_pinholes": "regular pinhole array",
    "random": "random mask (the dissertation's start)",
    "optimized": "optimized design",
    "quantized": "after quantization",
    "as_built": "as built (real holes, real thickness)",
    "as_built_mesh": "as built, traced through the written mesh",
    "as_built_diffraction": "as built, with diffraction",
}
#: Figures report_html places, and the caption of each.
FIGURE_KEYS: dict[str, str] = {
    "views": "The target and what the eye sees through the as-built part, beside each baseline "
             "(each view scaled by its least-squares gain).",
    "hole_map": "Hole diameter of each cell of the plate.",
    "display": "The content shown on the display.",
    "loss": "Optimization loss per iteration.",
    "eyebox": "The as-built view at each eye position across the eyebox.",
    "tolerance": "PSNR over manufacturing-tolerance samples; the line marks the threshold.",
}
#: The page's sections, top to bottom: (id, heading).
SECTION_TITLES: tuple[tuple[str, str], ...] = (
    ("summary", "Summary"),
    ("views", "What the eye sees"),
    ("metrics", "Image quality by variant"),
    ("plate", "Plate and hole sizes"),
    ("display", "Display content"),
    ("loss", "Optimization"),
    ("eyebox", "Across the eyebox"),
    ("tolerance", "Manufacturing tolerance"),
    ("fabrication", "Fabrication checks"),
    ("mesh", "Mesh checks"),
    ("timings", "Timings"),
    ("scene", "Scene"),
    ("config", "Configuration and versions"),
)
NOT_COMPUTED = "not computed"

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
FIGURE_DPI = 100
PANEL_INCHES = 2.2
MAX_PANELS_PER_ROW = 6
UM_PER_MM = 1000.0
PERCENTILES: tuple[str, ...] = ("5", "50", "95")
#: Headline variant for verdicts: the first of these that the report holds.
HEADLINE_VARIANTS: tuple[tuple[str, str], ...] = (
    ("as_built", "As built"), ("quantized", "After quantization"), ("optimized", "As optimized"),
)
VIEW_KEY = re.compile(r"(?P<variant>[a-z_]+)/(?P<target>[^/]+)(/pos(?P<pos>\d+))?")

# ---------------------------------------------------------------------------------------------
# Checking the report's structure

Kind = Literal["number", "number or null", "int", "bool", "str", "dict", "list", "int pair",
               "int pair or null", "number pair"]

_METRICS_SPEC: dict[str, Kind] = {key: "number or null" for key in METRIC_KEYS}
_FABRICATION_SPEC: dict[str, Kind] = {
    "process": "str", "holes": "int", "smallest_hole_diameter_mm": "number or null",
    "smallest_web_mm": "number or null", "violations": "list",
}
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
    "schema_version": "int", "metrics": "dict", "fabrication": "dict", "mesh": "dict",
    "timings_s": "dict", "scene": "dict", "config": "dict", "versions": "dict",
}


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
    "str": lambda v: isinstance(v, str),
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


# ---------------------------------------------------------------------------------------------
# Building and writing the report


def _plain(value: Any, where: str = "report") -> Any:
    """JSON-ready copy: numpy values to Python, tuples to lists, NaN and infinities to None."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v, f"{where}.{k}") for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return _plain(value.tolist(), where)
    if isinstance(value, (list, tuple)):
        return [_plain(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, np.generic):
        return _plain(value.item(), where)
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
                "weights": list(eye.weights)},
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
) -> dict[str, Any]:
    """The report.json structure, checked (see the module docstring).

    metrics: {variant: {target name: metrics dict (aperture_fab.metrics.metrics)}}; each
        variant's mean over targets is added, and variants are listed in REPORT_VARIANTS order.
    """
    unknown = [v for v in metrics if v not in REPORT_VARIANTS]
    if unknown:
        raise ValueError(f"metrics has unknown variants {unknown}; allowed: {REPORT_VARIANTS}.")
    blocks: dict[str, Any] = {}
    for variant in (v for v in REPORT_VARIANTS if v in metrics):
        per_target = _plain(metrics[variant], f"metrics.{variant}")
        for name, values in per_target.items():
            _check(values, _METRICS_SPEC, f"metrics.{variant}.per_target.{name}")
        # summarize sees NaN for a metric that is null (not computed), so its mean is null too
        with_nan = [{k: math.nan if v is None else v for k, v in values.items()}
                    for values in per_target.values()]
        mean = summarize(with_nan) if with_nan else {}
        blocks[variant] = {"per_target": per_target, "mean": mean}
    report = _plain({
        "schema_version": SCHEMA_VERSION,
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
    plain = _plain(report)
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


# ---------------------------------------------------------------------------------------------
# Figures (PNG bytes)


def _figure(width_in: float, height_in: float) -> Any:
    """A matplotlib Figure on the Agg canvas; no pyplot, so no global figure state."""
    try:
        from matplotlib.figure import Figure
    except ImportError as err:
        raise ImportError("report figures need matplotlib: pip install matplotlib") from err
    return Figure(figsize=(width_in, height_in), dpi=FIGURE_DPI, layout="constrained")


def _png(fig: Any) -> bytes:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    return buffer.getvalue()


def _as_rgb(image: np.ndarray, name: str) -> np.ndarray:
    """(C, ny, nx) or (ny, nx) linear image to (ny, nx, 3) float64."""
    array = np.asarray(image, dtype=np.float64)
    if array.ndim == 2:
        array = array[None]
    if array.ndim != 3 or array.shape[0] not in (1, 3) or min(array.shape) == 0:
        raise ValueError(f"{name} has shape {array.shape}; expected (C, ny, nx) with C = 1 or 3, "
                         "or (ny, nx).")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} holds NaN or infinite values.")
    return np.repeat(array, 3 // array.shape[0], axis=0).transpose(1, 2, 0)


def figure_views(rows: list[tuple[str, np.ndarray]], title: str, *,
                 gain_to_first: bool = True) -> bytes:
    """PNG of labelled images side by side (wrapping after MAX_PANELS_PER_ROW), in sRGB.

    rows: (label, image) pairs, images (C, ny, nx) or (ny, nx) in linear light; the first is
        usually the target.
    gain_to_first: scale each later image by its least-squares gain onto the first (the eye
        cannot see more light than the holes pass: compare shapes, not levels); images must then
        share the first one's shape. Images are clipped to [0, 1] for display.
    """
    if not rows:
        raise ValueError("figure_views got no images; give (label, image) pairs.")
    images = [_as_rgb(image, f"image {label!r}") for label, image in rows]
    if gain_to_first:
        for i, image in enumerate(images[1:], start=1):
            if image.shape != images[0].shape:
                raise ValueError(f"image {rows[i][0]!r} has shape {image.shape[:2]} but the first "
                                 f"has {images[0].shape[:2]}; gain_to_first needs equal shapes.")
            images[i] = image * gain(image, images[0])
    cols = min(len(rows), MAX_PANELS_PER_ROW)
    lines = math.ceil(len(rows) / cols)
    fig = _figure(cols * PANEL_INCHES, lines * PANEL_INCHES + 0.4)
    fig.suptitle(title)
    for i, ((label, _), image) in enumerate(zip(rows, images, strict=True)):
        ax = fig.add_subplot(lines, cols, i + 1)
        ax.imshow(linear_to_srgb(np.clip(image, 0.0, 1.0)), interpolation="nearest")
        ax.set_title(label, fontsize=9)
        ax.set_axis_off()
    return _png(fig)


def figure_hole_map(values: np.ndarray, pitch_mm: tuple[float, float], *,
                    kind: Literal["radius_mm", "open_fraction"] = "radius_mm") -> bytes:
    """PNG colour map of each cell's hole diameter (um), closed cells grey, axes in mm.

    values: (rows, cols) hole radii in mm, or open-area fractions a = pi r^2 / (px py).
    pitch_mm: (px, py) cell pitch.
    """
    array = np.asarray(values, dtype=np.float64)
    if array.ndim != 2 or min(array.shape) == 0 or not np.all(np.isfinite(array)):
        raise ValueError(f"hole map values have shape {array.shape}; expected finite "
                         "(rows, cols).")
    if array.min() < 0:
        raise ValueError(f"hole map {kind} values go down to {array.min():g}; allowed: >= 0.")
    px, py = pitch_mm
    radii = array if kind == "radius_mm" else np.sqrt(array * px * py / math.pi)
    diameter_um = np.ma.masked_less_equal(2 * radii * UM_PER_MM, 0.0)
    rows, cols = array.shape
    half_w, half_h = cols * px / 2, rows * py / 2
    import matplotlib as mpl  # _figure has checked that matplotlib is there

    fig = _figure(5.0, 4.2)
    cmap = mpl.colormaps["viridis"].with_extremes(bad="0.8")
    ax = fig.add_subplot()
    shown = ax.imshow(diameter_um, cmap=cmap, interpolation="nearest",
                      extent=(-half_w, half_w, -half_h, half_h))
    fig.colorbar(shown, ax=ax, label="hole diameter (µm)")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(f"{int(np.count_nonzero(radii > 0))} holes (grey: closed)")
    return _png(fig)


def figure_loss(history: np.ndarray) -> bytes:
    """PNG of the loss per iteration (log scale when every value is positive)."""
    values = np.asarray(history, dtype=np.float64)
    if values.ndim != 1 or values.size == 0 or not np.all(np.isfinite(values)):
        raise ValueError(f"loss history has shape {values.shape}; expected finite (N,), N >= 1.")
    fig = _figure(5.0, 3.2)
    ax = fig.add_subplot()
    ax.plot(np.arange(1, values.size + 1), values)
    if values.min() > 0:
        ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss (MSE after gain)")
    ax.grid(True, which="both", alpha=0.3)
    return _png(fig)


def figure_histogram(values: np.ndarray, threshold: float | None) -> bytes:
    """PNG histogram of PSNR (dB) over tolerance samples, with the yield threshold marked."""
    data = np.asarray(values, dtype=np.float64)
    if data.ndim != 1 or data.size == 0 or not np.all(np.isfinite(data)):
        raise ValueError(f"histogram values have shape {data.shape}; expected finite (N,), "
                         "N >= 1.")
    fig = _figure(5.0, 3.2)
    ax = fig.add_subplot()
    ax.hist(data, bins="auto", color="0.4")
    if threshold is not None:
        ax.axvline(threshold, color="tab:red", label=f"threshold {threshold:g} dB")
        ax.legend()
    ax.set_xlabel("PSNR as built (dB)")
    ax.set_ylabel("samples")
    return _png(fig)


# ---------------------------------------------------------------------------------------------
# Verdicts in words


def _mean(report: Mapping[str, Any], variant: str, key: str = "psnr_db") -> float | None:
    block = report["metrics"].get(variant)
    value = None if block is None else block["mean"].get(key)
    return None if value is None else float(value)


def _compare(difference: float, what: str) -> str:
    return f"{abs(difference):.1f} dB {'better' if difference >= 0 else 'worse'} than {what}"


def verdicts(report: Mapping[str, Any], diffraction_blur_px: float | None = None,
             diffraction_hole_mm: float | None = None) -> list[str]:
    """Plain-language findings, most important first.

    diffraction_blur_px: diffraction blur of the holes named by diffraction_hole_mm, in view
        pixels (None: not computed, no line).
    diffraction_hole_mm: the hole diameter that blur is for; None takes the smallest hole.
    """
    lines: list[str] = []
    head = next(((v, words) for v, words in HEADLINE_VARIANTS
                 if _mean(report, v) is not None), None)
    if head is not None:
        variant, words = head
        psnr = _mean(report, variant)
        assert psnr is not None
        ssim = _mean(report, variant, "ssim")
        text = f"{words}, the view scores {psnr:.1f} dB PSNR"
        text += "" if ssim is None else f" (SSIM {ssim:.2f})"
        baselines = [(_mean(report, "open"), "the open display"),
                     (_mean(report, "regular_pinholes"), "a regular pinhole array")]
        compared = [_compare(psnr - value, what) for value, what in baselines if value is not None]
        lines.append(text + (", " + " and ".join(compared) if compared else "") + ".")
        optimized = _mean(report, "optimized")
        if variant != "optimized" and optimized is not None:
            cause = "Quantization and fabrication" if variant == "as_built" else "Quantization"
            cost = optimized - psnr
            lines.append(f"{cause} cost {cost:.1f} dB." if cost >= 0 else
                         f"{cause} cost nothing: the view is {-cost:.1f} dB better than the "
                         "optimized design's.")
        efficiency = _mean(report, variant, "light_efficiency")
        if efficiency is not None:
            lines.append(f"The eye sees {100 * efficiency:.0f} % of the light of the open display.")
    built, traced = _mean(report, "as_built"), _mean(report, "as_built_mesh")
    if built is not None and traced is not None:
        lines.append(f"Traced through the written mesh, the view scores {traced:.1f} dB "
                     f"({traced - built:+.1f} dB from the hole layout's trace).")
    diffracted = _mean(report, "as_built_diffraction")
    if built is not None and diffracted is not None:
        lines.append(f"With diffraction, the as-built view scores {diffracted:.1f} dB "
                     f"({diffracted - built:+.1f} dB from the geometric trace).")
    hole_mm = diffraction_hole_mm
    if hole_mm is None:
        hole_mm = report["fabrication"].get("smallest_hole_diameter_mm")
    if diffraction_blur_px is not None and hole_mm is not None:
        lines.append(f"Holes of {hole_mm:.3f} mm: diffraction blurs them by about "
                     f"{diffraction_blur_px:.1f} view pixels.")
    tolerance = report["tolerance"]
    if tolerance is not None:
        text = (f"Yield at {tolerance['threshold_db']:g} dB over {tolerance['samples']} tolerance "
                f"samples: {100 * tolerance['yield']:.0f} %.")
        low, median = tolerance["psnr_percentiles"]["5"], tolerance["psnr_percentiles"]["50"]
        if low is not None and median is not None:
            text += f" Median {median:.1f} dB; 1 part in 20 scores below {low:.1f} dB."
        lines.append(text)
    fabrication = report["fabrication"]
    violations = fabrication["violations"]
    if violations:
        counts: dict[str, int] = {}
        for violation in violations:
            counts[violation["rule"]] = counts.get(violation["rule"], 0) + 1
        rules = ", ".join(f"{rule} x{n}" for rule, n in counts.items())
        lines.append(f"{len(violations)} fabrication rule violations of the "
                     f"{fabrication['process']} process were resolved ({rules}); see Fabrication "
                     "checks.")
    else:
        lines.append(f"The {fabrication['holes']} holes meet every rule of the "
                     f"{fabrication['process']} process.")
    mesh = report["mesh"]
    if mesh["watertight"]:
        per_hole = " (one per hole)" if mesh["genus"] == fabrication["holes"] else ""
        lines.append(f"The mesh is watertight, genus {mesh['genus']}{per_hole}, "
                     f"{mesh['triangles']} triangles.")
    else:
        lines.append("The mesh is NOT watertight: do not print it; please report this design.")
    return lines


# ---------------------------------------------------------------------------------------------
# The HTML page

#: Everything the page needs is inline: no script, nothing fetched; images only from data: URIs.
CSP = "default-src 'none'; img-src data:; style-src 'unsafe-inline'"
CSS = """
body { font: 15px/1.45 system-ui, sans-serif; color: #222; margin: 0; background: #fafafa; }
main { max-width: 60rem; margin: 0 auto; padding: 1rem 1.5rem 3rem; background: #fff; }
h1 { font-size: 1.6rem; } h2 { border-bottom: 1px solid #ccc; margin-top: 2.2rem; }
nav a { margin-right: 0.8rem; white-space: nowrap; }
table { border-collapse: collapse; margin: 0.6rem 0; }
th, td { border: 1px solid #ddd; padding: 0.2rem 0.6rem; text-align: left; }
td.n { text-align: right; font-variant-numeric: tabular-nums; }
figure { margin: 0.6rem 0; } figure img { max-width: 100%; height: auto; }
figcaption, .muted { color: #666; font-size: 0.9rem; }
ul.verdicts li { margin: 0.3rem 0; } pre { background: #f4f4f4; padding: 0.6rem; overflow: auto; }
.bad { color: #b00; font-weight: bold; }
"""


def _e(value: Any) -> str:
    return html.escape(str(value), quote=True)


def _num(value: Any, digits: int = 3, scale: float = 1.0) -> str:
    if value is None:
        return NOT_COMPUTED
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return _e(value)
    return f"{value * scale:.{digits}f}" if isinstance(value, float) else str(value)


def _table(header: list[str], rows: list[list[str]], numeric: tuple[int, ...] = ()) -> str:
    """An HTML table; cells are already escaped text; the `numeric` columns align right."""
    out = ["<table><tr>", *(f"<th>{_e(h)}</th>" for h in header), "</tr>"]
    for row in rows:
        out.append("<tr>")
        out.extend(f'<td class="n">{c}</td>' if i in numeric else f"<td>{c}</td>"
                   for i, c in enumerate(row))
        out.append("</tr>")
    out.append("</table>")
    return "".join(out)


def _value(value: Any) -> str:
    """A value for a key/value table, escaped: yes/no, 6 significant digits, JSON for lists."""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, (list, tuple, Mapping)):
        return _e(json.dumps(value))
    return NOT_COMPUTED if value is None else _e(value)


def _pairs(block: Mapping[str, Any]) -> str:
    """A key/value table of a flat block."""
    return _table(["quantity", "value"], [[_e(k), _value(v)] for k, v in block.items()])


def _img(figures: Mapping[str, bytes], key: str) -> str:
    data = figures.get(key)
    if data is None:
        return f'<p class="muted">Figure {NOT_COMPUTED}.</p>'
    encoded = base64.b64encode(data).decode("ascii")
    caption = FIGURE_KEYS[key]
    return (f'<figure><img alt="{_e(caption)}" src="data:image/png;base64,{encoded}">'
            f"<figcaption>{_e(caption)}</figcaption></figure>")


def _metrics_html(metrics: Mapping[str, Any]) -> str:
    def cells(values: Mapping[str, Any]) -> list[str]:
        return [_num(values["psnr_db"], 2), _num(values["ssim"], 3),
                _num(values["light_efficiency"], 1, 100.0), _num(values["mse"], 6)]

    header = ["PSNR (dB)", "SSIM", "light efficiency (%)", "MSE"]
    numeric = (1, 2, 3, 4)
    out = ["<h3>Mean over targets</h3>",
           _table(["variant", *header],
                  [[_e(VARIANT_LABELS[v]), *cells(b["mean"])] for v, b in metrics.items()],
                  numeric)]
    for variant, block in metrics.items():
        rows = [[_e(name), *cells(values)] for name, values in block["per_target"].items()]
        rows.append(["<b>mean</b>", *cells(block["mean"])])
        out += [f"<h3>{_e(VARIANT_LABELS[variant])}</h3>",
                _table(["target", *header], rows, numeric)]
    return "".join(out)


def _fabrication_html(fabrication: Mapping[str, Any]) -> str:
    known = {k: fabrication[k] for k in _FABRICATION_SPEC if k != "violations"}
    others = {k: v for k, v in fabrication.items() if k not in _FABRICATION_SPEC}
    out = [_pairs({**known, **others})]
    violations = fabrication["violations"]
    if not violations:
        out.append("<p>No rule violations.</p>")
    else:
        rows = [[_e(v["rule"]), _e("plate" if v["cell"] is None else tuple(v["cell"])),
                 _num(v["value_mm"], 4), _num(v["limit_mm"], 4), _e(v["resolution"])]
                for v in violations]
        out.append(_table(["rule", "cell", "asked (mm)", "limit (mm)", "resolution"], rows,
                          numeric=(2, 3)))
    return "".join(out)


def _mesh_html(mesh: Mapping[str, Any]) -> str:
    verdict = ("watertight" if mesh["watertight"]
               else '<span class="bad">NOT watertight: do not print</span>')
    return f"<p>The mesh is {verdict}.</p>" + _pairs(mesh)


def _timings_html(timings: Mapping[str, Any]) -> str:
    if not timings:
        return f'<p class="muted">{NOT_COMPUTED}.</p>'
    rows = [[_e(stage), _num(seconds, 2)] for stage, seconds in timings.items()]
    total = sum(s for s in timings.values() if s is not None)
    rows.append(["<b>total</b>", f"{total:.2f}"])
    return _table(["stage", "seconds"], rows, numeric=(1,))


def _scene_html(scene: Mapping[str, Any]) -> str:
    eye = dict(scene["eye"])
    if eye["focus_mm"] is None:
        eye["focus_mm"] = "infinity"
    return "".join(f"<h3>{_e(part)}</h3>{_pairs(block)}"
                   for part, block in (("Display", scene["display"]), ("Plate", scene["plate"]),
                                       ("Eye", eye)))


def _tolerance_html(tolerance: Mapping[str, Any] | None, figures: Mapping[str, bytes]) -> str:
    if tolerance is None:
        return f'<p class="muted">Tolerance analysis {NOT_COMPUTED}.</p>'
    p = tolerance["psnr_percentiles"]
    rows = [["samples", _num(tolerance["samples"])],
            ["threshold (dB)", _num(tolerance["threshold_db"], 1)],
            ["yield (%)", _num(tolerance["yield"], 1, 100.0)],
            *[[f"PSNR, {k}th percentile (dB)", _num(p[k], 2)] for k in PERCENTILES]]
    return _img(figures, "tolerance") + _table(["quantity", "value"], rows, numeric=(1,))


def report_html(report: Mapping[str, Any], figures: Mapping[str, bytes],
                verdicts: list[str]) -> str:
    """One self-contained HTML page: inline CSS, figures as data:image/png;base64, no script.

    figures: PNG bytes keyed by FIGURE_KEYS; a missing one is shown as "not computed".
    verdicts: plain-language lines for the summary (see `verdicts`).
    """
    validate_report(report)
    for key, data in figures.items():
        if key not in FIGURE_KEYS:
            raise ValueError(f"figure {key!r} is not one the page places; allowed: "
                             f"{', '.join(FIGURE_KEYS)}.")
        if not (isinstance(data, bytes) and data.startswith(PNG_SIGNATURE)):
            raise ValueError(f"figure {key!r} is not PNG bytes; make it with figure_*().")
    plate = report["scene"]["plate"]
    targets = sorted({n for b in report["metrics"].values() for n in b["per_target"]})
    body: dict[str, str] = {
        "summary": "<ul class=\"verdicts\">" + "".join(f"<li>{_e(v)}</li>" for v in verdicts)
                   + "</ul>" if verdicts else f'<p class="muted">{NOT_COMPUTED}.</p>',
        "views": _img(figures, "views"),
        "metrics": _metrics_html(report["metrics"]),
        "plate": _img(figures, "hole_map") + _pairs(plate),
        "display": _img(figures, "display"),
        "loss": _img(figures, "loss"),
        "eyebox": _img(figures, "eyebox"),
        "tolerance": _tolerance_html(report["tolerance"], figures),
        "fabrication": _fabrication_html(report["fabrication"]),
        "mesh": _mesh_html(report["mesh"]),
        "timings": _timings_html(report["timings_s"]),
        "scene": _scene_html(report["scene"]),
        "config": _pairs(report["versions"])
                  + f"<pre>{_e(json.dumps(_plain(report['config']), indent=2))}</pre>",
    }
    title = "aperture-fab validation report"
    nav = " ".join(f'<a href="#{key}">{_e(heading)}</a>' for key, heading in SECTION_TITLES)
    sections = "\n".join(f'<section id="{key}"><h2>{_e(heading)}</h2>{body[key]}</section>'
                         for key, heading in SECTION_TITLES)
    digest = hashlib.sha256(json.dumps(_plain(report), sort_keys=True).encode()).hexdigest()
    return f"""<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta http-equiv="Content-Security-Policy" content="{CSP}">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{title}</title>
<style>{CSS}</style>
</head>
<body>
<main>
<h1>{title}</h1>
<p class="muted">Targets: {_e(", ".join(targets))}. Schema {report["schema_version"]};
report digest {digest[:12]}.</p>
<nav>{nav}</nav>
{sections}
</main>
</body>
</html>
"""
