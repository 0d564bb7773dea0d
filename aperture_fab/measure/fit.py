"""Sub-pixel circles: each opening's centre and radius fitted to its edge.

Model (least squares over the pixels of the blob's territory around it): a disk of radius r at
(u, v) blurred by a Gaussian of sigma s, seen as

    I(rho) = b + (a - b) * erfc((rho - r) / (sqrt(2) s)) / 2,   rho = |pixel - (u, v)|,

with a the open level (the back light there) and b the solid's level. A pixel's own width adds
1/12 px^2 to s^2, which the fit absorbs. The erf edge of a curved disk sits inside the true rim
by about s^2 / (2 r) (the blurred disk's half-level contour), which is added back.

Two passes (`fit_circles`): the first fits all six numbers per hole; the blur and the back light
found on the holes wide enough to show them (`light_field`) are then held fixed for a second
pass, so that a hole little wider than the blur, whose peak never reaches the open level, still
gets a true radius.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.special import erfc

from aperture_fab.measure.detect import Blobs

__all__ = ["CircleFits", "LightField", "fit_circles", "light_field"]

SQRT2 = math.sqrt(2.0)
SQRT_PI = math.sqrt(math.pi)
#: Pixels beyond a blob's box that its fit sees, in blur sigmas (plus WINDOW_PAD_PX): the
#: erf edge's tail and enough solid to set b.
WINDOW_SIGMAS = 4.0
WINDOW_PAD_PX = 3
#: Blur sigma (px) the first pass starts from.
START_BLUR_PX = 1.0
#: Holes whose radius is at least this many blur sigmas show the blur and the open level
#: (their peak reaches it): only they set the second pass's fixed values.
WIDE_HOLE_SIGMAS = 3.0
#: Degree of the back light's polynomial in (u, v) (a smooth field: tilt and bowl).
LIGHT_DEGREE = 2
#: Smallest and largest blur the fit may return, px.
BLUR_RANGE_PX = (0.2, 20.0)


@dataclass(frozen=True)
class CircleFits:
    """Fitted circles, one per blob index given (all (N,) float64 unless stated).

    centres_px: (N, 2) (u, v) px. radii_px: rim radius, px (curvature-corrected). blur_px: the
    edge's sigma. open_level, solid_level: the fitted levels (share of full scale). residual:
    RMS misfit as a share of (open - solid). area_radius_px: the radius of a disk passing the
    same light (sum of (I - b) / (a - b) over the territory), a cross-check that no edge fit
    needs: it drops when dust covers part of a hole.
    """

    centres_px: np.ndarray
    radii_px: np.ndarray
    blur_px: np.ndarray
    open_level: np.ndarray
    solid_level: np.ndarray
    residual: np.ndarray
    area_radius_px: np.ndarray


@dataclass(frozen=True)
class LightField:
    """The back light's open level over the scan: a polynomial of degree LIGHT_DEGREE in
    (u / width, v / height) with coefficients `coefficients` ((d+1)(d+2)/2,) float64, and the
    scan's blur sigma blur_px (px), both found on the wide holes."""

    coefficients: np.ndarray
    scale_px: tuple[float, float]
    blur_px: float

    def at(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """The open level at pixels (u, v), same shape as u."""
        return _terms(u / self.scale_px[0], v / self.scale_px[1]) @ self.coefficients


def _terms(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    return np.stack([x ** i * y ** j for i in range(LIGHT_DEGREE + 1)
                     for j in range(LIGHT_DEGREE + 1 - i)], axis=-1)


def _window(blobs: Blobs, index: int, shape: tuple[int, int], blur_px: float
            ) -> tuple[slice, slice]:
    rows, cols = blobs.boxes[index]
    pad = math.ceil(WINDOW_SIGMAS * blur_px) + WINDOW_PAD_PX
    return (slice(max(0, rows.start - pad), min(shape[0], rows.stop + pad)),
            slice(max(0, cols.start - pad), min(shape[1], cols.stop + pad)))


def _pixels(image: np.ndarray, blobs: Blobs, index: int, blur_px: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u, v, value) of the pixels of blob `index`'s territory in its window, 1-D each."""
    rows, cols = _window(blobs, index, image.shape, blur_px)
    mine = blobs.territory[rows, cols] == index + 1
    vv, uu = np.nonzero(mine)
    return uu + cols.start + 0.0, vv + rows.start + 0.0, image[rows, cols][mine]


def _edge(rho: np.ndarray, r: float, s: float) -> tuple[np.ndarray, np.ndarray]:
    """erfc((rho - r) / (sqrt 2 s)) / 2 and its derivative in (rho - r) / (sqrt 2 s)."""
    e = (rho - r) / (SQRT2 * s)
    return 0.5 * erfc(e), -np.exp(-e * e) / SQRT_PI


def _fit_one(u: np.ndarray, v: np.ndarray, value: np.ndarray, start: np.ndarray,
             open_level: np.ndarray | None, blur_px: float | None) -> np.ndarray:
    """Least-squares (cu, cv, r, s, a, b); with open_level (per pixel) and blur_px given, only
    (cu, cv, r, b) are free. Returns all six (a: the mean open level over the pixels)."""
    free_all = open_level is None or blur_px is None

    def unpack(p: np.ndarray) -> tuple[float, float, float, float, np.ndarray | float, float]:
        if free_all:
            return p[0], p[1], p[2], p[3], p[4], p[5]
        assert open_level is not None and blur_px is not None
        return p[0], p[1], p[2], blur_px, open_level, p[3]

    def residual(p: np.ndarray) -> np.ndarray:
        cu, cv, r, s, a, b = unpack(p)
        rho = np.hypot(u - cu, v - cv)
        edge, _ = _edge(rho, r, s)
        return b + (a - b) * edge - value

    def jacobian(p: np.ndarray) -> np.ndarray:
        cu, cv, r, s, a, b = unpack(p)
        du, dv = u - cu, v - cv
        rho = np.maximum(np.hypot(du, dv), 1e-9)
        edge, slope = _edge(rho, r, s)
        k = (a - b) * slope / (SQRT2 * s)
        # d rho / d cu = -du / rho, and d edge / d rho = slope / (sqrt 2 s).
        columns = [-k * du / rho, -k * dv / rho, -k]
        if free_all:
            columns += [-k * (rho - r) / s, edge, 1 - edge]
        else:
            columns += [1 - edge]
        return np.column_stack(columns)

    x0 = start if free_all else start[[0, 1, 2, 5]]
    solved = least_squares(residual, x0, jac=jacobian, method="lm", x_scale="jac")
    cu, cv, r, s, a, b = unpack(solved.x)
    return np.array([cu, cv, r, s, float(np.mean(a)), b])


def _start(u: np.ndarray, v: np.ndarray, value: np.ndarray, solid: float, opened: float
           ) -> np.ndarray:
    """(cu, cv, r, s, a, b) to start from: the light-weighted centroid, the radius of a disk
    passing the same light."""
    weight = np.clip((value - solid) / (opened - solid), 0, None)
    total = max(float(weight.sum()), 1e-9)
    return np.array([float(weight @ u) / total, float(weight @ v) / total,
                     max(math.sqrt(total / math.pi), 0.5), START_BLUR_PX, opened, solid])


def fit_circles(image: np.ndarray, blobs: Blobs, indices: np.ndarray,
                light: LightField | None = None) -> CircleFits:
    """The circle of each blob in `indices` (0-based): all six numbers free without `light`,
    else the blur and the open level held at light's (module docstring)."""
    rows = []
    for index in indices:
        blur = START_BLUR_PX if light is None else light.blur_px
        u, v, value = _pixels(image, blobs, int(index), blur)
        start = _start(u, v, value, blobs.solid_level, blobs.open_level)
        if light is None:
            p = _fit_one(u, v, value, start, None, None)
        else:
            start[4] = float(np.mean(light.at(u, v)))
            p = _fit_one(u, v, value, start, light.at(u, v), light.blur_px)
        cu, cv, r, s, a, b = p
        s = float(np.clip(abs(s), *BLUR_RANGE_PX))
        model = b + (a - b) * _edge(np.hypot(u - cu, v - cv), r, s)[0]
        gap = max(a - b, 1e-9)
        misfit = float(np.sqrt(np.mean((model - value) ** 2))) / gap
        area = math.sqrt(max(float(np.sum((value - b) / gap)), 0.0) / math.pi)
        rim = r + s * s / (2 * r) if r > s else r  # the half-level contour lies inside the rim
        rows.append((cu, cv, rim, s, a, b, misfit, area))
    table = np.asarray(rows, dtype=np.float64).reshape(-1, 8)
    return CircleFits(table[:, :2].copy(), table[:, 2].copy(), table[:, 3].copy(),
                      table[:, 4].copy(), table[:, 5].copy(), table[:, 6].copy(),
                      table[:, 7].copy())


def light_field(fits: CircleFits, shape: tuple[int, int]) -> LightField:
    """The back light and blur found on the wide holes of a first pass (all holes when too few
    are wide): the median blur, and a least-squares polynomial through the open levels (a
    constant when there are too few holes for the polynomial)."""
    wide = fits.radii_px >= WIDE_HOLE_SIGMAS * fits.blur_px
    terms_needed = (LIGHT_DEGREE + 1) * (LIGHT_DEGREE + 2) // 2
    if wide.sum() < 1:
        wide = np.ones_like(wide)
    blur = float(np.median(fits.blur_px[wide]))
    height, width = shape
    scale = (float(width), float(height))
    u, v = fits.centres_px[wide, 0] / scale[0], fits.centres_px[wide, 1] / scale[1]
    levels = fits.open_level[wide]
    coefficients = np.zeros(terms_needed)
    coefficients[0] = float(np.median(levels))
    if wide.sum() >= 3 * terms_needed:
        terms = _terms(u, v)
        keep = np.ones(len(levels), dtype=bool)
        for _ in range(3):  # drop holes a speck of dust darkened, then refit
            coefficients = np.linalg.lstsq(terms[keep], levels[keep], rcond=None)[0]
            misfit = levels - terms @ coefficients
            spread = 1.4826 * float(np.median(np.abs(misfit[keep]))) + 1e-12
            keep = np.abs(misfit) < 4 * spread
    return LightField(coefficients, scale, blur)
