"""The holes to make: what quantization produces and fabrication consumes."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["Violation", "HoleLayout"]

#: How far (per mm of z) a convergent layout's axes may differ from (E_xy - centres) / D.
CONVERGE_AXIS_TOL = 1e-9


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
