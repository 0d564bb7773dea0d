"""A plate as made, judged over made copies and eye states.

Every figure here views the plate through `aperture_fab.optics.as_made`: the holes as made (the
process's bias in their sizes, a fresh draw of its radius and position errors per made copy),
diffraction at the holes and the veil the solid leaks. A plate is judged by percentiles of the
gain-corrected PSNR over (made copies x eye states), pooled. Its light is given two ways: its
efficiency for a uniform white display (the mean view through the nominal copy's holes over the
eye states, the open display's being 1), a property of the plate alone; and its light at the eye
(`eye_level`): the mean view of the content it shows, as a share of the panel's full white,
which the panel's luminance turns into cd/m2. Plates are compared at the light at the eye: a
plate whose display content is dark (a coded plate's often is, to keep its holes' images apart)
is dimmer at the eye than its efficiency says, and a rival is only "as bright" when the eye sees
as much light from it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from aperture_fab.config.stages import MADE_COPIES
from aperture_fab.metrics import gain_psnr_db
from aperture_fab.optics.as_made import (
    MadeOptics,
    draw_errors,
    made_views,
    made_views_and_white,
)
from aperture_fab.optics.eyes import EyeStates
from aperture_fab.optics.model import Renderer
from aperture_fab.optimize.optimizer import combine_states

__all__ = ["MadeQuality", "as_arrays", "from_arrays", "judge_made", "judge_stacks"]

#: Seed stream of the made copies (apart from the eye states').
COPY_STREAM = 2


@dataclass(frozen=True)
class MadeQuality:
    """A plate as made over made copies and eye states.

    psnr_db: (T, copies, S) float64, gain-corrected PSNR per target, made copy and eye state.
    efficiency: the light efficiency for a white display (share of the open display's),
        through the holes as made (the copies' mean; geometric: no veil).
    eye_level: the light at the eye: the mean view of the shown displays over targets, copies
        and eye states (veil included), as a share of the panel's full white.
    """

    psnr_db: np.ndarray
    efficiency: float
    eye_level: float

    def percentile(self, q: float) -> np.ndarray:
        """(T,) the q-th percentile per target over copies and states pooled."""
        flat = self.psnr_db.reshape(self.psnr_db.shape[0], -1)
        return np.percentile(flat, q, axis=1, method="hazen")

    def mean_mse_psnr(self, tail_share: float = 1.0) -> np.ndarray:
        """(T,) the PSNR of the mean squared error over copies and states, or over the worst
        tail_share of them (`combine_states`): the figure the optimizer's loss with that
        `tail_share` gives (`optimizer.psnr` of its loss), to compare the two."""
        flat = torch.as_tensor(10 ** (-self.psnr_db.reshape(self.psnr_db.shape[0], -1) / 10))
        weights = torch.full((flat.shape[1],), 1.0 / flat.shape[1], dtype=flat.dtype)
        mse = [float(combine_states(row, weights, tail_share)) for row in flat]
        return -10 * np.log10(np.array(mse))


def as_arrays(judged: Sequence[MadeQuality]) -> dict[str, np.ndarray]:
    """Judgements as named arrays (what a `judged_cache.JudgedCache` keeps): psnr_db_<i> per
    judgement, and their efficiencies and eye levels."""
    arrays = {f"psnr_db_{i}": q.psnr_db for i, q in enumerate(judged)}
    arrays["efficiency"] = np.array([q.efficiency for q in judged])
    arrays["eye_level"] = np.array([q.eye_level for q in judged])
    return arrays


def from_arrays(arrays: Mapping[str, np.ndarray]) -> list[MadeQuality] | None:
    """The judgements `as_arrays` gave these arrays, or None when they hold none (another
    record under the key: judge again)."""
    try:
        return [MadeQuality(np.asarray(arrays[f"psnr_db_{i}"]), float(efficiency), float(level))
                for i, (efficiency, level) in enumerate(zip(
                    arrays["efficiency"], arrays["eye_level"], strict=True))]
    except (KeyError, ValueError, TypeError):
        return None


def judge_stacks(renderer: Renderer, displays: np.ndarray) -> list[torch.Tensor]:
    """The stacks `judge_made` renders displays (T, C, H, W) from: each display's
    `renderer.display_stack`, the first with the white display's joined (with_white: the
    plate's efficiency rides in its render). Plates that show the same content share them."""
    with torch.no_grad():
        return [renderer.display_stack(torch.as_tensor(d, dtype=renderer.dtype,
                                                       device=renderer.device),
                                       with_white=index == 0)
                for index, d in enumerate(displays)]


def judge_made(renderer: Renderer, targets: np.ndarray, open_fraction: np.ndarray,
               displays: np.ndarray, optics: MadeOptics, states: EyeStates,
               copies: int = MADE_COPIES, seed: int = 0,
               stacks: Sequence[torch.Tensor] | None = None) -> MadeQuality:
    """Judge a plate of made open fractions (rows, cols) showing displays (T, C, H, W) for
    targets (T, C, ny, nx): `copies` made copies (the nominal one when the process has no random
    error), each over every eye state of `states`. stacks: the displays' `judge_stacks`, when
    the caller has them (plates that show the same content)."""
    if not (isinstance(copies, int) and copies >= 1):
        raise ValueError(f"copies = {copies!r} must be a whole number >= 1.")
    dtype, device = renderer.dtype, renderer.device
    a = torch.as_tensor(open_fraction, dtype=dtype, device=device)
    rng = np.random.default_rng((seed, COPY_STREAM))
    count = copies if optics.has_errors else 1
    draws = [draw_errors(tuple(open_fraction.shape), optics, rng) if optics.has_errors else None
             for _ in range(count)]
    if stacks is None:
        stacks = judge_stacks(renderer, displays)
    psnr = np.zeros((len(targets), count, len(states)))
    level = np.zeros((len(targets), count))
    white = np.zeros(count)
    with torch.no_grad():
        for t, display in enumerate(displays):
            shown = torch.as_tensor(display, dtype=dtype, device=device)
            for k, draw in enumerate(draws):
                # The stack is the display's alone: every copy, moved holes or not, reads it.
                # The first target's render carries the white display too (the efficiency).
                if t == 0:
                    views, _, light = made_views_and_white(renderer, a, shown, stacks[0],
                                                           states, optics, draw)
                    white[k] = float(light.mean())
                else:
                    views, _ = made_views(renderer, a, shown, states, optics, draw, stacks[t])
                psnr[t, k] = gain_psnr_db(views.cpu().double().numpy()[None], targets[t : t + 1])[0]
                level[t, k] = float(views.mean())
    return MadeQuality(psnr, float(white.mean()), float(level.mean()))
