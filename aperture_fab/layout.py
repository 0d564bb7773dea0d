"""The holes to make: what quantization produces and fabrication consumes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Violation", "HoleLayout"]


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

    @property
    def count(self) -> int:
        return len(self.radii_mm)
