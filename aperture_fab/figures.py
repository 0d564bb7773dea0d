"""The validation report's figures: PNG bytes from arrays, drawn with matplotlib.

Pure functions, values in and PNG bytes out; aperture_fab.report_html places them on the page.
matplotlib is imported inside the functions (an optional package: pip install matplotlib), and
only its object-oriented API is used, so no pyplot global figure state.
"""

from __future__ import annotations

import io
import math
from typing import Any, Literal

import numpy as np

from aperture_fab.images import linear_to_srgb
from aperture_fab.metrics import gain

__all__ = ["figure_views", "figure_hole_map", "figure_loss", "figure_histogram"]

FIGURE_DPI = 100
#: Width and height of one image panel in figure_views (inches).
PANEL_INCHES = 2.2
MAX_PANELS_PER_ROW = 6
UM_PER_MM = 1000.0


def _figure(width_in: float, height_in: float) -> Any:
    """A matplotlib Figure on the Agg canvas; no pyplot, so no global figure state."""
    try:
        from matplotlib.figure import Figure
    except ImportError as err:
        raise ImportError("report figures need matplotlib: pip install matplotlib") from err
    return Figure(figsize=(width_in, height_in), dpi=FIGURE_DPI, layout="constrained")


def _png(fig: Any) -> bytes:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    return buffer.getvalue()


def _as_rgb(image: np.ndarray, name: str) -> np.ndarray:
    """(C, ny, nx) or (ny, nx) linear image to (ny, nx, 3) float64."""
    array = np.asarray(image, dtype=np.float64)
    if array.ndim == 2:
        array = array[None]
    if array.ndim != 3 or array.shape[0] not in (1, 3) or min(array.shape) == 0:
        raise ValueError(f"{name} has shape {array.shape}; expected (C, ny, nx) with C = 1 or 3, "
                         "or (ny, nx).")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} holds NaN or infinite values.")
    return np.repeat(array, 3 // array.shape[0], axis=0).transpose(1, 2, 0)


def figure_views(rows: list[tuple[str, np.ndarray]], title: str, *,
                 gain_to_first: bool = True) -> bytes:
    """PNG of labelled images side by side (wrapping after MAX_PANELS_PER_ROW), in sRGB.

    rows: (label, image) pairs, images (C, ny, nx) or (ny, nx) in linear light; the first is
        usually the target.
    gain_to_first: scale each later image by its least-squares gain onto the first (the eye
        cannot see more light than the holes pass: compare shapes, not levels); images must then
        share the first one's shape. Images are clipped to [0, 1] for display.
    """
    if not rows:
        raise ValueError("figure_views got no images; give (label, image) pairs.")
    images = [_as_rgb(image, f"image {label!r}") for label, image in rows]
    if gain_to_first:
        for i, image in enumerate(images[1:], start=1):
            if image.shape != images[0].shape:
                raise ValueError(f"image {rows[i][0]!r} has shape {image.shape[:2]} but the first "
                                 f"has {images[0].shape[:2]}; gain_to_first needs equal shapes.")
            images[i] = image * gain(image, images[0])
    cols = min(len(rows), MAX_PANELS_PER_ROW)
    lines = math.ceil(len(rows) / cols)
    fig = _figure(cols * PANEL_INCHES, lines * PANEL_INCHES + 0.4)
    fig.suptitle(title)
    for i, ((label, _), image) in enumerate(zip(rows, images, strict=True)):
        ax = fig.add_subplot(lines, cols, i + 1)
        ax.imshow(linear_to_srgb(np.clip(image, 0.0, 1.0)), interpolation="nearest")
        ax.set_title(label, fontsize=9)
        ax.set_axis_off()
    return _png(fig)


def figure_hole_map(values: np.ndarray, pitch_mm: tuple[float, float], *,
                    kind: Literal["radius_mm", "open_fraction"] = "radius_mm") -> bytes:
    """PNG colour map of each cell's hole diameter (um), closed cells grey, axes in mm.

    values: (rows, cols) hole radii in mm, or open-area fractions a = pi r^2 / (px py).
    pitch_mm: (px, py) cell pitch.
    """
    array = np.asarray(values, dtype=np.float64)
    if array.ndim != 2 or min(array.shape) == 0 or not np.all(np.isfinite(array)):
        raise ValueError(f"hole map values have shape {array.shape}; expected finite "
                         "(rows, cols).")
    if array.min() < 0:
        raise ValueError(f"hole map {kind} values go down to {array.min():g}; allowed: >= 0.")
    px, py = pitch_mm
    radii = array if kind == "radius_mm" else np.sqrt(array * px * py / math.pi)
    diameter_um = np.ma.masked_less_equal(2 * radii * UM_PER_MM, 0.0)
    rows, cols = array.shape
    half_w, half_h = cols * px / 2, rows * py / 2
    import matplotlib as mpl  # _figure has checked that matplotlib is there

    fig = _figure(5.0, 4.2)
    cmap = mpl.colormaps["viridis"].with_extremes(bad="0.8")
    ax = fig.add_subplot()
    shown = ax.imshow(diameter_um, cmap=cmap, interpolation="nearest",
                      extent=(-half_w, half_w, -half_h, half_h))
    fig.colorbar(shown, ax=ax, label="hole diameter (µm)")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(f"{int(np.count_nonzero(radii > 0))} holes (grey: closed)")
    return _png(fig)


def figure_loss(history: np.ndarray) -> bytes:
    """PNG of the loss per iteration (log scale when every value is positive)."""
    values = np.asarray(history, dtype=np.float64)
    if values.ndim != 1 or values.size == 0 or not np.all(np.isfinite(values)):
        raise ValueError(f"loss history has shape {values.shape}; expected finite (N,), N >= 1.")
    fig = _figure(5.0, 3.2)
    ax = fig.add_subplot()
    ax.plot(np.arange(1, values.size + 1), values)
    if values.min() > 0:
        ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss (MSE after gain)")
    ax.grid(True, which="both", alpha=0.3)
    return _png(fig)


def figure_histogram(values: np.ndarray, threshold: float | None) -> bytes:
    """PNG histogram of PSNR (dB) over tolerance samples, with the yield threshold marked."""
    data = np.asarray(values, dtype=np.float64)
    if data.ndim != 1 or data.size == 0 or not np.all(np.isfinite(data)):
        raise ValueError(f"histogram values have shape {data.shape}; expected finite (N,), "
                         "N >= 1.")
    fig = _figure(5.0, 3.2)
    ax = fig.add_subplot()
    ax.hist(data, bins="auto", color="0.4")
    if threshold is not None:
        ax.axvline(threshold, color="tab:red", label=f"threshold {threshold:g} dB")
        ax.legend()
    ax.set_xlabel("PSNR as built (dB)")
    ax.set_ylabel("samples")
    return _png(fig)
