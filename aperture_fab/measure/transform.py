"""Where the plate lies in a scan: a similarity transform, with an optional mirror, from the
design's millimetres (x right, y up, seen from the eye) to the image's pixels (column u to the
right, row v down, pixel centres at whole numbers)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["MM_PER_INCH", "ScanTransform", "mm_per_px_of_dpi"]

#: Millimetres per inch: a scanner's dpi is pixels per 25.4 mm.
MM_PER_INCH = 25.4


def mm_per_px_of_dpi(dpi: float) -> float:
    """The pixel size (mm) of a scan at `dpi` dots per inch."""
    if not (math.isfinite(dpi) and dpi > 0):
        raise ValueError(f"dpi = {dpi!r} must be a positive number, e.g. 4800.")
    return MM_PER_INCH / dpi


@dataclass(frozen=True)
class ScanTransform:
    """design (x, y) mm -> image (u, v) px: mirror x (x -> -x) when `mirror`, rotate by
    rotation_rad counter-clockwise (as seen in the design's frame), scale by px_per_mm, then
    u = centre_px[0] + x', v = centre_px[1] - y' (image rows grow downwards).

    mirror: the scan shows the plate from its back (the wrong side). rotation_rad: radians.
    px_per_mm: pixels per mm as the plate really lies on the scanner. centre_px: (u, v) of the
    design's origin, px.
    """

    mirror: bool
    rotation_rad: float
    px_per_mm: float
    centre_px: tuple[float, float]

    def _rotation(self) -> np.ndarray:
        c, s = math.cos(self.rotation_rad), math.sin(self.rotation_rad)
        return np.array([[c, -s], [s, c]])

    def to_image(self, points_mm: np.ndarray) -> np.ndarray:
        """(N, 2) float64 design mm -> (N, 2) float64 image (u, v) px."""
        p = np.asarray(points_mm, dtype=np.float64).reshape(-1, 2).copy()
        if self.mirror:
            p[:, 0] = -p[:, 0]
        r = p @ self._rotation().T * self.px_per_mm
        return np.column_stack([self.centre_px[0] + r[:, 0], self.centre_px[1] - r[:, 1]])

    def to_design(self, points_px: np.ndarray) -> np.ndarray:
        """(N, 2) float64 image (u, v) px -> (N, 2) float64 design mm (the inverse)."""
        q = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
        r = np.column_stack([q[:, 0] - self.centre_px[0], self.centre_px[1] - q[:, 1]])
        p = r @ self._rotation() / self.px_per_mm
        if self.mirror:
            p[:, 0] = -p[:, 0]
        return p
