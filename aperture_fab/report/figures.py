"""The validation report's figures: PNG bytes from arrays, drawn with matplotlib.

Pure functions, values in and PNG bytes out; aperture_fab.report.page places them on the
page. matplotlib is imported inside the functions (an optional package: pip install matplotlib),
and only its object-oriented API is used, so no pyplot global figure state.
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from aperture_fab.io.images import linear_to_srgb
from aperture_fab.metrics import agreement_db, gain

__all__ = ["PANEL_INCHES", "TITLE_FONT_SIZE", "figure_views", "figure_loss", "figure_histogram",
           "figure_eyebox_map", "figure_mesh_disagreement", "figure_sweep", "figure_thumbnails",
           "text_width_in", "wrap_to_width"]

FIGURE_DPI = 100
#: Width and height of one image panel in figure_views (inches): a row of MAX_PANELS_PER_ROW
#: (the target and the seven views of the report) fits the page's width at 1280 px, one figure
#: pixel per CSS pixel, and a 128 x 128 view shows about 1:1.
PANEL_INCHES = 1.45
MAX_PANELS_PER_ROW = 8
UM_PER_MM = 1000.0
#: Line styles for the targets of a sweep (colours tell the variants apart).
TARGET_STYLES = ("-", "--", ":", "-.")
#: The eyebox map's panel (inches, square) and a sweep's figure (width, height): two of them
#: side by side fit the page at 1280 px, one figure pixel per CSS pixel.
MAP_INCHES = 3.3
SWEEP_INCHES = (5.6, 3.0)
#: The loss and the tolerance histogram (width, height), side by side on the page.
PLOT_INCHES = (5.0, 2.8)
#: Value labels in the eyebox map's cells up to this many cells per side.
MAX_LABELLED_CELLS = 9
#: Font size (points) of panel titles in figure_views.
TITLE_FONT_SIZE = 9
#: Share of a panel's width its title may fill (the rest keeps neighbouring titles apart).
TITLE_WIDTH_SHARE = 0.95
POINTS_PER_INCH = 72.0


def text_width_in(text: str, fontsize: float) -> float:
    """The widest line of `text` as matplotlib draws it (inches, default font)."""
    from matplotlib.font_manager import FontProperties
    from matplotlib.textpath import TextToPath

    prop = FontProperties(size=fontsize)
    measure = TextToPath()
    widths = [measure.get_text_width_height_descent(line, prop, ismath=False)[0]
              for line in text.split("\n")]
    return max(widths) / POINTS_PER_INCH


def wrap_to_width(text: str, width_in: float, fontsize: float) -> str:
    """`text` broken at spaces into lines no wider than width_in as drawn (existing line breaks
    kept); a single word wider than that is shortened with an ellipsis rather than cut."""
    lines: list[str] = []
    for paragraph in text.split("\n"):
        line = ""
        for word in paragraph.split(" "):
            trial = f"{line} {word}" if line else word
            if line and text_width_in(trial, fontsize) > width_in:
                lines.append(line)
                trial = word
            line = trial
        lines.append(line)
    for i, line in enumerate(lines):
        while text_width_in(line, fontsize) > width_in and len(line) > 2:
            line = line[:-2] + "…"
        lines[i] = line
    return "\n".join(lines)


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
        usually the target. Labels are wrapped to the panel's width (wrap_to_width).
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
    labels = [wrap_to_width(label, PANEL_INCHES * TITLE_WIDTH_SHARE, TITLE_FONT_SIZE)
              for label, _ in rows]
    title_lines = max(label.count("\n") + 1 for label in labels)
    title_in = title_lines * TITLE_FONT_SIZE * 1.3 / POINTS_PER_INCH
    fig = _figure(cols * PANEL_INCHES, lines * (PANEL_INCHES + title_in) + 0.4)
    fig.suptitle(wrap_to_width(title, cols * PANEL_INCHES * TITLE_WIDTH_SHARE, 12), fontsize=12)
    for i, (label, image) in enumerate(zip(labels, images, strict=True)):
        ax = fig.add_subplot(lines, cols, i + 1)
        ax.imshow(linear_to_srgb(np.clip(image, 0.0, 1.0)), interpolation="nearest")
        ax.set_title(label, fontsize=TITLE_FONT_SIZE)
        ax.set_axis_off()
    return _png(fig)


def figure_mesh_disagreement(traced: np.ndarray, exact: np.ndarray, stderr_rms: float) -> bytes:
    """PNG of the mesh re-trace's disagreement with the exact model: traced - exact per view
    pixel (mean over colour channels, linear light) on a scale symmetric about 0, titled with
    the PSNR of traced against exact (peak: exact's maximum) and the trace's RMS standard
    error, so a reader can tell noise (speckle at the standard error) from a systematic
    difference (structure).

    traced, exact: (C, ny, nx) or (ny, nx) linear views of the same shape."""
    mesh, model = _as_rgb(traced, "traced view"), _as_rgb(exact, "exact view")
    if mesh.shape != model.shape:
        raise ValueError(f"traced view has shape {mesh.shape[:2]} but the exact view has "
                         f"{model.shape[:2]}.")
    difference = (mesh - model).mean(axis=2)
    psnr = agreement_db(mesh, model)
    top = float(np.abs(difference).max()) or 1.0
    fig = _figure(*PLOT_INCHES)
    ax = fig.add_subplot()
    shown = ax.imshow(difference, cmap="RdBu_r", vmin=-top, vmax=top, interpolation="nearest")
    ax.set_title(wrap_to_width(f"mesh re-trace vs exact model: {psnr:.1f} dB PSNR, noise "
                               f"{stderr_rms:.2g} RMS", PLOT_INCHES[0] * TITLE_WIDTH_SHARE,
                               TITLE_FONT_SIZE), fontsize=TITLE_FONT_SIZE)
    ax.set_axis_off()
    fig.colorbar(shown, ax=ax, label="mesh re-trace - exact model", shrink=0.9)
    return _png(fig)


def figure_loss(history: np.ndarray) -> bytes:
    """PNG of the loss per iteration (log scale when every value is positive)."""
    values = np.asarray(history, dtype=np.float64)
    if values.ndim != 1 or values.size == 0 or not np.all(np.isfinite(values)):
        raise ValueError(f"loss history has shape {values.shape}; expected finite (N,), N >= 1.")
    fig = _figure(*PLOT_INCHES)
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
    fig = _figure(*PLOT_INCHES)
    ax = fig.add_subplot()
    ax.hist(data, bins="auto", color="0.4")
    if threshold is not None:
        ax.axvline(threshold, color="tab:red", label=f"threshold {threshold:.1f} dB")
        ax.legend()
    ax.set_xlabel("PSNR as built (dB)")
    ax.set_ylabel("samples")
    return _png(fig)


def _finite(array: Any, name: str, ndim: int, *, allow_nan: bool = False) -> np.ndarray:
    values = np.asarray(array, dtype=np.float64)
    if values.ndim != ndim or min(values.shape, default=0) == 0:
        raise ValueError(f"{name} has shape {values.shape}; expected {ndim} non-empty axes.")
    bad = np.isinf(values) if allow_nan else ~np.isfinite(values)
    if np.any(bad):
        raise ValueError(f"{name} holds {'infinite' if allow_nan else 'NaN or infinite'} values.")
    return values


def figure_eyebox_map(psnr_db: np.ndarray, offsets_mm: np.ndarray, eyebox_mm: tuple[float, float],
                      *, shape: str = "ellipse", centre_mm: tuple[float, float] = (0.0, 0.0),
                      names: Sequence[str] = ()) -> bytes:
    """PNG heat map of PSNR (dB) over pupil offsets, one panel per target, the eyebox outlined.

    psnr_db: (T, n, n), row 0 at +y, NaN outside the eyebox (grey). offsets_mm: (n, n, 2) the
    cell centres, an n x n division of the eyebox's bounding box (eyes.EyeDistribution
    .eyebox_grid). eyebox_mm: (w, h) full size, at least one of them > 0; shape "ellipse" or
    "rect"; names: target names for the panel titles.
    """
    values = _finite(psnr_db, "eyebox map PSNR", 3, allow_nan=True)
    offsets = _finite(offsets_mm, "eyebox map offsets", 3)
    count, n = values.shape[0], values.shape[1]
    if values.shape[1:] != (n, n) or offsets.shape != (n, n, 2):
        raise ValueError(f"eyebox map PSNR {values.shape} and offsets {offsets.shape} do not "
                         "match; expected (T, n, n) and (n, n, 2).")
    if np.all(np.isnan(values)):
        raise ValueError("eyebox map PSNR is NaN everywhere: no position inside the eyebox.")
    w, h = (float(v) for v in eyebox_mm)
    if not (w > 0 or h > 0):
        raise ValueError(f"eyebox_mm = {eyebox_mm}: a point has no map; give a size > 0.")
    cx, cy = centre_mm
    # A zero-size axis is drawn one cell thick (a cell as wide as the other axis's cells).
    cell_w, cell_h = (w or h) / n, (h or w) / n
    half_w, half_h = n * cell_w / 2, n * cell_h / 2
    import matplotlib as mpl  # _figure checks that matplotlib is there
    from matplotlib.patches import Ellipse, Rectangle

    fig = _figure(0.6 + MAP_INCHES * count, MAP_INCHES)
    cmap = mpl.colormaps["viridis"].with_extremes(bad="0.85")
    low, high = float(np.nanmin(values)), float(np.nanmax(values))
    if high - low < 0.1:
        low, high = low - 0.05, high + 0.05
    axes = [fig.add_subplot(1, count, t + 1) for t in range(count)]
    shown = None
    for t, ax in enumerate(axes):
        shown = ax.imshow(np.ma.masked_invalid(values[t]), cmap=cmap, vmin=low, vmax=high,
                          interpolation="nearest", origin="upper",
                          extent=(cx - half_w, cx + half_w, cy - half_h, cy + half_h))
        outline = (Ellipse((cx, cy), w, h) if shape == "ellipse"
                   else Rectangle((cx - w / 2, cy - h / 2), w, h))
        outline.set(fill=False, edgecolor="tab:red", linewidth=1.5)
        ax.add_patch(outline)
        if n <= MAX_LABELLED_CELLS:
            middle = (low + high) / 2
            for i in range(n):
                for j in range(n):
                    if np.isfinite(values[t, i, j]):
                        x, y = offsets[i, j]
                        ax.text(x if w else cx, y if h else cy, f"{values[t, i, j]:.1f}",
                                ha="center", va="center", fontsize=7,
                                color="white" if values[t, i, j] < middle else "black")
        ax.set_xlabel("pupil offset x (mm)")
        ax.set_ylabel("pupil offset y (mm)")
        if len(names) > t:
            ax.set_title(f"target {names[t]!r}", fontsize=10)
    fig.colorbar(shown, ax=axes, label="PSNR (dB)")
    return _png(fig)


def figure_sweep(x: np.ndarray, curves: Mapping[str, np.ndarray], *, xlabel: str,
                 shaded: tuple[float, float], nominal: float | None = None,
                 names: Sequence[str] = (), title: str = "") -> bytes:
    """PNG of PSNR (dB) against one eye parameter: one line per variant (colour) and target
    (line style), the distribution's range shaded (a point range: a dashed line at it).

    x: (m,) the parameter's values. curves: {label: (T, m) PSNR per target}. shaded: (lo, hi)
    the distribution's range; nominal: the nominal value, marked inside a range. names: target names
    for the legend when there are several.
    """
    xs = _finite(x, "sweep values", 1)
    if not curves:
        raise ValueError("figure_sweep got no curves; give {label: (T, m) PSNR}.")
    fig = _figure(*SWEEP_INCHES)
    ax = fig.add_subplot()
    lo, hi = shaded
    if hi > lo:
        ax.axvspan(lo, hi, color="0.5", alpha=0.15, label="the distribution's range")
        if nominal is not None:
            ax.axvline(nominal, color="0.3", linewidth=0.8, label="nominal")
    else:  # one value: the nominal one
        ax.axvline(lo, color="0.5", linestyle="--", label="the distribution (one value)")
    for k, (label, values) in enumerate(curves.items()):  # colours C0, C1, ...: the cycle
        ys = _finite(values, f"sweep curve {label!r}", 2)
        if ys.shape[1] != xs.size:
            raise ValueError(f"sweep curve {label!r} has {ys.shape[1]} points but x has "
                             f"{xs.size}.")
        for t, row in enumerate(ys):
            suffix = f" ({names[t]})" if len(ys) > 1 and len(names) > t else ""
            ax.plot(xs, row, color=f"C{k % 10}", marker=".",
                    linestyle=TARGET_STYLES[t % len(TARGET_STYLES)], label=label + suffix)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("PSNR (dB)")
    if title:
        ax.set_title(title, fontsize=10)
    ax.grid(True, alpha=0.3)
    fig.legend(loc="outside right upper", fontsize=7)
    return _png(fig)


def figure_thumbnails(targets: np.ndarray, views: np.ndarray, offsets_mm: np.ndarray,
                      psnr_db: np.ndarray, names: Sequence[str] = ()) -> bytes:
    """PNG of what the eye sees at chosen pupil offsets: one row per target, the target first,
    then each view labelled with its offset and PSNR.

    targets: (T, C, ny, nx) linear; views: (T, k, C, ny, nx) linear, already scaled (shown
    clipped to [0, 1]); offsets_mm: (k, 2); psnr_db: (T, k).
    """
    images = np.asarray(views, dtype=np.float64)
    goal = np.asarray(targets, dtype=np.float64)
    offsets = _finite(offsets_mm, "thumbnail offsets", 2)
    quality = _finite(psnr_db, "thumbnail PSNR", 2)
    if images.ndim != 5 or goal.ndim != 4 or images.shape[0] != goal.shape[0]:
        raise ValueError(f"thumbnails {images.shape} and targets {goal.shape}; expected "
                         "(T, k, C, ny, nx) and (T, C, ny, nx).")
    count, k = images.shape[:2]
    if offsets.shape != (k, 2) or quality.shape != (count, k):
        raise ValueError(f"thumbnail offsets {offsets.shape} and PSNR {quality.shape}; expected "
                         f"({k}, 2) and ({count}, {k}).")
    cols = k + 1
    fig = _figure(cols * PANEL_INCHES * 0.8, count * (PANEL_INCHES * 0.8 + 0.8))
    for t in range(count):
        panels = [(f"target {names[t]!r}" if len(names) > t else "target", goal[t])]
        panels += [(f"({offsets[j, 0]:+.1f}, {offsets[j, 1]:+.1f}) mm\n{quality[t, j]:.1f} dB",
                    images[t, j]) for j in range(k)]
        for j, (label, image) in enumerate(panels):
            ax = fig.add_subplot(count, cols, t * cols + j + 1)
            rgb = _as_rgb(image, f"thumbnail {label!r}")
            ax.imshow(linear_to_srgb(np.clip(rgb, 0.0, 1.0)), interpolation="nearest")
            ax.set_title(label, fontsize=8)
            ax.set_axis_off()
    return _png(fig)
