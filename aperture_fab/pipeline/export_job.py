"""The export job: a saved design's open fractions made into a part for a process, written as
one part file or a folder of every format."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from aperture_fab.config.config import Config, parse_toml, resolve
from aperture_fab.config.stages import FabricationSettings
from aperture_fab.fabrication.part import Part, make_part
from aperture_fab.fabrication.rules import check_plate
from aperture_fab.io.atomic import write_atomic
from aperture_fab.io.files import output_folder, read_text
from aperture_fab.io.formats import (
    PART_FILE_SUFFIXES,
    PART_FORMATS,
    PartFormat,
    part_files,
)
from aperture_fab.io.manifest import refuse_overwrite
from aperture_fab.pipeline.design_files import write_part
from aperture_fab.pipeline.saved import check_sources, read_design

__all__ = ["Exported", "export", "part_format_of", "read_export_inputs", "run_export"]


@dataclass(frozen=True)
class Exported:
    """An export's part and the files written (in the order written)."""

    part: Part
    written: tuple[Path, ...]


def part_format_of(out: Path, allowed: tuple[str, ...], label: str = "--out"
                   ) -> PartFormat | None:
    """The part format a path `out` names, or None when it is a folder: an existing folder or a
    name without a suffix. Any other suffix than `allowed` is refused (not made a folder of that
    name, which is what a typo such as plate.stk would otherwise give); `label` names the
    argument in the message."""
    suffix = out.suffix.lower()
    if not suffix or out.is_dir():
        return None
    if suffix not in allowed:
        raise ValueError(
            f"{label} {out}: {out.suffix!r} is not a part file suffix; allowed: "
            f"{' '.join(allowed)} (that one file), or a folder without a suffix (every "
            f"format). Give e.g. {label} {out.with_suffix('.stl')} (a file) or {label} "
            f"{out.with_suffix('')} (a folder).")
    return next(f for f in PART_FORMATS.values() if suffix in f.suffixes)


def read_export_inputs(design: Path, config_path: Path, preset: str | None
                       ) -> tuple[np.ndarray, Config]:
    """The open fractions (rows, cols) of a saved design.npz and the config it was made with
    (its design.toml, over `preset`), checked to belong together."""
    open_fraction = read_design(design).open_fraction  # checked: a whole file, 0..1
    try:
        text = read_text(config_path, "the design's config", "give the design's design.toml "
                         "with --config.")
    except OSError as err:
        raise ValueError(f"{config_path}: cannot read the design's config ({err.strerror}); give "
                         "it with --config.") from err
    config = resolve(preset, parse_toml(text, str(config_path)), file_source=str(config_path))
    check_sources(config_path, design, "design")
    return open_fraction, config


def run_export(open_fraction: np.ndarray, config: Config, fabrication: FabricationSettings,
               out: Path, file_format: PartFormat | None, *, progress: bool = False,
               stage: Callable[[str], None] = lambda line: None) -> Exported:
    """Make the part and write it: `file_format` given, the one file `out` (its folder is its
    parent); None, every format (STEP when fabrication.step) into the folder `out`."""
    folder = output_folder(out.parent if file_format else out)
    formats = ((file_format.name,) if file_format else
               tuple(name for name in PART_FORMATS if name != "step" or fabrication.step))
    refuse_overwrite(folder, [out.name] if file_format else
                     [PART_FORMATS[name].file_name for name in formats])
    part = make_part(open_fraction, config.scene, fabrication)
    stage(f"writing {', '.join(formats)} for {part.layout.count} holes")
    if file_format:
        # Written straight under the name given: a rename afterwards could replace a file of
        # the standard name (plate.stl) that a design left in the same folder.
        write_atomic(out, part_files(part, formats, fabrication)[file_format.file_name])
        return Exported(part, (out,))
    return Exported(part, tuple(write_part(folder, part, fabrication, formats,
                                           progress=progress)))


def export(design: Path, out: Path, *, process: str | None = None, step: bool = False,
           force: bool = False, config_path: Path | None = None, preset: str | None = None,
           progress: bool = False) -> Exported:
    """The `aperture-fab export` job: the part of a saved design (design.npz, with the
    design.toml beside it unless `config_path`) for `process` (default: the one design.toml
    records), written as the one file `out` names (plate.stl, .3mf, .step, .dxf, .svg, ...) or,
    for a folder, in every format (STEP with `step`). A process that cannot make the design's
    plate raises UnmakeableError unless `force`."""
    design, out = Path(design), Path(out)
    open_fraction, config = read_export_inputs(
        design, config_path if config_path is not None else design.parent / "design.toml", preset)
    fabrication = config.fabrication.with_flags(process, force or None, step or None)
    if not fabrication.force:
        check_plate(fabrication.process, config.scene.plate, config.scene.eye.eye_relief_mm)
    file_format = part_format_of(out, PART_FILE_SUFFIXES, "out =")
    return run_export(open_fraction, config, fabrication, out, file_format, progress=progress)
