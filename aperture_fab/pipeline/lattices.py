"""Of two parts designed on different lattices, the one the design job keeps: the part as made
that beats its own best regular pinhole array by more (`design_job.design` with
optimizer.lattice = "rival")."""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the design job calls these; its module imports this one
    from aperture_fab.pipeline.design_job import DesignResult

__all__ = ["better_part", "margin_db"]


def margin_db(result: DesignResult) -> float:
    """The part's smallest margin over its best regular array (dB): -inf when the part as made
    was not judged, +inf when no regular array is as bright at the eye."""
    block = None if result.report is None else result.report.made_part
    if not block:
        return -math.inf
    return math.inf if block["margin_db"] is None else float(min(block["margin_db"]))


def better_part(first: DesignResult, second: DesignResult) -> DesignResult:
    """Of two designs on different lattices, the one whose part as made beats its own best
    regular array by more (the first on a tie), with both in `lattices`."""
    kept = second if margin_db(second) > margin_db(first) else first

    def record(result: DesignResult) -> dict[str, Any]:
        plate = result.config.scene.plate
        block = None if result.report is None else result.report.made_part
        return {"pitch_mm": list(plate.pitch_mm), "cells": list(plate.cells),
                "p10_db": None if not block else list(block["part"]["p10_db"]),
                "margin_db": None if not block else block["margin_db"],
                "kept": result is kept}

    return dataclasses.replace(kept, lattices=(record(first), record(second)))
