"""The report page of a real (tiny) design in headless Chromium, and the figures' titles: no
panel title is cut and no figure text leaves its figure."""

from __future__ import annotations

import base64
import datetime
import io
import re
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import design_tiny
from PIL import Image

from aperture_fab.cli import EXIT_OK, EXIT_REPORT_FAIL
from aperture_fab.config.presets import DEFAULT_PROCESS
from aperture_fab.validation import figures, part_figures
from aperture_fab.validation.figures import (
    PANEL_INCHES,
    TITLE_FONT_SIZE,
    TITLE_WIDTH_SHARE,
    figure_views,
    text_width_in,
    wrap_to_width,
)
from aperture_fab.validation.part_figures import figure_errors, figure_hole_map
from aperture_fab.validation.report_html import SECTION_TITLES
from aperture_fab.validation.variants import VARIANTS
from tests.test_report import chromium, chromium_dom

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
