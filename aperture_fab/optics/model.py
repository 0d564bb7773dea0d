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
from dataclasses import dataclass
from typing import Any, Literal, cast

import numpy as np
import torch
import torch.nn.functional as F

from aperture_fab.optics import kernels
from aperture_fab.optics.eyes import EyeStates
from aperture_fab.optics.kernels import STATE_FIELDS
from aperture_fab.optics.scene import SUBPIXEL_CHANNELS, Scene

__all__ = ["BACKENDS", "Backend", "Renderer", "Running", "backend_for", "render_open",
           "render_open_states"]

#: Spacing of the blur-stack radius levels in display pixels (finer: smaller interpolation error).
LEVEL_SPACING_PX = 0.5
MAX_LEVELS = 24
#: Quadrature points over a window disk when building the blur kernels.
DISK_RINGS = 24
DISK_SPOKES = 48
#: (view pixel, hole) pairs evaluated at once; bounds memory to a few hundred MB.
DEFAULT_CHUNK_PAIRS = 1_500_000
_EPS = 1e-12
#: A cell whose radius is at most this (mm) is closed: the renderer gives it sqrt(_EPS).
CLOSED_RADIUS_MM = math.sqrt(2 * _EPS)
#: An eye state must focus beyond this multiple of the pupil-to-plate distance (as Scene checks).
FOCUS_MARGIN = 1.05


@dataclass(frozen=True)
class _Optics:
    """Distances and the affine maps between planes, all in mm (see module docstring)."""

    s_bottom: float  # pupil to the plate's bottom face
    s_top: float  # pupil to the plate's top face
    s_display: float  # pupil to the display
    beta_bottom: float  # 1 - s q at each plane
    beta_top: float
    beta_display: float

    @classmethod
    def of(cls, scene: Scene, q: float | None = None) -> _Optics:
        """The scene's optics, for its eye's focus or for q = 1 / focus distance (1/mm)."""
        if q is None:
            q = 0.0 if scene.eye.focus_mm is None else 1.0 / scene.eye.focus_mm
        s_b, s_t, s_d = scene.plate_distance_mm, scene.eye.eye_relief_mm, scene.display_distance_mm
        return cls(s_b, s_t, s_d, 1 - s_b * q, 1 - s_t * q, 1 - s_d * q)

    @property
    def top_to_bottom(self) -> float:
        """Scale from a top-face offset to the matching bottom-face offset (same pupil point)."""
        return self.beta_bottom / self.beta_top

    @property
    def window_scale(self) -> float:
        """Scale from bottom-face offsets to display offsets for rays of one view direction."""
        return self.beta_display / self.beta_bottom

    @property
    def window_rate(self) -> float:
        """How fast (mm per unit tan) the display window moves as the view direction changes."""
        mu = self.window_scale
        lens_rate = 0.5 * (self.s_bottom - self.top_to_bottom * self.s_top)
        return abs(self.s_display - mu * self.s_bottom + mu * lens_rate)


def _trapezoid(offset_mm: np.ndarray, pixel_mm: float, box_mm: float) -> np.ndarray:
    """Fraction of a box of width box_mm, centred at offset, that falls in a pixel at 0."""
    if box_mm <= 0:
        return (np.abs(offset_mm) < pixel_mm / 2).astype(np.float64)
    lo = np.maximum(offset_mm - box_mm / 2, -pixel_mm / 2)
    hi = np.minimum(offset_mm + box_mm / 2, pixel_mm / 2)
    return np.clip(hi - lo, 0, None) / box_mm


def _window_kernels(
    pixel_mm: tuple[float, float], box_mm: tuple[float, float], radii_mm: np.ndarray,
    shift_mm: float = 0.0,
) -> np.ndarray:
    """Weights (L, 2k+1, 2k+1) of display pixels around a sample point at a pixel centre.

    Level l is the mean over a disk of radius radii_mm[l], smeared by the view pixel's box, of a
    display that is constant over each pixel, each pixel's emitting area moved by shift_mm along
    +x (a sub-pixel stripe's offset; |shift_mm| <= a third of a pixel, which the kernel's one
    pixel of slack covers). Rows run toward -y like images; the kernels are symmetric (for
    shift_mm = 0) so the sign does not matter.
    """
    wx, wy = pixel_mm
    reach = float(radii_mm.max()) + max(box_mm) / 2
    k = math.ceil(reach / min(wx, wy) + 1)
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


@dataclass(frozen=True)
class _Pairs:
    """The (view pixel, hole) pairs that can carry light for one eye position, packed (N, S).

    Everything here is independent of the hole radii and the display content: the lens centre is
    taken midway between its two disks' centres, exact for equal radii (infinite focus) and off by
    at most |1 - m| r / 2 otherwise (m: top-face radius scale, within a few % of 1).
    """

    hole: torch.Tensor  # (N, S) int64 flat cell index; the extra last index is a closed cell
    lens_offset_mm: torch.Tensor  # (N, S) centre distance of the lens's two disks
    pupil_offset_mm: torch.Tensor  # (N, S) lens centre to the pupil footprint's centre
    grid_xy: torch.Tensor  # (N, S, 2) normalized display sample point of the lens centre
    #: (N, S) the display's emission falloff cos^k at the pair's chief ray; None: Lambertian.
    emission: torch.Tensor | None = None


class _PairWeights(torch.autograd.Function):
    """Per (view pixel, hole) pair: the pupil share of the rays that pass the hole, and the
    blur-stack coordinate of its display window, from the hole radii. Fused, with a hand-written
    backward, because this runs on millions of pairs per view."""

    @staticmethod
    def forward(ctx, radius, hole, lens_offset, pupil_offset, top_scale, pupil_r, level_scale):
        r1 = radius[hole]
        d = lens_offset
        if top_scale == 1.0:
            # Equal disks (infinite focus): A = 2 r^2 acos(d / 2r) - (d / 2) sqrt(4 r^2 - d^2),
            # dA/dr = 4 r acos(d / 2r).
            half = (d / (2 * r1)).clamp(max=1.0)
            theta = torch.acos(half)
            area = 2 * r1 * r1 * theta - d * r1 * (1 - half * half).sqrt()
            darea = 4 * r1 * theta
        else:
            r2 = r1 * top_scale
            inside = d <= (r1 - r2).abs()
            partial = (d < r1 + r2) & ~inside
            d_s = d.clamp_min(_EPS)
            c1 = ((d_s * d_s + r1 * r1 - r2 * r2) / (2 * d_s * r1)).clamp(-1, 1)
            c2 = ((d_s * d_s + r2 * r2 - r1 * r1) / (2 * d_s * r2)).clamp(-1, 1)
            t1, t2 = torch.acos(c1), torch.acos(c2)
            kite = (r1 * torch.sin(t1)) * d_s  # half-chord times centre distance
            small = torch.minimum(r1, r2)
            zero = torch.zeros_like(r1)
            area = torch.where(partial, r1 * r1 * t1 + r2 * r2 * t2 - kite,
                               torch.where(inside, math.pi * small * small, zero))
            # dA/dr1 = 2 r1 theta1, dA/dr2 = 2 r2 theta2, and r2 = top_scale * r1.
            darea = torch.where(partial, 2 * r1 * t1 + 2 * top_scale * r2 * t2,
                                torch.where(inside, 2 * math.pi * small * small / r1, zero))
        # Pupil clipping: share of an equal-area disk inside the pupil's (locally straight) edge.
        lens_r = (area / math.pi).clamp_min(_EPS).sqrt()
        x = (pupil_r - pupil_offset) / lens_r
        cut = x.abs() < 1
        xs = torch.where(cut, x, torch.zeros_like(x))
        root = (1 - xs**2).clamp_min(0).sqrt()
        share = torch.where(cut, 0.5 + (torch.asin(xs) + xs * root) / math.pi, (x >= 1).to(x.dtype))
        norm = 1 / (math.pi * pupil_r**2)
        weight = area * share * norm
        level = (2 * level_scale * area - 1).clamp(-1, 1)
        ctx.save_for_backward(hole, darea * (share - xs * root / math.pi) * norm,
                              darea * (2 * level_scale) * (level.abs() < 1))
        ctx.cells = radius.shape[0]
        return weight, level

    @staticmethod
    def backward(ctx, grad_weight, grad_level):
        hole, dweight, dlevel = ctx.saved_tensors
        grad_r = grad_weight * dweight + grad_level * dlevel
        grad_radius = torch.zeros(ctx.cells, dtype=grad_r.dtype, device=grad_r.device)
        grad_radius.index_add_(0, hole.reshape(-1), grad_r.reshape(-1))
        return grad_radius, None, None, None, None, None, None


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
#: Most grad-stack buffers of the CPU kernel's backward (one per block of view rows).
MAX_GRAD_BLOCKS_BYTES = 2 * 2**30


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
    """

    def __init__(
        self,
        scene: Scene,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
        chunk_pairs: int = DEFAULT_CHUNK_PAIRS,
        hole_offset_mm: np.ndarray | None = None,
        backend: Backend = "auto",
    ) -> None:
        self.scene = scene
        self.hole_offset_mm = _checked_offsets(scene, hole_offset_mm)
        self.device = torch.device(device)
        self.dtype = dtype
        self.chunk_pairs = chunk_pairs
        self.backend = backend_for(backend, self.device)
        self.optics = opt = _Optics.of(scene)
        plate, eye, display = scene.plate, scene.eye, scene.display

        # Radius levels of the display window (mm on the display), uniform in radius squared;
        # wide enough for an eye focused at infinity too (|mu| = 1), for eye states off nominal.
        self.window_max_mm = max(abs(opt.window_scale), 1.0) * plate.max_radius_mm
        pixel_mm = display.pixel_mm
        levels = math.ceil(self.window_max_mm / (LEVEL_SPACING_PX * min(pixel_mm))) + 1
        levels = min(MAX_LEVELS, max(2, levels))
        radii = self.window_max_mm * np.sqrt(np.linspace(0, 1, levels))
        step = eye.view_step
        # The view pixel's box on the display, at the nominal focus (see docs/model.md); cover
        # glass slows the window's motion by its paraxial apparent-depth loss t_g (1 - 1/n).
        rate = opt.window_rate
        if display.cover_glass_mm > 0:
            rate = max(rate - display.cover_glass_mm * (1 - 1 / display.cover_glass_index), 0.0)
        box = (rate * step[0], rate * step[1])
        kernels = _window_kernels(pixel_mm, box, radii)
        # Striped RGB: each channel's kernels with its stripe's offset (built for a 3-channel
        # display only; a grey display's one channel fills the pixel).
        self._subpixel_spectrum: torch.Tensor | None = None
        offsets_px = display.subpixel_offsets_px(SUBPIXEL_CHANNELS)
        self.kernel_size = kernels.shape[-1]
        self.pad = self.kernel_size // 2 + 1
        ny, nx = display.pixels[1] + 2 * self.pad, display.pixels[0] + 2 * self.pad
        self._fft_shape = (ny + self.kernel_size - 1, nx + self.kernel_size - 1)
        k = torch.as_tensor(kernels, dtype=dtype, device=self.device)
        self._kernel_spectrum = torch.fft.rfft2(k, s=self._fft_shape)
        if offsets_px is not None:
            per_channel = np.stack([_window_kernels(pixel_mm, box, radii, o * pixel_mm[0])
                                    for o in offsets_px])
            self._subpixel_spectrum = torch.fft.rfft2(
                torch.as_tensor(per_channel, dtype=dtype, device=self.device), s=self._fft_shape)
        self.pupil_bottom_mm = eye.pupil_mm / 2 * abs(opt.beta_bottom)
        self._pairs: dict[tuple[float, ...], _Pairs] = {}
        self._white: torch.Tensor | None = None
        self._gpu_constants: tuple[torch.Tensor, ...] | None = None

    @property
    def _axis_length(self) -> float:
        """Plate mid-thickness to the pupil: the length of a chief-ray hole axis."""
        return self.scene.mid_plane_distance_mm

    @property
    def _search_extra_mm(self) -> float:
        """How much farther than the footprint a hole's axis may lie and still reach it: the
        chief-ray tilt at the bottom face plus the largest hole displacement."""
        plate, eye = self.scene.plate, self.scene.eye
        extra = 0.0
        if plate.hole_axis == "chief_ray":
            half = math.hypot(plate.size_mm[0] / 2 + abs(eye.positions_mm[0][0]),
                              plate.size_mm[1] / 2 + abs(eye.positions_mm[0][1]))
            extra = plate.thickness_mm / 2 * half / self._axis_length
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
            opt = _Optics.of(scene, diopters / 1000.0)
            pupil_b = pupil / 2 * abs(opt.beta_bottom)
            mu = opt.window_scale
            rows.append((cx, cy, pupil_b, opt.top_to_bottom, mu,
                         mu * mu / math.pi / max(self.window_max_mm**2, _EPS),
                         1 / (math.pi * pupil_b**2), pupil_b + 2 * scene.plate.max_radius_mm))
        return np.asarray(rows, dtype=np.float64).reshape(-1, len(STATE_FIELDS))

    def pair_count(self, position: int = 0) -> int:
        """(view pixel, hole) pairs the nominal state at `position` evaluates."""
        return int(self._pair_table(self.state_rows(self.nominal_states(position))[0])
                   .hole.numel())

    # -- display ------------------------------------------------------------------------------

    def display_stack(self, display: torch.Tensor) -> torch.Tensor:
        """Pre-filter a display (C, H, W) into the window stack (1, C, L, H', W'). A striped
        RGB display (`Display.subpixels`) filters each channel with its stripe's offset."""
        d = F.pad(display.to(self.device, self.dtype), (self.pad,) * 4)
        spectrum = torch.fft.rfft2(d, s=self._fft_shape)  # (C, ., .)
        kernel = self._kernel_spectrum[None]
        if self.scene.display.subpixel_offsets_px(d.shape[0]) is not None:
            kernel = cast(torch.Tensor, self._subpixel_spectrum)
        full = torch.fft.irfft2(spectrum[:, None] * kernel, s=self._fft_shape)
        c = self.kernel_size // 2
        return full[:, :, c : c + d.shape[-2], c : c + d.shape[-1]].unsqueeze(0)

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
        a = open_fraction.to(self.device, self.dtype).reshape(-1).clamp_min(0)
        px, py = scene.plate.pitch_mm
        radius = (a * (px * py / math.pi)).add(_EPS).sqrt()
        rows = self.state_rows(states)
        if self.backend == "kernel":
            view = _KernelView.apply(radius, stack, self, rows)
        elif self.backend == "triton":
            view = _TritonView.apply(radius, stack.to(self.device), self, rows)
        else:
            view = torch.stack([self._render_table(radius, stack, row) for row in rows])
        return view.reshape(len(rows), stack.shape[1], *reversed(scene.eye.view_pixels))

    # -- torch path: pair tables --------------------------------------------------------------

    def _pair_table(self, row: np.ndarray) -> _Pairs:
        key = tuple(float(v) for v in row)
        if key not in self._pairs:
            if len(self._pairs) >= TABLE_CACHE:
                self._pairs.pop(next(iter(self._pairs)))
            with torch.no_grad():
                self._pairs[key] = self._build_pairs(row)
        return self._pairs[key]

    def _render_table(self, radius: torch.Tensor, stack: torch.Tensor, row: np.ndarray
                      ) -> torch.Tensor:
        pairs = self._pair_table(row)
        radius = torch.cat([radius, radius.new_full((1,), math.sqrt(_EPS))])  # a closed cell
        rows_per_chunk = max(1, self.chunk_pairs // max(1, pairs.hole.shape[1]))
        out = []
        for start in range(0, pairs.hole.shape[0], rows_per_chunk):
            sl = slice(start, start + rows_per_chunk)
            weight, level = _PairWeights.apply(
                radius, pairs.hole[sl], pairs.lens_offset_mm[sl], pairs.pupil_offset_mm[sl],
                abs(float(row[3])), float(row[2]), float(row[5]))
            grid = torch.cat([pairs.grid_xy[sl], level.unsqueeze(-1)], dim=-1)[None, None]
            samples = F.grid_sample(stack, grid, mode="bilinear", padding_mode="zeros",
                                    align_corners=True)[0, :, 0]  # (C, n, S)
            if pairs.emission is not None:
                weight = weight * pairs.emission[sl]
            out.append((samples * weight).sum(-1))
        return torch.cat(out, dim=1)

    def _build_pairs(self, row: np.ndarray) -> _Pairs:
        scene = self.scene
        plate, eye = scene.plate, scene.eye
        px, py = plate.pitch_mm
        ncx, ncy = plate.cells
        t = plate.thickness_mm
        cx, cy, _, m, mu, _, _, keep_within = (float(v) for v in row)
        s_b, s_t, s_d = scene.plate_distance_mm, eye.eye_relief_mm, scene.display_distance_mm
        dt = torch.float64  # geometry in double, stored in the working dtype
        vx, vy = eye.view_directions()
        gy, gx = np.meshgrid(vy, vx, indexing="ij")
        views = torch.as_tensor(np.stack([gx.ravel(), gy.ravel()], 1), dtype=dt,
                                device=self.device)
        offsets = None
        if self.hole_offset_mm is not None:
            offsets = torch.as_tensor(self.hole_offset_mm.reshape(-1, 2), dtype=dt,
                                      device=self.device)
        display = scene.display
        display_optics = display.cover_glass_mm > 0 or display.emission_power > 0
        reach = keep_within + self._search_extra_mm
        # The window may reach past the plate's edge (masked below); never clamp its size to
        # the plate, which would shift it off the holes on narrow plates.
        nsx = math.floor(2 * reach / px) + 2
        nsy = math.floor(2 * reach / py) + 2
        oy, ox = torch.meshgrid(torch.arange(nsy, device=self.device),
                                torch.arange(nsx, device=self.device), indexing="ij")
        oy, ox = oy.reshape(1, -1), ox.reshape(1, -1)
        per_chunk = max(1, self.chunk_pairs // (nsx * nsy))
        parts: list[list[torch.Tensor]] = []
        for start in range(0, views.shape[0], per_chunk):
            v = views[start : start + per_chunk]
            fx = cx + s_b * v[:, :1]
            fy = cy + s_b * v[:, 1:]
            rows = torch.ceil((ncy - 1) / 2 - (fy + reach) / py).long() + oy
            cols = torch.ceil((fx - reach) / px + (ncx - 1) / 2).long() + ox
            hx = (cols - (ncx - 1) / 2).to(dt) * px  # hole axis at mid-thickness
            hy = ((ncy - 1) / 2 - rows).to(dt) * py
            if plate.hole_axis == "chief_ray":
                ex, ey = eye.positions_mm[0]
                ax, ay = (ex - hx) / self._axis_length, (ey - hy) / self._axis_length
            else:
                ax = ay = torch.zeros_like(hx)
            keep = (rows >= 0) & (rows < ncy) & (cols >= 0) & (cols < ncx)
            if offsets is not None:
                shift = offsets[rows.clamp(0, ncy - 1) * ncx + cols.clamp(0, ncx - 1)]
                hx, hy = hx + shift[..., 0], hy + shift[..., 1]
            bx, by = hx - t / 2 * ax, hy - t / 2 * ay  # bottom-face centre
            tx, ty = hx + t / 2 * ax, hy + t / 2 * ay  # top-face centre
            keep &= (bx - fx) ** 2 + (by - fy) ** 2 < keep_within**2
            # Top-face disk mapped to the bottom face, for this view direction.
            ctx = fx + m * (tx - cx - s_t * v[:, :1])
            cty = fy + m * (ty - cy - s_t * v[:, 1:])
            dx, dy = ctx - bx, cty - by
            dist = (dx**2 + dy**2).sqrt()
            # Lens centre midway between the two disks; its offset from the footprint centre.
            lx, ly = (bx + ctx) / 2, (by + cty) / 2
            pupil_off = ((lx - fx) ** 2 + (ly - fy) ** 2).sqrt()
            wx = cx + s_d * v[:, :1] + mu * (lx - fx)
            wy = cy + s_d * v[:, 1:] + mu * (ly - fy)
            emission = None
            if display_optics:
                wx, wy, emission = self._display_optics(wx, wy, lx, ly)
            gx, gy = self._normalize(wx, wy)
            hole = torch.where(keep, rows.clamp(0, ncy - 1) * ncx + cols.clamp(0, ncx - 1),
                               ncx * ncy)
            # Pack the kept pairs to the front of each row.
            order = torch.argsort((~keep).to(torch.int8), dim=1, stable=True)
            fields = [hole, dist, pupil_off, gx, gy]
            if emission is not None:
                fields.append(emission)
            parts.append([f.gather(1, order) for f in fields] + [keep.sum(1)])
        width = max(1, int(max(int(p[-1].max()) for p in parts)))
        cat = [torch.cat([p[i][:, :width] for p in parts]) for i in range(len(parts[0]) - 1)]
        return _Pairs(
            hole=cat[0],
            lens_offset_mm=cat[1].to(self.dtype),
            pupil_offset_mm=cat[2].to(self.dtype),
            grid_xy=torch.stack([cat[3], cat[4]], -1).to(self.dtype),
            emission=cat[5].to(self.dtype) if len(cat) > 5 else None,
        )

    def _display_optics(self, wx: torch.Tensor, wy: torch.Tensor, lx: torch.Tensor,
                        ly: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor,
                                                   torch.Tensor | None]:
        """A pair's window centre (wx, wy) on the emitting surface moved by the cover glass,
        and its emission falloff (None: Lambertian), both at the pair's chief ray: the ray
        through the lens centre (lx, ly) on the bottom face toward the window centre in air,
        slope w = (window - lens) / gap (v at infinite focus). See docs/model.md."""
        display = self.scene.display
        gap = self.scene.plate.gap_mm
        sx, sy = (wx - lx) / gap, (wy - ly) / gap
        tan2 = sx * sx + sy * sy
        t_g, n = display.cover_glass_mm, display.cover_glass_index
        if t_g > 0:
            # Straight on in air to z = 0, less the glass's shortfall: in the glass the slope is
            # w tan(theta_g) / tan(theta) = w / sqrt(n^2 + (n^2 - 1) |w|^2) (Snell).
            loss = t_g * (1 - (n * n + (n * n - 1) * tan2).rsqrt())
            wx, wy = wx - loss * sx, wy - loss * sy
        emission = None
        k = display.emission_power
        if k > 0:
            emission = (1 + tan2).pow(-k / 2)  # cos(theta)^k, theta the angle in air
        return wx, wy, emission

    def _normalize(self, x_mm: torch.Tensor, y_mm: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor]:
        display = self.scene.display
        width = display.pixels[0] + 2 * self.pad
        height = display.pixels[1] + 2 * self.pad
        col = (x_mm + display.width_mm / 2) / display.pixel_mm[0] - 0.5 + self.pad
        row = (display.height_mm / 2 - y_mm) / display.pixel_mm[1] - 0.5 + self.pad
        return 2 * col / (width - 1) - 1, 2 * row / (height - 1) - 1

    # -- kernel path --------------------------------------------------------------------------

    def kernel_geometry(self) -> np.ndarray:
        """The scene's constants for `aperture_fab.optics.kernels`, in GEOMETRY_FIELDS order."""
        scene = self.scene
        plate, eye, display = scene.plate, scene.eye, scene.display
        ex, ey = eye.positions_mm[0]
        return np.array([
            plate.cells[0], plate.cells[1], plate.pitch_mm[0], plate.pitch_mm[1],
            plate.thickness_mm, float(plate.hole_axis == "chief_ray"), ex, ey,
            self._axis_length, scene.plate_distance_mm, eye.eye_relief_mm,
            scene.display_distance_mm, display.width_mm / 2, display.height_mm / 2,
            display.pixel_mm[0], display.pixel_mm[1], self.pad,
            display.cover_glass_mm, display.cover_glass_index, display.emission_power,
        ], dtype=np.float64)


def _gpu_constants(renderer: Renderer) -> tuple[torch.Tensor, ...]:
    """The triton path's fixed inputs on the renderer's device (view directions vx, vy, hole
    offsets (K, 2), geometry), copied there once: each blocking host-to-device copy waits for
    the GPU's queue to drain."""
    if renderer._gpu_constants is None:
        vx, vy = renderer.scene.eye.view_directions()
        cells = renderer.scene.plate.cells
        offsets = (np.zeros((cells[0] * cells[1], 2)) if renderer.hole_offset_mm is None
                   else renderer.hole_offset_mm.reshape(-1, 2))
        renderer._gpu_constants = tuple(
            torch.as_tensor(np.ascontiguousarray(v), dtype=torch.float64,
                            device=renderer.device)
            for v in (vx, vy, offsets, renderer.kernel_geometry()))
    return renderer._gpu_constants


def _walk_plan(renderer: Renderer, radius: torch.Tensor, rows: np.ndarray, radius_grad: bool
               ) -> tuple[np.ndarray, float, int, bool, float, float]:
    """What the fused kernels' hole walk needs beyond the scene (see
    `aperture_fab.optics.kernels`): the hole offsets (K, 2) mm, the search's extra reach, the
    box of holes the union of the states' windows can span, whether every state focuses at
    infinity (they then share each pair's geometry and display sample), the walk's margin and
    the radius at or below which a hole is skipped."""
    scene = renderer.scene
    vx, vy = scene.eye.view_directions()
    offsets = (np.zeros((radius.shape[0], 2)) if renderer.hole_offset_mm is None
               else renderer.hole_offset_mm.reshape(-1, 2))
    extra = renderer._search_extra_mm
    shared = bool(np.all(rows[:, 3] == 1.0) and np.all(rows[:, 4] == 1.0))
    # Holes per axis that the union of the states' windows can span, plus slack.
    slack = scene.plate.thickness_mm * float(np.hypot(np.abs(vx).max(), np.abs(vy).max()))
    spread = float(np.ptp(rows[:, :2], axis=0).max() + 2 * (rows[:, 7].max() + extra) + slack)
    box = math.ceil(spread / min(scene.plate.pitch_mm)) + 3
    margin = float(radius.detach().max()) + (0.0 if renderer.hole_offset_mm is None else float(
        np.linalg.norm(renderer.hole_offset_mm, axis=-1).max()))
    # Without a radius gradient, closed cells (radius sqrt(_EPS): no area) are skipped; a
    # gradient keeps them, as a closed cell's gradient can open it.
    closed = 0.0 if radius_grad else CLOSED_RADIUS_MM
    return offsets, extra, box, shared, margin, closed


class _KernelView(torch.autograd.Function):
    """Views (S, C, ny, nx) from hole radii (K,) and a display stack (1, C, L, H, W) through
    the fused CPU kernels, for the eye states `rows` (`Renderer.state_rows`). States that all
    focus at infinity share each pair's geometry and display sample."""

    @staticmethod
    def forward(ctx, radius, stack, renderer, rows):
        vx, vy = renderer.scene.eye.view_directions()
        offsets, extra, box, shared, margin, closed = _walk_plan(
            renderer, radius, rows, ctx.needs_input_grad[0])
        channels_last = stack.detach()[0].permute(1, 2, 3, 0).contiguous().numpy()
        args: tuple[Any, ...] = (radius.detach().double().numpy(), channels_last, vx, vy, rows,
                                 renderer.kernel_geometry(), offsets, extra, box, shared, margin,
                                 closed)
        out = np.zeros((len(rows), stack.shape[1], len(vy), len(vx)))
        cast(Any, kernels.view_forward)(*args, out)  # numba dispatchers are untyped
        ctx.args, ctx.dtype = args, stack.dtype
        return torch.from_numpy(out).to(stack.dtype)

    @staticmethod
    def backward(ctx, grad_view):
        radius, channels_last, _, vy = ctx.args[:4]
        want_stack = ctx.needs_input_grad[1]
        stack_bytes = channels_last.nbytes if want_stack else 0
        blocks = max(1, min(len(vy), kernels.thread_count(),
                            MAX_GRAD_BLOCKS_BYTES // max(1, stack_bytes)))
        grad_radius = np.zeros((blocks, len(radius)))
        grad_stack = np.zeros((blocks, *channels_last.shape) if want_stack else (1, 1, 1, 1, 1),
                              dtype=channels_last.dtype)
        grad = np.ascontiguousarray(grad_view.detach().double().numpy())
        cast(Any, kernels.view_backward)(*ctx.args, grad, grad_radius, grad_stack, want_stack)
        out_radius = torch.from_numpy(grad_radius.sum(0)).to(ctx.dtype)
        out_stack = None
        if want_stack:
            out_stack = torch.from_numpy(grad_stack.sum(0)).permute(3, 0, 1, 2)[None]
            out_stack = out_stack.to(ctx.dtype).contiguous()
        return out_radius, out_stack, None, None


class _TritonView(torch.autograd.Function):
    """As `_KernelView`, through the fused GPU kernels (`aperture_fab.optics.gpu_kernels`) on
    the stack's device: every eye state in one launch, nothing per pair stored."""

    @staticmethod
    def forward(ctx, radius, stack, renderer, rows):
        from aperture_fab.optics import gpu_kernels

        _, extra, _, shared, margin, closed = _walk_plan(
            renderer, radius, rows, ctx.needs_input_grad[0])
        vx, vy, offsets, geometry = _gpu_constants(renderer)
        walk = gpu_kernels.Walk(
            radius.detach().double().contiguous(),
            stack.detach()[0].permute(1, 2, 3, 0).contiguous(), vx, vy, rows,
            renderer.kernel_geometry(), geometry, offsets, extra, shared, margin, closed)
        ctx.walk, ctx.dtype = walk, stack.dtype
        return gpu_kernels.view_forward(walk).to(stack.dtype)

    @staticmethod
    def backward(ctx, grad_view):
        from aperture_fab.optics import gpu_kernels

        grad_radius, grad_stack = gpu_kernels.view_backward(
            ctx.walk, grad_view.detach(), bool(ctx.needs_input_grad[1]))
        out_stack = None
        if grad_stack is not None:
            out_stack = grad_stack.permute(3, 0, 1, 2)[None].to(ctx.dtype).contiguous()
        return grad_radius.to(ctx.dtype), out_stack, None, None


def render_open_states(scene: Scene, display: torch.Tensor, states: EyeStates,
                       pupil_samples: int = 128, subpixels: int = 2) -> torch.Tensor:
    """Views (S, C, ny, nx) of the display with no plate for each eye state (see
    `render_open`)."""
    return torch.stack([
        render_open(scene, display, pupil_samples=pupil_samples, subpixels=subpixels,
                    offset_mm=tuple(offset), pupil_mm=float(pupil),
                    focus_diopters=float(diopters))
        for offset, pupil, diopters in zip(states.offset_mm, states.pupil_mm,
                                           states.focus_diopters, strict=True)
    ])


def render_open(
    scene: Scene,
    display: torch.Tensor,
    position: int = 0,
    pupil_samples: int = 128,
    subpixels: int = 2,
    *,
    offset_mm: tuple[float, float] | None = None,
    pupil_mm: float | None = None,
    focus_diopters: float | None = None,
) -> torch.Tensor:
    """View (C, ny, nx) of the display with no plate, by quadrature over the pupil (a sunflower
    pattern of `pupil_samples` points) and `subpixels`^2 points per view pixel, from eyebox
    position `position`, or from the pupil centre `offset_mm` with `pupil_mm` and
    `focus_diopters` (each None: the scene's)."""
    eye, disp = scene.eye, scene.display
    opt = _Optics.of(scene, None if focus_diopters is None else focus_diopters / 1000.0)
    dev, dtype = display.device, display.dtype
    cx, cy = eye.positions_mm[position] if offset_mm is None else offset_mm
    pupil = eye.pupil_mm if pupil_mm is None else pupil_mm
    if disp.has_optics:
        return _render_open_optics(scene, display, opt, (cx, cy), pupil, pupil_samples,
                                   subpixels)
    spread = pupil / 2 * abs(opt.beta_display)
    n = pupil_samples if spread > 1e-3 * min(disp.pixel_mm) else 1
    k = torch.arange(n, dtype=dtype, device=dev) + 0.5
    golden = math.pi * (3 - math.sqrt(5))
    radius = torch.sqrt(k / n) * spread
    px, py = radius * torch.cos(golden * k), radius * torch.sin(golden * k)  # (n,)
    sub = (torch.arange(subpixels, dtype=dtype, device=dev) + 0.5) / subpixels - 0.5
    vx, vy = (torch.as_tensor(v, dtype=dtype, device=dev) for v in eye.view_directions())
    step = eye.view_step
    sx = (vx[:, None] + sub[None, :] * step[0]).reshape(-1)  # (nx * s,)
    # Normalized display coordinates (align_corners=False: -1 and 1 are the display's edges).
    to_gx = 2 / disp.width_mm
    to_gy = -2 / disp.height_mm
    gx = ((cx + opt.s_display * sx)[None, :, None] + px[None, None, :]) * to_gx  # (1, nx s, n)
    rows = []
    for y in vy:
        sy = y - sub * step[1]  # (s,)
        gy = ((cy + opt.s_display * sy)[:, None, None] + py[None, None, :]) * to_gy  # (s, 1, n)
        grid = torch.stack(torch.broadcast_tensors(gx, gy), -1).reshape(1, 1, -1, 2)
        out = F.grid_sample(display.unsqueeze(0), grid, mode="bilinear", padding_mode="zeros",
                            align_corners=False)  # (1, C, 1, s * nx * s * n)
        rows.append(out.reshape(display.shape[0], subpixels, len(vx), subpixels * n).mean((1, 3)))
    return torch.stack(rows, 1)


def _render_open_optics(scene: Scene, display: torch.Tensor, opt: _Optics,
                        centre_mm: tuple[float, float], pupil_mm: float, pupil_samples: int,
                        subpixels: int) -> torch.Tensor:
    """`render_open` with display-side optics, per ray: each ray (view sample s, pupil point
    u) has slope w = s - q u in air, lands on the emitting surface short of its straight
    continuation by the cover glass's shortfall t_g w (1 - 1 / sqrt(n^2 + (n^2 - 1) |w|^2)),
    carries cos^k of its angle in air, and reads each channel at its sub-pixel stripe's
    offset."""
    eye, disp = scene.eye, scene.display
    dev, dtype = display.device, display.dtype
    q = (1 - opt.beta_display) / opt.s_display
    n = pupil_samples
    k = torch.arange(n, dtype=dtype, device=dev) + 0.5
    golden = math.pi * (3 - math.sqrt(5))
    radius = torch.sqrt(k / n) * (pupil_mm / 2)
    ux, uy = radius * torch.cos(golden * k), radius * torch.sin(golden * k)  # (n,) pupil points
    sub = (torch.arange(subpixels, dtype=dtype, device=dev) + 0.5) / subpixels - 0.5
    vx, vy = (torch.as_tensor(v, dtype=dtype, device=dev) for v in eye.view_directions())
    step = eye.view_step
    sx = (vx[:, None] + sub[None, :] * step[0]).reshape(-1)[None, :, None]  # (1, nx s, 1)
    t_g, index, power = disp.cover_glass_mm, disp.cover_glass_index, disp.emission_power
    shifts = disp.subpixel_offsets_px(display.shape[0])
    channels = [0.0] * display.shape[0] if shifts is None else list(shifts)
    to_gx = 2 / disp.width_mm
    to_gy = -2 / disp.height_mm
    rows = []
    for y in vy:
        sy = (y - sub * step[1])[:, None, None]  # (s, 1, 1)
        wx, wy = sx - q * ux, sy - q * uy  # (., ., n) slopes in air
        tan2 = wx * wx + wy * wy
        loss = t_g * (1 - (index * index + (index * index - 1) * tan2).rsqrt())
        lx = centre_mm[0] + opt.s_display * sx + opt.beta_display * ux - loss * wx
        ly = centre_mm[1] + opt.s_display * sy + opt.beta_display * uy - loss * wy
        lx, ly = torch.broadcast_tensors(lx, ly)
        weight = (1 + tan2).pow(-power / 2) if power > 0 else torch.ones_like(tan2)
        out = []
        for c, shift_px in enumerate(channels):
            gx = (lx - shift_px * disp.pixel_mm[0]) * to_gx
            grid = torch.stack([gx, ly * to_gy], -1).reshape(1, 1, -1, 2)
            value = F.grid_sample(display[c][None, None], grid, mode="bilinear",
                                  padding_mode="zeros", align_corners=False)
            out.append((value.reshape(lx.shape) * weight).mean((0, 2)).reshape(len(vx), -1)
                       .mean(1))
        rows.append(torch.stack(out))
    return torch.stack(rows, 1)
