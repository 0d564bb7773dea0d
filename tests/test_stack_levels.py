"""A display stack for holes of a known smallest size (`Renderer`'s min_radius_mm,
`optics.stack_levels`): it holds only the levels such holes read, and the kernels' level
offset maps their windows onto them, so their views and gradients are the whole stack's."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from conftest import tiny_config
from test_model import make_scene

from aperture_fab.fabrication.process import resolve_process
from aperture_fab.optics.eyes import EyeStates
from aperture_fab.optics.model import Renderer
from aperture_fab.optics.stack_levels import lens_area_mm2
from aperture_fab.validation.regular import RADIUS_SIGMAS, regular_arrays


@pytest.mark.parametrize(("distance", "share"), [
    (0.0, 1.0), (1.0, (2 * math.pi / 3 - math.sqrt(3) / 2) / math.pi), (2.0, 0.0), (3.0, 0.0)])
def test_the_lens_area_of_two_unit_disks(distance: float, share: float) -> None:
    assert lens_area_mm2(1.0, distance) == pytest.approx(math.pi * share, abs=1e-12)


def _states(offsets: list[tuple[float, float]], pupils: list[float],
            focus: float = 0.0) -> EyeStates:
    count = len(offsets)
    return EyeStates(np.array(offsets, dtype=np.float64), np.array(pupils, dtype=np.float64),
                     np.full(count, focus), np.zeros((count, 2)), np.full(count, 1 / count))


@pytest.mark.parametrize("backend", ["kernel", "torch"])
@pytest.mark.parametrize(("axis", "thickness"), [("straight", 0.0), ("chief_ray", 0.05),
                                                 ("chief_ray", 0.3), ("straight", 0.3)])
def test_holes_at_least_min_radius_render_as_from_the_whole_stack(
        backend: str, axis: str, thickness: float) -> None:
    """Random holes from min_radius_mm to max_radius_mm, moved off their cells, eye states
    across an eyebox and pupil sizes, on plates thin and thick (lenses that shrink): the
    views and both gradients equal the whole stack's, from fewer levels: to the last bits
    through the fused kernels (the kernels' spectra are transformed in batches of another
    size, and the level coordinate goes through another scale and an offset), to 1e-10
    through the torch path, which pads its pair tables with closed cells of about 1e-12 mm^2
    (`render_table`) that read the lowest level held."""
    scene = make_scene(cells=(6, 6), pitch=1.0, thickness=thickness, axis=axis,
                       pixels=(120, 120), size=12.0, view=(24, 24))
    if thickness == 0.3 and axis == "straight":  # display optics and RGB stripes too
        scene = dataclasses.replace(scene, display=dataclasses.replace(
            scene.display, subpixels="rgb_stripe", cover_glass_mm=0.5))
    rng = np.random.default_rng(int(thickness * 100) + len(axis))
    low, high = 0.38, 0.45
    radius = rng.uniform(low, high, (6, 6))
    a = np.pi * radius**2  # 1 mm cells
    offsets = rng.normal(0.0, 0.03, (6, 6, 2))
    states = _states([(0.0, 0.0), (1.2, -0.8), (-1.5, 0.3)], [3.0, 4.0, 6.0])
    display = torch.rand(3, 120, 120, generator=torch.Generator().manual_seed(3),
                         dtype=torch.float64)
    weights = torch.rand(3, 3, 24, 24, generator=torch.Generator().manual_seed(4),
                         dtype=torch.float64)
    results = []
    for smallest in (None, low):
        renderer = Renderer(scene, dtype=torch.float64, backend=backend,  # type: ignore[arg-type]
                            hole_offset_mm=offsets, max_radius_mm=high,
                            min_radius_mm=smallest)
        shown = display.clone().requires_grad_(True)
        fraction = torch.as_tensor(a).requires_grad_(True)
        stack = renderer.display_stack(shown)
        assert stack.shape[2] == renderer.shape.levels - renderer.first_level
        views = renderer.render_states(fraction, stack, states)
        (views * weights).sum().backward()
        results.append((renderer.first_level, views.detach(), shown.grad, fraction.grad))
    (whole, *full), (first, *pruned) = results
    assert whole == 0 and first > 0
    for mine, theirs in zip(pruned, full, strict=True):
        if backend == "kernel":
            torch.testing.assert_close(mine, theirs, rtol=1e-13, atol=1e-14)
        else:
            torch.testing.assert_close(mine, theirs, rtol=0, atol=1e-10)


def test_states_focused_off_infinity_are_refused() -> None:
    scene = make_scene(cells=(6, 6), pitch=1.0, pixels=(120, 120), size=12.0, view=(16, 16))
    renderer = Renderer(scene, dtype=torch.float64, max_radius_mm=0.45, min_radius_mm=0.4)
    assert renderer.first_level > 0
    stack = renderer.display_stack(torch.ones(3, 120, 120, dtype=torch.float64))
    a = torch.full((6, 6), math.pi * 0.42**2, dtype=torch.float64)
    with pytest.raises(ValueError, match="min_radius_mm=None"):
        renderer.render_states(a, stack, _states([(0.0, 0.0)], [4.0], focus=2.0))


@pytest.mark.parametrize("radius", [0.0, -0.1, math.nan])
def test_a_min_radius_not_above_zero_is_refused(radius: float) -> None:
    scene = make_scene(cells=(6, 6), pitch=1.0)
    with pytest.raises(ValueError, match="min_radius_mm"):
        Renderer(scene, min_radius_mm=radius)


def test_a_regular_array_gives_its_smallest_made_hole_at_infinite_focus_only() -> None:
    process = resolve_process("photomask")
    config = tiny_config("near-eye")
    regular = next(r for r in regular_arrays(config.scene, process)
                   if r.array.diameter_mm > 0.2)
    assert regular.min_radius_mm == pytest.approx(
        regular.array.diameter_mm / 2 - RADIUS_SIGMAS * process.radius_sigma_mm)
    focusing = tiny_config("near-eye", **{"eye.focus_range_diopters": [0.0, 2.0]})
    regular = next(r for r in regular_arrays(focusing.scene, process)
                   if r.array.diameter_mm > 0.2)
    assert regular.min_radius_mm is None
