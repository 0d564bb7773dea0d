"""The view traced through the written mesh (aperture_fab.validation.retrace) against the fast
model, exact light levels, the two samplings against each other and its own error estimate. Every
part is built with make_part (or build_mesh), written as STL and read back, so what is traced is the
file a user would print."""

from __future__ import annotations

import math
from functools import cache
from typing import Any

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from aperture_fab.config.stages import FabricationSettings
from aperture_fab.fabrication.layout import HoleLayout
from aperture_fab.fabrication.mesh import PlateMesh, build_mesh, outline_points_mm
from aperture_fab.fabrication.mesh_holes import mesh_hole_loops
from aperture_fab.fabrication.part import Part, design_bounds, make_part
from aperture_fab.fabrication.process import PROCESSES
from aperture_fab.fabrication.rules import check_plate
from aperture_fab.io.formats import read_stl, stl_bytes
from aperture_fab.optics.model import STACK_OVERSAMPLE, Renderer
from aperture_fab.optics.scene import Display, Eye, Plate, Scene, display_fov_deg
from aperture_fab.targets import star
from aperture_fab.validation.retrace import TracedView, trace_mesh_view
from aperture_fab.validation.retrace_holes import Disks, clear_radius, disk_neighbours
from aperture_fab.validation.retrace_rays import outline_hull
from aperture_fab.validation.retrace_sampling import (
    CHORD_BUDGET,
    DEFAULT_SAMPLES,
    LEAST_CHORDS,
    MOST_SAMPLES,
    RAY_BUDGET,
    REPLICATES,
    cap_angle,
    concentric_disk,
    lens_sample,
    sample_budget,
    strata,
)
from aperture_fab.validation.validate import layout_fractions

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

#: The model's own approximations (pupil-rim clipping, view-box averaging) leave an RMS difference
#: of about 1 % of the view's mean at any sample count, whatever the tessellation or thickness.
MODEL_FLOOR = 0.015


@pytest.mark.parametrize("sampling, samples, min_psnr_db", [
    ("holes", 16, 38.0),
    ("pupil", 2048, 28.0),
    pytest.param("holes", 256, 43.0, marks=pytest.mark.slow),
])
@pytest.mark.parametrize("axis", ["straight", "chief_ray"])
def test_mesh_view_agrees_with_the_model(axis, sampling, samples, min_psnr_db):
    """Polygonal holes of the circles' area, read back from STL, against the closed-form model of
    the as-built circles: they differ by Monte Carlo noise and the model's small floor."""
    scene, part, a, display = random_case(axis)
    traced = trace_mesh_view(written_mesh(part), scene, display, samples_per_pixel=samples,
                             sampling=sampling)
    model = model_view(scene, a, display)
    assert traced.view.shape == model.shape == (3, 12, 12)
    assert traced.sampling == sampling and traced.rays_cast > 0
    assert psnr(traced.view, model) >= min_psnr_db
    # The error is noise, and the noise is what the tracer says it is, over the model's floor.
    rms_error = math.sqrt(float(np.mean((traced.view - model) ** 2)))
    rms_stderr = math.sqrt(float(np.mean(traced.stderr**2)))
    assert rms_error <= 2.0 * rms_stderr + MODEL_FLOOR * float(model.mean())


@cache
def near_eye_case(seed: int) -> tuple[Scene, Part, np.ndarray]:
    """The near-eye preset (80 x 80 chief-ray holes in 0.3 mm resin, 128 x 128 view): random
    open fractions in [0, 0.35] and a random display, pixel by pixel (the noisiest content)."""
    from aperture_fab.config.config import resolve

    scene = resolve("near-eye", overrides={"plate.thickness_mm": 0.3, "plate.cells": [80, 80],
                                           "plate.pitch_mm": [0.25, 0.25]}).scene
    rng = np.random.default_rng(seed)
    part = make_part(rng.uniform(0.0, 0.35, scene.plate.cells[::-1]), scene,
                     FabricationSettings(PROCESSES["resin"]))
    return scene, part, rng.random((3, scene.display.pixels[1], scene.display.pixels[0]))


@pytest.mark.slow
def test_near_eye_mesh_view_agrees_with_the_model():
    """The acceptance case: default samples, at least 35 dB against the model's view."""
    scene, part, display = near_eye_case(0)
    traced = trace_mesh_view(written_mesh(part), scene, display)
    model = model_view(scene, layout_fractions(part.layout), display)
    assert traced.samples_per_pixel == LEAST_CHORDS  # the budget's fewest: a dense plate
    assert psnr(traced.view, model) >= 35.0
    rms_error = math.sqrt(float(np.mean((traced.view - model) ** 2)))
    assert rms_error <= 1.2 * math.sqrt(float(np.mean(traced.stderr**2)))


def test_one_pixel_lines_need_the_oversampled_stack():
    """A grid of one-pixel bright lines on black (an optimized display's thin bright features)
    behind a random photomask plate, near-eye geometry at a smaller size: the model with its
    stack sampled twice per display pixel agrees with the trace through the written mesh to 38
    dB or better; one sample per pixel, read bilinearly, misses by about 10 dB more."""
    from aperture_fab.config.config import resolve

    scene = resolve("near-eye", overrides={
        "display.pixels": [200, 200], "display.width_mm": 10.0, "display.height_mm": 10.0,
        "plate.cells": [40, 40], "plate.pitch_mm": [0.25, 0.25], "eye.view_pixels": [64, 64]}).scene
    rng = np.random.default_rng(0)
    low, high = design_bounds(scene, PROCESS)
    part = make_part(rng.uniform(low, high, scene.plate.cells[::-1]), scene,
                     FabricationSettings(PROCESS))
    display = np.zeros((1, 200, 200))
    display[0, :, ::5] = display[0, ::5, :] = 1.0
    traced = trace_mesh_view(written_mesh(part), scene, display, seed=0)
    a = torch.as_tensor(layout_fractions(part.layout))
    fine, coarse = (Renderer(scene, dtype=torch.float64, oversample=k)
                    .render(a, torch.as_tensor(display)).numpy() for k in (STACK_OVERSAMPLE, 1))
    assert STACK_OVERSAMPLE >= 2
    assert psnr(traced.view, fine) >= 38.0
    assert psnr(traced.view, coarse) <= psnr(traced.view, fine) - 6.0


# -- the two samplings and the error estimate ----------------------------------------------------


def pooled_ratio(one: TracedView, two: TracedView) -> float:
    """Mean squared difference over the mean predicted variance (near 1 when both are unbiased
    and their standard errors honest)."""
    sigma2 = one.stderr**2 + two.stderr**2
    return float(np.mean((one.view - two.view) ** 2) / np.mean(sigma2))


def assert_same_mean(one: TracedView, two: TracedView) -> None:
    """Each channel's mean over the view agrees within 4 standard errors (pixels are
    independent; a pixel's channels share rays, so channels are tested one by one)."""
    difference = (one.view - two.view).mean(axis=(1, 2))
    sigma = np.sqrt(np.sum(one.stderr**2 + two.stderr**2, axis=(1, 2))) / one.view[0].size
    assert np.all(np.abs(difference) <= 4 * sigma)


@pytest.mark.parametrize("axis, focus_mm, eye_mm", [
    ("straight", None, (0.0, 0.0)),
    ("chief_ray", None, (0.0, 0.0)),
    ("chief_ray", 25.0, (0.6, -0.4)),  # near focus: the footprint scales by 1 - s q
])
def test_hole_sampling_agrees_with_pupil_sampling(axis, focus_mm, eye_mm):
    """Sampling only the holes loses nothing: the uniform pupil sampler, which draws every ray,
    agrees pixel by pixel within the standard errors and in the mean over the view."""
    scene, part, _, display = random_case(axis)
    mesh = written_mesh(part)
    eye = scene.eye
    scene = Scene(scene.display, scene.plate, Eye(eye.pupil_mm, eye.eye_relief_mm, eye.fov_deg,
                                                  eye.view_pixels, focus_mm, (eye_mm,)))
    holes = trace_mesh_view(mesh, scene, display, samples_per_pixel=64, seed=1)
    pupil = trace_mesh_view(mesh, scene, display, samples_per_pixel=4096, seed=2,
                            sampling="pupil")
    assert 0.6 <= pooled_ratio(holes, pupil) <= 1.5
    assert_same_mean(holes, pupil)
    # And it is far more efficient: variance x rays (and chords) cast over 10 x smaller; near
    # focus the pupil's small footprint cuts the lenses, leaving more of each chord to rays.
    cost = [float(np.mean(t.stderr**2)) * t.rays_cast for t in (holes, pupil)]
    assert cost[0] < (0.1 if focus_mm is None else 0.15) * cost[1]


def test_stderr_predicts_the_spread_between_seeds():
    """Two seeds differ by sqrt(2) standard errors: RMS ratio near 1, 95 % within 3 sigma."""
    scene, part, _, display = random_case("chief_ray")
    mesh = written_mesh(part)
    one = trace_mesh_view(mesh, scene, display, samples_per_pixel=16, seed=1)
    two = trace_mesh_view(mesh, scene, display, samples_per_pixel=16, seed=2)
    difference = one.view - two.view
    sigma = np.sqrt(one.stderr**2 + two.stderr**2)
    assert np.any(difference != 0)
    assert 0.7 <= pooled_ratio(one, two) <= 1.4
    assert np.mean(np.abs(difference) <= 3 * sigma) >= 0.95


def test_z_scores_against_a_precise_view_follow_students_t():
    """Against a view with 8 x the samples (3 x smaller errors), z = error / stderr of a
    4-replicate estimate follows Student's t with 3 degrees of freedom: 95 % within 3.18."""
    scene, part, _, display = random_case("straight")
    mesh = written_mesh(part)
    reference = trace_mesh_view(mesh, scene, display, samples_per_pixel=128, seed=7)
    zs = []
    for seed in range(3):
        traced = trace_mesh_view(mesh, scene, display, samples_per_pixel=16, seed=seed)
        error = traced.view - reference.view
        zs.append(error / np.sqrt(traced.stderr**2 + reference.stderr**2))
        assert 0.6 <= pooled_ratio(traced, reference) <= 1.5
    z = np.concatenate([x.ravel() for x in zs])
    assert 0.92 <= np.mean(np.abs(z) <= 3.182) <= 0.98
    assert abs(float(np.median(z))) <= 0.1


def overlapping_holes_mesh() -> tuple[Scene, PlateMesh]:
    """Straight octagonal holes of radius 0.49 p in a 0.2 mm plate: their circumscribed disks
    (radius 0.517 p) overlap their neighbours' though the octagons keep a web."""
    scene = make_scene(cells=10)
    radius = 0.49 * PITCH_MM
    xs = (np.arange(10) - 4.5) * PITCH_MM
    rows, cols = np.divmod(np.arange(100), 10)
    layout = HoleLayout(cells=np.stack([rows, cols], axis=1),
                        centres_mm=np.stack([xs[cols], -xs[rows]], axis=1),
                        radii_mm=np.full(100, radius), axes=np.zeros((100, 2)),
                        pitch_mm=(PITCH_MM, PITCH_MM), grid=(10, 10), outline_mm=(4.0, 4.0),
                        thickness_mm=0.2)
    mesh = build_mesh(layout, chord_tolerance_mm=0.1, segments_min=8, segments_max=8)
    return scene, read_stl(stl_bytes(mesh))


def test_overlapping_hole_disks_are_counted_once():
    scene, mesh = overlapping_holes_mesh()
    assert Disks.of(mesh_hole_loops(mesh), mesh).neighbours.shape[1] > 0
    display = np.kron(np.random.default_rng(3).random((1, 6, 6)), np.ones((8, 8)))
    holes = trace_mesh_view(mesh, scene, display, samples_per_pixel=64, seed=1)
    pupil = trace_mesh_view(mesh, scene, display, samples_per_pixel=4096, seed=2,
                            sampling="pupil")
    assert 0.6 <= pooled_ratio(holes, pupil) <= 1.5
    assert_same_mean(holes, pupil)


def test_disk_neighbours_are_the_overlapping_pairs():
    rng = np.random.default_rng(0)
    centre = rng.uniform(0, 5, (300, 2))
    radius = rng.uniform(0.05, 0.3, 300)
    table = disk_neighbours(centre, radius)
    gap = np.linalg.norm(centre[:, None] - centre[None], axis=2)
    want = (gap < radius[:, None] + radius[None]) & ~np.eye(300, dtype=bool)
    got = np.zeros_like(want)
    for i, row in enumerate(table):
        got[i, row[row >= 0]] = True
    np.testing.assert_array_equal(got, want)


# -- exact light levels -------------------------------------------------------------------------


@pytest.mark.parametrize("sampling", ["holes", "pupil"])
def test_closed_plate_is_black(sampling):
    scene = make_scene()
    part = make_part(np.zeros((20, 20)), scene, FabricationSettings(PROCESS))
    assert part.layout.count == 0
    traced = trace_mesh_view(written_mesh(part), scene, np.ones((1, 48, 48)),
                             samples_per_pixel=64, sampling=sampling)
    assert np.all(traced.view == 0) and np.all(traced.stderr == 0)


@pytest.mark.parametrize("sampling, samples", [("holes", 32), ("pupil", 1024)])
def test_uniform_display_through_equal_holes_gives_the_open_fraction(sampling, samples):
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
                             samples_per_pixel=samples, sampling=sampling)
    mean = float(traced.view.mean())
    stderr = math.sqrt(float(np.sum(traced.stderr**2))) / traced.view.size
    width = 2 * 1.1 * radius[0]  # a polygon's width is below 2.2 r
    loss = thickness * tan_half * math.sqrt(2) * width / (math.pi * radius[0] ** 2)
    assert a * (1 - loss) - 3 * stderr <= mean <= a + 3 * stderr


@pytest.mark.parametrize("sampling", ["holes", "pupil"])
def test_the_mount_blocks_rays_outside_the_outline(sampling):
    """A field wider than the plate: view pixels whose pupil footprint on the bottom face lies
    wholly outside the outline are black (the display behind them is lit), central ones are not."""
    s_bottom = RELIEF_MM + 0.2
    tan_half = 8.0 / s_bottom
    scene = make_scene(cells=20, display_mm=40.0, display_px=8, tan_half=tan_half)
    part = make_part(np.full((20, 20), 0.3), scene, FabricationSettings(PROCESS))
    traced = trace_mesh_view(written_mesh(part), scene, np.ones((1, 8, 8)), sampling=sampling)
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
    hull = outline_hull(written_mesh(part).vertices[:, :2])
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
    corner, size = strata(n)
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
    x, y = concentric_disk(rng.random(200_000), rng.random(200_000))
    r2 = x**2 + y**2
    assert r2.max() <= 1 + 1e-12
    counts = np.histogram(r2, bins=10, range=(0, 1))[0]
    np.testing.assert_allclose(counts / len(r2), 0.1, atol=0.004)
    counts = np.histogram(np.arctan2(y, x), bins=12, range=(-np.pi, np.pi))[0]
    np.testing.assert_allclose(counts / len(r2), 1 / 12, atol=0.004)


@pytest.mark.parametrize("sampling", ["holes", "pupil"])
def test_chunking_and_seed_give_reproducible_views(sampling):
    scene, part, _, display = random_case("straight")
    mesh = written_mesh(part)
    calls: list[tuple[int, int]] = []
    whole = trace_mesh_view(mesh, scene, display, samples_per_pixel=16, seed=3,
                            sampling=sampling)
    chunked = trace_mesh_view(mesh, scene, display, samples_per_pixel=16, seed=3, max_rays=500,
                              progress=lambda done, total: calls.append((done, total)),
                              sampling=sampling)
    other = trace_mesh_view(mesh, scene, display, samples_per_pixel=16, seed=4,
                            sampling=sampling)
    assert isinstance(whole, TracedView)
    np.testing.assert_array_equal(whole.view, chunked.view)
    np.testing.assert_array_equal(whole.stderr, chunked.stderr)
    assert not np.array_equal(whole.view, other.view)
    assert len(calls) > 1 and calls[-1] == (144, 144)
    assert [done for done, _ in calls] == sorted(done for done, _ in calls)


@pytest.mark.parametrize("sampling", ["holes", "pupil"])
def test_samples_round_up_to_whole_replicates(sampling):
    scene, part, _, display = random_case("straight")
    mesh = written_mesh(part)
    traced = trace_mesh_view(mesh, scene, display, samples_per_pixel=2 * REPLICATES + 1,
                             sampling=sampling)
    assert traced.samples_per_pixel == 3 * REPLICATES
    default = trace_mesh_view(mesh, scene, display, sampling=sampling)
    if sampling == "pupil":
        assert default.samples_per_pixel == DEFAULT_SAMPLES[sampling]
    else:  # a chord budget: this small plate gets the most per pair
        assert default.samples_per_pixel == MOST_SAMPLES
        assert default.pairs * MOST_SAMPLES <= CHORD_BUDGET
    assert (default.pairs > 0) == (sampling == "holes")


@pytest.mark.parametrize("chords, budget, least", [(True, CHORD_BUDGET, LEAST_CHORDS),
                                                   (False, RAY_BUDGET, DEFAULT_SAMPLES["holes"])])
def test_the_budget_gives_dense_plates_fewer_samples_per_pair(chords, budget, least):
    assert sample_budget(1000, chords) == MOST_SAMPLES
    assert sample_budget(budget // 100, chords) == 100
    assert sample_budget(100 * budget, chords) == least


@pytest.mark.parametrize("kwargs, message", [
    (dict(display=np.ones((1, 10, 10))), "display has shape"),
    (dict(position=1), "position = 1"),
    (dict(samples_per_pixel=1), "samples_per_pixel = 1"),
    (dict(max_rays=0), "max_rays = 0"),
    (dict(sampling="grid"), "sampling = 'grid'"),
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


def test_a_mesh_that_is_not_a_plate_needs_pupil_sampling():
    """Without one hole's wall the mesh has no hole structure to sample; "pupil" still traces."""
    scene, part, _, display = random_case("straight")
    mesh = written_mesh(part)
    z = mesh.vertices[mesh.faces, 2]
    wall = (z.min(axis=1) == 0) & (z.max(axis=1) > 0)
    near = np.linalg.norm(mesh.vertices[mesh.faces, :2].mean(axis=1)
                          - part.layout.centres_mm[0], axis=1) < 2 * part.layout.radii_mm[0]
    cut = PlateMesh(mesh.vertices, mesh.faces[~(wall & near)])
    with pytest.raises(ValueError, match="sampling='pupil' traces any mesh"):
        trace_mesh_view(cut, scene, display)
    assert trace_mesh_view(cut, scene, display, samples_per_pixel=8, sampling="pupil").view.any()


# -- clear cylinders: rays decided without a cast ------------------------------------------------


def clear_radius_of(mesh: PlateMesh) -> tuple[np.ndarray, Any]:
    """Each hole's clear-cylinder radius (mm), as trace_mesh_view finds it, and the loops."""
    loops = mesh_hole_loops(mesh)
    z = mesh.vertices[:, 2]
    low = loops.bottom_centroid_mm + loops.axes * float(z.min())
    cap = np.maximum(loops.top_circum_radius_mm, loops.bottom_circum_radius_mm)
    return clear_radius(mesh, low, loops.top_centroid_mm, (float(z.min()), float(z.max())),
                         cap), loops


@pytest.mark.parametrize("axis", ["straight", "chief_ray"])
def test_a_prism_holes_clear_radius_is_its_inscribed_radius(axis):
    """build_mesh's holes are regular polygons swept along their axis: no triangle comes
    nearer the axis than the polygon's inscribed radius, and the walls reach it."""
    _, part, _, _ = random_case(axis)
    rho, loops = clear_radius_of(written_mesh(part))
    inscribed = loops.top_circum_radius_mm * np.cos(np.pi / loops.segments)
    np.testing.assert_allclose(rho, inscribed, rtol=1e-4)


def test_a_stray_triangle_in_a_hole_narrows_its_clear_cylinder():
    """Any triangle of the mesh counts, not only the hole's wall: a sliver standing in hole 0,
    0.3 of its radius from the axis, brings rho down to 0.3 r there and nowhere else."""
    _, part, _, _ = random_case("straight")
    mesh = written_mesh(part)
    before, loops = clear_radius_of(mesh)
    centre, radius = loops.top_centroid_mm[0], loops.top_area_radius_mm[0]
    t = loops.thickness_mm
    corners = np.array([[centre[0] + 0.3 * radius, centre[1] - 0.2 * radius, 0.3 * t],
                        [centre[0] + 0.3 * radius, centre[1] + 0.2 * radius, 0.3 * t],
                        [centre[0] + 0.5 * radius, centre[1], 0.6 * t]])
    stray = PlateMesh(np.concatenate([mesh.vertices, corners]),
                      np.concatenate([mesh.faces, len(mesh.vertices) + np.array([[0, 1, 2]])]))
    after, _ = clear_radius_of(stray)
    assert after[0] == pytest.approx(0.3 * radius, rel=1e-9)
    np.testing.assert_array_equal(after[1:], before[1:])


@pytest.mark.parametrize("case", ["chief_ray", "thin"])
def test_clear_cylinders_decide_rays_as_embree_does(case, monkeypatch):
    """The rays passed through a clear cylinder without a cast are rays Embree finds clear:
    with every ray cast (a margin too wide for any cylinder) the view is the same, to
    rounding, and so are the rays counted."""
    from aperture_fab.validation import retrace_holes

    if case == "thin":  # a 5 um plate (the photomask default): nearly every ray is clear
        scene = make_scene(thickness=0.005, cells=20)
        a = np.random.default_rng(2).uniform(0.05, 0.5, (20, 20))
        part = make_part(a, scene, FabricationSettings(PROCESS))
        display = np.random.default_rng(4).random((3, 48, 48))
    else:
        scene, part, _, display = random_case(case)
    mesh = written_mesh(part)
    monkeypatch.setattr(retrace_holes, "MIN_BOX_PX", math.inf)  # rays only: no chords
    fast = trace_mesh_view(mesh, scene, display, samples_per_pixel=16, seed=5)
    monkeypatch.setattr(retrace_holes, "CLEAR_RTOL", 1.0)
    cast = trace_mesh_view(mesh, scene, display, samples_per_pixel=16, seed=5)
    assert fast.rays_cast == cast.rays_cast > 0
    np.testing.assert_allclose(fast.view, cast.view, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(fast.stderr, cast.stderr, rtol=1e-9, atol=1e-15)


# -- chords: the closed forms against rays -------------------------------------------------------


@pytest.mark.parametrize("axis", ["straight", "chief_ray"])
@pytest.mark.parametrize("clear", [True, False])
def test_chords_agree_with_rays(axis, clear, monkeypatch):
    """The chords' closed forms (over the view box and along x, where the clear cylinder says
    no ray meets the mesh) estimate what rays do: pixel by pixel within the standard errors and
    in the mean, against the per-ray path; without clear cylinders (every ray cast) they fall
    back to rays decided by Embree, and still agree."""
    from aperture_fab.validation import retrace_holes

    scene, part, _, display = random_case(axis)
    mesh = written_mesh(part)
    if not clear:
        monkeypatch.setattr(retrace_holes, "CLEAR_RTOL", 1.0)
    chords = trace_mesh_view(mesh, scene, display, samples_per_pixel=64, seed=1)
    monkeypatch.setattr(retrace_holes, "MIN_BOX_PX", math.inf)
    rays = trace_mesh_view(mesh, scene, display, samples_per_pixel=64, seed=2)
    assert 0.6 <= pooled_ratio(chords, rays) <= 1.5
    assert_same_mean(chords, rays)


def test_a_siemens_star_is_traced_within_35_db(monkeypatch):
    """Dense edges at every orientation (a Siemens star on the display, behind the default
    0.005 mm photomask film), at the fewest chords per pair the budget gives: the trace agrees
    with the exact model at 35 dB or better, where rays alone (as many per pair) reach ~32."""
    from aperture_fab.validation import retrace_holes

    scene = make_scene(thickness=0.005)
    part = make_part(np.random.default_rng(3).uniform(0.05, 0.5, (20, 20)), scene,
                     FabricationSettings(PROCESS))
    display = star(scene.display.pixels[0])
    mesh = written_mesh(part)
    model = model_view(scene, layout_fractions(part.layout), display)
    traced = trace_mesh_view(mesh, scene, display, samples_per_pixel=LEAST_CHORDS, seed=1)
    assert psnr(traced.view, model) >= 35.0
    monkeypatch.setattr(retrace_holes, "MIN_BOX_PX", math.inf)
    rays = trace_mesh_view(mesh, scene, display, samples_per_pixel=LEAST_CHORDS, seed=1)
    assert psnr(traced.view, model) >= psnr(rays.view, model) + 3.0


# -- the lens sampler -----------------------------------------------------------------------------


def test_cap_angle_inverts_the_cap_area():
    theta = np.linspace(0, np.pi, 20001)
    area = theta - np.sin(theta) * np.cos(theta)
    np.testing.assert_allclose(cap_angle(area), theta, atol=1e-6)  # cube-root flat at 0
    np.testing.assert_allclose(cap_angle(area) - np.sin(cap_angle(area))
                               * np.cos(cap_angle(area)), area, atol=1e-14)


@settings(max_examples=30, deadline=None)
@given(r=st.floats(0.2, 2.0), s=st.floats(0.2, 2.0), d=st.floats(0.0, 4.0),
       angle=st.floats(0.0, 2 * np.pi))
def test_lens_sample_is_uniform_over_the_lens(r, s, d, angle):
    """Points lie in both disks, their area is the lens's (by counting a fine grid), and the
    points' mean and spread match the lens's centroid and second moments on that grid."""
    a = np.array([0.3, -0.2])
    b = a + d * np.array([np.cos(angle), np.sin(angle)])
    rng = np.random.default_rng(0)
    m = 20000
    points, area = lens_sample(a[None], np.array([r]), b[None], np.array([s]),
                                rng.random((1, m, 2)))
    step = 0.01
    grid = np.stack(np.meshgrid(np.arange(-2.5, 6.5, step), np.arange(-4.5, 4.5, step)), axis=-1)
    grid = grid.reshape(-1, 2)
    inside = grid[(np.sum((grid - a) ** 2, axis=1) <= r**2)
                  & (np.sum((grid - b) ** 2, axis=1) <= s**2)]
    grid_area = len(inside) * step**2
    assert area[0] == pytest.approx(grid_area, abs=0.02 * min(r, s) + 4 * step * (r + s))
    if area[0] < 0.05:
        return
    p = points[0]
    tol = 1e-9 * max(r, s)
    assert np.all(np.sum((p - a) ** 2, axis=1) <= r**2 + tol)
    assert np.all(np.sum((p - b) ** 2, axis=1) <= s**2 + tol)
    spread = math.sqrt(grid_area)
    np.testing.assert_allclose(p.mean(axis=0), inside.mean(axis=0), atol=0.03 * spread)
    np.testing.assert_allclose(np.cov(p.T), np.cov(inside.T), atol=0.03 * spread**2)
