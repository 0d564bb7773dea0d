"""Fabrication process presets, overrides and plate checks."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from aperture_fab.fabrication.process import (
    PROCESSES,
    Process,
    UnmakeableError,
    drawn_radii_mm,
    process_summary,
    resolve_process,
)
from aperture_fab.fabrication.rules import (
    check_plate,
    hole_radius_bounds,
    makeable_processes,
    min_pitch_mm,
    open_fraction_bounds,
)
from aperture_fab.optics.scene import Plate


def plate(pitch: float = 0.25, thickness: float = 0.05, cells: tuple[int, int] = (8, 6)) -> Plate:
    return Plate(cells=cells, pitch_mm=(pitch, pitch), gap_mm=10.0, thickness_mm=thickness)


def near_eye_plate() -> Plate:
    """The default "near-eye" preset's plate: 80 x 80 cells of 0.25 mm, 0.3 mm thick."""
    return Plate(cells=(80, 80), pitch_mm=(0.25, 0.25), gap_mm=10.0, thickness_mm=0.3,
                 hole_axis="chief_ray")


def test_presets_are_the_five_processes_with_sources() -> None:
    assert set(PROCESSES) == {"resin", "fdm", "laser", "etched-foil", "photomask"}
    for name, p in PROCESSES.items():
        assert p.name == name
        assert p.sources, f"{name} has no sources"
        assert p.thickness_range_mm[0] < p.thickness_range_mm[1]


def test_fdm_cannot_make_pinholes_but_photomask_can() -> None:
    # docs/design.md: a slicer closes holes under about 0.6 mm with a 0.4 mm nozzle.
    assert PROCESSES["fdm"].min_hole_mm >= 0.6
    assert PROCESSES["photomask"].min_hole_mm <= 0.05
    # docs/design.md: holes are 0.05 to 0.3 mm; the best single pinhole at h = 10 mm is about
    # sqrt(2 lambda h) = 0.105 mm across, which the default (resin) process must reach.
    assert PROCESSES["resin"].min_hole_for(0.3) < math.sqrt(2 * 550e-6 * 10.0)


def test_default_near_eye_plate_is_makeable_in_resin_only() -> None:
    resin = PROCESSES["resin"]
    pl = near_eye_plate()
    check_plate(resin, pl)  # does not raise
    # Independent numbers: 4 pixels of 22 um for the hole, 2 for the web.
    r_min, r_max = 0.088 / 2, 0.25 / 2 - 0.044 / 2
    assert hole_radius_bounds(resin, pl) == pytest.approx((r_min, r_max))
    a_min, a_max = open_fraction_bounds(resin, pl)
    assert a_min == pytest.approx(math.pi * r_min**2 / 0.0625)
    assert a_max == pytest.approx(math.pi * r_max**2 / 0.0625)
    assert a_min < 0.1 and a_max > 0.5 and a_max > 5 * a_min  # a useful range to optimize in
    assert makeable_processes(pl) == ["resin"]


def test_fdm_refuses_the_near_eye_plate_and_names_resin() -> None:
    with pytest.raises(UnmakeableError) as info:
        check_plate(PROCESSES["fdm"], near_eye_plate())
    message = str(info.value)
    assert "0.4 to 10 mm" in message  # 0.3 mm is also too thin for fdm
    assert "at least 1.8 mm" in message and "7.2x" in message
    assert "processes that can make it at 0.3 mm: resin" in message


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"min_hole_mm": -0.1}, "min_hole_mm"),
        ({"min_hole_mm": 0.0}, "min_hole_mm"),
        ({"min_web_mm": math.nan}, "min_web_mm"),
        ({"thickness_range_mm": (1.0, 0.5)}, "thickness_range_mm"),
        ({"radius_step_mm": -0.01}, "radius_step_mm"),
        ({"hole_sizes_mm": (0.3, 0.2)}, "hole_sizes_mm"),
        ({"hole_sizes_mm": (0.01,)}, "hole_sizes_mm"),
        ({"hole_sizes_mm": (0.2, 0.3), "radius_step_mm": 0.01}, "radius_step_mm"),
        ({"radius_bias_mm": -0.2}, "radius_bias_mm"),
        ({"radius_sigma_mm": -1.0}, "radius_sigma_mm"),
        ({"position_sigma_mm": math.inf}, "position_sigma_mm"),
        ({"name": ""}, "name"),
    ],
)
def test_invalid_process_names_the_field(change: dict, field: str) -> None:
    base = Process("x", "test", min_hole_mm=0.1, min_web_mm=0.1, thickness_range_mm=(0.1, 1.0))
    with pytest.raises(ValueError, match=field):
        dataclasses.replace(base, **change)


def test_wrong_types_raise_type_error() -> None:
    with pytest.raises(TypeError, match="min_hole_mm"):
        Process("x", "t", min_hole_mm="0.1", min_web_mm=0.1,  # type: ignore[arg-type]
                thickness_range_mm=(0.1, 1.0))
    with pytest.raises(TypeError, match="hole_sizes_mm"):
        Process("x", "t", min_hole_mm=0.1, min_web_mm=0.1, thickness_range_mm=(0.1, 1.0),
                hole_sizes_mm=[0.2])  # type: ignore[arg-type]


@pytest.mark.parametrize(("name", "suggestion"), [("etched_foil", "etched-foil"),
                                                  ("photomsk", "photomask"), ("lazer", "laser")])
def test_unknown_process_lists_processes_and_suggests(name: str, suggestion: str) -> None:
    with pytest.raises(ValueError) as info:
        resolve_process(name, None)
    message = str(info.value)
    assert f"Did you mean {suggestion!r}" in message
    for known in PROCESSES:
        assert known in message


def test_override_key_typo_suggests_field() -> None:
    with pytest.raises(ValueError, match="Did you mean 'min_hole_mm'"):
        resolve_process("resin", {"min_hole": 0.3})


def test_overrides_are_applied_and_validated() -> None:
    p = resolve_process("resin", {"min_hole_mm": 0.3, "thickness_range_mm": [0.2, 2.0]})
    assert p.min_hole_mm == 0.3
    assert p.thickness_range_mm == (0.2, 2.0)
    assert p.min_web_mm == PROCESSES["resin"].min_web_mm
    assert resolve_process("resin", None) is PROCESSES["resin"]
    with pytest.raises(ValueError, match="min_web_mm"):
        resolve_process("laser", {"min_web_mm": -1.0})


def test_discrete_sizes_override_clears_the_radius_step() -> None:
    p = resolve_process("resin", {"hole_sizes_mm": [0.5, 0.6, 0.8]})
    assert p.hole_sizes_mm == (0.5, 0.6, 0.8)
    assert p.radius_step_mm == 0.0


@pytest.mark.parametrize("name", list(PROCESSES))
def test_summary_names_the_numbers(name: str) -> None:
    p = PROCESSES[name]
    text = process_summary(p)
    assert text.startswith(f"{name}:")
    assert f"{p.min_hole_mm:g} mm" in text
    assert f"{p.min_web_mm:g} mm" in text
    assert text.count("source:") == len(p.sources)


@pytest.mark.parametrize(
    ("name", "pitch", "thickness"),
    [("resin", 1.2, 1.0), ("resin", 0.25, 0.3), ("etched-foil", 0.25, 0.05),
     ("etched-foil", 0.5, 0.2), ("laser", 1.0, 0.3), ("photomask", 0.1, 0.18)],
)
def test_radius_and_fraction_bounds(name: str, pitch: float, thickness: float) -> None:
    p = PROCESSES[name]
    pl = Plate(cells=(4, 4), pitch_mm=(pitch, pitch * 1.5), gap_mm=10.0, thickness_mm=thickness)
    r_min, r_max = hole_radius_bounds(p, pl)
    hole = max(p.min_hole_mm, p.min_hole_per_thickness * thickness)
    web = max(p.min_web_mm, p.min_web_per_thickness * thickness)
    assert r_min == pytest.approx(hole / 2)
    assert r_max == pytest.approx(pitch / 2 - web / 2)  # the smaller pitch limits
    a_min, a_max = open_fraction_bounds(p, pl)
    cell = pitch * pitch * 1.5
    assert a_min == pytest.approx(math.pi * r_min**2 / cell)
    assert a_max == pytest.approx(math.pi * r_max**2 / cell)
    assert 0 < a_min < a_max < pl.max_open_fraction


def test_thickness_scaled_rules() -> None:
    foil = PROCESSES["etched-foil"]
    assert foil.min_hole_for(0.02) == pytest.approx(0.076)
    assert foil.min_hole_for(0.3) == pytest.approx(0.33)
    assert foil.min_web_for(0.3) == pytest.approx(0.3)
    assert min_pitch_mm(foil, 0.3) == pytest.approx(0.63)
    # Resin: 4 pixels in a thin plate; in a thick one the hole must stay washable
    # (depth <= 4 diameters), which reaches the generic 0.5 mm at 2 mm.
    resin = PROCESSES["resin"]
    assert resin.min_hole_for(0.3) == pytest.approx(0.088)
    assert resin.min_hole_for(2.0) == pytest.approx(0.5)
    assert resin.min_web_for(2.0) == pytest.approx(0.044)
    assert min_pitch_mm(resin, 1.0) == pytest.approx(0.25 + 0.044)


def test_no_hole_fits_gives_zero_fraction_bounds() -> None:
    assert open_fraction_bounds(PROCESSES["fdm"], plate(0.25, 1.0)) == (0.0, 0.0)


def test_check_plate_thickness_out_of_range() -> None:
    with pytest.raises(ValueError) as info:
        check_plate(PROCESSES["etched-foil"], plate(2.0, 1.0))
    message = str(info.value)
    assert "0.025 to 0.5 mm" in message
    assert "resin" in message and "fdm" in message  # processes that accept 1 mm
    assert isinstance(info.value, UnmakeableError)


@pytest.mark.parametrize(
    ("thickness", "need", "scale"),
    [(0.3, "0.132", "1.32x"),  # 4-pixel hole + 2-pixel web
     (0.6, "0.194", "1.94x")],  # the hole grows with thickness: 0.6 / 4 = 0.15 mm
)
def test_check_plate_pitch_too_small_names_min_pitch_and_processes(
    thickness: float, need: str, scale: str
) -> None:
    with pytest.raises(UnmakeableError) as info:
        check_plate(PROCESSES["resin"], plate(0.1, thickness))
    message = str(info.value)
    assert f"at least {need} mm" in message
    assert scale in message
    # No preset makes 0.1 mm cells at this thickness; the photomask does, thinner.
    assert "no process makes it at" in message
    assert "photomask (thickness 0.005 to 0.25 mm)" in message


@pytest.mark.parametrize("thickness", [0.15, 12.0])
def test_check_plate_resin_thickness_out_of_range(thickness: float) -> None:
    with pytest.raises(UnmakeableError) as info:
        check_plate(PROCESSES["resin"], plate(1.0, thickness))
    message = str(info.value)
    assert f"plate.thickness_mm = {thickness:g} is outside the resin range 0.2 to 10 mm" in message
    accept = [n for n, p in PROCESSES.items()
              if p.thickness_range_mm[0] <= thickness <= p.thickness_range_mm[1]]
    assert f"accept {thickness:g} mm: {', '.join(accept) or 'none of the presets'}" in message


def test_check_plate_passes_and_makeable_list() -> None:
    check_plate(PROCESSES["etched-foil"], plate(0.25, 0.05))
    names = makeable_processes(plate(0.25, 0.05))
    assert names == ["etched-foil", "photomask"]
    assert "photomask" not in makeable_processes(plate(0.25, 0.05), exclude="photomask")


def test_drawn_radii_compensate_the_bias() -> None:
    resin = PROCESSES["resin"]
    made = np.array([0.25, 0.3])
    np.testing.assert_allclose(drawn_radii_mm(resin, made) + resin.radius_bias_mm, made)
    with pytest.raises(ValueError, match="radius_bias_mm"):
        drawn_radii_mm(resolve_process("fdm", {"radius_bias_mm": 0.1}), np.array([0.05]))
