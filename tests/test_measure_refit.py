"""`aperture-fab display --refit MEASURED_FOLDER` (issue 17, item 3): the display content
re-fitted to the measured plate recovers at least half of the tolerance loss (nominal as built
against the made copy with the design's content) on simulated made copies: of their loss
together at the default learning rate, and of each copy's at the learning rate 0.05."""

from __future__ import annotations

import json
import statistics
from pathlib import Path
from typing import Any

import pytest
from conftest import design_tiny
from test_measure_judge import write_scan

from aperture_fab.cli import EXIT_OK, EXIT_USAGE, main
from aperture_fab.io.manifest import check_folder
from aperture_fab.measure.job import read_design_part
from aperture_fab.measure.simulate import ScanSettings, simulate_scan

pytestmark = pytest.mark.usefixtures("one_torch_thread")

#: The tiny design optimized far enough that its holes matter (100 iterations: 18.4 dB at the
#: learning rate 0.05, 19.7 dB at the default 0.1; the 8-iteration `designed` fixture's 10 dB
#: view barely depends on its holes, and a made copy scores as often above it as below).
ITERATIONS = "100"
#: The learning rate at which every copy of SEEDS recovers half its own loss (docs/measure.md):
#: at the default 0.1 copy 11 recovers 23 % of its 0.27 dB (the pooled test below).
LEARNING_RATE = "0.05"
#: Made copies of its photomask plate: radius sigma 3 um (the process's 2 um, worse), position
#: sigma 5 um (the process's), no bias (the process's, compensated in the drawing), three holes
#: blocked; scanned at 4800 dpi, turned 7 degrees (examples/simulate_scan.py's copy with
#: --blocked 3 --radius-sigma-um 3 --dust 0).
COPY = dict(dpi=4800, rotation_deg=7.0, radius_bias_mm=0.0, radius_sigma_mm=0.003,
            position_sigma_mm=0.005, blocked=3)
#: Copies that lose against the lr 0.05 design (seed 14's scores above it: nothing to recover).
SEEDS = (11, 12, 13)
#: Copies of the default design, pooled: every one of them loses against it. Over seeds 11 to
#: 30 the refit recovers 76 % of their loss together, the median copy 71 %, 18 of 20 at least
#: half (docs/measure.md); these six: 68 %, median 66 %.
POOLED_SEEDS = tuple(range(11, 17))
#: The issue's goal: at least half of the tolerance loss recovered.
GOAL_SHARE = 0.5


def _design(folder: Path, *flags: str) -> Path:
    assert design_tiny(folder, "--iterations", ITERATIONS, *flags, "--out",
                       str(folder / "plate.stl"), "--no-validate", "--quiet") == 0
    return folder


@pytest.fixture(scope="module")
def converged(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _design(tmp_path_factory.mktemp("converged"), "--lr", LEARNING_RATE)


@pytest.fixture(scope="module")
def converged_default(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _design(tmp_path_factory.mktemp("converged_default"))


def refit_copy(designed: Path, folder: Path, seed: int,
               capsys: pytest.CaptureFixture[str]) -> dict[str, Any]:
    """Scan a made copy (seed) of `designed`, measure it into folder/made, re-fit the display to
    it; refit.json's figures, after the checks every re-fit passes."""
    part = read_design_part(designed)
    scan = simulate_scan(part.layout, ScanSettings(**COPY, seed=seed),  # type: ignore[arg-type]
                         part.corner_cut_mm)
    path = write_scan(folder / f"scan_{seed}.png", scan)
    made = folder / f"made_{seed}"
    assert main(["measure", str(path), "--design", str(designed), "--out", str(made),
                 "--quiet"]) == EXIT_OK
    assert main(["display", "--refit", str(made), str(designed / "marker.png")]) == EXIT_OK
    assert "tolerance loss" in capsys.readouterr().out
    figures: dict[str, Any] = json.loads((made / "refit.json").read_text())
    print(f"seed {seed}: nominal {figures['nominal_psnr_db']:.2f} dB, made "
          f"{figures['made_psnr_db']:.2f} dB, refit {figures['refit_psnr_db']:.2f} dB, "
          f"nominal refit {figures['nominal_refit_psnr_db']:.2f} dB, "
          f"recovered {figures['recovered_share']}")
    assert figures["tolerance_loss_db"] > 0  # these copies lose against the design
    # The fit optimizes the model it is judged by, from the design's content: the nominal
    # plate's refit does not judge worse than the design (fitted at one sample per pixel and
    # the full learning rate it did, by 0.11 dB on the lr 0.1 design), nor the made plate's.
    assert figures["nominal_refit_psnr_db"] >= figures["nominal_psnr_db"]
    assert figures["refit_psnr_db"] >= figures["made_psnr_db"]
    assert (made / "refit_display_marker.png").is_file()
    check_folder(made)  # the figures joined the measured set
    return figures


@pytest.mark.parametrize("seed", SEEDS)
def test_the_refit_recovers_at_least_half_of_each_copys_loss(
        converged: Path, tmp_path: Path, seed: int, capsys: pytest.CaptureFixture[str]) -> None:
    figures = refit_copy(converged, tmp_path, seed, capsys)
    assert figures["recovered_share"] >= GOAL_SHARE


def test_at_the_default_learning_rate_the_refit_recovers_half_the_copies_loss(
        converged_default: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    copies = [refit_copy(converged_default, tmp_path, seed, capsys) for seed in POOLED_SEEDS]
    loss = sum(f["tolerance_loss_db"] for f in copies)
    left = sum(f["nominal_refit_psnr_db"] - f["refit_psnr_db"] for f in copies)
    assert 1 - left / loss >= GOAL_SHARE
    assert statistics.median(f["recovered_share"] for f in copies) >= GOAL_SHARE


def test_display_usage_with_and_without_refit(designed: Path, tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["display", str(designed / "design.npz"), str(designed / "marker.png"),
              "--pupil", "4", "--out", str(tmp_path / "f.png")])
    assert exit_.value.code == EXIT_USAGE
    assert "the following arguments are required: --eye" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["display", "--refit", str(tmp_path), str(designed / "marker.png"), "--eye",
              "0,0"])
    assert "drop --eye" in capsys.readouterr().err
    assert main(["display", "--refit", str(tmp_path), str(designed / "marker.png")]) != EXIT_OK
    assert "measure the plate's scan first" in capsys.readouterr().err
