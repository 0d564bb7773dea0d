"""The validation report's contents from a validated design: report dict, figures, verdicts and
the views archive. Values in, bytes out; the pipeline writes the files."""

from __future__ import annotations

import datetime
import math
import platform
import shlex
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from importlib import metadata
from typing import Any

import numpy as np

from aperture_fab.config.config import Config
from aperture_fab.config.written import to_dict
from aperture_fab.fabrication.layout import layout_stats
from aperture_fab.fabrication.mesh import outline_points_mm
from aperture_fab.fabrication.part import Part
from aperture_fab.fabrication.process import Process
from aperture_fab.io.images import encode_png
from aperture_fab.metrics import agreement_db, gain_psnr_db
from aperture_fab.report.figures import (
    figure_eyebox_map,
    figure_histogram,
    figure_loss,
    figure_mesh_disagreement,
    figure_sweep,
    figure_thumbnails,
    figure_views,
)
from aperture_fab.report.page import report_html
from aperture_fab.report.part_figures import (
    figure_errors,
    figure_hole_map,
    figure_made_front,
)
from aperture_fab.validation.light import content_level, photometry_block
from aperture_fab.validation.report import (
    EYE_VARIANT_LABELS,
    EYE_VARIANTS,
    build_report,
    scene_dict,
    validate_report,
    views_npz,
)
from aperture_fab.validation.robustness import PERCENTILES, EyeQuality
from aperture_fab.validation.validate import Validation
from aperture_fab.validation.variants import SHOWN_VARIANTS, VARIANTS
from aperture_fab.validation.verdicts import verdicts

__all__ = ["Evidence", "assemble", "eye_distribution_block", "eye_figures", "light_block",
           "run_block"]

#: Wavelength for the diffraction verdict (green, where the eye is most sensitive).
VERDICT_WAVELENGTH_MM = 530e-6


@dataclass(frozen=True)
class Evidence:
    """report: the report.json structure; html: report.html; views_npz: views.npz bytes."""

    report: dict[str, Any]
    html: str
    views_npz: bytes


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
              date: str | None = None) -> dict[str, Any]:
    """report.json's "run" block: the part's file name, the process, the date (ISO 8601 UTC,
    now unless given) and the command line (None: called from Python)."""
    when = date if date is not None else datetime.datetime.now(datetime.UTC).isoformat(
        timespec="seconds").replace("+00:00", "Z")
    line = command if command is None or isinstance(command, str) else shlex.join(command)
    return {"part": part_file, "process": process, "date": when, "command": line}


def light_block(config: Config, validation: Validation, displays: np.ndarray, process: Process,
                open_share: float) -> dict[str, Any] | None:
    """report.json's "photometry" block for the part as built (None when its light efficiency
    was not computed)."""
    per_target = validation.metrics.get("as_built", {})
    values = [m["light_efficiency"] for m in per_target.values()]
    if not values or any(v is None or not math.isfinite(v) for v in values):
        return None
    eye, optimizer = config.scene.eye, config.optimizer
    return photometry_block(
        efficiency=float(np.mean(values)), level=content_level(displays),
        settings=config.photometry,
        assumed_pupil_mm=eye.pupil_mm, fov_deg=(eye.fov_deg[0], eye.fov_deg[1]),
        min_efficiency=optimizer.min_efficiency, efficiency_weight=optimizer.efficiency_weight,
        min_eye_level=optimizer.min_eye_level,
        optical_density=process.optical_density,
        optical_density_note=process.optical_density_note, open_share=open_share)


def assemble(config: Config, names: tuple[str, ...], targets: np.ndarray,
             displays: np.ndarray, loss_history: np.ndarray, part: Part, process: Process,
             validation: Validation, timings_s: Mapping[str, float], *,
             part_file: str = "plate.stl", command: Sequence[str] | str | None = None,
             date: str | None = None) -> Evidence:
    """Everything the report shows, from the design job's values.

    part_file, command, date: the header's part (file name), the command line (None: called
    from Python) and the date (ISO 8601 UTC; None: now)."""
    stats = layout_stats(part.layout)
    fabrication = {
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
    mesh = {"watertight": part.report.watertight, "genus": part.report.genus,
            "volume_mm3": part.report.volume_mm3, "triangles": part.report.face_count}
    tolerance = None
    if validation.tolerance is not None:
        t = validation.tolerance
        tolerance = {"samples": t["samples"], "psnr_percentiles": t["psnr_percentiles"],
                     "yield": t["yield"], "threshold_db": t["threshold_db"],
                     "model": {k: v for k, v in t.items() if k not in (
                         "samples", "psnr_percentiles", "yield", "threshold_db")}}
    timings = {**timings_s, **validation.timings_s}
    eyes = validation.eyes
    report = build_report(metrics=validation.metrics, fabrication=fabrication, mesh=mesh,
                          tolerance=tolerance, timings_s=timings,
                          scene=scene_dict(config.scene), config=to_dict(config),
                          versions=_versions(),
                          eye_distribution=None if eyes is None else eye_distribution_block(
                              eyes, names, targets),
                          run=run_block(part_file, process.name, command, date),
                          photometry=light_block(config, validation, displays, process,
                                                 float(stats["open_area_fraction"])),
                          made_part=validation.made_part)
    if validation.mesh_stderr is not None:
        report["mesh_retrace_stderr_rms"] = float(np.sqrt(np.mean(validation.mesh_stderr**2)))
        # The first target's, as the page's disagreement map shows it.
        report["mesh_retrace_agreement_db"] = agreement_db(
            validation.views["as_built_mesh"][0, 0], validation.views["quantized"][0, 0])

    first = names[0]
    views = validation.views
    shown = [v for v in SHOWN_VARIANTS if v in views]
    rows = [("target", targets[0])] + [
        (_panel_label(v, validation.metrics.get(v, {}).get(first)), views[v][0, 0])
        for v in shown]
    layout = part.layout
    figures = {
        **({} if eyes is None else eye_figures(eyes, names, targets)),
        "views": figure_views(rows, f"Target {first!r}: what the eye sees"),
        "errors": figure_errors(targets[0], rows[1:],
                                title=f"Target {first!r}: error of each view"),
        "hole_map": figure_hole_map(layout.centres_mm, layout.radii_mm,
                                    outline_points_mm(layout, part.corner_cut_mm)),
        "loss": figure_loss(loss_history),
        **({} if validation.made_part is None else
           {"made_front": figure_made_front(validation.made_part)}),
    }
    if views["as_built"].shape[1] > 1:
        positions = views["as_built"][0]
        psnr = gain_psnr_db(positions[None], targets[0][None])[0]
        figures["eyebox"] = figure_views(
            [(f"eye at ({p[0]:g}, {p[1]:g}) mm\n{psnr[k]:.1f} dB", positions[k])
             for k, p in enumerate(config.scene.eye.positions_mm)],
            "As built, from each eye position")
    if validation.mesh_stderr is not None:
        figures["mesh_retrace"] = figure_mesh_disagreement(
            views["as_built_mesh"][0, 0], views["quantized"][0, 0],
            float(np.sqrt(np.mean(validation.mesh_stderr[0] ** 2))))
    if validation.tolerance is not None:
        figures["tolerance"] = figure_histogram(
            np.asarray(validation.tolerance["psnr_db"]), validation.tolerance["threshold_db"])
    blur = None
    if stats["smallest_hole_diameter_mm"]:
        from aperture_fab.optics.diffraction import airy_blur_px

        blur = airy_blur_px(stats["smallest_hole_diameter_mm"], VERDICT_WAVELENGTH_MM,
                            config.scene.eye.view_step)
    lines = verdicts(report, diffraction_blur_px=blur)
    report["verdicts"] = [line.as_dict() for line in lines]
    validate_report(report)
    html = report_html(report, figures, lines, {
        name: encode_png(np.clip(d, 0.0, 1.0)) for name, d in zip(names, displays, strict=True)})
    archive = {
        f"{variant}/{name}" + (f"/pos{k}" if v.shape[1] > 1 else ""): v[t, k]
        for variant, v in views.items()
        for t, name in enumerate(names)
        for k in range(v.shape[1])
    }
    return Evidence(report, html, views_npz(archive))


def _panel_label(variant: str, values: Mapping[str, Any] | None) -> str:
    """A view panel's title: the variant's name and its PSNR and SSIM (nominal eye)."""
    name = VARIANTS[variant].title
    if values is None or values.get("psnr_db") is None:
        return name
    ssim = values.get("ssim")
    return f"{name}\n{values['psnr_db']:.1f} dB" + ("" if ssim is None else f", SSIM {ssim:.2f}")



def _ordered(names: Any) -> list[str]:
    """Variant names with those of EYE_VARIANTS first, in that order."""
    return ([v for v in EYE_VARIANTS if v in names]
            + [v for v in names if v not in EYE_VARIANTS])


def eye_distribution_block(eyes: EyeQuality, names: tuple[str, ...], targets: np.ndarray
                           ) -> dict[str, Any]:
    """report.json's "eye_distribution" block (aperture_fab.validation.report, EYE_DISTRIBUTION):
    the summary, the eyebox map, the pupil and focus sweeps and the thumbnails' offsets and PSNR.

    targets: (T, C, ny, nx) linear, the targets the thumbnails are scored against."""
    summary = eyes.summary()
    order = _ordered(summary["variants"])
    return {
        "states": summary["states"],
        "percentiles": list(PERCENTILES),
        "targets": list(names),
        "distribution": summary["distribution"],
        "variants": {v: summary["variants"][v] for v in order},
        "eyebox_map": {
            "offsets_mm": eyes.map_offsets_mm, "inside": eyes.map_inside.astype(bool),
            "psnr_db": {v: eyes.map_psnr_db[v] for v in _ordered(eyes.map_psnr_db)},
        },
        "pupil": {"pupil_mm": eyes.pupil_mm,
                  "psnr_db": {v: eyes.pupil_psnr_db[v] for v in _ordered(eyes.pupil_psnr_db)}},
        "focus": {"focus_diopters": eyes.focus_diopters,
                  "psnr_db": {v: eyes.focus_psnr_db[v] for v in _ordered(eyes.focus_psnr_db)}},
        "thumbnails": {
            "variant": next(iter(eyes.psnr_db)), "offsets_mm": eyes.thumbnail_offsets_mm,
            "psnr_db": gain_psnr_db(eyes.thumbnails, targets),
        },
    }


def eye_figures(eyes: EyeQuality, names: tuple[str, ...], targets: np.ndarray
                ) -> dict[str, bytes]:
    """The eye distribution's figures: the part's eyebox map (none for an eyebox of zero size),
    PSNR against pupil and against focus, and the thumbnails."""
    d = eyes.distribution
    part = next(iter(eyes.psnr_db))
    figures: dict[str, bytes] = {}
    if part in eyes.map_psnr_db and (d.eyebox_mm[0] > 0 or d.eyebox_mm[1] > 0):
        figures["eye_map"] = figure_eyebox_map(
            eyes.map_psnr_db[part], eyes.map_offsets_mm, d.eyebox_mm, shape=d.eyebox_shape,
            centre_mm=d.centre_mm, names=names)
    for key, x, curves, label, shaded, nominal in (
            ("eye_pupil", eyes.pupil_mm, eyes.pupil_psnr_db, "pupil diameter (mm)",
             d.pupil_range_mm, d.nominal_pupil_mm),
            ("eye_focus", eyes.focus_diopters, eyes.focus_psnr_db,
             "focus (diopters, 0 = infinity)", d.focus_range_diopters,
             d.nominal_focus_diopters)):
        figures[key] = figure_sweep(
            x, {EYE_VARIANT_LABELS.get(v, v): curves[v] for v in _ordered(curves)},
            xlabel=label, shaded=shaded, nominal=nominal, names=names)
    figures["eye_thumbnails"] = figure_thumbnails(
        targets, eyes.thumbnails, eyes.thumbnail_offsets_mm,
        gain_psnr_db(eyes.thumbnails, targets), names)
    return figures
