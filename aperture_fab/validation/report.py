"""The validation report's data: `Report`, a judged part as a value (report.json's structure,
checked by `report_schema`), and the views archive.

Pure functions, values in and bytes or text out; the pipeline writes the files. The figures are
in aperture_fab.report.figures, the verdicts in aperture_fab.validation.verdicts, the HTML
page in aperture_fab.report.page.

report.json (`Report.as_json`; built by `build_report`, checked by `validate_report`, written
by `report_json`):

    schema_version  3
    run             (optional) {"part": the part's file name, "process", "date" (ISO 8601 UTC),
                    "command": the command line, or null when called from Python; and
                    "replaces" when the design job made this part on the best regular array's
                    lattice because its part on the config's own cells beat that array by too
                    little (`verdicts.RETRY_LATTICE_BELOW_DB`):
                    {"pitch_mm", "cells", "margin_db"} of that part; "tried" when it designed
                    on that lattice too and kept this part: the same of the other}
    photometry      (optional) the light budget of the part as built, or null when its light
                    efficiency was not computed; see PHOTOMETRY below
    eye_distribution  the headline: the part and the baselines judged over the eye distribution
                    (aperture_fab.validation.robustness), or null when not judged
                    (validation.eye_states
                    = 0); see EYE_DISTRIBUTION below
    made_part       (optional) the part as made (process errors drawn per made copy, diffraction,
                    the material's veil) over made copies x eye states beside the best regular
                    array at least as bright at the eye: {"copies", "states", "neglected", "part":
                    {"efficiency" (white display), "eye_level" (the light at the eye with the
                    shown content, a share of the panel's white), "p10_db", "p50_db", "p90_db",
                    "mean_mse_psnr_db" (per target: the PSNR of the mean squared error),
                    "loss_psnr_db" (the same over the worst optimizer.tail_share of copies x
                    states: the optimizer's figure)}, "regular": {"family", "fitted": per array
                    lists, "best": {"pitch_mm", "diameter_mm", "efficiency", "eye_level",
                    "p10_db", ...} or null}, "margin_db": per target or null,
                    "margin_interval_db" (with a best array; absent in older reports): per
                    target [low, high], the margin's bootstrap interval over other made copies
                    and eye states (aperture_fab.validation.margin_interval)}
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
    config          the resolved config (aperture_fab.config.written.to_dict)
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
    designed_pupils_mm (eye.pupil_range_mm, the pupils the design was made for, or null: the
    assumed pupil alone), pupil_mismatch_mm (how far the implied pupil lies outside them),
    designed_pupils (the same in words),
    field_area_deg2, observer_age_years, adapted_eyes, regime (photopic, mesopic, scotopic),
    photopic_efficiency (the efficiency that keeps this panel and content photopic, or null),
    min_efficiency (optimizer.min_efficiency, 0 = no floor), efficiency_weight,
    meets_min_efficiency (null without a floor), photopic_eye_level (the light at the eye,
    a share of the panel's white, of a photopic view), min_eye_level (optimizer.min_eye_level,
    0 = no floor), meets_min_eye_level (null without it), floors_on (where the floors are
    judged: "made copies x eye states", the part as made where the optimizer holds them, or
    "nominal eye" when that was not judged), floor_efficiency and floor_eye_level (the part's
    figures there), warnings [str],
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
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from aperture_fab.metrics import summarize
from aperture_fab.optics.eyes import distribution_of
from aperture_fab.optics.scene import Scene
from aperture_fab.validation.report_schema import (
    FABRICATION_KEYS,
    LEVELS,
    METRICS_SPEC,
    PERCENTILES,
    REPORT_VARIANTS,
    SCHEMA_VERSION,
    check_block,
    validate_report,
)
from aperture_fab.validation.variants import EYE_VARIANTS, SHOWN_VARIANTS, VARIANTS

__all__ = [
    "SCHEMA_VERSION",
    "EYE_TOPIC",
    "EYE_VARIANTS",
    "EYE_VARIANT_LABELS",
    "LEVELS",
    "JUDGED",
    "Report",
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
    "overall_level",
]

VARIANT_LABELS: dict[str, str] = {name: v.label for name, v in VARIANTS.items()}
EYE_VARIANT_LABELS: dict[str, str] = {name: str(VARIANTS[name].short) for name in EYE_VARIANTS}
#: The topic of the leading verdict: the part over the eye distribution.
EYE_TOPIC = "eye distribution"
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
                  "material's veil): 10th-percentile PSNR against the light at the eye (the "
                  "mean view of the content each shows, a share of the panel's white). Dots: "
                  "every array with elemental images (colour: pitch); dashed: their front; "
                  "squares: the rivals at least as bright at the eye with the display fitted "
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
#: A views.npz key: "<variant>/<target>" or "<variant>/<target>/pos<k>".
VIEW_KEY = re.compile(r"(?P<variant>[a-z_]+)/(?P<target>[^/]+)(/pos(?P<pos>\d+))?")

# ---------------------------------------------------------------------------------------------
# Verdicts


#: Judged levels, worst first (info is a finding without a judgement).
JUDGED = ("fail", "warn", "pass")


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

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Verdict:
        """A verdict from report.json ("fixes" absent in older reports)."""
        return cls(data["topic"], data["level"], data["text"], tuple(data.get("fixes", ())))


def overall_level(lines: Sequence[Verdict]) -> str:
    """A report's verdict: its worst judged level (fail, warn, pass), or info when none is."""
    return next((level for level in JUDGED if any(v.level == level for v in lines)), "info")


#: Top-level keys a report may carry after the blocks, in the order written: the mesh
#: re-trace's Monte Carlo noise and its agreement with the model (when re-traced), and the part
#: `validate` checked.
_TRAILING = ("mesh_retrace_stderr_rms", "mesh_retrace_agreement_db", "checked_part")


@dataclass(frozen=True)
class Report:
    """A judged part: report.json's content as a value (`as_json` gives the file's structure,
    described in this module's docstring; `from_json` reads it back, checked).

    verdicts: the findings, most important first (aperture_fab.validation.verdicts.verdicts;
        empty until judged). The blocks are JSON-ready values (dicts, lists, numbers, strings,
        None), each documented above under its report.json key; None where not computed.
    mesh_retrace_stderr_rms, mesh_retrace_agreement_db: the written mesh's re-trace against
        the model (RMS Monte Carlo noise, linear light; agreement in dB), or None.
    checked_part: what `validate` checked ({"path", "kind", "config", "display", "design",
        "measured_from_scan"}), or None for a design's own report.
    """

    metrics: Mapping[str, Any]
    fabrication: Mapping[str, Any]
    mesh: Mapping[str, Any]
    tolerance: Mapping[str, Any] | None
    timings_s: Mapping[str, float]
    scene: Mapping[str, Any]
    config: Mapping[str, Any]
    versions: Mapping[str, str]
    eye_distribution: Mapping[str, Any] | None = None
    verdicts: tuple[Verdict, ...] = ()
    run: Mapping[str, Any] | None = None
    photometry: Mapping[str, Any] | None = None
    made_part: Mapping[str, Any] | None = None
    mesh_retrace_stderr_rms: float | None = None
    mesh_retrace_agreement_db: float | None = None
    checked_part: Mapping[str, Any] | None = None

    def __post_init__(self) -> None:
        validate_report(self.as_json())

    def as_json(self) -> dict[str, Any]:
        """report.json's structure: plain JSON values, NaN and infinities as None."""
        trailing = {key: getattr(self, key) for key in _TRAILING
                    if getattr(self, key) is not None}
        return dict(json_ready({
            "schema_version": SCHEMA_VERSION,
            **({} if self.run is None else {"run": self.run}),
            "eye_distribution": self.eye_distribution,
            **({} if self.made_part is None else {"made_part": self.made_part}),
            "verdicts": [v.as_dict() for v in self.verdicts],
            "photometry": self.photometry,
            "metrics": self.metrics,
            "fabrication": self.fabrication,
            "mesh": self.mesh,
            "tolerance": self.tolerance,
            "timings_s": self.timings_s,
            "scene": self.scene,
            "config": self.config,
            "versions": self.versions,
            **trailing,
        }))

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Report:
        """A report read back from report.json's structure (checked: ValueError or TypeError
        naming the first key that is missing or wrong)."""
        validate_report(data)
        fields: dict[str, Any] = {key: data.get(key) for key in (
            "metrics", "fabrication", "mesh", "tolerance", "timings_s", "scene", "config",
            "versions", "eye_distribution", "run", "photometry", "made_part", *_TRAILING)}
        return cls(**fields, verdicts=tuple(Verdict.from_dict(v) for v in data["verdicts"]))

    @property
    def level(self) -> str:
        """The report's verdict, its page's headline: the worst judged level of its verdicts
        (fail, warn, pass), or info when none is judged."""
        return overall_level(self.verdicts)

    def with_timing(self, stage: str, seconds: float) -> Report:
        """The report with one more stage timed."""
        return replace(self, timings_s={**self.timings_s, stage: seconds})

    def mean(self, variant: str, key: str = "psnr_db") -> float | None:
        """A variant's mean over targets of one metric at the nominal eye point (None: not
        judged or not computed)."""
        block = self.metrics.get(variant)
        value = None if block is None else block["mean"].get(key)
        return None if value is None else float(value)


def eye_headline(report: Report) -> dict[str, Any] | None:
    """The eye distribution's numbers without the maps and sweeps, with its verdict: for
    design.json and the terminal. None when the report did not judge the eye distribution."""
    block = report.eye_distribution
    if block is None:
        return None
    verdict = next((v.as_dict() for v in report.verdicts if v.topic == EYE_TOPIC), None)
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
    verdicts: Sequence[Verdict] = (),
    run: Mapping[str, Any] | None = None,
    photometry: Mapping[str, Any] | None = None,
    made_part: Mapping[str, Any] | None = None,
) -> Report:
    """The report of a judged part, checked (see the module docstring).

    eye_distribution: the EYE_DISTRIBUTION block (aperture_fab.report.evidence builds it from
        robustness.EyeQuality), or None when the eye distribution was not judged.
    verdicts: most important first; usually added afterwards (`dataclasses.replace`), since
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
            check_block(values, METRICS_SPEC, f"metrics.{variant}.per_target.{name}")
        # summarize sees NaN for a metric that is null (not computed), so its mean is null too
        with_nan = [{k: math.nan if v is None else v for k, v in values.items()}
                    for values in per_target.values()]
        mean = summarize(with_nan) if with_nan else {}
        blocks[variant] = {"per_target": per_target, "mean": mean}
    return Report(metrics=blocks, fabrication=json_ready(fabrication, "fabrication"),
                  mesh=json_ready(mesh, "mesh"), tolerance=json_ready(tolerance, "tolerance"),
                  timings_s=json_ready(timings_s, "timings_s"), scene=json_ready(scene, "scene"),
                  config=json_ready(config, "config"), versions=json_ready(versions, "versions"),
                  eye_distribution=json_ready(eye_distribution, "eye_distribution"),
                  verdicts=tuple(verdicts), run=json_ready(run, "run"),
                  photometry=json_ready(photometry, "photometry"),
                  made_part=json_ready(made_part, "made_part"))


def report_json(report: Report) -> str:
    """report.json text: indent 2, NaN and infinities as null (strict JSON)."""
    return json.dumps(report.as_json(), indent=2, allow_nan=False) + "\n"


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
