"""The report's figures of the part and its errors: the plate to scale, error maps, and the
part as made against the regular pinhole family.

Pure functions, values in and PNG bytes out (aperture_fab.report.figures draws the others);
matplotlib's object-oriented API only.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from aperture_fab.metrics import gain
from aperture_fab.report.figures import (
    MAX_PANELS_PER_ROW,
    PANEL_INCHES,
    TITLE_FONT_SIZE,
    _as_rgb,
    _figure,
    _png,
    wrap_to_width,
)

__all__ = ["MIN_HOLE_MARKER_PX", "figure_errors", "figure_hole_map", "figure_made_front"]

UM_PER_MM = 1000.0
#: The hole map's plate drawing, inches on its longer side (with its colour bar, the figure
#: fits a column of the page's two at 1280 px, at one figure pixel per CSS pixel).
PLATE_INCHES = 4.0
#: Every hole is drawn at least this wide (figure pixels): to scale, the smallest holes of a
#: 20 mm plate are under a pixel, invisible. The title says how wide that is in µm.
MIN_HOLE_MARKER_PX = 3.0
#: The part of the colour map the holes use: its bright end, so that the smallest holes (the
#: lowest colour) stand out from the dark plate.
HOLE_COLOURS = (0.4, 1.0)
PLATE_GREY = "0.15"
#: The part-as-made figure (width, height): a column of the page at 1280 px, 1:1.
FRONT_INCHES = (5.6, 3.8)
#: Error maps share one scale up to this percentile of every map's errors (a few outliers do
#: not wash the rest out).
ERROR_SCALE_PERCENTILE = 99.5


def figure_hole_map(centres_mm: np.ndarray, radii_mm: np.ndarray,
                    outline_mm: Sequence[tuple[float, float]], *, title: str = "") -> bytes:
    """PNG of the plate to scale: each hole a circle of its diameter (colour: diameter in um),
    but never narrower than MIN_HOLE_MARKER_PX (the title then says which holes are drawn
    enlarged), the outline (a closed loop of (x, y) points, e.g.
    fabrication.mesh.outline_points_mm with its alignment chamfer), axes in mm, x right and y up
    as seen from the eye.

    centres_mm: (K, 2) hole centres; radii_mm: (K,) radii (> 0), K may be 0.
    """
    centres = np.asarray(centres_mm, dtype=np.float64).reshape(-1, 2)
    radii = np.asarray(radii_mm, dtype=np.float64).reshape(-1)
    outline = np.asarray(outline_mm, dtype=np.float64)
    if centres.shape[0] != radii.shape[0]:
        raise ValueError(f"hole map: {centres.shape[0]} centres but {radii.shape[0]} radii; "
                         "give one radius per hole.")
    if not (np.all(np.isfinite(centres)) and np.all(np.isfinite(radii)) and np.all(radii > 0)):
        raise ValueError("hole map centres and radii must be finite, radii > 0 (leave closed "
                         "cells out).")
    if outline.ndim != 2 or outline.shape[1] != 2 or len(outline) < 3:
        raise ValueError(f"hole map outline has shape {outline.shape}; expected (n >= 3, 2) "
                         "points of a closed loop.")
    import matplotlib as mpl  # _figure checks that matplotlib is there
    from matplotlib.cm import ScalarMappable
    from matplotlib.collections import PatchCollection
    from matplotlib.colors import ListedColormap, Normalize
    from matplotlib.patches import Circle, Polygon

    width = float(np.ptp(outline[:, 0]))
    height = float(np.ptp(outline[:, 1]))
    scale = PLATE_INCHES / max(width, height)
    fig = _figure(max(width * scale, 3.0) + 1.6, max(height * scale, 2.5) + 0.9)
    ax = fig.add_subplot()
    ax.add_patch(Polygon(outline, closed=True, facecolor=PLATE_GREY, edgecolor="black",
                         linewidth=1.0, zorder=0))
    pad = 0.03 * max(width, height)
    ax.set_xlim(outline[:, 0].min() - pad, outline[:, 0].max() + pad)
    ax.set_ylim(outline[:, 1].min() - pad, outline[:, 1].max() + pad)
    ax.set_aspect("equal")
    diameters_um = 2 * radii * UM_PER_MM
    colours = ListedColormap(mpl.colormaps["viridis"](np.linspace(*HOLE_COLOURS, 256)))
    norm = Normalize()
    if diameters_um.size:
        low, high = float(diameters_um.min()), float(diameters_um.max())
        norm = Normalize(low - 0.5, high + 0.5) if high - low < 1 else Normalize(low, high)
        fig.colorbar(ScalarMappable(norm, colours), ax=ax, label="hole diameter (µm)",
                     shrink=0.8)
    if len(outline) == 5:  # outline_points_mm's loop with the chamfer at points 1 and 2
        corner = outline[1:3].mean(axis=0)
        ax.annotate("alignment chamfer", corner, xytext=(8, -14), textcoords="offset points",
                    color="white", fontsize=8)
    ax.set_xlabel("x (mm), seen from the eye")
    ax.set_ylabel("y (mm), up")
    heading = title or f"{radii.size} holes; plate {width:.3g} x {height:.3g} mm"
    # The title's second line names the floor; it is one line whatever it says, so the layout
    # (and the floor in mm) does not depend on it.
    ax.set_title(_hole_map_title(heading, radii.size, radii.size, 0.0), fontsize=10)
    floor_mm = _marker_floor_mm(fig, ax)
    drawn = np.maximum(radii, floor_mm / 2)
    holes = PatchCollection([Circle((x, y), r) for (x, y), r in zip(centres, drawn, strict=True)],
                            cmap=colours, norm=norm, linewidth=0, zorder=1)
    holes.set_array(diameters_um)
    ax.add_collection(holes)
    enlarged = int(np.count_nonzero(radii < floor_mm / 2))
    ax.set_title(_hole_map_title(heading, enlarged, radii.size, floor_mm), fontsize=10)
    return _png(fig)


def _hole_map_title(heading: str, enlarged: int, holes: int, floor_mm: float) -> str:
    """The hole map's title: `heading`, then how many holes are drawn enlarged to the floor."""
    floor_um = f"{floor_mm * UM_PER_MM:.0f}"
    note = (f"holes under {floor_um} µm ({enlarged} of {holes}) drawn {floor_um} µm wide"
            if enlarged else "every hole drawn to scale")
    return wrap_to_width(heading, PLATE_INCHES, 10) + "\n" + note


def _marker_floor_mm(fig: Any, ax: Any) -> float:
    """MIN_HOLE_MARKER_PX in mm on `ax` as the figure will be drawn (its layout done, the
    axes' limits and aspect set)."""
    fig.draw_without_rendering()
    (x0, _), (x1, _) = ax.transData.transform([(0.0, 0.0), (1.0, 0.0)])
    return float(MIN_HOLE_MARKER_PX / abs(x1 - x0))


def figure_errors(target: np.ndarray, rows: list[tuple[str, np.ndarray]], *,
                  title: str = "") -> bytes:
    """PNG of error maps |g view - target| (g: each view's least-squares gain), the mean over
    colour channels, all on one scale (up to ERROR_SCALE_PERCENTILE of the errors), each panel
    labelled with its mean error.

    target: (C, ny, nx) or (ny, nx) linear; rows: (label, view) pairs of the target's shape.
    """
    if not rows:
        raise ValueError("figure_errors got no views; give (label, view) pairs.")
    goal = _as_rgb(target, "error map target")
    maps = []
    for label, view in rows:
        image = _as_rgb(view, f"error map view {label!r}")
        if image.shape != goal.shape:
            raise ValueError(f"error map view {label!r} has shape {image.shape[:2]} but the "
                             f"target has {goal.shape[:2]}.")
        maps.append(np.abs(gain(image, goal) * image - goal).mean(axis=2))
    top = float(np.percentile(np.stack(maps), ERROR_SCALE_PERCENTILE)) or 1.0
    cols = min(len(rows), MAX_PANELS_PER_ROW)
    lines = math.ceil(len(rows) / cols)
    labels = [wrap_to_width(f"{label}\nmean {m.mean():.3f}", PANEL_INCHES * 0.95,
                            TITLE_FONT_SIZE) for (label, _), m in zip(rows, maps, strict=True)]
    title_in = max(lab.count("\n") + 1 for lab in labels) * TITLE_FONT_SIZE * 1.3 / 72
    fig = _figure(cols * PANEL_INCHES + 0.9, lines * (PANEL_INCHES + title_in) + 0.4)
    if title:
        fig.suptitle(wrap_to_width(title, cols * PANEL_INCHES, 12), fontsize=12)
    axes = []
    shown = None
    for i, (label, error) in enumerate(zip(labels, maps, strict=True)):
        ax = fig.add_subplot(lines, cols, i + 1)
        shown = ax.imshow(error, cmap="magma", vmin=0.0, vmax=top, interpolation="nearest")
        ax.set_title(label, fontsize=TITLE_FONT_SIZE)
        ax.set_axis_off()
        axes.append(ax)
    fig.colorbar(shown, ax=axes, label="|g view - target|", shrink=0.8)
    return _png(fig)


def figure_made_front(block: Mapping[str, Any], title: str = "The part as made and the regular "
                      "pinhole family") -> bytes:
    """PNG of p10 PSNR against the light at the eye (log; the mean view of the content shown,
    as a share of the panel's white) from a "made_part" block
    (`aperture_fab.validation.made_part.made_part_block`): every regular array with elemental
    images (colour: pitch), the front they make, the rivals with their display fitted, and the
    part as made."""
    family, fitted = block["regular"]["family"], block["regular"]["fitted"]
    part = block["part"]
    fig = _figure(*FRONT_INCHES)
    ax = fig.add_subplot()
    light = np.asarray(family["eye_level"]) * 100
    p10 = np.asarray(family["p10_db"])
    points = ax.scatter(light, p10, s=12, c=family["pitch_mm"], cmap="viridis",
                        label="regular arrays, elemental images")
    fig.colorbar(points, ax=ax, label="regular pitch (mm)")
    levels = np.sort(light)
    ax.step(levels, [p10[light >= v].max() for v in levels], where="post", color="k", lw=0.8,
            ls="--", label="their front (best at least this bright)")
    if fitted["eye_level"]:
        ax.scatter(np.asarray(fitted["eye_level"]) * 100, fitted["p10_db"], marker="s", s=36,
                   facecolors="none", edgecolors="k", label="rivals, display fitted")
    ax.scatter([100 * part["eye_level"]], [float(np.mean(part["p10_db"]))], marker="*", s=220,
               c="C3", zorder=3, label="the part as made")
    ax.set_xscale("log")
    ax.set_xlabel("light at the eye with the content shown (% of the panel's white)")
    ax.set_ylabel(f"p10 PSNR, {block['copies']} copies x {block['states']} states (dB)")
    ax.set_title(wrap_to_width(title, 5.2, TITLE_FONT_SIZE), fontsize=TITLE_FONT_SIZE)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="lower left")
    return _png(fig)
