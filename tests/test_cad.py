"""The cad/ scripts read a design folder: the plate's outline, thickness and alignment key, and a
frame whose pocket is keyed to the plate. They build real CadQuery solids (slow); skipped when
cadquery is not installed (pip install -e .[cad])."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest

from aperture_fab.pipeline.assembly_job import load_design_part

pytestmark = pytest.mark.slow

CAD_DIR = Path(__file__).resolve().parent.parent / "cad"
#: Relative tolerance on B-rep volumes (exact circles; OCCT's volume integration).
REL = 1e-6


def load_cad(name: str) -> ModuleType:
    pytest.importorskip("cadquery", reason="cad/ scripts need cadquery (pip install cadquery)")
    spec = importlib.util.spec_from_file_location(f"cad_{name}", CAD_DIR / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def step_solid(path: Path) -> Any:
    import cadquery as cq

    shape = cq.importers.importStep(str(path)).val()
    assert shape.isValid()
    return shape


def test_plate_from_the_design_has_its_outline_key_and_holes(designed: Path,
                                                              tmp_path: Path) -> None:
    module = load_cad("plate_from_csv")
    out = tmp_path / "plate.step"
    module.main(["--design", str(designed), "--out", str(out)])
    part = load_design_part(designed).part
    width, height = part.layout.outline_mm
    cut, t = part.corner_cut_mm, part.layout.thickness_mm
    assert (width, height) == (6.0, 6.0) and cut > 0
    solid = step_solid(out)
    # Every z-section of a hole is a circle of its radius: each removes pi r^2 t.
    holes = float(np.sum(math.pi * part.layout.radii_mm**2)) * t
    assert solid.Volume() == pytest.approx((width * height - cut**2 / 2) * t - holes, rel=REL)
    box = solid.BoundingBox()
    assert (box.xlen, box.ylen, box.zlen) == pytest.approx((width, height, t), abs=1e-6)
    import cadquery as cq

    # the chamfer is at the top-left seen from the eye (-x, +y), nowhere else
    inset = cut / 4
    assert not solid.isInside(cq.Vector(-width / 2 + inset, height / 2 - inset, t / 2))
    assert solid.isInside(cq.Vector(width / 2 - inset, height / 2 - inset, t / 2))


def test_frame_from_the_design_is_keyed_to_the_plate(designed: Path, tmp_path: Path) -> None:
    import cadquery as cq

    module = load_cad("mount_frame")
    out = tmp_path / "frame.step"
    module.main(["--design", str(designed), "--display", "20", "12", "--out", str(out)])
    part = load_design_part(designed).part
    width, height = part.layout.outline_mm
    cut = part.corner_cut_mm
    plate = module.design_plate(designed)
    assert plate["key_mm"] == cut and plate["plate_width_mm"] == width
    spec = module.FrameSpec(display_width_mm=20.0, display_height_mm=12.0,
                            ledge_mm=module.default_ledge(plate), **plate)
    frame = step_solid(out)
    assert frame.Volume() == pytest.approx(module.make_frame(spec).val().Volume(), rel=REL)
    unkeyed = module.make_frame(module.FrameSpec(**{**vars(spec), "key_mm": 0.0})).val()
    leg = cut + spec.clearance_mm * (2 - math.sqrt(2))
    key = leg**2 / 2 * spec.plate_thickness_mm
    assert frame.Volume() - unkeyed.Volume() == pytest.approx(key, rel=1e-4)
    # The key fills the pocket's top-left corner (seen from the eye); the others are open.
    w, h = width / 2 + spec.clearance_mm, height / 2 + spec.clearance_mm
    z = spec.gap_mm + spec.plate_thickness_mm / 2
    d = leg / 4
    assert frame.isInside(cq.Vector(-w + d, h - d, z))
    for sx, sy in ((1, 1), (-1, -1), (1, -1)):
        assert not frame.isInside(cq.Vector(sx * (w - d), sy * (h - d), z))
    # the plate seats: its chamfered outline fits the keyed pocket everywhere
    plate_solid = load_cad("plate_from_csv").make_plate(
        [], width, height, spec.plate_thickness_mm, cut).val().moved(
        cq.Location(cq.Vector(0, 0, spec.gap_mm)))
    assert plate_solid.intersect(frame).Volume() == pytest.approx(0, abs=1e-9)
    # turned over (chamfer top-right), it hits the key
    turned = plate_solid.mirror("YZ")
    assert turned.intersect(frame).Volume() > 1e-4


def test_explicit_sizes_still_work(designed: Path, tmp_path: Path) -> None:
    module = load_cad("plate_from_csv")
    out = tmp_path / "plate.step"
    module.main([str(designed / "holes.csv"), "--width", "6", "--height", "6.5",
                 "--thickness", "0.4", "--out", str(out)])
    box = step_solid(out).BoundingBox()
    assert (box.xlen, box.ylen, box.zlen) == pytest.approx((6.0, 6.5, 0.4), abs=1e-6)


@pytest.mark.parametrize(("script", "argv", "words"), [
    ("plate_from_csv", ["{csv}", "--width", "-3", "--height", "6", "--thickness", "0.3"],
     ["--width -3.0", "allowed: 0 < width <= 2000 mm"]),
    ("plate_from_csv", ["{csv}", "--width", "3.5", "--height", "3.5", "--thickness", "0.3"],
     ["crosses the outline 3.5 x 3.5 mm", "allowed: an outline of at least", "--design"]),
    ("plate_from_csv", ["{csv}", "--width", "6", "--height", "6", "--thickness", "0.3",
                        "--corner-cut", "4"], ["--corner-cut 4.0", "allowed: 0 (no key)"]),
    ("plate_from_csv", ["{csv}", "--width", "6"], ["--height --thickness"]),
    ("plate_from_csv", ["--design", "{empty}"], ["not a design folder"]),
    ("mount_frame", ["--plate", "22", "22", "--key", "0.1"],
     ["key_mm = 0.1", "allowed: above 0.212 mm"]),
    ("mount_frame", ["--display", "10", "10", "--plate", "22", "22"],
     ["plate_width_mm = 22.0 does not fit", "Use a smaller plate"]),
    ("mount_frame", ["--gap", "0.9"], ["gap_mm = 0.9", "allowed: gap >= bezel height"]),
    ("mount_frame", ["--design", "{designed}", "--ledge", "1.2"],
     ["covers the outer holes", "allowed: ledge_mm <="]),
    ("mount_frame", ["--design", "{empty}"], ["not a design folder"]),
])
def test_bad_sizes_are_refused_with_the_value_range_and_fix(
        script: str, argv: list[str], words: list[str], designed: Path, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    module = load_cad(script)
    values = {"csv": str(designed / "holes.csv"), "empty": str(tmp_path),
              "designed": str(designed)}
    out = tmp_path / "x.step"
    with pytest.raises(SystemExit) as info:
        module.main([a.format(**values) for a in argv] + ["--out", str(out)])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    for word in words:
        assert word in err, err
    assert not out.exists()
