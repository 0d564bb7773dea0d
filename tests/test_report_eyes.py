"""The report's headline over the eye distribution: report.json block, verdict, HTML lead, the
design command's terminal table. Synthetic EyeQuality values, so every number is known."""

from __future__ import annotations

import json
from html.parser import HTMLParser
from typing import Any

import numpy as np
import pytest

from aperture_fab.cli.output import print_eye_distribution
from aperture_fab.optics.eyes import EyeDistribution
from aperture_fab.report.evidence import eye_figures
from aperture_fab.report.page import report_html
from aperture_fab.validation.judge import eye_distribution_block
from aperture_fab.validation.report import (
    EYE_TOPIC,
    FIGURE_KEYS,
    Report,
    Verdict,
    build_report,
    eye_headline,
    report_json,
    validate_report,
)
from aperture_fab.validation.robustness import EyeQuality, grid_offsets
from aperture_fab.validation.verdicts import EYE_MARGIN_DB, eye_verdict, verdicts
from tests.test_report import all_figures, complete_inputs, judged, made_block

NAMES = ("letter",)
STATES = 8
MAP = 5
#: The baselines' levels (dB); each variant's PSNR over the states is its level + SPREAD.
OPEN_DB, PINHOLES_DB = 19.0, 21.0
BEST_DB = max(OPEN_DB, PINHOLES_DB)
SPREAD = np.linspace(-2.0, 2.0, STATES)


def synthetic_eyes(part_db: float | list[float], *, targets: int = 1,
                   eyebox_mm: tuple[float, float] = (4.0, 4.0)) -> EyeQuality:
    """EyeQuality with the part ("as_built") at part_db (one per target, or one for all) and the
    baselines at OPEN_DB / PINHOLES_DB, every variant spread the same way over the states, so
    each 10th percentile differs from another by the difference of their levels."""
    distribution = EyeDistribution(eyebox_mm=eyebox_mm, pupil_range_mm=(3.0, 6.0),
                                   nominal_pupil_mm=4.0, focus_range_diopters=(0.0, 0.5))
    levels = {"as_built": np.broadcast_to(np.asarray(part_db, dtype=float), (targets,)),
              "optimized": np.full(targets, 30.0), "open": np.full(targets, OPEN_DB),
              "regular_pinholes": np.full(targets, PINHOLES_DB)}
    _, inside = distribution.eyebox_grid(MAP)
    psnr = {v: level[:, None] + SPREAD for v, level in levels.items()}
    ssim = {v: np.clip(0.5 + (p - 20) / 40, 0, 1) for v, p in psnr.items()}
    pupils, focus = np.linspace(3, 6, 4), np.linspace(0, 0.5, 3)
    mapped = {v: np.where(inside, level[:, None, None], np.nan)
              for v, level in levels.items() if v != "open"}
    rng = np.random.default_rng(0)
    return EyeQuality(
        distribution=distribution, states=distribution.evaluation_states(STATES),
        psnr_db=psnr, ssim=ssim, nominal_psnr_db={v: level + 3 for v, level in levels.items()},
        map_offsets_mm=grid_offsets(distribution, MAP), map_inside=inside,
        map_psnr_db=mapped,
        pupil_mm=pupils, pupil_psnr_db={v: level[:, None] - pupils for v, level in levels.items()},
        focus_diopters=focus,
        focus_psnr_db={v: level[:, None] - focus for v, level in levels.items()},
        thumbnail_offsets_mm=np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [0.0, 2.0]]),
        thumbnails=rng.uniform(0, 1, (targets, 4, 1, 6, 6)),
    )


def report_for(eyes: EyeQuality | None, names: tuple[str, ...] = NAMES) -> dict[str, Any]:
    """A complete report holding the eye distribution of `eyes` (None: not judged), with its
    verdicts, as evidence.assemble makes it."""
    inputs = complete_inputs(names)
    targets = np.random.default_rng(1).uniform(0, 1, (len(names), 1, 6, 6))
    inputs["eye_distribution"] = (None if eyes is None
                                  else eye_distribution_block(eyes, names, targets))
    report = build_report(**inputs).as_json()
    report["verdicts"] = [v.as_dict() for v in verdicts(Report.from_json(report))]
    validate_report(report)
    return report


def judged_for(eyes: EyeQuality | None, names: tuple[str, ...] = NAMES) -> Report:
    """`report_for`'s report as a value."""
    return Report.from_json(report_for(eyes, names))


def headline(report: dict[str, Any]) -> dict[str, Any]:
    """design.json's metrics with the report's eye-distribution headline."""
    return {"eye_distribution": eye_headline(Report.from_json(report))}


# ---------------------------------------------------------------------------------------------
# The verdict


def test_red_when_the_parts_10th_percentile_is_below_the_open_displays() -> None:
    report = report_for(synthetic_eyes(OPEN_DB - 1.5))
    report["config"]["optimizer"]["eye_states"] = 8  # designed for the distribution already
    verdict = eye_verdict(Report.from_json(report))
    assert verdict.topic == EYE_TOPIC and verdict.level == "fail"
    p10 = report["eye_distribution"]["variants"]["as_built"]["psnr_db"]["p10"][0]
    open_p10 = report["eye_distribution"]["variants"]["open"]["psnr_db"]["p10"][0]
    assert p10 == pytest.approx(open_p10 - 1.5)
    text = verdict.text
    assert f"{p10:.1f} dB PSNR at the 10th percentile" in text  # names the figures
    assert f"{open_p10:.1f} dB for the open display (-1.5 dB)" in text
    assert f"{open_p10 + 2:.1f} dB for the regular pinhole array (-3.5 dB)" in text
    assert "below that of the open display and the regular pinhole array" in text
    # ... and what to change, one fix at a time, the geometry first (the design already
    # samples the eye distribution)
    fixes = " ".join(verdict.fixes)
    for advice in ("eyebox_mm = [4, 4]", "only if they do not", "smaller pitch",
                   "plate.pitch_mm, now 0.25 x 0.25 mm", "larger gap", "plate.gap_mm, now",
                   'optimizer.tracking = "tracked"', "aperture-fab display"):
        assert advice in fixes and advice not in text, advice
    assert verdict.fixes[0].startswith("Design again with a smaller pitch")
    assert not any("eye_states" in f for f in verdict.fixes)  # already > 1
    assert verdicts(Report.from_json(report))[0] == verdict  # it leads


def test_red_below_the_regular_pinholes_for_one_target_of_two() -> None:
    eyes = synthetic_eyes([BEST_DB + 5, PINHOLES_DB - 0.3], targets=2)  # above the open one
    verdict = eye_verdict(judged_for(eyes, ("letter", "grid")))
    assert verdict.level == "fail"
    assert "for target 'grid'" in verdict.text
    assert "below that of the regular pinhole array:" in verdict.text
    assert "below that of the open display" not in verdict.text


def test_amber_within_a_db_and_green_above() -> None:
    close = eye_verdict(judged_for(synthetic_eyes(BEST_DB + EYE_MARGIN_DB / 2)))
    assert close.level == "warn"
    assert "Less than 1 dB above a baseline" in close.text and close.fixes
    good = eye_verdict(judged_for(synthetic_eyes(BEST_DB + 4)))
    assert good.level == "pass"
    assert good.fixes == ()
    assert "(+6.0 dB)" in good.text and "(+4.0 dB)" in good.text


def test_a_nominal_point_design_is_told_to_design_for_the_distribution() -> None:
    report = report_for(synthetic_eyes(OPEN_DB - 1))
    report["config"]["optimizer"]["eye_states"] = 1
    # recommended first
    assert "optimizer.eye_states > 1" in eye_verdict(Report.from_json(report)).fixes[0]
    report["config"]["optimizer"]["tracking"] = "tracked"
    # already tracked
    assert not any("tracked" in f for f in eye_verdict(Report.from_json(report)).fixes)


def test_not_judged_falls_back_to_the_nominal_figures_with_a_note() -> None:
    report = report_for(None)
    assert report["eye_distribution"] is None
    verdict = eye_verdict(Report.from_json(report))
    assert verdict.level == "info" and "validation.eye_states = 0" in verdict.text
    assert report["verdicts"][0]["topic"] == EYE_TOPIC
    assert eye_headline(Report.from_json(report)) is None
    page = report_html(judged(report), {})
    lead = page[page.index('<section id="eyes">'):page.index('<section id="views">')]
    assert "PSNR nominal (dB), mean over targets" in lead and "NOTE" in lead
    assert "validation.eye_states = 0" in page[:page.index('<section id="eyes">')]
    assert "<img" not in lead


# ---------------------------------------------------------------------------------------------
# report.json


def test_report_json_round_trips_through_the_schema_check() -> None:
    report = report_for(synthetic_eyes(BEST_DB + 3))
    text = report_json(Report.from_json(report))
    again = json.loads(text)
    assert again == report
    validate_report(again)
    assert list(again)[:3] == ["schema_version", "eye_distribution", "verdicts"]
    block = again["eye_distribution"]
    assert list(block["variants"]) == ["as_built", "optimized", "open", "regular_pinholes"]
    assert block["states"] == STATES and block["percentiles"] == [10, 50, 90]
    assert block["targets"] == list(NAMES)
    p = block["variants"]["as_built"]["psnr_db"]
    assert p["p10"][0] < p["p50"][0] < p["p90"][0]
    assert p["p50"][0] == pytest.approx(BEST_DB + 3)  # the spread is symmetric
    assert block["variants"]["open"]["nominal_psnr_db"] == [OPEN_DB + 3]
    grid = block["eyebox_map"]
    assert np.asarray(grid["offsets_mm"]).shape == (MAP, MAP, 2)
    assert "open" not in grid["psnr_db"]  # the open display has no map
    corner = grid["psnr_db"]["as_built"][0][0][0]
    assert corner is None and grid["inside"][0][0] is False  # outside the ellipse: null
    assert grid["psnr_db"]["as_built"][0][2][2] == BEST_DB + 3
    assert block["pupil"]["pupil_mm"] == [3.0, 4.0, 5.0, 6.0]
    assert len(block["focus"]["psnr_db"]["open"][0]) == 3
    assert len(block["thumbnails"]["psnr_db"][0]) == 4
    headline = eye_headline(Report.from_json(again))
    assert headline is not None and headline["verdict"]["level"] == "pass"
    assert "eyebox_map" not in headline and headline["variants"] == block["variants"]


# ---------------------------------------------------------------------------------------------
# The page


class Lead(HTMLParser):
    """Section ids, tables (their first row's cells and every row's first cell) and image ids,
    in page order."""

    def __init__(self) -> None:
        super().__init__()
        self.sections: list[str] = []
        self.tables: list[list[list[str]]] = []
        self.images: list[tuple[str, str]] = []  # (section, image id)
        self._cell: list[str] | None = None

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        values = dict(attrs)
        if tag == "section":
            self.sections.append(values.get("id") or "")
        elif tag == "table":
            self.tables.append([])
        elif tag == "tr":
            self.tables[-1].append([])
        elif tag in ("td", "th"):
            self._cell = []
        elif tag == "img":
            self.images.append((self.sections[-1], values.get("id") or ""))

    def handle_endtag(self, tag: str) -> None:
        if tag in ("td", "th") and self._cell is not None:
            self.tables[-1][-1].append("".join(self._cell))
            self._cell = None

    def handle_data(self, data: str) -> None:
        if self._cell is not None:
            self._cell.append(data)


def test_html_leads_with_the_eye_distribution_table_and_figures() -> None:
    eyes = synthetic_eyes(OPEN_DB - 1.5)
    report = report_for(eyes)
    targets = np.random.default_rng(1).uniform(0, 1, (1, 1, 6, 6))
    figures = eye_figures(eyes, NAMES, targets)
    assert set(figures) == {"eye_map", "eye_pupil", "eye_focus", "eye_thumbnails"}
    page = report_html(judged(report), figures)
    lead = Lead()
    lead.feed(page)
    assert lead.sections[:4] == ["verdict", "made", "light", "eyes"]
    first = lead.tables[0]
    assert first[0] == ["variant", "PSNR p10 (dB)", "PSNR median (dB)", "PSNR p90 (dB)",
                        "SSIM p10", "PSNR nominal (dB)"]
    assert [row[0] for row in first[1:]] == ["as built", "optimized", "open display",
                                             "regular pinholes"]
    p10 = report["eye_distribution"]["variants"]["as_built"]["psnr_db"]["p10"][0]
    ssim = report["eye_distribution"]["variants"]["as_built"]["ssim"]["p10"][0]
    assert first[1][1] == f"{p10:.1f}" and first[1][4] == f"{ssim:.2f}"  # 0.1 dB, 0.01
    assert first[1][5] == f"{OPEN_DB - 1.5 + 3:.1f}"
    assert lead.images == [("eyes", f"fig-{key}") for key in (
        "eye_map", "eye_pupil", "eye_focus", "eye_thumbnails")]
    # the red verdict leads the page; under the eye table, before the figures, its level
    # points to it; its text is on the page once
    verdict_html = page[page.index('<section id="verdict">'):page.index('<section id="light">')]
    assert 'class="overall overall-fail"' in verdict_html
    assert "below that of the open display" in verdict_html
    eyes_html = page[page.index('<section id="eyes">'):page.index('<section id="views">')]
    assert eyes_html.index("<table>") < eyes_html.index('class="verdict verdict-fail"') \
        < eyes_html.index("<img")
    assert page.count("below that of the open display") == 1
    assert "nominal eye point only (a second optimization" in eyes_html  # what is not judged


def test_html_with_every_figure_has_one_image_per_figure_key() -> None:
    eyes = synthetic_eyes(BEST_DB + 2)
    report = {**report_for(eyes), "made_part": made_block(len(NAMES))}
    figures = {**all_figures(), **eye_figures(eyes, NAMES, np.ones((1, 1, 6, 6)))}
    lead = Lead()
    lead.feed(report_html(judged(report), figures))
    assert sorted(i for _, i in lead.images) == sorted(f"fig-{k}" for k in FIGURE_KEYS)


def test_an_eyebox_of_zero_size_has_no_map() -> None:
    eyes = synthetic_eyes(BEST_DB + 2, eyebox_mm=(0.0, 0.0))
    figures = eye_figures(eyes, NAMES, np.ones((1, 1, 6, 6)))
    assert "eye_map" not in figures
    report = report_for(eyes)
    page = report_html(judged(report), figures)
    assert "No eyebox map: the eyebox has zero size" in page


# ---------------------------------------------------------------------------------------------
# The terminal


def test_the_terminal_table_leads_with_the_distribution(capsys: pytest.CaptureFixture[str]
                                                         ) -> None:
    report = report_for(synthetic_eyes([OPEN_DB - 1.5, 30.0], targets=2), ("letter", "grid"))
    print_eye_distribution(headline(report), ("letter", "grid"),
                            validated=True)
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == f"PSNR over the eye distribution (dB), p10 / median / p90, {STATES} states:"
    assert lines[1].split() == ["target", "as_built", "optimized", "open", "regular_pinholes"]
    block = report["eye_distribution"]["variants"]
    for t, name in enumerate(("letter", "grid")):
        row = lines[2 + t]
        assert row.split()[0] == name
        cells = [c.strip() for c in row[len(name) + 2:].split("  ") if c.strip()]
        assert cells[0] == " / ".join(f"{block['as_built']['psnr_db'][k][t]:.1f}"
                                      for k in ("p10", "p50", "p90"))
    assert lines[4].startswith("eye distribution: FAIL: Over the eye distribution")


def test_the_terminal_says_when_the_distribution_was_not_judged(
        capsys: pytest.CaptureFixture[str]) -> None:
    print_eye_distribution({"eye_distribution": None}, NAMES, validated=True)
    assert "validation.eye_states = 0" in capsys.readouterr().out
    print_eye_distribution({}, NAMES, validated=False)
    assert "--no-validate" in capsys.readouterr().out


def test_the_terminal_lists_the_reports_other_warnings_and_failures(
        capsys: pytest.CaptureFixture[str]) -> None:
    report = report_for(synthetic_eyes([OPEN_DB - 1.5, 30.0], targets=2), ("letter", "grid"))
    verdicts = [Verdict("light", "warn", "The view is mesopic."),
                Verdict("contrast", "fail", "Leakage."), Verdict("mesh", "pass", "Watertight."),
                Verdict("eye distribution", "fail", "Printed above.")]
    print_eye_distribution(headline(report), ("letter", "grid"),
                            validated=True, verdicts=verdicts)
    out = capsys.readouterr().out
    assert "light: WARN: The view is mesopic." in out
    assert "contrast: FAIL: Leakage." in out
    assert "Watertight" not in out and "Printed above" not in out


def test_the_terminal_ends_with_the_recommended_fix(capsys: pytest.CaptureFixture[str]) -> None:
    report = report_for(synthetic_eyes(OPEN_DB - 1.5))
    lines = Report.from_json(report).verdicts
    print_eye_distribution(headline(report), NAMES, validated=True, verdicts=lines)
    out = " ".join(capsys.readouterr().out.split())
    first = lines[0]
    assert first.topic == EYE_TOPIC and first.level == "fail"
    others = sum(len(v.fixes) for v in lines) - 1
    assert out.endswith(f"recommended fix (eye distribution): {first.fixes[0]} ({others} "
                        "other fixes in the report)")
    assert first.fixes[1] not in out  # the others are in the report
    print_eye_distribution({"eye_distribution": None}, NAMES, validated=True)
    assert "recommended fix" not in capsys.readouterr().out  # no verdicts, no fix
