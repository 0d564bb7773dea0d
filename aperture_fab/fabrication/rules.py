"""Process rules: what a process allows in a plate, and which rules a hole layout breaks.

What a process allows: each number derived from a process and a plate is computed here, once.
The thickness rules themselves are the process's (Process.min_hole_for, Process.min_web_for);
from them come the pitch that fits the smallest hole plus a web (min_pitch_mm), the radius range
of a cell (hole_radius_bounds, open_fraction_bounds; radius_range for quantization, relaxed when
forced past a pitch no hole fits), and the outline margin (resolve_margin_mm). check_plate
refuses a plate the process cannot make at all, naming the presets that could and the plate
settings with which this process could (makeable_settings).

Which rules a layout breaks (layout_violations): for a part edited by hand, where nothing is
resolved (quantization resolves what it breaks itself; see aperture_fab.fabrication.quantize).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from aperture_fab.fabrication.layout import HoleLayout, Violation, face_webs
from aperture_fab.fabrication.process import PROCESSES, Process, UnmakeableError
from aperture_fab.optics.scene import Plate, open_fraction_of

__all__ = [
    "RadiusRange",
    "check_plate",
    "hole_radius_bounds",
    "layout_violations",
    "makeable_processes",
    "makeable_settings",
    "min_pitch_mm",
    "open_fraction_bounds",
    "radius_range",
    "resolve_margin_mm",
]

#: Slack for the rule checks of a hand-made layout: 10 nm, far below any process, above the
#: rounding of a hole table (1 nm) and of float32 STL coordinates.
RULE_TOL_MM = 1e-5
#: Above this many cells breaking one rule, one aggregated Violation is recorded instead.
MAX_CELL_VIOLATIONS = 50
UNRESOLVED = "not changed: validated as given"
#: Smallest default margin around the cell grid.
MIN_MARGIN_MM = 1.0
#: When forced past a pitch no hole fits, holes may grow to this share of the pitch (radius).
FORCED_MAX_RADIUS_FRACTION = 0.45
#: A pitch that makeable_settings grows holds holes up to this many times the smallest hole's
#: diameter: at the bare minimum pitch every hole would be the smallest one (a regular array,
#: nothing left to design), and a chief-ray hole's tilted top face would have no room at all.
SUGGESTED_SIZE_RANGE = 1.5
#: makeable_settings rounds a grown pitch up to this step, mm.
SUGGESTED_PITCH_STEP_MM = 0.01


def _largest_radius_mm(pitch_mm: float, web_mm: float) -> float:
    """Largest hole radius (mm) that keeps half a web inside a cell of this pitch, so that
    neighbours (diagonals too) keep the whole web between them."""
    return pitch_mm / 2 - web_mm / 2


def min_pitch_mm(process: Process, thickness_mm: float) -> float:
    """Smallest cell pitch that holds the smallest hole plus one web."""
    return process.min_hole_for(thickness_mm) + process.min_web_for(thickness_mm)


def hole_radius_bounds(process: Process, plate: Plate, pitch_scale: float = 1.0
                       ) -> tuple[float, float]:
    """(smallest makeable radius, largest radius that keeps the web) in mm, straight holes, with
    the plate's pitch scaled by pitch_scale.

    The largest may be below the smallest: then no hole fits (see check_plate).
    """
    t = plate.thickness_mm
    r_min = process.min_hole_for(t) / 2
    r_max = _largest_radius_mm(min(plate.pitch_mm) * pitch_scale, process.min_web_for(t))
    return r_min, r_max


def open_fraction_bounds(process: Process, plate: Plate) -> tuple[float, float]:
    """(a_min, a_max): open-area fractions of the smallest and largest makeable holes.

    a = pi r^2 / (px py). A cell is either closed (0) or within [a_min, a_max]. Both are 0
    when no hole fits the cell.
    """
    r_min, r_max = hole_radius_bounds(process, plate)
    if r_max < r_min:
        return 0.0, 0.0
    return (float(open_fraction_of(r_min, plate.pitch_mm)),
            float(open_fraction_of(r_max, plate.pitch_mm)))


@dataclass(frozen=True)
class RadiusRange:
    """The hole radii quantization may make in a cell of a plate, mm.

    lo_mm: smallest radius. hi_mm: largest radius of a straight hole. web_mm: the web kept
    between holes and to the outline. The process's rules, or, only when forced past a pitch no
    hole fits, relaxed to what the cell geometry allows (hi_mm = FORCED_MAX_RADIUS_FRACTION x
    pitch, web_mm what that leaves).
    """

    lo_mm: float
    hi_mm: float
    web_mm: float

    def cell_max_mm(self, plate: Plate, face_scale: float = 1.0) -> float:
        """The largest radius (mm) that keeps half a web inside the cell at a face whose grid is
        the mid-plane grid scaled by face_scale (chief-ray holes' top face: 1 - t / 2D)."""
        return min(_largest_radius_mm(min(plate.pitch_mm) * face_scale, self.web_mm),
                   self.hi_mm)


def radius_range(process: Process, plate: Plate) -> RadiusRange:
    """The radii a cell allows (see RadiusRange); relaxed only when no hole fits the pitch."""
    r_lo, r_hi = hole_radius_bounds(process, plate)
    min_web = process.min_web_for(plate.thickness_mm)
    if r_hi < r_lo:
        cap = FORCED_MAX_RADIUS_FRACTION * min(plate.pitch_mm)
        r_lo, r_hi = min(r_lo, cap), max(r_hi, cap)
        min_web = min(plate.pitch_mm) - 2 * r_hi
    return RadiusRange(r_lo, r_hi, min_web)


def resolve_margin_mm(web_mm: float, overhang_mm: float, requested_mm: float | None = None
                      ) -> float:
    """The solid margin around the (mid-plane) cell grid on each side, mm.

    requested_mm, or by default max(MIN_MARGIN_MM, 2 x web + overhang). overhang_mm: how far a
    face's scaled grid reaches past the mid-plane grid (0 for straight holes). With the half web
    each hole keeps inside its cell, a margin of overhang + half a web keeps the whole web to the
    outline at both faces; a smaller requested_mm raises ValueError.
    """
    least_margin = overhang_mm + web_mm / 2
    if requested_mm is None:
        margin = max(MIN_MARGIN_MM, 2 * web_mm + overhang_mm)
    else:
        margin = requested_mm
    if not (math.isfinite(margin) and margin >= least_margin):
        raise ValueError(
            f"outline_margin_mm = {margin!r} is too small; allowed: >= {least_margin:.3g} mm "
            f"(with the half web inside the cell it keeps the {web_mm:.3g} mm edge web at both "
            f"faces; chief-ray holes' scaled grid reaches {overhang_mm:.3g} mm past the cell grid)."
        )
    return margin


def makeable_processes(plate: Plate, exclude: str = "") -> list[str]:
    """Names of the presets that accept the plate's thickness and fit a hole in its cells."""
    names = []
    for name, p in PROCESSES.items():
        if name == exclude or not p.accepts_thickness(plate.thickness_mm):
            continue
        if min_pitch_mm(p, plate.thickness_mm) <= min(plate.pitch_mm):
            names.append(name)
    return names


def _pitch_alternatives(plate: Plate, exclude: str) -> str:
    """Which presets could make the plate's pitch: at its thickness, else at another one."""
    here = makeable_processes(plate, exclude)
    if here:
        return f"processes that can make it at {plate.thickness_mm:g} mm: {', '.join(here)}"
    pitch = min(plate.pitch_mm)
    elsewhere = []
    for name, p in PROCESSES.items():
        lo, hi = p.thickness_range_mm
        if name == exclude or min_pitch_mm(p, lo) > pitch:
            continue
        # The rules grow with thickness: bisect for the thickest plate that still fits.
        good, bad = lo, hi
        if min_pitch_mm(p, hi) <= pitch:
            good = hi
        else:
            for _ in range(40):
                mid = (good + bad) / 2
                good, bad = (mid, bad) if min_pitch_mm(p, mid) <= pitch else (good, mid)
        elsewhere.append(f"{name} (thickness {lo:g} to {good:.3g} mm)")
    if elsewhere:
        return (f"no process makes it at {plate.thickness_mm:g} mm thickness; at another "
                f"thickness: {', '.join(elsewhere)}")
    return "no preset process can make cells this small"


def _smallest_made_diameter_mm(process: Process, thickness_mm: float) -> float:
    """The smallest hole diameter (mm) the process makes in a plate of this thickness: its
    minimum, rounded up to its radius step or to its next available size."""
    d = process.min_hole_for(thickness_mm)
    if process.hole_sizes_mm:
        return min((size for size in process.hole_sizes_mm if size >= d), default=d)
    step = process.radius_step_mm
    return 2 * math.ceil(d / 2 / step - 1e-9) * step if step > 0 else d


def makeable_settings(process: Process, plate: Plate, eye_relief_mm: float | None = None
                      ) -> dict[str, Any]:
    """The plate settings to change, as dotted config keys, so that `process` can make the
    plate; {} when it can as it is. The rest of the plate is kept.

    A thickness outside the process's range moves to the nearest end of it. A pitch too small
    for the smallest hole plus a web grows, both axes by one factor, to hold holes from the
    smallest up to SUGGESTED_SIZE_RANGE x its diameter (rounded up to SUGGESTED_PITCH_STEP_MM),
    and the cell count shrinks so that the grid stays within its former extent (it still fits
    the display and the outline). With eye_relief_mm, chief-ray holes keep room for the smallest
    hole at the top face too, where their grid is 1 - t / (2 (eye relief + t / 2)) of the
    mid-plane's. Those are new design settings: a design's open fractions were optimized for
    its own plate, so they need a new design, not a new export.
    """
    changes: dict[str, Any] = {}
    t = plate.thickness_mm
    if not process.accepts_thickness(t):
        lo, hi = process.thickness_range_mm
        t = lo if t < lo else hi
        changes["plate.thickness_mm"] = t
    top_scale = 1.0
    if plate.hole_axis == "chief_ray" and eye_relief_mm is not None:
        top_scale = 1.0 - t / (2 * (eye_relief_mm + t / 2))
    if min_pitch_mm(process, t) > min(plate.pitch_mm) * top_scale:
        hole, web = _smallest_made_diameter_mm(process, t), process.min_web_for(t)
        room = max(SUGGESTED_SIZE_RANGE * hole + web, (hole + web) / top_scale)
        scale = room / min(plate.pitch_mm)
        step = SUGGESTED_PITCH_STEP_MM
        pitch = [round(math.ceil(p * scale / step - 1e-9) * step, 6) for p in plate.pitch_mm]
        cells = [max(1, math.floor(n * old / new + 1e-9))
                 for n, old, new in zip(plate.cells, plate.pitch_mm, pitch, strict=True)]
        changes["plate.pitch_mm"] = pitch
        changes["plate.cells"] = cells
    return changes


def _settings_text(process: Process, plate: Plate, eye_relief_mm: float | None) -> str:
    """The makeable_settings of a refused plate as a sentence for check_plate's message."""
    changes = makeable_settings(process, plate, eye_relief_mm)
    if not changes:
        return ""
    new = replace(plate, thickness_mm=changes.get("plate.thickness_mm", plate.thickness_mm),
                  pitch_mm=tuple(changes.get("plate.pitch_mm", plate.pitch_mm)),
                  cells=tuple(changes.get("plate.cells", plate.cells)))
    try:
        check_plate(process, new)
    except UnmakeableError:  # not expected (tests check every process); say nothing wrong
        return ""
    keys = ", ".join(f"{key} = {value:g}" if isinstance(value, float) else
                     f"{key} = [{', '.join(f'{v:g}' for v in value)}]"
                     for key, value in changes.items())
    return f"; {process.name} makes the plate designed with {keys} (the rest kept)"


def check_plate(process: Process, plate: Plate, eye_relief_mm: float | None = None) -> None:
    """Raise UnmakeableError (a ValueError) if the process cannot make this plate at all.

    Checks the thickness range and that the smallest hole plus its web fits the cell pitch.
    The message gives the allowed values, the presets that would accept the plate and the
    settings with which this process would (makeable_settings, given eye_relief_mm).
    """
    problems = []
    t = plate.thickness_mm
    if not process.accepts_thickness(t):
        lo, hi = process.thickness_range_mm
        others = [n for n, p in PROCESSES.items()
                  if n != process.name and p.accepts_thickness(t)]
        accept = ", ".join(others) if others else "none of the presets"
        problems.append(
            f"plate.thickness_mm = {t:g} is outside the {process.name} range {lo:g} to {hi:g} mm "
            f"(processes that accept {t:g} mm: {accept}); choose a thickness in range or "
            "another process"
        )
    need = min_pitch_mm(process, t)
    pitch = min(plate.pitch_mm)
    if need > pitch:
        problems.append(
            f"plate.pitch_mm = {plate.pitch_mm} is too small for {process.name}: its smallest "
            f"hole ({process.min_hole_for(t):.3g} mm) plus web ({process.min_web_for(t):.3g} mm) "
            f"needs a pitch of at least {need:.3g} mm (scale the plate by {need / pitch:.3g}x); "
            f"{_pitch_alternatives(plate, process.name)}"
        )
    if problems:
        raise UnmakeableError("; ".join(problems) + _settings_text(process, plate, eye_relief_mm)
                              + ".")


def _cell_rule(rule: str, layout: HoleLayout, broken: np.ndarray, values: np.ndarray,
               limit_mm: float, what: str) -> list[Violation]:
    """One Violation per cell breaking a rule, or one for all beyond MAX_CELL_VIOLATIONS."""
    index = np.flatnonzero(broken)
    if index.size > MAX_CELL_VIOLATIONS:
        worst = int(index[np.argmax(np.abs(values[index] - limit_mm))])
        return [Violation(rule, None, float(values[worst]), limit_mm,
                          f"{index.size} cells {what}; {UNRESOLVED}")]
    return [Violation(rule, (int(layout.cells[k, 0]), int(layout.cells[k, 1])),
                      float(values[k]), limit_mm, f"{what}; {UNRESOLVED}") for k in index]


def layout_violations(layout: HoleLayout, plate: Plate, process: Process
                      ) -> tuple[Violation, ...]:
    """The process rules a layout breaks, as it is (nothing resolved): the plate (thickness,
    pitch), the smallest hole, the web between holes and to the outline at both faces, and the
    allowed sizes (radius step or listed diameters). Values within RULE_TOL_MM pass."""
    found: list[Violation] = []
    t = layout.thickness_mm
    try:
        check_plate(process, plate)
    except UnmakeableError as err:
        found.append(Violation("process", None, t, 0.0, f"{err} {UNRESOLVED}"))
    if layout.count == 0:
        return tuple(found)
    diameters = 2 * layout.radii_mm
    least = process.min_hole_for(t)
    found += _cell_rule("min_hole", layout, diameters < least - RULE_TOL_MM, diameters, least,
                        f"have holes smaller than the {process.name} minimum {least:.4g} mm")
    webs = np.minimum(face_webs(layout, -t / 2).thinnest_mm,
                      face_webs(layout, t / 2).thinnest_mm)
    web = process.min_web_for(t)
    found += _cell_rule("min_web", layout, webs < web - RULE_TOL_MM, webs, web,
                        f"leave less than the {process.name} minimum web {web:.4g} mm")
    if process.hole_sizes_mm:
        sizes = np.asarray(process.hole_sizes_mm)
        off = np.min(np.abs(diameters[:, None] - sizes[None, :]), axis=1)
        found += _cell_rule("size", layout, off > RULE_TOL_MM, diameters, float(sizes[0]),
                            f"have diameters not among the {process.name} sizes "
                            f"{process.hole_sizes_mm} mm")
    elif process.radius_step_mm > 0:
        step = process.radius_step_mm
        off = np.abs(layout.radii_mm - step * np.round(layout.radii_mm / step))
        found += _cell_rule("size", layout, off > RULE_TOL_MM, layout.radii_mm, step,
                            f"have radii off the {process.name} radius step {step:g} mm")
    return tuple(found)
