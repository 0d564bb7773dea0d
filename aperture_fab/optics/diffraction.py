"""A diffraction-aware view: each hole's light spread in angle by its own Airy pattern.

The geometric model (aperture_fab.optics.model) neglects diffraction. Light through a circular hole
of diameter d is spread in angle by the Airy pattern I(theta) ~ [2 J1(x) / x]^2 with x = pi d
sin(theta) / lambda (first dark ring at sin(theta) = 1.22 lambda / d). Display pixels are mutually
incoherent, so intensities add: the diffraction-aware view is the geometric view of each hole's
light convolved with that hole's Airy pattern, per colour channel.

`diffraction_view` groups the holes by diameter (a quantized layout has a few distinct sizes;
continuous ones are binned into log-spaced classes), renders the geometric view with only one
class open, convolves each channel with the Airy kernel of the class's diameter at the channel's
wavelength, and sums over classes. It is linear in the display and conserves light, except that
light spread past the view's border is lost (zero padding): near the border the view is darker
than it should be by up to half the kernel's mass.

`AiryMixture` is the same physics in a form cheap and differentiable enough for the optimizer
and the report's headline: the view of all holes together blurred by one kernel per channel, the
light-weighted mixture of the Airy kernels of a few log-spaced diameters (each hole's light split
between the two classes around its diameter, linearly in log diameter). It is exact when holes of
every size are spread evenly over the plate and differs from `diffraction_view` where one region
holds mostly small holes and another mostly large ones (tests/test_diffraction.py measures the
difference on made layouts).

Approximations:

- the kernel is shift-invariant in tan(angle) with x = pi d rho / lambda, rho the tan-distance
  from the kernel centre (small angles: tan ~ sin ~ theta); at 26 deg off axis the true pattern
  is about 1 / cos^2 = 1.24 times wider in tan units than modelled;
- geometric blur and Airy spread are combined by convolution (the usual pinhole-camera treatment),
  not by a full Fresnel calculation of a hole lit by a point 10 mm away;
- the hole's diameter sets the pattern: in a thick straight-hole plate the oblique aperture (the
  two-disk lens) is narrower and diffracts more than modelled;
- classes share one mean diameter (binned layouts only; at most (d_max / d_min)^(1 / classes)
  apart within a class);
- the kernel is truncated where its encircled energy reaches 99.5 % and renormalized.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from aperture_fab.optics.model import Renderer
from aperture_fab.optics.scene import check_positive

__all__ = [
    "WAVELENGTHS_NM",
    "HoleClass",
    "airy_kernel",
    "airy_blur_px",
    "hole_classes",
    "diffraction_view",
    "AiryMixture",
    "airy_mixture",
]

#: Wavelengths (nm) of the red, green and blue channels; a single channel uses green's.
WAVELENGTHS_NM: tuple[float, float, float] = (630.0, 530.0, 460.0)
GREEN_INDEX = 1
MM_PER_NM = 1e-6
#: First zero of J1: the first dark ring is at x = 3.8317, sin(theta) = 1.2197 lambda / d.
AIRY_FIRST_ZERO_X = 3.8317059702075125
#: The kernel is truncated where the Airy pattern's encircled energy reaches this fraction.
KERNEL_ENERGY = 0.995
#: Sub-samples per first-dark-ring radius when integrating the kernel over a view pixel.
SAMPLES_PER_ZERO = 4
MIN_SUBSAMPLES = 3
#: Binned classes start no lower than d_max * this; smaller holes (each passing under 1e-4 of
#: the largest hole's light) join the smallest class instead of spending classes on dust.
SMALLEST_CLASS_RATIO = 0.01
_BISECTION_STEPS = 80


@dataclass(frozen=True)
class HoleClass:
    """Holes of (about) one diameter.

    diameter_mm: the class's diameter (exact, or the area-weighted mean of a bin), mm.
    mask: (rows, cols) bool tensor, True for the cells whose hole is in the class.
    """

    diameter_mm: float
    mask: torch.Tensor


def _check_step(view_step: tuple[float, float]) -> None:
    if not (isinstance(view_step, tuple) and len(view_step) == 2):
        raise TypeError(f"view_step must be a pair (x, y) of tan steps, got {view_step!r}")
    for step in view_step:
        check_positive("view_step", step, "Use Eye.view_step (view pixel size in tan units).")


def _encircled_energy(x: float) -> float:
    """Fraction of the Airy pattern's light within x: 1 - J0(x)^2 - J1(x)^2 (monotonic)."""
    t = torch.tensor(x, dtype=torch.float64)
    return float(1 - torch.special.bessel_j0(t) ** 2 - torch.special.bessel_j1(t) ** 2)


def _truncation_x(energy: float) -> float:
    """The x at which the encircled energy reaches `energy` (about 127 for 99.5 %)."""
    # 1 - EE(x) ~ 2 / (pi x) for large x, so the crossing lies below 4 / (pi (1 - energy)).
    lo, hi = 0.0, 4 / (math.pi * (1 - energy))
    for _ in range(_BISECTION_STEPS):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if _encircled_energy(mid) < energy else (lo, mid)
    return hi


def _airy(x: torch.Tensor) -> torch.Tensor:
    """[2 J1(x) / x]^2, 1 at x = 0."""
    safe = torch.where(x.abs() < 1e-8, torch.ones_like(x), x)
    return torch.where(x.abs() < 1e-8, torch.ones_like(x),
                       (2 * torch.special.bessel_j1(safe) / safe) ** 2)


def airy_kernel(
    diameter_mm: float,
    wavelength_mm: float,
    view_step: tuple[float, float],
    max_radius_px: int | None = None,
) -> np.ndarray:
    """The Airy pattern of a hole on the view grid: (2 ky + 1, 2 kx + 1) float64, sum 1.

    Entry (ky + j, kx + i) is the pattern's light in the view pixel offset by (i, j) pixels, by
    midpoint integration over the pixel (at least SAMPLES_PER_ZERO samples per first-ring radius).
    Pixels wholly outside the radius holding KERNEL_ENERGY of the light are dropped (and all
    beyond max_radius_px pixels along the finer axis), then the kernel is renormalized.
    """
    check_positive("diameter_mm", diameter_mm, "Give the hole's diameter in mm.")
    check_positive("wavelength_mm", wavelength_mm, "Give the wavelength in mm (550 nm = 5.5e-4).")
    _check_step(view_step)
    if max_radius_px is not None and not (isinstance(max_radius_px, int) and max_radius_px >= 0):
        raise ValueError(f"max_radius_px = {max_radius_px!r} must be a whole number >= 0 or None.")
    sx, sy = view_step
    scale = math.pi * diameter_mm / wavelength_mm  # x per unit tan
    reach = _truncation_x(KERNEL_ENERGY) / scale  # tan
    if max_radius_px is not None:
        reach = min(reach, max_radius_px * min(sx, sy))
    # Keep a pixel if its nearest point lies within the reach.
    kx, ky = max(0, math.ceil(reach / sx - 0.5)), max(0, math.ceil(reach / sy - 0.5))
    if kx == 0 and ky == 0:
        return np.ones((1, 1))
    zero = AIRY_FIRST_ZERO_X / scale
    nx = max(MIN_SUBSAMPLES, math.ceil(SAMPLES_PER_ZERO * sx / zero))
    ny = max(MIN_SUBSAMPLES, math.ceil(SAMPLES_PER_ZERO * sy / zero))
    f64 = torch.float64
    sub_x = (torch.arange(nx, dtype=f64) + 0.5) / nx - 0.5
    cols = ((torch.arange(-kx, kx + 1, dtype=f64)[:, None] + sub_x[None, :]) * sx).reshape(-1)
    rows = torch.arange(-ky, ky + 1, dtype=f64) * sy
    kernel = torch.zeros(2 * ky + 1, 2 * kx + 1, dtype=f64)
    # One sub-row at a time: memory stays at one kernel's worth of samples times nx.
    for k in range(ny):
        y = rows + ((k + 0.5) / ny - 0.5) * sy
        rho = torch.sqrt(y[:, None] ** 2 + cols[None, :] ** 2)
        kernel += _airy(scale * rho).reshape(2 * ky + 1, 2 * kx + 1, nx).sum(-1)
    near_x = (torch.arange(-kx, kx + 1, dtype=f64).abs() - 0.5).clamp_min(0) * sx
    near_y = (torch.arange(-ky, ky + 1, dtype=f64).abs() - 0.5).clamp_min(0) * sy
    kernel *= (near_y[:, None] ** 2 + near_x[None, :] ** 2) <= reach**2
    return (kernel / kernel.sum()).numpy()


def airy_blur_px(diameter_mm: float, wavelength_mm: float, view_step: tuple[float, float]
                 ) -> float:
    """Radius of the first dark ring, 1.22 lambda / d, in view pixels (of the geometric-mean
    size sqrt(step_x step_y))."""
    check_positive("diameter_mm", diameter_mm, "Give the hole's diameter in mm.")
    check_positive("wavelength_mm", wavelength_mm, "Give the wavelength in mm (550 nm = 5.5e-4).")
    _check_step(view_step)
    zero = AIRY_FIRST_ZERO_X / math.pi * wavelength_mm / diameter_mm
    return zero / math.sqrt(view_step[0] * view_step[1])


def hole_classes(open_fraction: torch.Tensor, pitch_mm: tuple[float, float],
                 max_classes: int = 12) -> list[HoleClass]:
    """Group the open holes (fraction > 0) of a (rows, cols) layout by diameter
    d = 2 sqrt(a px py / pi): one class per distinct diameter if there are at most max_classes,
    else max_classes log-spaced bins from the smallest diameter (but at least d_max *
    SMALLEST_CLASS_RATIO) to d_max, each with its area-weighted mean diameter. Classes are sorted
    by diameter; empty ones are dropped."""
    if not (isinstance(max_classes, int) and max_classes >= 1):
        raise ValueError(f"max_classes = {max_classes!r} must be a whole number >= 1.")
    a = open_fraction.detach().to(torch.float64)
    diameter = 2 * torch.sqrt(a.clamp_min(0) * (pitch_mm[0] * pitch_mm[1] / math.pi))
    is_open = a > 0
    if not bool(is_open.any()):
        return []
    distinct = torch.unique(diameter[is_open])
    if distinct.numel() <= max_classes:
        return [HoleClass(float(d), is_open & (diameter == d)) for d in distinct]
    d_max = float(distinct[-1])
    d_low = max(float(distinct[0]), d_max * SMALLEST_CLASS_RATIO)
    edges = torch.logspace(math.log10(d_low), math.log10(d_max),
                           max_classes + 1, dtype=torch.float64, device=diameter.device)
    # Interior edges only: smaller holes fall in bin 0, the largest in the last bin.
    index = torch.bucketize(diameter, edges[1:-1], right=True)
    classes = []
    for k in range(max_classes):
        mask = is_open & (index == k)
        if bool(mask.any()):
            mean = float((a[mask] * diameter[mask]).sum() / a[mask].sum())
            classes.append(HoleClass(mean, mask))
    return classes


def _channel_wavelengths_mm(channels: int, wavelengths_nm: tuple[float, ...]) -> list[float]:
    for w in wavelengths_nm:
        check_positive("wavelengths_nm", w, "Give one wavelength per channel in nm, e.g. 530.")
    if len(wavelengths_nm) == channels:
        return [w * MM_PER_NM for w in wavelengths_nm]
    if channels == 1 and len(wavelengths_nm) == len(WAVELENGTHS_NM):
        return [wavelengths_nm[GREEN_INDEX] * MM_PER_NM]
    raise ValueError(
        f"wavelengths_nm has {len(wavelengths_nm)} values for a display of {channels} channels; "
        "give one wavelength per channel (or RGB wavelengths for a single grey channel)."
    )


def _convolve_same(image: torch.Tensor, kernel: torch.Tensor) -> torch.Tensor:
    """image (ny, nx) convolved with an odd-sized kernel, zero padding, cropped to the image:
    what F.conv2d(padding=k) gives for a symmetric kernel, but by FFT, since a direct convolution
    with a 100-pixel kernel over a 128-pixel view takes seconds."""
    kh, kw = kernel.shape
    ny, nx = image.shape
    shape = (ny + kh - 1, nx + kw - 1)
    spectrum = torch.fft.rfft2(image, s=shape) * torch.fft.rfft2(kernel, s=shape)
    full = torch.fft.irfft2(spectrum, s=shape)
    return full[kh // 2 : kh // 2 + ny, kw // 2 : kw // 2 + nx]


def diffraction_view(
    renderer: Renderer,
    open_fraction: torch.Tensor,
    display: torch.Tensor,
    position: int = 0,
    wavelengths_nm: tuple[float, ...] = WAVELENGTHS_NM,
    max_classes: int = 12,
) -> torch.Tensor:
    """The view (C, ny, nx) through holes of open-area fractions (rows, cols) onto a display
    (C, H, W), in the renderer's dtype and device, with each hole's light spread by its Airy
    pattern at each channel's wavelength (C = 3: wavelengths_nm per channel; C = 1: green).

    Light spread past the view's border is lost (zero padding). Kernels reach at most the view's
    larger side, beyond which they could only carry light out of the view.
    """
    if display.ndim != 3:
        raise ValueError(f"display must be (C, H, W), got shape {tuple(display.shape)}.")
    waves = _channel_wavelengths_mm(display.shape[0], wavelengths_nm)
    eye = renderer.scene.eye
    a = open_fraction.to(renderer.device, renderer.dtype)
    stack = renderer.display_stack(display)
    view = torch.zeros(display.shape[0], eye.view_pixels[1], eye.view_pixels[0],
                       dtype=renderer.dtype, device=renderer.device)
    for group in hole_classes(a, renderer.scene.plate.pitch_mm, max_classes):
        mask = group.mask.to(a.device)
        part = renderer.render_stack(torch.where(mask, a, torch.zeros_like(a)), stack, position)
        spread = []
        for channel, wave in enumerate(waves):
            kernel = airy_kernel(group.diameter_mm, wave, eye.view_step, max(eye.view_pixels))
            k = torch.as_tensor(kernel, dtype=part.dtype, device=part.device)
            spread.append(_convolve_same(part[channel], k))
        view = view + torch.stack(spread)
    return view


#: Diameter classes of an AiryMixture (log-spaced between the smallest and largest hole).
MIXTURE_CLASSES = 6
#: An AiryMixture's kernels reach this many view pixels: beyond it lies under 3 % of the light of
#: a 25 um hole at 530 nm on a 0.34 deg view pixel (1 - EE(x) ~ 2 / (pi x)), less for larger
#: holes; the kernel is renormalized, so that light stays in the core instead of a faint halo.
#: Four times cheaper per iteration than the view-wide reach of `diffraction_view`.
MIXTURE_REACH_PX = 32


@dataclass(frozen=True)
class AiryMixture:
    """Airy kernels of a few hole diameters on one view grid, to blur a view by the
    light-weighted mixture of its holes' patterns (module docstring).

    diameters_mm: (K,) float64, log-spaced class diameters, increasing.
    spectra: (C, K, fy, fx // 2 + 1) complex, each class kernel's FFT per channel, padded for a
        linear (not circular) convolution of a view of `view_shape`.
    kernel_shape: (kh, kw) of the padded kernels (odd); view_shape: (ny, nx).
    """

    diameters_mm: np.ndarray
    spectra: torch.Tensor
    kernel_shape: tuple[int, int]
    view_shape: tuple[int, int]

    def weights(self, open_fraction: torch.Tensor, pitch_mm: tuple[float, float]
                ) -> torch.Tensor:
        """(K,) share of the light through holes (rows, cols) in each class: each hole weighs
        by its area and splits between the two classes around its diameter, linearly in log
        diameter (holes outside the range count in the end class). Differentiable."""
        a = open_fraction.reshape(-1).clamp_min(0)
        area = a * (pitch_mm[0] * pitch_mm[1])
        diameter = 2 * torch.sqrt(area / math.pi + 1e-30)
        logs = torch.as_tensor(np.log(self.diameters_mm), dtype=a.dtype, device=a.device)
        k = len(self.diameters_mm)
        if k == 1:
            return torch.ones(1, dtype=a.dtype, device=a.device)
        t = ((torch.log(diameter) - logs[0]) / (logs[1] - logs[0])).clamp(0, k - 1)
        low = t.detach().floor().clamp(max=k - 2).long()
        frac = t - low
        total = area.sum().clamp_min(1e-30)
        share = torch.zeros(k, dtype=a.dtype, device=a.device)
        share = share.index_add(0, low, area * (1 - frac)).index_add(0, low + 1, area * frac)
        return share / total

    def blur(self, views: torch.Tensor, open_fraction: torch.Tensor,
             pitch_mm: tuple[float, float]) -> torch.Tensor:
        """Views (..., C, ny, nx) through holes (rows, cols) blurred by their Airy mixture;
        zero padding (light spread past the border is lost, as in `diffraction_view`)."""
        if tuple(views.shape[-2:]) != self.view_shape:
            raise ValueError(f"views have shape {tuple(views.shape)}; this mixture is for "
                             f"views of {self.view_shape}.")
        complex_dtype = torch.complex128 if views.dtype == torch.float64 else torch.complex64
        w = self.weights(open_fraction, pitch_mm).to(views.dtype)
        spectra = self.spectra.to(views.device, complex_dtype)
        kernel = (spectra * w.to(complex_dtype)[None, :, None, None]).sum(1)  # (C, fy, fx')
        channels = views.shape[-3]
        if channels == 1 and kernel.shape[0] != 1:
            kernel = kernel[GREEN_INDEX : GREEN_INDEX + 1]
        (ny, nx), (kh, kw) = self.view_shape, self.kernel_shape
        shape = (ny + kh - 1, nx + kw - 1)
        full = torch.fft.irfft2(torch.fft.rfft2(views, s=shape) * kernel, s=shape)
        return full[..., kh // 2 : kh // 2 + ny, kw // 2 : kw // 2 + nx]


def airy_mixture(d_min_mm: float, d_max_mm: float, view_step: tuple[float, float],
                 view_pixels: tuple[int, int], wavelengths_nm: tuple[float, ...] =
                 WAVELENGTHS_NM, classes: int = MIXTURE_CLASSES,
                 reach_px: int = MIXTURE_REACH_PX) -> AiryMixture:
    """The Airy kernels of `classes` log-spaced diameters from d_min_mm to d_max_mm, per
    wavelength (one channel each), on a view grid of view_pixels (nx, ny) and view_step (tan);
    kernels reach at most reach_px view pixels (and the view's larger side)."""
    check_positive("d_min_mm", d_min_mm, "Give the smallest hole's diameter in mm.")
    if not d_max_mm >= d_min_mm:
        raise ValueError(f"d_max_mm = {d_max_mm!r} must be >= d_min_mm = {d_min_mm!r}.")
    if not (isinstance(classes, int) and classes >= 1):
        raise ValueError(f"classes = {classes!r} must be a whole number >= 1.")
    count = classes if d_max_mm > d_min_mm else 1
    diameters = np.geomspace(d_min_mm, d_max_mm, count)
    waves = [w * MM_PER_NM for w in wavelengths_nm]
    reach = min(reach_px, max(view_pixels))
    kernels = [[airy_kernel(float(d), wave, view_step, reach) for d in diameters]
               for wave in waves]
    kh = max(k.shape[0] for row in kernels for k in row)
    kw = max(k.shape[1] for row in kernels for k in row)
    padded = np.zeros((len(waves), count, kh, kw))
    for c, row in enumerate(kernels):
        for i, k in enumerate(row):
            y0, x0 = (kh - k.shape[0]) // 2, (kw - k.shape[1]) // 2
            padded[c, i, y0 : y0 + k.shape[0], x0 : x0 + k.shape[1]] = k
    nx, ny = view_pixels
    shape = (ny + kh - 1, nx + kw - 1)
    spectra = torch.fft.rfft2(torch.as_tensor(padded), s=shape)
    return AiryMixture(diameters, spectra, (kh, kw), (ny, nx))
