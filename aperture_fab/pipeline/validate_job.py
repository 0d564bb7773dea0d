"""The `aperture-fab validate` job: an existing part (a design.npz, a hole table or an STL,
edited or not) judged for a config and its targets, with the report written beside it.

The part a design wrote (its holes read back from the STL or holes.csv, or design.npz itself)
is judged exactly as `design` judged it: the same part, the display content the design ships
with it, the same validation, so both print the same figures and verdicts. The display is
software and follows the plate: a part that differs from the design's (an edited hole table, a
mesh of another design, another process) gets its display content re-fitted to it with the
same loss `design` uses (the part as made), starting from the design's content when a
design.npz lies beside the config.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np

from aperture_fab.config.config import Config
from aperture_fab.config.stages import FabricationSettings
from aperture_fab.fabrication.part import Part, made_optics, make_part
from aperture_fab.fabrication.process import Process, UnmakeableError
from aperture_fab.io.atomic import write_atomic
from aperture_fab.io.files import load_targets, output_folder
from aperture_fab.io.formats import PART_FORMATS
from aperture_fab.io.images import TargetOptions, encode_png, prepare_targets
from aperture_fab.io.manifest import publish, staging
from aperture_fab.optimize.optimizer import fit_display
from aperture_fab.pipeline.design_job import FIT_SHARE, MIN_FIT_ITERATIONS
from aperture_fab.pipeline.judged_folder import default_cache
from aperture_fab.pipeline.saved import (
    CONFIG_NAME,
    DESIGN_NAME,
    PartKind,
    SavedDesign,
    check_design,
    design_beside,
    load_part,
    measured_scan,
    part_kind,
    read_config,
)
from aperture_fab.validation.report import Report, report_json
from aperture_fab.validation.validate import Validation, layout_fractions, validate

__all__ = ["DisplaySource", "RecheckResult", "run_validate"]

#: The command a manifest names when the Python API, not the command line, ran the job.
VALIDATE_COMMAND = ("python", "-c", "aperture_fab.pipeline.validate_job.run_validate(...)")
#: Display content: fitted to the part, kept from the design, or the targets themselves.
DisplaySource = Literal["fitted", "kept", "targets"]
#: Holes read back from a written part (an STL's float32 vertices, holes.csv's six decimals)
#: that lie this close to the design's own, in centre and radius (mm), are the design's part.
SAME_HOLES_MM = 1e-4


@dataclass(frozen=True)
class RecheckResult:
    """What `run_validate` did.

    folder: where report.json, report.html, views.npz and display_<target>.png were written.
    kind: the part's kind. names: (T,) target names. part: the part checked (layout, mesh).
    validation: views and metrics. display_source: where the display content came from.
    timings_s: seconds per stage. report: the judged part as report.json holds it (its verdicts
    decide the exit status).
    """

    folder: Path
    kind: PartKind
    names: tuple[str, ...]
    part: Part
    validation: Validation
    display_source: DisplaySource
    timings_s: dict[str, float]
    report: Report


def design_part(design: SavedDesign, loaded: Part, config: Config,
                fabrication: FabricationSettings) -> Part | None:
    """The part the design made, when `loaded` holds its holes (every hole in the same cell,
    centre and radius within SAME_HOLES_MM), else None: an edited table, another design's
    mesh, another process."""
    try:
        own = make_part(design.open_fraction, config.scene, fabrication)
    except ValueError:  # a part made with --force, or another process
        return None
    a, b = loaded.layout, own.layout
    if a.count != b.count:
        return None
    order_a = np.lexsort((a.cells[:, 1], a.cells[:, 0]))
    order_b = np.lexsort((b.cells[:, 1], b.cells[:, 0]))
    same = (np.array_equal(a.cells[order_a], b.cells[order_b])
            and np.allclose(a.radii_mm[order_a], b.radii_mm[order_b], rtol=0, atol=SAME_HOLES_MM)
            and np.allclose(a.centres_mm[order_a], b.centres_mm[order_b], rtol=0,
                            atol=SAME_HOLES_MM))
    return own if same else None


def _display_content(config: Config, targets: np.ndarray, on_display: np.ndarray,
                     as_built: np.ndarray, design: SavedDesign | None, keep: bool,
                     process: Process, progress: bool
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, DisplaySource]:
    """(designed, shown, fit loss history, source): the content the design was optimized with
    and the content shown with the part (both (T, C, H, W)); a re-fit uses the loss `design`
    uses, the part as `process` makes it."""
    settings = config.optimizer
    if settings.display == "target":
        return on_display, on_display, np.zeros(0), "targets"
    if design is None:
        if keep:
            raise ValueError(f"--keep-display needs the design's display content, but there is "
                             f"no {DESIGN_NAME} beside the config; drop --keep-display to fit "
                             "the display to the part.")
        designed = start = on_display
    else:
        designed = design.optimum[1]
        start = design.built_displays if design.built_displays is not None else design.displays
    if keep:
        return designed, start, np.zeros(0), "kept"
    try:
        optics = made_optics(config.scene, process) if settings.quantize_share > 0 else None
    except UnmakeableError:  # the process makes no hole in this plate's cells
        optics = None
    iterations = max(MIN_FIT_ITERATIONS, settings.iterations // FIT_SHARE)
    fitted, history = fit_display(config.scene, targets, as_built, start, settings, iterations,
                                  optics=optics, progress=progress)
    return designed, fitted, history, "fitted"


def _refuse_design_folder(folder: Path) -> None:
    """validate publishes its report as a set of its own (with its manifest, replacing the tool
    files it did not write): in a design's folder that would replace the design's report and
    remove its part files."""
    design_files = ("design.toml", "design.npz", *(f.file_name for f in PART_FORMATS.values()))
    found = [name for name in design_files if (folder / name).exists()]
    if found:
        raise ValueError(
            f"--out {folder} holds a design ({', '.join(found[:3])}); validate writes its report "
            "as a set of its own there. Give a new folder (the default is validate_<part> "
            "beside the part).")


def run_validate(
    part: Path,
    targets: Sequence[Path],
    *,
    target_options: TargetOptions | None = None,
    config_path: Path | None = None,
    out: Path | None = None,
    process: str | None = None,
    keep_display: bool = False,
    tolerance_samples: int | None = None,
    mesh_samples: int | None = None,
    progress: bool = False,
    stage: Callable[[str], None] | None = None,
    command: Sequence[str] | None = None,
) -> RecheckResult:
    """The `aperture-fab validate` job: validate a part (design.npz, holes.csv or STL) for the
    config and targets; write report.json, report.html, views.npz and display_<target>.png
    into `out` (default: validate_<part stem> beside the part).

    config_path: default design.toml beside the part. process: overrides the config's
    [process] name. keep_display: show design.npz's display content unchanged instead of
    re-fitting it to the part (the design's own part keeps it always). tolerance_samples,
    mesh_samples: override [validation].
    stage: called with a line as each stage starts (for logs, where there are no progress bars).
    """
    from aperture_fab.report.evidence import assemble
    from aperture_fab.validation.judge import judge

    start = time.perf_counter()
    kind = part_kind(part)
    config_path = config_path if config_path is not None else part.parent / CONFIG_NAME
    config = read_config(config_path)
    fabrication = config.fabrication.with_flags(process=process)
    settings = config.validation.with_flags(tolerance_samples=tolerance_samples,
                                            mesh_samples=mesh_samples)
    images, names = load_targets(targets, config.scene.display.pixels, target_options)
    design = design_beside(config_path, part, kind)
    if design is not None:
        check_design(design, config, config_path)
        if len(design.displays) != len(images):
            raise ValueError(
                f"{design.path} was designed for {len(design.displays)} target(s) "
                f"({', '.join(design.names)}) but {len(images)} were given; give "
                f"{len(design.displays)} target(s) in the design's order.")
    loaded = load_part(part, kind, config, fabrication, config_path)
    if kind != "design" and loaded.layout.count == 0:
        # A cube, a blank plate or an empty table: validating it would "pass" with a black view.
        raise ValueError(
            f"no holes found in {part}: this is not a plate of the config's grid "
            f"({config.scene.plate.cells[0]} x {config.scene.plate.cells[1]} cells, from "
            f"{config_path}). Give the part the design wrote (plate.stl or holes.csv), or the "
            "config it was made with (--config).")
    own = None if design is None else design_part(design, loaded, config, fabrication)
    if own is not None:  # judged as design judged it: its part, with the mesh as given
        loaded = replace(own, mesh=loaded.mesh)
        keep_display = True
    folder = output_folder(out if out is not None else part.parent / f"validate_{part.stem}")
    _refuse_design_folder(folder)
    view_targets, on_display = prepare_targets(
        images, config.scene.eye.view_pixels, config.scene.display.pixels,
        None if design is None else design.displays.shape[1], names=[str(t) for t in targets])
    as_built = layout_fractions(loaded.layout, fabrication.process.radius_bias_mm)
    timings = {"load_s": time.perf_counter() - start}
    start = time.perf_counter()
    if stage is not None and not keep_display:
        stage(f"validate: fitting the display content to the part's {loaded.layout.count} holes")
    designed, shown, fit_history, source = _display_content(
        config, view_targets, on_display, as_built, design, keep_display, fabrication.process,
        progress)
    timings["fit_display_s"] = time.perf_counter() - start
    open_fraction = (design.optimum[0] if design is not None
                     else layout_fractions(loaded.layout))
    if stage is not None:
        stage("validate: the part as built, its tolerances, the mesh and diffraction")
    checked = validate(config, view_targets, designed, open_fraction, loaded,
                       fabrication.process, tuple(names), settings, loaded.mesh,
                       built_displays=shown, cache=default_cache())
    history = (design.loss_history if design is not None and design.loss_history.size
               else fit_history)
    if history.size == 0:  # nothing was optimized here: the loss of the part as it is
        history = np.array([checked.metrics["as_built"][names[0]]["mse"]])
    start = time.perf_counter()
    # A plate measured from a scan (`aperture-fab measure`): the report says so and names it.
    scan = measured_scan(config_path.parent)
    part_file = part.name if scan is None else (f"{part.name}, the plate as made, measured "
                                                f"from the scan {scan}")
    report = judge(config, tuple(names), view_targets, shown, loaded, fabrication.process,
                   checked, timings, part_file=part_file, command=command)
    evidence = assemble(report, tuple(names), view_targets, shown, history, loaded, checked)
    report = replace(
        evidence.report.with_timing("report_s", time.perf_counter() - start),
        checked_part={"path": str(part), "kind": kind, "config": str(config_path),
                      "display": source,
                      "design": None if design is None else str(design.path),
                      "measured_from_scan": scan})
    with staging(folder) as staged:
        write_atomic(staged / "views.npz", evidence.views_npz)
        write_atomic(staged / "report.html", evidence.html)
        write_atomic(staged / "report.json", report_json(report))
        for name, content in zip(names, shown, strict=True):
            write_atomic(staged / f"display_{name}.png", encode_png(np.clip(content, 0, 1)))
        publish(staged, folder, command if command is not None else VALIDATE_COMMAND)
    return RecheckResult(folder, kind, tuple(names), loaded, checked, source,
                         dict(report.timings_s), report)
