"""The validation report for people: verdicts in plain words and the self-contained HTML page.

Pure functions, the report.json structure (aperture_fab.validation.report) and PNG figures
(aperture_fab.validation.figures) in, text out; the pipeline writes report.html.
"""

from __future__ import annotations

import base64
import hashlib
import html
import json
from collections.abc import Mapping, Sequence
from typing import Any

from aperture_fab.validation.report import (
    EYE_TOPIC,
    EYE_VARIANT_LABELS,
    EYE_VARIANTS,
    FABRICATION_KEYS,
    FIGURE_KEYS,
    PERCENTILES,
    VARIANT_LABELS,
    Verdict,
    json_ready,
    validate_report,
)
from aperture_fab.validation.variants import EYE_BASELINES

__all__ = ["SECTION_TITLES", "CSP", "EYE_MARGIN_DB", "verdicts", "eye_verdict", "report_html"]

#: The page's sections, top to bottom: (id, heading).
SECTION_TITLES: tuple[tuple[str, str], ...] = (
    ("eyes", "Over the eye distribution"),
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
#: The part's 10th-percentile PSNR within this many dB above a baseline's is a warning (amber);
#: below it, a failure (red).
EYE_MARGIN_DB = 1.0
#: What the page and the terminal call each level.
LEVEL_WORDS = {"fail": "FAIL", "warn": "WARN", "pass": "PASS", "info": "NOTE"}
NOT_JUDGED = ("Not judged over the eye distribution (validation.eye_states = 0): every figure "
              "below is for the nominal eye point only, which can look far better than what a "
              "moving eye sees. Set [validation] eye_states (default 32) to judge the part over "
              "the eye distribution.")

# ---------------------------------------------------------------------------------------------
# Verdicts in words


def _mean(report: Mapping[str, Any], variant: str, key: str = "psnr_db") -> float | None:
    block = report["metrics"].get(variant)
    value = None if block is None else block["mean"].get(key)
    return None if value is None else float(value)


def _compare(difference: float, what: str) -> str:
    return f"{abs(difference):.1f} dB {'better' if difference >= 0 else 'worse'} than {what}"


def _range(values: Sequence[float], unit: str) -> str:
    lo, hi = values
    return f"{lo:g} {unit}" if lo == hi else f"{lo:g} to {hi:g} {unit}"


def _describe(distribution: Mapping[str, Any]) -> str:
    """The eye distribution in words: eyebox, pupils, focus, gaze."""
    w, h = distribution["eyebox_mm"]
    box = (f"eyebox {w:g} x {h:g} mm {distribution['eyebox_shape']}" if w or h
           else "no eyebox (a fixed pupil position)")
    parts = [box, "pupil " + _range(distribution["pupil_range_mm"], "mm"),
             "focus " + _range(distribution["focus_range_diopters"], "D")]
    if distribution["gaze_deg"]:
        parts.append(f"gaze up to {distribution['gaze_deg']:g} deg")
    return ", ".join(parts)


def _eye_advice(report: Mapping[str, Any]) -> str:
    """What to change when the part does not beat the baselines over the eye distribution."""
    plate = report["scene"]["plate"]
    optimizer = report["config"].get("optimizer", {})
    w, h = report["eye_distribution"]["distribution"]["eyebox_mm"]
    steps = []
    if optimizer.get("eye_states") == 1:
        steps.append("design for the distribution rather than the nominal eye point "
                     "(optimizer.eye_states > 1, as in the near-eye preset)")
    steps.append(f"check that the eyebox ([eye] eyebox_mm = [{w:g}, {h:g}]), pupil_range_mm and "
                 "focus_range_diopters describe the device; widen or shrink them only if they "
                 "do not (a smaller eyebox than the device has only flatters the report)")
    pitch = plate["pitch_mm"]
    steps.append(f"a smaller pitch (plate.pitch_mm, now {pitch[0]:g} x {pitch[1]:g} mm) or a "
                 f"larger gap (plate.gap_mm, now {plate['gap_mm']:g} mm), then design again")
    if optimizer.get("tracking") != "tracked":
        steps.append('or a tracked display (optimizer.tracking = "tracked", shown with '
                     "`aperture-fab display`), whose content follows the tracked eye")
    return "What to change: " + "; ".join(steps) + "."


def eye_verdict(report: Mapping[str, Any]) -> Verdict:
    """The leading verdict: does the part beat the baselines over the eye distribution?

    Red (fail) when the part's 10th-percentile PSNR is below the open display's or the regular
    pinhole array's for any target; amber (warn) when it is less than EYE_MARGIN_DB above one;
    green (pass) otherwise. The worst target and baseline are named. Without the eye
    distribution (null in the report) a note says that the figures are nominal only.
    """
    block = report.get("eye_distribution")
    if block is None:
        return Verdict(EYE_TOPIC, "info", NOT_JUDGED)
    variants, targets = block["variants"], block["targets"]
    part = next((v for v in ("as_built", "quantized", "optimized") if v in variants), None)
    if part is None:
        return Verdict(EYE_TOPIC, "info", "No part was judged over the eye distribution; "
                       f"judged: {', '.join(variants)}.")
    psnr = variants[part]["psnr_db"]
    margins = []  # (margin dB, target index, baseline)
    for t in range(len(targets)):
        own = psnr["p10"][t]
        for baseline, _ in EYE_BASELINES:
            other = variants.get(baseline, {}).get("psnr_db", {}).get("p10", [None] * (t + 1))[t]
            if own is not None and other is not None:
                margins.append((own - other, t, baseline))
    where = (f"Over the eye distribution ({block['states']} states: "
             f"{_describe(block['distribution'])})")
    if not margins:
        return Verdict(EYE_TOPIC, "info", f"{where}, no baseline was judged the same way; the "
                       "part's 10th percentile cannot be compared.")
    low, worst, _ = min(margins)
    name = f" for target {targets[worst]!r}" if len(targets) > 1 else ""
    words = "the part as built" if part == "as_built" else f"the part ({part})"
    nominal = variants[part]["nominal_psnr_db"][worst]
    baselines = dict(EYE_BASELINES)
    text = (f"{where}, {words} scores {psnr['p10'][worst]:.1f} dB PSNR at the 10th percentile"
            f"{name} (median {psnr['p50'][worst]:.1f}, 90th {psnr['p90'][worst]:.1f}"
            + ("" if nominal is None else f"; {nominal:.1f} at the nominal eye point")
            + "), against " + " and ".join(
                f"{variants[b]['psnr_db']['p10'][worst]:.1f} dB for {baselines[b]} ({m:+.1f} dB)"
                for m, t, b in margins if t == worst))
    if low < 0:
        beaten = " and ".join(baselines[b] for b, _ in EYE_BASELINES
                              if any(m < 0 and key == b for m, _, key in margins))
        return Verdict(EYE_TOPIC, "fail", text + f". Its 10th percentile is below that of "
                       f"{beaten}: for the worst tenth of eye states the plate does no better "
                       f"than {beaten}. " + _eye_advice(report))
    if low < EYE_MARGIN_DB:
        return Verdict(EYE_TOPIC, "warn", text + f". Less than {EYE_MARGIN_DB:g} dB above a "
                       "baseline at the 10th percentile: a slightly worse part or eye loses the "
                       "advantage. " + _eye_advice(report))
    return Verdict(EYE_TOPIC, "pass", text + f". At least {EYE_MARGIN_DB:g} dB above every "
                   "baseline judged the same way, for every target.")


def verdicts(report: Mapping[str, Any], diffraction_blur_px: float | None = None,
             diffraction_hole_mm: float | None = None) -> list[Verdict]:
    """Findings in plain language, most important first: the part over the eye distribution
    (`eye_verdict`), the tolerance yield, then the nominal eye point's figures, fabrication and
    mesh.

    diffraction_blur_px: diffraction blur of the holes named by diffraction_hole_mm, in view
        pixels (None: not computed, no line).
    diffraction_hole_mm: the hole diameter that blur is for; None takes the smallest hole.
    """
    lines: list[Verdict] = [eye_verdict(report)]

    def say(topic: str, text: str, level: str = "info") -> None:
        lines.append(Verdict(topic, level, text))

    tolerance = report["tolerance"]
    if tolerance is not None:
        threshold = tolerance["threshold_db"]
        text = (f"Yield at {threshold:.1f} dB over {tolerance['samples']} tolerance "
                f"samples: {100 * tolerance['yield']:.0f} %.")
        low, median = tolerance["psnr_percentiles"]["5"], tolerance["psnr_percentiles"]["50"]
        if low is not None and median is not None:
            text += f" Median {median:.1f} dB; 1 part in 20 scores below {low:.1f} dB."
        say("tolerance", text)
    head = next(((v, words) for v, words in HEADLINE_VARIANTS
                 if _mean(report, v) is not None), None)
    if head is not None:
        variant, words = head
        psnr = _mean(report, variant)
        assert psnr is not None
        ssim = _mean(report, variant, "ssim")
        text = f"At the nominal eye point, {words.lower()}, the view scores {psnr:.1f} dB PSNR"
        text += "" if ssim is None else f" (SSIM {ssim:.2f})"
        baselines = [(_mean(report, "open"), "the open display"),
                     (_mean(report, "regular_pinholes"), "a regular pinhole array")]
        compared = [_compare(psnr - value, what) for value, what in baselines if value is not None]
        say("nominal", text + (", " + " and ".join(compared) if compared else "") + ".")
        optimized = _mean(report, "optimized")
        if variant != "optimized" and optimized is not None:
            cause = "Quantization and fabrication" if variant == "as_built" else "Quantization"
            cost = optimized - psnr
            say("fabrication cost", f"{cause} cost {cost:.1f} dB." if cost >= 0 else
                f"{cause} cost nothing: the view is {-cost:.1f} dB better than the "
                "optimized design's.")
        efficiency = _mean(report, variant, "light_efficiency")
        if efficiency is not None:
            say("light", f"The eye sees {100 * efficiency:.2g} % of the light of the open "
                "display.")
    built = _mean(report, "as_built")
    drawn, traced = _mean(report, "quantized"), _mean(report, "as_built_mesh")
    if drawn is not None and traced is not None:
        noise = report.get("mesh_retrace_stderr_rms")
        say("mesh trace", "Traced through the written mesh (the holes as drawn), the view "
            f"scores {traced:.1f} dB ({traced - drawn:+.1f} dB from the hole layout's)"
            + (f"; Monte Carlo noise {noise:.2g} RMS per pixel: more rays per pixel sharpen "
               "this check (--mesh-samples)." if noise else "."))
    diffracted = _mean(report, "as_built_diffraction")
    if built is not None and diffracted is not None:
        say("diffraction", f"With diffraction, the as-built view scores {diffracted:.1f} dB "
            f"({diffracted - built:+.1f} dB from the geometric trace).")
    hole_mm = diffraction_hole_mm
    if hole_mm is None:
        hole_mm = report["fabrication"].get("smallest_hole_diameter_mm")
    if diffraction_blur_px is not None and hole_mm is not None:
        say("diffraction", f"Holes of {hole_mm:.3f} mm: diffraction blurs them by about "
            f"{diffraction_blur_px:.1f} view pixels.")
    fabrication = report["fabrication"]
    violations = fabrication["violations"]
    if violations:
        counts: dict[str, int] = {}
        for violation in violations:
            counts[violation["rule"]] = counts.get(violation["rule"], 0) + 1
        rules = ", ".join(f"{rule} x{n}" for rule, n in counts.items())
        say("fabrication", f"{len(violations)} fabrication rule violations of the "
            f"{fabrication['process']} process were resolved ({rules}); see Fabrication checks.")
    else:
        say("fabrication", f"The {fabrication['holes']} holes meet every rule of the "
            f"{fabrication['process']} process.")
    mesh = report["mesh"]
    if mesh["watertight"]:
        per_hole = " (one per hole)" if mesh["genus"] == fabrication["holes"] else ""
        say("mesh", f"The mesh is watertight, genus {mesh['genus']}{per_hole}, "
            f"{mesh['triangles']} triangles.")
    else:
        say("mesh", "The mesh is NOT watertight: do not print it; please report this design.",
            "fail")
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
.level { font-weight: bold; padding: 0 0.3rem; border-radius: 0.2rem; color: #fff; }
.level-fail { background: #b00; } .level-warn { background: #c70; }
.level-pass { background: #080; } .level-info { background: #777; }
p.verdict { border-left: 0.35rem solid #777; padding: 0.3rem 0.6rem; background: #f6f6f6; }
p.verdict-fail { border-color: #b00; background: #fdecec; }
p.verdict-warn { border-color: #c70; background: #fdf4e6; }
p.verdict-pass { border-color: #080; background: #edf7ed; }
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


def _img(figures: Mapping[str, bytes], key: str, missing: str = f"Figure {NOT_COMPUTED}."
         ) -> str:
    data = figures.get(key)
    if data is None:
        return f'<p class="muted">{_e(missing)}</p>'
    encoded = base64.b64encode(data).decode("ascii")
    caption = FIGURE_KEYS[key]
    return (f'<figure><img id="fig-{_e(key)}" alt="{_e(caption)}" '
            f'src="data:image/png;base64,{encoded}">'
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


def _as_verdict(line: Verdict | str) -> Verdict:
    return line if isinstance(line, Verdict) else Verdict("", "info", str(line))


def _verdict_html(verdict: Verdict, tag: str = "li") -> str:
    """A verdict with its level as a coloured badge (none for plain findings)."""
    badge = ("" if verdict.level == "info" and verdict.topic != EYE_TOPIC else
             f'<span class="level level-{verdict.level}">{LEVEL_WORDS[verdict.level]}</span> ')
    css = f' class="verdict verdict-{verdict.level}"' if tag == "p" else ""
    return f"<{tag}{css}>{badge}{_e(verdict.text)}</{tag}>"


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
            rows.append([_e(EYE_VARIANT_LABELS.get(variant, variant)),
                         *([_e(name)] if several else []),
                         _cell(psnr["p10"][t], 1), _cell(psnr["p50"][t], 1),
                         _cell(psnr["p90"][t], 1), _cell(ssim["p10"][t], 2),
                         _cell(values["nominal_psnr_db"][t], 1)])
    first = 2 if several else 1
    return _table(header, rows, numeric=tuple(range(first, first + 5)))


def _nominal_table(metrics: Mapping[str, Any]) -> str:
    """The fallback headline: the nominal eye point's figures of the same variants."""
    rows = [[_e(EYE_VARIANT_LABELS[v]), _cell(metrics[v]["mean"]["psnr_db"], 1),
             _cell(metrics[v]["mean"]["ssim"], 2)]
            for v in EYE_VARIANTS if v in metrics]
    return _table(["variant", "PSNR nominal (dB), mean over targets", "SSIM nominal"], rows,
                  numeric=(1, 2))


def _eyes_html(report: Mapping[str, Any], figures: Mapping[str, bytes],
               verdict: Verdict | None) -> str:
    """The page's lead: the table over the eye distribution, its verdict, then the figures."""
    block = report["eye_distribution"]
    banner = "" if verdict is None else _verdict_html(verdict, "p")
    if block is None:
        return _nominal_table(report["metrics"]) + banner
    d = block["distribution"]
    note = (f'<p class="muted">Percentiles over {block["states"]} eye states, a Halton set '
            f"covering the distribution ({_e(_describe(d))}), equally weighted; every variant "
            "is judged over the same states with one display content for all of them "
            "(untracked); nominal: the nominal eye point. Not judged here: the same plate "
            "designed for the nominal eye point only (a second optimization; the quality "
            "benchmark compares with it), and tracked displays.</p>")
    no_box = d["eyebox_mm"][0] == 0 and d["eyebox_mm"][1] == 0
    return "".join([
        _eye_table(block), banner, note,
        _img(figures, "eye_map", "No eyebox map: the eyebox has zero size (eyebox_mm = [0, 0])."
             if no_box else f"Figure {NOT_COMPUTED}."),
        _img(figures, "eye_pupil"), _img(figures, "eye_focus"), _img(figures, "eye_thumbnails"),
    ])


def report_html(report: Mapping[str, Any], figures: Mapping[str, bytes],
                verdicts: Sequence[Verdict | str]) -> str:
    """One self-contained HTML page: inline CSS, figures as data:image/png;base64, no script.

    figures: PNG bytes keyed by FIGURE_KEYS; a missing one is shown as "not computed".
    verdicts: findings (see `verdicts`; plain strings are findings without a level): the one on
        the eye distribution leads the page under its table, the others make the summary.
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
    lines = [_as_verdict(v) for v in verdicts]
    lead = next((v for v in lines if v.topic == EYE_TOPIC), None)
    rest = [v for v in lines if v is not lead]
    body: dict[str, str] = {
        "eyes": _eyes_html(report, figures, lead),
        "summary": "<ul class=\"verdicts\">" + "".join(_verdict_html(v) for v in rest)
                   + "</ul>" if rest else f'<p class="muted">{NOT_COMPUTED}.</p>',
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
