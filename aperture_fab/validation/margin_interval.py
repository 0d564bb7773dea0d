"""How far the made-part margin could move with other made copies and eye states: a bootstrap
interval of the difference between two plates' PSNR percentiles.

The part and its best regular array are each judged over a few made copies (each a fresh draw
of the process's errors) at the same eye states. Resampling both with replacement, the states
once for both plates (paired: a state hard for one is often hard for the other) and each
plate's copies on their own (independent draws), and taking the percentile of each resample,
gives the spread of the margin the finite judgement leaves. The states are a low-discrepancy
set, not random draws, so treating them as independent overstates their share of the spread:
the interval errs wide. It says nothing of errors the model leaves out (docs/model.md), nor of
the choice of the best of several regular arrays by the same figures.
"""

from __future__ import annotations

import numpy as np

__all__ = ["COVERAGE", "RESAMPLES", "margin_interval_db"]

#: The interval's coverage: the central 95 % of the resampled margins.
COVERAGE = 0.95
#: Resamples per interval: the ends' spread between seeds is about 0.015 dB (standard deviation
#: over 20 seeds, normal samples like the default photo part's: 4 copies x 32 states of 0.6 dB
#: spread; 0.007 dB at 4000), well under the 0.1 dB the report prints; 12 ms an interval.
RESAMPLES = 2000


def margin_interval_db(part_db: np.ndarray, rival_db: np.ndarray, q: float = 10.0,
                       coverage: float = COVERAGE, resamples: int = RESAMPLES,
                       seed: int = 0) -> np.ndarray:
    """(T, 2) float64: per target, the percentile-bootstrap interval (low, high) of the margin
    p_q(part) - p_q(rival), each percentile over copies and states pooled (as
    `MadeQuality.percentile`).

    part_db: (T, copies, S) float64 PSNR (dB) per target, made copy and eye state; rival_db:
    (T, copies', S), judged at the same S eye states. Deterministic in `seed`."""
    part, rival = np.asarray(part_db, dtype=np.float64), np.asarray(rival_db, dtype=np.float64)
    if part.ndim != 3 or rival.ndim != 3 or part.shape[0] != rival.shape[0] \
            or part.shape[2] != rival.shape[2]:
        raise ValueError(f"part_db has shape {part.shape} and rival_db {rival.shape}; allowed: "
                         "(targets, copies, states) each, with the same targets and states "
                         "(both plates judged at the same eye states).")
    if not (np.isfinite(part).all() and np.isfinite(rival).all()):
        raise ValueError("part_db or rival_db holds NaN or infinite PSNR; judge plates whose "
                         "views differ from their targets (finite PSNR) only.")
    if not 0 < coverage < 1:
        raise ValueError(f"coverage = {coverage!r} is out of range; allowed: above 0 and below "
                         "1 (e.g. 0.95 for the central 95 %).")
    if not (isinstance(resamples, int) and resamples >= 1):
        raise ValueError(f"resamples = {resamples!r}; allowed: a whole number >= 1.")
    rng = np.random.default_rng(seed)
    states = rng.integers(0, part.shape[2], (resamples, 1, part.shape[2]))

    def resampled(plate: np.ndarray) -> np.ndarray:
        copies = rng.integers(0, plate.shape[1], (resamples, plate.shape[1], 1))
        # (T, resamples, copies x states): each resample's samples pooled, per target.
        pooled = plate[:, copies, states].reshape(plate.shape[0], resamples, -1)
        return np.percentile(pooled, q, axis=2, method="hazen")

    margins = resampled(part) - resampled(rival)  # (T, resamples)
    tail = (1 - coverage) / 2
    return np.stack([np.quantile(margins, tail, axis=1),
                     np.quantile(margins, 1 - tail, axis=1)], axis=1)
