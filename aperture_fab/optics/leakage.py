"""The light the plate's material leaks: a veil over the whole view.

The solid plate passes 10^-OD of the light falling on it (OD: the process's optical density).
Through the material the display is far out of focus, so that light arrives as a nearly uniform
veil: per channel, the transmission times the plate's solid share (1 - f, f the mean open-area
fraction of its cells) times the display's mean radiance. In view units (the open display's view
of a uniform display of radiance L is L) the veil adds

    veil_c = 10^-OD (1 - f) mean(display_c)

to every view pixel. The same model gives the report's leakage share and contrast
(`aperture_fab.validation.light`). Neglected: the veil's slow fall-off toward the view's edges
(the plate is finite, the material scatters), light scattered off hole walls and plate faces.
"""

from __future__ import annotations

import math

import torch

__all__ = ["solid_transmission", "veil"]


def solid_transmission(optical_density: float) -> float:
    """Share of the light the solid material passes: 10^-OD (0 for an opaque plate, OD = inf)."""
    if math.isnan(optical_density) or optical_density < 0:
        raise ValueError(f"optical_density = {optical_density!r} must be >= 0 (inf: opaque).")
    return 0.0 if math.isinf(optical_density) else 10.0 ** -optical_density


def veil(open_fraction: torch.Tensor, display: torch.Tensor, transmission: float
         ) -> torch.Tensor:
    """The leakage veil (C, 1, 1) to add to views (…, C, ny, nx) of a display (C, H, W) through
    a plate of open-area fractions (rows, cols) whose solid passes `transmission` of the light.
    Differentiable in both."""
    if not 0 <= transmission <= 1:
        raise ValueError(f"transmission = {transmission!r} must be in [0, 1].")
    solid = 1 - open_fraction.clamp(0, 1).mean()
    return transmission * solid * display.mean((-2, -1))[:, None, None]
