"""Plate mesh: watertight, oriented, one body, genus = holes, exact volume, web rules."""

from __future__ import annotations

import math
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest
from conftest import require_tool
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from aperture_fab.fabrication.layout import HoleLayout
from aperture_fab.fabrication.mesh import PlateMesh, build_mesh, segment_count
from aperture_fab.fabrication.mesh_checks import check_mesh, manifold_check, mesh_volume_mm3
from aperture_fab.io.formats import read_stl, stl_bytes

#: Largest lateral shift of a tilted hole at either face, as a share of the pitch.
MAX_SHIFT_FRACTION = 0.1


def grid_layout(
    nx: int,
    ny: int,
    pitch_mm: tuple[float, float],
    thickness_mm: float,
    margin_mm: float,
    radii_mm: np.ndarray,
    axes: np.ndarray | None = None,
) -> HoleLayout:
    """Layout with holes where radii_mm (ny, nx) > 0, centred in their cells."""
    px, py = pitch_mm
    rows, cols = np.nonzero(radii_mm > 0)
    centres = np.stack([(cols - (nx - 1) / 2) * px, ((ny - 1) / 2 - rows) * py], axis=1)
    return HoleLayout(
        cells=np.stack([rows, cols], axis=1).astype(np.int64),
        centres_mm=centres.astype(np.float64),
        radii_mm=radii_mm[rows, cols].astype(np.float64),
        axes=np.zeros((len(rows), 2)) if axes is None else axes[rows, cols],
        pitch_mm=pitch_mm,
        grid=(nx, ny),
        outline_mm=(nx * px + 2 * margin_mm, ny * py + 2 * margin_mm),
        thickness_mm=thickness_mm,
    )


@st.composite
def layouts(draw: st.DrawFn) -> tuple[HoleLayout, float, float, float]:
    """(layout, min_web_mm, chord_tolerance_mm, corner_cut_mm) over the cases that matter."""
    nx, ny = draw(st.integers(1, 6)), draw(st.integers(1, 6))
    px, py = draw(st.floats(0.05, 2.0)), draw(st.floats(0.05, 2.0))
    pitch = min(px, py)
    web = draw(st.sampled_from([0.0, 0.05, 0.3])) * pitch
    thickness = draw(st.floats(0.01, 3.0))
    margin = draw(st.sampled_from([0.0, 0.02, 1.0])) * draw(st.floats(0.5, 3.0))
    occupancy = draw(st.sampled_from(["empty", "full", "one", "random"]))
    sizes = draw(st.sampled_from(["limit", "tiny", "random"]))
    tilted = draw(st.booleans())
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    if tilted:
        # Shift at a face = axis * t / 2, at most MAX_SHIFT_FRACTION of the pitch.
        share = rng.uniform(-1, 1, (ny, nx, 2)) * MAX_SHIFT_FRACTION
        axes = share * np.array([px, py]) * 2 / thickness
    else:
        axes = np.zeros((ny, nx, 2))
    shift = np.abs(axes) * thickness / 2
    # Largest circle that keeps half a web to the cell sides at both faces.
    limit = np.minimum(px / 2 - web / 2 - shift[..., 0], py / 2 - web / 2 - shift[..., 1])
    if sizes == "limit":
        radii = limit
    elif sizes == "tiny":
        radii = np.full((ny, nx), 1e-3 * pitch)
    else:
        radii = rng.uniform(0.01, 1.0, (ny, nx)) * limit
    if occupancy == "empty":
        radii = np.zeros((ny, nx))
    elif occupancy == "one":
        keep = np.zeros((ny, nx), dtype=bool)
        keep[rng.integers(ny), rng.integers(nx)] = True
        radii = np.where(keep, radii, 0.0)
    elif occupancy == "random":
        radii = np.where(rng.random((ny, nx)) < 0.5, radii, 0.0)
    layout = grid_layout(nx, ny, (px, py), thickness, margin, radii, axes)
    tolerance = draw(st.floats(1e-4, 1e-1)) * pitch
    cut = draw(st.sampled_from([0.0, 0.5])) * margin
    return layout, web, tolerance, cut


def convergent_layout(
    nx: int,
    ny: int,
    pitch_mm: tuple[float, float],
    thickness_mm: float,
    margin_mm: float,
    radii_mm: np.ndarray,
    converge_mm: tuple[float, float, float],
) -> HoleLayout:
    """Chief-ray layout: holes centred in their cells at mid-thickness, axes through the eye."""
    plain = grid_layout(nx, ny, pitch_mm, thickness_mm, margin_mm, radii_mm)
    ex, ey, distance = converge_mm
    axes = (np.array([ex, ey]) - plain.centres_mm) / distance
    return _with(plain, axes=axes, converge_mm=converge_mm)


def overhang_mm(nx: int, ny: int, pitch_mm: tuple[float, float], thickness_mm: float,
                converge_mm: tuple[float, float, float]) -> float:
    """How far the bottom face's grid (scaled by 1 + t / 2D about E) reaches past the
    mid-plane grid, on its farthest side."""
    ex, ey, distance = converge_mm
    half_w, half_h = nx * pitch_mm[0] / 2, ny * pitch_mm[1] / 2
    return thickness_mm / (2 * distance) * max(half_w + abs(ex), half_h + abs(ey))


@st.composite
def convergent_layouts(draw: st.DrawFn) -> tuple[HoleLayout, float, float, float]:
    """(layout, min_web_mm, chord_tolerance_mm, corner_cut_mm): chief-ray holes converging on
    an eye E within the plate's width, 2 to 50 mm from mid-thickness, near-eye-like pitches."""
    nx, ny = draw(st.integers(1, 12)), draw(st.integers(1, 12))
    px = draw(st.floats(0.05, 1.0))
    py = px * draw(st.floats(1.0, 1.5))
    pitch = min(px, py)
    web = draw(st.sampled_from([0.0, 0.05, 0.3])) * pitch
    thickness = draw(st.floats(0.01, 1.0))
    distance = draw(st.floats(2.0, 50.0))
    ex = draw(st.floats(-0.5, 0.5)) * nx * px
    ey = draw(st.floats(-0.5, 0.5)) * ny * py
    converge = (ex, ey, distance)
    frame = draw(st.sampled_from([1e-3, 0.02, 1.0])) * draw(st.floats(0.5, 3.0))
    margin = overhang_mm(nx, ny, (px, py), thickness, converge) + frame
    occupancy = draw(st.sampled_from(["empty", "full", "one", "random"]))
    sizes = draw(st.sampled_from(["limit", "tiny", "random"]))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    # Largest circle that keeps half a web inside the top face's (smaller) cell.
    limit = pitch * (1 - thickness / (2 * distance)) / 2 - web / 2
    if sizes == "limit":
        radii = np.full((ny, nx), limit)
    elif sizes == "tiny":
        radii = np.full((ny, nx), 1e-3 * pitch)
    else:
        radii = rng.uniform(0.01, 1.0, (ny, nx)) * limit
    if occupancy == "empty":
        radii = np.zeros((ny, nx))
    elif occupancy == "one":
        keep = np.zeros((ny, nx), dtype=bool)
        keep[rng.integers(ny), rng.integers(nx)] = True
        radii = np.where(keep, radii, 0.0)
    elif occupancy == "random":
        radii = np.where(rng.random((ny, nx)) < 0.5, radii, 0.0)
    layout = convergent_layout(nx, ny, (px, py), thickness, margin, radii, converge)
    tolerance = draw(st.floats(1e-4, 1e-1)) * pitch
    cut = draw(st.sampled_from([0.0, 0.5])) * frame
    return layout, web, tolerance, cut


def expected_volume(layout: HoleLayout, corner_cut_mm: float) -> float:
    width, height = layout.outline_mm
    area = width * height - corner_cut_mm**2 / 2 - np.sum(np.pi * layout.radii_mm**2)
    return float(area * layout.thickness_mm)


def face_signed_areas(mesh: PlateMesh, z_mm: float) -> np.ndarray:
    """Signed xy areas (counter-clockwise from +z positive) of faces lying in the plane z."""
    v = mesh.vertices
    flat = np.all(v[mesh.faces][:, :, 2] == z_mm, axis=1)
    a, b, c = (v[mesh.faces[flat, k], :2] for k in range(3))
    ab, ac = b - a, c - a
    return 0.5 * (ab[:, 0] * ac[:, 1] - ab[:, 1] * ac[:, 0])


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(layouts())
def test_mesh_is_a_closed_solid_with_one_tunnel_per_hole(
    case: tuple[HoleLayout, float, float, float],
) -> None:
    layout, web, tolerance, cut = case
    mesh = build_mesh(layout, tolerance, min_web_mm=web, corner_cut_mm=cut)
    # Faces do not fold over: every top (bottom) triangle faces up (down), and their areas add
    # up to the face's true area, so none overlap.
    assert_closed_solid(layout, mesh, cut)

    # Every hole vertex keeps half a web from its cell's sides.
    px, py = layout.pitch_mm
    v = mesh.vertices
    nx, ny = layout.grid
    inside = (np.abs(v[:, 0]) < nx * px / 2) & (np.abs(v[:, 1]) < ny * py / 2)
    dx = np.abs((v[inside, 0] / px + nx / 2) % 1 - 0.5) * px
    dy = np.abs((v[inside, 1] / py + ny / 2) % 1 - 0.5) * py
    grid_corner = (dx > px / 2 - 1e-9) & (dy > py / 2 - 1e-9)
    hole_vertex_count = len(v) - 2 * (nx + 1) * (ny + 1) - (0 if layout.outline_mm == (
        nx * px, ny * py) else 2 * (4 + (cut > 0)))
    assert np.sum(~grid_corner) == hole_vertex_count
    slack = 1e-12
    assert np.all(dx[~grid_corner] <= px / 2 - web / 2 + slack)
    assert np.all(dy[~grid_corner] <= py / 2 - web / 2 + slack)


def assert_closed_solid(layout: HoleLayout, mesh: PlateMesh, cut: float) -> None:
    """Watertight, oriented, one body, genus = holes, exact volume, faces not folded."""
    report = check_mesh(mesh)
    assert report.watertight and report.consistently_oriented
    assert report.degenerate_faces == 0
    assert report.bodies == 1
    assert report.genus == layout.count
    assert report.euler_characteristic == 2 - 2 * layout.count
    want = expected_volume(layout, cut)
    assert report.volume_mm3 == pytest.approx(want, rel=1e-6)
    assert report.positive_volume and report.ok
    face_area = want / layout.thickness_mm
    top = face_signed_areas(mesh, layout.thickness_mm)
    bottom = face_signed_areas(mesh, 0.0)
    assert np.all(top > 0) and np.all(bottom < 0)
    assert top.sum() == pytest.approx(face_area, rel=1e-9)
    assert -bottom.sum() == pytest.approx(face_area, rel=1e-9)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(convergent_layouts())
def test_convergent_mesh_is_a_closed_solid_with_holes_in_their_scaled_cells(
    case: tuple[HoleLayout, float, float, float],
) -> None:
    layout, web, tolerance, cut = case
    mesh = build_mesh(layout, tolerance, min_web_mm=web, corner_cut_mm=cut)
    assert_closed_solid(layout, mesh, cut)

    # Each face's hole vertices keep half a web inside their cell of that face's grid: the
    # mid-plane grid scaled about E by 1 + t / 2D (bottom, z = 0) or 1 - t / 2D (top).
    assert layout.converge_mm is not None
    ex, ey, distance = layout.converge_mm
    t = layout.thickness_mm
    px, py = layout.pitch_mm
    nx, ny = layout.grid
    v = mesh.vertices
    hole_vertices = 0
    for z, scale in ((0.0, 1 + t / (2 * distance)), (t, 1 - t / (2 * distance))):
        on_face = v[v[:, 2] == z]
        # Back to mid-plane grid coordinates, where cells are px x py, then distances scaled.
        x = ex + (on_face[:, 0] - ex) / scale
        y = ey + (on_face[:, 1] - ey) / scale
        inside = (np.abs(x) < nx * px / 2) & (np.abs(y) < ny * py / 2)
        dx = np.abs((x[inside] / px + nx / 2) % 1 - 0.5) * px * scale
        dy = np.abs((y[inside] / py + ny / 2) % 1 - 0.5) * py * scale
        grid_corner = (dx > scale * px / 2 - 1e-9) & (dy > scale * py / 2 - 1e-9)
        hole_vertices += int(np.sum(~grid_corner))
        slack = 1e-12
        assert np.all(dx[~grid_corner] <= scale * px / 2 - web / 2 + slack)
        assert np.all(dy[~grid_corner] <= scale * py / 2 - web / 2 + slack)
        # The face's outer grid corners lie on the scaled grid.
        for cx, cy in [(-nx * px / 2, ny * py / 2), (nx * px / 2, -ny * py / 2)]:
            corner = (ex + (cx - ex) * scale, ey + (cy - ey) * scale)
            assert np.any(np.all(np.isclose(on_face[:, :2], corner, rtol=0, atol=1e-12), axis=1))
    frame_vertices = 2 * (4 + (cut > 0))
    assert hole_vertices == len(v) - 2 * (nx + 1) * (ny + 1) - frame_vertices


@settings(max_examples=25, deadline=None)
@given(convergent_layouts())
def test_manifold3d_agrees_on_convergent_layouts(
    case: tuple[HoleLayout, float, float, float],
) -> None:
    layout, web, tolerance, cut = case
    mesh = build_mesh(layout, tolerance, min_web_mm=web, corner_cut_mm=cut)
    report = manifold_check(mesh)
    assert report.ok, report.status
    assert report.genus == layout.count
    assert report.triangle_count == len(mesh.faces)
    assert report.volume_mm3 == pytest.approx(expected_volume(layout, cut), rel=1e-4)


def test_near_eye_convergent_plate_builds() -> None:
    """80 x 80 cells of 0.25 mm, 0.3 mm thick, eye 10.15 mm away: corner holes move 0.3 mm
    (more than a cell) between the faces, yet each stays in its scaled cell with the web. The
    same holes judged against the unscaled cells are refused."""
    n, pitch, t, distance, web = 80, 0.25, 0.3, 10.15, 0.044
    limit = pitch * (1 - t / (2 * distance)) / 2 - web / 2
    radii = np.random.default_rng(0).uniform(0.044, limit, (n, n))
    layout = convergent_layout(n, n, (pitch, pitch), t, 1.0, radii, (0.0, 0.0, distance))
    assert np.abs(layout.axes).max() * t > pitch
    mesh = build_mesh(layout, 0.002, min_web_mm=web, corner_cut_mm=0.6)
    assert_closed_solid(layout, mesh, 0.6)
    # Triangles per cell as for straight holes: hole cell 4n + 8, frame, outer walls.
    sides = segment_count(layout.radii_mm, 0.002, 8, 256)
    assert len(mesh.faces) == int(np.sum(4 * sides + 8)) + 2 * (4 * n + 5) + 10
    with pytest.raises(ValueError, match="of its cell's side"):
        build_mesh(_with(layout, converge_mm=None), 0.002, min_web_mm=web)


def test_cell_edges_are_scaled_about_the_eye() -> None:
    """2 x 1 cells of 1 mm, E = (1, 0), D = 10: at z = +0.5 the grid is scaled by 0.95."""
    layout = convergent_layout(2, 1, (1.0, 1.0), 1.0, 1.0, np.full((1, 2), 0.2),
                               (1.0, 0.0, 10.0))
    xs, ys = layout.cell_edges_mm(0.5)
    np.testing.assert_allclose(xs, [-0.9, 0.05, 1.0], atol=1e-15)
    np.testing.assert_allclose(ys, [0.475, -0.475], atol=1e-15)
    xs, ys = layout.cell_edges_mm(-0.5)
    np.testing.assert_allclose(xs, [-1.1, -0.05, 1.0], atol=1e-15)
    np.testing.assert_allclose(ys, [0.525, -0.525], atol=1e-15)
    straight = grid_layout(2, 1, (1.0, 1.0), 1.0, 1.0, np.full((1, 2), 0.2))
    for z in (-0.5, 0.5):
        xs, ys = straight.cell_edges_mm(z)
        np.testing.assert_array_equal(xs, [-1.0, 0.0, 1.0])
        np.testing.assert_array_equal(ys, [0.5, -0.5])


def test_bad_convergent_layouts_are_refused() -> None:
    n, pitch, t, distance = 4, 0.25, 0.3, 10.0
    converge = (0.2, -0.1, distance)
    overhang = overhang_mm(n, n, (pitch, pitch), t, converge)
    layout = convergent_layout(n, n, (pitch, pitch), t, 1.0, np.full((n, n), 0.05), converge)
    with pytest.raises(ValueError, match="axes differ"):
        _with(layout, axes=layout.axes + 1e-6)
    with pytest.raises(ValueError, match="must be > the thickness"):
        _with(layout, axes=layout.axes * distance / t, converge_mm=(0.2, -0.1, t))
    with pytest.raises(ValueError, match="three finite numbers"):
        _with(layout, converge_mm=(0.2, math.nan, distance))
    # The outline must contain the bottom face's larger grid with a margin.
    for margin in (0.0, overhang * (1 - 1e-6)):
        side = n * pitch + 2 * margin
        with pytest.raises(ValueError, match="bottom face's scaled cell grid"):
            build_mesh(_with(layout, outline_mm=(side, side)), 1e-3)
    side = n * pitch + 2 * overhang * (1 + 1e-6)
    assert check_mesh(build_mesh(_with(layout, outline_mm=(side, side)), 1e-3)).ok
    # The chamfer must pass outside both faces' top-left grid corners; the bottom face's
    # reaches farther out: left by s (half + ex), up by s (half - ey), s = t / 2D.
    s, half = t / (2 * distance), n * pitch / 2
    limit = (1.0 - s * (half + converge[0])) + (1.0 - s * (half - converge[1]))
    assert check_mesh(build_mesh(layout, 1e-3, corner_cut_mm=limit - 1e-6)).ok
    with pytest.raises(ValueError, match="corner_cut_mm"):
        build_mesh(layout, 1e-3, corner_cut_mm=limit + 1e-6)


@settings(max_examples=25, deadline=None)
@given(layouts())
def test_manifold3d_agrees(case: tuple[HoleLayout, float, float, float]) -> None:
    layout, web, tolerance, cut = case
    mesh = build_mesh(layout, tolerance, min_web_mm=web, corner_cut_mm=cut)
    report = manifold_check(mesh)
    assert report.ok, report.status
    assert report.genus == layout.count
    assert report.triangle_count == len(mesh.faces)
    assert report.volume_mm3 == pytest.approx(expected_volume(layout, cut), rel=1e-4)


@settings(max_examples=25, deadline=None)
@given(layouts())
def test_stl_round_trip_is_float32_exact(case: tuple[HoleLayout, float, float, float]) -> None:
    layout, web, tolerance, cut = case
    mesh = build_mesh(layout, tolerance, min_web_mm=web, corner_cut_mm=cut)
    again = read_stl(stl_bytes(mesh))
    assert len(again.faces) == len(mesh.faces)
    single = mesh.vertices.astype(np.float32)
    np.testing.assert_array_equal(again.vertices[again.faces], single[mesh.faces])
    assert len(again.vertices) == len(np.unique(single, axis=0))
    report = check_mesh(again)
    assert report.consistently_oriented and report.genus == layout.count
    assert report.volume_mm3 == pytest.approx(mesh_volume_mm3(mesh), rel=1e-5)


def test_face_count_is_linear_in_cells_and_holes() -> None:
    """Closed cell 4, hole cell 4n + 8, frame 2 (2 (nx + ny) + 4), outer walls 8 triangles."""
    nx, ny = 7, 5
    radii = np.zeros((ny, nx))
    radii[1, 2], radii[3, 6], radii[4, 0] = 0.1, 0.2, 0.3
    layout = grid_layout(nx, ny, (1.0, 1.0), 0.5, 1.0, radii)
    tolerance = 1e-3
    mesh = build_mesh(layout, tolerance)
    n = segment_count(layout.radii_mm, tolerance, 8, 256)
    closed = nx * ny - layout.count
    want = 4 * closed + int(np.sum(4 * n + 8)) + 2 * (2 * (nx + ny) + 4) + 8
    assert len(mesh.faces) == want
    grid_vertices = 2 * (nx + 1) * (ny + 1)
    assert len(mesh.vertices) == grid_vertices + 8 + int(np.sum(2 * n))


@pytest.mark.parametrize("radius_mm", [1e-3, 0.01, 0.1, 1.0])
@pytest.mark.parametrize("tolerance_mm", [1e-4, 1e-3, 1e-2])
def test_segment_count_is_the_fewest_multiple_of_four_within_tolerance(
    radius_mm: float, tolerance_mm: float
) -> None:
    n = int(segment_count(np.array([radius_mm]), tolerance_mm, 8, 256)[0])
    assert n % 4 == 0 and 8 <= n <= 256

    def sagitta(k: int) -> float:
        return radius_mm * (1 - math.cos(math.pi / k))

    if n < 256:
        assert sagitta(n) <= tolerance_mm
    if n > 8:
        assert sagitta(n - 4) > tolerance_mm


@pytest.mark.parametrize(("low", "high"), [(6, 256), (8, 30), (0, 8), (16, 8)])
def test_segment_bounds_are_checked(low: int, high: int) -> None:
    with pytest.raises(ValueError, match="segments_m"):
        segment_count(np.array([0.1]), 1e-3, low, high)


def test_polygon_area_equals_circle_area() -> None:
    """One hole, few segments: the removed volume is still pi r^2 t."""
    radii = np.array([[0.4]])
    layout = grid_layout(1, 1, (1.0, 1.0), 2.0, 0.5, radii)
    mesh = build_mesh(layout, 0.1, segments_min=8, segments_max=8)
    assert mesh_volume_mm3(mesh) == pytest.approx((4.0 - math.pi * 0.16) * 2.0, rel=1e-12)


@pytest.mark.parametrize("tilt", [0.0, 0.05])
def test_web_violation_names_the_cell(tilt: float) -> None:
    """The polygon's extent along x and y is its apothem; just past the web limit it raises."""
    n, web, pitch, thickness = 16, 0.1, 1.0, 1.0
    apothem_per_radius = math.sqrt(math.pi / (n * math.tan(math.pi / n)))
    limit = (pitch / 2 - web / 2 - tilt * thickness / 2) / apothem_per_radius
    radii = np.zeros((3, 4))
    axes = np.zeros((3, 4, 2))
    axes[1, 2] = (tilt, 0.0)
    radii[1, 2] = limit * (1 - 1e-9)
    layout = grid_layout(4, 3, (pitch, pitch), thickness, 1.0, radii, axes)
    assert check_mesh(build_mesh(layout, 1.0, n, n, min_web_mm=web)).genus == 1
    radii[1, 2] = limit * (1 + 1e-6)
    layout = grid_layout(4, 3, (pitch, pitch), thickness, 1.0, radii, axes)
    with pytest.raises(ValueError, match=re.escape("cell (1, 2)")):
        build_mesh(layout, 1.0, n, n, min_web_mm=web)


def test_hole_touching_the_cell_side_is_refused_even_without_web() -> None:
    radii = np.array([[0.6]])  # apothem of a 256-gon of radius 0.6 exceeds the half pitch 0.5
    layout = grid_layout(1, 1, (1.0, 1.0), 1.0, 1.0, radii)
    with pytest.raises(ValueError, match=re.escape("cell (0, 0)")):
        build_mesh(layout, 1e-4)


def test_corner_cut_is_at_the_top_left() -> None:
    layout = grid_layout(2, 2, (1.0, 1.0), 1.0, 1.0, np.full((2, 2), 0.3))
    mesh = build_mesh(layout, 1e-3, corner_cut_mm=0.8)
    xy = mesh.vertices[:, :2]
    for corner in [(2.0, 2.0), (-2.0, -2.0), (2.0, -2.0)]:
        assert np.any(np.all(xy == corner, axis=1))
    assert not np.any(np.all(xy == (-2.0, 2.0), axis=1))
    assert np.any(np.all(np.isclose(xy, (-1.2, 2.0)), axis=1))
    assert np.any(np.all(np.isclose(xy, (-2.0, 1.2)), axis=1))


@pytest.mark.parametrize(
    ("margin", "cut", "match"),
    [(0.0, 0.1, "corner_cut_mm"), (0.5, 1.0, "corner_cut_mm"), (1.0, -0.1, "corner_cut_mm")],
)
def test_corner_cut_must_stay_in_the_margin(margin: float, cut: float, match: str) -> None:
    layout = grid_layout(2, 2, (1.0, 1.0), 1.0, margin, np.full((2, 2), 0.3))
    with pytest.raises(ValueError, match=match):
        build_mesh(layout, 1e-3, corner_cut_mm=cut)


def _with(layout: HoleLayout, **changes: object) -> HoleLayout:
    fields = {name: getattr(layout, name) for name in layout.__dataclass_fields__}
    fields.update(changes)
    return HoleLayout(**fields)


def test_bad_layouts_are_refused() -> None:
    layout = grid_layout(3, 2, (1.0, 1.0), 1.0, 1.0, np.full((2, 3), 0.3))
    cells = layout.cells.copy()
    cells[1] = cells[0]
    with pytest.raises(ValueError, match="more than once"):
        build_mesh(_with(layout, cells=cells), 1e-3)
    cells = layout.cells.copy()
    cells[0] = (2, 0)
    with pytest.raises(ValueError, match="outside the grid"):
        build_mesh(_with(layout, cells=cells), 1e-3)
    with pytest.raises(ValueError, match="smaller than the cell grid"):
        build_mesh(_with(layout, outline_mm=(2.5, 4.0)), 1e-3)
    with pytest.raises(ValueError, match="one axis only"):
        build_mesh(_with(layout, outline_mm=(3.0, 4.0)), 1e-3)
    with pytest.raises(ValueError, match="chord_tolerance_mm"):
        build_mesh(layout, 0.0)
    with pytest.raises(ValueError, match="min_web_mm"):
        build_mesh(layout, 1e-3, min_web_mm=-1.0)


def test_check_mesh_sees_defects() -> None:
    """The checker is not a rubber stamp: a hole in the surface, a flipped face, two bodies."""
    layout = grid_layout(2, 2, (1.0, 1.0), 1.0, 0.5, np.full((2, 2), 0.3))
    mesh = build_mesh(layout, 1e-2)
    open_mesh = PlateMesh(mesh.vertices, mesh.faces[1:])
    assert not check_mesh(open_mesh).watertight
    flipped = mesh.faces.copy()
    flipped[0] = flipped[0, ::-1]
    report = check_mesh(PlateMesh(mesh.vertices, flipped))
    assert report.watertight and not report.consistently_oriented
    shifted = mesh.vertices + np.array([10.0, 0.0, 0.0])
    two = PlateMesh(
        np.concatenate([mesh.vertices, shifted]),
        np.concatenate([mesh.faces, mesh.faces + len(mesh.vertices)]),
    )
    report = check_mesh(two)
    assert report.bodies == 2 and report.genus == 8 and not report.ok


@pytest.mark.slow
def test_large_plate_is_valid() -> None:
    """300 x 300 cells, all with holes: built in one pass and still one closed body."""
    n = 300
    rng = np.random.default_rng(0)
    radii = rng.uniform(0.02, 0.12, (n, n))
    layout = grid_layout(n, n, (0.3, 0.3), 1.0, 2.0, radii)
    mesh = build_mesh(layout, 0.002, min_web_mm=0.05)
    report = check_mesh(mesh)
    assert report.ok and report.genus == n * n
    assert report.volume_mm3 == pytest.approx(expected_volume(layout, 0.0), rel=1e-6)


def _run(command: list[str]) -> str:
    # admesh echoes the STL's 80-byte binary header, which need not be UTF-8.
    done = subprocess.run(command, capture_output=True, text=True, errors="replace",
                          timeout=300, check=False)
    return done.stdout + done.stderr


@pytest.fixture(scope="module")
def tilted_plate_stl(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, HoleLayout]:
    rng = np.random.default_rng(1)
    radii = np.where(rng.random((12, 10)) < 0.7, rng.uniform(0.05, 0.3, (12, 10)), 0.0)
    axes = rng.uniform(-0.05, 0.05, (12, 10, 2))
    layout = grid_layout(10, 12, (1.0, 1.0), 1.5, 1.0, radii, axes)
    path = tmp_path_factory.mktemp("stl") / "plate.stl"
    path.write_bytes(stl_bytes(build_mesh(layout, 1e-3, min_web_mm=0.1, corner_cut_mm=1.0)))
    return path, layout


@pytest.mark.slow
def test_admesh_accepts_the_stl(tilted_plate_stl: tuple[Path, HoleLayout]) -> None:
    admesh = require_tool("admesh", install="Debian: apt-get install -y admesh")
    path, layout = tilted_plate_stl
    text = _run([admesh, str(path)])

    def number(label: str) -> float:
        found = re.search(rf"{label}\s*:\s*([-\d.]+)", text)
        assert found, f"admesh output lacks {label!r}:\n{text}"
        return float(found.group(1))

    assert number("Number of parts") == 1
    assert number("Total disconnected facets") == 0
    assert number("Facets reversed") == 0
    assert number("Backwards edges") == 0
    assert number("Volume") == pytest.approx(expected_volume(layout, 1.0), rel=1e-4)


@pytest.mark.slow
def test_prusa_slicer_calls_the_stl_manifold(tilted_plate_stl: tuple[Path, HoleLayout]) -> None:
    slicer = require_tool("prusa-slicer", install="Debian: apt-get install -y prusa-slicer")
    path, layout = tilted_plate_stl
    text = _run([slicer, "--loglevel", "1", "--info", str(path)])
    if "manifold" not in text:
        pytest.skip(f"prusa-slicer did not run headless here:\n{text[-2000:]}")
    assert re.search(r"manifold = yes", text), text
    assert re.search(r"number_of_parts\s*=\s*1\b", text), text
    volume = re.search(r"volume\s*=\s*([-\d.]+)", text)
    assert volume and float(volume.group(1)) == pytest.approx(
        expected_volume(layout, 1.0), rel=1e-4
    )
