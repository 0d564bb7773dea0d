"""`aperture-fab measure --coupon` (issue 17, item 4): the calibration coupon's scan gives the
process's smallest hole, radius bias and sigma and position sigma, written as a config that
`design --config` takes."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import numpy as np
import pytest
from test_measure_judge import write_scan

from aperture_fab.cli import EXIT_BAD_INPUT, EXIT_OK, main
from aperture_fab.config.config import parse_toml, resolve
from aperture_fab.measure.job import read_design_coupon
from aperture_fab.measure.simulate import ScanSettings, SimulatedScan, simulate_scan

pytestmark = pytest.mark.usefixtures("one_torch_thread")

#: A photomask coupon (drawn diameters 12.5 to 50 um) made 1.5 um small in radius, 1 um radius
#: and 3 um position scatter, holes under 8.5 um made radius closed: the two smallest blocks
#: stay shut, the third and fourth partly, the rest come through whole. 4800 dpi, turned.
MADE = dict(dpi=4800, rotation_deg=93.0, radius_bias_mm=-0.0015, radius_sigma_mm=0.001,
            position_sigma_mm=0.003, closed_below_mm=0.0085, dust_open=1, dust_dark=2, seed=1)
#: How close the measured values must be to the made coupon's own (um): the radius is measured
#: to about 0.2 um RMS on these 2-5 px holes and 125 holes average it; the sigmas rest on 125
#: holes (a sigma's own sampling error is sigma / sqrt(2 n): 6 %).
BIAS_UM, SIGMA_UM, POSITION_UM = 0.3, 0.25, 0.6


def truth_of(coupon_diameters: tuple[float, ...], scan: SimulatedScan, drawn_r: np.ndarray
             ) -> dict[str, float]:
    """The made coupon's own values, computed as the calibration defines them."""
    closed = scan.truth.blocked.reshape(len(coupon_diameters), -1).any(axis=1)
    first = int(np.flatnonzero(closed).max()) + 1
    per_block = scan.truth.blocked.size // len(coupon_diameters)
    used = np.arange(scan.truth.blocked.size) >= first * per_block
    made = scan.truth.radii_mm[used]
    blocks = made.reshape(-1, per_block)
    within = np.sqrt(np.sum((blocks - blocks.mean(axis=1, keepdims=True)) ** 2)
                     / (made.size - len(blocks)))
    return {"min_hole_mm": coupon_diameters[first],
            "radius_bias_mm": float(np.mean(made - drawn_r[used])),
            "radius_sigma_mm": float(within)}


def test_measure_coupon_writes_the_process_that_design_takes(
        designed: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    coupon, part = read_design_coupon(designed)
    scan = simulate_scan(part.layout, ScanSettings(**MADE), part.corner_cut_mm)  # type: ignore[arg-type]
    path = write_scan(tmp_path / "coupon.png", scan)
    out = tmp_path / "coupon"
    assert main(["measure", str(path), "--design", str(designed), "--coupon", "--out",
                 str(out)]) == EXIT_OK
    assert "process.toml" in capsys.readouterr().out
    truth = truth_of(coupon.diameters_mm, scan, part.layout.radii_mm)
    process = tomllib.loads((out / "process.toml").read_text())["process"]
    assert process["name"] == "photomask"
    assert process["min_hole_mm"] == pytest.approx(truth["min_hole_mm"])
    assert process["radius_bias_mm"] == pytest.approx(truth["radius_bias_mm"],
                                                      abs=BIAS_UM / 1000)
    assert process["radius_sigma_mm"] == pytest.approx(truth["radius_sigma_mm"],
                                                       abs=SIGMA_UM / 1000)
    assert process["position_sigma_mm"] == pytest.approx(0.003, abs=POSITION_UM / 1000)
    report = json.loads((out / "measured.json").read_text())
    opened = [b["opened"] for b in report["coupon"]["blocks"]]
    assert opened == [int(n) for n in (~scan.truth.blocked).reshape(len(opened), -1).sum(1)]
    # design --config takes it: the process as measured, the rest the design's config.
    config = resolve(None, parse_toml((out / "process.toml").read_text(), "process.toml"))
    made = config.fabrication.process
    assert made.radius_bias_mm == process["radius_bias_mm"]
    assert made.min_hole_for(config.scene.plate.thickness_mm) == process["min_hole_mm"]
    redesign = tmp_path / "redesign"
    assert main(["design", str(designed / "marker.png"), "--config", str(out / "process.toml"),
                 "--iterations", "2", "--no-validate", "--quiet", "--out",
                 str(redesign / "plate.stl")]) == EXIT_OK
    again = tomllib.loads((redesign / "design.toml").read_text())["process"]
    assert again["radius_bias_mm"] == process["radius_bias_mm"]


def test_a_plate_scan_is_not_a_coupon(designed: Path, tmp_path: Path,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    from aperture_fab.measure.job import read_design_part

    part = read_design_part(designed)
    scan = simulate_scan(part.layout, ScanSettings(dpi=4800), part.corner_cut_mm)
    path = write_scan(tmp_path / "plate.png", scan)
    status = main(["measure", str(path), "--design", str(designed), "--coupon", "--out",
                   str(tmp_path / "coupon")])
    err = capsys.readouterr().err
    assert status == EXIT_BAD_INPUT and "calibration coupon" in err
    assert not (tmp_path / "coupon" / "process.toml").exists()
