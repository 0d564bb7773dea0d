"""The brightness floors: the optimizer keeps the plate's light efficiency
(optimizer.min_efficiency) or the light at the eye with its content (optimizer.min_eye_level)
up to the floor, and gives up image quality for it; a floor no plate reaches is refused."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import tiny_config

from aperture_fab.config import resolve
from aperture_fab.config.presets import LIGHT_FLOOR
from aperture_fab.config.stages import FabricationSettings
from aperture_fab.fabrication.process import resolve_process
from aperture_fab.optics.as_made import white_transmission
from aperture_fab.optics.eyes import EyeStates
from aperture_fab.optics.model import Renderer
from aperture_fab.optics.open_view import render_open
from aperture_fab.optimize.optimizer import (
    EYE_FLOOR_HEADROOM,
    EYE_FLOOR_MEMORY,
    FLOOR_AIM,
    FLOOR_WEIGHT,
    LIGHT_VIEW_PIXELS,
    _design_loss,
    _hold_eye_floor,
    light_renderer,
    training_states,
)
from aperture_fab.pipeline.design_job import design
from aperture_fab.targets import digit

pytestmark = pytest.mark.usefixtures("one_torch_thread")
#: The floor may be missed by this share after a short run (a penalty, not a hard constraint).
FLOOR_SLACK = 0.1


def efficiency(config, result) -> float:  # type: ignore[no-untyped-def]
    renderer = Renderer(config.scene, dtype=torch.float64)
    a = torch.as_tensor(result.design.open_fraction)
    shown = torch.as_tensor(result.design.displays[0])
    with torch.no_grad():
        view = renderer.render(a, shown, 0)
        return float(view.mean() / render_open(config.scene, shown, 0).mean())


@pytest.mark.slow
def test_the_floor_holds_and_costs_quality() -> None:
    free = tiny_config(**{"optimizer.iterations": 60})
    floored = tiny_config(**{"optimizer.iterations": 60, "optimizer.min_efficiency": 0.02})
    plain, bright = design([digit("3")], free), design([digit("3")], floored)
    assert efficiency(free, plain) < 0.02  # the floor binds: the free design is darker
    assert efficiency(floored, bright) >= 0.02 * (1 - FLOOR_SLACK)
    assert bright.metrics["optimized"]["psnr_db"][0] < plain.metrics["optimized"]["psnr_db"][0]


@pytest.mark.parametrize("tail_share", [0.5, 1.0])
def test_the_efficiency_floor_holds_the_states_mean_white_efficiency(tail_share: float) -> None:
    """The floor's penalty is FLOOR_WEIGHT (1 - E / (FLOOR_AIM floor))^2 with E the states'
    weighted mean light efficiency (each state's view of a white display, rendered here on its
    own), and nothing above that however dim a state is, or the content: the report judges E."""
    scene = tiny_config().scene
    renderer = Renderer(scene, dtype=torch.float64)
    rng = np.random.default_rng(3)
    a = torch.as_tensor(rng.uniform(0.05, 0.4, (scene.plate.cells[1], scene.plate.cells[0])))
    pixels = scene.display.pixels[::-1]
    display = torch.as_tensor(rng.uniform(0.0, 0.2, (3, *pixels)))  # a dark content
    target = torch.as_tensor(rng.uniform(0.0, 1.0, (1, 3, *scene.eye.view_pixels[::-1])))
    # an eye off to the side sees less of the display: a dimmer state
    states = EyeStates(np.array([[0.0, 0.0], [1.5, 0.5], [-0.3, 0.2]]), np.array([4.0, 3.0, 5.0]),
                       np.zeros(3), np.zeros((3, 2)), np.array([0.5, 0.3, 0.2]))
    with torch.no_grad():
        white = renderer.render_states(a, renderer.display_stack(torch.ones(1, *pixels)), states)
    each = white.mean((1, 2, 3)).numpy()
    mean = float((each * states.weight).sum())
    assert each.min() < 0.9 * mean  # a per-state floor between them would bind

    def penalty(floor: float) -> float:
        loss = [float(_design_loss(renderer, a, display[None], target, states, 0.0, tail_share,
                                   min_efficiency=f)) for f in (floor, 0.0)]
        return loss[0] - loss[1]

    assert penalty((each.min() + mean) / 2) == 0.0
    floor = 1.25 * mean
    want = FLOOR_WEIGHT * (1 - mean / (FLOOR_AIM * floor)) ** 2
    assert penalty(floor) == pytest.approx(want, rel=1e-9)


def test_the_floor_measures_the_light_on_a_coarse_view_as_well_as_on_the_full_one() -> None:
    """The light efficiency per eye state from `light_renderer` (the near-eye preset's 128 x 128
    view cut to LIGHT_VIEW_PIXELS per axis) is the full view's within 0.2 %."""
    config = resolve("near-eye")
    renderer = Renderer(config.scene)
    light = light_renderer(renderer)
    assert light.scene.eye.view_pixels == (LIGHT_VIEW_PIXELS, LIGHT_VIEW_PIXELS)
    assert light.scene.eye.fov_deg == renderer.scene.eye.fov_deg
    cells = (config.scene.plate.cells[1], config.scene.plate.cells[0])
    a = torch.as_tensor(np.random.default_rng(4).uniform(0.0, 0.3, cells), dtype=torch.float32)
    states = training_states(config.scene, config.optimizer, 7)
    full, coarse = (white_transmission(r, a, states) for r in (renderer, light))
    torch.testing.assert_close(coarse, full, rtol=2e-3, atol=0.0)
    assert light_renderer(light) is light  # a view that small is kept


def eye_level(config, result) -> float:  # type: ignore[no-untyped-def]
    """The light at the eye: the mean view of the design's content (nominal eye)."""
    renderer = Renderer(config.scene, dtype=torch.float64)
    with torch.no_grad():
        return float(renderer.render(torch.as_tensor(result.design.open_fraction),
                                     torch.as_tensor(result.design.displays[0]), 0).mean())


@pytest.mark.slow
def test_the_floor_on_the_light_at_the_eye_holds_and_costs_quality() -> None:
    free = tiny_config(**{"optimizer.iterations": 60})
    plain = design([digit("3")], free)
    # binding, and far enough above the free design that the penalty's first steps overshoot
    # it (8 times without the hold below)
    floor = 3 * eye_level(free, plain)
    floored = tiny_config(**{"optimizer.iterations": 60, "optimizer.min_eye_level": floor})
    bright = design([digit("3")], floored)
    # held near the floor, not above it: the image loss is blind to the content's scale, so
    # the content is scaled down to the floor after each step (EYE_FLOOR_HEADROOM)
    assert floor * (1 - FLOOR_SLACK) <= eye_level(floored, bright) \
        <= floor * (1 + EYE_FLOOR_HEADROOM + FLOOR_SLACK)
    assert bright.metrics["optimized"]["psnr_db"][0] < plain.metrics["optimized"]["psnr_db"][0]


@pytest.mark.parametrize(("level", "since", "scaled", "after"), [
    (0.02, math.inf, False, math.inf),  # above and never below: the content's own light
    (0.005, 3.0, False, 0.0),  # below: the penalty pushes
    (0.02, 3.0, True, 4.0),  # above, just after a push: the overshoot is undone
    (0.0102, 3.0, False, 4.0),  # within the headroom
    (0.02, EYE_FLOOR_MEMORY, False, EYE_FLOOR_MEMORY + 1.0),  # the push has run out
])
def test_the_eye_floor_is_held_only_while_its_push_goes_on(level, since, scaled, after) -> None:
    floor = 0.01
    display = torch.full((3, 4, 4), 0.5, dtype=torch.float64)
    count = _hold_eye_floor(display, {"eye_level": level}, floor, since)
    assert count == after
    want = 0.5 * floor * (1 + EYE_FLOOR_HEADROOM) / level if scaled else 0.5
    torch.testing.assert_close(display, torch.full_like(display, want))


def test_no_eye_floor_leaves_the_content_alone() -> None:
    display = torch.full((3, 4, 4), 0.5, dtype=torch.float64)
    assert _hold_eye_floor(display, {"eye_level": 0.3}, 0.0, math.inf) == math.inf
    assert bool((display == 0.5).all())


@pytest.mark.parametrize(("key", "light"), [("min_efficiency", "the open display's light"),
                                            ("min_eye_level", "the panel's white at the eye")])
def test_a_floor_no_plate_reaches_is_refused_before_the_work(key: str, light: str) -> None:
    config = tiny_config(**{f"optimizer.{key}": 0.6, "plate.thickness_mm": 0.005})
    with pytest.raises(ValueError, match=rf"optimizer.{key} = 0.6 \(60.00% of {light}\) cannot "
                       r"be met: the brightest plate with process 'photomask'.* passes "
                       r"\d+\.\d+%. Lower the floor to"):
        design([digit("3")], config,
               fabrication=FabricationSettings(resolve_process("photomask")))


@pytest.mark.parametrize(("overrides", "fragment"), [
    ({"optimizer.min_eye_level": 1.0}, "optimizer.min_eye_level = 1.0 is out of range"),
    ({"optimizer.min_eye_level": -0.1}, "optimizer.min_eye_level = -0.1 is out of range"),
    ({"optimizer.min_eye_level": 0.01, "optimizer.tracking": "tracked"},
     "optimizer.min_eye_level holds an untracked design's brightness"),
    ({"optimizer.min_efficiency": 1.0}, "optimizer.min_efficiency = 1.0 is out of range"),
    ({"optimizer.min_efficiency": -0.1}, "optimizer.min_efficiency = -0.1 is out of range"),
])
def test_bad_floors_are_refused(overrides: dict, fragment: str) -> None:
    with pytest.raises(ValueError, match=fragment):
        resolve("near-eye", overrides=overrides)


def test_the_default_floor_is_two_percent_and_a_tracked_design_keeps_it() -> None:
    assert resolve("near-eye").optimizer.min_efficiency == LIGHT_FLOOR == 0.02
    assert resolve("seed").optimizer.min_efficiency == 0.0
    # the plate's white efficiency does not depend on the content shown: it holds for a
    # tracked design too, whose frames keep the untracked content's light
    tracked = resolve("near-eye", overrides={"optimizer.tracking": "tracked"})
    assert tracked.optimizer.min_efficiency == LIGHT_FLOOR
    # a floor on the light at the eye set below the tracked design's layer is dropped
    both = resolve("near-eye", {"optimizer": {"min_eye_level": 0.01}},
                   overrides={"optimizer.tracking": "tracked"})
    assert both.optimizer.min_eye_level == 0.0
