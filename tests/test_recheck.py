"""`aperture-fab validate` and `aperture-fab render` on an existing part (design.npz, holes.csv,
STL), and read_holes_csv, the hole table read back."""

from __future__ import annotations

import csv
import io
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import design_tiny
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from aperture_fab.cli import EXIT_BAD_INPUT, EXIT_OK, EXIT_REPORT_FAIL, main
from aperture_fab.config.config import parse_toml, resolve
from aperture_fab.fabrication.layout import HoleLayout
from aperture_fab.fabrication.process import resolve_process
from aperture_fab.fabrication.rules import layout_violations
from aperture_fab.io.formats import holes_csv, read_holes_csv
from aperture_fab.io.images import srgb_to_linear
from aperture_fab.optics.model import Renderer
from aperture_fab.optics.scene import Plate
from aperture_fab.pipeline.render_job import run_render
from aperture_fab.pipeline.saved import load_part, read_design
from aperture_fab.validation.report import validate_report
from aperture_fab.validation.validate import layout_fractions

pytestmark = pytest.mark.usefixtures("one_torch_thread")

FAST = ["--tolerance-samples", "2", "--mesh-samples", "16", "--quiet"]
#: 8-bit sRGB PNGs hold a value to half a step.
HALF_STEP = 0.5 / 255 + 1e-9


@pytest.fixture
def copy(designed: Path, tmp_path: Path) -> Path:
    """A private copy of the design folder (tests write beside the part)."""
    target = tmp_path / "design"
    shutil.copytree(designed, target)
    return target


def validate_cli(part: Path, *extra: str) -> dict:
    out = part.parent / f"check_{part.suffix[1:]}"
    code = main(["validate", str(part), str(part.parent / "marker.png"), "--out", str(out),
                 *FAST, *extra])
    assert code in (EXIT_OK, EXIT_REPORT_FAIL)  # any verdict
    return json.loads((out / "report.json").read_text())


def as_built_psnr(report: dict) -> float:
    return float(report["metrics"]["as_built"]["mean"]["psnr_db"])


def png_linear(path: Path) -> np.ndarray:
    with Image.open(path) as im:
        samples = np.asarray(im, dtype=np.float64) / 255
    samples = samples[None] if samples.ndim == 2 else samples.transpose(2, 0, 1)
    return srgb_to_linear(samples)


# --- read_holes_csv ----------------------------------------------------------------------------


def _layout(seed: int, chief_ray: bool) -> tuple[HoleLayout, Plate]:
    rng = np.random.default_rng(seed)
    nx, ny, pitch, t = 5, 4, 0.5, 0.3
    plate = Plate((nx, ny), (pitch, pitch), 5.0, t, "chief_ray" if chief_ray else "straight")
    k = int(rng.integers(0, nx * ny + 1))
    rows, cols = np.divmod(np.sort(rng.choice(nx * ny, size=k, replace=False)), nx)
    centres = np.stack([(cols - (nx - 1) / 2) * pitch, ((ny - 1) / 2 - rows) * pitch], axis=1)
    converge = (0.3, -0.2, 8.0) if chief_ray else None
    axes = ((np.array([0.3, -0.2]) - centres) / 8.0 if chief_ray else np.zeros((k, 2)))
    layout = HoleLayout(np.stack([rows, cols], axis=1).astype(np.int64), centres.astype(float),
                        rng.uniform(0.02, 0.2, k), axes, (pitch, pitch), (nx, ny), (4.5, 4.0), t,
                        converge_mm=converge)
    return layout, plate


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), chief_ray=st.booleans())
def test_read_holes_csv_inverts_holes_csv(seed: int, chief_ray: bool) -> None:
    layout, plate = _layout(seed, chief_ray)
    back = read_holes_csv(holes_csv(layout), plate, outline_mm=layout.outline_mm,
                          converge_mm=layout.converge_mm)
    np.testing.assert_array_equal(back.cells, layout.cells)
    np.testing.assert_allclose(back.centres_mm, layout.centres_mm, atol=5e-7)
    np.testing.assert_allclose(back.radii_mm, layout.radii_mm, atol=5e-7)
    np.testing.assert_allclose(back.axes, layout.axes, atol=1e-7)
    assert back.converge_mm == layout.converge_mm
    assert (back.grid, back.pitch_mm, back.outline_mm, back.thickness_mm) == (
        layout.grid, layout.pitch_mm, layout.outline_mm, layout.thickness_mm)
    # Rewriting the table read back gives the same text: nothing is lost or reordered.
    assert holes_csv(back) == holes_csv(layout)


def test_read_holes_csv_closes_zero_radii_and_keeps_edited_axes() -> None:
    layout, plate = _layout(7, True)
    rows = list(csv.reader(io.StringIO(holes_csv(layout))))
    rows[1][4] = "0"  # close the first hole
    rows[2][5] = "0.5"  # tilt the second far from the eye point
    assert layout.count >= 2
    text = ",".join(reversed(rows[0])) + "\r\n" + "\r\n".join(
        ",".join(reversed(r)) for r in rows[1:]) + "\r\n\r\n"
    back = read_holes_csv(text, plate, outline_mm=layout.outline_mm,
                          converge_mm=layout.converge_mm)
    assert back.count == layout.count - 1
    assert tuple(back.cells[0]) == tuple(layout.cells[1])
    assert back.axes[0, 0] == 0.5
    assert back.converge_mm is None  # the axes no longer meet at one point


@pytest.mark.parametrize(("edit", "message"), [
    (lambda t: "row,col,x,y\n" + t.split("\n", 1)[1], "header"),
    (lambda t: t + "99,0,0,0,0.1,0,0\n", "line"),
    (lambda t: t + "0,0,0,0,-0.1,0,0\n", "radius_mm = -0.1"),
    (lambda t: t + "0,0,0,0,abc,0,0\n", "'abc' is not a number"),
    (lambda t: t + "0,0,0,0,0.1\n", "5 fields"),
    (lambda t: t + t.split("\n")[1] + "\n", "listed again"),
    (lambda t: "", "empty"),
])
def test_read_holes_csv_errors_name_the_line_and_the_fix(edit, message: str) -> None:
    layout, plate = _layout(3, False)
    assert layout.count > 0
    with pytest.raises(ValueError, match=message) as info:
        read_holes_csv(edit(holes_csv(layout)), plate, outline_mm=layout.outline_mm,
                       source="edited.csv")
    assert "edited.csv" in str(info.value)


def test_layout_violations_lists_small_holes_and_thin_webs() -> None:
    layout, plate = _layout(11, False)
    process = resolve_process("laser")  # 0.3 mm holes and webs at 0.3 mm thickness
    found = layout_violations(layout, plate, process)
    diameters = 2 * layout.radii_mm
    small = {tuple(c) for c, d in zip(layout.cells.tolist(), diameters, strict=True) if d < 0.3}
    assert {v.cell for v in found if v.rule == "min_hole"} == small
    assert all(v.limit_mm == pytest.approx(0.3) for v in found if v.rule == "min_hole")
    # 0.5 mm cells cannot hold a 0.3 mm hole and a 0.3 mm web: the plate itself is named.
    assert [v.rule for v in found if v.cell is None] == ["process"]
    # Widely spaced, large-enough holes break nothing.
    plate = Plate((3, 3), (2.0, 2.0), 5.0, 0.3)
    ok = HoleLayout(np.array([[0, 0], [1, 1]]), np.array([[-2.0, 2.0], [0.0, 0.0]]),
                    np.array([0.4, 0.5]), np.zeros((2, 2)), (2.0, 2.0), (3, 3), (8.0, 8.0), 0.3)
    assert layout_violations(ok, plate, process) == ()
    near = HoleLayout(np.array([[1, 0], [1, 1]]), np.array([[-2.0, 0.0], [-0.8, 0.0]]),
                      np.array([0.5, 0.5]), np.zeros((2, 2)), (2.0, 2.0), (3, 3), (8.0, 8.0),
                      0.3)  # hand-moved: 0.2 mm web between the two holes
    webs = [v for v in layout_violations(near, plate, process) if v.rule == "min_web"]
    assert {v.cell for v in webs} == {(1, 0), (1, 1)}
    assert webs[0].value_mm == pytest.approx(0.2)


# --- validate ----------------------------------------------------------------------------------


def test_validate_agrees_across_part_kinds_and_writes_valid_reports(copy: Path) -> None:
    reports = {kind: validate_cli(copy / name)
               for kind, name in (("npz", "design.npz"), ("csv", "holes.csv"),
                                  ("stl", "plate.stl"))}
    for kind, report in reports.items():
        validate_report(report)
        folder = copy / f"check_{kind}"
        assert {p.name for p in folder.iterdir()} >= {"report.json", "report.html", "views.npz",
                                                      "display_marker.png"}
        assert report["checked_part"]["display"] == "kept"  # the design's own part
        with np.load(folder / "views.npz") as views:
            assert views["as_built/marker"].shape == (1, 16, 16)
    psnr = {kind: as_built_psnr(r) for kind, r in reports.items()}
    assert psnr["csv"] == pytest.approx(psnr["npz"], abs=0.01)
    assert psnr["stl"] == pytest.approx(psnr["npz"], abs=0.01)
    assert reports["csv"]["fabrication"]["holes"] == reports["npz"]["fabrication"]["holes"]


@pytest.fixture(scope="module")
def validated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny design's folder with its own report (design validated it)."""
    folder = tmp_path_factory.mktemp("validated")
    assert design_tiny(folder, "--out", str(folder / "plate.stl"), "--quiet") in (
        EXIT_OK, EXIT_REPORT_FAIL)
    return folder


def _judgement(report: dict) -> dict:
    """What a report says of a part: verdict levels, the figures over the eye distribution and
    as made, and the nominal metrics."""
    made = report["made_part"]
    return {"verdicts": [(v["topic"], v["level"]) for v in report["verdicts"]],
            "eye": report["eye_distribution"]["variants"]["as_built"]["psnr_db"],
            "made": (made["part"], made["margin_db"]),
            "nominal": {k: report["metrics"][k]["mean"]["psnr_db"]
                        for k in ("optimized", "quantized", "as_built")},
            "tolerance": report["tolerance"]}


@pytest.mark.slow
@pytest.mark.parametrize("name", ["plate.stl", "holes.csv", "design.npz"])
def test_validate_of_a_designs_part_says_what_design_said(validated: Path, name: str) -> None:
    """One judgement: validate of the part a design wrote gives the design's own figures and
    verdicts (the same part, display content and validation settings)."""
    out = validated / f"again_{name.replace('.', '_')}"
    assert main(["validate", str(validated / name), str(validated / "marker.png"), "--out",
                 str(out), "--quiet"]) in (EXIT_OK, EXIT_REPORT_FAIL)
    design = json.loads((validated / "report.json").read_text())
    again = json.loads((out / "report.json").read_text())
    assert again["checked_part"]["display"] == "kept"
    want, got = _judgement(design), _judgement(again)
    assert got["verdicts"] == want["verdicts"]
    for key in ("eye", "made", "nominal", "tolerance"):
        assert json.dumps(got[key], sort_keys=True) == json.dumps(want[key], sort_keys=True), key


def test_closing_holes_in_the_table_changes_the_judged_part(copy: Path) -> None:
    before = as_built_psnr(validate_cli(copy / "holes.csv", "--keep-display"))
    # The comment line (the outline) is last; keep it out of the edit.
    lines = [line for line in (copy / "holes.csv").read_text().splitlines()
             if not line.startswith("#")]
    assert len(lines) > 2
    # Close three holes in four. The tiny design (8 iterations from the dense start) is far from
    # optimal, so closing holes may help it or hurt it; either way validate judges the edit.
    edited = [lines[0]] + [
        ",".join([*line.split(",")[:4], "0", *line.split(",")[5:]]) if i % 4 else line
        for i, line in enumerate(lines[1:])]
    (copy / "holes.csv").write_text("\n".join(edited) + "\n")
    report = validate_cli(copy / "holes.csv", "--keep-display")
    assert report["checked_part"]["display"] == "kept"
    assert report["fabrication"]["holes"] == (len(lines) - 1 + 3) // 4
    assert abs(as_built_psnr(report) - before) > 0.5


def test_a_hole_that_breaks_the_rules_is_validated_and_reported(copy: Path) -> None:
    lines = (copy / "holes.csv").read_text().splitlines()
    fields = lines[1].split(",")
    fields[4] = "0.005"  # a 0.01 mm hole: below photomask film's 0.025 mm smallest
    (copy / "holes.csv").write_text("\n".join([lines[0], ",".join(fields), *lines[2:]]) + "\n")
    report = validate_cli(copy / "holes.csv", "--keep-display")
    rules = [(v["rule"], v["cell"]) for v in report["fabrication"]["violations"]]
    assert ("min_hole", [int(fields[0]), int(fields[1])]) in rules


def test_an_stl_of_another_grid_is_refused_naming_the_file(
        copy: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = copy / "other" / "design.toml"  # no design.npz beside it
    config.parent.mkdir()
    config.write_text((copy / "design.toml").read_text().replace("cells = [16, 16]",
                                                                 "cells = [4, 4]"))
    code = main(["validate", str(copy / "plate.stl"), str(copy / "marker.png"), "--config",
                 str(config), *FAST])
    err = capsys.readouterr().err
    assert code == EXIT_BAD_INPUT
    assert "plate.stl" in err and "4 x 4 cells" in err and "--config" in err


def test_the_number_of_targets_must_match_the_design(
        copy: Path, capsys: pytest.CaptureFixture[str]) -> None:
    marker = str(copy / "marker.png")
    code = main(["validate", str(copy / "holes.csv"), marker, marker, *FAST])
    err = capsys.readouterr().err
    assert code == EXIT_BAD_INPUT and "design.npz" in err and "1 target(s)" in err


@pytest.mark.parametrize(("argv", "named"), [
    (["validate", "{d}/nothing.csv", "{d}/marker.png"], "nothing.csv"),
    (["validate", "{d}/holes.csv", "{d}/missing.png"], "missing.png"),
    (["validate", "{d}/holes.csv", "{d}/marker.png", "--config", "{d}/none.toml"], "none.toml"),
    (["validate", "{d}/marker.png", "{d}/marker.png"], "marker.png"),
    (["render", "{d}/gone.stl"], "gone.stl"),
    (["render", "{d}/plate.stl", "--config", "{d}/none.toml"], "none.toml"),
    (["render", "{d}/plate.stl", "{d}/missing.png"], "missing.png"),
])
def test_missing_or_wrong_files_exit_three_naming_the_file(
        designed: Path, argv: list[str], named: str,
        capsys: pytest.CaptureFixture[str]) -> None:
    code = main([a.format(d=designed) for a in argv])
    err = capsys.readouterr().err
    assert code == EXIT_BAD_INPUT
    assert named in err


# --- render ------------------------------------------------------------------------------------


def test_render_matches_the_renderer_and_the_png(copy: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    out = copy / "view.png"
    assert main(["render", str(copy / "holes.csv"), "--out", str(out)]) == 0
    assert "light efficiency" in capsys.readouterr().out
    config = resolve(None, parse_toml((copy / "design.toml").read_text(), "design.toml"))
    process = config.fabrication.process
    layout = load_part(copy / "holes.csv", "holes", config, config.fabrication,
                       copy / "design.toml").layout
    display = read_design(copy / "design.npz").built_displays
    assert display is not None
    renderer = Renderer(config.scene, dtype=torch.float32)
    with torch.no_grad():
        want = renderer.render(torch.as_tensor(layout_fractions(layout, process.radius_bias_mm),
                                               dtype=torch.float32),
                               torch.as_tensor(display[0], dtype=torch.float32), 0).double().numpy()
    rendered = run_render(copy / "holes.csv", out=copy / "again.png")
    np.testing.assert_allclose(rendered.view, want, rtol=1e-5, atol=1e-9)
    scaled = np.clip(want / np.percentile(want, 99.5), 0, 1)
    got = png_linear(out)
    assert got.shape == want.shape
    # Compare in sRGB samples: the PNG holds each to half a step.
    from aperture_fab.io.images import linear_to_srgb

    assert np.max(np.abs(linear_to_srgb(got) - linear_to_srgb(scaled))) <= HALF_STEP


def test_render_with_a_target_reports_its_psnr(copy: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    out = copy / "t.png"
    assert main(["render", str(copy / "plate.stl"), str(copy / "marker.png"), "--out",
                 str(out)]) == 0
    text = capsys.readouterr().out
    rendered = run_render(copy / "plate.stl", target=copy / "marker.png", out=copy / "t2.png")
    assert rendered.psnr_db is not None and f"PSNR {rendered.psnr_db:.2f} dB" in text
    assert 0 < rendered.light_efficiency < 1
    assert out.read_bytes() == (copy / "t2.png").read_bytes()


def test_a_moved_eye_sees_another_view(copy: Path) -> None:
    here = run_render(copy / "design.npz", out=copy / "a.png")
    there = run_render(copy / "design.npz", eye_mm=(2.5, -1.0), out=copy / "b.png")
    assert there.eye_mm == (2.5, -1.0) and here.eye_mm == (0.0, 0.0)
    change = np.abs(there.view - here.view).sum() / np.abs(here.view).sum()
    assert change > 0.2
    assert main(["render", str(copy / "design.npz"), "--eye", "2.5,-1", "--pupil", "3",
                 "--focus", "infinity", "--out", str(copy / "c.png")]) == 0


def test_render_through_the_mesh_follows_the_model(copy: Path) -> None:
    exact = run_render(copy / "plate.stl", out=copy / "exact.png")
    traced = run_render(copy / "plate.stl", mesh=True, mesh_samples=64, out=copy / "mesh.png")
    assert traced.view.shape == exact.view.shape
    # Two independent models of the same holes: the light they pass agrees roughly.
    assert traced.view.mean() == pytest.approx(exact.view.mean(), rel=0.5)


def test_render_flags_are_checked(copy: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["render", str(copy / "plate.stl"), "--eye", "1"]) == EXIT_BAD_INPUT
    assert "--eye '1'" in capsys.readouterr().err
    assert main(["render", str(copy / "plate.stl"), "--target-index", "3"]) == EXIT_BAD_INPUT
    assert "--target-index 3" in capsys.readouterr().err
    assert main(["render", str(copy / "plate.stl"), "--focus", "near"]) == EXIT_BAD_INPUT
    assert "--focus 'near'" in capsys.readouterr().err
