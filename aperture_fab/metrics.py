"""Image metrics for validation: how well a view matches its target, and how much light it passes.

The eye cannot see more light than the holes pass, so a view is compared with its target after the
view's least-squares gain (docs/design.md section 3): MSE and PSNR (peak 1, linear light) on the
gain-scaled view, SSIM on the gain-scaled view clipped to [0, 1]. Light efficiency is the view's
mean level over the open display's, reported beside them. Images are float arrays (C, ny, nx) of
linear light, as everywhere in the model.
"""

from __future__ import annotations

import math

import numpy as np
import torch

__all__ = ["METRIC_KEYS", "agreement_db", "gain", "gain_mse", "gain_mse_states", "gain_psnr_db",
           "gains", "metrics", "psnr_db", "summarize"]

#: The keys of a metrics dict, in the order reports list them.
METRIC_KEYS: tuple[str, ...] = ("mse", "psnr_db", "ssim", "light_efficiency")

#: Guards the gain's division for a black view.
GAIN_EPS = 1e-20
#: SSIM's default Gaussian-free window is 7 x 7; smaller views use the largest odd window that
#: fits, and views under 3 x 3 get NaN (no local statistics to compare).
SSIM_WINDOW = 7
SSIM_MIN_WINDOW = 3


def _check_image(name: str, x: np.ndarray) -> np.ndarray:
    array = np.asarray(x, dtype=np.float64)
    if array.ndim != 3 or min(array.shape) == 0:
        raise ValueError(
            f"{name} has shape {array.shape}; expected (C, ny, nx) with C = 1 or 3 channels "
            "first and no empty axis. Add a channel axis to a grey image: x[None]."
        )
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} holds NaN or infinite values; give finite linear light.")
    return array


def gain(view: np.ndarray, target: np.ndarray) -> float:
    """Least-squares gain g minimising |g view - target|^2: <view, target> / <view, view>.

    A black view gets gain 0. Shapes must match.
    """
    v = np.asarray(view, dtype=np.float64)
    t = np.asarray(target, dtype=np.float64)
    if v.shape != t.shape:
        raise ValueError(f"view has shape {v.shape} but target has {t.shape}; they must match.")
    return float(np.sum(v * t) / (np.sum(v * v) + GAIN_EPS))


def psnr_db(mse: float) -> float:
    """PSNR (dB) for a peak of 1 (linear light in [0, 1])."""
    return 10 * math.log10(1 / max(mse, GAIN_EPS))


def agreement_db(view: np.ndarray, reference: np.ndarray) -> float:
    """How closely two calculations of one view agree: the PSNR (dB) of `view` against
    `reference` (same shape, the same light: no gain), the reference's maximum the peak; inf
    when they are equal."""
    v, r = np.asarray(view, dtype=np.float64), np.asarray(reference, dtype=np.float64)
    if v.shape != r.shape:
        raise ValueError(f"view has shape {v.shape} but the reference has {r.shape}; they "
                         "must match.")
    mse, peak = float(np.mean((v - r) ** 2)), float(r.max())
    if mse == 0:
        return math.inf
    return 10 * math.log10(peak**2 / mse) if peak > 0 else -math.inf


def gains(views: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """`gain` of many views at once: views (T, k, C, ny, nx), k views of each of the T targets
    (T, C, ny, nx). Returns (T, k) float64."""
    flat = views.reshape(*views.shape[:2], -1)
    goal = targets.reshape(targets.shape[0], 1, -1)
    return np.asarray((flat * goal).sum(-1) / ((flat * flat).sum(-1) + GAIN_EPS))


def gain_psnr_db(views: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """PSNR (dB) after each view's least-squares gain, (T, k) for views (T, k, C, ny, nx) of the
    targets (T, C, ny, nx)."""
    flat = views.reshape(*views.shape[:2], -1)
    goal = targets.reshape(targets.shape[0], 1, -1)
    mse = ((gains(views, targets)[..., None] * flat - goal) ** 2).mean(-1)
    return np.asarray(10 * np.log10(1 / np.maximum(mse, GAIN_EPS)))


def _ssim(scaled: np.ndarray, target: np.ndarray) -> float:
    try:
        from skimage.metrics import structural_similarity
    except ImportError as err:
        raise ImportError(
            "SSIM needs scikit-image: pip install scikit-image"
        ) from err
    side = min(scaled.shape[1:])
    if side < SSIM_MIN_WINDOW:
        return math.nan
    window = min(SSIM_WINDOW, side if side % 2 else side - 1)
    if scaled.shape[0] == 1:
        return float(structural_similarity(scaled[0], target[0], data_range=1.0,
                                           win_size=window))
    return float(structural_similarity(scaled, target, data_range=1.0, win_size=window,
                                       channel_axis=0))


def metrics(view: np.ndarray, target: np.ndarray, open_level: float) -> dict[str, float]:
    """How well `view` matches `target`, and its light efficiency.

    view, target: (C, ny, nx) linear light; the target in [0, 1].
    open_level: the open display's mean view level (no plate) at the same eye position, > 0.
    Returns {"mse", "psnr_db", "ssim", "light_efficiency"}: MSE and PSNR (dB, peak 1) of the
    gain-scaled view; SSIM of the gain-scaled view clipped to [0, 1] (data range 1; NaN for
    views under 3 x 3 pixels); light efficiency = view mean / open_level.
    """
    v = _check_image("view", view)
    t = _check_image("target", target)
    if v.shape != t.shape:
        raise ValueError(
            f"view has shape {v.shape} but target has {t.shape}; render the view on the "
            "target's grid (C, ny, nx)."
        )
    if t.min() < 0 or t.max() > 1:
        raise ValueError(
            f"target holds values from {t.min():g} to {t.max():g}; allowed: 0 to 1 (linear light)."
        )
    if not (isinstance(open_level, (int, float, np.floating)) and math.isfinite(open_level)
            and open_level > 0):
        raise ValueError(
            f"open_level = {open_level!r} is out of range; allowed: a finite number > 0, the "
            "open display's mean view level."
        )
    scaled = gain(v, t) * v
    mse = float(np.mean((scaled - t) ** 2))
    return {
        "mse": mse,
        "psnr_db": psnr_db(mse),
        "ssim": _ssim(np.clip(scaled, 0.0, 1.0), t),
        "light_efficiency": float(v.mean() / open_level),
    }


def summarize(per_target: list[dict[str, float]]) -> dict[str, float]:
    """The mean of each metric over targets (NaN stays NaN). All dicts must have the same keys."""
    if not per_target:
        raise ValueError("summarize got no metrics; give one metrics dict per target.")
    keys = list(per_target[0])
    for i, entry in enumerate(per_target):
        if set(entry) != set(keys):
            raise ValueError(
                f"metrics dict {i} has keys {sorted(entry)}; expected {sorted(keys)} like the "
                "first."
            )
    return {key: float(np.mean([entry[key] for entry in per_target])) for key in keys}


def gain_mse(view: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """MSE between target and view after the view's least-squares gain: shapes, not level."""
    gain = (view * target).sum() / ((view * view).sum() + GAIN_EPS)
    return ((gain * view - target) ** 2).mean()


def gain_mse_states(views: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """`gain_mse` of each of a batch of views (S, C, ny, nx) against one target: (S,)."""
    flat = views.reshape(views.shape[0], -1)
    goal = target.reshape(1, -1)
    gain = (flat * goal).sum(1, keepdim=True) / ((flat * flat).sum(1, keepdim=True) + GAIN_EPS)
    return ((gain * flat - goal) ** 2).mean(1)
