"""The hole layout as the STEP writer (aperture_fab.fabrication.step) needs it: the checks a layout
must pass before OCCT sees it (holes apart, inside the outline, clear of the chamfer), and the
tiles the plate is cut into so that each face stays small."""

from __future__ import annotations

import math

import numpy as np

from aperture_fab.fabrication.layout import HoleLayout

__all__ = ["CLEARANCE_MM", "HOLES_PER_TILE_SIDE", "check_chamfer_clear", "check_holes_apart",
           "check_layout", "hole_footprints", "tile_count", "tile_cuts", "tile_grids"]


#: Smallest distance kept between hole walls, the outline and tile cut lines (0.1 um): below
#: this OCCT would see touching geometry; far below any process's minimum web.
CLEARANCE_MM = 1e-4
#: Hole columns (and rows) per tile: about 36 holes per planar face keeps STEP I/O linear.
HOLES_PER_TILE_SIDE = 6


def hole_footprints(layout: HoleLayout) -> tuple[np.ndarray, np.ndarray]:
    """Hole centres (K, 2) mm on the bottom (z = 0) and top (z = thickness) faces."""
    half = layout.thickness_mm / 2
    centres = np.asarray(layout.centres_mm, dtype=np.float64)
    axes = np.asarray(layout.axes, dtype=np.float64)
    return centres - half * axes, centres + half * axes


def check_layout(layout: HoleLayout, corner_cut_mm: float = 0.0) -> None:
    """Raise ValueError unless every hole lies inside the (chamfered) outline and no two meet."""
    width, height = layout.outline_mm
    if not (width > 0 and height > 0):
        raise ValueError(f"HoleLayout.outline_mm = {layout.outline_mm} must be > 0 in both axes.")
    # Shorter legs would make edges OCCT cannot tell from points.
    longest_cut = min(width, height) - CLEARANCE_MM
    if not (corner_cut_mm == 0 or CLEARANCE_MM <= corner_cut_mm < longest_cut):
        raise ValueError(
            f"corner_cut_mm = {corner_cut_mm!r} must be 0 (square corner) or from "
            f"{CLEARANCE_MM:g} mm up to below the outline's shorter side less {CLEARANCE_MM:g} "
            f"({longest_cut:g} mm); use the value given to build_mesh."
        )
    radii = np.asarray(layout.radii_mm, dtype=np.float64)
    if not (np.all(np.isfinite(layout.centres_mm)) and np.all(np.isfinite(layout.axes))
            and np.all(np.isfinite(radii))):
        raise ValueError("HoleLayout centres_mm, axes and radii_mm must be finite.")
    limit = np.array([width / 2, height / 2])
    for name, centres in zip(("bottom", "top"), hole_footprints(layout), strict=True):
        reach = np.abs(centres) + radii[:, None] + CLEARANCE_MM
        outside = np.flatnonzero(np.any(reach > limit, axis=1))
        if len(outside):
            k = int(outside[0])
            raise ValueError(
                f"Hole {k} (cell {tuple(layout.cells[k])}, radius {radii[k]:g} mm) reaches "
                f"past the plate outline {layout.outline_mm} mm on the {name} face; allowed: "
                f"|centre| + radius <= outline / 2 - {CLEARANCE_MM:g} mm. Widen the margin."
            )
        if corner_cut_mm > 0:
            check_chamfer_clear(layout, corner_cut_mm, name, centres)
    check_holes_apart(layout)


def check_chamfer_clear(layout: HoleLayout, corner_cut_mm: float, face: str,
                        centres: np.ndarray) -> None:
    """Raise ValueError if the chamfer comes closer than CLEARANCE_MM to a hole on this face.

    centres: (K, 2) hole centres on the face, mm, already inside the outline. The chamfer line
    is (x + W/2) + (H/2 - y) = cut; a hole inside the outline can only meet it on the chamfer
    itself, and the wall between the faces is straight, so both faces' checks cover the plate.
    """
    width, height = layout.outline_mm
    radii = np.asarray(layout.radii_mm, dtype=np.float64)
    # Largest cut that leaves each hole CLEARANCE_MM of material.
    allowed = (centres[:, 0] + width / 2 + height / 2 - centres[:, 1]
               - math.sqrt(2.0) * (radii + CLEARANCE_MM))
    cut = np.flatnonzero(corner_cut_mm > allowed)
    if len(cut):
        k = int(cut[np.argmin(allowed[cut])])
        raise ValueError(
            f"corner_cut_mm = {corner_cut_mm:g} cuts into hole {k} (cell {tuple(layout.cells[k])},"
            f" radius {radii[k]:g} mm) on the {face} face; allowed: <= {float(np.min(allowed)):.4g}"
            " mm (the chamfer needs the margin clear of holes). Widen the margin or cut less."
        )


def check_holes_apart(layout: HoleLayout) -> None:
    """Raise ValueError if two hole walls come closer than CLEARANCE_MM anywhere in the plate."""
    k = layout.count
    if k < 2:
        return
    bottom, top = hole_footprints(layout)
    radii = np.asarray(layout.radii_mm, dtype=np.float64)
    lo = np.minimum(bottom, top) - radii[:, None]
    hi = np.maximum(bottom, top) + radii[:, None]
    # Sweep and prune on x, then test y overlap, then the exact closest approach.
    order = np.argsort(lo[:, 0], kind="stable")
    lo_sorted = lo[order, 0]
    ends = np.searchsorted(lo_sorted, hi[order, 0] + CLEARANCE_MM, side="right")
    counts = np.maximum(ends - np.arange(k) - 1, 0)
    first = np.repeat(np.arange(k), counts)
    offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    second = first + 1 + offsets
    i, j = order[first], order[second]
    near = (lo[i, 1] <= hi[j, 1] + CLEARANCE_MM) & (lo[j, 1] <= hi[i, 1] + CLEARANCE_MM)
    i, j = i[near], j[near]
    # Centre distance d0 + s * da over s in [-t/2, t/2] is convex in s: closest at the clipped
    # stationary point.
    d0 = layout.centres_mm[i] - layout.centres_mm[j]
    da = layout.axes[i] - layout.axes[j]
    da2 = np.sum(da * da, axis=1)
    half = layout.thickness_mm / 2
    s = np.clip(-np.sum(d0 * da, axis=1) / np.where(da2 > 0, da2, 1.0), -half, half)
    gap = np.hypot(*(d0 + s[:, None] * da).T) - radii[i] - radii[j]
    bad = np.flatnonzero(gap < CLEARANCE_MM)
    if len(bad):
        a, b = int(i[bad[0]]), int(j[bad[0]])
        raise ValueError(
            f"Holes {a} (cell {tuple(layout.cells[a])}) and {b} (cell {tuple(layout.cells[b])}) "
            f"leave a web of {gap[bad[0]]:.3g} mm; allowed: >= {CLEARANCE_MM:g} mm. "
            "Quantize with a positive minimum web."
        )


def tile_cuts(centres: np.ndarray, radii: np.ndarray, half_size: float) -> np.ndarray:
    """Tile boundaries along one axis: -half_size, cuts in the webs between holes, +half_size.

    centres: (K,) hole centre coordinates on one face (mm). A cut goes in the middle of a gap
    that no hole crosses, after every HOLES_PER_TILE_SIDE clusters of overlapping holes.
    """
    cuts = [-half_size]
    if len(centres):
        order = np.argsort(centres - radii, kind="stable")
        lo = (centres - radii)[order]
        hi = np.maximum.accumulate((centres + radii)[order])
        # A gap between clusters lies after hole n when the next hole starts past all before.
        gaps = np.flatnonzero(lo[1:] > hi[:-1] + 2 * CLEARANCE_MM)
        clusters = 0
        for n in gaps:
            clusters += 1
            if clusters >= HOLES_PER_TILE_SIDE:
                cuts.append(float((hi[n] + lo[n + 1]) / 2))
                clusters = 0
    cuts.append(half_size)
    return np.asarray(cuts)


def tile_grids(layout: HoleLayout, corner_cut_mm: float = 0.0
               ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Tile boundaries (xs, ys) in mm for the bottom face, then the top face.

    Cut lines that would meet the chamfer are dropped (merging tiles), so it lies in the
    top-left tile of each face.
    """
    width, height = layout.outline_mm
    grids = []
    for centres in hole_footprints(layout):
        xs = tile_cuts(centres[:, 0], layout.radii_mm, width / 2)
        ys = tile_cuts(centres[:, 1], layout.radii_mm, height / 2)
        if corner_cut_mm > 0:
            reach = corner_cut_mm + CLEARANCE_MM
            xs = np.concatenate([xs[:1], xs[1:-1][xs[1:-1] > xs[0] + reach], xs[-1:]])
            ys = np.concatenate([ys[:1], ys[1:-1][ys[1:-1] < ys[-1] - reach], ys[-1:]])
        grids.append((xs, ys))
    return grids


def tile_count(layout: HoleLayout, corner_cut_mm: float = 0.0) -> tuple[int, int]:
    """Planar tiles on the (bottom, top) faces.

    The solid has bottom + top + 4 side faces (5 with a corner cut) + one wall face per hole.
    """
    check_layout(layout, corner_cut_mm)
    bottom, top = ((len(xs) - 1) * (len(ys) - 1) for xs, ys in tile_grids(layout, corner_cut_mm))
    return bottom, top
