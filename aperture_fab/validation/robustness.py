"""How a part looks over the eye distribution: the headline figures of a design.

A worn device sees many eye states (`aperture_fab.optics.eyes`), so a plate is judged by
percentiles of
its quality over a fixed, low-discrepancy set of states drawn from the scene's eye distribution
(`EyeDistribution.evaluation_states`), each variant (the part and every baseline) the same way,
with one display content for every state (untracked). Beside the percentiles: the quality over
the eyebox (a map of pupil offsets at the nominal pupil and focus), against pupil diameter and
against focus (nominal position), and views at a few offsets.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np
import torch

from aperture_fab.config.stages import EVALUATION_STATES
from aperture_fab.metrics import gain_psnr_db, gains
from aperture_fab.metrics import metrics as view_metrics
from aperture_fab.optics.eyes import EyeDistribution, EyeStates, distribution_of, percentiles
from aperture_fab.optics.model import Renderer
from aperture_fab.optics.open_view import render_open_states
from aperture_fab.optics.scene import Scene
from aperture_fab.validation.judged_cache import JudgedCache, cached

__all__ = ["EyeQuality", "Variant", "judge_eyes", "PERCENTILES"]

#: The percentiles the headline reports.
PERCENTILES = (10, 50, 90)
#: Eyebox map size (n x n pupil offsets over the eyebox's bounding box).
MAP_SIZE = 7
#: Points of the pupil and focus sweeps.
SWEEP_POINTS = 7
#: Focus sweep when the distribution holds the focus fixed: relaxed (0 D) to 2 D.
FOCUS_SWEEP_DIOPTERS = (0.0, 2.0)
#: The open display's view is a pupil quadrature (open_view.render_open); these keep it quick.
OPEN_PUPIL_SAMPLES = 64
OPEN_SUBPIXELS = 2
#: Offsets (as shares of the eyebox's half size) of the thumbnails.
THUMBNAIL_SHARES = ((0.0, 0.0), (0.5, 0.0), (1.0, 0.0), (0.0, 1.0))


@dataclass(frozen=True)
class Variant:
    """A plate and its display content, judged over the eye distribution.

    open_fraction: (rows, cols) float64, or None for the open display (no plate).
    displays: (T, C, H, W) float64 linear display content per target (one for every state).
    """

    open_fraction: np.ndarray | None
    displays: np.ndarray


@dataclass(frozen=True)
class EyeQuality:
    """Quality of each variant over the eye distribution.

    distribution: the distribution judged.
    states: the evaluation set (E states, equal weights).
    psnr_db, ssim: {variant: (T, E) float64} per target and state (PSNR after gain).
    nominal_psnr_db: {variant: (T,)} at the nominal state.
    map_offsets_mm: (n, n, 2) pupil offsets of the eyebox map (row 0 at +y); map_inside (n, n).
    map_psnr_db: {part: (T, n, n)} at the nominal pupil and focus (NaN outside the eyebox).
    pupil_mm: (m,) and pupil_psnr_db {variant: (T, m)}: nominal position and focus.
    focus_diopters: (m,) and focus_psnr_db {part: (T, m)}: nominal position and pupil.
    thumbnail_offsets_mm: (k, 2); thumbnails: (T, k, C, ny, nx) views of the first variant,
        scaled by their gain and clipped to [0, 1].
    """

    distribution: EyeDistribution
    states: EyeStates
    psnr_db: dict[str, np.ndarray]
    ssim: dict[str, np.ndarray]
    nominal_psnr_db: dict[str, np.ndarray]
    map_offsets_mm: np.ndarray
    map_inside: np.ndarray
    map_psnr_db: dict[str, np.ndarray]
    pupil_mm: np.ndarray
    pupil_psnr_db: dict[str, np.ndarray]
    focus_diopters: np.ndarray
    focus_psnr_db: dict[str, np.ndarray]
    thumbnail_offsets_mm: np.ndarray
    thumbnails: np.ndarray

    def percentiles(self, variant: str, metric: str = "psnr_db") -> dict[str, list[float]]:
        """{"p10": [per target], "p50": ..., "p90": ...} of a metric over the states."""
        values = getattr(self, metric)[variant]
        table = [percentiles(row, self.states.weight, PERCENTILES) for row in values]
        return {f"p{q}": [float(t[i]) for t in table] for i, q in enumerate(PERCENTILES)}

    def summary(self) -> dict[str, Any]:
        """Plain numbers for report.json: per variant the PSNR and SSIM percentiles and the
        nominal PSNR per target, and the distribution judged."""
        d = self.distribution
        return {
            "states": len(self.states),
            "distribution": {
                "centre_mm": list(d.centre_mm), "eyebox_mm": list(d.eyebox_mm),
                "eyebox_shape": d.eyebox_shape, "pupil_range_mm": list(d.pupil_range_mm),
                "focus_range_diopters": list(d.focus_range_diopters), "gaze_deg": d.gaze_deg,
                "rotation_mm": d.rotation_mm,
            },
            "variants": {
                name: {"psnr_db": self.percentiles(name),
                       "ssim": self.percentiles(name, "ssim"),
                       "nominal_psnr_db": [float(v) for v in self.nominal_psnr_db[name]]}
                for name in self.psnr_db
            },
        }


def _views(renderer: Renderer, variant: Variant, targets: np.ndarray,
           batches: Sequence[EyeStates]) -> list[np.ndarray]:
    """Views (T, S, C, ny, nx) float64 of a variant for every target and the states of each
    batch. Each target's display stack is built once, and the batches whose states all focus at
    infinity are rendered in one pass, the others in a second: the kernels share a pair's
    geometry between states only when every state of a pass focuses at infinity, and a state's
    view is otherwise the same whatever the other states of its pass (so each batch's views
    are those it gets alone)."""
    dtype, device = renderer.dtype, renderer.device
    at_infinity = [bool(np.all(b.focus_diopters == 0)) for b in batches]
    passes = [[k for k, shared in enumerate(at_infinity) if shared == flag]
              for flag in (True, False)]
    out: list[list[np.ndarray]] = [[] for _ in batches]
    with torch.no_grad():
        for t in range(len(targets)):
            display = torch.as_tensor(variant.displays[t], dtype=dtype, device=device)
            stack = None if variant.open_fraction is None else renderer.display_stack(display)
            for members in filter(None, passes):
                states = EyeStates.concat([batches[k] for k in members])
                if stack is None:
                    views = render_open_states(renderer.scene, display, states,
                                               pupil_samples=OPEN_PUPIL_SAMPLES,
                                               subpixels=OPEN_SUBPIXELS)
                else:
                    a = torch.as_tensor(variant.open_fraction, dtype=dtype, device=device)
                    views = renderer.render_states(a, stack, states)
                split = np.cumsum([len(batches[k]) for k in members])[:-1]
                for k, part in zip(members, np.split(views.cpu().double().numpy(), split),
                                   strict=True):
                    out[k].append(part)
    return [np.stack(views) for views in out]


def _states(offset_mm: np.ndarray, pupil_mm: np.ndarray | float,
            focus_diopters: np.ndarray | float) -> EyeStates:
    """Equally weighted states, the arguments broadcast against each other."""
    offsets, pupils, focus = np.broadcast_arrays(np.atleast_2d(offset_mm)[:, 0],
                                                 np.asarray(pupil_mm), np.asarray(focus_diopters))
    ys = np.broadcast_to(np.atleast_2d(offset_mm)[:, 1], offsets.shape)
    count = offsets.size
    return EyeStates(np.stack([offsets, ys], -1).reshape(count, 2), pupils.reshape(count),
                     focus.reshape(count), np.zeros((count, 2)), np.full(count, 1 / count))


def _sweep(lo: float, hi: float, fixed: tuple[float, float]) -> np.ndarray:
    if hi > lo:
        return np.linspace(lo, hi, SWEEP_POINTS)
    return np.linspace(*fixed, SWEEP_POINTS)


def judge_eyes(scene: Scene, targets: np.ndarray, variants: dict[str, Variant], *,
               device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32,
               count: int = EVALUATION_STATES, map_size: int = MAP_SIZE,
               cache: JudgedCache | None = None) -> EyeQuality:
    """Judge variants over the scene's eye distribution.

    targets: (T, C, ny, nx) linear, on the view grid. variants: {name: Variant}; the first is
    the part: the eyebox map, the focus sweep (whose states away from infinity cannot share
    display samples) and the thumbnails are rendered for it alone; the percentiles, the
    nominal figure and the pupil sweep for every variant. cache: keeps the other variants'
    figures between runs under a digest of their plate, display and every input (the
    baselines', which do not depend on the part, are read back by the next validation of the
    target).
    """
    if not variants:
        raise ValueError("judge_eyes got no variants; give at least the part.")
    distribution = distribution_of(scene.eye)
    renderer = Renderer(scene, device=device, dtype=dtype)
    states = distribution.evaluation_states(count)
    nominal = distribution.nominal()
    grid, inside = distribution.eyebox_grid(map_size)
    grid = grid.subset(np.flatnonzero(inside.reshape(-1)))
    pupils = _sweep(*distribution.pupil_range_mm, (2.0, 8.0))
    focus = _sweep(*distribution.focus_range_diopters, FOCUS_SWEEP_DIOPTERS)
    centre = nominal.offset_mm[0]
    pupil_states = _states(centre, pupils, distribution.nominal_focus_diopters)
    focus_states = _states(centre, distribution.nominal_pupil_mm, focus)
    half = np.asarray(distribution.eyebox_mm) / 2
    thumb_offsets = centre + np.asarray(THUMBNAIL_SHARES) * half
    thumb_states = _states(thumb_offsets, distribution.nominal_pupil_mm,
                           distribution.nominal_focus_diopters)
    psnr, ssim, nominal_psnr, map_psnr, pupil_psnr, focus_psnr = {}, {}, {}, {}, {}, {}
    thumbnails = np.zeros(0)
    for index, (name, variant) in enumerate(variants.items()):
        # The map, focus sweep and thumbnails are the part's alone.
        part = index == 0
        mapped = part and variant.open_fraction is not None
        batches = [states, nominal, pupil_states]
        if not part:
            figures = cached(cache, partial(_judge, renderer, variant, targets, batches),
                             "eye judgement", scene, targets, variant, batches, dtype,
                             torch.device(device).type)
            psnr[name], ssim[name], nominal_psnr[name], pupil_psnr[name] = (
                figures[key] for key in JUDGED)
            continue
        batches += [focus_states, thumb_states] + ([grid] if mapped else [])
        views, nominal_views, pupil_views, *more = _views(renderer, variant, targets, batches)
        figures = _figures(views, nominal_views, pupil_views, targets)
        psnr[name], ssim[name], nominal_psnr[name], pupil_psnr[name] = (
            figures[key] for key in JUDGED)
        focus_psnr[name] = gain_psnr_db(more[0], targets)
        thumbs = more[1]
        thumbnails = np.clip(thumbs * gains(thumbs, targets)[..., None, None, None], 0, 1)
        if mapped:
            full = np.full((len(targets), map_size * map_size), np.nan)
            full[:, inside.reshape(-1)] = gain_psnr_db(more[2], targets)
            map_psnr[name] = full.reshape(len(targets), map_size, map_size)
    offsets = grid_offsets(distribution, map_size)
    return EyeQuality(distribution, states, psnr, ssim, nominal_psnr, offsets, inside, map_psnr,
                      pupils, pupil_psnr, focus, focus_psnr, thumb_offsets, thumbnails)


#: A variant's figures over the states of `judge_eyes` (each (T, S), nominal (T,)).
JUDGED = ("psnr_db", "ssim", "nominal_psnr_db", "pupil_psnr_db")


def _figures(views: np.ndarray, nominal_views: np.ndarray, pupil_views: np.ndarray,
             targets: np.ndarray) -> dict[str, np.ndarray]:
    """A variant's JUDGED figures from its views of the states, the nominal state and the
    pupil sweep (each (T, S, C, ny, nx))."""
    ssim = np.array([[view_metrics(v, targets[t], 1.0)["ssim"] for v in views[t]]
                     for t in range(len(targets))])
    return dict(zip(JUDGED, (gain_psnr_db(views, targets), ssim,
                             gain_psnr_db(nominal_views, targets)[:, 0],
                             gain_psnr_db(pupil_views, targets)), strict=True))


def _judge(renderer: Renderer, variant: Variant, targets: np.ndarray,
           batches: Sequence[EyeStates]) -> dict[str, np.ndarray]:
    """`_figures` of a variant rendered for batches (states, nominal, pupil sweep)."""
    views, nominal_views, pupil_views = _views(renderer, variant, targets, batches)
    return _figures(views, nominal_views, pupil_views, targets)


def grid_offsets(distribution: EyeDistribution, map_size: int) -> np.ndarray:
    """Pupil offsets (n, n, 2) mm of the eyebox map, row 0 at +y."""
    grid, _ = distribution.eyebox_grid(map_size)
    return grid.offset_mm.reshape(map_size, map_size, 2)
