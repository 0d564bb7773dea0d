"""Named starting points for a configuration, as plain nested dicts in the TOML file's shape.

Every preset gives every key of the four sections ([display], [plate], [eye], [optimizer]), so a
user file only states what differs. `aperture_fab.config.config.resolve` turns a preset, a file and
command-line overrides into checked dataclasses.

Why the "near-eye" numbers (the default):

- display 20 x 20 mm at 400 x 400 pixels: 50 um pixels, like a ~500 ppi phone panel, and a patch
  of it about as wide as the field a pinhole plate 1 cm away can usefully show;
- gap 10 mm: a slim device, and a pinhole height at which the best single hole is about 0.1 mm
  across (sqrt(2 lambda h) at 550 nm), so diffraction and geometric blur are balanced;
- cells 40 x 40 at 0.5 mm pitch: the plate covers the display, a cell spans 10 display pixels
  and holds holes up to 0.48 mm. Finer cells buy nothing as made: 80 x 80 cells of 0.25 mm
  (the default until 2026-11-29) gave parts within 0.2 dB p10 of these on a photo, a digit, a
  letter and a line pattern (20.5 / 16.0 / 16.5 / 12.6 dB against 20.6 / 16.0 / 16.4 /
  12.5), as the moving eye averages fine structure away, at three times the optimizer's time
  (the renderer's work grows with the holes under the pupil); 1 mm cells lose up to 0.4 dB
  on the letter and the line pattern (README, "The part as made");
- process photomask film, thickness 0.005 mm (its emulsion, the only opaque layer): it makes
  holes from 0.025 mm with 0.016 mm webs and is opaque (OD 4), where resin's 0.088 mm holes and
  OD 2 leave a grey veil over a view six times brighter than the light through the holes
  (docs/processes.md, "The default process"); chief-ray holes are kept for thicker plates;
- pupil 4 mm: an indoor pupil; eye relief 10 mm: close, like glasses on the nose;
- the eye moves (docs/design.md section 3): the design is optimized over a distribution of eye
  states, 8 fresh ones each iteration, for one display content (untracked): the pupil centre
  uniform over a 4 mm ellipse (a device on a head sits a little differently each time it is
  put on and slips while worn: a few mm, docs/design.md section 3), pupils 3 to 6 mm (indoor
  light levels; 4 mm nominal), focus at infinity (relaxed: the plate's depth of field makes
  accommodation a weak effect, measured on natural over 0 to 0.5 D: 22.4 to 22.3 dB for a
  part designed over the eyebox, 33.6 to 33.2 dB at the nominal point for a nominal-point
  part; states at one focus also share their display samples in the renderer, so sampling
  focus costs several times more; focus_range_diopters = [0, 0.5] adds it), no gaze rotation
  (the field is 44 deg and viewed mostly straight through; gaze_deg > 0 adds it with the
  eye's centre of rotation 11 mm behind the pupil);
- view 128 x 128 over the field the display covers from every pupil centre of the eyebox
  (44 deg; 53 deg from the nominal point alone: an eye 2 mm off the axis would see past the
  display's edge over the outer 5 deg, which no plate or display content can fix): about
  0.34 deg per view pixel, finer than the geometric blur of a hole (about 2r / h ~ 0.6 deg), so
  the model resolves it;
- Adam at 0.1 from a regular pinhole array (the cells between its holes open at a small
  hole), 150 iterations that all see the part as made (quantize_share 1: holes the process
  makes, a made copy's errors, diffraction and the material's veil; docs/model.md), with a
  light floor of 2 % (min_efficiency), stopping after 60 iterations without progress; 8 eye
  states per iteration: a state's cost is the renderer's, and 8 states reached about what 16
  do as made on natural (20.3 dB p10 at 2.4 % light against 20.7 at 2.2 %, both judged as made
  over 4 copies x 32 states, on the 0.25 mm cells);
  the loss is the mean over the worst half of each iteration's states (tail_share 0.5), which
  the report's p10 rewards: against the plain mean, +0.6 to +1.7 dB over the best regular
  array at the part's light on the digit, the letter and the line pattern, the same on the
  photo (README).

The "near-eye-nominal" preset is near-eye judged and optimized at its one nominal eye state
(the behaviour before eye distributions): the baseline that
shows what designing for a moving eye buys.

The "seed" preset is the 2022 dissertation's setting: a 28 x 28 aperture 1 cm from a 10 x 15 mm
source showing the target, SGD (lr 0.8, momentum 0.9) for 300 epochs from a random mask, with
the eye fixed at its nominal state.
"""

from __future__ import annotations

import copy
from typing import Any

from aperture_fab.optics.scene import Display, display_fov_deg, eyebox_margin_mm

__all__ = ["DEFAULT_PRESET", "PRESETS", "PRESET_DESCRIPTIONS", "preset_summary"]

DEFAULT_PRESET = "near-eye"

#: The default process and its plate: printed photomask film, whose opaque layer is its
#: emulsion, about 5 um thick (the 0.18 mm polyester base under it is clear).
DEFAULT_PROCESS = "photomask"
PHOTOMASK_EMULSION_MM = 0.005
#: The default brightness floor (optimizer.min_efficiency): 2 % of the open display's light.
LIGHT_FLOOR = 0.02

_SEED_WIDTH_MM = 10.0
_SEED_HEIGHT_MM = 15.0
_SEED_CELLS = 28

#: The [eye] distribution keys of a fixed eye: the nominal state only.
_NOMINAL_EYE: dict[str, Any] = {
    "eyebox_mm": [0.0, 0.0],
    "eyebox_shape": "ellipse",
    "pupil_range_mm": "nominal",
    "focus_range_diopters": "nominal",
    "gaze_deg": 0.0,
    "rotation_mm": 11.0,
}

#: The [display] optics keys of a display without them: no cover glass (its index unused),
#: every channel filling the pixel, Lambertian emission (docs/model.md "Display-side optics").
_PLAIN_DISPLAY: dict[str, Any] = {
    "cover_glass_mm": 0.0,
    "cover_glass_index": 1.5,
    "subpixels": "none",
    "emission": "lambertian",
    "emission_exponent": 1.0,
}

PRESETS: dict[str, dict[str, Any]] = {
    "near-eye": {
        "display": {"width_mm": 20.0, "height_mm": 20.0, "pixels": [400, 400],
                    **_PLAIN_DISPLAY},
        "plate": {
            "cells": [40, 40],
            "pitch_mm": [0.5, 0.5],
            "gap_mm": 10.0,
            "thickness_mm": PHOTOMASK_EMULSION_MM,
            # Tilted toward the eye: straight holes in a 0.3 mm plate vignette the field's edge
            # (offset t tan(theta) = 0.15 mm at 26 deg, as wide as a hole).
            "hole_axis": "chief_ray",
        },
        "eye": {
            "pupil_mm": 4.0,
            "eye_relief_mm": 10.0,
            "focus_mm": "infinity",
            "fov_deg": "display",
            "view_pixels": [128, 128],
            "positions_mm": [[0.0, 0.0]],
            "weights": [1.0],
            "eyebox_mm": [4.0, 4.0],
            "eyebox_shape": "ellipse",
            "pupil_range_mm": [3.0, 6.0],
            "focus_range_diopters": "nominal",
            "gaze_deg": 0.0,
            "rotation_mm": 11.0,
        },
        "optimizer": {
            "method": "adam",
            # 0.1 rather than 0.05: +0.5 to +0.9 dB p10 as made in 150 iterations (README)
            "learning_rate": 0.1,
            "momentum": 0.9,  # unused by Adam; kept so a switch to SGD has a sensible value
            "iterations": 150,
            "schedule": "cosine",
            "init": "pinholes",
            "init_diameter_mm": 0.0,  # the diffraction-optimal pinholes
            "display": "optimized",
            "efficiency_weight": 0.0,
            "min_efficiency": LIGHT_FLOOR,
            "min_eye_level": 0.0,
            "plateau_patience": 60,
            "plateau_tolerance": 1e-4,
            "seed": 0,
            "precision": "float32",
            "device": "auto",
            "checkpoint_every": 50,
            "quantize_share": 1.0,
            "eye_states": 8,
            # The worst half of the states: +0.6 to +1.7 dB over the best regular array at
            # the part's light on three of the four targets, the same on the photo (README)
            "tail_share": 0.5,
            "tracking": "untracked",
            # A part within 2 dB of a plain array is designed again on that array's lattice,
            # from its holes (README)
            "lattice": "rival",
        },
        "process": {"name": DEFAULT_PROCESS},
    },
    "seed": {
        "display": {
            "width_mm": _SEED_WIDTH_MM,
            "height_mm": _SEED_HEIGHT_MM,
            "pixels": [_SEED_CELLS, _SEED_CELLS],
            **_PLAIN_DISPLAY,
        },
        "plate": {
            "cells": [_SEED_CELLS, _SEED_CELLS],
            # The aperture covers the source exactly: one cell per source pixel.
            "pitch_mm": [_SEED_WIDTH_MM / _SEED_CELLS, _SEED_HEIGHT_MM / _SEED_CELLS],
            "gap_mm": 10.0,
            "thickness_mm": 0.2,
            "hole_axis": "straight",
        },
        "eye": {
            "pupil_mm": 4.0,
            "eye_relief_mm": 10.0,
            "focus_mm": "infinity",
            "fov_deg": "display",
            "view_pixels": [_SEED_CELLS, _SEED_CELLS],
            "positions_mm": [[0.0, 0.0]],
            "weights": [1.0],
            **_NOMINAL_EYE,
        },
        "optimizer": {
            "method": "sgd",
            "learning_rate": 0.8,
            "momentum": 0.9,
            "iterations": 300,
            "schedule": "constant",
            "init": "random",
            "init_diameter_mm": 0.0,
            "display": "target",
            "efficiency_weight": 0.0,
            "min_efficiency": 0.0,
            "min_eye_level": 0.0,
            "plateau_patience": 0,  # the dissertation always ran all 300 epochs
            "plateau_tolerance": 1e-4,
            "seed": 0,
            "precision": "float32",
            "device": "auto",
            "checkpoint_every": 50,
            "quantize_share": 0.3,
            "eye_states": 1,
            "tail_share": 1.0,
            "tracking": "untracked",
            "lattice": "fixed",  # the dissertation's plate
        },
    },
}
PRESETS["near-eye-nominal"] = copy.deepcopy(PRESETS["near-eye"])
PRESETS["near-eye-nominal"]["eye"].update(copy.deepcopy(_NOMINAL_EYE))
PRESETS["near-eye-nominal"]["optimizer"]["eye_states"] = 1
# The weighted mean over the eyebox positions, as before eye distributions.
PRESETS["near-eye-nominal"]["optimizer"]["tail_share"] = 1.0

PRESET_DESCRIPTIONS: dict[str, str] = {
    "near-eye": "Slim near-eye display: 20 mm, 500 ppi panel, 0.5 mm cells 10 mm in front, "
    "Adam, display content optimized, designed for a moving eye (4 mm eyebox, 3 to 6 mm "
    "pupil) (default).",
    "seed": "The 2022 dissertation's setting: 28 x 28 aperture 10 mm from a 10 x 15 mm source "
    "showing the target, SGD lr 0.8 momentum 0.9, 300 epochs from a random mask.",
    "near-eye-nominal": "near-eye designed for its one nominal eye state (4 mm pupil at the "
    "nominal position, relaxed): the behaviour before eye distributions, sharp there and "
    "not around it.",
}


def _check_name(name: str) -> dict[str, Any]:
    if name not in PRESETS:
        raise ValueError(
            f"preset = {name!r} is not a known preset; choose one of {', '.join(PRESETS)}."
        )
    return PRESETS[name]


def _mm(value: float) -> str:
    return f"{value:.4g}"


def _spread(bounds: Any, unit: str) -> str | None:
    """"3-6 mm" for a range that spreads, None for "nominal" or a single value."""
    if bounds == "nominal" or bounds[0] == bounds[1]:
        return None
    return f"{bounds[0]:g}-{bounds[1]:g} {unit}"


def _eye_states_line(eye: dict[str, Any], opt: dict[str, Any]) -> str:
    """What the eye distribution spreads over, and how the optimizer samples it."""
    parts = []
    width, height = eye["eyebox_mm"]
    if width or height:
        parts.append(f"eyebox {_mm(width)} x {_mm(height)} mm {eye['eyebox_shape']}")
    pupil = _spread(eye["pupil_range_mm"], "mm")
    if pupil:
        parts.append(f"pupil {pupil}")
    focus = _spread(eye["focus_range_diopters"], "D")
    if focus:
        parts.append(f"focus {focus}")
    if eye["gaze_deg"]:
        parts.append(f"gaze up to {eye['gaze_deg']:g} deg (rotation {_mm(eye['rotation_mm'])} mm)")
    spread = ", ".join(parts) if parts else "the nominal eye only"
    count = opt["eye_states"]
    tail = ("" if opt["tail_share"] == 1 else
            f", loss over the worst {100 * opt['tail_share']:g} %")
    return (f"  eye states {spread}; {count} state{'s' if count != 1 else ''} per iteration, "
            f"{opt['tracking']}{tail}")


def preset_summary(name: str) -> str:
    """A few lines with a preset's key numbers, for `aperture-fab presets`."""
    preset = _check_name(name)
    disp, plate, eye, opt = (preset[s] for s in ("display", "plate", "eye", "optimizer"))
    display = Display(disp["width_mm"], disp["height_mm"], tuple(disp["pixels"]))
    pitch = plate["pitch_mm"]
    pitch_x, pitch_y = (pitch, pitch) if isinstance(pitch, (int, float)) else pitch
    view_x, view_y = eye["view_pixels"]
    distance_mm = eye["eye_relief_mm"] + plate["thickness_mm"] + plate["gap_mm"]
    if eye["fov_deg"] == "display":
        margin = eyebox_margin_mm(tuple(eye["eyebox_mm"]), eye["gaze_deg"], eye["rotation_mm"])
        fov_x, fov_y = display_fov_deg(display, distance_mm, margin)
        fov = f"the display's field, {fov_x:.1f} x {fov_y:.1f} deg"
    else:
        fov_x, fov_y = eye["fov_deg"]
        fov = f"{fov_x:.1f} x {fov_y:.1f} deg"
    focus = eye["focus_mm"] if isinstance(eye["focus_mm"], str) else f"{eye['focus_mm']} mm"
    pixel_x_um, pixel_y_um = (1000 * p for p in display.pixel_mm)
    stop = (
        f"stop after {opt['plateau_patience']} iterations without progress"
        if opt["plateau_patience"] > 0 else "no early stop"
    )
    hole_window_px = pitch_x / display.pixel_mm[0]
    lines = [
        f"{name}: {PRESET_DESCRIPTIONS[name]}",
        f"  display    {_mm(disp['width_mm'])} x {_mm(disp['height_mm'])} mm, "
        f"{disp['pixels'][0]} x {disp['pixels'][1]} pixels "
        f"({pixel_x_um:.3g} x {pixel_y_um:.3g} um)",
        f"  plate      {plate['cells'][0]} x {plate['cells'][1]} cells, pitch "
        f"{_mm(pitch_x)} x {_mm(pitch_y)} mm (~{hole_window_px:.3g} display pixels), "
        f"gap {_mm(plate['gap_mm'])} mm, thickness {_mm(plate['thickness_mm'])} mm, "
        f"{plate['hole_axis']} holes",
        f"  eye        pupil {_mm(eye['pupil_mm'])} mm, eye relief {_mm(eye['eye_relief_mm'])} mm, "
        f"focus {focus}, display {_mm(distance_mm)} mm from the pupil, "
        f"{len(eye['positions_mm'])} position(s)",
        _eye_states_line(eye, opt),
        f"  view       {view_x} x {view_y} pixels over {fov} "
        f"({fov_x / view_x:.2f} x {fov_y / view_y:.2f} deg per pixel)",
        f"  optimizer  {opt['method']} lr {opt['learning_rate']:g}"
        + (f" momentum {opt['momentum']:g}" if opt["method"] == "sgd" else "")
        + f", {opt['iterations']} iterations, {opt['schedule']} schedule, {stop}, "
        f"init {opt['init']}, display {opt['display']}",
    ]
    return "\n".join(lines)
