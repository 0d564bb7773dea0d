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

from aperture_fab.config.stages import PhotometrySettings
from aperture_fab.optics.photometry import MESOPIC_UPPER_CD_M2, PUPIL_TOLERANCE_MM, light_budget
from aperture_fab.validation.formatting import percent, sig
from aperture_fab.validation.report import Verdict

__all__ = ["FLOOR_FAIL_SHARE", "LEAKAGE_WARN_SHARE", "MADE_STATES", "NOMINAL_EYE",
           "PUPIL_SOURCE", "content_level",
           "contrast_verdict", "light_verdict", "lower_floor_fix", "photometry_block"]

#: Leakage through the material above this share of the light through the holes: warn.
LEAKAGE_WARN_SHARE = 0.03
#: A brightness floor (optimizer.min_efficiency) missed by more than this share of it: fail;
#: missed by less: warn.
FLOOR_FAIL_SHARE = 0.10
#: Where the light floors are judged (the photometry block's "floors_on"): the part as made
#: over made copies x eye states, where the optimizer holds them, or the nominal eye (no part as
#: made judged).
MADE_STATES, NOMINAL_EYE = "made copies x eye states", "nominal eye"
#: Rec. 709 / sRGB luminance weights of linear R, G, B.
LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)
PUPIL_SOURCE = ("Watson and Yellott (2012), A unified formula for light-adapted pupil size, "
                "Journal of Vision 12(10):12, doi:10.1167/12.10.12")
LIGHT_TOPIC = "light"
CONTRAST_TOPIC = "contrast"
#: Processes whose plate is metal sheet or foil: opaque (a fix for leakage names one of them).
METAL_PROCESSES = ("etched-foil", "laser")
#: The start of a photometry warning that the [photometry] settings could not be used (the
#: block's other warnings, the light regime and the pupil, the light verdict words itself).
SETTINGS_WARNING = "[photometry]"


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
                     min_eye_level: float = 0.0,
                     held: tuple[float, float] | None = None,
                     designed_pupils_mm: tuple[float, float] | None = None) -> dict[str, Any]:
    """report.json's "photometry" block (report.py's PHOTOMETRY).

    efficiency: the part as built's light efficiency (mean over targets, nominal eye).
    level: the shown content's mean linear level (`content_level`). min_efficiency,
    efficiency_weight: the optimizer's brightness floor and light weight. min_eye_level: its
    floor on the light at the eye (a share of the panel's white; the part's is efficiency x
    level at the nominal eye). open_share: the plate's open area fraction. held: the part as
    made over made copies x eye states (the made-part block's efficiency and light at the eye),
    what the optimizer holds its floors on (per drawn eye state, as made): the floors are
    judged on it; None judges them at the nominal eye. designed_pupils_mm: the pupil range the
    design was made for (eye.pupil_range_mm; None: the assumed pupil alone).
    """
    budget = light_budget(efficiency, level, settings, assumed_pupil_mm, fov_deg,
                          designed_pupils_mm)
    warnings = budget.warnings()
    floor = float(min_efficiency)
    held_efficiency, held_level = (efficiency, efficiency * level) if held is None else held
    meets = None if floor <= 0 else bool(held_efficiency >= floor)
    transmitted = 10.0 ** -optical_density
    leak = math.inf if efficiency <= 0 else transmitted * (1.0 - open_share) / efficiency
    needed = MESOPIC_UPPER_CD_M2 / (settings.panel_luminance_cd_m2 * level) if level > 0 else None
    eye_floor = float(min_eye_level)
    return {
        "panel_luminance_cd_m2": settings.panel_luminance_cd_m2,
        "light_efficiency": efficiency,
        "content_level": level,
        "view_luminance_cd_m2": budget.view_cd_m2,
        "retinal_illuminance_td": budget.trolands,
        "assumed_pupil_mm": budget.assumed_pupil_mm,
        "implied_pupil_mm": budget.implied_pupil_mm,
        "designed_pupils_mm": None if designed_pupils_mm is None else list(designed_pupils_mm),
        "pupil_mismatch_mm": budget.pupil_mismatch_mm,
        "designed_pupils": budget.designed_pupils(),
        "pupil_source": PUPIL_SOURCE,
        "field_area_deg2": budget.field_area_deg2,
        "observer_age_years": settings.observer_age_years,
        "adapted_eyes": settings.adapted_eyes,
        "regime": budget.regime,
        "photopic_efficiency": needed,
        "min_efficiency": floor,
        "efficiency_weight": float(efficiency_weight),
        "meets_min_efficiency": meets,
        "photopic_eye_level": MESOPIC_UPPER_CD_M2 / settings.panel_luminance_cd_m2,
        "min_eye_level": eye_floor,
        "meets_min_eye_level": None if eye_floor <= 0 else bool(held_level >= eye_floor),
        "floors_on": NOMINAL_EYE if held is None else MADE_STATES,
        "floor_efficiency": held_efficiency,
        "floor_eye_level": held_level,
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


def lower_floor_fix(floor: float) -> str:
    """Lowering the brightness floor `floor` (> 0), in the same words wherever it is proposed
    (so that the page lists it once)."""
    return (f"Lower the brightness floor (optimizer.min_efficiency, now {_pct(floor)}) if the "
            "panel is bright enough.")


def _light_fixes(block: Mapping[str, Any], *, dark: bool, pupil: bool, missed: bool
                 ) -> tuple[str, ...]:
    """What to change for the light verdict's problems, most effective first, leaving out what
    the design already does (a floor is raised or lowered, not set, when it is set)."""
    floor, needed = block["min_efficiency"], block["photopic_efficiency"]
    eye_floor, photopic = block["min_eye_level"], block["photopic_eye_level"]
    keeps = "" if needed is None else f"about {_pct(needed)} keeps this panel and content photopic"
    fixes = []
    if dark and not missed and photopic < 1:
        # The direct fix: the plate's efficiency alone leaves the content dark (a coded plate's
        # is), so a floor on the light at the eye lets the optimizer brighten both.
        fixes.append(
            f"{'Raise' if eye_floor > 0 else 'Set'} the floor on the light at the eye "
            f"(optimizer.min_eye_level{f', now {_pct(eye_floor)}' if eye_floor > 0 else ''}) "
            f"to {photopic:.2g} ({MESOPIC_UPPER_CD_M2:g} cd/m2 from this panel) and design "
            "again: the view gets brighter at some cost in sharpness.")
    if missed:
        fixes.append("Design again with more iterations (optimizer.iterations) or a larger "
                     "optimizer.tail_share, so that the part reaches its floor.")
        if floor > 0:
            fixes.append(lower_floor_fix(floor))
    if dark and floor <= 0 and block["efficiency_weight"] <= 0:
        fixes.append("Set optimizer.min_efficiency to the light efficiency the device needs"
                     + (f" ({keeps})" if keeps else "") + " and design again.")
    elif dark and not missed:
        fixes.append(f"Raise the brightness floor (optimizer.min_efficiency, now {_pct(floor)}"
                     + (f"; {keeps}" if keeps else "") + ") and design again.")
    if dark:
        fixes.append("Use a brighter panel, and set [photometry] panel_luminance_cd_m2 (now "
                     f"{block['panel_luminance_cd_m2']:.3g} cd/m2) to its full-white luminance.")
    if pupil:
        fixes.append(f"Set eye.pupil_mm (and eye.pupil_range_mm) to the pupil at this light, "
                     f"about {block['implied_pupil_mm']:.1f} mm, and design again.")
    return tuple(fixes)


def light_verdict(block: Mapping[str, Any]) -> Verdict:
    """Fail when a light floor (the brightness floor, or the floor on the light at the eye) is
    set and missed by more than FLOOR_FAIL_SHARE of it; warn when the view is mesopic (or
    darker), when the implied pupil differs from the assumed by more than PUPIL_TOLERANCE_MM,
    or when a floor is missed by less; pass otherwise."""
    efficiency, floor = block["light_efficiency"], block["min_efficiency"]
    text = (f"The part passes {_pct(efficiency)} of the open display's light (nominal eye, mean "
            f"over targets): a {block['panel_luminance_cd_m2']:.3g} cd/m2 panel showing this "
            f"content (mean level {block['content_level']:.2f}) gives "
            f"{block['view_luminance_cd_m2']:.2g} cd/m2 at the eye, "
            f"{block['retinal_illuminance_td']:.2g} td through the assumed "
            f"{block['assumed_pupil_mm']:.3g} mm pupil: {block['regime']}.")
    problems = [w for w in block["warnings"] if w.startswith(SETTINGS_WARNING)]
    dark = block["regime"] != "photopic"
    if dark:
        problems.append(f"The view is {block['regime']} (below {MESOPIC_UPPER_CD_M2:g} cd/m2): "
                        "acuity and colour fall off.")
    # Blocks written before the design's pupil range was recorded compare with the assumed.
    mismatch = block.get("pupil_mismatch_mm",
                         block["implied_pupil_mm"] - block["assumed_pupil_mm"])
    designed = block.get("designed_pupils",
                         f"the {block['assumed_pupil_mm']:g} mm the design assumed")
    pupil = abs(mismatch) > PUPIL_TOLERANCE_MM
    if pupil:
        problems.append(f"At that light the pupil opens to about "
                        f"{block['implied_pupil_mm']:.1f} mm (Watson and Yellott 2012), outside "
                        f"{designed}.")
    else:
        text += (f" At that light the pupil opens to about {block['implied_pupil_mm']:.1f} mm "
                 f"(Watson and Yellott 2012), within {PUPIL_TOLERANCE_MM:g} mm of {designed}.")
    level = "warn" if problems else "pass"
    missed = False
    eye_floor = block["min_eye_level"]
    # Blocks written before the floors were judged where the optimizer holds them lack these.
    made = block.get("floors_on") == MADE_STATES
    for key, value, bound, what in (
            ("min_efficiency", block.get("floor_efficiency", efficiency), floor,
             "the brightness floor"),
            ("min_eye_level", block.get("floor_eye_level", efficiency * block["content_level"]),
             eye_floor, "the floor on the light at the eye")):
        on = (f" ({_pct(value)} as made over the eye distribution, where the optimizer holds "
              "it)" if made else "")
        if bound > 0 and block[f"meets_{key}"] is False:
            short = 1.0 - value / bound
            problems.append(f"It misses {what} optimizer.{key} = {_pct(bound)}{on} by "
                            f"{_pct(short)} of it.")
            missed = True
            if short > FLOOR_FAIL_SHARE:
                level = "fail"
            elif level == "pass":
                level = "warn"
        elif bound > 0:
            text += f" It meets {what} optimizer.{key} = {_pct(bound)}{on}."
    if (level != "pass" and floor <= 0 and eye_floor <= 0
            and block["efficiency_weight"] <= 0):
        problems.append("Nothing in the design asked for light: optimizer.efficiency_weight, "
                        "optimizer.min_efficiency and optimizer.min_eye_level are 0.")
    if not problems:
        text += f" Photopic, and the pupil within {PUPIL_TOLERANCE_MM:g} mm of the design's."
    fixes = () if level == "pass" else _light_fixes(block, dark=dark, pupil=pupil,
                                                    missed=missed)
    return Verdict(LIGHT_TOPIC, level, " ".join([text, *problems]), fixes)


def _contrast_fixes(block: Mapping[str, Any], process: str | None,
                    process_settings: Mapping[str, Any]) -> tuple[str, ...]:
    """What to change for too much leakage, leaving out what the design already does."""
    leak = block["leakage"]
    fixes = []
    if "estimate" in leak["optical_density_note"] and "optical_density" not in process_settings:
        fixes.append("Measure a blank of the plate's thickness and set [process] "
                     f"optical_density (now {leak['optical_density']:g}, an estimate).")
    fixes.append("Make the plate thicker or blacker, or coat its display side opaque.")
    if process not in METAL_PROCESSES:
        fixes.append(f"Make it of metal ({' or '.join(METAL_PROCESSES)}): opaque.")
    floor = block["min_efficiency"]
    fixes.append("Pass more light through the holes: "
                 + (f"raise optimizer.min_efficiency (now {_pct(floor)})" if floor > 0
                    else "set optimizer.min_efficiency") + " and design again.")
    return tuple(fixes)


def contrast_verdict(block: Mapping[str, Any], process: str | None = None,
                     process_settings: Mapping[str, Any] | None = None) -> Verdict:
    """Warn when the plate material leaks more than LEAKAGE_WARN_SHARE of the light through the
    holes; pass otherwise. process, process_settings: the process's name and the config's
    [process] table, so that a fix the design already applied is not proposed."""
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
            f" More than {_pct(LEAKAGE_WARN_SHARE)}: dark parts of the view turn grey."),
            _contrast_fixes(block, process, {} if process_settings is None else process_settings))
    return Verdict(CONTRAST_TOPIC, "pass", text + f" At most {_pct(LEAKAGE_WARN_SHARE)}.")
