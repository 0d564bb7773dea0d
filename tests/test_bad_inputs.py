"""The bad-input catalogue (issues 10 and 21, item 10): each bad input or fault, run through
the command line, gives one clear line (naming the input, the value, what is allowed and the
fix) and its own exit status, or a correct result; never a traceback, a hang or a silently
wrong file.

The first tables (CASES, TARGET_CASES) are rows (id, setup, argv, exit status, fragment);
setup(folder) writes the bad input into a private copy of a tiny design's folder; "{d}" in argv
is that folder. The catalogue below them ("The catalogue") holds the rest as tables of Case
rows judged alike by `judge`: target files, config values generated from the config schema,
config files, flags per command, output places, parts and sub-commands, hostile files, the
environment (disk, permissions, missing packages), Ctrl-C, real signals and concurrent runs.
Slow cases (a design that runs, a subprocess) are marked slow.
"""

from __future__ import annotations

import contextlib
import errno
import io
import json
import math
import os
import re
import shutil
import signal
import struct
import subprocess
import sys
import time
import tomllib
import zipfile
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import pytest
from conftest import TINY_TOML

from aperture_fab.cli import (
    EXIT_BAD_INPUT,
    EXIT_CANNOT_WRITE,
    EXIT_FAILED,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_REPORT_FAIL,
    EXIT_REPORT_WARN,
    EXIT_TERMINATED,
    EXIT_USAGE,
    main,
)
from aperture_fab.config.presets import PHOTOMASK_EMULSION_MM
from aperture_fab.fabrication.mesh import PlateMesh
from aperture_fab.io.formats import stl_bytes
from aperture_fab.io.images import encode_png
from aperture_fab.targets import asymmetric_marker

pytestmark = pytest.mark.usefixtures("one_torch_thread")

ROOT = Path(__file__).resolve().parents[1]
#: Validation settings that keep a tiny validation to a few seconds.
FAST = ["--tolerance-samples", "2", "--mesh-samples", "16"]

Setup = Callable[[Path], None]


def _nothing(folder: Path) -> None:
    pass


def _image(name: str, image: np.ndarray) -> Setup:
    def setup(folder: Path) -> None:
        (folder / name).write_bytes(encode_png(image))
    return setup


def _truncated(name: str, keep: int) -> Setup:
    def setup(folder: Path) -> None:
        data = (folder / name).read_bytes()
        (folder / name).write_bytes(data[:keep])
    return setup


def _checkpoint(folder: Path) -> None:
    (folder / "run").mkdir()
    (folder / "run" / "checkpoint.pt").write_bytes(b"PK\x03\x04 half a checkpoint")


def _cube(folder: Path) -> None:
    # as thick as the config's plate (photomask film's emulsion), so that only its holes differ
    corners = np.array([[x, y, z] for x in (-2, 2) for y in (-2, 2)
                        for z in (0.0, PHOTOMASK_EMULSION_MM)])
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    (folder / "cube.stl").write_bytes(stl_bytes(PlateMesh(vertices=corners, faces=faces)))


def _empty_csv(folder: Path) -> None:
    header = (folder / "holes.csv").read_text().splitlines()[0]
    (folder / "empty.csv").write_text(header + "\n")


def _ascii_stl(folder: Path) -> None:
    (folder / "ascii.stl").write_text(
        "solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\n"
        "endloop\nendfacet\nendsolid x\n")


def _scaled_design(folder: Path) -> None:
    """design.npz with 1.5 added to its open fractions (all above 1), as a bad edit might."""
    with np.load(folder / "design.npz") as data:
        arrays = {k: data[k] for k in data.files}
    arrays["open_fraction"] = arrays["open_fraction"] + 1.5
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    (folder / "scaled.npz").write_bytes(buffer.getvalue())


def _folder(name: str) -> Setup:
    def setup(folder: Path) -> None:
        (folder / name).mkdir()
    return setup


GREY = np.full((3, 32, 32), 0.5)
MARKER = asymmetric_marker(32)

CASES: list[tuple[str, Setup, list[str], int, str]] = [
    # -- output paths --
    ("unknown --out suffix (export)", _nothing,
     ["export", "{d}/design.npz", "--out", "{d}/x/plate.xyz"], EXIT_BAD_INPUT,
     "'.xyz' is not a part file suffix; allowed: .stl"),
    ("unknown --out suffix (design)", _nothing,
     ["design", "{d}/marker.png", "--config", "{d}/tiny.toml", "--out", "{d}/x/plate.xyz"],
     EXIT_BAD_INPUT, "--out {d}/x/plate.xyz: '.xyz' is not a part file suffix"),
    ("render --out an existing folder", _folder("views"),
     ["render", "{d}/design.npz", "--out", "{d}/views"], EXIT_BAD_INPUT,
     "--out {d}/views is a folder; give a PNG file name in it"),
    ("render --out not a PNG", _nothing,
     ["render", "{d}/design.npz", "--out", "{d}/view.jpg"], EXIT_BAD_INPUT,
     "give a name ending in .png"),
    ("truncated design.npz", _truncated("design.npz", 300),
     ["export", "{d}/design.npz", "--out", "{d}/x/"], EXIT_BAD_INPUT,
     "design.npz: not a design.npz written by `aperture-fab design`, or truncated"),
    ("truncated design.npz (render)", _truncated("design.npz", 300),
     ["render", "{d}/design.npz", "--out", "{d}/v.png"], EXIT_BAD_INPUT, "or truncated"),
    ("truncated checkpoint", _checkpoint,
     ["design", "{d}/marker.png", "--config", "{d}/tiny.toml", "--out", "{d}/run",
      "--resume"], EXIT_BAD_INPUT, "checkpoint.pt cannot be read"),
    # -- silent wrong results --
    ("all-black target", _image("black.png", np.zeros((3, 32, 32))),
     ["render", "{d}/design.npz", "{d}/black.png", "--out", "{d}/v.png"], EXIT_BAD_INPUT,
     "black.png' is black everywhere (no light)"),
    ("all-black target (design)", _image("black.png", np.zeros((3, 32, 32))),
     ["design", "{d}/black.png", "--config", "{d}/tiny.toml", "--out", "{d}/run"],
     EXIT_BAD_INPUT, "'black' is black everywhere"),
    ("1 x 1 target", _image("dot.png", np.full((3, 1, 1), 0.5)),
     ["render", "{d}/design.npz", "{d}/dot.png", "--out", "{d}/v.png"], EXIT_BAD_INPUT,
     "is 1 x 1 pixels; allowed: at least 8 pixels per side"),
    ("cube STL", _cube, ["validate", "{d}/cube.stl", "{d}/marker.png", *FAST], EXIT_BAD_INPUT,
     "no holes found in {d}/cube.stl: this is not a plate of the config's grid"),
    ("empty holes.csv", _empty_csv, ["validate", "{d}/empty.csv", "{d}/marker.png", *FAST],
     EXIT_BAD_INPUT, "no holes found in {d}/empty.csv"),
    ("open fractions above 1", _scaled_design,
     ["export", "{d}/scaled.npz", "--out", "{d}/x/"], EXIT_BAD_INPUT,
     "open_fraction holds values from 1.5"),
    ("eye far away", _nothing,
     ["render", "{d}/design.npz", "--eye", "50,50", "--out", "{d}/v.png"], EXIT_BAD_INPUT,
     "--eye 50,50: the eye sees no light from the display at that position"),
    ("ASCII STL is read, and judged as a part", _ascii_stl,
     ["validate", "{d}/ascii.stl", "{d}/marker.png", *FAST], EXIT_BAD_INPUT,
     "{d}/ascii.stl is not a plate of the config's grid"),
    # -- usage --
    ("unknown flag", _nothing, ["render", "{d}/design.npz", "--bogus"], EXIT_USAGE,
     "unrecognized arguments: --bogus"),
    ("-q with -v", _nothing, ["render", "{d}/design.npz", "-q", "-v"], EXIT_USAGE,
     "not allowed with argument"),
]


@pytest.fixture
def folder(designed: Path, tmp_path: Path) -> Path:
    """A private copy of the tiny design's folder (with tiny.toml and marker.png)."""
    copy = tmp_path / "d"
    shutil.copytree(designed, copy)
    return copy


def run(argv: list[str], folder: Path) -> int:
    """main(argv) with {d} filled in; argparse's SystemExit becomes its status."""
    try:
        return main([a.format(d=folder) for a in argv])
    except SystemExit as stop:
        return int(stop.code or 0)


@pytest.mark.parametrize(("setup", "argv", "status", "fragment"),
                         [case[1:] for case in CASES], ids=[case[0] for case in CASES])
def test_bad_input_gives_one_clear_line_and_its_status(
        folder: Path, capsys: pytest.CaptureFixture[str], setup: Setup, argv: list[str],
        status: int, fragment: str) -> None:
    setup(folder)
    code = run(argv, folder)
    err = capsys.readouterr().err
    assert code == status, err
    assert fragment.format(d=folder) in err, err
    assert "Traceback" not in err
    errors = [line for line in err.splitlines() if line.startswith("aperture-fab: error:")]
    assert len(errors) <= 1 and (status == EXIT_USAGE or len(errors) == 1), err


# -- output names ----------------------------------------------------------------------------


def test_export_holes_csv_writes_the_hole_table(folder: Path) -> None:
    out = folder / "x" / "holes.csv"
    assert run(["export", "{d}/design.npz", "--out", str(out), "-q"], folder) == EXIT_OK
    assert out.is_file() and out.read_text().startswith((folder / "holes.csv").read_text()[:10])


def test_export_keeps_the_name_given_and_the_design_s_file(folder: Path) -> None:
    before = (folder / "plate.stl").read_bytes()
    out = folder / "Plate.STL"
    assert run(["export", "{d}/design.npz", "--out", str(out), "-q"], folder) == EXIT_OK
    assert out.name in os.listdir(folder) and out.stat().st_size > 0
    if (folder / "plate.stl").resolve() != out.resolve():  # a case-sensitive file system
        assert (folder / "plate.stl").read_bytes() == before


# -- faults ----------------------------------------------------------------------------------


def test_a_full_disk_names_the_output_and_the_fix(
        folder: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    def full(fd: int) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full)
    out = folder / "x" / "plate.stl"
    assert run(["export", "{d}/design.npz", "--out", str(out)], folder) == EXIT_CANNOT_WRITE
    err = capsys.readouterr().err
    assert f"--out {out}" in err and "disk is full" in err and "Traceback" not in err
    assert not out.exists()


def test_an_unwritable_output_names_the_file(
        folder: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    real_open = os.open

    def denied(path: str, *args: object, **kwargs: object) -> int:
        if str(path).endswith(".tmp"):
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))
        return real_open(path, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(os, "open", denied)
    out = folder / "x" / "plate.stl"
    assert run(["export", "{d}/design.npz", "--out", str(out)], folder) == EXIT_CANNOT_WRITE
    err = capsys.readouterr().err
    assert f"cannot write or read {out}:" in err and "no permission" in err


def test_ctrl_c_in_export_exits_130(folder: Path, monkeypatch: pytest.MonkeyPatch,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    import aperture_fab.pipeline.export_job as export_job

    def interrupted(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(export_job, "write_part", interrupted)
    assert run(["export", "{d}/design.npz", "--out", "{d}/x"], folder) == EXIT_INTERRUPTED
    err = capsys.readouterr().err
    assert "interrupted (Ctrl-C) during `export`" in err and "Traceback" not in err


def test_out_of_memory_is_a_refusal_not_a_traceback(folder: Path, monkeypatch: pytest.MonkeyPatch,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    import aperture_fab.pipeline.export_job as export_job

    def too_large(*args: object, **kwargs: object) -> None:
        raise MemoryError

    monkeypatch.setattr(export_job, "write_part", too_large)
    assert run(["export", "{d}/design.npz", "--out", "{d}/x"], folder) == EXIT_FAILED
    err = capsys.readouterr().err
    assert "`export` ran out of memory" in err and "Traceback" not in err


@pytest.mark.parametrize(("signum", "how", "code"), [
    (signal.SIGTERM, "SIGTERM", EXIT_TERMINATED),
    (signal.SIGINT, "Ctrl-C", EXIT_INTERRUPTED),
], ids=["SIGTERM", "SIGINT"])
@pytest.mark.parametrize("then", ["fails", "finishes"])
def test_a_signal_dropped_inside_a_library_still_stops_the_command(
        folder: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
        then: str, signum: signal.Signals, how: str, code: int) -> None:
    """A SIGTERM or Ctrl-C whose exception lands in a ctypes callback (Numba's compiler: CI saw
    it) is printed and dropped there; the command then fails for another reason or finishes,
    and exits as stopped by that signal all the same, the handlers restored."""
    import aperture_fab.pipeline.export_job as export_job

    write_part = export_job.write_part

    def signalled(*args: object, **kwargs: object) -> object:
        with contextlib.suppress(KeyboardInterrupt):  # as the callback's caller drops it
            signal.raise_signal(signum)
        if then == "fails":
            raise ValueError("the compiler's state after the dropped exception")
        return write_part(*args, **kwargs)

    monkeypatch.setattr(export_job, "write_part", signalled)
    # What the handlers were (SIGINT is ignored, not Python's handler, in a background job).
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    assert run(["export", "{d}/design.npz", "--out", "{d}/x"], folder) == code
    err = capsys.readouterr().err
    assert f"({how}) during `export`" in err and "Traceback" not in err
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before


@pytest.mark.slow
@pytest.mark.parametrize(("signum", "how", "codes"), [
    # 130, or killed by SIGINT (-2), which a shell reports as 130 too: CPython re-sends SIGINT
    # to itself at exit when the Ctrl-C landed inside exec'd code (e.g. a module import).
    (signal.SIGINT, "Ctrl-C", (EXIT_INTERRUPTED, -signal.SIGINT)),
    (signal.SIGTERM, "SIGTERM", (EXIT_TERMINATED,)),
], ids=["SIGINT", "SIGTERM"])
def test_a_signal_during_validation_stops_it_cleanly(folder: Path, signum: signal.Signals,
                                                     how: str, codes: tuple[int, ...]) -> None:
    """A real signal to a running `validate`, sent once it says validation has started."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    child = subprocess.Popen(
        [sys.executable, "-m", "aperture_fab.cli", "validate", str(folder / "holes.csv"),
         str(folder / "marker.png"), "--out", str(folder / "check"), *FAST],
        stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env, cwd=ROOT)
    assert child.stderr is not None
    lines = []
    for line in child.stderr:
        lines.append(line)
        if "validate:" in line:  # a stage line: stderr is not a terminal
            break
    time.sleep(0.5)
    child.send_signal(signum)
    _, rest = child.communicate(timeout=120)
    err = "".join(lines) + rest
    assert child.returncode in codes, err
    assert f"interrupted ({how}) during `validate`" in err and "Traceback" not in err


# -- honest reports --------------------------------------------------------------------------


def test_force_reports_how_many_holes_break_which_rules(
        folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert run(["export", "{d}/design.npz", "--process", "fdm", "--force", "--out",
                "{d}/fdm/"], folder) == EXIT_OK
    err = capsys.readouterr().err
    assert "--force:" in err and "holes break process fdm's rules" in err
    assert "written anyway" in err


def test_a_stretched_target_is_warned_about(folder: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    (folder / "wide.png").write_bytes(encode_png(np.full((3, 32, 64), 0.5)))
    assert run(["render", "{d}/design.npz", "{d}/wide.png", "--out", "{d}/v.png"],
               folder) == EXIT_OK
    err = capsys.readouterr().err
    assert "warning: target image" in err and "wide.png" in err and "stretched" in err
    # -q keeps only errors and the result line.
    assert run(["render", "{d}/design.npz", "{d}/wide.png", "--out", "{d}/v.png", "-q"],
               folder) == EXIT_OK
    assert capsys.readouterr().err == ""


def test_ascii_stl_reads_like_binary() -> None:
    from aperture_fab.io.formats import read_stl

    corners = np.array([[x, y, z] for x in (-2, 2) for y in (-2, 2) for z in (0.0, 0.3)])
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5]])
    mesh = PlateMesh(vertices=corners, faces=faces)
    facets = "".join("facet normal 0 0 0\nouter loop\n" + "".join(
        f"vertex {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in corners[f]) + "endloop\nendfacet\n"
        for f in faces)
    text = read_stl(f"solid plate\n{facets}endsolid plate\n".encode())
    binary = read_stl(stl_bytes(mesh))
    np.testing.assert_array_equal(text.vertices, binary.vertices)
    np.testing.assert_array_equal(text.faces, binary.faces)


# -- conventions -----------------------------------------------------------------------------


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    from aperture_fab import __version__

    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0 and capsys.readouterr().out.strip() == f"aperture-fab {__version__}"


def test_help_documents_the_exit_codes(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    assert "exit status:" in out and "130" in out and "-q/--quiet" in out


@pytest.mark.parametrize("command", ["design", "export", "validate", "render", "display",
                                     "presets", "processes"])
def test_every_command_takes_quiet_and_verbose(command: str,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main([command, "--help"])
    out = capsys.readouterr().out
    assert "-q, --quiet" in out and "-v, --verbose" in out


def test_verbose_shows_the_traceback(folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["render", "{d}/design.npz", "--eye", "50,50", "--out", "{d}/v.png"]
    assert run([*argv, "-v"], folder) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "Traceback" in err and err.rstrip().splitlines()[-1].startswith("aperture-fab: error:")


def test_no_progress_bar_escapes_in_a_log(folder: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    """stderr is not a terminal under pytest: stage lines, no carriage returns."""
    assert run(["export", "{d}/design.npz", "--out", "{d}/x"], folder) == EXIT_OK
    err = capsys.readouterr().err
    assert "\r" not in err and "\x1b" not in err
    assert "aperture-fab: writing" in err


def test_a_zip_that_is_no_design_is_refused(folder: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    with zipfile.ZipFile(folder / "other.npz", "w") as z:
        z.writestr("readme.txt", "hello")
    assert run(["export", "{d}/other.npz", "--config", "{d}/design.toml", "--out", "{d}/x"],
               folder) == EXIT_BAD_INPUT
    assert "not a design.npz" in capsys.readouterr().err


# -- target images (issue 21, item 6): --alpha, --fit, --frame reach every command -------------


def _transparent(folder: Path) -> None:
    """alpha.png: grey (sRGB 200), transparent in its left half."""
    pixels = np.full((32, 32, 4), 200, dtype=np.uint8)
    pixels[:, :, 3] = 255
    pixels[:, :16, 3] = 0
    from PIL import Image

    Image.fromarray(pixels, "RGBA").save(folder / "alpha.png")


def _animated(folder: Path) -> None:
    from PIL import Image

    frames = [Image.new("L", (32, 32), level) for level in (60, 120, 180)]
    frames[0].save(folder / "anim.gif", save_all=True, append_images=frames[1:], duration=100)


REFUSE = "alpha.png: the image is transparent or partly transparent in 50.0% of its pixels"
TARGET_CASES: list[tuple[str, Setup, list[str], int, str]] = [
    ("--alpha refuse (design)", _transparent,
     ["design", "{d}/alpha.png", "--config", "{d}/tiny.toml", "--out", "{d}/run", "--alpha",
      "refuse"], EXIT_BAD_INPUT, REFUSE),
    ("--alpha refuse (validate)", _transparent,
     ["validate", "{d}/holes.csv", "{d}/alpha.png", "--alpha", "refuse", *FAST],
     EXIT_BAD_INPUT, REFUSE),
    ("--alpha refuse (render)", _transparent,
     ["render", "{d}/design.npz", "{d}/alpha.png", "--alpha", "refuse", "--out", "{d}/v.png"],
     EXIT_BAD_INPUT, REFUSE),
    ("--alpha refuse (display)", _transparent,
     ["display", "{d}/design.npz", "{d}/alpha.png", "--eye", "0,0", "--pupil", "4", "--alpha",
      "refuse", "--out", "{d}/f.png"], EXIT_BAD_INPUT, REFUSE),
    ("--frame out of range", _animated,
     ["render", "{d}/design.npz", "{d}/anim.gif", "--frame", "3", "--out", "{d}/v.png"],
     EXIT_BAD_INPUT, "anim.gif: --frame 3 is out of range; the file has 3 frame(s)"),
    ("--frame negative", _animated,
     ["render", "{d}/design.npz", "{d}/anim.gif", "--frame", "-1", "--out", "{d}/v.png"],
     EXIT_BAD_INPUT, "--frame -1 is not allowed; give a whole number from 0"),
    ("--fit unknown", _nothing,
     ["render", "{d}/design.npz", "{d}/marker.png", "--fit", "zoom", "--out", "{d}/v.png"],
     EXIT_USAGE, "argument --fit: invalid choice: 'zoom'"),
    ("a folder as the target", _folder("targets"),
     ["render", "{d}/design.npz", "{d}/targets", "--out", "{d}/v.png"], EXIT_BAD_INPUT,
     "target image {d}/targets is a folder; give an image file"),
]


@pytest.mark.parametrize(("setup", "argv", "status", "fragment"),
                         [case[1:] for case in TARGET_CASES],
                         ids=[case[0] for case in TARGET_CASES])
def test_a_bad_target_gives_one_clear_line_and_its_status(
        folder: Path, capsys: pytest.CaptureFixture[str], setup: Setup, argv: list[str],
        status: int, fragment: str) -> None:
    test_bad_input_gives_one_clear_line_and_its_status(folder, capsys, setup, argv, status,
                                                       fragment)


def test_target_warnings_name_the_file_and_the_flag(folder: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """The default alpha, frame and fit are said on the command line; choosing them is not."""
    _transparent(folder)
    _animated(folder)
    (folder / "wide.png").write_bytes(encode_png(np.full((3, 32, 64), 0.5)))
    for target in ("alpha.png", "anim.gif", "wide.png"):
        assert run(["render", "{d}/design.npz", f"{{d}}/{target}", "--out", "{d}/v.png"],
                   folder) == EXIT_OK
    err = capsys.readouterr().err
    assert f"warning: target image {folder}/alpha.png is transparent in 50.0%" in err
    assert "composited on black" in err and "--alpha white" in err
    assert f"warning: target image {folder}/anim.gif is an animation" in err
    assert "of 3 frames; the first (--frame 0) is used" in err
    assert f"warning: target image '{folder}/wide.png' is 64 x 32 pixels" in err
    assert "--fit pad" in err
    for target, flags in (("alpha.png", ["--alpha", "white"]), ("anim.gif", ["--frame", "1"]),
                          ("wide.png", ["--fit", "pad"]), ("wide.png", ["--fit", "crop"])):
        assert run(["render", "{d}/design.npz", f"{{d}}/{target}", *flags, "--out",
                    "{d}/v.png"], folder) == EXIT_OK
        assert "warning: target image" not in capsys.readouterr().err, flags


# =============================================================================================
# The catalogue (issue 21, item 10): every kind of bad input, as tables of cases judged alike
# =============================================================================================
#
# A Case is (id, argv, outcome, setup): setup(folder) puts the bad input into a private copy of
# a tiny design's folder ("{d}" in argv), `aperture-fab argv` runs in-process under a deadline,
# and `judge` holds the run to its outcome:
#   Refused(status, fragments): a clear error: that documented exit status, one error line on
#     stderr holding every fragment (the input and the value it names) and a fix, and no
#     traceback, no raw library warning, no temporary file left behind;
#   Works(check): a correct result: a documented success status, no error line, check(folder).
# A case that raises (a traceback), runs past CASE_DEADLINE_S (a hang) or writes a wrong file
# fails. The catalogue's other pages: the tables above (CASES, TARGET_CASES),
# tests/test_target_inputs.py (--alpha, --fit, --frame, float images, FIFOs, devices, sockets),
# tests/test_safe_by_construction.py (hostile checkpoints, manifests naming files outside their
# folder, concurrent publishes) and tests/test_output_folder.py (SIGKILL while exporting).

#: Seconds a case may run before it counts as hung (a tiny design takes a few).
CASE_DEADLINE_S = 120
#: Every status `aperture-fab --help` documents.
DOCUMENTED_STATUSES = (EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_BAD_INPUT, EXIT_CANNOT_WRITE,
                       EXIT_REPORT_FAIL, EXIT_REPORT_WARN, EXIT_INTERRUPTED)
#: The statuses of a result: design and validate exit with their report's verdict.
RESULT_STATUSES = (EXIT_OK, EXIT_REPORT_FAIL, EXIT_REPORT_WARN)
#: An error line: the tool's own ("aperture-fab: error:") or argparse's ("aperture-fab
#: render: error:").
ERROR_LINE = re.compile(r"^aperture-fab(?: [a-z]+)?: error: .*$", re.MULTILINE)
#: A Python warning printed raw (a library's, not the tool's one-line "warning:").
RAW_WARNING = re.compile(r"\b[A-Z]\w*Warning: ")
#: Words of a fix: what to give, choose or change, or an example of a good value (argparse's
#: usage errors show the usage instead).
FIX = re.compile(r"\b(give|choose|allowed|use|expected|fix|check|re-export|downscale|rename|"
                 r"install|again|drop|lower|move|widen|save|free|create|make|convert|keep|"
                 r"leave|remove|re-run|delete|did you mean|must be|e\.g\.)", re.IGNORECASE)
#: The tiny design: its view and display grids (x, y).
VIEW_PIXELS = (16, 16)
DISPLAY_PIXELS = (32, 32)


@dataclass(frozen=True)
class Refused:
    """A clear error with this status whose message holds every fragment ("{d}": the folder)."""

    status: int
    fragments: tuple[str, ...] = ()


@dataclass(frozen=True)
class Works:
    """A correct result: a status of `statuses`, no error, and check(folder) passes."""

    check: Callable[[Path], None] | None = None
    statuses: tuple[int, ...] = (EXIT_OK,)


Outcome = Refused | Works


def bad(*fragments: str) -> Refused:
    return Refused(EXIT_BAD_INPUT, fragments)


def usage(*fragments: str) -> Refused:
    return Refused(EXIT_USAGE, fragments)


def failed(*fragments: str) -> Refused:
    return Refused(EXIT_FAILED, fragments)


def unwritable(*fragments: str) -> Refused:
    return Refused(EXIT_CANNOT_WRITE, fragments)


class Case(NamedTuple):
    id: str
    argv: list[str]
    outcome: Outcome
    setup: Callable[..., None] = _nothing
    slow: bool = False


def params(cases: list[Case]) -> list[Any]:
    """The cases as pytest parameters (setup, argv, outcome), slow ones marked."""
    assert len({c.id for c in cases}) == len(cases), "case ids must be unique"
    return [pytest.param(c.setup, c.argv, c.outcome, id=c.id,
                         marks=[pytest.mark.slow] if c.slow else [])
            for c in cases]


class Hung(BaseException):
    """A case ran past its deadline (a BaseException: the command line must not catch it)."""


@contextlib.contextmanager
def deadline(seconds: float) -> Iterator[None]:
    """Raise Hung in the main thread once `seconds` have passed."""
    def stop(signum: int, frame: object) -> None:
        raise Hung(f"no result after {seconds} s")

    previous = signal.signal(signal.SIGALRM, stop)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def leftovers(folder: Path) -> list[Path]:
    """Temporary files (write_atomic's .NAME.<pid>-<hex>.tmp) left anywhere under folder."""
    return [p for p in folder.rglob("*.tmp") if p.is_file()]


def judge(argv: list[str], folder: Path, capsys: pytest.CaptureFixture[str],
          outcome: Outcome) -> str:
    """Run `aperture-fab argv` ({d}: folder) and hold it to `outcome`; its stderr."""
    capsys.readouterr()
    with deadline(CASE_DEADLINE_S):
        code = run(argv, folder)
    err = capsys.readouterr().err
    assert code in DOCUMENTED_STATUSES, f"exit status {code}: {err}"
    assert "Traceback" not in err, err
    assert not RAW_WARNING.search(err), f"a raw library warning: {err}"
    assert not leftovers(folder), f"temporary files left: {leftovers(folder)}"
    errors = ERROR_LINE.findall(err)
    if isinstance(outcome, Refused):
        assert code == outcome.status, f"exit status {code}, not {outcome.status}: {err}"
        assert len(errors) == 1, err
        for fragment in outcome.fragments:
            assert fragment.format(d=folder) in errors[0], f"{fragment!r} not in: {errors[0]}"
        if code != EXIT_USAGE:  # argparse's own errors show the usage instead
            assert FIX.search(errors[0].split("error:", 1)[1]), f"no fix in: {errors[0]}"
    else:
        assert code in outcome.statuses, f"exit status {code}: {err}"
        assert not errors, err
        if outcome.check is not None:
            outcome.check(folder)
    return err


# -- checks of a correct result ------------------------------------------------------------


def png_of(name: str, size: tuple[int, int]) -> Callable[[Path], None]:
    """The PNG `name` in the folder is whole and `size` (width, height) pixels."""
    def check(folder: Path) -> None:
        from PIL import Image

        with Image.open(folder / name) as image:
            image.load()
            assert image.format == "PNG" and image.size == size, (image.format, image.size)
    return check


def published(name: str) -> Callable[[Path], None]:
    """The folder `name` holds a whole design set: its manifest verifies."""
    def check(folder: Path) -> None:
        from aperture_fab.io.manifest import check_folder

        assert (folder / name / "manifest.json").is_file()
        check_folder(folder / name)
    return check


def files(*names: str) -> Callable[[Path], None]:
    """Each file is there and not empty."""
    def check(folder: Path) -> None:
        for name in names:
            assert (folder / name).stat().st_size > 0, name
    return check


VIEW_PNG = Works(png_of("v.png", VIEW_PIXELS))
FRAME_PNG = Works(png_of("f.png", DISPLAY_PIXELS))


# -- setups ----------------------------------------------------------------------------------


def _write(name: str, data: bytes | str) -> Setup:
    def setup(folder: Path) -> None:
        path = folder / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data if isinstance(data, bytes) else data.encode())
    return setup


def _pil(image: Any, fmt: str, **options: Any) -> bytes:
    buffer = io.BytesIO()
    image.save(buffer, fmt, **options)
    return buffer.getvalue()


def _image_file(name: str, make: Callable[[], Any], fmt: str, keep: int | None = None,
                **options: Any) -> Setup:
    """Save make() (a PIL image) as fmt under `name`, its first `keep` bytes only if given."""
    def setup(folder: Path) -> None:
        (folder / name).write_bytes(_pil(make(), fmt, **options)[:keep])
    return setup


def _png_chunk(kind: bytes, payload: bytes) -> bytes:
    return (struct.pack(">I", len(payload)) + kind + payload
            + struct.pack(">I", zlib.crc32(kind + payload)))


def _png_declaring(width: int, height: int) -> bytes:
    """A PNG whose header declares width x height 8-bit RGB, with one short row of data."""
    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", header)
            + _png_chunk(b"IDAT", zlib.compress(b"\x00" * 100)) + _png_chunk(b"IEND", b""))


def _png_bomb(side: int) -> bytes:
    """A real decompression bomb: a 1-bit side x side PNG of zeros (kilobytes on disk)."""
    header = struct.pack(">IIBBBBB", side, side, 1, 0, 0, 0, 0)
    row = b"\x00" * (side // 8 + 2)
    packer = zlib.compressobj(9)
    data = b"".join(packer.compress(row) for _ in range(side)) + packer.flush()
    return (b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", header) + _png_chunk(b"IDAT", data)
            + _png_chunk(b"IEND", b""))


def _grey(size: tuple[int, int] = (32, 32), level: int = 128) -> Any:
    from PIL import Image

    return Image.new("L", size, level)


def _colour() -> Any:
    from PIL import Image

    return Image.new("RGB", (32, 32), (200, 40, 40))


def _corrupt_png(folder: Path) -> None:
    """marker.png with its image data scrambled (the zlib stream breaks)."""
    data = bytearray((folder / "marker.png").read_bytes())
    start = data.index(b"IDAT") + 8
    data[start:start + 40] = bytes(range(40))
    (folder / "bad.png").write_bytes(bytes(data))


def _link(name: str, to: str) -> Setup:
    def setup(folder: Path) -> None:
        (folder / name).symlink_to(folder / to)
    return setup


def _loop(folder: Path) -> None:
    (folder / "a.png").symlink_to(folder / "b.png")
    (folder / "b.png").symlink_to(folder / "a.png")


def _copy(source: str, name: str) -> Setup:
    def setup(folder: Path) -> None:
        (folder / name).write_bytes((folder / source).read_bytes())
    return setup


NON_UTF8 = os.fsdecode(b"\xffsign.png")


def render_of(target: str, *flags: str) -> list[str]:
    return ["render", "{d}/design.npz", target, "--out", "{d}/v.png", *flags]


# -- targets ---------------------------------------------------------------------------------

TARGET_FILES: list[Case] = [
    # truncated and corrupt
    Case("truncated PNG", render_of("{d}/t.png"), bad("{d}/t.png", "truncated or corrupt"),
         _image_file("t.png", _grey, "PNG", keep=60)),
    Case("PNG signature only", render_of("{d}/t.png"),
         bad("{d}/t.png: looks like a PNG file but cannot be read"),
         _write("t.png", b"\x89PNG\r\n\x1a\n")),
    Case("scrambled PNG data", render_of("{d}/bad.png"), bad("{d}/bad.png", "corrupt"),
         _corrupt_png),
    Case("truncated JPEG", render_of("{d}/t.jpg"),
         bad("{d}/t.jpg: looks like a JPEG file but cannot be read"),
         _image_file("t.jpg", _colour, "JPEG", keep=200)),
    Case("truncated TIFF (and no raw Pillow warning)", render_of("{d}/t.tif"),
         bad("{d}/t.tif: looks like a TIFF file but cannot be read"),
         _image_file("t.tif", _colour, "TIFF", keep=100)),
    Case("truncated GIF", render_of("{d}/t.gif"), bad("{d}/t.gif"),
         _image_file("t.gif", _grey, "GIF", keep=30)),
    Case("zero bytes", render_of("{d}/t.png"), bad("{d}/t.png: the file is empty (0 bytes)"),
         _write("t.png", b"")),
    Case("text named .png", render_of("{d}/t.png"),
         bad("{d}/t.png: is not an image file that can be read"),
         _write("t.png", "hello, not a picture")),
    Case("SVG", render_of("{d}/t.svg"), bad("{d}/t.svg: is not an image file that can be read"),
         _write("t.svg", "<svg xmlns='http://www.w3.org/2000/svg' width='32' height='32'/>")),
    Case("PDF", render_of("{d}/t.pdf"), bad("{d}/t.pdf: is not an image file that can be read"),
         _write("t.pdf", "%PDF-1.4\n%%EOF\n")),
    Case("numpy array named .png", render_of("{d}/t.png"), bad("{d}/t.png", "not an image"),
         _write("t.png", b"\x93NUMPY\x01\x00v\x00")),
    # sizes
    Case("header claims 100000 x 100000 (decompression bomb)", render_of("{d}/t.png"),
         bad("{d}/t.png: the image is too large", "megapixels"),
         _write("t.png", _png_declaring(100_000, 100_000))),
    Case("header claims 9000 x 9000", render_of("{d}/t.png"),
         bad("{d}/t.png: the image is 9000 x 9000 pixels", "limit of 64 megapixels"),
         _write("t.png", _png_declaring(9000, 9000))),
    Case("12000 x 12000 of compressed zeros (decompression bomb)", render_of("{d}/t.png"),
         bad("{d}/t.png", "megapixels"), _write("t.png", _png_bomb(12_000))),
    Case("header claims 0 x 32", render_of("{d}/t.png"),
         bad("{d}/t.png: the image has zero size (0 x 32 pixels)"),
         _write("t.png", _png_declaring(0, 32))),
    Case("7 x 7", render_of("{d}/t.png"),
         bad("{d}/t.png' is 7 x 7 pixels; allowed: at least 8 pixels per side"),
         _image_file("t.png", lambda: _grey((7, 7)), "PNG")),
    Case("2000 x 1", render_of("{d}/t.png"), bad("is 2000 x 1 pixels; allowed: at least 8"),
         _image_file("t.png", lambda: _grey((2000, 1)), "PNG")),
    # colour for a grey design: the message names the file
    Case("colour JPEG for a grey design", render_of("{d}/c.jpg"),
         bad("target image '{d}/c.jpg' has colour", "greyscale"),
         _image_file("c.jpg", _colour, "JPEG")),
    Case("CMYK TIFF for a grey design", render_of("{d}/c.tif"),
         bad("target image '{d}/c.tif' has colour"),
         _image_file("c.tif", lambda: _colour().convert("CMYK"), "TIFF")),
    Case("CMYK JPEG for a grey design", render_of("{d}/c.jpg"),
         bad("target image '{d}/c.jpg' has colour"),
         _image_file("c.jpg", lambda: _colour().convert("CMYK"), "JPEG")),
    Case("colour palette PNG for a grey design", render_of("{d}/c.png"),
         bad("target image '{d}/c.png' has colour"),
         _image_file("c.png", lambda: _colour().convert("P"), "PNG")),
    Case("colour WebP for a grey design", render_of("{d}/c.webp"),
         bad("target image '{d}/c.webp' has colour"),
         _image_file("c.webp", _colour, "WEBP", lossless=True)),
    Case("black 16-bit PNG", render_of("{d}/k.png"), bad("k.png' is black everywhere"),
         _write("k.png", encode_png(np.zeros((1, 32, 32)), bits=16))),
    # paths
    Case("missing file", render_of("{d}/none.png"),
         bad("target image {d}/none.png does not exist; check the path")),
    Case("dangling symlink", render_of("{d}/l.png"),
         bad("target image {d}/l.png does not exist"), _link("l.png", "gone.png")),
    Case("symlink loop", render_of("{d}/a.png"),
         bad("cannot read target image {d}/a.png", "symbolic links"), _loop),
    Case("--frame 2 of a still PNG", render_of("{d}/marker.png", "--frame", "2"),
         bad("marker.png: --frame 2 is out of range; the file has 1 frame(s)")),
    # read correctly
    Case("16-bit grey PNG", render_of("{d}/g16.png"), VIEW_PNG,
         _write("g16.png", encode_png(np.full((1, 32, 32), 0.4), bits=16))),
    Case("32-bit integer TIFF", render_of("{d}/i.tif"), VIEW_PNG,
         _image_file("i.tif", lambda: _grey().convert("I"), "TIFF")),
    Case("float TIFF in 0..1", render_of("{d}/f.tif"), VIEW_PNG,
         _image_file("f.tif", lambda: _grey().convert("F").point(lambda v: v / 255), "TIFF")),
    Case("1-bit PNG", render_of("{d}/b.png"), VIEW_PNG,
         _image_file("b.png", lambda: _grey().convert("1"), "PNG")),
    Case("grey with opaque alpha (LA)", render_of("{d}/la.png"), VIEW_PNG,
         _image_file("la.png", lambda: _grey().convert("LA"), "PNG")),
    Case("grey palette PNG", render_of("{d}/p.png"), VIEW_PNG,
         _image_file("p.png", lambda: _grey().convert("P"), "PNG")),
    Case("grey JPEG", render_of("{d}/g.jpg"), VIEW_PNG, _image_file("g.jpg", _grey, "JPEG")),
    Case("grey BMP", render_of("{d}/g.bmp"), VIEW_PNG, _image_file("g.bmp", _grey, "BMP")),
    Case("grey lossless WebP", render_of("{d}/g.webp"), VIEW_PNG,
         _image_file("g.webp", _grey, "WEBP", lossless=True)),
    Case("grey RGB (R = G = B) PNG", render_of("{d}/rgb.png"), VIEW_PNG,
         _image_file("rgb.png", lambda: _grey().convert("RGB"), "PNG")),
    Case("JPEG named .png (wrong extension)", render_of("{d}/j.png"), VIEW_PNG,
         _image_file("j.png", _grey, "JPEG")),
    Case("PNG named .jpg (wrong extension)", render_of("{d}/p.jpg"), VIEW_PNG,
         _copy("marker.png", "p.jpg")),
    Case("no extension", render_of("{d}/target"), VIEW_PNG, _copy("marker.png", "target")),
    Case("upper-case extension", render_of("{d}/T.PNG"), VIEW_PNG, _copy("marker.png", "T.PNG")),
    Case("animated GIF (first frame, warned)", render_of("{d}/anim.gif"), VIEW_PNG,
         _image_file("anim.gif", _grey, "GIF", save_all=True,
                     append_images=[_grey(level=200)])),
    Case("symlink to an image", render_of("{d}/l.png"), VIEW_PNG, _link("l.png", "marker.png")),
    Case("spaces and accents in the name", render_of("{d}/my café target.png"), VIEW_PNG,
         _copy("marker.png", "my café target.png")),
    Case("non-UTF-8 bytes in the name", render_of("{d}/" + NON_UTF8), VIEW_PNG,
         _copy("marker.png", NON_UTF8)),
    # every command reads targets alike, before any work
    Case("truncated PNG (design)",
         ["design", "{d}/t.png", "--config", "{d}/tiny.toml", "--out", "{d}/run",
          "--no-validate"], bad("{d}/t.png", "truncated or corrupt"),
         _image_file("t.png", _grey, "PNG", keep=60)),
    Case("truncated PNG (validate)", ["validate", "{d}/holes.csv", "{d}/t.png", *FAST],
         bad("{d}/t.png", "truncated or corrupt"), _image_file("t.png", _grey, "PNG", keep=60)),
    Case("truncated PNG (display)",
         ["display", "{d}/design.npz", "{d}/t.png", "--eye", "0,0", "--pupil", "4", "--out",
          "{d}/f.png"], bad("{d}/t.png", "truncated or corrupt"),
         _image_file("t.png", _grey, "PNG", keep=60)),
    Case("colour target (display)",
         ["display", "{d}/design.npz", "{d}/c.png", "--eye", "0,0", "--pupil", "4", "--out",
          "{d}/f.png"], bad("'{d}/c.png' has colour"), _image_file("c.png", _colour, "PNG")),
    Case("a second target missing (design)",
         ["design", "{d}/marker.png", "{d}/none.png", "--config", "{d}/tiny.toml", "--out",
          "{d}/run", "--no-validate"], bad("target image {d}/none.png does not exist")),
]


@pytest.mark.parametrize(("setup", "argv", "outcome"), params(TARGET_FILES))
def test_target_file(folder: Path, capsys: pytest.CaptureFixture[str], setup: Setup,
                     argv: list[str], outcome: Outcome) -> None:
    setup(folder)
    judge(argv, folder, capsys, outcome)


# -- config values, generated from the schema ----------------------------------------------
# For every key of config.SECTION_KEYS, by its kind (config.py's conversion sets), a negative,
# zero, NaN, the infinities, text, a huge value, a boolean and a list; each is written into the
# tiny config and given to `design`, which must refuse it naming the key and the value, before
# any work. Values a key allows are listed in IN_RANGE and checked to be taken as given.

NAN, INF = math.nan, math.inf
BAD_NUMBERS: list[Any] = [-1.0, 0.0, NAN, INF, -INF, "text", 1e300, True, [1.0, 2.0]]
BAD_WHOLES: list[Any] = [-1, 0, 1.5, NAN, "text", 2**62, True]
BAD_WHOLE_PAIRS: list[Any] = [[0, 0], [-1, 16], [1.5, 16], [16], [16, 16, 16], "16",
                              [100_000, 100_000], NAN]
BAD_TEXTS: list[Any] = ["bogus", "", 1, ["adam"]]
#: The keys of their own kind (config._convert's special cases).
BAD_OTHERS: dict[str, list[Any]] = {
    "plate.pitch_mm": [-1.0, 0.0, NAN, INF, [0.25], [0.25, -1.0], "x", 1e300],
    "eye.eyebox_mm": [-1.0, NAN, INF, [2.0], "x", 1e300, [1.0, -1.0]],
    "eye.pupil_range_mm": ["x", 3.0, [6.0, 3.0], [-1.0, 2.0], [NAN, 1.0], [1.0, INF],
                           [0.0, 100.0]],
    "eye.focus_range_diopters": ["x", 3.0, [3.0, 1.0], [-1.0, 2.0], [NAN, 1.0], [0.0, 1e9]],
    "eye.focus_mm": [-1.0, 0.0, NAN, INF, "x", "Infinity", 1.0],
    "eye.fov_deg": [0.0, [0.0, 10.0], [200.0, 200.0], "x", [NAN, 10.0], [10.0]],
    "eye.positions_mm": [[], [[NAN, 0.0]], [[1.0, 2.0, 3.0]], "x", [[INF, 0.0]], [1.0, 2.0],
                         [[100.0, 100.0]]],
    "eye.weights": [[-1.0], [0.0], "x", [1.0, 2.0], [NAN], [INF], []],
}
#: Generated values that the key allows, and what they mean: taken as given.
IN_RANGE: dict[tuple[str, Any], str] = {
    ("display.cover_glass_mm", 0.0): "no cover glass",
    ("display.emission_exponent", 0.0): "cos^0: Lambertian",
    ("eye.gaze_deg", 0.0): "no gaze",
    ("eye.rotation_mm", 0.0): "the pupil at the centre of rotation",
    ("optimizer.momentum", 0.0): "plain SGD",
    ("optimizer.efficiency_weight", 0.0): "light level ignored",
    ("optimizer.min_efficiency", 0.0): "no light floor",
    ("optimizer.min_eye_level", 0.0): "no floor on the light at the eye",
    ("optimizer.plateau_patience", 0): "never stop early",
    ("optimizer.plateau_tolerance", 0.0): "any improvement counts",
    ("optimizer.seed", 0): "seed 0",
    ("optimizer.quantize_share", 0.0): "quantize afterwards only",
    ("optimizer.init_diameter_mm", 0.0): "the diffraction-optimal pinholes",
}
#: Generated values refused by a later check with an outcome of their own.
LATER: dict[tuple[str, Any], Outcome] = {
    # The process (photomask film, the tiny config's) makes no plate 0 mm thick.
    ("plate.thickness_mm", 0.0): failed("plate.thickness_mm = 0"),
    # An eye 100 mm off the axis sees no light: refused before optimizing nothing.
    ("eye.positions_mm", (100.0, 100.0)): bad("eye.positions_mm holds (100, 100) mm",
                                              "sees no light"),
}
#: Refused by the optimizer on its first step (slow: it gets that far).
SLOW_VALUES: dict[tuple[str, Any], Outcome] = {
    ("optimizer.efficiency_weight", 1e300): failed("the loss became inf at iteration 0"),
}


def _frozen(value: Any) -> Any:
    """A hashable form of a config value (lists become tuples; a one-item list of a list, its
    item), for the tables above."""
    if isinstance(value, list):
        items = tuple(_frozen(v) for v in value)
        return items[0] if len(items) == 1 and isinstance(items[0], tuple) else items
    return value


def _kind(key: str) -> list[Any]:
    from aperture_fab.config.config import _FLOATS, _TEXTS, _WHOLE_PAIRS, _WHOLES

    if key in BAD_OTHERS:
        return BAD_OTHERS[key]
    for keys, values in ((_FLOATS, BAD_NUMBERS), (_WHOLES, BAD_WHOLES),
                         (_WHOLE_PAIRS, BAD_WHOLE_PAIRS), (_TEXTS, BAD_TEXTS)):
        if key in keys:
            return values
    raise AssertionError(f"{key}: no kind; add it to BAD_OTHERS")


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf") \
            if math.isinf(value) else repr(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        return json.dumps(value)
    return "[" + ", ".join(_toml_value(v) for v in value) + "]"


def _toml(document: dict[str, Any]) -> str:
    lines = [f"preset = {_toml_value(document['preset'])}"]
    for section, table in document.items():
        if section != "preset":
            lines += [f"[{section}]", *(f"{k} = {_toml_value(v)}" for k, v in table.items())]
    return "\n".join(lines) + "\n"


def _with_value(key: str, value: Any) -> str:
    """The tiny config as TOML with key set to value."""
    section, _, name = key.partition(".")
    document = tomllib.loads(TINY_TOML)
    document.setdefault(section, {})[name] = value
    return _toml(document)


def _shown(value: Any) -> list[str]:
    """How a message may show value (or, for a list, one of its items)."""
    if isinstance(value, list):  # an empty list is said in words
        return [text for item in value for text in _shown(item)] or ["empty", "0 values"]
    if isinstance(value, float):
        return [repr(value), f"{value:g}"]
    return [repr(value)]


class ConfigValue(NamedTuple):
    key: str
    value: Any
    outcome: Outcome | None  # None: IN_RANGE (checked by resolve, not run)
    slow: bool


def config_values() -> list[ConfigValue]:
    from aperture_fab.config.config import SECTION_KEYS

    rows = []
    for section, names in SECTION_KEYS.items():
        for name in names:
            key = f"{section}.{name}"
            for value in _kind(key):
                where = (key, _frozen(value))
                if where in IN_RANGE:
                    rows.append(ConfigValue(key, value, None, False))
                elif where in SLOW_VALUES:
                    rows.append(ConfigValue(key, value, SLOW_VALUES[where], True))
                else:
                    rows.append(ConfigValue(key, value, LATER.get(where, bad(key)), False))
    return rows


CONFIG_VALUES = config_values()
REFUSED_VALUES = [v for v in CONFIG_VALUES if v.outcome is not None]


@pytest.fixture
def inputs(tmp_path: Path) -> Path:
    """marker.png and tiny.toml, for commands that need no design."""
    (tmp_path / "marker.png").write_bytes(encode_png(MARKER))
    (tmp_path / "tiny.toml").write_text(TINY_TOML)
    return tmp_path


@pytest.mark.parametrize(
    "row", [pytest.param(v, id=f"{v.key} = {_toml_value(v.value)}",
                         marks=[pytest.mark.slow] if v.slow else []) for v in REFUSED_VALUES])
def test_config_value(inputs: Path, capsys: pytest.CaptureFixture[str],
                      row: ConfigValue) -> None:
    (inputs / "bad.toml").write_text(_with_value(row.key, row.value))
    argv = ["design", "{d}/marker.png", "--config", "{d}/bad.toml", "--out", "{d}/run",
            "--no-validate", "-q"]
    assert row.outcome is not None
    err = judge(argv, inputs, capsys, row.outcome)
    if row.outcome == bad(row.key):  # the generic refusal names the value too
        assert any(text in err for text in _shown(row.value)), (row.value, err)
        assert not (inputs / "run").exists() or not any((inputs / "run").iterdir())


@pytest.mark.parametrize(("key", "value"), [pytest.param(v.key, v.value, id=f"{v.key} = "
                                                         f"{_toml_value(v.value)}")
                                            for v in CONFIG_VALUES if v.outcome is None])
def test_config_value_in_range_is_taken_as_given(key: str, value: Any) -> None:
    from aperture_fab.config.config import parse_toml, resolve
    from aperture_fab.config.written import to_dict, to_toml

    config = resolve(None, parse_toml(_with_value(key, value), "in range"))
    section, _, name = key.partition(".")
    assert to_dict(config)[section][name] == value, IN_RANGE[(key, _frozen(value))]
    assert resolve(None, parse_toml(to_toml(config), "written")) == config


# -- config files ----------------------------------------------------------------------------


def _config(text: str, name: str = "bad.toml") -> Setup:
    """tiny.toml with text appended, as `name`."""
    def setup(folder: Path) -> None:
        (folder / name).write_text(TINY_TOML + "\n" + text)
    return setup


def _config_edit(old: str, new: str, source: str = "tiny.toml") -> Setup:
    """source (tiny.toml or the design's design.toml) with old replaced by new, as bad.toml."""
    def setup(folder: Path) -> None:
        text = (folder / source).read_text()
        assert old in text, old
        (folder / "bad.toml").write_text(text.replace(old, new))
    return setup


DESIGN_BAD = ["design", "{d}/marker.png", "--config", "{d}/bad.toml", "--out", "{d}/run",
              "--no-validate"]
#: design with its validation settings read (still refused before any work).
DESIGN_BAD_VALIDATED = ["design", "{d}/marker.png", "--config", "{d}/bad.toml", "--out",
                        "{d}/run"]
EXPORT_BAD = ["export", "{d}/design.npz", "--config", "{d}/bad.toml", "--out", "{d}/x/"]
SYNTAX = "bad.toml: TOML syntax error at line"

CONFIG_FILES: list[Case] = [
    Case("unclosed bracket", DESIGN_BAD, bad(SYNTAX, "Fix that line"),
         _config("[plate\ngap_mm = 5.0\n")),
    Case("text without quotes", DESIGN_BAD, bad(SYNTAX),
         _config_edit("[plate]", "[plate]\nhole_axis = straight")),
    Case("a table declared twice", DESIGN_BAD, bad(SYNTAX, "twice"),
         _config("[plate]\ngap_mm = 5.0\n")),
    Case("a key given twice", DESIGN_BAD, bad(SYNTAX, "Cannot overwrite a value"),
         _config_edit("[plate]", "[plate]\ngap_mm = 5.0\ngap_mm = 6.0")),
    Case("preset given twice", DESIGN_BAD, bad(SYNTAX),
         _config_edit('preset = "near-eye-nominal"', 'preset = "seed"\npreset = "near-eye"')),
    Case("an array of tables for a section", DESIGN_BAD, bad("Top-level key 'plate'"),
         _config_edit("[plate]", "[[plate]]")),
    Case("unknown key", DESIGN_BAD, bad("Unknown key 'gapmm' in section [plate]",
                                        "Did you mean 'gap_mm'?"),
         _config_edit("[plate]", "[plate]\ngapmm = 5.0")),
    Case("key of another section", DESIGN_BAD, bad("'pupil_mm' belongs in [eye]"),
         _config_edit("[plate]", "[plate]\npupil_mm = 4.0")),
    Case("misspelt section", DESIGN_BAD, bad("Unknown section [optimiser]",
                                             "did you mean [optimizer]?"),
         _config("[optimiser]\niterations = 3\n")),
    Case("a key at the top", DESIGN_BAD, bad("Top-level key 'gap_mm'", "belongs in [plate]"),
         _config_edit('preset = "near-eye-nominal"', 'preset = "near-eye-nominal"\ngap_mm = 5')),
    Case("unknown preset", DESIGN_BAD, bad("preset = 'nope' is not a known preset; choose one"),
         _config_edit('preset = "near-eye-nominal"', 'preset = "nope"')),
    Case("preset not text", DESIGN_BAD, Refused(EXIT_BAD_INPUT, ("preset = ['seed']",
                                                                 "must be text")),
         _config_edit('preset = "near-eye-nominal"', 'preset = ["seed"]')),
    Case("a date for a length", DESIGN_BAD, bad("plate.gap_mm = datetime.date(1979, 5, 27)",
                                                "expected a number"),
         _config_edit("[plate]", "[plate]\ngap_mm = 1979-05-27")),
    Case("Latin-1 text (not UTF-8)", DESIGN_BAD, bad("--config {d}/bad.toml is not UTF-8 text"),
         _write("bad.toml", "# caf\xe9\n".encode("latin-1"))),
    Case("a PNG given as the config", ["design", "{d}/marker.png", "--config", "{d}/marker.png",
                                       "--out", "{d}/run"],
         bad("--config {d}/marker.png is not UTF-8 text")),
    Case("config is a folder", ["design", "{d}/marker.png", "--config", "{d}", "--out",
                                "{d}/run"], bad("--config {d}: cannot read it")),
    Case("config missing", ["design", "{d}/marker.png", "--config", "{d}/none.toml", "--out",
                            "{d}/run"], bad("--config {d}/none.toml: cannot read it")),
    Case("[validation] unknown key", DESIGN_BAD_VALIDATED,
         bad("[validation] has unknown key(s) ['bogus']"), _config("[validation]\nbogus = 1\n")),
    Case("[validation] huge tolerance_samples", DESIGN_BAD_VALIDATED,
         bad("validation.tolerance_samples = 1000000000 is out of range; allowed: 0 to"),
         _config("[validation]\ntolerance_samples = 1000000000\n")),
    Case("[validation] huge made_copies", DESIGN_BAD_VALIDATED,
         bad("validation.made_copies = 99999 is out of range"),
         _config("[validation]\nmade_copies = 99999\n")),
    Case("[validation] diffraction as text", DESIGN_BAD_VALIDATED,
         bad("validation.diffraction = 'yes' has the wrong type: expected true or false"),
         _config("[validation]\ndiffraction = 'yes'\n")),
    Case("[validation] threshold_db as text", DESIGN_BAD_VALIDATED,
         bad("validation.threshold_db = 'x' has the wrong type"),
         _config("[validation]\nthreshold_db = 'x'\n")),
    Case("[validation] threshold_db NaN", DESIGN_BAD_VALIDATED,
         bad("validation.threshold_db = nan must be a finite PSNR"),
         _config("[validation]\nthreshold_db = nan\n")),
    Case("[validation] tilt 90 degrees", DESIGN_BAD_VALIDATED,
         bad("validation.tilt_sigma_deg = 90.0 is out of range"),
         _config("[validation]\ntilt_sigma_deg = 90.0\n")),
    Case("[validation] gap sigma as text", DESIGN_BAD_VALIDATED,
         bad("validation.gap_sigma_mm = 'x' has the wrong type"),
         _config("[validation]\ngap_sigma_mm = 'x'\n")),
    Case("[process] unknown name", DESIGN_BAD, bad("process = 'nope' is not a known process"),
         _config("[process]\nname = 'nope'\n")),
    Case("[process] misspelt field", DESIGN_BAD, bad("process override 'nmae' is not a process "
                                                     "field"),
         _config("[process]\nnmae = 'resin'\n")),
    Case("[process] negative smallest hole", DESIGN_BAD,
         bad("process.min_hole_mm = -1 is out of range"),
         _config("[process]\nname = 'resin'\nmin_hole_mm = -1\n")),
    Case("[photometry] unknown key", DESIGN_BAD, bad("[photometry] has unknown key(s) ['bogus']"),
         _config("[photometry]\nbogus = 1\n")),
    # export, render and validate read a config too
    Case("empty config (export)", EXPORT_BAD, bad("open_fraction has shape (16, 16)",
                                                  "(40, 40)"), _write("bad.toml", "")),
    Case("binary design.toml (export)", ["export", "{d}/design.npz", "--out", "{d}/x/"],
         bad("{d}/design.toml is not UTF-8 text"), _write("design.toml", b"\x89PNG\xff\xfe")),
    Case("binary design.toml (render)", ["render", "{d}/design.npz", "--out", "{d}/v.png"],
         bad("config {d}/design.toml is not UTF-8 text"),
         _write("design.toml", b"\x89PNG\xff\xfe")),
    Case("binary design.toml (validate)", ["validate", "{d}/holes.csv", "{d}/marker.png", *FAST],
         bad("config {d}/design.toml is not UTF-8 text"),
         _write("design.toml", b"\x89PNG\xff\xfe")),
    Case("syntax error in design.toml (render)",
         ["render", "{d}/design.npz", "--config", "{d}/bad.toml", "--out", "{d}/v.png"],
         bad(SYNTAX), _config_edit("gap_mm = ", "gap_mm = 1 + ", source="design.toml")),
    Case("another grid (render)",
         ["render", "{d}/design.npz", "--config", "{d}/bad.toml", "--out", "{d}/v.png"],
         bad("has (16, 16) cells", "give the config the design was made with"),
         _config_edit("cells = [16, 16]", "cells = [8, 8]", source="design.toml")),
    Case("design.toml edited in the design folder (render)",
         ["render", "{d}/design.npz", "--out", "{d}/v.png"],
         bad("does not match its manifest.json: design.toml differs"),
         lambda folder: (folder / "design.toml").write_text(
             (folder / "design.toml").read_text().replace("pupil_mm = 4.0", "pupil_mm = 5.0"))),
    Case("a UTF-8 byte-order mark (export)", EXPORT_BAD,
         Works(files("x/plate.stl", "x/holes.csv")),
         lambda folder: (folder / "bad.toml").write_bytes(
             b"\xef\xbb\xbf" + (folder / "design.toml").read_bytes())),
    Case("a comment added (export)", EXPORT_BAD, Works(files("x/plate.stl")),
         _config_edit("[plate]", "# mine\n[plate]", source="design.toml")),
    # the sweep file
    Case("sweep file missing", ["sweep", "{d}/none.toml", "--dry-run"],
         bad("sweep file {d}/none.toml: cannot read it")),
    Case("sweep file binary", ["sweep", "{d}/s.toml", "--dry-run"],
         bad("sweep file {d}/s.toml is not UTF-8 text"), _write("s.toml", b"\x89PNG\xff")),
    Case("sweep file syntax", ["sweep", "{d}/s.toml", "--dry-run"],
         bad("{d}/s.toml: TOML syntax error"), _write("s.toml", "[sweep\n")),
    Case("sweep file empty", ["sweep", "{d}/s.toml", "--dry-run"],
         bad("[sweep] targets: give the target images"), _write("s.toml", "")),
    Case("sweep grid value out of range", ["sweep", "{d}/s.toml", "--dry-run"],
         bad("[grid] plate.gap_mm = -1.0", "Fix: remove or change -1.0"),
         _write("s.toml", '[sweep]\nmode = "grid"\ntargets = ["marker.png"]\n'
                          '[grid]\n"plate.gap_mm" = [-1.0]\n')),
    Case("sweep grid key misspelt", ["sweep", "{d}/s.toml", "--dry-run"],
         bad("Unknown key 'gapmm' in section [plate]"),
         _write("s.toml", '[sweep]\nmode = "grid"\ntargets = ["marker.png"]\n'
                          '[grid]\n"plate.gapmm" = [1.0]\n')),
    Case("sweep file checks (dry run)", ["sweep", "{d}/s.toml", "--dry-run"], Works(),
         _write("s.toml", '[sweep]\nmode = "grid"\ntargets = ["marker.png"]\nconfig = '
                          '"tiny.toml"\n[grid]\n"plate.gap_mm" = [9.0, 10.0]\n')),
]


@pytest.mark.parametrize(("setup", "argv", "outcome"), params(CONFIG_FILES))
def test_config_file(folder: Path, capsys: pytest.CaptureFixture[str], setup: Setup,
                     argv: list[str], outcome: Outcome) -> None:
    setup(folder)
    judge(argv, folder, capsys, outcome)


# -- flags, per command ----------------------------------------------------------------------

#: design on the tiny config: refused before any work in every FLAGS case.
DESIGN = ["design", "{d}/marker.png", "--config", "{d}/tiny.toml", "--out", "{d}/run",
          "--no-validate"]
DESIGN_VALIDATED = ["design", "{d}/marker.png", "--config", "{d}/tiny.toml", "--out",
                    "{d}/run"]
RENDER = ["render", "{d}/design.npz", "--out", "{d}/v.png"]
DISPLAY = ["display", "{d}/design.npz", "{d}/marker.png", "--out", "{d}/f.png"]
EYE = ["--eye", "0,0", "--pupil", "4"]
EXPORT = ["export", "{d}/design.npz"]
VALIDATE = ["validate", "{d}/holes.csv", "{d}/marker.png"]
INVALID = "invalid {} value"


def design_flag(flag: str, *values: str) -> list[str]:
    return [*DESIGN, flag, *values]


FLAGS: list[Case] = [
    # design: the config flags, each checked like its config key
    Case("design --cells 0 0", design_flag("--cells", "0", "0"),
         bad("plate.cells = (0, 0) is out of range", "came from the overrides (flags)")),
    Case("design --cells -1 16", design_flag("--cells", "-1", "16"), bad("plate.cells = (-1, 16)")),
    Case("design --cells a b", design_flag("--cells", "a", "b"),
         usage("argument --cells: invalid int value: 'a'")),
    Case("design --cells 16 (one number)", design_flag("--cells", "16"),
         usage("argument --cells: expected 2 arguments")),
    Case("design --cells 100000 100000", design_flag("--cells", "100000", "100000"),
         bad("plate.cells = (100000, 100000) is out of range; allowed: 1 to 16384")),
    Case("design --pitch-mm 0", design_flag("--pitch-mm", "0"), bad("plate.pitch_mm = 0.0")),
    Case("design --pitch-mm nan", design_flag("--pitch-mm", "nan"), bad("plate.pitch_mm = nan")),
    Case("design --pitch-mm inf", design_flag("--pitch-mm", "inf"), bad("plate.pitch_mm = inf")),
    Case("design --pitch-mm x", design_flag("--pitch-mm", "x"),
         usage("argument --pitch-mm: invalid float value: 'x'")),
    Case("design --gap-mm -1", design_flag("--gap-mm", "-1"), bad("plate.gap_mm = -1.0")),
    Case("design --gap-mm 1e300", design_flag("--gap-mm", "1e300"), bad("plate.gap_mm = 1e+300")),
    Case("design --thickness-mm -1", design_flag("--thickness-mm", "-1"),
         bad("plate.thickness_mm = -1.0 is out of range")),
    Case("design --thickness-mm 1000", design_flag("--thickness-mm", "1000"),
         bad("plate.thickness_mm = 1000.0 is out of range; allowed: 0 to 100 mm")),
    Case("design --hole-axis diagonal", design_flag("--hole-axis", "diagonal"),
         usage("argument --hole-axis: invalid choice: 'diagonal'")),
    Case("design --pupil-mm 0", design_flag("--pupil-mm", "0"), bad("eye.pupil_mm = 0.0")),
    Case("design --pupil-mm 100", design_flag("--pupil-mm", "100"),
         bad("eye.pupil_mm = 100.0 is out of range; allowed: 0 < eye.pupil_mm <= 20")),
    Case("design --eye-relief-mm -1", design_flag("--eye-relief-mm", "-1"),
         bad("eye.eye_relief_mm = -1.0")),
    Case("design --focus-mm abc", design_flag("--focus-mm", "abc"),
         bad("--focus-mm 'abc': give a distance in mm or 'infinity'")),
    Case("design --focus-mm 0", design_flag("--focus-mm", "0"),
         bad("eye.focus_mm = 0.0 is out of range")),
    Case("design --focus-mm -5", design_flag("--focus-mm", "-5"), bad("eye.focus_mm = -5.0")),
    Case("design --focus-mm 1 (in front of the plate)", design_flag("--focus-mm", "1"),
         bad("eye.focus_mm = 1.0 focuses on or in front of the plate")),
    Case("design --focus-mm Infinity", design_flag("--focus-mm", "Infinity"),
         bad("eye.focus_mm = inf is out of range")),
    Case("design --view-pixels 0 0", design_flag("--view-pixels", "0", "0"),
         bad("eye.view_pixels = (0, 0)")),
    Case("design --method lbfgs", design_flag("--method", "lbfgs"),
         usage("argument --method: invalid choice: 'lbfgs'")),
    Case("design --lr 0", design_flag("--lr", "0"), bad("optimizer.learning_rate = 0.0")),
    Case("design --lr nan", design_flag("--lr", "nan"), bad("optimizer.learning_rate = nan")),
    Case("design --lr 1e9", design_flag("--lr", "1e9"),
         bad("optimizer.learning_rate = 1000000000.0 is out of range")),
    Case("design --iterations 0", design_flag("--iterations", "0"),
         bad("optimizer.iterations = 0 is out of range; allowed: >= 1")),
    Case("design --iterations -1", design_flag("--iterations", "-1"),
         bad("optimizer.iterations = -1")),
    Case("design --iterations 1.5", design_flag("--iterations", "1.5"),
         usage("argument --iterations: invalid int value: '1.5'")),
    Case("design --iterations 10000000", design_flag("--iterations", "10000000"),
         bad("optimizer.iterations = 10000000 is out of range")),
    Case("design --init zeros", design_flag("--init", "zeros"),
         usage("argument --init: invalid choice: 'zeros'")),
    Case("design --display-mode both", design_flag("--display-mode", "both"),
         usage("argument --display-mode: invalid choice: 'both'")),
    Case("design --efficiency-weight -1", design_flag("--efficiency-weight", "-1"),
         bad("optimizer.efficiency_weight = -1.0 is out of range")),
    Case("design --seed -1", design_flag("--seed", "-1"), bad("optimizer.seed = -1")),
    Case("design --seed 99999999999999999999", design_flag("--seed", "99999999999999999999"),
         bad("optimizer.seed = 99999999999999999999 is out of range")),
    Case("design --precision float16", design_flag("--precision", "float16"),
         usage("argument --precision: invalid choice: 'float16'")),
    Case("design --device tpu", design_flag("--device", "tpu"),
         bad("optimizer.device = 'tpu' is not allowed; use auto, cpu, cuda or cuda:N")),
    Case("design --preset nope", design_flag("--preset", "nope"),
         bad("preset = 'nope' is not a known preset")),
    Case("design --process nope", design_flag("--process", "nope"),
         bad("process = 'nope' is not a known process; choose one of")),
    Case("design --process FDM (case matters)", design_flag("--process", "FDM"),
         bad("process = 'FDM' is not a known process")),
    Case("design --tolerance-samples -1", [*DESIGN_VALIDATED, "--tolerance-samples", "-1"],
         bad("validation.tolerance_samples = -1 must be a whole number >= 0")),
    Case("design --tolerance-samples 100000 (would run for hours)",
         [*DESIGN_VALIDATED, "--tolerance-samples", "100000"],
         bad("validation.tolerance_samples = 100000 is out of range; allowed: 0 to 10000")),
    Case("design --mesh-samples 100000000 (would run for hours)",
         [*DESIGN_VALIDATED, "--mesh-samples", "100000000"],
         bad("validation.mesh_samples = 100000000 is out of range; allowed: 0 to 4096")),
    Case("design --mesh-samples x", [*DESIGN_VALIDATED, "--mesh-samples", "x"],
         usage("argument --mesh-samples: invalid int value: 'x'")),
    Case("design --strict with --no-validate", [*DESIGN, "--strict"],
         usage("--strict exits on the report's WARN, but --no-validate writes no report")),
    Case("design --resume without a checkpoint", [*DESIGN, "--resume"],
         bad("--resume: no checkpoint at {d}/run/checkpoint.pt; run without --resume")),
    Case("design --frame x", design_flag("--frame", "x"),
         usage("argument --frame: invalid int value: 'x'")),
    Case("design --frame -1", design_flag("--frame", "-1"),
         bad("--frame -1 is not allowed; give a whole number from 0")),
    Case("design --alpha grey", design_flag("--alpha", "grey"),
         usage("argument --alpha: invalid choice: 'grey'")),
    Case("design without targets", ["design", "--config", "{d}/tiny.toml"],
         usage("the following arguments are required: TARGET")),
    Case("design --out '' (an unset variable)", ["design", "{d}/marker.png", "--out", ""],
         usage("--out is given an empty value")),
    Case("design --out= (empty)", ["design", "{d}/marker.png", "--out="],
         usage("--out is given an empty value")),
    Case("design --process '' (empty)", design_flag("--process", ""),
         usage("--process is given an empty value")),
    Case("design --bogus", design_flag("--bogus"), usage("unrecognized arguments: --bogus")),
    # render
    Case("render --target-index 5", [*RENDER, "--target-index", "5"],
         bad("--target-index 5 is out of range", "allowed 0 to 0")),
    Case("render --target-index -1", [*RENDER, "--target-index", "-1"],
         bad("--target-index -1 is out of range")),
    Case("render --target-index x", [*RENDER, "--target-index", "x"],
         usage("argument --target-index: invalid int value: 'x'")),
    Case("render --eye a,b", [*RENDER, "--eye", "a,b"],
         bad("--eye 'a,b': give two numbers in mm as X,Y")),
    Case("render --eye 1", [*RENDER, "--eye", "1"], bad("--eye '1': give two numbers")),
    Case("render --eye 1,2,3", [*RENDER, "--eye", "1,2,3"], bad("--eye '1,2,3'")),
    Case("render --eye nan,0", [*RENDER, "--eye", "nan,0"],
         bad("--eye (nan, 0.0): give two finite numbers")),
    Case("render --eye inf,0", [*RENDER, "--eye", "inf,0"],
         bad("--eye (inf, 0.0): give two finite numbers")),
    Case("render --eye 1e308,0", [*RENDER, "--eye", "1e308,0"],
         bad("the eye sees no light from the display at that position")),
    Case("render --eye ' 0 , 0 ' (spaces)", [*RENDER, "--eye", " 0 , 0 "], VIEW_PNG),
    Case("render --pupil 0", [*RENDER, "--pupil", "0"], bad("--pupil 0 is out of range")),
    Case("render --pupil nan", [*RENDER, "--pupil", "nan"], bad("--pupil nan is out of range")),
    Case("render --pupil 1e9", [*RENDER, "--pupil", "1e9"], bad("--pupil 1e+09 is out of range")),
    Case("render --pupil x", [*RENDER, "--pupil", "x"],
         usage("argument --pupil: invalid float value: 'x'")),
    Case("render --focus abc", [*RENDER, "--focus", "abc"],
         bad("--focus 'abc': give a distance in mm or 'infinity'")),
    Case("render --focus 0", [*RENDER, "--focus", "0"], bad("--focus 0 is out of range")),
    Case("render --focus nan", [*RENDER, "--focus", "nan"], bad("--focus nan is out of range")),
    Case("render --focus 1 (in front of the plate)", [*RENDER, "--focus", "1"],
         bad("--focus 1 is out of range; allowed: a distance beyond")),
    Case("render --focus 1e300 (as good as infinity)", [*RENDER, "--focus", "1e300"], VIEW_PNG),
    Case("render --process nope", [*RENDER, "--process", "nope"],
         bad("process = 'nope' is not a known process")),
    Case("render --mesh --mesh-samples 0", [*RENDER, "--mesh", "--mesh-samples", "0"],
         bad("--mesh-samples 0 is out of range; allowed: a whole number from 8 to 4096")),
    Case("render --mesh --mesh-samples 100000000 (would run for hours)",
         [*RENDER, "--mesh", "--mesh-samples", "100000000"],
         bad("--mesh-samples 100000000 is out of range")),
    Case("render --config missing", [*RENDER, "--config", "{d}/none.toml"],
         bad("config {d}/none.toml does not exist")),
    Case("render '' as the part", ["render", "", "--out", "{d}/v.png"],
         usage("argument 2 is empty")),
    # display
    Case("display without --eye", [*DISPLAY, "--pupil", "4"],
         usage("the following arguments are required: --eye")),
    Case("display --eye a", [*DISPLAY, "--eye", "a", "--pupil", "4"], bad("--eye 'a'")),
    Case("display --eye nan,nan", [*DISPLAY, "--eye", "nan,nan", "--pupil", "4"],
         bad("--eye (nan, nan): give two finite numbers")),
    Case("display --eye 50,50 (sees nothing)", [*DISPLAY, "--eye", "50,50", "--pupil", "4"],
         bad("the eye at (50, 50) mm with a 4 mm pupil sees no light")),
    Case("display --pupil 0", [*DISPLAY, "--eye", "0,0", "--pupil", "0"],
         bad("--pupil 0 is out of range; allowed: 0 < pupil <= 20 mm")),
    Case("display --pupil nan", [*DISPLAY, "--eye", "0,0", "--pupil", "nan"],
         bad("--pupil nan is out of range")),
    Case("display --pupil 100", [*DISPLAY, "--eye", "0,0", "--pupil", "100"],
         bad("--pupil 100 is out of range")),
    Case("display --iterations -1", [*DISPLAY, *EYE, "--iterations", "-1"],
         bad("--iterations -1 is out of range; allowed: a whole number from 0 to 1000")),
    Case("display --iterations 100000000", [*DISPLAY, *EYE, "--iterations", "100000000"],
         bad("--iterations 100000000 is out of range")),
    Case("display --focus 0", [*DISPLAY, *EYE, "--focus", "0"],
         bad("--focus 0 is out of range; allowed: a distance beyond")),
    Case("display --focus x", [*DISPLAY, *EYE, "--focus", "x"], bad("--focus 'x'")),
    Case("display --target-index 3", [*DISPLAY, *EYE, "--target-index", "3"],
         bad("--target-index 3 is out of range")),
    Case("display --process nope", [*DISPLAY, *EYE, "--process", "nope"],
         bad("process = 'nope' is not a known process")),
    Case("display --iterations 0 (the untracked content)", [*DISPLAY, *EYE, "--iterations", "0"],
         FRAME_PNG),
    # export
    Case("export without --out", EXPORT, usage("the following arguments are required: --out")),
    Case("export --process nope", [*EXPORT, "--out", "{d}/x/", "--process", "nope"],
         bad("process = 'nope' is not a known process")),
    Case("export --preset nope", [*EXPORT, "--out", "{d}/x/", "--preset", "nope"],
         bad("preset = 'nope' is not a known preset")),
    Case("export --config missing", [*EXPORT, "--out", "{d}/x/", "--config", "{d}/none.toml"],
         bad("{d}/none.toml: cannot read the design's config", "give it with --config")),
    Case("export --out ''", [*EXPORT, "--out", ""], usage("--out is given an empty value")),
    # validate
    Case("validate --tolerance-samples -1", [*VALIDATE, "--tolerance-samples", "-1"],
         bad("validation.tolerance_samples = -1")),
    Case("validate --tolerance-samples 100000", [*VALIDATE, "--tolerance-samples", "100000"],
         bad("validation.tolerance_samples = 100000 is out of range")),
    Case("validate --mesh-samples -1", [*VALIDATE, "--mesh-samples", "-1"],
         bad("validation.mesh_samples = -1")),
    Case("validate --process nope", [*VALIDATE, "--process", "nope", *FAST],
         bad("process = 'nope' is not a known process")),
    Case("validate two targets for a one-target design",
         ["validate", "{d}/holes.csv", "{d}/marker.png", "{d}/marker.png", *FAST],
         bad("was designed for 1 target(s) (marker) but 2 were given")),
    Case("validate without targets", ["validate", "{d}/holes.csv"],
         usage("the following arguments are required: TARGET")),
    Case("validate --strict -q -v", [*VALIDATE, "--strict", "-q", "-v"],
         usage("not allowed with argument")),
    # assembly, sweep, presets, processes
    Case("assembly --out a.txt", ["assembly", "{d}", "--out", "{d}/a.txt"],
         bad("the sheet is an HTML page; give a name ending in .html")),
    Case("assembly --out in a missing folder", ["assembly", "{d}", "--out", "{d}/no/a.html"],
         bad("the folder {d}/no does not exist; create it or choose another --out")),
    Case("sweep --workers 0", ["sweep", "{d}/s.toml", "--dry-run", "--workers", "0"],
         bad("--workers 0: give a whole number >= 1")),
    Case("sweep --cpus-per-point 0", ["sweep", "{d}/s.toml", "--dry-run", "--cpus-per-point",
                                      "0"], bad("--cpus-per-point 0: give a whole number >= 1")),
    Case("presets with an argument", ["presets", "near-eye"],
         usage("unrecognized arguments: near-eye")),
    Case("processes --bogus", ["processes", "--bogus"], usage("unrecognized arguments: --bogus")),
    Case("an unknown command", ["optimise", "x.png"], usage("invalid choice: 'optimise'")),
    Case("no command", [], usage("the following arguments are required: COMMAND")),
]


@pytest.mark.parametrize(("setup", "argv", "outcome"), params(FLAGS))
def test_flag(folder: Path, capsys: pytest.CaptureFixture[str], setup: Setup,
              argv: list[str], outcome: Outcome) -> None:
    setup(folder)
    judge(argv, folder, capsys, outcome)


# -- output places ---------------------------------------------------------------------------


def _user_folder(name: str, *files: str) -> Setup:
    """A folder of the user's own files (not a design's)."""
    def setup(folder: Path) -> None:
        (folder / name).mkdir()
        for file in files:
            (folder / name / file).write_text("the user's own")
    return setup


def _kept(name: str) -> Callable[[Path], None]:
    """The user's file is still there, unchanged."""
    def check(folder: Path) -> None:
        assert (folder / name).read_text() == "the user's own"
    return check


def _set_unchanged(folder: Path) -> None:
    from aperture_fab.io.manifest import check_folder

    check_folder(folder)


def _mine_published_notes_kept(folder: Path) -> None:
    published("mine")(folder)
    _kept("mine/notes.txt")(folder)


NOT_UTF8_FOLDER = os.fsdecode(b"out-\xff\xfe")

OUTPUT_PLACES: list[Case] = [
    # a file where a folder is expected, and the reverse
    Case("design --out is the target image", [*DESIGN[:5], "{d}/marker.png", "--no-validate"],
         bad("--out {d}/marker.png: '.png' is not a part file suffix")),
    Case("design --out under a file", [*DESIGN[:5], "{d}/marker.png/run", "--no-validate"],
         bad("cannot create the output folder {d}/marker.png/run", "choose another --out")),
    Case("design --out /dev/null", [*DESIGN[:5], "/dev/null", "--no-validate"],
         bad("cannot create the output folder /dev/null")),
    Case("design --out a 300-character name", [*DESIGN[:5], "{d}/" + "x" * 300,
                                               "--no-validate"],
         bad("cannot create the output folder", "choose another --out")),
    Case("design --out not UTF-8 (refused before the work)",
         [*DESIGN[:5], "{d}/" + NOT_UTF8_FOLDER, "--no-validate"],
         bad("has a name that is not valid UTF-8 text", "\\xff\\xfe")),
    Case("validate --out is a file", [*VALIDATE, *FAST, "--out", "{d}/marker.png"],
         bad("cannot create the output folder {d}/marker.png")),
    Case("validate --out is the design's folder", [*VALIDATE, *FAST, "--out", "{d}"],
         bad("--out {d} holds a design", "Give a new folder")),
    Case("render --out is a folder", [*RENDER[:2], "--out", "{d}"],
         bad("--out {d} is a folder; give a PNG file name in it")),
    Case("render --out under a file", [*RENDER[:2], "--out", "{d}/marker.png/v.png"],
         bad("cannot create the folder {d}/marker.png", "choose another --out")),
    Case("render --out .npz", [*RENDER[:2], "--out", "{d}/design.npz"],
         bad("--out {d}/design.npz: .npz is not allowed", "give a name ending in .png")),
    Case("render --out in a new folder (made)", [*RENDER[:2], "--out", "{d}/new/deep/v.png"],
         Works(png_of("new/deep/v.png", VIEW_PIXELS))),
    Case("display --out is a folder", [*DISPLAY[:3], *EYE, "--out", "{d}"],
         bad("--out {d} is a folder")),
    Case("display --out .jpg", [*DISPLAY[:3], *EYE, "--out", "{d}/f.jpg"],
         bad("--out {d}/f.jpg: .jpg is not allowed")),
    Case("export --out under a file", [*EXPORT, "--out", "{d}/marker.png/x"],
         bad("cannot create the output folder {d}/marker.png/x")),
    Case("export --out .npz", [*EXPORT, "--out", "{d}/x/design.npz"],
         bad("'.npz' is not a part file suffix")),
    # out inside the input: the inputs and a design's set are never written over
    Case("render --out is its own target image", [*RENDER[:2], "{d}/marker.png", "--out",
                                                  "{d}/marker.png"],
         bad("--out {d}/marker.png is the target image", "would destroy it")),
    Case("display --out is its own target image", [*DISPLAY[:3], *EYE, "--out",
                                                   "{d}/marker.png"],
         bad("--out {d}/marker.png is the target image")),
    Case("render --out is a file of the design's set", [*RENDER[:2], "--out",
                                                        "{d}/display_marker.png"],
         bad("display_marker.png belong to the design set recorded in {d}/manifest.json")),
    Case("display --out is a file of the design's set", [*DISPLAY[:3], *EYE, "--out",
                                                         "{d}/view_optimized_marker.png"],
         bad("view_optimized_marker.png belong to the design set")),
    Case("export --out the design's own folder", [*EXPORT, "--out", "{d}"],
         bad("plate.stl", "belong to the design set recorded in {d}/manifest.json")),
    Case("export --out the design's plate.stl", [*EXPORT, "--out", "{d}/plate.stl"],
         bad("plate.stl belong to the design set")),
    Case("assembly --out a new name beside the design's files", ["assembly", "{d}", "--out",
                                                                 "{d}/display_marker.html"],
         Works(files("display_marker.html"))),
    Case("render a second time over its own view", [*RENDER, "--eye", "0.1,0"], VIEW_PNG,
         _copy("marker.png", "v.png")),
    # a folder of another design, or of the user
    Case("design into a folder of the user's files (kept)",
         [*DESIGN[:5], "{d}/mine", "--no-validate", "--iterations", "2"],
         Works(_mine_published_notes_kept),
         _user_folder("mine", "notes.txt"), slow=True),
    Case("design over a user's plate.stl (kept, no manifest names it)",
         [*DESIGN[:5], "{d}/mine", "--no-validate", "--iterations", "2"],
         Works(published("mine")), _user_folder("mine", "plate.stl"), slow=True),
    Case("design into another design's folder (replaced whole)",
         [*DESIGN[:5], "{d}", "--no-validate", "--iterations", "2"],
         Works(_set_unchanged), slow=True),
    Case("validate into a new folder beside the part", [*VALIDATE, *FAST, "--out", "{d}/check"],
         Works(files("check/report.json", "check/report.html"), RESULT_STATUSES), slow=True),
]


@pytest.mark.parametrize(("setup", "argv", "outcome"), params(OUTPUT_PLACES))
def test_output_place(folder: Path, capsys: pytest.CaptureFixture[str], setup: Setup,
                      argv: list[str], outcome: Outcome) -> None:
    setup(folder)
    judge(argv, folder, capsys, outcome)
    if isinstance(outcome, Refused) and (folder / "manifest.json").is_file():
        _set_unchanged(folder)  # a refused run leaves the design's set whole


# -- parts and sub-commands ------------------------------------------------------------------


def _edited_csv(edit: Callable[[list[str]], list[str]]) -> Setup:
    """holes.csv, its lines edited, as edit.csv."""
    def setup(folder: Path) -> None:
        lines = (folder / "holes.csv").read_text().splitlines()
        (folder / "edit.csv").write_text("\n".join(edit(lines)) + "\n")
    return setup


def _first_row(field: int, value: str) -> Setup:
    def edit(lines: list[str]) -> list[str]:
        cells = lines[1].split(",")
        cells[field] = value
        return [lines[0], ",".join(cells), *lines[2:]]
    return _edited_csv(edit)


def _stl_count(count: int) -> bytes:
    """A binary STL whose header promises `count` facets and holds none."""
    return b"\0" * 80 + struct.pack("<I", count) + b"\0" * 50


def _moved(name: str) -> Setup:
    def setup(folder: Path) -> None:
        (folder / name).rename(folder / f"moved-{name}")
    return setup


def render_part(part: str, *flags: str) -> list[str]:
    return ["render", part, "--out", "{d}/v.png", *flags]


def validate_part(part: str) -> list[str]:
    return ["validate", part, "{d}/marker.png", *FAST, "--out", "{d}/check"]


CSV_COLUMNS = "row,col,x_mm,y_mm,radius_mm,axis_x,axis_y"

PARTS: list[Case] = [
    # validate and render of what is no part
    Case("validate a PNG", validate_part("{d}/marker.png"),
         bad("part {d}/marker.png: .png is not a part file; give a design.npz, a holes.csv")),
    Case("validate a TOML", validate_part("{d}/tiny.toml"), bad(".toml is not a part file")),
    Case("validate a 3MF", validate_part("{d}/plate.3mf"), bad(".3mf is not a part file")),
    Case("validate a folder named .stl", validate_part("{d}/dir.stl"),
         bad("part {d}/dir.stl does not exist or is not a file"),
         lambda folder: (folder / "dir.stl").mkdir()),
    Case("render a missing part", render_part("{d}/none.npz"),
         bad("part {d}/none.npz does not exist or is not a file; check the path")),
    Case("render a folder", render_part("{d}"), bad("part {d}: no suffix is not a part file")),
    Case("render a part without its design.toml", render_part("{d}/design.npz"),
         bad("config {d}/design.toml does not exist; give the design's design.toml with "
             "--config"), _moved("design.toml")),
    Case("render holes.csv without design.npz beside", render_part("{d}/holes.csv"),
         bad("no display content: there is no design.npz beside {d}/design.toml"),
         _moved("design.npz")),
    # STL
    Case("empty STL", validate_part("{d}/e.stl"),
         bad("{d}/e.stl: STL data has 0 bytes; a binary STL has at least 84"),
         _write("e.stl", b"")),
    Case("STL of random bytes", validate_part("{d}/g.stl"), bad("{d}/g.stl: STL data has",
                                                                "truncated"),
         _write("g.stl", b"x" * 200)),
    Case("STL promising 4e9 facets", validate_part("{d}/h.stl"),
         bad("header promises 4000000000 facets", "Export the mesh again"),
         _write("h.stl", _stl_count(4_000_000_000))),
    Case("truncated STL", render_part("{d}/t.stl"), bad("{d}/t.stl", "it is truncated"),
         lambda folder: (folder / "t.stl").write_bytes((folder / "plate.stl").read_bytes()[:1000])),
    Case("STL of non-finite vertices", render_part("{d}/n.stl"),
         bad("{d}/n.stl: STL data has non-finite vertex coordinates"),
         lambda folder: (folder / "n.stl").write_bytes(
             b"\0" * 80 + struct.pack("<I", 1) + struct.pack("<12fH", *[math.nan] * 12, 0))),
    Case("ASCII STL that is not ASCII", render_part("{d}/a.stl"), bad("{d}/a.stl", "solid"),
         _write("a.stl", b"solid x\n\xff\xfe facet")),
    # holes.csv
    Case("empty holes.csv file", validate_part("{d}/e.csv"),
         bad("{d}/e.csv is empty; a hole table starts with the header"), _write("e.csv", "")),
    Case("holes.csv of other columns", validate_part("{d}/e.csv"),
         bad("{d}/e.csv: the header is 'a,b,c'", CSV_COLUMNS), _write("e.csv", "a,b,c\n1,2,3\n")),
    Case("holes.csv in UTF-16", validate_part("{d}/e.csv"),
         bad("hole table {d}/e.csv is not UTF-8 text"),
         lambda folder: (folder / "e.csv").write_bytes(
             (folder / "holes.csv").read_text().encode("utf-16"))),
    Case("holes.csv NaN", render_part("{d}/edit.csv"),
         bad("{d}/edit.csv line 2: axis_y = 'nan'; allowed: a finite number"),
         _first_row(6, "nan")),
    Case("holes.csv text for a number", render_part("{d}/edit.csv"),
         bad("{d}/edit.csv line 2: x_mm = 'wide' is not a number"), _first_row(2, "wide")),
    Case("holes.csv short line", render_part("{d}/edit.csv"),
         bad("{d}/edit.csv line 2 has 1 fields; every line needs 7"),
         _edited_csv(lambda lines: [lines[0], lines[1].split(",")[0], *lines[2:]])),
    Case("holes.csv a cell twice", render_part("{d}/edit.csv"),
         bad("cell (0, 0) is listed again (first on line 2)"),
         _edited_csv(lambda lines: [*lines, lines[1]])),
    Case("holes.csv axis 1e300", render_part("{d}/edit.csv"),
         bad("{d}/edit.csv: the holes cannot be built into a plate"), _first_row(6, "1e300")),
    Case("holes.csv with a byte-order mark (spreadsheet)", render_part("{d}/edit.csv"), VIEW_PNG,
         _edited_csv(lambda lines: ["\ufeff" + lines[0], *lines[1:]])),
    Case("holes.csv with CRLF lines", render_part("{d}/edit.csv"), VIEW_PNG,
         lambda folder: (folder / "edit.csv").write_bytes(
             (folder / "holes.csv").read_bytes().replace(b"\n", b"\r\n"))),
    Case("holes.csv without holes", validate_part("{d}/empty.csv"),
         bad("no holes found in {d}/empty.csv"), _empty_csv),
    # export of what is no design.npz (export reads design.npz only)
    Case("export an STL", ["export", "{d}/plate.stl", "--out", "{d}/x/"],
         bad("{d}/plate.stl: not a design.npz written by `aperture-fab design`",
             "not a whole .npz archive")),
    Case("export a holes.csv", ["export", "{d}/holes.csv", "--out", "{d}/x/"],
         bad("{d}/holes.csv: not a design.npz")),
    Case("export a 3MF (a zip of other files)", ["export", "{d}/plate.3mf", "--out", "{d}/x/"],
         bad("{d}/plate.3mf: not a design.npz", "the magic string is not correct")),
    Case("export a corrupt 3MF", ["export", "{d}/bad.3mf", "--out", "{d}/x/"],
         bad("{d}/bad.3mf: not a design.npz"), _write("bad.3mf", b"PK\x03\x04garbage")),
    Case("export a folder", ["export", "{d}", "--out", "{d}/x/"],
         bad("{d}: not a design.npz", "Is a directory")),
    Case("export a missing design", ["export", "{d}/none.npz", "--out", "{d}/x/"],
         bad("{d}/none.npz: not a design.npz", "No such file")),
    Case("export a design without its design.toml", ["export", "{d}/design.npz", "--out",
                                                     "{d}/x/"],
         bad("{d}/design.toml: cannot read the design's config", "give it with --config"),
         _moved("design.toml")),
    # assembly
    Case("assembly of a missing folder", ["assembly", "{d}/none"],
         bad("design folder {d}/none does not exist or is not a folder")),
    Case("assembly of a file", ["assembly", "{d}/marker.png"],
         bad("design folder {d}/marker.png does not exist or is not a folder")),
    Case("assembly of a folder without design.npz", ["assembly", "{d}"],
         bad("{d} is not a design folder: it lacks design.npz"), _moved("design.npz")),
    Case("assembly to another name", ["assembly", "{d}", "--out", "{d}/sheet.html"],
         Works(files("sheet.html"))),
]


@pytest.mark.parametrize(("setup", "argv", "outcome"), params(PARTS))
def test_part_file(folder: Path, capsys: pytest.CaptureFixture[str], setup: Setup,
                   argv: list[str], outcome: Outcome) -> None:
    setup(folder)
    judge(argv, folder, capsys, outcome)


# -- hostile files ---------------------------------------------------------------------------


def _npz(name: str, arrays: dict[str, np.ndarray], **kwargs: Any) -> Setup:
    """design.npz's arrays with `arrays` replacing or adding some, as `name`."""
    def setup(folder: Path) -> None:
        with np.load(folder / "design.npz") as data:
            merged = {k: data[k] for k in data.files}
        merged.update(arrays)
        buffer = io.BytesIO()
        np.savez(buffer, **merged, **kwargs)
        (folder / name).write_bytes(buffer.getvalue())
    return setup


def _npz_declaring(name: str, shape: tuple[int, ...], deflated_mb: int = 0) -> Setup:
    """An .npz whose open_fraction.npy header declares `shape` (float64); its data is
    `deflated_mb` MB of zeros, deflated to kilobytes (a zip bomb), or none."""
    def setup(folder: Path) -> None:
        header = io.BytesIO()
        np.lib.format.write_array_header_1_0(
            header, {"descr": "<f8", "fortran_order": False, "shape": shape})
        with zipfile.ZipFile(folder / name, "w", compression=zipfile.ZIP_DEFLATED) as archive:
            with archive.open("open_fraction.npy", "w", force_zip64=True) as member:
                member.write(header.getvalue())
                for _ in range(deflated_mb):
                    member.write(bytes(1 << 20))
            archive.writestr("displays.npy", header.getvalue())
    return setup


class _Trap:
    """Pickled, it writes a file when unpickled: a design.npz must never run it."""

    def __reduce__(self) -> tuple[Any, ...]:
        return (Path.write_text, (Path(os.environ["APERTURE_TRAP"]), "ran"))


def _pickle_trap(folder: Path) -> None:
    os.environ["APERTURE_TRAP"] = str(folder / "trap-ran.txt")
    _npz("pickled.npz", {"names": np.array([_Trap()], dtype=object)})(folder)


def _trap_not_run(folder: Path) -> None:
    assert not (folder / "trap-ran.txt").exists()


def _text_bomb(folder: Path) -> None:
    """marker.png with a zTXt chunk that inflates to 100 MB."""
    data = (folder / "marker.png").read_bytes()
    at = data.index(b"IDAT") - 4
    bomb = _png_chunk(b"zTXt", b"Comment\x00\x00" + zlib.compress(b"A" * 100_000_000, 9))
    (folder / "z.png").write_bytes(data[:at] + bomb + data[at:])


def _threemf_bomb(folder: Path) -> None:
    with zipfile.ZipFile(folder / "bomb.3mf", "w", compression=zipfile.ZIP_DEFLATED) as archive:
        with archive.open("3D/3dmodel.model", "w", force_zip64=True) as member:
            for _ in range(64):
                member.write(bytes(1 << 20))


def _manifest_outside(folder: Path) -> None:
    """The folder's manifest names ../victim.txt, a file outside the folder."""
    (folder.parent / "victim.txt").write_text("keep me")
    manifest = json.loads((folder / "manifest.json").read_text())
    manifest["files"]["../victim.txt"] = {"sha256": "0" * 64, "size_bytes": 7}
    (folder / "manifest.json").write_text(json.dumps(manifest))


def _victim_kept(folder: Path) -> None:
    assert (folder.parent / "victim.txt").read_text() == "keep me"


HUGE = (1_000_000, 1_000_000)  # 7.3 TiB of float64

HOSTILE: list[Case] = [
    Case("design.npz declaring 7 TiB (export)", ["export", "{d}/huge.npz", "--out", "{d}/x/"],
         bad("{d}/huge.npz: its array open_fraction.npy declares shape (1000000, 1000000)",
             "more than any design holds"), _npz_declaring("huge.npz", HUGE)),
    Case("design.npz declaring 7 TiB (render)", render_part("{d}/design.npz"),
         bad("{d}/design.npz: its array open_fraction.npy declares shape"),
         _npz_declaring("design.npz", HUGE)),
    Case("design.npz declaring 7 TiB (validate)", validate_part("{d}/design.npz"),
         bad("declares shape (1000000, 1000000)"), _npz_declaring("design.npz", HUGE)),
    Case("design.npz declaring 2**62 x 2", ["export", "{d}/huge.npz", "--out", "{d}/x/"],
         bad("declares shape (4611686018427387904, 2)"), _npz_declaring("huge.npz", (2**62, 2))),
    Case("design.npz zip bomb (64 MB of zeros in kilobytes, 7 GB declared)",
         ["export", "{d}/bomb.npz", "--out", "{d}/x/"], bad("declares shape (30000, 30000)"),
         _npz_declaring("bomb.npz", (30_000, 30_000), deflated_mb=64)),
    Case("design.npz with a pickled object (never run)",
         ["export", "{d}/pickled.npz", "--out", "{d}/x/"],
         Refused(EXIT_BAD_INPUT, ("{d}/pickled.npz: not a design.npz",)), _pickle_trap),
    Case("design.npz open fractions NaN", ["export", "{d}/nan.npz", "--out", "{d}/x/"],
         bad("open_fraction holds values from nan", "allowed: finite values from 0 to 1"),
         _npz("nan.npz", {"open_fraction": np.full((16, 16), np.nan)})),
    Case("design.npz open fractions negative", ["export", "{d}/neg.npz", "--out", "{d}/x/"],
         bad("open_fraction holds values from -1"),
         _npz("neg.npz", {"open_fraction": np.full((16, 16), -1.0)})),
    Case("design.npz of one dimension", ["export", "{d}/flat.npz", "--out", "{d}/x/"],
         bad("open_fraction has shape (256,)", "expected (rows, cols)"),
         _npz("flat.npz", {"open_fraction": np.full(256, 0.1)})),
    Case("design.npz of another grid", ["export", "{d}/other.npz", "--out", "{d}/x/"],
         bad("open_fraction has shape (8, 8)"),
         _npz("other.npz", {"open_fraction": np.full((8, 8), 0.1)})),
    Case("design.npz without its displays", ["export", "{d}/nodisp.npz", "--out", "{d}/x/"],
         bad("{d}/nodisp.npz: not a design.npz", "displays"),
         lambda folder: _strip_npz(folder, "displays", "nodisp.npz")),
    Case("design.npz linked to /etc/hostname", ["export", "{d}/l.npz", "--out", "{d}/x/"],
         bad("{d}/l.npz: not a design.npz"),
         lambda folder: (folder / "l.npz").symlink_to("/etc/hostname")),
    Case("PNG whose text chunk inflates to 100 MB", render_of("{d}/z.png"),
         bad("{d}/z.png: looks like a PNG file but cannot be read", "MAX_TEXT_CHUNK"),
         _text_bomb),
    Case("3MF zip bomb given to validate (never opened)", validate_part("{d}/bomb.3mf"),
         bad("part {d}/bomb.3mf: .3mf is not a part file"), _threemf_bomb),
    Case("manifest naming ../victim.txt (render refuses, victim kept)",
         render_part("{d}/design.npz"), bad("does not match its manifest.json"),
         _manifest_outside),
    Case("manifest naming ../victim.txt (assembly refuses, victim kept)",
         ["assembly", "{d}", "--out", "{d}/sheet.html"], bad("does not match its manifest.json"),
         _manifest_outside),
    Case("manifest that is not JSON", render_part("{d}/design.npz"),
         bad("{d}/manifest.json: not a manifest written by aperture-fab",
             "delete {d}/manifest.json"), _write("manifest.json", "{not json")),
    Case("manifest of a publish that never finished", render_part("{d}/design.npz"),
         bad("the run stopped while publishing its files"),
         lambda folder: (folder / "manifest.json").write_text(json.dumps(
             {**json.loads((folder / "manifest.json").read_text()), "complete": False}))),
    Case("design.npz changed after the design (render)", render_part("{d}/design.npz"),
         bad("design.npz differs from the file the run wrote"),
         lambda folder: _npz("design.npz", {"loss_history": np.zeros(3)})(folder)),
    Case("design over a manifest naming ../victim.txt (victim kept)",
         [*DESIGN[:5], "{d}", "--no-validate", "--iterations", "2", "--force"],
         Works(_victim_kept), _manifest_outside, slow=True),
]


def _strip_npz(folder: Path, key: str, name: str) -> None:
    with np.load(folder / "design.npz") as data:
        kept = {k: data[k] for k in data.files if k != key}
    buffer = io.BytesIO()
    np.savez(buffer, **kept)
    (folder / name).write_bytes(buffer.getvalue())


@pytest.mark.parametrize(("setup", "argv", "outcome"), params(HOSTILE))
def test_hostile_file(folder: Path, capsys: pytest.CaptureFixture[str], setup: Setup,
                      argv: list[str], outcome: Outcome) -> None:
    setup(folder)
    judge(argv, folder, capsys, outcome)
    _trap_not_run(folder)
    if (folder.parent / "victim.txt").exists():
        _victim_kept(folder)


# -- the environment: the disk, permissions, missing packages --------------------------------
# Each fault is a monkeypatch (setup(folder, monkeypatch)): the machine cannot be made to fill
# its disk or, as root, to deny a write.

Fault = Callable[[Path, pytest.MonkeyPatch], None]


def _fsync_fails(code: int) -> Fault:
    """Every fsync (write_atomic's last step before the rename) fails with errno `code`."""
    def fault(folder: Path, monkeypatch: pytest.MonkeyPatch) -> None:
        def fail(fd: int) -> None:
            raise OSError(code, os.strerror(code))
        monkeypatch.setattr(os, "fsync", fail)
    return fault


def _temp_open_fails(code: int) -> Fault:
    """Creating write_atomic's temporary file fails with errno `code` (a read-only disk, no
    permission)."""
    def fault(folder: Path, monkeypatch: pytest.MonkeyPatch) -> None:
        real_open = os.open

        def refuse(path: Any, flags: int, *args: Any, **kwargs: Any) -> int:
            if str(path).endswith(".tmp"):
                raise OSError(code, os.strerror(code), str(path))
            return real_open(path, flags, *args, **kwargs)
        monkeypatch.setattr(os, "open", refuse)
    return fault


def _mkdir_denied(folder: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def deny(self: Path, *args: Any, **kwargs: Any) -> None:
        raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(self))
    monkeypatch.setattr(Path, "mkdir", deny)


def _not_writable(folder: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """os.access says no folder is writable (a read-only folder, as root cannot be made)."""
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda path, mode, *a, **k: False if mode == os.W_OK
                        else real_access(path, mode, *a, **k))


def _target_read_fails(folder: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Reading a target image fails with EIO (a failing disk or network share)."""
    real_fdopen = os.fdopen

    def failing(fd: int, mode: str = "r", *args: Any, **kwargs: Any) -> Any:
        if mode == "rb":
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        return real_fdopen(fd, mode, *args, **kwargs)
    monkeypatch.setattr(os, "fdopen", failing)


def _without(*packages: str) -> Fault:
    """The packages cannot be imported (an optional extra not installed)."""
    def fault(folder: Path, monkeypatch: pytest.MonkeyPatch) -> None:
        for name in list(sys.modules):
            if name.split(".")[0] in packages:
                monkeypatch.delitem(sys.modules, name)
        for package in packages:
            monkeypatch.setitem(sys.modules, package, None)
    return fault


def _nothing_written(name: str) -> Callable[[Path], None]:
    """No file `name`, and no file in it when it is a folder (one made empty may stay)."""
    def check(folder: Path) -> None:
        path = folder / name
        empty_folder = path.is_dir() and not any(p.is_file() for p in path.rglob("*"))
        assert empty_folder or not path.exists(), name
    return check


DISK_FULL = "No space left on device; the disk is full: free some space, or give --out on " \
    "another disk"

ENVIRONMENT: list[Case] = [
    Case("disk full (render)", RENDER, unwritable("--out {d}/v.png", DISK_FULL),
         _fsync_fails(errno.ENOSPC)),
    Case("disk full (display)", [*DISPLAY, *EYE], unwritable("{d}/f.png", "the disk is full"),
         _fsync_fails(errno.ENOSPC)),
    Case("disk full (export, one file)", [*EXPORT, "--out", "{d}/x/p.svg"],
         unwritable("{d}/x/p.svg", "the disk is full"), _fsync_fails(errno.ENOSPC)),
    Case("disk full (assembly)", ["assembly", "{d}", "--out", "{d}/sheet.html"],
         unwritable("{d}/sheet.html", "the disk is full"), _fsync_fails(errno.ENOSPC)),
    Case("quota used up (render)", RENDER, unwritable("{d}/v.png", "the disk quota is used up"),
         _fsync_fails(errno.EDQUOT)),
    Case("disk full (design: the set is not published)",
         [*DESIGN, "--iterations", "2"], unwritable("the disk is full"),
         _fsync_fails(errno.ENOSPC), slow=True),
    Case("read-only file system (render)", RENDER,
         unwritable("{d}/v.png", "the file system is read-only: choose an --out on a writable "
                    "disk"), _temp_open_fails(errno.EROFS)),
    Case("read-only file system (export)", [*EXPORT, "--out", "{d}/x/"],
         unwritable("the file system is read-only"), _temp_open_fails(errno.EROFS)),
    Case("no permission (display)", [*DISPLAY, *EYE], unwritable("{d}/f.png", "no permission"),
         _temp_open_fails(errno.EACCES)),
    Case("no permission to create the output folder (design)", DESIGN,
         bad("cannot create the output folder {d}/run: Permission denied", "choose another "
             "--out"), _mkdir_denied),
    Case("output folder not writable (export)", [*EXPORT, "--out", "{d}/x/"],
         bad("the output folder {d}/x is not writable; choose another --out"), _not_writable),
    Case("the target cannot be read (I/O error)", render_of("{d}/marker.png"),
         bad("cannot read target image {d}/marker.png: Input/output error"),
         _target_read_fails),
    Case("STEP without its extra (OCP)", [*EXPORT, "--out", "{d}/x.step"],
         usage("STEP export needs OCCT's Python bindings: pip install cadquery-ocp"),
         _without("OCP")),
    Case("3MF without lxml", [*EXPORT, "--out", "{d}/x.3mf"],
         usage("threemf_bytes needs the lxml package: pip install lxml"), _without("lxml")),
    Case("DXF without ezdxf", [*EXPORT, "--out", "{d}/x.dxf"],
         usage("dxf_bytes needs the ezdxf package: pip install ezdxf"), _without("ezdxf")),
    Case("mesh re-trace without embreex", [*RENDER, "--mesh"],
         usage("needs the embreex package (Embree): pip install embreex"), _without("embreex")),
    Case("STL export needs no optional package", [*EXPORT, "--out", "{d}/x.stl"],
         Works(files("x.stl")), _without("OCP", "lxml", "ezdxf", "embreex", "ray")),
    Case("design --step without OCP", [*DESIGN, "--iterations", "2", "--step"],
         usage("STEP export needs OCCT's Python bindings"), _without("OCP"), slow=True),
]


@pytest.mark.parametrize(("setup", "argv", "outcome"), params(ENVIRONMENT))
def test_environment(folder: Path, capsys: pytest.CaptureFixture[str],
                     monkeypatch: pytest.MonkeyPatch, setup: Fault, argv: list[str],
                     outcome: Outcome) -> None:
    setup(folder, monkeypatch)
    judge(argv, folder, capsys, outcome)
    monkeypatch.undo()
    if isinstance(outcome, Refused):
        _set_unchanged(folder)  # the design's own set is still whole
        for name in ("v.png", "f.png", "sheet.html", "x", "run/manifest.json"):
            _nothing_written(name)(folder)


# -- interrupts ------------------------------------------------------------------------------
# Ctrl-C in-process (KeyboardInterrupt raised where the work is): exit 130, one "interrupted"
# line naming the command, no file half-written. Real signals to a real process are below.


def _interrupt(where: str) -> Fault:
    """Raise KeyboardInterrupt when module.function `where` is called."""
    module_name, _, function = where.rpartition(".")

    def fault(folder: Path, monkeypatch: pytest.MonkeyPatch) -> None:
        import importlib

        def interrupted(*args: Any, **kwargs: Any) -> None:
            raise KeyboardInterrupt
        monkeypatch.setattr(importlib.import_module(module_name), function, interrupted)
    return fault


def _interrupt_design(folder: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from conftest import interrupt_at_call

    interrupt_at_call(monkeypatch, 2)


def _rename_interrupted(folder: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Ctrl-C inside write_atomic, the data written but not yet renamed into place."""
    def interrupted(source: Any, target: Any) -> None:
        raise KeyboardInterrupt
    monkeypatch.setattr(os, "replace", interrupted)


class Interrupt(NamedTuple):
    id: str
    argv: list[str]
    fault: Fault
    absent: tuple[str, ...]  # outputs that must not exist afterwards
    slow: bool = False


INTERRUPTS: list[Interrupt] = [
    Interrupt("render, while writing", RENDER,
              _interrupt("aperture_fab.pipeline.render_job.write_atomic"), ("v.png",)),
    Interrupt("render, inside write_atomic (before the rename)", RENDER, _rename_interrupted,
              ("v.png",)),
    Interrupt("display, while solving", [*DISPLAY, *EYE],
              _interrupt("aperture_fab.optimize.tracking.tracked_views"), ("f.png",)),
    Interrupt("export, inside write_atomic", [*EXPORT, "--out", "{d}/x/p.stl"],
              _rename_interrupted, ("x/p.stl",)),
    Interrupt("assembly, while writing", ["assembly", "{d}", "--out", "{d}/sheet.html"],
              _interrupt("aperture_fab.pipeline.assembly_job.write_atomic"), ("sheet.html",)),
    Interrupt("validate, while validating", [*VALIDATE, *FAST, "--out", "{d}/check"],
              _interrupt("aperture_fab.pipeline.validate_job.validate"),
              ("check/manifest.json",)),
    Interrupt("design, while optimizing (checkpoint saved)", [*DESIGN, "--iterations", "50"],
              _interrupt_design, ("run/manifest.json",), slow=True),
]


@pytest.mark.parametrize("case", [pytest.param(c, id=c.id, marks=[pytest.mark.slow] if c.slow
                                               else []) for c in INTERRUPTS])
def test_ctrl_c(folder: Path, capsys: pytest.CaptureFixture[str],
                monkeypatch: pytest.MonkeyPatch, case: Interrupt) -> None:
    case.fault(folder, monkeypatch)
    with deadline(CASE_DEADLINE_S):
        code = run(case.argv, folder)
    monkeypatch.undo()
    err = capsys.readouterr().err
    command = case.argv[0]
    assert code == EXIT_INTERRUPTED, err
    assert "Traceback" not in err and not ERROR_LINE.findall(err), err
    assert f"interrupted (Ctrl-C) during `{command}`" in err or (
        command == "design" and "checkpoint saved" in err and "--resume" in err), err
    assert not leftovers(folder), leftovers(folder)
    for name in case.absent:
        assert not (folder / name).exists(), name
    _set_unchanged(folder)
    if command == "design":
        assert (folder / "run" / "checkpoint.pt").is_file()


# -- real signals and concurrent runs (subprocesses) -----------------------------------------

#: Iterations of a design that a signal interrupts: enough to be still optimizing when the
#: signal comes (right after the first checkpoint), few enough to resume quickly.
SIGNAL_ITERATIONS = 60
#: How long to wait for a child to reach the point where it is signalled, or to end.
CHILD_TIMEOUT_S = 180


def _design_child(folder: Path, out: Path, *flags: str) -> subprocess.Popen[str]:
    """`aperture-fab design` in a child process on the tiny config, checkpointing every
    iteration (sig.toml)."""
    (folder / "sig.toml").write_text(
        TINY_TOML.replace("[optimizer]\n", "[optimizer]\ncheckpoint_every = 1\n"))
    return subprocess.Popen(
        [sys.executable, "-m", "aperture_fab.cli", "design", str(folder / "marker.png"),
         "--config", str(folder / "sig.toml"), "--out", str(out), "--no-validate", "-q",
         "--iterations", str(SIGNAL_ITERATIONS), *flags],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
        env={**os.environ, "OMP_NUM_THREADS": "1"})


def _when_checkpointed(child: subprocess.Popen[str], out: Path) -> None:
    """Wait until the child has written its first checkpoint (it is optimizing)."""
    waited = time.monotonic() + CHILD_TIMEOUT_S
    while not (out / "checkpoint.pt").is_file():
        if child.poll() is not None:
            raise AssertionError(f"the child ended first: {child.communicate()}")
        assert time.monotonic() < waited, "no checkpoint in time"
        time.sleep(0.02)


@pytest.mark.slow
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM, signal.SIGKILL],
                         ids=["SIGINT", "SIGTERM", "SIGKILL"])
def test_a_signal_while_designing_leaves_the_folder_whole(folder: Path,
                                                          signum: signal.Signals) -> None:
    """A design replacing the one in `folder` (--force) gets the signal while optimizing: the
    folder is still the old set, whole; SIGINT and SIGTERM say so and save a checkpoint that
    --resume finishes; after SIGKILL the next run cleans up and publishes its set."""
    from aperture_fab.io.manifest import check_folder

    old = json.loads((folder / "manifest.json").read_text())["files"]
    child = _design_child(folder, folder, "--force")
    try:
        _when_checkpointed(child, folder)
        child.send_signal(signum)
        _, err = child.communicate(timeout=CHILD_TIMEOUT_S)
    finally:
        child.kill()
    assert "Traceback" not in err, err
    check_folder(folder)
    assert json.loads((folder / "manifest.json").read_text())["files"] == old
    if signum in (signal.SIGINT, signal.SIGTERM):
        assert child.returncode in ((EXIT_INTERRUPTED, -signal.SIGINT) if signum == signal.SIGINT
                                    else (EXIT_TERMINATED,)), err
        assert "checkpoint saved" in err and "--resume" in err, err
        assert run(["design", "{d}/marker.png", "--config", "{d}/sig.toml", "--out", "{d}",
                    "--no-validate", "-q", "--iterations", str(SIGNAL_ITERATIONS), "--force",
                    "--resume"], folder) == EXIT_OK
    else:
        assert child.returncode == -signum, err
        assert run(["design", "{d}/marker.png", "--config", "{d}/sig.toml", "--out", "{d}",
                    "--no-validate", "-q", "--iterations", "2", "--force"], folder) == EXIT_OK
    check_folder(folder)
    assert not list(folder.glob(".staging-*")) and not leftovers(folder)
    assert not (folder / "checkpoint.pt").exists()


@pytest.mark.slow
def test_two_designs_into_one_folder_at_once_leave_one_whole_set(inputs: Path) -> None:
    """Two runs publish one after the other (the publish lock): the folder is one run's set."""
    from aperture_fab.io.manifest import check_folder

    out = inputs / "shared"
    children = [_design_child(inputs, out, "--seed", str(seed)) for seed in (1, 2)]
    results = [child.communicate(timeout=CHILD_TIMEOUT_S) for child in children]
    for child, (_, err) in zip(children, results, strict=True):
        assert "Traceback" not in err, err
        assert child.returncode in (EXIT_OK, EXIT_BAD_INPUT), err
        if child.returncode == EXIT_BAD_INPUT:  # refused, saying why
            assert "aperture-fab: error:" in err and str(out) in err, err
    assert any(child.returncode == EXIT_OK for child in children)
    check_folder(out)
    command = json.loads((out / "manifest.json").read_text())["command"]
    assert command[-1] in ("1", "2")  # the seed of the run whose set it is
    assert not list(out.glob(".staging-*")) and not leftovers(out)


@pytest.mark.slow
def test_two_exports_into_one_folder_at_once_write_whole_files(folder: Path) -> None:
    """export writes each file atomically: whatever the order, every file is whole."""
    from aperture_fab.io.formats import read_stl

    children = [subprocess.Popen(
        [sys.executable, "-m", "aperture_fab.cli", "export", str(folder / "design.npz"),
         "--out", str(folder / "both"), "-q"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True, cwd=ROOT, env={**os.environ, "OMP_NUM_THREADS": "1"}) for _ in range(2)]
    for child in children:
        _, err = child.communicate(timeout=CHILD_TIMEOUT_S)
        assert child.returncode == EXIT_OK and "Traceback" not in err, err
    assert read_stl((folder / "both" / "plate.stl").read_bytes()).faces.size
    with zipfile.ZipFile(folder / "both" / "plate.3mf") as archive:
        assert archive.testzip() is None
    assert not leftovers(folder)
