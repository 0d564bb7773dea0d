"""The design job: targets in, an optimized plate and its evidence out.

`design` is the Python API (values in, values out, no files). `run_design` is the same job on
files: it reads the targets, writes every output atomically, checkpoints, and resumes.
"""

from __future__ import annotations

import json
import os
import secrets
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from aperture_fab.config.config import Config, to_dict, to_toml
from aperture_fab.fabrication.part import (
    PART_FORMATS,
    FabricationSettings,
    Part,
    PartFormat,
    design_bounds,
    eye_distance_mm,
    make_part,
    part_files,
)
from aperture_fab.fabrication.process import check_plate
from aperture_fab.fabrication.quantize import made_sizes
from aperture_fab.io.images import decode_image, encode_png, is_grey, resample
from aperture_fab.optics.baselines import elemental_display, regular_pinholes
from aperture_fab.optics.model import Renderer, render_open
from aperture_fab.optimize.optimizer import (
    Interrupted,
    MaskDesign,
    fit_display,
    gain_mse,
    initial_design,
    optimize,
    psnr_db,
    resolve_device,
)
from aperture_fab.validation.validate import (
    Validation,
    ValidationSettings,
    layout_fractions,
    validate,
)

__all__ = ["DesignResult", "design", "run_design", "write_atomic", "load_targets"]

CHECKPOINT_NAME = "checkpoint.pt"
#: The display is re-fitted to the part as built for this share of the design's iterations.
FIT_SHARE = 3
MIN_FIT_ITERATIONS = 20
PART_SUFFIXES = (".stl", ".step", ".stp", ".3mf", ".dxf", ".svg")


@dataclass(frozen=True)
class DesignResult:
    """Everything the design job produced.

    design: the optimized plate and display content.
    names: (T,) target names.
    targets: (T, C, ny, nx) float64 linear targets on the view grid.
    views: {"initial" | "optimized" | "open" | "regular_pinholes": (T, P, C, ny, nx) float64}
        for every target and eyebox position.
    metrics: {variant: {"psnr_db": [per target], "mse": [per target]}} at the nominal position;
        run_design adds "quantized" and "as_built" when it validates the part, and
        "eye_distribution": the part and the baselines over the eye distribution
        (report.eye_headline: percentiles per variant and target, and the verdict), or None
        when validation did not judge it.
    part: the part as made (None when no fabrication settings were given).
    built_displays: (T, C, H, W) display content fitted to the part as made: optimized with the
        snapped plate, or re-fitted to the part when no iteration saw it (None when the display
        shows the targets, or without a part): what the device should show.
    timings_s: seconds per stage.
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


def _prepare(config: Config, images: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Targets on the view grid (T, C, ny, nx) and on the display grid (T, C, H, W); one channel
    when every target is grey."""
    eye, display = config.scene.eye, config.scene.display
    grey = all(is_grey(im) for im in images)
    views, shown = [], []
    for im in images:
        im = im[:1] if grey else im
        views.append(resample(im, eye.view_pixels))
        shown.append(resample(im, display.pixels))
    return np.stack(views), np.stack(shown)


def design(
    images: Sequence[np.ndarray],
    config: Config,
    *,
    names: Sequence[str] | None = None,
    fabrication: FabricationSettings | None = None,
    state: dict[str, Any] | None = None,
    on_checkpoint: Callable[[dict[str, Any]], None] | None = None,
    progress: bool = False,
) -> DesignResult:
    """Design a plate for target images (each (3, H, W) linear RGB in [0, 1]); with
    `fabrication`, designed within what its process can make and made into a part."""
    if not images:
        raise ValueError("no targets given; pass at least one image.")
    names = tuple(names) if names is not None else tuple(f"target{i}" for i in range(len(images)))
    scene, settings = config.scene, config.optimizer
    bounds = made = None
    if fabrication is not None:
        if not fabrication.force:
            check_plate(fabrication.process, scene.plate)  # refuse before optimizing
            if settings.quantize_share > 0:
                made = made_sizes(scene.plate, fabrication.process, eye_distance_mm(scene))
        bounds = design_bounds(scene, fabrication.process)
    targets, shown = _prepare(config, images)
    timings = {}
    start = time.perf_counter()
    result = optimize(scene, targets, shown, settings, bounds=bounds, made=made, state=state,
                      on_checkpoint=on_checkpoint, progress=progress)
    timings["optimize_s"] = time.perf_counter() - start
    start = time.perf_counter()
    views, metrics = evaluate(config, targets, {
        "initial": initial_design(scene, targets, shown, settings, bounds),
        "optimized": optimum(result),
    })
    timings["evaluate_s"] = time.perf_counter() - start
    start = time.perf_counter()
    part = None if fabrication is None else make_part(result.open_fraction, scene, fabrication)
    timings["quantize_build_s"] = time.perf_counter() - start
    built = None
    if part is not None and settings.display == "optimized" and result.continuous is not None:
        built = result.displays  # optimized for the holes as made
    elif part is not None and settings.display == "optimized" and settings.iterations > 1:
        # The plate is hardware and the display software: fit the display to the part as it
        # will be made (quantized holes, the process's radius bias).
        start = time.perf_counter()
        as_built = layout_fractions(part.layout, fabrication.process.radius_bias_mm
                                    if fabrication is not None else 0.0)
        built, _ = fit_display(scene, targets, as_built, result.displays, settings,
                               max(MIN_FIT_ITERATIONS, settings.iterations // FIT_SHARE),
                               progress=progress)
        timings["fit_display_s"] = time.perf_counter() - start
    return DesignResult(config, result, names, targets, views, metrics, part, built, timings)


def optimum(design: MaskDesign) -> tuple[np.ndarray, np.ndarray]:
    """The optimized design before quantization: (open fractions, displays)."""
    if design.continuous is not None:
        return design.continuous
    return design.open_fraction, design.displays


def evaluate(
    config: Config,
    targets: np.ndarray,
    variants: dict[str, tuple[np.ndarray, np.ndarray]],
) -> tuple[dict[str, np.ndarray], dict[str, dict[str, list[float]]]]:
    """Views (T, P, C, ny, nx) and gain-corrected metrics (nominal eye position) for plate
    variants {name: (open fractions, displays)}, plus the open display (showing the target)
    and a regular pinhole array showing elemental images."""
    scene = config.scene
    device = resolve_device(config.optimizer.device)
    dtype = torch.float64 if config.optimizer.precision == "float64" else torch.float32
    renderer = Renderer(scene, device=device, dtype=dtype)
    positions = range(len(scene.eye.positions_mm))
    target_t = torch.as_tensor(targets, dtype=dtype, device=device)
    array = regular_pinholes(scene)
    views: dict[str, np.ndarray] = {}
    with torch.no_grad():
        for name, (a, displays) in variants.items():
            a_t = torch.as_tensor(a, dtype=dtype, device=device)
            views[name] = np.stack([
                np.stack([renderer.render(a_t, torch.as_tensor(d, dtype=dtype, device=device), p)
                          .cpu().double().numpy() for p in positions])
                for d in displays
            ])
        # The open display shows the target itself: the best it can do without a plate.
        views["open"] = np.stack([
            np.stack([render_open(scene, t, p).cpu().double().numpy() for p in positions])
            for t in _display_targets(config, target_t)
        ])
        pin_a = torch.as_tensor(array.open_fraction, dtype=dtype, device=device)
        # One display for all eye positions (for the nominal one), like the design's.
        pin_displays = [elemental_display(scene, array, t) for t in target_t]
        views["regular_pinholes"] = np.stack([
            np.stack([renderer.render(pin_a, d, p).cpu().double().numpy() for p in positions])
            for d in pin_displays
        ])
    metrics: dict[str, dict[str, list[float]]] = {}
    for name, v in views.items():
        mse = [float(gain_mse(torch.as_tensor(v[t, 0]), torch.as_tensor(targets[t])))
               for t in range(len(targets))]
        metrics[name] = {"mse": mse, "psnr_db": [psnr_db(m) for m in mse]}
    return views, metrics


def _display_targets(config: Config, targets: torch.Tensor) -> torch.Tensor:
    """Targets resampled onto the display grid, (T, C, H, W)."""
    size = config.scene.display.pixels
    return torch.stack([
        torch.as_tensor(resample(t.cpu().double().numpy(), size), dtype=targets.dtype,
                        device=targets.device)
        for t in targets
    ])


# -- files --------------------------------------------------------------------------------------


def write_atomic(path: Path, data: bytes | str) -> None:
    """Write via a temporary file in the same folder and rename: never a truncated file."""
    payload = data.encode() if isinstance(data, str) else data
    tmp = path.parent / f".{path.name}.{secrets.token_hex(6)}.tmp"
    # os.open with 0o666 honours the umask, unlike mkstemp's private 0o600.
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(payload)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def output_folder(out: Path) -> Path:
    """The folder for all outputs: `out` itself, or its parent when `out` names a part file."""
    folder = out.parent if out.suffix.lower() in PART_SUFFIXES else out
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(f"cannot create the output folder {folder}: {err.strerror}; choose "
                         "another --out.") from err
    if not os.access(folder, os.W_OK):
        raise ValueError(f"the output folder {folder} is not writable; choose another --out.")
    return folder


def load_targets(paths: Sequence[Path]) -> tuple[list[np.ndarray], list[str]]:
    """Read and decode target images; names are the file stems, made unique."""
    images, names = [], []
    for path in paths:
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            raise ValueError(f"target image {path} does not exist; check the path.") from None
        except IsADirectoryError:
            raise ValueError(f"target image {path} is a folder; give an image file.") from None
        except OSError as err:
            raise ValueError(f"cannot read target image {path}: {err.strerror}.") from err
        images.append(decode_image(data, str(path)))
        name = "".join(c if c.isalnum() or c in "-_" else "_" for c in path.stem) or "target"
        while name in names:
            name += "_"
        names.append(name)
    return images, names


def _save_checkpoint(folder: Path, state: dict[str, Any], fingerprint: str) -> None:
    import io

    buffer = io.BytesIO()
    torch.save({"state": state, "fingerprint": fingerprint}, buffer)
    write_atomic(folder / CHECKPOINT_NAME, buffer.getvalue())


def run_design(paths: Sequence[Path], out: Path, config: Config, *,
               fabrication: FabricationSettings | None = None,
               validation: ValidationSettings | None = None, resume: bool = False,
               progress: bool = True) -> DesignResult:
    """The `aperture-fab design` job on files. Raises Interrupted after saving a checkpoint."""
    folder = output_folder(out)
    images, names = load_targets(paths)
    fingerprint = to_toml(config) + "\n".join(str(Path(p).resolve()) for p in paths)
    state = None
    checkpoint = folder / CHECKPOINT_NAME
    if resume:
        if not checkpoint.exists():
            raise ValueError(f"--resume: no checkpoint at {checkpoint}; run without --resume.")
        saved = torch.load(checkpoint, weights_only=False)
        if saved["fingerprint"] != fingerprint:
            raise ValueError(f"--resume: {checkpoint} was made with another config or other "
                             "targets; run without --resume to start again.")
        state = saved["state"]
    write_atomic(folder / "design.toml", to_toml(config))
    try:
        result = design(images, config, names=names, fabrication=fabrication, state=state,
                        progress=progress,
                        on_checkpoint=lambda s: _save_checkpoint(folder, s, fingerprint))
    except Interrupted as stop:
        _save_checkpoint(folder, stop.state, fingerprint)
        raise
    write_outputs(folder, result)
    if result.part is not None and fabrication is not None:
        start = time.perf_counter()
        write_part(folder, result.part, fabrication, _formats(out, fabrication), progress)
        result.timings_s["export_s"] = time.perf_counter() - start
        if validation is not None:
            checked = write_report(folder, result, fabrication, validation)
            for variant in ("quantized", "as_built"):
                per_target = [checked.metrics[variant][name] for name in result.names]
                result.metrics[variant] = {key: [m[key] for m in per_target]
                                           for key in ("mse", "psnr_db")}
            write_summary(folder, result)  # design.json again, with the validated figures
    checkpoint.unlink(missing_ok=True)
    return result


def write_report(folder: Path, result: DesignResult, fabrication: FabricationSettings,
                 settings: ValidationSettings) -> Validation:
    """Validate the part as written (plate.stl re-read from disk) and write report.json,
    views.npz and report.html; result.metrics["eye_distribution"] gets the headline over the
    eye distribution (None when not judged)."""
    from aperture_fab.io.formats import read_stl
    from aperture_fab.validation.evidence import assemble
    from aperture_fab.validation.report import eye_headline, report_json

    if result.part is None:
        raise ValueError("no part to validate: design with fabrication settings first.")
    mesh = read_stl((folder / "plate.stl").read_bytes())
    open_fraction, displays = optimum(result.design)
    checked = validate(result.config, result.targets, displays, open_fraction, result.part,
                       fabrication.process, result.names, settings, mesh,
                       built_displays=result.built_displays)
    start = time.perf_counter()
    shown = result.design.displays if result.built_displays is None else result.built_displays
    evidence = assemble(result.config, result.names, result.targets, shown,
                        result.design.loss_history, result.part, fabrication.process, checked,
                        result.timings_s)
    evidence.report["timings_s"]["report_s"] = time.perf_counter() - start
    write_atomic(folder / "views.npz", evidence.views_npz)
    write_atomic(folder / "report.html", evidence.html)
    write_atomic(folder / "report.json", report_json(evidence.report))
    result.metrics["eye_distribution"] = eye_headline(evidence.report)
    return checked


def _formats(out: Path, fabrication: FabricationSettings) -> tuple[PartFormat, ...]:
    formats: list[PartFormat] = ["stl", "3mf", "csv", "dxf", "svg"]
    if fabrication.step or out.suffix.lower() in (".step", ".stp"):
        formats.append("step")
    return tuple(formats)


def write_part(folder: Path, part: Part, fabrication: FabricationSettings,
               formats: Sequence[PartFormat] = PART_FORMATS, progress: bool = True) -> list[Path]:
    """Write the part's files atomically; a format that fails leaves no file behind."""
    from tqdm import tqdm

    written = []
    for fmt in tqdm(formats, desc="export", unit="file", disable=not progress, leave=False):
        holes = tqdm(total=part.layout.count, desc=f"{fmt} holes", unit="hole", leave=False,
                     disable=not progress or fmt != "step")

        def advance(done: int, bar: Any = holes) -> None:
            bar.update(done - bar.n)

        for name, data in part_files(part, (fmt,), fabrication, advance).items():
            write_atomic(folder / name, data)
            written.append(folder / name)
        holes.close()
    return written


def write_outputs(folder: Path, result: DesignResult) -> None:
    """design.npz, display and view PNGs, loss curve, design.json."""
    import io

    d = result.design
    buffer = io.BytesIO()
    shown = d.displays if result.built_displays is None else result.built_displays
    np.savez_compressed(buffer, open_fraction=d.open_fraction, displays=d.displays,
                        built_displays=shown, loss_history=d.loss_history,
                        bounds=np.asarray(d.bounds), names=np.asarray(result.names))
    write_atomic(folder / "design.npz", buffer.getvalue())
    for t, name in enumerate(result.names):
        write_atomic(folder / f"display_{name}.png", encode_png(shown[t]))
        write_atomic(folder / f"target_{name}.png", encode_png(result.targets[t]))
        for variant in ("initial", "optimized", "open", "regular_pinholes"):
            view = result.views[variant][t, 0]
            scaled = view * _gain(view, result.targets[t])
            write_atomic(folder / f"view_{variant}_{name}.png", encode_png(np.clip(scaled, 0, 1)))
    write_atomic(folder / "loss.png", _loss_plot(d.loss_history))
    write_summary(folder, result)


def write_summary(folder: Path, result: DesignResult) -> None:
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
        "config": to_dict(result.config),
    }
    write_atomic(folder / "design.json", json.dumps(summary, indent=2))


def _part_summary(part: Part) -> dict[str, Any]:
    from aperture_fab.fabrication.quantize import layout_stats

    stats = {k: (float(v) if isinstance(v, (float, np.floating)) else v)
             for k, v in layout_stats(part.layout).items()}
    return {
        "layout": stats,
        "violations": [
            {"rule": v.rule, "cell": v.cell, "value_mm": v.value_mm, "limit_mm": v.limit_mm,
             "resolution": v.resolution}
            for v in part.layout.violations
        ],
        "mesh": {"watertight": part.report.watertight, "genus": part.report.genus,
                 "volume_mm3": part.report.volume_mm3, "triangles": part.report.face_count},
    }


def _gain(view: np.ndarray, target: np.ndarray) -> float:
    return float((view * target).sum() / max((view * view).sum(), 1e-20))


def _loss_plot(history: np.ndarray) -> bytes:
    import io

    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as err:  # pragma: no cover - matplotlib is a dependency
        raise ImportError("the loss plot needs matplotlib: pip install matplotlib") from err
    fig, ax = plt.subplots(figsize=(5, 3.2), dpi=100)
    ax.semilogy(np.arange(1, len(history) + 1), history)
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss (MSE after gain)")
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    plt.close(fig)
    return buffer.getvalue()
