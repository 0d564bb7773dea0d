"""Independent checks of the optical model: analytic cases, a per-ray Monte Carlo reference
(tests/reference_tracer.py, which shares no code with the model) and float64 gradient checks."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from reference_tracer import trace_view

from aperture_fab.optics.model import STACK_OVERSAMPLE, Renderer
from aperture_fab.optics.open_view import render_open
from aperture_fab.optics.scene import Display, Eye, Plate, Scene, display_fov_deg


def make_scene(*, cells=(12, 12), pitch=0.25, gap=10.0, thickness=0.0, axis="straight",
               pixels=(60, 60), size=15.0, pupil=4.0, relief=10.0, focus=None, view=(32, 32),
               fov=None, positions=((0.0, 0.0),)) -> Scene:
    display = Display(size, size, pixels)
    plate = Plate(cells, (pitch, pitch), gap, thickness, axis)
    distance = gap + thickness + relief
    eye = Eye(pupil, relief, fov or display_fov_deg(display, distance), view, focus,
              tuple(positions), tuple(1.0 for _ in positions))
    return Scene(display, plate, eye)


def render(scene: Scene, a: np.ndarray, display: np.ndarray, position: int = 0,
           dtype=torch.float64, oversample: int = STACK_OVERSAMPLE) -> np.ndarray:
    renderer = Renderer(scene, dtype=dtype, oversample=oversample)
    view = renderer.render(torch.as_tensor(a, dtype=dtype), torch.as_tensor(display, dtype=dtype),
                           position)
    return view.numpy()


def reference(scene: Scene, a: np.ndarray, display: np.ndarray, position: int = 0,
              samples: int = 4096, seed: int = 0) -> np.ndarray:
    plate, eye = scene.plate, scene.eye
    radii = np.sqrt(a * plate.pitch_mm[0] * plate.pitch_mm[1] / math.pi)
    return trace_view(display, (scene.display.width_mm, scene.display.height_mm), radii,
                      plate.pitch_mm, plate.gap_mm, plate.thickness_mm, plate.hole_axis,
                      eye.pupil_mm, eye.eye_relief_mm, eye.focus_mm, eye.fov_deg,
                      eye.view_pixels, eye_position_mm=eye.positions_mm[position],
                      tilt_target_mm=eye.positions_mm[0], samples_per_pixel=samples, seed=seed)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    peak = max(float(np.abs(b).max()), 1e-12)
    return 10 * math.log10(peak**2 / float(np.mean((a - b) ** 2)))


# -- analytic cases ----------------------------------------------------------------------------


@pytest.mark.parametrize("hole_col, hole_row, eye_x", [(40, 40, 0.0), (52, 31, 0.0),
                                                        (36, 44, 1.5)])
@pytest.mark.parametrize("thickness", [0.0, 0.3])
def test_single_pinhole_maps_display_point_to_direction(hole_col, hole_row, eye_x, thickness):
    """A bright display dot at x_d seen through one hole appears at tan = (x_d - x_h) / h with
    h = gap + thickness / 2, within 0.1 view pixel."""
    cells = (80, 80)
    view = (64, 64)
    tan_span = 0.08  # a narrow field around the expected direction: fine view pixels
    scene = make_scene(cells=cells, pitch=0.25, thickness=thickness, pixels=(800, 800),
                       size=20.0, view=view, positions=((eye_x, 0.0),),
                       fov=(math.degrees(2 * math.atan(tan_span)),) * 2)
    a = np.zeros((cells[1], cells[0]))
    a[hole_row, hole_col] = 0.05
    xs, ys = scene.plate.cell_centres_mm()
    hx, hy = xs[hole_col], ys[hole_row]
    h = scene.pinhole_height_mm
    # Put the dot where the hole is seen at a small angle inside the view field.
    target_tan = (0.021, -0.013)
    dx, dy = scene.display.pixel_centres_mm()
    col = int(np.argmin(np.abs(dx - (hx + h * target_tan[0]))))
    row = int(np.argmin(np.abs(dy - (hy + h * target_tan[1]))))
    display = np.zeros((1, 800, 800))
    display[0, row, col] = 1.0
    # The eye must see the hole: shift the eye so the chief ray passes near it.
    s_b = scene.plate_distance_mm
    offset = (hx - target_tan[0] * s_b, hy - target_tan[1] * s_b)
    scene = make_scene(cells=cells, pitch=0.25, thickness=thickness, pixels=(800, 800),
                       size=20.0, view=view, positions=(offset,),
                       fov=(math.degrees(2 * math.atan(tan_span)),) * 2)
    img = render(scene, a, display)[0]
    vx, vy = scene.eye.view_directions()
    total = img.sum()
    assert total > 0
    cx = float((img.sum(0) * vx).sum() / total)
    cy = float((img.sum(1) * vy).sum() / total)
    step = scene.eye.view_step
    assert abs(cx - (dx[col] - hx) / h) < 0.1 * step[0]
    assert abs(cy - (dy[row] - hy) / h) < 0.1 * step[1]


def test_uniform_display_thin_plate_passes_open_fraction():
    """Uniform white display, thin plate, holes of open-area fraction a: the view is a times
    the open view (within 1 %)."""
    # The pupil holds a whole number of holes, so single view pixels fluctuate by about
    # 1 / sqrt(holes at the pupil edge); a 0.1 mm pitch keeps that under 1 % too.
    scene = make_scene(cells=(250, 250), pitch=0.1, pixels=(100, 100), size=25.0,
                       view=(16, 16), fov=(20.0, 20.0))
    white = np.ones((1, 100, 100))
    open_view = render_open(scene, torch.as_tensor(white)).numpy()
    for a in (0.05, 0.2, 0.6):
        view = render(scene, np.full((250, 250), a), white)
        assert view.mean() == pytest.approx(a * open_view.mean(), rel=0.01)
        np.testing.assert_allclose(view, a * open_view, rtol=0.01)


def two_disk_overlap(r: float, d: float) -> float:
    if d >= 2 * r:
        return 0.0
    return 2 * r**2 * math.acos(d / (2 * r)) - d / 2 * math.sqrt(4 * r**2 - d**2)


@pytest.mark.parametrize("tan", [0.0, 0.1, 0.2, 0.3])
def test_thick_plate_follows_two_disk_overlap(tan):
    """Straight holes in a thick plate pass, at view angle theta, the overlap of two disks offset
    by t tan(theta) (uniform display, infinite focus: every ray of one direction is parallel)."""
    t, a, pitch = 0.3, 0.5, 0.25
    scene = make_scene(cells=(160, 160), pitch=pitch, thickness=t, pixels=(50, 50), size=60.0,
                       view=(61, 1), fov=(2 * math.degrees(math.atan(0.305)), 0.5))
    view = render(scene, np.full((160, 160), a), np.ones((1, 50, 50)))[0, 0]
    vx, _ = scene.eye.view_directions()
    j = int(np.argmin(np.abs(vx - tan)))
    r = math.sqrt(a * pitch**2 / math.pi)
    expected = two_disk_overlap(r, t * abs(vx[j])) / pitch**2
    assert view[j] == pytest.approx(expected, rel=0.01)


def test_focused_on_display_reproduces_display_upright():
    """Open plate (largest holes, thin), eye focused on the display: the view is the display,
    upright and unmirrored, when view pixels map 1:1 onto display pixels. Exactly so with one
    stack sample per display pixel: the display's mean over a pixel-wide box is linear between
    pixel centres, so reading it bilinearly between them is exact (finer samples fall between its
    kinks and blur it slightly; docs/model.md)."""
    n = 24
    size = 12.0
    gap, relief = 10.0, 10.0
    distance = gap + relief
    scene = make_scene(cells=(48, 48), pitch=0.25, gap=gap, relief=relief, pixels=(n, n),
                       size=size, view=(n, n), focus=distance,
                       fov=display_fov_deg(Display(size, size, (n, n)), distance))
    rng = np.random.default_rng(1)
    display = rng.random((1, n, n))
    display[0, 2:6, 2:4] = 1.0  # an asymmetric block near the top-left
    view = render(scene, np.full((48, 48), scene.plate.max_open_fraction), display,
                  oversample=1)[0]
    gain = float((view * display[0]).sum() / (view * view).sum())
    inner = slice(2, n - 2)
    np.testing.assert_allclose(gain * view[inner, inner], display[0, inner, inner], atol=0.03)
    assert view[3, 3] > view[3, n - 4] and view[3, 3] > view[n - 4, 3]


# -- the Monte Carlo reference ------------------------------------------------------------------


CASES = {
    "thin-straight": dict(thickness=0.0, axis="straight"),
    "thick-straight": dict(thickness=0.3, axis="straight"),
    "thick-chief-ray": dict(thickness=0.3, axis="chief_ray"),
    "offset-eye": dict(thickness=0.2, axis="chief_ray", positions=((1.0, -0.5),)),
    "finite-focus": dict(thickness=0.2, axis="straight", focus=300.0),
}


@pytest.mark.slow
@pytest.mark.parametrize("case", list(CASES))
def test_model_matches_monte_carlo_reference(case):
    """Random holes (including 0.1 x pitch), smooth random display: PSNR >= 35 dB."""
    rng = np.random.default_rng(7)
    kw = CASES[case]
    scene = make_scene(cells=(40, 40), pitch=0.3, pixels=(120, 120), size=12.0, view=(24, 24),
                       **kw)
    radii_share = rng.choice([0.0, 0.1, 0.25, 0.4, 0.5], size=(40, 40))
    a = math.pi * (radii_share * 0.3) ** 2 / 0.3**2
    coarse = rng.random((3, 15, 15))
    display = np.kron(coarse, np.ones((8, 8)))  # 8-pixel blocks: sharp edges, smooth inside
    model = render(scene, a, display)
    ref = reference(scene, a, display, samples=16384)
    assert psnr(model, ref) >= 35.0


def test_reference_agrees_on_a_quick_case():
    """Fast version of the Monte Carlo comparison, run by default."""
    rng = np.random.default_rng(3)
    scene = make_scene(cells=(24, 24), pitch=0.3, pixels=(48, 48), size=7.2, view=(10, 10),
                       thickness=0.2, axis="chief_ray")
    a = rng.uniform(0.02, 0.6, size=(24, 24))
    display = np.kron(rng.random((1, 6, 6)), np.ones((8, 8)))
    assert psnr(render(scene, a, display), reference(scene, a, display, samples=4096)) >= 30.0


# -- gradients ----------------------------------------------------------------------------------


@pytest.mark.parametrize("fast", [True, pytest.param(False, marks=pytest.mark.slow)])
@pytest.mark.parametrize("axis, thickness, focus", [("straight", 0.0, None),
                                                    ("chief_ray", 0.2, None),
                                                    ("straight", 0.2, 200.0)])
def test_gradcheck_float64(axis, thickness, focus, fast):
    """Analytic (hand-written backward) against numerical gradients; fast mode checks random
    projections of the Jacobian, the slow run every entry."""
    scene = make_scene(cells=(6, 6), pitch=0.5, pixels=(12, 12), size=3.0, view=(4, 4),
                       thickness=thickness, axis=axis, focus=focus, pupil=2.0)
    renderer = Renderer(scene, dtype=torch.float64)
    gen = torch.Generator().manual_seed(0)
    a = (0.1 + 0.5 * torch.rand(6, 6, generator=gen, dtype=torch.float64)).requires_grad_(True)
    d = torch.rand(1, 12, 12, generator=gen, dtype=torch.float64).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, d: renderer.render(a, d), (a, d), eps=1e-6,
                                    atol=1e-6, rtol=1e-4, fast_mode=fast)


def test_float32_matches_float64():
    rng = np.random.default_rng(0)
    scene = make_scene(thickness=0.3, axis="chief_ray")
    a = rng.uniform(0, 0.5, (12, 12))
    display = rng.random((3, 60, 60))
    np.testing.assert_allclose(render(scene, a, display, dtype=torch.float32),
                               render(scene, a, display), atol=2e-5)


def test_chunking_does_not_change_the_view():
    rng = np.random.default_rng(0)
    scene = make_scene(thickness=0.3, axis="chief_ray")
    a = torch.as_tensor(rng.uniform(0, 0.5, (12, 12)))
    display = torch.as_tensor(rng.random((1, 60, 60)))
    whole = Renderer(scene, dtype=torch.float64).render(a, display)
    chunked = Renderer(scene, dtype=torch.float64, chunk_pairs=20_000).render(a, display)
    torch.testing.assert_close(whole, chunked)


def test_wrong_mask_shape_is_a_clear_error():
    scene = make_scene()
    with pytest.raises(ValueError, match="open_fraction has shape"):
        Renderer(scene).render(torch.zeros(5, 5), torch.zeros(1, 60, 60))


@pytest.mark.parametrize("focus", [None, 300.0])
def test_open_display_matches_the_reference(focus):
    """No plate: the defocused display, against the Monte Carlo tracer's plate=False."""
    rng = np.random.default_rng(5)
    scene = make_scene(pixels=(40, 40), size=12.0, view=(12, 12), focus=focus)
    display = np.kron(rng.random((1, 5, 5)), np.ones((8, 8)))
    eye = scene.eye
    ref = trace_view(display, (12.0, 12.0), np.zeros((12, 12)), scene.plate.pitch_mm,
                     scene.plate.gap_mm, 0.0, "straight", eye.pupil_mm, eye.eye_relief_mm,
                     eye.focus_mm, eye.fov_deg, eye.view_pixels, samples_per_pixel=4096,
                     plate=False)
    model = render_open(scene, torch.as_tensor(display), pupil_samples=256, subpixels=4).numpy()
    assert psnr(model, ref) >= 30.0


def test_narrow_plate_centre_hole_is_seen_centred():
    """A plate narrower than the pupil's footprint: the one open hole on the axis shows up
    centred in the view (the hole search must not slide off the plate)."""
    scene = make_scene(cells=(5, 5), pitch=0.3, pixels=(40, 40), size=8.0, view=(11, 11),
                       fov=(20.0, 20.0))
    a = np.zeros((5, 5))
    a[2, 2] = 0.3
    view = render(scene, a, np.ones((1, 40, 40)))[0]
    np.testing.assert_allclose(view, view[::-1, ::-1], atol=1e-12)
    assert view[5, 5] == pytest.approx(view.max(), rel=1e-9) and view.max() > 0


# -- displaced holes ----------------------------------------------------------------------------


def centroids(view: np.ndarray, scene: Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per channel of a view (C, ny, nx): centroid (tan x, tan y) and total."""
    vx, vy = scene.eye.view_directions()
    total = view.sum((1, 2))
    assert np.all(total > 0)
    return (view.sum(1) * vx).sum(1) / total, (view.sum(2) * vy).sum(1) / total, total


def render_offset(scene: Scene, a: np.ndarray, display: np.ndarray,
                  offsets: np.ndarray | None = None) -> np.ndarray:
    renderer = Renderer(scene, dtype=torch.float64, hole_offset_mm=offsets)
    return renderer.render(torch.as_tensor(a), torch.as_tensor(display)).numpy()


@pytest.mark.parametrize("offset", [(0.03, -0.02), (-0.6, 0.45)])
@pytest.mark.parametrize("thickness, axis", [(0.0, "straight"), (0.3, "chief_ray")])
@pytest.mark.usefixtures("one_torch_thread")
def test_displaced_pinhole_moves_its_image(offset, thickness, axis):
    """One hole displaced by d (x right, y up), also by more than a pitch: a display dot at x_d
    appears at tan = (x_d - x_h - d) / (gap + t / 2), within 0.1 view pixel."""
    cells, pixels, size = (40, 40), (400, 400), 10.0
    fov = (math.degrees(2 * math.atan(0.08)),) * 2
    row, col = 15, 26
    a = np.zeros((cells[1], cells[0]))
    a[row, col] = 0.05
    scene = make_scene(cells=cells, thickness=thickness, axis=axis, pixels=pixels, size=size,
                       view=(64, 64), fov=fov)
    xs, ys = scene.plate.cell_centres_mm()
    hx, hy = xs[col] + offset[0], ys[row] + offset[1]
    h = scene.pinhole_height_mm
    target_tan = (0.021, -0.013)
    dx, dy = scene.display.pixel_centres_mm()
    dcol = int(np.argmin(np.abs(dx - (hx + h * target_tan[0]))))
    drow = int(np.argmin(np.abs(dy - (hy + h * target_tan[1]))))
    display = np.zeros((1, *pixels))
    display[0, drow, dcol] = 1.0
    # The eye sees the displaced hole near target_tan; chief-ray axes aim at it.
    s_b = scene.plate_distance_mm
    eye = ((hx - target_tan[0] * s_b, hy - target_tan[1] * s_b),)
    scene = make_scene(cells=cells, thickness=thickness, axis=axis, pixels=pixels, size=size,
                       view=(64, 64), fov=fov, positions=eye)
    offsets = np.zeros((cells[1], cells[0], 2))
    offsets[row, col] = offset
    view = render_offset(scene, a, display, offsets)
    cx, cy, _ = centroids(view, scene)
    step = scene.eye.view_step
    assert abs(cx[0] - (dx[dcol] - hx) / h) < 0.1 * step[0]
    assert abs(cy[0] - (dy[drow] - hy) / h) < 0.1 * step[1]
    # The undisplaced hole shows the dot elsewhere or not at all: the test sees the offset.
    assert np.abs(render_offset(scene, a, display) - view).sum() > 0.5 * view.sum()


@pytest.mark.parametrize("axis", ["straight", "chief_ray"])
def test_zero_offsets_give_bit_identical_views(axis):
    rng = np.random.default_rng(4)
    scene = make_scene(thickness=0.3, axis=axis, positions=((0.0, 0.0), (0.7, -0.3)))
    a = torch.as_tensor(rng.uniform(0, 0.5, (12, 12)))
    display = torch.as_tensor(rng.random((2, 60, 60)))
    plain = Renderer(scene, dtype=torch.float64)
    zero = Renderer(scene, dtype=torch.float64, hole_offset_mm=np.zeros((12, 12, 2)))
    for position in (0, 1):
        assert torch.equal(plain.render(a, display, position), zero.render(a, display, position))


@pytest.mark.parametrize("offsets, message", [
    (np.zeros((12, 12)), "shape"),
    (np.zeros((12, 11, 2)), "shape"),
    (np.full((12, 12, 2), np.nan), "NaN"),
    (np.full((12, 12, 2), 4.0), "plate's size"),
])
def test_bad_hole_offsets_are_clear_errors(offsets, message):
    with pytest.raises(ValueError, match=f"hole_offset_mm.*{message}"):
        Renderer(make_scene(), hole_offset_mm=offsets)


@pytest.mark.usefixtures("one_torch_thread")
def test_raised_hole_looks_like_its_lateral_equivalent():
    """A hole raised by delta toward the eye (plate tilt) against the same hole at its height,
    displaced by e = (x_h - c) delta / (s_h - delta) (its central projection from the eye):
    a dot at the centre of what the hole shows lands within 0.1 view pixel, one a quarter of
    the hole's visible range away within the first-order bound delta |v - v_chief| / h; on a
    white display the light agrees within 1 % and its centroid within delta R / s_h^2 (R: pupil
    radius; the edge of the range where the pupil sees the hole moves by delta |v - v_chief| /
    s_h). Without e the first dot is more than a view pixel off."""
    delta, gap, relief, pitch, thickness = 0.05, 10.0, 10.0, 0.25, 0.2
    cells = (80, 9)
    row, col = 4, 70
    view = (600, 2)  # a strip: fine view pixels (0.0012 in tan) along x
    fov = (math.degrees(2 * math.atan(0.36)), math.degrees(2 * math.atan(0.01)))
    display = Display(24.0, 2.0, (960, 80))
    xs, _ = Plate(cells, (pitch, pitch), gap, thickness).cell_centres_mm()
    hx = xs[col]
    s_h, h = relief + thickness / 2, gap + thickness / 2
    v_chief = 0.3
    eye_xy = (hx - v_chief * s_h, 0.0)

    def scene(gap_mm: float, relief_mm: float) -> Scene:
        return Scene(display, Plate(cells, (pitch, pitch), gap_mm, thickness),
                     Eye(4.0, relief_mm, fov, view, None, (eye_xy,), (1.0,)))

    raised, level = scene(gap + delta, relief - delta), scene(gap, relief)
    a = np.zeros((cells[1], cells[0]))
    a[row, col] = 0.3  # wide enough that the wall clips only the far end of its range
    offsets = np.zeros((cells[1], cells[0], 2))
    offsets[row, col, 0] = (hx - eye_xy[0]) * delta / (s_h - delta)
    dx, _ = display.pixel_centres_mm()
    dots = (v_chief, v_chief - 0.1)
    content = np.zeros((3, 80, 960))
    for k, v_dot in enumerate(dots):
        content[k, 40, int(np.argmin(np.abs(dx - (hx + (h + delta) * v_dot))))] = 1.0
    content[2] = 1.0
    up_x, _, up_total = centroids(render_offset(raised, a, content), raised)
    eq_x, _, eq_total = centroids(render_offset(level, a, content, offsets), level)
    flat_x, _, _ = centroids(render_offset(level, a, content), level)
    step = level.eye.view_step[0]
    assert abs(up_x[0] - eq_x[0]) < 0.1 * step
    assert abs(up_x[1] - eq_x[1]) < delta * abs(dots[1] - v_chief) / h + 0.1 * step
    assert abs(up_x[2] - eq_x[2]) < delta * raised.eye.pupil_mm / 2 / s_h**2
    assert eq_total[2] == pytest.approx(up_total[2], rel=0.01)
    assert abs(up_x[0] - flat_x[0]) > step
