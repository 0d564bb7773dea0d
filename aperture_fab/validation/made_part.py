"""The part as made, judged over the eye distribution and the process's random errors, beside
the family of regular pinhole arrays the same process makes.

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

The regular family: square lattices of equal holes on the plate's cell grid, every lattice step
up to `max_pitch_mm` and a ladder of the sizes the process makes, each with the display showing
its elemental images for the nominal eye (`aperture_fab.optics.baselines`). Its front is, at each
light level at the eye, the best 10th percentile of any array at least that bright; the design is
compared with the front at its own light (`RegularFront.best_at`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from aperture_fab.config.settings import OptimizerSettings
from aperture_fab.config.stages import MADE_COPIES
from aperture_fab.fabrication.part import made_optics
from aperture_fab.fabrication.process import Process
from aperture_fab.fabrication.quantize import MadeSizes, made_sizes
from aperture_fab.metrics import gain_psnr_db
from aperture_fab.optics.as_made import (
    MadeOptics,
    draw_errors,
    made_views,
    made_views_and_white,
)
from aperture_fab.optics.baselines import PinholeArray, elemental_display
from aperture_fab.optics.eyes import EyeStates, distribution_of
from aperture_fab.optics.model import Renderer
from aperture_fab.optics.scene import Scene, hole_radius_mm
from aperture_fab.optimize.optimizer import combine_states, fit_display

__all__ = ["MadeQuality", "RegularArray", "RegularFront", "judge_made", "regular_arrays",
           "regular_front", "rivals_at", "made_part_block",
           "REGULAR_SIZES", "MAX_REGULAR_PITCH_MM"]

#: Hole sizes per lattice step in the regular family (from the smallest made to the largest).
REGULAR_SIZES = 6
#: The regular family's coarsest lattice: beyond ~3 mm a 3 to 6 mm pupil sees too few holes.
MAX_REGULAR_PITCH_MM = 3.0
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


def judge_made(renderer: Renderer, targets: np.ndarray, open_fraction: np.ndarray,
               displays: np.ndarray, optics: MadeOptics, states: EyeStates,
               copies: int = MADE_COPIES, seed: int = 0,
               stacks: Sequence[torch.Tensor] | None = None) -> MadeQuality:
    """Judge a plate of made open fractions (rows, cols) showing displays (T, C, H, W) for
    targets (T, C, ny, nx): `copies` made copies (the nominal one when the process has no random
    error), each over every eye state of `states`. stacks: the displays'
    `renderer.display_stack`s, when the caller has them (plates that show the same content)."""
    if not (isinstance(copies, int) and copies >= 1):
        raise ValueError(f"copies = {copies!r} must be a whole number >= 1.")
    dtype, device = renderer.dtype, renderer.device
    a = torch.as_tensor(open_fraction, dtype=dtype, device=device)
    rng = np.random.default_rng((seed, COPY_STREAM))
    count = copies if optics.has_errors else 1
    draws = [draw_errors(tuple(open_fraction.shape), optics, rng) if optics.has_errors else None
             for _ in range(count)]
    psnr = np.zeros((len(targets), count, len(states)))
    level = np.zeros((len(targets), count))
    white = np.zeros(count)
    with torch.no_grad():
        for t, display in enumerate(displays):
            shown = torch.as_tensor(display, dtype=dtype, device=device)
            stack = renderer.display_stack(shown) if stacks is None else stacks[t]
            for k, draw in enumerate(draws):
                # The stack is the display's alone: every copy, moved holes or not, reads it.
                # The first target's render carries the white display too (the efficiency).
                if t == 0:
                    views, _, light = made_views_and_white(renderer, a, shown, stack, states,
                                                           optics, draw)
                    white[k] = float(light.mean())
                else:
                    views, _ = made_views(renderer, a, shown, states, optics, draw, stack)
                psnr[t, k] = gain_psnr_db(views.cpu().double().numpy()[None], targets[t : t + 1])[0]
                level[t, k] = float(views.mean())
    return MadeQuality(psnr, float(white.mean()), float(level.mean()))


@dataclass(frozen=True)
class RegularArray:
    """One regular array: `array` (its holes and lattice), pitch_mm and made diameter_mm."""

    array: PinholeArray
    pitch_mm: float


def regular_arrays(scene: Scene, sizes: MadeSizes, max_pitch_mm: float = MAX_REGULAR_PITCH_MM,
                   count: int = REGULAR_SIZES) -> list[RegularArray]:
    """The regular family: every lattice step (in cells) up to max_pitch_mm, times `count`
    made sizes from the smallest to the largest (the process's own steps when it has few)."""
    plate = scene.plate
    pitch = max(plate.pitch_mm)
    if sizes.levels is not None and len(sizes.levels) - 1 <= count:
        levels = np.asarray(sizes.levels[1:])
    elif sizes.levels is not None:
        pick = np.unique(np.round(np.geomspace(1, len(sizes.levels) - 1, count)).astype(int))
        levels = np.asarray(sizes.levels)[pick]
    else:
        levels = np.geomspace(sizes.lo, sizes.hi, count)
    ncx, ncy = plate.cells
    origin = (ncy // 2, ncx // 2)
    out = []
    for step in range(1, max(1, math.floor(max_pitch_mm / pitch + 1e-9)) + 1):
        rows = (np.arange(ncy) - origin[0]) % step == 0
        cols = (np.arange(ncx) - origin[1]) % step == 0
        lattice = rows[:, None] & cols[None, :]
        for level in levels:
            diameter = 2 * float(hole_radius_mm(level, plate.pitch_mm))
            a = np.where(lattice, level, 0.0)
            out.append(RegularArray(PinholeArray(a, step, origin, diameter), step * pitch))
    return out


@dataclass(frozen=True)
class RegularFront:
    """The regular family judged: per array (A) its pitch and diameter (mm), white efficiency,
    light at the eye (`MadeQuality.eye_level`) and PSNR percentiles (p10, p50, p90 per target:
    (A, T) each). "At least as bright" means at least as much light at the eye."""

    pitch_mm: np.ndarray
    diameter_mm: np.ndarray
    efficiency: np.ndarray
    eye_level: np.ndarray
    p10: np.ndarray
    p50: np.ndarray
    p90: np.ndarray

    def best_at(self, eye_level: float) -> int | None:
        """Index of the array with the best p10 (mean over targets) among those with at least
        `eye_level` light at the eye; None when none is that bright."""
        bright = np.flatnonzero(self.eye_level >= eye_level * (1 - 1e-9))
        if bright.size == 0:
            return None
        return int(bright[np.argmax(self.p10[bright].mean(1))])

    def front(self) -> tuple[np.ndarray, np.ndarray]:
        """The front as a staircase: lights at the eye (increasing) and the best p10 (mean
        over targets) of the arrays at least that bright."""
        level = np.sort(self.eye_level)
        p10 = self.p10.mean(1)
        return level, np.array([p10[self.eye_level >= v].max() for v in level])

    def subset(self, index: Sequence[int]) -> RegularFront:
        """The arrays at `index`."""
        pick = np.asarray(index, dtype=np.int64)
        return RegularFront(self.pitch_mm[pick], self.diameter_mm[pick], self.efficiency[pick],
                            self.eye_level[pick], self.p10[pick], self.p50[pick],
                            self.p90[pick])

    def as_dict(self) -> dict[str, list[float]]:
        """Plain lists for report.json: per array its pitch, diameter, efficiency, light at
        the eye and p10 / p50 (mean over targets)."""
        return {"pitch_mm": self.pitch_mm.tolist(), "diameter_mm": self.diameter_mm.tolist(),
                "efficiency": self.efficiency.tolist(), "eye_level": self.eye_level.tolist(),
                "p10_db": self.p10.mean(1).tolist(), "p50_db": self.p50.mean(1).tolist()}


def rivals_at(front: RegularFront, eye_level: float, per_pitch: int = 2) -> list[int]:
    """Indices of the arrays that can be the best regular array with at least `eye_level`
    light at the eye: per lattice pitch, the `per_pitch` smallest holes that bright (a larger
    hole at the same pitch is only blurrier), to judge again with the display fitted."""
    out = []
    for pitch in np.unique(front.pitch_mm):
        bright = np.flatnonzero((front.pitch_mm == pitch)
                                & (front.eye_level >= eye_level * (1 - 1e-9)))
        out += [int(i) for i in bright[np.argsort(front.diameter_mm[bright])][:per_pitch]]
    return sorted(out)


def _elemental(scene: Scene, array: PinholeArray, targets: torch.Tensor) -> np.ndarray:
    """The array's elemental images for the nominal eye, (T, C, H, W) float64."""
    return np.stack([elemental_display(scene, array, t).cpu().double().numpy() for t in targets])


def _rank(quality: MadeQuality, eye_level: float) -> tuple[bool, float]:
    """How good a judged content is for a rival: first those with at least `eye_level` light
    at the eye, by p10 (mean over targets); then the others, by their light."""
    bright = quality.eye_level >= eye_level * (1 - 1e-9)
    return bright, float(quality.percentile(10).mean()) if bright else quality.eye_level


def regular_front(renderer: Renderer, targets: np.ndarray, arrays: Sequence[RegularArray],
                  optics: MadeOptics, states: EyeStates, copies: int = 1, seed: int = 0,
                  fit: Callable[[np.ndarray, np.ndarray], Sequence[np.ndarray]] | None = None,
                  progress: Callable[[int, int], None] | None = None,
                  eye_level: float = 0.0) -> RegularFront:
    """Judge every regular array as made (`judge_made`), its display showing elemental images
    for the nominal eye, or with `fit`, the contents fit(open_fraction, elemental displays)
    returns (the part's display fit, so that arrays and part are judged alike; several: points
    along the fit), each array judged with the best of them: the highest p10 (mean over
    targets) among those with at least `eye_level` light at the eye (when none has, the
    brightest). progress(done, total) is told after each array."""
    scene = renderer.scene
    target_t = torch.as_tensor(targets, dtype=renderer.dtype, device=renderer.device)
    eff, level, p10, p50, p90 = [], [], [], [], []
    # Elemental images depend on the lattice alone, not the hole size: consecutive arrays of
    # one lattice (regular_arrays' order) show the same content, whose stacks are built once
    # and kept until the lattice changes (a fitted display is each array's own).
    last: tuple[tuple[int, tuple[int, int]], np.ndarray, list[torch.Tensor]] | None = None
    for index, regular in enumerate(arrays):
        a = regular.array.open_fraction
        if fit is not None:
            elemental = _elemental(scene, regular.array, target_t)
            quality = max((judge_made(renderer, targets, a, shown, optics, states, copies, seed)
                           for shown in fit(a, elemental)),
                          key=lambda q: _rank(q, eye_level))
        else:
            lattice = (regular.array.step_cells, regular.array.origin)
            if last is None or last[0] != lattice:
                displays = _elemental(scene, regular.array, target_t)
                with torch.no_grad():
                    stacks = [renderer.display_stack(torch.as_tensor(
                        d, dtype=renderer.dtype, device=renderer.device)) for d in displays]
                last = lattice, displays, stacks
            quality = judge_made(renderer, targets, a, last[1], optics, states, copies, seed,
                                 last[2])
        eff.append(quality.efficiency)
        level.append(quality.eye_level)
        p10.append(quality.percentile(10))
        p50.append(quality.percentile(50))
        p90.append(quality.percentile(90))
        if progress is not None:
            progress(index + 1, len(arrays))
    return RegularFront(np.array([r.pitch_mm for r in arrays]),
                        np.array([r.array.diameter_mm for r in arrays]), np.array(eff),
                        np.array(level), np.array(p10), np.array(p50), np.array(p90))


#: The report's regular search: eye states of the elemental-image pass over the whole family,
#: rivals whose display is then fitted, and the fit's Adam iterations.
FAMILY_STATES = 16
FITTED_RIVALS = 2
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
                    rivals: int = FITTED_RIVALS, fit_iterations: int = RIVAL_FIT_ITERATIONS,
                    family_states: int = FAMILY_STATES,
                    device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32
                    ) -> dict[str, Any]:
    """report.json's "made_part" block: the part as made (made open fractions (rows, cols),
    displays (T, C, H, W)) over `copies` made copies x `states` eye states, and the best
    regular array at least as bright at the eye, searched over the family with elemental
    images (family_states eye states), its `rivals` best rivals that bright judged again with
    the display fitted like the part's (fit_iterations of `fit_display` on the same as-made
    loss; 0: elemental images), each at its best of RIVAL_FIT_SHARES of the fit: the part
    meets its rivals at their best."""
    renderer = Renderer(scene, device=device, dtype=dtype)
    optics = made_optics(scene, process)
    distribution = distribution_of(scene.eye)
    evaluation = distribution.evaluation_states(states)
    part = judge_made(renderer, targets, open_fraction, displays, optics, evaluation, copies, seed)
    arrays = regular_arrays(scene, made_sizes(scene.plate, process, scene.mid_plane_distance_mm))
    family = regular_front(renderer, targets, arrays, optics,
                           distribution.evaluation_states(min(states, family_states)))
    chosen = sorted(rivals_at(family, part.eye_level),
                    key=lambda i: -float(family.p10[i].mean()))[:rivals]

    def fit(a: np.ndarray, shown: np.ndarray) -> list[np.ndarray]:
        kept = {max(1, round(share * fit_iterations)) for share in RIVAL_FIT_SHARES}
        along: list[np.ndarray] = []

        def keep(iteration: int, content: torch.Tensor) -> None:
            if iteration in kept:
                along.append(content.to("cpu", torch.float64, copy=True).numpy())

        fit_display(scene, targets, a, shown, settings, fit_iterations, optics=optics,
                    on_iteration=keep)
        return along

    fitted = regular_front(renderer, targets, [arrays[i] for i in chosen], optics, evaluation,
                           copies, seed, fit=fit if fit_iterations > 0 else None,
                           eye_level=part.eye_level)
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
    return block
