"""The validation report drawn: the figures, report.html and the views archive, from a judged
part (aperture_fab.validation.judge's `Report`) and the arrays it was judged on. Values in,
bytes out; the pipeline writes the files."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from aperture_fab.fabrication.mesh import outline_points_mm
from aperture_fab.fabrication.part import Part
from aperture_fab.io.images import encode_png
from aperture_fab.metrics import gain_psnr_db
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
from aperture_fab.validation.report import EYE_VARIANT_LABELS, Report, views_npz
from aperture_fab.validation.robustness import EyeQuality
from aperture_fab.validation.validate import Validation
from aperture_fab.validation.variants import SHOWN_VARIANTS, VARIANTS, eye_first

__all__ = ["Evidence", "assemble", "eye_figures"]


@dataclass(frozen=True)
class Evidence:
    """report: the judged part (report.json's content); html: report.html; views_npz: views.npz
    bytes; figures: the page's figures, name -> PNG bytes; displays: the display contents shown,
    target name -> PNG bytes."""

    report: Report
    html: str
    views_npz: bytes
    figures: Mapping[str, bytes] = field(default_factory=dict)
    displays: Mapping[str, bytes] = field(default_factory=dict)

    def with_report(self, report: Report) -> Evidence:
        """This evidence for an amended report: its page drawn again from the same figures."""
        return replace(self, report=report,
                       html=report_html(report, self.figures, self.displays))


def assemble(report: Report, names: tuple[str, ...], targets: np.ndarray,
             displays: np.ndarray, loss_history: np.ndarray, part: Part,
             validation: Validation) -> Evidence:
    """Everything the report shows: its figures and page, and the views archive.

    targets: (T, C, ny, nx) linear, on the view grid; displays: (T, C, H, W) the content
    shown; loss_history: the optimizer's loss per iteration."""
    first = names[0]
    views, eyes = validation.views, validation.eyes
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
             for k, p in enumerate(report.scene["eye"]["positions_mm"])],
            "As built, from each eye position")
    if validation.mesh_stderr is not None:
        figures["mesh_retrace"] = figure_mesh_disagreement(
            views["as_built_mesh"][0, 0], views["quantized"][0, 0],
            float(np.sqrt(np.mean(validation.mesh_stderr[0] ** 2))))
    if validation.tolerance is not None:
        figures["tolerance"] = figure_histogram(
            np.asarray(validation.tolerance["psnr_db"]), validation.tolerance["threshold_db"])
    shown_png = {name: encode_png(np.clip(d, 0.0, 1.0))
                 for name, d in zip(names, displays, strict=True)}
    html = report_html(report, figures, shown_png)
    archive = {
        f"{variant}/{name}" + (f"/pos{k}" if v.shape[1] > 1 else ""): v[t, k]
        for variant, v in views.items()
        for t, name in enumerate(names)
        for k in range(v.shape[1])
    }
    return Evidence(report, html, views_npz(archive), figures, shown_png)


def _panel_label(variant: str, values: Mapping[str, Any] | None) -> str:
    """A view panel's title: the variant's name and its PSNR and SSIM (nominal eye)."""
    name = VARIANTS[variant].title
    if values is None or values.get("psnr_db") is None:
        return name
    ssim = values.get("ssim")
    return f"{name}\n{values['psnr_db']:.1f} dB" + ("" if ssim is None else f", SSIM {ssim:.2f}")


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
            x, {EYE_VARIANT_LABELS.get(v, v): curves[v] for v in eye_first(curves)},
            xlabel=label, shaded=shaded, nominal=nominal, names=names)
    figures["eye_thumbnails"] = figure_thumbnails(
        targets, eyes.thumbnails, eyes.thumbnail_offsets_mm,
        gain_psnr_db(eyes.thumbnails, targets), names)
    return figures
