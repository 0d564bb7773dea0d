"""The assembly sheet (aperture_fab/validation/assembly.py) and `aperture-fab assembly`."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from aperture_fab.cli import main
from aperture_fab.config.presets import PHOTOMASK_EMULSION_MM
from aperture_fab.fabrication.process import resolve_process
from aperture_fab.io.manifest import MANIFEST_NAME, check_folder
from aperture_fab.pipeline.assembly_job import (
    ASSEMBLY_NAME,
    load_design_part,
    plate_geometry,
    run_assembly,
)
from aperture_fab.validation.assembly import assembly_html, calibration_coupon

SVG = re.compile(r"<svg\b.*?</svg>", re.S)
NS = "{http://www.w3.org/2000/svg}"
#: A4 in PostScript points.
A4_PT = (595.28, 841.89)


def drawings(page: str) -> dict[str, ET.Element]:
    """Each inline SVG of the page, parsed, by its kind (the class after "drawing")."""
    found = {}
    for text in SVG.findall(page):
        svg = ET.fromstring(text)
        found[svg.get("class", "").split()[1]] = svg
    return found


def view_box(svg: ET.Element) -> tuple[float, float, float, float]:
    x, y, w, h = (float(v) for v in svg.get("viewBox", "").split())
    return x, y, w, h


@pytest.fixture(scope="module")
def sheet(designed: Path) -> str:
    loaded = load_design_part(designed)
    return assembly_html(loaded.part, loaded.config, loaded.fabrication.process, loaded.names,
                         design_name="tiny")


def test_the_design_job_writes_the_sheet_into_its_set(designed: Path) -> None:
    assert (designed / ASSEMBLY_NAME).is_file()
    listed = json.loads((designed / MANIFEST_NAME).read_text())["files"]
    assert ASSEMBLY_NAME in listed


def test_the_sheet_states_the_plate_display_and_coupon(designed: Path, sheet: str) -> None:
    loaded = load_design_part(designed)
    width, height = loaded.part.layout.outline_mm
    cut = loaded.part.corner_cut_mm
    assert (width, height) == (6.0, 6.0)  # 16 cells of 0.25 mm plus a 1 mm margin each side
    assert cut > 0
    for text in (f"{width:g} x {height:g} mm", f"{cut:.3f} mm x {cut:.3f} mm", "chamfer",
                 "top-left", f"key: {cut:.2f} mm", f"{loaded.config.scene.plate.thickness_mm:g} mm",
                 "32 x 32 pixels", "display_marker.png", "1:1, pixel for pixel",
                 "Calibration coupon", "coupon_holes.csv", "Assembly procedure",
                 "100 %", "@media print", "size: A4", f"{loaded.part.layout.count}"):
        assert text in sheet, text
    assert "<script" not in sheet


def test_drawings_parse_and_hold_the_plate_in_millimetres(designed: Path, sheet: str) -> None:
    loaded = load_design_part(designed)
    width, height = loaded.part.layout.outline_mm
    found = drawings(sheet)
    assert {"plate", "stack", "placement", "coupon", "scale-bar"} <= set(found)
    for kind, svg in found.items():
        _, _, w, h = view_box(svg)
        scale = float(svg.get("data-scale", "nan"))
        # printed size = viewBox (mm) x the stated scale
        assert float(svg.get("width", "").removesuffix("mm")) == pytest.approx(w * scale, abs=1e-3)
        assert float(svg.get("height", "").removesuffix("mm")) == pytest.approx(h * scale,
                                                                                abs=1e-3), kind
    plate = found["plate"]
    outline = plate.find(f"{NS}polygon[@class='outline']")
    assert outline is not None
    points = [tuple(float(v) for v in p.split(",")) for p in outline.get("points", "").split()]
    xs, ys = [p[0] for p in points], [p[1] for p in points]
    assert max(xs) - min(xs) == pytest.approx(width) and max(ys) - min(ys) == pytest.approx(height)
    assert len(points) == 5  # the chamfered corner
    x0, y0, w, h = view_box(plate)  # the viewBox holds the plate, centred, with room around it
    assert x0 < -width / 2 and y0 < -height / 2 and w > width and h > height
    assert x0 + w / 2 == pytest.approx(0) and y0 + h / 2 == pytest.approx(0)
    # top-left seen from the eye: the cut corner lies at -x and at SVG's -y (the part's +y)
    cut = loaded.part.corner_cut_mm
    assert (-width / 2 + cut, -height / 2) in [(pytest.approx(x), pytest.approx(y))
                                                for x, y in points]
    holes = plate.findall(f"{NS}g[@class='holes']/{NS}circle")
    assert len(holes) == loaded.part.layout.count


def test_the_coupon_follows_the_processes_doc() -> None:
    from aperture_fab.optics.scene import Plate

    plate = Plate((80, 80), (0.25, 0.25), 10.0, 0.3)
    coupon = calibration_coupon(resolve_process("resin", {}), plate)
    # 2 to 10 pixels of 22 um, every one below the pitch
    assert coupon.diameters_mm == pytest.approx([0.022 * k for k in range(2, 11)])
    assert coupon.thickness_mm == 0.3 and coupon.pitch_mm == 0.25
    rows = coupon.holes_csv().splitlines()
    assert rows[0] == "row,col,x_mm,y_mm,radius_mm,axis_x,axis_y"
    assert len(rows) == 1 + 9 * 25
    width, height = coupon.outline_mm
    for row in rows[1:]:
        _, _, x, y, r, _, _ = (float(v) for v in row.split(","))
        assert abs(x) + r < width / 2 and abs(y) + r < height / 2
    fine = calibration_coupon(resolve_process("photomask", {}), plate)
    assert fine.diameters_mm[0] < resolve_process("photomask", {}).min_hole_mm \
        < fine.diameters_mm[-1]


def test_a_config_of_another_plate_is_refused(designed: Path) -> None:
    from aperture_fab.config.config import resolve

    loaded = load_design_part(designed)
    other = resolve("near-eye-nominal")
    with pytest.raises(ValueError, match=r"plate\.cells"):
        assembly_html(loaded.part, other, loaded.fabrication.process, loaded.names)


def test_plate_geometry_is_the_part_as_built(designed: Path) -> None:
    geometry = plate_geometry(designed)
    part = load_design_part(designed).part
    assert (geometry.width_mm, geometry.height_mm) == part.layout.outline_mm
    assert geometry.corner_cut_mm == part.corner_cut_mm
    assert geometry.thickness_mm == PHOTOMASK_EMULSION_MM and geometry.gap_mm == 10.0


def test_the_command_writes_the_sheet(designed: Path, tmp_path: Path,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "sheet.html"
    assert main(["assembly", str(designed), "--out", str(out), "--quiet"]) == 0
    assert out.read_text() == (designed / ASSEMBLY_NAME).read_text()  # the design job's own
    assert str(out) in capsys.readouterr().out
    # in place: the same sheet, so the folder still matches its manifest
    assert run_assembly(designed) == designed / ASSEMBLY_NAME
    check_folder(designed)


@pytest.mark.parametrize(("make", "message"), [
    (lambda p: p, "not a design folder: it lacks design.toml and design.npz"),
    (lambda p: p / "missing", "does not exist or is not a folder"),
])
def test_the_command_refuses_a_folder_without_a_design(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], make, message: str) -> None:
    (tmp_path / "notes.txt").write_text("not a design\n")
    assert main(["assembly", str(make(tmp_path))]) == 3
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not (tmp_path / ASSEMBLY_NAME).exists()


def test_the_command_refuses_an_out_that_is_not_html(designed: Path, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["assembly", str(designed), "--out", str(tmp_path / "sheet.pdf")]) == 3
    assert "ending in .html" in capsys.readouterr().err


@pytest.mark.slow
def test_the_sheet_prints_on_a4_in_headless_chromium(designed: Path, tmp_path: Path) -> None:
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        pytest.skip("headless Chromium is not installed (Debian: apt-get install -y chromium)")
    page = tmp_path / "assembly.html"
    page.write_text((designed / ASSEMBLY_NAME).read_text())
    pdf, png = tmp_path / "sheet.pdf", tmp_path / "sheet.png"
    common = [browser, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
              "--disable-background-networking", "--disable-component-update", "--disable-sync",
              f"--user-data-dir={tmp_path / 'profile'}", "--virtual-time-budget=3000"]
    for flag in (f"--print-to-pdf={pdf}", f"--screenshot={png}"):
        result = subprocess.run([*common, "--no-pdf-header-footer", flag, page.as_uri()],
                                capture_output=True, text=True, timeout=120, check=False)
        assert result.returncode == 0, result.stderr[-2000:]
    data = pdf.read_bytes()
    boxes = [tuple(float(v) for v in m.groups())
             for m in re.finditer(rb"/MediaBox\s*\[\s*0 0 ([\d.]+) ([\d.]+)\s*\]", data)]
    assert boxes  # every page A4 (the @page rule), to a point (Chromium rounds)
    assert all(box == pytest.approx(A4_PT, abs=1.0) for box in boxes), boxes
    assert png.stat().st_size > 10_000  # a rendered page, not a blank one
