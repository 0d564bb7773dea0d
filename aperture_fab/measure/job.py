"""The `aperture-fab measure` job: read a scan and a design folder, measure, write holes.csv,
measured.json and measured.html (each atomically) into the output folder."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

from aperture_fab.fabrication.part import Part, fabrication_settings
from aperture_fab.io.files import output_folder, write_atomic
from aperture_fab.io.formats import holes_csv
from aperture_fab.measure.measure import Measurement, NoHolesError, measure_plate
from aperture_fab.measure.register import RegistrationError
from aperture_fab.measure.report import measured_json, measured_layout, measured_page
from aperture_fab.measure.scan import ScanEncoding, decode_scan
from aperture_fab.pipeline.saved import CONFIG_NAME, load_part, read_config

__all__ = ["HOLES_NAME", "MeasureResult", "read_design_part", "run_measure"]

HOLES_NAME = "holes.csv"
JSON_NAME = "measured.json"
PAGE_NAME = "measured.html"


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
    return load_part(table, "holes", config, fabrication_settings(config.extra, {}), config_path)


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


def run_measure(scan: Path, design: Path, out: Path, mm_per_px: float,
                encoding: ScanEncoding = "linear") -> MeasureResult:
    """Measure `scan` (an image file) of the plate made from the design folder `design` at
    mm_per_px, and write the results into the folder `out`."""
    timings: dict[str, float] = {}
    start = time.perf_counter()
    part = read_design_part(design)
    image = decode_scan(_read_scan(scan, encoding), str(scan), encoding)
    timings["read_s"] = time.perf_counter() - start
    start = time.perf_counter()
    try:
        measurement = measure_plate(image, part.layout, mm_per_px)
    except NoHolesError as err:
        raise NoHolesError(f"scan {scan}: {err}. Expected the plate's {part.layout.count} "
                           "holes as bright disks on the dark solid: scan with the "
                           "transparency unit (back light) on, the plate flat on the glass, "
                           "and save the scan linear (gamma 1.0).") from err
    except RegistrationError as err:
        raise RegistrationError(f"scan {scan} measured against the design {design} "
                                f"({part.layout.count} holes): {err}") from err
    timings["measure_s"] = time.perf_counter() - start
    start = time.perf_counter()
    folder = output_folder(out)
    summary = measured_json(measurement, str(scan), str(design))
    write_atomic(folder / HOLES_NAME, holes_csv(measured_layout(measurement)))
    write_atomic(folder / JSON_NAME, json.dumps(summary, indent=1) + "\n")
    write_atomic(folder / PAGE_NAME, measured_page(measurement, image, summary))
    timings["write_s"] = time.perf_counter() - start
    return MeasureResult(folder, measurement, tuple(summary["notes"]), timings)
