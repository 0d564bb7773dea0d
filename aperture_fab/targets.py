"""Procedural example targets: glyphs, pixel art, a natural-looking scene, test patterns.

Every function returns a square linear-light RGB image, float64 (3, size, size) in [0, 1], row 0
the top, and is deterministic: the same arguments (and seed) give the same pixels.
"""

from __future__ import annotations

import string
from collections.abc import Callable
from functools import partial

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from aperture_fab.io.images import srgb_to_linear

__all__ = [
    "EXAMPLES",
    "asymmetric_marker",
    "checker",
    "digit",
    "line_pairs",
    "natural",
    "pixel_art",
    "star",
]

#: Largest target side these generators make; beyond it a value is a mistake.
MAX_TARGET_SIZE = 2048
#: Supersampled drawings are kept at most this many pixels across (memory), so large targets
#: are drawn with a smaller supersampling factor.
MAX_RENDER_PX = 2048

#: MNIST puts each digit in a 20 x 20 box centred in a 28 x 28 image.
GLYPH_BOX_FRACTION = 20 / 28
#: Glyphs and the natural scene are drawn this many times finer, then area averaged (antialias).
GLYPH_SUPERSAMPLE = 8
NATURAL_SUPERSAMPLE = 4
#: Pen width as a fraction of the font size: thickens the font's strokes to MNIST's pen.
GLYPH_STROKE_FRACTION = 1 / 40
GLYPH_CHARACTERS = frozenset(string.ascii_letters + string.digits + string.punctuation)

#: Pixel art: a house, a tree, the sun and a cloud on a 16 x 16 grid (row 0 the top).
PIXEL_ART_ROWS = (
    ".YYY......CCC...",
    "YYYYY....CCCCC..",
    "YYYYY...........",
    ".YYY.......TTT..",
    "..........TTTTT.",
    "....BB....TTTTT.",
    "...BBBB...TTTTT.",
    "..BBBBBB...TTT..",
    ".BBBBBBBB...K...",
    "..RRRRRR....K...",
    "..RWWRRR....K...",
    "..RWWRDR....K...",
    "..RRRRDR....K...",
    "GGGGGGGGGGGGGGGG",
    "GGGGGGGGGGGGGGGG",
    "GGGGGGGGGGGGGGGG",
)
#: Saturated sRGB 8-bit colours of the pixel-art palette.
PIXEL_ART_PALETTE = {
    ".": (40, 150, 255),   # sky
    "Y": (255, 215, 0),    # sun
    "C": (255, 255, 255),  # cloud
    "B": (150, 40, 20),    # roof
    "R": (230, 30, 30),    # wall
    "W": (255, 255, 100),  # lit window
    "D": (90, 45, 10),     # door
    "T": (0, 160, 40),     # leaves
    "K": (110, 60, 20),    # trunk
    "G": (60, 210, 40),    # grass
}

#: The letter F on an 8 x 8 grid: no flip or half-turn maps it onto itself, so a view that shows
#: it as drawn is upright and unmirrored.
MARKER_ROWS = (
    "........",
    ".######.",
    ".######.",
    ".##.....",
    ".#####..",
    ".##.....",
    ".##.....",
    "........",
)

#: Natural scene colours, sRGB 8-bit.
SKY_TOP = (30, 80, 190)
SKY_HORIZON = (250, 205, 160)
SUN = (255, 245, 200)
FAR_MOUNTAINS = (95, 105, 150)
NEAR_HILLS_TOP = (70, 140, 50)
NEAR_HILLS_BOTTOM = (20, 60, 20)
PINE = (10, 70, 30)
#: Natural scene geometry in image-height units (0 top, 1 bottom).
SUN_CENTRE = (0.72, 0.30)
SUN_RADIUS = 0.07
SUN_GLOW_RADIUS = 0.2
SUN_GLOW_STRENGTH = 0.35
FAR_RIDGE = 0.55
FAR_RIDGE_AMPLITUDE = 0.12
NEAR_RIDGE = 0.75
NEAR_RIDGE_AMPLITUDE = 0.05
RIDGE_OCTAVES = 6
PINE_COUNT = 3
PINE_HEIGHT = 0.16
PINE_HALF_WIDTH = 0.045


def _check_size(name: str, size: int, minimum: int) -> None:
    if not (isinstance(size, int) and not isinstance(size, bool)):
        raise TypeError(f"{name} size must be a whole number of pixels, got {size!r}")
    if not minimum <= size <= MAX_TARGET_SIZE:
        raise ValueError(f"{name} size = {size} is out of range; allowed: {minimum} to "
                         f"{MAX_TARGET_SIZE} pixels.")


def _linear(colour: tuple[int, int, int]) -> np.ndarray:
    """An sRGB 8-bit colour to linear RGB, shape (3,)."""
    return srgb_to_linear(np.asarray(colour, dtype=np.float64) / 255)


def _paint(colour: tuple[int, int, int]) -> np.ndarray:
    """An sRGB 8-bit colour as linear RGB of shape (3, 1, 1), to broadcast over an image."""
    return _linear(colour).reshape(3, 1, 1)


def _from_grid(rows: tuple[str, ...], palette: dict[str, tuple[int, int, int]],
               size: int) -> np.ndarray:
    """A character grid to a (3, size, size) image, nearest cell per pixel (hard edges)."""
    colours = np.stack([_linear(palette[ch]) for row in rows for ch in row])
    cells = colours.reshape(len(rows), len(rows[0]), 3)
    row_index = (np.arange(size) * len(rows)) // size
    col_index = (np.arange(size) * len(rows[0])) // size
    return np.ascontiguousarray(cells[row_index][:, col_index].transpose(2, 0, 1))


def _supersampling(size: int, preferred: int) -> int:
    """Supersampling factor for a target of side size: preferred, less for large targets."""
    return max(1, min(preferred, MAX_RENDER_PX // size))


def _area_average(fine: np.ndarray, factor: int) -> np.ndarray:
    """Average factor x factor blocks of the last two axes (exact box downsampling)."""
    *lead, height, width = fine.shape
    blocks = fine.reshape(*lead, height // factor, factor, width // factor, factor)
    return blocks.mean(axis=(-3, -1))


def _glyph_mask(char: str, box_px: int) -> Image.Image:
    """An 8-bit coverage mask of char, cropped to its ink and scaled to fit box_px."""
    font = ImageFont.load_default(size=box_px)
    canvas_px = 3 * box_px
    mask = Image.new("L", (canvas_px, canvas_px))
    draw = ImageDraw.Draw(mask)
    if isinstance(font, ImageFont.FreeTypeFont):
        stroke = max(1, round(box_px * GLYPH_STROKE_FRACTION))
        draw.text((canvas_px // 2, canvas_px // 2), char, fill=255, font=font, anchor="mm",
                  stroke_width=stroke, stroke_fill=255)
    else:
        # Without FreeType Pillow's default font is a small bitmap: draw it, then enlarge.
        draw.text((canvas_px // 4, canvas_px // 4), char, fill=255, font=font)
    ink = mask.getbbox()
    if ink is None:
        raise ValueError(f"digit char = {char!r} draws nothing; give a letter or digit.")
    glyph = mask.crop(ink)
    scale = box_px / max(glyph.size)
    fitted = (max(1, round(glyph.width * scale)), max(1, round(glyph.height * scale)))
    return glyph.resize(fitted, Image.Resampling.LANCZOS)


def digit(char: str, size: int = 28) -> np.ndarray:
    """A white glyph (digit, letter or sign) on black, like MNIST/EMNIST: (3, size, size).

    Drawn with Pillow's default font (FreeType when available), fitted to a 20/28 box, centred,
    antialiased by area averaging a drawing up to 8 times finer. Glyph coverage is linear light.
    """
    if not isinstance(char, str):
        raise TypeError(f"digit char must be a str of one character, got {char!r}")
    if not (len(char) == 1 and char in GLYPH_CHARACTERS):
        raise ValueError(f"digit char = {char!r} is not allowed; give one printable ASCII "
                         "character that is not a space, e.g. '3' or 'A'.")
    _check_size("digit", size, 8)
    factor = _supersampling(size, GLYPH_SUPERSAMPLE)
    fine_px = size * factor
    glyph = _glyph_mask(char, round(GLYPH_BOX_FRACTION * fine_px))
    canvas = Image.new("L", (fine_px, fine_px))
    canvas.paste(glyph, ((fine_px - glyph.width) // 2, (fine_px - glyph.height) // 2))
    coverage = _area_average(np.asarray(canvas, dtype=np.float64) / 255, factor)
    return np.repeat(coverage[None], 3, axis=0)


def pixel_art(size: int = 32) -> np.ndarray:
    """A colourful 16 x 16 pixel-art scene (house, tree, sun, cloud) with hard pixel edges.

    Each art pixel becomes size / 16 image pixels (nearest cell when size is not a multiple).
    """
    _check_size("pixel_art", size, len(PIXEL_ART_ROWS))
    return _from_grid(PIXEL_ART_ROWS, PIXEL_ART_PALETTE, size)


def asymmetric_marker(size: int = 32) -> np.ndarray:
    """A white letter F on black, drawn from blocks (no font): tells upright and unmirrored views.

    The F's stem is on the left and its bars point right from the top and the middle.
    """
    _check_size("asymmetric_marker", size, len(MARKER_ROWS))
    return _from_grid(MARKER_ROWS, {".": (0, 0, 0), "#": (255, 255, 255)}, size)


def checker(size: int = 32, cells: int = 8) -> np.ndarray:
    """A black and white checkerboard of cells x cells squares, the top-left one white."""
    _check_size("checker", size, 1)
    if not (isinstance(cells, int) and not isinstance(cells, bool) and 1 <= cells <= size):
        raise ValueError(f"checker cells = {cells!r} is out of range; allowed: 1 to size "
                         f"({size}).")
    cell = (np.arange(size) * cells) // size
    white = (cell[:, None] + cell[None, :]) % 2 == 0
    return np.repeat(white[None].astype(np.float64), 3, axis=0)


#: Bar periods (as shares of the image side) of the line-pair pattern's groups, coarse to fine.
LINE_PERIODS = (1 / 4, 1 / 8, 1 / 16)


def line_pairs(size: int = 64) -> np.ndarray:
    """A resolution pattern: white bars on black, in three groups of decreasing period (a
    quarter, an eighth and a sixteenth of the side), vertical bars in the top half and
    horizontal ones in the bottom half, each group in its own column."""
    _check_size("line_pairs", size, 2 * round(1 / LINE_PERIODS[-1]))
    u = (np.arange(size) + 0.5) / size
    image = np.zeros((size, size))
    width = 1 / len(LINE_PERIODS)
    for k, period in enumerate(LINE_PERIODS):
        column = (u >= k * width) & (u < (k + 1) * width)
        bars = ((u - k * width) % period) < period / 2
        top, bottom = u < 0.5, u >= 0.5
        image[np.ix_(top, column)] = bars[column][None, :]
        image[np.ix_(bottom, column)] = ((u % period) < period / 2)[bottom][:, None]
    return np.repeat(image[None], 3, axis=0)


#: Siemens star: white and black sector pairs (cycles) around the centre, filling the disk
#: inscribed in the image (black outside); drawn this many times finer, then area averaged.
STAR_CYCLES = 18
STAR_SUPERSAMPLE = 8


def star(size: int = 128, cycles: int = STAR_CYCLES) -> np.ndarray:
    """A Siemens star: `cycles` white sectors alternating with black ones around the centre, in
    the disk inscribed in the image, black outside. Its spatial frequency grows toward the
    centre without limit, so every imaging system blurs it there: a test of dense edges at every
    orientation. Antialiased by area averaging a drawing up to 8 times finer."""
    _check_size("star", size, 16)
    if not (isinstance(cycles, int) and not isinstance(cycles, bool) and 2 <= cycles <= size):
        raise ValueError(f"star cycles = {cycles!r} is out of range; allowed: 2 to size "
                         f"({size}).")
    factor = _supersampling(size, STAR_SUPERSAMPLE)
    fine_px = size * factor
    centres = (np.arange(fine_px) + 0.5) / fine_px - 0.5  # image-width units about the centre
    y, x = centres[:, None], centres[None, :]
    angle = np.arctan2(-y, x)  # counter-clockwise from +x, row 0 the top
    white = (np.floor(angle * cycles / np.pi) % 2 == 0) & (np.hypot(x, y) <= 0.5)
    coverage = _area_average(white.astype(np.float64), factor)
    return np.repeat(coverage[None], 3, axis=0)


def _ridge(x: np.ndarray, rng: np.random.Generator, base: float, amplitude: float) -> np.ndarray:
    """A mountain ridge height (0 top, 1 bottom) along x in [0, 1]: octaves of random sines."""
    height = np.full_like(x, base)
    for octave in range(RIDGE_OCTAVES):
        frequency = 2.0**octave
        phase = rng.uniform(0, 2 * np.pi)
        height += amplitude * 0.5**octave * np.sin(2 * np.pi * frequency * x + phase)
    return height


def natural(size: int = 128, seed: int = 0) -> np.ndarray:
    """A natural-looking colour landscape: smooth sky and glow, a sharp sun disk, noisy mountain
    ridges, shaded hills and pine trees. The seed sets the ridges and the trees."""
    _check_size("natural", size, 8)
    rng = np.random.default_rng(seed)
    factor = _supersampling(size, NATURAL_SUPERSAMPLE)
    fine_px = size * factor
    # Pixel centres in image-width units; y grows downward (row 0 is the top).
    centres = (np.arange(fine_px) + 0.5) / fine_px
    y, x = centres[None, :, None], centres[None, None, :]

    # Sky: a smooth vertical blend in linear light, brightened around the sun.
    blend = np.clip(y / FAR_RIDGE, 0.0, 1.0) ** 1.5
    image = (1 - blend) * _paint(SKY_TOP) + blend * _paint(SKY_HORIZON)
    distance = np.hypot(x - SUN_CENTRE[0], y - SUN_CENTRE[1])
    glow = SUN_GLOW_STRENGTH * np.exp(-((distance / SUN_GLOW_RADIUS) ** 2))
    image = image + glow * (_paint(SUN) - image)
    image = np.where(distance <= SUN_RADIUS, _paint(SUN), image)

    # Mountains and hills: sharp silhouettes with noisy ridges; hills darken downward.
    far_top = _ridge(x, rng, FAR_RIDGE, FAR_RIDGE_AMPLITUDE)
    image = np.where(y >= far_top, _paint(FAR_MOUNTAINS), image)
    near_top = _ridge(x, rng, NEAR_RIDGE, NEAR_RIDGE_AMPLITUDE)
    depth = np.clip((y - near_top) / (1 - NEAR_RIDGE + NEAR_RIDGE_AMPLITUDE), 0.0, 1.0)
    hills = (1 - depth) * _paint(NEAR_HILLS_TOP) + depth * _paint(NEAR_HILLS_BOTTOM)
    image = np.where(y >= near_top, hills, image)

    # Pine trees standing on the hills: triangles with hard edges.
    tree_base = NEAR_RIDGE + 1.5 * NEAR_RIDGE_AMPLITUDE
    for tree_x in rng.uniform(0.1, 0.9, PINE_COUNT):
        rise = (tree_base - y) / PINE_HEIGHT
        inside = (rise >= 0) & (rise <= 1) & (np.abs(x - tree_x) <= PINE_HALF_WIDTH * (1 - rise))
        image = np.where(inside, _paint(PINE), image)

    return np.clip(_area_average(image, factor), 0.0, 1.0)


#: Named example targets, as made by examples/make_targets.py.
EXAMPLES: dict[str, Callable[[], np.ndarray]] = {
    "digit-3": partial(digit, "3"),
    "letter-A": partial(digit, "A"),
    "pixel-art": pixel_art,
    "natural": natural,
    "checker": checker,
    "line-pairs": line_pairs,
    "marker-F": asymmetric_marker,
    "star": star,
}
