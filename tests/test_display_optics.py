"""Display-side optics (issue 11 item 2): cover glass, RGB sub-pixel stripes, angular emission
falloff. Analytic cases, the fused kernels against the torch path, the Monte Carlo reference
(tests/reference_tracer.py, refracting each ray exactly), and the config keys."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from reference_tracer import trace_view
from test_kernels import BATCHES, states, views_and_grads
from test_model import make_scene, psnr, render

from aperture_fab.config.config import parse_toml, resolve
from aperture_fab.config.written import to_dict, to_toml
from aperture_fab.optics.model import Renderer
from aperture_fab.optics.open_view import render_open
from aperture_fab.optics.pair_table import display_optics_at
from aperture_fab.optics.scene import Display, Scene

#: The issue's example: 0.5 mm of n = 1.5 glass seen at 26 degrees.
GLASS_MM = 0.5
GLASS_INDEX = 1.5
ANGLE_DEG = 26.0
#: t_g (tan 26 deg - tan theta_g), sin 26 deg = 1.5 sin theta_g (theta_g = 16.99 deg).
SHIFT_26_MM = 0.09107200


def with_display(scene: Scene, **changes) -> Scene:
    return Scene(dataclasses.replace(scene.display, **changes), scene.plate, scene.eye)


def refracted_landing(x_mm: float, y_mm: float, tx: float, ty: float, glass_mm: float,
                      index: float) -> tuple[float, float]:
    """Where a ray of slopes (tx, ty) in air, straight on to (x, y) at z = 0, really meets the
    emitting surface under the glass: Snell with angles, independent of the model's form."""
    tan_air = math.hypot(tx, ty)
    if tan_air == 0:
        return x_mm, y_mm
    theta = math.atan(tan_air)
    theta_g = math.asin(math.sin(theta) / index)
    short = glass_mm * (tan_air - math.tan(theta_g))
    return x_mm - short * tx / tan_air, y_mm - short * ty / tan_air


def test_glass_shift_at_26_degrees_is_the_refraction_number():
    """The issue's number: 0.5 mm glass, n = 1.5, 26 deg: 0.0911 mm, as Snell gives it, and
    what the model moves a window by (torch path's formula)."""
    tan = math.tan(math.radians(ANGLE_DEG))
    x, _ = refracted_landing(0.0, 0.0, tan, 0.0, GLASS_MM, GLASS_INDEX)
    assert -x == pytest.approx(SHIFT_26_MM, abs=1e-7)
    scene = with_display(make_scene(), cover_glass_mm=GLASS_MM, cover_glass_index=GLASS_INDEX)
    renderer = Renderer(scene, dtype=torch.float64, backend="torch")
    gap = scene.plate.gap_mm
    lens = torch.zeros(1, dtype=torch.float64)
    wx, wy, emission = display_optics_at(renderer, lens + gap * tan, lens.clone(), lens, lens)
    assert gap * tan - float(wx) == pytest.approx(-x, abs=1e-12)
    assert float(wy) == 0.0 and emission is None


@pytest.mark.parametrize("backend", ["kernel", "torch"])
def test_single_pinhole_through_glass_maps_point_to_refracted_direction(backend):
    """A bright display dot seen through one hole at about 26 deg appears where the ray that
    refracts at the glass lands on it: within 0.1 view pixel, and 3.8 view pixels away from
    where a model without the glass would put it."""
    cells, pitch, gap, relief = (16, 16), 0.25, 10.0, 10.0
    hole_row, hole_col = 7, 3
    pixels = 800  # 25 um display pixels over 20 mm
    view = (420, 16)
    fov = (math.degrees(2 * math.atan(0.5)), math.degrees(2 * math.atan(0.02)))
    base = make_scene(cells=cells, pitch=pitch, gap=gap, relief=relief, pixels=(pixels, pixels),
                      size=20.0, view=view, fov=fov)
    xs, ys = base.plate.cell_centres_mm()
    hx, hy = float(xs[hole_col]), float(ys[hole_row])
    tan = math.tan(math.radians(ANGLE_DEG))
    dx, dy = base.display.pixel_centres_mm()
    col = int(np.argmin(np.abs(dx - (hx + gap * tan - SHIFT_26_MM))))
    row = int(np.argmin(np.abs(dy - hy)))
    # The direction whose refracted ray through the hole lands on the dot's centre (Newton on
    # the exact landing point; the plate is thin, so the hole is at height gap).
    t = np.array([(dx[col] - hx) / gap, (dy[row] - hy) / gap])
    for _ in range(30):
        def miss(tt):
            land = refracted_landing(hx + gap * tt[0], hy + gap * tt[1], tt[0], tt[1], GLASS_MM,
                                     GLASS_INDEX)
            return np.array(land) - (dx[col], dy[row])
        h = 1e-7
        jac = np.stack([(miss(t + h * e) - miss(t - h * e)) / (2 * h) for e in np.eye(2)], 1)
        t = t - np.linalg.solve(jac, miss(t))
    # Put the eye where its chief ray through the hole has that direction.
    eye_at = ((hx - relief * t[0], hy - relief * t[1]),)
    scene = make_scene(cells=cells, pitch=pitch, gap=gap, relief=relief,
                       pixels=(pixels, pixels), size=20.0, view=view, fov=fov, positions=eye_at)
    scene = with_display(scene, cover_glass_mm=GLASS_MM, cover_glass_index=GLASS_INDEX)
    a = np.zeros((cells[1], cells[0]))
    a[hole_row, hole_col] = 0.05
    display = np.zeros((1, pixels, pixels))
    display[0, row, col] = 1.0
    renderer = Renderer(scene, dtype=torch.float64, backend=backend)
    img = renderer.render(torch.as_tensor(a), torch.as_tensor(display)).numpy()[0]
    vx, vy = scene.eye.view_directions()
    total = img.sum()
    assert total > 0
    cx = float((img.sum(0) * vx).sum() / total)
    cy = float((img.sum(1) * vy).sum() / total)
    step = scene.eye.view_step
    assert abs(cx - t[0]) < 0.1 * step[0]
    assert abs(cy - t[1]) < 0.1 * step[1]
    without_glass = (dx[col] - hx) / gap
    assert abs(cx - without_glass) > 3.5 * step[0]


def pinhole_centroids(subpixels: str, channels: int = 3) -> np.ndarray:
    """Centroids (C,) in tan x of one lit pixel (all channels) seen through one hole."""
    cells, pixels = (16, 16), 800
    scene = make_scene(cells=cells, pitch=0.25, pixels=(pixels, pixels), size=20.0,
                       view=(96, 16), fov=(math.degrees(2 * math.atan(0.03)),
                                           math.degrees(2 * math.atan(0.03))),
                       positions=((-0.125, 0.125),))
    scene = with_display(scene, subpixels=subpixels)
    a = np.zeros(cells[::-1])
    a[7, 7] = 0.5  # a wide hole (0.2 mm): a smooth window over several display pixels
    dx, dy = scene.display.pixel_centres_mm()
    display = np.zeros((channels, pixels, pixels))  # one pixel lit, seen through the hole
    display[:, int(np.argmin(np.abs(dy - 0.125))), int(np.argmin(np.abs(dx + 0.125)))] = 1.0
    img = render(scene, a, display)
    vx, _ = scene.eye.view_directions()
    profile = img.sum(1)  # (C, nx)
    return (profile * vx).sum(1) / profile.sum(1)


def test_subpixel_stripes_move_each_channel_by_a_third_of_a_pixel():
    """rgb_stripe: red's image moves left, blue's right, by a third of a pixel's angle
    (pixel / 3 / h) against green's; bgr_stripe mirrors it; 'none' keeps them together. The
    stack's kernels carry the offset exactly; sampling them at pixel centres costs up to 3 %
    of it (0.01 pixel) for this 0.2 mm hole (docs/model.md)."""
    third = 20.0 / 800 / 3 / 10.0  # tan
    plain = pinhole_centroids("none")
    np.testing.assert_allclose(plain - plain[1], 0.0, atol=1e-12)
    rgb = pinhole_centroids("rgb_stripe")
    np.testing.assert_allclose(rgb - rgb[1], [-third, 0.0, third], atol=0.04 * third)
    assert rgb[1] == pytest.approx(plain[1], abs=1e-12)
    bgr = pinhole_centroids("bgr_stripe")
    np.testing.assert_allclose(bgr - bgr[1], [third, 0.0, -third], atol=0.04 * third)


def test_grey_display_ignores_subpixels():
    """A one-channel display drives the three stripes alike, which fill the pixel: unchanged."""
    np.testing.assert_array_equal(pinhole_centroids("rgb_stripe", channels=1),
                                  pinhole_centroids("none", channels=1))


def test_subpixels_need_one_or_three_channels():
    scene = with_display(make_scene(), subpixels="rgb_stripe")
    renderer = Renderer(scene, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"display.subpixels = 'rgb_stripe' needs an RGB"):
        renderer.display_stack(torch.zeros(2, 60, 60, dtype=torch.float64))


@pytest.mark.parametrize("k", [1.0, 4.0])
@pytest.mark.parametrize("backend", ["kernel", "torch"])
def test_falloff_dims_a_centred_pinhole_by_cos_power(k, backend):
    """Uniform display, one centred hole (thin plate, infinite focus): the light through it seen
    from an eye placed so it is seen at 20 deg is cos^k(20 deg) of the light seen on axis. A
    small pupil (0.3 mm) keeps the directions that see the hole within 0.015 of tan 20 deg."""
    cells = (9, 9)
    a = np.zeros(cells)
    a[4, 4] = 0.3
    white = np.ones((1, 400, 400))
    tan = math.tan(math.radians(20.0))
    light = []
    for eye_x in (0.0, -10.0 * tan):
        scene = make_scene(cells=cells, pitch=0.25, pixels=(400, 400), size=20.0, view=(200, 8),
                           fov=(2 * math.degrees(math.atan(0.45)), 4.0), pupil=0.3,
                           positions=((eye_x, 0.0),))
        scene = with_display(scene, emission="cosine_power", emission_exponent=k)
        renderer = Renderer(scene, dtype=torch.float64, backend=backend)
        light.append(float(renderer.render(torch.as_tensor(a), torch.as_tensor(white)).sum()))
    assert light[1] / light[0] == pytest.approx(math.cos(math.radians(20.0)) ** k, rel=2e-3)


def test_falloff_is_cos_power_of_the_view_direction():
    """Uniform display behind a plate of equal holes: each view pixel dims by (1 + |v|^2)^(-k/2)
    against the Lambertian view, and so does the open display's view."""
    k = 3.0
    scene = make_scene(cells=(120, 120), pitch=0.25, pixels=(100, 100), size=30.0, view=(16, 16),
                       fov=(50.0, 50.0))
    dim = with_display(scene, emission="cosine_power", emission_exponent=k)
    white = np.ones((1, 100, 100))
    a = np.full((120, 120), 0.3)
    vx, vy = scene.eye.view_directions()
    cos_k = (1 + vx[None, :] ** 2 + vy[:, None] ** 2) ** (-k / 2)
    ratio = render(dim, a, white)[0] / render(scene, a, white)[0]
    np.testing.assert_allclose(ratio, cos_k, rtol=1e-9)
    white_t = torch.as_tensor(white)
    open_ratio = (render_open(dim, white_t) / render_open(scene, white_t)).numpy()[0]
    np.testing.assert_allclose(open_ratio, cos_k, rtol=0.01)


def test_index_one_glass_changes_nothing():
    """Glass of index 1 does not refract: the same view as no glass (within rounding), in the
    model and in the open display's view."""
    rng = np.random.default_rng(2)
    scene = make_scene(thickness=0.2, axis="chief_ray")
    air = with_display(scene, cover_glass_mm=2.0, cover_glass_index=1.0)
    a, display = rng.uniform(0, 0.6, (12, 12)), rng.random((3, 60, 60))
    np.testing.assert_allclose(render(air, a, display), render(scene, a, display), rtol=1e-12,
                               atol=1e-15)
    d = torch.as_tensor(display)
    torch.testing.assert_close(render_open(air, d), render_open(scene, d), rtol=1e-9, atol=1e-12)


def test_open_view_through_glass_moves_by_the_refraction_shift():
    """The open display's view through glass (per ray): an edge at x_e appears where the
    refracted ray lands on it, not where the straight one would."""
    n = 200
    scene = make_scene(pixels=(n, n), size=20.0, view=(400, 4), focus=None, pupil=0.5,
                       fov=(2 * math.degrees(math.atan(0.6)), 1.0))
    glass = with_display(scene, cover_glass_mm=GLASS_MM, cover_glass_index=GLASS_INDEX)
    display = np.zeros((1, n, n))
    display[:, :, 150:] = 1.0  # an edge at x = 5 mm
    view = render_open(glass, torch.as_tensor(display), pupil_samples=64).numpy()[0].mean(0)
    vx, _ = scene.eye.view_directions()
    j = int(np.argmax(view >= 0.5))  # the view rises through 0.5 at the edge
    share = (0.5 - view[j - 1]) / (view[j] - view[j - 1])
    crossing = float(vx[j - 1] + share * (vx[j] - vx[j - 1]))
    s_d = scene.display_distance_mm
    land, _ = refracted_landing(s_d * crossing, 0.0, crossing, 0.0, GLASS_MM, GLASS_INDEX)
    assert land == pytest.approx(5.0, abs=0.2 * scene.eye.view_step[0] * s_d)


# -- the kernels against the torch path --------------------------------------------------------


FEATURES = {
    "glass": {"cover_glass_mm": 0.7, "cover_glass_index": 1.6},
    "subpixels": {"subpixels": "bgr_stripe"},
    "falloff": {"emission": "cosine_power", "emission_exponent": 2.5},
    "all": {"cover_glass_mm": 0.5, "subpixels": "rgb_stripe", "emission": "cosine_power",
            "emission_exponent": 4.0},
}
CASES = {
    "thin straight": {},
    "thick chief-ray": {"thickness": 0.3, "axis": "chief_ray"},
    "thick straight, finite focus": {"thickness": 0.2, "focus": 500.0},
}


@pytest.mark.parametrize("batch_name", list(BATCHES))
@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("feature", list(FEATURES))
def test_kernels_match_the_torch_path_with_display_optics(feature, case, batch_name):
    """Same views and gradients (radii and display) from both backends, float64, each display
    feature on, for states that share their samples and states that do not."""
    rng = np.random.default_rng(8)
    scene = with_display(make_scene(**CASES[case]), **FEATURES[feature])
    batch = states(*BATCHES[batch_name])
    a = rng.uniform(0, 0.6, (12, 12))
    display = rng.random((3, 60, 60))
    weight = rng.random((len(batch), 3, 32, 32))
    got = views_and_grads(Renderer(scene, dtype=torch.float64, backend="kernel"), a, display,
                          batch, weight)
    want = views_and_grads(Renderer(scene, dtype=torch.float64, backend="torch"), a, display,
                           batch, weight)
    plain = views_and_grads(Renderer(make_scene(**CASES[case]), dtype=torch.float64,
                                     backend="torch"), a, display, batch, weight)
    assert float((want[0] - plain[0]).abs().max()) > 1e-3 * float(want[0].abs().max())
    for g, w in zip(got, want, strict=True):
        # atol: the torch path pads with closed cells of radius 1e-6 (area ~3e-12).
        torch.testing.assert_close(g, w, rtol=1e-7, atol=1e-9 * float(w.abs().max()))


def test_gradcheck_with_display_optics():
    """The hand-written backward (kernel path) against numerical gradients, every feature on,
    finite focus (the chief ray's slope varies with the lens)."""
    rng = np.random.default_rng(5)
    scene = with_display(make_scene(cells=(6, 6), pixels=(24, 24), size=6.0, view=(8, 8),
                                    thickness=0.2, focus=300.0), **FEATURES["all"])
    renderer = Renderer(scene, dtype=torch.float64)
    a = torch.as_tensor(rng.uniform(0.1, 0.6, (6, 6))).requires_grad_(True)
    display = torch.as_tensor(rng.random((3, 24, 24))).requires_grad_(True)
    probe = torch.as_tensor(rng.random((3, 8, 8)))

    def loss(a_, d_):
        return (renderer.render(a_, d_) * probe).sum()

    assert torch.autograd.gradcheck(loss, (a, display), eps=1e-6, atol=1e-6, rtol=1e-4,
                                    fast_mode=True)


# -- the Monte Carlo reference -----------------------------------------------------------------


def reference(scene: Scene, a: np.ndarray, display: np.ndarray, samples: int,
              seed: int = 0) -> np.ndarray:
    plate, eye, disp = scene.plate, scene.eye, scene.display
    radii = np.sqrt(a * plate.pitch_mm[0] * plate.pitch_mm[1] / math.pi)
    return trace_view(display, (disp.width_mm, disp.height_mm), radii, plate.pitch_mm,
                      plate.gap_mm, plate.thickness_mm, plate.hole_axis, eye.pupil_mm,
                      eye.eye_relief_mm, eye.focus_mm, eye.fov_deg, eye.view_pixels,
                      eye_position_mm=eye.positions_mm[0], tilt_target_mm=eye.positions_mm[0],
                      samples_per_pixel=samples, seed=seed,
                      cover_glass_mm=disp.cover_glass_mm,
                      cover_glass_index=disp.cover_glass_index, subpixels=disp.subpixels,
                      emission_exponent=disp.emission_power)


def test_reference_agrees_with_glass_on_a_quick_case():
    """Fast: thick glass and falloff on, against the per-ray reference, and they visibly
    matter (the model without them is far worse). Sub-pixel stripes triple the reference's
    noise; the slow comparison checks them with more rays."""
    rng = np.random.default_rng(3)
    base = make_scene(cells=(24, 24), pitch=0.3, pixels=(48, 48), size=7.2, view=(10, 10),
                      thickness=0.2, axis="chief_ray")
    scene = with_display(base, cover_glass_mm=3.0, cover_glass_index=1.5,
                         emission="cosine_power", emission_exponent=4.0)
    a = rng.uniform(0.02, 0.6, size=(24, 24))
    display = np.kron(rng.random((3, 6, 6)), np.ones((8, 8)))
    ref = reference(scene, a, display, samples=4096)
    assert psnr(render(scene, a, display), ref) >= 30.0
    # The reference's own noise (about 34 dB here) caps both; the model without the glass and
    # falloff is 1.8 dB further off (seeded, so the margin is fixed).
    assert psnr(render(base, a, display), ref) < psnr(render(scene, a, display), ref) - 1.5


MC_CASES = {
    "glass thick chief-ray": (dict(thickness=0.3, axis="chief_ray"), FEATURES["glass"]),
    "glass finite focus": (dict(thickness=0.2, focus=300.0), {"cover_glass_mm": 1.0}),
    "glass offset eye": (dict(thickness=0.2, axis="chief_ray", positions=((1.0, -0.5),)),
                         {"cover_glass_mm": 0.5}),
    "subpixels": (dict(thickness=0.3, axis="chief_ray"), FEATURES["subpixels"]),
    "falloff": (dict(thickness=0.3, axis="chief_ray"), FEATURES["falloff"]),
    "all": (dict(thickness=0.2, focus=300.0), FEATURES["all"]),
}
#: Rays per view pixel: stripes lit at 3 times the value on a third of the area triple the
#: reference's variance, so they get 4 times the rays.
MC_SAMPLES = 16384
MC_STRIPE_SAMPLES = 65536


@pytest.mark.slow
@pytest.mark.parametrize("case", list(MC_CASES))
def test_model_matches_monte_carlo_reference_with_display_optics(case):
    """As test_model's Monte Carlo comparison (random holes, 8-pixel blocks), display optics on:
    PSNR >= 35 dB."""
    rng = np.random.default_rng(7)
    geometry, optics = MC_CASES[case]
    scene = with_display(make_scene(cells=(40, 40), pitch=0.3, pixels=(120, 120), size=12.0,
                                    view=(24, 24), **geometry), **optics)
    radii_share = rng.choice([0.0, 0.1, 0.25, 0.4, 0.5], size=(40, 40))
    a = math.pi * (radii_share * 0.3) ** 2 / 0.3**2
    display = np.kron(rng.random((3, 15, 15)), np.ones((8, 8)))
    samples = MC_SAMPLES if scene.display.subpixels == "none" else MC_STRIPE_SAMPLES
    assert psnr(render(scene, a, display), reference(scene, a, display, samples)) >= 35.0


# -- scene and config ----------------------------------------------------------------------------


def test_defaults_are_off():
    display = Display(20.0, 20.0, (400, 400))
    assert (display.cover_glass_mm, display.subpixels, display.emission_power) == (0.0, "none", 0)
    assert not display.has_optics
    assert not resolve().scene.display.has_optics


@pytest.mark.parametrize("changes, words", [
    ({"cover_glass_mm": -0.1}, ["display.cover_glass_mm = -0.1", "0 to 10"]),
    ({"cover_glass_index": 3.0}, ["display.cover_glass_index = 3.0", "1 to 2.5"]),
    ({"subpixels": "pentile"}, ["display.subpixels = 'pentile'", "rgb_stripe"]),
    ({"emission": "cos"}, ["display.emission = 'cos'", "cosine_power"]),
    ({"emission_exponent": -1.0}, ["display.emission_exponent = -1.0", "0 to 100"]),
])
def test_display_rejects_bad_optics(changes, words):
    with pytest.raises(ValueError) as err:
        Display(20.0, 20.0, (400, 400), **changes)
    for word in words:
        assert word in str(err.value)


def test_glass_must_fit_in_the_gap():
    with pytest.raises(ValueError, match=r"display.cover_glass_mm = 10 is not less than "
                                         r"plate.gap_mm = 10.*inside the gap"):
        resolve(overrides={"display.cover_glass_mm": 10.0})


def test_config_keys_round_trip_and_are_written_when_off():
    plain = to_dict(resolve())
    assert plain["display"]["cover_glass_mm"] == 0.0  # every value explicit
    config = resolve(file_dict=parse_toml(
        '[display]\ncover_glass_mm = 0.5\ncover_glass_index = 1.52\nsubpixels = "rgb_stripe"\n'
        'emission = "cosine_power"\nemission_exponent = 2\n', "x"))
    display = config.scene.display
    assert (display.cover_glass_mm, display.cover_glass_index, display.subpixels,
            display.emission, display.emission_exponent) == (
        0.5, 1.52, "rgb_stripe", "cosine_power", 2.0)
    assert resolve(file_dict=parse_toml(to_toml(config), "y")) == config


def test_config_names_the_key_of_a_wrong_type():
    with pytest.raises(TypeError, match=r"display.subpixels = 3 .* one of none, rgb_stripe"):
        resolve(overrides={"display.subpixels": 3})


# -- the mesh re-trace -----------------------------------------------------------------------------


@pytest.mark.parametrize("optics, samples, min_psnr_db", [
    ({"cover_glass_mm": 1.0, "emission": "cosine_power", "emission_exponent": 2.0}, 64, 41.0),
    ({"subpixels": "rgb_stripe"}, 256, 38.0),  # stripes triple the noise: more rays
])
def test_mesh_retrace_applies_display_optics_per_ray(optics, samples, min_psnr_db):
    """The re-trace of the written mesh (glass refracted, stripes and falloff per ray) agrees
    with the model with the same display optics (43.8 and 39.8 dB measured), and the glass and
    falloff case not with the model without them (39.7 dB)."""
    from test_retrace import model_view, random_case, written_mesh
    from test_retrace import psnr as psnr_retrace

    from aperture_fab.validation.retrace import trace_mesh_view

    base, part, a, display = random_case("chief_ray")
    scene = with_display(base, **optics)
    traced = trace_mesh_view(written_mesh(part), scene, display, samples_per_pixel=samples,
                             seed=3)
    with_optics = psnr_retrace(traced.view, model_view(scene, a, display))
    assert with_optics >= min_psnr_db
    if "cover_glass_mm" in optics:
        assert psnr_retrace(traced.view, model_view(base, a, display)) < with_optics - 3.0


def test_elemental_images_follow_the_glass():
    """The regular pinholes' display content under glass: each display pixel shows the target
    at the direction from which the eye really sees it (the refracted ray through its hole)."""
    from aperture_fab.optics.baselines import _through_glass

    display = Display(20.0, 20.0, (400, 400), cover_glass_mm=GLASS_MM,
                      cover_glass_index=GLASS_INDEX)
    tan = math.tan(math.radians(ANGLE_DEG))
    h = 10.0
    land, _ = refracted_landing(h * tan, 0.0, tan, 0.0, GLASS_MM, GLASS_INDEX)
    dx = np.array([land])  # the dot a ray at 26 deg through a hole at 0 lands on
    vx, vy = _through_glass(display, dx, np.zeros(1), h, dx / h, np.zeros(1))
    assert float(vx[0]) == pytest.approx(tan, abs=1e-7) and float(vy[0]) == 0.0
