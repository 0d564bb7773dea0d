"""A validated part judged: its `Report` (report.json's content and the verdicts) from the
design job's values. Values in, a value out; aperture_fab.report.evidence draws it and the
pipeline writes it."""

from __future__ import annotations

import datetime
import math
import platform
import shlex
from collections.abc import Mapping, Sequence
from dataclasses import replace
from importlib import metadata
from typing import Any

import numpy as np

from aperture_fab.config.config import Config
from aperture_fab.config.settings import OptimizerSettings
from aperture_fab.config.stages import PhotometrySettings
from aperture_fab.config.written import to_dict
from aperture_fab.fabrication.layout import layout_stats
from aperture_fab.fabrication.part import Part
from aperture_fab.fabrication.process import Process
from aperture_fab.metrics import agreement_db, gain_psnr_db
from aperture_fab.optics.scene import Eye
from aperture_fab.validation.light import content_level, photometry_block
from aperture_fab.validation.report import Report, build_report, scene_dict
from aperture_fab.validation.robustness import PERCENTILES, EyeQuality
from aperture_fab.validation.validate import Validation
from aperture_fab.validation.variants import eye_first
from aperture_fab.validation.verdicts import verdicts

__all__ = ["eye_distribution_block", "judge", "light_block", "run_block"]

#: Wavelength for the diffraction verdict (green, where the eye is most sensitive).
VERDICT_WAVELENGTH_MM = 530e-6
#: The packages whose versions the report records: those whose code computes its figures.
REPORTED_PACKAGES = ("aperture-fab", "torch", "numpy", "numba", "manifold3d", "embreex",
                     "scikit-image")


def _versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for package in REPORTED_PACKAGES:
        try:
            out[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            out[package] = "not installed"
    return out


def run_block(part_file: str, process: str, command: Sequence[str] | str | None,
              date: str | None = None, replaces: Mapping[str, Any] | None = None
              ) -> dict[str, Any]:
    """report.json's "run" block: the part's file name, the process, the date (ISO 8601 UTC,
    now unless given), the command line (None: called from Python) and, for a part the design
    job made on a regular array's lattice instead of the config's own cells, `replaces`: that
    first part's plate and margins ({"pitch_mm", "cells", "margin_db"})."""
    when = date if date is not None else datetime.datetime.now(datetime.UTC).isoformat(
        timespec="seconds").replace("+00:00", "Z")
    line = command if command is None or isinstance(command, str) else shlex.join(command)
    block = {"part": part_file, "process": process, "date": when, "command": line}
    return block if replaces is None else {**block, "replaces": dict(replaces)}


def light_block(settings: PhotometrySettings, optimizer: OptimizerSettings, eye: Eye,
                validation: Validation, displays: np.ndarray, process: Process,
                open_share: float) -> dict[str, Any] | None:
    """report.json's "photometry" block for the part as built, seen by `eye`, with the
    optimizer's light floor and weight, judged on the part as made over made copies x eye
    states where that was judged (None when its light efficiency was not computed)."""
    per_target = validation.metrics.get("as_built", {})
    values = [m["light_efficiency"] for m in per_target.values()]
    if not values or any(v is None or not math.isfinite(v) for v in values):
        return None
    made = validation.made_part
    held = None if not made else (float(made["part"]["efficiency"]),
                                  float(made["part"]["eye_level"]))
    return photometry_block(
        held=held,
        efficiency=float(np.mean(values)), level=content_level(displays),
        settings=settings,
        assumed_pupil_mm=eye.pupil_mm, fov_deg=(eye.fov_deg[0], eye.fov_deg[1]),
        min_efficiency=optimizer.min_efficiency, efficiency_weight=optimizer.efficiency_weight,
        min_eye_level=optimizer.min_eye_level, designed_pupils_mm=eye.pupil_range_mm,
        optical_density=process.optical_density,
        optical_density_note=process.optical_density_note, open_share=open_share)


def eye_distribution_block(eyes: EyeQuality, names: tuple[str, ...], targets: np.ndarray
                           ) -> dict[str, Any]:
    """report.json's "eye_distribution" block (aperture_fab.validation.report, EYE_DISTRIBUTION):
    the summary, the eyebox map, the pupil and focus sweeps and the thumbnails' offsets and PSNR.

    targets: (T, C, ny, nx) linear, the targets the thumbnails are scored against."""
    summary = eyes.summary()
    order = eye_first(summary["variants"])
    return {
        "states": summary["states"],
        "percentiles": list(PERCENTILES),
        "targets": list(names),
        "distribution": summary["distribution"],
        "variants": {v: summary["variants"][v] for v in order},
        "eyebox_map": {
            "offsets_mm": eyes.map_offsets_mm, "inside": eyes.map_inside.astype(bool),
            "psnr_db": {v: eyes.map_psnr_db[v] for v in eye_first(eyes.map_psnr_db)},
        },
        "pupil": {"pupil_mm": eyes.pupil_mm,
                  "psnr_db": {v: eyes.pupil_psnr_db[v] for v in eye_first(eyes.pupil_psnr_db)}},
        "focus": {"focus_diopters": eyes.focus_diopters,
                  "psnr_db": {v: eyes.focus_psnr_db[v] for v in eye_first(eyes.focus_psnr_db)}},
        "thumbnails": {
            "variant": next(iter(eyes.psnr_db)), "offsets_mm": eyes.thumbnail_offsets_mm,
            "psnr_db": gain_psnr_db(eyes.thumbnails, targets),
        },
    }


def _fabrication_block(part: Part, process: Process, stats: Mapping[str, Any]
                       ) -> dict[str, Any]:
    return {
        "process": process.name,
        "holes": int(stats["hole_count"]),
        "smallest_hole_diameter_mm": stats["smallest_hole_diameter_mm"],
        "smallest_web_mm": stats["smallest_web_mm"],
        "smallest_edge_web_mm": stats["smallest_edge_web_mm"],
        "open_area_fraction": stats["open_area_fraction"],
        "outline_mm": [float(v) for v in part.layout.outline_mm],
        "violations": [
            {"rule": v.rule, "cell": None if v.cell is None else list(v.cell),
             "value_mm": v.value_mm, "limit_mm": v.limit_mm, "resolution": v.resolution}
            for v in part.layout.violations
        ],
    }


def _tolerance_block(tolerance: Mapping[str, Any] | None) -> dict[str, Any] | None:
    if tolerance is None:
        return None
    headline = ("samples", "psnr_percentiles", "yield", "threshold_db")
    return {**{key: tolerance[key] for key in headline},
            "model": {k: v for k, v in tolerance.items() if k not in headline}}


def judge(config: Config, names: tuple[str, ...], targets: np.ndarray, displays: np.ndarray,
          part: Part, process: Process, validation: Validation,
          timings_s: Mapping[str, float], *, part_file: str = "plate.stl",
          command: Sequence[str] | str | None = None, date: str | None = None,
          replaces: Mapping[str, Any] | None = None) -> Report:
    """The report of a validated part, its verdicts included.

    targets: (T, C, ny, nx) linear, on the view grid; displays: (T, C, H, W) the content shown.
    part_file, command, date: the header's part (file name), the command line (None: called
    from Python) and the date (ISO 8601 UTC; None: now). replaces: the part on the config's
    own cells this one replaces (`run_block`), or None."""
    stats = layout_stats(part.layout)
    mesh = {"watertight": part.report.watertight, "genus": part.report.genus,
            "volume_mm3": part.report.volume_mm3, "triangles": part.report.face_count}
    eyes = validation.eyes
    report = build_report(metrics=validation.metrics,
                          fabrication=_fabrication_block(part, process, stats), mesh=mesh,
                          tolerance=_tolerance_block(validation.tolerance),
                          timings_s={**timings_s, **validation.timings_s},
                          scene=scene_dict(config.scene), config=to_dict(config),
                          versions=_versions(),
                          eye_distribution=None if eyes is None else eye_distribution_block(
                              eyes, names, targets),
                          run=run_block(part_file, process.name, command, date, replaces),
                          photometry=light_block(config.photometry, config.optimizer,
                                                 config.scene.eye, validation, displays,
                                                 process, float(stats["open_area_fraction"])),
                          made_part=validation.made_part)
    if validation.mesh_stderr is not None:
        views = validation.views
        report = replace(
            report,
            mesh_retrace_stderr_rms=float(np.sqrt(np.mean(validation.mesh_stderr**2))),
            # The first target's, as the page's disagreement map shows it.
            mesh_retrace_agreement_db=agreement_db(views["as_built_mesh"][0, 0],
                                                   views["quantized"][0, 0]))
    blur = None
    if stats["smallest_hole_diameter_mm"]:
        from aperture_fab.optics.diffraction import airy_blur_px

        blur = airy_blur_px(stats["smallest_hole_diameter_mm"], VERDICT_WAVELENGTH_MM,
                            config.scene.eye.view_step)
    return replace(report, verdicts=tuple(verdicts(report, diffraction_blur_px=blur)))
