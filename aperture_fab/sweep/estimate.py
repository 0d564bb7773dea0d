"""What a sweep will cost, before any cluster work (--dry-run): which points the checks
`aperture-fab design` runs first refuse, the optimizer's memory per point (optimize/budget.py)
and the CPU time.

The CPU time comes from the sweep's own finished points in --out when there are some (their
mean CPU seconds: the best guide there is); otherwise from a model of one core: a fixed cost
per job, a cost per view pixel (evaluation and validation render every pixel whatever the
iterations) and a cost per view pixel x eye state x iteration x target (the optimizer).
Calibrated by least squares on 7 design jobs on one thread (2 shared, loaded cores): near-eye
with 16 x 16 cells, a 32 x 32 display, 16/32/64 px square views x 10/60 iterations, and
tolerance_samples 2/16 (which changed the time by less than the noise); each job's CPU time is
within 11 % of the model (the old one, 4 s + 2.5e-6 s per unit of work, was 39-82 % low). It
extrapolates to about 4.5 min for the default near-eye job (128 x 128, 150 iterations), as
the README's "about five minutes"; expect +-30 % on other machines and settings.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from aperture_fab.sweep.spec import Point, SweepSpec, make_point
from aperture_fab.sweep.worker import plain

if TYPE_CHECKING:
    from aperture_fab.sweep.preflight import Resolver

__all__ = ["Estimate", "estimate_points", "model_cpu_seconds"]

#: The model: CPU seconds of a design job with no view and no iterations (imports, export) ...
SETUP_CPU_S = 5.25
#: ... plus this per view pixel (evaluation, validation: every pixel, whatever the iterations)
CPU_S_PER_VIEW_PIXEL = 4.5e-3
#: ... plus this per view pixel x eye state x target x iteration (optimizer and fitting).
CPU_S_PER_WORK = 9.6e-6


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
    return SETUP_CPU_S + CPU_S_PER_VIEW_PIXEL * width * height + CPU_S_PER_WORK * work


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
    from aperture_fab.sweep.preflight import Preflight, Resolver

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
    return Estimate(tuple(refused), peak, mean, "a model of one core, +-30 %; the finished "
                    "points' own times replace it on the next --dry-run")
