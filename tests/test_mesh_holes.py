"""Holes read back from a plate mesh (aperture_fab.fabrication.mesh_holes) against the layout it was
built from. Parts are built with make_part and, where said, written as STL and read back
(float32)."""

from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, reject, settings
from hypothesis import strategies as st

from aperture_fab.config.stages import FabricationSettings
from aperture_fab.fabrication.layout import HoleLayout
from aperture_fab.fabrication.mesh import PlateMesh, build_mesh, segment_count
from aperture_fab.fabrication.mesh_holes import hole_layout_from_mesh, mesh_hole_loops
from aperture_fab.fabrication.part import Part, make_part
from aperture_fab.fabrication.process import PROCESSES, UnmakeableError
from aperture_fab.io.formats import read_stl, stl_bytes
from aperture_fab.optics.scene import Display, Eye, Plate, Scene

PROCESS = PROCESSES["photomask"]
PITCH_MM = 0.3
#: What float32 STL coordinates (|x| < 16 mm, spacing 1e-6 mm) allow after averaging a loop.
STL_TOL_MM = 1e-6
#: The float64 mesh keeps everything but rounding.
EXACT_TOL_MM = 1e-9


def make_scene(axis: str, cells: int = 12, thickness: float = 0.2) -> Scene:
    plate = Plate((cells, cells), (PITCH_MM, PITCH_MM), 10.0, thickness, axis)  # type: ignore[arg-type]
    return Scene(Display(6.0, 6.0, (48, 48)), plate, Eye(3.0, 10.0, (30.0, 30.0), (8, 8)))


def make(axis: str, fraction: np.ndarray, thickness: float = 0.2) -> Part:
    scene = make_scene(axis, fraction.shape[0], thickness)
    return make_part(fraction, scene, FabricationSettings(PROCESS))


def recover(part: Part, mesh: PlateMesh) -> HoleLayout:
    layout = part.layout
    return hole_layout_from_mesh(mesh, layout.pitch_mm, layout.grid, layout.converge_mm)


def assert_same_layout(got: HoleLayout, want: HoleLayout, tol_mm: float) -> None:
    np.testing.assert_array_equal(got.cells, want.cells)
    np.testing.assert_allclose(got.radii_mm, want.radii_mm, rtol=0, atol=tol_mm)
    np.testing.assert_allclose(got.centres_mm, want.centres_mm, rtol=0, atol=tol_mm)
    # The axis as the lateral shift across the plate, what the faces' centroids measure.
    np.testing.assert_allclose(got.axes * want.thickness_mm, want.axes * want.thickness_mm,
                               rtol=0, atol=tol_mm)
    np.testing.assert_allclose(got.outline_mm, want.outline_mm, rtol=0, atol=tol_mm)
    assert got.thickness_mm == pytest.approx(want.thickness_mm, abs=tol_mm)
    assert got.converge_mm == want.converge_mm and got.grid == want.grid


def random_fraction(seed: int, cells: int = 12) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = rng.uniform(0.0, 0.6, (cells, cells))
    a[rng.random((cells, cells)) < 0.2] = 0.0
    return a


@pytest.mark.parametrize("axis", ["straight", "chief_ray"])
def test_layout_is_recovered_from_the_mesh_and_from_its_stl(axis):
    part = make(axis, random_fraction(0))
    assert part.layout.count > 50 and (axis == "straight") == (part.layout.converge_mm is None)
    assert_same_layout(recover(part, part.mesh), part.layout, EXACT_TOL_MM)
    assert_same_layout(recover(part, read_stl(stl_bytes(part.mesh))), part.layout, STL_TOL_MM)


@pytest.mark.parametrize("axis", ["straight", "chief_ray"])
def test_loops_measure_each_hole(axis):
    """Loop centroids are the hole centres at the faces (centre +- t/2 axis); area radii are the
    drawn radii (area-preserving polygons); the circumscribed radius is the polygon's."""
    part = make(axis, random_fraction(1))
    layout = part.layout
    loops = mesh_hole_loops(part.mesh)
    top = np.round(loops.top_centroid_mm, 9)  # equal within a row, up to rounding
    order = np.lexsort((top[:, 0], -top[:, 1]))
    half = 0.5 * layout.thickness_mm * layout.axes
    # Cells run row-major (top to bottom, left to right), as the top centroids sort here.
    np.testing.assert_allclose(loops.top_centroid_mm[order], layout.centres_mm + half, atol=1e-12)
    np.testing.assert_allclose(loops.bottom_centroid_mm[order], layout.centres_mm - half,
                               atol=1e-12)
    n = segment_count(layout.radii_mm, 0.25 * PROCESS.radius_sigma_mm, 8, 256)
    np.testing.assert_array_equal(loops.segments[order], n)
    for radius in (loops.top_area_radius_mm, loops.bottom_area_radius_mm):
        np.testing.assert_allclose(radius[order], layout.radii_mm, rtol=1e-12)
    circum = layout.radii_mm * np.sqrt(2 * np.pi / (n * np.sin(2 * np.pi / n)))
    np.testing.assert_allclose(loops.top_circum_radius_mm[order], circum, rtol=1e-12)
    assert loops.thickness_mm == layout.thickness_mm
    np.testing.assert_allclose(loops.outline_max_mm - loops.outline_min_mm, layout.outline_mm)


@settings(max_examples=15, deadline=None)
@given(
    fractions=st.lists(st.floats(0.0, 0.6), min_size=36, max_size=36),
    axis=st.sampled_from(["straight", "chief_ray"]),
    thickness=st.sampled_from([0.005, 0.05, 0.25]),  # the photomask's range
)
def test_any_design_is_recovered(fractions, axis, thickness):
    """Any design the process can make: one that is refused (almost no open area: less than a
    few of the smallest holes) has no part to recover."""
    try:
        part = make(axis, np.array(fractions).reshape(6, 6), thickness)
    except UnmakeableError:
        reject()
    assert_same_layout(recover(part, read_stl(stl_bytes(part.mesh))), part.layout, STL_TOL_MM)


def test_plate_without_holes_has_none():
    part = make("chief_ray", np.zeros((6, 6)))
    loops = mesh_hole_loops(part.mesh)
    assert loops.count == 0 and recover(part, part.mesh).count == 0


def test_a_removed_hole_is_detected():
    """A mesh built without one of the layout's holes recovers the layout less that hole."""
    part = make("chief_ray", random_fraction(2))
    layout = part.layout
    keep = np.arange(layout.count) != 7
    edited = replace(layout, cells=layout.cells[keep], centres_mm=layout.centres_mm[keep],
                     radii_mm=layout.radii_mm[keep], axes=layout.axes[keep])
    mesh = build_mesh(edited, 0.25 * PROCESS.radius_sigma_mm,
                      corner_cut_mm=part.corner_cut_mm)
    got = recover(part, mesh)
    assert got.count == layout.count - 1
    missing = {tuple(c) for c in layout.cells.tolist()} - {tuple(c) for c in got.cells.tolist()}
    assert missing == {tuple(layout.cells[7].tolist())}
    assert_same_layout(got, edited, EXACT_TOL_MM)


def faces_on(mesh: PlateMesh, z: float) -> np.ndarray:
    return np.flatnonzero(np.all(mesh.vertices[mesh.faces, 2] == z, axis=1))


def test_a_hole_without_its_wall_is_an_error():
    part = make("straight", random_fraction(3))
    mesh = part.mesh
    z = mesh.vertices[mesh.faces, 2]
    wall = np.flatnonzero((z.min(axis=1) == 0) & (z.max(axis=1) > 0))
    # The triangles of the first hole's wall: those that use its first bottom vertex's loop.
    loops_x = mesh.vertices[mesh.faces[wall], :2].mean(axis=1)
    centre = part.layout.centres_mm[0]
    hole_wall = wall[np.linalg.norm(loops_x - centre, axis=1) < 1.5 * part.layout.radii_mm[0]]
    cut = PlateMesh(mesh.vertices, np.delete(mesh.faces, hole_wall, axis=0))
    with pytest.raises(ValueError, match="has no wall reaching the"):
        mesh_hole_loops(cut)


def test_a_flipped_triangle_on_a_loop_is_an_error():
    part = make("straight", random_fraction(4))
    mesh = part.mesh
    top = faces_on(mesh, part.layout.thickness_mm)
    faces = mesh.faces.copy()
    # A top-face triangle with an edge on a hole loop: an edge no other top triangle uses.
    edges = np.sort(faces[top][:, [0, 1, 1, 2, 2, 0]].reshape(-1, 3, 2), axis=2)
    keys = edges[..., 0] * len(mesh.vertices) + edges[..., 1]
    unique, counts = np.unique(keys, return_counts=True)
    single = np.isin(keys, unique[counts == 1]).any(axis=1)
    outline = mesh.vertices[faces[top], :2].max(axis=(1, 2)) > part.layout.outline_mm[0] / 2 - 1e-9
    face = top[np.flatnonzero(single & ~outline)[0]]
    faces[face] = faces[face, ::-1]
    with pytest.raises(ValueError, match="is not closed at vertex"):
        mesh_hole_loops(PlateMesh(mesh.vertices, faces))


@pytest.mark.parametrize("grid, pitch, message", [
    ((6, 6), PITCH_MM, "lies outside the grid of 6 x 6 cells"),
    ((6, 6), 2 * PITCH_MM, "two holes lie in cell"),
])
def test_holes_that_do_not_fit_the_grid_are_errors(grid, pitch, message):
    part = make("straight", np.full((12, 12), 0.3))
    with pytest.raises(ValueError, match=message):
        hole_layout_from_mesh(part.mesh, (pitch, pitch), grid)


def test_wrong_convergence_point_is_an_error():
    part = make("chief_ray", random_fraction(5))
    ex, ey, distance = part.layout.converge_mm  # type: ignore[misc]
    with pytest.raises(ValueError, match="differ from"):
        hole_layout_from_mesh(part.mesh, part.layout.pitch_mm, part.layout.grid,
                              (ex + 1.0, ey, distance))


def test_a_mesh_that_is_not_a_plate_is_an_error():
    vertices = np.array([[0, 0, 1.0], [1, 0, 1], [0, 1, 1], [0, 0, 2]])
    with pytest.raises(ValueError, match="bottom face at z = 0"):
        mesh_hole_loops(PlateMesh(vertices, np.array([[0, 1, 2], [0, 1, 3]])))


@pytest.mark.slow
def test_6400_holes_take_under_two_seconds():
    """The near-eye plate: 80 x 80 holes, ~0.5 million triangles, read back from STL."""
    scene = Scene(Display(20.0, 20.0, (400, 400)),
                  Plate((80, 80), (0.25, 0.25), 10.0, 0.3, "chief_ray"),
                  Eye(4.0, 10.0, (50.0, 50.0), (16, 16)))
    part = make_part(np.full((80, 80), 0.3), scene, FabricationSettings(PROCESSES["resin"]))
    mesh = read_stl(stl_bytes(part.mesh))
    start = time.process_time()
    got = recover(part, mesh)
    elapsed = time.process_time() - start
    assert got.count == 6400 and elapsed < 2.0
    assert_same_layout(got, part.layout, STL_TOL_MM)
    assert math.isclose(got.thickness_mm, 0.3, abs_tol=STL_TOL_MM)
