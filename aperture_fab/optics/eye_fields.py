"""The eye's fields and their checks: the eyebox, pupil, focus, gaze and rotation ranges an eye
(aperture_fab.optics.scene.Eye) and its distribution (aperture_fab.optics.eyes) may take, each
checked with a message that names the field, the value, the allowed range and the fix."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Literal

import numpy as np

__all__ = ["EYEBOX_SHAPES", "EyeboxShape", "MAX_ACCOMMODATION_DIOPTERS", "MAX_EYEBOX_MM",
           "MAX_GAZE_DEG", "MAX_PUPIL_MM", "MAX_ROTATION_MM", "check_fields", "check_number",
           "check_pair"]


EyeboxShape = Literal["ellipse", "rect"]


EYEBOX_SHAPES: tuple[EyeboxShape, ...] = ("ellipse", "rect")


MAX_EYEBOX_MM = 50.0


MAX_PUPIL_MM = 20.0


#: A human eye accommodates by at most about 10 D (less with age); a fixed focus may be nearer.
MAX_ACCOMMODATION_DIOPTERS = 10.0


MAX_GAZE_DEG = 45.0


MAX_ROTATION_MM = 30.0


#: Relative slack in "the nominal lies inside its range" (1000 / mm round trips).
_RANGE_SLACK = 1e-9


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float, np.floating, np.integer)) and not isinstance(value, bool)


def check_number(name: str, value: object, low: float, high: float, fix: str,
                  *, positive: bool = False) -> None:
    """low <= value <= high (low < value when positive), finite, else an error naming `name`."""
    if not _is_number(value):
        raise TypeError(f"{name} must be a number, got {value!r} ({type(value).__name__})")
    number = float(value)  # type: ignore[arg-type]
    if not (math.isfinite(number) and (low < number if positive else low <= number)
            and number <= high):
        allowed = (f"{low:g} < {name.rsplit('.', 1)[-1]} <= {high:g}" if positive
                   else f"{low:g} to {high:g}")
        raise ValueError(f"{name} = {value!r} is out of range; allowed: {allowed}. {fix}")


def check_pair(name: str, value: object) -> tuple[float, float]:
    if not (isinstance(value, (tuple, list)) and len(value) == 2 and all(map(_is_number, value))):
        raise TypeError(f"{name} must be a pair of numbers, got {value!r}")
    return (float(value[0]), float(value[1]))


def _check_range(name: str, value: object, low: float, high: float, fix: str,
                 *, positive: bool = False) -> tuple[float, float]:
    lo, hi = check_pair(name, value)
    bad_low = lo <= low if positive else lo < low
    if not (math.isfinite(lo) and math.isfinite(hi)) or bad_low or hi > high or lo > hi:
        first = f"0 < lo <= hi <= {high:g}" if positive else f"{low:g} <= lo <= hi <= {high:g}"
        raise ValueError(f"{name} = {value!r} is out of range; allowed: [lo, hi] with {first}. "
                         f"{fix}")
    return lo, hi


def _inside(value: float, lo: float, hi: float) -> bool:
    slack = _RANGE_SLACK * max(1.0, abs(lo), abs(hi))
    return lo - slack <= value <= hi + slack


def check_fields(
    names: Mapping[str, str],
    *,
    eyebox_mm: object,
    eyebox_shape: object,
    pupil_range_mm: object | None,
    nominal_pupil_mm: float,
    focus_range_diopters: object | None,
    nominal_focus_diopters: float,
    gaze_deg: object,
    rotation_mm: object,
) -> None:
    """Raise ValueError / TypeError naming the field unless the distribution fields are valid.

    names: how messages name each field ("eyebox_mm", ..., "pupil", "focus" for the nominals),
        e.g. "eye.eyebox_mm" for the config's [eye] section. A None range is the nominal point.
    """
    w, h = check_pair(names["eyebox_mm"], eyebox_mm)
    for size in (w, h):
        if not (math.isfinite(size) and 0 <= size <= MAX_EYEBOX_MM):
            raise ValueError(
                f"{names['eyebox_mm']} = {eyebox_mm!r} is out of range; allowed: 0 to "
                f"{MAX_EYEBOX_MM:g} mm per axis. Give the full width and height of the region "
                "the pupil centre can take, e.g. [4, 4]; [0, 0] fixes it at the nominal position."
            )
    if eyebox_shape not in EYEBOX_SHAPES:
        raise ValueError(f"{names['eyebox_shape']} = {eyebox_shape!r} is not allowed; choose one "
                         f"of {', '.join(EYEBOX_SHAPES)}.")
    if pupil_range_mm is not None:
        lo, hi = _check_range(names["pupil_range_mm"], pupil_range_mm, 0.0, MAX_PUPIL_MM,
                              "Pupil diameters in mm; a human pupil is about 2 to 8 mm across.",
                              positive=True)
        if not _inside(nominal_pupil_mm, lo, hi):
            raise ValueError(
                f"{names['pupil']} = {nominal_pupil_mm!r} is outside {names['pupil_range_mm']} "
                f"= {pupil_range_mm!r}; allowed: lo <= nominal <= hi. Widen the range or move "
                "the nominal pupil into it."
            )
    if focus_range_diopters is not None:
        lo, hi = _check_range(names["focus_range_diopters"], focus_range_diopters, 0.0, math.inf,
                              "Give finite diopters (1000 / focus distance in mm, 0 = "
                              "infinity), the lower first, e.g. [0, 2].")
        fixed = lo == hi and _inside(nominal_focus_diopters, lo, hi)
        if hi > MAX_ACCOMMODATION_DIOPTERS and not fixed:
            raise ValueError(
                f"{names['focus_range_diopters']} = {focus_range_diopters!r} is out of range; "
                f"allowed: 0 <= lo <= hi <= {MAX_ACCOMMODATION_DIOPTERS:g} diopters (1000 / "
                "focus distance in mm, 0 = infinity; a human eye accommodates by at most about "
                "10 D). A fixed focus nearer than that: give the same value twice."
            )
        if not _inside(nominal_focus_diopters, lo, hi):
            raise ValueError(
                f"{names['focus']} is {nominal_focus_diopters:.6g} diopters, outside "
                f"{names['focus_range_diopters']} = {focus_range_diopters!r}; allowed: lo <= "
                "nominal <= hi (diopters = 1000 / focus distance in mm, 0 = infinity). Widen "
                "the range or move the nominal focus into it."
            )
    check_number(names["gaze_deg"], gaze_deg, 0.0, MAX_GAZE_DEG,
                  "The largest gaze rotation from straight ahead in degrees; 0: no gaze.")
    check_number(names["rotation_mm"], rotation_mm, 0.0, MAX_ROTATION_MM,
                  "Pupil to the eye's centre of rotation, about 10 to 13 mm (default 11).")
