"""Before a sweep runs: each point resolved to its config (Resolver) and checked as a design job
would check it (Preflight), so that a point that cannot run is refused before any work."""

from __future__ import annotations

import json
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from typing import Any

from aperture_fab.sweep.settings import resolve_point
from aperture_fab.sweep.spec import (
    SweepSpec,
)

__all__ = ["Preflight", "Resolver", "preflight"]


class Resolver:
    """resolve_point for one sweep's settings, each distinct set of overrides resolved once
    (an error too): a grid's points are resolved by the checks, then read again by the
    preflight and the estimate, and a one-key grid's points are its values' own checks."""

    def __init__(self, spec: SweepSpec) -> None:
        self.spec = spec
        self.done: dict[str, tuple[Any, Any, Any] | Exception] = {}

    def __call__(self, overrides: Mapping[str, Any]) -> tuple[Any, Any, Any]:
        key = json.dumps(overrides, sort_keys=True, default=str)
        if key not in self.done:
            try:
                self.done[key] = resolve_point(self.spec.preset, self.spec.base_file, overrides)
            except (ValueError, TypeError, KeyError) as err:
                self.done[key] = err
        found = self.done[key]
        if isinstance(found, Exception):
            raise found
        return found


class Preflight:
    """The checks `aperture-fab design` runs before its work, on one point's settings.

    The two that render (the light floor, that the eye sees the display) cost tens of ms each;
    their answers are kept by exactly the inputs they read, so points that differ only in what
    those checks do not read (iterations, validation, the process's tolerances ...) pay
    once."""

    def __init__(self) -> None:
        self.seen: dict[Any, str | None] = {}

    def __call__(self, config: Any, fabrication: Any, targets: int = 1) -> int:
        """Raise the checks' ValueError (e.g. a process that cannot make the plate); return
        the optimizer's memory estimate per iteration, bytes (optimize/budget.py)."""
        from aperture_fab.fabrication.part import design_bounds
        from aperture_fab.fabrication.rules import check_plate
        from aperture_fab.optimize.budget import estimate_bytes

        scene, settings = config.scene, config.optimizer
        if not fabrication.force:
            check_plate(fabrication.process, scene.plate, scene.eye.eye_relief_mm)
        bounds = design_bounds(scene, fabrication.process)
        # Exactly what the two checks read (check_light_floor: the floor, the states drawn
        # by eye_states and seed, the bounds, the process's name for its message).
        key = (scene, settings.min_efficiency, settings.min_eye_level, settings.eye_states,
               settings.seed, bounds, fabrication.process.name)
        if key not in self.seen:
            self.seen[key] = _rendered_checks(scene, settings, bounds, fabrication)
        if self.seen[key] is not None:
            raise ValueError(self.seen[key])
        states = len(scene.eye.positions_mm) if scene.eye.eyebox_mm == 0 else settings.eye_states
        return int(estimate_bytes(scene, max(1, states), "kernel", settings.precision,
                                  targets=targets,
                                  display_optimized=settings.display == "optimized"))


@contextmanager
def _one_thread() -> Iterator[None]:
    """torch and numba on one thread for the checks, then as they were. The checks' renders
    last milliseconds; their thread pools' hand-offs cost as much again on an idle machine and
    several times more on a busy one (measured: a tiny scene's light floor 78 ms on 2 threads
    of 2 loaded cores, 13 ms on one), and the answers are the same."""
    import numba
    import torch

    threads, numba_threads = torch.get_num_threads(), numba.get_num_threads()
    torch.set_num_threads(1)
    numba.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
        numba.set_num_threads(numba_threads)


def _rendered_checks(scene: Any, settings: Any, bounds: Any, fabrication: Any) -> str | None:
    """The error of design's light-floor and eye-sees-display checks, or None."""
    from aperture_fab.pipeline.design_job import check_eye_sees_display, check_light_floor

    try:
        with _one_thread():
            check_light_floor(scene, settings, bounds, fabrication)
            check_eye_sees_display(scene)
    except ValueError as err:
        return str(err)
    return None


def preflight(config: Any, fabrication: Any, targets: int = 1) -> int:
    """Preflight()(...) for one point: the checks `design` runs first; the memory estimate."""
    return Preflight()(config, fabrication, targets)
