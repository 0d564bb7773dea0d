"""The differentiable view of an eye through a plate of holes onto a display.

For one view pixel (a small box of view directions v) and one eye position c, the value is the mean
over the pupil of the display radiance along each ray the eye's lens sends to that pixel, counting
only rays that pass the same hole at both plate faces. Everything is planar, so the point where a
ray crosses any plane is affine in (v, pupil point u): with q = 1 / focus distance (0 at
infinity), a ray is at lateral position c + s v + (1 - s q) u at depth s below the pupil.

For each hole, with the crossing point x_b at the bottom face as the variable, the rays that pass
form the intersection of three disks: the hole at the bottom face, the hole at the top face mapped
to the bottom face, and the pupil mapped to the bottom face. The model integrates each in closed
form (two-disk lens area, pupil clipping at the lens) and takes the display radiance as its mean
over the window those rays see, which is the lens mapped affinely onto the display. That mean comes
from a stack of the display pre-filtered by the exact pixel / view-pixel / window kernels at a few
window radii, sampled trilinearly (position, radius). So a hole is a hole: it shows a window of
the display the size of the hole, displaced with the hole, never its cell's light smeared.

Neglected (stated in docs/model.md): diffraction (see validation), the lens window's shape beyond
its area and centre (an equal-area disk stands in for the two-disk lens), the pupil's curvature
across one hole, light scattered or reflected by the hole walls and plate surfaces, the eye's
aberrations and Stiles-Crawford effect.

Display-side optics (`Display`; docs/model.md "Display-side optics"): a cover glass moves each
pair's window by the refraction shift at the pair's chief ray, and a cos^k emission falloff
weighs the pair by its chief ray's angle; striped RGB sub-pixels move each channel's pixel box
by its stripe's offset in the stack's kernels. All off by default, leaving every render as it
was.
"""

from __future__ import annotations

import copy
import importlib.util
import math
import os
from dataclasses import dataclass, fields
from typing import Literal, cast

import numpy as np
import torch
import torch.nn.functional as F

from aperture_fab.optics.eyes import EyeStates
from aperture_fab.optics.fused_views import KernelView, TritonView
from aperture_fab.optics.kernels import STATE_FIELDS
from aperture_fab.optics.pair_table import Pairs, build_pairs, render_table
from aperture_fab.optics.planes import EPS, Optics
from aperture_fab.optics.scene import SUBPIXEL_CHANNELS, Scene
from aperture_fab.optics.stack_filter import filter_levels, filter_levels_into
from aperture_fab.optics.stack_levels import lowest_level

__all__ = [
    "BACKENDS",
    "STACK_OVERSAMPLE",
    "Backend",
    "Renderer",
    "Running",
    "StackShape",
    "backend_for",
    "stack_shape",
]

#: Spacing of the blur-stack radius levels in display pixels (finer: smaller interpolation error).
LEVEL_SPACING_PX = 0.5
MAX_LEVELS = 24
#: Stack samples per display pixel along each axis. The stack is read bilinearly between its
#: samples, and the display's mean over a window is only piecewise smooth (pixel edges): one
#: sample per pixel left about 2 % rms error on high-contrast content (a line-pair design's view
#: 33.3 dB against the mesh re-trace, whose noise alone allows 41 dB); two leave 39.7 dB
#: (docs/model.md, "Approximations").
STACK_OVERSAMPLE = 2
#: Quadrature points over a window disk when building the blur kernels.
DISK_RINGS = 24
DISK_SPOKES = 48
#: (view pixel, hole) pairs evaluated at once; bounds memory to a few hundred MB.
DEFAULT_CHUNK_PAIRS = 1_500_000
#: An eye state must focus beyond this multiple of the pupil-to-plate distance (as Scene checks).
FOCUS_MARGIN = 1.05


def _trapezoid(offset_mm: np.ndarray, pixel_mm: float, box_mm: float) -> np.ndarray:
    """Fraction of a box of width box_mm, centred at offset, that falls in a pixel at 0."""
    if box_mm <= 0:
        return (np.abs(offset_mm) < pixel_mm / 2).astype(np.float64)
    lo = np.maximum(offset_mm - box_mm / 2, -pixel_mm / 2)
    hi = np.minimum(offset_mm + box_mm / 2, pixel_mm / 2)
    return np.clip(hi - lo, 0, None) / box_mm


def _window_kernels(
    pixel_mm: tuple[float, float], box_mm: tuple[float, float], radii_mm: np.ndarray,
    shift_mm: float = 0.0, slack_mm: float = 0.0,
) -> np.ndarray:
    """Weights (L, 2k+1, 2k+1) of stack samples around a sample point at a sample's centre.

    Level l is the mean over a disk of radius radii_mm[l], smeared by the view pixel's box, of a
    display that is constant over each sample's box (pixel_mm), each box's emitting area moved
    by shift_mm along +x (a sub-pixel stripe's offset). The kernels reach far enough for any
    shift up to slack_mm (at least half a sample), so kernels of different shifts have one size.
    Rows run toward -y like images; the kernels are symmetric (for shift_mm = 0) so the sign
    does not matter.
    """
    wx, wy = pixel_mm
    k = _kernel_reach(pixel_mm, box_mm, float(radii_mm.max()), slack_mm)
    off = np.arange(-k, k + 1)
    # Disk quadrature: equal-area rings, uniform spokes.
    rings = np.sqrt((np.arange(DISK_RINGS) + 0.5) / DISK_RINGS)
    angles = 2 * np.pi * (np.arange(DISK_SPOKES) + 0.5) / DISK_SPOKES
    unit = np.stack([np.outer(rings, np.cos(angles)).ravel(),
                     np.outer(rings, np.sin(angles)).ravel()])
    kernels = []
    for radius in radii_mm:
        points = unit * radius if radius > 0 else np.zeros((2, 1))
        # Column offset of the sample point from each pixel's emitting centre (the disk's
        # quadrature is symmetric, so -points is the same set of points).
        tx = _trapezoid(off[:, None] * wx - points[0][None, :] - shift_mm, wx,
                        box_mm[0])  # (2k+1, P)
        ty = _trapezoid(off[:, None] * wy - points[1][None, :], wy, box_mm[1])
        kernel = ty @ tx.T / points.shape[1]  # (rows, cols)
        kernels.append(kernel / kernel.sum())
    return np.stack(kernels)


def _fast_length(n: int) -> int:
    """The smallest length >= n whose only prime factors are 2, 3, 5 and 7: FFTs of such
    lengths are several times faster than of lengths with a large prime factor."""
    while True:
        m = n
        for p in (2, 3, 5, 7):
            while m % p == 0:
                m //= p
        if m == 1:
            return n
        n += 1


@dataclass(frozen=True)
class StackShape:
    """The display stack a Renderer builds: C x levels x height x width samples (the display
    split into oversample x oversample samples per pixel, padded by pad samples per side),
    pre-filtered through FFTs of fft_height x fft_width by window kernels kernel_size samples
    wide.

    pixels: (x, y) samples of the unpadded display; pixel_mm: (x, y) one sample's size (mm).
    window_max_mm: the largest window radius on the display; radii_mm: (levels,) float64 the
    levels' window radii (mm), uniform in radius squared. box_mm: (x, y) the view pixel's box on
    the display (mm). slack_mm: the largest sub-pixel stripe offset the kernels reach for.
    """

    levels: int
    height: int
    width: int
    fft_height: int
    fft_width: int
    kernel_size: int
    pad: int
    pixels: tuple[int, int]
    pixel_mm: tuple[float, float]
    window_max_mm: float
    radii_mm: np.ndarray
    box_mm: tuple[float, float]
    slack_mm: float

    def filters_like(self, other: StackShape, box_rtol: float) -> bool:
        """Whether a stack of this shape pre-filters a display as one of `other`'s does: every
        field equal but the view pixel's box on the display, which may differ by box_rtol
        (relative)."""
        for field in fields(self):
            mine, theirs = getattr(self, field.name), getattr(other, field.name)
            if field.name == "box_mm":
                if not all(math.isclose(a, b, rel_tol=box_rtol)
                           for a, b in zip(mine, theirs, strict=True)):
                    return False
            elif not np.array_equal(mine, theirs):
                return False
        return True


def stack_shape(scene: Scene, oversample: int = STACK_OVERSAMPLE,
                max_radius_mm: float | None = None) -> StackShape:
    """The display stack's shape, levels and kernels' extent for a scene (see StackShape),
    for holes up to max_radius_mm (None: the largest a cell holds)."""
    if not (isinstance(oversample, int) and oversample >= 1):
        raise ValueError(f"oversample = {oversample!r}; allowed: an integer >= 1 (stack "
                         "samples per display pixel along each axis).")
    optics = Optics.of(scene)
    plate, eye, display = scene.plate, scene.eye, scene.display
    radius = plate.max_radius_mm
    if max_radius_mm is not None:
        if not (math.isfinite(max_radius_mm) and 0 < max_radius_mm <= radius):
            raise ValueError(f"max_radius_mm = {max_radius_mm!r}; allowed: above 0 and up to "
                             f"the cell's largest hole, {radius:g} mm (or None for that).")
        radius = max_radius_mm
    # Wide enough for an eye focused at infinity too (|mu| = 1), for eye states off nominal.
    window_max = max(abs(optics.window_scale), 1.0) * radius
    levels = math.ceil(window_max / (LEVEL_SPACING_PX * min(display.pixel_mm))) + 1
    levels = min(MAX_LEVELS, max(2, levels))
    # The view pixel's box on the display, at the nominal focus (see docs/model.md); cover
    # glass slows the window's motion by its paraxial apparent-depth loss t_g (1 - 1/n).
    rate = optics.window_rate
    if display.cover_glass_mm > 0:
        rate = max(rate - display.cover_glass_mm * (1 - 1 / display.cover_glass_index), 0.0)
    box = (rate * eye.view_step[0], rate * eye.view_step[1])
    pixel_mm = (display.pixel_mm[0] / oversample, display.pixel_mm[1] / oversample)
    offsets_px = display.subpixel_offsets_px(SUBPIXEL_CHANNELS)
    slack = 0.0 if offsets_px is None else max(map(abs, offsets_px)) * display.pixel_mm[0]
    size = 2 * _kernel_reach(pixel_mm, box, window_max, slack) + 1
    pad = size // 2 + 1
    pixels = (display.pixels[0] * oversample, display.pixels[1] * oversample)
    height, width = pixels[1] + 2 * pad, pixels[0] + 2 * pad
    # Kernels centred on sample 0 (`Renderer._spectra`) keep the stack at samples 0 .. height
    # of the transforms, whose circular convolution wraps nothing into them once they are
    # height long, not height + size - 1 as a full linear convolution needs: the display is
    # zero in its pad border, wider than a kernel's half (a 3 mm lattice's judged stack:
    # transforms of 900^2 against 1000^2).
    return StackShape(levels, height, width, _fast_length(height), _fast_length(width),
                      size, pad, pixels, pixel_mm, window_max,
                      window_max * np.sqrt(np.linspace(0, 1, levels)), box, slack)


def _kernel_reach(pixel_mm: tuple[float, float], box_mm: tuple[float, float],
                  radius_mm: float, slack_mm: float) -> int:
    """Samples a window kernel reaches on each side of its centre: the window's radius, half the
    view pixel's box, a stripe's offset up to slack_mm (at least half a sample) and half a
    sample of the sample's own box."""
    step = min(pixel_mm)
    return math.ceil((radius_mm + max(box_mm) / 2 + max(slack_mm, step / 2)) / step + 0.5)


def _checked_offsets(scene: Scene, offsets: np.ndarray | None) -> np.ndarray | None:
    """The hole offsets as a float64 (rows, cols, 2) array, or a ValueError naming the fix."""
    if offsets is None:
        return None
    cells = (scene.plate.cells[1], scene.plate.cells[0], 2)
    array = np.asarray(offsets, dtype=np.float64)
    if array.shape != cells:
        raise ValueError(
            f"hole_offset_mm has shape {array.shape}; the plate needs (rows, cols, 2) = {cells}: "
            "one (x, y) displacement in mm per cell."
        )
    if not np.all(np.isfinite(array)):
        raise ValueError("hole_offset_mm holds NaN or infinite values; give finite (x, y) "
                         "displacements in mm (0 for a hole where it was drawn).")
    largest = float(np.linalg.norm(array, axis=-1).max())
    limit = max(scene.plate.size_mm)
    if largest > limit:
        raise ValueError(
            f"hole_offset_mm moves a hole by {largest:g} mm; allowed: up to the plate's size "
            f"({limit:g} mm). Give displacements in mm, not microns."
        )
    return array


Backend = Literal["auto", "kernel", "torch", "triton"]
BACKENDS: tuple[Backend, ...] = ("auto", "kernel", "torch", "triton")
#: A backend that runs ("auto" resolved by `backend_for`).
Running = Literal["kernel", "torch", "triton"]
#: Pair tables of the torch path kept per renderer (nominal positions and recent eye states).
TABLE_CACHE = 8


def backend_for(backend: Backend, device: torch.device) -> Running:
    """The backend that runs: "auto" is the CPU kernels on the CPU, the Triton kernels on CUDA
    (the torch path where Triton is not installed); a backend that cannot run on `device` is a
    ValueError naming the fix."""
    if backend not in BACKENDS:
        raise ValueError(f"backend = {backend!r} is not allowed; choose one of "
                         f"{', '.join(BACKENDS)}.")
    triton_here = importlib.util.find_spec("triton") is not None
    if backend == "auto":
        if device.type == "cpu":
            return "kernel"
        return "triton" if triton_here and device.type == "cuda" else "torch"
    if backend == "kernel" and device.type != "cpu":
        raise ValueError(f"backend 'kernel' runs on the CPU; device is {device}. Use backend "
                         "'triton' or 'torch' (or 'auto') on CUDA.")
    if backend == "triton":
        if not triton_here:
            raise ValueError("backend 'triton' needs the triton package (it comes with CUDA "
                             "builds of PyTorch); use backend 'torch' or 'auto'.")
        if device.type != "cuda" and os.environ.get("TRITON_INTERPRET", "0") != "1":
            raise ValueError(f"backend 'triton' runs on CUDA; device is {device}. Use backend "
                             "'kernel' (or 'auto') on the CPU; TRITON_INTERPRET=1 runs it on "
                             "the CPU for tests.")
    return cast(Running, backend)


class Renderer:
    """Renders views of one scene for any batch of eye states; differentiable in the open-area
    fractions and the display content.

    scene: the scene (its eye gives the nominal pupil, focus and positions; `render_states`
        takes any others); device, dtype: where and how to compute; chunk_pairs: memory bound
        of the torch path (pairs evaluated at once).
    hole_offset_mm: (rows, cols, 2) float64 or None, lateral displacement (x right, y up; row 0
        at +y) of each cell's hole from its cell centre, the same at both faces and for every
        eye state (chief-ray axes keep the direction of the undisplaced hole). Offsets of
        more than a pitch are handled: the hole search widens by the largest offset (cost grows
        as its square), so no pair is lost; holes that come to overlap add their light (no
        union). Offsets beyond the plate's size are rejected.
    backend: "kernel" (fused CPU kernels, `aperture_fab.optics.kernels`: geometry on the fly, a
        batch of eye states in one pass), "triton" (the same walk as fused GPU kernels,
        `aperture_fab.optics.gpu_kernels`), "torch" (pair tables and grid_sample: the reference
        the kernels are tested against) or "auto" (kernel on the CPU, triton on CUDA, torch
        there without Triton).
    oversample: display stack samples per display pixel along each axis (STACK_OVERSAMPLE by
        default; 1 is faster, about 20 % per optimizer iteration, and less exact: see there).
    max_radius_mm: the largest hole radius it renders (made errors included); None: the
        largest a cell holds. The display stack's levels and kernels span the windows of holes
        up to it, so a plate of holes much smaller than its cells (a regular array of small
        holes on a coarse lattice) renders from a far smaller stack; a larger hole reads the
        largest window (too sharp).
    min_radius_mm: the smallest open hole radius it renders (made errors included); None:
        any. Its display stacks hold only the levels such holes read, from `first_level` up
        (`stack_levels`): a regular array's holes, all of one size, read a few of them. A
        smaller hole reads the lowest level held (too wide a window). For eye states focused
        at infinity only (`render_states` refuses others).
    """

    def __init__(
        self,
        scene: Scene,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
        chunk_pairs: int = DEFAULT_CHUNK_PAIRS,
        hole_offset_mm: np.ndarray | None = None,
        backend: Backend = "auto",
        oversample: int = STACK_OVERSAMPLE,
        max_radius_mm: float | None = None,
        min_radius_mm: float | None = None,
    ) -> None:
        self.scene = scene
        self.hole_offset_mm = _checked_offsets(scene, hole_offset_mm)
        self.device = torch.device(device)
        self.dtype = dtype
        self.chunk_pairs = chunk_pairs
        self.backend = backend_for(backend, self.device)
        self.optics = opt = Optics.of(scene)
        eye = scene.eye
        self.shape = shape = stack_shape(scene, oversample, max_radius_mm)
        self.window_max_mm = shape.window_max_mm
        self.oversample = oversample
        self.kernel_size, self.pad = shape.kernel_size, shape.pad
        self._fft_shape = (shape.fft_height, shape.fft_width)
        self.first_level = 0 if min_radius_mm is None else lowest_level(
            scene, shape.levels, shape.window_max_mm, min_radius_mm)
        # A stack of the upper levels only: the kernels map a window's area onto its levels
        # by a level scale stretched to them and this offset (kernels.GEOMETRY_FIELDS).
        self.stack_levels = shape.levels - self.first_level
        self.level_offset = 2 * self.first_level / (self.stack_levels - 1)
        self._filters: tuple[torch.Tensor, torch.Tensor | None] | None = None
        self.pupil_bottom_mm = eye.pupil_mm / 2 * abs(opt.beta_bottom)
        self._pairs: dict[tuple[float, ...], Pairs] = {}
        self._white: torch.Tensor | None = None
        self._gpu_constants: tuple[torch.Tensor, ...] | None = None

    @property
    def axis_length(self) -> float:
        """Plate mid-thickness to the pupil: the length of a chief-ray hole axis."""
        return self.scene.mid_plane_distance_mm

    @property
    def search_extra_mm(self) -> float:
        """How much farther than the footprint a hole's axis may lie and still reach it: the
        chief-ray tilt at the bottom face plus the largest hole displacement."""
        plate, eye = self.scene.plate, self.scene.eye
        extra = 0.0
        if plate.hole_axis == "chief_ray":
            half = math.hypot(plate.size_mm[0] / 2 + abs(eye.positions_mm[0][0]),
                              plate.size_mm[1] / 2 + abs(eye.positions_mm[0][1]))
            extra = plate.thickness_mm / 2 * half / self.axis_length
        if self.hole_offset_mm is not None:
            extra += float(np.linalg.norm(self.hole_offset_mm, axis=-1).max())
        return extra

    def with_hole_offsets(self, hole_offset_mm: np.ndarray | None) -> Renderer:
        """This renderer with other hole offsets (see the class docstring), sharing its display
        kernels: cheap enough to move the holes by fresh process errors every iteration."""
        moved = copy.copy(self)
        moved.hole_offset_mm = _checked_offsets(self.scene, hole_offset_mm)
        moved._pairs = {}  # the torch path's pair tables depend on the offsets
        moved._gpu_constants = None  # as do the triton path's
        return moved

    def nominal_states(self, position: int = 0) -> EyeStates:
        """The eye state at eyebox position `position` of the scene, nominal pupil and focus."""
        eye = self.scene.eye
        if not 0 <= position < len(eye.positions_mm):
            raise ValueError(f"position = {position} is out of range; the scene has "
                             f"{len(eye.positions_mm)} eyebox position(s).")
        return EyeStates(
            offset_mm=np.array([eye.positions_mm[position]], dtype=np.float64),
            pupil_mm=np.array([eye.pupil_mm]),
            focus_diopters=np.array([0.0 if eye.focus_mm is None else 1000.0 / eye.focus_mm]),
            gaze_deg=np.zeros((1, 2)),
            weight=np.ones(1),
        )

    def state_rows(self, states: EyeStates) -> np.ndarray:
        """Per state (S, len(STATE_FIELDS)) float64: the constants the pair geometry needs."""
        scene = self.scene
        limit_d = 1000.0 / (scene.plate_distance_mm * FOCUS_MARGIN)
        rows = []
        for (cx, cy), pupil, diopters in zip(states.offset_mm, states.pupil_mm,
                                             states.focus_diopters, strict=True):
            if not 0 <= diopters < limit_d:
                raise ValueError(
                    f"eye state focus {diopters:g} diopters is out of range; allowed: 0 (infinity)"
                    f" up to {limit_d:.3g} (focused beyond the plate).")
            opt = Optics.of(scene, diopters / 1000.0)
            pupil_b = pupil / 2 * abs(opt.beta_bottom)
            mu = opt.window_scale
            level_scale = mu * mu / math.pi / max(self.window_max_mm**2, EPS)
            if self.first_level:
                level_scale *= (self.shape.levels - 1) / (self.stack_levels - 1)
            rows.append((cx, cy, pupil_b, opt.top_to_bottom, mu, level_scale,
                         1 / (math.pi * pupil_b**2), pupil_b + 2 * scene.plate.max_radius_mm))
        return np.asarray(rows, dtype=np.float64).reshape(-1, len(STATE_FIELDS))

    def pair_count(self, position: int = 0) -> int:
        """(view pixel, hole) pairs the nominal state at `position` evaluates."""
        return int(self._pair_table(self.state_rows(self.nominal_states(position))[0])
                   .hole.numel())

    # -- display ------------------------------------------------------------------------------

    def display_stack(self, display: torch.Tensor, with_white: bool = False) -> torch.Tensor:
        """Pre-filter a display (C, H, W) into the window stack (1, C, L, H', W'), its levels
        from first_level up (L = stack_levels; min_radius_mm in the class docstring). A striped
        RGB display (`Display.subpixels`) filters each channel with its stripe's offset.
        with_white: the uniform white display's stack (`white_stack`) joined as channel C
        (what `as_made.made_views_and_white` renders), each level written beside it rather
        than the whole stack copied again to join them (up to 280 MB a judged stack); not
        differentiable. The filter's forward and backward: `stack_filter.filter_levels`."""
        d = display.to(self.device, self.dtype)
        if self.oversample > 1:  # each pixel is uniform: its samples repeat its value
            d = d.repeat_interleave(self.oversample, -1).repeat_interleave(self.oversample, -2)
        d = F.pad(d, (self.pad,) * 4)
        kernel, striped = self._window_spectra()
        if self.scene.display.subpixel_offsets_px(d.shape[0]) is not None:
            kernel = cast(torch.Tensor, striped)
        if with_white:
            white = self.white_stack()[0].permute(1, 2, 3, 0)  # (L, H', W', 1)
            channels = d.shape[0]
            levels = torch.empty((*white.shape[:3], channels + 1), dtype=self.dtype,
                                 device=self.device)
            with torch.no_grad():
                filter_levels_into(levels[..., :channels], d, kernel, self._fft_shape)
            levels[..., channels:] = white
        else:
            levels = filter_levels(d, kernel, self._fft_shape)
        return levels.permute(3, 0, 1, 2).unsqueeze(0)  # (L, H, W, C) in memory

    def _window_spectra(self) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The window kernels' spectra (L, H, W', 1), channels last as the stack is built, and
        for a striped RGB display each channel's with its stripe's offset (L, H, W', 3; None
        otherwise: a grey display's one channel fills the pixel). Built on the first display
        stack: a renderer given its stacks (a tolerance sample's) never needs them."""
        if self._filters is None:
            shape, display = self.shape, self.scene.display
            radii = shape.radii_mm[self.first_level:]  # the levels held
            plain = self._spectra(_window_kernels(shape.pixel_mm, shape.box_mm, radii,
                                                  slack_mm=shape.slack_mm)[..., None])
            striped = None
            offsets_px = display.subpixel_offsets_px(SUBPIXEL_CHANNELS)
            if offsets_px is not None:
                striped = self._spectra(np.stack(
                    [_window_kernels(shape.pixel_mm, shape.box_mm, radii,
                                     o * display.pixel_mm[0], shape.slack_mm)
                     for o in offsets_px], -1))
            self._filters = (plain, striped)
        return self._filters

    def _spectra(self, kernels: np.ndarray) -> torch.Tensor:
        """Spectra (L, H, W', K) complex of window kernels (L, h, w, K) over the FFT shape,
        each centred on sample 0 (wrapped around), so that it filters a display in place."""
        k = torch.as_tensor(kernels, dtype=self.dtype, device=self.device)
        full = k.new_zeros((k.shape[0], *self._fft_shape, k.shape[-1]))
        full[:, :k.shape[1], :k.shape[2]] = k
        centre = (-(k.shape[1] // 2), -(k.shape[2] // 2))
        return torch.fft.rfft2(torch.roll(full, centre, dims=(1, 2)), dim=(1, 2))

    def white_stack(self) -> torch.Tensor:
        """The stack (1, 1, L, H', W') of a uniform white one-channel display, built once (a
        plate's light efficiency is its mean view of it)."""
        if self._white is None:
            pixels = self.scene.display.pixels
            with torch.no_grad():
                self._white = self.display_stack(torch.ones(
                    1, pixels[1], pixels[0], dtype=self.dtype, device=self.device))
        return self._white

    # -- rendering ----------------------------------------------------------------------------

    def render(self, open_fraction: torch.Tensor, display: torch.Tensor, position: int = 0
               ) -> torch.Tensor:
        """View (C, ny, nx) through holes of open-area fractions (rows, cols) onto a display
        (C, H, W) in linear light, from eye position `position` of the scene's eyebox."""
        return self.render_stack(open_fraction, self.display_stack(display), position)

    def render_stack(self, open_fraction: torch.Tensor, stack: torch.Tensor, position: int = 0
                     ) -> torch.Tensor:
        """As `render`, with the display already pre-filtered by `display_stack`."""
        return self.render_states(open_fraction, stack, self.nominal_states(position))[0]

    def render_states(self, open_fraction: torch.Tensor, stack: torch.Tensor,
                      states: EyeStates) -> torch.Tensor:
        """Views (S, C, ny, nx) of one display stack (from `display_stack`) through holes of
        open-area fractions (rows, cols), for each of a batch of eye states, in one pass."""
        scene = self.scene
        cells = (scene.plate.cells[1], scene.plate.cells[0])
        if tuple(open_fraction.shape) != cells:
            raise ValueError(
                f"open_fraction has shape {tuple(open_fraction.shape)}; the plate has "
                f"(rows, cols) = {cells}."
            )
        if self.first_level > 0 and np.any(states.focus_diopters != 0):
            raise ValueError(
                f"eye states focused at {sorted(set(states.focus_diopters.tolist()))} diopters; "
                "a renderer given min_radius_mm renders eye states focused at infinity (0) "
                "only, whose lens areas bound its stack's levels. Give min_radius_mm=None.")
        a = open_fraction.to(self.device, self.dtype).reshape(-1).clamp_min(0)
        px, py = scene.plate.pitch_mm
        radius = (a * (px * py / math.pi)).add(EPS).sqrt()
        rows = self.state_rows(states)
        if self.backend == "kernel":
            view = KernelView.apply(radius, stack, self, rows)
        elif self.backend == "triton":
            view = TritonView.apply(radius, stack.to(self.device), self, rows)
        else:
            view = torch.stack([render_table(self, radius, stack, row) for row in rows])
        return view.reshape(len(rows), stack.shape[1], *reversed(scene.eye.view_pixels))

    # -- torch path: pair tables --------------------------------------------------------------

    def _pair_table(self, row: np.ndarray) -> Pairs:
        key = tuple(float(v) for v in row)
        if key not in self._pairs:
            if len(self._pairs) >= TABLE_CACHE:
                self._pairs.pop(next(iter(self._pairs)))
            with torch.no_grad():
                self._pairs[key] = build_pairs(self, row)
        return self._pairs[key]


    # -- kernel path --------------------------------------------------------------------------

    def kernel_geometry(self) -> np.ndarray:
        """The scene's constants for `aperture_fab.optics.kernels`, in GEOMETRY_FIELDS order."""
        scene = self.scene
        plate, eye, display = scene.plate, scene.eye, scene.display
        ex, ey = eye.positions_mm[0]
        return np.array([
            plate.cells[0], plate.cells[1], plate.pitch_mm[0], plate.pitch_mm[1],
            plate.thickness_mm, float(plate.hole_axis == "chief_ray"), ex, ey,
            self.axis_length, scene.plate_distance_mm, eye.eye_relief_mm,
            scene.display_distance_mm, display.width_mm / 2, display.height_mm / 2,
            self.shape.pixel_mm[0], self.shape.pixel_mm[1], self.pad,
            display.cover_glass_mm, display.cover_glass_index, display.emission_power,
            self.level_offset,
        ], dtype=np.float64)


