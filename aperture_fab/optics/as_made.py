"""The view through a plate as a process makes it: the holes with the process's random errors,
the material's leakage veil and diffraction at the holes.

The optimizer's loss and the report's headline use this one model (docs/model.md, "The part as
made"), so what the optimizer says of a plate and what `validate` says of the written part agree.
The process's systematic radius bias is not here: it is in the made sizes the plate is snapped
to (`aperture_fab.fabrication.quantize.MadeSizes`). Each made copy draws

- a radius error per hole, normal with the process's radius sigma (a hole never below 0);
- a lateral position error per hole and axis, normal with the process's position sigma;

then renders the holes (`Renderer`), blurs the view by the holes' Airy mixture
(`aperture_fab.optics.diffraction.AiryMixture`) and adds the veil the solid leaks
(`aperture_fab.optics.leakage`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from aperture_fab.optics.diffraction import AiryMixture
from aperture_fab.optics.eyes import EyeStates
from aperture_fab.optics.leakage import veil
from aperture_fab.optics.model import Renderer

__all__ = ["MadeOptics", "MadeDraw", "draw_errors", "drawn_fractions", "made_views",
           "made_views_and_white", "made_white", "white_transmission"]


@dataclass(frozen=True)
class MadeOptics:
    """What separates a made plate's view from its drawn holes' geometric view.

    radius_sigma_mm, position_sigma_mm: the process's 1-sigma random hole-radius error and
        lateral position error (per axis), mm, >= 0.
    solid_transmission: share of the light the solid passes (10^-OD), 0 to 1.
    diffraction: the Airy kernels of the plate's hole sizes, or None to neglect diffraction.
    """

    radius_sigma_mm: float = 0.0
    position_sigma_mm: float = 0.0
    solid_transmission: float = 0.0
    diffraction: AiryMixture | None = None

    def __post_init__(self) -> None:
        for name in ("radius_sigma_mm", "position_sigma_mm"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"MadeOptics.{name} = {value!r} must be >= 0 (mm).")
        if not 0 <= self.solid_transmission <= 1:
            raise ValueError(f"MadeOptics.solid_transmission = {self.solid_transmission!r} "
                             "must be in [0, 1] (10^-OD).")

    @property
    def has_errors(self) -> bool:
        """Whether made copies differ from each other (a random radius or position error)."""
        return self.radius_sigma_mm > 0 or self.position_sigma_mm > 0


@dataclass(frozen=True)
class MadeDraw:
    """One made copy's random errors.

    radius_mm: (rows, cols) float64 radius error of each cell's hole, mm.
    offset_mm: (rows, cols, 2) float64 lateral (x, y) position error, mm, or None (none drawn).
    """

    radius_mm: np.ndarray
    offset_mm: np.ndarray | None


def draw_errors(cells: tuple[int, int], optics: MadeOptics, rng: np.random.Generator
                ) -> MadeDraw:
    """Random errors of one made copy of a plate of cells (rows, cols); the radius errors are
    drawn first, then the offsets (so a process without position error draws the same radii)."""
    radius = rng.normal(0.0, optics.radius_sigma_mm, cells) if optics.radius_sigma_mm > 0 \
        else np.zeros(cells)
    offset = None
    if optics.position_sigma_mm > 0:
        offset = rng.normal(0.0, optics.position_sigma_mm, (*cells, 2))
    return MadeDraw(radius, offset)


def drawn_fractions(open_fraction: torch.Tensor, radius_error_mm: np.ndarray | None,
                    pitch_mm: tuple[float, float]) -> torch.Tensor:
    """Open fractions (rows, cols) of the holes with their radius errors (closed cells stay
    closed, a hole shrinks to 0 at most); differentiable in open_fraction."""
    if radius_error_mm is None or not np.any(radius_error_mm):
        return open_fraction
    cell = pitch_mm[0] * pitch_mm[1]
    error = torch.as_tensor(radius_error_mm, dtype=open_fraction.dtype,
                            device=open_fraction.device)
    radius = torch.sqrt(open_fraction.clamp_min(0) * (cell / math.pi) + 1e-18)
    moved = math.pi * (radius + error).clamp_min(0) ** 2 / cell
    return torch.where(open_fraction.detach() > 0, moved, open_fraction)


def made_views(renderer: Renderer, open_fraction: torch.Tensor, display: torch.Tensor,
               states: EyeStates, optics: MadeOptics, draw: MadeDraw | None = None,
               stack: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Views (S, C, ny, nx) of a display (C, H, W) through a plate of open fractions
    (rows, cols) as made, with one copy's errors `draw` (None: the nominal copy), for each eye
    state. Returns (views with the veil, views without it: the light through the holes).
    stack: the display's `renderer.display_stack`, when the caller has it already."""
    if stack is None:
        stack = renderer.display_stack(display)
    views, a = _render_copy(renderer, open_fraction, stack, states, draw)
    return _finish(views, a, display, optics, renderer.scene.plate.pitch_mm)


def made_views_and_white(renderer: Renderer, open_fraction: torch.Tensor,
                         display: torch.Tensor, joined: torch.Tensor, states: EyeStates,
                         optics: MadeOptics, draw: MadeDraw | None = None
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """As `made_views`, plus the copy's light efficiency per eye state (S,): its mean view of
    a uniform white display through the same holes, as `white_transmission` gives the drawn
    plate's. joined: the display's stack with the white one (`Renderer.display_stack` with
    with_white): the white display rides in the same render as an extra channel, since the
    render's cost is in the holes' geometry, not in its channels."""
    channels = display.shape[0]
    views, a = _render_copy(renderer, open_fraction, joined, states, draw)
    shown, through = _finish(views[:, :channels], a, display, optics,
                             renderer.scene.plate.pitch_mm)
    return shown, through, views[:, channels].mean((1, 2))


def _render_copy(renderer: Renderer, open_fraction: torch.Tensor, stack: torch.Tensor,
                 states: EyeStates, draw: MadeDraw | None) -> tuple[torch.Tensor, torch.Tensor]:
    """The geometric views (S, C, ny, nx) of a display stack through one made copy, and the
    copy's open fractions (its radius errors drawn)."""
    a = open_fraction
    if draw is not None:
        a = drawn_fractions(a, draw.radius_mm, renderer.scene.plate.pitch_mm)
        if draw.offset_mm is not None:
            renderer = renderer.with_hole_offsets(draw.offset_mm)
    return renderer.render_states(a, stack, states), a


def _finish(views: torch.Tensor, a: torch.Tensor, display: torch.Tensor, optics: MadeOptics,
            pitch_mm: tuple[float, float]) -> tuple[torch.Tensor, torch.Tensor]:
    """Geometric views through made holes `a` with their diffraction and the veil: (views
    with the veil, views without it)."""
    if optics.diffraction is not None:
        views = optics.diffraction.blur(views, a, pitch_mm)
    if optics.solid_transmission == 0:
        return views, views
    return views + veil(a, display.to(views), optics.solid_transmission), views


def made_white(renderer: Renderer, open_fraction: torch.Tensor, states: EyeStates,
               draw: MadeDraw | None = None) -> torch.Tensor:
    """(S,) a made copy's light efficiency per eye state, independent of content and
    differentiable in open_fraction: its mean view of a uniform white display through the
    copy's holes (the open display's view of it is 1). draw: the copy's errors (None: the
    nominal copy)."""
    views, _ = _render_copy(renderer, open_fraction, renderer.white_stack(), states, draw)
    return views.mean((1, 2, 3))


def white_transmission(renderer: Renderer, open_fraction: torch.Tensor, states: EyeStates
                       ) -> torch.Tensor:
    """(S,) the plate's light efficiency per eye state (`made_white` of the nominal copy)."""
    with torch.no_grad():
        return made_white(renderer, open_fraction.to(renderer.device, renderer.dtype), states)
