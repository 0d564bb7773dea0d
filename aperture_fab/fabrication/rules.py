"""The process rules a hole layout breaks as it is: for a part edited by hand, where nothing is
resolved (quantization resolves what it breaks itself; see aperture_fab.fabrication.quantize)."""

from __future__ import annotations

import numpy as np

from aperture_fab.fabrication.layout import HoleLayout, Violation
from aperture_fab.fabrication.process import Process, UnmakeableError, check_plate
from aperture_fab.optics.scene import Plate

__all__ = ["layout_violations"]

#: Slack for the rule checks of a hand-made layout: 10 nm, far below any process, above the
#: rounding of a hole table (1 nm) and of float32 STL coordinates.
RULE_TOL_MM = 1e-5
#: Above this many cells breaking one rule, one aggregated Violation is recorded instead.
MAX_CELL_VIOLATIONS = 50
UNRESOLVED = "not changed: validated as given"


def _hole_webs(layout: HoleLayout, z_mm: float) -> np.ndarray:
    """(K,) the thinnest web of each hole at height z_mm above mid-thickness: to its eight
    neighbours and to the outline."""
    nx, ny = layout.grid
    rows, cols = layout.cells[:, 0], layout.cells[:, 1]
    slot = np.full((ny, nx), -1, dtype=np.int64)
    slot[rows, cols] = np.arange(layout.count)
    x = layout.centres_mm[:, 0] + z_mm * layout.axes[:, 0]
    y = layout.centres_mm[:, 1] + z_mm * layout.axes[:, 1]
    r = layout.radii_mm
    half_w, half_h = layout.outline_mm[0] / 2, layout.outline_mm[1] / 2
    webs = np.minimum(half_w - np.abs(x) - r, half_h - np.abs(y) - r)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            if di == dj == 0:
                continue
            nr, nc = rows + di, cols + dj
            inside = (nr >= 0) & (nr < ny) & (nc >= 0) & (nc < nx)
            other = np.full(layout.count, -1, dtype=np.int64)
            other[inside] = slot[nr[inside], nc[inside]]
            has = other >= 0
            o = other[has]
            gap = np.hypot(x[has] - x[o], y[has] - y[o]) - r[has] - r[o]
            webs[has] = np.minimum(webs[has], gap)
    return webs


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
    webs = np.minimum(_hole_webs(layout, -t / 2), _hole_webs(layout, t / 2))
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
