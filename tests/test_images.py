"""Tests for aperture_fab.io.images: sRGB curves, decoding, resampling, PNG encoding."""

from __future__ import annotations

import io
import struct
import warnings
import zlib

import numpy as np
import png
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from PIL import Image

from aperture_fab.io.decode import MAX_IMAGE_PIXELS, decode_image
from aperture_fab.io.images import (
    TargetWarning,
    encode_png,
    is_grey,
    linear_to_srgb,
    resample,
    srgb_to_linear,
)

#: IEC 61966-2-1's thresholds (0.04045 encoded, 0.0031308 linear) disagree by this much.
KNEE_MISMATCH = 5e-8


def saved(image: Image.Image, fmt: str = "PNG", **options: object) -> bytes:
    buffer = io.BytesIO()
    image.save(buffer, format=fmt, **options)
    return buffer.getvalue()


def srgb_formula(v: float) -> float:
    """IEC 61966-2-1 decoding written out independently, for scalars."""
    return v / 12.92 if v <= 0.04045 else ((v + 0.055) / 1.055) ** 2.4


def lin(code: int) -> float:
    """Linear value of an 8-bit sRGB code."""
    return srgb_formula(code / 255)


def png_chunk(kind: bytes, payload: bytes) -> bytes:
    return (struct.pack(">I", len(payload)) + kind + payload
            + struct.pack(">I", zlib.crc32(kind + payload)))


def crafted_png(width: int, height: int, idat: bytes = b"") -> bytes:
    """A PNG whose header claims width x height 8-bit grey, with the given (short) IDAT."""
    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", header) + png_chunk(b"IDAT", idat)
            + png_chunk(b"IEND", b""))


def noise_rgb(seed: int = 0, size: int = 64) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (size, size, 3), dtype=np.uint8)


# --- sRGB curves -------------------------------------------------------------------------------

@pytest.mark.parametrize(("encoded", "linear"), [
    (0.0, 0.0), (1.0, 1.0), (0.5, 0.214041140), (0.04045, 0.04045 / 12.92), (0.02, 0.02 / 12.92),
    (0.8, 0.603827338),
])
def test_srgb_known_values(encoded: float, linear: float) -> None:
    assert srgb_to_linear(np.array(encoded)) == pytest.approx(linear, abs=1e-9)
    assert linear_to_srgb(np.array(linear)) == pytest.approx(encoded, abs=KNEE_MISMATCH)


def test_srgb_matches_formula_and_is_continuous() -> None:
    values = np.linspace(0, 1, 1001)
    expected = [srgb_formula(v) for v in values]
    np.testing.assert_allclose(srgb_to_linear(values), expected, rtol=0, atol=1e-15)
    below, above = srgb_to_linear(np.array([0.04045, 0.04045 + 1e-12]))
    assert abs(above - below) < 1e-7


@given(arrays(np.float64, st.integers(1, 50), elements=st.floats(0, 1)))
def test_srgb_round_trip(x: np.ndarray) -> None:
    # Exact except between the standard's two knee thresholds (0.04045 vs 12.92 * 0.0031308).
    near_knee = np.abs(x - 0.04045) < 1e-4
    tolerance = np.where(near_knee, KNEE_MISMATCH, 1e-12)
    assert np.all(np.abs(linear_to_srgb(srgb_to_linear(x)) - x) <= tolerance)
    near_knee = np.abs(x - 0.0031308) < 1e-5
    tolerance = np.where(near_knee, KNEE_MISMATCH, 1e-12)
    assert np.all(np.abs(srgb_to_linear(linear_to_srgb(x)) - x) <= tolerance)


def test_srgb_is_monotonic() -> None:
    values = np.linspace(0, 1, 10001)
    assert np.all(np.diff(srgb_to_linear(values)) > 0)
    assert np.all(np.diff(linear_to_srgb(values)) > 0)


@pytest.mark.parametrize("bad", [np.array([-0.1]), np.array([1.5]), np.array([np.nan])])
def test_srgb_rejects_out_of_range(bad: np.ndarray) -> None:
    with pytest.raises(ValueError, match="srgb_to_linear input"):
        srgb_to_linear(bad)
    with pytest.raises(ValueError, match="linear_to_srgb input"):
        linear_to_srgb(bad)


# --- decoding each mode ------------------------------------------------------------------------

def test_decode_rgb_values_and_orientation() -> None:
    pixels = noise_rgb()
    pixels[0, :] = (255, 0, 0)  # top row red
    decoded = decode_image(saved(Image.fromarray(pixels)), "noise.png")
    assert decoded.shape == (3, 64, 64) and decoded.dtype == np.float64
    expected = np.vectorize(lin)(pixels).transpose(2, 0, 1)
    np.testing.assert_allclose(decoded, expected, atol=1e-12)
    assert decoded[:, 0, 5].tolist() == [1.0, 0.0, 0.0]


def test_decode_greyscale_l() -> None:
    pixels = np.array([[0, 64, 128, 255]], dtype=np.uint8)
    decoded = decode_image(saved(Image.fromarray(pixels)), "grey.png")
    assert decoded.shape == (3, 1, 4) and is_grey(decoded)
    np.testing.assert_allclose(decoded[1, 0], [lin(0), lin(64), lin(128), lin(255)], atol=1e-12)


def test_decode_bilevel() -> None:
    image = Image.new("1", (3, 2))
    image.putpixel((1, 0), 1)
    decoded = decode_image(saved(image), "bits.png")
    assert decoded[:, 0, 1].tolist() == [1.0, 1.0, 1.0]
    assert decoded.sum() == 3.0


def test_decode_16bit_grey_keeps_precision() -> None:
    codes = np.array([[0, 1, 2, 30000, 30001, 65534, 65535]], dtype=np.uint16)
    data = saved(Image.fromarray(codes))
    assert Image.open(io.BytesIO(data)).mode in ("I;16", "I")
    decoded = decode_image(data, "deep.png")
    expected = [srgb_formula(c / 65535) for c in codes[0]]
    np.testing.assert_allclose(decoded[0, 0], expected, atol=1e-14)
    # Neighbouring 16-bit codes stay distinct: nothing was rounded to 8 bits.
    assert np.all(np.diff(decoded[0, 0]) > 0)


def test_decode_mode_i_from_pgm() -> None:
    data = b"P5\n3 1\n65535\n" + np.array([0, 1, 65535], dtype=">u2").tobytes()
    assert Image.open(io.BytesIO(data)).mode == "I"
    decoded = decode_image(data, "deep.pgm")
    np.testing.assert_allclose(decoded[2, 0], [0.0, srgb_formula(1 / 65535), 1.0], atol=1e-15)


def test_decode_rgba_composites_on_black_in_linear_light() -> None:
    pixels = np.array([[[255, 255, 255, 128], [200, 100, 0, 51], [10, 20, 30, 0],
                        [90, 180, 45, 255]]], dtype=np.uint8)
    with pytest.warns(TargetWarning, match="alpha.png is transparent in 75.0%.*on black"):
        decoded = decode_image(saved(Image.fromarray(pixels, "RGBA")), "alpha.png")
    # Half-covered white is half the light (0.502), not sRGB 0.5 of grey (0.214).
    np.testing.assert_allclose(decoded[:, 0, 0], 128 / 255, atol=1e-12)
    np.testing.assert_allclose(decoded[:, 0, 1],
                               [lin(200) * 0.2, lin(100) * 0.2, 0.0], atol=1e-12)
    assert decoded[:, 0, 2].tolist() == [0.0, 0.0, 0.0]
    np.testing.assert_allclose(decoded[:, 0, 3], [lin(90), lin(180), lin(45)], atol=1e-12)


def test_decode_la() -> None:
    pixels = np.array([[[200, 100], [255, 255]]], dtype=np.uint8)
    decoded = decode_image(saved(Image.fromarray(pixels, "LA")), "la.png", alpha="black")
    np.testing.assert_allclose(decoded[:, 0, 0], lin(200) * 100 / 255, atol=1e-12)
    np.testing.assert_allclose(decoded[:, 0, 1], 1.0, atol=1e-12)


@pytest.mark.parametrize("transparent", [False, True])
def test_decode_palette(transparent: bool) -> None:
    image = Image.new("P", (3, 1))
    image.putpalette([0, 0, 255, 255, 0, 0, 10, 200, 30])
    for x, index in enumerate([0, 1, 2]):
        image.putpixel((x, 0), index)
    data = saved(image, transparency=0) if transparent else saved(image)
    assert Image.open(io.BytesIO(data)).mode == "P"
    decoded = decode_image(data, "palette.png", alpha="black")
    first = [0.0, 0.0, 0.0] if transparent else [0.0, 0.0, 1.0]
    np.testing.assert_allclose(decoded[:, 0, 0], first, atol=1e-12)
    np.testing.assert_allclose(decoded[:, 0, 1], [1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(decoded[:, 0, 2], [lin(10), lin(200), lin(30)], atol=1e-12)


def test_decode_rgb_colour_key_transparency() -> None:
    pixels = np.array([[[0, 0, 255], [255, 255, 0]]], dtype=np.uint8)
    data = saved(Image.fromarray(pixels), transparency=(0, 0, 255))
    decoded = decode_image(data, "keyed.png", alpha="black")
    assert decoded[:, 0, 0].tolist() == [0.0, 0.0, 0.0]
    assert decoded[:, 0, 1].tolist() == [1.0, 1.0, 0.0]


@pytest.mark.parametrize("fmt", ["TIFF", "JPEG"])
def test_decode_cmyk(fmt: str) -> None:
    image = Image.new("CMYK", (4, 1))
    for x, ink in enumerate([(0, 0, 0, 0), (255, 0, 0, 0), (0, 0, 0, 255), (0, 255, 255, 0)]):
        image.putpixel((x, 0), ink)
    data = saved(image, fmt, **({"quality": 100} if fmt == "JPEG" else {}))
    assert Image.open(io.BytesIO(data)).mode == "CMYK"
    decoded = decode_image(data, f"inks.{fmt.lower()}")
    expected = [[1, 1, 1], [0, 1, 1], [0, 0, 0], [1, 0, 0]]  # white, cyan, black, red
    np.testing.assert_allclose(decoded[:, 0, :].T, expected, atol=0.02)


def test_decode_jpeg_grey_level() -> None:
    data = saved(Image.new("RGB", (16, 16), (128, 128, 128)), "JPEG", quality=95)
    decoded = decode_image(data, "grey.jpg")
    np.testing.assert_allclose(linear_to_srgb(decoded), 128 / 255, atol=1.5 / 255)


def test_decode_applies_exif_orientation() -> None:
    pixels = np.zeros((1, 2), dtype=np.uint8)
    pixels[0, 0] = 255  # white on the left as stored
    exif = Image.Exif()
    exif[0x0112] = 3  # rotate 180 degrees to view upright
    decoded = decode_image(saved(Image.fromarray(pixels), "JPEG", exif=exif, quality=100), "r.jpg")
    assert decoded[0, 0, 1] > 0.9 > 0.1 > decoded[0, 0, 0]


# --- decoding errors ---------------------------------------------------------------------------

def test_decode_empty() -> None:
    with pytest.raises(ValueError, match=r"blank\.png: the file is empty"):
        decode_image(b"", "blank.png")


def test_decode_garbage() -> None:
    with pytest.raises(ValueError, match=r"notes\.txt: is not an image.*PNG"):
        decode_image(b"hello, this is text, not a picture", "notes.txt")


def test_decode_wrong_type() -> None:
    with pytest.raises(TypeError, match="bytes"):
        decode_image("target.png", "target.png")  # type: ignore[arg-type]


@pytest.mark.parametrize("fmt", ["PNG", "JPEG"])
def test_decode_truncated(fmt: str) -> None:
    data = saved(Image.fromarray(noise_rgb()), fmt)
    with pytest.raises(ValueError, match=r"cut\.img: .*truncated.*Re-export it as PNG"):
        decode_image(data[: len(data) // 2], "cut.img")


def test_decode_truncated_in_header() -> None:
    data = saved(Image.fromarray(noise_rgb()))
    with pytest.raises(ValueError, match=r"stub\.png: looks like a PNG file.*truncated"):
        decode_image(data[:40], "stub.png")


def test_decode_zero_sized() -> None:
    # PNG cannot hold a 0 x 0 image; a crafted header claims one, and Pillow refuses it.
    with pytest.raises(ValueError, match=r"empty\.png: the image has zero size \(0 x 5"):
        decode_image(crafted_png(0, 5), "empty.png")


def test_decode_bomb_refused_before_decoding() -> None:
    limit_before = Image.MAX_IMAGE_PIXELS
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no DecompressionBombWarning may escape
        with pytest.raises(ValueError, match=r"bomb\.png: .*too large.*Downscale it below 64"):
            decode_image(crafted_png(100_000, 100_000), "bomb.png")
        # 108 megapixels: over our limit, under Pillow's hard limit (it would only warn).
        with pytest.raises(ValueError, match=r"big\.png: the image is 12000 x 9000 pixels "
                                             r"\(108\.0 megapixels\).*Downscale"):
            decode_image(crafted_png(12_000, 9_000), "big.png")
    assert Image.MAX_IMAGE_PIXELS == limit_before
    assert MAX_IMAGE_PIXELS == 64_000_000


def test_decode_max_pixels_checked_from_header() -> None:
    # The IDAT is empty: had the image been decoded, the error would say "truncated".
    with pytest.raises(ValueError, match=r"2000 x 1000 pixels.*limit of 1 megapixels"):
        decode_image(crafted_png(2000, 1000), "wide.png", max_pixels=1_000_000)


def test_decode_max_pixels_real_image() -> None:
    data = saved(Image.new("1", (2000, 1000)))
    assert len(data) < 10_000  # large but cheap
    with pytest.raises(ValueError, match=r"2\.0 megapixels"):
        decode_image(data, "sheet.png", max_pixels=1_000_000)
    assert decode_image(data, "sheet.png", max_pixels=2_000_000).shape == (3, 1000, 2000)


@pytest.mark.parametrize("bad", [0, -5, 1.5, True])
def test_decode_bad_max_pixels(bad: object) -> None:
    with pytest.raises(ValueError, match="max_pixels"):
        decode_image(b"x", "x.png", max_pixels=bad)  # type: ignore[arg-type]


@settings(max_examples=60, deadline=None)
@given(st.sampled_from(["PNG", "JPEG"]), st.data())
def test_decode_corrupted_bytes_raise_value_error(fmt: str, data: st.DataObject) -> None:
    original = bytearray(saved(Image.fromarray(noise_rgb(size=16)), fmt))
    for _ in range(data.draw(st.integers(1, 4))):
        position = data.draw(st.integers(0, len(original) - 1))
        original[position] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(1, len(original)))
    try:
        decoded = decode_image(bytes(original[:cut]), "fuzz")
    except ValueError as error:
        assert "fuzz" in str(error)
    else:
        assert decoded.shape[0] == 3 and decoded.min() >= 0 and decoded.max() <= 1


# --- resampling --------------------------------------------------------------------------------

@pytest.mark.parametrize("kernel", ["box", "bilinear"])
@pytest.mark.parametrize("size", [(7, 5), (64, 48), (13, 100), (1, 1), (300, 2)])
def test_resample_uniform_is_preserved(kernel: str, size: tuple[int, int]) -> None:
    image = np.empty((3, 48, 64))
    image[:] = np.array([0.3, 0.123456789, 1.0])[:, None, None]
    out = resample(image, size, kernel)  # type: ignore[arg-type]
    assert out.shape == (3, size[1], size[0])
    np.testing.assert_allclose(out, np.broadcast_to(image[:, :1, :1], out.shape), rtol=1e-14)


def test_resample_box_integer_factor_is_block_mean() -> None:
    image = np.random.default_rng(1).random((3, 12, 20))
    expected = image.reshape(3, 3, 4, 5, 4).mean(axis=(2, 4))
    np.testing.assert_allclose(resample(image, (5, 3)), expected, atol=1e-15)


@pytest.mark.parametrize(("n_in", "n_out"), [(3, 2), (120, 37), (10, 23), (7, 7), (5, 1)])
def test_resample_box_is_exact_area_average(n_in: int, n_out: int) -> None:
    # Independent: split every pixel into n_out (input) or n_in (output) equal sub-pixels.
    row = np.random.default_rng(7).random(n_in)
    expected = np.repeat(row, n_out).reshape(n_out, n_in).mean(axis=1)
    np.testing.assert_allclose(resample(row[None, None], (n_out, 1))[0, 0], expected, atol=1e-14)
    column = resample(row[None, :, None], (1, n_out))[0, :, 0]
    np.testing.assert_allclose(column, expected, atol=1e-14)


def test_resample_box_fractional_overlap() -> None:
    row = np.array([[[0.2, 0.6, 1.0]]])
    out = resample(row, (2, 1))
    # Output pixels cover [0, 1.5) and [1.5, 3) of the input.
    np.testing.assert_allclose(out[0, 0], [(0.2 + 0.5 * 0.6) / 1.5, (0.5 * 0.6 + 1.0) / 1.5])


@pytest.mark.parametrize("size", [(17, 9), (120, 77), (40, 40)])
def test_resample_bilinear_matches_pillow(size: tuple[int, int]) -> None:
    channel = np.random.default_rng(2).random((33, 50))
    reference = Image.fromarray(channel.astype(np.float32), "F").resize(
        size, Image.Resampling.BILINEAR)
    np.testing.assert_allclose(resample(channel[None], size, "bilinear")[0],
                               np.asarray(reference), atol=1e-6)


@pytest.mark.parametrize("kernel", ["box", "bilinear"])
def test_resample_smooth_ramp(kernel: str) -> None:
    width, out_width = 120, 37
    ramp = np.broadcast_to((np.arange(width) + 0.5) / width, (1, 4, width))
    out = resample(np.ascontiguousarray(ramp), (out_width, 4), kernel)  # type: ignore[arg-type]
    expected = (np.arange(out_width) + 0.5) / out_width
    # Close to the ramp at the output pixel centres (within 5 % of an input step); bilinear
    # truncates its kernel at the borders, so only the inside is compared for it.
    inner = slice(0, None) if kernel == "box" else slice(2, -2)
    np.testing.assert_allclose(out[0, 0, inner], expected[inner], atol=0.05 / width)


def test_resample_box_antialiases_fine_detail() -> None:
    fine = (np.indices((96, 96)).sum(axis=0) % 2).astype(np.float64)[None]  # 1-pixel checker
    out = resample(fine, (30, 30))
    assert abs(out.mean() - 0.5) < 1e-12
    assert out.std() < 0.03  # point sampling would alias it to stripes (std 0.5)


@settings(max_examples=80, deadline=None)
@given(
    arrays(np.float64, st.tuples(st.sampled_from([1, 3]), st.integers(1, 16), st.integers(1, 16)),
           elements=st.floats(0, 1)),
    st.integers(1, 24), st.integers(1, 24), st.sampled_from(["box", "bilinear"]),
)
def test_resample_properties(image: np.ndarray, nx: int, ny: int, kernel: str) -> None:
    out = resample(image, (nx, ny), kernel)  # type: ignore[arg-type]
    assert out.shape == (image.shape[0], ny, nx)
    assert np.all(out >= image.min() - 1e-12) and np.all(out <= image.max() + 1e-12)
    assert out.min() >= 0.0 and out.max() <= 1.0
    if kernel == "box":
        np.testing.assert_allclose(out.mean(), image.mean(), atol=1e-12)


@pytest.mark.parametrize("size", [(0, 4), (4, -1), (4.0, 4), [4, 4], (4,), (True, 4)])
def test_resample_bad_size(size: object) -> None:
    with pytest.raises(ValueError, match="resample size"):
        resample(np.zeros((3, 4, 4)), size)  # type: ignore[arg-type]


def test_resample_bad_inputs() -> None:
    with pytest.raises(ValueError, match="kernel"):
        resample(np.zeros((3, 4, 4)), (2, 2), "lanczos")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"shape \(C, H, W\)"):
        resample(np.zeros((4, 4)), (2, 2))
    with pytest.raises(ValueError, match="NaN"):
        resample(np.full((1, 4, 4), np.nan), (2, 2))


# --- encoding ----------------------------------------------------------------------------------

def test_encode_png_8bit_round_trip() -> None:
    image = np.random.default_rng(3).random((3, 20, 30))
    data = encode_png(image)
    assert Image.open(io.BytesIO(data)).mode == "RGB"
    decoded = decode_image(data, "round.png")
    # Quantization to 8-bit sRGB: half a code step in the encoded domain.
    assert np.abs(linear_to_srgb(decoded) - linear_to_srgb(image)).max() <= 0.5 / 255 + 1e-12


def test_encode_png_exact_for_8bit_levels() -> None:
    codes = np.random.default_rng(4).integers(0, 256, (3, 8, 9))
    image = srgb_to_linear(codes / 255)
    np.testing.assert_allclose(decode_image(encode_png(image), "levels.png"), image, atol=1e-13)


def test_encode_png_grey_one_channel() -> None:
    image = np.linspace(0, 1, 12).reshape(1, 3, 4)
    data = encode_png(image)
    assert Image.open(io.BytesIO(data)).mode == "L"
    decoded = decode_image(data, "grey.png")
    assert decoded.shape == (3, 3, 4) and is_grey(decoded)


def test_encode_png_16bit_grey_round_trip() -> None:
    image = np.linspace(0, 1, 400).reshape(1, 20, 20)
    data = encode_png(image, bits=16)
    assert Image.open(io.BytesIO(data)).mode in ("I;16", "I")
    decoded = decode_image(data, "deep.png")
    assert np.abs(linear_to_srgb(decoded[:1]) - linear_to_srgb(image)).max() <= 0.5 / 65535 + 1e-12


def test_encode_png_16bit_rgb_samples() -> None:
    image = np.random.default_rng(5).random((3, 4, 5))
    data = encode_png(image, bits=16)
    Image.open(io.BytesIO(data)).verify()  # valid chunks and CRCs
    assert Image.open(io.BytesIO(data)).size == (5, 4)
    # Read the samples back independently: one IDAT, filter byte 0 per row, big-endian.
    assert data[12:16] == b"IHDR" and struct.unpack(">IIBB", data[16:26]) == (5, 4, 16, 2)
    idat_at = data.index(b"IDAT")
    length = struct.unpack(">I", data[idat_at - 4: idat_at])[0]
    raw = np.frombuffer(zlib.decompress(data[idat_at + 4: idat_at + 4 + length]), np.uint8)
    rows = raw.reshape(4, 1 + 5 * 3 * 2)
    assert np.all(rows[:, 0] == 0)
    samples = rows[:, 1:].copy().view(">u2").reshape(4, 5, 3).transpose(2, 0, 1)
    expected = np.rint(np.vectorize(lambda v: 1.055 * v ** (1 / 2.4) - 0.055 if v > 0.0031308
                                    else 12.92 * v)(image) * 65535)
    np.testing.assert_array_equal(samples, expected)


def test_encode_png_16bit_large_rgb_one_idat_full_precision() -> None:
    # Over pypng's default chunk limit (1 MiB of rows), still one IDAT chunk as before pypng;
    # pypng's reader gives the 16-bit colour samples back (Pillow reads them at 8 bits).
    image = np.random.default_rng(9).random((3, 300, 600))
    data = encode_png(image, bits=16)
    assert data.count(b"IDAT") == 1
    width, height, rows, info = png.Reader(bytes=data).read()
    assert (width, height, info["bitdepth"], info["planes"]) == (600, 300, 16, 3)
    samples = np.array([np.asarray(row) for row in rows]).reshape(300, 600, 3).transpose(2, 0, 1)
    np.testing.assert_array_equal(samples, np.rint(linear_to_srgb(image) * 65535))


@pytest.mark.parametrize(("image", "bits", "match"), [
    (np.zeros((2, 4, 4)), 8, "2 channels"),
    (np.full((3, 4, 4), 1.2), 8, "Clip it first"),
    (np.full((3, 4, 4), np.nan), 8, "NaN"),
    (np.zeros((3, 4, 4)), 12, "bits"),
    (np.zeros((3, 0, 4)), 8, "zero size"),
])
def test_encode_png_errors(image: np.ndarray, bits: int, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        encode_png(image, bits=bits)  # type: ignore[arg-type]


# --- is_grey -----------------------------------------------------------------------------------

def test_is_grey() -> None:
    grey = np.repeat(np.random.default_rng(6).random((1, 5, 5)), 3, axis=0)
    assert is_grey(grey) and is_grey(grey[:1])
    nearly = grey.copy()
    nearly[2, 1, 1] += 1e-12
    assert is_grey(nearly)
    tinted = grey.copy()
    tinted[0, 4, 4] += 1e-6
    assert not is_grey(tinted)
    with pytest.raises(ValueError, match="4 channels"):
        is_grey(np.zeros((4, 2, 2)))
