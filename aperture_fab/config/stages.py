"""The tables of the stages after the optimizer, typed and read once with the config:

    [process]     name = "photomask" (`aperture-fab processes`), and any of its fields replaced
    [fabrication] force, step, alignment_cut, svg_polarity = "holes_black" | "holes_white"
    [validation]  tolerance_samples, threshold_db, gap_sigma_mm, eye_sigma_mm, tilt_sigma_deg,
                  mesh_samples, diffraction, seed, eye_states, made_copies
    [photometry]  panel_luminance_cd_m2, observer_age_years, adapted_eyes
    [part]        outline_mm (what a design recorded of the plate it built; not read back)

`read_tables` turns the merged tables into `FabricationSettings`, `ValidationSettings` and
`PhotometrySettings`; `written_tables` gives them back as a config file writes them. Flags change
a setting with `with_flags`, never by editing tables.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

from aperture_fab.fabrication.process import PROCESSES, Process, resolve_process

__all__ = [
    "TABLES",
    "FabricationSettings",
    "ValidationSettings",
    "PhotometrySettings",
    "read_tables",
    "written_tables",
]

#: The stage tables a config may hold, in the order a written config gives them.
TABLES = ("validation", "photometry", "process", "fabrication", "part")
#: The process of a config that names none.
UNNAMED_PROCESS = "resin"

SvgPolarity = Literal["holes_black", "holes_white"]
SVG_POLARITIES: tuple[SvgPolarity, ...] = ("holes_black", "holes_white")


def _process_changes(process: Process) -> dict[str, Any]:
    """The fields of `process` that differ from the catalog's process of its name."""
    base = PROCESSES.get(process.name)
    return {f.name: getattr(process, f.name) for f in dataclasses.fields(process)
            if f.name != "name" and (base is None or getattr(process, f.name)
                                     != getattr(base, f.name))}


@dataclass(frozen=True)
class FabricationSettings:
    """How the part is made ([process] and [fabrication]).

    process: the fabrication process (rules and tolerances).
    force: write parts the process cannot make, with the violations recorded.
    step: also write a STEP B-rep.
    alignment_cut: chamfer the outline's top-left corner so the plate goes one way round.
    svg_polarity: "holes_black" (holes drawn black on white) or "holes_white".
    """

    process: Process = field(default_factory=lambda: PROCESSES[UNNAMED_PROCESS])
    force: bool = False
    step: bool = False
    alignment_cut: bool = True
    svg_polarity: SvgPolarity = "holes_black"

    def __post_init__(self) -> None:
        if self.svg_polarity not in SVG_POLARITIES:
            raise ValueError(f"fabrication.svg_polarity = {self.svg_polarity!r}; use holes_black "
                             "or holes_white.")

    def with_flags(self, process: str | None = None, force: bool | None = None,
                   step: bool | None = None) -> FabricationSettings:
        """These settings with the flags given (None: not given): --process names another
        process, given the fields this one changes from its catalog entry; --force, --step."""
        changes: dict[str, Any] = {k: v for k, v in (("force", force), ("step", step))
                                   if v is not None}
        if process is not None:
            changes["process"] = resolve_process(process, _process_changes(self.process))
        return dataclasses.replace(self, **changes)


#: Default yield threshold: this far below the part's own figure without errors.
YIELD_MARGIN_DB = 3.0
#: Largest plate-tilt sigma: beyond a few degrees the plate is not seated (an assembly fault,
#: not a tolerance) and the small-tilt model of the tolerance analysis no longer holds.
MAX_TILT_SIGMA_DEG = 5.0
#: Eye states of the evaluation set over the eye distribution (Halton points).
EVALUATION_STATES = 32
#: Made copies (draws of the process's errors) a part is judged over.
MADE_COPIES = 4
#: An example of each number of [validation], for messages.
VALIDATION_EXAMPLES = {"gap_sigma_mm": "0.1", "eye_sigma_mm": "1.0", "tilt_sigma_deg": "0.5",
                       "threshold_db": "20.0"}
#: The most of each count a validation takes: beyond these a run takes hours for no visible
#: gain, so a larger value is a typo (an extra zero), refused before any work rather than
#: left to run as if hung.
MAX_COUNTS: dict[str, int] = {
    "tolerance_samples": 10_000,
    "mesh_samples": 4096,  # rays per (view pixel, hole) pair; the default budget gives 12 to 256
    "eye_states": 4096,
    "made_copies": 1000,
}


@dataclass(frozen=True)
class ValidationSettings:
    """How much validation to do ([validation]).

    tolerance_samples: Monte Carlo samples of the tolerance analysis (0 skips it).
    threshold_db: PSNR that counts as a good part for the yield; None: the part's own figure
        without errors (as built, judged like the samples) minus YIELD_MARGIN_DB.
    gap_sigma_mm: assembly error of the display-to-plate gap (1 sigma).
    tilt_sigma_deg: assembly tilt of the plate against the display (1 sigma of the angle, about
        an in-plane axis of uniformly random direction through the plate's centre), degrees,
        0 to MAX_TILT_SIGMA_DEG. The default 0.5 is a plate seated by hand on spacers: two
        supports 20 mm apart whose heights each err by the gap sigma (0.1 mm) differ by
        0.14 mm, 0.4 deg.
    eye_sigma_mm: eye position error across the eyebox (1 sigma, each axis).
    mesh_samples: rays per (view pixel, hole) pair for the mesh re-trace (0 skips it; None:
        a budget of about retrace_sampling.RAY_BUDGET rays, 12 to 256 per pair).
    diffraction: render the diffraction-aware view.
    seed: random seed (random mask, tolerance samples, ray sampling).
    eye_states: states of the evaluation set over the eye distribution
        (`aperture_fab.validation.robustness`); 0 skips the judgement over the distribution.
    made_copies: made copies (draws of the process's errors) the part as made is judged over,
        beside the best regular array (`aperture_fab.validation.made_part`); 0 skips it.
    """

    tolerance_samples: int = 16
    threshold_db: float | None = None
    gap_sigma_mm: float = 0.1
    eye_sigma_mm: float = 1.0
    tilt_sigma_deg: float = 0.5
    mesh_samples: int | None = None
    diffraction: bool = True
    seed: int = 0
    eye_states: int = EVALUATION_STATES
    made_copies: int = MADE_COPIES

    def __post_init__(self) -> None:
        for name in ("tolerance_samples", "mesh_samples", "seed", "eye_states", "made_copies"):
            value = getattr(self, name)
            if name == "mesh_samples" and value is None:
                continue
            if not (isinstance(value, int) and not isinstance(value, bool) and value >= 0):
                raise ValueError(f"validation.{name} = {value!r} must be a whole number >= 0.")
            most = MAX_COUNTS.get(name)
            if most is not None and value > most:
                raise ValueError(f"validation.{name} = {value} is out of range; allowed: 0 to "
                                 f"{most} (more takes hours for no visible gain). Give a "
                                 "smaller number.")
        for name in ("gap_sigma_mm", "eye_sigma_mm", "tilt_sigma_deg", "threshold_db"):
            value = getattr(self, name)
            if name == "threshold_db" and value is None:
                continue
            if not (isinstance(value, (int, float)) and not isinstance(value, bool)):
                raise TypeError(f"validation.{name} = {value!r} has the wrong type: expected a "
                                f"number, e.g. {name} = {VALIDATION_EXAMPLES[name]}.")
        if not isinstance(self.diffraction, bool):
            raise TypeError(f"validation.diffraction = {self.diffraction!r} has the wrong type: "
                            "expected true or false (without quotes).")
        if self.threshold_db is not None and not math.isfinite(self.threshold_db):
            raise ValueError(f"validation.threshold_db = {self.threshold_db!r} must be a finite "
                             "PSNR in dB, e.g. 20, or left out (the part's own figure minus "
                             f"{YIELD_MARGIN_DB:g} dB).")
        for name in ("gap_sigma_mm", "eye_sigma_mm"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"validation.{name} = {value!r} must be >= 0 (mm).")
        tilt = self.tilt_sigma_deg
        if not (math.isfinite(tilt) and 0 <= tilt <= MAX_TILT_SIGMA_DEG):
            raise ValueError(
                f"validation.tilt_sigma_deg = {tilt!r} is out of range; allowed: 0 to "
                f"{MAX_TILT_SIGMA_DEG:g} (degrees, 1 sigma). A plate tilted more is not seated; "
                "fix the mount rather than the tolerance."
            )

    def with_flags(self, **flags: Any) -> ValidationSettings:
        """These settings with the flags given (None values: not given)."""
        return dataclasses.replace(self, **{k: v for k, v in flags.items() if v is not None})


#: A typical phone panel's full-white luminance (cd/m2): phone OLED and LCD panels sit at about
#: 400 to 800 cd/m2 in normal (not boosted) mode.
DEFAULT_PANEL_CD_M2 = 500.0
MAX_PANEL_CD_M2 = 1e6
#: The age range Watson and Yellott's pupil formula was fitted over, and the default observer.
AGE_RANGE_YEARS = (20.0, 83.0)
DEFAULT_AGE_YEARS = 30.0


@dataclass(frozen=True)
class PhotometrySettings:
    """The panel and the observer ([photometry]; aperture_fab.optics.photometry).

    panel_luminance_cd_m2: the display's full-white luminance. observer_age_years: for the pupil
    formula. adapted_eyes: 2 when both eyes see the device (a binocular headset), 1 when one does.
    """

    panel_luminance_cd_m2: float = DEFAULT_PANEL_CD_M2
    observer_age_years: float = DEFAULT_AGE_YEARS
    adapted_eyes: int = 2

    def __post_init__(self) -> None:
        if not (isinstance(self.panel_luminance_cd_m2, (int, float))
                and 0 < self.panel_luminance_cd_m2 <= MAX_PANEL_CD_M2):
            raise ValueError(
                f"photometry.panel_luminance_cd_m2 = {self.panel_luminance_cd_m2!r} is out of "
                f"range; allowed: 0 < L <= {MAX_PANEL_CD_M2:g} cd/m2. Give the panel's "
                f"full-white luminance (a phone panel is about {DEFAULT_PANEL_CD_M2:g}).")
        low, high = AGE_RANGE_YEARS
        if not (isinstance(self.observer_age_years, (int, float))
                and low <= self.observer_age_years <= high):
            raise ValueError(
                f"photometry.observer_age_years = {self.observer_age_years!r} is out of range; "
                f"allowed: {low:g} to {high:g} (the pupil formula's fitted range).")
        if self.adapted_eyes not in (1, 2):
            raise ValueError(f"photometry.adapted_eyes = {self.adapted_eyes!r}; allowed: 1 or 2 "
                             "(2 when both eyes look into the device).")


def _keys(table_name: str, table: Mapping[str, Any], allowed: list[str]) -> dict[str, Any]:
    unknown = sorted(set(table) - set(allowed))
    if unknown:
        raise ValueError(f"[{table_name}] has unknown key(s) {unknown}; allowed: "
                         f"{sorted(allowed)}.")
    return dict(table)


def _fields(cls: type) -> list[str]:
    return [f.name for f in dataclasses.fields(cls)]


def _outline(value: Any) -> tuple[float, float]:
    if not (isinstance(value, (list, tuple)) and len(value) == 2
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
        raise TypeError(f"part.outline_mm = {value!r} must be two numbers [width, height] (mm): "
                        "the outline a design recorded; leave [part] out of a config you write.")
    return float(value[0]), float(value[1])


def read_tables(tables: Mapping[str, Mapping[str, Any]]
                ) -> tuple[FabricationSettings, ValidationSettings, PhotometrySettings,
                           tuple[float, float] | None]:
    """The stage tables merged from a config's layers (name -> table), typed and checked:
    (fabrication, validation, photometry, the recorded part outline or None)."""
    unknown = sorted(set(tables) - set(TABLES))
    if unknown:
        close = difflib.get_close_matches(unknown[0], TABLES, n=1)
        hint = f" Did you mean [{close[0]}]?" if close else ""
        raise ValueError(f"unknown table(s) {', '.join(f'[{n}]' for n in unknown)}; a config "
                         "holds [display], [plate], [eye], [optimizer] and the stage tables "
                         f"{', '.join(f'[{n}]' for n in TABLES)}. Remove or rename it.{hint}")
    section = dict(tables.get("process", {}))
    name = section.pop("name", UNNAMED_PROCESS)
    process = resolve_process(str(name), section)
    fab = _keys("fabrication", tables.get("fabrication", {}),
                ["force", "step", "alignment_cut", "svg_polarity"])
    fabrication = FabricationSettings(
        process, bool(fab.get("force", False)), bool(fab.get("step", False)),
        bool(fab.get("alignment_cut", True)), fab.get("svg_polarity", "holes_black"))
    validation = ValidationSettings(**_keys("validation", tables.get("validation", {}),
                                            _fields(ValidationSettings)))
    photometry = PhotometrySettings(**_keys("photometry", tables.get("photometry", {}),
                                            _fields(PhotometrySettings)))
    part = _keys("part", tables.get("part", {}), ["outline_mm"])
    outline = _outline(part["outline_mm"]) if "outline_mm" in part else None
    return fabrication, validation, photometry, outline


def _changed(settings: Any) -> dict[str, Any]:
    """The fields of a settings value that differ from its defaults."""
    default = type(settings)()
    return {f.name: getattr(settings, f.name) for f in dataclasses.fields(settings)
            if getattr(settings, f.name) != getattr(default, f.name)}


def written_tables(fabrication: FabricationSettings, validation: ValidationSettings,
                   photometry: PhotometrySettings, outline_mm: tuple[float, float] | None
                   ) -> dict[str, dict[str, Any]]:
    """The stage tables as a written config holds them (plain dicts and lists): the process by
    name with every field that differs from the catalog's, the fabrication settings in full, the
    validation and photometry settings that differ from their defaults (a table only when one
    does) and the recorded outline."""
    tables: dict[str, dict[str, Any]] = {}
    for table, settings in (("validation", validation), ("photometry", photometry)):
        changed = _changed(settings)
        if changed:
            tables[table] = changed
    tables["process"] = {"name": fabrication.process.name,
                         **{k: list(v) if isinstance(v, tuple) else v
                            for k, v in _process_changes(fabrication.process).items()}}
    tables["fabrication"] = {"force": fabrication.force, "step": fabrication.step,
                             "alignment_cut": fabrication.alignment_cut,
                             "svg_polarity": fabrication.svg_polarity}
    if outline_mm is not None:
        tables["part"] = {"outline_mm": list(outline_mm)}
    return tables
