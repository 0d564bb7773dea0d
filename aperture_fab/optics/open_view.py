"""The view of the display with no plate (the open display): the reference the plate's views
are scored against, by quadrature over the pupil and each view pixel."""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F

from aperture_fab.optics.eyes import EyeStates
from aperture_fab.optics.kernel_open import LANES, open_quadrature
from aperture_fab.optics.planes import Optics
from aperture_fab.optics.scene import Scene

__all__ = ["OpenBackend", "render_open", "render_open_states"]

#: How `render_open` takes its samples (see there).
OpenBackend = Literal["auto", "kernel", "torch"]
#: The sunflower pattern's angle step between pupil points (radians).
GOLDEN_ANGLE = math.pi * (3 - math.sqrt(5))


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
    backend: OpenBackend = "auto",
) -> torch.Tensor:
    """View (C, ny, nx) of the display with no plate, by quadrature over the pupil (a sunflower
    pattern of `pupil_samples` points) and `subpixels`^2 points per view pixel, from eyebox
    position `position`, or from the pupil centre `offset_mm` with `pupil_mm` and
    `focus_diopters` (each None: the scene's).

    backend: "kernel" (the fused CPU kernel, `kernel_open`: no gradient), "torch" (sample grids
    and grid_sample: the reference, on any device, with gradients) or "auto" (the kernel for a
    display on the CPU that needs no gradient, else torch). A display with optics (cover
    glass, sub-pixel stripes, emission falloff) always takes the torch path."""
    eye, disp = scene.eye, scene.display
    opt = Optics.of(scene, None if focus_diopters is None else focus_diopters / 1000.0)
    dev, dtype = display.device, display.dtype
    cx, cy = eye.positions_mm[position] if offset_mm is None else offset_mm
    pupil = eye.pupil_mm if pupil_mm is None else pupil_mm
    if disp.has_optics:
        return _render_open_optics(scene, display, opt, (cx, cy), pupil, pupil_samples,
                                   subpixels)
    spread = pupil / 2 * abs(opt.beta_display)
    n = pupil_samples if spread > 1e-3 * min(disp.pixel_mm) else 1
    if backend == "auto":
        backend = "kernel" if dev.type == "cpu" and not display.requires_grad else "torch"
    if backend == "kernel":
        if dev.type != "cpu":
            raise ValueError(f"render_open(backend='kernel') needs the display on the CPU, not "
                             f"{dev}; give backend='auto' or 'torch' there.")
        return _render_open_kernel(scene, display, opt.s_display, (cx, cy), spread, n,
                                   subpixels)
    k = torch.arange(n, dtype=dtype, device=dev) + 0.5
    radius = torch.sqrt(k / n) * spread
    px, py = radius * torch.cos(GOLDEN_ANGLE * k), radius * torch.sin(GOLDEN_ANGLE * k)  # (n,)
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


def _render_open_kernel(scene: Scene, display: torch.Tensor, s_display: float,
                        centre_mm: tuple[float, float], spread_mm: float, pupil_samples: int,
                        subpixels: int) -> torch.Tensor:
    """`render_open`'s quadrature (no display optics) by the fused CPU kernel: the same
    samples, taken without building them (`kernel_open`)."""
    eye, disp = scene.eye, scene.display
    k = np.arange(pupil_samples) + 0.5
    radius = np.sqrt(k / pupil_samples) * spread_mm
    angle = GOLDEN_ANGLE * k
    sub = (np.arange(subpixels) + 0.5) / subpixels - 0.5
    vx, vy = eye.view_directions()
    step = eye.view_step
    xs = centre_mm[0] + s_display * (vx[:, None] + sub[None, :] * step[0])  # (nx, s)
    ys = centre_mm[1] + s_display * (vy[:, None] - sub[None, :] * step[1])  # (ny, s)
    # grid_sample's unnormalized coordinates (align_corners=False): display pixels from the
    # first pixel's centre.
    width, height = display.shape[-1], display.shape[-2]
    to_px, to_py = width / disp.width_mm, -height / disp.height_mm
    fx, fy = xs * to_px + (width - 1) / 2, ys * to_py + (height - 1) / 2
    values = display.detach().to(torch.float64).numpy()
    channels = values.shape[0]
    out = np.empty((-(-channels // LANES) * LANES, len(vy), len(vx)))
    for first in range(0, channels, LANES):  # LANES channels a call, the last padded with 0
        lanes = np.zeros((height, width, LANES))
        lanes[..., :min(LANES, channels - first)] = values[first:first + LANES].transpose(1, 2, 0)
        open_quadrature(lanes, fx, fy, radius * np.cos(angle) * to_px,
                        radius * np.sin(angle) * to_py, out[first:first + LANES])
    out = out[:channels]
    return torch.from_numpy(out).to(display.dtype)


def _render_open_optics(scene: Scene, display: torch.Tensor, opt: Optics,
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
    radius = torch.sqrt(k / n) * (pupil_mm / 2)
    ux, uy = radius * torch.cos(GOLDEN_ANGLE * k), radius * torch.sin(GOLDEN_ANGLE * k)  # (n,)
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
