"""Find the openings in a grey transmission scan: the bright connected regions between the
solid's level and the open level, each with its pixels' territory for the fit."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

__all__ = ["Blobs", "detect_blobs"]

#: Threshold between the solid's and the open level, as a share of the gap: low enough that a
#: hole only a little wider than the blur (whose peak does not reach the open level) is found.
THRESHOLD_SHARE = 0.3
#: The threshold must clear the solid's noise by this many sigma (no blob made of noise).
NOISE_SIGMA = 8.0
#: A blob of fewer pixels than this is not an opening (a hot pixel, a noise spike).
MIN_BLOB_PIXELS = 3
#: Pixels sampled for the levels: a whole scan's histogram is not needed to find two levels.
LEVEL_SAMPLES = 400_000
#: Histogram bins of Otsu's threshold.
OTSU_BINS = 512
#: Normal sigma per median absolute deviation.
MAD_SIGMA = 1.4826


@dataclass(frozen=True)
class Blobs:
    """The openings of a scan.

    labels: (H, W) int32, 0 for the solid, n for blob n (1-based). territory: (H, W) int32, the
    blob each pixel is nearest to (where its fit may look). boxes: per blob (row slice, column
    slice) of its pixels. pixels: (N,) int64 pixel count. touches_edge: (N,) bool, the blob
    reaches the image's edge (light around the plate, not a hole). solid_level, open_level:
    the scan's two levels (share of full scale); noise: the solid's noise sigma; threshold:
    where they were split.
    """

    labels: np.ndarray
    territory: np.ndarray
    boxes: tuple[tuple[slice, slice], ...]
    pixels: np.ndarray
    touches_edge: np.ndarray
    solid_level: float
    open_level: float
    noise: float
    threshold: float

    @property
    def count(self) -> int:
        return len(self.boxes)


def _otsu(values: np.ndarray) -> float:
    """Otsu's threshold of `values` (the split that best separates two classes)."""
    hist, edges = np.histogram(values, bins=OTSU_BINS)
    mids = (edges[:-1] + edges[1:]) / 2
    weight = np.cumsum(hist)
    mean = np.cumsum(hist * mids)
    total, total_mean = weight[-1], mean[-1]
    w0, w1 = weight[:-1], total - weight[:-1]
    valid = (w0 > 0) & (w1 > 0)
    between = np.zeros_like(mids[:-1])
    m0 = mean[:-1][valid] / w0[valid]
    m1 = (total_mean - mean[:-1][valid]) / w1[valid]
    between[valid] = w0[valid] * w1[valid] * (m0 - m1) ** 2
    return float(edges[1:][np.argmax(between)])


def detect_blobs(image: np.ndarray) -> Blobs | None:
    """The openings of a grey scan (H, W) float64 in [0, 1], or None when there are none (an
    image of one level, or one whose bright part is only noise)."""
    flat = image.ravel()
    step = max(1, flat.size // LEVEL_SAMPLES)
    sample = flat[::step]
    if float(np.ptp(sample)) <= 0:
        return None
    split = _otsu(sample)
    dark, bright = sample[sample < split], sample[sample >= split]
    if dark.size == 0 or bright.size == 0:
        return None
    solid = float(np.median(dark))
    noise = MAD_SIGMA * float(np.median(np.abs(dark - solid)))
    # The open level: a high percentile of the bright class (the middle of holes and the light
    # around the plate), not its median, which blurred edges pull down.
    opened = float(np.percentile(bright, 90))
    threshold = solid + THRESHOLD_SHARE * (opened - solid)
    if threshold < solid + NOISE_SIGMA * noise:
        return None
    labels, count = ndimage.label(image > threshold)
    labels = labels.astype(np.int32)
    pixels = np.bincount(labels.ravel(), minlength=count + 1)[1:].astype(np.int64)
    keep = np.flatnonzero(pixels >= MIN_BLOB_PIXELS) + 1
    if keep.size < count:  # drop noise specks and renumber
        relabel = np.zeros(count + 1, dtype=np.int32)
        relabel[keep] = np.arange(1, keep.size + 1, dtype=np.int32)
        labels = relabel[labels]
        pixels = pixels[keep - 1]
        count = keep.size
    if count == 0:
        return None
    boxes = tuple((b[0], b[1]) for b in ndimage.find_objects(labels) if b is not None)
    height, width = image.shape
    edge = np.array([b[0].start == 0 or b[1].start == 0 or b[0].stop == height
                     or b[1].stop == width for b in boxes])
    # Each pixel goes to its nearest blob: a fit sees its own hole's edge, not a neighbour's.
    _, (rows, cols) = ndimage.distance_transform_edt(labels == 0, return_indices=True)
    territory = labels[rows, cols]
    return Blobs(labels, territory, boxes, pixels, edge, solid, opened, noise, threshold)
