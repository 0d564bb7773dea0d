"""The optimizer's starting point: the open fractions of a regular pinhole array (or random, or
uniform), as logits, and the display content it starts from."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from aperture_fab.config.settings import OptimizerSettings
from aperture_fab.optics.baselines import PinholeArray, elemental_display, regular_pinholes
from aperture_fab.optics.scene import Scene, open_fraction_of

__all__ = ["INIT_CLOSED_SHARE", "initial_state", "initial_design"]


#: Initial logit span: closed cells start at this share of the allowed range, so they can open.
INIT_CLOSED_SHARE = 0.02


def _logit(x: torch.Tensor) -> torch.Tensor:
    x = x.clamp(1e-4, 1 - 1e-4)
    return torch.log(x) - torch.log1p(-x)


def initial_state(scene: Scene, targets: torch.Tensor, target_displays: torch.Tensor,
                   settings: OptimizerSettings, bounds: tuple[float, float],
                   smallest_made: float = 0.0) -> dict[str, Any]:
    """The starting state. smallest_made: the smallest open fraction the process makes (0:
    any); the pinhole start's holes are at least that, or the snapped plate would start
    closed, black, with no gradient to open it (laser, fdm: their smallest hole is above the
    scene's optimal pinhole)."""
    lo, hi = bounds
    rows, cols = scene.plate.cells[1], scene.plate.cells[0]
    gen = torch.Generator().manual_seed(settings.seed)
    displays = target_displays.clone()
    if settings.init == "random":
        share = torch.rand(rows, cols, generator=gen, dtype=torch.float64)
    elif settings.init == "uniform":
        share = torch.full((rows, cols), 0.5, dtype=torch.float64)
    else:
        array = _start_array(scene, settings.init_diameter_mm, max(lo, smallest_made), hi)
        a = torch.as_tensor(array.open_fraction)
        share = torch.where(a > 0, (a - lo) / (hi - lo), torch.full_like(a, INIT_CLOSED_SHARE))
        share = share.clamp(INIT_CLOSED_SHARE, 1 - INIT_CLOSED_SHARE)
        if settings.display == "optimized":
            displays = torch.stack([elemental_display(scene, array, t) for t in targets])
    state: dict[str, Any] = {
        "iteration": 0,
        "history": [],
        "best": math.inf,
        "best_iteration": 0,
        "mask_logits": _logit(share),
        # Display content is optimized directly and projected onto [0, 1] after each step: a
        # sigmoid would freeze the black and white pixels that elemental images are full of.
        "display": displays.clamp(0, 1) if settings.display == "optimized" else None,
        "optimizer": None,
        # Fabrication-aware phase: the first iteration that sees makeable holes, and the
        # design just before it.
        "snap_from": settings.iterations - round(settings.quantize_share * settings.iterations),
        "continuous": None,
        # Steps since the light at the eye was last below optimizer.min_eye_level (inf: never).
        "since_below_floor": math.inf,
    }
    return state


def _start_array(scene: Scene, diameter_mm: float, lo: float, hi: float) -> PinholeArray:
    """The pinhole start: holes of diameter_mm in every cell (their open fraction within
    [lo, hi]), or with 0 the scene's regular pinhole array (`regular_pinholes`)."""
    if diameter_mm <= 0:
        return regular_pinholes(scene, min_fraction=lo)
    plate = scene.plate
    ncx, ncy = plate.cells
    fraction = min(max(float(open_fraction_of(diameter_mm / 2, plate.pitch_mm)), lo), hi)
    return PinholeArray(np.full((ncy, ncx), fraction), 1, (ncy // 2, ncx // 2), diameter_mm)


def initial_design(scene: Scene, targets: np.ndarray, target_displays: np.ndarray,
                   settings: OptimizerSettings, bounds: tuple[float, float] | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The optimizer's starting point: open fractions (rows, cols) and displays (T, C, H, W)."""
    lo, hi = bounds if bounds is not None else (0.0, scene.plate.max_open_fraction)
    state = initial_state(scene, torch.as_tensor(targets, dtype=torch.float64),
                           torch.as_tensor(target_displays, dtype=torch.float64), settings,
                           (lo, hi))
    a = lo + (hi - lo) * torch.sigmoid(state["mask_logits"])
    shown = state["display"]
    displays = target_displays if shown is None else shown.numpy()
    return a.numpy(), np.asarray(displays, dtype=np.float64)
