"""Fabrication-aware design: the sizes a process makes (quantize.made_sizes), the optimizer's
snapped last iterations, and make_part's bias compensation, which together make the optimized
plate exactly the part that is built."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from aperture_fab.config.config import Config
from aperture_fab.config.stages import FabricationSettings
from aperture_fab.fabrication.part import design_bounds, drawn_fractions, made_optics, make_part
from aperture_fab.fabrication.process import PROCESSES, resolve_process
from aperture_fab.fabrication.quantize import MadeSizes, made_sizes
from aperture_fab.io.images import resample
from aperture_fab.optimize.optimizer import _snapped, optimize
from aperture_fab.targets import asymmetric_marker
from aperture_fab.validation.validate import layout_fractions

pytestmark = pytest.mark.usefixtures("one_torch_thread")

MakeConfig = Callable[..., Config]
RESIN = PROCESSES["resin"]
#: A plate resin makes (the presets' is photomask film's 5 um emulsion).
RESIN_PLATE = {"plate.thickness_mm": 0.3}


def resin_sizes(config: Config) -> MadeSizes:
    return made_sizes(config.scene.plate, RESIN, config.scene.mid_plane_distance_mm)


def test_resin_levels_are_the_made_areas_of_its_radius_steps(make_config: MakeConfig) -> None:
    config = make_config(**RESIN_PLATE)
    plate = config.scene.plate
    made = resin_sizes(config)
    assert made.levels is not None and made.levels[0] == 0
    cell = plate.pitch_mm[0] * plate.pitch_mm[1]
    radii = np.sqrt(made.levels[1:] * cell / math.pi) - RESIN.radius_bias_mm  # drawn
    steps = radii / RESIN.radius_step_mm
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-9)  # on the process's step
    assert radii[0] >= RESIN.min_hole_mm / 2 - 1e-12
    # The largest keeps the web at the top face of a chief-ray plate.
    assert 2 * radii[-1] + RESIN.min_web_for(plate.thickness_mm) <= min(plate.pitch_mm) + 1e-9
    assert np.all(np.diff(made.levels) > 0)
    assert design_bounds(config.scene, RESIN)[1] == pytest.approx(made.hi)


def test_continuous_process_snaps_below_half_the_smallest_hole_to_closed() -> None:
    made = MadeSizes(None, 0.1, 0.5)
    np.testing.assert_array_equal(made.snap(np.array([0.0, 0.049, 0.051, 0.3, 0.7])),
                                  [0.0, 0.0, 0.1, 0.3, 0.5])


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(0, 0.6), min_size=8, max_size=8))
def test_snap_picks_the_nearest_level(values: list[float]) -> None:
    made = MadeSizes(np.array([0.0, 0.1, 0.15, 0.4]), 0.1, 0.4)
    a = np.array(values)
    snapped = made.snap(a)
    nearest = made.levels[np.argmin(np.abs(a[:, None] - made.levels[None]), axis=1)]
    np.testing.assert_allclose(np.abs(snapped - a), np.abs(nearest - a), atol=1e-15)


def test_snapped_is_the_snap_forward_and_the_identity_backward() -> None:
    made = MadeSizes(np.array([0.0, 0.1, 0.2, 0.4]), 0.1, 0.4)
    a = torch.tensor([0.02, 0.08, 0.16, 0.33, 0.5], dtype=torch.float64, requires_grad=True)
    weights = torch.arange(1.0, 6.0, dtype=torch.float64)
    out = _snapped(a, made)
    np.testing.assert_array_equal(out.detach().numpy(), made.snap(a.detach().numpy()))
    (out * weights).sum().backward()
    assert a.grad is not None
    np.testing.assert_array_equal(a.grad.numpy(), weights.numpy())


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_a_plate_of_made_sizes_is_built_exactly(seed: int) -> None:
    """make_part draws each hole bias-compensated; quantization keeps a plate that is already
    makeable, so the holes as made are the design's, cell for cell."""
    from tests.conftest import tiny_config

    config = tiny_config(**RESIN_PLATE)
    made = resin_sizes(config)
    assert made.levels is not None
    rng = np.random.default_rng(seed)
    rows, cols = config.scene.plate.cells[1], config.scene.plate.cells[0]
    a = made.levels[rng.integers(0, len(made.levels), (rows, cols))]
    part = make_part(a, config.scene, FabricationSettings(RESIN))
    np.testing.assert_allclose(layout_fractions(part.layout, RESIN.radius_bias_mm), a,
                               atol=1e-12)


def test_drawn_fractions_undo_the_bias(make_config: MakeConfig) -> None:
    plate = make_config().scene.plate
    process = resolve_process("resin", {"radius_bias_mm": -0.02})
    cell = plate.pitch_mm[0] * plate.pitch_mm[1]
    a = np.array([[0.0, 0.1], [0.2, 0.3]])
    drawn = np.sqrt(drawn_fractions(a, plate, process) * cell / math.pi)
    made = np.where(a > 0, drawn + process.radius_bias_mm, 0.0)
    np.testing.assert_allclose(math.pi * made**2 / cell, a, atol=1e-12)


def run(config: Config, **kwargs: Any) -> Any:
    scene = config.scene
    image = asymmetric_marker(32)[:1]
    targets = resample(image, scene.eye.view_pixels)[None]
    shown = resample(image, scene.display.pixels)[None]
    return optimize(scene, targets, shown, config.optimizer, progress=False, **kwargs)


def test_fabrication_aware_run_ends_makeable_and_keeps_its_continuous_optimum(
        make_config: MakeConfig) -> None:
    config = make_config(**RESIN_PLATE,
                         **{"optimizer.iterations": 10, "optimizer.quantize_share": 0.4})
    made = resin_sizes(config)
    result = run(config, bounds=design_bounds(config.scene, RESIN), made=made)
    assert made.levels is not None
    assert np.all(np.isin(result.open_fraction, made.levels))
    assert result.continuous is not None
    continuous, displays = result.continuous
    assert not np.all(np.isin(continuous, made.levels))
    assert displays.shape == result.displays.shape
    # The first 6 iterations are a plain 6-iteration run (one cosine cycle), and the kept
    # optimum is its result.
    plain = run(make_config(**RESIN_PLATE,
                            **{"optimizer.iterations": 6, "optimizer.quantize_share": 0.0}),
                bounds=design_bounds(config.scene, RESIN), made=made)
    assert plain.continuous is None
    np.testing.assert_allclose(result.loss_history[:6], plain.loss_history, rtol=1e-5)
    np.testing.assert_allclose(continuous, plain.open_fraction, rtol=1e-5, atol=1e-7)


def test_fabrication_aware_run_resumes_exactly(make_config: MakeConfig) -> None:
    config = make_config(**RESIN_PLATE,
                         **{"optimizer.iterations": 12, "optimizer.checkpoint_every": 4,
                            "optimizer.precision": "float64", "optimizer.quantize_share": 0.5})
    made = resin_sizes(config)
    whole = run(config, made=made)
    saved: list[dict[str, Any]] = []
    run(config, made=made, on_checkpoint=saved.append)
    for state in saved[:2]:  # before and after the snap starts (iteration 6)
        again = run(config, made=made, state=state)
        np.testing.assert_allclose(again.loss_history, whole.loss_history, rtol=1e-6)
        np.testing.assert_array_equal(again.open_fraction, whole.open_fraction)


def test_an_as_made_run_snaps_every_iteration_and_resumes_exactly(
        make_config: MakeConfig) -> None:
    """quantize_share 1: every iteration sees holes the process makes and one made copy's
    errors (photomask film, diffraction, veil); there is no unconstrained design to keep, the
    display is fitted to the snapped plate, and a resume draws the same copies."""
    process = PROCESSES["photomask"]
    config = make_config(**{"optimizer.iterations": 8, "optimizer.checkpoint_every": 4,
                            "optimizer.precision": "float64", "optimizer.quantize_share": 1.0})
    made = made_sizes(config.scene.plate, process, config.scene.mid_plane_distance_mm)
    optics = made_optics(config.scene, process)
    assert optics.has_errors and optics.diffraction is not None
    saved: list[dict[str, Any]] = []
    whole = run(config, made=made, optics=optics, on_checkpoint=saved.append)
    assert whole.snapped and whole.continuous is None
    assert np.all(np.isin(whole.open_fraction, made.snap(whole.open_fraction)))
    again = run(config, made=made, optics=optics, state=saved[0])
    np.testing.assert_allclose(again.loss_history, whole.loss_history, rtol=1e-9)
    np.testing.assert_array_equal(again.open_fraction, whole.open_fraction)
