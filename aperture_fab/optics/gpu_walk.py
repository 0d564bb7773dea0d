"""Launching the fused GPU kernels (aperture_fab.optics.gpu_kernels): what they read, on one
device (`Walk`), the box of holes each lane walks, and the forward and backward passes."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import triton

from aperture_fab.optics.gpu_kernels import BLOCK, NUM_WARPS, backward_kernel, forward_kernel

__all__ = ["Walk", "view_backward", "view_forward"]


def _box(outer_mm: float, pitch_mm: float) -> int:
    """Holes per axis that a disk of radius outer_mm can span from its first one."""
    return math.floor(2 * outer_mm / pitch_mm) + 2


def _walk(states: np.ndarray, geometry: np.ndarray, margin: float, extra: float, shared: bool,
          union: bool) -> tuple[int, int]:
    """Box (rows, columns) of holes each lane walks: one state's disk, or (union) the disk
    around every state's, as `_span` places them."""
    outer = (states[:, 2] + margin) if shared else (states[:, 7] + extra)
    spread = np.ptp(states[:, :2], axis=0) if union else np.zeros(2)
    return (_box(float(outer.max() + spread[1] / 2), float(geometry[3])),
            _box(float(outer.max() + spread[0] / 2), float(geometry[2])))


@dataclass(frozen=True)
class Walk:
    """What the kernels read, on one device (as `aperture_fab.optics.kernels`' arguments).

    radius: (K,) float64 hole radii, mm. stack: (L, H, W, C) channels-last display stack, in
    its own dtype. vx, vy: (nx,), (ny,) float64 view directions (tan). states: (S, 8) and
    geometry: (len(GEOMETRY_FIELDS),) float64 numpy rows; device_geometry: the same row on the
    stack's device. offsets: (K, 2) float64 hole displacements, mm. extra, margin, closed: mm;
    shared: every state focuses at infinity.
    """

    radius: torch.Tensor
    stack: torch.Tensor
    vx: torch.Tensor
    vy: torch.Tensor
    states: np.ndarray
    geometry: np.ndarray
    device_geometry: torch.Tensor
    offsets: torch.Tensor
    extra: float
    shared: bool
    margin: float
    closed: float

    def __post_init__(self) -> None:
        for name in ("radius", "vx", "vy", "offsets", "device_geometry"):
            value = getattr(self, name)
            if value.dtype != torch.float64 or not value.is_contiguous():
                raise TypeError(f"Walk.{name} must be a contiguous float64 tensor; got "
                                f"{value.dtype}.")
        if self.stack.dim() != 4 or not self.stack.is_contiguous():
            raise TypeError("Walk.stack must be a contiguous (L, H, W, C) tensor (channels "
                            f"last); got shape {tuple(self.stack.shape)}.")

    @functools.cached_property
    def _args(self) -> tuple[Any, ...]:
        """The kernels' tensor arguments; the states copied to the device once per walk (the
        forward's and the backward's), without waiting for the GPU's queue."""
        rows = torch.from_numpy(np.ascontiguousarray(self.states, dtype=np.float64))
        if self.stack.is_cuda:
            rows = rows.pin_memory()
        rows = rows.to(self.stack.device, non_blocking=True)
        return (self.radius, self.offsets, self.stack, self.vx, self.vy, rows,
                self.device_geometry)

    @property
    def _optics(self) -> bool:
        return bool(self.geometry[17] > 0 or self.geometry[19] > 0)


def view_forward(walk: Walk) -> torch.Tensor:
    """Views (S, C, ny, nx) float64 (see `aperture_fab.optics.kernels.view_forward`)."""
    levels, height, width, channels = walk.stack.shape
    nx, ny, count = len(walk.vx), len(walk.vy), len(walk.states)
    out = torch.empty((count, channels, ny, nx), dtype=torch.float64, device=walk.stack.device)
    box_r, box_c = _walk(walk.states, walk.geometry, walk.margin, walk.extra, walk.shared,
                         union=False)
    forward_kernel[(triton.cdiv(nx * ny, BLOCK), count)](
        *walk._args, out, walk.extra, walk.margin, walk.closed, nx, ny, levels, height, width,
        box_r, box_c, C=channels, CP=triton.next_power_of_2(channels), BLOCK=BLOCK,
        SHARED=walk.shared, OPTICS=walk._optics, num_warps=NUM_WARPS)
    return out


def view_backward(walk: Walk, grad_out: torch.Tensor, want_stack: bool
                  ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Gradients of sum(grad_out * view) (grad_out (S, C, ny, nx)) in the radii (K,) float64
    and, when want_stack, the stack (L, H, W, C) float64."""
    levels, height, width, channels = walk.stack.shape
    nx, ny, count = len(walk.vx), len(walk.vy), len(walk.states)
    grad_radius = torch.zeros_like(walk.radius)
    grad_stack = torch.zeros(walk.stack.shape if want_stack else (1,), dtype=torch.float64,
                             device=walk.stack.device)
    if not count:  # no state gets a gradient
        return grad_radius, (grad_stack if want_stack else None)
    box_r, box_c = _walk(walk.states, walk.geometry, walk.margin, walk.extra, walk.shared,
                         union=walk.shared)
    backward_kernel[(triton.cdiv(nx * ny, BLOCK), 1 if walk.shared else count)](
        *walk._args, grad_out.to(torch.float64).contiguous(), grad_radius, grad_stack,
        walk.extra, walk.margin, walk.closed, nx, ny, levels, height, width, box_r, box_c, count,
        C=channels, CP=triton.next_power_of_2(channels), BLOCK=BLOCK, SHARED=walk.shared,
        OPTICS=walk._optics, WANT_STACK=want_stack, num_warps=NUM_WARPS)
    return grad_radius, (grad_stack if want_stack else None)
