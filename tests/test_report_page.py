"""The report page of a real (tiny) design in headless Chromium, and the figures' titles: no
panel title is cut and no figure text leaves its figure."""

from __future__ import annotations

import base64
import dataclasses
import datetime
import io
import math
import re
import subprocess
from collections.abc import Iterator
from html.parser import HTMLParser
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import design_tiny
from PIL import Image

from aperture_fab.cli import EXIT_OK, EXIT_REPORT_FAIL
from aperture_fab.config.presets import DEFAULT_PROCESS
from aperture_fab.report import figures, part_figures
from aperture_fab.report.figures import (
    PANEL_INCHES,
    TITLE_FONT_SIZE,
    TITLE_WIDTH_SHARE,
    figure_views,
    text_width_in,
    wrap_to_width,
)
from aperture_fab.report.page import MAX_PAGE_HEIGHT_PX, SECTION_TITLES
from aperture_fab.report.part_figures import figure_errors, figure_hole_map
from aperture_fab.validation.report import FIGURE_KEYS
from aperture_fab.validation.variants import VARIANTS
from tests.test_report import chromium, chromium_dom, page_height

#: The longest label a view panel gets after the variant's title.
SCORE_LINE = "\n99.9 dB, SSIM 0.99"
DATA_PNG = re.compile(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"')
#: The screenshot's window (CSS pixels).
WINDOW = (1200, 3000)


# ---------------------------------------------------------------------------------------------
# Titles


def test_every_panel_title_fits_its_panel_uncut() -> None:
    width = PANEL_INCHES * TITLE_WIDTH_SHARE
    for name, info in VARIANTS.items():
        for text in (info.title + SCORE_LINE, info.label):
            wrapped = wrap_to_width(text, width, TITLE_FONT_SIZE)
            assert "…" not in wrapped, (name, wrapped)
            assert wrapped.split() == text.split(), (name, wrapped)  # every word kept
            assert text_width_in(wrapped, TITLE_FONT_SIZE) <= width, (name, wrapped)


def test_a_word_too_long_for_a_panel_is_shortened_visibly() -> None:
    wrapped = wrap_to_width("x" * 80, 1.0, TITLE_FONT_SIZE)
    assert wrapped.endswith("…") and text_width_in(wrapped, TITLE_FONT_SIZE) <= 1.0


@pytest.fixture
def drawn(monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    """The matplotlib Figures the figure functions draw, in order (their PNGs still made)."""
    made: list[Any] = []
    original = figures._png

    def keep(fig: Any) -> bytes:
        made.append(fig)
        return original(fig)

    monkeypatch.setattr(figures, "_png", keep)
    monkeypatch.setattr(part_figures, "_png", keep)
    return made


def texts_outside(fig: Any) -> list[str]:
    """What of `fig` is drawn beyond its edges (1 pixel of slack): each axes (its title, tick
    labels and axis labels as drawn, colour bars included) and each figure text (the suptitle),
    named by its title or text."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)  # as savefig draws it (layout included)
    canvas.draw()
    renderer = canvas.get_renderer()
    box = fig.bbox
    drawn = [(ax.get_title() or ax.get_ylabel() or "axes", ax.get_tightbbox(renderer))
             for ax in fig.axes]
    drawn += [(t.get_text(), t.get_window_extent(renderer)) for t in fig.texts
              if t.get_visible() and t.get_text().strip()]
    return [name for name, extent in drawn
            if extent.x0 < box.x0 - 1 or extent.x1 > box.x1 + 1 or extent.y0 < box.y0 - 1
            or extent.y1 > box.y1 + 1]


def test_no_figure_text_leaves_its_figure(drawn: list[Any]) -> None:
    rng = np.random.default_rng(0)
    target = rng.uniform(0, 1, (3, 16, 16))
    rows = [(info.title + SCORE_LINE, target * 0.5) for info in VARIANTS.values()]
    long_title = "Target 'a rather long target name for a test': what the eye sees"
    figure_views([("target", target), *rows], long_title)
    figure_views([("target", target), rows[0]], long_title)  # two panels, a long title
    figure_errors(target, rows, title=long_title)
    outline = [(11.0, 11.0), (-10.0, 11.0), (-11.0, 10.0), (-11.0, -11.0), (11.0, -11.0)]
    figure_hole_map(rng.uniform(-9, 9, (50, 2)), rng.uniform(0.04, 0.07, 50), outline)
    assert len(drawn) == 4
    for fig in drawn:
        assert texts_outside(fig) == []


def test_the_check_sees_a_title_wider_than_its_figure(drawn: list[Any],
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """Without wrapping, the old cut titles come back, and texts_outside names them."""
    monkeypatch.setattr(figures, "wrap_to_width", lambda text, width, size: text)
    target = np.ones((3, 8, 8))
    figure_views([("target", target), (VARIANTS["random"].label, target)],
                 "a title far wider than the two panels of this figure can hold")
    assert texts_outside(drawn[0])


# ---------------------------------------------------------------------------------------------
# The page of a tiny design


@pytest.fixture(scope="module")
def report_folder(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """A tiny design, validated: its output folder (report.html, report.json, ...)."""
    folder = tmp_path_factory.mktemp("page")
    assert design_tiny(folder, "--out", str(folder / "out" / "plate.stl"), "--tolerance-samples",
                       "2", "--mesh-samples", "8", "--quiet") in (EXIT_OK, EXIT_REPORT_FAIL)
    yield folder / "out"


@pytest.mark.slow
def test_the_report_of_a_tiny_design_loads_whole_in_chromium(report_folder: Path,
                                                              tmp_path: Path) -> None:
    import json

    page = (report_folder / "report.html").read_text(encoding="utf-8")
    report = json.loads((report_folder / "report.json").read_text(encoding="utf-8"))
    ok, total, dom = chromium_dom(page, tmp_path)
    # every image decodes in the browser, under the page's own policy
    assert total == page.count("<img ") and ok == total
    for key, heading in SECTION_TITLES:
        if key == "eyebox":  # one eye position: nothing to show, left out
            assert f'<section id="{key}">' not in dom
            continue
        assert f'<section id="{key}">' in dom
        assert f"<h2>{heading}</h2>" in dom  # whole, not cut
    assert "nowrap" not in page[page.index("h1 {"):page.index("nav a")]  # headings may wrap
    # the verdict leads, in colour, with the part, process, date and command above it
    assert dom.index('class="overall overall-') < dom.index('<section id="light">')
    run = report["run"]
    assert run["part"] == "plate.stl" and run["process"] == DEFAULT_PROCESS
    assert run["command"].startswith("aperture-fab design ")
    assert datetime.datetime.fromisoformat(run["date"].replace("Z", "+00:00")).tzinfo
    assert f"Validation report: {run['part']}" in dom and run["date"] in dom
    assert {v["topic"] for v in report["verdicts"]} >= {"light", "contrast", "tolerance",
                                                        "made part"}
    assert report["photometry"]["leakage"]["optical_density"] == 4.0  # photomask film
    assert dom.index('<section id="made">') < dom.index('<section id="light">')
    # every embedded PNG decodes; the display is at its native size, one pixel per pixel
    sizes = []
    for data in DATA_PNG.findall(page):
        with Image.open(io.BytesIO(base64.b64decode(data, validate=True))) as image:
            image.load()
            assert image.width > 0 and image.height > 0
            sizes.append(image.size)
    assert len(sizes) == total
    nx, ny = report["scene"]["display"]["pixels"]
    assert (nx, ny) in sizes
    assert f'id="display-marker" width="{nx}" height="{ny}"' in page
    # a screenshot of the whole window
    shot = tmp_path / "report.png"
    result = subprocess.run(
        [chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
         f"--user-data-dir={tmp_path / 'shot-profile'}", f"--screenshot={shot}",
         f"--window-size={WINDOW[0]},{WINDOW[1]}", (report_folder / "report.html").as_uri()],
        capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode == 0 and shot.exists(), result.stderr[-2000:]
    with Image.open(shot) as image:
        assert image.size == WINDOW
        low, high = image.convert("L").getextrema()
        assert high - low > 100  # a page, not a blank window


# ---------------------------------------------------------------------------------------------
# The hole map: every hole visible


#: A 20 x 20 mm plate (the near-eye preset's size).
PLATE_20MM = [(10.0, 10.0), (-10.0, 10.0), (-10.0, -10.0), (10.0, -10.0)]
#: How far a pixel's colour (sum of |R, G, B| differences, 0 to 765) is from the plate's
#: before it counts as part of a hole.
VISIBLE_DIFFERENCE = 90
#: The smallest hole the catalogue makes (photomask film: 25 µm), radius in mm.
SMALLEST_RADIUS_MM = 0.0125


def hole_pixels(png: bytes, fig: Any, centre_mm: tuple[float, float]) -> int:
    """The pixels of the PNG around `centre_mm` (a hole's centre on the figure's plate axes)
    that differ visibly from the plate's colour."""
    import matplotlib as mpl

    x, y = fig.axes[0].transData.transform(centre_mm)  # from the bottom left
    with Image.open(io.BytesIO(png)) as image:
        rgb = np.asarray(image.convert("RGB"), dtype=np.float64)
    row, col = round(float(rgb.shape[0] - y)), round(float(x))
    window = rgb[row - 8:row + 9, col - 8:col + 9]
    plate = np.asarray(mpl.colors.to_rgb(part_figures.PLATE_GREY)) * 255
    return int(np.count_nonzero(np.abs(window - plate).sum(axis=-1) > VISIBLE_DIFFERENCE))


@pytest.mark.parametrize("floor_px", [part_figures.MIN_HOLE_MARKER_PX, 0.0],
                         ids=["with the floor", "to scale"])
def test_the_smallest_hole_shows_in_the_hole_map(drawn: list[Any], monkeypatch: pytest.MonkeyPatch,
                                                 floor_px: float) -> None:
    """To scale, a 25 µm hole of a 20 mm plate is a tenth of a pixel: invisible. Drawn at the
    floor, it covers about a MIN_HOLE_MARKER_PX-wide disk in a colour far from the plate's, and
    the title says which holes are drawn enlarged."""
    monkeypatch.setattr(part_figures, "MIN_HOLE_MARKER_PX", floor_px)
    centres = np.array([[0.0, 0.0], [5.0, 5.0], [-5.0, 5.0]])
    radii = np.array([SMALLEST_RADIUS_MM, 0.05, 0.15])
    png = figure_hole_map(centres, radii, PLATE_20MM)
    fig = drawn[-1]
    shown = hole_pixels(png, fig, (0.0, 0.0))
    title = fig.axes[0].get_title()
    if floor_px == 0:
        assert shown <= 1 and "every hole drawn to scale" in title
        return
    disk = math.pi * (floor_px / 2) ** 2
    assert shown >= 0.8 * disk, shown
    # the floor in µm as the title states it, and which holes it enlarged
    floor_um = float(re.search(r"holes under (\d+) µm \((\d+) of 3\)", title)[1])
    px_per_mm = fig.axes[0].transData.transform((1.0, 0.0))[0] - fig.axes[0].transData.transform(
        (0.0, 0.0))[0]
    assert floor_um == pytest.approx(1000 * floor_px / px_per_mm, abs=1)
    assert re.search(r"\((\d+) of 3\)", title)[1] == str(int(np.sum(2000 * radii < floor_um)))


# ---------------------------------------------------------------------------------------------
# Captions: each says what its figure draws


def drawn_texts(fig: Any) -> list[str]:
    """Every text a figure draws: titles, axis labels, legend entries, the suptitle."""
    out = [t.get_text() for t in fig.texts]
    for ax in fig.axes:
        out += [ax.get_title(), ax.get_xlabel(), ax.get_ylabel()]
        legend = ax.get_legend()
        out += [] if legend is None else [t.get_text() for t in legend.get_texts()]
    out += [t.get_text() for legend in fig.legends for t in legend.get_texts()]
    return [t for t in out if t]


def figures_as_drawn(drawn: list[Any]) -> dict[str, Any]:
    """Every figure the page places, drawn with the functions and labels the report uses
    (evidence.assemble, eye_figures): {figure key: the matplotlib Figure}."""
    from aperture_fab.report.evidence import _panel_label, eye_figures
    from aperture_fab.report.figures import (
        figure_histogram,
        figure_loss,
        figure_mesh_disagreement,
    )
    from aperture_fab.report.part_figures import figure_made_front
    from aperture_fab.validation.variants import SHOWN_VARIANTS
    from tests.test_report import made_block
    from tests.test_report_eyes import NAMES, synthetic_eyes

    rng = np.random.default_rng(0)
    target = rng.uniform(0, 1, (3, 12, 12))
    score = {"psnr_db": 20.0, "ssim": 0.5}
    rows = [("target", target)] + [(_panel_label(v, score), target * 0.5)
                                   for v in SHOWN_VARIANTS]
    # judge_eyes sweeps focus for the part alone (robustness.EyeQuality)
    quality = synthetic_eyes(25.0)
    quality = dataclasses.replace(quality, focus_psnr_db={
        "as_built": quality.focus_psnr_db["as_built"]})
    before = len(drawn)
    eyes = eye_figures(quality, NAMES, np.ones((1, 1, 6, 6)))
    assert tuple(eyes) == FIGURE_KEYS_DRAWN_BY_EYES
    out = dict(zip(eyes, drawn[before:], strict=True))
    for key, draw in (
            ("views", lambda: figure_views(rows, "what the eye sees")),
            ("errors", lambda: figure_errors(target, rows[1:], title="error of each view")),
            ("hole_map", lambda: figure_hole_map(rng.uniform(-9, 9, (40, 2)),
                                                 rng.uniform(0.0125, 0.06, 40), PLATE_20MM)),
            ("loss", lambda: figure_loss(np.geomspace(1, 1e-2, 20))),
            ("made_front", lambda: figure_made_front(made_block())),
            ("eyebox", lambda: figure_views(
                [(f"eye at ({x:g}, 0) mm\n20.0 dB", target) for x in (-1.0, 1.0)],
                "As built, from each eye position")),
            ("tolerance", lambda: figure_histogram(rng.normal(30, 2, 16), 25.0)),
            ("mesh_retrace", lambda: figure_mesh_disagreement(target + 0.01, target, 0.01))):
        draw()
        out[key] = drawn[-1]
    return out


#: The figures eye_figures draws, in the order it draws them.
FIGURE_KEYS_DRAWN_BY_EYES = ("eye_map", "eye_pupil", "eye_focus", "eye_thumbnails")
#: For each figure: (what it draws, in its texts; what its caption must then say), both as
#: fragments. A caption that describes another figure fails one of them.
CAPTION_FACTS: dict[str, list[tuple[str, str]]] = {
    "eye_map": [("pupil offset x", "pupil centre offset"), ("PSNR (dB)", "PSNR of the part")],
    "eye_pupil": [("pupil diameter", "against pupil diameter"),
                  ("regular pinholes", "one line per variant"),
                  ("the distribution's range", "shaded")],
    "eye_focus": [("focus (diopters", "against focus in diopters"),
                  ("the distribution's range", "shaded")],
    "eye_thumbnails": [("target", "The target, then"), ("mm\n", "pupil offsets")],
    "views": [("what the eye sees", "what the eye sees")],
    "errors": [("mean", "mean error"), ("view - target|", "|gain x view - target|")],
    "hole_map": [("drawn", "drawn enlarged"), ("hole diameter", "diameter (colour)")],
    "loss": [("iteration", "per iteration"), ("loss", "loss")],
    "made_front": [("regular arrays, elemental images", "Dots: every array with elemental"),
                   ("their front", "dashed: their front"),
                   ("rivals, display fitted", "squares: the rivals"),
                   ("the part as made", "The part as made (star)")],
    "eyebox": [("eye at (", "eye positions")],
    "tolerance": [("threshold", "threshold"), ("PSNR", "Histogram of PSNR")],
    "mesh_retrace": [("mesh re-trace - exact model", "mesh re-trace - exact model"),
                     ("dB PSNR", "titled with the PSNR"), ("noise", "RMS Monte Carlo noise")],
}


def test_each_caption_describes_the_figure_it_sits_under(drawn: list[Any]) -> None:
    figures = figures_as_drawn(drawn)
    assert set(figures) == set(FIGURE_KEYS) == set(CAPTION_FACTS)
    for key, fig in figures.items():
        texts = "\n".join(drawn_texts(fig))
        for drawn_fragment, caption_fragment in CAPTION_FACTS[key]:
            assert drawn_fragment in texts, (key, drawn_fragment)
            assert caption_fragment in FIGURE_KEYS[key], (key, caption_fragment)
    # the panels of the main figure and the error maps, in the order drawn, are the caption's
    for key in ("views", "errors"):
        titles = [" ".join(line for line in ax.get_title().split("\n")
                           if "dB" not in line and "mean" not in line)  # the name, unwrapped
                  for ax in figures[key].axes if ax.get_title()]
        titles = [t for t in titles if t != "target"]
        assert ", ".join(titles) in FIGURE_KEYS[key], key
    # the focus sweep draws the part only; the pupil sweep every variant judged
    focus = [t for t in drawn_texts(figures["eye_focus"]) if t in EYE_LABELS]
    pupil = [t for t in drawn_texts(figures["eye_pupil"]) if t in EYE_LABELS]
    assert focus == ["as built"] and "one line per variant" not in FIGURE_KEYS["eye_focus"]
    assert len(pupil) > 1


#: The eye-distribution table's names of the variants (the sweeps' legend entries).
EYE_LABELS = {"as built", "optimized", "open display", "regular pinholes"}


# ---------------------------------------------------------------------------------------------
# No empty section


class Sections(HTMLParser):
    """Per <section id>: the text outside its heading, and whether it holds an image or a
    table."""

    def __init__(self) -> None:
        super().__init__()
        self.text: dict[str, str] = {}
        self.content: dict[str, bool] = {}
        self._section: str | None = None
        self._heading = False

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        if tag == "section":
            self._section = dict(attrs)["id"] or ""
            self.text[self._section], self.content[self._section] = "", False
        elif tag == "h2":
            self._heading = True
        elif tag in ("img", "table") and self._section is not None:
            self.content[self._section] = True

    def handle_endtag(self, tag: str) -> None:
        if tag == "section":
            self._section = None
        elif tag == "h2":
            self._heading = False

    def handle_data(self, data: str) -> None:
        if self._section is not None and not self._heading:
            self.text[self._section] += data


def report_variant(name: str) -> tuple[dict[str, Any], dict[str, bytes]]:
    """A report (and its figures) of one kind: complete, or without a part of validation."""
    from aperture_fab.validation.report import build_report
    from tests.test_report import all_figures, complete_inputs, made_block

    inputs = complete_inputs()
    figures = all_figures()
    made: dict[str, Any] | None = made_block()
    if name == "not judged over the eye distribution":
        inputs["eye_distribution"] = None
        for key in FIGURE_KEYS_DRAWN_BY_EYES:
            del figures[key]
    elif name == "one eye position":
        del figures["eyebox"]
    elif name == "bare":  # no eye distribution, part as made, tolerance, light or figures
        inputs["eye_distribution"] = inputs["tolerance"] = None
        inputs["metrics"] = {"as_built": inputs["metrics"]["as_built"]}
        inputs["timings_s"] = {}
        made, figures = None, {}
    report = build_report(**inputs, made_part=made).as_json()
    return report, figures


@pytest.mark.parametrize("name", ["complete", "not judged over the eye distribution",
                                  "one eye position", "bare"])
def test_no_section_is_only_a_heading(name: str) -> None:
    from aperture_fab.report.page import report_html
    from tests.test_report import judged

    report, figures = report_variant(name)
    page = report_html(judged(report), figures)
    sections = Sections()
    sections.feed(page)
    assert sections.text
    for key, text in sections.text.items():
        assert sections.content[key] or len(text.split()) >= 3, (name, key, text)
    # a section left out is left out of the contents too
    shown = set(sections.text)
    assert {k for k, _ in SECTION_TITLES if f'href="#{k}"' in page} == shown
    assert ("eyebox" in shown) == ("eyebox" in figures)


# ---------------------------------------------------------------------------------------------
# The page's height


@pytest.mark.slow
def test_the_tiny_designs_page_is_short_in_chromium(report_folder: Path, tmp_path: Path
                                                    ) -> None:
    """The tiny design's page (every section of the default design's) at a 1280 px wide window
    is under MAX_PAGE_HEIGHT_PX tall: docs/validation.md gives the default design's figure."""
    page = (report_folder / "report.html").read_text(encoding="utf-8")
    ok, total, dom = chromium_dom(page, tmp_path)
    assert ok == total
    height = page_height(dom)
    assert 2000 < height < MAX_PAGE_HEIGHT_PX, height
