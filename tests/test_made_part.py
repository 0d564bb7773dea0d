"""The part as made and the regular family (aperture_fab.validation.made_part): the front's
logic against brute force, the known best regular array (the smallest hole without diffraction,
near sqrt(2.44 lambda h) with it), the light at the eye, the as-made model against the written
part, and the verdict. (A light floor that no plate reaches: tests/test_brightness_floor.py.)"""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from conftest import tiny_config
from hypothesis import given, settings
from hypothesis import strategies as st

from aperture_fab.config.config import resolve
from aperture_fab.config.stages import FabricationSettings
from aperture_fab.fabrication.part import made_optics
from aperture_fab.fabrication.process import resolve_process
from aperture_fab.io.formats import holes_csv, read_holes_csv
from aperture_fab.io.images import prepare_targets
from aperture_fab.optics.as_made import MadeOptics
from aperture_fab.optics.baselines import elemental_display
from aperture_fab.optics.eyes import distribution_of
from aperture_fab.optics.model import Renderer
from aperture_fab.pipeline.design_job import design
from aperture_fab.targets import EXAMPLES, digit
from aperture_fab.validation.light import lower_floor_fix
from aperture_fab.validation.made_quality import MadeQuality, judge_made
from aperture_fab.validation.regular import (
    RegularArray,
    RegularFront,
    regular_arrays,
    regular_front,
)
from aperture_fab.validation.rival_search import climb_rivals
from aperture_fab.validation.validate import layout_fractions
from aperture_fab.validation.verdicts import (
    FLOOR_BINDS,
    LATTICE_FIX_BELOW_DB,
    MADE_MARGIN_DB,
    RETRY_LATTICE_BELOW_DB,
    made_verdict,
    rival_lattice,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")

#: Green, for the diffraction-limited pinhole: d* = sqrt(2.44 lambda h) balances the geometric
#: blur d / h against the Airy core's 2.44 lambda / d.
GREEN_MM = 530e-6


# -- the front ----------------------------------------------------------------------------------

fronts = st.integers(1, 12).flatmap(lambda n: st.tuples(
    st.lists(st.floats(1e-4, 0.5), min_size=n, max_size=n),
    st.lists(st.floats(5.0, 30.0), min_size=n, max_size=n),
    st.lists(st.sampled_from([0.5, 1.0, 1.5]), min_size=n, max_size=n),
    st.floats(1e-4, 0.6)))


def make_front(light: list[float], p10: list[float], pitch: list[float]) -> RegularFront:
    """A front whose light at the eye is `light` (and whose white efficiency is not: arrays
    are compared at the eye)."""
    p = np.array(p10)[:, None]
    return RegularFront(np.array(pitch), np.array(light) * 0.5 + 0.01, np.array(light)[::-1],
                        np.array(light), p, p + 1, p + 2)


@settings(max_examples=60, deadline=None)
@given(fronts)
def test_best_at_is_the_brute_force_best_at_least_as_bright(case):
    eff, p10, pitch, light = case
    front = make_front(eff, p10, pitch)
    bright = [i for i, e in enumerate(eff) if e >= light * (1 - 1e-9)]
    best = front.best_at(light)
    if not bright:
        assert best is None
        return
    assert best is not None and best in bright
    assert p10[best] == max(p10[i] for i in bright)
    levels, staircase = front.front()
    for e, value in zip(levels, staircase, strict=True):
        assert value == max(p10[i] for i, x in enumerate(eff) if x >= e)


def ladder_front(elemental: list[list[float]], light: list[list[float]]) -> RegularFront:
    """A family of len(elemental) pitches (1, 2, ... mm), pitch k with holes 0.1, 0.2, ... mm
    whose elemental p10 is elemental[k] and light at the eye light[k]."""
    pitch = [float(k + 1) for k, row in enumerate(elemental) for _ in row]
    diameter = [0.1 * (j + 1) for row in elemental for j in range(len(row))]
    p = np.array([v for row in elemental for v in row])[:, None]
    level = np.array([v for row in light for v in row])
    return RegularFront(np.array(pitch), np.array(diameter), level, level, p, p + 1, p + 2)


#: Per pitch: hole sizes, the fitted p10's peak among them, and each size's elemental p10.
ladders = st.lists(st.integers(1, 7).flatmap(lambda n: st.tuples(
    st.integers(0, n - 1), st.lists(st.floats(5.0, 30.0), min_size=n, max_size=n),
    st.lists(st.floats(1e-3, 1.0), min_size=n, max_size=n))), min_size=1, max_size=5)


@settings(max_examples=80, deadline=None)
@given(ladders, st.floats(0.0, 0.8), st.integers(1, 5))
def test_the_climb_finds_each_climbed_pitchs_peak(case, light, pitches):
    """With a fitted p10 that rises to one peak over a pitch's hole sizes and falls after it,
    the climb judges only bright arrays, of the `pitches` pitches the elemental pass ranks
    first, each once, and finds each one's best bright size: the brute-force best of them."""
    front = ladder_front([row for _, row, _ in case], [level for _, _, level in case])
    peaks = {k + 1.0: peak for k, (peak, _, _) in enumerate(case)}
    size_of = np.rint(front.diameter_mm / 0.1).astype(int) - 1

    def fitted_p10(i: int) -> float:  # unimodal in the hole size, distinct values
        return 40.0 - abs(size_of[i] - peaks[front.pitch_mm[i]]) - 0.01 * size_of[i]

    calls: list[int] = []

    def judge(i: int) -> float:
        calls.append(i)
        return fitted_p10(i)

    chosen = climb_rivals(front, light, judge, pitches)
    assert sorted(calls) == sorted(chosen) and len(set(calls)) == len(calls)
    bright = [i for i in range(len(size_of)) if front.eye_level[i] >= light * (1 - 1e-9)]
    assert set(chosen) <= set(bright)
    elemental = front.p10[:, 0]
    best_of = {p: max(elemental[i] for i in bright if front.pitch_mm[i] == p)
               for p in {front.pitch_mm[i] for i in bright}}
    climbed = sorted(best_of, key=lambda p: -best_of[p])[:pitches]
    assert {front.pitch_mm[i] for i in chosen} == set(climbed)
    for p in climbed:
        at = [i for i in bright if front.pitch_mm[i] == p]
        best = max(at, key=fitted_p10)
        assert best in chosen


def test_the_climb_refuses_no_pitches():
    front = ladder_front([[10.0]], [[1.0]])
    with pytest.raises(ValueError, match="pitches = 0"):
        climb_rivals(front, 0.5, lambda i: 0.0, 0)


# -- the known best regular array ---------------------------------------------------------------

@pytest.fixture(scope="module")
def one_pitch():  # type: ignore[no-untyped-def]
    """The regular arrays of one 1 mm pitch (photomask: 12 made sizes, 25 to 984 um) on a thin
    plate 10 mm over the display, a line-pair target, the nominal eye; the scene is the
    arrays' (a plate of 1 mm cells)."""
    config = resolve("near-eye-nominal", overrides={
        "plate.thickness_mm": 0.005, "eye.view_pixels": [96, 96], "display.pixels": [300, 300]})
    scene = config.scene
    process = resolve_process("photomask")
    targets, _ = prepare_targets([EXAMPLES["line-pairs"]()], scene.eye.view_pixels,
                                 scene.display.pixels)
    arrays = [a for a in regular_arrays(scene, process) if math.isclose(a.pitch_mm, 1.0)]
    renderer = Renderer(arrays[0].scene, dtype=torch.float64)
    return arrays[0].scene, process, targets, arrays, renderer


def made_by(arrays: list[RegularArray], optics: MadeOptics) -> list[RegularArray]:
    """The arrays made with `optics`."""
    return [dataclasses.replace(a, optics=optics) for a in arrays]


def test_without_diffraction_the_smallest_hole_is_best(one_pitch):
    """Geometric optics: a smaller hole is a sharper pinhole, so sharpness falls with size and
    the best array at least as bright as e is the smallest hole that bright."""
    _, _, targets, arrays, renderer = one_pitch
    front = regular_front(targets, made_by(arrays, MadeOptics()), renderer.nominal_states(),
                          dtype=torch.float64)
    assert np.all(np.diff(front.p10[:, 0]) < 0)
    for k, light in enumerate(front.eye_level):
        assert front.best_at(float(light)) == k
    # and the light of a thin regular array is about its open area, (pi d^2 / 4) / pitch^2,
    # less at the view's edge, where part of the pupil's footprint leaves the 20 mm plate
    # (a little less so for holes near the cell's size: the outer ones reach further out)
    ratio = front.efficiency / (np.pi * front.diameter_mm**2 / 4)
    assert np.all((ratio > 0.85) & (ratio <= 1.0 + 1e-6))
    np.testing.assert_allclose(ratio, ratio[0], rtol=0.06)


@pytest.mark.parametrize(("floor_share", "kept"), [(0.0, "dim"), (0.8, "noisy"), (2.0, "noisy")])
def test_a_fitted_rival_keeps_its_best_content_that_is_bright_enough(one_pitch, floor_share,
                                                                     kept):
    """regular_front with several contents along a fit judges the array with the best p10
    among those with at least the light asked for, else the brightest: the elemental images
    at 0.4 of their level (as sharp: PSNR after gain ignores the level) against a noisier
    content at full light."""
    scene, _, targets, arrays, renderer = one_pitch
    array, states = arrays[3], renderer.nominal_states()
    elemental = np.stack([elemental_display(scene, array.array, torch.as_tensor(t)).numpy()
                          for t in targets])
    noise = np.random.default_rng(0).normal(0.0, 0.5, elemental.shape)
    contents = {"noisy": np.clip(elemental + noise, 0.0, 1.0), "dim": 0.4 * elemental}
    # a fitted rival renders from a stack sized to its holes (RegularArray.max_radius_mm)
    rival = made_by([array], MadeOptics())[0]
    sized = Renderer(scene, dtype=torch.float64, max_radius_mm=rival.max_radius_mm)
    judged = {name: judge_made(sized, targets, array.array.open_fraction, shown, MadeOptics(),
                               states) for name, shown in contents.items()}
    assert judged["dim"].percentile(10).mean() > judged["noisy"].percentile(10).mean() + 0.5
    assert judged["dim"].eye_level < 0.5 * judged["noisy"].eye_level
    level = floor_share * judged["noisy"].eye_level
    front = regular_front(targets, [rival], states,
                          fit=lambda regular, shown: list(contents.values()), eye_level=level,
                          dtype=torch.float64)
    np.testing.assert_allclose(front.p10[0], judged[kept].percentile(10))
    assert front.eye_level[0] == pytest.approx(judged[kept].eye_level)


def test_with_diffraction_the_best_hole_is_the_diffraction_limited_one(one_pitch):
    scene, process, targets, arrays, renderer = one_pitch
    optics = dataclasses.replace(made_optics(scene, process), radius_sigma_mm=0.0,
                                 position_sigma_mm=0.0, solid_transmission=0.0)
    front = regular_front(targets, made_by(arrays, optics), renderer.nominal_states(),
                          dtype=torch.float64)
    best = front.best_at(0.0)
    assert best is not None and 0 < best < len(arrays) - 1  # inside the ladder
    optimum = math.sqrt(2.44 * GREEN_MM * scene.pinhole_height_mm)
    assert optimum / 1.5 < front.diameter_mm[best] < optimum * 1.5


def test_light_at_the_eye_is_the_white_efficiency_of_a_white_display_and_follows_the_content(
        one_pitch):
    """The light at the eye (what plates are compared by) is the mean view of the content
    shown: for a white display, without veil or diffraction (whose blur loses a little light
    off the view's edges), it is the plate's white efficiency, and it halves with the content
    while the PSNR after gain does not move."""
    scene, process, targets, arrays, renderer = one_pitch
    optics = dataclasses.replace(made_optics(scene, process), radius_sigma_mm=0.0,
                                 position_sigma_mm=0.0, solid_transmission=0.0, diffraction=None)
    width, height = scene.display.pixels
    white = np.ones((1, targets.shape[1], height, width))
    plate = arrays[len(arrays) // 2].array.open_fraction
    full = judge_made(renderer, targets, plate, white, optics, renderer.nominal_states())
    half = judge_made(renderer, targets, plate, white / 2, optics, renderer.nominal_states())
    assert full.eye_level == pytest.approx(full.efficiency, rel=1e-9)
    assert half.eye_level == pytest.approx(full.eye_level / 2, rel=1e-9)
    np.testing.assert_allclose(half.psnr_db, full.psnr_db, atol=1e-6)


# -- the model the optimizer sees is the part that is written -----------------------------------

def test_the_optimizer_plate_is_the_written_part_and_they_score_alike():
    config = tiny_config("near-eye", **{"plate.thickness_mm": 0.005,
                                        "optimizer.quantize_share": 1.0,
                                        "optimizer.iterations": 4})
    process = resolve_process("photomask")
    result = design([digit("3")], config, fabrication=FabricationSettings(process))
    assert result.part is not None
    layout = result.part.layout
    text = holes_csv(layout)
    read = read_holes_csv(text, config.scene.plate, outline_mm=layout.outline_mm,
                          converge_mm=layout.converge_mm)
    written = layout_fractions(read, process.radius_bias_mm)
    np.testing.assert_allclose(written, result.design.open_fraction, rtol=1e-4, atol=1e-9)
    renderer = Renderer(config.scene)
    optics = made_optics(config.scene, process)
    states = distribution_of(config.scene.eye).evaluation_states(8)
    shown = result.built_displays if result.built_displays is not None \
        else result.design.displays
    ours = judge_made(renderer, result.targets, result.design.open_fraction, shown, optics,
                      states, copies=2)
    theirs = judge_made(renderer, result.targets, written, shown, optics, states, copies=2)
    assert abs(float(ours.percentile(10)[0] - theirs.percentile(10)[0])) < 0.5


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(0.0, 60.0), min_size=1, max_size=24))
def test_mean_mse_psnr_is_the_psnr_of_the_mean_error(psnr: list[float]) -> None:
    """The optimizer's figure (PSNR of the mean squared error) from per-state PSNRs: equal to
    them when they are equal, never above their mean (Jensen), never below their minimum."""
    values = np.array(psnr)
    quality = MadeQuality(values.reshape(1, 1, -1), 0.01, 0.003)
    mse = np.mean(10 ** (-values / 10))
    figure = float(quality.mean_mse_psnr()[0])
    assert figure == pytest.approx(-10 * math.log10(mse), abs=1e-9)
    assert values.min() - 1e-9 <= figure <= values.mean() + 1e-9
    flat = MadeQuality(np.full((1, 2, 3), values[0]), 0.01, 0.003)
    assert float(flat.mean_mse_psnr()[0]) == pytest.approx(values[0], abs=1e-9)


@pytest.mark.parametrize("share", [0.25, 0.5, 1.0])
def test_tail_mse_psnr_is_the_psnr_of_the_worst_states_mean_error(share: float) -> None:
    """With a tail share (the optimizer's loss over the worst states), the figure is the PSNR
    of the mean squared error of the worst share of copies x states, pooled."""
    values = np.array([[[30.0, 12.0, 18.0, 24.0], [15.0, 27.0, 21.0, 33.0]]])
    worst = np.sort(values.ravel())[: round(share * values.size)]
    expected = -10 * math.log10(np.mean(10 ** (-worst / 10)))
    quality = MadeQuality(values, 0.01, 0.003)
    assert float(quality.mean_mse_psnr(share)[0]) == pytest.approx(expected, abs=1e-9)


# -- the verdict --------------------------------------------------------------------------------

def block(margin: float | None) -> dict:
    best = None if margin is None else {
        "pitch_mm": 1.0, "diameter_mm": 0.1, "efficiency": 0.03, "eye_level": 0.009,
        "p10_db": [20.0 - margin], "p50_db": [21.0], "p90_db": [22.0]}
    return {"copies": 4, "states": 32, "neglected": [],
            "part": {"efficiency": 0.025, "eye_level": 0.004, "p10_db": [20.0], "p50_db": [22.0],
                     "p90_db": [24.0]},
            "regular": {"family": {"pitch_mm": [0.25, 3.0], "diameter_mm": [0.025, 0.234]},
                        "fitted": {}, "best": best},
            "margin_db": None if margin is None else [margin]}


@pytest.mark.parametrize(("margin", "level"), [
    (MADE_MARGIN_DB + 0.5, "pass"), (1.0, "warn"), (-0.5, "fail"), (None, "info")])
def test_made_verdict_levels(margin, level):
    verdict = made_verdict(block(margin))
    assert verdict.level == level
    assert "20.0 dB at 2.5 % light (0.4 % of the panel's white at the eye" in verdict.text
    if margin is not None:  # what the family searched
        assert "among pitches to 3 mm and holes to 234 um" in verdict.text


@pytest.mark.parametrize(("rival_pitch_mm", "margin", "flags"), [
    (2.5, LATTICE_FIX_BELOW_DB - 1.5, "--pitch-mm 2.5 --cells 8 8"),
    (2.75, LATTICE_FIX_BELOW_DB - 0.5, "--pitch-mm 2.75 --cells 7 7"),
    (2.5, LATTICE_FIX_BELOW_DB, None), (0.5, LATTICE_FIX_BELOW_DB - 1.5, None)])
def test_a_made_fix_names_the_best_rivals_lattice_when_it_is_coarser(rival_pitch_mm, margin,
                                                                     flags):
    """Below LATTICE_FIX_BELOW_DB over a rival on a coarser lattice than the part's cells."""
    found = block(margin)
    found["regular"]["best"]["pitch_mm"] = rival_pitch_mm
    report = SimpleNamespace(scene={"plate": {"pitch_mm": [0.5, 0.5], "cells": [40, 40]}},
                             config={"optimizer": {}}, fabrication={"process": "photomask"},
                             eye_distribution=None, checked_part=None, run=None)
    fixes = made_verdict(found, report).fixes
    named = [fix for fix in fixes if "best regular array's lattice" in fix]
    if flags is None:
        assert not named
    else:
        assert len(named) == 1 and flags in named[0]
    assert not any("more iterations" in fix for fix in fixes)


@pytest.mark.parametrize(("efficiency", "named"), [(0.02, True), (FLOOR_BINDS * 0.02, True),
                                                  (0.027, False)])
def test_lowering_the_floor_is_proposed_only_where_the_part_sits_at_it(efficiency, named):
    """A part well above its brightness floor (2 %) was not shaped by it."""
    found = block(1.0)
    found["part"]["efficiency"] = efficiency
    report = SimpleNamespace(scene={"plate": {"pitch_mm": [0.5, 0.5], "cells": [40, 40]}},
                             config={"optimizer": {"min_efficiency": 0.02}},
                             fabrication={"process": "photomask"}, eye_distribution=None,
                             checked_part=None, run=None)
    fixes = made_verdict(found, report).fixes
    assert (lower_floor_fix(0.02) in fixes) == named


@pytest.mark.parametrize(("lattice", "checked_part", "margin", "named"), [
    ("rival", None, RETRY_LATTICE_BELOW_DB - 0.5, False),  # the design job tried it
    ("rival", None, LATTICE_FIX_BELOW_DB + 0.5, False),  # the part is far enough ahead
    ("rival", {"path": "plate.stl"}, RETRY_LATTICE_BELOW_DB - 0.5, True),  # validate's report
    ("fixed", None, RETRY_LATTICE_BELOW_DB - 0.5, True)])
def test_the_lattice_fix_is_left_out_where_the_design_job_tried_it(lattice, checked_part,
                                                                    margin, named):
    found = block(margin)
    found["regular"]["best"]["pitch_mm"] = 2.5
    report = SimpleNamespace(scene={"plate": {"pitch_mm": [0.5, 0.5], "cells": [40, 40]}},
                             config={"optimizer": {"lattice": lattice}},
                             fabrication={"process": "photomask"}, eye_distribution=None,
                             checked_part=checked_part,
                             run=None)
    fixes = made_verdict(found, report).fixes
    assert any("best regular array's lattice" in fix for fix in fixes) == named


@pytest.mark.parametrize(("pitch", "margin", "cells"), [
    (2.5, -0.1, (8, 8)), (3.0, -2.0, (6, 6)), (3.0, RETRY_LATTICE_BELOW_DB - 0.1, (6, 6)),
    (2.5, RETRY_LATTICE_BELOW_DB, None), (0.5, -1.0, None)])
def test_rival_lattice_is_the_rivals_pitch_over_the_plate(pitch, margin, cells):
    found = block(margin)
    found["regular"]["best"]["pitch_mm"] = pitch
    plate = {"pitch_mm": [0.5, 0.5], "cells": [40, 40]}
    lattice = rival_lattice(plate, found, RETRY_LATTICE_BELOW_DB)
    assert lattice == (None if cells is None else (pitch, cells))


def fake_design_stages(monkeypatch, first_margin, second_margin, drawn=None):
    """The design job's stages replaced by fakes: each design made on its config, the first
    judged as made (`first_margin`) and any finished with a report (the second design's part at
    `second_margin`; drawn: its evidence). Returns the configs made and, per finished design,
    (its config, the replaces it was given)."""
    from aperture_fab.pipeline import design_job

    made, finished = [], []

    def found(margin):
        judged = block(margin)
        judged["regular"]["best"]["pitch_mm"] = 2.5
        return judged

    def make(images, config, **_):
        made.append(config)
        return design_job.DesignResult(config, None, ("t",), np.zeros(1), {}, {},
                                       timings_s={"optimize_s": 1.0})

    def judged_as_made(result, *_):
        return dataclasses.replace(result, made_part=found(first_margin))

    def finish(result, replaces=None, **_):
        finished.append((result.config, replaces))
        judged = result.made_part or found(first_margin if len(made) == 1 else second_margin)
        plate = result.config.scene.plate
        report = SimpleNamespace(made_part=judged, timings_s={"optimize_s": 1.0}, scene={
            "plate": {"pitch_mm": list(plate.pitch_mm), "cells": list(plate.cells)}})
        return dataclasses.replace(result, report=report, made_part=judged,
                                   evidence=None if drawn is None else drawn(report))

    monkeypatch.setattr(design_job, "_made", make)
    monkeypatch.setattr(design_job, "_judged_as_made", judged_as_made)
    monkeypatch.setattr(design_job, "_finish", finish)
    return made, finished


@pytest.mark.parametrize(("lattice", "first_margin", "second_margin", "kept_second"), [
    ("rival", -0.3, 0.7, True), ("rival", -0.3, -0.5, False),
    ("rival", RETRY_LATTICE_BELOW_DB - 0.1, RETRY_LATTICE_BELOW_DB + 0.5, True),
    ("rival", RETRY_LATTICE_BELOW_DB + 0.1, None, False), ("fixed", -0.3, None, False)])
def test_the_design_job_designs_again_on_the_lattice_of_an_array_close_to_it(
        monkeypatch, lattice, first_margin, second_margin, kept_second):
    """optimizer.lattice = "rival": a part that beats the best regular array by less than
    RETRY_LATTICE_BELOW_DB is designed again on its lattice, from its holes, and the one with
    the larger margin kept (both in `lattices`); a first part the second replaces is judged as
    made only, never written or judged in full."""
    from aperture_fab.pipeline import design_job

    made, finished = fake_design_stages(monkeypatch, first_margin, second_margin)
    config = resolve("near-eye", None, {"optimizer.lattice": lattice})
    result = design_job.design([np.zeros((3, 4, 4))], config)
    if second_margin is None:
        assert len(made) == 1 and result.config is made[0] and result.lattices == ()
        assert finished == [(made[0], None)]
        return
    assert [c.scene.plate.pitch_mm for c in made] == [(0.5, 0.5), (2.5, 2.5)]
    assert made[1].scene.plate.cells == (8, 8)
    assert [c.optimizer.init_diameter_mm for c in made] == [0.0, 0.1]  # the rival's holes
    replaces = {"pitch_mm": [0.5, 0.5], "cells": [40, 40], "margin_db": [first_margin]}
    assert finished == [(made[1], replaces)] + ([] if kept_second else [(made[0], None)])
    assert result.config is made[1 if kept_second else 0]
    assert [entry["kept"] for entry in result.lattices] == [not kept_second, kept_second]
    assert [entry["margin_db"] for entry in result.lattices] == [[first_margin],
                                                                  [second_margin]]


@pytest.mark.parametrize("margin", [[0.2], None])
def test_a_part_kept_over_its_rivals_lattice_says_what_the_job_tried(margin):
    found = block(-0.3)
    report = SimpleNamespace(scene={"plate": {"pitch_mm": [0.5, 0.5], "cells": [40, 40]}},
                             config={"optimizer": {"lattice": "rival"}},
                             fabrication={"process": "photomask"}, eye_distribution=None,
                             checked_part=None,
                             run={"tried": {"pitch_mm": [2.5, 2.5], "cells": [8, 8],
                                            "margin_db": margin}})
    text = made_verdict(found, report).text
    assert text.startswith("As made")
    assert ("The design job also designed on the lattice of the best regular array (8 x 8 "
            "cells of 2.5 mm") in text
    assert ("+0.2 dB over its own best regular array" if margin else "was not judged") in text


def test_the_design_jobs_kept_first_part_gets_the_tried_lattice_in_its_report(monkeypatch):
    """The first part kept: its report (and the page drawn again) records the other lattice."""
    from aperture_fab.pipeline import design_job

    amended = []

    class Drawn:
        def __init__(self, report):
            self.report = report

        def with_report(self, report):
            return Drawn(report)

    def with_tried(report, tried):
        amended.append(tried)
        return SimpleNamespace(**{**vars(report), "tried": tried})

    fake_design_stages(monkeypatch, -0.3, -0.5, drawn=Drawn)
    monkeypatch.setattr(design_job, "with_tried_lattice", with_tried)
    monkeypatch.setattr(design_job, "evidence_files", lambda e: {"report.json": e.report})
    result = design_job.design([np.zeros((3, 4, 4))], resolve("near-eye", None, {}))
    assert amended == [{"pitch_mm": [2.5, 2.5], "cells": [8, 8], "margin_db": [-0.5]}]
    assert result.report.tried == amended[0] and result.evidence.report is result.report
    assert result.report_files == {"report.json": result.report}


def test_a_part_made_on_its_rivals_lattice_says_what_it_replaces():
    found = block(0.7)
    report = SimpleNamespace(scene={"plate": {"pitch_mm": [2.5, 2.5], "cells": [8, 8]}},
                             config={"optimizer": {"lattice": "rival"}},
                             fabrication={"process": "photomask"}, eye_distribution=None,
                             checked_part=None,
                             run={"replaces": {"pitch_mm": [0.5, 0.5], "cells": [40, 40],
                                               "margin_db": [-0.3]}})
    text = made_verdict(found, report).text
    assert text.startswith("The design job made this part on the lattice of the best regular "
                           "array against its part on 40 x 40 cells of 0.5 mm (-0.3 dB")
    plain = SimpleNamespace(**{**vars(report), "run": {"part": "plate.stl"}})
    assert made_verdict(found, plain).text.startswith("As made")
