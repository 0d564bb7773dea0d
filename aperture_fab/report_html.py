"""The validation report for people: verdicts in plain words and the self-contained HTML page.

Pure functions, the report.json structure (aperture_fab.report) and PNG figures
(aperture_fab.figures) in, text out; the pipeline writes report.html.
"""

from __future__ import annotations

import base64
import hashlib
import html
import json
from collections.abc import Mapping
from typing import Any

from aperture_fab.report import (
    FABRICATION_KEYS,
    FIGURE_KEYS,
    PERCENTILES,
    VARIANT_LABELS,
    json_ready,
    validate_report,
)

__all__ = ["SECTION_TITLES", "CSP", "verdicts", "report_html"]

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
#: Headline variant for verdicts: the first of these that the report holds.
HEADLINE_VARIANTS: tuple[tuple[str, str], ...] = (
    ("as_built", "As built"), ("quantized", "After quantization"), ("optimized", "As optimized"),
)

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
            lines.append(f"The eye sees {100 * efficiency:.2g} % of the light of the open "
                         "display.")
    built = _mean(report, "as_built")
    drawn, traced = _mean(report, "quantized"), _mean(report, "as_built_mesh")
    if drawn is not None and traced is not None:
        noise = report.get("mesh_retrace_stderr_rms")
        lines.append(f"Traced through the written mesh (the holes as drawn), the view scores "
                     f"{traced:.1f} dB ({traced - drawn:+.1f} dB from the hole layout's)"
                     + (f"; Monte Carlo noise {noise:.2g} RMS per pixel: more rays per pixel "
                        "sharpen this check (--mesh-samples)." if noise else "."))
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
        threshold = tolerance["threshold_db"]
        text = (f"Yield at {threshold:.1f} dB over {tolerance['samples']} tolerance "
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
    known = {k: fabrication[k] for k in FABRICATION_KEYS if k != "violations"}
    others = {k: v for k, v in fabrication.items() if k not in FABRICATION_KEYS}
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
                  + f"<pre>{_e(json.dumps(json_ready(report['config']), indent=2))}</pre>",
    }
    title = "aperture-fab validation report"
    nav = " ".join(f'<a href="#{key}">{_e(heading)}</a>' for key, heading in SECTION_TITLES)
    sections = "\n".join(f'<section id="{key}"><h2>{_e(heading)}</h2>{body[key]}</section>'
                         for key, heading in SECTION_TITLES)
    digest = hashlib.sha256(json.dumps(json_ready(report), sort_keys=True).encode()).hexdigest()
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
