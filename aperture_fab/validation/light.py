"""The report's light budget and contrast: what the eye gets through the part as built, in
cd/m2 and trolands (aperture_fab.optics.photometry), and the light the plate material leaks.

Pure functions, values in and report.json's "photometry" block or verdicts out.

Leakage (the contrast model). The solid plate passes 10^-OD of the light falling on it (OD: the
process's `optical_density`). Relative to the open display, the light through the holes is the
light efficiency E; the light through the material is 10^-OD (1 - f), f the open share of the
plate (the eye looks through the whole plate, so its open area fraction stands for the open
share of the pupil's view). The leakage share is

    leak = 10^-OD (1 - f) / E,

a veil of that share of the signal's mean, nearly uniform (the display is far out of focus
through the material). A full-white region over a black one then reaches a contrast ratio of
(E + veil) / veil = 1 + 1 / leak. Neglected: light scattered off the hole walls, reflections
off the plate's faces and the eye, the display's own black level and the OD's change with the
plate's thickness (the catalogue gives it at the process's typical thickness).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from aperture_fab.optics.photometry import (
    MESOPIC_UPPER_CD_M2,
    PUPIL_TOLERANCE_MM,
    PhotometrySettings,
    light_budget,
)
from aperture_fab.validation.formatting import percent, sig
from aperture_fab.validation.report import Verdict

__all__ = ["FLOOR_FAIL_SHARE", "LEAKAGE_WARN_SHARE", "PUPIL_SOURCE", "content_level",
           "contrast_verdict", "light_verdict", "photometry_block"]

#: Leakage through the material above this share of the light through the holes: warn.
LEAKAGE_WARN_SHARE = 0.03
#: A brightness floor (optimizer.min_efficiency) missed by more than this share of it: fail;
#: missed by less: warn.
FLOOR_FAIL_SHARE = 0.10
#: Rec. 709 / sRGB luminance weights of linear R, G, B.
LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)
PUPIL_SOURCE = ("Watson and Yellott (2012), A unified formula for light-adapted pupil size, "
                "Journal of Vision 12(10):12, doi:10.1167/12.10.12")
LIGHT_TOPIC = "light"
CONTRAST_TOPIC = "contrast"


def content_level(displays: np.ndarray) -> float:
    """The mean linear luminance level (0 to 1) of display contents (T, C, ny, nx), C = 1 or 3
    (RGB weighted by LUMINANCE_WEIGHTS)."""
    array = np.asarray(displays, dtype=np.float64)
    if array.ndim != 4 or array.shape[1] not in (1, 3) or array.size == 0:
        raise ValueError(f"display contents have shape {array.shape}; expected (T, C, ny, nx) "
                         "with C = 1 or 3.")
    means = np.clip(array, 0.0, 1.0).mean(axis=(0, 2, 3))
    if means.size == 1:
        return float(means[0])
    return float(np.dot(LUMINANCE_WEIGHTS, means))


def photometry_block(*, efficiency: float, level: float, settings: PhotometrySettings,
                     assumed_pupil_mm: float, fov_deg: tuple[float, float],
                     min_efficiency: float, efficiency_weight: float, optical_density: float,
                     optical_density_note: str, open_share: float,
                     settings_error: str | None = None) -> dict[str, Any]:
    """report.json's "photometry" block (report.py's PHOTOMETRY).

    efficiency: the part as built's light efficiency (mean over targets, nominal eye).
    level: the shown content's mean linear level (`content_level`). min_efficiency,
    efficiency_weight: the optimizer's brightness floor and light weight. open_share: the
    plate's open area fraction. settings_error: why the config's [photometry] could not be
    used (the defaults were), or None.
    """
    budget = light_budget(efficiency, level, settings, assumed_pupil_mm, fov_deg)
    warnings = budget.warnings()
    if settings_error is not None:
        warnings.insert(0, f"{settings_error} The defaults were used.")
    floor = float(min_efficiency)
    meets = None if floor <= 0 else bool(efficiency >= floor)
    transmitted = 10.0 ** -optical_density
    leak = math.inf if efficiency <= 0 else transmitted * (1.0 - open_share) / efficiency
    needed = MESOPIC_UPPER_CD_M2 / (settings.panel_luminance_cd_m2 * level) if level > 0 else None
    return {
        "panel_luminance_cd_m2": settings.panel_luminance_cd_m2,
        "light_efficiency": efficiency,
        "content_level": level,
        "view_luminance_cd_m2": budget.view_cd_m2,
        "retinal_illuminance_td": budget.trolands,
        "assumed_pupil_mm": budget.assumed_pupil_mm,
        "implied_pupil_mm": budget.implied_pupil_mm,
        "pupil_source": PUPIL_SOURCE,
        "field_area_deg2": budget.field_area_deg2,
        "observer_age_years": settings.observer_age_years,
        "adapted_eyes": settings.adapted_eyes,
        "regime": budget.regime,
        "photopic_efficiency": needed,
        "min_efficiency": floor,
        "efficiency_weight": float(efficiency_weight),
        "meets_min_efficiency": meets,
        "warnings": warnings,
        "leakage": {
            "optical_density": float(optical_density),
            "optical_density_note": optical_density_note,
            "open_share": float(open_share),
            "leakage_share": leak,
            "contrast_ratio": math.inf if leak == 0 else 1.0 + 1.0 / leak,
        },
    }


def _pct(value: float) -> str:
    """A share as a percentage, or as "N times" from 1 up."""
    return percent(value) if value < 1 else f"{sig(value, 2)} times"


def light_verdict(block: Mapping[str, Any]) -> Verdict:
    """Fail when the brightness floor is set and missed by more than FLOOR_FAIL_SHARE of it;
    warn when the view is mesopic (or darker), when the implied pupil differs from the assumed
    by more than PUPIL_TOLERANCE_MM, or when the floor is missed by less; pass otherwise."""
    efficiency, floor = block["light_efficiency"], block["min_efficiency"]
    text = (f"The part passes {_pct(efficiency)} of the open display's light (nominal eye, mean "
            f"over targets): a {block['panel_luminance_cd_m2']:.3g} cd/m2 panel showing this "
            f"content (mean level {block['content_level']:.2f}) gives "
            f"{block['view_luminance_cd_m2']:.2g} cd/m2 at the eye, "
            f"{block['retinal_illuminance_td']:.2g} td through the assumed "
            f"{block['assumed_pupil_mm']:.3g} mm pupil: {block['regime']}.")
    problems = list(block["warnings"])
    if abs(block["implied_pupil_mm"] - block["assumed_pupil_mm"]) <= PUPIL_TOLERANCE_MM:
        text += (f" At that light the pupil opens to about {block['implied_pupil_mm']:.1f} mm "
                 "(Watson and Yellott 2012).")
    level = "pass"
    if problems:
        level = "warn"
    if floor > 0 and block["meets_min_efficiency"] is False:
        short = 1.0 - efficiency / floor
        problems.append(
            f"It misses the brightness floor optimizer.min_efficiency = {_pct(floor)} by "
            f"{_pct(short)} of it: design again with more iterations or a larger tail_share, or "
            "lower the floor if the panel is bright enough.")
        level = "fail" if short > FLOOR_FAIL_SHARE else "warn"
    elif floor > 0:
        text += f" It meets the brightness floor optimizer.min_efficiency = {_pct(floor)}."
    if level != "pass" and floor <= 0 and block["efficiency_weight"] <= 0:
        needed = block["photopic_efficiency"]
        hint = "" if needed is None else (
            f" (about {_pct(needed)} keeps this panel and content photopic)")
        problems.append(
            "Nothing in the design asked for light: optimizer.efficiency_weight and "
            "optimizer.min_efficiency are 0. Fix: set optimizer.min_efficiency to the light "
            f"efficiency the device needs{hint}, or raise [photometry] panel_luminance_cd_m2 "
            "if the panel is brighter.")
    if not problems:
        text += (f" Photopic, and the pupil within {PUPIL_TOLERANCE_MM:g} mm of the design's.")
    return Verdict(LIGHT_TOPIC, level, " ".join([text, *problems]))


def contrast_verdict(block: Mapping[str, Any]) -> Verdict:
    """Warn when the plate material leaks more than LEAKAGE_WARN_SHARE of the light through the
    holes; pass otherwise."""
    leak = block["leakage"]
    share, ratio = leak["leakage_share"], leak["contrast_ratio"]
    ratio_text = "unlimited" if ratio is None or not math.isfinite(ratio) else f"{ratio:.3g}:1"
    share_text = ("unbounded" if share is None or not math.isfinite(share)
                  else _pct(share) + (" of" if share < 1 else ""))
    note = leak["optical_density_note"]
    source = "an estimate" if "estimate" in note else note.split(".")[0]
    text = (f"The plate material (optical density {leak['optical_density']:g}, {source}) "
            f"passes 10^-{leak['optical_density']:g} of the light over the "
            f"{percent(1 - leak['open_share'], 3)} of the plate that is solid: {share_text} the "
            f"light through the holes, a veil that limits the contrast to {ratio_text}.")
    if share is None or share > LEAKAGE_WARN_SHARE:
        return Verdict(CONTRAST_TOPIC, "warn", text + (
            f" More than {_pct(LEAKAGE_WARN_SHARE)}: dark parts of the view turn grey. Fix: "
            "measure a blank of the plate's thickness and set [process] optical_density; a "
            "thicker or blacker plate, a metal process (etched-foil) or an opaque coating on "
            "the plate's display side; or more light through the holes "
            "(optimizer.min_efficiency)."))
    return Verdict(CONTRAST_TOPIC, "pass", text + f" At most {_pct(LEAKAGE_WARN_SHARE)}.")
