"""The design job: targets in, an optimized plate and its evidence out.

`design` is the Python API (values in, values out, no files). `run_design` is the same job on
files: it reads the targets, writes every output atomically, checkpoints, and resumes.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from aperture_fab.config.config import Config
from aperture_fab.config.settings import OptimizerSettings
from aperture_fab.config.stages import FabricationSettings, ValidationSettings
from aperture_fab.fabrication.part import Part, design_bounds, made_optics, make_part
from aperture_fab.fabrication.quantize import made_sizes
from aperture_fab.fabrication.rules import check_plate
from aperture_fab.io.atomic import write_atomic
from aperture_fab.io.files import created_folder, load_targets
from aperture_fab.io.formats import FormatName
from aperture_fab.io.images import TargetOptions, prepare_targets
from aperture_fab.io.manifest import publish, remove_listed, staging
from aperture_fab.metrics import gain_mse, psnr_db
from aperture_fab.optics.as_made import white_transmission
from aperture_fab.optics.device import resolve_device, torch_dtype
from aperture_fab.optics.model import Renderer
from aperture_fab.optics.open_view import render_open
from aperture_fab.optics.scene import Scene
from aperture_fab.optimize.optimizer import (
    Interrupted,
    MaskDesign,
    fit_display,
    optimize,
    training_states,
)
from aperture_fab.optimize.start import initial_design
from aperture_fab.pipeline.checkpoint import (
    CHECKPOINT_NAME,
    input_digests,
    resume_state,
    save_checkpoint,
    sha256,
)
from aperture_fab.pipeline.design_files import (
    design_outputs,
    evidence_files,
    judge_written,
    part_bytes,
    part_formats,
    summary_json,
)
from aperture_fab.pipeline.judged_folder import default_cache
from aperture_fab.pipeline.lattices import better_part, margin_db, rival_start
from aperture_fab.pipeline.saved import validations_of
from aperture_fab.validation.judged_cache import JudgedCache
from aperture_fab.validation.report import Report, Verdict, eye_headline
from aperture_fab.validation.validate import (
    Validation,
    baseline_views,
    judge_made_part,
    layout_fractions,
)
from aperture_fab.validation.verdicts import (
    with_tried_lattice,
)

if TYPE_CHECKING:
    from aperture_fab.report.evidence import Evidence

__all__ = ["DesignResult", "check_light_floor", "design", "recorded_config", "run_design"]

#: The display is re-fitted to the part as built for this share of the design's iterations.
FIT_SHARE = 3
MIN_FIT_ITERATIONS = 20
#: design.toml records the outline to 1 nm (holes.csv's precision).
OUTLINE_DECIMALS = 6
#: The command a manifest names when the Python API, not the command line, ran the job.
DEFAULT_COMMAND = ("python", "-c", "aperture_fab.pipeline.design_job.run_design(...)")


@dataclass(frozen=True)
class DesignResult:
    """Everything the design job produced, as values (run_design writes them).

    config: the config as design.toml records it (`recorded_config`).
    design: the optimized plate and display content.
    names: (T,) target names.
    targets: (T, C, ny, nx) float64 linear targets on the view grid.
    views: {"initial" | "optimized" | "open" | "regular_pinholes": (T, P, C, ny, nx) float64}
        for every target and eyebox position.
    metrics: {variant: {"psnr_db": [per target], "mse": [per target]}} at the nominal position;
        with the part judged (validation settings) also "quantized" and "as_built", and
        "eye_distribution": the part and the baselines over the eye distribution
        (report.eye_headline: percentiles per variant and target, and the verdict), or None
        when validation did not judge it.
    part: the part as made (None when no fabrication settings were given).
    built_displays: (T, C, H, W) display content fitted to the part as made: optimized with the
        snapped plate, or re-fitted to the part when no iteration saw it (None when the display
        shows the targets, or without a part): what the device should show.
    timings_s: seconds per stage.
    part_files: the part's files, file name -> bytes (plate.stl, plate.3mf, ...;
        empty without a part).
    report: the judged part (verdicts and report.json's content) when it was judged
        (`design`'s validation settings): what the CLI prints and the sweep tabulates; None
        otherwise.
    report_files: that report's files, name -> bytes (report.json, report.html, views.npz;
        empty when not judged).
    lattices: when the job designed on two lattices (optimizer.lattice = "rival", `design`),
        each one's plate and part as made: {"pitch_mm", "cells", "p10_db", "margin_db" (per
        target, over its own best regular array), "kept" (the part this result holds)}, the
        config's own lattice first; empty when it designed on one.
    evidence: the judged part's figures and page, from which report_files are made (None when
        not judged).
    made_part: report.json's "made_part" block (`validate.judge_made_part`): the part as made
        beside its best regular array, or None when not judged; with optimizer.lattice = "rival"
        judged first, alone, to choose the lattice (a first part the second replaces is judged
        no further).
    """

    config: Config
    design: MaskDesign
    names: tuple[str, ...]
    targets: np.ndarray
    views: dict[str, np.ndarray]
    metrics: dict[str, Any]
    part: Part | None = None
    built_displays: np.ndarray | None = None
    timings_s: dict[str, float] = field(default_factory=dict)
    part_files: dict[str, bytes] = field(default_factory=dict)
    report: Report | None = None
    report_files: dict[str, bytes] = field(default_factory=dict)
    lattices: tuple[dict[str, Any], ...] = ()
    evidence: Evidence | None = None
    made_part: dict[str, Any] | None = None

    @property
    def verdicts(self) -> tuple[Verdict, ...]:
        """The report's findings, most important first; empty when the part was not judged."""
        return () if self.report is None else self.report.verdicts


def design(
    images: Sequence[np.ndarray],
    config: Config,
    *,
    names: Sequence[str] | None = None,
    fabrication: FabricationSettings | None = None,
    validation: ValidationSettings | None = None,
    formats: Sequence[FormatName] | None = None,
    command: Sequence[str] | None = None,
    state: dict[str, Any] | None = None,
    on_checkpoint: Callable[[dict[str, Any]], None] | None = None,
    progress: bool = False,
    stage: Callable[[str], None] | None = None,
) -> DesignResult:
    """Design a plate for target images (each (3, H, W) linear RGB in [0, 1]); with
    `fabrication`, designed within what its process can make, made into a part and its files
    (`formats`; default every format, STEP only with fabrication.step) and, with `validation`,
    judged as written (the STL's bytes parsed again): the report's values and files. Nothing
    is written; `run_design` writes the result. command: what the report says ran it.
    stage: told each stage after the optimizer as it starts, in words.

    With optimizer.lattice = "rival" (the default), a part as made that beats the best regular
    pinhole array of a coarser pitch by less than `verdicts.RETRY_LATTICE_BELOW_DB` is designed
    again on that array's lattice, from that array's holes (`lattices.rival_start`), and the
    part with the larger margin over its own best regular array is kept (`lattices` says
    both). The first part is judged as made alone to choose (`made_part`); one the second
    replaces is neither written nor judged further. The second design is not checkpointed:
    interrupted, the job stops and --resume starts again from the first design's checkpoint."""
    if not images:
        raise ValueError("no targets given; pass at least one image.")
    if validation is not None and formats is not None and "stl" not in formats:
        raise ValueError(f"formats = {list(formats)}: the validation judges the part's STL as "
                         'written; add "stl" to formats, or validation = None.')
    names = tuple(names) if names is not None else tuple(f"target{i}" for i in range(len(images)))
    made = functools.partial(_made, images, names=names, fabrication=fabrication,
                             progress=progress,
                             cache=default_cache() if validation is not None else None)
    finish = functools.partial(_finish, fabrication=fabrication, validation=validation,
                               formats=formats, command=command, progress=progress, stage=stage)
    first = made(config, state=state, on_checkpoint=on_checkpoint)
    if config.optimizer.lattice != "rival":
        return finish(first)
    # The part as made judged alone first: a part the second design replaces needs no more.
    first = _judged_as_made(first, fabrication, validation, stage)
    block = first.made_part
    start = rival_start(config.scene, config.optimizer, block) if block else None
    if start is None or not block:
        return finish(first)
    moved = dataclasses.replace(config, scene=start[0], optimizer=start[1])
    plate = config.scene.plate
    given = {"pitch_mm": list(plate.pitch_mm), "cells": list(plate.cells),
             "margin_db": block["margin_db"]}
    if stage is not None:
        nx, ny = moved.scene.plate.cells
        stage(f"design: the part as made is {margin_db(first):+.1f} dB against a regular "
              f"array of {moved.scene.plate.pitch_mm[0]:g} mm pitch; "
              f"designing again on its lattice ({nx} x {ny} cells) from its holes")
    try:
        second = finish(made(moved), replaces=given)
    except Interrupted:
        raise KeyboardInterrupt from None  # the first design's checkpoint stays for --resume
    if margin_db(second) > margin_db(first):
        return better_part(first, second)
    result = better_part(finish(first), second)
    if result.evidence is not None:
        # The first part kept: its report says what the job tried instead (page drawn again).
        tried = {key: result.lattices[1][key] for key in ("pitch_mm", "cells", "margin_db")}
        evidence = result.evidence.with_report(with_tried_lattice(result.evidence.report,
                                                                  tried))
        result = dataclasses.replace(result, report=evidence.report, evidence=evidence,
                                     report_files=evidence_files(evidence))
    return result


def _made(
    images: Sequence[np.ndarray],
    config: Config,
    *,
    names: tuple[str, ...],
    fabrication: FabricationSettings | None = None,
    state: dict[str, Any] | None = None,
    on_checkpoint: Callable[[dict[str, Any]], None] | None = None,
    progress: bool = False,
    cache: JudgedCache | None = None,
) -> DesignResult:
    """The plate designed on the config's own lattice, made into a part with the process
    (quantized and built; its display fitted to it), neither written nor judged. cache: keeps
    the baselines' views between runs (`evaluate`)."""
    scene, settings = config.scene, config.optimizer
    bounds = made = optics = None
    if fabrication is not None:
        if not fabrication.force:
            # Refused before optimizing, naming the settings with which the process makes it.
            check_plate(fabrication.process, scene.plate, scene.eye.eye_relief_mm)
            if settings.quantize_share > 0:
                made = made_sizes(scene.plate, fabrication.process, scene.mid_plane_distance_mm)
                optics = made_optics(scene, fabrication.process)
        bounds = design_bounds(scene, fabrication.process)
    check_light_floor(scene, settings, bounds, fabrication)
    check_eye_sees_display(scene)
    targets, shown = prepare_targets(list(images), scene.eye.view_pixels, scene.display.pixels,
                                     names=names)
    timings = {}
    start = time.perf_counter()
    result = optimize(scene, targets, shown, settings, bounds=bounds, made=made, optics=optics,
                      state=state, on_checkpoint=on_checkpoint, progress=progress)
    timings["optimize_s"] = time.perf_counter() - start
    start = time.perf_counter()
    renderer = Renderer(scene, device=resolve_device(settings.device),
                        dtype=torch_dtype(settings.precision))
    views, metrics = evaluate(renderer, targets, {
        "initial": initial_design(scene, targets, shown, settings, bounds),
        "optimized": result.optimum,
    }, cache)
    timings["evaluate_s"] = time.perf_counter() - start
    start = time.perf_counter()
    part = None if fabrication is None else make_part(result.open_fraction, scene, fabrication)
    timings["quantize_build_s"] = time.perf_counter() - start
    built = None
    if part is not None and settings.display == "optimized" and result.snapped:
        built = result.displays  # optimized for the holes as made
    elif part is not None and settings.display == "optimized" and settings.iterations > 1:
        # The plate is hardware and the display software: fit the display to the part as it
        # will be made (quantized holes, the process's radius bias).
        start = time.perf_counter()
        as_built = layout_fractions(part.layout, fabrication.process.radius_bias_mm
                                    if fabrication is not None else 0.0)
        built, _ = fit_display(scene, targets, as_built, result.displays, settings,
                               max(MIN_FIT_ITERATIONS, settings.iterations // FIT_SHARE),
                               optics=optics, progress=progress)
        timings["fit_display_s"] = time.perf_counter() - start
    return DesignResult(recorded_config(config, None), result, names, targets, views, metrics,
                        part, built, timings)


def _judged_as_made(result: DesignResult, fabrication: FabricationSettings | None,
                    validation: ValidationSettings | None,
                    stage: Callable[[str], None] | None = None) -> DesignResult:
    """The result with its part as made judged beside its best regular array (`made_part`),
    when there are a part and validation settings; nothing else judged or written."""
    if result.part is None or fabrication is None or validation is None:
        return result
    if stage is not None:
        stage("design: judging the part as made against the best regular pinhole arrays")
    start = time.perf_counter()
    shown = result.design.optimum[1] if result.built_displays is None else result.built_displays
    block = judge_made_part(result.config.scene, result.config.optimizer, result.targets,
                            result.part, fabrication.process, shown, validation, default_cache())
    timings = {**result.timings_s, "made_part_s": time.perf_counter() - start}
    return dataclasses.replace(result, made_part=block, timings_s=timings)


def _finish(
    result: DesignResult,
    *,
    fabrication: FabricationSettings | None = None,
    validation: ValidationSettings | None = None,
    formats: Sequence[FormatName] | None = None,
    command: Sequence[str] | None = None,
    progress: bool = False,
    stage: Callable[[str], None] | None = None,
    replaces: dict[str, Any] | None = None,
) -> DesignResult:
    """A made design's part written (`formats`; default every format, STEP only with
    fabrication.step) and, with `validation`, judged as written, its made-part block kept when
    judged already (`_judged_as_made`); replaces: the part on the given cells this one
    replaces, for its report (`aperture_fab.validation.judge.run_block`)."""
    part = result.part
    if part is None or fabrication is None:
        return result
    announce = stage if stage is not None else (lambda _line: None)
    formats = tuple(formats) if formats is not None else part_formats(fabrication)
    announce(f"design: writing {', '.join(formats)} ({part.layout.count} holes)")
    start = time.perf_counter()
    files = part_bytes(part, fabrication, formats, progress)
    written = dataclasses.replace(
        result, config=recorded_config(result.config, fabrication, formats,
                                       part.layout.outline_mm),
        timings_s={**result.timings_s, "export_s": time.perf_counter() - start},
        part_files=files)
    if validation is None:
        return written
    announce("design: validating the part as written (eye distribution, mesh re-trace, "
             "tolerances)")
    checked, evidence = judge_written(written, fabrication, validation, files["plate.stl"],
                                      command, replaces, result.made_part)
    return _with_judgement(written, checked, evidence)


#: Pupil points of the quick look check_eye_sees_display takes.
SEEN_PUPIL_SAMPLES = 8


def check_eye_sees_display(scene: Scene) -> None:
    """Refuse, before the work, an eye position (eye.positions_mm) from which no light of the
    display reaches the pupil even with no plate: every view there is black, so the optimizer
    has nothing to fit and the design would be empty (render refuses such an --eye too)."""
    white = torch.ones((1, scene.display.pixels[1], scene.display.pixels[0]),
                       dtype=torch.float64)
    for position, (x, y) in enumerate(scene.eye.positions_mm):
        with torch.no_grad():
            # A few pupil points say at once that light arrives; the full quadrature
            # (seconds for a large scene) confirms only a black answer.
            seen = float(render_open(scene, white, position, SEEN_PUPIL_SAMPLES, 1).mean())
            if not seen > 0:
                seen = float(render_open(scene, white, position).mean())
        if not seen > 0:
            half_width, half_height = scene.display.width_mm / 2, scene.display.height_mm / 2
            raise ValueError(
                f"eye.positions_mm holds ({x:g}, {y:g}) mm, from where the eye sees no light "
                "from the display, even with no plate (it is outside the cone of light the "
                f"display sends; the display spans +-{half_width:g} x +-{half_height:g} mm "
                "around the axis). Give positions near the axis, e.g. positions_mm = [[0, 0]].")


#: check_light_floor first renders sparse plates: one cell in stride x stride at its largest
#: hole, the rest closed. A view is a sum of one non-negative term per open hole (its area,
#: the share the pupil takes, the white display's level), each read from that hole's radius
#: alone, so a sparse plate passes no more light than the brightest plate: when it already
#: reaches the floor, the floor is met, at a fraction of the cost (the kernel's work follows
#: the open holes). Strides tried in turn; the full plate decides the rest and is the only one
#: that can refuse.
FLOOR_SCREEN_STRIDES = (4, 2)
#: Rounding slack for that bound (the white display's pre-filtered level may round below 0).
FLOOR_SCREEN_SLACK = 1e-9


def _white_reach(renderer: Renderer, scene: Scene, settings: OptimizerSettings, top: float,
                 stride: int = 1) -> float:
    """The mean white efficiency, over the eye states of iteration 0, of a plate whose cells
    (every stride-th row and column) are at open fraction `top`, the others closed."""
    open_fraction = torch.zeros((scene.plate.cells[1], scene.plate.cells[0]),
                                dtype=torch.float64)
    open_fraction[::stride, ::stride] = top
    return float(white_transmission(renderer, open_fraction,
                                    training_states(scene, settings, 0)).mean())


def check_light_floor(scene: Scene, settings: OptimizerSettings,
                      bounds: tuple[float, float] | None,
                      fabrication: FabricationSettings | None) -> None:
    """Refuse, before the work, a brightness floor (optimizer.min_efficiency, or the light at
    the eye optimizer.min_eye_level) that no plate of this scene and process reaches: the
    brightest, every cell at its largest hole, passes less light (its white efficiency over the
    eye states of one iteration; the light at the eye is at most that, a white content's)."""
    key, floor = max((("min_efficiency", settings.min_efficiency),
                      ("min_eye_level", settings.min_eye_level)), key=lambda item: item[1])
    if floor <= 0:
        return
    top = scene.plate.max_open_fraction if bounds is None else bounds[1]
    renderer = Renderer(scene, dtype=torch.float64)
    for stride in FLOOR_SCREEN_STRIDES:
        if floor <= _white_reach(renderer, scene, settings, top, stride) - FLOOR_SCREEN_SLACK:
            return  # a sparser plate reaches it: so does the brightest
    reach = _white_reach(renderer, scene, settings, top)
    if floor > reach:
        process = "" if fabrication is None else f" with process {fabrication.process.name!r}"
        what = ("the open display's light" if key == "min_efficiency"
                else "the panel's white at the eye")
        raise ValueError(
            f"optimizer.{key} = {floor:g} ({floor:.2%} of {what}) "
            f"cannot be met: the brightest plate{process}, every "
            f"{scene.plate.pitch_mm[0]:g} mm cell at its largest hole in a "
            f"{scene.plate.thickness_mm:g} mm plate, passes {reach:.2%}. Lower the floor to "
            f"{reach:.3g} or less, or give more light room: a thinner plate, a process with "
            "thinner webs (`aperture-fab processes`), or chief-ray hole axes.")


def evaluate(
    renderer: Renderer,
    targets: np.ndarray,
    variants: dict[str, tuple[np.ndarray, np.ndarray]],
    cache: JudgedCache | None = None,
) -> tuple[dict[str, np.ndarray], dict[str, dict[str, list[float]]]]:
    """Views (T, P, C, ny, nx) through the renderer's scene and gain-corrected metrics (nominal
    eye position) for plate variants {name: (open fractions, displays)}, plus the baselines
    (`baseline_views`: the open display showing the target and a regular pinhole array showing
    elemental images; cache keeps them between runs)."""
    scene, device, dtype = renderer.scene, renderer.device, renderer.dtype
    positions = range(len(scene.eye.positions_mm))
    views: dict[str, np.ndarray] = {}
    with torch.no_grad():
        for name, (a, displays) in variants.items():
            a_t = torch.as_tensor(a, dtype=dtype, device=device)
            views[name] = np.stack([
                np.stack([renderer.render(a_t, torch.as_tensor(d, dtype=dtype, device=device), p)
                          .cpu().double().numpy() for p in positions])
                for d in displays
            ])
    views.update(baseline_views(renderer, targets, cache))
    metrics: dict[str, dict[str, list[float]]] = {}
    for name, v in views.items():
        mse = [float(gain_mse(torch.as_tensor(v[t, 0]), torch.as_tensor(targets[t])))
               for t in range(len(targets))]
        metrics[name] = {"mse": mse, "psnr_db": [psnr_db(m) for m in mse]}
    return views, metrics


def recorded_config(config: Config, fabrication: FabricationSettings | None,
                    formats: Sequence[FormatName] = (), outline_mm: tuple[float, float] | None
                    = None) -> Config:
    """The config as design.toml records it: the fabrication settings as used (the process
    with its changes; step: whether STEP was written) and the plate outline as built (a record,
    not read), so that `--config design.toml` re-runs and `export`/`validate` re-make exactly
    this part."""
    outline = None if outline_mm is None else (round(float(outline_mm[0]), OUTLINE_DECIMALS),
                                                round(float(outline_mm[1]), OUTLINE_DECIMALS))
    if fabrication is not None:
        config = dataclasses.replace(
            config, fabrication=dataclasses.replace(fabrication, step="step" in formats))
    return dataclasses.replace(config, part_outline_mm=outline)


def _with_judgement(result: DesignResult, checked: Validation, evidence: Evidence
                    ) -> DesignResult:
    """The result with the written part's judgement: the headline over the eye distribution
    and the metrics as built (design.json gives them in this order), the verdicts, the
    report and its files."""
    report = evidence.report
    metrics = {**result.metrics, "eye_distribution": eye_headline(report)}
    for variant in ("quantized", "as_built"):
        per_target = [checked.metrics[variant][name] for name in result.names]
        metrics[variant] = {key: [m[key] for m in per_target] for key in ("mse", "psnr_db")}
    return dataclasses.replace(result, metrics=metrics, report=report,
                               report_files=evidence_files(evidence), evidence=evidence,
                               made_part=checked.made_part)


def run_design(paths: Sequence[Path], out: Path, config: Config, *,
               target_options: TargetOptions | None = None,
               fabrication: FabricationSettings | None = None,
               validation: ValidationSettings | None = None, resume: bool = False,
               progress: bool = True, command: Sequence[str] | None = None,
               on_staged: Callable[[Path], None] | None = None,
               stage: Callable[[str], None] | None = None,
               replace_validated: bool = False) -> DesignResult:
    """The `aperture-fab design` job on files. Raises Interrupted after saving a checkpoint.

    A folder whose design was validated (`validations_of`) is refused before the work, as the
    new design would leave those reports describing a part that is gone; replace_validated
    (the CLI's --force) replaces it and removes those validation folders with the old set.

    Every check and all the computation come before anything is written into the folder (only
    the checkpoint is saved there while optimizing), and a folder the run made is removed again
    when the run fails before writing there, so a refused run changes nothing. The outputs
    are written into a staging folder and published as one set with manifest.json
    (aperture_fab.io.manifest). command: recorded in the manifest (default: this function).
    on_staged: a testing seam, called with the staging folder after each group of files is
    staged (tests pause there to kill the process mid-export); None in normal use.
    stage: told each later stage as it starts, in words (the CLI prints them in a log, where
    there are no progress bars). target_options: how the files become targets (--alpha, --fit,
    --frame; aperture_fab.io.images.TargetOptions).
    """
    with created_folder(out) as folder:
        validated = validations_of(folder)
        if validated and not replace_validated:
            reports = ", ".join(str(v / "report.json") for v in validated)
            raise ValueError(
                f"--out {folder} holds a design that was validated ({reports}); a new design "
                "there would replace it and leave that report describing a part that is gone. "
                "Give another --out to keep both, or add --force to replace the design and its "
                "validation.")
        images, names = load_targets(paths, config.scene.display.pixels, target_options)
        inputs = input_digests(paths, config, fabrication)
        chosen = None if target_options is None else target_options.changes()
        if chosen is not None:  # other targets from the same files: --resume must see a change
            inputs["the target options (--alpha, --fit, --frame)"] = sha256(chosen.encode())
        checkpoint = folder / CHECKPOINT_NAME
        state = resume_state(checkpoint, inputs, paths) if resume else None
        formats = part_formats(fabrication, out) if fabrication is not None else ()
        try:
            result = design(images, config, names=names, fabrication=fabrication,
                            validation=validation, formats=formats, command=command, state=state,
                            progress=progress, stage=stage,
                            on_checkpoint=lambda s: save_checkpoint(folder, s, inputs))
        except Interrupted as stop:
            save_checkpoint(folder, stop.state, inputs)
            raise
        staged = on_staged if on_staged is not None else (lambda _stage: None)
        own = design_outputs(result)
        sheet: dict[str, bytes] = {}
        if result.part is not None and fabrication is not None:  # assembly.html, coupon.*
            from aperture_fab.pipeline.assembly_job import sheet_files

            sheet = sheet_files(result.part, result.config.scene, fabrication, result.names,
                                folder.resolve(),
                                {name: own[f"display_{name}.png"] for name in result.names})
        # Staged in groups, the part one file at a time (the test seam pauses after each group).
        groups = [own, *({name: data} for name, data in result.part_files.items()),
                  {**result.report_files, "design.json": summary_json(result)}]
        with staging(folder) as stage_folder:
            for group in groups:
                for name, data in group.items():
                    write_atomic(stage_folder / name, data)
                staged(stage_folder)
            for name, data in sheet.items():
                write_atomic(stage_folder / name, data)
            publish(stage_folder, folder, command if command is not None else DEFAULT_COMMAND)
        for stale in validated:  # they judged the design just replaced
            remove_listed(stale)
            # A folder that still holds the user's files stays.
            with contextlib.suppress(OSError):
                stale.rmdir()
        checkpoint.unlink(missing_ok=True)
        return result


