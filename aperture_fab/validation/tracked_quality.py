"""A plate as made, judged with a tracked display: each eye state sees display content solved
for it (`aperture_fab.optimize.tracking.solve_display`, MLEM started from the untracked
content), as a device with an eye tracker would show it.

The solve sees the nominal plate (what the device knows of its part: the made sizes, no random
errors) through the renderer's geometric model; each made copy, its own errors unknown to the
device, is then judged with that content as `aperture_fab.validation.made_quality.judge_made`
judges untracked content: diffraction and the material's veil included, the same copies drawn
from the same seed. Neglected besides what the made-part model neglects: the tracker's errors and
latency (the content is solved for the state the eye is in).
"""

from __future__ import annotations

import numpy as np
import torch

from aperture_fab.config.stages import MADE_COPIES
from aperture_fab.metrics import gain_psnr_db
from aperture_fab.optics.as_made import MadeOptics, draw_errors, made_views, made_white
from aperture_fab.optics.eyes import EyeStates
from aperture_fab.optics.model import Renderer
from aperture_fab.optimize.tracking import DEFAULT_ITERATIONS, solve_display
from aperture_fab.validation.made_quality import COPY_STREAM, MadeQuality

__all__ = ["judge_tracked"]


def judge_tracked(renderer: Renderer, targets: np.ndarray, open_fraction: np.ndarray,
                  displays: np.ndarray, optics: MadeOptics, states: EyeStates,
                  copies: int = MADE_COPIES, seed: int = 0,
                  iterations: int = DEFAULT_ITERATIONS, light_floor: float = 0.0
                  ) -> MadeQuality:
    """Judge a plate of made open fractions (rows, cols) for targets (T, C, ny, nx) with a
    tracked display: for each target and eye state of `states`, the content solved for that
    state by `iterations` MLEM iterations from the untracked display (displays: (T, C, H, W));
    then `copies` made copies (the nominal one when the process has no random error), each
    shown, per state, that state's content. 0 iterations judges the untracked display (scaled
    to a peak of 1: the PSNR after gain is `judge_made`'s). light_floor: the share of the
    untracked content's light that each solved content keeps (`solve_display`; 0: none). The
    light at the eye is the mean view of the solved contents; the efficiency, the copies' white
    view, is `judge_made`'s."""
    if not (isinstance(copies, int) and copies >= 1):
        raise ValueError(f"copies = {copies!r} must be a whole number >= 1.")
    dtype, device = renderer.dtype, renderer.device
    a = torch.as_tensor(open_fraction, dtype=dtype, device=device)
    rng = np.random.default_rng((seed, COPY_STREAM))  # judge_made's copies
    count = copies if optics.has_errors else 1
    draws = [draw_errors(tuple(open_fraction.shape), optics, rng) if optics.has_errors else None
             for _ in range(count)]
    psnr = np.zeros((len(targets), count, len(states)))
    level = np.zeros((len(targets), count, len(states)))
    for t, display in enumerate(displays):
        target = torch.as_tensor(targets[t], dtype=dtype, device=device)
        solved = solve_display(renderer, a, target, states, display, iterations,
                               light_floor=light_floor)
        with torch.no_grad():
            for s in range(len(states)):
                state = states.subset([s])
                stack = renderer.display_stack(solved[s])
                for k, draw in enumerate(draws):
                    views, _ = made_views(renderer, a, solved[s], state, optics, draw, stack)
                    psnr[t, k, s] = gain_psnr_db(views.cpu().double().numpy()[None],
                                                 targets[t : t + 1])[0, 0]
                    level[t, k, s] = float(views.mean())
    with torch.no_grad():
        white = [float(made_white(renderer, a, states, draw).mean()) for draw in draws]
    return MadeQuality(psnr, float(np.mean(white)), float(level.mean()))
