"""The report page's sections after the lead: tables of the report's blocks, rounded and
labelled for people (aperture_fab.validation.formatting), and the display content at its native
resolution.

Pure functions, report.json blocks (aperture_fab.validation.report) in, escaped HTML out;
aperture_fab.validation.report_html puts them on the page.
"""

from __future__ import annotations

import base64
import struct
from collections.abc import Mapping
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
from aperture_fab.validation.report import FABRICATION_KEYS, PERCENTILES, VARIANT_LABELS

__all__ = ["config_html", "display_html", "fabrication_html", "light_html", "mesh_html",
           "metrics_html", "pairs", "png_size", "scene_html", "timings_html", "tolerance_table"]

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
UM_PER_MM = 1000.0


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
        out += ["<h3>Per target</h3>", table(["variant", "target", *header], rows,
                                             (2, 3, 4, 5))]
    return "".join(out)


def fabrication_html(fabrication: Mapping[str, Any]) -> str:
    known = {k: fabrication[k] for k in FABRICATION_KEYS if k != "violations"}
    others = {k: v for k, v in fabrication.items() if k not in FABRICATION_KEYS}
    out = [pairs({**known, **others})]
    violations = fabrication["violations"]
    if not violations:
        out.append("<p>No rule violations.</p>")
    else:
        rows = [[e(v["rule"]), e("plate" if v["cell"] is None else tuple(v["cell"])),
                 sig(v["value_mm"]), sig(v["limit_mm"]), e(v["resolution"])]
                for v in violations]
        out.append(table(["rule", "cell (row, col)", "asked (mm)", "limit (mm)", "resolution"],
                         rows, numeric=(2, 3)))
    return "".join(out)


def mesh_html(mesh: Mapping[str, Any]) -> str:
    verdict = ("watertight" if mesh["watertight"]
               else '<span class="bad">NOT watertight: do not print</span>')
    return f"<p>The mesh is {verdict}.</p>" + pairs(mesh)


def timings_html(timings: Mapping[str, Any]) -> str:
    if not timings:
        return f'<p class="muted">{NOT_COMPUTED}.</p>'
    rows = [[e(stage.removesuffix("_s").replace("_", " ")),
             NOT_COMPUTED if s is None else sig(s, 2)] for stage, s in timings.items()]
    total = sum(s for s in timings.values() if s is not None)
    rows.append(["<b>total</b>", sig(total, 3)])
    return table(["stage", "seconds"], rows, numeric=(1,))


def scene_html(scene: Mapping[str, Any]) -> str:
    eye = dict(scene["eye"])
    if eye["focus_mm"] is None:
        eye["focus_mm"] = "infinity"
    return "".join(f"<h3>{e(part)}</h3>{pairs(block)}"
                   for part, block in (("Display", scene["display"]), ("Plate", scene["plate"]),
                                       ("Eye", eye)))


def tolerance_table(tolerance: Mapping[str, Any]) -> str:
    p = tolerance["psnr_percentiles"]
    rows = [["samples", quantity("samples", tolerance["samples"])],
            ["threshold (dB)", quantity("threshold_db", tolerance["threshold_db"])],
            ["yield (above the threshold)", percent(tolerance["yield"])],
            *[[f"PSNR, {k}th percentile (dB)", quantity("psnr_db", p[k])] for k in PERCENTILES]]
    return table(["quantity", "value"], rows, numeric=(1,))


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
         + ("met" if photometry["meets_min_efficiency"] else "<b>missed</b>")),
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
    out = [table(["light budget", "value"], [[e(k), v] for k, v in rows], (1,)),
           f'<p class="muted">Pupil: {e(photometry["pupil_source"])}, for '
           f"{sig(photometry['field_area_deg2'])} deg² seen by {photometry['adapted_eyes']} "
           f"eye(s), age {photometry['observer_age_years']:g} ([photometry] settings).</p>",
           table(["contrast", "value"], [[e(k), v] for k, v in leak_rows], (1,)),
           '<p class="muted">Leakage = 10^-OD x (1 - open share) / light efficiency: the '
           "material's light, a nearly uniform veil, over the holes'. Neglected: scatter off "
           "the hole walls, reflections, the display's black level, the OD's change with "
           "thickness (docs/validation.md).</p>"]
    if photometry["warnings"]:
        out.append('<ul class="warnings">' + "".join(f"<li>{e(w)}</li>"
                                                     for w in photometry["warnings"]) + "</ul>")
    return "".join(out)


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
    """The resolved config as (section, key, value) rows, then the package versions."""
    return (table(["section", "key", "value"], config_rows(config))
            + "<h3>Versions</h3>"
            + table(["package", "version"], [[e(k), e(v)] for k, v in versions.items()]))
