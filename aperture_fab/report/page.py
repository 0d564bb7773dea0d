"""The validation report for people: one self-contained HTML page, the verdict first.

Pure functions, the report.json structure (aperture_fab.validation.report), its verdicts
(aperture_fab.validation.verdicts) and PNG figures (aperture_fab.report.figures,
part_figures) in, text out; the pipeline writes report.html. The sections after the lead are in
aperture_fab.report.sections.

The page is short enough to read (under MAX_PAGE_HEIGHT_PX at a 1280 px wide window, checked in
headless Chromium by the slow tests): figures side by side in grids, small sections in pairs,
long tables folded into <details>, and a section with nothing to show left out.
"""

from __future__ import annotations

import base64
import hashlib
import json
from collections.abc import Mapping, Sequence
from typing import Any

from aperture_fab.report.sections import (
    PNG_SIGNATURE,
    config_html,
    display_html,
    fabrication_html,
    figure_grid,
    folded,
    light_html,
    mesh_html,
    metrics_html,
    pairs,
    scene_html,
    side_by_side,
    timings_html,
    tolerance_table,
)
from aperture_fab.validation.formatting import NOT_COMPUTED, e, table
from aperture_fab.validation.margin_interval import COVERAGE
from aperture_fab.validation.report import (
    EYE_TOPIC,
    EYE_VARIANT_LABELS,
    EYE_VARIANTS,
    FIGURE_KEYS,
    JUDGED,
    LEVELS,
    SCHEMA_VERSION,
    Report,
    Verdict,
    overall_level,
)
from aperture_fab.validation.verdicts import (
    LEVEL_WORDS,
    FixPlan,
    describe_distribution,
    family_reach,
    fix_plan,
)

__all__ = ["CSP", "MAX_PAGE_HEIGHT_PX", "PAIRED_SECTIONS", "SECTION_TITLES", "WINDOW_WIDTH_PX",
           "report_html"]

#: The page's sections, top to bottom: (id, heading).
SECTION_TITLES: tuple[tuple[str, str], ...] = (
    ("verdict", "Verdict"),
    ("made", "The part as made"),
    ("light", "Light and contrast"),
    ("eyes", "Over the eye distribution"),
    ("views", "What the eye sees"),
    ("eyebox", "At each eye position"),
    ("errors", "Error maps"),
    ("metrics", "Image quality by variant"),
    ("plate", "Plate and hole sizes"),
    ("display", "Display content"),
    ("loss", "Optimization"),
    ("tolerance", "Manufacturing tolerance"),
    ("fabrication", "Fabrication checks"),
    ("mesh", "Mesh checks"),
    ("timings", "Timings"),
    ("scene", "Scene"),
    ("config", "Configuration and versions"),
)
#: Sections shown side by side (a two-column row, each a column) when both are on the page,
#: the second right after the first.
PAIRED_SECTIONS: tuple[tuple[str, str], ...] = (
    ("plate", "display"), ("loss", "tolerance"), ("fabrication", "mesh"), ("timings", "scene"),
)
#: The page's height (CSS px) in a WINDOW_WIDTH_PX wide window stays under this for the default
#: design (docs/validation.md; measured in headless Chromium by the slow tests).
MAX_PAGE_HEIGHT_PX = 6000
WINDOW_WIDTH_PX = 1280

#: Everything the page needs is inline: no script, nothing fetched; images only from data: URIs.
CSP = "default-src 'none'; img-src data:; style-src 'unsafe-inline'"
CSS = """
body { font: 15px/1.45 system-ui, sans-serif; color: #222; margin: 0; background: #fafafa; }
main { max-width: 76rem; margin: 0 auto; padding: 0.5rem 1.5rem 2rem; background: #fff; }
h1 { font-size: 1.6rem; overflow-wrap: anywhere; margin: 0.6rem 0; }
h2 { border-bottom: 1px solid #ccc; margin: 1.4rem 0 0.5rem; }
h3 { margin: 0.8rem 0 0.3rem; } p { margin: 0.4rem 0; }
div.row, div.figs { display: grid; grid-template-columns: repeat(auto-fit, minmax(26rem, 1fr));
  gap: 0.3rem 1.5rem; align-items: start; }
div.row > *, div.figs > * { min-width: 0; }
details { margin: 0.4rem 0; } summary { cursor: pointer; color: #036; }
div.fix { border: 2px solid #036; background: #eef4fb; padding: 0.5rem 0.8rem;
  border-radius: 0.3rem; margin: 0.6rem 0; font-size: 1.05rem; }
ul.fixes li, ul.findings li { margin: 0.15rem 0; }
nav a { margin-right: 0.8rem; white-space: nowrap; }
table { border-collapse: collapse; margin: 0.6rem 0; }
th, td { border: 1px solid #ddd; padding: 0.2rem 0.6rem; text-align: left; }
td.n { text-align: right; font-variant-numeric: tabular-nums; }
figure { margin: 0.4rem 0; } figure img { max-width: 100%; height: auto; }
figcaption, .muted { color: #666; font-size: 0.9rem; }
code { overflow-wrap: anywhere; }
.bad { color: #b00; font-weight: bold; }
.level { font-weight: bold; padding: 0 0.3rem; border-radius: 0.2rem; color: #fff; }
.level-fail { background: #b00; } .level-warn { background: #c70; }
.level-pass { background: #080; } .level-info { background: #777; }
p.verdict { border-left: 0.35rem solid #777; padding: 0.3rem 0.6rem; background: #f6f6f6;
  margin: 0.4rem 0; }
p.verdict-fail { border-color: #b00; background: #fdecec; }
p.verdict-warn { border-color: #c70; background: #fdf4e6; }
p.verdict-pass { border-color: #080; background: #edf7ed; }
div.overall { font-size: 1.25rem; font-weight: bold; padding: 0.5rem 0.8rem; color: #fff;
  border-radius: 0.3rem; margin: 0.6rem 0; }
div.overall-fail { background: #b00; } div.overall-warn { background: #c70; }
div.overall-pass { background: #080; } div.overall-info { background: #777; }
.topic { font-weight: bold; }
div.native-box { display: inline-block; overflow: auto; max-height: 80vh; max-width: 100%;
  border: 1px solid #ccc; margin: 0.4rem 0; }
img.native { image-rendering: pixelated; max-width: none; display: block; }
ul.warnings li { color: #8a5200; }
"""


def _img(figures: Mapping[str, bytes], key: str, missing: str = f"Figure {NOT_COMPUTED}."
         ) -> str:
    """The figure `key` with its caption (FIGURE_KEYS, the one place captions are written), or
    one line saying that it is missing (and why, when `missing` says)."""
    data = figures.get(key)
    if data is None:
        return f'<p class="muted">{e(missing)}</p>'
    encoded = base64.b64encode(data).decode("ascii")
    caption = FIGURE_KEYS[key]
    return (f'<figure><img id="fig-{e(key)}" alt="{e(caption)}" '
            f'src="data:image/png;base64,{encoded}">'
            f"<figcaption>{e(caption)}</figcaption></figure>")


def _topic(topic: str) -> str:
    return topic[:1].upper() + topic[1:]


def _badge(level: str) -> str:
    return f'<span class="level level-{level}">{LEVEL_WORDS[level]}</span> '


def _verdict_html(verdict: Verdict) -> str:
    """A judged verdict: a coloured box with its badge, topic and text (its reason; the page
    lists its fixes apart)."""
    topic = f'<span class="topic">{e(_topic(verdict.topic))}:</span> ' if verdict.topic else ""
    return (f'<p class="verdict verdict-{verdict.level}">{_badge(verdict.level)}{topic}'
            f"{e(verdict.text)}</p>")


def _recommended_html(plan: FixPlan) -> str:
    """The one recommended fix, in a box, naming the check it addresses."""
    if plan.recommended is None or plan.deciding is None:
        return ""
    deciding = plan.deciding
    return (f'<div class="fix" id="recommended-fix"><b>Recommended fix</b> (for the '
            f"{e(deciding.topic)} check, {LEVEL_WORDS[deciding.level]}): "
            f"{e(plan.recommended)}</div>")


def _alternatives_html(plan: FixPlan) -> str:
    """The other fixes the failing and warning checks propose, each with its check."""
    if not plan.alternatives:
        return ""
    return ('<h3>Other fixes</h3><ul class="fixes" id="other-fixes">' + "".join(
        f'<li><span class="topic">{e(_topic(topic))}:</span> {e(fix)}</li>'
        for topic, fix in plan.alternatives) + "</ul>")


def _verdict_section(lines: Sequence[Verdict]) -> str:
    """The overall verdict, the recommended fix, each judged finding worst first, the other
    fixes, then the findings without a judgement."""
    level = overall_level(lines)
    counts = ", ".join(f"{sum(v.level == k for v in lines)} {k}" for k in JUDGED
                       if any(v.level == k for v in lines))
    headline = {"fail": "FAIL: do not make this part as it is",
                "warn": "WARN: usable, with the reservations below",
                "pass": "PASS: every check passed",
                "info": "No judged checks"}[level]
    plan = fix_plan(lines)
    out = [f'<div class="overall overall-{level}">{e(headline)}'
           + (f" ({e(counts)})" if counts else "") + "</div>", _recommended_html(plan)]
    judged = sorted((v for v in lines if v.level != "info"), key=lambda v: LEVELS.index(v.level))
    out += [_verdict_html(v) for v in judged]
    out.append(_alternatives_html(plan))
    findings = [v for v in lines if v.level == "info"]
    if findings:
        topics = ", ".join(dict.fromkeys(v.topic for v in findings if v.topic))
        out.append(folded(
            f"Findings without a judgement ({len(findings)})" + (f": {e(topics)}" if topics
                                                                  else ""),
            '<ul class="findings">' + "".join(f"<li>{e(v.text)}</li>" for v in findings)
            + "</ul>"))
    return "".join(out)


def _cell(value: Any, digits: int) -> str:
    return NOT_COMPUTED if value is None else f"{value:.{digits}f}"


def _eye_table(block: Mapping[str, Any]) -> str:
    """The headline table: per variant (and target), PSNR p10 / median / p90, SSIM p10 and the
    nominal PSNR; 0.1 dB and 0.01 SSIM."""
    targets = block["targets"]
    several = len(targets) > 1
    header = ["variant", *(["target"] if several else []), "PSNR p10 (dB)",
              "PSNR median (dB)", "PSNR p90 (dB)", "SSIM p10", "PSNR nominal (dB)"]
    rows = []
    for variant, values in block["variants"].items():
        for t, name in enumerate(targets):
            psnr, ssim = values["psnr_db"], values["ssim"]
            rows.append([e(EYE_VARIANT_LABELS.get(variant, variant)),
                         *([e(name)] if several else []),
                         _cell(psnr["p10"][t], 1), _cell(psnr["p50"][t], 1),
                         _cell(psnr["p90"][t], 1), _cell(ssim["p10"][t], 2),
                         _cell(values["nominal_psnr_db"][t], 1)])
    first = 2 if several else 1
    return table(header, rows, numeric=tuple(range(first, first + 5)))


def _nominal_table(metrics: Mapping[str, Any]) -> str:
    """The fallback headline: the nominal eye point's figures of the same variants."""
    rows = [[e(EYE_VARIANT_LABELS[v]), _cell(metrics[v]["mean"]["psnr_db"], 1),
             _cell(metrics[v]["mean"]["ssim"], 2)]
            for v in EYE_VARIANTS if v in metrics]
    return table(["variant", "PSNR nominal (dB), mean over targets", "SSIM nominal"], rows,
                 numeric=(1, 2))


def _eyes_html(report: Report, figures: Mapping[str, bytes],
               verdict: Verdict | None) -> str:
    """The table over the eye distribution, its verdict's level (the text leads the page),
    then the figures."""
    block = report.eye_distribution
    pointer = "" if verdict is None else (
        f'<p class="verdict verdict-{verdict.level}">{_badge(verdict.level)}'
        f'<a href="#verdict">The verdict on the eye distribution</a> leads the page.</p>')
    if block is None:
        return _nominal_table(report.metrics) + pointer
    d = block["distribution"]
    note = (f'<p class="muted">Percentiles over {block["states"]} eye states, a Halton set '
            f"covering the distribution ({e(describe_distribution(d))}), equally weighted; "
            "every variant is judged over the same states with one display content for all of them "
            "(untracked); nominal: the nominal eye point. Not judged here: the same plate "
            "designed for the nominal eye point only (a second optimization; the quality "
            "benchmark compares with it), and tracked displays.</p>")
    no_box = d["eyebox_mm"][0] == 0 and d["eyebox_mm"][1] == 0
    return "".join([
        _eye_table(block), pointer, note,
        figure_grid([
            _img(figures, "eye_map", "No eyebox map: the eyebox has zero size (eyebox_mm = "
                 "[0, 0])." if no_box else f"Figure {NOT_COMPUTED}."),
            _img(figures, "eye_pupil"), _img(figures, "eye_focus"),
            _img(figures, "eye_thumbnails")]),
    ])


def made_html(block: Mapping[str, Any] | None, figures: Mapping[str, bytes]) -> str:
    """The part as made beside the best regular array at its light: a table and the front."""
    if block is None:
        return (f'<p class="muted">The part as made {NOT_COMPUTED} (validation.made_copies = 0, '
                "or a part forced past its process's rules).</p>")
    part, best = block["part"], block["regular"]["best"]
    rows = [("the part as made", part["p10_db"], part["p50_db"], part["p90_db"],
             part["efficiency"], part["eye_level"])]
    if best is not None:
        rows.append((f"best regular array at least as bright at the eye: {best['pitch_mm']:g} "
                     f"mm pitch, {1000 * best['diameter_mm']:.0f} um holes, display fitted",
                     best["p10_db"], best["p50_db"], best["p90_db"], best["efficiency"],
                     best["eye_level"]))
    cells = "".join(
        f"<tr><td>{e(name)}</td>" + "".join(
            f'<td class="n">{" / ".join(f"{v:.1f}" for v in values)}</td>'
            for values in (p10, p50, p90))
        + f'<td class="n">{100 * white:.3g} %</td><td class="n">{100 * eye:.3g} %</td></tr>'
        for name, p10, p50, p90, white, eye in rows)
    margin = block.get("margin_db")
    interval = block.get("margin_interval_db")
    spread = "" if not interval else (
        f"; {100 * COVERAGE:.0f} % interval "
        + " / ".join(f"{low:+.1f} to {high:+.1f}" for low, high in interval)
        + " dB over other made copies and eye states (a bootstrap of the judged ones)")
    note = ("" if margin is None else
            "<p>Margin over it (at equal or more light at the eye): <b>"
            f"{' / '.join(f'{m:+.1f}' for m in margin)} dB</b> (per target){spread}, "
            f"{e(family_reach(block))}.</p>")
    return figure_grid([
        f"<p>PSNR after gain over {block['copies']} made copies (the process's radius and "
        f"position errors drawn afresh for each) x {block['states']} eye states, with "
        "diffraction at the holes and the veil the plate's material leaks. Light: for a white "
        "display (the plate's efficiency), and at the eye with the content each shows (a share "
        "of the panel's white), by which the plates are compared: a dark content dims the view "
        "as much as small holes do. Not modelled: " + e("; ".join(block["neglected"])) + ".</p>"
        "<table><tr><th>plate</th><th>p10 (dB)</th><th>p50 (dB)</th><th>p90 (dB)</th>"
        f"<th>light, white</th><th>light at the eye</th></tr>{cells}</table>{note}",
        _img(figures, "made_front")])


def _header(report: Report, targets: Sequence[str]) -> str:
    """The part, its process, the date and the command that made the report."""
    run = report.run
    process = report.fabrication["process"]
    if run is None:
        return (f"<h1>Validation report</h1><p>Process <b>{e(process)}</b>; targets "
                f"{e(', '.join(targets))}.</p>")
    command = run["command"]
    return (f"<h1>Validation report: {e(run['part'])}</h1>"
            f"<p>Process <b>{e(process)}</b>; targets {e(', '.join(targets))}; made "
            f'<span class="date">{e(run["date"])}</span>.<br>Command: '
            + ("<i>not recorded (called from Python)</i>" if command is None
               else f"<code>{e(command)}</code>") + "</p>")


def _check_images(figures: Mapping[str, bytes], displays: Mapping[str, bytes]) -> None:
    for key, data in figures.items():
        if key not in FIGURE_KEYS:
            raise ValueError(f"figure {key!r} is not one the page places; allowed: "
                             f"{', '.join(FIGURE_KEYS)}.")
        if not (isinstance(data, bytes) and data.startswith(PNG_SIGNATURE)):
            raise ValueError(f"figure {key!r} is not PNG bytes; make it with figure_*().")
    for name, data in displays.items():
        if not (isinstance(data, bytes) and data.startswith(PNG_SIGNATURE)):
            raise ValueError(f"display {name!r} is not PNG bytes; encode it with "
                             "aperture_fab.io.images.encode_png.")


def _sections(shown: Sequence[tuple[str, str]], body: Mapping[str, str | None]) -> str:
    """The sections in order, each pair of PAIRED_SECTIONS side by side when both are shown,
    one after the other."""
    keys = [key for key, _ in shown]
    html = {key: f'<section id="{key}"><h2>{e(heading)}</h2>{body[key]}</section>'
            for key, heading in shown}
    out: list[str] = []
    i = 0
    while i < len(keys):
        pair = tuple(keys[i:i + 2])
        if pair in PAIRED_SECTIONS:
            out.append(side_by_side([html[k] for k in pair]))
            i += 2
        else:
            out.append(html[keys[i]])
            i += 1
    return "\n".join(out)


def report_html(report: Report, figures: Mapping[str, bytes],
                displays: Mapping[str, bytes] | None = None) -> str:
    """One self-contained HTML page: inline CSS, images as data:image/png;base64, no script.

    The page leads with the report's overall verdict and every judged one, worst first.
    figures: PNG bytes keyed by FIGURE_KEYS; a missing one is shown as "not computed".
    displays: {target name: PNG of the display content}, shown at native resolution.
    """
    displays = {} if displays is None else displays
    _check_images(figures, displays)
    targets = sorted({n for b in report.metrics.values() for n in b["per_target"]})
    lines = report.verdicts
    lead = next((v for v in lines if v.topic == EYE_TOPIC), None)
    tolerance = report.tolerance
    # None: nothing to show, so the section is left out.
    body: dict[str, str | None] = {
        "verdict": _verdict_section(lines) if lines else f'<p class="muted">{NOT_COMPUTED}.</p>',
        "made": made_html(report.made_part, figures),
        "light": light_html(report.photometry),
        "eyes": _eyes_html(report, figures, lead),
        "views": _img(figures, "views"),
        "errors": _img(figures, "errors"),
        "metrics": metrics_html(report.metrics),
        "plate": _img(figures, "hole_map") + folded(
            "The plate's geometry", pairs(report.scene["plate"])),
        "display": display_html(displays, report.scene["display"]),
        "loss": _img(figures, "loss"),
        # Only with several eye positions (eye.positions_mm); the eye distribution covers the
        # eyebox otherwise.
        "eyebox": _img(figures, "eyebox") if "eyebox" in figures else None,
        "tolerance": (f'<p class="muted">Tolerance analysis {NOT_COMPUTED}.</p>'
                      if tolerance is None else
                      _img(figures, "tolerance") + tolerance_table(tolerance)),
        "fabrication": fabrication_html(report.fabrication),
        "mesh": mesh_html(report.mesh) + (_img(figures, "mesh_retrace")
                                          if "mesh_retrace" in figures else ""),
        "timings": timings_html(report.timings_s),
        "scene": scene_html(report.scene),
        "config": config_html(report.config, report.versions),
    }
    shown = [(key, heading) for key, heading in SECTION_TITLES if body[key] is not None]
    nav = " ".join(f'<a href="#{key}">{e(heading)}</a>' for key, heading in shown)
    sections = _sections(shown, body)
    digest = hashlib.sha256(json.dumps(report.as_json(), sort_keys=True).encode()).hexdigest()
    run = report.run
    title = "aperture-fab validation report" + ("" if run is None else f": {run['part']}")
    return f"""<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta http-equiv="Content-Security-Policy" content="{CSP}">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{e(title)}</title>
<style>{CSS}</style>
</head>
<body>
<main>
{_header(report, targets)}
<p class="muted">Schema {SCHEMA_VERSION}; report digest {digest[:12]}.</p>
<nav>{nav}</nav>
{sections}
</main>
</body>
</html>
"""
