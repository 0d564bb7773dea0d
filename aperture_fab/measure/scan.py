"""A scan file (bytes) as a grey transmission image: 8- or 16-bit, grey or RGB, PNG through
pypng (which reads 16-bit colour), other formats (TIFF, BMP) through Pillow.

The scan must be linear in light (a scanner's "gamma 1.0" or raw 16-bit mode) or sRGB-encoded
(say so: `encoding="srgb"` decodes it): the edge fit assumes that a pixel's value is the light
through it, so a gamma curve left in would bias every radius.
"""

from __future__ import annotations

import io
from typing import Literal

import numpy as np
import png
from PIL import Image, UnidentifiedImageError

from aperture_fab.io.images import srgb_to_linear

__all__ = ["MAX_SCAN_PIXELS", "ScanEncoding", "decode_scan"]

ScanEncoding = Literal["linear", "srgb"]
#: Largest scan read (150 megapixels: a 60 mm plate at 4800 dpi); a larger file is refused
#: before it is decoded (a decompression bomb, or a scan of the whole bed at full resolution).
MAX_SCAN_PIXELS = 150_000_000
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: Pillow modes read as grey or colour, with their full scale.
PILLOW_FULL_SCALE = {"1": 1, "L": 255, "P": 255, "RGB": 255, "RGBA": 255, "LA": 255,
                     "I;16": 65535, "I;16B": 65535, "I;16L": 65535, "I": 65535, "F": 1}


def _too_large(name: str, width: int, height: int) -> ValueError:
    return ValueError(f"scan {name} is {width} x {height} pixels, over the {MAX_SCAN_PIXELS:,} "
                      "read; crop the scan to the plate (a few mm of border) or scan at a lower "
                      "resolution.")


def _png_codes(data: bytes, name: str) -> tuple[np.ndarray, int]:
    reader = png.Reader(bytes=data)
    width, height, rows, info = reader.asDirect()
    if width * height > MAX_SCAN_PIXELS:
        raise _too_large(name, width, height)
    planes = int(info["planes"])
    codes = np.vstack([np.asarray(row, dtype=np.float64) for row in rows])
    codes = codes.reshape(height, width, planes)
    if info.get("alpha"):
        codes = codes[..., :-1]
    return codes, 2 ** int(info["bitdepth"]) - 1


def _pillow_codes(data: bytes, name: str) -> tuple[np.ndarray, int]:
    Image.MAX_IMAGE_PIXELS = None  # checked below, by our own limit
    with Image.open(io.BytesIO(data)) as opened:
        width, height = opened.size
        if width * height > MAX_SCAN_PIXELS:
            raise _too_large(name, width, height)
        mode = opened.mode
        picture: Image.Image = opened
        if mode not in PILLOW_FULL_SCALE:
            picture, mode = opened.convert("RGB"), "RGB"
        elif mode in ("P", "LA", "RGBA"):
            picture = opened.convert("RGB" if mode != "LA" else "L")
        codes = np.asarray(picture, dtype=np.float64)
    full = PILLOW_FULL_SCALE[mode]
    if mode == "F":
        full = MAX_FLOAT_SCALE if codes.max(initial=0) > 1 else 1
    return codes.reshape(codes.shape[0], codes.shape[1], -1), full


#: A float scan with values above 1 holds 16-bit codes.
MAX_FLOAT_SCALE = 65535


def decode_scan(data: bytes, name: str, encoding: ScanEncoding = "linear") -> np.ndarray:
    """The scan as (H, W) float64 grey light in [0, 1] (RGB channels averaged: the back light
    is white, and averaging lowers the noise). ValueError naming the file when it is empty, not
    an image, or too large."""
    if not data:
        raise ValueError(f"scan {name} is empty (0 bytes); give the scanner's image file "
                         "(PNG or TIFF, 8 or 16 bit).")
    try:
        codes, full = (_png_codes(data, name) if data.startswith(PNG_SIGNATURE)
                       else _pillow_codes(data, name))
    except (png.Error, UnidentifiedImageError, OSError, SyntaxError, EOFError) as err:
        raise ValueError(f"scan {name} is not a readable image ({type(err).__name__}: {err}); "
                         "give the scanner's image file (PNG or TIFF, 8 or 16 bit, grey or "
                         "RGB), saved whole.") from err
    grey = codes.mean(axis=2) / full
    if not np.all(np.isfinite(grey)):
        raise ValueError(f"scan {name} holds values that are not finite numbers; save it again "
                         "as an 8- or 16-bit PNG or TIFF.")
    grey = np.clip(grey, 0.0, 1.0)
    return srgb_to_linear(grey) if encoding == "srgb" else grey
