"""The view of a plate as made (aperture_fab.optics.as_made): the leakage veil by hand, the Airy
mixture against the per-class diffraction view and direct convolution, made copies' errors,
float64 gradient checks, and the white-display efficiency of a thin plate against its open area."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from aperture_fab.optics.as_made import (
    MadeOptics,
    draw_errors,
    drawn_fractions,
    made_views,
    made_views_and_white,
    white_transmission,
)
from aperture_fab.optics.diffraction import (
    WAVELENGTHS_NM,
    airy_kernel,
    airy_mixture,
    diffraction_view,
)
from aperture_fab.optics.eyes import EyeStates
from aperture_fab.optics.leakage import solid_transmission, veil
from aperture_fab.optics.model import Renderer
from aperture_fab.optics.scene import Display, Eye, Plate, Scene

pytestmark = pytest.mark.usefixtures("one_torch_thread")

PITCH_MM = 0.5


def array_scene() -> Scene:
    """A thin plate of 0.5 mm cells 10 mm over a 15 mm display, a 61-pixel view."""
    return Scene(Display(15.0, 15.0, (100, 100)), Plate((31, 31), (PITCH_MM, PITCH_MM), 10.0, 0.0),
                 Eye(3.0, 10.0, (20.0, 20.0), (61, 61)))


@pytest.fixture(scope="module")
def renderer() -> Renderer:
    return Renderer(array_scene(), dtype=torch.float64)


@pytest.fixture(scope="module")
def display() -> torch.Tensor:
    rng = np.random.default_rng(0)
    return torch.as_tensor(np.kron(rng.random((3, 10, 10)), np.ones((10, 10))))


def fraction(diameter_mm: float) -> float:
    return math.pi * (diameter_mm / 2) ** 2 / PITCH_MM**2


def nominal(renderer: Renderer) -> EyeStates:
    return renderer.nominal_states()


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return 10 * math.log10(float(np.abs(b).max()) ** 2 / float(np.mean((a - b) ** 2)))


# -- the veil -----------------------------------------------------------------------------------

@pytest.mark.parametrize(("od", "expected"), [(2.0, 0.01), (4.0, 1e-4), (math.inf, 0.0)])
def test_transmission_is_ten_to_the_minus_od(od, expected):
    assert solid_transmission(od) == pytest.approx(expected, rel=1e-12)


def test_veil_by_hand():
    """A uniform display of radiance (0.2, 0.5, 1) behind a plate 3 % open whose solid passes
    1 %: 0.01 x 0.97 x L per channel."""
    a = torch.full((4, 4), 0.03, dtype=torch.float64)
    shown = torch.ones(3, 8, 8, dtype=torch.float64) * torch.tensor([0.2, 0.5, 1.0])[:, None, None]
    got = veil(a, shown, 0.01)
    assert got.shape == (3, 1, 1)
    np.testing.assert_allclose(got.reshape(-1).numpy(), 0.01 * 0.97 * np.array([0.2, 0.5, 1.0]))


def test_made_view_adds_the_veil_to_the_light_through_the_holes(renderer, display):
    a = torch.full((31, 31), fraction(0.1), dtype=torch.float64)
    optics = MadeOptics(solid_transmission=1e-2)
    with_veil, through = made_views(renderer, a, display, nominal(renderer), optics)
    geometric = renderer.render(a, display)[None]
    torch.testing.assert_close(through, geometric)
    torch.testing.assert_close(with_veil - through,
                               (veil(a, display, 1e-2)[None]).expand_as(through))


def test_no_errors_no_diffraction_no_leak_is_the_geometric_view(renderer, display):
    a = torch.full((31, 31), fraction(0.1), dtype=torch.float64)
    views, _ = made_views(renderer, a, display, nominal(renderer), MadeOptics())
    torch.testing.assert_close(views[0], renderer.render(a, display))


# -- diffraction as a mixture -------------------------------------------------------------------

def mixture_for(renderer: Renderer, d_min: float, d_max: float):  # type: ignore[no-untyped-def]
    eye = renderer.scene.eye
    return airy_mixture(d_min, d_max, eye.view_step, eye.view_pixels,
                        reach_px=max(eye.view_pixels))


def test_one_size_at_a_class_is_that_class_exactly(renderer, display):
    """Equal holes at a class diameter: the mixture is that class's kernel, and the view is the
    geometric view convolved with it, here by direct convolution (conv2d, zero padding)."""
    mixture = mixture_for(renderer, 0.04, 0.16)
    a = torch.full((31, 31), fraction(0.04), dtype=torch.float64)
    weights = mixture.weights(a, (PITCH_MM, PITCH_MM))
    np.testing.assert_allclose(weights.numpy(), np.eye(len(weights))[0], atol=1e-9)
    geometric = renderer.render(a, display)
    view = mixture.blur(geometric[None], a, (PITCH_MM, PITCH_MM))[0]
    for channel, wavelength in enumerate(np.array(WAVELENGTHS_NM) * 1e-6):
        kernel = torch.as_tensor(airy_kernel(0.04, wavelength, renderer.scene.eye.view_step,
                                             max(renderer.scene.eye.view_pixels)))
        pad = (kernel.shape[0] // 2, kernel.shape[1] // 2)
        direct = F.conv2d(geometric[channel][None, None], kernel[None, None], padding=pad)[0, 0]
        torch.testing.assert_close(view[channel], direct, rtol=1e-7, atol=1e-10)


def test_mixed_sizes_agree_with_the_per_class_view(renderer, display):
    """Hole sizes spread evenly over the plate (a made layout's ladder): the mixture is within
    35 dB of diffraction_view, which renders each size class on its own."""
    rng = np.random.default_rng(3)
    ladder = np.array([0.04, 0.06, 0.09, 0.13])
    a = torch.as_tensor(fraction(1.0) * rng.choice(ladder, (31, 31)) ** 2)
    mixture = mixture_for(renderer, 0.04, 0.13)
    geometric = renderer.render(a, display)
    mixed = mixture.blur(geometric[None], a, (PITCH_MM, PITCH_MM))[0].numpy()
    exact = diffraction_view(renderer, a, display).numpy()
    assert psnr(mixed, exact) > 35.0
    assert psnr(geometric.numpy(), exact) < psnr(mixed, exact) - 5.0  # diffraction matters here
    # The optimizer's shorter reach (MIXTURE_REACH_PX) costs little beside the model's error.
    eye = renderer.scene.eye
    short = airy_mixture(0.04, 0.13, eye.view_step, eye.view_pixels, reach_px=16)
    assert psnr(short.blur(geometric[None], a, (PITCH_MM, PITCH_MM))[0].numpy(), exact) > 30.0


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), classes=st.integers(1, 8))
def test_mixture_weights_are_shares_of_the_light(seed, classes):
    rng = np.random.default_rng(seed)
    eye = array_scene().eye
    mixture = airy_mixture(0.03, 0.2, eye.view_step, eye.view_pixels, classes=classes)
    a = torch.as_tensor(rng.uniform(0, fraction(0.25), (5, 5)) * (rng.random((5, 5)) > 0.3))
    if not bool((a > 0).any()):
        return
    w = mixture.weights(a, (PITCH_MM, PITCH_MM)).numpy()
    assert np.all(w >= -1e-12)
    assert w.sum() == pytest.approx(1.0, abs=1e-12)


def test_mixture_weights_gradient_float64():
    eye = array_scene().eye
    mixture = airy_mixture(0.03, 0.2, eye.view_step, eye.view_pixels, classes=4)
    a = torch.tensor([[fraction(0.05), fraction(0.08)], [fraction(0.12), fraction(0.17)]],
                     dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: mixture.weights(x, (PITCH_MM, PITCH_MM)), (a,))


# -- made copies --------------------------------------------------------------------------------

def test_draws_are_seeded_and_keep_closed_cells_closed():
    optics = MadeOptics(radius_sigma_mm=0.01, position_sigma_mm=0.005)
    first = draw_errors((6, 6), optics, np.random.default_rng(1))
    again = draw_errors((6, 6), optics, np.random.default_rng(1))
    np.testing.assert_array_equal(first.radius_mm, again.radius_mm)
    assert first.offset_mm is not None and first.offset_mm.shape == (6, 6, 2)
    a = torch.zeros(6, 6, dtype=torch.float64)
    a[2, 3] = fraction(0.02)
    made = drawn_fractions(a, first.radius_mm * 10, (PITCH_MM, PITCH_MM))  # errors up to 0.3 mm
    assert bool((made[a == 0] == 0).all())
    assert float(made.min()) >= 0.0


def test_radius_errors_move_the_made_radius():
    a = torch.full((2, 2), fraction(0.1), dtype=torch.float64)
    error = np.array([[0.01, -0.01], [0.0, -1.0]])
    made = drawn_fractions(a, error, (PITCH_MM, PITCH_MM)).numpy()
    expected = np.array([[fraction(0.12), fraction(0.08)], [fraction(0.1), 0.0]])
    np.testing.assert_allclose(made, expected, rtol=1e-9, atol=1e-15)


def test_drawn_fractions_gradient_float64():
    a = torch.tensor([[fraction(0.05), fraction(0.1)], [fraction(0.2), fraction(0.15)]],
                     dtype=torch.float64, requires_grad=True)
    error = np.array([[0.003, -0.004], [0.01, -0.002]])
    assert torch.autograd.gradcheck(lambda x: drawn_fractions(x, error, (PITCH_MM, PITCH_MM)),
                                    (a,))


def test_moved_renderer_is_a_renderer_built_with_the_offsets(renderer, display):
    rng = np.random.default_rng(2)
    offsets = rng.normal(0, 0.02, (31, 31, 2))
    a = torch.full((31, 31), fraction(0.1), dtype=torch.float64)
    built = Renderer(array_scene(), dtype=torch.float64, hole_offset_mm=offsets)
    torch.testing.assert_close(renderer.with_hole_offsets(offsets).render(a, display),
                               built.render(a, display))
    assert renderer.hole_offset_mm is None  # the original is unchanged


@pytest.mark.parametrize("diameter", [0.05, 0.1, 0.2])
def test_white_efficiency_of_a_thin_plate_is_its_open_area(renderer, diameter):
    """Straight holes in a plate of no thickness pass, for a uniform display, the share of the
    pupil's rays that meet a hole: the open area fraction (away from the view's edge, where the
    field leaves the plate, the view is that flat)."""
    a = torch.full((31, 31), fraction(diameter), dtype=torch.float64)
    states = nominal(renderer)
    assert float(white_transmission(renderer, a, states)[0]) == pytest.approx(
        fraction(diameter), rel=0.03)


def test_a_stack_with_white_is_the_two_stacks_joined(renderer, display):
    """display_stack(with_white=True) writes the white display's stack beside the content's:
    the same values, to the bit, as the two stacks built apart and joined, in the kernels'
    channels-last layout."""
    joined = renderer.display_stack(display, with_white=True)
    apart = torch.cat([renderer.display_stack(display), renderer.white_stack()], 1)
    assert joined.shape == apart.shape
    assert torch.equal(joined, apart)
    assert joined[0].permute(1, 2, 3, 0).is_contiguous()


@pytest.mark.parametrize("with_errors", [False, True])
def test_the_white_channel_is_the_made_copys_efficiency(renderer, display, with_errors):
    """made_views_and_white renders the white display beside the content: the content views
    are made_views' and the efficiency is white_transmission of the copy built by hand (its
    drawn radii, a renderer moved by its offsets), diffraction and veil or not."""
    rng = np.random.default_rng(3)
    a = torch.as_tensor(rng.uniform(0.0, fraction(0.2), (31, 31)))
    scene = renderer.scene
    optics = MadeOptics(radius_sigma_mm=0.005, position_sigma_mm=0.01, solid_transmission=1e-3,
                        diffraction=mixture_for(renderer, 0.02, 0.2))
    draw = draw_errors((31, 31), optics, np.random.default_rng(4)) if with_errors else None
    states = nominal(renderer)
    stack = renderer.display_stack(display)
    joined = renderer.display_stack(display, with_white=True)
    views, through, white = made_views_and_white(renderer, a, display, joined, states, optics,
                                                 draw)
    alone, alone_through = made_views(renderer, a, display, states, optics, draw, stack)
    torch.testing.assert_close(views, alone)
    torch.testing.assert_close(through, alone_through)
    copy, moved = a, renderer
    if draw is not None:
        copy = drawn_fractions(a, draw.radius_mm, scene.plate.pitch_mm)
        moved = Renderer(scene, dtype=torch.float64, hole_offset_mm=draw.offset_mm)
    torch.testing.assert_close(white, white_transmission(moved, copy, states))
