"""Configuration: a TOML document holding the scene and the optimizer settings, in layers.

Precedence, lowest first: a preset (`aperture_fab.config.presets`), a user's TOML file, then
overrides (dotted keys such as "plate.gap_mm", from command-line flags). Every section is optional
in a file; what it leaves out comes from the preset.

    preset = "near-eye"          # optional; the `preset` argument (CLI --preset) wins over it
    [display]   width_mm, height_mm, pixels = [nx, ny], cover_glass_mm, cover_glass_index,
                subpixels = "none" | "rgb_stripe" | "bgr_stripe",
                emission = "lambertian" | "cosine_power", emission_exponent
    [plate]     cells = [nx, ny], pitch_mm = [px, py] or one number, gap_mm, thickness_mm,
                hole_axis
    [eye]       pupil_mm, eye_relief_mm, focus_mm = "infinity" | number,
                fov_deg = "display" | [x, y], view_pixels = [nx, ny],
                positions_mm = [[x, y], ...], weights = [...],
                eyebox_mm = [w, h] or one number, eyebox_shape = "ellipse" | "rect",
                pupil_range_mm = "nominal" | [lo, hi],
                focus_range_diopters = "nominal" | [lo, hi], gaze_deg, rotation_mm
    [optimizer] method, learning_rate, momentum, iterations, schedule, init, display,
                efficiency_weight, plateau_patience, plateau_tolerance, seed, precision,
                device, checkpoint_every, quantize_share, eye_states, tail_share, tracking,
                lattice

The eye distribution ([eye] eyebox_mm to rotation_mm, see aperture_fab.optics.eyes) spreads the eye
around its nominal state (pupil_mm, focus_mm, the first position); "nominal" ranges are that
state only. A nominal pupil_mm or focus_mm set in a higher layer than its range, and outside
that range, pins it: the range becomes "nominal" (e.g. --pupil-mm 8 over the near-eye preset's
3 to 6 mm designs for an 8 mm pupil; --focus-mm 500 for 500 mm). Set both to spread around it.

The later stages' tables ([process], [fabrication], [validation], [photometry], [part]) are
read into typed settings too (`aperture_fab.config.stages`). Unknown keys, sections and tables
are errors.

This module reads and writes text only; the CLI reads and writes the files.
"""

from __future__ import annotations

import difflib
import math
import re
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import tomlkit

from aperture_fab.config.presets import DEFAULT_PRESET, PRESETS
from aperture_fab.config.settings import (
    DISPLAY_MODES,
    INITS,
    LATTICES,
    METHODS,
    PRECISIONS,
    SCHEDULES,
    TRACKINGS,
    OptimizerSettings,
)
from aperture_fab.config.stages import (
    FabricationSettings,
    PhotometrySettings,
    ValidationSettings,
    read_tables,
)
from aperture_fab.optics.eye_fields import EYEBOX_SHAPES
from aperture_fab.optics.scene import (
    EMISSIONS,
    HOLE_AXES,
    SUBPIXEL_LAYOUTS,
    Display,
    Eye,
    Plate,
    Scene,
    display_fov_deg,
    eyebox_margin_mm,
)

__all__ = ["SECTION_KEYS", "Config", "parse_toml", "resolve"]

#: The keys each known section allows, in the order `to_toml` writes them.
SECTION_KEYS: dict[str, tuple[str, ...]] = {
    "display": ("width_mm", "height_mm", "pixels", "cover_glass_mm", "cover_glass_index",
                "subpixels", "emission", "emission_exponent"),
    "plate": ("cells", "pitch_mm", "gap_mm", "thickness_mm", "hole_axis"),
    "eye": ("pupil_mm", "eye_relief_mm", "focus_mm", "fov_deg", "view_pixels", "positions_mm",
            "weights", "eyebox_mm", "eyebox_shape", "pupil_range_mm", "focus_range_diopters",
            "gaze_deg", "rotation_mm"),
    "optimizer": ("method", "learning_rate", "momentum", "iterations", "schedule", "init",
                  "init_diameter_mm", "display", "efficiency_weight", "min_efficiency",
                  "min_eye_level", "plateau_patience", "plateau_tolerance", "seed",
                  "precision", "device", "checkpoint_every", "quantize_share", "eye_states",
                  "tail_share", "tracking", "lattice"),
}

INFINITY = "infinity"
DISPLAY_FOV = "display"
NOMINAL = "nominal"
#: Each eye range and the nominal value that pins it when set in a higher layer.
_RANGE_NOMINALS = {"eye.pupil_range_mm": "eye.pupil_mm",
                   "eye.focus_range_diopters": "eye.focus_mm"}

_FLOATS = {
    "display.width_mm", "display.height_mm", "plate.gap_mm", "plate.thickness_mm",
    "eye.pupil_mm", "eye.eye_relief_mm", "optimizer.learning_rate", "optimizer.momentum",
    "optimizer.efficiency_weight", "optimizer.min_efficiency", "optimizer.min_eye_level",
    "optimizer.plateau_tolerance",
    "optimizer.quantize_share",
    "eye.gaze_deg", "eye.rotation_mm", "optimizer.tail_share", "optimizer.init_diameter_mm",
    "display.cover_glass_mm", "display.cover_glass_index", "display.emission_exponent",
}
_WHOLES = {
    "optimizer.iterations", "optimizer.plateau_patience", "optimizer.seed",
    "optimizer.checkpoint_every", "optimizer.eye_states",
}
_WHOLE_PAIRS = {"display.pixels", "plate.cells", "eye.view_pixels"}
#: Text keys and their choices (None: free text, checked by the dataclass).
_TEXTS: dict[str, tuple[str, ...] | None] = {
    "display.subpixels": SUBPIXEL_LAYOUTS,
    "display.emission": EMISSIONS,
    "plate.hole_axis": HOLE_AXES,
    "eye.eyebox_shape": EYEBOX_SHAPES,
    "optimizer.tracking": TRACKINGS,
    "optimizer.lattice": LATTICES,
    "optimizer.method": METHODS,
    "optimizer.schedule": SCHEDULES,
    "optimizer.init": INITS,
    "optimizer.display": DISPLAY_MODES,
    "optimizer.precision": PRECISIONS,
    "optimizer.device": None,
}

#: Layer ranks: a higher rank overrides a lower one.
_PRESET, _FILE, _FLAG = 0, 1, 2
#: difflib similarity above which an unknown table name is taken for a typo of a known section.
_SECTION_TYPO_CUTOFF = 0.8
_KEY_TYPO_CUTOFF = 0.6

_TOML_POSITION = re.compile(r"\(at line (\d+), column (\d+)\)")


@dataclass(frozen=True)
class Config:
    """A fully resolved configuration.

    preset: name of the preset the values started from.
    scene: display, plate and eye (field of view in explicit degrees).
    optimizer: optimizer settings.
    fabrication: how the part is made ([process], [fabrication]).
    validation: how much validation to do ([validation]).
    photometry: the panel and the observer ([photometry]).
    part_outline_mm: the plate outline (width, height) a design recorded ([part]), or None.
    fov_from_display: whether scene.eye.fov_deg was derived from the geometry
        (`fov_deg = "display"`) rather than set; a written config then says "display", so a
        rerun with another gap or eyebox derives the field again instead of freezing this one.
    """

    preset: str
    scene: Scene
    optimizer: OptimizerSettings
    fabrication: FabricationSettings = field(default_factory=FabricationSettings)
    validation: ValidationSettings = field(default_factory=ValidationSettings)
    photometry: PhotometrySettings = field(default_factory=PhotometrySettings)
    part_outline_mm: tuple[float, float] | None = None
    fov_from_display: bool = False


# ---------------------------------------------------------------------------------------------
# Reading


def parse_toml(text: str, source: str) -> dict[str, Any]:
    """Parse TOML text; a syntax error becomes a ValueError naming `source` and the line."""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        message = str(err)
        match = _TOML_POSITION.search(message)
        where = f"line {match[1]}, column {match[2]}" if match else "somewhere"
        what = _TOML_POSITION.sub("", message).strip()
        raise ValueError(
            f"{source}: TOML syntax error at {where}: {what}. Fix that line: text values need "
            'quotes (hole_axis = "straight"), lists use brackets (pixels = [400, 400]), each '
            "key = value on its own line, each [section] at most once."
        ) from err


class _Layers:
    """Values of the four known sections by dotted key, with the layer each came from."""

    def __init__(self) -> None:
        self.values: dict[str, Any] = {}
        self.sources: dict[str, tuple[int, str]] = {}
        self.tables: dict[str, Any] = {}  # the stage tables, merged (config.stages)

    def set(self, key: str, value: Any, rank: int, label: str) -> None:
        self.values[key] = value
        self.sources[key] = (rank, label)

    def where(self, key: str) -> str:
        return f"from {self.sources[key][1]}"


def _suggest(word: str, choices: tuple[str, ...] | list[str]) -> str:
    close = difflib.get_close_matches(word, choices, n=1, cutoff=_KEY_TYPO_CUTOFF)
    return f" Did you mean {close[0]!r}?" if close else ""


def _other_section(key: str) -> str:
    """" 'pupil_mm' belongs in [eye]." when `key` is a key of some section, else ""."""
    homes = [s for s, keys in SECTION_KEYS.items() if key in keys]
    return f" {key!r} belongs in [{homes[0]}]." if homes else ""


def _check_key(section: str, key: str, label: str) -> None:
    allowed = SECTION_KEYS[section]
    if key not in allowed:
        hint = _other_section(key) or _suggest(key, list(allowed))
        raise ValueError(
            f"Unknown key {key!r} in section [{section}] ({label}); allowed keys: "
            f"{', '.join(allowed)}.{hint}"
        )


def _check_section_name(name: str, label: str) -> None:
    """Reject a table whose name looks like a misspelt known section (it would be ignored)."""
    close = difflib.get_close_matches(name, list(SECTION_KEYS), n=1, cutoff=_SECTION_TYPO_CUTOFF)
    if close:
        raise ValueError(
            f"Unknown section [{name}] ({label}); did you mean [{close[0]}]? Known sections: "
            f"{', '.join(SECTION_KEYS)}, and the stage tables (aperture_fab.config.stages)."
        )


def _merge(into: dict[str, Any], new: Mapping[str, Any]) -> None:
    """Deep-merge `new` into `into`: tables merge key by key, other values replace."""
    for key, value in new.items():
        if isinstance(value, Mapping) and isinstance(into.get(key), dict):
            _merge(into[key], value)
        else:
            into[key] = _plain(value)  # a deep copy, so later merges never touch the source


def _add_document(layers: _Layers, doc: Mapping[str, Any], rank: int, label: str) -> None:
    """Add a preset or file document (TOML shape) to the layers."""
    for name, table in doc.items():
        if name == "preset":
            continue
        if not isinstance(table, Mapping):
            raise TypeError(
                f"Top-level key {name!r} = {table!r} ({label}) is not allowed: only "
                f'preset = "name" and [sections] go at the top.{_other_section(name)}'
            )
        if name in SECTION_KEYS:
            for key, value in table.items():
                _check_key(name, key, label)
                layers.set(f"{name}.{key}", value, rank, label)
        else:
            _check_section_name(name, label)
            _merge(layers.tables, {name: table})


def _add_overrides(layers: _Layers, overrides: Mapping[str, Any]) -> None:
    """Add dotted-key overrides; None means "not given" (an unset CLI flag)."""
    all_keys = [f"{s}.{k}" for s, keys in SECTION_KEYS.items() for k in keys]
    for dotted, value in overrides.items():
        if value is None:
            continue
        section, _, key = dotted.partition(".")
        if not key:
            bare = [k for k in all_keys if k.endswith(f".{dotted}")]
            hint = f" Did you mean {bare[0]!r}?" if bare else _suggest(dotted, all_keys)
            raise ValueError(
                f"Override {dotted!r} must be a dotted key such as 'plate.gap_mm' (the preset "
                f"is chosen with the preset argument).{hint}"
            )
        if section in SECTION_KEYS:
            _check_key(section, key, f"override {dotted!r}")
            layers.set(dotted, value, _FLAG, "the overrides (flags)")
        else:
            _check_section_name(section, f"override {dotted!r}")
            nested: Any = value
            for part in reversed(dotted.split(".")[1:]):
                nested = {part: nested}
            _merge(layers.tables, {section: nested})


# ---------------------------------------------------------------------------------------------
# Converting values, with errors that name the key, the value, where it came from and the fix


def _example(key: str) -> str:
    section, _, name = key.partition(".")
    return f"{name} = {tomlkit.item(PRESETS[DEFAULT_PRESET][section][name]).as_string()}"


def _wrong(key: str, value: Any, where: str, expected: str) -> TypeError:
    return TypeError(
        f"{key} = {value!r} ({where}) has the wrong type: expected {expected}, "
        f"e.g. {_example(key)}."
    )


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _is_whole(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _float_pair(key: str, value: Any, where: str) -> tuple[float, float]:
    if not (isinstance(value, (list, tuple)) and len(value) == 2 and all(map(_is_number, value))):
        raise _wrong(key, value, where, "a pair of numbers [x, y]")
    return (float(value[0]), float(value[1]))


def _convert(layers: _Layers, key: str) -> Any:
    """The value of `key`, checked for type and converted to what the dataclass holds."""
    value, where = layers.values[key], layers.where(key)
    if key in _FLOATS:
        if not _is_number(value):
            raise _wrong(key, value, where, "a number")
        return float(value)
    if key in _WHOLES:
        if not _is_whole(value):
            raise _wrong(key, value, where, "a whole number")
        return value
    if key in _WHOLE_PAIRS:
        if not (isinstance(value, (list, tuple)) and len(value) == 2
                and all(map(_is_whole, value))):
            raise _wrong(key, value, where, "a pair of whole numbers [nx, ny]")
        return (value[0], value[1])
    if key in _TEXTS:
        if not isinstance(value, str):
            choices = _TEXTS[key]
            expected = f"one of {', '.join(choices)}" if choices else "text in quotes"
            raise _wrong(key, value, where, expected)
        return value
    if key in ("plate.pitch_mm", "eye.eyebox_mm"):
        if _is_number(value):
            return (float(value), float(value))
        return _float_pair(key, value, where)
    if key in _RANGE_NOMINALS:
        if value == NOMINAL:
            return None
        if _is_number(value) or isinstance(value, str):
            raise _wrong(key, value, where, f'"{NOMINAL}" or a pair [lo, hi]')
        return _float_pair(key, value, where)
    if key == "eye.focus_mm":
        if value == INFINITY:
            return None
        if not _is_number(value):
            raise _wrong(key, value, where, f'"{INFINITY}" or a distance in mm')
        return float(value)
    if key == "eye.fov_deg":
        if value == DISPLAY_FOV:
            return DISPLAY_FOV
        if _is_number(value) or isinstance(value, str):
            raise _wrong(key, value, where, f'"{DISPLAY_FOV}" or a pair of angles [x, y]')
        return _float_pair(key, value, where)
    if key == "eye.positions_mm":
        if not isinstance(value, (list, tuple)):
            raise _wrong(key, value, where, "a list of [x, y] pairs")
        return tuple(_float_pair(key, pos, where) for pos in value)
    if key == "eye.weights":
        if not (isinstance(value, (list, tuple)) and all(map(_is_number, value))):
            raise _wrong(key, value, where, "a list of numbers, one per position")
        return tuple(float(w) for w in value)
    raise AssertionError(f"no converter for {key}")  # SECTION_KEYS and the sets above disagree


def _build(cls: Any, kwargs: dict[str, Any], layers: _Layers) -> Any:
    """cls(**kwargs), with any error it raises extended by where the keys it names came from."""
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as err:
        named = [k for k in layers.sources if re.search(rf"(?<![\w.]){re.escape(k)}\b", str(err))]
        if not named:
            raise
        origins = "; ".join(f"{k} came {layers.where(k)}" for k in named)
        if "eye.fov_deg" in named and layers.values["eye.fov_deg"] == DISPLAY_FOV:
            origins += ' as "display", the field the display subtends from the pupil'
        raise type(err)(f"{err} ({origins})") from err


def _section(layers: _Layers, section: str) -> dict[str, Any]:
    return {key: _convert(layers, f"{section}.{key}") for key in SECTION_KEYS[section]}


def _plain(value: Any) -> Any:
    """A deep copy as plain dicts and lists."""
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def _pin_ranges(eye_args: dict[str, Any], layers: _Layers) -> None:
    """A nominal set in a higher layer than its range, outside it, makes the range nominal."""
    focus_mm = eye_args["focus_mm"]
    # A focus of 0 mm (which the Eye refuses, naming it) is infinitely many diopters.
    focus_diopters = (0.0 if focus_mm is None else math.inf if focus_mm == 0
                      else 1000.0 / focus_mm)
    nominals = {"eye.pupil_mm": eye_args["pupil_mm"], "eye.focus_mm": focus_diopters}
    for range_key, nominal_key in _RANGE_NOMINALS.items():
        name = range_key.partition(".")[2]
        bounds, value = eye_args[name], nominals[nominal_key]
        if (bounds is not None and layers.sources[nominal_key][0] > layers.sources[range_key][0]
                and not bounds[0] <= value <= bounds[1]):
            eye_args[name] = None


def resolve(
    preset: str | None = None,
    file_dict: Mapping[str, Any] | None = None,
    overrides: Mapping[str, Any] | None = None,
    *,
    file_source: str | None = None,
) -> Config:
    """Resolve preset < file < overrides into a checked Config.

    preset: preset name; None takes the file's `preset` key, else the default ("near-eye").
    file_dict: a parsed TOML document (see `parse_toml`); any section may be left out.
    overrides: dotted keys ("plate.gap_mm") to values, e.g. from flags; None values are skipped.
    file_source: how errors name the file (its path); None says "the config file".
    """
    file_label = "the config file" if file_source is None else f"file {file_source!r}"
    file_dict = {} if file_dict is None else file_dict
    if not isinstance(file_dict, Mapping):
        raise TypeError(f"{file_label} must hold a TOML table, got {type(file_dict).__name__}")
    if preset is None:
        preset = file_dict.get("preset", DEFAULT_PRESET)
        if not isinstance(preset, str):
            raise TypeError(
                f'preset = {preset!r} (from {file_label}) must be text, e.g. preset = "near-eye"'
            )
    if preset not in PRESETS:
        raise ValueError(
            f"preset = {preset!r} is not a known preset; choose one of {', '.join(PRESETS)}."
        )

    layers = _Layers()
    _add_document(layers, PRESETS[preset], _PRESET, f"preset {preset!r}")
    _add_document(layers, file_dict, _FILE, file_label)
    _add_overrides(layers, overrides or {})
    missing = [f"{s}.{k}" for s, keys in SECTION_KEYS.items() for k in keys
               if f"{s}.{k}" not in layers.values]
    if missing:  # a preset must give every key
        raise AssertionError(f"preset {preset!r} lacks {', '.join(missing)}")

    display = _build(Display, _section(layers, "display"), layers)
    plate = _build(Plate, _section(layers, "plate"), layers)
    eye_args = _section(layers, "eye")
    # Positions set in a higher layer than the weights get equal weights (the preset's single
    # weight cannot fit a new eyebox).
    n_positions = len(eye_args["positions_mm"])
    if (len(eye_args["weights"]) != n_positions
            and layers.sources["eye.weights"][0] < layers.sources["eye.positions_mm"][0]):
        eye_args["weights"] = (1.0,) * n_positions
    _pin_ranges(eye_args, layers)
    fov_from_display = eye_args["fov_deg"] == DISPLAY_FOV
    if fov_from_display:
        distance_mm = eye_args["eye_relief_mm"] + plate.thickness_mm + plate.gap_mm
        # Check the eye's own values first (their messages are the clearer ones), then take
        # the field the display covers from every pupil position of the eyebox.
        _build(Eye, {**eye_args, "fov_deg": display_fov_deg(display, distance_mm)}, layers)
        margin = eyebox_margin_mm(eye_args["eyebox_mm"], eye_args["gaze_deg"],
                                  eye_args["rotation_mm"])
        try:
            eye_args["fov_deg"] = display_fov_deg(display, distance_mm, margin)
        except ValueError as err:
            raise ValueError(
                f"eye.eyebox_mm = {list(eye_args['eyebox_mm'])} and eye.gaze_deg = "
                f"{eye_args['gaze_deg']:g} ({layers.where('eye.eyebox_mm')}) with "
                f'eye.fov_deg = "display": {err}') from err
    eye = _build(Eye, eye_args, layers)
    scene = _build(Scene, {"display": display, "plate": plate, "eye": eye}, layers)
    optimizer_args = _section(layers, "optimizer")
    # A tracked design set above the layer that set a floor on the light at the eye drops it
    # (that floor holds one display's brightness; a tracked design's frames keep their warm
    # start's instead).
    if (optimizer_args["tracking"] == "tracked"
            and layers.sources["optimizer.min_eye_level"][0]
            < layers.sources["optimizer.tracking"][0]):
        optimizer_args["min_eye_level"] = 0.0
    optimizer = _build(OptimizerSettings, optimizer_args, layers)
    fabrication, validation, photometry, outline = read_tables(layers.tables)
    return Config(preset=preset, scene=scene, optimizer=optimizer, fabrication=fabrication,
                  validation=validation, photometry=photometry, part_outline_mm=outline,
                  fov_from_display=fov_from_display)


# ---------------------------------------------------------------------------------------------
# Writing


