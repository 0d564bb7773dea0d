"""Photometry (aperture_fab.optics.photometry) against hand calculations of Watson and Yellott's
(2012) formula, its limits and the issue's worked example."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from aperture_fab.config.stages import PhotometrySettings, read_tables
from aperture_fab.optics.photometry import (
    MESOPIC_LOWER_CD_M2,
    MESOPIC_UPPER_CD_M2,
    PUPIL_TOLERANCE_MM,
    REFERENCE_AGE_YEARS,
    light_budget,
    pupil_diameter_mm,
    regime,
    trolands,
)


def test_the_formula_at_a_point_worked_by_hand() -> None:
    # F / 846 = 1 makes (F / 846)^0.41 = 1, so D_SD = 7.75 - 5.75 / 3; at the reference age the
    # age term vanishes.
    assert pupil_diameter_mm(846.0, 1.0, REFERENCE_AGE_YEARS) == pytest.approx(7.75 - 5.75 / 3)
    # One adapted eye counts a tenth of the flux: the same pupil at ten times the luminance.
    assert pupil_diameter_mm(8460.0, 1.0, REFERENCE_AGE_YEARS, eyes=1) == pytest.approx(
        7.75 - 5.75 / 3)
    # Age 60: D_SD + (60 - 28.58) (0.02132 - 0.009562 D_SD).
    d_sd = 7.75 - 5.75 / 3
    assert pupil_diameter_mm(846.0, 1.0, 60.0) == pytest.approx(
        d_sd + (60 - 28.58) * (0.02132 - 0.009562 * d_sd))


def test_the_limits_are_the_stanley_davies_range() -> None:
    assert pupil_diameter_mm(0.0, 100.0, REFERENCE_AGE_YEARS) == pytest.approx(7.75)
    assert pupil_diameter_mm(1e12, 100.0, REFERENCE_AGE_YEARS) == pytest.approx(2.0, abs=1e-2)


@given(st.floats(1e-4, 1e5), st.floats(1e-4, 1e5), st.floats(1.0, 3000.0),
       st.floats(20.0, 83.0))
def test_the_pupil_closes_as_the_light_rises(low: float, high: float, area: float,
                                             age: float) -> None:
    low, high = sorted((low, high))
    assert pupil_diameter_mm(high, area, age) <= pupil_diameter_mm(low, area, age) + 1e-12
    assert 1.0 < pupil_diameter_mm(high, area, age) < 9.0


def test_the_issues_example_is_mesopic_with_a_wider_pupil() -> None:
    """0.16 % of a 500 cd/m2 panel is 0.8 cd/m2: mesopic, the pupil near 5.5 mm over a 43 deg
    field, not the 4 mm the design assumed."""
    budget = light_budget(0.0016, 1.0, PhotometrySettings(), 4.0, (43.0, 43.0))
    assert budget.view_cd_m2 == pytest.approx(0.8)
    assert budget.regime == "mesopic"
    assert budget.trolands == pytest.approx(0.8 * math.pi * 4.0)
    power = (0.8 * 43 * 43 / 846) ** 0.41
    d_sd = 7.75 - 5.75 * power / (power + 2)
    assert budget.implied_pupil_mm == pytest.approx(
        d_sd + (30 - 28.58) * (0.02132 - 0.009562 * d_sd))
    assert 5.0 < budget.implied_pupil_mm < 6.0
    words = " ".join(budget.warnings())
    assert "mesopic" in words and "eye.pupil_mm" in words


def test_a_bright_view_with_the_right_pupil_has_no_warning() -> None:
    settings = PhotometrySettings(panel_luminance_cd_m2=1000.0)
    implied = pupil_diameter_mm(100.0, 40.0 * 40.0)
    budget = light_budget(0.1, 1.0, settings, implied, (40.0, 40.0))
    assert budget.regime == "photopic" and budget.warnings() == []


@pytest.mark.parametrize(("pupils", "warned"), [
    ((3.0, 6.0), False), ((4.5, 6.0), True), (None, True)])
def test_the_pupil_is_judged_against_the_pupils_the_design_was_made_for(pupils, warned) -> None:
    """A design made over pupils of 3 to 6 mm (eye.pupil_range_mm) was judged at the 3.4 mm
    pupil of a 34 cd/m2 view; one made for 4 mm alone, or 4.5 to 6, was not."""
    settings = PhotometrySettings(panel_luminance_cd_m2=500.0)
    budget = light_budget(0.5, 0.136, settings, 4.0, (43.0, 43.0), pupils)
    assert 3.0 < budget.implied_pupil_mm < 4.0 - PUPIL_TOLERANCE_MM
    lo, hi = pupils or (4.0, 4.0)
    assert budget.pupil_mismatch_mm == pytest.approx(budget.implied_pupil_mm - lo if warned
                                                     else 0.0)
    words = " ".join(budget.warnings())
    assert ("eye.pupil_mm" in words) == warned
    if warned:
        assert (f"outside the {lo:g} to {hi:g} mm the design was made for" if pupils else
                "outside the 4 mm the design assumed") in words


@pytest.mark.parametrize(("luminance", "expected"), [
    (MESOPIC_UPPER_CD_M2, "photopic"), (MESOPIC_UPPER_CD_M2 * 0.99, "mesopic"),
    (MESOPIC_LOWER_CD_M2, "mesopic"), (MESOPIC_LOWER_CD_M2 * 0.99, "scotopic")])
def test_regimes_follow_cie_191(luminance: float, expected: str) -> None:
    assert regime(luminance) == expected


def test_trolands_are_luminance_times_pupil_area() -> None:
    assert trolands(100.0, 2.0) == pytest.approx(100.0 * math.pi)


@pytest.mark.parametrize(("table", "fragment"), [
    ({"panel_luminance_cd_m2": -1}, "panel_luminance_cd_m2 = -1"),
    ({"observer_age_years": 5}, "observer_age_years = 5"),
    ({"adapted_eyes": 3}, "adapted_eyes = 3"),
    ({"panel_nits": 500}, "unknown key(s) ['panel_nits']"),
])
def test_bad_settings_are_refused(table: dict, fragment: str) -> None:
    with pytest.raises(ValueError) as info:
        read_tables({"photometry": table})
    assert fragment in str(info.value)


@pytest.mark.parametrize(("args", "fragment"), [
    ((-1.0, 10.0), "luminance_cd_m2"), ((1.0, 0.0), "field_area_deg2")])
def test_bad_formula_inputs_are_refused(args: tuple[float, float], fragment: str) -> None:
    with pytest.raises(ValueError, match=fragment):
        pupil_diameter_mm(*args)
