"""A scan simulator: a design's holes as a process makes them, as a flatbed scanner with a
transparency unit sees them (tests and examples know the truth this way).

The plate is rendered as transmission (1 open, 10^-OD solid) with area-correct holes (each
pixel's coverage from 8 x 8 sub-samples), then blurred by a Gaussian PSF, lit by an uneven back
light (a smooth gain field), given shot and read noise and quantized to 8 or 16 bits, grey or
RGB. A hole's image is the projection of its mid-thickness disk (the overlap of a tilted hole's
two face disks is not modelled: thin plates, see docs/measure.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from scipy.ndimage import gaussian_filter

from aperture_fab.fabrication.layout import HoleLayout
from aperture_fab.fabrication.mesh import outline_points_mm
from aperture_fab.measure.transform import ScanTransform, mm_per_px_of_dpi

__all__ = ["ScanBits", "ScanColour", "ScanSettings", "ScanTruth", "SimulatedScan",
           "Surround", "simulate_scan"]

ScanBits = Literal[8, 16]
ScanColour = Literal["grey", "rgb"]
#: What the scanner sees around the plate: its open back light, or a dark mask (black card).
Surround = Literal["open", "dark"]

#: Sub-samples per pixel side for a hole's coverage: 64 per pixel, so an edge pixel's area is
#: right to 1/128 and a hole's centre and radius are exact far below the measurement's error.
SUPERSAMPLE = 8
#: Relative gains of the R, G, B channels of a scan (a warm lamp, a slightly blue-poor sensor).
RGB_GAINS = (1.0, 0.97, 0.92)
#: Dust: radius range of a speck (mm), and how far (px) a speck stays from holes and the edge
#: when placed "on the solid".
DUST_RADIUS_MM = (0.004, 0.015)
DUST_CLEARANCE_PX = 3.0


@dataclass(frozen=True)
class ScanSettings:
    """How the plate is made and scanned.

    dpi: the scanner's nominal resolution. scale_error: share by which the real pixel size
    differs (px/mm = dpi / 25.4 * (1 + scale_error)). rotation_deg, mirror: how the plate lies
    (mirror: scanned from its back). offset_px: (u, v) shift of the plate from the image centre.
    border_mm: scan area beyond the plate's bounding box. surround: what lies around the plate.
    radius_bias_mm, radius_sigma_mm, position_sigma_mm: the process (made radius = drawn +
    bias + N(0, sigma); centres moved by N(0, sigma) in x and y). blur_px: Gaussian PSF sigma,
    px. light_unevenness: peak-to-peak share of the back light's smooth variation.
    open_level: an open hole's signal at the mean light, share of full scale. optical_density:
    the solid's. read_noise, shot_noise: noise sigma as shares of full scale (shot noise at
    full scale; it scales as the square root of the signal). dust_open: extra openings (pin
    holes) in the solid; dust_dark: dark specks on the glass over the solid; blocked: holes
    that did not open; closed_below_mm: holes whose made radius is under this stay closed (the
    process's smallest hole: what a calibration coupon measures). bits, colour: the file.
    seed: the random draws.
    """

    dpi: float = 4800.0
    scale_error: float = 0.0
    rotation_deg: float = 0.0
    mirror: bool = False
    offset_px: tuple[float, float] = (0.0, 0.0)
    border_mm: float = 0.6
    surround: Surround = "open"
    radius_bias_mm: float = -0.004
    radius_sigma_mm: float = 0.003
    position_sigma_mm: float = 0.004
    blur_px: float = 1.0
    light_unevenness: float = 0.2
    open_level: float = 0.8
    optical_density: float = 2.5
    read_noise: float = 0.004
    shot_noise: float = 0.01
    dust_open: int = 0
    dust_dark: int = 0
    blocked: int = 0
    closed_below_mm: float = 0.0
    bits: ScanBits = 16
    colour: ScanColour = "grey"
    seed: int = 0


@dataclass(frozen=True)
class ScanTruth:
    """What the simulated scan shows, in the design's frame.

    transform: design mm -> image px as the plate really lies. centres_mm: (K, 2) float64, each
    design hole's made centre, mm. radii_mm: (K,) float64, its made radius, mm. blocked: (K,)
    bool, holes that did not open. extra_centres_mm (M, 2) and extra_radii_mm (M,): openings in
    the solid (dust pin holes), mm. dark_centres_mm (D, 2): dark specks on the solid, mm.
    optical_density: the solid's.
    """

    transform: ScanTransform
    centres_mm: np.ndarray
    radii_mm: np.ndarray
    blocked: np.ndarray
    extra_centres_mm: np.ndarray
    extra_radii_mm: np.ndarray
    dark_centres_mm: np.ndarray
    optical_density: float


@dataclass(frozen=True)
class SimulatedScan:
    """A simulated scan: image (H, W) or (H, W, 3), uint8 or uint16 codes, linear in light;
    mm_per_px the nominal pixel size (from the dpi); truth what it shows."""

    image: np.ndarray
    mm_per_px: float
    truth: ScanTruth = field(repr=False)


def _disk_coverage(u: float, v: float, r: float, shape: tuple[int, int]
                   ) -> tuple[slice, slice, np.ndarray]:
    """Area share of each pixel covered by the disk (u, v, r) px: (rows, cols, (h, w))."""
    height, width = shape
    c0, c1 = max(0, math.floor(u - r) - 1), min(width, math.ceil(u + r) + 2)
    r0, r1 = max(0, math.floor(v - r) - 1), min(height, math.ceil(v + r) + 2)
    if c0 >= c1 or r0 >= r1:
        return slice(0, 0), slice(0, 0), np.zeros((0, 0))
    sub = (np.arange(SUPERSAMPLE) + 0.5) / SUPERSAMPLE - 0.5
    us = (np.arange(c0, c1)[:, None] + sub[None, :]).ravel() - u
    vs = (np.arange(r0, r1)[:, None] + sub[None, :]).ravel() - v
    inside = (vs[:, None] ** 2 + us[None, :] ** 2) <= r * r
    cover = inside.reshape(r1 - r0, SUPERSAMPLE, c1 - c0, SUPERSAMPLE).mean(axis=(1, 3))
    return slice(r0, r1), slice(c0, c1), cover


def _polygon_coverage(points_px: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Coverage (H, W) of a convex polygon, from each pixel's signed distance to its edges
    (exact for a straight edge far from a corner: the outline is not measured to sub-pixel)."""
    height, width = shape
    vv, uu = np.mgrid[0:height, 0:width].astype(np.float64)
    centroid = points_px.mean(axis=0)
    inside = np.full(shape, np.inf)
    for a, b in zip(points_px, np.roll(points_px, -1, axis=0), strict=True):
        normal = np.array([a[1] - b[1], b[0] - a[0]])
        normal /= np.hypot(*normal)
        if np.dot(centroid - a, normal) < 0:
            normal = -normal
        inside = np.minimum(inside, (uu - a[0]) * normal[0] + (vv - a[1]) * normal[1])
    return np.clip(inside + 0.5, 0.0, 1.0)


def _dust(rng: np.random.Generator, count: int, layout: HoleLayout, radii_mm: np.ndarray,
          centres_mm: np.ndarray, mm_per_px: float) -> tuple[np.ndarray, np.ndarray]:
    """`count` specks on the solid, clear of every hole and of the outline: (M, 2), (M,) mm."""
    half = np.array(layout.outline_mm) / 2
    clearance = DUST_CLEARANCE_PX * mm_per_px
    spots: list[tuple[float, float]] = []
    sizes: list[float] = []
    for _ in range(count * 200):
        if len(spots) == count:
            break
        r = float(rng.uniform(*DUST_RADIUS_MM))
        p = rng.uniform(-half * 0.9, half * 0.9)
        gaps = np.hypot(*(centres_mm - p).T) - radii_mm - r
        others = [math.hypot(p[0] - q[0], p[1] - q[1]) - r - s for q, s in zip(spots, sizes,
                                                                               strict=True)]
        if (gaps.size and gaps.min() < clearance) or min(others, default=np.inf) < clearance:
            continue
        spots.append((float(p[0]), float(p[1])))
        sizes.append(r)
    return np.asarray(spots, dtype=np.float64).reshape(-1, 2), np.asarray(sizes, np.float64)


def _transform(layout: HoleLayout, settings: ScanSettings, corner_cut_mm: float,
               rng: np.random.Generator) -> tuple[ScanTransform, tuple[int, int]]:
    """How the plate lies, and the image's (H, W): the plate's bounding box plus the border."""
    px_per_mm = (1 + settings.scale_error) / mm_per_px_of_dpi(settings.dpi)
    here = ScanTransform(settings.mirror, math.radians(settings.rotation_deg), px_per_mm,
                         (0.0, 0.0))
    corners = here.to_image(np.array(outline_points_mm(layout, corner_cut_mm)))
    border = settings.border_mm * px_per_mm
    width = math.ceil(np.ptp(corners[:, 0]) + 2 * border)
    height = math.ceil(np.ptp(corners[:, 1]) + 2 * border)
    # A random sub-pixel phase: holes do not sit on pixel centres in a real scan.
    phase = rng.uniform(0, 1, 2)
    centre = (width / 2 + settings.offset_px[0] + phase[0] - 0.5,
              height / 2 + settings.offset_px[1] + phase[1] - 0.5)
    return ScanTransform(settings.mirror, here.rotation_rad, px_per_mm, centre), (height, width)


def _light(shape: tuple[int, int], unevenness: float, rng: np.random.Generator) -> np.ndarray:
    """A smooth back-light gain (H, W) around 1: a tilt in a random direction and a bowl."""
    height, width = shape
    y, x = np.mgrid[-1:1:height * 1j, -1:1:width * 1j]
    angle = rng.uniform(0, 2 * math.pi)
    return 1 + unevenness / 2 * (0.6 * (math.cos(angle) * x + math.sin(angle) * y)
                                 + 0.4 * (1 - x * x - y * y) - 0.2)


def simulate_scan(layout: HoleLayout, settings: ScanSettings,
                  corner_cut_mm: float = 0.0) -> SimulatedScan:
    """The scan of `layout` as made and scanned per `settings` (module docstring); the plate's
    outline with its alignment chamfer of legs corner_cut_mm."""
    rng = np.random.default_rng(settings.seed)
    mm_per_px = mm_per_px_of_dpi(settings.dpi)
    transform, shape = _transform(layout, settings, corner_cut_mm, rng)
    k = layout.count
    radii = np.maximum(layout.radii_mm + settings.radius_bias_mm
                       + rng.normal(0, settings.radius_sigma_mm, k), 0.0)
    centres = layout.centres_mm + rng.normal(0, settings.position_sigma_mm, (k, 2))
    blocked = np.zeros(k, dtype=bool)
    blocked[rng.choice(k, size=min(settings.blocked, k), replace=False)] = True
    blocked |= radii < settings.closed_below_mm
    extra_c, extra_r = _dust(rng, settings.dust_open, layout, radii, centres, mm_per_px)
    dark_c, dark_r = _dust(rng, settings.dust_dark, layout, np.concatenate([radii, extra_r]),
                           np.concatenate([centres, extra_c]), mm_per_px)

    openings = np.zeros(shape)
    for (u, v), r in zip(transform.to_image(np.concatenate([centres[~blocked], extra_c])),
                         np.concatenate([radii[~blocked], extra_r]) * transform.px_per_mm,
                         strict=True):
        rows, cols, cover = _disk_coverage(u, v, r, shape)
        openings[rows, cols] += cover
    darkness = np.zeros(shape)
    for (u, v), r in zip(transform.to_image(dark_c), dark_r * transform.px_per_mm, strict=True):
        rows, cols, cover = _disk_coverage(u, v, r, shape)
        darkness[rows, cols] += cover
    solid = 10.0 ** -settings.optical_density
    plate = _polygon_coverage(transform.to_image(np.array(outline_points_mm(layout,
                                                                            corner_cut_mm))),
                              shape)
    around = 1.0 if settings.surround == "open" else 0.0
    transmission = (around * (1 - plate) + plate * (solid + (1 - solid) * np.minimum(openings, 1)))
    transmission *= 1 - np.minimum(darkness, 1)
    blurred = gaussian_filter(transmission, settings.blur_px, mode="nearest")
    signal = settings.open_level * _light(shape, settings.light_unevenness, rng) * blurred
    gains = RGB_GAINS if settings.colour == "rgb" else (1.0,)
    channels = []
    full = 2 ** settings.bits - 1
    for gain in gains:
        s = signal * gain
        noisy = s + rng.normal(size=shape) * np.sqrt(settings.read_noise ** 2
                                                     + settings.shot_noise ** 2 * s)
        channels.append(np.round(np.clip(noisy, 0, 1) * full))
    dtype = np.uint8 if settings.bits == 8 else np.uint16
    image = (channels[0] if len(channels) == 1 else np.stack(channels, axis=-1)).astype(dtype)
    truth = ScanTruth(transform, centres, radii, blocked, extra_c, extra_r, dark_c,
                      settings.optical_density)
    return SimulatedScan(image, mm_per_px, truth)
