"""A sweep's results: one row per point, the Pareto front, and a page to browse them.

The figures come from each design job's report.json (the part as built, judged over the eye
distribution), so the sweep ranks designs by what the validation measured, not by the
optimizer's loss. Brightness is light_efficiency (the view's level as a share of the open
display's) and, where the report has its photometry block, the luminance the eye sees for the
config's panel ([photometry] panel_luminance_cd_m2), the retinal illuminance and the contrast
left by the light the plate material leaks.

Files, each written atomically: results.csv and results.parquet (every point), pareto.csv (the
non-dominated ok points over the objectives), sweep.html (the Pareto plot, each point a link to
its points/<id>/report.html, and the table).
"""

from __future__ import annotations

import csv
import html
import io
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from aperture_fab.sweep.spec import FIGURES, Point, SweepSpec

__all__ = ["FIGURE_HELP", "figures_from_report", "summary_line", "dominates", "pareto_mask",
           "table_rows", "write_results", "TableLog", "note"]

#: What each figure means (the docs and the page repeat it).
FIGURE_HELP: dict[str, str] = {
    "eye_p10_psnr_db": "PSNR after gain (dB) of the part as built, 10th percentile over the eye "
                       "distribution (mean over targets): the sharpness most eyes get at least",
    "eye_p50_psnr_db": "the same, median",
    "eye_p90_psnr_db": "the same, 90th percentile",
    "nominal_psnr_db": "PSNR after gain (dB) of the part as built at the nominal eye point",
    "light_efficiency": "view level of the part as built / open display level (brightness "
                        "share; times the panel's luminance gives the luminance seen)",
    "luminance_cd_m2": "luminance the eye sees through the part, cd/m2, for the config's panel "
                       "luminance and the content shown (report photometry block)",
    "retinal_illuminance_td": "retinal illuminance, trolands (report photometry block)",
    "contrast_ratio": "contrast left by the light the plate material leaks (report photometry "
                      "block; inf: an opaque plate)",
    "made_p10_psnr_db": "PSNR after gain (dB) of the part as made (made copies with the "
                        "process's errors, diffraction, the material's veil), 10th percentile "
                        "over copies x eye states (mean over targets; report made_part block)",
    "made_p50_psnr_db": "the same, median",
    "made_light_efficiency": "light efficiency of the part as made for a white display",
    "regular_p10_psnr_db": "the same 10th percentile of the best regular pinhole array the "
                           "process makes at least as bright as the part",
    "made_margin_db": "made_p10_psnr_db less regular_p10_psnr_db: what the design gains over "
                      "the best regular array at equal light",
    "fov_x_deg": "horizontal field of view, degrees",
    "fov_y_deg": "vertical field of view, degrees",
    "hole_count": "holes in the part",
    "rule_violations": "process rule violations resolved while making the part",
    "seconds": "wall time of the design job, seconds",
}
BASE_COLUMNS = ("id", "status")
#: attempts: runs of the point (more than 1: its worker or node was lost and it ran again);
#: note: "lost, retried" and what was lost.
TAIL_COLUMNS = ("attempts", "note", "error", "report")
RESULTS_CSV = "results.csv"
PLOT_INCHES = (6.4, 4.4)
#: Characters of a failed point's error shown in the page's table.
ERROR_CHARS = 120


def _mean(values: Sequence[Any] | None) -> float | None:
    kept = [float(v) for v in values or () if v is not None]
    return sum(kept) / len(kept) if kept else None


def figures_from_report(report: Mapping[str, Any]) -> dict[str, Any]:
    """The sweep's figures from a design job's report.json (None where it has none)."""
    metrics = report.get("metrics", {}).get("as_built", {}).get("mean", {})
    eye = report.get("eye_distribution") or {}
    psnr = eye.get("variants", {}).get("as_built", {}).get("psnr_db", {})
    fab = report.get("fabrication") or {}
    fov = report.get("scene", {}).get("eye", {}).get("fov_deg") or [None, None]
    light = report.get("photometry") or {}
    made = report.get("made_part") or {}
    part = made.get("part") or {}
    best = (made.get("regular") or {}).get("best") or {}
    return {
        "eye_p10_psnr_db": _mean(psnr.get("p10")),
        "eye_p50_psnr_db": _mean(psnr.get("p50")),
        "eye_p90_psnr_db": _mean(psnr.get("p90")),
        "nominal_psnr_db": metrics.get("psnr_db"),
        "light_efficiency": metrics.get("light_efficiency"),
        "luminance_cd_m2": light.get("view_luminance_cd_m2"),
        "retinal_illuminance_td": light.get("retinal_illuminance_td"),
        "contrast_ratio": (light.get("leakage") or {}).get("contrast_ratio"),
        "made_p10_psnr_db": _mean(part.get("p10_db")),
        "made_p50_psnr_db": _mean(part.get("p50_db")),
        "made_light_efficiency": part.get("efficiency"),
        "regular_p10_psnr_db": _mean(best.get("p10_db")),
        "made_margin_db": _mean(made.get("margin_db")),
        "fov_x_deg": fov[0],
        "fov_y_deg": fov[1],
        "hole_count": fab.get("holes"),
        "rule_violations": len(fab.get("violations") or ()),
    }


def _num(value: Any, form: str) -> str:
    return "-" if value is None else format(value, form)


def note(record: Mapping[str, Any]) -> str | None:
    """"lost, retried (...)" for a point that ran again after its worker or node was lost,
    "lost (...)" for one that was lost every time; None otherwise."""
    lost = record.get("lost") or []
    if not lost:
        return None
    times = f"{len(lost)} time{'s' if len(lost) > 1 else ''}"
    state = "lost" if record["status"] == "lost" else "lost, retried"
    return f"{state} ({times}: {lost[-1]})"


def summary_line(record: Mapping[str, Any], label: str) -> str:
    """One progress line for a finished point."""
    head = f"{record['status']:<6} {record['id']}  {label}"
    if record["status"] == "lost":
        return f"{head}  LOST: {record['error']}"
    if record["status"] != "ok":
        return f"{head}  FAILED: {record['error']}"
    f = record["figures"]
    light = None if f.get("light_efficiency") is None else 100 * f["light_efficiency"]
    return (f"{head}  eye p10 {_num(f.get('eye_p10_psnr_db'), '.2f')} dB, light "
            f"{_num(light, '.3f')} %, {f.get('hole_count')} holes, "
            f"{_num(record.get('seconds'), '.1f')} s"
            + (f"  [{note(record)}]" if note(record) else ""))


def dominates(a: Sequence[float], b: Sequence[float], maximize: Sequence[bool]) -> bool:
    """a is at least as good as b in every objective and better in one."""
    better = False
    for x, y, up in zip(a, b, maximize, strict=True):
        if (x < y) if up else (x > y):
            return False
        better = better or x != y
    return better


def pareto_mask(values: Sequence[Sequence[float]], maximize: Sequence[bool]) -> list[bool]:
    """Which rows no other row dominates (duplicates of a front point are all on it)."""
    return [not any(dominates(other, row, maximize) for other in values) for row in values]


def _cell(value: Any) -> Any:
    """A table cell: numbers and text as they are, pairs and lists as JSON text."""
    return json.dumps(value) if isinstance(value, (list, tuple, dict)) else value


def table_rows(spec: SweepSpec, points: Sequence[Point],
               records: Mapping[str, Mapping[str, Any]]) -> list[dict[str, Any]]:
    """One row per point in the sweep's order (unfinished points: status "pending")."""
    rows = []
    for point in points:
        record = records.get(point.id)
        figures = record.get("figures", {}) if record else {}
        row: dict[str, Any] = {"id": point.id,
                               "status": record["status"] if record else "pending"}
        row.update({k: _cell(v) for k, v in point.settings})
        row.update({f: figures.get(f) for f in FIGURES})
        row["attempts"] = record.get("attempts", 1) if record else None
        row["note"] = note(record) if record else None
        row["error"] = record.get("error") if record else None
        ok = record is not None and record["status"] == "ok"
        row["report"] = f"points/{point.id}/{'report.html' if ok else 'point.json'}"
        rows.append(row)
    return rows


def _front(spec: SweepSpec, rows: list[dict[str, Any]]) -> tuple[list[dict[str, Any]],
                                                                   list[bool]]:
    """Rows that can be ranked (ok, every objective known) and which are on the front."""
    ranked = [r for r in rows if r["status"] == "ok" and all(  # inf ranks; NaN cannot
        r[o.figure] is not None and not math.isnan(r[o.figure]) for o in spec.objectives)]
    values = [[float(r[o.figure]) for o in spec.objectives] for r in ranked]
    return ranked, pareto_mask(values, [o.maximize for o in spec.objectives])


def _csv(rows: list[dict[str, Any]], columns: list[str]) -> str:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, columns, lineterminator="\n")
    writer.writeheader()
    writer.writerows({c: ("" if r[c] is None else r[c]) for c in columns} for r in rows)
    return buffer.getvalue()


def _parquet(rows: list[dict[str, Any]], columns: list[str]) -> bytes:
    from aperture_fab.sweep.settings import require

    pa = require("pyarrow")
    pq = require("pyarrow.parquet")
    arrays = {}
    for c in columns:
        values = [r[c] for r in rows]
        present = [v for v in values if v is not None]
        if not present:
            arrays[c] = pa.array(values, type=pa.float64() if c in FIGURES else pa.string())
            continue
        if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in present) and \
                any(isinstance(v, float) for v in present):
            values = [None if v is None else float(v) for v in values]
        elif not all(isinstance(v, type(present[0])) for v in present[1:]):
            values = [None if v is None else str(v) for v in values]  # mixed: text
        arrays[c] = pa.array(values)
    buffer = io.BytesIO()
    pq.write_table(pa.table(arrays), buffer)
    return buffer.getvalue()


def _plot_svg(spec: SweepSpec, ranked: list[dict[str, Any]], front: list[bool]) -> str:
    """The Pareto plot as inline SVG: the first two objectives (one: against the point's
    number), dominated points grey, the front highlighted, each point a link to its report."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    objectives = spec.objectives
    fig, ax = plt.subplots(figsize=PLOT_INCHES)
    xs = [r[objectives[0].figure] for r in ranked]
    ys = [r[objectives[1].figure] for r in ranked] if len(objectives) > 1 else \
        list(range(1, len(ranked) + 1))
    for on, colour, label in ((False, "#b0b0b0", "dominated"), (True, "#d62728", "Pareto front")):
        idx = [i for i, f in enumerate(front) if f == on]
        if not idx:
            continue
        dots = ax.scatter([xs[i] for i in idx], [ys[i] for i in idx], c=colour, s=36,
                          label=label, zorder=3 if on else 2, edgecolors="black" if on else "none")
        dots.set_urls([ranked[i]["report"] for i in idx])
    on_front = sorted((xs[i], ys[i]) for i, f in enumerate(front) if f)
    if len(objectives) > 1 and len(on_front) > 1:
        ax.plot(*zip(*on_front, strict=True), color="#d62728", lw=1, alpha=0.6, zorder=1)
    ax.set_xlabel(str(objectives[0]))
    ax.set_ylabel(str(objectives[1]) if len(objectives) > 1 else "point")
    ax.grid(True, alpha=0.3)
    if ranked:
        ax.legend(loc="best", fontsize="small")
    fig.tight_layout()
    buffer = io.StringIO()
    fig.savefig(buffer, format="svg")
    plt.close(fig)
    text = buffer.getvalue()
    return text[text.index("<svg"):]  # inline: no XML prolog or DOCTYPE


def _html(spec: SweepSpec, rows: list[dict[str, Any]], columns: list[str], svg: str,
          front_ids: set[str]) -> str:
    esc = html.escape
    ok = sum(r["status"] == "ok" for r in rows)
    failed = sum(r["status"] in ("failed", "lost") for r in rows)
    objectives = ", ".join(str(o) for o in spec.objectives)
    extra = "" if len(spec.objectives) < 3 else (
        f"<p>The plot shows the first two of {len(spec.objectives)} objectives; the front is "
        "computed over all of them.</p>")
    head = "".join(f"<th>{esc(c)}</th>" for c in columns)
    body = []
    for r in rows:
        cells = []
        for c in columns:
            value = r[c]
            text = "" if value is None else (f"{value:.4g}" if isinstance(value, float)
                                             else str(value))
            if c == "id":
                text = f'<a href="{esc(r["report"])}">{esc(text)}</a>'
            elif c == "error" and len(text) > ERROR_CHARS:  # in full: hover, or the CSV
                short = esc(text[:ERROR_CHARS])
                cells.append(f'<td class="err" title="{esc(text)}">{short}...</td>')
                continue
            elif c != "report":
                text = esc(text)
            else:
                continue
            cells.append(f"<td>{text}</td>")
        cls = ' class="front"' if r["id"] in front_ids else ""
        body.append(f"<tr{cls}>{''.join(cells)}</tr>")
    legend = "".join(f"<li><b>{esc(k)}</b>: {esc(v)}</li>" for k, v in FIGURE_HELP.items())
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>aperture-fab sweep</title>
<style>body{{font-family:sans-serif;margin:1.5em;max-width:100em}}
table{{border-collapse:collapse;font-size:0.85em}}td,th{{border:1px solid #ccc;padding:2px 6px}}
tr.front{{background:#fde8e8}}td.err{{min-width:28em;font-size:0.85em}}svg{{max-width:100%;height:auto}}</style></head><body>
<h1>Sweep {esc(spec.source.name)}</h1>
<p>{len(rows)} points ({ok} ok, {failed} failed or lost, {len(rows) - ok - failed} not run);
mode {esc(spec.mode)}; objectives: {esc(objectives)}; {len(front_ids)} point(s) on the Pareto
front (highlighted). Click a point in the plot or an id in the table for its report.</p>
{extra}{svg}
<h2>Points</h2><div style="overflow-x:auto"><table><tr>{head.replace("<th>report</th>", "")}</tr>
{chr(10).join(body)}</table></div>
<h2>Figures</h2><ul>{legend}</ul></body></html>
"""


def write_results(out: Path, spec: SweepSpec, points: Sequence[Point],
                  records: Mapping[str, Mapping[str, Any]]) -> dict[str, Path]:
    """Write results.csv, results.parquet, pareto.csv and sweep.html; return their paths."""
    from aperture_fab.io.atomic import write_atomic

    rows = table_rows(spec, points, records)
    columns = list(rows[0]) if rows else [*BASE_COLUMNS, *spec.swept_keys, *FIGURES,
                                          *TAIL_COLUMNS]
    ranked, front = _front(spec, rows)
    front_rows = [r for r, f in zip(ranked, front, strict=True) if f]
    paths = {name: out / name for name in (RESULTS_CSV, "results.parquet", "pareto.csv",
                                           "sweep.html")}
    write_atomic(paths[RESULTS_CSV], _csv(rows, columns))
    write_atomic(paths["pareto.csv"], _csv(front_rows, columns))
    if rows:
        write_atomic(paths["results.parquet"], _parquet(rows, columns))
    else:
        del paths["results.parquet"]
    svg = _plot_svg(spec, ranked, front)
    write_atomic(paths["sweep.html"], _html(spec, rows, columns, svg,
                                            {r["id"] for r in front_rows}))
    return paths


def columns_of(spec: SweepSpec) -> list[str]:
    """The table's columns, in order."""
    return [*BASE_COLUMNS, *spec.swept_keys, *FIGURES, *TAIL_COLUMNS]


class TableLog:
    """results.csv kept current while a sweep runs: `start` writes the points finished before,
    `append` adds one row as each point finishes (a killed driver loses no finished point),
    and `refresh` rewrites every table (at most every refresh_s seconds: the page's plot
    costs a fraction of a second). write_results at the end puts the rows in the sweep's
    order, with the points not run."""

    def __init__(self, out: Path, spec: SweepSpec, refresh_s: float,
                 clock: Any = None) -> None:
        import time

        self.out, self.spec, self.refresh_s = out, spec, refresh_s
        self.clock = clock or time.monotonic
        self.columns = columns_of(spec)
        self.last = self.clock()

    def start(self, points: Sequence[Point], records: Mapping[str, Mapping[str, Any]]) -> None:
        from aperture_fab.io.atomic import write_atomic

        rows = table_rows(self.spec, [p for p in points if p.id in records], records)
        write_atomic(self.out / RESULTS_CSV, _csv(rows, self.columns))

    def append(self, point: Point, record: Mapping[str, Any]) -> None:
        import os

        text = _csv(table_rows(self.spec, [point], {point.id: record}), self.columns)
        with open(self.out / RESULTS_CSV, "a", encoding="utf-8") as table:
            table.write(text.split("\n", 1)[1])  # the row, not the header
            table.flush()
            os.fsync(table.fileno())

    def refresh(self, points: Sequence[Point], records: Mapping[str, Mapping[str, Any]],
                force: bool = False) -> None:
        if force or self.clock() - self.last >= self.refresh_s:
            write_results(self.out, self.spec, [p for p in points if p.id in records], records)
            self.last = self.clock()
