"""The fabrication stage inside the design job and the export command."""

from __future__ import annotations

import io
import math
import zipfile

import numpy as np
import pytest

from aperture_fab.cli import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_OK, EXIT_REPORT_FAIL, main
from aperture_fab.config.config import resolve
from aperture_fab.config.stages import FabricationSettings
from aperture_fab.fabrication.mesh_checks import check_mesh, mesh_volume_mm3
from aperture_fab.fabrication.part import design_bounds, make_part
from aperture_fab.fabrication.process import PROCESSES, UnmakeableError, resolve_process
from aperture_fab.io.formats import read_stl
from aperture_fab.io.images import encode_png
from aperture_fab.targets import digit

TINY = {
    "display.width_mm": 4.0, "display.height_mm": 4.0, "display.pixels": [32, 32],
    "plate.cells": [16, 16], "plate.pitch_mm": [0.25, 0.25], "eye.view_pixels": [12, 12],
    "plate.thickness_mm": 0.1, "optimizer.iterations": 3, "optimizer.device": "cpu",
}


def tiny_config(**extra):
    return resolve("near-eye-nominal", overrides={**TINY, **extra})


def test_design_bounds_follow_the_process():
    scene = tiny_config().scene
    lo, hi = design_bounds(scene, PROCESSES["photomask"])
    assert lo == 0.0
    assert 0 < hi <= scene.plate.max_open_fraction


@pytest.mark.parametrize("axis", ["straight", "chief_ray"])
def test_make_part_builds_a_checked_solid(axis):
    config = tiny_config(**{"plate.hole_axis": axis})
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 0.4, (16, 16))
    settings = FabricationSettings(resolve_process("photomask"))
    part = make_part(a, config.scene, settings)
    report = check_mesh(part.mesh)
    assert report.watertight and report.consistently_oriented and report.bodies == 1
    assert report.genus == part.layout.count > 0
    width, height = part.layout.outline_mm
    chamfer = part.corner_cut_mm**2 / 2
    solid = (width * height - chamfer - np.sum(math.pi * part.layout.radii_mm**2))
    assert mesh_volume_mm3(part.mesh) == pytest.approx(solid * part.layout.thickness_mm, rel=1e-6)


def test_unmakeable_design_is_refused_before_optimizing(tmp_path, capsys):
    target = tmp_path / "t.png"
    target.write_bytes(encode_png(digit("3")))
    flags = ["design", str(target), "--out", str(tmp_path / "out" / "plate.stl"), "--quiet",
             "--process", "fdm", "--cells", "16", "16", "--view-pixels", "12", "12",
             "--iterations", "2", "--device", "cpu", "--thickness-mm", "0.1"]
    assert main(flags) == EXIT_FAILED  # refused: the process cannot make it
    err = capsys.readouterr().err
    assert "fdm" in err and ("photomask" in err or "etched-foil" in err)
    assert not (tmp_path / "out" / "design.npz").exists()


def test_force_writes_with_violations(tmp_path):
    target = tmp_path / "t.png"
    target.write_bytes(encode_png(digit("3")))
    out = tmp_path / "out"
    flags = ["design", str(target), "--out", str(out / "plate.stl"), "--quiet", "--process",
             "fdm", "--force", "--cells", "16", "16", "--view-pixels", "12", "12",
             "--iterations", "2", "--device", "cpu", "--thickness-mm", "0.1"]
    assert main(flags) in (EXIT_OK, EXIT_REPORT_FAIL)
    import json

    summary = json.loads((out / "design.json").read_text())
    rules = {v["rule"] for v in summary["fabrication"]["violations"]}
    assert "process" in rules
    mesh = read_stl((out / "plate.stl").read_bytes())
    assert check_mesh(mesh).watertight


def test_design_writes_every_part_file_and_export_rebuilds(tmp_path):
    target = tmp_path / "t.png"
    target.write_bytes(encode_png(digit("3")))
    out = tmp_path / "out"
    flags = ["design", str(target), "--out", str(out / "plate.stl"), "--quiet", "--process",
             "photomask", "--cells", "16", "16", "--view-pixels", "12", "12",
             "--iterations", "2", "--device", "cpu", "--thickness-mm", "0.1"]
    assert main(flags) in (EXIT_OK, EXIT_REPORT_FAIL)
    for name in ("plate.stl", "plate.3mf", "holes.csv", "plate.dxf", "plate.svg"):
        assert (out / name).stat().st_size > 0, name
    with zipfile.ZipFile(io.BytesIO((out / "plate.3mf").read_bytes())) as z:
        assert "3D/3dmodel.model" in z.namelist()
    holes = [line for line in (out / "holes.csv").read_text().strip().splitlines()
             if not line.startswith("#")]  # the outline comment
    mesh = read_stl((out / "plate.stl").read_bytes())
    assert check_mesh(mesh).genus == len(holes) - 1
    # Rebuild for another process and format from the saved design.
    again = tmp_path / "again" / "part.svg"
    assert main(["export", str(out / "design.npz"), "--out", str(again), "--process",
                 "etched-foil", "--quiet"]) == 0
    assert again.read_text().startswith("<")
    assert not list(again.parent.glob(".*.tmp"))


def test_export_of_a_missing_design_is_a_clear_error(tmp_path, capsys):
    argv = ["export", str(tmp_path / "nope.npz"), "--out", str(tmp_path / "x.stl")]
    assert main(argv) == EXIT_BAD_INPUT
    assert "nope.npz" in capsys.readouterr().err


def test_unknown_process_and_bad_thickness_are_clear_errors():
    with pytest.raises(ValueError, match="resin"):
        FabricationSettings().with_flags(process="resn")
    config = tiny_config(**{"plate.thickness_mm": 20.0})
    with pytest.raises(UnmakeableError, match="thickness"):
        make_part(np.full((16, 16), 0.2), config.scene,
                  FabricationSettings().with_flags(process="photomask"))


def test_pitch_too_small_names_what_would_work():
    config = tiny_config(**{"plate.pitch_mm": [0.05, 0.05]})
    process = resolve_process("laser")
    with pytest.raises(UnmakeableError) as err:
        make_part(np.full((16, 16), 0.2), config.scene,
                  FabricationSettings(process))
    assert "pitch" in str(err.value)
