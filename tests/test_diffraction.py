"""Checks of the diffraction-aware view against independent calculations: the Airy pattern from
scipy's Bessel functions (the module uses torch's), its encircled energy 1 - J0^2 - J1^2, direct
convolution by torch's conv2d (the module convolves by FFT), and second moments of pinhole spots
against the continuous truncated Airy pattern's variance."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import optimize, special

from aperture_fab.optics.diffraction import (
    AIRY_FIRST_ZERO_X,
    KERNEL_ENERGY,
    WAVELENGTHS_NM,
    airy_blur_px,
    airy_kernel,
    diffraction_view,
    hole_classes,
)
from aperture_fab.optics.model import Renderer
from aperture_fab.optics.scene import Display, Eye, Plate, Scene

pytestmark = pytest.mark.usefixtures("one_torch_thread")

GREEN_MM = 530e-6
RED_MM, BLUE_MM = 630e-6, 460e-6


def encircled_energy(x: float) -> float:
    return float(1 - special.j0(x) ** 2 - special.j1(x) ** 2)


def airy(x: np.ndarray | float) -> np.ndarray:
    x = np.maximum(np.asarray(x, dtype=np.float64), 1e-12)
    return (2 * special.j1(x) / x) ** 2


#: x within which the Airy pattern holds KERNEL_ENERGY of its light, by root finding.
X_TRUNC = optimize.brentq(lambda x: encircled_energy(x) - KERNEL_ENERGY, 50.0, 400.0)


def truncated_variance_x2() -> float:
    """Per-axis variance (x units squared) of the Airy pattern truncated at X_TRUNC."""
    x = np.linspace(0, X_TRUNC, 400_001)
    weight = airy(x) * x
    return 0.5 * float(np.trapezoid(x**2 * weight, x) / np.trapezoid(weight, x))


def make_scene(*, cells: int = 15, pitch: float = 0.25, pixels: int = 201, size: float = 4.02,
               view: int = 81, step: float = 0.012, pupil: float = 2.0) -> Scene:
    """A small thin plate 10 mm over the display, the eye 10 mm above it, a view of `view` pixels
    of `step` tan each. The plate is wider than the pupil's footprint on it plus two cells: on a
    narrower plate the model's hole search window is clamped in size but not in position and
    misses holes."""
    fov = math.degrees(2 * math.atan(view * step / 2))
    return Scene(Display(size, size, (pixels, pixels)),
                 Plate((cells, cells), (pitch, pitch), 10.0, 0.0),
                 Eye(pupil, 10.0, (fov, fov), (view, view)))


def fraction(diameter_mm: float, pitch_mm: float = 0.25) -> float:
    return math.pi * (diameter_mm / 2) ** 2 / pitch_mm**2


def spot_moments(img: np.ndarray) -> tuple[float, float, float]:
    """Total, and per-axis variance (pixels squared) about the centroid, of a (ny, nx) image."""
    total = float(img.sum())
    y, x = np.indices(img.shape)
    cx, cy = (img * x).sum() / total, (img * y).sum() / total
    return total, float((img * (x - cx) ** 2).sum() / total), \
        float((img * (y - cy) ** 2).sum() / total)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return 10 * math.log10(float(np.abs(b).max()) ** 2 / float(np.mean((a - b) ** 2)))


@pytest.fixture(scope="module")
def spot_renderer() -> Renderer:
    return Renderer(make_scene(), dtype=torch.float64)


def pinhole_spot(renderer: Renderer, diameter_mm: float, channels: int = 3
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Geometric and diffraction views of a one-pixel white dot under the centre hole: the spot
    falls on the centre view pixel."""
    cells = renderer.scene.plate.cells[0]
    a = torch.zeros(cells, cells, dtype=torch.float64)
    a[cells // 2, cells // 2] = fraction(diameter_mm)
    n = renderer.scene.display.pixels[0]
    display = torch.zeros(channels, n, n, dtype=torch.float64)
    display[:, n // 2, n // 2] = 1.0
    return (renderer.render(a, display).numpy(),
            diffraction_view(renderer, a, display).numpy())


# -- the kernel ---------------------------------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(diameter_mm=st.floats(0.01, 1.0), wavelength_nm=st.floats(400.0, 700.0),
       step_x=st.floats(0.002, 0.03), aspect=st.floats(0.5, 2.0),
       cap=st.integers(0, 20))
def test_kernel_is_normalized_symmetric_and_peaked(diameter_mm, wavelength_nm, step_x, aspect,
                                                   cap):
    kernel = airy_kernel(diameter_mm, wavelength_nm * 1e-6, (step_x, step_x * aspect), cap)
    ky, kx = (s // 2 for s in kernel.shape)
    assert kernel.shape[0] % 2 == 1 and kernel.shape[1] % 2 == 1
    assert max(kx, ky) <= cap
    assert kernel.sum() == pytest.approx(1.0, abs=1e-12)
    assert kernel.min() >= 0
    np.testing.assert_allclose(kernel, kernel[::-1, :], atol=1e-15)
    np.testing.assert_allclose(kernel, kernel[:, ::-1], atol=1e-15)
    assert kernel[ky, kx] == kernel.max()


def test_kernel_profile_matches_airy_pattern():
    """First dark ring 8 pixels out: pixel values follow [2 J1(x)/x]^2 integrated over the pixel
    (fine independent quadrature), and its value at the pixel centre."""
    step = 1e-3
    diameter = AIRY_FIRST_ZERO_X / math.pi * GREEN_MM / (8 * step)
    kernel = airy_kernel(diameter, GREEN_MM, (step, step), max_radius_px=40)
    c = kernel.shape[0] // 2
    scale = math.pi * diameter / GREEN_MM * step  # x per pixel
    fine = (np.arange(64) + 0.5) / 64 - 0.5

    def pixel_integral(i: int, j: int) -> float:
        yy, xx = np.meshgrid(j + fine, i + fine, indexing="ij")
        return float(airy(scale * np.hypot(xx, yy)).mean())

    centre = pixel_integral(0, 0)
    for i, j in [(0, 2), (3, 0), (4, 4), (0, 6), (11, 0), (7, 8)]:
        expected = pixel_integral(i, j) / centre
        assert kernel[c + j, c + i] / kernel[c, c] == pytest.approx(expected, rel=0.01, abs=1e-5)
        point = float(airy(scale * math.hypot(i, j)))
        assert kernel[c + j, c + i] / kernel[c, c] == pytest.approx(point, rel=0.05, abs=2e-4)


def test_first_dark_ring_radius():
    """airy_blur_px is 1.22 lambda / d in pixels, and the kernel's profile along a row has its
    first minimum there."""
    zero_x = special.jn_zeros(1, 1)[0]
    step = 1e-3
    for diameter, wavelength in [(0.05, GREEN_MM), (0.08, RED_MM), (0.03, BLUE_MM)]:
        expected = zero_x / math.pi * wavelength / diameter / step
        assert airy_blur_px(diameter, wavelength, (step, step)) == pytest.approx(expected,
                                                                                 rel=1e-9)
        kernel = airy_kernel(diameter, wavelength, (step, step), max_radius_px=60)
        c = kernel.shape[0] // 2
        row = kernel[c, c:]
        first_min = int(np.argmin(row[: int(1.5 * expected)]))
        assert abs(first_min - expected) <= 0.6
    # Anisotropic pixels: the geometric-mean pixel size.
    assert airy_blur_px(0.05, GREEN_MM, (1e-3, 4e-3)) == pytest.approx(
        zero_x / math.pi * GREEN_MM / 0.05 / 2e-3, rel=1e-9)


def test_encircled_energy_of_first_ring():
    """83.8 % of the light lies inside the first dark ring (of what the kernel keeps)."""
    step = 1e-3
    diameter = AIRY_FIRST_ZERO_X / math.pi * GREEN_MM / (8 * step)
    kernel = airy_kernel(diameter, GREEN_MM, (step, step))
    c = kernel.shape[0] // 2
    y, x = np.indices(kernel.shape)
    inside = kernel[np.hypot(x - c, y - c) <= 8.0].sum()
    first_ring = encircled_energy(special.jn_zeros(1, 1)[0])
    assert first_ring == pytest.approx(0.838, abs=5e-4)
    assert inside == pytest.approx(first_ring / KERNEL_ENERGY, rel=0.01)


def test_kernel_reaches_the_truncation_radius():
    """Untruncated by max_radius_px, the kernel reaches where the encircled energy is 99.5 %."""
    step = 2e-3
    for diameter in (0.04, 0.1):
        reach_px = X_TRUNC * GREEN_MM / (math.pi * diameter) / step
        kernel = airy_kernel(diameter, GREEN_MM, (step, step))
        assert kernel.shape[0] // 2 == math.ceil(reach_px - 0.5)


def test_large_hole_kernel_is_a_single_pixel():
    assert airy_kernel(5.0, GREEN_MM, (0.01, 0.01)).tolist() == [[1.0]]


@pytest.mark.parametrize("kwargs, field", [
    (dict(diameter_mm=-0.1), "diameter_mm"),
    (dict(wavelength_mm=0.0), "wavelength_mm"),
    (dict(view_step=(0.01, -0.01)), "view_step"),
    (dict(max_radius_px=-1), "max_radius_px"),
])
def test_kernel_rejects_bad_arguments(kwargs, field):
    args = dict(diameter_mm=0.1, wavelength_mm=GREEN_MM, view_step=(0.01, 0.01)) | kwargs
    with pytest.raises(ValueError, match=field):
        airy_kernel(**args)


# -- classes ------------------------------------------------------------------------------------


def test_quantized_layout_has_one_class_per_size():
    rng = np.random.default_rng(0)
    diameters = np.array([0.0, 0.1, 0.16, 0.2])
    choice = rng.integers(0, 4, size=(9, 11))
    a = torch.as_tensor(math.pi * (diameters[choice] / 2) ** 2 / 0.25**2)
    classes = hole_classes(a, (0.25, 0.25))
    assert [c.diameter_mm for c in classes] == pytest.approx([0.1, 0.16, 0.2], rel=1e-12)
    for k, group in enumerate(classes, start=1):
        np.testing.assert_array_equal(group.mask.numpy(), choice == k)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31), max_classes=st.integers(1, 12))
def test_binned_classes_partition_the_open_holes(seed, max_classes):
    rng = np.random.default_rng(seed)
    a = rng.uniform(0, 0.7, size=(12, 10)) ** 3  # many sizes, some tiny
    a[rng.random(a.shape) < 0.2] = 0.0
    d = 2 * np.sqrt(a * 0.3 * 0.2 / math.pi)
    classes = hole_classes(torch.as_tensor(a), (0.3, 0.2), max_classes)
    assert 1 <= len(classes) <= max_classes
    masks = np.stack([c.mask.numpy() for c in classes])
    np.testing.assert_array_equal(masks.sum(0), a > 0)  # each open hole in exactly one class
    for group in classes:
        members, weights = d[group.mask.numpy()], a[group.mask.numpy()]
        assert group.diameter_mm == pytest.approx(float((members * weights).sum()
                                                        / weights.sum()), rel=1e-9)
        assert members.min() * (1 - 1e-12) <= group.diameter_mm <= members.max() * (1 + 1e-12)
    assert [c.diameter_mm for c in classes] == sorted(c.diameter_mm for c in classes)


def test_closed_plate_has_no_classes_and_a_black_view(spot_renderer):
    assert hole_classes(torch.zeros(4, 4), (0.25, 0.25)) == []
    view = diffraction_view(spot_renderer, torch.zeros(15, 15, dtype=torch.float64),
                            torch.ones(1, 201, 201, dtype=torch.float64))
    assert view.shape == (1, 81, 81) and float(view.abs().max()) == 0.0


# -- the view -----------------------------------------------------------------------------------


@pytest.mark.parametrize("diameter", [0.05, 0.07])
def test_pinhole_spot_spreads_as_the_airy_pattern(spot_renderer, diameter):
    """A dot under one hole: the spot's second moment grows by the variance of the truncated Airy
    pattern, (lambda / (pi d))^2 times a constant, plus the pixel box's 1/12."""
    geometric, diffracted = pinhole_spot(spot_renderer, diameter)
    step = spot_renderer.scene.eye.view_step[0]
    for channel, wavelength in enumerate(np.array(WAVELENGTHS_NM) * 1e-6):
        total_g, gx, gy = spot_moments(geometric[channel])
        total_d, vx, vy = spot_moments(diffracted[channel])
        assert gx < 0.05  # the geometric spot sits within one view pixel
        expected = truncated_variance_x2() * (wavelength / (math.pi * diameter) / step) ** 2
        assert vx - gx == pytest.approx(expected + 1 / 12, rel=0.05)
        assert vy - gy == pytest.approx(expected + 1 / 12, rel=0.05)
        assert total_d == pytest.approx(total_g, rel=1e-3)


def test_spot_variance_scales_as_inverse_diameter_squared(spot_renderer):
    added = []
    for diameter in (0.05, 0.075):
        geometric, diffracted = pinhole_spot(spot_renderer, diameter, channels=1)
        added.append(spot_moments(diffracted[0])[1] - spot_moments(geometric[0])[1] - 1 / 12)
    assert added[0] / added[1] == pytest.approx(1.5**2, rel=0.05)


def test_red_spreads_more_than_blue(spot_renderer):
    geometric, diffracted = pinhole_spot(spot_renderer, 0.07)
    added = [spot_moments(diffracted[c])[1] - spot_moments(geometric[c])[1] - 1 / 12
             for c in range(3)]
    assert added[0] > added[1] > added[2] > 0
    assert added[0] / added[2] == pytest.approx((RED_MM / BLUE_MM) ** 2, rel=0.05)


@pytest.fixture(scope="module")
def array_scene() -> tuple[Renderer, torch.Tensor]:
    """A plate of 0.5 mm cells over a display of 2 mm blocks, coarse view pixels (0.025)."""
    view, step = 40, 0.025
    fov = math.degrees(2 * math.atan(view * step / 2))
    scene = Scene(Display(20.0, 20.0, (100, 100)), Plate((31, 31), (0.5, 0.5), 10.0, 0.0),
                  Eye(2.0, 10.0, (fov, fov), (view, view)))
    rng = np.random.default_rng(0)
    display = torch.as_tensor(np.kron(rng.random((3, 10, 10)), np.ones((10, 10))))
    return Renderer(scene, dtype=torch.float64), display


def test_large_holes_match_the_geometric_view_small_ones_blur(array_scene):
    renderer, display = array_scene
    scores = []
    for diameter in (0.5, 0.1, 0.015):
        a = torch.full((31, 31), fraction(diameter, 0.5), dtype=torch.float64)
        geometric = renderer.render(a, display).numpy()
        scores.append(psnr(diffraction_view(renderer, a, display).numpy(), geometric))
    assert scores[0] > 40.0  # first dark ring 0.06 view pixel across
    assert scores[2] < 30.0  # first dark ring 2 view pixels across
    assert scores[0] > scores[1] > scores[2]


def test_one_size_is_the_geometric_view_convolved(array_scene):
    """Equal holes: the view is the geometric view convolved with one kernel per channel, here by
    direct convolution (conv2d, zero padding)."""
    renderer, display = array_scene
    a = torch.full((31, 31), fraction(0.04, 0.5), dtype=torch.float64)
    geometric = renderer.render(a, display)
    view = diffraction_view(renderer, a, display)
    for channel, wavelength in enumerate(np.array(WAVELENGTHS_NM) * 1e-6):
        kernel = torch.as_tensor(airy_kernel(0.04, wavelength, renderer.scene.eye.view_step, 40))
        pad = (kernel.shape[0] // 2, kernel.shape[1] // 2)
        direct = F.conv2d(geometric[channel][None, None], kernel[None, None], padding=pad)[0, 0]
        torch.testing.assert_close(view[channel], direct, rtol=1e-9, atol=1e-12)


def test_light_is_conserved_away_from_the_border(spot_renderer):
    """Random hole sizes (binned into 4 classes), light only near the view's centre: the total is
    unchanged."""
    rng = np.random.default_rng(5)
    a = torch.as_tensor(fraction(0.25) * rng.uniform(0.32, 1.0, size=(15, 15)) ** 2)
    display = torch.zeros(3, 201, 201, dtype=torch.float64)
    display[:, 95:106, 95:106] = torch.as_tensor(rng.random((3, 11, 11)))
    geometric = spot_renderer.render(a, display)
    assert float(geometric[:, :5].sum() + geometric[:, -5:].sum()) == 0.0
    assert len(hole_classes(a, (0.25, 0.25), 4)) == 4
    view = diffraction_view(spot_renderer, a, display, max_classes=4)
    torch.testing.assert_close(view.sum((1, 2)), geometric.sum((1, 2)), rtol=1e-3, atol=0.0)
    assert float(view.min()) > -1e-12


def test_light_spread_past_the_border_is_lost(array_scene):
    """The documented loss: a view lit to its border loses what the kernels carry out of it."""
    renderer, display = array_scene
    a = torch.full((31, 31), fraction(0.02, 0.5), dtype=torch.float64)
    geometric = renderer.render(a, display)
    assert float(geometric[:, :, 0].sum()) > 0  # lit to the left edge
    ratio = float(diffraction_view(renderer, a, display).sum() / geometric.sum())
    assert 0.95 < ratio < 0.999


def test_linear_in_the_display(array_scene):
    renderer, display = array_scene
    rng = np.random.default_rng(2)
    a = torch.as_tensor(rng.uniform(0.01, 0.7, size=(31, 31)))
    other = torch.as_tensor(rng.random(display.shape))
    combined = diffraction_view(renderer, a, 0.3 * display + 2.0 * other)
    parts = 0.3 * diffraction_view(renderer, a, display) + 2.0 * diffraction_view(renderer, a,
                                                                                  other)
    torch.testing.assert_close(combined, parts, rtol=1e-9, atol=1e-12)


@pytest.fixture(scope="module")
def grey_case(spot_renderer) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Random holes, a random grey display, and the float64 view of that display as RGB."""
    rng = np.random.default_rng(4)
    a = torch.as_tensor(rng.uniform(0.02, 0.5, size=(15, 15)))
    grey = torch.as_tensor(rng.random((1, 201, 201)))
    return a, grey, diffraction_view(spot_renderer, a, grey.repeat(3, 1, 1), max_classes=4)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_grey_and_colour_displays_in_both_precisions(spot_renderer, grey_case, dtype):
    """C = 1 uses the green wavelength: it equals the green channel of a grey colour display.
    float32 agrees with float64."""
    a, grey, reference = grey_case
    renderer = spot_renderer if dtype == torch.float64 else Renderer(make_scene(), dtype=dtype)
    mono = diffraction_view(renderer, a.to(dtype), grey.to(dtype), max_classes=4)
    colour = diffraction_view(renderer, a.to(dtype), grey.repeat(3, 1, 1).to(dtype),
                              max_classes=4)
    assert mono.shape == (1, 81, 81) and colour.shape == (3, 81, 81)
    assert mono.dtype == dtype and colour.dtype == dtype
    tol = 1e-4 if dtype == torch.float32 else 1e-10
    peak = float(reference.abs().max())
    torch.testing.assert_close(mono[0].double(), reference[1], rtol=0, atol=tol * peak)
    torch.testing.assert_close(colour.double(), reference, rtol=0, atol=tol * peak)
    # Red spreads more, so it differs from green: the grey view is not the red one.
    assert float((reference[0] - reference[1]).abs().max()) > 1e-3 * peak


def test_view_rejects_bad_arguments(spot_renderer):
    a = torch.zeros(15, 15, dtype=torch.float64)
    with pytest.raises(ValueError, match="wavelengths_nm"):
        diffraction_view(spot_renderer, a, torch.ones(2, 201, 201))
    with pytest.raises(ValueError, match="display"):
        diffraction_view(spot_renderer, a, torch.ones(201, 201))
    with pytest.raises(ValueError, match="max_classes"):
        diffraction_view(spot_renderer, a + 0.1, torch.ones(1, 201, 201), max_classes=0)
