"""An output folder is one consistent set (issue 10): staged and published at once with
manifest.json, refused runs change nothing, stale files never outlive their run, readers refuse
a folder that does not match its manifest, the process and the outline are recorded, and
--resume compares its inputs' content."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest
import torch
from conftest import TINY_TOML, interrupt_at_call, tiny_config

from aperture_fab.cli import EXIT_OK, EXIT_REPORT_FAIL, main
from aperture_fab.config.presets import DEFAULT_PROCESS
from aperture_fab.io.images import encode_png
from aperture_fab.io.manifest import MANIFEST_NAME, check_folder
from aperture_fab.optimize.optimizer import Interrupted
from aperture_fab.pipeline.design_job import run_design
from aperture_fab.targets import asymmetric_marker, checker

pytestmark = pytest.mark.usefixtures("one_torch_thread")

#: A tiny design: three iterations, no validation unless a test adds it.
TINY_FLAGS = ["--iterations", "3", "--quiet"]
FAST_VALIDATION = ["--tolerance-samples", "2", "--mesh-samples", "8"]
#: How long the signal test's child pauses after each group of staged files.
STAGE_PAUSE_S = 0.4
#: How long the signal test waits for the child to reach a kill point.
KILL_POINT_TIMEOUT_S = 120.0


def snapshot(folder: Path) -> dict[str, str]:
    """Every file under folder (relative path -> SHA-256 of its bytes)."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def design_cli(folder: Path, *extra: str, target: str = "marker.png") -> int:
    return main(["design", str(folder / target), "--config", str(folder / "tiny.toml"),
                 "--out", str(folder), *TINY_FLAGS, *extra])


@pytest.fixture(scope="module")
def validated_set(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny design folder written with validation, plus the user's own files."""
    folder = tmp_path_factory.mktemp("set")
    (folder / "tiny.toml").write_text(TINY_TOML)
    (folder / "marker.png").write_bytes(encode_png(asymmetric_marker(32)))
    (folder / "notes.txt").write_text("the user's own file\n")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert design_cli(folder, *FAST_VALIDATION) in (EXIT_OK, EXIT_REPORT_FAIL)  # any verdict
    finally:
        torch.set_num_threads(threads)
    return folder


@pytest.fixture
def folder(validated_set: Path, tmp_path: Path) -> Path:
    """A private copy of the validated design folder."""
    target = tmp_path / "set"
    shutil.copytree(validated_set, target)
    return target


def manifest_files(folder: Path) -> dict[str, dict[str, object]]:
    return json.loads((folder / MANIFEST_NAME).read_text())["files"]


# --- publishing ------------------------------------------------------------------------------


def test_a_run_publishes_every_file_in_its_manifest(folder: Path) -> None:
    manifest = json.loads((folder / MANIFEST_NAME).read_text())
    assert manifest["complete"] is True
    assert manifest["command"][:2] == ["aperture-fab", "design"]
    assert manifest["tool_version"] and manifest["created_utc"]
    files = manifest["files"]
    assert {"plate.stl", "holes.csv", "plate.dxf", "design.toml", "design.npz", "report.json",
            "views.npz"} <= set(files)
    for name, entry in files.items():
        data = (folder / name).read_bytes()
        assert entry["sha256"] == hashlib.sha256(data).hexdigest()
        assert entry["size_bytes"] == len(data)
        assert ("content_sha256" in entry) == name.endswith(".toml")
    # The user's files are not the run's; no staging folder or temporary file is left.
    assert "notes.txt" not in files and "marker.png" not in files
    assert not [p for p in folder.iterdir() if p.name.startswith(".")]
    check_folder(folder)


@pytest.mark.parametrize(("flags", "target", "message"), [
    (["--gap-mm", "-1"], "marker.png", "gap_mm"),  # a bad config
    (["--process", "fdm"], "marker.png", "fdm"),  # a process that cannot make the plate
    ([], "missing.png", "missing.png"),  # a missing target
    ([], "notes.txt", "notes.txt"),  # a file that is not an image
])
def test_a_refused_rerun_leaves_the_folder_byte_identical(
        folder: Path, flags: list[str], target: str, message: str,
        capsys: pytest.CaptureFixture[str]) -> None:
    before = snapshot(folder)
    assert design_cli(folder, *flags, target=target) != 0
    assert message in capsys.readouterr().err
    assert snapshot(folder) == before


@pytest.mark.parametrize(("flags", "target", "floor"), [
    ([], "missing.png", 0.0),  # a missing target
    (["--process", "fdm"], "marker.png", 0.0),  # a process that cannot make the plate
    ([], "marker.png", 0.99),  # a brightness floor no plate reaches (refused in the job)
])
def test_a_refused_first_run_leaves_no_folder_behind(
        folder: Path, tmp_path: Path, flags: list[str], target: str, floor: float) -> None:
    config = tmp_path / "floor.toml"
    config.write_text(TINY_TOML.replace("min_efficiency = 0.0", f"min_efficiency = {floor}"))
    out = tmp_path / "new" / "deeper" / "plate.stl"
    assert main(["design", str(folder / target), "--config", str(config), "--out", str(out),
                 *TINY_FLAGS, *flags]) != 0
    assert not (tmp_path / "new").exists()


def test_a_refused_first_run_keeps_the_folders_that_were_there(folder: Path,
                                                              tmp_path: Path) -> None:
    (tmp_path / "mine").mkdir()
    out = tmp_path / "mine" / "run"
    assert main(["design", str(folder / "missing.png"), "--config",
                 str(folder / "tiny.toml"), "--out", str(out), *TINY_FLAGS]) != 0
    assert (tmp_path / "mine").is_dir() and not out.exists()


def test_a_rerun_without_validation_leaves_no_stale_report(folder: Path) -> None:
    stale = folder / "view_initial_old.png"  # a view of a target the new run does not have
    stale.write_bytes((folder / "view_initial_marker.png").read_bytes())
    manifest = json.loads((folder / MANIFEST_NAME).read_text())
    manifest["files"][stale.name] = manifest["files"]["view_initial_marker.png"]  # the run's
    (folder / MANIFEST_NAME).write_text(json.dumps(manifest))
    holiday = folder / "view_holiday.png"  # named like ours, but no manifest lists it
    holiday.write_bytes(b"the user's photo")
    assert design_cli(folder, "--no-validate", "--seed", "5") == 0
    names = {p.name for p in folder.iterdir()}
    assert not names & {"report.json", "report.html", "views.npz", stale.name}
    assert set(manifest_files(folder)) == names - {"tiny.toml", "marker.png", "notes.txt",
                                                   holiday.name, MANIFEST_NAME}
    assert (folder / "notes.txt").read_text() == "the user's own file\n"
    assert holiday.read_bytes() == b"the user's photo"
    check_folder(folder)


# --- readers check the manifest -------------------------------------------------------------


def _append(path: Path) -> None:
    """Change a file: a byte more, or for a TOML file a value (a comment is harmless)."""
    if path.suffix == ".toml":
        text = path.read_text()
        assert "seed = 0" in text
        path.write_text(text.replace("seed = 0", "seed = 1", 1))
    else:
        path.write_bytes(path.read_bytes() + b"\n")


@pytest.mark.parametrize(("changed", "command", "named"), [
    ("design.npz", ["render", "{d}/design.npz"], "design.npz differs"),
    ("design.toml", ["validate", "{d}/holes.csv", "{d}/marker.png"], "design.toml differs"),
    ("plate.stl", ["render", "{d}/holes.csv"], "plate.stl differs"),
    ("report.html", ["export", "{d}/design.npz", "--out", "{d}/../exported"],
     "report.html differs"),
    ("design.toml", ["display", "{d}/design.npz", "{d}/marker.png", "--eye", "0,0", "--pupil",
                     "4", "--out", "{d}/../frame.png"], "design.toml differs"),
])
def test_readers_refuse_a_folder_that_does_not_match_its_manifest(
        folder: Path, changed: str, command: list[str], named: str,
        capsys: pytest.CaptureFixture[str]) -> None:
    _append(folder / changed)
    assert main([a.format(d=folder) for a in command]) != 0
    err = capsys.readouterr().err
    assert named in err and MANIFEST_NAME in err and "re-run" in err


def test_a_comment_in_design_toml_is_harmless(folder: Path) -> None:
    config = folder / "design.toml"
    config.write_text("# printed on the lab's film, 2026-11-26\n" + config.read_text()
                      + "\n# gap checked with calipers\n")
    check_folder(folder)
    assert main(["render", str(folder / "design.npz"), "--out", str(folder.parent / "v.png"),
                 "--quiet"]) == 0


def test_a_rerun_into_a_validated_design_is_refused_unless_forced(
        folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    checked = folder / "validate_plate"  # validate's default folder beside the part
    assert main(["validate", str(folder / "plate.stl"), str(folder / "marker.png"), "--quiet",
                 *FAST_VALIDATION]) in (EXIT_OK, EXIT_REPORT_FAIL)
    assert (checked / "report.json").is_file()
    before = snapshot(folder)
    assert design_cli(folder, "--no-validate", "--seed", "5") != 0
    err = capsys.readouterr().err
    assert "was validated" in err and str(checked / "report.json") in err and "--force" in err
    assert snapshot(folder) == before
    (checked / "notes.txt").write_text("mine")  # the user's file in it stays, and so the folder
    assert design_cli(folder, "--no-validate", "--seed", "5", "--force") == 0
    assert [p.name for p in checked.iterdir()] == ["notes.txt"]
    check_folder(folder)


def test_a_partial_set_is_refused_and_deleting_the_manifest_accepts_it(
        folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (folder / "plate.dxf").unlink()
    assert main(["render", str(folder / "design.npz"), "--out", str(folder / "v.png")]) != 0
    assert "plate.dxf is listed but missing" in capsys.readouterr().err
    (folder / MANIFEST_NAME).unlink()
    assert main(["render", str(folder / "design.npz"), "--out", str(folder / "v.png")]) == 0


def test_a_hole_table_edited_by_hand_may_be_validated_in_place(folder: Path) -> None:
    lines = (folder / "holes.csv").read_text().splitlines()
    fields = lines[1].split(",")
    fields[4] = "0"  # close the first hole
    (folder / "holes.csv").write_text("\n".join([lines[0], ",".join(fields), *lines[2:]]) + "\n")
    out = folder.parent / "check"
    assert main(["validate", str(folder / "holes.csv"), str(folder / "marker.png"), "--out",
                 str(out), "--keep-display", "--quiet", *FAST_VALIDATION]) in (
                     EXIT_OK, EXIT_REPORT_FAIL)


def test_validate_publishes_its_own_set_and_refuses_a_design_folder(
        folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = folder.parent / "validated"
    assert main(["validate", str(folder / "plate.stl"), str(folder / "marker.png"), "--out",
                 str(out), "--quiet", *FAST_VALIDATION]) in (EXIT_OK, EXIT_REPORT_FAIL)
    check_folder(out)  # report, views and display content, with their manifest
    assert set(manifest_files(out)) >= {"report.json", "report.html", "views.npz"}
    before = snapshot(folder)
    assert main(["validate", str(folder / "plate.stl"), str(folder / "marker.png"), "--out",
                 str(folder), "--quiet", *FAST_VALIDATION]) != 0
    assert "holds a design" in capsys.readouterr().err
    assert snapshot(folder) == before


def test_export_refuses_to_overwrite_a_published_set(
        folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    before = snapshot(folder)
    assert main(["export", str(folder / "design.npz"), "--out", str(folder / "plate.dxf"),
                 "--quiet"]) != 0
    assert "plate.dxf" in capsys.readouterr().err
    assert snapshot(folder) == before


# --- the process and the outline are recorded -----------------------------------------------


def test_outline_is_stated_in_every_record(folder: Path) -> None:
    recorded = tomllib.loads((folder / "design.toml").read_text())
    outline = recorded["part"]["outline_mm"]
    assert len(outline) == 2 and all(v > 4.0 for v in outline)  # 16 cells of 0.25 mm + margin
    assert recorded["process"]["name"] == DEFAULT_PROCESS
    assert set(recorded["fabrication"]) == {"force", "step", "alignment_cut", "svg_polarity"}
    summary = json.loads((folder / "design.json").read_text())
    assert summary["fabrication"]["outline_mm"] == pytest.approx(outline)
    report = json.loads((folder / "report.json").read_text())
    assert report["fabrication"]["outline_mm"] == pytest.approx(outline)
    assert "outline_mm" in (folder / "report.html").read_text()
    last = (folder / "holes.csv").read_text().splitlines()[-1]
    assert last.startswith("#") and f"outline_mm {outline[0]:.6f} x {outline[1]:.6f}" in last


def test_the_recorded_process_is_used_by_export_and_validate(tmp_path: Path) -> None:
    (tmp_path / "tiny.toml").write_text(TINY_TOML)
    (tmp_path / "marker.png").write_bytes(encode_png(asymmetric_marker(32)))
    out = tmp_path / "mask"
    assert main(["design", str(tmp_path / "marker.png"), "--config", str(tmp_path / "tiny.toml"),
                 "--out", str(out), "--process", "photomask", "--thickness-mm", "0.1",
                 "--no-validate", *TINY_FLAGS]) == 0
    assert tomllib.loads((out / "design.toml").read_text())["process"]["name"] == "photomask"
    # Resin cannot make a 0.1 mm plate: export and validate must take photomask from the record.
    exported = tmp_path / "again"
    assert main(["export", str(out / "design.npz"), "--out", str(exported), "--quiet"]) == 0
    assert (exported / "holes.csv").read_bytes() == (out / "holes.csv").read_bytes()
    assert (exported / "plate.dxf").is_file()
    check = tmp_path / "check"
    assert main(["validate", str(out / "holes.csv"), str(tmp_path / "marker.png"), "--out",
                 str(check), "--quiet", *FAST_VALIDATION]) in (EXIT_OK, EXIT_REPORT_FAIL)
    report = json.loads((check / "report.json").read_text())
    assert report["fabrication"]["process"] == "photomask"
    # --process still overrides the record (and resin refuses the 0.1 mm plate).
    assert main(["export", str(out / "design.npz"), "--out", str(tmp_path / "resin"),
                 "--process", "resin", "--quiet"]) != 0


# --- resume compares content ----------------------------------------------------------------


@pytest.mark.parametrize("change", ["target", "config"])
def test_resume_refuses_a_changed_input_naming_it(tmp_path: Path, change: str,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    config = tiny_config(**{"optimizer.iterations": 6, "optimizer.checkpoint_every": 2})
    target = tmp_path / "t.png"
    target.write_bytes(encode_png(asymmetric_marker(32)))
    out = tmp_path / "out"
    interrupt_at_call(monkeypatch, 4)
    with pytest.raises(Interrupted):
        run_design([target], out, config, progress=False)
    monkeypatch.undo()
    assert (out / "checkpoint.pt").is_file()
    assert not (out / MANIFEST_NAME).exists()  # an interrupted run publishes nothing
    if change == "target":  # the same path, other pixels
        target.write_bytes(encode_png(checker(32)))
        named = "target image 1"
    else:
        config = tiny_config(**{"optimizer.iterations": 6, "optimizer.checkpoint_every": 2,
                                "plate.gap_mm": 9.0})
        named = "the config"
    with pytest.raises(ValueError, match=named) as info:
        run_design([target], out, config, resume=True, progress=False)
    assert "SHA-256" in str(info.value) and "without --resume" in str(info.value)
    assert (out / "checkpoint.pt").is_file()  # kept for the right inputs


# --- killed while exporting -----------------------------------------------------------------

CHILD = """\
import sys, time
from pathlib import Path
from aperture_fab.config.config import parse_toml, resolve

from aperture_fab.pipeline.design_job import run_design

folder = Path(sys.argv[1])
config = resolve(None, parse_toml((folder / "tiny.toml").read_text(), "tiny.toml"),
                 {{"optimizer.iterations": 3, "optimizer.seed": 11}})
run_design([folder / "marker.png"], folder, config,
           fabrication=config.fabrication, progress=False,
           on_staged=lambda stage: time.sleep({pause}))
"""


def _staged_count(folder: Path) -> int:
    """Files finished in the staging folders (none once the run has published)."""
    count = 0
    for stage in folder.glob(".staging-*"):
        try:
            count += sum(1 for p in stage.iterdir() if not p.name.endswith(".tmp"))
        except FileNotFoundError:  # published and removed meanwhile
            pass
    return count


@pytest.mark.slow
@pytest.mark.parametrize("kill_after_files", [1, 12, 15])
def test_a_run_killed_during_export_leaves_the_old_set_or_the_new(
        folder: Path, kill_after_files: int) -> None:
    """SIGKILL once the staging folder holds some files: 1, while the design's own files are
    staged; 12, between part files; 15, after the last, before publishing (the child pauses
    after each group of files via run_design's on_staged seam). The folder is still the old
    set, whole."""
    old = manifest_files(folder)
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD.format(pause=STAGE_PAUSE_S), str(folder)],
        cwd=Path(__file__).resolve().parents[1], stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE, env={**os.environ, "OMP_NUM_THREADS": "1"})
    deadline = time.monotonic() + KILL_POINT_TIMEOUT_S
    try:
        while _staged_count(folder) < kill_after_files:
            assert child.poll() is None, child.stderr.read().decode() if child.stderr else ""
            assert time.monotonic() < deadline, "the child never reached the kill point"
            time.sleep(0.01)
        child.send_signal(signal.SIGKILL)
    finally:
        child.wait()
    check_folder(folder)  # the manifest verifies: a whole set
    assert manifest_files(folder) == old  # and it is the old one
    # The next run cleans the dead run's staging folder and publishes the new set.
    assert design_cli(folder, "--no-validate") == 0
    assert not list(folder.glob(".staging-*"))
    check_folder(folder)


def test_a_dead_writers_temporary_file_is_removed_and_a_live_ones_kept(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A run killed while writing into the folder itself (its checkpoint) leaves write_atomic's
    temporary file; the next run's staging removes it, by its writer's pid, and leaves alone a
    file another run is still writing."""
    from aperture_fab.io.atomic import TEMPORARY_NAME, write_atomic
    from aperture_fab.io.manifest import staging

    child = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                           capture_output=True, text=True, check=True)
    dead = tmp_path / f".checkpoint.pt.{int(child.stdout)}-0123456789ab.tmp"
    live = tmp_path / f".checkpoint.pt.{os.getpid()}-0123456789ab.tmp"
    other = tmp_path / ".notes.tmp"  # not write_atomic's: the user's
    for path in (dead, live, other):
        path.write_bytes(b"partial")
        assert TEMPORARY_NAME.fullmatch(path.name) or path is other
    with staging(tmp_path):
        pass
    assert not dead.exists() and live.exists() and other.exists()
    renamed: list[str] = []  # write_atomic's own temporary names are the ones matched
    replace = os.replace
    monkeypatch.setattr(os, "replace", lambda src, dst: (renamed.append(Path(src).name),
                                                         replace(src, dst))[1])
    write_atomic(tmp_path / "x.bin", b"whole")
    assert (tmp_path / "x.bin").read_bytes() == b"whole"
    assert len(renamed) == 1 and TEMPORARY_NAME.fullmatch(renamed[0])
    # A file written again (a checkpoint, a render) removes what a killed writer left of it.
    stale = tmp_path / f".x.bin.{int(child.stdout)}-0123456789ab.tmp"
    stale.write_bytes(b"partial")
    write_atomic(tmp_path / "x.bin", b"again")
    assert not stale.exists() and live.exists()
