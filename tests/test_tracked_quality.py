"""A plate as made judged with a tracked display (aperture_fab.validation.tracked_quality)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from aperture_fab.config.config import resolve
from aperture_fab.fabrication.process import resolve_process
from aperture_fab.io.images import prepare_targets
from aperture_fab.optics.as_made import MadeOptics
from aperture_fab.optics.eyes import distribution_of
from aperture_fab.optics.model import Renderer
from aperture_fab.targets import EXAMPLES
from aperture_fab.validation.made_quality import judge_made
from aperture_fab.validation.regular import elemental, regular_arrays
from aperture_fab.validation.tracked_quality import judge_tracked


@pytest.fixture(scope="module")
def array():  # type: ignore[no-untyped-def]
    """A 1 mm regular array of mid-size photomask holes on a thin plate, a line-pair target,
    3 eye states of the near-eye distribution, the array's elemental images as its untracked
    content, float64."""
    config = resolve("near-eye", overrides={
        "plate.thickness_mm": 0.005, "eye.view_pixels": [40, 40], "display.pixels": [120, 120]})
    scene, process = config.scene, resolve_process("photomask")
    targets, _ = prepare_targets([EXAMPLES["line-pairs"]()], scene.eye.view_pixels,
                                 scene.display.pixels)
    arrays = [a for a in regular_arrays(scene, process) if math.isclose(a.pitch_mm, 1.0)]
    regular = arrays[len(arrays) // 2]
    renderer = Renderer(regular.scene, dtype=torch.float64)
    states = distribution_of(scene.eye).evaluation_states(3)
    shown = elemental(regular, torch.as_tensor(targets))
    return renderer, np.asarray(targets), regular, shown, states


def test_without_iterations_it_is_the_untracked_judgement(array):
    """0 iterations shows the untracked content (scaled to a peak of 1) in every state: the
    PSNR after gain, the copies (the same draws) and the efficiency are judge_made's."""
    renderer, targets, regular, shown, states = array
    a = regular.array.open_fraction
    tracked = judge_tracked(renderer, targets, a, shown, regular.optics, states, copies=2,
                            iterations=0)
    untracked = judge_made(renderer, targets, a, shown, regular.optics, states, copies=2)
    assert regular.optics.has_errors and tracked.psnr_db.shape == (1, 2, len(states))
    np.testing.assert_allclose(tracked.psnr_db, untracked.psnr_db, atol=1e-9)
    assert tracked.efficiency == pytest.approx(untracked.efficiency, rel=1e-9)
    peak = float(shown.max())
    assert tracked.eye_level == pytest.approx(untracked.eye_level / peak, rel=1e-9)


def test_a_solved_display_is_never_worse_than_the_untracked_one_when_the_model_is_exact(array):
    """With the judged optics the solver's own (no errors, veil or diffraction) the solve keeps
    its best iterate, so each state's PSNR is at least the untracked display's, and it gains."""
    renderer, targets, regular, shown, states = array
    exact = MadeOptics()
    a = regular.array.open_fraction
    tracked = judge_tracked(renderer, targets, a, shown, exact, states, copies=3, iterations=3)
    untracked = judge_made(renderer, targets, a, shown, exact, states)
    assert tracked.psnr_db.shape == untracked.psnr_db.shape == (1, 1, len(states))
    assert np.all(tracked.psnr_db >= untracked.psnr_db - 1e-9)
    assert float(tracked.psnr_db.mean()) > float(untracked.psnr_db.mean()) + 0.5


def test_it_is_deterministic_and_checks_its_copies(array):
    renderer, targets, regular, shown, states = array
    optics = dataclasses.replace(regular.optics, diffraction=None)
    a = regular.array.open_fraction
    first = judge_tracked(renderer, targets, a, shown, optics, states.subset([0]), copies=2,
                          iterations=1)
    again = judge_tracked(renderer, targets, a, shown, optics, states.subset([0]), copies=2,
                          iterations=1)
    np.testing.assert_array_equal(first.psnr_db, again.psnr_db)
    for copies in (0, 1.5):
        with pytest.raises(ValueError, match="copies"):
            judge_tracked(renderer, targets, a, shown, optics, states, copies=copies)


def test_a_light_floor_keeps_the_untracked_light_at_the_eye(array):
    """With the exact model, a floor of 1 keeps each state's light at least the untracked
    content's, where the unfloored solve darkens it; both still gain over untracked."""
    renderer, targets, regular, shown, states = array
    exact = MadeOptics()
    a = regular.array.open_fraction
    untracked = judge_made(renderer, targets, a, shown, exact, states)
    free = judge_tracked(renderer, targets, a, shown, exact, states, iterations=3)
    held = judge_tracked(renderer, targets, a, shown, exact, states, iterations=3,
                         light_floor=1.0)
    assert free.eye_level < untracked.eye_level
    assert held.eye_level >= untracked.eye_level * (1 - 1e-9)
    assert float(held.psnr_db.mean()) > float(untracked.psnr_db.mean()) + 0.5
