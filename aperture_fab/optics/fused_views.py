"""The renderer's views through the fused kernels as autograd functions: the CPU kernels
(aperture_fab.optics.kernels) and the GPU kernels (aperture_fab.optics.gpu_kernels), every eye
state of a batch in one pass."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import torch

from aperture_fab.optics import kernels
from aperture_fab.optics.device import to_device
from aperture_fab.optics.planes import EPS

if TYPE_CHECKING:  # the renderer calls these; its module imports this one
    from aperture_fab.optics.model import Renderer

__all__ = ["CLOSED_RADIUS_MM", "MAX_GRAD_BLOCKS_BYTES", "KernelView", "TritonView"]

#: A cell whose radius is at most this (mm) is closed: the renderer gives it sqrt(EPS).
CLOSED_RADIUS_MM = math.sqrt(2 * EPS)
#: Most grad-stack buffers of the CPU kernel's backward (one per block of view rows).
MAX_GRAD_BLOCKS_BYTES = 2 * 2**30


def _gpu_constants(renderer: Renderer) -> tuple[torch.Tensor, ...]:
    """The triton path's fixed inputs on the renderer's device (view directions vx, vy, hole
    offsets (K, 2), geometry), copied there once per renderer (a made copy's moved holes make
    a new one each iteration), without waiting for the GPU's queue."""
    if renderer._gpu_constants is None:
        vx, vy = renderer.scene.eye.view_directions()
        cells = renderer.scene.plate.cells
        offsets = (np.zeros((cells[0] * cells[1], 2)) if renderer.hole_offset_mm is None
                   else renderer.hole_offset_mm.reshape(-1, 2))
        renderer._gpu_constants = tuple(
            to_device(v, torch.float64, renderer.device)
            for v in (vx, vy, offsets, renderer.kernel_geometry()))
    return renderer._gpu_constants


def _walk_plan(renderer: Renderer, radius: torch.Tensor, rows: np.ndarray, radius_grad: bool
               ) -> tuple[np.ndarray, float, int, bool, float, float]:
    """What the fused kernels' hole walk needs beyond the scene (see
    `aperture_fab.optics.kernels`): the hole offsets (K, 2) mm, the search's extra reach, the
    box of holes the union of the states' windows can span, whether every state focuses at
    infinity (they then share each pair's geometry and display sample), the largest hole
    displacement (mm; the walk's margin is it plus the largest radius) and the radius at or
    below which a hole is skipped."""
    scene = renderer.scene
    vx, vy = scene.eye.view_directions()
    offsets = (np.zeros((radius.shape[0], 2)) if renderer.hole_offset_mm is None
               else renderer.hole_offset_mm.reshape(-1, 2))
    extra = renderer.search_extra_mm
    shared = bool(np.all(rows[:, 3] == 1.0) and np.all(rows[:, 4] == 1.0))
    # Holes per axis that the union of the states' windows can span, plus slack.
    slack = scene.plate.thickness_mm * float(np.hypot(np.abs(vx).max(), np.abs(vy).max()))
    spread = float(np.ptp(rows[:, :2], axis=0).max() + 2 * (rows[:, 7].max() + extra) + slack)
    box = math.ceil(spread / min(scene.plate.pitch_mm)) + 3
    offset_mm = (0.0 if renderer.hole_offset_mm is None else
                 float(np.linalg.norm(renderer.hole_offset_mm, axis=-1).max()))
    # Without a radius gradient, closed cells (radius sqrt(EPS): no area) are skipped; a
    # gradient keeps them, as a closed cell's gradient can open it.
    closed = 0.0 if radius_grad else CLOSED_RADIUS_MM
    return offsets, extra, box, shared, offset_mm, closed


class KernelView(torch.autograd.Function):
    """Views (S, C, ny, nx) from hole radii (K,) and a display stack (1, C, L, H, W) through
    the fused CPU kernels, for the eye states `rows` (`Renderer.state_rows`). States that all
    focus at infinity share each pair's geometry and display sample."""

    @staticmethod
    def forward(ctx, radius, stack, renderer, rows):
        vx, vy = renderer.scene.eye.view_directions()
        offsets, extra, box, shared, offset_mm, closed = _walk_plan(
            renderer, radius, rows, ctx.needs_input_grad[0])
        channels_last = stack.detach()[0].permute(1, 2, 3, 0).contiguous().numpy()
        radius_mm = radius.detach().double().numpy()
        margin = float(radius_mm.max()) + offset_mm
        next_open = kernels.open_index(radius_mm, renderer.scene.plate.cells, closed)
        args: tuple[Any, ...] = (radius_mm, channels_last, vx, vy, rows,
                                 renderer.kernel_geometry(), offsets, extra, box, shared, margin,
                                 next_open)
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
        grad = grad_view.detach().double().numpy()
        # States the loss does not reach (a tail loss's best ones) add nothing: the backward
        # walks the others only (a pair costs the same for one state as for all, so fewer
        # states save the pairs only they reach: 37 % of the backward at 4 of 8 states).
        live = np.flatnonzero(grad.reshape(len(grad), -1).any(axis=1))
        if len(live):
            rows = np.ascontiguousarray(ctx.args[4][live])
            cast(Any, kernels.view_backward)(*ctx.args[:4], rows, *ctx.args[5:],
                                             np.ascontiguousarray(grad[live]), grad_radius,
                                             grad_stack, want_stack)
        out_radius = torch.from_numpy(grad_radius.sum(0)).to(ctx.dtype)
        out_stack = None
        if want_stack:
            for b in range(1, blocks):  # in place: no second stack-sized buffer
                grad_stack[0] += grad_stack[b]
            # Channels last, the stack's own layout (Renderer.display_stack): no copy.
            out_stack = torch.from_numpy(grad_stack[0]).permute(3, 0, 1, 2)[None].to(ctx.dtype)
        return out_radius, out_stack, None, None


class TritonView(torch.autograd.Function):
    """As `KernelView`, through the fused GPU kernels (`aperture_fab.optics.gpu_kernels`) on
    the stack's device: every eye state in one launch, nothing per pair stored."""

    @staticmethod
    def forward(ctx, radius, stack, renderer, rows):
        from aperture_fab.optics import gpu_walk

        _, extra, _, shared, offset_mm, closed = _walk_plan(
            renderer, radius, rows, ctx.needs_input_grad[0])
        vx, vy, offsets, geometry = _gpu_constants(renderer)
        walk = gpu_walk.Walk(
            radius.detach().double().contiguous(),
            stack.detach()[0].permute(1, 2, 3, 0).contiguous(), vx, vy, rows,
            renderer.kernel_geometry(), geometry, offsets, extra, shared, offset_mm, closed)
        ctx.walk, ctx.dtype = walk, stack.dtype
        return gpu_walk.view_forward(walk).to(stack.dtype)

    @staticmethod
    def backward(ctx, grad_view):
        from aperture_fab.optics import gpu_walk

        # States without a gradient are skipped in the kernel, as KernelView skips them.
        grad_radius, grad_stack = gpu_walk.view_backward(ctx.walk, grad_view.detach(),
                                                         bool(ctx.needs_input_grad[1]))
        out_stack = None
        if grad_stack is not None:
            out_stack = grad_stack.permute(3, 0, 1, 2)[None].to(ctx.dtype).contiguous()
        return grad_radius.to(ctx.dtype), out_stack, None, None
