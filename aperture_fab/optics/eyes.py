"""The eye as a distribution: where the pupil is, how wide, how focused, which way it looks.

A worn device sees many eye states (docs/design.md section 3, "The eye moves"): the pupil centre
sits anywhere in an eyebox of a few millimetres, moves with gaze as the eye rotates, changes
diameter with the light level and accommodates. `EyeDistribution` describes that spread,
`EyeStates` is a batch of S concrete states with quadrature weights, and the methods of
`EyeDistribution` draw batches: random ones for the optimizer (`sample`, one fresh batch per
iteration via `iteration_seed`), a fixed low-discrepancy set for judging a part
(`evaluation_states`, then `percentiles`), and regular grids and sweeps for maps and plots.

Numpy only: the renderer turns a batch into tensors itself.

Conventions (docs/design.md section 2): mm; x to the right, y up, for the eye looking toward
-z; offsets are absolute pupil-centre positions in the scene frame, like `Eye.positions_mm`.
Focus is in diopters, 1000 / focus distance in mm, 0 = infinity (relaxed).

The gaze model. The eye rotates about a centre `rotation_mm` behind the pupil (the pupil is
between the centre and the plate). Looking by angles (ax, ay) toward +x / +y (the view's right /
top) moves the pupil centre by (rotation_mm sin ax, rotation_mm sin ay), each axis on its own.
Neglected: the pupil's axial shift toward the centre, rotation_mm (1 - cos angle) (0.17 mm at
10 deg); the pupil's tilt and foreshortening (an ellipse of minor axis cos(angle) times the
diameter, 1.5 % at 10 deg); the coupling of the two axes (a diagonal gaze of polar angle t moves
the pupil by rotation_mm sin t along its azimuth, which the per-axis form matches to second
order); Listing's-law torsion. The view itself stays in world directions: the image the plate
forms is fixed to the device, so a rotated eye sees the same view grid through a moved pupil,
only centred on the fovea elsewhere (the model's retina is uniform, it has no fovea).

Centre of rotation: about 13.5 mm behind the corneal apex (Gullstrand's value, the one used in
spectacle-lens design, e.g. M. Jalie, "The role of the eye's centre of rotation in lens
design", Points de Vue 69, 2013), and the entrance pupil about 3 mm behind the apex (3.04 mm in
Le Grand's theoretical eye): about 10.5 mm between them; measured eyes spread over about 10 to
13 mm (G. A. Fry and W. W. Hill, "The center of rotation of the eye", Am. J. Optom. 39, 581,
1962). Default 11 mm.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from aperture_fab.optics.eye_fields import (
    MAX_PUPIL_MM,
    EyeboxShape,
    check_fields,
    check_number,
    check_pair,
)

if TYPE_CHECKING:
    from aperture_fab.optics.scene import Eye


__all__ = [
    "EyeStates",
    "EyeDistribution",
    "distribution_of",
    "iteration_seed",
    "percentiles",
]


#: Distance from the pupil to the eye's centre of rotation, mm (see the module docstring).
ROTATION_MM = 11.0
#: How far weights may sum from 1 before it is an error rather than rounding.
_WEIGHT_SUM_SLACK = 1e-6
#: Unit-cube coordinates of a state: eyebox (2), gaze (2), pupil, focus.
_DIMS = 6
_PRIMES = (2, 3, 5, 7, 11, 13)


# ---------------------------------------------------------------------------------------------
# Checks shared with scene.Eye


# ---------------------------------------------------------------------------------------------
# A batch of eye states


def _frozen(array: np.ndarray) -> np.ndarray:
    array.setflags(write=False)
    return array


@dataclass(frozen=True, eq=False)
class EyeStates:
    """A batch of S eye states, each with a quadrature weight; arrays are float64, read-only.

    offset_mm: (S, 2) pupil-centre position (x, y) in the scene frame (absolute, like
        Eye.positions_mm), gaze shift included.
    pupil_mm: (S,) pupil diameters.
    focus_diopters: (S,) accommodation, 1000 / focus distance in mm; 0 = infinity.
    gaze_deg: (S, 2) the gaze rotation (x, y) that produced part of the offset (for reports).
    weight: (S,) non-negative weights summing to 1 (renormalised exactly on construction).
    """

    offset_mm: np.ndarray
    pupil_mm: np.ndarray
    focus_diopters: np.ndarray
    gaze_deg: np.ndarray
    weight: np.ndarray

    def __post_init__(self) -> None:
        offset = np.array(self.offset_mm, dtype=np.float64)
        if offset.ndim != 2 or offset.shape[1] != 2 or offset.shape[0] < 1:
            raise ValueError(f"EyeStates.offset_mm has shape {offset.shape}; allowed: (S, 2) "
                             "with S >= 1. Give one (x, y) pupil position per state.")
        count = offset.shape[0]
        arrays = {"offset_mm": offset}
        for name, shape in (("pupil_mm", (count,)), ("focus_diopters", (count,)),
                            ("gaze_deg", (count, 2)), ("weight", (count,))):
            array = np.array(getattr(self, name), dtype=np.float64)
            if array.shape != shape:
                raise ValueError(f"EyeStates.{name} has shape {array.shape}; allowed: {shape}, "
                                 f"one per state like offset_mm.")
            arrays[name] = array
        for name, array in arrays.items():
            if not np.all(np.isfinite(array)):
                raise ValueError(f"EyeStates.{name} holds non-finite values "
                                 f"{array[~np.isfinite(array)][:3]}; allowed: finite numbers.")
        checks = (("pupil_mm", arrays["pupil_mm"] > 0, "> 0 mm"),
                  ("focus_diopters", arrays["focus_diopters"] >= 0, ">= 0 (0 = infinity)"),
                  ("weight", arrays["weight"] >= 0, ">= 0"))
        for name, ok, allowed in checks:
            if not np.all(ok):
                raise ValueError(f"EyeStates.{name} holds {arrays[name][~ok][:3]}; allowed: "
                                 f"{allowed}.")
        total = float(arrays["weight"].sum())
        if abs(total - 1) > _WEIGHT_SUM_SLACK:
            raise ValueError(f"EyeStates.weight sums to {total!r}; allowed: a sum of 1. "
                             "Divide the weights by their sum.")
        arrays["weight"] = arrays["weight"] / total
        for name, array in arrays.items():
            object.__setattr__(self, name, _frozen(array))

    def __len__(self) -> int:
        return int(self.offset_mm.shape[0])

    def focus_mm(self, i: int) -> float | None:
        """State i's focus distance from the pupil in mm; None for infinity (0 diopters)."""
        diopters = float(self.focus_diopters[i])
        return None if diopters == 0 else 1000.0 / diopters

    def subset(self, index: int | slice | Sequence[int] | np.ndarray) -> EyeStates:
        """The states picked by an index, slice, index list or boolean mask; weights
        renormalised."""
        picked = np.atleast_1d(np.arange(len(self))[index])
        weight = self.weight[picked]
        total = weight.sum()
        if picked.size == 0 or total <= 0:
            raise ValueError(f"EyeStates.subset({index!r}) picks no state of positive weight; "
                             "pick at least one.")
        return EyeStates(self.offset_mm[picked], self.pupil_mm[picked],
                         self.focus_diopters[picked], self.gaze_deg[picked], weight / total)

    @staticmethod
    def concat(parts: Sequence[EyeStates]) -> EyeStates:
        """One batch from several; each part's weights are scaled by its share of the states
        (so batches of equal weights give equal weights)."""
        if not parts:
            raise ValueError("EyeStates.concat got no batches; give at least one.")
        total = sum(len(p) for p in parts)
        return EyeStates(
            np.concatenate([p.offset_mm for p in parts]),
            np.concatenate([p.pupil_mm for p in parts]),
            np.concatenate([p.focus_diopters for p in parts]),
            np.concatenate([p.gaze_deg for p in parts]),
            np.concatenate([p.weight * len(p) / total for p in parts]),
        )


# ---------------------------------------------------------------------------------------------
# The distribution


def iteration_seed(seed: int, iteration: int) -> int:
    """A seed for iteration `iteration` of a run seeded `seed`: independent streams per
    iteration, the same on every machine and after a resume."""
    for name, value in (("seed", seed), ("iteration", iteration)):
        if not (isinstance(value, (int, np.integer)) and not isinstance(value, bool)
                and value >= 0):
            raise ValueError(f"iteration_seed: {name} = {value!r}; allowed: a whole number >= 0.")
    return int(np.random.SeedSequence([int(seed), int(iteration)]).generate_state(1)[0])


def _radical_inverse(index: np.ndarray, base: int) -> np.ndarray:
    """Van der Corput radical inverse of non-negative integers in `base`, float64."""
    result = np.zeros(index.shape, dtype=np.float64)
    remaining = index.astype(np.int64)
    scale = 1.0 / base
    while np.any(remaining > 0):
        result += scale * (remaining % base)
        remaining //= base
        scale /= base
    return result


@dataclass(frozen=True)
class EyeDistribution:
    """The eye states a worn device sees; every part uniform and independent of the others.

    centre_mm: (x, y) nominal pupil centre, in the scene frame.
    eyebox_mm: (w, h) full size of the region the pupil centre takes (before gaze), uniform over
        it; (0, 0): fixed at centre_mm.
    eyebox_shape: "ellipse" (inscribed in w x h) or "rect".
    pupil_range_mm: (lo, hi) pupil diameters, uniform in diameter.
    nominal_pupil_mm: the nominal diameter, within the range.
    focus_range_diopters: (lo, hi) accommodation, uniform in diopters (0 = infinity).
    nominal_focus_diopters: the nominal accommodation, within the range.
    gaze_deg: largest gaze rotation from straight ahead, degrees; the angles (ax, ay) are uniform
        over the disk of that radius; 0: no gaze.
    rotation_mm: pupil to the eye's centre of rotation (default 11 mm; see the module docstring
        for the gaze model and its neglected terms).
    """

    centre_mm: tuple[float, float] = (0.0, 0.0)
    eyebox_mm: tuple[float, float] = (0.0, 0.0)
    eyebox_shape: EyeboxShape = "ellipse"
    pupil_range_mm: tuple[float, float] = (4.0, 4.0)
    nominal_pupil_mm: float = 4.0
    focus_range_diopters: tuple[float, float] = (0.0, 0.0)
    nominal_focus_diopters: float = 0.0
    gaze_deg: float = 0.0
    rotation_mm: float = ROTATION_MM

    def __post_init__(self) -> None:
        centre = check_pair("EyeDistribution.centre_mm", self.centre_mm)
        if not all(map(math.isfinite, centre)):
            raise ValueError(f"EyeDistribution.centre_mm = {self.centre_mm!r}; allowed: finite "
                             "[x, y] in mm.")
        check_number("EyeDistribution.nominal_pupil_mm", self.nominal_pupil_mm, 0.0,
                      MAX_PUPIL_MM, "A human pupil is about 2 to 8 mm across.", positive=True)
        check_number("EyeDistribution.nominal_focus_diopters", self.nominal_focus_diopters, 0.0,
                      math.inf, "Diopters are 1000 / focus distance in mm; 0 = infinity.")
        names = {k: f"EyeDistribution.{k}" for k in (
            "eyebox_mm", "eyebox_shape", "pupil_range_mm", "focus_range_diopters", "gaze_deg",
            "rotation_mm")}
        names["pupil"] = "EyeDistribution.nominal_pupil_mm"
        names["focus"] = "EyeDistribution.nominal_focus_diopters"
        check_fields(names, eyebox_mm=self.eyebox_mm, eyebox_shape=self.eyebox_shape,
                     pupil_range_mm=self.pupil_range_mm, nominal_pupil_mm=self.nominal_pupil_mm,
                     focus_range_diopters=self.focus_range_diopters,
                     nominal_focus_diopters=self.nominal_focus_diopters, gaze_deg=self.gaze_deg,
                     rotation_mm=self.rotation_mm)
        for name, value in (("centre_mm", centre), ("eyebox_mm", self.eyebox_mm),
                            ("pupil_range_mm", self.pupil_range_mm),
                            ("focus_range_diopters", self.focus_range_diopters)):
            object.__setattr__(self, name, check_pair(name, value))
        for name in ("nominal_pupil_mm", "nominal_focus_diopters", "gaze_deg", "rotation_mm"):
            object.__setattr__(self, name, float(getattr(self, name)))

    @property
    def is_point(self) -> bool:
        """True when every state is the nominal one (no eyebox, no ranges, no gaze)."""
        return (self.eyebox_mm == (0.0, 0.0) and self.gaze_deg == 0.0
                and self.pupil_range_mm == (self.nominal_pupil_mm,) * 2
                and self.focus_range_diopters == (self.nominal_focus_diopters,) * 2)

    # -- from unit-cube coordinates to states --------------------------------------------------

    def _eyebox_offsets(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(N, 2) lateral offsets from the centre, uniform over the eyebox for uniform u, v."""
        half_w, half_h = self.eyebox_mm[0] / 2, self.eyebox_mm[1] / 2
        if self.eyebox_shape == "rect":
            return np.stack([(2 * u - 1) * half_w, (2 * v - 1) * half_h], axis=-1)
        radius, angle = np.sqrt(u), 2 * math.pi * v
        return np.stack([half_w * radius * np.cos(angle), half_h * radius * np.sin(angle)],
                        axis=-1)

    def _states(self, unit: np.ndarray, weight: np.ndarray | None = None) -> EyeStates:
        """States from (N, 6) points of the unit cube: eyebox (2), gaze (2), pupil, focus."""
        count = unit.shape[0]
        box = self._eyebox_offsets(unit[:, 0], unit[:, 1])
        radius, angle = self.gaze_deg * np.sqrt(unit[:, 2]), 2 * math.pi * unit[:, 3]
        gaze = np.stack([radius * np.cos(angle), radius * np.sin(angle)], axis=-1)
        offset = np.asarray(self.centre_mm) + box + self.rotation_mm * np.sin(np.radians(gaze))
        lo, hi = self.pupil_range_mm
        pupil = lo + (hi - lo) * unit[:, 4]
        f_lo, f_hi = self.focus_range_diopters
        focus = f_lo + (f_hi - f_lo) * unit[:, 5]
        if weight is None:
            weight = np.full(count, 1.0 / count)
        return EyeStates(offset, pupil, focus, gaze, weight)

    # -- batches ------------------------------------------------------------------------------

    def sample(self, count: int, seed: int) -> EyeStates:
        """`count` states drawn independently (equal weights); deterministic in (count, seed).

        All six coordinates are drawn whether or not they vary, so two distributions sampled
        with the same seed use the same random numbers (common random numbers).
        """
        _check_count("sample", count)
        _check_seed("sample", seed)
        rng = np.random.Generator(np.random.PCG64(int(seed)))
        return self._states(rng.random((count, _DIMS)))

    def nominal(self) -> EyeStates:
        """The one nominal state: centre, nominal pupil and focus, no gaze."""
        return EyeStates(np.asarray([self.centre_mm], dtype=float),
                         np.array([self.nominal_pupil_mm]),
                         np.array([self.nominal_focus_diopters]), np.zeros((1, 2)),
                         np.ones(1))

    def evaluation_states(self, count: int, seed: int = 0) -> EyeStates:
        """A fixed low-discrepancy set of `count` states covering the distribution (equal
        weights), for judging a part: percentiles over it converge much faster than over random
        draws.

        The Halton sequence (bases 2, 3, 5, 7, 11, 13, index 1 to count) gives the varying
        coordinates in the order eyebox (2), gaze (2), pupil, focus, the lowest bases to the
        first; seed > 0 shifts it on the unit torus (Cranley-Patterson rotation) by a random
        vector, for an independent set of the same quality.
        """
        _check_count("evaluation_states", count)
        _check_seed("evaluation_states", seed)
        shift = (np.random.Generator(np.random.PCG64(int(seed))).random(_DIMS) if seed
                 else np.zeros(_DIMS))
        return self._halton(count, shift)

    def stratified(self, count: int, seed: int) -> EyeStates:
        """`count` states that spread evenly over the distribution and are still a random draw
        (equal weights): the Halton set of `evaluation_states`, shifted on the unit torus by a
        vector drawn from `seed` (a randomized quasi-Monte Carlo set). Every point is uniform
        over the distribution, so a mean over the set estimates the expectation without bias,
        with less variance than `count` independent draws: the optimizer's draw per iteration.
        Deterministic in (count, seed)."""
        _check_count("stratified", count)
        _check_seed("stratified", seed)
        return self._halton(count, np.random.Generator(np.random.PCG64(int(seed))).random(_DIMS))

    def _halton(self, count: int, shift: np.ndarray) -> EyeStates:
        varying = [self.eyebox_mm[0] > 0 or self.eyebox_mm[1] > 0] * 2
        varying += [self.gaze_deg > 0 and self.rotation_mm > 0] * 2
        varying += [self.pupil_range_mm[0] < self.pupil_range_mm[1],
                    self.focus_range_diopters[0] < self.focus_range_diopters[1]]
        unit = np.full((count, _DIMS), 0.5)
        index = np.arange(1, count + 1)
        primes = iter(_PRIMES)
        for dim, varies in enumerate(varying):
            if varies:
                unit[:, dim] = (_radical_inverse(index, next(primes)) + shift[dim]) % 1.0
        return self._states(unit)

    def eyebox_grid(self, n: int) -> tuple[EyeStates, np.ndarray]:
        """n x n pupil positions over the eyebox's bounding box, at the nominal pupil and focus.

        Returns all n * n states, row-major with row 0 at +y (the top, like images) and column
        0 at -x, at the centres of an n x n division of the box; and `inside` (n, n) bool, True
        where the position lies in the eyebox shape. Weights are equal over the inside states
        and 0 outside, so a weighted mean is one over the eyebox. A zero-size axis puts every
        column (row) at the centre.
        """
        _check_count("eyebox_grid", n)
        w, h = self.eyebox_mm
        steps = (np.arange(n) + 0.5) / n * 2 - 1  # -1 to 1, cell centres
        ys, xs = np.meshgrid(-steps, steps, indexing="ij")  # row 0 at +y
        if self.eyebox_shape == "rect":
            inside = np.ones((n, n), dtype=bool)
        else:
            inside = (xs * (w > 0)) ** 2 + (ys * (h > 0)) ** 2 <= 1 + 1e-12
        offset = np.stack([xs * w / 2, ys * h / 2], axis=-1).reshape(-1, 2)
        count = n * n
        weight = inside.reshape(-1) / inside.sum()
        states = EyeStates(offset + np.asarray(self.centre_mm),
                           np.full(count, self.nominal_pupil_mm),
                           np.full(count, self.nominal_focus_diopters), np.zeros((count, 2)),
                           weight)
        return states, inside


_MAX_STATES = 10_000_000


def _check_count(what: str, count: int) -> None:
    if not (isinstance(count, (int, np.integer)) and not isinstance(count, bool)
            and 1 <= count <= _MAX_STATES):
        raise ValueError(f"EyeDistribution.{what}: count = {count!r}; allowed: a whole number "
                         f"from 1 to {_MAX_STATES}.")


def _check_seed(what: str, seed: int) -> None:
    if not (isinstance(seed, (int, np.integer)) and not isinstance(seed, bool) and seed >= 0):
        raise ValueError(f"EyeDistribution.{what}: seed = {seed!r}; allowed: a whole number "
                         ">= 0 (see iteration_seed).")


def distribution_of(eye: Eye) -> EyeDistribution:
    """The distribution a scene's Eye describes: centred on its first (nominal) position; a
    None range is the nominal point."""
    focus = eye.focus_diopters
    pupil_range = eye.pupil_range_mm or (eye.pupil_mm, eye.pupil_mm)
    focus_range = eye.focus_range_diopters or (focus, focus)
    # Keep the nominal exactly inside a range whose end it equals up to 1000 / mm rounding.
    focus = min(max(focus, focus_range[0]), focus_range[1])
    return EyeDistribution(
        centre_mm=eye.positions_mm[0],
        eyebox_mm=eye.eyebox_mm,
        eyebox_shape=eye.eyebox_shape,
        pupil_range_mm=pupil_range,
        nominal_pupil_mm=eye.pupil_mm,
        focus_range_diopters=focus_range,
        nominal_focus_diopters=focus,
        gaze_deg=eye.gaze_deg,
        rotation_mm=eye.rotation_mm,
    )


# ---------------------------------------------------------------------------------------------
# Judging over states


def percentiles(values: Sequence[float] | np.ndarray, weights: Sequence[float] | np.ndarray | None,
                qs: Sequence[float] = (10, 50, 90)) -> np.ndarray:
    """Weighted percentiles (len(qs),) of `values` (S,) with `weights` (S,) (None: equal).

    Definition: sort the values; the k-th (weight w_k, weights normalised to sum 1, zero
    weights dropped) sits at the midpoint of its share of the cumulative weight,
    p_k = 100 (W_k - w_k / 2) with W_k the cumulative weight up to and including it; the
    percentile q is linear interpolation in p, clamped to the smallest / largest value outside
    [p_first, p_last]. With equal weights this is numpy's method="hazen" (p_k = 100 (k + 1/2) /
    S) exactly, and within one gap between neighbouring sorted values of its default "linear".
    """
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    w = np.full(v.shape, 1.0) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != v.shape or v.size == 0:
        raise ValueError(f"percentiles: {v.size} values and weights of shape {w.shape}; allowed: "
                         "one weight per value, at least one value.")
    if not (np.all(np.isfinite(v)) and np.all(np.isfinite(w)) and np.all(w >= 0)
            and w.sum() > 0):
        raise ValueError("percentiles: values must be finite and weights finite, >= 0, with a "
                         "positive sum.")
    q = np.asarray(qs, dtype=np.float64)
    if not np.all((q >= 0) & (q <= 100)):
        raise ValueError(f"percentiles: qs = {qs!r}; allowed: 0 to 100.")
    keep = w > 0
    v, w = v[keep], w[keep]
    order = np.argsort(v, kind="stable")
    v, w = v[order], w[order] / w.sum()
    position = 100.0 * (np.cumsum(w) - w / 2)
    return np.interp(q, position, v)
