"""The bad-input catalogue (issue 10): each bad input or fault, run through the command line,
gives one clear line (naming the input, the value, what is allowed and the fix) and its own
exit status, never a traceback or a silent wrong result.

A row is (id, setup, argv, exit status, fragment of the message). setup(folder) writes the bad
input into a private copy of a tiny design's folder; "{d}" in argv is that folder.
"""

from __future__ import annotations

import errno
import io
import os
import shutil
import signal
import subprocess
import sys
import time
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from aperture_fab.cli import (
    EXIT_BAD_INPUT,
    EXIT_CANNOT_WRITE,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_USAGE,
    main,
)
from aperture_fab.config.presets import PHOTOMASK_EMULSION_MM
from aperture_fab.fabrication.mesh import PlateMesh
from aperture_fab.io.formats import stl_bytes
from aperture_fab.io.images import encode_png

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
    import aperture_fab.pipeline.design_job as design_job

    def interrupted(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(design_job, "write_part", interrupted)
    assert run(["export", "{d}/design.npz", "--out", "{d}/x"], folder) == EXIT_INTERRUPTED
    err = capsys.readouterr().err
    assert "interrupted (Ctrl-C) during `export`" in err and "Traceback" not in err


@pytest.mark.slow
def test_ctrl_c_during_validation_exits_130(folder: Path) -> None:
    """A real SIGINT to a running `validate`, sent once it says validation has started."""
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
    child.send_signal(signal.SIGINT)
    _, rest = child.communicate(timeout=120)
    err = "".join(lines) + rest
    # 130, or killed by SIGINT (-2), which a shell reports as 130 too: CPython re-sends SIGINT
    # to itself at exit when the Ctrl-C landed inside exec'd code (e.g. a module import).
    assert child.returncode in (EXIT_INTERRUPTED, -signal.SIGINT), err
    assert "interrupted (Ctrl-C) during `validate`" in err and "Traceback" not in err


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
