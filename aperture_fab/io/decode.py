"""Reading an image file into linear light: the formats and their signatures, 8-, 16-bit and
float samples, alpha composited on a stated background, the frame of an animation, and a clear
refusal (naming the file and the fix) for anything else."""

from __future__ import annotations

import io
import re
import struct
import warnings
import zlib

import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from aperture_fab.io.images import (
    ALPHA_BACKGROUND_VALUES,
    MAX_8BIT,
    MAX_16BIT,
    AlphaBackground,
    TargetOptions,
    TargetWarning,
    srgb_to_linear,
)

__all__ = ["FLOAT_FULL_SCALES", "FLOAT_SLACK", "MAX_IMAGE_PIXELS", "PILLOW_BUFFER_REPR",
           "PILLOW_MODULES", "PNG_SIGNATURE", "REEXPORT", "SIGNATURES", "WIDE_GREY_MODES",
           "decode_image"]


#: Largest image decode_image accepts by default (64 megapixels): larger files are almost surely
#: a mistake, and a decompression bomb must be refused before it is decoded.
MAX_IMAGE_PIXELS = 64_000_000


#: A float image (Pillow mode "F", e.g. a 32-bit float TIFF) is read by its largest value: up to
#: 1 it is sRGB in [0, 1] like every other file; up to 255 or 65535 it holds 8- or 16-bit codes
#: as floats (scaled, with a warning). Each full scale, smallest first.
FLOAT_FULL_SCALES = (1, MAX_8BIT, MAX_16BIT)


#: Float values above a full scale by no more than this share are rounding (1.0000001), clipped.
FLOAT_SLACK = 1e-4


#: Pillow names the in-memory file it could not identify ("<_io.BytesIO object at 0x...>"):
#: noise in a message about the user's file, which is named instead.
PILLOW_BUFFER_REPR = re.compile(r"\s*<_io\.BytesIO object at 0x[0-9a-fA-F]+>")


#: Pillow's own warnings while it opens a file (e.g. "Truncated File Read" from a TIFF): the file
#: is refused with one line naming it, or read; a second, raw line would only confuse.
PILLOW_MODULES = r"PIL\."


#: Pillow modes holding one grey sample of up to 16 bits (16-bit PNG greyscale, PGM, ...).
WIDE_GREY_MODES = ("I;16", "I;16B", "I;16L", "I;16N", "I")


#: File signatures, to say what a file that Pillow cannot read looks like.
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


SIGNATURES: tuple[tuple[bytes, str], ...] = (
    (PNG_SIGNATURE, "PNG"),
    (b"\xff\xd8\xff", "JPEG"),
    (b"GIF87a", "GIF"),
    (b"GIF89a", "GIF"),
    (b"II*\x00", "TIFF"),
    (b"MM\x00*", "TIFF"),
    (b"BM", "BMP"),
)


REEXPORT = "Re-export it as PNG (8 or 16 bit, RGB or greyscale) and try again."


def _unreadable_message(name: str, data: bytes, error: Exception) -> str:
    """Say what a file that Pillow cannot open looks like, and what to do."""
    for signature, kind in SIGNATURES:
        if data.startswith(signature):
            if kind == "PNG" and len(data) >= 24 and data[12:16] == b"IHDR":
                width, height = struct.unpack(">II", data[16:24])
                if width == 0 or height == 0:
                    return (f"{name}: the image has zero size ({width} x {height} pixels). "
                            f"{REEXPORT}")
            reason = PILLOW_BUFFER_REPR.sub("", str(error))
            return (f"{name}: looks like a {kind} file but cannot be read ({reason}); it is "
                    f"probably truncated or corrupt. {REEXPORT}")
    return (f"{name}: is not an image file that can be read ({len(data)} bytes, starting "
            f"{data[:8]!r}). Give a PNG or JPEG image, or re-export it as PNG.")


def _too_large_message(name: str, width: int, height: int, max_pixels: int) -> str:
    shrink = (max_pixels / (width * height)) ** 0.5
    fit = (max(1, int(width * shrink)), max(1, int(height * shrink)))
    return (f"{name}: the image is {width} x {height} pixels ({width * height / 1e6:.1f} "
            f"megapixels), more than the limit of {max_pixels / 1e6:g} megapixels. Downscale it "
            f"below {max_pixels / 1e6:g} megapixels (e.g. to {fit[0]} x {fit[1]}) and try again.")


def _decoding_table(full_scale: int) -> np.ndarray:
    """Linear value of every integer sRGB code 0..full_scale, float64 (full_scale + 1,)."""
    return srgb_to_linear(np.arange(full_scale + 1) / full_scale)


def _float_grey(values: np.ndarray, name: str) -> np.ndarray:
    """A float image's values (H, W) to linear grey (H, W) float64, read by their range
    (FLOAT_FULL_SCALES); NaN, infinite, negative or too large values are refused."""
    bad = ~np.isfinite(values)
    if np.any(bad):
        raise ValueError(f"{name}: the float image holds NaN or infinite values ({int(bad.sum())} "
                         f"pixels); allowed: finite values from 0 (0 to 1, 0 to {MAX_8BIT} or 0 "
                         f"to {MAX_16BIT}). Fix those pixels, or re-export the image as a 16-bit "
                         "PNG.")
    low, high = float(values.min()), float(values.max())
    if low < 0:
        raise ValueError(f"{name}: the float image holds values from {low:g} to {high:g}; "
                         f"allowed: 0 and above (light is not negative: 0 to 1, 0 to {MAX_8BIT} "
                         f"or 0 to {MAX_16BIT}). Clip it at 0, or re-export the image as a 16-bit "
                         "PNG.")
    scale = next((s for s in FLOAT_FULL_SCALES if high <= s * (1 + FLOAT_SLACK)), None)
    if scale is None:
        raise ValueError(f"{name}: the float image holds values up to {high:g}; allowed: 0 to 1 "
                         f"(sRGB), or 8- or 16-bit codes (up to {MAX_8BIT} or {MAX_16BIT}). Scale "
                         "it into 0 to 1 (divide by its maximum), or re-export it as a 16-bit PNG.")
    if scale > 1:
        # 0..1 is the convention for float images; larger values are integer codes stored as
        # floats (a common export), so the image is scaled rather than clipped to white.
        warnings.warn(f"target image {name} is a float image with values from {low:g} to "
                      f"{high:g}, above 1: read as codes from 0 to {scale} (divided by "
                      f"{scale}). Give values from 0 to 1 (sRGB), or a PNG, to avoid the guess.",
                      TargetWarning, stacklevel=4)
    return srgb_to_linear(np.clip(values / scale, 0.0, 1.0))


def _composite(linear: np.ndarray, coverage: np.ndarray, name: str,
               alpha: AlphaBackground | None) -> np.ndarray:
    """Linear RGB (3, H, W) with its alpha coverage (H, W) in [0, 1] composited on alpha's
    background (None: black, warned); "refuse" refuses any pixel not fully opaque."""
    partial = coverage < 1
    if not np.any(partial):
        return linear
    share = f"{np.mean(partial):.1%} of its pixels"
    if alpha == "refuse":
        raise ValueError(f"{name}: the image is transparent or partly transparent in {share} "
                         "(alpha below full); allowed with --alpha refuse: none. Flatten it onto "
                         "a background in an image editor, or give --alpha black or --alpha "
                         "white.")
    if alpha is None:
        warnings.warn(f"target image {name} is transparent in {share}; composited on black "
                      "(no light on a display). Give --alpha white to composite on white, "
                      "--alpha black to accept black, or --alpha refuse to stop.",
                      TargetWarning, stacklevel=4)
    background = ALPHA_BACKGROUND_VALUES[alpha or "black"]
    # Alpha is coverage, a linear quantity: composite in linear light.
    return linear * coverage + background * (1.0 - coverage)


def _linear_rgb(image: Image.Image, name: str,
                alpha: AlphaBackground | None = None) -> np.ndarray:
    """A loaded Pillow image to linear RGB (3, H, W) float64, alpha composited on alpha's
    background (_composite)."""
    if image.mode in WIDE_GREY_MODES:
        # 16-bit greyscale keeps its full precision; Pillow gives these as 0..65535 integers.
        codes = np.clip(np.asarray(image), 0, MAX_16BIT).astype(np.intp)
        return np.repeat(_decoding_table(MAX_16BIT)[codes][None], 3, axis=0)
    if image.mode == "F":
        grey = _float_grey(np.asarray(image, dtype=np.float64), name)
        return np.repeat(grey[None], 3, axis=0)
    has_alpha = image.has_transparency_data
    try:
        # Palette, CMYK (Pillow's simple conversion), YCbCr, 1-bit, LA, ... all become 8-bit RGB(A).
        converted = image.convert("RGBA" if has_alpha else "RGB")
    except (ValueError, OSError) as error:
        raise ValueError(f"{name}: colour mode {image.mode} is not supported ({error}). "
                         f"{REEXPORT}") from error
    codes = np.asarray(converted).transpose(2, 0, 1)
    linear = _decoding_table(MAX_8BIT)[codes[:3]]
    if has_alpha:
        linear = _composite(linear, codes[3] / MAX_8BIT, name, alpha)
    return linear


def _choose_frame(opened: Image.Image, name: str, frame: int | None) -> None:
    """Seek `opened` to `frame` (None: the first, warned when there are several)."""
    try:
        frames = int(getattr(opened, "n_frames", 1))
    except (OSError, SyntaxError, ValueError, EOFError, zlib.error) as error:
        raise ValueError(f"{name}: its frames cannot be counted ({error}); the file is probably "
                         f"truncated or corrupt. {REEXPORT}") from error
    if frame is None:
        if frames > 1:
            warnings.warn(f"target image {name} is an animation (or a multi-page file) of "
                          f"{frames} frames; the first (--frame 0) is used. Give --frame N (0 to "
                          f"{frames - 1}) to choose one, or export one frame as PNG.",
                          TargetWarning, stacklevel=3)
        return
    if frame >= frames:
        raise ValueError(f"{name}: --frame {frame} is out of range; the file has {frames} "
                         f"frame(s), numbered 0 to {frames - 1}. Give --frame from 0 to "
                         f"{frames - 1}.")
    if frame > 0:
        try:
            opened.seek(frame)
        except (OSError, SyntaxError, ValueError, EOFError, zlib.error) as error:
            raise ValueError(f"{name}: frame {frame} cannot be read ({error}); the file is "
                             f"probably truncated or corrupt. {REEXPORT}") from error


def decode_image(data: bytes, name: str, max_pixels: int = MAX_IMAGE_PIXELS, *,
                 alpha: AlphaBackground | None = None, frame: int | None = None) -> np.ndarray:
    """Decode an image file's bytes to linear-light RGB, float64 (3, H, W) in [0, 1], row 0 top.

    Reads what Pillow reads (PNG, JPEG, ...). sRGB is assumed (embedded ICC profiles are ignored);
    the EXIF orientation is applied so the image is upright. 16-bit greyscale keeps its
    precision; 16-bit colour PNG is read at 8 bits by Pillow. A float image (e.g. a 32-bit float
    TIFF) is read by its range: up to 1 as sRGB in [0, 1], up to 255 or 65535 as 8- or 16-bit
    codes (scaled, with a TargetWarning); NaN, infinite, negative or larger values are refused.
    alpha: transparent pixels are composited, in linear light, on "black" or "white", or
    "refuse"d; None: on black with a TargetWarning. frame: the frame of an animation to use
    (0 the first); None: the first, with a TargetWarning when there are several.
    `name` (usually the file name) is only used in messages. Raises ValueError, naming `name`,
    for empty, unreadable, truncated, zero-sized or larger than max_pixels images; the size
    is checked from the header, before decoding.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise TypeError(f"{name}: decode_image takes the file's bytes, got {type(data).__name__}")
    if not (isinstance(max_pixels, int) and not isinstance(max_pixels, bool) and max_pixels > 0):
        raise ValueError(f"max_pixels = {max_pixels!r} must be a positive whole number of pixels, "
                         f"e.g. {MAX_IMAGE_PIXELS}.")
    TargetOptions(alpha=alpha, frame=frame)  # refuses a bad alpha or frame before decoding
    data = bytes(data)
    if len(data) == 0:
        raise ValueError(f"{name}: the file is empty (0 bytes). Check the path, or re-export the "
                         "image as PNG.")
    with warnings.catch_warnings():
        # Pillow's own bomb warning is replaced by the max_pixels check below; its global
        # Image.MAX_IMAGE_PIXELS is left as it is (it still refuses images over twice its limit).
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        warnings.filterwarnings("ignore", module=PILLOW_MODULES)
        try:
            opened = Image.open(io.BytesIO(data))
        except Image.DecompressionBombError as error:
            raise ValueError(f"{name}: the image is too large ({error}). Downscale it below "
                             f"{max_pixels / 1e6:g} megapixels and try again.") from error
        except (UnidentifiedImageError, OSError, SyntaxError, ValueError, EOFError) as error:
            raise ValueError(_unreadable_message(name, data, error)) from error
        with opened:
            width, height = opened.size
            if width == 0 or height == 0:
                raise ValueError(f"{name}: the image has zero size ({width} x {height} pixels). "
                                 f"{REEXPORT}")
            if width * height > max_pixels:
                raise ValueError(_too_large_message(name, width, height, max_pixels))
            _choose_frame(opened, name, frame)
            try:
                # Truncated files raise here ("image file is truncated"): never load them anyway.
                opened.load()
                upright = ImageOps.exif_transpose(opened)
            except Image.DecompressionBombError as error:
                raise ValueError(f"{name}: the image is too large ({error}). Downscale it below "
                                 f"{max_pixels / 1e6:g} megapixels and try again.") from error
            except (OSError, SyntaxError, ValueError, EOFError, zlib.error) as error:
                raise ValueError(f"{name}: the image data cannot be decoded ({error}); the file "
                                 f"is probably truncated or corrupt. {REEXPORT}") from error
            return np.ascontiguousarray(_linear_rgb(upright, name, alpha))
