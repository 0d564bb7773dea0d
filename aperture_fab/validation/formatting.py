"""Numbers and names for people: the report page's rounding and labels.

Pure functions, values in and escaped HTML text out. Numbers are rounded to what they mean:
PSNR 0.1 dB, lengths 3 significant digits, shares as percentages of 2 significant digits;
field names become labels with their unit ("smallest_web_mm" -> "smallest web (mm)").
"""

from __future__ import annotations

import html
import math
from collections.abc import Mapping, Sequence
from typing import Any

__all__ = ["NOT_COMPUTED", "config_rows", "e", "label", "percent", "quantity", "sig", "table"]

NOT_COMPUTED = "not computed"
#: Unit suffixes of field names, longest first: (suffix, unit).
UNITS: tuple[tuple[str, str], ...] = (
    ("_cd_m2", "cd/m²"), ("_deg2", "deg²"), ("_mm3", "mm³"), ("_mm2", "mm²"),
    ("_diopters", "D"), ("_deg", "deg"), ("_db", "dB"), ("_mm", "mm"), ("_um", "µm"),
    ("_td", "td"), ("_s", "s"),
)
#: Words that mark a share (0 to 1), shown as a percentage.
SHARE_WORDS = ("fraction", "share", "efficiency", "yield")
#: Labels that the generic rule gets wrong or could say better.
LABELS: dict[str, str] = {
    "holes": "holes", "genus": "genus (one per hole)", "triangles": "triangles",
    "watertight": "watertight", "process": "process", "pixels": "pixels (x, y)",
    "cells": "cells (x, y)", "pitch_mm": "cell pitch (mm, x, y)", "outline_mm":
    "outline (mm, width, height)", "hole_axis": "hole axis", "fov_deg": "field of view (deg, x, y)",
    "view_pixels": "view pixels (x, y)", "positions_mm": "eye positions (mm)",
    "focus_mm": "focus distance (mm)", "eyebox_mm": "eyebox (mm, width, height)",
    "gaze_deg": "gaze up to (deg)", "rotation_mm": "eye rotation radius (mm)",
    "smallest_hole_diameter_mm": "smallest hole (mm)", "largest_hole_diameter_mm":
    "largest hole (mm)", "open_area_fraction": "open area",
}
SIGNIFICANT = 3


def e(value: Any) -> str:
    """HTML-escaped text of a value."""
    return html.escape(str(value), quote=True)


def sig(value: float, digits: int = SIGNIFICANT) -> str:
    """`value` to `digits` significant digits, without an exponent from 1e-4 to 1e7."""
    if value == 0 or not math.isfinite(value):
        return "0" if value == 0 else str(value)
    exponent = math.floor(math.log10(abs(value)))
    if not -4 <= exponent < 7:
        return f"{value:.{digits - 1}e}"
    decimals = max(digits - 1 - exponent, 0)
    return f"{round(value, decimals):.{decimals}f}"


def percent(share: float | None, digits: int = 2) -> str:
    """A share (0 to 1) as a percentage of `digits` significant digits ("0.13 %")."""
    return NOT_COMPUTED if share is None else f"{sig(100 * share, digits)} %"


def _is_share(key: str) -> bool:
    return any(word in key for word in SHARE_WORDS)


def label(key: str) -> str:
    """A field name as a label with its unit: "view_luminance_cd_m2" -> "view luminance
    (cd/m²)" (shares are shown with their "%")."""
    if key in LABELS:
        return LABELS[key]
    for suffix, unit in UNITS:
        if key.endswith(suffix):
            return f"{key[:-len(suffix)].replace('_', ' ')} ({unit})"
    return key.replace("_", " ")


def quantity(key: str, value: Any) -> str:
    """`value` of the field `key`, rounded to its meaning and escaped: dB to 0.1, shares as
    percentages, other numbers to 3 significant digits, lists on one line, yes / no."""
    if value is None:
        return NOT_COMPUTED
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return e(f"{value:,}" if abs(value) >= 10_000 else value)
    if isinstance(value, float):
        if key.endswith("_db"):
            return f"{value:.1f}"
        return percent(value) if _is_share(key) else sig(value)
    if isinstance(value, Sequence) and not isinstance(value, str):
        return "[" + ", ".join(quantity(key, v) for v in value) + "]"
    if isinstance(value, Mapping):
        return ", ".join(f"{e(k)} {quantity(str(k), v)}" for k, v in value.items())
    return e(value)


def table(header: Sequence[str], rows: Sequence[Sequence[str]], numeric: tuple[int, ...] = ()
          ) -> str:
    """An HTML table; cells are already escaped text; the `numeric` columns align right."""
    out = ["<table><tr>", *(f"<th>{e(h)}</th>" for h in header), "</tr>"]
    for row in rows:
        out.append("<tr>")
        out.extend(f'<td class="n">{c}</td>' if i in numeric else f"<td>{c}</td>"
                   for i, c in enumerate(row))
        out.append("</tr>")
    out.append("</table>")
    return "".join(out)


def _config_value(value: Any) -> str:
    """A config value as given (no rounding: it is what was asked for), lists on one line."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, Sequence):
        return "[" + ", ".join(_config_value(v) for v in value) + "]"
    return str(value)


def config_rows(config: Mapping[str, Any]) -> list[list[str]]:
    """The config as escaped (section, key, value) rows: nested tables as dotted keys, lists
    on one line, top-level scalars in section ""."""
    rows: list[list[str]] = []

    def walk(section: str, prefix: str, block: Mapping[str, Any]) -> None:
        for key, value in block.items():
            if isinstance(value, Mapping):
                walk(section, f"{prefix}{key}.", value)
            else:
                rows.append([e(section), e(prefix + str(key)), e(_config_value(value))])

    for key, value in config.items():
        if isinstance(value, Mapping):
            walk(str(key), "", value)
        else:
            rows.append(["", e(key), e(_config_value(value))])
    return rows
