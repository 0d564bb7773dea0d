"""The sweep file (sweep.toml): what to vary, what to keep, and what "better" means.

A designer sweeps config keys (gap, pitch, thickness, process, eyebox, panel ...) to find the
best trade-off between sharpness over the eyebox, brightness and field of view. Every point is a
full design job, minutes each, so a mistake in the file must be caught before the first job
starts: `load_spec` checks the file's shape and `check_points` resolves every point's config
(with the package's own `resolve`, so the keys and values are the real ones) and names the
sweep file, the point, the key, the value, what is allowed and the fix.

    [sweep]
    mode = "grid"                     # or "search" (Optuna's NSGA-II multi-objective sampler)
    targets = ["targets/natural.png"] # relative to this file
    objectives = ["maximize eye_p10_psnr_db", "maximize light_efficiency"]
    preset = "near-eye"               # optional; config = "base.toml" optional too
    trials = 40                       # search only; also seed, population

    [base]                            # fixed overrides, dotted config keys
    "optimizer.iterations" = 300

    [grid]                            # mode = "grid": every combination of these lists
    "plate.gap_mm" = [8.0, 10.0, 12.0]
    "process.name" = ["resin", "etched-foil"]

    [space]                           # mode = "search": ranges and choices
    "plate.gap_mm" = { low = 6.0, high = 14.0 }
    "plate.pitch_mm" = { low = 0.2, high = 0.6, log = true }
    "process.name" = { choices = ["resin", "etched-foil"] }
"""

from __future__ import annotations

import difflib
import hashlib
import itertools
import json
import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, cast, get_args

__all__ = ["Mode", "Figure", "Objective", "FloatRange", "IntRange", "Choice", "Point",
           "SweepSpec", "FIGURES", "load_spec", "parse_spec", "grid_points", "point_id",
           "check_points"]

Mode = Literal["grid", "search"]
Direction = Literal["maximize", "minimize"]
#: The figures each point reports (see results.FIGURE_HELP); any can be an objective.
Figure = Literal["eye_p10_psnr_db", "eye_p50_psnr_db", "eye_p90_psnr_db", "nominal_psnr_db",
                 "light_efficiency", "luminance_cd_m2", "retinal_illuminance_td",
                 "contrast_ratio", "made_p10_psnr_db", "made_p50_psnr_db",
                 "made_light_efficiency", "regular_p10_psnr_db", "made_margin_db", "fov_x_deg",
                 "fov_y_deg", "hole_count", "rule_violations", "seconds"]
FIGURES: tuple[Figure, ...] = get_args(Figure)
MODES: tuple[Mode, ...] = get_args(Mode)
DIRECTIONS: tuple[Direction, ...] = get_args(Direction)

DEFAULT_OBJECTIVES = ("maximize eye_p10_psnr_db", "maximize light_efficiency")
DEFAULT_TRIALS = 32
#: NSGA-II generation size when the file gives none (capped by the number of trials).
DEFAULT_POPULATION = 16
MIN_POPULATION = 2
#: Hex digits of a point's id: 48 bits, no collision in any sweep a person would run.
ID_DIGITS = 12
#: Sections a swept key may name: the config's own, and the tables the later stages read.
SECTIONS = ("display", "plate", "eye", "optimizer", "process", "fabrication", "validation")
SWEEP_KEYS = ("mode", "targets", "objectives", "preset", "config", "trials", "seed",
              "population")
TABLES = ("sweep", "base", "grid", "space")
RANGE_KEYS = ("low", "high", "log")
_TYPO_CUTOFF = 0.6


@dataclass(frozen=True)
class Objective:
    """One objective: a figure and whether more (maximize) or less (minimize) is better."""

    direction: Direction
    figure: Figure

    @property
    def maximize(self) -> bool:
        return self.direction == "maximize"

    def __str__(self) -> str:
        return f"{self.direction} {self.figure}"


@dataclass(frozen=True)
class FloatRange:
    """A real search dimension from low to high (sampled on a log scale when log)."""

    key: str
    low: float
    high: float
    log: bool = False


@dataclass(frozen=True)
class IntRange:
    """A whole-number search dimension from low to high inclusive."""

    key: str
    low: int
    high: int
    log: bool = False


@dataclass(frozen=True)
class Choice:
    """A search dimension over listed values (any TOML value, e.g. [24, 24] or "resin")."""

    key: str
    choices: tuple[Any, ...]


Dimension = FloatRange | IntRange | Choice


@dataclass(frozen=True)
class Point:
    """One design job of the sweep: its id, the swept values and every override it runs with.

    settings: the swept keys and their values, in the file's order (what the table shows).
    overrides: [base] then settings, dotted keys (what `resolve` gets).
    """

    id: str
    settings: tuple[tuple[str, Any], ...]
    overrides: tuple[tuple[str, Any], ...]

    def label(self) -> str:
        return ", ".join(f"{k}={_text(v)}" for k, v in self.settings)


@dataclass(frozen=True)
class SweepSpec:
    """A checked sweep file. Paths are absolute; base_file is the optional config TOML's
    contents (the `resolve` file layer)."""

    source: Path
    mode: Mode
    targets: tuple[Path, ...]
    objectives: tuple[Objective, ...]
    preset: str | None
    base_file: Mapping[str, Any] | None
    base: tuple[tuple[str, Any], ...]
    grid: tuple[tuple[str, tuple[Any, ...]], ...]
    space: tuple[Dimension, ...]
    trials: int
    seed: int
    population: int
    #: SHA-256 of the target files' names and contents: an edited image makes new points.
    target_digest: str = ""

    @property
    def swept_keys(self) -> tuple[str, ...]:
        if self.mode == "grid":
            return tuple(k for k, _ in self.grid)
        return tuple(d.key for d in self.space)


def _text(value: Any) -> str:
    return json.dumps(value) if not isinstance(value, str) else value


def _fail(source: Path, where: str, what: str) -> ValueError:
    return ValueError(f"{source}: {where}: {what}")


def _hint(word: str, choices: tuple[str, ...]) -> str:
    close = difflib.get_close_matches(word, choices, n=1, cutoff=_TYPO_CUTOFF)
    return f" Did you mean {close[0]!r}?" if close else ""


def _flatten(table: Mapping[str, Any], leaf: Any, prefix: str = "") -> dict[str, Any]:
    """Dotted keys from nested tables ([base] plate.gap_mm = 8 and "plate.gap_mm" = 8 alike);
    `leaf(value)` says when a table is a value (a {low, high} range) rather than a section."""
    out: dict[str, Any] = {}
    for key, value in table.items():
        dotted = f"{prefix}{key}"
        if isinstance(value, Mapping) and not leaf(value):
            out.update(_flatten(value, leaf, f"{dotted}."))
        else:
            out[dotted] = value
    return out


def _check_key(source: Path, table: str, key: str) -> None:
    section, _, name = key.partition(".")
    if not name:
        raise _fail(source, f"[{table}] {key!r}", "a key must be dotted, section.key, e.g. "
                    '"plate.gap_mm" or "process.name".')
    if section not in SECTIONS:
        raise _fail(source, f"[{table}] {key!r}", f"unknown section {section!r}; allowed: "
                    f"{', '.join(SECTIONS)}.{_hint(section, SECTIONS)}")


def _objective(source: Path, text: Any) -> Objective:
    words = text.split() if isinstance(text, str) else []
    fix = f'write "maximize FIGURE" or "minimize FIGURE" with FIGURE one of {", ".join(FIGURES)}'
    if len(words) != 2 or words[0] not in DIRECTIONS:
        raise _fail(source, "[sweep] objectives", f"{text!r} is not an objective; {fix}.")
    if words[1] not in FIGURES:
        raise _fail(source, "[sweep] objectives", f"unknown figure {words[1]!r}; "
                    f"{fix}.{_hint(words[1], FIGURES)}")
    return Objective(cast(Direction, words[0]), cast(Figure, words[1]))


def _dimension(source: Path, key: str, value: Any) -> Dimension:
    where = f"[space] {key!r}"
    if not isinstance(value, Mapping):
        raise _fail(source, where, f"{value!r} is not a range or choices; write "
                    "{ low = 6.0, high = 14.0 } (add log = true for a log scale) or "
                    '{ choices = ["resin", "etched-foil"] }.')
    if "choices" in value:
        choices = value["choices"]
        if set(value) != {"choices"} or not isinstance(choices, list) or not choices:
            raise _fail(source, where, "choices must be the table's only key and a non-empty "
                        'list, e.g. { choices = ["resin", "etched-foil"] }.')
        return Choice(key, tuple(_freeze(c) for c in choices))
    unknown = sorted(set(value) - set(RANGE_KEYS))
    if unknown or "low" not in value or "high" not in value:
        raise _fail(source, where, f"a range has keys low, high and optionally log (got "
                    f"{', '.join(sorted(value))}); e.g. {{ low = 6.0, high = 14.0 }}.")
    low, high, log = value["low"], value["high"], value.get("log", False)
    numbers = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (low, high))
    if not numbers or not all(math.isfinite(v) for v in (low, high)):
        raise _fail(source, where, f"low = {low!r} and high = {high!r} must be finite numbers.")
    if not isinstance(log, bool):
        raise _fail(source, where, f"log = {log!r} must be true or false.")
    if not low < high:
        raise _fail(source, where, f"low = {low!r} must be below high = {high!r}; for one "
                    "value put the key in [base] instead.")
    if log and low <= 0:
        raise _fail(source, where, f"a log range needs low > 0 (got low = {low!r}).")
    if isinstance(low, int) and isinstance(high, int):
        return IntRange(key, low, high, log)
    return FloatRange(key, float(low), float(high), log)


def _freeze(value: Any) -> Any:
    """Lists become tuples (hashable, read-only); everything else is kept."""
    return tuple(_freeze(v) for v in value) if isinstance(value, list) else value


def _thaw(value: Any) -> Any:
    return [_thaw(v) for v in value] if isinstance(value, tuple) else value


def _whole(source: Path, table: Mapping[str, Any], key: str, default: int, low: int) -> int:
    value = table.get(key, default)
    if not (isinstance(value, int) and not isinstance(value, bool) and value >= low):
        raise _fail(source, f"[sweep] {key}", f"{value!r} must be a whole number >= {low}.")
    return value


def parse_spec(doc: Mapping[str, Any], source: Path) -> SweepSpec:
    """Check a parsed sweep document; relative paths are taken from `source`'s folder."""
    for name in doc:
        if name not in TABLES or not isinstance(doc[name], Mapping):
            raise _fail(source, f"top level {name!r}", f"only the tables [{'], ['.join(TABLES)}] "
                        f"belong at the top.{_hint(name, TABLES)}")
    sweep = doc.get("sweep", {})
    for key in sweep:
        if key not in SWEEP_KEYS:
            raise _fail(source, f"[sweep] {key!r}", f"unknown key; allowed: "
                        f"{', '.join(SWEEP_KEYS)}.{_hint(key, SWEEP_KEYS)}")
    mode = sweep.get("mode", "grid")
    if mode not in MODES:
        raise _fail(source, "[sweep] mode", f"{mode!r}; choose one of {', '.join(MODES)}.")
    folder = source.parent
    targets = sweep.get("targets")
    if not (isinstance(targets, list) and targets and all(isinstance(t, str) for t in targets)):
        raise _fail(source, "[sweep] targets", "give the target images as a list of paths "
                    'relative to the sweep file, e.g. targets = ["targets/natural.png"].')
    paths = tuple((folder / t).resolve() for t in targets)
    for text, path in zip(targets, paths, strict=True):
        if not path.is_file():
            raise _fail(source, "[sweep] targets", f"target {text!r} ({path}) does not exist; "
                        "paths are relative to the sweep file's folder.")
    objectives = sweep.get("objectives", list(DEFAULT_OBJECTIVES))
    if not (isinstance(objectives, list) and objectives):
        raise _fail(source, "[sweep] objectives", "give a non-empty list, e.g. "
                    f"objectives = {json.dumps(list(DEFAULT_OBJECTIVES))}.")
    parsed = tuple(_objective(source, o) for o in objectives)
    if len({o.figure for o in parsed}) != len(parsed):
        raise _fail(source, "[sweep] objectives", "each figure may appear once.")
    preset = sweep.get("preset")
    if preset is not None and not isinstance(preset, str):
        raise _fail(source, "[sweep] preset", f"{preset!r} must be a preset name in quotes.")
    base_file = _base_file(source, sweep.get("config"))
    base = _flatten(doc.get("base", {}), lambda v: False)
    for key in base:
        _check_key(source, "base", key)
    grid: tuple[tuple[str, tuple[Any, ...]], ...] = ()
    space: tuple[Dimension, ...] = ()
    if mode == "grid":
        if "space" in doc:
            raise _fail(source, "[space]", 'is for mode = "search"; use [grid] lists for a grid.')
        grid = _grid(source, doc.get("grid", {}))
    else:
        if "grid" in doc:
            raise _fail(source, "[grid]", 'is for mode = "grid"; use [space] ranges for a search.')
        space = _space(source, doc.get("space", {}))
    swept = {k for k, _ in grid} | {d.key for d in space}
    both = sorted(swept & set(base))
    if both:
        raise _fail(source, f"[base] {both[0]!r}", "is also swept; keep it in one table.")
    trials = _whole(source, sweep, "trials", DEFAULT_TRIALS, 1)
    population = _whole(source, sweep, "population", min(DEFAULT_POPULATION, trials),
                        MIN_POPULATION)
    return SweepSpec(source=source, mode=mode, targets=paths, objectives=parsed, preset=preset,
                     base_file=base_file, base=tuple((k, _freeze(v)) for k, v in base.items()),
                     grid=grid, space=space, trials=trials,
                     seed=_whole(source, sweep, "seed", 0, 0), population=population,
                     target_digest=_digest(paths))


def _digest(paths: tuple[Path, ...]) -> str:
    digest = hashlib.sha256()
    for path in paths:
        digest.update(path.name.encode() + b"\0" + hashlib.sha256(path.read_bytes()).digest())
    return digest.hexdigest()


def _base_file(source: Path, name: Any) -> Mapping[str, Any] | None:
    if name is None:
        return None
    if not isinstance(name, str):
        raise _fail(source, "[sweep] config", f"{name!r} must be a path in quotes.")
    from aperture_fab.io.files import read_text

    path = (source.parent / name).resolve()
    try:
        return tomllib.loads(read_text(path, "[sweep] config", "give a TOML config saved as "
                                       "UTF-8 text."))
    except OSError as err:
        raise _fail(source, "[sweep] config", f"cannot read {path} ({err.strerror}); the path "
                    "is relative to the sweep file's folder.") from err
    except tomllib.TOMLDecodeError as err:
        raise _fail(source, "[sweep] config", f"{path} is not valid TOML: {err}.") from err


def _grid(source: Path, table: Mapping[str, Any]) -> tuple[tuple[str, tuple[Any, ...]], ...]:
    grid = _flatten(table, lambda v: False)
    if not grid:
        raise _fail(source, "[grid]", 'is empty; list values per key, e.g. "plate.gap_mm" = '
                    "[8.0, 10.0, 12.0].")
    out = []
    for key, values in grid.items():
        _check_key(source, "grid", key)
        if not (isinstance(values, list) and values):
            raise _fail(source, f"[grid] {key!r}", f"{values!r} must be a non-empty list of "
                        "values, e.g. [8.0, 10.0] (a pair value is a list of pairs: "
                        "[[16, 16], [24, 24]]).")
        frozen = tuple(_freeze(v) for v in values)
        if len(set(map(json.dumps, values))) != len(values):
            raise _fail(source, f"[grid] {key!r}", f"{values!r} repeats a value.")
        out.append((key, frozen))
    return tuple(out)


def _space(source: Path, table: Mapping[str, Any]) -> tuple[Dimension, ...]:
    space = _flatten(table, lambda v: any(k in v for k in ("low", "high", "choices")))
    if not space:
        raise _fail(source, "[space]", "is empty; give ranges or choices, e.g. "
                    '"plate.gap_mm" = { low = 6.0, high = 14.0 }.')
    for key in space:
        _check_key(source, "space", key)
    return tuple(_dimension(source, k, v) for k, v in space.items())


def load_spec(path: Path) -> SweepSpec:
    """Read and check a sweep file (the shape only; `check_points` checks the values)."""
    from aperture_fab.io.files import read_text

    try:
        text = read_text(path, "sweep file", "save it as UTF-8 text (TOML), e.g. from "
                         "examples/sweep.toml.")
    except OSError as err:
        raise ValueError(f"sweep file {path}: cannot read it ({err.strerror}); check the "
                         "path (examples/sweep.toml is one).") from err
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ValueError(f"{path}: TOML syntax error: {err}. Text values need quotes, dotted "
                         'keys too when they hold a dot: "plate.gap_mm" = [8.0, 10.0].') from err
    return parse_spec(doc, path.resolve())


def point_id(spec: SweepSpec, overrides: Mapping[str, Any]) -> str:
    """A stable id for a design job: a hash of everything that decides its outputs (preset,
    config file, overrides, the target files' names and contents). The same settings give the
    same id in any sweep, so a rerun or a grown grid finds its finished points again."""
    payload = {"preset": spec.preset, "config": spec.base_file,
               "overrides": {k: _thaw(v) for k, v in sorted(overrides.items())},
               "targets": spec.target_digest}
    text = json.dumps(payload, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:ID_DIGITS]


def make_point(spec: SweepSpec, settings: tuple[tuple[str, Any], ...]) -> Point:
    overrides = dict(spec.base) | dict(settings)
    return Point(point_id(spec, overrides), settings, tuple(overrides.items()))


def grid_points(spec: SweepSpec) -> list[Point]:
    """Every combination of the grid's values, the last key varying fastest."""
    keys = [k for k, _ in spec.grid]
    return [make_point(spec, tuple(zip(keys, combo, strict=True)))
            for combo in itertools.product(*(values for _, values in spec.grid))]


def check_points(spec: SweepSpec, points: list[Point], check: Any) -> None:
    """Resolve [base], each swept value on its own, then each point with `check(overrides)`
    (resolve plus the process and validation settings); the first error raised names the
    sweep file, the table, the key, the value and the fix."""
    def attempt(overrides: Mapping[str, Any], where: str, fix: str) -> None:
        try:
            check({k: _thaw(v) for k, v in overrides.items()})
        except (ValueError, TypeError, KeyError) as err:
            text = str(err).replace("the overrides (flags)", "the sweep file")
            if "nknown key" in text:
                fix = "rename the key to one of the allowed keys."
            raise _fail(spec.source, where, f"{text} Fix: {fix}") from err

    base = dict(spec.base)
    attempt(base, "[base]", "change the value in [base] (or in the [sweep] config file).")
    for key, values in spec.grid:
        listed = ", ".join(map(_text, values))  # once per key: a long list costs n^2 else
        for value in values:
            attempt(base | {key: value}, f"[grid] {key} = {_text(value)}",
                    f"remove or change {_text(value)} in [grid] {key!r} (its values: "
                    f"{listed}).")
    for dim in spec.space:
        ends = dim.choices if isinstance(dim, Choice) else (dim.low, dim.high)
        for value in ends:
            attempt(base | {dim.key: value}, f"[space] {dim.key} = {_text(value)}",
                    f"narrow the range or change the choices of [space] {dim.key!r}.")
    for n, point in enumerate(points, 1):
        attempt(dict(point.overrides), f"point {n} ({point.label()})",
                "these values do not go together; change the [grid] lists or [base].")
