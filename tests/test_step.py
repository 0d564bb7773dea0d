"""STEP export: one valid closed solid with exact hole walls, checked against plain geometry.

Needs OCCT's bindings: pip install cadquery-ocp==7.9.3.1.1 (the cad/ tests also need cadquery).
"""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from aperture_fab.fabrication.layout import HoleLayout
from aperture_fab.fabrication.process import PROCESSES
from aperture_fab.fabrication.quantize import quantize
from aperture_fab.fabrication.step import (
    STRAIGHT_AXIS_LIMIT,
    StepSummary,
    build_solid,
    read_step_summary,
    shape_summary,
    step_bytes,
)
from aperture_fab.fabrication.step_layout import HOLES_PER_TILE_SIDE, tile_count
from aperture_fab.optics.scene import Plate

# aperture_fab.fabrication.step imports OCP only inside its functions.
pytest.importorskip("OCP", reason="STEP export needs cadquery-ocp (pip install cadquery-ocp)")

THICKNESS_MM = 0.3
PITCH_MM = 1.0
MARGIN_MM = 1.0
#: OCCT pads bounding boxes by its tolerance; our checks allow this much.
BOUNDS_SLACK_MM = 1e-6
REL = 1e-6
CAD_DIR = Path(__file__).resolve().parent.parent / "cad"


def grid_layout(
    nx: int,
    ny: int,
    tilt_per_mm: float = 0.0,
    keep: np.ndarray | None = None,
    seed: int = 0,
) -> HoleLayout:
    """nx x ny holes at PITCH_MM, radii varying, axes = tilt_per_mm * centre (chief-ray like)."""
    rows, cols = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    cells = np.stack([rows.ravel(), cols.ravel()], axis=1).astype(np.int64)
    if keep is not None:
        cells = cells[keep]
    centres = np.stack(
        [(cells[:, 1] - (nx - 1) / 2) * PITCH_MM, ((ny - 1) / 2 - cells[:, 0]) * PITCH_MM], axis=1
    )
    radii = np.random.default_rng(seed).uniform(0.1, 0.4, size=len(cells))
    return HoleLayout(
        cells=cells,
        centres_mm=centres,
        radii_mm=radii,
        axes=tilt_per_mm * centres,
        pitch_mm=(PITCH_MM, PITCH_MM),
        grid=(nx, ny),
        outline_mm=(nx * PITCH_MM + 2 * MARGIN_MM, ny * PITCH_MM + 2 * MARGIN_MM),
        thickness_mm=THICKNESS_MM,
    )


def holes_layout(centres: list[tuple[float, float]], radii: list[float],
                 axes: list[tuple[float, float]], outline: tuple[float, float] = (6.0, 4.0)
                 ) -> HoleLayout:
    k = len(radii)
    return HoleLayout(
        cells=np.zeros((k, 2), dtype=np.int64) + np.arange(k)[:, None],
        centres_mm=np.array(centres, dtype=np.float64).reshape(k, 2),
        radii_mm=np.array(radii, dtype=np.float64),
        axes=np.array(axes, dtype=np.float64).reshape(k, 2),
        pitch_mm=(1.0, 1.0),
        grid=(max(k, 1), 1),
        outline_mm=outline,
        thickness_mm=THICKNESS_MM,
    )


def expected_volume(layout: HoleLayout, cut: float = 0.0) -> float:
    """Each z-slice of a hole is a disc of radius r, tilted or not: pi r^2 t per hole; the
    chamfer removes a right triangle of legs `cut` from every slice."""
    width, height = layout.outline_mm
    t = layout.thickness_mm
    return (width * height - cut**2 / 2) * t - float(np.sum(math.pi * layout.radii_mm**2 * t))


def expected_area(layout: HoleLayout, cut: float = 0.0) -> float:
    """Faces + sides + hole walls; an oblique wall's area is t r integral sqrt(1 + (a.n)^2) du.
    The chamfer takes cut^2 / 2 off each face and a leg off two sides, and adds its hypotenuse."""
    width, height = layout.outline_mm
    t = layout.thickness_mm
    u = np.linspace(0.0, 2 * math.pi, 4096, endpoint=False)  # periodic: converges fast
    normals = np.stack([np.cos(u), np.sin(u)], axis=1)
    walls = [t * r * 2 * math.pi * np.mean(np.sqrt(1 + (normals @ a) ** 2))
             for r, a in zip(layout.radii_mm, layout.axes, strict=True)]
    caps = 2 * (width * height - cut**2 / 2 - float(np.sum(math.pi * layout.radii_mm**2)))
    sides = (2 * (width + height) - 2 * cut + math.sqrt(2) * cut) * t
    return caps + sides + float(np.sum(walls))


def strips(n: int) -> int:
    """Tiles along an axis with n separated hole columns: a cut after every few columns."""
    return 1 + (n - 1) // HOLES_PER_TILE_SIDE if n else 1


def check_solid(layout: HoleLayout, planar_faces: int, cut: float = 0.0) -> None:
    """The solid as built and as read back from STEP (readers heal some faults on the way in)."""
    check_summary(shape_summary(build_solid(layout, corner_cut_mm=cut)), layout, planar_faces, cut)
    check_summary(read_step_summary(step_bytes(layout, corner_cut_mm=cut)), layout, planar_faces,
                  cut)


def side_count(cut: float) -> int:
    """Four outer walls, and the chamfer's."""
    return 4 + (cut > 0)


def check_summary(summary: StepSummary, layout: HoleLayout, planar_faces: int,
                  cut: float = 0.0) -> None:
    # A vanishing tilt (hypothesis finds 1e-210) is built as a true cylinder.
    straight = np.all(np.abs(layout.axes) <= STRAIGHT_AXIS_LIMIT, axis=1)
    assert summary.solids == 1
    assert summary.valid
    assert summary.closed
    assert summary.faces == planar_faces + side_count(cut) + layout.count
    assert summary.cylindrical_faces == int(np.sum(straight))
    assert summary.extrusion_faces == int(np.sum(~straight))
    assert summary.volume_mm3 == pytest.approx(expected_volume(layout, cut), rel=REL)
    width, height = layout.outline_mm
    removed = (width * height - cut**2 / 2) * layout.thickness_mm - summary.volume_mm3
    assert removed == pytest.approx(
        float(np.sum(math.pi * layout.radii_mm**2 * layout.thickness_mm)), rel=REL, abs=1e-9
    )
    assert summary.area_mm2 == pytest.approx(expected_area(layout, cut), rel=REL)
    want = np.array([[-width / 2, -height / 2, 0.0], [width / 2, height / 2, layout.thickness_mm]])
    np.testing.assert_allclose(summary.bounds_mm, want, atol=BOUNDS_SLACK_MM)
    # Straight holes are true cylinders at the right place and radius.
    for (x, y), r in zip(layout.centres_mm[straight], layout.radii_mm[straight], strict=True):
        found = summary.cylinders_mm
        nearest = np.argmin(np.hypot(found[:, 0] - x, found[:, 1] - y))
        np.testing.assert_allclose(found[nearest], [x, y, r], atol=1e-9)


CASES = {
    "empty": (holes_layout([], [], []), 2),
    "one straight hole": (holes_layout([(0.5, -0.25)], [0.3], [(0.0, 0.0)]), 2),
    # A steep tilt: a circular cylinder along the axis would remove 1/cos = 1.16 x as much.
    "one tilted hole": (holes_layout([(0.0, 0.0)], [0.3], [(0.5, -0.3)]), 2),
    "a few holes": (
        holes_layout([(-2.0, 1.0), (0.3, 0.2), (2.1, -1.2)], [0.2, 0.45, 0.1],
                     [(0.0, 0.0), (0.1, 0.2), (0.0, 0.0)]),
        2,
    ),
    "7x5 straight": (grid_layout(7, 5), 2 * strips(7) * strips(5)),
    "7x5 tilted": (grid_layout(7, 5, tilt_per_mm=0.05), 2 * strips(7) * strips(5)),
}


@pytest.mark.parametrize("name", list(CASES))
def test_step_is_one_closed_valid_solid_matching_geometry(name: str) -> None:
    layout, planar_faces = CASES[name]
    check_solid(layout, planar_faces)


def test_tiles_follow_hole_columns() -> None:
    assert tile_count(grid_layout(13, 13)) == (strips(13) ** 2, strips(13) ** 2) == (9, 9)
    assert tile_count(grid_layout(28, 3, tilt_per_mm=0.02)) == (strips(28), strips(28))


@pytest.mark.slow
def test_many_tiles_share_edges() -> None:
    check_solid(grid_layout(13, 13, tilt_per_mm=0.03), 2 * strips(13) ** 2)


@given(
    keep=st.lists(st.booleans(), min_size=12, max_size=12),
    tilt=st.floats(-0.1, 0.1),
    seed=st.integers(0, 1000),
    cut=st.one_of(st.just(0.0), st.floats(1e-4, 0.9)),
)
@settings(max_examples=12, deadline=None)
def test_random_small_plates(keep: list[bool], tilt: float, seed: int, cut: float) -> None:
    # At most 4 columns and 3 rows: fewer than HOLES_PER_TILE_SIDE, so one tile per face.
    # A cut below 0.9 mm stays clear of the corner hole (x' + y' = 3 mm from the corner, r 0.4).
    check_solid(grid_layout(4, 3, tilt_per_mm=tilt, keep=np.array(keep), seed=seed), 2, cut)


@pytest.mark.parametrize("cut", [1e-4, 0.3, 0.95])
def test_corner_cut_removes_its_triangle(cut: float) -> None:
    layout = grid_layout(7, 5, tilt_per_mm=0.05)
    plain = shape_summary(build_solid(layout))
    cut_summary = shape_summary(build_solid(layout, corner_cut_mm=cut))
    assert (cut_summary.solids, cut_summary.valid, cut_summary.closed) == (1, True, True)
    assert cut_summary.faces == plain.faces + 1
    assert plain.volume_mm3 - cut_summary.volume_mm3 == pytest.approx(
        cut**2 / 2 * layout.thickness_mm, rel=REL
    )
    check_solid(layout, 2 * strips(7) * strips(5), cut)


def test_corner_cut_past_a_tile_line_merges_tiles() -> None:
    # 13 rows: a tile line between the top two rows, 2 mm below the top edge. A 2.5 mm cut
    # (the top-left hole left out) reaches past it, so that line goes: 3 tile rows become 2.
    keep = np.ones(7 * 13, dtype=bool)
    keep[0] = False
    layout = grid_layout(7, 13, keep=keep)
    assert tile_count(layout) == (strips(7) * strips(13),) * 2 == (6, 6)
    assert tile_count(layout, corner_cut_mm=2.5) == (4, 4)
    check_solid(layout, 2 * 4, cut=2.5)


@pytest.mark.parametrize(
    ("cut", "message"),
    [
        (-0.1, "must be 0"),
        (5e-5, "must be 0"),  # shorter than OCCT can tell from a point
        (float("nan"), "must be 0"),
        (float("inf"), "must be 0"),
        (4.0, "must be 0"),  # the outline is 5 x 4 mm
        (2.95, "cuts into hole 0"),  # the top-left hole is 3 mm from the corner along x + y
    ],
)
def test_rejects_bad_corner_cuts(cut: float, message: str) -> None:
    layout = grid_layout(3, 2)
    with pytest.raises(ValueError, match=f"corner_cut_mm.*{message}"):
        build_solid(layout, corner_cut_mm=cut)
    with pytest.raises(ValueError, match="corner_cut_mm"):
        step_bytes(layout, corner_cut_mm=cut)


def test_corner_cut_checks_the_tilted_top_face() -> None:
    # The centre is x' + y' = 3.0 mm from the corner at mid-thickness, 2.7 at the top face and
    # 3.3 at the bottom; the hole keeps sqrt(2) r = 0.28 mm more: a 2.6 mm chamfer only meets
    # the top face's circle, a 2.3 mm one clears both.
    layout = holes_layout([(-1.5, 0.5)], [0.2], [(-1.0, 1.0)])
    with pytest.raises(ValueError, match="top face"):
        build_solid(layout, corner_cut_mm=2.6)
    check_solid(layout, 2, cut=2.3)


def occupied_strips(layout: HoleLayout) -> int:
    """Tiles per face of a grid plate: each occupied column (row) of cells is its own cluster."""
    columns = len(np.unique(layout.cells[:, 1]))
    rows = len(np.unique(layout.cells[:, 0]))
    return strips(columns) * strips(rows)


@pytest.fixture(scope="module")
def chief_ray_plate() -> HoleLayout:
    """A quantized 20 x 20 chief-ray plate: holes converge on the eye, each face's cell grid
    is the mid-plane grid scaled about it."""
    plate = Plate(cells=(20, 20), pitch_mm=(0.25, 0.25), gap_mm=2.0, thickness_mm=0.3,
                  hole_axis="chief_ray")
    fractions = np.random.default_rng(7).uniform(0.0, 0.5, size=(20, 20))
    return quantize(fractions, plate, PROCESSES["resin"], tilt_target_mm=(0.0, 0.0),
                    eye_distance_mm=10.15)


@pytest.mark.parametrize("share", [0.0, 0.6])
def test_quantized_chief_ray_plate(chief_ray_plate: HoleLayout, share: float) -> None:
    layout = chief_ray_plate
    assert layout.converge_mm is not None and layout.count > 300
    width, height = layout.outline_mm
    margin = (width - layout.grid[0] * layout.pitch_mm[0]) / 2
    cut = share * margin  # as fabricate.make_part cuts it
    summary = shape_summary(build_solid(layout, corner_cut_mm=cut))
    assert (summary.solids, summary.valid, summary.closed) == (1, True, True)
    assert summary.faces == 2 * occupied_strips(layout) + side_count(cut) + layout.count
    assert summary.extrusion_faces + summary.cylindrical_faces == layout.count
    volume = (width * height - cut**2 / 2 - float(np.sum(math.pi * layout.radii_mm**2)))
    assert summary.volume_mm3 == pytest.approx(volume * layout.thickness_mm, rel=REL)


def test_units_are_millimetres() -> None:
    data = step_bytes(grid_layout(2, 1))
    assert b"SI_UNIT(.MILLI.,.METRE.)" in data.replace(b" ", b"")


def test_progress_reports_hole_count() -> None:
    calls: list[int] = []
    step_bytes(grid_layout(3, 2), progress=calls.append)
    assert calls[-1] == 6


@pytest.mark.parametrize(
    ("layout", "message"),
    [
        (holes_layout([(2.9, 0.0)], [0.2], [(0.0, 0.0)]), "outline"),
        # Inside at mid-thickness, but the tilt carries the top circle past the edge.
        (holes_layout([(2.6, 0.0)], [0.2], [(2.0, 0.0)]), "top face"),
        (holes_layout([(0.0, 0.0), (0.5, 0.0)], [0.3, 0.3], [(0.0, 0.0), (0.0, 0.0)]), "web"),
        # Apart on both faces, but the tilted holes cross at mid-thickness.
        (holes_layout([(0.0, 0.0), (0.0, 0.0)], [0.1, 0.1], [(2.0, 0.0), (-2.0, 0.0)]), "web"),
    ],
)
def test_rejects_impossible_layouts(layout: HoleLayout, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        step_bytes(layout)


def load_cad(name: str) -> ModuleType:
    pytest.importorskip("cadquery", reason="cad/ scripts need cadquery (pip install cadquery)")
    spec = importlib.util.spec_from_file_location(name, CAD_DIR / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    # Registered for the run, as a normal import would be (dataclasses look their module up).
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def holes_csv(layout: HoleLayout) -> str:
    lines = ["row,col,x_mm,y_mm,radius_mm,axis_x,axis_y"]
    for (row, col), (x, y), r, (ax, ay) in zip(
        layout.cells, layout.centres_mm, layout.radii_mm, layout.axes, strict=True
    ):
        values = (float(value) for value in (x, y, r, ax, ay))
        lines.append(f"{row},{col}," + ",".join(repr(value) for value in values))
    return "\n".join(lines) + "\n"


@pytest.mark.slow
def test_cad_plate_from_csv_matches_layout(tmp_path: Path) -> None:
    module = load_cad("plate_from_csv")
    layout = grid_layout(3, 2, tilt_per_mm=0.2)
    csv_path, out = tmp_path / "holes.csv", tmp_path / "plate.step"
    csv_path.write_text(holes_csv(layout))
    width, height = layout.outline_mm
    module.main([str(csv_path), "--width", str(width), "--height", str(height),
                 "--thickness", str(layout.thickness_mm), "--out", str(out)])
    summary = read_step_summary(out.read_bytes())
    assert (summary.solids, summary.valid, summary.closed) == (1, True, True)
    assert summary.volume_mm3 == pytest.approx(expected_volume(layout), rel=REL)
    assert summary.area_mm2 == pytest.approx(expected_area(layout), rel=REL)


@pytest.mark.slow
def test_cad_mount_frame_volume_and_placement(tmp_path: Path) -> None:
    module = load_cad("mount_frame")
    spec = module.FrameSpec(display_width_mm=60.0, display_height_mm=40.0, bezel_height_mm=0.5,
                            gap_mm=8.0, plate_width_mm=30.0, plate_height_mm=20.0,
                            plate_thickness_mm=0.4, wall_mm=2.0, skirt_mm=2.0, ledge_mm=1.0,
                            clearance_mm=0.2)
    out = tmp_path / "frame.step"
    module.export(module.make_frame(spec), out)
    summary = read_step_summary(out.read_bytes())
    assert (summary.solids, summary.valid, summary.closed) == (1, True, True)
    # Independent volume: outer block less display recess, window above it, plate pocket ring.
    outer_w, outer_h = 60.0 + 2 * 2.2, 40.0 + 2 * 2.2
    bottom, top = 0.5 - 2.0, 8.0 + 0.4
    window = 28.0 * 18.0
    volume = (outer_w * outer_h * (top - bottom) - 60.4 * 40.4 * 2.0
              - window * (top - bottom - 2.0) - (30.4 * 20.4 - window) * 0.4)
    assert summary.volume_mm3 == pytest.approx(volume, rel=REL)
    np.testing.assert_allclose(
        summary.bounds_mm, [[-outer_w / 2, -outer_h / 2, bottom], [outer_w / 2, outer_h / 2, top]],
        atol=BOUNDS_SLACK_MM,
    )
    with pytest.raises(ValueError, match="gap_mm"):
        module.FrameSpec(gap_mm=0.9, bezel_height_mm=0.5)
    stl = tmp_path / "frame.stl"
    module.main(["--out", str(stl)])
    assert stl.stat().st_size > 0


def test_part_files_step_carries_the_parts_chamfer() -> None:
    # The STEP part must match the mesh (and DXF/SVG) outline: the same chamfer, same volume.
    from aperture_fab.config.config import resolve
    from aperture_fab.config.stages import FabricationSettings
    from aperture_fab.fabrication.mesh_checks import mesh_volume_mm3
    from aperture_fab.fabrication.part import make_part
    from aperture_fab.io.formats import part_files

    config = resolve("near-eye-nominal", overrides={
        "display.width_mm": 4.0, "display.height_mm": 4.0, "display.pixels": [32, 32],
        "plate.cells": [16, 16], "plate.pitch_mm": [0.25, 0.25], "eye.view_pixels": [12, 12],
        "plate.thickness_mm": 0.3, "plate.hole_axis": "chief_ray",
    })
    settings = FabricationSettings()  # resin
    fractions = np.random.default_rng(3).uniform(0.0, 0.5, size=(16, 16))
    part = make_part(fractions, config.scene, settings)
    assert part.corner_cut_mm > 0
    summary = read_step_summary(part_files(part, ("step",), settings)["plate.step"])
    assert (summary.solids, summary.valid, summary.closed) == (1, True, True)
    assert summary.faces == 2 * occupied_strips(part.layout) + 5 + part.layout.count
    assert summary.volume_mm3 == pytest.approx(mesh_volume_mm3(part.mesh), rel=REL)
    assert summary.volume_mm3 == pytest.approx(
        expected_volume(part.layout, part.corner_cut_mm), rel=REL
    )
