"""The files of a design folder as bytes: the part in every format, design.npz and its
pictures, design.json, and the report of the part as written (`run_design` writes them, once;
`write_part` is the export job's, which writes each format as it is made)."""

from __future__ import annotations

import io
import json
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from aperture_fab.config.stages import FabricationSettings, ValidationSettings
from aperture_fab.config.written import to_dict, to_toml
from aperture_fab.fabrication.part import Part
from aperture_fab.io.atomic import write_atomic
from aperture_fab.io.formats import PART_FORMATS, FormatName, part_files
from aperture_fab.io.images import encode_png
from aperture_fab.metrics import gain
from aperture_fab.pipeline.judged_folder import default_cache
from aperture_fab.validation.judge import judge
from aperture_fab.validation.validate import BASELINES, Validation, validate

if TYPE_CHECKING:  # the job's value; design_job imports this module
    from aperture_fab.pipeline.design_job import DesignResult
    from aperture_fab.report.evidence import Evidence

__all__ = ["design_outputs", "evidence_files", "judge_written", "part_bytes", "part_formats",
           "summary_json", "write_part"]


def judge_written(result: DesignResult, fabrication: FabricationSettings,
                  settings: ValidationSettings, stl: bytes, command: Sequence[str] | None = None,
                  replaces: Mapping[str, Any] | None = None,
                  made_part: dict[str, Any] | None = None) -> tuple[Validation, Evidence]:
    """Validate the part as written (`stl`: plate.stl's bytes as written, parsed again), judge
    it and draw its report (views.npz, report.html): values, nothing written
    (`evidence_files` gives their bytes). replaces: the report's run.replaces (`judge`).
    made_part: the part's made-part block when judged already (`validate`)."""
    from aperture_fab.io.formats import read_stl
    from aperture_fab.report.evidence import assemble

    if result.part is None:
        raise ValueError("no part to validate: design with fabrication settings first.")
    mesh = read_stl(stl)
    open_fraction, displays = result.design.optimum
    checked = validate(result.config, result.targets, displays, open_fraction, result.part,
                       fabrication.process, result.names, settings, mesh,
                       built_displays=result.built_displays,
                       baselines={k: result.views[k] for k in BASELINES},
                       cache=default_cache(), made_part=made_part)
    start = time.perf_counter()
    shown = result.design.displays if result.built_displays is None else result.built_displays
    report = judge(result.config, result.names, result.targets, shown, result.part,
                   fabrication.process, checked, result.timings_s, part_file="plate.stl",
                   command=command, replaces=replaces)
    evidence = assemble(report, result.names, result.targets, shown,
                        result.design.loss_history, result.part, checked)
    timed = evidence.report.with_timing("report_s", time.perf_counter() - start)
    return checked, replace(evidence, report=timed)


def evidence_files(evidence: Evidence) -> dict[str, bytes]:
    """The files of a judged part's report, name -> bytes: views.npz, report.html, report.json."""
    from aperture_fab.validation.report import report_json

    return {"views.npz": evidence.views_npz, "report.html": evidence.html.encode(),
            "report.json": report_json(evidence.report).encode()}


def part_formats(fabrication: FabricationSettings, out: Path | None = None
                 ) -> tuple[FormatName, ...]:
    """Every format; STEP (slow) only when asked for, by fabrication.step (--step) or an `out`
    that names a STEP file."""
    step = fabrication.step or (out is not None
                                and out.suffix.lower() in PART_FORMATS["step"].suffixes)
    return tuple(name for name in PART_FORMATS if name != "step" or step)


def part_bytes(part: Part, fabrication: FabricationSettings,
               formats: Sequence[FormatName] = tuple(PART_FORMATS), progress: bool = True,
               on_format: Callable[[dict[str, bytes]], None] | None = None) -> dict[str, bytes]:
    """The part's files in `formats`, file name -> bytes, in that order, with progress bars.
    on_format: told each format's files as they are made."""
    from tqdm import tqdm

    files: dict[str, bytes] = {}
    for fmt in tqdm(formats, desc="export", unit="file", disable=not progress, leave=False):
        holes = tqdm(total=part.layout.count, desc=f"{fmt} holes", unit="hole", leave=False,
                     disable=not progress or fmt != "step")

        def advance(done: int, bar: Any = holes) -> None:
            bar.update(done - bar.n)

        made = part_files(part, (fmt,), fabrication, advance)
        holes.close()
        files.update(made)
        if on_format is not None:
            on_format(made)
    return files


def write_part(folder: Path, part: Part, fabrication: FabricationSettings,
               formats: Sequence[FormatName] = tuple(PART_FORMATS), progress: bool = True
               ) -> dict[Path, bytes]:
    """Write the part's files atomically, each format's as it is made (an interrupted export
    keeps those before it); a format that fails leaves no file behind. Returns each file
    written with its bytes, in the order written."""
    written: dict[Path, bytes] = {}

    def write(made: dict[str, bytes]) -> None:
        for name, data in made.items():
            write_atomic(folder / name, data)
            written[folder / name] = data

    part_bytes(part, fabrication, formats, progress, on_format=write)
    return written


def design_outputs(result: DesignResult) -> dict[str, bytes]:
    """The design's own files, name -> bytes, in the order written: design.npz, design.toml,
    per target its display, target and view PNGs, loss.png (design.json comes last,
    `summary_json`, with the figures of the part as written)."""
    from aperture_fab.report.figures import figure_loss

    d = result.design
    buffer = io.BytesIO()
    shown = d.displays if result.built_displays is None else result.built_displays
    # The design before quantization, when one was kept: validate judges it as design did.
    arrays: dict[str, Any] = {
        "open_fraction": d.open_fraction, "displays": d.displays, "built_displays": shown,
        "loss_history": d.loss_history, "bounds": np.asarray(d.bounds),
        "names": np.asarray(result.names)}
    if d.continuous is not None:
        arrays["continuous_open_fraction"], arrays["continuous_displays"] = d.continuous
    np.savez_compressed(buffer, **arrays)
    files = {"design.npz": buffer.getvalue(), "design.toml": to_toml(result.config).encode()}
    for t, name in enumerate(result.names):
        files[f"display_{name}.png"] = encode_png(shown[t])
        files[f"target_{name}.png"] = encode_png(result.targets[t])
        for variant in ("initial", "optimized", "open", "regular_pinholes"):
            view = result.views[variant][t, 0]
            scaled = view * gain(view, result.targets[t])
            files[f"view_{variant}_{name}.png"] = encode_png(np.clip(scaled, 0, 1))
    files["loss.png"] = figure_loss(d.loss_history)
    return files


def summary_json(result: DesignResult) -> bytes:
    """design.json: the run's numbers (metrics as they are so far) and its config."""
    d = result.design
    summary = {
        "schema_version": 1,
        "targets": list(result.names),
        "final_loss": float(d.loss_history[-1]) if len(d.loss_history) else None,
        "iterations": len(d.loss_history),
        "stopped": d.stopped,
        "bounds": list(d.bounds),
        "metrics": result.metrics,
        "fabrication": None if result.part is None else _part_summary(result.part),
        **({"lattices": list(result.lattices)} if result.lattices else {}),
        "config": to_dict(result.config),
    }
    return json.dumps(summary, indent=2).encode()


def _part_summary(part: Part) -> dict[str, Any]:
    from aperture_fab.fabrication.layout import layout_stats

    stats = {k: (float(v) if isinstance(v, (float, np.floating)) else v)
             for k, v in layout_stats(part.layout).items()}
    return {
        "layout": stats,
        "outline_mm": [float(v) for v in part.layout.outline_mm],
        "violations": [
            {"rule": v.rule, "cell": v.cell, "value_mm": v.value_mm, "limit_mm": v.limit_mm,
             "resolution": v.resolution}
            for v in part.layout.violations
        ],
        "mesh": {"watertight": part.report.watertight, "genus": part.report.genus,
                 "volume_mm3": part.report.volume_mm3, "triangles": part.report.face_count},
    }
