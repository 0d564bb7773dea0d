"""The design job's second lattice (`design_job.design` with optimizer.lattice = "rival"): the
config that designs on the best regular array's lattice from that array's holes, and of the two
parts the one kept, the part as made that beats its own best regular pinhole array by more."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from aperture_fab.config.settings import OptimizerSettings
from aperture_fab.optics.scene import Scene
from aperture_fab.validation.regular import lattice_scene
from aperture_fab.validation.verdicts import RETRY_LATTICE_BELOW_DB, rival_lattice

if TYPE_CHECKING:  # the design job calls these; its module imports this one
    from aperture_fab.pipeline.design_job import DesignResult

__all__ = ["better_part", "margin_db", "rival_start"]


def margin_db(result: DesignResult) -> float:
    """The part's smallest margin over its best regular array (dB): -inf when the part as made
    was not judged, +inf when no regular array is as bright at the eye."""
    block = result.made_part
    if not block:
        return -math.inf
    return math.inf if block["margin_db"] is None else float(min(block["margin_db"]))


def better_part(first: DesignResult, second: DesignResult) -> DesignResult:
    """Of two designs on different lattices, the one whose part as made beats its own best
    regular array by more (the first on a tie), with both in `lattices` (each design's stage
    seconds among them: its report's, or the stages it ran when it was not judged in full; the
    kept part's report times its own)."""
    kept = second if margin_db(second) > margin_db(first) else first

    def record(result: DesignResult) -> dict[str, Any]:
        plate = result.config.scene.plate
        block = result.made_part
        return {"pitch_mm": list(plate.pitch_mm), "cells": list(plate.cells),
                "p10_db": None if not block else list(block["part"]["p10_db"]),
                "margin_db": None if not block else block["margin_db"],
                "kept": result is kept,
                "timings_s": dict(result.timings_s if result.report is None
                                  else result.report.timings_s)}

    return dataclasses.replace(kept, lattices=(record(first), record(second)))


def rival_start(scene: Scene, optimizer: OptimizerSettings, block: Mapping[str, Any],
                ) -> tuple[Scene, OptimizerSettings] | None:
    """The scene and optimizer settings of the second design, or None: when the part as made
    (its report's made_part `block`) beats its best regular array by less than
    RETRY_LATTICE_BELOW_DB and that array's pitch is coarser than the plate's cells
    (`rival_lattice`), the plate of that pitch over the same outline, started from the array's
    own holes (optimizer.init_diameter_mm) and its elemental images: the part then starts where
    its rival is, at its light."""
    plate = scene.plate
    given = {"pitch_mm": list(plate.pitch_mm), "cells": list(plate.cells)}
    lattice = rival_lattice(given, block, RETRY_LATTICE_BELOW_DB)
    if lattice is None:
        return None
    start = dataclasses.replace(optimizer, init="pinholes",
                                init_diameter_mm=float(block["regular"]["best"]["diameter_mm"]))
    return lattice_scene(scene, lattice[0]), start
