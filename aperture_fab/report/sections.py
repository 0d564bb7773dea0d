"""The report page's sections after the lead: tables of the report's blocks, rounded and
labelled for people (aperture_fab.validation.formatting), and the display content at its native
resolution.

Pure functions, report.json blocks (aperture_fab.validation.report) in, escaped HTML out;
aperture_fab.report.page puts them on the page.
"""

from __future__ import annotations

import base64
import struct
from collections.abc import Mapping, Sequence
from typing import Any

from aperture_fab.validation.formatting import (
    NOT_COMPUTED,
    config_rows,
    e,
    label,
    percent,
    quantity,
    sig,
    table,
)
from aperture_fab.validation.light import SETTINGS_WARNING
from aperture_fab.validation.report import FABRICATION_KEYS, PERCENTILES, VARIANT_LABELS

__all__ = ["config_html", "display_html", "fabrication_html", "figure_grid", "folded",
           "light_html", "mesh_html", "metrics_html", "pairs", "png_size", "scene_html",
           "side_by_side", "timings_html", "tolerance_table"]

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
UM_PER_MM = 1000.0
#: A table of more rows than this is folded into <details> (its summary says what it holds).
MAX_OPEN_ROWS = 12


def figure_grid(items: Sequence[str]) -> str:
    """Figures (or a table and a figure) side by side, as many columns as the page's width
    holds (two at 1280 px), each scaled to its column."""
    return '<div class="figs">' + "".join(f"<div>{item}</div>" for item in items) + "</div>"


def side_by_side(sections: Sequence[str]) -> str:
    """Whole sections in one row of columns (one column each on a narrow window)."""
    return '<div class="row">' + "".join(sections) + "</div>"


def folded(summary: str, content: str) -> str:
    """`content` behind a one-line `summary` (escaped HTML) that opens it."""
    return f"<details><summary>{summary}</summary>{content}</details>"


def pairs(block: Mapping[str, Any], skip: tuple[str, ...] = ()) -> str:
    """A two-column table of a flat block: human labels, values rounded to their meaning."""
    return table(["quantity", "value"],
                 [[e(label(k)), quantity(k, v)] for k, v in block.items() if k not in skip])


def metrics_html(metrics: Mapping[str, Any]) -> str:
    """Mean over targets per variant, then (with several targets) each target's figures."""
    header = ["PSNR (dB)", "SSIM", "light efficiency", "MSE"]

    def cells(values: Mapping[str, Any]) -> list[str]:
        psnr, ssim = values["psnr_db"], values["ssim"]
        return [NOT_COMPUTED if psnr is None else f"{psnr:.1f}",
                NOT_COMPUTED if ssim is None else f"{ssim:.2f}",
                percent(values["light_efficiency"]),
                NOT_COMPUTED if values["mse"] is None else sig(values["mse"], 2)]

    out = [table(["variant", *header],
                 [[e(VARIANT_LABELS[v]), *cells(b["mean"])] for v, b in metrics.items()],
                 (1, 2, 3, 4))]
    names = list(next(iter(metrics.values()))["per_target"])
    if len(names) > 1:
        rows = [[e(VARIANT_LABELS[v]), e(name), *cells(b["per_target"][name])]
                for v, b in metrics.items() for name in b["per_target"]]
        out.append(folded(f"Per target ({len(names)} targets)",
                          table(["variant", "target", *header], rows, (2, 3, 4, 5))))
    return "".join(out)


def fabrication_html(fabrication: Mapping[str, Any]) -> str:
    """The holes and webs in one line (the full table folded), then the rule violations."""
    known = {k: fabrication[k] for k in FABRICATION_KEYS if k != "violations"}
    others = {k: v for k, v in fabrication.items() if k not in FABRICATION_KEYS}
    hole, web = fabrication["smallest_hole_diameter_mm"], fabrication["smallest_web_mm"]
    summary = (f"{quantity('holes', fabrication['holes'])} holes, {e(fabrication['process'])}; "
               f"smallest hole {quantity('smallest_hole_diameter_mm', hole)} mm, smallest web "
               f"{quantity('smallest_web_mm', web)} mm")
    out = [folded(summary, pairs({**known, **others}))]
    violations = fabrication["violations"]
    if not violations:
        out.append("<p>No rule violations.</p>")
    else:
        rows = [[e(v["rule"]), e("plate" if v["cell"] is None else tuple(v["cell"])),
                 sig(v["value_mm"]), sig(v["limit_mm"]), e(v["resolution"])]
                for v in violations]
        listed = table(["rule", "cell (row, col)", "asked (mm)", "limit (mm)", "resolution"],
                       rows, numeric=(2, 3))
        out.append(listed if len(rows) <= MAX_OPEN_ROWS else
                   folded(f"{len(rows)} rule violations, each resolved", listed))
    return "".join(out)


def mesh_html(mesh: Mapping[str, Any]) -> str:
    """Watertight or not, in one line (the mesh's figures folded)."""
    verdict = ("watertight" if mesh["watertight"]
               else '<span class="bad">NOT watertight: do not print</span>')
    return (f"<p>The mesh is {verdict}.</p>"
            + folded(f"Genus {quantity('genus', mesh['genus'])}, "
                     f"{quantity('triangles', mesh['triangles'])} triangles", pairs(mesh)))


def timings_html(timings: Mapping[str, Any]) -> str:
    """The total, then the seconds of each stage (folded)."""
    if not timings:
        return f'<p class="muted">Timings {NOT_COMPUTED}.</p>'
    rows = [[e(stage.removesuffix("_s").replace("_", " ")),
             NOT_COMPUTED if s is None else sig(s, 2)] for stage, s in timings.items()]
    total = sum(s for s in timings.values() if s is not None)
    rows.append(["<b>total</b>", sig(total, 3)])
    return folded(f"{sig(total, 3)} s in all; by stage", table(["stage", "seconds"], rows,
                                                               numeric=(1,)))


def scene_html(scene: Mapping[str, Any]) -> str:
    """The display, plate and eye as judged (folded: the config below says the same)."""
    eye = dict(scene["eye"])
    if eye["focus_mm"] is None:
        eye["focus_mm"] = "infinity"
    display, plate = scene["display"], scene["plate"]
    summary = (f"Display {sig(display['width_mm'])} x {sig(display['height_mm'])} mm; plate "
               f"{plate['cells'][0]} x {plate['cells'][1]} cells {sig(plate['gap_mm'])} mm in "
               f"front of it; eye pupil {sig(eye['pupil_mm'])} mm")
    return folded(e(summary), "".join(
        f"<h3>{e(part)}</h3>{pairs(block)}"
        for part, block in (("Display", display), ("Plate", plate), ("Eye", eye))))


def tolerance_table(tolerance: Mapping[str, Any]) -> str:
    """The yield in one line, then its figures (folded)."""
    p = tolerance["psnr_percentiles"]
    rows = [["samples", quantity("samples", tolerance["samples"])],
            ["threshold (dB)", quantity("threshold_db", tolerance["threshold_db"])],
            ["yield (above the threshold)", percent(tolerance["yield"])],
            *[[f"PSNR, {k}th percentile (dB)", quantity("psnr_db", p[k])] for k in PERCENTILES]]
    summary = (f"Yield {percent(tolerance['yield'])} of {tolerance['samples']} samples above "
               f"{quantity('threshold_db', tolerance['threshold_db'])} dB; the percentiles")
    return folded(summary, table(["quantity", "value"], rows, numeric=(1,)))


def light_html(photometry: Mapping[str, Any] | None) -> str:
    """The light budget and the leakage, with their warnings."""
    if photometry is None:
        return (f'<p class="muted">Light budget {NOT_COMPUTED}: the part\'s light efficiency '
                "is unknown.</p>")
    rows = [
        ("panel luminance (full white)", f"{sig(photometry['panel_luminance_cd_m2'])} cd/m²"),
        ("light efficiency of the part as built (nominal eye, mean over targets)",
         percent(photometry["light_efficiency"])),
        ("content level (mean linear luminance shown)", f"{photometry['content_level']:.2f}"),
        ("luminance at the eye", f"{sig(photometry['view_luminance_cd_m2'], 2)} cd/m²"),
        ("retinal illuminance (assumed pupil)",
         f"{sig(photometry['retinal_illuminance_td'], 2)} td"),
        ("light regime (CIE 191:2010)", e(photometry["regime"])),
        ("pupil the design assumed", f"{sig(photometry['assumed_pupil_mm'])} mm"),
        ("pupil at this light", f"{photometry['implied_pupil_mm']:.1f} mm"),
        ("efficiency that stays photopic", percent(photometry["photopic_efficiency"])),
        ("brightness floor (optimizer.min_efficiency)",
         "none" if photometry["min_efficiency"] <= 0 else
         f"{percent(photometry['min_efficiency'])}, "
         + ("met" if photometry["meets_min_efficiency"] else "<b>missed</b>")
         + f" ({e(photometry.get('floors_on', 'nominal eye'))})"),
    ]
    leak = photometry["leakage"]
    share, ratio = leak["leakage_share"], leak["contrast_ratio"]
    leak_rows = [
        ("optical density of the plate material", f"{leak['optical_density']:g}"),
        ("its source", e(leak["optical_density_note"])),
        ("solid share of the plate", percent(1 - leak["open_share"], 3)),
        ("leakage (light through the material / through the holes)",
         "unbounded" if share is None else percent(share)),
        ("contrast ratio (white over the veil)", "unlimited" if ratio is None
         else f"{sig(ratio, 2)}:1"),
    ]
    contrast = "unlimited" if ratio is None else f"{sig(ratio, 2)}:1"
    summary = (f"{percent(photometry['light_efficiency'])} of the open display's light: "
               f"{sig(photometry['view_luminance_cd_m2'], 2)} cd/m² at the eye from a "
               f"{sig(photometry['panel_luminance_cd_m2'])} cd/m² panel "
               f"({e(photometry['regime'])}, pupil about {photometry['implied_pupil_mm']:.1f} "
               f"mm); leakage {'unbounded' if share is None else percent(share)}, contrast "
               f"{contrast}. The light budget and the contrast, in full")
    out = [figure_grid([
        table(["light budget", "value"], [[e(k), v] for k, v in rows], (1,))
        + f'<p class="muted">Pupil: {e(photometry["pupil_source"])}, for '
        f"{sig(photometry['field_area_deg2'])} deg² seen by {photometry['adapted_eyes']} "
        f"eye(s), age {photometry['observer_age_years']:g} ([photometry] settings).</p>",
        table(["contrast", "value"], [[e(k), v] for k, v in leak_rows], (1,))
        + '<p class="muted">Leakage = 10^-OD x (1 - open share) / light efficiency: the '
        "material's light, a nearly uniform veil, over the holes'. Neglected: scatter off "
        "the hole walls, reflections, the display's black level, the OD's change with "
        "thickness (docs/validation.md).</p>"])]
    # The light verdict words the regime and the pupil (with its fixes); only a settings problem
    # is left to say here.
    settings = [w for w in photometry["warnings"] if w.startswith(SETTINGS_WARNING)]
    if settings:
        out.append('<ul class="warnings">' + "".join(f"<li>{e(w)}</li>" for w in settings)
                   + "</ul>")
    return folded(summary, "".join(out))


def png_size(data: bytes) -> tuple[int, int]:
    """(width, height) of PNG bytes, read from the IHDR chunk."""
    if not (data.startswith(PNG_SIGNATURE) and data[12:16] == b"IHDR"):
        raise ValueError("not PNG bytes: expected the PNG signature and an IHDR chunk.")
    width, height = struct.unpack(">II", data[16:24])
    return int(width), int(height)


def display_html(displays: Mapping[str, bytes], display: Mapping[str, Any]) -> str:
    """Each display content at its native resolution (one image pixel per CSS pixel, pixelated,
    scrollable), with its orientation and physical size. display: the scene's display block."""
    if not displays:
        return f'<p class="muted">Display content {NOT_COMPUTED}.</p>'
    nx, ny = display["pixels"]
    w, h = display["width_mm"], display["height_mm"]
    note = (f'<p class="note">Shown 1:1 (one image pixel per screen pixel): {nx} x {ny} panel '
            f"pixels over {sig(w)} x {sig(h)} mm (pixel pitch {sig(w / nx * UM_PER_MM)} x "
            f"{sig(h / ny * UM_PER_MM)} µm). <b>Orientation:</b> the image's top edge is the "
            "panel's top (+y) and its left edge the panel's left (−x), as the eye sees the "
            "panel through the plate; show it unmirrored and unscaled. The PNG written beside "
            "the report (display_&lt;target&gt;.png) is the same image.</p>")
    out = [note]
    for name, data in displays.items():
        width, height = png_size(data)
        encoded = base64.b64encode(data).decode("ascii")
        out.append(f'<h3>Target {e(name)}</h3><div class="native-box">'
                   f'<img class="native" id="display-{e(name)}" width="{width}" '
                   f'height="{height}" alt="display content for target {e(name)}, {width} x '
                   f'{height} pixels" src="data:image/png;base64,{encoded}"></div>')
    return "".join(out)


def config_html(config: Mapping[str, Any], versions: Mapping[str, str]) -> str:
    """The resolved config as (section, key, value) rows, then the package versions, each
    folded behind a line that says what it holds."""
    rows = config_rows(config)
    preset = config.get("preset")
    return (folded(f"The resolved configuration: {len(rows)} settings"
                   + ("" if preset is None else f", preset {e(preset)}"),
                   table(["section", "key", "value"], rows))
            + folded("Package versions: " + e(", ".join(
                f"{k} {v}" for k, v in versions.items() if k in ("aperture-fab", "python"))),
                table(["package", "version"], [[e(k), e(v)] for k, v in versions.items()])))
