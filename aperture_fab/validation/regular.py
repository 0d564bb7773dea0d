"""The family of regular pinhole arrays a process makes, judged as made: the baseline a coded part
must beat.

An array of the family is a square lattice of equal holes over the family's outline (the
part's plate or the display, whichever is larger along each axis: `family_outline_mm`): its own
plate, whose cells are the lattice pitch (every multiple of `PITCH_STEP_MM` up to
`MAX_REGULAR_PITCH_MM` at which the process makes a hole), each holding one hole of a size the
process makes in a cell that large. The family depends on the process and that outline, not on
the part's own cells, so designs on different cells meet the same baseline: the design job's
second design, on a coarser lattice whose whole cells fill a little less than the first's
plate (`pipeline.lattices`), among them. Holes far larger than the part's cells are in the
family: at a coarse pitch a large hole often gives a plain array the same sharpness at several
times the light. The sizes per pitch are a geometric
ladder of made diameters, `SIZE_RATIO` apart, from the process's smallest hole up to the largest
that pitch holds (which is always in). Each array is judged with its own renderer and made
optics (`aperture_fab.fabrication.part.made_optics` of its plate), the display showing its
elemental images for the nominal eye (`aperture_fab.optics.baselines`) or, with a fit, the
content the part's display fit gives it.

Its front is, at each light level at the eye, the best 10th percentile of any array at least
that bright; a design is compared with the front at its own light (`RegularFront.best_at`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np
import torch

from aperture_fab.fabrication.part import made_optics
from aperture_fab.fabrication.process import Process, UnmakeableError
from aperture_fab.fabrication.quantize import MadeSizes, made_sizes
from aperture_fab.optics.as_made import MadeOptics
from aperture_fab.optics.baselines import PinholeArray, elemental_display
from aperture_fab.optics.diffraction import airy_mixture
from aperture_fab.optics.eyes import EyeStates, distribution_of
from aperture_fab.optics.model import Renderer
from aperture_fab.optics.scene import Scene, hole_radius_mm, open_fraction_of
from aperture_fab.validation.judged_cache import JudgedCache, digest
from aperture_fab.validation.made_quality import (
    MadeQuality,
    as_arrays,
    from_arrays,
    judge_made,
    judge_stacks,
)

__all__ = ["RegularArray", "RegularFront", "elemental", "family_outline_mm", "lattice_scene",
           "regular_arrays", "regular_front", "MAX_REGULAR_PITCH_MM", "PITCH_STEP_MM",
           "SIZE_RATIO"]

#: The regular family's coarsest lattice: beyond ~3 mm a 3 to 6 mm pupil sees too few holes.
MAX_REGULAR_PITCH_MM = 3.0
#: The family's lattice pitches are the multiples of this (the default plate's cell pitch).
PITCH_STEP_MM = 0.25
#: Neighbouring hole diameters of the family's ladder: a sqrt(2) step doubles the light from
#: one size to the next. Neighbours' p10 differ by 0.4 dB or less from 50 um to 1.6 mm, by up
#: to 0.7 dB above, where the holes fill their cells (the natural target, near-eye preset,
#: elemental images, 16 eye states, at 2.5 and 3 mm pitch).
SIZE_RATIO = math.sqrt(2.0)
#: A regular array is rendered for holes up to its made radius plus this many standard
#: deviations of the process's radius error (`RegularArray.max_radius_mm`).
RADIUS_SIGMAS = 4.0
#: Relative slack of float comparisons (pitches, diameters).
_SLACK = 1e-9


@dataclass(frozen=True)
class RegularArray:
    """One regular array: one hole of the same made size in every cell of its own plate.

    scene: the part's scene with the array's plate (`lattice_scene`).
    optics: how the process makes that plate (`made_optics`: errors, veil; diffraction by the
        family's Airy mixture, whose classes are its ladder of diameters).
    array: its holes; `array.open_fraction` is (rows, cols) of that plate, float64.
    """

    scene: Scene
    optics: MadeOptics
    array: PinholeArray

    @property
    def pitch_mm(self) -> float:
        """The lattice pitch (its plate's cells are square)."""
        return max(self.scene.plate.pitch_mm)

    @property
    def max_radius_mm(self) -> float:
        """The largest hole radius a made copy has, to render it with (`Renderer`): the made
        radius plus RADIUS_SIGMAS of the process's radius error, at most the cell's largest.
        A small hole on a coarse lattice then renders from a far smaller display stack (a
        0.4 mm hole on 2.5 mm cells: 6 levels instead of 24)."""
        radius = self.array.diameter_mm / 2 + RADIUS_SIGMAS * self.optics.radius_sigma_mm
        return min(radius, self.scene.plate.max_radius_mm)

    @property
    def min_radius_mm(self) -> float | None:
        """The smallest hole radius a made copy has, to render it with (`Renderer`): the made
        radius less RADIUS_SIGMAS of the process's radius error; None (any) when that is not
        above 0 or the eye distribution focuses off infinity. The stack then holds only the
        levels holes of that size read (a 2.26 mm hole on 3 mm cells: 3 of 24)."""
        radius = self.array.diameter_mm / 2 - RADIUS_SIGMAS * self.optics.radius_sigma_mm
        if radius <= 0 or distribution_of(self.scene.eye).focus_range_diopters != (0.0, 0.0):
            return None
        return radius


def family_outline_mm(scene: Scene) -> tuple[float, float]:
    """The outline (x, y) mm the regular family's plates fill: the part's plate or the
    display, whichever is larger along each axis (a regular array for this display covers
    it, whatever cells the part was given)."""
    plate, display = scene.plate.size_mm, scene.display
    return max(plate[0], display.width_mm), max(plate[1], display.height_mm)


def lattice_scene(scene: Scene, pitch_mm: float,
                  outline_mm: tuple[float, float] | None = None) -> Scene:
    """The scene with a plate of square pitch_mm cells, as many as fit `outline_mm` (default:
    the part's plate; at least one), the rest of the plate kept."""
    plate = scene.plate
    outline = plate.size_mm if outline_mm is None else outline_mm
    width, height = (max(1, math.floor(size / pitch_mm + _SLACK)) for size in outline)
    cells = (width, height)
    return replace(scene, plate=replace(plate, cells=cells, pitch_mm=(pitch_mm, pitch_mm)))


def _made_diameters(sizes: MadeSizes, pitch_mm: tuple[float, float]) -> np.ndarray:
    """The made hole diameters (mm, increasing) a cell of pitch_mm holds."""
    if sizes.levels is not None:
        return 2 * hole_radius_mm(np.asarray(sizes.levels[1:]), pitch_mm)
    return 2 * hole_radius_mm(np.array([sizes.lo, sizes.hi]), pitch_mm)


def _ladder(made: np.ndarray, smallest_mm: float, discrete: bool) -> np.ndarray:
    """The family's diameters at one lattice: the ladder smallest_mm x SIZE_RATIO^k below the
    lattice's largest made diameter, and that largest; a process with discrete sizes takes
    its nearest made size to each rung (in log)."""
    top = float(made[-1])
    rungs = smallest_mm * SIZE_RATIO ** np.arange(
        math.floor(math.log(top / smallest_mm) / math.log(SIZE_RATIO) + _SLACK) + 1)
    rungs = rungs[rungs < top * (1 - _SLACK)]
    if discrete:
        rungs = made[np.argmin(np.abs(np.log(made[None, :] / rungs[:, None])), axis=1)]
    return np.unique(np.append(rungs, top))


def regular_arrays(scene: Scene, process: Process,
                   max_pitch_mm: float = MAX_REGULAR_PITCH_MM) -> list[RegularArray]:
    """The regular family of `process` over `family_outline_mm`: every multiple of
    PITCH_STEP_MM up to max_pitch_mm at which the process makes a hole, each with its ladder
    of made sizes (module docstring), in order of pitch, then size. Raises UnmakeableError
    when the process makes none of them."""
    eye_distance = scene.mid_plane_distance_mm
    outline = family_outline_mm(scene)
    lattices = []
    for k in range(1, math.floor(max_pitch_mm / PITCH_STEP_MM + _SLACK) + 1):
        lattice = lattice_scene(scene, k * PITCH_STEP_MM, outline)
        try:
            lattices.append((lattice, made_sizes(lattice.plate, process, eye_distance)))
        except UnmakeableError:  # too fine for the process: coarser lattices may do
            continue
    if not lattices:
        raise UnmakeableError(
            f"process {process.name!r} makes no regular array with a pitch up to "
            f"{max_pitch_mm:g} mm on plate.thickness_mm = {scene.plate.thickness_mm:g}: its "
            "holes and webs need a coarser pitch; choose another process.")
    first, first_sizes = lattices[0]
    smallest = float(_made_diameters(first_sizes, first.plate.pitch_mm)[0])
    ladders = [_ladder(_made_diameters(sizes, lattice.plate.pitch_mm), smallest,
                       sizes.levels is not None) for lattice, sizes in lattices]
    # One Airy mixture for the whole family, its classes the ladder's rungs (a lattice's
    # largest hole falls between two): 3 to 5 times fewer kernels than one per lattice, which
    # took 2.2 of the seed preset's 3.5 s made-part block, and exact at the rungs.
    rungs = math.ceil(math.log(max(d[-1] for d in ladders) / smallest) / math.log(SIZE_RATIO)
                      - _SLACK)
    eye = scene.eye
    mixture = airy_mixture(smallest, smallest * SIZE_RATIO**rungs, eye.view_step,
                           eye.view_pixels, classes=rungs + 1)
    out = []
    for (lattice, _), diameters in zip(lattices, ladders, strict=True):
        pitch = lattice.plate.pitch_mm
        optics = replace(made_optics(lattice, process, diffraction=False), diffraction=mixture)
        ncx, ncy = lattice.plate.cells
        for diameter in diameters:
            level = float(open_fraction_of(diameter / 2, pitch))
            holes = PinholeArray(np.full((ncy, ncx), level), 1, (ncy // 2, ncx // 2),
                                 float(diameter))
            out.append(RegularArray(lattice, optics, holes))
    return out


@dataclass(frozen=True)
class RegularFront:
    """The regular family judged: per array (A) its pitch and diameter (mm), white efficiency,
    light at the eye (`MadeQuality.eye_level`) and PSNR percentiles (p10, p50, p90 per target:
    (A, T) each). "At least as bright" means at least as much light at the eye.

    psnr_db: per array the PSNR samples its percentiles come from ((T, copies, S) float64,
    `MadeQuality.psnr_db`), or empty when they were not kept."""

    pitch_mm: np.ndarray
    diameter_mm: np.ndarray
    efficiency: np.ndarray
    eye_level: np.ndarray
    p10: np.ndarray
    p50: np.ndarray
    p90: np.ndarray
    psnr_db: tuple[np.ndarray, ...] = ()

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
                            self.p90[pick],
                            tuple(self.psnr_db[i] for i in pick) if self.psnr_db else ())

    @staticmethod
    def joined(fronts: Sequence[RegularFront]) -> RegularFront:
        """The arrays of `fronts`, in order (their PSNR samples when every front kept them)."""
        joined = {field.name: np.concatenate([getattr(f, field.name) for f in fronts])
                  for field in fields(RegularFront) if field.name != "psnr_db"}
        kept = all(f.psnr_db for f in fronts)
        return RegularFront(**joined, psnr_db=tuple(s for f in fronts for s in f.psnr_db)
                            if kept else ())

    def as_dict(self) -> dict[str, list[float]]:
        """Plain lists for report.json: per array its pitch, diameter, efficiency, light at
        the eye and p10 / p50 (mean over targets)."""
        return {"pitch_mm": self.pitch_mm.tolist(), "diameter_mm": self.diameter_mm.tolist(),
                "efficiency": self.efficiency.tolist(), "eye_level": self.eye_level.tolist(),
                "p10_db": self.p10.mean(1).tolist(), "p50_db": self.p50.mean(1).tolist()}


def elemental(regular: RegularArray, targets: torch.Tensor) -> np.ndarray:
    """The array's elemental images for the nominal eye, (T, C, H, W) float64."""
    return np.stack([elemental_display(regular.scene, regular.array, t).cpu().double().numpy()
                     for t in targets])


def _rank(quality: MadeQuality, eye_level: float) -> tuple[bool, float]:
    """How good a judged content is for a rival: first those with at least `eye_level` light
    at the eye, by p10 (mean over targets); then the others, by their light."""
    bright = quality.eye_level >= eye_level * (1 - 1e-9)
    return bright, float(quality.percentile(10).mean()) if bright else quality.eye_level


#: A display fit for a rival: fit(array, its elemental images (T, C, H, W)) gives contents
#: along the fit, each (T, C, H, W).
RivalFit = Callable[[RegularArray, np.ndarray], Sequence[np.ndarray]]


def regular_front(targets: np.ndarray, arrays: Sequence[RegularArray], states: EyeStates,
                  copies: int = 1, seed: int = 0, fit: RivalFit | None = None,
                  progress: Callable[[int, int], None] | None = None, eye_level: float = 0.0,
                  device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32,
                  cache: JudgedCache | None = None, fit_key: Any = None) -> RegularFront:
    """Judge every regular array as made (`judge_made`, its own renderer and optics), its
    display showing elemental images for the nominal eye, or with `fit`, the contents
    fit(array, elemental displays) returns (the part's display fit, so that arrays and part
    are judged alike; several: points along the fit), each array judged with the best of them:
    the highest p10 (mean over targets) among those with at least `eye_level` light at the eye
    (when none has, the brightest). progress(done, total) is told after each array.
    cache: keeps each array's judgements (`judged_cache`) under a digest of the array, the
    targets, states, copies, seed, dtype, device and, with a fit, `fit_key`: every value the
    fit's contents depend on besides the array and the targets (required then)."""
    if cache is not None and fit is not None and fit_key is None:
        raise ValueError("regular_front: a cache with a fit needs fit_key, the values the fit's "
                         "contents depend on (its settings), or judgements of other fits "
                         "would be read back.")
    eff, level, p10, p50, p90, samples = [], [], [], [], [], []
    target_t = torch.as_tensor(targets, dtype=dtype, device=device)
    common = digest("fitted" if fit is not None else "elemental", targets, states, copies, seed,
                    dtype, torch.device(device).type, fit_key) if cache is not None else ""
    known: dict[int, str] = {}  # digests of the scenes and optics the arrays share, by id

    def key_of(regular: RegularArray) -> str:
        for shared in (regular.scene, regular.optics):
            if id(shared) not in known:
                known[id(shared)] = digest(shared)
        return digest(common, known[id(regular.scene)], known[id(regular.optics)],
                      regular.array)

    # Elemental images depend on the lattice alone, not the hole size: the consecutive arrays
    # of one lattice (regular_arrays' order) share them, their renderer and stacks. A fitted
    # content is each array's own, rendered from a stack sized to its holes.
    lattice: tuple[Scene, np.ndarray, Renderer, list[torch.Tensor]] | None = None
    for index, regular in enumerate(arrays):
        a = regular.array.open_fraction
        key = key_of(regular) if cache is not None else ""
        kept = cache.get(key) if cache is not None else None
        judged = None if kept is None else from_arrays(kept)
        if judged is None:
            if fit is not None:
                renderer = Renderer(regular.scene, device=device, dtype=dtype,
                                    max_radius_mm=regular.max_radius_mm,
                                    min_radius_mm=regular.min_radius_mm)
                judged = [judge_made(renderer, targets, a, shown, regular.optics, states, copies,
                                     seed)
                          for shown in fit(regular, elemental(regular, target_t))]
            else:
                if lattice is None or lattice[0] is not regular.scene:
                    renderer = Renderer(regular.scene, device=device, dtype=dtype)
                    displays = elemental(regular, target_t)
                    lattice = regular.scene, displays, renderer, judge_stacks(renderer, displays)
                _, displays, renderer, stacks = lattice
                judged = [judge_made(renderer, targets, a, displays, regular.optics, states,
                                     copies, seed, stacks)]
            if cache is not None:
                cache.put(key, as_arrays(judged))
        quality = max(judged, key=lambda q: _rank(q, eye_level))
        eff.append(quality.efficiency)
        level.append(quality.eye_level)
        p10.append(quality.percentile(10))
        p50.append(quality.percentile(50))
        p90.append(quality.percentile(90))
        samples.append(quality.psnr_db)
        if progress is not None:
            progress(index + 1, len(arrays))
    return RegularFront(np.array([r.pitch_mm for r in arrays]),
                        np.array([r.array.diameter_mm for r in arrays]), np.array(eff),
                        np.array(level), np.array(p10), np.array(p50), np.array(p90),
                        tuple(samples))
