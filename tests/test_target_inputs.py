"""Target images as inputs (issue 21, item 6): transparency (--alpha), another aspect than the
display's (--fit), animations (--frame), float images read by their range, and files that are
not regular files (a FIFO must be refused at once, never read)."""

from __future__ import annotations

import io
import os
import socket
import subprocess
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image

from aperture_fab import cli
from aperture_fab.cli import flags
from aperture_fab.io.decode import decode_image
from aperture_fab.io.files import load_targets
from aperture_fab.io.images import (
    ALPHA_BACKGROUNDS,
    TARGET_FITS,
    TargetOptions,
    TargetWarning,
    encode_png,
    fit_target,
    prepare_targets,
    resample,
    srgb_to_linear,
)

ROOT = Path(__file__).resolve().parents[1]
#: A refusal is immediate; a hang (reading a FIFO blocks until a writer comes) fails here.
HANG_S = 20
#: The CLI in a child process imports torch first: allow for a loaded machine.
CLI_HANG_S = 120


def saved(image: Image.Image, fmt: str = "PNG", **options: object) -> bytes:
    buffer = io.BytesIO()
    image.save(buffer, format=fmt, **options)
    return buffer.getvalue()


def lin(code: int | np.ndarray) -> np.ndarray:
    """Linear value of 8-bit sRGB codes."""
    return srgb_to_linear(np.asarray(code, dtype=np.float64) / 255)


def target_warnings(record: list[warnings.WarningMessage]) -> list[str]:
    return [str(w.message) for w in record if issubclass(w.category, TargetWarning)]


# --- --alpha -----------------------------------------------------------------------------------

#: Opaque red, fully transparent blue, half-covered white, a quarter-covered grey.
RGBA = np.array([[[255, 0, 0, 255], [0, 0, 255, 0], [255, 255, 255, 128], [100, 100, 100, 64]]],
                dtype=np.uint8)


@pytest.mark.parametrize("alpha", [None, "black", "white"])
def test_transparency_is_composited_on_the_background_in_linear_light(alpha: str | None) -> None:
    background = 1.0 if alpha == "white" else 0.0
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        decoded = decode_image(saved(Image.fromarray(RGBA, "RGBA")), "sprite.png",
                               alpha=alpha)  # type: ignore[arg-type]
    np.testing.assert_allclose(decoded[:, 0, 0], [1.0, 0.0, 0.0], atol=1e-12)  # opaque: as is
    np.testing.assert_allclose(decoded[:, 0, 1], background, atol=1e-12)  # the background only
    coverage = np.array([128, 64]) / 255
    expected = lin(np.array([255, 100])) * coverage + background * (1 - coverage)
    np.testing.assert_allclose(decoded[:, 0, 2], expected[0], atol=1e-12)
    np.testing.assert_allclose(decoded[:, 0, 3], expected[1], atol=1e-12)
    said = target_warnings(record)
    if alpha is None:  # the default, black, is said: naming the file, the share and the flag
        assert len(said) == 1
        assert "sprite.png" in said[0] and "75.0% of its pixels" in said[0]
        assert "composited on black" in said[0] and "--alpha white" in said[0]
    else:  # chosen: nothing to say
        assert said == []


def test_alpha_refuse_refuses_transparency_naming_the_file_and_the_fix() -> None:
    with pytest.raises(ValueError, match=r"sprite\.png: the image is transparent or partly "
                       r"transparent in 75\.0% of its pixels.*--alpha refuse: none.*"
                       r"--alpha black or --alpha white"):
        decode_image(saved(Image.fromarray(RGBA, "RGBA")), "sprite.png", alpha="refuse")


@pytest.mark.parametrize("alpha", ALPHA_BACKGROUNDS)
def test_an_opaque_alpha_channel_is_neither_warned_nor_refused(alpha: str) -> None:
    pixels = RGBA.copy()
    pixels[..., 3] = 255
    with warnings.catch_warnings():
        warnings.simplefilter("error", TargetWarning)
        decoded = decode_image(saved(Image.fromarray(pixels, "RGBA")), "opaque.png",
                               alpha=alpha)  # type: ignore[arg-type]
    np.testing.assert_allclose(decoded[:, 0, 1], [0.0, 0.0, 1.0], atol=1e-12)


def test_palette_transparency_on_white() -> None:
    image = Image.new("P", (2, 1))
    image.putpalette([0, 0, 255, 255, 0, 0])
    image.putpixel((1, 0), 1)
    decoded = decode_image(saved(image, transparency=0), "keyed.png", alpha="white")
    np.testing.assert_allclose(decoded[:, 0, 0], 1.0, atol=1e-12)
    np.testing.assert_allclose(decoded[:, 0, 1], [1.0, 0.0, 0.0], atol=1e-12)


@pytest.mark.parametrize("bad", ["grey", "", "BLACK"])
def test_an_unknown_alpha_is_refused(bad: str) -> None:
    with pytest.raises(ValueError, match=r"--alpha .* is not allowed; choose one of black, "
                       "white, refuse"):
        TargetOptions(alpha=bad)  # type: ignore[arg-type]


# --- --fit -------------------------------------------------------------------------------------

def wide_target(width: int = 640, height: int = 480) -> np.ndarray:
    """(3, height, width): a horizontal ramp in red, a vertical one in green, blue 0.5."""
    x = (np.arange(width) + 0.5) / width
    y = (np.arange(height) + 0.5) / height
    return np.stack([np.broadcast_to(x, (height, width)),
                     np.broadcast_to(y[:, None], (height, width)),
                     np.full((height, width), 0.5)])


def test_fit_pad_letterboxes_a_wide_target_centred_on_black() -> None:
    image = wide_target()
    padded = fit_target(image, (32, 32), "pad")
    assert padded.shape == (3, 640, 640)
    np.testing.assert_array_equal(padded[:, 80:560], image)  # every pixel kept, centred
    assert not padded[:, :80].any() and not padded[:, 560:].any()  # black bars


def test_fit_crop_keeps_the_centre_of_a_wide_target() -> None:
    image = wide_target()
    cropped = fit_target(image, (32, 32), "crop")
    assert cropped.shape == (3, 480, 480)
    np.testing.assert_array_equal(cropped, image[:, :, 80:560])


def test_fit_stretch_keeps_the_target_and_the_stretch_is_warned() -> None:
    image = wide_target()
    assert fit_target(image, (32, 32), "stretch") is not None
    np.testing.assert_array_equal(fit_target(image, (32, 32), "stretch"), image)
    with pytest.warns(TargetWarning, match=r"640 x 480 pixels.*stretched to fit \(--fit stretch, "
                      r"the default\).*--fit pad.*--fit crop"):
        prepare_targets([image], (16, 16), (32, 32), names=["wide.png"])


@pytest.mark.parametrize(("size", "display", "pad", "crop"), [
    ((480, 640), (32, 32), (640, 640), (480, 480)),  # portrait on a square display: pillarbox
    ((640, 640), (40, 30), (853, 640), (640, 480)),  # square on a 4:3 display
    ((300, 200), (30, 20), (300, 200), (300, 200)),  # already the display's aspect: as it is
])
def test_fit_gives_the_display_s_aspect(size: tuple[int, int], display: tuple[int, int],
                                        pad: tuple[int, int], crop: tuple[int, int]) -> None:
    image = wide_target(*size)
    for fit, expected in (("pad", pad), ("crop", crop)):
        fitted = fit_target(image, display, fit)  # type: ignore[arg-type]
        assert fitted.shape[1:] == (expected[1], expected[0]), fit
        assert abs(fitted.shape[2] / fitted.shape[1] / (display[0] / display[1]) - 1) < 0.01


@pytest.mark.parametrize("fit", TARGET_FITS)
def test_a_640_by_480_file_on_a_square_display_with_each_fit(tmp_path: Path, fit: str) -> None:
    """Through load_targets and prepare_targets, as the design, validate and render jobs do:
    the shapes on the display grid and where the content lands."""
    image = wide_target()
    path = tmp_path / "wide.png"
    path.write_bytes(encode_png(image))
    display, view = (32, 32), (16, 16)
    images, names = load_targets([path], display, TargetOptions(fit=fit))  # type: ignore[arg-type]
    assert names == ["wide"]
    loaded = load_targets([path])[0][0]  # as the file holds it, to 8-bit precision
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        on_view, on_display = prepare_targets(images, view, display, names=[str(path)])
    assert on_view.shape == (1, 3, 16, 16) and on_display.shape == (1, 3, 32, 32)
    shown = on_display[0]
    stretched = [m for m in target_warnings(record) if "stretched" in m]
    if fit == "stretch":
        assert images[0].shape == (3, 480, 640) and len(stretched) == 1
        np.testing.assert_allclose(shown, resample(loaded, display), atol=1e-12)
    elif fit == "pad":
        # 640 x 640 padded onto 32 x 32: 20 file rows a display row, the bars 80 rows = 4 rows.
        assert images[0].shape == (3, 640, 640) and stretched == []
        assert not shown[:, :4].any() and not shown[:, 28:].any()
        np.testing.assert_allclose(shown[:, 4:28], resample(loaded, (32, 24)), atol=1e-12)
        np.testing.assert_allclose(shown[2, 4:28], 0.5, atol=0.01)  # the content, not the bars
    else:
        # The centre 480 x 480: the red ramp spans 80/640 to 560/640 across the display.
        assert images[0].shape == (3, 480, 480) and stretched == []
        np.testing.assert_allclose(shown, resample(loaded[:, :, 80:560], display), atol=1e-12)
        assert shown[0, 16, 0] == pytest.approx(0.125 + 0.75 / 64, abs=0.01)
        assert shown[0, 16, -1] == pytest.approx(0.875 - 0.75 / 64, abs=0.01)


def test_a_fit_other_than_stretch_needs_the_display(tmp_path: Path) -> None:
    path = tmp_path / "wide.png"
    path.write_bytes(encode_png(wide_target(64, 48)))
    with pytest.raises(ValueError, match="--fit pad needs the display's pixel count"):
        load_targets([path], None, TargetOptions(fit="pad"))


# --- --frame -----------------------------------------------------------------------------------

GIF_LEVELS = (10, 128, 250)


def animated_gif() -> bytes:
    """Three 16 x 16 grey frames, each one level of GIF_LEVELS."""
    frames = [Image.new("L", (16, 16), level) for level in GIF_LEVELS]
    return saved(frames[0], "GIF", save_all=True, append_images=frames[1:], duration=100,
                 loop=0)


def test_an_animation_gives_its_first_frame_with_a_warning() -> None:
    with pytest.warns(TargetWarning, match=r"anim\.gif is an animation \(or a multi-page file\) "
                      r"of 3 frames; the first \(--frame 0\) is used. Give --frame N \(0 to 2\)"):
        decoded = decode_image(animated_gif(), "anim.gif")
    assert decoded.shape == (3, 16, 16)
    np.testing.assert_allclose(decoded, lin(GIF_LEVELS[0]), atol=1e-12)


@pytest.mark.parametrize("frame", [0, 1, 2])
def test_frame_chooses_a_frame_without_a_warning(frame: int) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error", TargetWarning)
        decoded = decode_image(animated_gif(), "anim.gif", frame=frame)
    np.testing.assert_allclose(decoded, lin(GIF_LEVELS[frame]), atol=1e-12)


def test_frame_through_load_targets(tmp_path: Path) -> None:
    path = tmp_path / "anim.gif"
    path.write_bytes(animated_gif())
    images, _ = load_targets([path], (32, 32), TargetOptions(frame=2))
    np.testing.assert_allclose(images[0], lin(GIF_LEVELS[2]), atol=1e-12)


@pytest.mark.parametrize(("data", "frame", "count"), [
    (animated_gif(), 3, 3),
    (saved(Image.new("L", (16, 16), 128)), 1, 1),  # a still image has frame 0 only
])
def test_a_frame_out_of_range_is_refused(data: bytes, frame: int, count: int) -> None:
    with pytest.raises(ValueError, match=rf"x\.img: --frame {frame} is out of range; the file has "
                       rf"{count} frame\(s\), numbered 0 to {count - 1}"):
        decode_image(data, "x.img", frame=frame)


@pytest.mark.parametrize("bad", [-1, 1.5, True])
def test_a_bad_frame_is_refused(bad: object) -> None:
    with pytest.raises(ValueError, match=r"--frame .* is not allowed; give a whole number from 0"):
        TargetOptions(frame=bad)  # type: ignore[arg-type]


# --- float images ------------------------------------------------------------------------------

def float_tiff(values: np.ndarray) -> bytes:
    """A 32-bit float greyscale TIFF (Pillow mode "F") of values (H, W)."""
    image = Image.fromarray(values.astype(np.float32), "F")
    data = saved(image, "TIFF")
    assert Image.open(io.BytesIO(data)).mode == "F"
    return data


RAMP = np.linspace(0.0, 1.0, 64).reshape(8, 8)


def test_a_float_image_in_0_1_is_srgb_without_a_warning() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error", TargetWarning)
        decoded = decode_image(float_tiff(RAMP), "unit.tif")
    expected = srgb_to_linear(RAMP.astype(np.float32).astype(np.float64))
    np.testing.assert_allclose(decoded, np.broadcast_to(expected, (3, 8, 8)), atol=1e-12)


@pytest.mark.parametrize("scale", [255, 65535])
def test_a_float_image_of_codes_is_scaled_with_a_warning(scale: int) -> None:
    values = np.rint(RAMP * scale)
    with pytest.warns(TargetWarning, match=rf"codes\.tif is a float image with values from 0 to "
                      rf"{scale}, above 1: read as codes from 0 to {scale} \(divided by {scale}\)"):
        decoded = decode_image(float_tiff(values), "codes.tif")
    np.testing.assert_allclose(decoded[0], srgb_to_linear(values / scale), atol=1e-9)


def test_a_float_image_a_rounding_above_1_is_read_as_0_1() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error", TargetWarning)
        decoded = decode_image(float_tiff(RAMP * 1.00001), "round.tif")
    assert decoded.max() == 1.0


@pytest.mark.parametrize(("value", "fragment"), [
    (-0.5, r"holds values from -0\.5 to 1; allowed: 0 and above"),
    (np.nan, r"holds NaN or infinite values \(1 pixels\); allowed: finite values"),
    (np.inf, r"holds NaN or infinite values \(1 pixels\)"),
    (70000.0, r"holds values up to 70000; allowed: 0 to 1 \(sRGB\), or 8- or 16-bit codes"),
])
def test_a_float_image_out_of_range_is_refused_naming_the_file(value: float,
                                                                fragment: str) -> None:
    values = RAMP.copy()
    values[3, 3] = value
    with pytest.raises(ValueError, match=r"bad\.tif: the float image " + fragment):
        decode_image(float_tiff(values), "bad.tif")


# --- files that are not regular files ----------------------------------------------------------

#: load_targets on argv[1] in a child: prints the error, or "read" when it read the file.
LOAD_CHILD = """\
import sys
from pathlib import Path
from aperture_fab.io.files import load_targets
try:
    load_targets([Path(sys.argv[1])])
except ValueError as error:
    print(error)
else:
    print("read")
"""


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no named pipes on this system")
def test_a_fifo_target_is_refused_at_once(tmp_path: Path) -> None:
    fifo = tmp_path / "pipe.png"
    os.mkfifo(fifo)
    # In a child with a timeout: reading the FIFO would block this test run forever.
    done = subprocess.run([sys.executable, "-c", LOAD_CHILD, str(fifo)], cwd=ROOT, text=True,
                          capture_output=True, timeout=HANG_S, check=False)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == (f"target image {fifo} is a named pipe (FIFO), not a regular "
                                   "file; give a regular image file (PNG, JPEG, ...), e.g. save "
                                   "what the pipe or device gives to a file first.")


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no named pipes on this system")
def test_the_cli_refuses_a_fifo_target_with_status_3(tmp_path: Path) -> None:
    from conftest import TINY_TOML

    fifo = tmp_path / "pipe.png"
    os.mkfifo(fifo)
    (tmp_path / "tiny.toml").write_text(TINY_TOML)
    done = subprocess.run(
        [sys.executable, "-m", "aperture_fab.cli", "design", str(fifo), "--config",
         str(tmp_path / "tiny.toml"), "--out", str(tmp_path / "run"), "--no-validate"],
        cwd=ROOT, text=True, capture_output=True, timeout=CLI_HANG_S, check=False)
    assert done.returncode == cli.EXIT_BAD_INPUT, done.stderr
    assert f"error: target image {fifo} is a named pipe (FIFO)" in done.stderr
    assert "give a regular image file" in done.stderr


def test_a_device_target_is_refused(tmp_path: Path) -> None:
    if not Path(os.devnull).exists() or Path(os.devnull).is_file():
        pytest.skip("no character device at os.devnull")
    with pytest.raises(ValueError, match=rf"target image {os.devnull} is a character device, not "
                       "a regular file; give a regular image file"):
        load_targets([Path(os.devnull)])


def test_a_socket_target_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "s.png"
    if not hasattr(socket, "AF_UNIX") or len(str(path)) > 100:
        pytest.skip("no Unix sockets here, or the path is too long for one")
    with socket.socket(socket.AF_UNIX) as server:
        server.bind(str(path))
        with pytest.raises(ValueError, match="is a socket, not a regular file; give a regular "
                           "image file"):
            load_targets([path])


def test_a_folder_and_a_missing_file_are_still_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="is a folder; give an image file"):
        load_targets([tmp_path])
    with pytest.raises(ValueError, match="does not exist; check the path"):
        load_targets([tmp_path / "missing.png"])


def test_a_link_to_an_image_is_read(tmp_path: Path) -> None:
    (tmp_path / "real.png").write_bytes(encode_png(np.full((3, 8, 8), 0.25)))
    (tmp_path / "link.png").symlink_to(tmp_path / "real.png")
    images, names = load_targets([tmp_path / "link.png"])
    assert names == ["link"]
    np.testing.assert_allclose(images[0], 0.25, rtol=0.01)


# --- the options and the command line ----------------------------------------------------------

def test_the_cli_offers_the_choices_images_defines() -> None:
    # cli/flags.py writes them out (building the parser must not import PIL): they must agree.
    assert flags.ALPHA_CHOICES == ALPHA_BACKGROUNDS and flags.FIT_CHOICES == TARGET_FITS
    parser = cli.build_parser()
    for command in ("design", "validate", "render", "display"):
        text = parser._subparsers._group_actions[0].choices[command].format_help()  # type: ignore
        assert "--alpha" in text and "--fit" in text and "--frame N" in text, command


@pytest.mark.parametrize(("options", "changes"), [
    (TargetOptions(), None),
    (TargetOptions(alpha="black", fit="stretch", frame=0), None),  # the defaults, chosen
    (TargetOptions(alpha="white"), "--alpha white"),
    (TargetOptions(alpha="refuse"), "--alpha refuse"),
    (TargetOptions(fit="pad", frame=2), "--fit pad --frame 2"),
])
def test_options_that_change_targets_are_named_for_the_checkpoint(
        options: TargetOptions, changes: str | None) -> None:
    assert options.changes() == changes


def test_resume_with_other_target_options_is_refused(
        tmp_path: Path, marker_png: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The same file made another target (--fit pad) is another input: --resume refuses it."""
    from conftest import interrupt_at_call, tiny_config

    from aperture_fab.optimize.optimizer import Interrupted
    from aperture_fab.pipeline.design_job import run_design

    overrides: dict[str, Any] = {"optimizer.iterations": 10, "optimizer.checkpoint_every": 3}
    config = tiny_config(**overrides)
    out = tmp_path / "out"
    interrupt_at_call(monkeypatch, 5)
    with pytest.raises(Interrupted):
        run_design([marker_png], out, config, progress=False)
    monkeypatch.undo()
    with pytest.raises(ValueError, match=r"--resume: the target options \(--alpha, --fit, "
                       r"--frame\) changed since"):
        run_design([marker_png], out, config, resume=True, progress=False,
                   target_options=TargetOptions(alpha="white"))
    # The defaults, chosen by name, make the same targets: that resumes.
    run_design([marker_png], out, config, resume=True, progress=False,
               target_options=TargetOptions(alpha="black", fit="stretch", frame=0))
    assert (out / "design.npz").is_file()
