"""`aperture-fab measure` (issue 17, item 1): what it writes, and its refusals' exit status."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import png
import pytest
from test_measure import grid_layout

from aperture_fab.cli import EXIT_BAD_INPUT, EXIT_OK, main
from aperture_fab.config.config import parse_toml, resolve
from aperture_fab.io.formats import read_holes_csv
from aperture_fab.measure.job import read_design_part
from aperture_fab.measure.simulate import ScanSettings, simulate_scan


def _write_png(path: Path, image: np.ndarray, bits: int = 16) -> Path:
    with path.open("wb") as f:
        png.Writer(image.shape[1], image.shape[0], greyscale=image.ndim == 2,
                   bitdepth=bits).write(f, image.reshape(image.shape[0], -1))
    return path


def _scan(designed: Path, tmp_path: Path, **settings: object) -> tuple[Path, object]:
    part = read_design_part(designed)
    scan = simulate_scan(part.layout, ScanSettings(dpi=4800, **settings),  # type: ignore[arg-type]
                         part.corner_cut_mm)
    bits = 8 if scan.image.dtype == np.uint8 else 16
    return _write_png(tmp_path / "scan.png", scan.image, bits), scan


def test_measure_writes_a_hole_table_json_and_page(designed: Path, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    path, _ = _scan(designed, tmp_path, rotation_deg=-33, blocked=1, colour="rgb", bits=8)
    out = tmp_path / "made"
    assert main(["measure", str(path), "--design", str(designed), "--out", str(out)]) == EXIT_OK
    report = json.loads((out / "measured.json").read_text())
    assert report["registration"]["mirror"] is False
    assert report["registration"]["rotation_deg"] == pytest.approx(327, abs=0.1)
    assert report["defects"]["blocked"] >= 1
    assert "measured.html" in {p.name for p in out.iterdir()}
    # holes.csv reads back as the design's plate does.
    config = resolve(None, parse_toml((designed / "design.toml").read_text(), "design.toml"))
    layout = read_holes_csv((out / "holes.csv").read_text(), config.scene.plate,
                            outline_mm=read_design_part(designed).layout.outline_mm)
    assert layout.count == sum(h["radius_mm"] is not None for h in report["holes"])
    assert "holes measured" in capsys.readouterr().out


def test_a_mirrored_scan_is_measured_mirrored_with_a_warning(
        designed: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, _ = _scan(designed, tmp_path, rotation_deg=12, mirror=True, radius_sigma_mm=0.006)
    out = tmp_path / "made"
    assert main(["measure", str(path), "--design", str(designed), "--out", str(out)]) == EXIT_OK
    assert json.loads((out / "measured.json").read_text())["registration"]["mirror"] is True
    assert "mirrored" in capsys.readouterr().err


@pytest.mark.parametrize("case", ["missing", "not an image", "hole-free", "wrong design"])
def test_bad_scans_exit_3_naming_the_input(designed: Path, tmp_path: Path, case: str,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "scan.png"
    expect = {"missing": "does not exist", "not an image": "not a readable image",
              "hole-free": "no openings", "wrong design": "Check --design"}[case]
    if case == "not an image":
        path.write_bytes(b"\x89PNG\r\n\x1a\nbroken")
    elif case == "hole-free":
        _write_png(path, np.full((300, 400), 300, dtype=np.uint16))
    elif case == "wrong design":
        other = simulate_scan(grid_layout(n=6), ScanSettings(dpi=4800))
        _write_png(path, other.image)
    status = main(["measure", str(path), "--design", str(designed), "--out",
                   str(tmp_path / "made")])
    err = capsys.readouterr().err
    assert status == EXIT_BAD_INPUT
    assert expect in err and ("scan" in err or "design" in err)
    assert not (tmp_path / "made" / "measured.json").exists()
