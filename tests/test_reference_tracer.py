"""Checks of the reference Monte Carlo tracer against analytic cases (it checks the fast model).

Monte Carlo error bound used throughout (see reference_tracer's docstring): a view pixel whose
integrand is 0/1 with mean p has standard error <= sqrt(p (1 - p) / N), and <= f_max / (2 sqrt N)
for an integrand in [0, f_max]; N = stratified_sample_count(samples_per_pixel). Pixels are
independent. Tests allow Z_BOUND standard errors per pixel.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from reference_tracer import stratified_sample_count, trace_tan_window, trace_view

#: Allowed deviation in bounded standard errors; a false alarm per pixel is below 1e-6.
Z_BOUND = 5.0
GAP_MM = 10.0
EYE_RELIEF_MM = 15.0


def lens_area(radius_mm: float, distance_mm: np.ndarray) -> np.ndarray:
    """Area of the overlap of two disks of equal radius whose centres are distance_mm apart."""
    d = np.minimum(np.abs(distance_mm), 2.0 * radius_mm)
    return 2.0 * radius_mm**2 * np.arccos(d / (2.0 * radius_mm)) - (d / 2.0) * np.sqrt(
        4.0 * radius_mm**2 - d**2
    )


def binary_std_bound(mean: float, samples_per_pixel: int) -> float:
    return math.sqrt(mean * (1.0 - mean) / stratified_sample_count(samples_per_pixel))


def full_fov_deg(half_tan: float) -> float:
    return 2.0 * math.degrees(math.atan(half_tan))


# --- open display, eye focused on it -----------------------------------------------------------


@pytest.mark.parametrize(
    ("eye_shift_px", "thickness_mm"), [((0, 0), 1.0), ((1, 0), 0.0), ((0, -2), 2.0), ((-1, 1), 1.0)]
)
def test_focused_view_is_the_display_upright(
    eye_shift_px: tuple[int, int], thickness_mm: float
) -> None:
    """View pixel (i, j) sees display pixel (i, j) when one view pixel spans one display pixel."""
    nx, ny, pixel_mm = 7, 5, 0.5
    display = np.random.default_rng(3).random((3, ny, nx))  # asymmetric: catches flips
    distance = GAP_MM + thickness_mm + EYE_RELIEF_MM
    fov = (full_fov_deg(nx * pixel_mm / 2 / distance), full_fov_deg(ny * pixel_mm / 2 / distance))
    eye = (eye_shift_px[0] * pixel_mm, eye_shift_px[1] * pixel_mm)
    view = trace_view(
        display, (nx * pixel_mm, ny * pixel_mm), np.zeros((1, 1)), (1.0, 1.0), GAP_MM,
        thickness_mm, "straight", 4.0, EYE_RELIEF_MM, distance, fov, (nx, ny),
        eye_position_mm=eye, samples_per_pixel=256, plate=False,
    )  # fmt: skip
    # Moving the eye by +1 pixel in x shows display column j + 1 in view column j (y is up,
    # rows go down, so +1 pixel in y shows row i - 1). Off the display is black.
    expected = np.zeros_like(display)
    sx, sy = eye_shift_px
    for i in range(ny):
        for j in range(nx):
            if 0 <= i - sy < ny and 0 <= j + sx < nx:
                expected[:, i, j] = display[:, i - sy, j + sx]
    np.testing.assert_allclose(view, expected, atol=1e-12)


@settings(max_examples=20, deadline=None)
@given(
    focus=st.one_of(st.none(), st.floats(5.0, 1e4)),
    eye_x=st.floats(-3.0, 3.0),
    eye_y=st.floats(-3.0, 3.0),
    fov=st.floats(1.0, 60.0),
    pupil=st.floats(0.5, 6.0),
)
def test_uniform_open_display_is_exactly_one(
    focus: float | None, eye_x: float, eye_y: float, fov: float, pupil: float
) -> None:
    view = trace_view(
        np.ones((1, 4, 4)), (200.0, 200.0), np.zeros((1, 1)), (1.0, 1.0), GAP_MM, 1.0,
        "straight", pupil, EYE_RELIEF_MM, focus, (fov, fov / 2), (3, 2),
        eye_position_mm=(eye_x, eye_y), samples_per_pixel=16, plate=False,
    )  # fmt: skip
    assert view.shape == (1, 2, 3)
    np.testing.assert_array_equal(view, 1.0)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31), weight=st.floats(-2.0, 2.0), eye_x=st.floats(-1.0, 1.0))
def test_linear_in_display(seed: int, weight: float, eye_x: float) -> None:
    """Same seed, same rays: the view of a sum of displays is the sum of the views."""
    rng = np.random.default_rng(seed)
    first, second = rng.random((2, 2, 6, 6))
    radii = rng.uniform(0.0, 0.2, (9, 9))

    def view(display: np.ndarray) -> np.ndarray:
        return trace_view(
            display, (6.0, 6.0), radii, (0.4, 0.4), GAP_MM, 0.5, "chief_ray", 3.0,
            EYE_RELIEF_MM, 300.0, (20.0, 20.0), (3, 3), eye_position_mm=(eye_x, 0.0),
            samples_per_pixel=81, seed=seed,
        )  # fmt: skip

    np.testing.assert_allclose(
        view(first + weight * second), view(first) + weight * view(second), atol=1e-12
    )


@settings(max_examples=15, deadline=None)
@given(
    seed=st.integers(0, 2**31), focus=st.one_of(st.none(), st.floats(20.0, 1e3)),
    axis=st.sampled_from(["straight", "chief_ray"]),
)  # fmt: skip
def test_thin_plate_of_overlapping_holes_is_fully_open(
    seed: int, focus: float | None, axis: str
) -> None:
    """r = 1.4 p > p / sqrt(2): every point of a thin plate lies in some hole, so it is open."""
    display = np.random.default_rng(seed).random((1, 8, 8))
    kwargs: dict[str, Any] = dict(
        display=display, display_size_mm=(8.0, 8.0), radii_mm=np.full((61, 61), 0.7),
        pitch_mm=(0.5, 0.5), gap_mm=GAP_MM, thickness_mm=0.0, hole_axis=axis, pupil_mm=4.0,
        eye_relief_mm=EYE_RELIEF_MM, focus_mm=focus, fov_deg=(20.0, 20.0), view_pixels=(4, 4),
        samples_per_pixel=16, seed=seed,
    )  # fmt: skip
    np.testing.assert_array_equal(trace_view(**kwargs), trace_view(**kwargs, plate=False))


def test_closed_plate_is_black() -> None:
    view = trace_view(
        np.ones((2, 4, 4)), (50.0, 50.0), np.zeros((5, 5)), (0.3, 0.3), GAP_MM, 0.0,
        "straight", 4.0, EYE_RELIEF_MM, None, (10.0, 10.0), (3, 3), samples_per_pixel=16,
    )  # fmt: skip
    np.testing.assert_array_equal(view, 0.0)


# --- thin plate: open-area fraction ---------------------------------------------------------------


@pytest.mark.parametrize(
    ("focus_mm", "hole_axis", "eye_mm"),
    [(None, "straight", (0.0, 0.0)), (500.0, "straight", (0.37, -0.21)),
     (None, "chief_ray", (-0.5, 0.2))],
)  # fmt: skip
def test_thin_plate_passes_the_open_area_fraction(
    focus_mm: float | None, hole_axis: str, eye_mm: tuple[float, float]
) -> None:
    """Each view pixel spans exactly one plate period at the plate (tan box = pitch / e), so for
    every pupil point the plate crossing sweeps whole periods: the expected value is exactly
    a = pi r^2 / (px py), for every view pixel."""
    pitch, radius, samples, n_view = (0.3, 0.25), 0.1, 4096, 6
    area_fraction = math.pi * radius**2 / (pitch[0] * pitch[1])
    fov = (
        full_fov_deg(n_view / 2 * pitch[0] / EYE_RELIEF_MM),
        full_fov_deg(n_view / 2 * pitch[1] / EYE_RELIEF_MM),
    )
    view = trace_view(
        np.ones((1, 8, 8)), (60.0, 60.0), np.full((41, 41), radius), pitch, GAP_MM, 0.0,
        hole_axis, 4.0, EYE_RELIEF_MM, focus_mm, fov, (n_view, n_view), eye_position_mm=eye_mm,
        samples_per_pixel=samples,
    )  # fmt: skip
    std = binary_std_bound(area_fraction, samples)
    assert np.max(np.abs(view - area_fraction)) < Z_BOUND * std
    assert abs(view.mean() - area_fraction) < Z_BOUND * std / n_view


# --- thick plate, straight holes: two-disk overlap ---------------------------------------------


@pytest.mark.parametrize("along", ["x", "y"])
def test_thick_straight_holes_pass_the_two_disk_overlap(along: str) -> None:
    """Through a straight hole of length t, direction v passes lens(r, t |v|) / (px py). Each view
    pixel spans one plate period (tan box = pitch / e); the expectation is the closed-form lens
    area averaged over the pixel's tan box (64 x 64 midpoint rule)."""
    pitch, radius, thickness, samples, n_view = (0.3, 0.28), 0.1, 1.0, 65536, 25
    steps = (pitch[0] / EYE_RELIEF_MM, pitch[1] / EYE_RELIEF_MM)
    nx_view, ny_view = (n_view, 1) if along == "x" else (1, n_view)
    half = (nx_view * steps[0] / 2, ny_view * steps[1] / 2)
    view = trace_tan_window(
        np.ones((1, 4, 4)), (60.0, 60.0), np.full((61, 61), radius), pitch, GAP_MM, thickness,
        "straight", 4.0, EYE_RELIEF_MM, None, (-half[0], half[0]), (-half[1], half[1]),
        (nx_view, ny_view), samples_per_pixel=samples,
    )[0].ravel()  # fmt: skip

    quad = (np.arange(64) + 0.5) / 64
    expected = []
    for k in range(n_view):
        # Pixel k along the scan axis, box lower corners; rows count down from +tan_y.
        lo_x = -half[0] + (k if along == "x" else 0) * steps[0]
        hi_y = half[1] - (k if along == "y" else 0) * steps[1]
        tx, ty = np.meshgrid(lo_x + quad * steps[0], hi_y - quad * steps[1])
        overlap = lens_area(radius, thickness * np.hypot(tx, ty))
        expected.append(overlap.mean() / (pitch[0] * pitch[1]))
    expected_arr = np.array(expected)
    assert expected_arr[n_view // 2] > 0.3 and expected_arr[0] == 0.0  # spans open to shut
    bound = np.array([Z_BOUND * binary_std_bound(p, samples) for p in expected_arr])
    assert np.all(np.abs(view - expected_arr) <= bound + 1e-12), (view, expected_arr)


# --- single pinhole: image position ---------------------------------------------------------------

DISPLAY_PX = 201  # odd: pixel 100 is centred on the axis
DISPLAY_PIXEL_MM = 0.1
PINHOLE_CELLS = 11
PINHOLE_PITCH_MM = 0.5
PINHOLE_RADIUS_MM = 0.08
WINDOW_HALF_TAN = 0.02
WINDOW_PX = 20
#: A short eye relief and a pupil just big enough keep most pupil samples useful (low noise).
PINHOLE_EYE_RELIEF_MM = 5.0
PINHOLE_PUPIL_MM = 0.7
PINHOLE_SEED = 0


@pytest.mark.slow
@pytest.mark.parametrize(
    ("hole_cell", "bright_px", "thickness_mm", "hole_axis", "eye_offset_mm"),
    [
        ((5, 5), (100, 100), 0.0, "straight", (0.1, -0.05)),  # on axis
        ((3, 7), (120, 130), 0.0, "straight", (0.1, -0.05)),  # off axis
        ((6, 2), (80, 75), 0.0, "chief_ray", (-0.07, 0.12)),  # off axis
        ((4, 4), (95, 95), 0.5, "straight", (0.05, 0.1)),  # thick, pixel under the hole
        ((3, 7), (120, 130), 1.0, "chief_ray", (0.1, -0.05)),  # thick, axis through the pixel
    ],
)
def test_pinhole_images_a_pixel_at_the_predicted_direction(
    hole_cell: tuple[int, int],
    bright_px: tuple[int, int],
    thickness_mm: float,
    hole_axis: str,
    eye_offset_mm: tuple[float, float],
) -> None:
    """A display point x_d seen through a hole at h appears at tan = (x_d - h) / (g + t / 2),
    wherever the eye is. Each case is point-symmetric about that direction (thin plate; thick
    plate with the hole's axis through the pixel), so the centroid is exact up to noise."""
    half_width = DISPLAY_PX * DISPLAY_PIXEL_MM / 2
    row, col = bright_px
    x_d = -half_width + (col + 0.5) * DISPLAY_PIXEL_MM
    y_d = half_width - (row + 0.5) * DISPLAY_PIXEL_MM
    centre = (PINHOLE_CELLS - 1) / 2
    h_x = (hole_cell[1] - centre) * PINHOLE_PITCH_MM
    h_y = (centre - hole_cell[0]) * PINHOLE_PITCH_MM
    height = GAP_MM + thickness_mm / 2
    v_x, v_y = (x_d - h_x) / height, (y_d - h_y) / height
    # A chief-ray hole's axis points along -v at the eye point E, so it passes through (x_d, y_d).
    to_eye = PINHOLE_EYE_RELIEF_MM + thickness_mm / 2
    tilt_target = (h_x - v_x * to_eye, h_y - v_y * to_eye)
    if hole_axis == "straight":
        assert thickness_mm == 0.0 or (v_x, v_y) == (0.0, 0.0)  # else not symmetric
    # Eye placed so that the pupil holds every ray that reaches the pixel (no clipping).
    eye = (h_x - v_x * to_eye + eye_offset_mm[0], h_y - v_y * to_eye + eye_offset_mm[1])

    display = np.zeros((1, DISPLAY_PX, DISPLAY_PX))
    display[0, row, col] = 1.0
    radii = np.zeros((PINHOLE_CELLS, PINHOLE_CELLS))
    radii[hole_cell] = PINHOLE_RADIUS_MM
    samples = 16384
    view = trace_tan_window(
        display, (2 * half_width, 2 * half_width), radii, (PINHOLE_PITCH_MM, PINHOLE_PITCH_MM),
        GAP_MM, thickness_mm, hole_axis, PINHOLE_PUPIL_MM, PINHOLE_EYE_RELIEF_MM, None,
        (v_x - WINDOW_HALF_TAN, v_x + WINDOW_HALF_TAN),
        (v_y - WINDOW_HALF_TAN, v_y + WINDOW_HALF_TAN),
        (WINDOW_PX, WINDOW_PX), eye_position_mm=eye, tilt_target_mm=tilt_target,
        samples_per_pixel=samples, seed=PINHOLE_SEED,
    )[0]  # fmt: skip

    step = 2 * WINDOW_HALF_TAN / WINDOW_PX
    centres = (np.arange(WINDOW_PX) + 0.5) * step - WINDOW_HALF_TAN  # relative to (v_x, v_y)
    # The image lies well inside the window (a ring of dark pixels around it).
    assert view[[0, -1], :].max() == 0.0 and view[:, [0, -1]].max() == 0.0
    total = view.sum()
    centroid_x = (view.sum(axis=0) * centres).sum() / total
    centroid_y = -(view.sum(axis=1) * centres).sum() / total  # rows go toward -tan_y
    assert abs(centroid_x) < 0.1 * step and abs(centroid_y) < 0.1 * step

    if thickness_mm == 0.0:
        # Total light: the hole's disk swept over the pixel, integral over v of
        # area(disk(h + g v, r) ∩ pixel) / (pi R^2) = pi r^2 * pixel^2 / (g^2 pi R^2).
        pupil_radius = PINHOLE_PUPIL_MM / 2
        flux = total * step**2
        expected_flux = (PINHOLE_RADIUS_MM * DISPLAY_PIXEL_MM / (GAP_MM * pupil_radius)) ** 2
        # Pixels are 0/1 integrands: var(sum) <= sum(p) / N.
        flux_std = math.sqrt(total / stratified_sample_count(samples)) * step**2
        assert abs(flux - expected_flux) < Z_BOUND * flux_std


# --- convergence and determinism -----------------------------------------------------------------


@pytest.mark.slow
def test_two_seeds_agree_within_the_error_bound() -> None:
    rng = np.random.default_rng(11)
    display = rng.random((3, 60, 60))
    radii = rng.uniform(0.0, 0.15, (41, 41))
    kwargs: dict[str, Any] = dict(
        display=display, display_size_mm=(12.0, 12.0), radii_mm=radii, pitch_mm=(0.3, 0.3),
        gap_mm=GAP_MM, thickness_mm=0.8, hole_axis="chief_ray", pupil_mm=4.0,
        eye_relief_mm=EYE_RELIEF_MM, focus_mm=None, fov_deg=(24.0, 24.0), view_pixels=(32, 32),
        eye_position_mm=(0.5, -0.3), samples_per_pixel=4096,
    )  # fmt: skip
    first = trace_view(**kwargs, seed=1)
    second = trace_view(**kwargs, seed=2)
    std = 1.0 / (2.0 * math.sqrt(stratified_sample_count(4096)))  # integrand in [0, 1]
    difference = np.abs(first - second)
    assert difference.max() < Z_BOUND * math.sqrt(2.0) * std
    # Mean |difference| of two independent errors <= sqrt(2) std (1024 x 3 pixels).
    assert difference.mean() < math.sqrt(2.0) * std
    assert difference.max() > 0.0  # the seed is used
    np.testing.assert_array_equal(first, trace_view(**kwargs, seed=1))


def test_sample_count_rounds_up_to_whole_strata() -> None:
    assert stratified_sample_count(4096) == 4096
    assert stratified_sample_count(1000) == 1250  # 5^4 strata, 2 each
    assert stratified_sample_count(1) == 1
    assert all(stratified_sample_count(n) >= n for n in range(1, 300))


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"hole_axis": "tilted"}, "hole_axis"),
        ({"radii_mm": np.full((3, 3), -0.1)}, "radii_mm"),
        ({"radii_mm": np.full((3, 3), 0.5)}, "radii_mm"),
        ({"display": np.ones((4, 4))}, "display"),
        ({"focus_mm": -5.0}, "focus_mm"),
        ({"thickness_mm": -1.0}, "thickness_mm"),
        ({"fov_deg": (0.0, 10.0)}, "fov_deg"),
        ({"view_pixels": (0, 3)}, "view_pixels"),
    ],
)
def test_bad_input_is_refused(change: dict[str, Any], message: str) -> None:
    kwargs: dict[str, Any] = dict(
        display=np.ones((1, 4, 4)), display_size_mm=(10.0, 10.0), radii_mm=np.full((3, 3), 0.1),
        pitch_mm=(0.3, 0.3), gap_mm=GAP_MM, thickness_mm=0.5, hole_axis="straight",
        pupil_mm=4.0, eye_relief_mm=EYE_RELIEF_MM, focus_mm=None, fov_deg=(10.0, 10.0),
        view_pixels=(3, 3), samples_per_pixel=16,
    )  # fmt: skip
    kwargs.update(change)
    with pytest.raises(ValueError, match=message):
        trace_view(**kwargs)
