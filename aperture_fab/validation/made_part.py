"""The part as made beside the best regular pinhole array the same process makes, at least as
bright at the eye: report.json's "made_part" block.

The part is judged as made (`aperture_fab.validation.made_quality`) over made copies x eye
states; the regular family (`aperture_fab.validation.regular`) is searched with elemental images
over fewer eye states, and at its best pitches the arrays at the part's light are judged again
with their display fitted the way the part's is, climbing over hole sizes
(`aperture_fab.validation.rival_search`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from aperture_fab.config.settings import OptimizerSettings
from aperture_fab.config.stages import MADE_COPIES
from aperture_fab.fabrication.part import made_optics
from aperture_fab.fabrication.process import Process
from aperture_fab.optics.eyes import distribution_of
from aperture_fab.optics.model import Renderer
from aperture_fab.optics.scene import Scene
from aperture_fab.optimize.optimizer import fit_display, fit_settings
from aperture_fab.validation.judged_cache import JudgedCache
from aperture_fab.validation.made_quality import judge_made
from aperture_fab.validation.margin_interval import margin_interval_db
from aperture_fab.validation.regular import (
    RegularArray,
    RegularFront,
    regular_arrays,
    regular_front,
)
from aperture_fab.validation.rival_search import RIVAL_PITCHES, climb_rivals

__all__ = ["made_part_block", "FAMILY_STATES", "RIVAL_FIT_ITERATIONS"]

#: The report's regular search: eye states of the elemental-image pass over the whole family,
#: whose best pitches the fitted search then climbs (`rival_search.climb_rivals`). The pass is
#: cheap at 8 states (17.7 s for 154 arrays, 22 s at 16).
FAMILY_STATES = 8
RIVAL_FIT_ITERATIONS = 20
#: A rival is judged at these shares of its fit and keeps its best: the fit lowers the mean
#: loss over eye states, and past a point trades the worst states (p10) for the median.
#: Measured on the near-eye preset, photomask, 4 copies x 32 states, fits of 10 / 20 / 40 / 80
#: iterations of a 1.75 mm, 0.234 mm array (1.5 mm on line-pairs): p10 natural 17.67 / 17.62 /
#: 17.14 / 16.96 dB, digit-3 11.74 / 11.66 / 11.34 / 11.41, line-pairs 8.67 / 8.93 / 8.85 /
#: 8.75 (elemental images: 16.27, 11.33, 7.61); the content darkens as the fit goes on on the
#: digit and the line pattern (the photo's brightens to 40 iterations, then darkens).
RIVAL_FIT_SHARES = (0.5, 1.0)
#: What the made-part model leaves out (docs/model.md).
NEGLECTED = ("light scattered off hole walls and plate faces", "the veil's fall-off toward "
             "the view's edges", "plate warp and thickness error", "assembly errors (gap, "
             "tilt: see the tolerance section)")


def made_part_block(scene: Scene, settings: OptimizerSettings, targets: np.ndarray,
                    open_fraction: np.ndarray, displays: np.ndarray, process: Process, *,
                    states: int, copies: int = MADE_COPIES, seed: int = 0,
                    rival_pitches: int = RIVAL_PITCHES, fit_iterations: int = RIVAL_FIT_ITERATIONS,
                    family_states: int = FAMILY_STATES,
                    device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32,
                    cache: JudgedCache | None = None) -> dict[str, Any]:
    """report.json's "made_part" block: the part as made (made open fractions (rows, cols),
    displays (T, C, H, W)) over `copies` made copies x `states` eye states, and the best
    regular array at least as bright at the eye, searched over the family with elemental
    images (family_states eye states), then the arrays that bright at its `rival_pitches` best
    pitches judged again with the display fitted like the part's (fit_iterations of
    `fit_display` on the same as-made loss; 0: elemental images), climbing over hole sizes
    (`climb_rivals`), each at its best of RIVAL_FIT_SHARES of the fit: the part meets its
    rivals at their best. "margin_interval_db" gives per target the bootstrap interval of the
    margin over the best (`margin_interval.margin_interval_db`: other made copies and eye
    states). cache: keeps the family's judgements between runs
    (`regular_front`; they do not depend on the part)."""
    renderer = Renderer(scene, device=device, dtype=dtype)
    optics = made_optics(scene, process)
    distribution = distribution_of(scene.eye)
    evaluation = distribution.evaluation_states(states)
    part = judge_made(renderer, targets, open_fraction, displays, optics, evaluation, copies, seed)
    arrays = regular_arrays(scene, process)
    family = regular_front(targets, arrays,
                           distribution.evaluation_states(min(states, family_states)),
                           device=device, dtype=dtype, cache=cache)

    def fit(regular: RegularArray, shown: np.ndarray) -> list[np.ndarray]:
        kept = {max(1, round(share * fit_iterations)) for share in RIVAL_FIT_SHARES}
        along: list[np.ndarray] = []

        def keep(iteration: int, content: torch.Tensor) -> None:
            if iteration in kept:
                along.append(content.to("cpu", torch.float64, copy=True).numpy())

        fit_display(regular.scene, targets, regular.array.open_fraction, shown, settings,
                    fit_iterations, optics=regular.optics, max_radius_mm=regular.max_radius_mm,
                    min_radius_mm=regular.min_radius_mm, on_iteration=keep)
        return along

    # What a rival's fitted contents depend on besides the array and the targets: the settings
    # the fit reads, its own iteration count and the points kept along it.
    fit_key = (fit_settings(settings), fit_iterations, RIVAL_FIT_SHARES) \
        if fit_iterations > 0 else None
    judged: dict[int, RegularFront] = {}

    def judge(index: int) -> float:
        one = regular_front(targets, [arrays[index]], evaluation, copies, seed,
                            fit=fit if fit_iterations > 0 else None, eye_level=part.eye_level,
                            device=device, dtype=dtype, cache=cache, fit_key=fit_key)
        judged[index] = one
        return float(one.p10.mean()) if one.best_at(part.eye_level) is not None else -math.inf

    chosen = climb_rivals(family, part.eye_level, judge, rival_pitches)
    fitted = RegularFront.joined([judged[i] for i in chosen]) if chosen else family.subset([])
    best = fitted.best_at(part.eye_level)
    percentiles = {f"p{q}_db": part.percentile(q).tolist() for q in (10, 50, 90)}
    block: dict[str, Any] = {
        "copies": int(part.psnr_db.shape[1]), "states": len(evaluation),
        "neglected": list(NEGLECTED),
        "part": {"efficiency": part.efficiency, "eye_level": part.eye_level, **percentiles,
                 "mean_mse_psnr_db": part.mean_mse_psnr().tolist(),
                 "loss_psnr_db": part.mean_mse_psnr(settings.tail_share).tolist()},
        "regular": {"family": family.as_dict(), "fitted": fitted.as_dict(), "best": None},
        "margin_db": None,
    }
    if best is not None:
        block["regular"]["best"] = {
            "pitch_mm": float(fitted.pitch_mm[best]),
            "diameter_mm": float(fitted.diameter_mm[best]),
            "efficiency": float(fitted.efficiency[best]),
            "eye_level": float(fitted.eye_level[best]),
            "p10_db": fitted.p10[best].tolist(), "p50_db": fitted.p50[best].tolist(),
            "p90_db": fitted.p90[best].tolist()}
        block["margin_db"] = (part.percentile(10) - fitted.p10[best]).tolist()
        if fitted.psnr_db:
            block["margin_interval_db"] = margin_interval_db(
                part.psnr_db, fitted.psnr_db[best], seed=seed).tolist()
    return block
