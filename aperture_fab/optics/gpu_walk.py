"""Launching the fused GPU kernels (aperture_fab.optics.gpu_kernels): what they read, on one
device (`Walk`), and the forward and backward passes. The kernels size each lane's box of holes
themselves, from the margin and the live states they read on the device."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import triton

from aperture_fab.optics.device import to_device
from aperture_fab.optics.gpu_kernels import BLOCK, NUM_WARPS, backward_kernel, forward_kernel

__all__ = ["Walk", "view_backward", "view_forward"]


@dataclass(frozen=True)
class Walk:
    """What the kernels read, on one device (as `aperture_fab.optics.kernels`' arguments).

    radius: (K,) float64 hole radii, mm. stack: (L, H, W, C) channels-last display stack, in
    its own dtype. vx, vy: (nx,), (ny,) float64 view directions (tan). states: (S, 8) and
    geometry: (len(GEOMETRY_FIELDS),) float64 numpy rows; device_geometry: the same row on the
    stack's device. offsets: (K, 2) float64 hole displacements, mm. extra, closed: mm;
    shared: every state focuses at infinity. offset_mm: the largest hole displacement, mm;
    the walk's margin is it plus the largest radius, found on the device (reading it back
    would make the host wait for the GPU's queue at every pass).
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
    offset_mm: float
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
        rows = to_device(self.states, torch.float64, self.stack.device)
        margin = self.radius.max().reshape(1) + self.offset_mm
        return (self.radius, self.offsets, self.stack, self.vx, self.vy, rows,
                self.device_geometry, margin)

    @property
    def _optics(self) -> bool:
        return bool(self.geometry[17] > 0 or self.geometry[19] > 0)


def view_forward(walk: Walk) -> torch.Tensor:
    """Views (S, C, ny, nx) float64 (see `aperture_fab.optics.kernels.view_forward`)."""
    levels, height, width, channels = walk.stack.shape
    nx, ny, count = len(walk.vx), len(walk.vy), len(walk.states)
    out = torch.empty((count, channels, ny, nx), dtype=torch.float64, device=walk.stack.device)
    forward_kernel[(triton.cdiv(nx * ny, BLOCK), count)](
        *walk._args, out, walk.extra, walk.closed, nx, ny, levels, height, width,
        C=channels, CP=triton.next_power_of_2(channels), BLOCK=BLOCK, SHARED=walk.shared,
        OPTICS=walk._optics, num_warps=NUM_WARPS)
    return out


def view_backward(walk: Walk, grad_out: torch.Tensor, want_stack: bool
                  ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Gradients of sum(grad_out * view) (grad_out (S, C, ny, nx)) in the radii (K,) float64
    and, when want_stack, the stack (L, H, W, C) float64. States whose grad_out is all zero
    are not walked (found on the device)."""
    levels, height, width, channels = walk.stack.shape
    nx, ny, count = len(walk.vx), len(walk.vy), len(walk.states)
    grad_radius = torch.zeros_like(walk.radius)
    grad_stack = torch.zeros(walk.stack.shape if want_stack else (1,), dtype=torch.float64,
                             device=walk.stack.device)
    if not count:  # no state gets a gradient
        return grad_radius, (grad_stack if want_stack else None)
    alive = grad_out.flatten(1).any(dim=1).to(torch.int32)
    backward_kernel[(triton.cdiv(nx * ny, BLOCK), 1 if walk.shared else count)](
        *walk._args, alive, grad_out.to(torch.float64).contiguous(), grad_radius, grad_stack,
        walk.extra, walk.closed, nx, ny, levels, height, width, count,
        C=channels, CP=triton.next_power_of_2(channels), BLOCK=BLOCK, SHARED=walk.shared,
        OPTICS=walk._optics, WANT_STACK=want_stack, num_warps=NUM_WARPS)
    return grad_radius, (grad_stack if want_stack else None)
