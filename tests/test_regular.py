"""The regular family (aperture_fab.validation.regular): every array is one the process makes on
its own plate inside the part's outline, the ladder of sizes per pitch, and a search that
reaches holes larger than the part's cells. (The front's logic and the known best array:
tests/test_made_part.py.)"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import tiny_config

from aperture_fab.fabrication.process import UnmakeableError, resolve_process
from aperture_fab.fabrication.quantize import made_sizes
from aperture_fab.io.images import prepare_targets
from aperture_fab.optics.as_made import made_views
from aperture_fab.optics.eyes import distribution_of
from aperture_fab.optics.model import Renderer
from aperture_fab.optics.scene import hole_radius_mm
from aperture_fab.targets import EXAMPLES
from aperture_fab.validation.regular import (
    MAX_REGULAR_PITCH_MM,
    PITCH_STEP_MM,
    SIZE_RATIO,
    elemental,
    family_outline_mm,
    lattice_scene,
    regular_arrays,
    regular_front,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")

#: Each process on a plate it makes: photomask on the tiny plate, the others at a thickness
#: (and, for the laser, a pitch) in their range.
MAKEABLE = {
    "photomask": {},
    "etched-foil": {"plate.thickness_mm": 0.05},
    "resin": {"plate.thickness_mm": 0.2, "plate.pitch_mm": 0.5, "plate.cells": [8, 8]},
    "laser": {"plate.thickness_mm": 0.1, "plate.pitch_mm": 0.5, "plate.cells": [8, 8]},
}


def made_diameters(scene, process) -> np.ndarray:  # type: ignore[no-untyped-def]
    sizes = made_sizes(scene.plate, process, scene.mid_plane_distance_mm)
    levels = sizes.levels[1:] if sizes.levels is not None else np.array([sizes.lo, sizes.hi])
    return 2 * hole_radius_mm(levels, scene.plate.pitch_mm)


@pytest.mark.parametrize("name", sorted(MAKEABLE))
def test_every_array_is_made_by_the_process_inside_the_parts_outline(name: str) -> None:
    scene = tiny_config("near-eye", **MAKEABLE[name]).scene
    process = resolve_process(name)
    arrays = regular_arrays(scene, process)
    smallest = made_diameters(scene, process)[0]
    pitches = sorted({a.pitch_mm for a in arrays})
    steps = [round(p / PITCH_STEP_MM) for p in pitches]
    assert np.allclose(pitches, np.array(steps) * PITCH_STEP_MM)
    # every multiple of the pitch step from the finest the process makes to the coarsest
    assert steps == list(range(steps[0], steps[-1] + 1))
    assert (steps[-1] + 1) * PITCH_STEP_MM > MAX_REGULAR_PITCH_MM
    if steps[0] > 1:
        with pytest.raises(UnmakeableError):
            made_diameters(lattice_scene(scene, (steps[0] - 1) * PITCH_STEP_MM), process)
    for pitch in pitches:
        lattice = [a for a in arrays if a.pitch_mm == pitch]
        plate = lattice[0].scene.plate
        assert all(a.scene is lattice[0].scene for a in lattice)
        assert all(s <= t + 1e-9 for s, t in zip(plate.size_mm, scene.plate.size_mm, strict=True))
        made = made_diameters(lattice[0].scene, process)
        diameters = np.array([a.array.diameter_mm for a in lattice])
        assert np.all(np.diff(diameters) > 0)
        assert diameters[0] == pytest.approx(smallest)
        assert diameters[-1] == pytest.approx(made[-1])  # the lattice's largest hole is in
        if process.radius_step_mm > 0:  # discrete sizes: each one the process makes
            assert all(np.isclose(made, d).any() for d in diameters)
        else:  # a ladder no coarser than SIZE_RATIO
            assert np.all(diameters[1:] / diameters[:-1] <= SIZE_RATIO * (1 + 1e-9))
        for a in lattice:
            assert a.array.open_fraction.shape == (plate.cells[1], plate.cells[0])
            radius = hole_radius_mm(a.array.open_fraction, plate.pitch_mm)
            np.testing.assert_allclose(2 * radius, a.array.diameter_mm)


def test_the_family_does_not_depend_on_the_parts_cells() -> None:
    """Two parts of one outline on different cells meet the same regular arrays."""
    process = resolve_process("photomask")
    fine = regular_arrays(tiny_config("near-eye").scene, process)
    coarse = regular_arrays(tiny_config("near-eye", **{"plate.pitch_mm": 0.5,
                                                       "plate.cells": [8, 8]}).scene, process)
    assert len(fine) == len(coarse)
    for a, b in zip(fine, coarse, strict=True):
        assert a.scene == b.scene and a.array.diameter_mm == b.array.diameter_mm
        np.testing.assert_array_equal(a.array.open_fraction, b.array.open_fraction)


@pytest.mark.parametrize("pitch_mm", [0.75, 1.5, 2.5])
def test_a_part_moved_to_coarser_cells_meets_the_same_family(pitch_mm: float) -> None:
    """The design job's second design sits on whole cells of a rival's pitch, a plate smaller
    than the display (4 mm) when the pitch does not divide it; its family is still the one over
    the display, the first design's."""
    process = resolve_process("photomask")
    scene = tiny_config("near-eye").scene
    moved = lattice_scene(scene, pitch_mm)
    assert moved.plate.size_mm[0] <= scene.plate.size_mm[0]
    assert family_outline_mm(moved) == family_outline_mm(scene) == scene.plate.size_mm
    first, second = regular_arrays(scene, process), regular_arrays(moved, process)
    assert len(first) == len(second)
    for a, b in zip(first, second, strict=True):
        assert a.scene == b.scene and a.array.diameter_mm == b.array.diameter_mm
        np.testing.assert_array_equal(a.array.open_fraction, b.array.open_fraction)


def test_the_search_reaches_holes_larger_than_the_parts_cells() -> None:
    """At 1 % of the panel's white at the eye, the best regular array of the tiny scene is a
    coarse lattice of holes larger than the part's cells, well ahead of every array whose
    holes fit those cells (the old family, which could not hold it)."""
    scene = tiny_config("near-eye").scene
    process = resolve_process("photomask")
    targets, _ = prepare_targets([EXAMPLES["digit-3"]()], scene.eye.view_pixels,
                                 scene.display.pixels)
    states = distribution_of(scene.eye).evaluation_states(4)
    front = regular_front(targets, regular_arrays(scene, process), states, dtype=torch.float64)
    light = 0.01
    best = front.best_at(light)
    assert best is not None
    cell_max = made_diameters(scene, process)[-1]
    assert front.diameter_mm[best] > cell_max and front.pitch_mm[best] > max(scene.plate.pitch_mm)
    bright = front.eye_level >= light
    assert math.isclose(front.p10[best].mean(), front.p10[bright].mean(1).max())
    fits_cell = bright & (front.diameter_mm <= cell_max * (1 + 1e-9))
    assert front.p10[best].mean() > front.p10[fits_cell].mean(1).max() + 1.0


def test_a_stack_sized_to_the_holes_renders_them_as_the_cells_stack() -> None:
    """A regular array renders its holes on coarse cells from a stack sized to them
    (`RegularArray.max_radius_mm`): fewer levels, the same views to within the levels'
    interpolation, on a display fine enough that the cells' stack interpolates well too (its
    first levels are coarse for small holes: 0.1 mm holes on this 1 mm lattice agree to
    only 35 dB)."""
    scene = tiny_config("near-eye", **{"display.pixels": [256, 256]}).scene
    targets, _ = prepare_targets([EXAMPLES["digit-3"]()], scene.eye.view_pixels,
                                 scene.display.pixels)
    states = distribution_of(scene.eye).evaluation_states(4)
    arrays = [a for a in regular_arrays(scene, resolve_process("photomask"))
              if a.pitch_mm == 1.0 and 0.15 < a.array.diameter_mm < 0.3]
    assert arrays
    for regular in arrays:
        display = torch.as_tensor(elemental(regular, torch.as_tensor(targets))[0])
        a = torch.as_tensor(regular.array.open_fraction)
        views = []
        for radius in (None, regular.max_radius_mm):
            renderer = Renderer(regular.scene, dtype=torch.float64, max_radius_mm=radius)
            views.append((made_views(renderer, a, display, states, regular.optics)[0],
                          renderer.shape.levels))
        (full, full_levels), (sized, sized_levels) = views
        assert sized_levels < full_levels
        error = float(((sized - full) ** 2).mean() / full.max() ** 2)
        assert -10 * math.log10(error) > 45


@pytest.mark.parametrize("radius", [0.0, -0.1, 0.6, math.nan])
def test_a_stack_larger_than_the_cell_or_empty_is_refused(radius: float) -> None:
    scene = tiny_config("near-eye").scene  # 0.25 mm cells: holes to 0.125 mm radius
    with pytest.raises(ValueError, match="max_radius_mm"):
        Renderer(scene, max_radius_mm=radius)
