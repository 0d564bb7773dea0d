"""The assembly sheet (aperture_fab/report/assembly.py) and `aperture-fab assembly`."""

from __future__ import annotations

import html
import importlib.util
import json
import math
import re
import shlex
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from conftest import require_tool

from aperture_fab.cli import main
from aperture_fab.config.presets import PHOTOMASK_EMULSION_MM
from aperture_fab.fabrication.coupon import coupon_layout
from aperture_fab.fabrication.mesh_checks import check_mesh, manifold_check
from aperture_fab.fabrication.process import resolve_process
from aperture_fab.io.formats import holes_csv, read_stl
from aperture_fab.io.manifest import MANIFEST_NAME, check_folder
from aperture_fab.pipeline.assembly_job import (
    ASSEMBLY_NAME,
    SHEET_NAMES,
    load_design_part,
    plate_geometry,
    run_assembly,
)
from aperture_fab.report.assembly import (
    CAD_EXTRA,
    COUPON_CSV,
    COUPON_STL,
    COUPON_SVG,
    assembly_html,
    calibration_coupon,
)

SVG = re.compile(r"<svg\b.*?</svg>", re.S)
NS = "{http://www.w3.org/2000/svg}"
#: A4 in PostScript points.
A4_PT = (595.28, 841.89)
#: A command the sheet prints, with the folder it runs in, what it needs and the note after it.
COMMAND = re.compile(r'<pre class="command" data-cwd="([^"]*)" data-needs="([^"]*)">(.*?)</pre>'
                     r'<p class="needs">(.*?)</p>', re.S)
#: The cad/ scripts' run time, generously (CadQuery import, a 75-hole coupon, the frame).
CAD_COMMAND_TIMEOUT_S = 300
HAS_CAD = importlib.util.find_spec("cadquery") is not None


def sheet_commands(page: str) -> list[tuple[Path, bool, str, str]]:
    """(folder, needs the cad extra, command line, note) of every command the page prints."""
    return [(Path(html.unescape(cwd)), needs == "cad", html.unescape(line), note)
            for cwd, needs, line, note in COMMAND.findall(page)]


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
    return assembly_html(loaded.part, loaded.config.scene, loaded.fabrication.process, loaded.names,
                         design_name="tiny")


def test_the_design_job_writes_the_sheet_into_its_set(designed: Path) -> None:
    listed = json.loads((designed / MANIFEST_NAME).read_text())["files"]
    for name in SHEET_NAMES:  # the sheet and the coupon as a part, published with the plate
        assert (designed / name).is_file() and name in listed, name


def test_the_coupon_is_a_closed_solid_with_a_tunnel_per_hole(designed: Path) -> None:
    loaded = load_design_part(designed)
    coupon = calibration_coupon(loaded.fabrication.process, loaded.config.scene.plate)
    table = [r for r in (designed / COUPON_CSV).read_text().splitlines() if r[:1] != "#"]
    assert table[0] == "row,col,x_mm,y_mm,radius_mm,axis_x,axis_y"
    radii = np.sort([float(r.split(",")[4]) for r in table[1:]])
    want = np.sort(np.repeat(np.array(coupon.diameters_mm) / 2, coupon.repeat**2))
    assert radii == pytest.approx(want, abs=1e-6)
    mesh = read_stl((designed / COUPON_STL).read_bytes())  # as written, float32
    report = check_mesh(mesh)
    assert report.ok and report.watertight and report.consistently_oriented
    assert report.degenerate_faces == 0 and report.genus == len(radii)
    width, height = coupon.outline_mm
    t, cut = coupon.thickness_mm, coupon.corner_cut_mm
    assert cut > 0
    # polygons keep their circles' areas: solid = (outline - chamfer - holes) x thickness
    volume = (width * height - cut**2 / 2 - math.pi * float(np.sum(radii**2))) * t
    assert report.volume_mm3 == pytest.approx(volume, rel=1e-4)
    assert manifold_check(mesh).genus == len(radii)
    extent = mesh.vertices.max(axis=0) - mesh.vertices.min(axis=0)
    assert extent == pytest.approx([width, height, t], abs=1e-5)
    # the chamfer is on the top-left corner (-x, +y): no vertex there
    x, y = mesh.vertices[:, 0], mesh.vertices[:, 1]
    assert not np.any((x < -width / 2 + cut / 4) & (y > height / 2 - cut / 4))


def test_the_coupon_svg_draws_every_hole_to_scale(designed: Path) -> None:
    loaded = load_design_part(designed)
    coupon = calibration_coupon(loaded.fabrication.process, loaded.config.scene.plate)
    width, height = coupon.outline_mm
    svg = ET.fromstring((designed / COUPON_SVG).read_text())
    assert float(svg.get("width", "").removesuffix("mm")) == pytest.approx(width)
    assert float(svg.get("height", "").removesuffix("mm")) == pytest.approx(height)
    circles = svg.findall(f".//{NS}circle")
    layout = coupon_layout(coupon)
    assert len(circles) == layout.count == len(coupon.diameters_mm) * coupon.repeat**2
    drawn = np.array([[float(c.get(k, "nan")) for k in ("cx", "cy", "r")] for c in circles])
    # SVG's y runs down from the top edge: (x + width / 2, height / 2 - y)
    want = np.column_stack([layout.centres_mm[:, 0] + width / 2,
                            height / 2 - layout.centres_mm[:, 1], layout.radii_mm])
    assert drawn == pytest.approx(want, abs=1e-6)
    assert np.all(drawn[:, 2] > 0) and np.all(np.abs(drawn[:, :2] - [width / 2, height / 2])
                                              + drawn[:, 2:] < [width / 2, height / 2])


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
    rows = [r for r in holes_csv(coupon_layout(coupon)).splitlines() if not r.startswith("#")]
    assert rows[0] == "row,col,x_mm,y_mm,radius_mm,axis_x,axis_y"
    assert len(rows) == 1 + 9 * 25
    assert coupon.block_gap_mm == pytest.approx(1.0)  # whole cells: 4 of 0.25 mm
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
        assembly_html(loaded.part, other.scene, loaded.fabrication.process, loaded.names)


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


def test_the_sheet_says_where_each_command_runs_and_what_it_needs(designed: Path) -> None:
    page = (designed / ASSEMBLY_NAME).read_text()
    listed = json.loads((designed / MANIFEST_NAME).read_text())["files"]
    commands = sheet_commands(page)
    assert sorted(shlex.split(line)[-1] for _, _, line, _ in commands) == ["coupon.step",
                                                                           "frame.stl"]
    assert f"run in the design folder ({shlex.join(['cd', str(designed.resolve())])})" in page
    for folder, needs_cad, line, note in commands:
        argv = shlex.split(line)
        assert folder == designed.resolve()
        assert argv[0] == sys.executable  # the Python that has aperture-fab
        script = Path(argv[1])
        assert script.is_absolute() and script.is_file(), script
        if "--design" in argv:
            assert (folder / argv[argv.index("--design") + 1] / "design.toml").is_file()
        for arg in argv[2:]:
            if arg.endswith(".csv"):
                assert (folder / arg).is_file(), arg
        assert argv[-1] not in listed  # what it writes never clashes with the design's set
        assert needs_cad, line  # both are cad/ scripts: the note says so, and how to install
        assert f"<b>{CAD_EXTRA}</b> extra" in note and "1.3 GB" in note
        assert "pip install -e" in note and f"[{CAD_EXTRA}]" in note


def test_the_command_adds_the_sheet_to_an_older_or_moved_design_set(designed: Path,
                                                                     tmp_path: Path) -> None:
    folder = tmp_path / "moved"
    shutil.copytree(designed, folder)
    manifest = json.loads((folder / MANIFEST_NAME).read_text())
    for name in (COUPON_STL, COUPON_SVG, COUPON_CSV):  # as an older aperture-fab left it
        (folder / name).unlink()
        del manifest["files"][name]
    (folder / MANIFEST_NAME).write_text(json.dumps(manifest))
    check_folder(folder)
    assert run_assembly(folder) == folder / ASSEMBLY_NAME
    check_folder(folder)  # sheet and coupon joined the set: it still matches its manifest
    again = json.loads((folder / MANIFEST_NAME).read_text())
    assert set(SHEET_NAMES) <= set(again["files"]) and again["command"] == manifest["command"]
    assert set(again["files"]) == set(manifest["files"]) | set(SHEET_NAMES)
    for name in (COUPON_STL, COUPON_SVG, COUPON_CSV):
        assert (folder / name).read_bytes() == (designed / name).read_bytes()
    # the sheet now sends its commands to the folder where the design is
    assert {cwd for cwd, *_ in sheet_commands((folder / ASSEMBLY_NAME).read_text())} \
        == {folder.resolve()}


@pytest.mark.slow
@pytest.mark.parametrize("writes", ["frame.stl", "coupon.step"])
def test_the_sheet_commands_run_as_printed(designed: Path, tmp_path: Path, writes: str) -> None:
    folder = tmp_path / "design"
    shutil.copytree(designed, folder)
    run_assembly(folder)
    [(cwd, needs_cad, line, _)] = [c for c in sheet_commands((folder / ASSEMBLY_NAME).read_text())
                                   if shlex.split(c[2])[-1] == writes]
    if needs_cad and not HAS_CAD:
        pytest.skip(f"{writes}: the command needs the {CAD_EXTRA} extra (CadQuery, about 1.3 GB), "
                    f"not installed here: pip install -e '.[{CAD_EXTRA}]'")
    result = subprocess.run(line, shell=True, cwd=cwd, capture_output=True, text=True,
                            timeout=CAD_COMMAND_TIMEOUT_S, check=False)
    assert result.returncode == 0, result.stderr[-2000:]
    assert f"wrote {writes}" in result.stdout
    assert (cwd / writes).stat().st_size > 0
    check_folder(folder)  # what the commands write stays outside the design's set
    if writes == "coupon.step":  # the CAD coupon is the mesh coupon: the same solid
        import cadquery as cq

        solid = cq.importers.importStep(str(cwd / writes)).val()
        mesh = check_mesh(read_stl((folder / COUPON_STL).read_bytes()))
        assert solid.isValid() and solid.Volume() == pytest.approx(mesh.volume_mm3, rel=1e-4)


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
    browser = require_tool("chromium", "chromium-browser",
                           install="Debian: apt-get install -y chromium")
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
