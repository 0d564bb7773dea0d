"""Slow, plain Monte Carlo reference ray tracer: the eye looking through a pinhole plate.

Used only by the test suite to check the fast differentiable model. It deliberately imports
nothing from aperture_fab, so a mistake shared by both cannot hide; numpy only.

Geometry (millimetres, see docs/design.md section 2): display at z = 0, plate bottom face at z = g,
top face at z = g + t, eye pupil plane at z_e = g + t + e, pupil centre at lateral c. A view
direction is v = (tan theta_x, tan theta_y). The ray for direction v and pupil point c + u
(|u| <= R), with the eye focused at distance D, is, at depth s below the pupil plane,

    x(s) = c + u + s * (v - u / D)        (D = infinity: c + u + s * v)

so it meets the plate top face at s = e, the bottom face at s = e + t, the display at s = z_e.
A view pixel's value is the mean, over its tan-box and the pupil disk (both uniform), of the
display radiance where the ray lands, times 1 if the ray passes one hole at both plate faces.

Display-side optics, each ray exactly: a cover glass of thickness t_g and index n fills
0 <= z <= t_g (inside the gap); a ray refracts at its top face (Snell: sin(theta) = n
sin(theta_g), the angle theta in air from its slope) and runs on at the glass angle to the
emitting surface at z = 0. Striped sub-pixels: channel c of a pixel emits only from its vertical
stripe, a third of the pixel wide, centred (c - 1) / 3 pixel right of the pixel centre for
"rgb_stripe" (left for "bgr_stripe"), at three times the pixel's value (the same light per
pixel). Emission falloff: radiance times cos(theta)^k, theta the ray's angle in air.

Sampling: per view pixel, the 4-D unit cube (v in box: 2 dims, pupil radius^2 and angle: 2 dims)
is cut into k^4 equal strata, each sampled with the same number of uniform jittered points.
Equal-allocation stratified sampling never has a larger variance than independent uniform
sampling with as many points, so a pixel whose integrand lies in [0, f_max] has
standard error <= f_max / (2 sqrt(N)), and <= sqrt(p (1 - p) / N) for a 0/1 integrand of mean p
(N = stratified_sample_count(samples_per_pixel)). View pixels use independent random numbers.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["stratified_sample_count", "trace_tan_window", "trace_view"]

HOLE_AXES = ("straight", "chief_ray")
#: Rays traced at once; bounds memory (a few dozen float64 arrays of this length live at a time).
RAYS_PER_CHUNK = 1 << 16
#: The 3x3 cell search is exact only while no hole reaches beyond its neighbouring cells.
MAX_RADIUS_PER_PITCH = 1.5
#: Sample dimensions: view tan x, view tan y, pupil radius^2 fraction, pupil angle fraction.
SAMPLE_DIMS = 4
MAX_FOV_DEG = 179.0


def stratified_sample_count(samples_per_pixel: int) -> int:
    """Samples really used per view pixel: samples_per_pixel rounded up to fill k^4 strata evenly.

    k = floor(samples_per_pixel ** (1/4)); e.g. 4096 -> 4096 (8^4 strata), 1000 -> 1250.
    """
    if not (isinstance(samples_per_pixel, (int, np.integer)) and samples_per_pixel >= 1):
        raise ValueError(f"samples_per_pixel = {samples_per_pixel!r}; allowed: whole number >= 1.")
    strata_per_dim = _strata_per_dim(samples_per_pixel)
    strata = strata_per_dim**SAMPLE_DIMS
    return strata * math.ceil(samples_per_pixel / strata)


def trace_view(
    display: np.ndarray,
    display_size_mm: tuple[float, float],
    radii_mm: np.ndarray,
    pitch_mm: tuple[float, float],
    gap_mm: float,
    thickness_mm: float,
    hole_axis: str,
    pupil_mm: float,
    eye_relief_mm: float,
    focus_mm: float | None,
    fov_deg: tuple[float, float],
    view_pixels: tuple[int, int],
    eye_position_mm: tuple[float, float] = (0.0, 0.0),
    tilt_target_mm: tuple[float, float] = (0.0, 0.0),
    samples_per_pixel: int = 4096,
    seed: int = 0,
    plate: bool = True,
    cover_glass_mm: float = 0.0,
    cover_glass_index: float = 1.5,
    subpixels: str = "none",
    emission_exponent: float = 0.0,
) -> np.ndarray:
    """The eye's view, shape (C, ny_view, nx_view) float64, linear radiance.

    display: (C, ny, nx) radiance; display_size_mm: (W, H); radii_mm: (ny_c, nx_c), 0 = closed;
    pitch_mm: (px, py); hole_axis: "straight" or "chief_ray"; focus_mm: None = infinity;
    fov_deg: full field of view (x, y); view_pixels: (nx_view, ny_view), uniform in tan;
    plate=False traces the open display (no plate at all); cover_glass_mm (0: none),
    cover_glass_index, subpixels ("none", "rgb_stripe", "bgr_stripe") and emission_exponent
    (0: Lambertian): the display-side optics of the module docstring.
    """
    for name, angle in (("fov_deg[0]", fov_deg[0]), ("fov_deg[1]", fov_deg[1])):
        if not 0.0 < angle < MAX_FOV_DEG:
            raise ValueError(
                f"{name} = {angle!r} is out of range; allowed: 0 < fov < {MAX_FOV_DEG} degrees "
                "(full angle). Give the field of view in degrees."
            )
    tan_x = math.tan(math.radians(fov_deg[0]) / 2.0)
    tan_y = math.tan(math.radians(fov_deg[1]) / 2.0)
    return trace_tan_window(
        display, display_size_mm, radii_mm, pitch_mm, gap_mm, thickness_mm, hole_axis,
        pupil_mm, eye_relief_mm, focus_mm,
        tan_x_range=(-tan_x, tan_x), tan_y_range=(-tan_y, tan_y), view_pixels=view_pixels,
        eye_position_mm=eye_position_mm, tilt_target_mm=tilt_target_mm,
        samples_per_pixel=samples_per_pixel, seed=seed, plate=plate,
        cover_glass_mm=cover_glass_mm, cover_glass_index=cover_glass_index,
        subpixels=subpixels, emission_exponent=emission_exponent,
    )  # fmt: skip


def trace_tan_window(
    display: np.ndarray,
    display_size_mm: tuple[float, float],
    radii_mm: np.ndarray,
    pitch_mm: tuple[float, float],
    gap_mm: float,
    thickness_mm: float,
    hole_axis: str,
    pupil_mm: float,
    eye_relief_mm: float,
    focus_mm: float | None,
    tan_x_range: tuple[float, float],
    tan_y_range: tuple[float, float],
    view_pixels: tuple[int, int],
    eye_position_mm: tuple[float, float] = (0.0, 0.0),
    tilt_target_mm: tuple[float, float] = (0.0, 0.0),
    samples_per_pixel: int = 4096,
    seed: int = 0,
    plate: bool = True,
    cover_glass_mm: float = 0.0,
    cover_glass_index: float = 1.5,
    subpixels: str = "none",
    emission_exponent: float = 0.0,
) -> np.ndarray:
    """Like trace_view, but over any tan-rectangle: tan_x_range, tan_y_range = (lo, hi), (lo, hi).

    Column j covers tan x in [lo + j dx, lo + (j + 1) dx]; row i covers tan y in
    [hi - (i + 1) dy, hi - i dy] (row 0 top). Returns (C, ny_view, nx_view) float64.
    """
    _validate(
        display, display_size_mm, radii_mm, pitch_mm, gap_mm, thickness_mm, hole_axis, pupil_mm,
        eye_relief_mm, focus_mm, tan_x_range, tan_y_range, view_pixels, samples_per_pixel,
    )  # fmt: skip
    if not (0.0 <= cover_glass_mm < gap_mm and 1.0 <= cover_glass_index):
        raise ValueError(f"cover_glass_mm = {cover_glass_mm!r}, cover_glass_index = "
                         f"{cover_glass_index!r}; allowed: 0 <= glass < gap_mm, index >= 1.")
    if subpixels not in SUBPIXEL_ORDER:
        raise ValueError(f"subpixels = {subpixels!r}; allowed: {tuple(SUBPIXEL_ORDER)}.")
    if not (math.isfinite(emission_exponent) and emission_exponent >= 0):
        raise ValueError(f"emission_exponent = {emission_exponent!r}; allowed: >= 0.")
    display = np.asarray(display, dtype=np.float64)
    radii = np.asarray(radii_mm, dtype=np.float64)
    nx_view, ny_view = view_pixels
    n_samples = stratified_sample_count(samples_per_pixel)
    strata_offsets = _strata_offsets(samples_per_pixel)  # (n_samples, 4) lower corners in [0, 1)
    strata_per_dim = _strata_per_dim(samples_per_pixel)
    inverse_focus = 0.0 if focus_mm is None or math.isinf(focus_mm) else 1.0 / focus_mm
    pupil_radius = pupil_mm / 2.0
    tan_x_step = (tan_x_range[1] - tan_x_range[0]) / nx_view
    tan_y_step = (tan_y_range[1] - tan_y_range[0]) / ny_view
    # Depths below the pupil plane of the top face, bottom face and display.
    depth_top = eye_relief_mm
    depth_bottom = eye_relief_mm + thickness_mm
    depth_display = eye_relief_mm + thickness_mm + gap_mm

    rng = np.random.default_rng(seed)
    n_pixels = nx_view * ny_view
    pixels_per_chunk = max(1, RAYS_PER_CHUNK // n_samples)
    view = np.zeros((display.shape[0], n_pixels), dtype=np.float64)
    for first in range(0, n_pixels, pixels_per_chunk):
        pixel_index = np.arange(first, min(first + pixels_per_chunk, n_pixels))
        row = (pixel_index // nx_view)[:, None]  # (P, 1)
        col = (pixel_index % nx_view)[:, None]
        jitter = rng.random((pixel_index.size, n_samples, SAMPLE_DIMS))
        unit = strata_offsets[None, :, :] + jitter / strata_per_dim  # (P, N, 4) in [0, 1)

        # View direction, uniform over the pixel's tan-box.
        vx = tan_x_range[0] + (col + unit[..., 0]) * tan_x_step
        vy = tan_y_range[1] - (row + unit[..., 1]) * tan_y_step
        # Pupil point, uniform over the disk (radius ~ sqrt keeps equal area).
        radius = pupil_radius * np.sqrt(unit[..., 2])
        angle = 2.0 * np.pi * unit[..., 3]
        ux = radius * np.cos(angle)
        uy = radius * np.sin(angle)
        # Lateral slope per mm of depth: all rays from the pupil meet at depth D.
        slope_x = vx - ux * inverse_focus
        slope_y = vy - uy * inverse_focus
        start_x = eye_position_mm[0] + ux
        start_y = eye_position_mm[1] + uy

        # In air down to the glass's top face, then at the refracted angle through the glass.
        glass_x, glass_y = _glass_slopes(slope_x, slope_y, cover_glass_index)
        depth_glass = depth_display - cover_glass_mm
        radiance = _display_radiance(
            display, display_size_mm,
            start_x + depth_glass * slope_x + cover_glass_mm * glass_x,
            start_y + depth_glass * slope_y + cover_glass_mm * glass_y,
            subpixels,
        )  # fmt: skip
        if emission_exponent > 0:
            cos_air = 1.0 / np.sqrt(1.0 + slope_x**2 + slope_y**2)
            radiance = radiance * cos_air[None] ** emission_exponent
        if plate:
            passes = _passes_plate(
                radii, pitch_mm, gap_mm, thickness_mm, hole_axis, eye_relief_mm, tilt_target_mm,
                top_xy=(start_x + depth_top * slope_x, start_y + depth_top * slope_y),
                bottom_xy=(start_x + depth_bottom * slope_x, start_y + depth_bottom * slope_y),
            )  # fmt: skip
            radiance = radiance * passes[None, :, :]
        view[:, pixel_index] = radiance.mean(axis=2)
    return view.reshape(display.shape[0], ny_view, nx_view)


def _passes_plate(
    radii: np.ndarray,
    pitch_mm: tuple[float, float],
    gap_mm: float,
    thickness_mm: float,
    hole_axis: str,
    eye_relief_mm: float,
    tilt_target_mm: tuple[float, float],
    top_xy: tuple[np.ndarray, np.ndarray],
    bottom_xy: tuple[np.ndarray, np.ndarray],
) -> np.ndarray:
    """True where the ray passes one and the same hole at the bottom face, mid-plane, top face."""
    ny_cells, nx_cells = radii.shape
    px, py = pitch_mm
    z_mid = gap_mm + thickness_mm / 2.0
    z_eye = gap_mm + thickness_mm + eye_relief_mm
    # (height above mid-plane, ray x, ray y) at the three planes checked; rays are straight.
    mid_xy = ((top_xy[0] + bottom_xy[0]) / 2.0, (top_xy[1] + bottom_xy[1]) / 2.0)
    planes = (
        (-thickness_mm / 2.0, bottom_xy),
        (0.0, mid_xy),
        (thickness_mm / 2.0, top_xy),
    )
    # Any hole the ray passes contains its mid-plane point, so that point's cell and its 8
    # neighbours hold every candidate (radius < 1.5 pitch, checked in _validate).
    col_mid = np.rint(mid_xy[0] / px + (nx_cells - 1) / 2.0).astype(np.int64)
    row_mid = np.rint((ny_cells - 1) / 2.0 - mid_xy[1] / py).astype(np.int64)
    passes = np.zeros(mid_xy[0].shape, dtype=bool)
    for d_row in (-1, 0, 1):
        for d_col in (-1, 0, 1):
            row = row_mid + d_row
            col = col_mid + d_col
            inside = (row >= 0) & (row < ny_cells) & (col >= 0) & (col < nx_cells)
            # The plate is opaque beyond its grid: such cells count as closed.
            cell_radius = radii[np.clip(row, 0, ny_cells - 1), np.clip(col, 0, nx_cells - 1)]
            r = np.where(inside, cell_radius, 0.0)
            centre_x = (col - (nx_cells - 1) / 2.0) * px
            centre_y = ((ny_cells - 1) / 2.0 - row) * py
            if hole_axis == "chief_ray":
                # Axis through the cell centre at mid-thickness, aimed at the nominal eye point.
                axis_x = (tilt_target_mm[0] - centre_x) / (z_eye - z_mid)
                axis_y = (tilt_target_mm[1] - centre_y) / (z_eye - z_mid)
            else:
                axis_x = np.zeros_like(centre_x, dtype=np.float64)
                axis_y = np.zeros_like(centre_y, dtype=np.float64)
            in_this_hole = r > 0.0
            for height, (x, y) in planes:
                dx = x - (centre_x + height * axis_x)
                dy = y - (centre_y + height * axis_y)
                in_this_hole &= dx * dx + dy * dy <= r * r
            passes |= in_this_hole
    return passes


def _glass_slopes(slope_x: np.ndarray, slope_y: np.ndarray, index: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The ray's lateral slopes inside glass of `index`, by Snell's law at a face normal to z."""
    tan_air = np.hypot(slope_x, slope_y)
    sin_air = tan_air / np.sqrt(1.0 + tan_air**2)
    sin_glass = sin_air / index
    tan_glass = sin_glass / np.sqrt(1.0 - sin_glass**2)
    ratio = np.divide(tan_glass, tan_air, out=np.full_like(tan_air, 1.0 / index),
                      where=tan_air > 0)
    return slope_x * ratio, slope_y * ratio


#: Each channel's stripe centre, in pixels right of the pixel centre, per layout.
SUBPIXEL_ORDER = {"none": None, "rgb_stripe": (-1.0, 0.0, 1.0), "bgr_stripe": (1.0, 0.0, -1.0)}
STRIPES = 3


def _display_radiance(
    display: np.ndarray, display_size_mm: tuple[float, float], x: np.ndarray, y: np.ndarray,
    subpixels: str = "none",
) -> np.ndarray:
    """Radiance (C, *x.shape) of the piecewise-constant display at (x, y); 0 off the display.
    Striped sub-pixels (3 channels): channel c is lit, at 3 times its value, only on its stripe."""
    _, ny, nx = display.shape
    width, height = display_size_mm
    col_f = (x + width / 2.0) / width * nx
    col = np.floor(col_f).astype(np.int64)
    row = np.floor((height / 2.0 - y) / height * ny).astype(np.int64)
    on_display = (col >= 0) & (col < nx) & (row >= 0) & (row < ny)
    values = display[:, np.clip(row, 0, ny - 1), np.clip(col, 0, nx - 1)]
    order = SUBPIXEL_ORDER[subpixels]
    if order is not None and display.shape[0] == STRIPES:
        within = col_f - col - 0.5  # position in the pixel, -0.5 to 0.5
        stripes = [np.abs(within - o / STRIPES) < 0.5 / STRIPES for o in order]
        values = values * STRIPES * np.stack(stripes)
    return np.where(on_display[None], values, 0.0)


def _strata_per_dim(samples_per_pixel: int) -> int:
    # Integer fourth root, robust to float rounding (e.g. 4096 ** 0.25 = 7.999...).
    k = max(1, round(samples_per_pixel ** (1.0 / SAMPLE_DIMS)))
    while k**SAMPLE_DIMS > samples_per_pixel:
        k -= 1
    return k


def _strata_offsets(samples_per_pixel: int) -> np.ndarray:
    """Lower corner (in [0, 1)^4) of the stratum of each sample, shape (N, 4) float64."""
    k = _strata_per_dim(samples_per_pixel)
    n_samples = stratified_sample_count(samples_per_pixel)
    stratum = np.arange(n_samples) % k**SAMPLE_DIMS
    digits = np.stack([(stratum // k**d) % k for d in range(SAMPLE_DIMS)], axis=1)
    return digits.astype(np.float64) / k


def _validate(
    display: np.ndarray,
    display_size_mm: tuple[float, float],
    radii_mm: np.ndarray,
    pitch_mm: tuple[float, float],
    gap_mm: float,
    thickness_mm: float,
    hole_axis: str,
    pupil_mm: float,
    eye_relief_mm: float,
    focus_mm: float | None,
    tan_x_range: tuple[float, float],
    tan_y_range: tuple[float, float],
    view_pixels: tuple[int, int],
    samples_per_pixel: int,
) -> None:
    display = np.asarray(display)
    if display.ndim != 3 or 0 in display.shape or not np.all(np.isfinite(display)):
        raise ValueError(
            f"display has shape {display.shape}; expected a finite (C, ny, nx) array. "
            "Add a channel axis to a grey image: display[None]."
        )
    radii = np.asarray(radii_mm, dtype=np.float64)
    if radii.ndim != 2 or 0 in radii.shape or not np.all(np.isfinite(radii)) or radii.min() < 0:
        raise ValueError(
            f"radii_mm has shape {radii.shape} (min {radii.min() if radii.size else None}); "
            "expected a finite (ny_c, nx_c) array of radii >= 0 mm (0 = closed)."
        )
    positives = {
        "display_size_mm[0]": display_size_mm[0], "display_size_mm[1]": display_size_mm[1],
        "pitch_mm[0]": pitch_mm[0], "pitch_mm[1]": pitch_mm[1], "gap_mm": gap_mm,
        "pupil_mm": pupil_mm, "eye_relief_mm": eye_relief_mm,
    }  # fmt: skip
    if focus_mm is not None and not math.isinf(focus_mm):
        positives["focus_mm"] = focus_mm
    for name, value in positives.items():
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name} = {value!r} is out of range; allowed: {name} > 0 (mm).")
    if focus_mm is not None and focus_mm < 0:
        raise ValueError(f"focus_mm = {focus_mm!r}; allowed: > 0 mm, or None for infinity.")
    if not (math.isfinite(thickness_mm) and thickness_mm >= 0):
        raise ValueError(f"thickness_mm = {thickness_mm!r}; allowed: >= 0 mm.")
    if hole_axis not in HOLE_AXES:
        raise ValueError(f"hole_axis = {hole_axis!r}; allowed: {HOLE_AXES}.")
    max_radius = MAX_RADIUS_PER_PITCH * min(pitch_mm)
    if radii.max() >= max_radius:
        raise ValueError(
            f"radii_mm max = {radii.max():g} mm; allowed: < {MAX_RADIUS_PER_PITCH} x the smaller "
            f"pitch ({max_radius:g} mm), where the 3x3 neighbour search stays exact."
        )
    for name, (lo, hi) in (("tan_x_range", tan_x_range), ("tan_y_range", tan_y_range)):
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ValueError(f"{name} = {(lo, hi)!r}; allowed: finite lo < hi.")
    for name, count in (("view_pixels", view_pixels), ("samples_per_pixel", (samples_per_pixel,))):
        if not all(isinstance(n, (int, np.integer)) and n >= 1 for n in count):
            raise ValueError(f"{name} = {count!r}; allowed: whole numbers >= 1.")
