"""The view traced through the written mesh (aperture_fab.retrace) against the fast model, exact
light levels and its own error estimate. Every part is built with make_part, written as STL and
read back, so what is traced is the file a user would print."""

from __future__ import annotations

import math
from functools import cache
from typing import Any

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from aperture_fab.exporters import read_stl, stl_bytes
from aperture_fab.fabricate import FabricationSettings, Part, make_part
from aperture_fab.mesh import PlateMesh, outline_points_mm
from aperture_fab.model import Renderer
from aperture_fab.process import PROCESSES, check_plate
from aperture_fab.retrace import (
    REPLICATES,
    TracedView,
    _concentric_disk,
    _outline_hull,
    _strata,
    trace_mesh_view,
)
from aperture_fab.scene import Display, Eye, Plate, Scene, display_fov_deg

PROCESS = PROCESSES["photomask"]
PITCH_MM = 0.3
GAP_MM = 10.0
RELIEF_MM = 10.0
PUPIL_MM = 3.0


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR (dB) of a against b, peak b's maximum."""
    return 10 * math.log10(float(np.abs(b).max()) ** 2 / float(np.mean((a - b) ** 2)))


def make_scene(axis: str = "straight", thickness: float = 0.2, cells: int = 20,
               display_mm: float = 6.0, display_px: int = 48,
               tan_half: float | None = None) -> Scene:
    display = Display(display_mm, display_mm, (display_px, display_px))
    plate = Plate((cells, cells), (PITCH_MM, PITCH_MM), GAP_MM, thickness, axis)  # type: ignore[arg-type]
    fov = (display_fov_deg(display, GAP_MM + thickness + RELIEF_MM) if tan_half is None
           else (math.degrees(2 * math.atan(tan_half)),) * 2)
    eye = Eye(PUPIL_MM, RELIEF_MM, fov, (12, 12))
    scene = Scene(display, plate, eye)
    check_plate(PROCESS, plate)  # the photomask process makes this plate
    return scene


def written_mesh(part: Part) -> PlateMesh:
    """The mesh as read back from its STL file."""
    return read_stl(stl_bytes(part.mesh))


def as_built_fraction(part: Part, scene: Scene) -> np.ndarray:
    """Open-area fraction (rows, cols) of the holes as made: pi r^2 / (px py), 0 when closed."""
    a = np.zeros((scene.plate.cells[1], scene.plate.cells[0]))
    px, py = scene.plate.pitch_mm
    layout = part.layout
    a[layout.cells[:, 0], layout.cells[:, 1]] = math.pi * layout.radii_mm**2 / (px * py)
    return a


@cache
def random_case(axis: str) -> tuple[Scene, Part, np.ndarray, np.ndarray]:
    """Random holes (some closed) in a 0.2 mm photomask plate and a blocky colour display;
    returns the scene, the part, the as-built fractions and the display (3, 48, 48)."""
    rng = np.random.default_rng(1)
    scene = make_scene(axis)
    a = rng.uniform(0.0, 0.6, (20, 20))
    a[rng.random((20, 20)) < 0.15] = 0.0
    part = make_part(a, scene, FabricationSettings(PROCESS))
    display = np.kron(rng.random((3, 6, 6)), np.ones((8, 8)))  # 8-pixel blocks: sharp edges
    return scene, part, as_built_fraction(part, scene), display


def model_view(scene: Scene, a: np.ndarray, display: np.ndarray) -> np.ndarray:
    view = Renderer(scene, dtype=torch.float64).render(torch.as_tensor(a),
                                                        torch.as_tensor(display))
    return view.numpy()


# -- agreement with the fast model ----------------------------------------------------------------


@pytest.mark.parametrize("samples, min_psnr_db", [
    (2048, 28.0),
    pytest.param(16384, 35.0, marks=pytest.mark.slow),
])
@pytest.mark.parametrize("axis", ["straight", "chief_ray"])
def test_mesh_view_agrees_with_the_model(axis, samples, min_psnr_db):
    """Polygonal holes of the circles' area, read back from STL, against the closed-form model of
    the as-built circles: they differ by polygon shape and Monte Carlo noise only."""
    scene, part, a, display = random_case(axis)
    traced = trace_mesh_view(written_mesh(part), scene, display, samples_per_pixel=samples)
    model = model_view(scene, a, display)
    assert traced.view.shape == model.shape == (3, 12, 12)
    assert psnr(traced.view, model) >= min_psnr_db
    # The error is mostly noise, and the noise is what the tracer says it is.
    rms_error = math.sqrt(float(np.mean((traced.view - model) ** 2)))
    rms_stderr = math.sqrt(float(np.mean(traced.stderr**2)))
    assert rms_error <= 2.0 * rms_stderr


def test_stderr_predicts_the_spread_between_seeds():
    """Two seeds differ by sqrt(2) standard errors: RMS ratio near 1, 95 % within 3 sigma."""
    scene, part, _, display = random_case("chief_ray")
    mesh = written_mesh(part)
    one = trace_mesh_view(mesh, scene, display, samples_per_pixel=256, seed=1)
    two = trace_mesh_view(mesh, scene, display, samples_per_pixel=256, seed=2)
    difference = one.view - two.view
    sigma = np.sqrt(one.stderr**2 + two.stderr**2)
    assert np.any(difference != 0)
    ratio = float(np.mean(difference**2) / np.mean(sigma**2))
    assert 0.7 <= ratio <= 1.4
    assert np.mean(np.abs(difference) <= 3 * sigma) >= 0.95


# -- exact light levels -------------------------------------------------------------------------


def test_closed_plate_is_black():
    scene = make_scene()
    part = make_part(np.zeros((20, 20)), scene, FabricationSettings(PROCESS))
    assert part.layout.count == 0
    traced = trace_mesh_view(written_mesh(part), scene, np.ones((1, 48, 48)),
                             samples_per_pixel=64)
    assert np.all(traced.view == 0) and np.all(traced.stderr == 0)


def test_uniform_display_through_equal_holes_gives_the_open_fraction():
    """Uniform display, equal holes of open fraction a. The pupil's footprint on the plate slides
    over a whole number of periods across the view, so the view's mean is exactly the polygons'
    open fraction (their area is the circle's) for a thin plate; the thickness (5 um) can only
    remove the overlap loss |d| w / area of a polygon and its translate by d = t tan."""
    thickness = 0.005
    s_bottom = RELIEF_MM + thickness
    periods = 10
    tan_half = periods * PITCH_MM / 2 / s_bottom
    scene = make_scene(thickness=thickness, cells=24, display_mm=12.0, display_px=8,
                       tan_half=tan_half)
    part = make_part(np.full((24, 24), 0.35), scene, FabricationSettings(PROCESS))
    radius = part.layout.radii_mm
    assert part.layout.count == 24 * 24 and np.ptp(radius) == 0
    a = math.pi * radius[0] ** 2 / PITCH_MM**2
    traced = trace_mesh_view(written_mesh(part), scene, np.ones((1, 8, 8)),
                             samples_per_pixel=1024)
    mean = float(traced.view.mean())
    stderr = math.sqrt(float(np.sum(traced.stderr**2))) / traced.view.size
    width = 2 * 1.1 * radius[0]  # a polygon's width is below 2.2 r
    loss = thickness * tan_half * math.sqrt(2) * width / (math.pi * radius[0] ** 2)
    assert a * (1 - loss) - 3 * stderr <= mean <= a + 3 * stderr


def test_the_mount_blocks_rays_outside_the_outline():
    """A field wider than the plate: view pixels whose pupil footprint on the bottom face lies
    wholly outside the outline are black (the display behind them is lit), central ones are not."""
    s_bottom = RELIEF_MM + 0.2
    tan_half = 8.0 / s_bottom
    scene = make_scene(cells=20, display_mm=40.0, display_px=8, tan_half=tan_half)
    part = make_part(np.full((20, 20), 0.3), scene, FabricationSettings(PROCESS))
    traced = trace_mesh_view(written_mesh(part), scene, np.ones((1, 8, 8)),
                             samples_per_pixel=256)
    half_outline = part.layout.outline_mm[0] / 2
    vx, _ = scene.eye.view_directions()
    step = scene.eye.view_step[0]
    reach = s_bottom * (np.abs(vx) - step / 2) - PUPIL_MM / 2  # nearest footprint point, per axis
    outside = (reach[None, :] > half_outline) | (reach[:, None] > half_outline)
    assert outside.sum() > 0 and (~outside).sum() > 0
    assert np.all(traced.view[0][outside] == 0)
    centre = slice(5, 7)
    assert np.all(traced.view[0][centre, centre] > 0.1)


def test_outline_hull_is_the_chamfered_outline():
    _, part, _, _ = random_case("straight")
    hull = _outline_hull(written_mesh(part).vertices[:, :2])
    expected = np.array(outline_points_mm(part.layout, part.corner_cut_mm))
    assert part.corner_cut_mm > 0 and len(hull) == len(expected) == 5
    # Same points, same (counter-clockwise) order, up to the starting point and float32.
    start = int(np.argmin(np.linalg.norm(hull - expected[0], axis=1)))
    np.testing.assert_allclose(np.roll(hull, -start, axis=0), expected, atol=1e-6)


# -- sampling and plumbing ------------------------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(st.integers(min_value=1, max_value=300))
def test_strata_tile_the_unit_square(n):
    """n strata of area 1 / n each, covering every point of the square exactly once."""
    corner, size = _strata(n)
    np.testing.assert_allclose(size.prod(axis=1), 1.0 / n, rtol=1e-12)
    grid = (np.arange(97) + 0.5) / 97
    px, py = (g.ravel() for g in np.meshgrid(grid, grid))
    inside = ((px[:, None] >= corner[None, :, 0]) & (px[:, None] < corner[None, :, 0]
              + size[None, :, 0]) & (py[:, None] >= corner[None, :, 1])
              & (py[:, None] < corner[None, :, 1] + size[None, :, 1]))
    assert np.all(inside.sum(axis=1) == 1)


def test_concentric_map_is_uniform_on_the_disk():
    """Uniform points of the square land uniformly in the unit disk: r^2 and angle uniform."""
    rng = np.random.default_rng(0)
    x, y = _concentric_disk(rng.random(200_000), rng.random(200_000))
    r2 = x**2 + y**2
    assert r2.max() <= 1 + 1e-12
    counts = np.histogram(r2, bins=10, range=(0, 1))[0]
    np.testing.assert_allclose(counts / len(r2), 0.1, atol=0.004)
    counts = np.histogram(np.arctan2(y, x), bins=12, range=(-np.pi, np.pi))[0]
    np.testing.assert_allclose(counts / len(r2), 1 / 12, atol=0.004)


def test_chunking_and_seed_give_reproducible_views():
    scene, part, _, display = random_case("straight")
    mesh = written_mesh(part)
    calls: list[tuple[int, int]] = []
    whole = trace_mesh_view(mesh, scene, display, samples_per_pixel=64, seed=3)
    chunked = trace_mesh_view(mesh, scene, display, samples_per_pixel=64, seed=3, max_rays=500,
                              progress=lambda done, total: calls.append((done, total)))
    other = trace_mesh_view(mesh, scene, display, samples_per_pixel=64, seed=4)
    assert isinstance(whole, TracedView)
    np.testing.assert_array_equal(whole.view, chunked.view)
    np.testing.assert_array_equal(whole.stderr, chunked.stderr)
    assert not np.array_equal(whole.view, other.view)
    assert len(calls) > 1 and calls[-1] == (144, 144)
    assert [done for done, _ in calls] == sorted(done for done, _ in calls)


def test_samples_round_up_to_whole_replicates():
    scene, part, _, display = random_case("straight")
    traced = trace_mesh_view(written_mesh(part), scene, display, samples_per_pixel=2 * REPLICATES
                             + 1)
    assert traced.samples_per_pixel == 3 * REPLICATES


@pytest.mark.parametrize("kwargs, message", [
    (dict(display=np.ones((1, 10, 10))), "display has shape"),
    (dict(position=1), "position = 1"),
    (dict(samples_per_pixel=1), "samples_per_pixel = 1"),
    (dict(max_rays=0), "max_rays = 0"),
])
def test_bad_inputs_are_clear_errors(kwargs, message):
    scene, part, _, display = random_case("straight")
    args: dict[str, Any] = dict(mesh=written_mesh(part), scene=scene, display=display)
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        trace_mesh_view(**args)


def test_mesh_above_the_pupil_is_an_error():
    scene, part, _, display = random_case("straight")
    mesh = written_mesh(part)
    lifted = PlateMesh(mesh.vertices + np.array([0.0, 0.0, 50.0]), mesh.faces)
    with pytest.raises(ValueError, match="bottom face at z = 0"):
        trace_mesh_view(lifted, scene, display)
