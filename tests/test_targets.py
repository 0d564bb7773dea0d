"""Tests for aperture_fab.targets and examples/make_targets.py."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import ImageFont

from aperture_fab import targets
from aperture_fab.io.decode import decode_image
from aperture_fab.io.images import is_grey, linear_to_srgb
from aperture_fab.targets import (
    EXAMPLES,
    asymmetric_marker,
    checker,
    digit,
    natural,
    pixel_art,
)

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "examples" / "make_targets.py"
#: An 8-bit sRGB PNG holds a value to half a code step of the encoded value.
HALF_CODE = 0.5 / 255 + 1e-12


def ink_box(image: np.ndarray, level: float = 0.02) -> tuple[int, int, int, int]:
    """Rows and columns (top, bottom, left, right), inclusive, where any channel exceeds level."""
    rows = np.flatnonzero((image > level).any(axis=(0, 2)))
    cols = np.flatnonzero((image > level).any(axis=(0, 1)))
    return int(rows[0]), int(rows[-1]), int(cols[0]), int(cols[-1])


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_examples_are_valid_and_deterministic(name: str) -> None:
    image = EXAMPLES[name]()
    assert image.dtype == np.float64 and image.ndim == 3 and image.shape[0] == 3
    assert image.shape[1] == image.shape[2] >= 16
    assert np.all(np.isfinite(image)) and image.min() >= 0.0 and image.max() <= 1.0
    assert image.max() > 0.5 and image.min() < 0.1  # has content, not flat
    np.testing.assert_array_equal(image, EXAMPLES[name]())


def test_examples_names() -> None:
    assert {"digit-3", "letter-A", "pixel-art", "natural", "marker-F"} <= set(EXAMPLES)


# --- glyphs ------------------------------------------------------------------------------------

@pytest.mark.parametrize("char", ["0", "3", "7", "A", "g", "F"])
@pytest.mark.parametrize("size", [28, 64, 700])
def test_digit_like_mnist(char: str, size: int) -> None:
    image = digit(char, size)
    assert image.shape == (3, size, size) and is_grey(image)
    assert image[:, 0, :].max() == 0 and image[:, -1, :].max() == 0  # black border
    assert image.max() > 0.99  # white ink
    assert np.any((image > 0.1) & (image < 0.9))  # antialiased edges
    top, bottom, left, right = ink_box(image)
    box = 20 / 28 * size
    # The glyph fills the 20/28 box along its longer side and is centred in the image.
    assert max(bottom - top, right - left) + 1 == pytest.approx(box, abs=2)
    assert (top + bottom) / 2 == pytest.approx((size - 1) / 2, abs=1)
    assert (left + right) / 2 == pytest.approx((size - 1) / 2, abs=1)


def test_digits_differ() -> None:
    images = [digit(c) for c in "0123456789"]
    for i in range(10):
        for j in range(i + 1, 10):
            assert np.abs(images[i] - images[j]).mean() > 0.02


def test_digit_bitmap_font_fallback(monkeypatch: pytest.MonkeyPatch) -> None:
    # Without FreeType, Pillow's default font is a small bitmap font.
    bitmap = ImageFont.load_default_imagefont()
    monkeypatch.setattr(targets.ImageFont, "load_default", lambda size=None: bitmap)
    image = digit("3")
    assert image.shape == (3, 28, 28) and is_grey(image) and image.max() > 0.9
    top, bottom, left, right = ink_box(image)
    assert max(bottom - top, right - left) + 1 == pytest.approx(20, abs=2)


@pytest.mark.parametrize("char", ["", "12", " ", "\n", "é"])
def test_digit_rejects_bad_char(char: str) -> None:
    with pytest.raises(ValueError, match="digit char"):
        digit(char)


def test_digit_rejects_bad_types() -> None:
    with pytest.raises(TypeError, match="digit char"):
        digit(3)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="digit size"):
        digit("3", 28.0)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="digit size = 4"):
        digit("3", 4)


# --- pixel art, marker, checker ----------------------------------------------------------------

@pytest.mark.parametrize("size", [16, 32, 40, 100])
def test_pixel_art_hard_edges_and_colourful(size: int) -> None:
    image = pixel_art(size)
    assert image.shape == (3, size, size) and not is_grey(image)
    colours = np.unique(image.reshape(3, -1).T, axis=0)
    assert len(colours) == len(targets.PIXEL_ART_PALETTE)  # only palette colours: no blending
    saturation = colours.max(axis=1) - colours.min(axis=1)
    assert np.sum(saturation > 0.5) >= 5


def test_pixel_art_blocks() -> None:
    image = pixel_art(64)
    blocks = image.reshape(3, 16, 4, 16, 4)
    assert np.all(blocks == blocks[:, :, :1, :, :1])
    np.testing.assert_array_equal(pixel_art(16), blocks[:, :, 0, :, 0])


@pytest.mark.parametrize("size", [8, 32, 50])
def test_marker_is_asymmetric_and_upright(size: int) -> None:
    image = asymmetric_marker(size)
    assert image.shape == (3, size, size) and is_grey(image)
    for changed in (image[:, :, ::-1], image[:, ::-1, :], image[:, ::-1, ::-1],
                    image.transpose(0, 2, 1)):
        assert np.abs(changed - image).mean() > 0.05  # 4 or more of the 64 cells differ
    half = size // 2
    assert image[:, :, :half].mean() > image[:, :, half:].mean()  # stem on the left
    assert image[:, :half].mean() > image[:, half:].mean()  # top bar above
    expected = np.array([[ch == "#" for ch in row] for row in targets.MARKER_ROWS], float)
    if size % 8 == 0:
        np.testing.assert_array_equal(image[0], np.kron(expected, np.ones((size // 8,) * 2)))


@pytest.mark.parametrize(("size", "cells"), [(32, 8), (30, 3), (10, 10), (7, 1)])
def test_checker(size: int, cells: int) -> None:
    image = checker(size, cells)
    assert image.shape == (3, size, size) and is_grey(image)
    assert image[0, 0, 0] == 1.0
    if size % cells == 0:
        pattern = (np.indices((cells, cells)).sum(axis=0) + 1) % 2
        np.testing.assert_array_equal(image[0], np.kron(pattern, np.ones((size // cells,) * 2)))


def test_checker_bad_cells() -> None:
    with pytest.raises(ValueError, match="checker cells"):
        checker(8, 9)


@pytest.mark.parametrize("maker", [pixel_art, asymmetric_marker, natural, checker])
def test_sizes_out_of_range(maker: object) -> None:
    with pytest.raises(ValueError, match="size = 5000"):
        maker(5000)  # type: ignore[operator]
    with pytest.raises(TypeError, match="whole number"):
        maker(True)  # type: ignore[operator]


# --- natural scene -----------------------------------------------------------------------------

def test_natural_seeded() -> None:
    a, b = natural(64, seed=1), natural(64, seed=2)
    np.testing.assert_array_equal(a, natural(64, seed=1))
    assert np.abs(a - b).mean() > 0.005


def test_natural_smooth_gradients_and_sharp_edges() -> None:
    image = natural(128)
    assert not is_grey(image)
    encoded = linear_to_srgb(image)
    # The sky's top rows change smoothly downward, and it is bluer above than at the horizon.
    sky = encoded[:, :20, :30]
    assert np.abs(np.diff(sky, axis=1)).max() < 0.02
    assert encoded[2, 0].mean() > encoded[0, 0].mean()
    assert encoded[0, 60].mean() > encoded[0, 0].mean()
    # Somewhere there is a hard edge (sun disk, ridges, trees): a jump over a large part of range.
    assert np.abs(np.diff(encoded, axis=1)).max() > 0.3
    assert np.abs(np.diff(encoded, axis=2)).max() > 0.3


# --- the examples script -----------------------------------------------------------------------

def run_script(*args: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH",
                                                                                 "")]))
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True,
                          env=env, check=False, timeout=120)


def assert_matches_examples(folder: Path) -> None:
    for name, make in EXAMPLES.items():
        path = folder / f"{name}.png"
        decoded = decode_image(path.read_bytes(), path.name)
        difference = np.abs(linear_to_srgb(decoded) - linear_to_srgb(make()))
        assert difference.max() <= HALF_CODE, name


def test_make_targets_script(tmp_path: Path) -> None:
    out = tmp_path / "new" / "targets"
    result = run_script("--out", str(out))
    assert result.returncode == 0, result.stderr
    assert sorted(p.name for p in out.iterdir()) == sorted(f"{n}.png" for n in EXAMPLES)
    assert_matches_examples(out)
    # Running again replaces the files in place and leaves no temporary files behind.
    assert run_script("--out", str(out)).returncode == 0
    assert len(list(out.iterdir())) == len(EXAMPLES)


def test_shipped_targets_are_up_to_date() -> None:
    assert_matches_examples(REPO / "examples" / "targets")
