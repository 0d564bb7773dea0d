"""The light budget in real units: what the eye sees through the plate, in cd/m2 and trolands,
the pupil that light level implies, and the contrast the plate material's leakage leaves.

A plate passes a small share of the display's light (its light efficiency: the view's mean level
over the open display's with the same content). With the panel's luminance that share becomes
the luminance of the view. The pupil the eye opens to at that luminance follows Watson and
Yellott's unified formula:

    A. B. Watson and J. I. Yellott (2012), "A unified formula for light-adapted pupil size",
    Journal of Vision 12(10):12, doi:10.1167/12.10.12, equation 21:
    D_U = D_SD(F, 1) + (y - y0) (0.02132 - 0.009562 D_SD(F, 1)),  F = L a M(e),
    D_SD(F, 1) = 7.75 - 5.75 (F / 846)^0.41 / ((F / 846)^0.41 + 2)   (Stanley and Davies 1995),

with L the adapting luminance (cd/m2), a the adapting field's area (deg2), y the observer's age
(years, the formula fitted over 20 to 83), y0 = 28.58 years and M(e) = 1 for two adapted eyes,
0.1 for one. Retinal illuminance in trolands is L times the pupil's area in mm2.

The view is mesopic below MESOPIC_UPPER_CD_M2 (CIE 191:2010 takes 0.005 to 5 cd/m2), where
rods start to contribute and acuity and colour vision fall off.

Neglected: the Stiles-Crawford effect (light through the pupil's edge counts less), the eye's
own transmission, and that the adapting field is the view rather than a uniform field centred
on fixation (the formula's condition).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from aperture_fab.config.stages import AGE_RANGE_YEARS, DEFAULT_AGE_YEARS, PhotometrySettings

__all__ = [
    "LightBudget",
    "Regime",
    "light_budget",
    "pupil_diameter_mm",
    "regime",
    "trolands",
]

#: The age Watson and Yellott's formula is referred to (its fitted range and the default
#: observer: aperture_fab.config.stages).
REFERENCE_AGE_YEARS = 28.58
#: M(e): the share of the corneal flux that counts when one eye only is adapted.
MONOCULAR_FACTOR = 0.1
#: CIE 191:2010's mesopic range (cd/m2): photopic above, scotopic below.
MESOPIC_UPPER_CD_M2 = 5.0
MESOPIC_LOWER_CD_M2 = 0.005
#: Assumed and implied pupil differ "materially" beyond this (mm): a tenth of a millimetre
#: of pupil already moves the view by more than the design's margin (README).
PUPIL_TOLERANCE_MM = 0.5

Regime = Literal["photopic", "mesopic", "scotopic"]


def pupil_diameter_mm(luminance_cd_m2: float, field_area_deg2: float,
                      age_years: float = DEFAULT_AGE_YEARS, eyes: int = 2) -> float:
    """Watson and Yellott's (2012) light-adapted pupil diameter in mm (module docstring).

    luminance_cd_m2: the adapting field's luminance (>= 0). field_area_deg2: its area (> 0).
    age_years: clamped to the fitted 20 to 83. eyes: 1 or 2 adapted eyes.
    """
    if not (math.isfinite(luminance_cd_m2) and luminance_cd_m2 >= 0):
        raise ValueError(f"luminance_cd_m2 = {luminance_cd_m2!r}; allowed: a number >= 0.")
    if not (math.isfinite(field_area_deg2) and field_area_deg2 > 0):
        raise ValueError(f"field_area_deg2 = {field_area_deg2!r}; allowed: a number > 0.")
    if eyes not in (1, 2):
        raise ValueError(f"eyes = {eyes!r}; allowed: 1 or 2 adapted eyes.")
    flux = luminance_cd_m2 * field_area_deg2 * (1.0 if eyes == 2 else MONOCULAR_FACTOR)
    power = (flux / 846.0) ** 0.41
    d_sd = 7.75 - 5.75 * power / (power + 2.0)
    age = min(max(age_years, AGE_RANGE_YEARS[0]), AGE_RANGE_YEARS[1])
    return d_sd + (age - REFERENCE_AGE_YEARS) * (0.02132 - 0.009562 * d_sd)


def trolands(luminance_cd_m2: float, pupil_mm: float) -> float:
    """Retinal illuminance (td): luminance (cd/m2) times the pupil's area (mm2)."""
    return luminance_cd_m2 * math.pi * (pupil_mm / 2) ** 2


def regime(luminance_cd_m2: float) -> Regime:
    """Photopic, mesopic or scotopic by CIE 191:2010's limits."""
    if luminance_cd_m2 >= MESOPIC_UPPER_CD_M2:
        return "photopic"
    return "mesopic" if luminance_cd_m2 >= MESOPIC_LOWER_CD_M2 else "scotopic"


@dataclass(frozen=True)
class LightBudget:
    """What the eye gets through the plate.

    efficiency: view mean / the open display's with the same content.
    panel_cd_m2: the panel's full-white luminance; content_level: the mean linear level of the
    content shown (0 to 1). view_cd_m2: the view's mean luminance. trolands: retinal
    illuminance with the assumed pupil. assumed_pupil_mm: the design's pupil.
    implied_pupil_mm: the pupil Watson and Yellott give for view_cd_m2 over the field of view.
    regime: photopic, mesopic or scotopic. field_area_deg2: the adapting field.
    designed_pupils_mm: the pupil diameters (lo, hi) the design was made and judged for (its
        eye distribution's eye.pupil_range_mm); None: the assumed pupil alone.
    """

    efficiency: float
    panel_cd_m2: float
    content_level: float
    view_cd_m2: float
    trolands: float
    assumed_pupil_mm: float
    implied_pupil_mm: float
    regime: Regime
    field_area_deg2: float
    designed_pupils_mm: tuple[float, float] | None = None

    @property
    def pupil_mismatch_mm(self) -> float:
        """How far the implied pupil lies outside the designed ones (mm; negative: smaller,
        0: among them)."""
        lo, hi = self.designed_pupils_mm or (self.assumed_pupil_mm, self.assumed_pupil_mm)
        return self.implied_pupil_mm - min(max(self.implied_pupil_mm, lo), hi)

    def designed_pupils(self) -> str:
        """The pupils the design was made for, in words."""
        if self.designed_pupils_mm is None:
            return f"the {self.assumed_pupil_mm:g} mm the design assumed"
        lo, hi = self.designed_pupils_mm
        return f"the {lo:g} to {hi:g} mm the design was made for"

    def warnings(self) -> list[str]:
        """What a designer should act on, in words; empty when nothing."""
        out = []
        if self.regime != "photopic":
            out.append(
                f"The view is {self.regime} ({self.view_cd_m2:.3g} cd/m2, below "
                f"{MESOPIC_UPPER_CD_M2:g}): acuity and colour fall off. Raise the panel's "
                "luminance ([photometry] panel_luminance_cd_m2) or the plate's light efficiency "
                "(optimizer.min_efficiency, a larger pitch fill).")
        if abs(self.pupil_mismatch_mm) > PUPIL_TOLERANCE_MM:
            out.append(
                f"At {self.view_cd_m2:.3g} cd/m2 the pupil opens to about "
                f"{self.implied_pupil_mm:.1f} mm (Watson and Yellott 2012), outside "
                f"{self.designed_pupils()}: set eye.pupil_mm (and "
                "eye.pupil_range_mm) to the pupil at this light level, or change the light level.")
        return out


def light_budget(efficiency: float, content_level: float, settings: PhotometrySettings,
                 assumed_pupil_mm: float, fov_deg: tuple[float, float],
                 designed_pupils_mm: tuple[float, float] | None = None) -> LightBudget:
    """The light budget of a view: efficiency and the content's mean linear level (0 to 1) on a
    panel of settings.panel_luminance_cd_m2, seen over a field fov_deg (x, y) in degrees, by a
    design made for designed_pupils_mm (lo, hi; None: the assumed pupil alone)."""
    if not (math.isfinite(efficiency) and efficiency >= 0):
        raise ValueError(f"efficiency = {efficiency!r}; allowed: a number >= 0.")
    if not (math.isfinite(content_level) and 0 <= content_level <= 1):
        raise ValueError(f"content_level = {content_level!r}; allowed: 0 to 1 (linear).")
    view = settings.panel_luminance_cd_m2 * content_level * efficiency
    area = fov_deg[0] * fov_deg[1]
    implied = pupil_diameter_mm(view, area, settings.observer_age_years, settings.adapted_eyes)
    return LightBudget(efficiency, settings.panel_luminance_cd_m2, content_level, view,
                       trolands(view, assumed_pupil_mm), assumed_pupil_mm, implied, regime(view),
                       area, designed_pupils_mm)
