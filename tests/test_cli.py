"""The `aperture-fab` command line: exit codes, messages, outputs and config precedence."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from importlib.metadata import entry_points
from pathlib import Path

import numpy as np
import pytest
import torch

import aperture_fab.optimize.optimizer as optimize_module
from aperture_fab.cli import EXIT_BAD_INPUT, EXIT_OK, EXIT_REPORT_FAIL, main
from aperture_fab.cli.flags import OVERRIDES
from aperture_fab.config.config import parse_toml, resolve
from aperture_fab.config.presets import PRESET_DESCRIPTIONS, PRESETS

pytestmark = pytest.mark.usefixtures("one_torch_thread")

VARIANTS = ("initial", "optimized", "open", "regular_pinholes")
#: A design that ran to the end exits with its report's verdict; these tests check its files
#: (tests/test_verdict_status.py checks the statuses).
WRITTEN = (EXIT_OK, EXIT_REPORT_FAIL)


def design_args(target: Path, config: Path, out: Path, *flags: str, quiet: bool = True
                ) -> list[str]:
    return ["design", str(target), "--config", str(config), "--out", str(out),
            *(["--quiet"] if quiet else []), *flags]


def written_config(folder: Path) -> dict:
    return parse_toml((folder / "design.toml").read_text(), "design.toml")


# --- help and presets ------------------------------------------------------------------------


def test_presets_lists_every_preset_with_its_key_numbers(capsys: pytest.CaptureFixture[str]
                                                         ) -> None:
    assert main(["presets"]) == 0
    out = capsys.readouterr().out
    assert set(PRESETS) == {"near-eye", "seed", "near-eye-nominal"}
    for name in PRESETS:
        assert f"{name}:" in out
    for numbers in ("400 x 400 pixels", "40 x 40 cells", "gap 10 mm", "pupil 4 mm",
                    "adam lr 0.1", "300 iterations",  # near-eye
                    "28 x 28 cells", "sgd lr 0.8 momentum 0.9", "init random",  # seed
                    "eyebox 4 x 4 mm ellipse", "the nominal eye only"):  # eye states
        assert numbers in out, numbers


def test_presets_prints_each_description_once(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["presets"]) == 0
    out = capsys.readouterr().out
    for description in PRESET_DESCRIPTIONS.values():
        assert out.count(description) == 1


def test_help_exits_zero_and_names_the_commands(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    assert "usage: aperture-fab" in out
    for command in ("design", "presets"):
        assert command in out


def test_design_help_lists_every_flag(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["design", "--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    for flag in ("--resume", "--preset", "--config", "--out", "--quiet"):
        assert flag in out
    for flag, *_ in OVERRIDES:
        assert flag in out
    assert "design.toml" in out and "Precedence" in out


@pytest.mark.parametrize("argv", [[], ["frobnicate"], ["design"],
                                  ["design", "x.png", "--method", "lbfgs"],
                                  ["design", "x.png", "--iterations", "many"]])
def test_usage_errors_exit_two(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    assert "usage:" in capsys.readouterr().err


# --- design ----------------------------------------------------------------------------------


def test_design_writes_outputs_and_prints_the_psnr_table(
        tmp_path: Path, marker_png: Path, tiny_toml: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out" / "plate.stl"
    # 8 iterations make a poor part: its report says FAIL, and every file is written anyway.
    assert main(design_args(marker_png, tiny_toml, out, quiet=False)) == EXIT_REPORT_FAIL
    folder = out.parent
    for name in ("design.npz", "design.toml", "design.json", "display_marker.png", "loss.png",
                 *(f"view_{v}_marker.png" for v in VARIANTS)):
        assert (folder / name).is_file(), name
    assert (folder / "plate.stl").stat().st_size > 0
    assert not list(folder.glob(".*.tmp"))
    assert not (folder / "checkpoint.pt").exists()

    lines = capsys.readouterr().out.splitlines()
    report = json.loads((folder / "report.json").read_text())
    # The table leads with the eye distribution, its verdict under it, then the nominal table;
    # the last line is the outcome: the verdict and where the report is.
    assert lines[-1].startswith(f"FAIL: wrote {folder}/ (8 iterations, stopped: ")
    assert f"{folder / 'report.html'} says do not make this part as it is; " in lines[-1]
    eyes = report["eye_distribution"]
    assert lines[0] == (f"PSNR over the eye distribution (dB), p10 / median / p90, "
                        f"{eyes['states']} states:")
    assert lines[1].split() == ["target", "as_built", "optimized", "open", "regular_pinholes"]
    cells = lines[2].split()
    assert cells[0] == "marker"
    assert " ".join(cells[1:]) == " ".join(
        " / ".join(f"{values['psnr_db'][k][0]:.1f}" for k in ("p10", "p50", "p90"))
        for values in eyes["variants"].values())
    level = report["verdicts"][0]["level"]
    assert lines[3].startswith(f"eye distribution: {level.upper()}: Over the eye distribution")
    nominal = lines.index("PSNR after gain (dB), nominal eye position:")
    assert nominal > 3
    header = lines[nominal + 1]
    assert header.split()[1:] == [*VARIANTS, "quantized", "as_built"]
    row = lines[nominal + 2]
    assert row.split()[0] == "marker"
    shown = [float(x) for x in row.split()[1:]]
    summary = json.loads((folder / "design.json").read_text())
    assert summary["iterations"] == 8
    assert summary["metrics"]["eye_distribution"]["verdict"] == report["verdicts"][0]
    assert summary["metrics"]["eye_distribution"]["variants"] == eyes["variants"]
    expected = [summary["metrics"][v]["psnr_db"][0] for v in VARIANTS]
    expected += [report["metrics"][v]["per_target"]["marker"]["psnr_db"]
                 for v in ("quantized", "as_built")]
    np.testing.assert_allclose(shown, expected, atol=0.006)
    # The baselines are rendered once (validation.validate.baseline_views): the same figures in
    # design.json and in the report (each computes its PSNR its own way, torch and numpy: they
    # differ in the last bit about one view in seven).
    for variant in ("open", "regular_pinholes"):
        assert summary["metrics"][variant]["psnr_db"] == pytest.approx(
            [report["metrics"][variant]["per_target"]["marker"]["psnr_db"]], rel=1e-12)
    with np.load(folder / "design.npz") as npz:
        assert npz["open_fraction"].shape == (16, 16)


def test_precedence_preset_then_file_then_flags(tmp_path: Path, marker_png: Path) -> None:
    config = tmp_path / "mine.toml"
    config.write_text(
        'preset = "near-eye"\n'  # the --preset flag wins over this
        "[plate]\ngap_mm = 8.0\nthickness_mm = 0.25\n"
        '[optimizer]\niterations = 2\nlearning_rate = 0.5\ndevice = "cpu"\n'
    )
    out = tmp_path / "out"
    argv = design_args(marker_png, config, out, "--preset", "seed", "--gap-mm", "6",
                       "--lr", "0.3", "--cells", "8", "6", "--pitch-mm", "0.3",
                       "--focus-mm", "500", "--view-pixels", "12", "10")
    assert main(argv) in WRITTEN
    written = written_config(out)
    assert written["preset"] == "seed"
    # From the seed preset, untouched by file or flags.
    assert written["optimizer"]["method"] == "sgd"
    assert written["optimizer"]["momentum"] == 0.9
    assert written["display"]["pixels"] == [28, 28]
    # The file over the preset.
    assert written["plate"]["thickness_mm"] == 0.25
    assert written["optimizer"]["iterations"] == 2
    # Flags over the file.
    assert written["plate"]["gap_mm"] == 6.0
    assert written["optimizer"]["learning_rate"] == 0.3
    # Flags converted to config values.
    assert written["plate"]["cells"] == [8, 6]
    assert written["plate"]["pitch_mm"] == [0.3, 0.3]
    assert written["eye"]["focus_mm"] == 500.0
    assert written["eye"]["view_pixels"] == [12, 10]
    # design.toml re-runs exactly: it resolves to the same values with no preset or flags.
    again = resolve(file_dict=written)
    assert again.scene.plate.gap_mm == 6.0 and again.optimizer.method == "sgd"
    with np.load(out / "design.npz") as npz:
        assert npz["open_fraction"].shape == (6, 8)
        assert npz["loss_history"].shape == (2,)


def test_the_written_config_reruns_the_same_design(tmp_path: Path, marker_png: Path,
                                                   tiny_toml: Path) -> None:
    first, second = tmp_path / "first", tmp_path / "second"
    assert main(design_args(marker_png, tiny_toml, first, "--gap-mm", "9")) in WRITTEN
    assert main(design_args(marker_png, first / "design.toml", second)) in WRITTEN
    assert (first / "design.toml").read_text() == (second / "design.toml").read_text()
    with np.load(first / "design.npz") as a, np.load(second / "design.npz") as b:
        np.testing.assert_array_equal(a["open_fraction"], b["open_fraction"])


@pytest.mark.parametrize(("flags", "named"), [
    (["--gap-mm", "-1"], "plate.gap_mm"),
    (["--pupil-mm", "0"], "eye.pupil_mm"),
    (["--iterations", "0"], "optimizer.iterations"),
    (["--lr", "-0.1"], "optimizer.learning_rate"),
    (["--focus-mm", "near"], "--focus-mm"),
    (["--view-pixels", "0", "4"], "eye.view_pixels"),
])
def test_a_bad_value_returns_three_naming_the_field(
        tmp_path: Path, marker_png: Path, tiny_toml: Path,
        capsys: pytest.CaptureFixture[str], flags: list[str], named: str) -> None:
    out = tmp_path / "out"
    assert main(design_args(marker_png, tiny_toml, out, *flags)) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert err.startswith("aperture-fab: error:")
    assert named in err
    assert not out.exists()  # refused before anything was written


def test_a_missing_target_returns_three_naming_the_file(
        tmp_path: Path, tiny_toml: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "no such target.png"
    assert main(design_args(missing, tiny_toml, tmp_path / "out")) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert str(missing) in err and "does not exist" in err


def test_a_garbage_target_returns_three_naming_the_file(
        tmp_path: Path, tiny_toml: Path, capsys: pytest.CaptureFixture[str]) -> None:
    garbage = tmp_path / "garbage.png"
    garbage.write_bytes(b"not a png" * 50)
    assert main(design_args(garbage, tiny_toml, tmp_path / "out")) == EXIT_BAD_INPUT
    assert str(garbage) in capsys.readouterr().err


def test_an_unknown_preset_returns_three(tmp_path: Path, marker_png: Path, tiny_toml: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    argv = design_args(marker_png, tiny_toml, tmp_path / "out", "--preset", "near_eye")
    assert main(argv) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "'near_eye'" in err
    for name in PRESETS:
        assert name in err


def test_a_missing_config_file_returns_three(tmp_path: Path, marker_png: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "nope.toml"
    assert main(design_args(marker_png, missing, tmp_path / "out")) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert str(missing) in err and "cannot read" in err


def test_a_config_syntax_error_returns_three_naming_file_and_line(
        tmp_path: Path, marker_png: Path, capsys: pytest.CaptureFixture[str]) -> None:
    broken = tmp_path / "broken.toml"
    broken.write_text("[plate]\ngap_mm = 8.0\nhole_axis = straight\n")
    assert main(design_args(marker_png, broken, tmp_path / "out")) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert str(broken) in err and "line 3" in err


def test_a_config_with_an_unknown_key_returns_three(tmp_path: Path, marker_png: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    typo = tmp_path / "typo.toml"
    typo.write_text("[plate]\ngap = 8.0\n")
    assert main(design_args(marker_png, typo, tmp_path / "out")) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "'gap'" in err and "gap_mm" in err


def test_an_output_under_a_regular_file_returns_three(
        tmp_path: Path, marker_png: Path, tiny_toml: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    blocker = tmp_path / "blocker"
    blocker.write_text("x")
    assert main(design_args(marker_png, tiny_toml, blocker / "plate.stl")) == EXIT_BAD_INPUT
    assert "blocker" in capsys.readouterr().err


# --- Ctrl-C and --resume ---------------------------------------------------------------------


def test_ctrl_c_saves_a_checkpoint_and_resume_finishes(
        tmp_path: Path, marker_png: Path, tiny_toml: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    calls = {"n": 0}
    real = optimize_module.gain_mse_states

    def interrupted(view: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        calls["n"] += 1
        if calls["n"] == 4:
            raise KeyboardInterrupt
        return real(view, target)

    monkeypatch.setattr(optimize_module, "gain_mse_states", interrupted)
    out = tmp_path / "out"
    assert main(design_args(marker_png, tiny_toml, out)) == 130
    err = capsys.readouterr().err
    assert "interrupted at iteration 3" in err and "--resume" in err
    assert (out / "checkpoint.pt").is_file()
    assert not (out / "design.npz").exists()
    monkeypatch.undo()

    assert main(design_args(marker_png, tiny_toml, out, "--resume")) in WRITTEN
    assert json.loads((out / "design.json").read_text())["iterations"] == 8
    assert not (out / "checkpoint.pt").exists()
    # Resuming again has nothing to resume from.
    assert main(design_args(marker_png, tiny_toml, out, "--resume")) == EXIT_BAD_INPUT
    assert "no checkpoint" in capsys.readouterr().err


# --- installation ----------------------------------------------------------------------------


def test_the_console_script_points_at_main() -> None:
    scripts = {e.name: e.value for e in entry_points(group="console_scripts")}
    assert scripts.get("aperture-fab") == "aperture_fab.cli:main"


def test_the_module_runs_as_a_program(tmp_path: Path) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-m", "aperture_fab.cli", "design", "--help"],
                          capture_output=True, text=True, env=env, cwd=tmp_path, timeout=120)
    assert done.returncode == 0, done.stderr
    assert re.search(r"usage: aperture-fab design", done.stdout)
    assert "--resume" in done.stdout


@pytest.mark.slow
def test_a_part_a_regular_array_beats_is_designed_again_on_its_lattice(
        tmp_path: Path, marker_png: Path, tiny_toml: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    """--lattice rival: the tiny part loses to a regular array on a coarser lattice, so the job
    designs on that lattice too, keeps the part with the larger margin and says so."""
    out = tmp_path / "out"
    main(design_args(marker_png, tiny_toml, out, "--lattice", "rival", quiet=False))
    said = capsys.readouterr()
    assert "designing again on its lattice" in said.out + said.err
    first, second = json.loads((out / "design.json").read_text())["lattices"]
    assert first["cells"] == [16, 16] and first["margin_db"][0] < 0
    assert second["pitch_mm"][0] > first["pitch_mm"][0]
    assert first["kept"] != second["kept"]
    kept = first if first["kept"] else second
    assert written_config(out)["plate"]["cells"] == kept["cells"]
    report = json.loads((out / "report.json").read_text())
    assert report["scene"]["plate"]["cells"] == kept["cells"]
    # Each design's stages are timed (bench_end_to_end sums them); the report's are the kept's.
    assert first["timings_s"]["optimize_s"] > 0 and second["timings_s"]["optimize_s"] > 0
    assert kept["timings_s"]["optimize_s"] == report["timings_s"]["optimize_s"]
    # A part made on the rival's lattice says which part it replaces; the first part kept says
    # what the job tried, in report.json and on the page.
    assert ("replaces" in report["run"]) == second["kept"]
    assert ("tried" in report["run"]) == first["kept"]
    page = (out / "report.html").read_text()
    assert ("also designed on the lattice" in page) == first["kept"]
    if first["kept"]:
        assert report["run"]["tried"] == {k: second[k] for k in ("pitch_mm", "cells",
                                                                  "margin_db")}
