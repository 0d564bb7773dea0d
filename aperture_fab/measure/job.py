"""The `aperture-fab measure` job: read a scan and a design folder, measure, and publish into
the output folder (one set with its manifest.json, aperture_fab.io.manifest) holes.csv,
measured.json and measured.html, plus what makes the folder read as a design folder of the
plate as made: design.toml (the design's, the process's bias and random errors set to 0) and
the design's design.npz (its display content), so that `validate`, `render` and `display`
judge the plate as made unchanged (issue 17, item 2)."""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from aperture_fab.config.config import parse_toml, resolve
from aperture_fab.fabrication.coupon import Coupon, calibration_coupon, coupon_part
from aperture_fab.fabrication.layout import HoleLayout
from aperture_fab.fabrication.part import Part
from aperture_fab.fabrication.process import MAX_OPTICAL_DENSITY
from aperture_fab.io.atomic import write_atomic
from aperture_fab.io.files import load_targets, output_folder
from aperture_fab.io.formats import holes_csv
from aperture_fab.io.images import TargetOptions, encode_png, prepare_targets
from aperture_fab.io.manifest import check_folder, publish, staging
from aperture_fab.measure.coupon import (
    COUPON_MIN_MATCH_SHARE,
    CouponCalibration,
    calibrate_coupon,
    process_overrides,
)
from aperture_fab.measure.folder import AS_MADE_PROCESS, derived_config
from aperture_fab.measure.measure import Measurement, NoHolesError, measure_plate
from aperture_fab.measure.refit import Refit, refit_display
from aperture_fab.measure.register import MIN_MATCH_SHARE, RegistrationError
from aperture_fab.measure.report import measured_json, measured_layout, measured_page
from aperture_fab.measure.scan import ScanEncoding, decode_scan
from aperture_fab.pipeline.design_job import FIT_SHARE, MIN_FIT_ITERATIONS
from aperture_fab.pipeline.saved import (
    CONFIG_NAME,
    DESIGN_NAME,
    MEASURED_NAME,
    check_design,
    load_part,
    measured_scan,
    read_config,
    read_design,
)
from aperture_fab.validation.validate import layout_fractions

__all__ = ["HOLES_NAME", "PROCESS_NAME", "REFIT_NAME", "CouponResult", "MeasureResult",
           "RefitResult", "read_design_part", "run_measure", "run_measure_coupon", "run_refit"]

HOLES_NAME = "holes.csv"
JSON_NAME = MEASURED_NAME
PAGE_NAME = "measured.html"
#: What `measure --coupon` writes: the process as measured, a config `design --config` takes,
#: and the coupon's holes as made.
PROCESS_NAME = "process.toml"
COUPON_HOLES_NAME = "coupon_holes.csv"
#: What `display --refit` adds to a measured folder's set: the figures, and the re-fitted
#: display content per target (refit_display_<target>.png).
REFIT_NAME = "refit.json"
REFIT_DISPLAY = "refit_display_{}.png"
#: Most iterations a re-fit takes (each a forward and a backward pass).
MAX_REFIT_ITERATIONS = 2000
#: The command a manifest names when the Python API, not the command line, ran the job.
MEASURE_COMMAND = ("python", "-c", "aperture_fab.measure.job.run_measure(...)")


@dataclass(frozen=True)
class MeasureResult:
    """What `run_measure` did: folder (where it wrote), measurement, notes (measured.json's),
    timings_s (seconds per stage)."""

    folder: Path
    measurement: Measurement
    notes: tuple[str, ...]
    timings_s: dict[str, float]


def read_design_part(folder: Path) -> Part:
    """The part a design folder's holes.csv holds (drawn holes, outline, chamfer), checked
    against the folder's design.toml and manifest."""
    config_path, table = folder / CONFIG_NAME, folder / HOLES_NAME
    if not folder.is_dir():
        raise ValueError(f"--design {folder} is not a folder; give the folder `aperture-fab "
                         "design` wrote for the plate (it holds design.toml and holes.csv).")
    for path in (config_path, table):
        if not path.is_file():
            raise ValueError(f"--design {folder} has no {path.name}; give the folder "
                             "`aperture-fab design` wrote for the plate.")
    config = read_config(config_path)
    return load_part(table, "holes", config, config.fabrication, config_path)


@dataclass(frozen=True)
class CouponResult:
    """What `run_measure_coupon` did: folder (where it wrote), measurement (of the coupon),
    calibration (the process it shows), process (the [process] values written), notes,
    timings_s (seconds per stage)."""

    folder: Path
    measurement: Measurement
    calibration: CouponCalibration
    process: dict[str, float]
    notes: tuple[str, ...]
    timings_s: dict[str, float]


def read_design_coupon(folder: Path) -> tuple[Coupon, Part]:
    """The calibration coupon of a design folder (the one `design` wrote as coupon.stl, .svg
    and coupon_holes.csv: rebuilt from its design.toml's process and plate) and its part; the
    folder checked against its manifest."""
    config_path = folder / CONFIG_NAME
    if not config_path.is_file():
        raise ValueError(f"--design {folder} has no {CONFIG_NAME}; give the folder `aperture-fab "
                         "design` wrote (it holds the coupon: coupon.stl, coupon.svg).")
    check_folder(folder)
    config = read_config(config_path)
    process = config.fabrication.process
    coupon = calibration_coupon(process, config.scene.plate)
    return coupon, coupon_part(coupon, process)


def _read_scan(path: Path, encoding: ScanEncoding) -> bytes:
    if path.is_dir():
        raise ValueError(f"scan {path} is a folder; give the scan's image file.")
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise ValueError(f"scan {path} does not exist; check the path.") from None
    except OSError as err:
        raise ValueError(f"cannot read scan {path}: {err.strerror}; check that it is an image "
                         "file you may read.") from err


def check_out(out: Path, design: Path) -> None:
    """Refuse an --out that is the design folder, or another design's folder: publishing the
    measured set there would replace the design's holes.csv and design.toml."""
    if out.exists() and design.exists() and out.resolve() == design.resolve():
        raise ValueError(f"--out {out} is the design folder; measure writes the plate as made "
                         "(its own holes.csv and design.toml) as a set of its own. Give a new "
                         f"folder, e.g. --out {design.with_name(design.name + '_made')}.")
    if (out / CONFIG_NAME).is_file() and not (out / JSON_NAME).is_file():
        raise ValueError(f"--out {out} holds a design ({CONFIG_NAME}) that measure did not "
                         "write; publishing there would replace it. Give a new folder.")


def as_made_config(design: Path, scan: Path, measurement: Measurement) -> str:
    """The measured folder's design.toml: the design's, with the process's radius bias and
    random errors 0 (holes.csv holds the holes as made) and, where the scan resolved it, the
    solid's optical density as measured; a note of where it came from."""
    source = design / CONFIG_NAME
    process: dict[str, float | str] = dict(AS_MADE_PROCESS)
    if not measurement.solid_at_floor and 0 < measurement.optical_density <= MAX_OPTICAL_DENSITY:
        process["optical_density"] = round(measurement.optical_density, 3)
    note = (f"The plate as made: measured by `aperture-fab measure` from the scan {scan}",
            f"against the design {design} (issue 17). holes.csv holds the measured holes, so",
            "[process] radius_bias_mm, radius_sigma_mm and position_sigma_mm are 0 (nothing to",
            "add, no more random error to draw)"
            + ("; optical_density is the scan's." if "optical_density" in process else "."))
    text = source.read_text(encoding="utf-8-sig")
    return derived_config(text, str(source), process, note)


def _measure(scan: Path, design: Path, layout: HoleLayout, mm_per_px: float,
             encoding: ScanEncoding, what: str, min_match_share: float = MIN_MATCH_SHARE
             ) -> tuple[Measurement, np.ndarray]:
    """(measurement, image) of `scan` against `layout` (the `what` of the design folder), the
    refusals naming the scan and what was expected."""
    image = decode_scan(_read_scan(scan, encoding), str(scan), encoding)
    try:
        return measure_plate(image, layout, mm_per_px, min_match_share), image
    except NoHolesError as err:
        raise NoHolesError(f"scan {scan}: {err}. Expected the {what}'s {layout.count} "
                           "holes as bright disks on the dark solid: scan with the "
                           "transparency unit (back light) on, the plate flat on the glass, "
                           "and save the scan linear (gamma 1.0).") from err
    except RegistrationError as err:
        raise RegistrationError(f"scan {scan} measured against the {what} of {design} "
                                f"({layout.count} holes): {err}") from err


def run_measure_coupon(scan: Path, design: Path, out: Path, mm_per_px: float,
                       encoding: ScanEncoding = "linear",
                       command: Sequence[str] | None = None) -> CouponResult:
    """Measure `scan` of the calibration coupon of the design folder `design` and publish into
    `out`: process.toml (the design's config with the [process] the coupon measured: `design
    --config` takes it), coupon_holes.csv (the coupon's holes as made), measured.json (with a
    "coupon" block: every block's holes, opened and measured, and the process's values) and
    measured.html."""
    timings: dict[str, float] = {}
    start = time.perf_counter()
    check_out(out, design)
    coupon, part = read_design_coupon(design)
    timings["read_s"] = time.perf_counter() - start
    start = time.perf_counter()
    measurement, image = _measure(scan, design, part.layout, mm_per_px, encoding,
                                  "calibration coupon", COUPON_MIN_MATCH_SHARE)
    calibration = calibrate_coupon(measurement, coupon)
    timings["measure_s"] = time.perf_counter() - start
    start = time.perf_counter()
    values = process_overrides(calibration)
    note = ("The process as measured on the calibration coupon: `aperture-fab measure --coupon`",
            f"of the scan {scan}, coupon of the design {design} (issue 17). [process] holds",
            "the smallest drawn hole that came through whole (min_hole_mm), the made - drawn",
            "radius bias, the radius and position sigmas; the rest is the design's config.",
            f"Use it: aperture-fab design TARGET --config {out / PROCESS_NAME}")
    text = derived_config((design / CONFIG_NAME).read_text(encoding="utf-8-sig"),
                          str(design / CONFIG_NAME), values, note)
    resolve(None, parse_toml(text, PROCESS_NAME))  # refused here, not by design
    folder = output_folder(out)
    summary = measured_json(measurement, str(scan), str(design))
    smallest = calibration.blocks[0]
    if smallest.complete:
        summary["notes"].append(
            f"Every block came through, the smallest ({smallest.drawn_diameter_mm * 1000:.1f} um "
            "drawn) too: the process's smallest hole is at most that.")
    summary["coupon"] = calibration.as_json() | {"process": values}
    with staging(folder) as staged:
        write_atomic(staged / COUPON_HOLES_NAME, holes_csv(measured_layout(measurement)))
        write_atomic(staged / JSON_NAME, json.dumps(summary, indent=1) + "\n")
        write_atomic(staged / PAGE_NAME, measured_page(measurement, image, summary))
        write_atomic(staged / PROCESS_NAME, text)
        publish(staged, folder, command if command is not None else MEASURE_COMMAND)
    timings["write_s"] = time.perf_counter() - start
    return CouponResult(folder, measurement, calibration, values, tuple(summary["notes"]),
                        timings)


def run_measure(scan: Path, design: Path, out: Path, mm_per_px: float,
                encoding: ScanEncoding = "linear",
                command: Sequence[str] | None = None) -> MeasureResult:
    """Measure `scan` (an image file) of the plate made from the design folder `design` at
    mm_per_px, and publish the results into the folder `out` as a design folder of the plate
    as made (module docstring)."""
    timings: dict[str, float] = {}
    start = time.perf_counter()
    check_out(out, design)
    part = read_design_part(design)
    timings["read_s"] = time.perf_counter() - start
    start = time.perf_counter()
    measurement, image = _measure(scan, design, part.layout, mm_per_px, encoding, "plate")
    timings["measure_s"] = time.perf_counter() - start
    start = time.perf_counter()
    folder = output_folder(out)
    summary = measured_json(measurement, str(scan), str(design))
    config_text = as_made_config(design, scan, measurement)
    with staging(folder) as staged:
        write_atomic(staged / HOLES_NAME, holes_csv(measured_layout(measurement)))
        write_atomic(staged / JSON_NAME, json.dumps(summary, indent=1) + "\n")
        write_atomic(staged / PAGE_NAME, measured_page(measurement, image, summary))
        write_atomic(staged / CONFIG_NAME, config_text)
        if (design / DESIGN_NAME).is_file():  # the display content the plate is shown with
            shutil.copyfile(design / DESIGN_NAME, staged / DESIGN_NAME)
        publish(staged, folder, command if command is not None else MEASURE_COMMAND)
    timings["write_s"] = time.perf_counter() - start
    return MeasureResult(folder, measurement, tuple(summary["notes"]), timings)


@dataclass(frozen=True)
class RefitResult:
    """What `run_refit` did: folder (the measured folder), names (T,) target names, refit (the
    content and its figures: aperture_fab.measure.refit.Refit), paths (the PNGs written),
    timings_s (seconds per stage)."""

    folder: Path
    names: tuple[str, ...]
    refit: Refit
    paths: tuple[Path, ...]
    timings_s: dict[str, float]


def run_refit(measured: Path, targets: Sequence[Path], *,
              target_options: TargetOptions | None = None, iterations: int | None = None,
              progress: bool = False, command: Sequence[str] | None = None) -> RefitResult:
    """`display --refit`: re-fit the display content to the plate as measured in the folder
    `measured` (what `measure` wrote), for the design's targets, and say how much of the
    tolerance loss that recovers (aperture_fab.measure.refit). Adds refit.json and
    refit_display_<target>.png to the folder's set. iterations: the fit's (default as
    `validate` re-fits: max(MIN_FIT_ITERATIONS, optimizer.iterations // FIT_SHARE))."""
    start = time.perf_counter()
    config_path = measured / CONFIG_NAME
    scan = measured_scan(measured)
    if not measured.is_dir() or scan is None or not config_path.is_file():
        raise ValueError(f"--refit {measured} is not a folder `aperture-fab measure` wrote (no "
                         f"{JSON_NAME} and {CONFIG_NAME}); measure the plate's scan first: "
                         "aperture-fab measure SCAN --design FOLDER --out DIR.")
    summary = json.loads((measured / JSON_NAME).read_text(encoding="utf-8"))
    design = Path(str(summary.get("design", "")))
    if not (design / DESIGN_NAME).is_file():
        raise ValueError(f"--refit {measured}: the design it was measured against, {design} "
                         f"(its {JSON_NAME}), has no {DESIGN_NAME}; the nominal plate and its "
                         "display content come from there. Put the design folder back, or "
                         "measure again with --design where it is now.")
    config = read_config(config_path)
    fabrication = config.fabrication
    made_part = load_part(measured / HOLES_NAME, "holes", config, fabrication, config_path)
    design_config = read_config(design / CONFIG_NAME)
    design_process = design_config.fabrication.process
    nominal_part = read_design_part(design)
    saved = read_design(design / DESIGN_NAME)
    check_design(saved, config, config_path)
    shipped = saved.built_displays if saved.built_displays is not None else saved.displays
    images, names = load_targets(targets, config.scene.display.pixels, target_options)
    if len(images) != len(shipped):
        raise ValueError(f"{saved.path} was designed for {len(shipped)} target(s) "
                         f"({', '.join(saved.names)}) but {len(images)} were given; give "
                         f"{len(shipped)} target(s) in the design's order.")
    view_targets, _ = prepare_targets(images, config.scene.eye.view_pixels,
                                      config.scene.display.pixels, shipped.shape[1],
                                      names=[str(t) for t in targets])
    settings = config.optimizer
    if iterations is None:
        iterations = max(MIN_FIT_ITERATIONS, settings.iterations // FIT_SHARE)
    if not (isinstance(iterations, int) and 1 <= iterations <= MAX_REFIT_ITERATIONS):
        raise ValueError(f"--iterations {iterations!r} is out of range for --refit; allowed: a "
                         f"whole number from 1 to {MAX_REFIT_ITERATIONS} (the fit's; default "
                         f"{max(MIN_FIT_ITERATIONS, settings.iterations // FIT_SHARE)}).")
    timings = {"load_s": time.perf_counter() - start}
    start = time.perf_counter()
    refit = refit_display(config.scene, view_targets,
                          layout_fractions(nominal_part.layout, design_process.radius_bias_mm),
                          layout_fractions(made_part.layout), shipped, settings, iterations,
                          progress)
    timings["refit_s"] = time.perf_counter() - start
    figures = {"scan": scan, "design": str(design), "targets": list(names),
               "iterations": iterations, "nominal_psnr_db": refit.nominal_db,
               "made_psnr_db": refit.made_db, "refit_psnr_db": refit.refit_db,
               "nominal_refit_psnr_db": refit.nominal_refit_db,
               "tolerance_loss_db": refit.loss_db, "loss_left_db": refit.left_db,
               "recovered_share": refit.recovered,
               "displays": [REFIT_DISPLAY.format(n) for n in names]}
    check_folder(measured)
    with staging(measured) as staged:
        write_atomic(staged / REFIT_NAME, json.dumps(figures, indent=1) + "\n")
        for name, content in zip(names, refit.displays, strict=True):
            write_atomic(staged / REFIT_DISPLAY.format(name), encode_png(content))
        publish(staged, measured, command if command is not None else MEASURE_COMMAND,
                add=True)
    paths = tuple(measured / REFIT_DISPLAY.format(n) for n in names)
    return RefitResult(measured, tuple(names), refit, paths, timings)
