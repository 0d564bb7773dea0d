"""What a sweep will cost, before any cluster work (--dry-run): which points the checks
`aperture-fab design` runs first refuse, the optimizer's memory per point (optimize/budget.py)
and the CPU time.

The CPU time comes from the sweep's own finished points in --out when there are some (their
mean CPU seconds: the best guide there is); otherwise from a rough model, a fixed cost per job
(imports, validation, export) plus a cost per traced view pixel, eye state and iteration,
calibrated on this project's tiny designs on one core. It is a planning figure: a factor of
two either way is expected.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from aperture_fab.sweep.spec import Point, SweepSpec, make_point
from aperture_fab.sweep.worker import plain

if TYPE_CHECKING:
    from aperture_fab.sweep.run import Resolver

__all__ = ["Estimate", "estimate_points", "model_cpu_seconds"]

#: The model: CPU seconds of a design job with no optimizer work (validation, export) ...
SETUP_CPU_S = 4.0
#: ... plus this per view pixel x eye state x target x iteration (optimizer and fitting).
CPU_S_PER_WORK = 2.5e-6


@dataclass(frozen=True)
class Estimate:
    """refused: (point, the error) for each point the checks refuse; peak_bytes: the largest
    optimizer memory estimate; cpu_seconds: per point; basis: where that figure comes from."""

    refused: tuple[tuple[Point, str], ...]
    peak_bytes: int
    cpu_seconds: float
    basis: str


def model_cpu_seconds(config: object, targets: int) -> float:
    """The rough model's CPU seconds of one design job."""
    scene, settings = config.scene, config.optimizer  # type: ignore[attr-defined]
    width, height = scene.eye.view_pixels
    states = 1 if scene.eye.eyebox_mm == 0 else max(1, settings.eye_states)
    work = settings.iterations * width * height * states * targets
    return SETUP_CPU_S + CPU_S_PER_WORK * work


def _measured(spec: SweepSpec, points: Sequence[Point], out: Path) -> list[float]:
    from aperture_fab.sweep.run import POINTS_DIR, load_record

    seconds = []
    for point in points:
        record = load_record(out / POINTS_DIR / point.id)
        if record is not None and record["status"] == "ok" and record.get("cpu_seconds"):
            seconds.append(float(record["cpu_seconds"]))
    return seconds


def estimate_points(spec: SweepSpec, points: Sequence[Point], out: Path,
                    resolve: Resolver | None = None) -> Estimate:
    """Run the checks on every point (a search: on [base] alone) and sum up; `resolve`: the
    sweep's Resolver, when the points were resolved already."""
    from aperture_fab.sweep.run import Preflight, Resolver

    resolve = resolve or Resolver(spec)

    checked = list(points) or [make_point(spec, ())]
    refused: list[tuple[Point, str]] = []
    peak, model = 0, []
    preflight = Preflight()
    for point in checked:
        try:
            config, fabrication, _ = resolve({k: plain(v) for k, v in point.overrides})
            peak = max(peak, preflight(config, fabrication, len(spec.targets)))
        except ValueError as err:
            refused.append((point, str(err)))
            continue
        model.append(model_cpu_seconds(config, len(spec.targets)))
    measured = _measured(spec, points, out.resolve())
    if measured:
        return Estimate(tuple(refused), peak, sum(measured) / len(measured),
                        f"the mean of the {len(measured)} point(s) finished in {out}")
    mean = sum(model) / len(model) if model else 0.0
    return Estimate(tuple(refused), peak, mean, "a rough model of one core; the finished "
                    "points' own times replace it on the next --dry-run")
