"""Target images: linear-light RGB arrays, resampled, encoded as PNG, fitted to a display (files
are decoded in aperture_fab.io.decode).

Inside the model colour is linear light in [0, 1]; files are sRGB (docs/design.md section 2), so
this module converts at the edge. An image array is float64 of shape (C, H, W): C = 3 (RGB) or 1
(grey), row 0 the top, column 0 the left. This module does not touch the filesystem: it takes and
returns bytes; the caller reads and writes files.

A file is made a target by TargetOptions (the CLI's --alpha, --fit and --frame): transparent
pixels are composited on black (warned) or white, or refused; an animation gives its first frame
(warned) or the one asked for; a target of another aspect than the display's is stretched
(warned), padded with black or cropped (fit_target). Float images are read by their range.
"""

from __future__ import annotations

import io
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import png  # pypng: 16-bit PNG, which Pillow cannot write in colour
from PIL import Image

__all__ = [
    "ALPHA_BACKGROUNDS",
    "TARGET_FITS",
    "AlphaBackground",
    "PngBits",
    "ResampleKernel",
    "TargetFit",
    "TargetOptions",
    "TargetWarning",
    "check_target",
    "encode_png",
    "fit_target",
    "is_grey",
    "linear_to_srgb",
    "prepare_targets",
    "resample",
    "srgb_to_linear",
]

ResampleKernel = Literal["box", "bilinear"]
RESAMPLE_KERNELS: tuple[ResampleKernel, ...] = ("box", "bilinear")
PngBits = Literal[8, 16]

#: What transparent pixels are composited on, or "refuse" to refuse an image that has any.
AlphaBackground = Literal["black", "white", "refuse"]
ALPHA_BACKGROUNDS: tuple[AlphaBackground, ...] = ("black", "white", "refuse")
#: Linear value of each background: black is "no light" on a display, white its full light.
ALPHA_BACKGROUND_VALUES: dict[str, float] = {"black": 0.0, "white": 1.0}
#: How a target of another aspect than the display's is made to fit: stretched (every pixel
#: used, the picture distorted), padded with black (letterbox, centred) or cropped (centre).
TargetFit = Literal["stretch", "pad", "crop"]
TARGET_FITS: tuple[TargetFit, ...] = ("stretch", "pad", "crop")


#: IEC 61966-2-1 sRGB transfer curve: a linear toe below the thresholds, a 2.4 power above.
SRGB_ENCODED_THRESHOLD = 0.04045
SRGB_LINEAR_THRESHOLD = 0.0031308
SRGB_TOE_SLOPE = 12.92
SRGB_OFFSET = 0.055
SRGB_GAMMA = 2.4

#: Full scale of 8-bit and 16-bit samples.
MAX_8BIT = 255
MAX_16BIT = 65535
#: zlib level of 16-bit PNG data (the smallest files; pypng's default is zlib's, 6).
PNG_16BIT_LEVEL = 9

#: Smallest target side in pixels: a smaller one holds no picture to resample.
MIN_TARGET_PIXELS = 8
#: A target whose aspect ratio differs from the display's by more than this share is stretched
#: visibly (3 %: a circle becomes an ellipse one can see), so the user is warned.
ASPECT_TOLERANCE = 0.03


class TargetWarning(UserWarning):
    """A target that is used, but not as given: stretched to the display's aspect, its
    transparency composited on black, one frame of an animation, float values rescaled."""


@dataclass(frozen=True)
class TargetOptions:
    """How a target file becomes a target (the CLI's --alpha, --fit and --frame).

    alpha: the background transparent pixels are composited on, or "refuse"; None: black, with
        a TargetWarning (black is "no light" on a display, the image's own transparent areas).
    fit: for a target of another aspect than the display's (fit_target); "stretch", the
        default, is warned by check_target.
    frame: the frame of an animation (or page of a multi-page file) to use, 0 the first; None:
        the first, with a TargetWarning when there are several.
    """

    alpha: AlphaBackground | None = None
    fit: TargetFit = "stretch"
    frame: int | None = None

    def __post_init__(self) -> None:
        if self.alpha is not None and self.alpha not in ALPHA_BACKGROUNDS:
            raise ValueError(f"--alpha {self.alpha!r} is not allowed; choose one of "
                             f"{', '.join(ALPHA_BACKGROUNDS)}.")
        if self.fit not in TARGET_FITS:
            raise ValueError(f"--fit {self.fit!r} is not allowed; choose one of "
                             f"{', '.join(TARGET_FITS)}.")
        if self.frame is not None and not (isinstance(self.frame, int)
                                           and not isinstance(self.frame, bool)
                                           and self.frame >= 0):
            raise ValueError(f"--frame {self.frame!r} is not allowed; give a whole number from "
                             "0 (the first frame).")

    def changes(self) -> str | None:
        """The options that give other targets than the defaults do, in words (e.g. "--fit
        pad"), or None: a checkpoint records them so that --resume sees a change."""
        chosen = [f"--alpha {self.alpha}" if self.alpha not in (None, "black") else "",
                  f"--fit {self.fit}" if self.fit != "stretch" else "",
                  f"--frame {self.frame}" if self.frame else ""]
        return " ".join(c for c in chosen if c) or None


#: Channels that differ by no more than this count as equal in is_grey.
GREY_TOLERANCE = 1e-9


def _check_unit_array(name: str, x: np.ndarray) -> np.ndarray:
    array = np.asarray(x, dtype=np.float64)
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} holds NaN or infinite values; give finite values in [0, 1].")
    if array.size and (array.min() < 0.0 or array.max() > 1.0):
        raise ValueError(
            f"{name} holds values from {array.min():g} to {array.max():g}; allowed: 0 to 1. "
            "Clip it first, e.g. np.clip(x, 0, 1), or normalise it by its maximum."
        )
    return array


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] to linear light in [0, 1] (IEC 61966-2-1), float64."""
    v = _check_unit_array("srgb_to_linear input", x)
    power = ((v + SRGB_OFFSET) / (1 + SRGB_OFFSET)) ** SRGB_GAMMA
    return np.where(v <= SRGB_ENCODED_THRESHOLD, v / SRGB_TOE_SLOPE, power)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """Linear light in [0, 1] to sRGB-encoded values in [0, 1] (IEC 61966-2-1), float64."""
    v = _check_unit_array("linear_to_srgb input", x)
    power = (1 + SRGB_OFFSET) * v ** (1 / SRGB_GAMMA) - SRGB_OFFSET
    return np.where(v <= SRGB_LINEAR_THRESHOLD, v * SRGB_TOE_SLOPE, power)


def _check_image(name: str, image: np.ndarray) -> np.ndarray:
    if not isinstance(image, np.ndarray) or image.ndim != 3:
        shape = getattr(image, "shape", None)
        raise ValueError(f"{name} must be an array of shape (C, H, W), got shape {shape}.")
    if image.shape[1] == 0 or image.shape[2] == 0:
        raise ValueError(f"{name} has zero size, shape {image.shape}; give at least 1 x 1 pixels.")
    return image


def _axis_weights(n_in: int, n_out: int, kind: ResampleKernel) -> tuple[np.ndarray, np.ndarray]:
    """Sample indices (n_out, taps) int and weights (n_out, taps) float64, each row summing to 1.

    Pixel k of the output covers [k, k + 1) * n_in / n_out in input pixel units.
    box: the exact overlap area of each input pixel with the output pixel (area average).
    bilinear: a triangle filter of half-width max(1, n_in / n_out) input pixels (as Pillow's
    BILINEAR), truncated and renormalised at the borders.
    """
    scale = n_in / n_out
    if kind == "box":
        edges = np.arange(n_out + 1) * n_in / n_out
        low, high = edges[:-1, None], edges[1:, None]
        start = np.floor(edges[:-1]).astype(np.int64)
        taps = int(np.max(np.ceil(edges[1:]) - start))
        index = start[:, None] + np.arange(taps)
        weight = np.clip(np.minimum(index + 1, high) - np.maximum(index, low), 0.0, None)
    else:
        half_width = max(scale, 1.0)
        centre = (np.arange(n_out) + 0.5) * scale
        start = np.floor(centre - half_width - 0.5).astype(np.int64)
        taps = int(np.ceil(2 * half_width)) + 2
        index = start[:, None] + np.arange(taps)
        weight = np.clip(1.0 - np.abs(index + 0.5 - centre[:, None]) / half_width, 0.0, None)
    weight = np.where((index >= 0) & (index < n_in), weight, 0.0)
    index = np.clip(index, 0, n_in - 1)
    return index, weight / weight.sum(axis=1, keepdims=True)


def _resample_axis(image: np.ndarray, axis: int, n_out: int, kind: ResampleKernel) -> np.ndarray:
    n_in = image.shape[axis]
    if n_in == n_out:
        return image
    index, weight = _axis_weights(n_in, n_out, kind)
    shape = [1] * image.ndim
    shape[axis] = n_out
    out = np.zeros((*image.shape[:axis], n_out, *image.shape[axis + 1:]))
    for tap in range(index.shape[1]):
        out += weight[:, tap].reshape(shape) * np.take(image, index[:, tap], axis=axis)
    return out


def resample(image: np.ndarray, size: tuple[int, int],
             kernel: ResampleKernel = "box") -> np.ndarray:
    """Resample a linear image (C, H, W) to (C, ny, nx) for size = (nx, ny), float64 in [0, 1].

    Work in linear light. Separable kernels with non-negative weights, so the output stays within
    the input's range:
    - "box" (default): each output pixel is the exact area average of the input pixels it covers
      (pixels are uniformly lit squares). It preserves the mean of any image and keeps hard edges
      where they fall on output pixel edges; antialiasing on downsampling is the area average.
    - "bilinear": a triangle filter, widened when downsampling (antialiased, like Pillow's
      BILINEAR); smoother when enlarging.
    """
    # Not Pillow's resize (measured on the example targets, issue 21): on float ("F") images
    # its BOX weighs each input pixel by whether its centre falls in the output pixel, not by
    # the area they share (up to 0.75 off when enlarging by a fraction), and it keeps float32;
    # its BILINEAR matches "bilinear" here to 1e-7.
    source = _check_image("resample image", image)
    if not (isinstance(size, tuple) and len(size) == 2
            and all(isinstance(n, int) and not isinstance(n, bool) and n > 0 for n in size)):
        raise ValueError(f"resample size = {size!r} must be a pair of positive whole numbers "
                         "(nx, ny), e.g. (64, 64).")
    if kernel not in RESAMPLE_KERNELS:
        raise ValueError(f"resample kernel = {kernel!r} is not allowed; choose one of "
                         f"{', '.join(RESAMPLE_KERNELS)}.")
    values = np.asarray(source, dtype=np.float64)
    if not np.all(np.isfinite(values)):
        raise ValueError("resample image holds NaN or infinite values; give finite values.")
    nx, ny = size
    rows = _resample_axis(values, 1, ny, kernel)
    return np.clip(_resample_axis(rows, 2, nx, kernel), 0.0, 1.0)


def _png_16bit(samples: np.ndarray) -> bytes:
    """A 16-bit PNG from samples (H, W, C) uint16, C = 1 (grey) or 3 (RGB), written by pypng:
    Pillow cannot write 16-bit RGB (nor imageio, which writes PNG through Pillow). Unfiltered
    rows, zlib level 9, one IDAT chunk: the bytes aperture-fab wrote before it used pypng."""
    height, width, channels = samples.shape
    rows = samples.astype(">u2").reshape(height, width * channels).view(np.uint8)
    # pypng starts a new IDAT chunk past chunk_limit bytes of rows; the whole image keeps one.
    writer = png.Writer(width, height, greyscale=channels == 1, bitdepth=16,
                        compression=PNG_16BIT_LEVEL, chunk_limit=rows.size + height)
    buffer = io.BytesIO()
    # Packed rows are the samples as PNG stores them (big-endian); pypng adds the filter byte.
    writer.write_packed(buffer, (row.tobytes() for row in rows))
    return buffer.getvalue()


def encode_png(image: np.ndarray, bits: PngBits = 8) -> bytes:
    """Linear image (C, H, W) in [0, 1], C = 1 or 3, to sRGB PNG bytes of 8 or 16 bits."""
    source = _check_image("encode_png image", image)
    if source.shape[0] not in (1, 3):
        raise ValueError(f"encode_png image has {source.shape[0]} channels, shape "
                         f"{source.shape}; give 1 (grey) or 3 (RGB) channels.")
    if bits not in (8, 16):
        raise ValueError(f"encode_png bits = {bits!r} is not allowed; choose 8 or 16.")
    encoded = linear_to_srgb(_check_unit_array("encode_png image", source))
    if bits == 16:
        samples16 = np.rint(encoded * MAX_16BIT).astype(np.uint16).transpose(1, 2, 0)
        return _png_16bit(samples16)
    samples8 = np.rint(encoded * MAX_8BIT).astype(np.uint8).transpose(1, 2, 0)
    picture = Image.fromarray(samples8[:, :, 0] if samples8.shape[2] == 1 else samples8)
    buffer = io.BytesIO()
    picture.save(buffer, format="PNG", optimize=True)
    return buffer.getvalue()


def is_grey(image: np.ndarray) -> bool:
    """True when an image (C, H, W) is grey: one channel, or R, G and B equal within 1e-9."""
    source = _check_image("is_grey image", image)
    if source.shape[0] == 1:
        return True
    if source.shape[0] != 3:
        raise ValueError(f"is_grey image has {source.shape[0]} channels; give 1 or 3.")
    return bool(np.all(np.abs(source[0] - source[1]) <= GREY_TOLERANCE)
                and np.all(np.abs(source[0] - source[2]) <= GREY_TOLERANCE))


def check_target(image: np.ndarray, name: str, display_pixels: tuple[int, int]) -> None:
    """Refuse a target that cannot be judged, and warn (TargetWarning) when it will be
    stretched. image: (C, H, W) linear light; display_pixels: (W, H)."""
    height, width = image.shape[1:]
    if min(height, width) < MIN_TARGET_PIXELS:
        raise ValueError(f"target image {name} is {width} x {height} pixels; allowed: at least "
                         f"{MIN_TARGET_PIXELS} pixels per side (it is resampled onto the view and "
                         "display grids). Give a larger image.")
    # PSNR after the least-squares gain judges the shape of the light, and a black target has
    # none: the gain is 0 and the error 0 for any plate, a perfect score (the 200 dB floor)
    # that means nothing. Refused, as the figure of merit is undefined. A constant grey
    # target is kept: its PSNR honestly measures how evenly the plate lights the view.
    if not np.any(image > 0):
        raise ValueError(f"target image {name} is black everywhere (no light); a target must "
                         "show something to match. Give the image of what the eye should see.")
    shown = display_pixels[0] / display_pixels[1]
    aspect = width / height
    if abs(aspect / shown - 1) > ASPECT_TOLERANCE:
        warnings.warn(f"target image {name} is {width} x {height} pixels (aspect {aspect:.3g}) "
                      f"but the display is {display_pixels[0]} x {display_pixels[1]} (aspect "
                      f"{shown:.3g}); it will be stretched to fit (--fit stretch, the default). "
                      "Give --fit pad to letterbox it with black or --fit crop to crop its "
                      "centre, or crop or pad the file to the display's aspect.", TargetWarning,
                      stacklevel=3)


def fit_target(image: np.ndarray, display_pixels: tuple[int, int], fit: TargetFit) -> np.ndarray:
    """A target (C, H, W) made to the display's aspect (display_pixels: (W, H)), float64:
    "stretch" returns it as it is (prepare_targets stretches it, check_target warns); "pad"
    centres it on black (letterbox or pillarbox); "crop" keeps its centre. Centred to within
    half a pixel (an odd remainder goes to the bottom or right); its own pixels are kept, so
    the only resampling is prepare_targets'."""
    source = np.asarray(_check_image("fit_target image", image), dtype=np.float64)
    if fit not in TARGET_FITS:
        raise ValueError(f"--fit {fit!r} is not allowed; choose one of {', '.join(TARGET_FITS)}.")
    if fit == "stretch":
        return source
    height, width = source.shape[1:]
    shown = display_pixels[0] / display_pixels[1]
    # Width and height at the display's aspect that hold the image (pad) or lie in it (crop).
    wider = width / height > shown
    if fit == "pad":
        size = (width, round(width / shown)) if wider else (round(height * shown), height)
    else:
        size = (round(height * shown), height) if wider else (width, round(width / shown))
    size = (max(1, size[0]), max(1, size[1]))
    if fit == "crop":
        left, top = (width - size[0]) // 2, (height - size[1]) // 2
        return np.ascontiguousarray(source[:, top:top + size[1], left:left + size[0]])
    # Black is no light on a display: the bars show nothing, as a letterbox should.
    out = np.zeros((source.shape[0], size[1], size[0]))
    left, top = (size[0] - width) // 2, (size[1] - height) // 2
    out[:, top:top + height, left:left + width] = source
    return out


def prepare_targets(images: list[np.ndarray], view_pixels: tuple[int, int],
                    display_pixels: tuple[int, int], channels: int | None = None,
                    names: Sequence[str] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Targets on the view grid (T, C, ny, nx) and on the display grid (T, C, H, W), float64,
    each checked first (check_target; names: how errors name them, default by number).

    images: (C, H, W) linear light. C is 1 when every target is grey, else 3; `channels` fixes
    it when a saved design's display already has a channel count.
    """
    labels = [repr(names[n]) if names is not None else f"number {n + 1}"
              for n in range(len(images))]
    for label, image in zip(labels, images, strict=True):
        check_target(image, label, display_pixels)
    grey = all(is_grey(im) for im in images)
    want = channels if channels is not None else (1 if grey else 3)
    if want == 1 and not grey:
        colour = next(label for label, im in zip(labels, images, strict=True) if not is_grey(im))
        raise ValueError(f"target image {colour} has colour, but the design's display is grey "
                         "(one channel); give a grey target (convert it to greyscale), or "
                         "design again with colour targets.")
    prepared = [np.ascontiguousarray(im[:1] if want == 1 else
                                     np.broadcast_to(im, (3, *im.shape[1:]))) for im in images]
    return (np.stack([resample(im, view_pixels) for im in prepared]),
            np.stack([resample(im, display_pixels) for im in prepared]))
