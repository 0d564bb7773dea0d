"""The physical scene: display, plate, eye. Millimetres and radians; see docs/design.md section 2.

Axes: z is the optical axis, the display at z = 0, the plate's bottom face at z = gap, its top
face at z = gap + thickness, the eye's pupil at z = gap + thickness + eye_relief. x to the right,
y up, for the eye looking toward -z. Image row 0 is the top (+y), column 0 the left (-x).

A view direction is stored as (tan theta_x, tan theta_y): the ray from the pupil toward the
display moves laterally by that much per millimetre of depth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from aperture_fab.optics.eye_fields import EyeboxShape, check_fields
from aperture_fab.optics.eyes import ROTATION_MM

__all__ = [
    "HoleAxis",
    "Display",
    "EMISSIONS",
    "Emission",
    "Plate",
    "SUBPIXEL_LAYOUTS",
    "Subpixels",
    "Eye",
    "Scene",
    "display_fov_deg",
    "eyebox_margin_mm",
    "hole_radius_mm",
    "open_fraction_of",
]

HoleAxis = Literal["straight", "chief_ray"]
HOLE_AXES: tuple[HoleAxis, ...] = ("straight", "chief_ray")
#: RGB sub-pixel layouts: "none" (every channel fills the pixel), or vertical stripes a third
#: of the pixel wide in this order from left (-x) to right (+x).
Subpixels = Literal["none", "rgb_stripe", "bgr_stripe"]
SUBPIXEL_LAYOUTS: tuple[Subpixels, ...] = ("none", "rgb_stripe", "bgr_stripe")
#: Angular emission: "lambertian" (radiance independent of angle) or "cosine_power" (radiance
#: proportional to cos(theta)^emission_exponent, theta the emission angle in air).
Emission = Literal["lambertian", "cosine_power"]
EMISSIONS: tuple[Emission, ...] = ("lambertian", "cosine_power")
#: Cover glass limits: thicker than this is not a display's cover; indices of optical glasses
#: and plastics lie between these.
MAX_COVER_GLASS_MM = 10.0
COVER_GLASS_INDEX_RANGE = (1.0, 2.5)
DEFAULT_COVER_GLASS_INDEX = 1.5
#: Largest cos^k exponent: beyond it a panel emits in a pencil no eye position could use.
MAX_EMISSION_EXPONENT = 100.0
#: Channels of a striped RGB display.
SUBPIXEL_CHANNELS = 3

#: Largest sensible sizes: beyond these a value is almost surely a unit mistake (metres, microns).
MAX_SIZE_MM = 2000.0
MAX_PIXELS = 16384
MAX_FOV_DEG = 170.0


def check_positive(name: str, value: float, fix: str, upper: float = math.inf) -> None:
    """Raise ValueError naming the field unless 0 < value <= upper and finite."""
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        raise TypeError(f"{name} must be a number, got {value!r} ({type(value).__name__})")
    if not (math.isfinite(value) and 0 < value <= upper):
        allowed = f"0 < {name} <= {upper:g}" if math.isfinite(upper) else f"{name} > 0"
        raise ValueError(f"{name} = {value!r} is out of range; allowed: {allowed}. {fix}")


def _check_range(name: str, value: float, lo: float, hi: float, fix: str) -> None:
    """Raise ValueError naming the field unless lo <= value <= hi and finite."""
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        raise TypeError(f"{name} must be a number, got {value!r} ({type(value).__name__})")
    if not (math.isfinite(value) and lo <= value <= hi):
        raise ValueError(f"{name} = {value!r} is out of range; allowed: {lo:g} to {hi:g}. {fix}")


def check_pair(name: str, value: tuple, kind: type) -> None:
    if not (isinstance(value, tuple) and len(value) == 2):
        raise TypeError(f"{name} must be a pair (x, y), got {value!r}")
    for item in value:
        if kind is int and not (isinstance(item, int) and not isinstance(item, bool)):
            raise TypeError(f"{name} must hold whole numbers, got {value!r}")


@dataclass(frozen=True)
class Display:
    """A pixel display whose emitting surface is at z = 0, centred on the axis, emitting each
    pixel's value; see docs/model.md "Display-side optics".

    width_mm, height_mm: size of the active area (x, y).
    pixels: (nx, ny) pixel count; a pixel is a uniformly lit rectangle.
    cover_glass_mm: thickness of the cover glass over the emitting surface, occupying
        0 <= z <= cover_glass_mm inside the plate's gap (the gap stays measured from the
        emitting surface); 0: none.
    cover_glass_index: its refractive index (one for all channels: no dispersion).
    subpixels: "none" (each channel fills the pixel) or "rgb_stripe" / "bgr_stripe" (channel c
        emits from a vertical stripe a third of the pixel wide, offset (c - 1) / 3 pixel in x for
        R, G, B left to right, reversed for bgr); one-channel (grey) displays ignore it.
    emission: "lambertian" (radiance independent of angle) or "cosine_power" (radiance
        proportional to cos(theta)^emission_exponent, theta the emission angle in air).
    emission_exponent: k of "cosine_power" (unused by "lambertian").
    """

    width_mm: float
    height_mm: float
    pixels: tuple[int, int]
    cover_glass_mm: float = 0.0
    cover_glass_index: float = DEFAULT_COVER_GLASS_INDEX
    subpixels: Subpixels = "none"
    emission: Emission = "lambertian"
    emission_exponent: float = 1.0

    def __post_init__(self) -> None:
        fix = "Give the display's active area in millimetres."
        check_positive("display.width_mm", self.width_mm, fix, MAX_SIZE_MM)
        check_positive("display.height_mm", self.height_mm, fix, MAX_SIZE_MM)
        check_pair("display.pixels", self.pixels, int)
        for n in self.pixels:
            if not 1 <= n <= MAX_PIXELS:
                raise ValueError(
                    f"display.pixels = {self.pixels} is out of range; allowed: 1 to {MAX_PIXELS} "
                    "per axis. Give the pixel count of the area used, e.g. [400, 400]."
                )
        _check_range("display.cover_glass_mm", self.cover_glass_mm, 0.0, MAX_COVER_GLASS_MM,
                     "Give the cover glass's thickness in mm (a phone panel's is about 0.5), "
                     "or 0 for none.")
        lo, hi = COVER_GLASS_INDEX_RANGE
        _check_range("display.cover_glass_index", self.cover_glass_index, lo, hi,
                     "Give the glass's refractive index, e.g. 1.5 (about 1.52 for soda-lime "
                     "glass, 1.49 for PMMA).")
        if self.subpixels not in SUBPIXEL_LAYOUTS:
            raise ValueError(
                f"display.subpixels = {self.subpixels!r} is not allowed; choose one of "
                f"{', '.join(SUBPIXEL_LAYOUTS)}."
            )
        if self.emission not in EMISSIONS:
            raise ValueError(
                f"display.emission = {self.emission!r} is not allowed; choose one of "
                f"{', '.join(EMISSIONS)}."
            )
        _check_range("display.emission_exponent", self.emission_exponent, 0.0,
                     MAX_EMISSION_EXPONENT, "Give k of radiance ~ cos(theta)^k, e.g. 1 to 4 for "
                     "a panel that dims off axis.")

    @property
    def emission_power(self) -> float:
        """The exponent k of radiance ~ cos(theta)^k; 0 for a Lambertian display."""
        return self.emission_exponent if self.emission == "cosine_power" else 0.0

    @property
    def has_optics(self) -> bool:
        """Whether any display-side optics is on (cover glass, sub-pixels or falloff)."""
        return (self.cover_glass_mm > 0 or self.subpixels != "none"
                or self.emission_power > 0)

    def subpixel_offsets_px(self, channels: int) -> tuple[float, ...] | None:
        """Each channel's emitting-stripe centre, in pixels along +x from the pixel centre, for
        a display of `channels` channels; None when every channel fills the pixel (layout
        "none", or a grey display: its one channel drives all three stripes alike)."""
        if self.subpixels == "none" or channels == 1:
            return None
        if channels != SUBPIXEL_CHANNELS:
            raise ValueError(
                f"display.subpixels = {self.subpixels!r} needs an RGB display of "
                f"{SUBPIXEL_CHANNELS} channels, got {channels}; use subpixels = \"none\" or an "
                "RGB (or one-channel grey) image."
            )
        order = (-1.0, 0.0, 1.0) if self.subpixels == "rgb_stripe" else (1.0, 0.0, -1.0)
        return tuple(o / SUBPIXEL_CHANNELS for o in order)

    @property
    def pixel_mm(self) -> tuple[float, float]:
        """Pixel pitch (x, y) in mm."""
        return (self.width_mm / self.pixels[0], self.height_mm / self.pixels[1])

    def pixel_centres_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """Centres of columns (nx,) and rows (ny,) in mm, float64; row 0 is the top (+y)."""
        px, py = self.pixel_mm
        xs = -self.width_mm / 2 + (np.arange(self.pixels[0]) + 0.5) * px
        ys = self.height_mm / 2 - (np.arange(self.pixels[1]) + 0.5) * py
        return xs, ys


def hole_radius_mm(open_fraction: Any, pitch_mm: tuple[float, float]) -> np.ndarray:
    """Radius (mm) of the round hole whose area is `open_fraction` of a px x py cell,
    a = pi r^2 / (px py); arrays or scalars (float64). The one home of this conversion for
    values; the differentiable renderer keeps its own gradient-safe torch form."""
    return np.sqrt(np.asarray(open_fraction, dtype=np.float64) * (pitch_mm[0] * pitch_mm[1])
                   / math.pi)


def open_fraction_of(radius_mm: Any, pitch_mm: tuple[float, float]) -> np.ndarray:
    """Open-area fraction of a px x py cell holding a round hole of `radius_mm` (mm),
    pi r^2 / (px py); arrays or scalars (float64). The inverse of `hole_radius_mm`."""
    return math.pi * np.asarray(radius_mm, dtype=np.float64) ** 2 / (pitch_mm[0] * pitch_mm[1])


@dataclass(frozen=True)
class Plate:
    """A plate of cells, each with one circular through-hole, centred on the axis.

    cells: (nx, ny) cell count; cell (i, j) is row i (row 0 at +y), column j.
    pitch_mm: (px, py) cell pitch.
    gap_mm: display to the plate's bottom face.
    thickness_mm: plate thickness.
    hole_axis: "straight" (along z) or "chief_ray" (each hole's axis passes through its cell
        centre at mid-thickness and points at the nominal eye position).
    """

    cells: tuple[int, int]
    pitch_mm: tuple[float, float]
    gap_mm: float
    thickness_mm: float
    hole_axis: HoleAxis = "straight"

    def __post_init__(self) -> None:
        check_pair("plate.cells", self.cells, int)
        for n in self.cells:
            if not 1 <= n <= MAX_PIXELS:
                raise ValueError(
                    f"plate.cells = {self.cells} is out of range; allowed: 1 to {MAX_PIXELS} "
                    "per axis."
                )
        check_pair("plate.pitch_mm", self.pitch_mm, float)
        for p in self.pitch_mm:
            check_positive("plate.pitch_mm", p, "Give the cell pitch in mm, e.g. 0.25.", 100.0)
        check_positive("plate.gap_mm", self.gap_mm, "The plate sits in front of the display.",
                       MAX_SIZE_MM)
        if not (isinstance(self.thickness_mm, (int, float)) and math.isfinite(self.thickness_mm)
                and 0 <= self.thickness_mm <= 100):
            raise ValueError(
                f"plate.thickness_mm = {self.thickness_mm!r} is out of range; allowed: 0 to 100 "
                "mm (0 models an ideal thin mask)."
            )
        if self.hole_axis not in HOLE_AXES:
            raise ValueError(
                f"plate.hole_axis = {self.hole_axis!r} is not allowed; choose one of {HOLE_AXES}."
            )

    @property
    def size_mm(self) -> tuple[float, float]:
        return (self.cells[0] * self.pitch_mm[0], self.cells[1] * self.pitch_mm[1])

    @property
    def max_radius_mm(self) -> float:
        """Largest hole that fits its cell."""
        return min(self.pitch_mm) / 2

    @property
    def max_open_fraction(self) -> float:
        """Open-area fraction of the largest hole that fits its cell."""
        return float(open_fraction_of(self.max_radius_mm, self.pitch_mm))

    def cell_centres_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """Cell centres: columns (nx,) and rows (ny,) in mm, float64; row 0 is the top (+y)."""
        px, py = self.pitch_mm
        xs = (np.arange(self.cells[0]) - (self.cells[0] - 1) / 2) * px
        ys = ((self.cells[1] - 1) / 2 - np.arange(self.cells[1])) * py
        return xs, ys


@dataclass(frozen=True)
class Eye:
    """A thin-lens eye with a circular pupil, looking toward -z through the plate.

    pupil_mm: pupil diameter.
    eye_relief_mm: plate top face to the pupil.
    focus_mm: distance from the pupil at which the eye is focused; None for infinity (relaxed).
    fov_deg: (x, y) full field of view covered by the view grid.
    view_pixels: (nx, ny) view grid, uniform in tan(angle).
    positions_mm: lateral pupil-centre offsets (x, y) across the eyebox; the first is nominal.
    weights: one weight per position (normalised when used).

    The distribution of eye states a worn device sees (`aperture_fab.optics.eyes.distribution_of`),
    around the nominal state above; the defaults are the nominal point only:
    eyebox_mm: (w, h) full size of the region the pupil centre takes around the first position.
    eyebox_shape: "ellipse" or "rect", uniform over it.
    pupil_range_mm: (lo, hi) pupil diameters, uniform; None: pupil_mm only.
    focus_range_diopters: (lo, hi) accommodation, uniform in diopters (1000 / mm, 0 =
        infinity); None: focus_mm only.
    gaze_deg: largest gaze rotation, degrees (uniform over a disk of gaze angles); 0: none.
    rotation_mm: pupil to the eye's centre of rotation (gaze moves the pupil by
        rotation_mm sin(angle) per axis).
    """

    pupil_mm: float
    eye_relief_mm: float
    fov_deg: tuple[float, float]
    view_pixels: tuple[int, int]
    focus_mm: float | None = None
    positions_mm: tuple[tuple[float, float], ...] = ((0.0, 0.0),)
    weights: tuple[float, ...] = (1.0,)
    eyebox_mm: tuple[float, float] = (0.0, 0.0)
    eyebox_shape: EyeboxShape = "ellipse"
    pupil_range_mm: tuple[float, float] | None = None
    focus_range_diopters: tuple[float, float] | None = None
    gaze_deg: float = 0.0
    rotation_mm: float = ROTATION_MM

    def __post_init__(self) -> None:
        check_positive("eye.pupil_mm", self.pupil_mm,
                       "A human pupil is about 2 to 8 mm across.", 20.0)
        check_positive("eye.eye_relief_mm", self.eye_relief_mm,
                       "Give the distance from the plate's top face to the pupil.", MAX_SIZE_MM)
        if self.focus_mm is not None:
            check_positive("eye.focus_mm", self.focus_mm,
                           "Use a distance from the pupil, or leave it out for infinity.")
        check_pair("eye.fov_deg", self.fov_deg, float)
        for f in self.fov_deg:
            check_positive("eye.fov_deg", f, "Give the full field of view in degrees.",
                           MAX_FOV_DEG)
        check_pair("eye.view_pixels", self.view_pixels, int)
        for n in self.view_pixels:
            if not 1 <= n <= MAX_PIXELS:
                raise ValueError(
                    f"eye.view_pixels = {self.view_pixels} is out of range; allowed: 1 to "
                    f"{MAX_PIXELS} per axis."
                )
        if len(self.positions_mm) == 0:
            raise ValueError(
                "eye.positions_mm is empty; give at least one position, e.g. [[0, 0]]."
            )
        for pos in self.positions_mm:
            if not (len(pos) == 2 and all(math.isfinite(c) for c in pos)):
                raise ValueError(f"eye.positions_mm holds {pos!r}; allowed: pairs of finite "
                                 "numbers [x_mm, y_mm], e.g. [[0, 0]].")
        if len(self.weights) != len(self.positions_mm):
            raise ValueError(
                f"eye.weights has {len(self.weights)} values for {len(self.positions_mm)} "
                "positions; give one weight per position."
            )
        if any(not (math.isfinite(w) and w >= 0) for w in self.weights) or sum(self.weights) <= 0:
            raise ValueError(
                f"eye.weights = {self.weights} is out of range; allowed: finite values >= 0 "
                "with a positive sum, one per position, e.g. [1.0]."
            )
        check_pair("eye.eyebox_mm", self.eyebox_mm, float)
        for name in ("pupil_range_mm", "focus_range_diopters"):
            if getattr(self, name) is not None:
                check_pair(f"eye.{name}", getattr(self, name), float)
        names = {k: f"eye.{k}" for k in ("eyebox_mm", "eyebox_shape", "pupil_range_mm",
                                         "focus_range_diopters", "gaze_deg", "rotation_mm")}
        names.update(pupil="eye.pupil_mm", focus="eye.focus_mm")
        check_fields(names, eyebox_mm=self.eyebox_mm, eyebox_shape=self.eyebox_shape,
                     pupil_range_mm=self.pupil_range_mm, nominal_pupil_mm=self.pupil_mm,
                     focus_range_diopters=self.focus_range_diopters,
                     nominal_focus_diopters=self.focus_diopters, gaze_deg=self.gaze_deg,
                     rotation_mm=self.rotation_mm)

    @property
    def focus_diopters(self) -> float:
        """The nominal accommodation, 1000 / focus_mm; 0 at infinity."""
        return 0.0 if self.focus_mm is None else 1000.0 / self.focus_mm

    @property
    def view_tan_half(self) -> tuple[float, float]:
        return tuple(math.tan(math.radians(f) / 2) for f in self.fov_deg)  # type: ignore[return-value]

    def view_directions(self) -> tuple[np.ndarray, np.ndarray]:
        """View pixel centres as tan(angle): columns (nx,) and rows (ny,), float64.

        Row 0 is the top of the view (+y), column 0 the left (-x): views are upright.
        """
        tx, ty = self.view_tan_half
        nx, ny = self.view_pixels
        vx = -tx + (np.arange(nx) + 0.5) * (2 * tx / nx)
        vy = ty - (np.arange(ny) + 0.5) * (2 * ty / ny)
        return vx, vy

    @property
    def view_step(self) -> tuple[float, float]:
        """Size of a view pixel in tan(angle), (x, y)."""
        tx, ty = self.view_tan_half
        return (2 * tx / self.view_pixels[0], 2 * ty / self.view_pixels[1])


def display_fov_deg(display: Display, distance_mm: float,
                    margin_mm: tuple[float, float] = (0.0, 0.0)) -> tuple[float, float]:
    """Full field of view (x, y) in degrees that the display subtends from every pupil centre
    within margin_mm (x, y) of the axis: from the axis when the margin is 0. An eye that moves
    across an eyebox sees the display across this whole field from every position in it."""
    halves = []
    for size, margin, axis in ((display.width_mm, margin_mm[0], "width"),
                               (display.height_mm, margin_mm[1], "height")):
        if margin >= size / 2:
            raise ValueError(
                f"the pupil moves {margin:g} mm off the axis, as far as the display's half "
                f"{axis} ({size / 2:g} mm): no direction shows the display from every eye "
                "position. Use a smaller eyebox or gaze, a larger display, or an explicit "
                "fov_deg.")
        halves.append(math.degrees(2 * math.atan((size / 2 - margin) / distance_mm)))
    return (halves[0], halves[1])


@dataclass(frozen=True)
class Scene:
    """Display, plate and eye together, with the distances the model needs."""

    display: Display
    plate: Plate
    eye: Eye

    def __post_init__(self) -> None:
        glass = self.display.cover_glass_mm
        if glass >= self.plate.gap_mm:
            raise ValueError(
                f"display.cover_glass_mm = {glass:g} is not less than plate.gap_mm = "
                f"{self.plate.gap_mm:g}: the glass lies inside the gap, which is measured from "
                "the display's emitting surface to the plate's bottom face; allowed: "
                f"0 <= cover_glass_mm < {self.plate.gap_mm:g}. Give a thinner glass or a "
                "larger gap (gap = glass + air between the glass and the plate)."
            )
        focus = self.eye.focus_mm
        if focus is not None and focus <= self.plate_distance_mm * 1.05:
            raise ValueError(
                f"eye.focus_mm = {focus} focuses on or in front of the plate (the plate's bottom "
                f"face is {self.plate_distance_mm:.3g} mm from the pupil); allowed: more than "
                f"{self.plate_distance_mm * 1.05:.3g} mm, or leave it out for infinity."
            )

    @property
    def plate_distance_mm(self) -> float:
        """Pupil to the plate's bottom face."""
        return self.eye.eye_relief_mm + self.plate.thickness_mm

    @property
    def mid_plane_distance_mm(self) -> float:
        """Pupil to the plate's mid-thickness: where chief-ray holes converge, and the length
        of their axes."""
        return self.eye.eye_relief_mm + self.plate.thickness_mm / 2

    @property
    def display_distance_mm(self) -> float:
        """Pupil to the display."""
        return self.plate_distance_mm + self.plate.gap_mm

    @property
    def pinhole_height_mm(self) -> float:
        """Effective pinhole height above the display: gap + thickness / 2."""
        return self.plate.gap_mm + self.plate.thickness_mm / 2


def eyebox_margin_mm(eyebox_mm: tuple[float, float], gaze_deg: float, rotation_mm: float
                     ) -> tuple[float, float]:
    """How far (x, y) mm the pupil centre moves off its nominal position: half the eyebox plus
    the largest gaze shift."""
    shift = rotation_mm * math.sin(math.radians(gaze_deg))
    return (eyebox_mm[0] / 2 + shift, eyebox_mm[1] / 2 + shift)
