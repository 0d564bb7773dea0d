"""Optimizer settings: what is optimized, how, and for how long."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from aperture_fab.optics.scene import check_positive

__all__ = ["Method", "Schedule", "Init", "DisplayMode", "Precision", "Tracking", "Lattice",
           "OptimizerSettings"]

Method = Literal["adam", "sgd"]
Schedule = Literal["constant", "cosine"]
Init = Literal["pinholes", "random", "uniform"]
DisplayMode = Literal["optimized", "target"]
Precision = Literal["float32", "float64"]
Tracking = Literal["untracked", "tracked"]
Lattice = Literal["fixed", "rival"]

METHODS: tuple[Method, ...] = ("adam", "sgd")
SCHEDULES: tuple[Schedule, ...] = ("constant", "cosine")
INITS: tuple[Init, ...] = ("pinholes", "random", "uniform")
DISPLAY_MODES: tuple[DisplayMode, ...] = ("optimized", "target")
PRECISIONS: tuple[Precision, ...] = ("float32", "float64")
TRACKINGS: tuple[Tracking, ...] = ("untracked", "tracked")
LATTICES: tuple[Lattice, ...] = ("fixed", "rival")

MAX_ITERATIONS = 1_000_000
#: Most eye states drawn per iteration: each is a full render of every target.
MAX_EYE_STATES = 1024
#: The largest hole diameter a pinhole start may ask for (mm); a cell caps it further.
MAX_INIT_DIAMETER_MM = 100.0


def _check_choice(name: str, value: str, allowed: tuple[str, ...]) -> None:
    if value not in allowed:
        raise ValueError(f"{name} = {value!r} is not allowed; choose one of {', '.join(allowed)}.")


@dataclass(frozen=True)
class OptimizerSettings:
    """How the plate (and display content) are optimized.

    method: "adam" (default) or "sgd" with momentum (the seed preset).
    learning_rate: step size on the unconstrained parameters (logits).
    momentum: SGD momentum (ignored by Adam).
    iterations: most iterations to run.
    schedule: learning-rate schedule, "cosine" decays to 5 % at the end.
    init: "pinholes" (a regular pinhole array of good size and pitch), "random" (uniform random
        mask, the dissertation's start) or "uniform" (every hole half open).
    init_diameter_mm: the pinhole start's hole diameter, a hole in every cell (the design job
        sets it to start a design on a regular rival's lattice from the rival's holes); 0 (the
        default): the diffraction-optimal pinhole, at the pitch that keeps each hole in its own
        elemental image. Only with init = "pinholes".
    display: "optimized" (display content optimized with the plate) or "target" (shown as is).
    efficiency_weight: weight of the light-efficiency term (0 ignores the light level).
    min_efficiency: a brightness floor: the plate's light efficiency as made (its view of a
        uniform white display over the open display's), the mean over each iteration's eye
        states, as the report judges it; enforced by a penalty that dominates the image loss
        below it, from a quarter of the iterations on; 0 sets no floor.
    min_eye_level: a floor on the light at the eye: the mean view of the design's display
        content over each iteration's eye states, as a share of the panel's full white (the
        panel's luminance times it is the luminance at the eye: 0.01 of a 500 cd/m2 panel is
        5 cd/m2, photopic). Unlike min_efficiency it counts the content, which a coded plate
        keeps dark; enforced by the same kind of penalty, and the content is scaled back down
        to the floor when the penalty's push leaves it higher (brighter costs contrast; a
        content above the floor on its own is left alone); 0 sets no floor.
    plateau_patience: stop when the loss has not improved by plateau_tolerance (relative) for
        this many iterations; 0 never stops early.
    plateau_tolerance: relative improvement that counts as progress.
    seed: random seed for initialization.
    precision: "float32" or "float64".
    device: "auto" (CUDA when available), "cpu", "cuda" or "cuda:N".
    checkpoint_every: iterations between checkpoints in a file-backed run.
    quantize_share: share of the iterations, at the end, that see the plate snapped to the holes
        the fabrication process makes (forward snapped, gradient straight through), so the
        display content and the other holes adapt to what is made; 0: quantize afterwards only.
        Used when designing for a process.
    eye_states: eye states drawn from the eye distribution (`aperture_fab.optics.eyes`) each
        iteration; a fresh draw every iteration. 1 with a point distribution is the nominal eye.
    tail_share: share of the worst states the loss averages: 1 is the plain expected loss over
        the states, 0.1 the mean of the worst 10 % (a CVaR, for a design that holds up at the
        edges of the eyebox rather than on average).
    tracking: "untracked" (one display content for every eye state: the device does not know
        where the eye is) or "tracked" (display content solved per eye state, as with an eye
        tracker, keeping the untracked content's light at the eye; docs/model.md).
    lattice: "rival" (default): when the part as made loses to the best regular pinhole array
        (`aperture_fab.validation.made_part`) and that array's pitch is coarser than the
        plate's cells, the design job designs again on the array's lattice (plate.pitch_mm and
        plate.cells of that pitch) and keeps the part with the larger margin over its best
        regular array (`aperture_fab.pipeline.design_job`); "fixed": plate.cells only. Needs
        the part judged as made (a process and validation.made_copies > 0).
    """

    method: Method = "adam"
    learning_rate: float = 0.05
    momentum: float = 0.9
    iterations: int = 300
    schedule: Schedule = "cosine"
    init: Init = "pinholes"
    init_diameter_mm: float = 0.0
    display: DisplayMode = "optimized"
    efficiency_weight: float = 0.0
    min_efficiency: float = 0.0
    min_eye_level: float = 0.0
    plateau_patience: int = 60
    plateau_tolerance: float = 1e-4
    seed: int = 0
    precision: Precision = "float32"
    device: str = "auto"
    checkpoint_every: int = 50
    quantize_share: float = 0.3
    eye_states: int = 16
    tail_share: float = 1.0
    tracking: Tracking = "untracked"
    lattice: Lattice = "rival"

    def __post_init__(self) -> None:
        _check_choice("optimizer.method", self.method, METHODS)
        _check_choice("optimizer.schedule", self.schedule, SCHEDULES)
        _check_choice("optimizer.init", self.init, INITS)
        _check_choice("optimizer.display", self.display, DISPLAY_MODES)
        _check_choice("optimizer.precision", self.precision, PRECISIONS)
        _check_choice("optimizer.tracking", self.tracking, TRACKINGS)
        _check_choice("optimizer.lattice", self.lattice, LATTICES)
        if self.tracking == "tracked" and self.display == "target":
            raise ValueError(
                'optimizer.tracking = "tracked" solves the display content per eye state, but '
                'optimizer.display = "target" shows the target as is; use display = '
                '"optimized" with tracking, or tracking = "untracked".')
        check_positive("optimizer.learning_rate", self.learning_rate,
                       "Typical: 0.01 to 0.1 for Adam, 0.1 to 1 for SGD.", 100.0)
        if not (math.isfinite(self.momentum) and 0 <= self.momentum < 1):
            raise ValueError(
                f"optimizer.momentum = {self.momentum!r} is out of range; "
                "allowed: 0 <= momentum < 1."
            )
        for name, value, low in (
            ("optimizer.iterations", self.iterations, 1),
            ("optimizer.plateau_patience", self.plateau_patience, 0),
            ("optimizer.checkpoint_every", self.checkpoint_every, 1),
            ("optimizer.seed", self.seed, 0),
        ):
            if not (isinstance(value, int) and not isinstance(value, bool)):
                raise TypeError(f"{name} must be a whole number, got {value!r}")
            if not low <= value <= MAX_ITERATIONS * (2**31 if name.endswith("seed") else 1):
                raise ValueError(f"{name} = {value} is out of range; allowed: >= {low}.")
        if not (math.isfinite(self.efficiency_weight) and self.efficiency_weight >= 0):
            raise ValueError(
                f"optimizer.efficiency_weight = {self.efficiency_weight!r} is out of range; "
                "allowed: a finite number >= 0 (0 ignores the light level)."
            )
        for name, floor, what in (
                ("min_efficiency", self.min_efficiency, "of the open display's light"),
                ("min_eye_level", self.min_eye_level, "of the panel's white at the eye")):
            # The plate's white efficiency does not depend on the content, so min_efficiency
            # holds for a tracked design too; the content's light is the warm start's there.
            if floor > 0 and self.tracking == "tracked" and name == "min_eye_level":
                raise ValueError(
                    f"optimizer.{name} holds an untracked design's brightness; a tracked "
                    "design's frames keep the light of its untracked content instead "
                    f'(tracking.DISPLAY_LIGHT_FLOOR). Use tracking = "untracked" with a floor, '
                    f"or {name} = 0.")
            if not (math.isfinite(floor) and 0 <= floor < 1):
                raise ValueError(
                    f"optimizer.{name} = {floor!r} is out of range; allowed: 0 <= floor < 1 "
                    f"(a share {what}, e.g. 0.005 for 0.5 %; 0 sets no floor).")
        if not (math.isfinite(self.init_diameter_mm)
                and 0 <= self.init_diameter_mm <= MAX_INIT_DIAMETER_MM):
            raise ValueError(
                f"optimizer.init_diameter_mm = {self.init_diameter_mm!r} is out of range; "
                f"allowed: 0 to {MAX_INIT_DIAMETER_MM:g} mm (the start's hole diameter, at most "
                "the cell's largest hole; 0: the diffraction-optimal pinhole).")
        if self.init_diameter_mm > 0 and self.init != "pinholes":
            raise ValueError(
                f"optimizer.init_diameter_mm = {self.init_diameter_mm:g} sizes the pinhole "
                f'start\'s holes, but optimizer.init = "{self.init}"; use init = "pinholes" or '
                "init_diameter_mm = 0.")
        if not (math.isfinite(self.quantize_share) and 0 <= self.quantize_share <= 1):
            raise ValueError(
                f"optimizer.quantize_share = {self.quantize_share!r} is out of range; allowed: "
                "0 to 1 (the share of iterations that see makeable holes; 0 turns it off)."
            )
        if not (isinstance(self.eye_states, int) and not isinstance(self.eye_states, bool)):
            raise TypeError(f"optimizer.eye_states must be a whole number, got "
                            f"{self.eye_states!r}")
        if not 1 <= self.eye_states <= MAX_EYE_STATES:
            raise ValueError(
                f"optimizer.eye_states = {self.eye_states} is out of range; allowed: 1 to "
                f"{MAX_EYE_STATES} (eye states drawn per iteration; each costs one render, "
                "typical 8 to 32; 1 for a fixed eye)."
            )
        if not (isinstance(self.tail_share, (int, float)) and not isinstance(self.tail_share, bool)
                and math.isfinite(self.tail_share) and 0 < self.tail_share <= 1):
            raise ValueError(
                f"optimizer.tail_share = {self.tail_share!r} is out of range; allowed: 0 < "
                "tail_share <= 1 (1: the mean loss over eye states; 0.1: the mean of the worst "
                "10 %)."
            )
        if not (math.isfinite(self.plateau_tolerance) and 0 <= self.plateau_tolerance < 1):
            raise ValueError(
                f"optimizer.plateau_tolerance = {self.plateau_tolerance!r} is out of range; "
                "allowed: 0 <= tolerance < 1."
            )
        if not (self.device in ("auto", "cpu", "cuda") or self.device.startswith("cuda:")):
            raise ValueError(
                f"optimizer.device = {self.device!r} is not allowed; use auto, cpu, cuda or cuda:N."
            )
