"""The holes to make: what quantization produces and fabrication consumes, and their geometry
(the webs between holes, summary numbers)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["FaceWebs", "HoleLayout", "Violation", "face_webs", "layout_stats"]

#: How far (per mm of z) a convergent layout's axes may differ from (E_xy - centres) / D.
CONVERGE_AXIS_TOL = 1e-9
#: Neighbour offsets (row, col) that meet every adjacent pair of cells once, from its first cell
#: (right, down, down-right, down-left); their negations are a hole's other four neighbours.
FORWARD_NEIGHBOURS = ((0, 1), (1, 0), (1, 1), (1, -1))


@dataclass(frozen=True)
class Violation:
    """One fabrication rule the design broke, and how it was resolved.

    rule: short name, e.g. "min_hole", "min_web", "thickness".
    cell: (row, col) of the cell concerned, or None for the whole plate.
    value_mm: the value the design asked for.
    limit_mm: the process limit.
    resolution: what was done, in words.
    """

    rule: str
    cell: tuple[int, int] | None
    value_mm: float
    limit_mm: float
    resolution: str


@dataclass(frozen=True)
class HoleLayout:
    """Holes in a plate, ready to build.

    cells: (K, 2) int64, (row, col) of each hole's cell.
    centres_mm: (K, 2) float64, (x, y) of each hole's axis at the plate's mid-thickness.
    radii_mm: (K,) float64, hole radius (> 0; closed cells have no entry).
    axes: (K, 2) float64, lateral displacement of the hole axis per mm of +z (0 for straight
        holes); the hole centre at height z above mid-thickness is centres_mm + z * axes.
    pitch_mm: (px, py) cell pitch.
    grid: (nx, ny) cell count.
    outline_mm: (width, height) of the plate's outer outline, centred on the axis (cells plus
        margin).
    thickness_mm: plate thickness.
    violations: rules the design broke and how each was resolved.
    converge_mm: (ex, ey, D), the point every hole axis passes through (chief-ray holes): lateral
        (ex, ey) at distance D > thickness_mm above the mid-thickness plane, so that
        axes = ((ex, ey) - centres_mm) / D. None for straight holes or arbitrary axes.

    Cells. Cell (i, j) at height z above mid-thickness spans cell_edges_mm(z). Without
    converge_mm that is the mid-plane grid at every z. With it, it is the mid-plane grid scaled
    about E = (ex, ey) by 1 - z / D, as the hole centres are (E + (c - E)(1 - z / D)), so a
    convergent hole centred in its cell at mid-thickness stays centred in its (scaled) cell at
    every z: the bottom face's grid has pitch p (1 + t / 2D), the top face's p (1 - t / 2D).
    """

    cells: np.ndarray
    centres_mm: np.ndarray
    radii_mm: np.ndarray
    axes: np.ndarray
    pitch_mm: tuple[float, float]
    grid: tuple[int, int]
    outline_mm: tuple[float, float]
    thickness_mm: float
    violations: tuple[Violation, ...] = ()
    converge_mm: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        k = len(self.radii_mm)
        shapes = {
            "cells": (self.cells.shape, (k, 2)),
            "centres_mm": (self.centres_mm.shape, (k, 2)),
            "axes": (self.axes.shape, (k, 2)),
        }
        for name, (got, want) in shapes.items():
            if got != want:
                raise ValueError(f"HoleLayout.{name} has shape {got}; expected {want}.")
        if k and not np.all(self.radii_mm > 0):
            raise ValueError("HoleLayout.radii_mm must be > 0; leave closed cells out.")
        if self.thickness_mm <= 0:
            raise ValueError(
                f"HoleLayout.thickness_mm = {self.thickness_mm} must be > 0 for a solid part."
            )
        if self.converge_mm is not None:
            self._check_converge(self.converge_mm)

    def _check_converge(self, converge_mm: tuple[float, float, float]) -> None:
        if len(converge_mm) != 3 or not all(math.isfinite(v) for v in converge_mm):
            raise ValueError(
                f"HoleLayout.converge_mm = {converge_mm!r} must be three finite numbers "
                "(ex, ey, D) in mm, or None for holes that do not converge."
            )
        ex, ey, distance = converge_mm
        if not distance > self.thickness_mm:
            raise ValueError(
                f"HoleLayout.converge_mm distance D = {distance:g} mm must be > the thickness "
                f"{self.thickness_mm:g} mm (the axes meet beyond the plate); pass the distance "
                "from the plate's mid-thickness to the eye."
            )
        want = (np.array([ex, ey]) - self.centres_mm) / distance
        error = float(np.max(np.abs(self.axes - want))) if len(want) else 0.0
        if not error <= CONVERGE_AXIS_TOL:
            raise ValueError(
                f"HoleLayout.axes differ from (E_xy - centres_mm) / D for converge_mm = "
                f"{converge_mm} by up to {error:.3g} per mm; allowed: {CONVERGE_AXIS_TOL:g}. "
                "Set axes = ((ex, ey) - centres_mm) / D, or converge_mm = None."
            )

    @property
    def count(self) -> int:
        return len(self.radii_mm)

    def grid_scale(self, z_mm: float) -> float:
        """Scale of the cell grid at height z_mm above mid-thickness (1 without converge_mm)."""
        if self.converge_mm is None:
            return 1.0
        return 1.0 - z_mm / self.converge_mm[2]

    def cell_edges_mm(self, z_mm: float) -> tuple[np.ndarray, np.ndarray]:
        """Cell boundaries at height z_mm above mid-thickness (see the class docstring).

        Returns xs (nx + 1,) float64, left to right, and ys (ny + 1,) float64, top (row 0's top)
        to bottom, mm: cell (i, j) spans xs[j]..xs[j + 1], ys[i + 1]..ys[i].
        """
        nx, ny = self.grid
        px, py = self.pitch_mm
        xs = (np.arange(nx + 1) - nx / 2) * px
        ys = (ny / 2 - np.arange(ny + 1)) * py
        if self.converge_mm is None:
            return xs, ys
        ex, ey, _ = self.converge_mm
        scale = self.grid_scale(z_mm)
        return ex + (xs - ex) * scale, ey + (ys - ey) * scale


@dataclass(frozen=True)
class FaceWebs:
    """The thinnest web of each hole of a layout at one height, mm; (K,) float64 each.

    edge_mm: to the plate's outline.
    forward_mm: to its FORWARD_NEIGHBOURS (inf where it has none); over all holes this meets
        every pair of adjacent holes once.
    backward_mm: to its other four neighbours (inf where it has none).
    """

    edge_mm: np.ndarray
    forward_mm: np.ndarray
    backward_mm: np.ndarray

    @property
    def thinnest_mm(self) -> np.ndarray:
        """(K,) float64, mm: the thinnest web of each hole, to its eight neighbours and the
        outline."""
        return np.minimum(self.edge_mm, np.minimum(self.forward_mm, self.backward_mm))


def face_webs(layout: HoleLayout, z_mm: float) -> FaceWebs:
    """The webs of every hole at height z_mm above mid-thickness (tilted holes are measured
    where their axis crosses that plane)."""
    nx, ny = layout.grid
    rows, cols = layout.cells[:, 0], layout.cells[:, 1]
    slot = np.full((ny, nx), -1, dtype=np.int64)
    slot[rows, cols] = np.arange(layout.count)
    x = layout.centres_mm[:, 0] + z_mm * layout.axes[:, 0]
    y = layout.centres_mm[:, 1] + z_mm * layout.axes[:, 1]
    r = layout.radii_mm
    half_w, half_h = layout.outline_mm[0] / 2, layout.outline_mm[1] / 2

    def to_neighbours(offsets: tuple[tuple[int, int], ...]) -> np.ndarray:
        webs = np.full(layout.count, np.inf)
        for di, dj in offsets:
            nr, nc = rows + di, cols + dj
            inside = (nr >= 0) & (nr < ny) & (nc >= 0) & (nc < nx)
            other = np.full(layout.count, -1, dtype=np.int64)
            other[inside] = slot[nr[inside], nc[inside]]
            has = other >= 0
            o = other[has]
            gap = np.hypot(x[has] - x[o], y[has] - y[o]) - r[has] - r[o]
            webs[has] = np.minimum(webs[has], gap)
        return webs

    backward = tuple((-di, -dj) for di, dj in FORWARD_NEIGHBOURS)
    return FaceWebs(
        edge_mm=np.minimum(half_w - np.abs(x) - r, half_h - np.abs(y) - r),
        forward_mm=to_neighbours(FORWARD_NEIGHBOURS),
        backward_mm=to_neighbours(backward),
    )


def layout_stats(layout: HoleLayout) -> dict[str, Any]:
    """Summary numbers of a layout (webs measured at both faces, neighbours incl. diagonals).

    Keys: hole_count, smallest_hole_diameter_mm, largest_hole_diameter_mm, smallest_web_mm
    (between adjacent holes; None with fewer than two neighbours), smallest_edge_web_mm,
    open_area_fraction (open area / cell-grid area), violation_count.
    """
    nx, ny = layout.grid
    px, py = layout.pitch_mm
    stats: dict[str, Any] = {
        "hole_count": layout.count,
        "smallest_hole_diameter_mm": None,
        "largest_hole_diameter_mm": None,
        "smallest_web_mm": None,
        "smallest_edge_web_mm": None,
        "open_area_fraction": float(np.sum(np.pi * layout.radii_mm**2)) / (nx * px * ny * py),
        "violation_count": len(layout.violations),
    }
    if layout.count == 0:
        return stats
    stats["smallest_hole_diameter_mm"] = float(2 * layout.radii_mm.min())
    stats["largest_hole_diameter_mm"] = float(2 * layout.radii_mm.max())
    faces = [face_webs(layout, z) for z in (-layout.thickness_mm / 2, layout.thickness_mm / 2)]
    web = min(float(f.forward_mm.min()) for f in faces)
    stats["smallest_web_mm"] = None if math.isinf(web) else web
    stats["smallest_edge_web_mm"] = min(float(f.edge_mm.min()) for f in faces)
    return stats
