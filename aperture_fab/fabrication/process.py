"""Fabrication processes: what each way of making the plate can and cannot make.

A `Process` states the smallest hole, the thinnest web of material (between holes and at the
plate's edge), the plate thicknesses it handles, how hole sizes are quantized (a radius step or a
list of discrete diameters) and its tolerances. Some rules scale with the plate's thickness
(photo-etching, laser cutting: "hole >= 1.1 x metal thickness"); `min_hole_for` and
`min_web_for` give the rule at a given thickness. What the rules allow in a given plate (radius
range, pitch, margin) and which rules a layout breaks: aperture_fab.fabrication.rules.

Radii in a `HoleLayout` are the holes as they should come out (the nominal, made holes); the
systematic bias is what the process adds to the radius that is drawn, so `drawn_radii_mm`
gives what to draw to get them. Numbers and their sources: docs/processes.md.
"""

from __future__ import annotations

import dataclasses
import difflib
import itertools
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from aperture_fab.errors import Refused

__all__ = [
    "PROCESSES",
    "Process",
    "UnmakeableError",
    "drawn_radii_mm",
    "process_summary",
    "resolve_process",
]

#: Largest sensible process dimension: beyond this a value is almost surely a unit mistake.
MAX_PROCESS_MM = 100.0

#: LCD pixel of the high-resolution MSLA printers the "resin" preset assumes (Phrozen Sonic
#: Mini 8K: 22 um; Elegoo Saturn 3/4 Ultra 12K: 19 x 24 um), mm.
MSLA_PIXEL_MM = 0.022
#: Smallest through-hole, in pixels: a 4-pixel hole survives light bleed in a thin plate
#: (estimate; calibrate with a hole-ladder test print).
MIN_HOLE_PIXELS = 4
#: Thinnest web between holes, in pixels (estimate).
MIN_WEB_PIXELS = 2
#: Optical density taken for "opaque" material (metal sheet and foil): 10^-6 of the light gets
#: through, which no display-and-eye measurement can tell from zero.
OPAQUE_OPTICAL_DENSITY = 6.0
#: Largest optical density a process may state.
MAX_OPTICAL_DENSITY = 12.0

#: Deepest resin hole per unit diameter (thickness / diameter): uncured resin must wash out of
#: it (estimate).
MAX_HOLE_ASPECT_RATIO = 4.0


class UnmakeableError(Refused, ValueError):
    """The design cannot be made with the chosen process (the message says why and what would)."""


def _check_number(name: str, value: Any, lo: float, hi: float, fix: str,
                  lo_inclusive: bool = True) -> None:
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        raise TypeError(f"process.{name} must be a number, got {value!r} ({type(value).__name__})")
    above = value >= lo if lo_inclusive else value > lo
    if not (math.isfinite(value) and above and value <= hi):
        low = f"{lo:g} <=" if lo_inclusive else f"{lo:g} <"
        raise ValueError(
            f"process.{name} = {value!r} is out of range; allowed: {low} {name} <= {hi:g}. {fix}"
        )


@dataclass(frozen=True)
class Process:
    """A fabrication process and its design rules. Millimetres throughout.

    name: short key, e.g. "etched-foil".
    description: one line for people.
    min_hole_mm: smallest hole diameter that comes out open and round.
    min_web_mm: thinnest material between neighbouring holes and between a hole and the edge.
    thickness_range_mm: (lo, hi) plate thicknesses the process handles.
    radius_step_mm: hole radii are whole multiples of this (0 = any radius). Exclusive with
        hole_sizes_mm.
    hole_sizes_mm: the only hole diameters available (drills, punches), ascending; () = any.
    radius_bias_mm: systematic error: made radius = drawn radius + bias (negative: holes come
        out small).
    radius_sigma_mm: random radius error, one standard deviation.
    position_sigma_mm: random hole-position error per axis, one standard deviation.
    min_hole_per_thickness: the smallest hole is also at least this times the thickness.
    min_web_per_thickness: the thinnest web is also at least this times the thickness.
    sources: where the numbers come from ("estimate" where nothing was found).
    optical_density: the plate material's optical density at the process's typical plate
        thickness: the solid plate passes 10^-optical_density of the light (the report weighs
        that leakage against the light through the holes). Metal: opaque
        (OPAQUE_OPTICAL_DENSITY). Override with [process] optical_density after measuring a
        blank of the plate's thickness.
    optical_density_note: where the optical density comes from ("estimate" when it is one).
    """

    name: str
    description: str
    min_hole_mm: float
    min_web_mm: float
    thickness_range_mm: tuple[float, float]
    radius_step_mm: float = 0.0
    hole_sizes_mm: tuple[float, ...] = ()
    radius_bias_mm: float = 0.0
    radius_sigma_mm: float = 0.0
    position_sigma_mm: float = 0.0
    min_hole_per_thickness: float = 0.0
    min_web_per_thickness: float = 0.0
    sources: tuple[str, ...] = ()
    optical_density: float = OPAQUE_OPTICAL_DENSITY
    optical_density_note: str = "not given: taken as opaque"

    def __post_init__(self) -> None:
        if not (isinstance(self.name, str) and self.name.strip()):
            raise ValueError(f"process.name = {self.name!r} must be a non-empty string.")
        if not isinstance(self.description, str):
            raise TypeError(f"process.description must be a string, got {self.description!r}")
        _check_number("min_hole_mm", self.min_hole_mm, 0.0, MAX_PROCESS_MM,
                      "Give the smallest hole diameter in mm, e.g. 0.5.", lo_inclusive=False)
        _check_number("min_web_mm", self.min_web_mm, 0.0, MAX_PROCESS_MM,
                      "Give the thinnest web of material in mm, e.g. 0.4.", lo_inclusive=False)
        rng = self.thickness_range_mm
        if not (isinstance(rng, tuple) and len(rng) == 2):
            raise TypeError(f"process.thickness_range_mm must be a pair (lo, hi), got {rng!r}")
        for value in rng:
            _check_number("thickness_range_mm", value, 0.0, MAX_PROCESS_MM,
                          "Give the thinnest and thickest plate in mm.", lo_inclusive=False)
        if rng[0] > rng[1]:
            raise ValueError(
                f"process.thickness_range_mm = {rng} has lo > hi; give (lo, hi), e.g. (0.4, 10)."
            )
        _check_number("radius_step_mm", self.radius_step_mm, 0.0, MAX_PROCESS_MM,
                      "Use 0 for any radius, or the radius increment in mm.")
        if not isinstance(self.hole_sizes_mm, tuple):
            raise TypeError(
                f"process.hole_sizes_mm must be a tuple of diameters, got {self.hole_sizes_mm!r}"
            )
        for size in self.hole_sizes_mm:
            _check_number("hole_sizes_mm", size, 0.0, MAX_PROCESS_MM,
                          "Give hole diameters in mm.", lo_inclusive=False)
        sizes = self.hole_sizes_mm
        if any(b <= a for a, b in itertools.pairwise(sizes)):
            raise ValueError(
                f"process.hole_sizes_mm = {sizes} must be strictly ascending without repeats."
            )
        if sizes and sizes[-1] < self.min_hole_mm:
            raise ValueError(
                f"process.hole_sizes_mm = {sizes} are all below min_hole_mm = {self.min_hole_mm}; "
                "give at least one size the process can make."
            )
        if sizes and self.radius_step_mm > 0:
            raise ValueError(
                f"process {self.name!r} sets both radius_step_mm = {self.radius_step_mm} and "
                f"hole_sizes_mm = {sizes}; use one: set radius_step_mm = 0 for discrete sizes."
            )
        _check_number("radius_bias_mm", self.radius_bias_mm, -self.min_hole_mm / 2,
                      MAX_PROCESS_MM, "A bias below -min_hole/2 would close the smallest hole.",
                      lo_inclusive=False)
        _check_number("radius_sigma_mm", self.radius_sigma_mm, 0.0, MAX_PROCESS_MM,
                      "Give one standard deviation in mm (0 = exact).")
        _check_number("position_sigma_mm", self.position_sigma_mm, 0.0, MAX_PROCESS_MM,
                      "Give one standard deviation in mm (0 = exact).")
        _check_number("min_hole_per_thickness", self.min_hole_per_thickness, 0.0, 100.0,
                      "Use 0 when the smallest hole does not depend on thickness.")
        _check_number("min_web_per_thickness", self.min_web_per_thickness, 0.0, 100.0,
                      "Use 0 when the thinnest web does not depend on thickness.")
        if not (isinstance(self.sources, tuple) and all(isinstance(s, str) for s in self.sources)):
            raise TypeError(f"process.sources must be a tuple of strings, got {self.sources!r}")
        _check_number("optical_density", self.optical_density, 0.0, MAX_OPTICAL_DENSITY,
                      "Give the plate material's optical density at the plate's thickness "
                      "(log10 of incident / transmitted light; metal: "
                      f"{OPAQUE_OPTICAL_DENSITY:g}).",
                      lo_inclusive=False)
        if not isinstance(self.optical_density_note, str):
            raise TypeError("process.optical_density_note must be a string, got "
                            f"{self.optical_density_note!r}")

    def min_hole_for(self, thickness_mm: float) -> float:
        """Smallest hole diameter (mm) in a plate of this thickness."""
        return max(self.min_hole_mm, self.min_hole_per_thickness * thickness_mm)

    def min_web_for(self, thickness_mm: float) -> float:
        """Thinnest web (mm) in a plate of this thickness."""
        return max(self.min_web_mm, self.min_web_per_thickness * thickness_mm)

    def accepts_thickness(self, thickness_mm: float) -> bool:
        lo, hi = self.thickness_range_mm
        return lo <= thickness_mm <= hi


PROCESSES: dict[str, Process] = {
    p.name: p
    for p in (
        Process(
            name="resin",
            description="High-resolution MSLA resin printing (8K-12K LCD, ~22 um pixels) of thin "
                        "pierced plates, hole axis along the build direction",
            min_hole_mm=MIN_HOLE_PIXELS * MSLA_PIXEL_MM,
            min_web_mm=MIN_WEB_PIXELS * MSLA_PIXEL_MM,
            thickness_range_mm=(0.2, 10.0),
            radius_step_mm=MSLA_PIXEL_MM / 2,
            radius_bias_mm=-0.01,
            radius_sigma_mm=0.008,
            position_sigma_mm=MSLA_PIXEL_MM / 2,
            min_hole_per_thickness=1 / MAX_HOLE_ASPECT_RATIO,
            sources=(
                "Pixel 0.022 mm: UVtools printer table (github.com/sn4k3/UVtools, "
                "UVtools.Core/Printer/Machine.cs): Phrozen Sonic Mini 8K 7500 x 3240 px on "
                "165 x 71.28 mm = 22 um; Elegoo Saturn 3 Ultra / Saturn 4 Ultra 12K "
                "11520 x 5120 px on 218.88 x 122.88 mm = 19 x 24 um (Elegoo Saturn 8K: 28.5 um, "
                "coarser than this preset assumes)",
                "Min hole 4 pixels (0.088 mm) through a thin plate: estimate, calibrate with a "
                "hole-ladder test print; consumer MSLA made ~75 um mould features and ~200 um "
                "embedded channels (Ahmed, Sullivan & Priye, Biosensors 12(8) 652, 2022); "
                "light bleed closes negative features first (Turek et al., Appl. Sci. 15 7412, "
                "2025; Reid et al., 3D Print. Addit. Manuf. 11(2) 517, 2024)",
                "Min hole also >= thickness / 4 (uncured resin must wash out of the hole): "
                "estimate; at 2 mm it gives the generic 0.5 mm of the Formlabs SLA design guide",
                "Min web 2 pixels (0.044 mm): estimate",
                "Thickness 0.2 to 10 mm: estimate (0.2 mm = 4 layers of 0.05 mm)",
                "Radius step half a pixel (0.011 mm, anti-aliased edges): estimate",
                "Holes print undersize by light bleed (Turek et al. 2025; blog.honzamrazek.cz "
                "2022/06 exposure bleeding): bias -0.01 mm estimate",
                "Calibrated MSLA parts come out within about one pixel (blog.honzamrazek.cz "
                "2022/06): radius sigma 0.008 mm, position sigma half a pixel (estimates)",
            ),
            optical_density=2.0,
            optical_density_note=(
                "estimate for black pigmented resin about 0.3 mm thick (the near-eye plate): a "
                "cure penetration depth of 0.05 to 0.1 mm, typical of pigmented resins, gives "
                "OD 1.3 to 2.6 at 0.3 mm by Beer-Lambert; thinner plates leak more, thicker "
                "less. Measure a printed blank and set [process] optical_density"),
        ),
        Process(
            name="fdm",
            description="FDM / FFF printing with a 0.4 mm nozzle (cannot make pinholes)",
            min_hole_mm=1.0,
            min_web_mm=0.8,
            thickness_range_mm=(0.4, 10.0),
            radius_bias_mm=-0.1,
            radius_sigma_mm=0.05,
            position_sigma_mm=0.1,
            sources=(
                "Min hole: estimate between the slicer limit (a 0.4 mm nozzle closes holes under "
                "about 0.6 mm, docs/design.md) and design guides (blog.my3dpm.com FDM design "
                "table: avoid holes under 2 mm; arti90.com: 2 mm)",
                "blog.my3dpm.com: minimum wall 0.8 mm (two 0.4 mm perimeters); "
                "3dservicesusa.com: FDM minimum wall 0.8 mm",
                "Min thickness 0.4 mm = two 0.2 mm layers (estimate)",
                "Vertical holes print undersize (blog.my3dpm.com); bias size: estimate",
                "Tolerance +-0.2 mm (prints.artrovogundam.com standard tier, arti90.com) read as "
                "2 sigma -> radius sigma 0.05 mm, position sigma 0.1 mm",
            ),
            optical_density=3.0,
            optical_density_note=(
                "estimate for black PLA about 1 mm thick (carbon-black filled; thin walls glow "
                "against a bright panel). Measure a printed blank and set [process] "
                "optical_density"),
        ),
        Process(
            name="laser",
            description="Laser-cut sheet (fiber laser on thin metal, CO2 on acrylic)",
            min_hole_mm=0.2,
            min_web_mm=0.2,
            thickness_range_mm=(0.1, 3.0),
            radius_sigma_mm=0.025,
            position_sigma_mm=0.05,
            min_hole_per_thickness=1.0,
            min_web_per_thickness=1.0,
            sources=(
                "snijlab.nl kerf width: kerf about 0.2 mm; the smallest hole is about the kerf",
                "tuanthinh.net sheet-metal rules: hole >= t, web between cuts >= t "
                "(acutelaser.com.au: 0.7 t)",
                "smslaserfab.com: the CAM programmer applies kerf compensation -> bias 0",
                "acutelaser.com.au: accuracy about 0.1 mm at 0.5 mm thickness -> radius sigma "
                "0.025 mm, position sigma 0.05 mm (estimate from it)",
                "Thickness range 0.1-3 mm: estimate",
            ),
            optical_density=OPAQUE_OPTICAL_DENSITY,
            optical_density_note=(
                "metal: opaque. Black acrylic (CO2 laser) transmits more: set [process] "
                "optical_density from its datasheet"),
        ),
        Process(
            name="etched-foil",
            description="Photo-chemically etched metal foil (stainless steel, brass)",
            min_hole_mm=0.076,
            min_web_mm=0.076,
            thickness_range_mm=(0.025, 0.5),
            radius_sigma_mm=0.005,
            position_sigma_mm=0.006,
            min_hole_per_thickness=1.1,
            min_web_per_thickness=1.0,
            sources=(
                "techetch.com flat-parts design guide: hole >= 1.1 x metal thickness, min "
                "0.003 in (0.076 mm); web >= metal thickness",
                "metaletching.com technical guidelines: same hole rule; web >= T, min 0.003 in; "
                "centre-to-centre +-0.0005 in up to 1 in -> position sigma 0.006 mm",
                "etchform.com design rules: thickness 0.003-1.5 mm standard; stainless dam 1 T, "
                "slot 1.2 T; tolerance +-10 % of T, min +-0.01 mm -> radius sigma 0.005 mm "
                "(2 sigma on a diameter at T about 0.2 mm)",
                "Thickness range narrowed to 0.025-0.5 mm for pinhole plates (estimate)",
            ),
            optical_density=OPAQUE_OPTICAL_DENSITY,
            optical_density_note="metal: opaque",
        ),
        Process(
            name="photomask",
            description="Printed photomask film (emulsion on 0.18 mm polyester, 20k dpi plotter)",
            min_hole_mm=0.025,
            min_web_mm=0.016,
            thickness_range_mm=(0.005, 0.25),
            radius_sigma_mm=0.002,
            position_sigma_mm=0.005,
            sources=(
                "jd-photodata.co.uk film resolutions: 20k dpi resolves 16 um lines; circles and "
                "spots distort near the limit -> min hole 25 um (estimate), min web 16 um",
                "jd-photodata.co.uk polyester: 0.18 mm base + 0.005 mm emulsion; the opaque "
                "layer is the emulsion, so 0.005-0.25 mm are accepted",
                "Radius and position sigma: estimates (polyester has low dimensional stability)",
            ),
            optical_density=4.0,
            optical_density_note=(
                "silver-halide film emulsion: maximum density about 4 (typical of phototooling "
                "film; estimate, check the bureau's datasheet). A chrome-on-glass mask is "
                "about 3"),
        ),
    )
}

_TUPLE_FIELDS = ("thickness_range_mm", "hole_sizes_mm", "sources")
#: How the report uses a process's optical density, for `aperture-fab processes`.
LEAKAGE_MODEL = (
    "light through the solid plate, as a share of the light through the holes: "
    "10^-OD x (1 - open share of the plate) / light efficiency (a uniform veil; neglects "
    "scatter off the hole walls, reflections and the display's own black level)")


def resolve_process(name: str, overrides: Mapping[str, Any] | None = None) -> Process:
    """The preset called `name`, with fields replaced by `overrides` (validated).

    Giving non-empty hole_sizes_mm without radius_step_mm sets radius_step_mm to 0.
    """
    if name not in PROCESSES:
        close = difflib.get_close_matches(name, list(PROCESSES), n=1)
        hint = f" Did you mean {close[0]!r}?" if close else ""
        raise ValueError(
            f"process = {name!r} is not a known process; choose one of "
            f"{', '.join(PROCESSES)}.{hint}"
        )
    base = PROCESSES[name]
    if not overrides:
        return base
    fields = [f.name for f in dataclasses.fields(Process) if f.name != "name"]
    changes: dict[str, Any] = {}
    for key, value in overrides.items():
        if key not in fields:
            close = difflib.get_close_matches(key, fields, n=1)
            hint = f" Did you mean {close[0]!r}?" if close else ""
            raise ValueError(
                f"process override {key!r} is not a process field; allowed: "
                f"{', '.join(fields)}.{hint}"
            )
        changes[key] = tuple(value) if key in _TUPLE_FIELDS and isinstance(value, list) else value
    if changes.get("hole_sizes_mm") and "radius_step_mm" not in changes:
        changes["radius_step_mm"] = 0.0
    return dataclasses.replace(base, **changes)


def process_summary(p: Process) -> str:
    """A few lines describing the process, for `aperture-fab processes`."""
    lo, hi = p.thickness_range_mm
    hole = f"{p.min_hole_mm:g} mm"
    if p.min_hole_per_thickness:
        hole += f" or {p.min_hole_per_thickness:g} x thickness, whichever is larger"
    web = f"{p.min_web_mm:g} mm"
    if p.min_web_per_thickness:
        web += f" or {p.min_web_per_thickness:g} x thickness, whichever is larger"
    if p.hole_sizes_mm:
        sizes = "diameters " + ", ".join(f"{d:g}" for d in p.hole_sizes_mm) + " mm only"
    elif p.radius_step_mm > 0:
        sizes = f"radius in steps of {p.radius_step_mm:g} mm"
    else:
        sizes = "any radius"
    lines = [
        f"{p.name}: {p.description}",
        f"  smallest hole: {hole}",
        f"  thinnest web:  {web}",
        f"  thickness:     {lo:g} to {hi:g} mm",
        f"  hole sizes:    {sizes}",
        f"  tolerances:    radius bias {p.radius_bias_mm:+g} mm, radius sigma "
        f"{p.radius_sigma_mm:g} mm, position sigma {p.position_sigma_mm:g} mm",
        f"  optical density: {p.optical_density:g} ({p.optical_density_note})",
        f"  leakage model:   {LEAKAGE_MODEL}",
    ]
    lines += [f"  source: {s}" for s in p.sources]
    return "\n".join(lines)


def drawn_radii_mm(process: Process, radii_mm: np.ndarray) -> np.ndarray:
    """Radii to draw (CAD, mask) so that holes come out at radii_mm: drawn = made - bias."""
    drawn = np.asarray(radii_mm, dtype=np.float64) - process.radius_bias_mm
    if drawn.size and not np.all(drawn > 0):
        raise ValueError(
            f"process {process.name!r}: radius_bias_mm = {process.radius_bias_mm} leaves a "
            f"drawn radius of {float(drawn.min()):.3g} mm <= 0; holes this small cannot be "
            "compensated."
        )
    return drawn
