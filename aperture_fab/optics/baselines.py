"""Simple alternatives a design is judged against, and the optimizer's default start.

The regular pinhole array: holes of the diffraction-optimal diameter sqrt(2 lambda h) on a square
lattice whose pitch keeps every hole in the pupil's footprint looking into its own elemental image
(pitch >= pupil footprint diameter * h / display distance), with the display showing those
elemental images.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from aperture_fab.optics.scene import Display, Scene

__all__ = ["DESIGN_WAVELENGTH_MM", "PinholeArray", "regular_pinholes", "elemental_display"]

#: Green, where the eye is most sensitive; used for the optimal pinhole diameter.
DESIGN_WAVELENGTH_MM = 550e-6


@dataclass(frozen=True)
class PinholeArray:
    """A regular pinhole array on the plate's cell grid.

    open_fraction: (rows, cols) float64, the pinholes' open-area fraction, 0 elsewhere.
    step_cells: lattice pitch in cells (same along x and y).
    origin: (row, col) of one lattice hole near the plate's centre.
    diameter_mm: pinhole diameter.
    """

    open_fraction: np.ndarray
    step_cells: int
    origin: tuple[int, int]
    diameter_mm: float


def regular_pinholes(scene: Scene, wavelength_mm: float = DESIGN_WAVELENGTH_MM,
                     min_fraction: float = 0.0) -> PinholeArray:
    """The regular pinhole array of optimal hole size and pitch for this scene."""
    plate, eye = scene.plate, scene.eye
    h = scene.pinhole_height_mm
    diameter = math.sqrt(2 * wavelength_mm * h)
    diameter = min(diameter, 2 * plate.max_radius_mm)
    footprint = eye.pupil_mm  # pupil diameter; the lens maps it almost 1:1 onto the plate
    pitch_mm = footprint * h / scene.display_distance_mm
    step = max(1, math.ceil(pitch_mm / max(plate.pitch_mm) - 1e-9))
    ncx, ncy = plate.cells
    origin = (ncy // 2, ncx // 2)
    rows = (np.arange(ncy) - origin[0]) % step == 0
    cols = (np.arange(ncx) - origin[1]) % step == 0
    fraction = math.pi * (diameter / 2) ** 2 / (plate.pitch_mm[0] * plate.pitch_mm[1])
    fraction = max(fraction, min_fraction)
    a = np.where(rows[:, None] & cols[None, :], fraction, 0.0)
    return PinholeArray(a, step, origin, diameter)


def elemental_display(scene: Scene, array: PinholeArray, target_view: torch.Tensor,
                      position: int = 0) -> torch.Tensor:
    """Display content (C, H, W) for a pinhole array: each display pixel shows the target at the
    direction in which the eye (at eyebox `position`) sees it through its own pinhole."""
    plate, display, eye = scene.plate, scene.display, scene.eye
    h = scene.pinhole_height_mm
    cx, cy = eye.positions_mm[position]
    xs, ys = display.pixel_centres_mm()
    x, y = np.meshgrid(xs, ys)  # (H, W)
    # Elemental image k is centred where the chief ray through pinhole k meets the display.
    scale = scene.display_distance_mm / (scene.display_distance_mm - h)
    hx0, hy0 = plate.cell_centres_mm()
    ox, oy = hx0[array.origin[1]], hy0[array.origin[0]]
    step_x, step_y = array.step_cells * plate.pitch_mm[0], array.step_cells * plate.pitch_mm[1]
    kx = np.round(((x - cx) / scale + cx - ox) / step_x)
    ky = np.round(((y - cy) / scale + cy - oy) / step_y)
    hole_x, hole_y = ox + kx * step_x, oy + ky * step_y
    tx, ty = eye.view_tan_half
    vx, vy = (x - hole_x) / h, (y - hole_y) / h
    if display.cover_glass_mm > 0:
        vx, vy = _through_glass(display, x - hole_x, y - hole_y, h, vx, vy)
    grid = np.stack([vx / tx, -vy / ty], -1)[None]  # normalized view coordinates
    g = torch.as_tensor(grid, dtype=target_view.dtype, device=target_view.device)
    out = F.grid_sample(target_view[None], g, mode="bilinear", padding_mode="zeros",
                        align_corners=False)
    return out[0]


#: Fixed-point steps that invert the cover glass's shift (each gains about a factor
#: t_g / h of 1/20 or less: far below a view pixel after three).
GLASS_ITERATIONS = 4


def _through_glass(display: Display, dx_mm: np.ndarray, dy_mm: np.ndarray, h_mm: float,
                   vx: np.ndarray, vy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The view directions (tan) from which display points (dx, dy) mm from their pinhole are
    seen under the cover glass: dx = h v - t_g v (1 - 1 / sqrt(n^2 + (n^2 - 1) |v|^2)) (the
    refraction shift of docs/model.md), solved by fixed-point steps from the straight v."""
    n2 = display.cover_glass_index**2
    for _ in range(GLASS_ITERATIONS):
        short = display.cover_glass_mm * (1 - 1 / np.sqrt(n2 + (n2 - 1) * (vx**2 + vy**2)))
        vx, vy = (dx_mm + short * vx) / h_mm, (dy_mm + short * vy) / h_mm
    return vx, vy
