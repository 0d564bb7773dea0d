"""A resolved Config written back: as a plain dict (report.json's config) and as TOML (design.toml),
every value explicit, so that `--config design.toml` re-runs a design exactly."""

from __future__ import annotations

from typing import Any

import tomlkit

from aperture_fab.config.config import DISPLAY_FOV, INFINITY, NOMINAL, SECTION_KEYS, Config
from aperture_fab.config.stages import written_tables

__all__ = ["TOML_HEADER", "to_dict", "to_toml"]


def _range_value(bounds: tuple[float, float] | None) -> Any:
    return NOMINAL if bounds is None else list(bounds)


def to_dict(config: Config) -> dict[str, Any]:
    """The fully resolved config as plain dicts and lists, in the TOML file's shape: every value
    explicit, so a written config re-runs the same even if a default changes; only a field of
    view derived from the geometry stays "display", so it follows a changed gap or eyebox."""
    display, plate, eye = config.scene.display, config.scene.plate, config.scene.eye
    opt = config.optimizer
    sections: dict[str, dict[str, Any]] = {
        "display": {"width_mm": display.width_mm, "height_mm": display.height_mm,
                    "pixels": list(display.pixels),
                    **{key: getattr(display, key) for key in SECTION_KEYS["display"][3:]}},
        "plate": {"cells": list(plate.cells), "pitch_mm": list(plate.pitch_mm),
                  "gap_mm": plate.gap_mm, "thickness_mm": plate.thickness_mm,
                  "hole_axis": plate.hole_axis},
        "eye": {"pupil_mm": eye.pupil_mm, "eye_relief_mm": eye.eye_relief_mm,
                "focus_mm": INFINITY if eye.focus_mm is None else eye.focus_mm,
                "fov_deg": DISPLAY_FOV if config.fov_from_display else list(eye.fov_deg),
                "view_pixels": list(eye.view_pixels),
                "positions_mm": [list(p) for p in eye.positions_mm],
                "weights": list(eye.weights), "eyebox_mm": list(eye.eyebox_mm),
                "eyebox_shape": eye.eyebox_shape,
                "pupil_range_mm": _range_value(eye.pupil_range_mm),
                "focus_range_diopters": _range_value(eye.focus_range_diopters),
                "gaze_deg": eye.gaze_deg, "rotation_mm": eye.rotation_mm},
        "optimizer": {key: getattr(opt, key) for key in SECTION_KEYS["optimizer"]},
    }
    tables = written_tables(config.fabrication, config.validation, config.photometry,
                            config.part_outline_mm)
    return {"preset": config.preset, **sections, **tables}


#: The first line of a written config.
TOML_HEADER = ("# aperture-fab configuration, fully resolved: every value explicit (fov_deg in "
               'degrees, or "display": derived from the geometry, its value in the comment).')


def to_toml(config: Config) -> str:
    """The fully resolved config as TOML text; resolving the parsed text gives `config` back."""
    # tomlkit writes a table's keys one per line before its sub-tables, arrays on one line,
    # floats as repr (the shortest text that reads back to the same float) and escapes what
    # TOML requires. The checkpoint's config digest (pipeline.checkpoint.input_digests) hashes
    # this text: tests/test_config.py holds the layout, so a tomlkit upgrade that changed it
    # is seen before it makes checkpoints refuse --resume.
    document = tomlkit.item(to_dict(config))
    if config.fov_from_display:
        fov_x, fov_y = config.scene.eye.fov_deg
        document["eye"]["fov_deg"].comment(f"{fov_x:.2f} x {fov_y:.2f} deg here")
    return f"{TOML_HEADER}\n{tomlkit.dumps(document)}"
