"""The renderer's torch path, the reference the fused kernels are tested against: per eye
state, a table of every (view pixel, hole) pair that can carry light, its geometry computed
once, then each view as pair weights times display-stack samples (grid_sample)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
import torch.nn.functional as F

from aperture_fab.optics.planes import EPS

if TYPE_CHECKING:  # the renderer calls these; its module imports this one
    from aperture_fab.optics.model import Renderer

__all__ = ["PairWeights", "Pairs", "build_pairs", "display_optics_at", "render_table"]


@dataclass(frozen=True)
class Pairs:
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


class PairWeights(torch.autograd.Function):
    """Per (view pixel, hole) pair: the pupil share of the rays that pass the hole, and the
    blur-stack coordinate of its display window, from the hole radii. Fused, with a hand-written
    backward, because this runs on millions of pairs per view."""

    @staticmethod
    def forward(ctx, radius, hole, lens_offset, pupil_offset, top_scale, pupil_r, level_scale,
                level_offset):
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
            d_s = d.clamp_min(EPS)
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
        lens_r = (area / math.pi).clamp_min(EPS).sqrt()
        x = (pupil_r - pupil_offset) / lens_r
        cut = x.abs() < 1
        xs = torch.where(cut, x, torch.zeros_like(x))
        root = (1 - xs**2).clamp_min(0).sqrt()
        share = torch.where(cut, 0.5 + (torch.asin(xs) + xs * root) / math.pi, (x >= 1).to(x.dtype))
        norm = 1 / (math.pi * pupil_r**2)
        weight = area * share * norm
        level = (2 * level_scale * area - 1 - level_offset).clamp(-1, 1)
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
        return grad_radius, None, None, None, None, None, None, None


def render_table(renderer: Renderer, radius: torch.Tensor, stack: torch.Tensor, row: np.ndarray
                  ) -> torch.Tensor:
    pairs = renderer._pair_table(row)
    radius = torch.cat([radius, radius.new_full((1,), math.sqrt(EPS))])  # a closed cell
    rows_per_chunk = max(1, renderer.chunk_pairs // max(1, pairs.hole.shape[1]))
    out = []
    for start in range(0, pairs.hole.shape[0], rows_per_chunk):
        sl = slice(start, start + rows_per_chunk)
        weight, level = PairWeights.apply(
            radius, pairs.hole[sl], pairs.lens_offset_mm[sl], pairs.pupil_offset_mm[sl],
            abs(float(row[3])), float(row[2]), float(row[5]), renderer.level_offset)
        grid = torch.cat([pairs.grid_xy[sl], level.unsqueeze(-1)], dim=-1)[None, None]
        samples = F.grid_sample(stack, grid, mode="bilinear", padding_mode="zeros",
                                align_corners=True)[0, :, 0]  # (C, n, S)
        if pairs.emission is not None:
            weight = weight * pairs.emission[sl]
        out.append((samples * weight).sum(-1))
    return torch.cat(out, dim=1)


def build_pairs(renderer: Renderer, row: np.ndarray) -> Pairs:
    scene = renderer.scene
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
                            device=renderer.device)
    offsets = None
    if renderer.hole_offset_mm is not None:
        offsets = torch.as_tensor(renderer.hole_offset_mm.reshape(-1, 2), dtype=dt,
                                  device=renderer.device)
    display = scene.display
    display_optics = display.cover_glass_mm > 0 or display.emission_power > 0
    reach = keep_within + renderer.search_extra_mm
    # The window may reach past the plate's edge (masked below); never clamp its size to
    # the plate, which would shift it off the holes on narrow plates.
    nsx = math.floor(2 * reach / px) + 2
    nsy = math.floor(2 * reach / py) + 2
    oy, ox = torch.meshgrid(torch.arange(nsy, device=renderer.device),
                            torch.arange(nsx, device=renderer.device), indexing="ij")
    oy, ox = oy.reshape(1, -1), ox.reshape(1, -1)
    per_chunk = max(1, renderer.chunk_pairs // (nsx * nsy))
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
            ax, ay = (ex - hx) / renderer.axis_length, (ey - hy) / renderer.axis_length
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
            wx, wy, emission = display_optics_at(renderer, wx, wy, lx, ly)
        gx, gy = _normalize(renderer, wx, wy)
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
    return Pairs(
        hole=cat[0],
        lens_offset_mm=cat[1].to(renderer.dtype),
        pupil_offset_mm=cat[2].to(renderer.dtype),
        grid_xy=torch.stack([cat[3], cat[4]], -1).to(renderer.dtype),
        emission=cat[5].to(renderer.dtype) if len(cat) > 5 else None,
    )


def display_optics_at(renderer: Renderer, wx: torch.Tensor, wy: torch.Tensor, lx: torch.Tensor,
                    ly: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor,
                                               torch.Tensor | None]:
    """A pair's window centre (wx, wy) on the emitting surface moved by the cover glass,
    and its emission falloff (None: Lambertian), both at the pair's chief ray: the ray
    through the lens centre (lx, ly) on the bottom face toward the window centre in air,
    slope w = (window - lens) / gap (v at infinite focus). See docs/model.md."""
    display = renderer.scene.display
    gap = renderer.scene.plate.gap_mm
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


def _normalize(renderer: Renderer, x_mm: torch.Tensor, y_mm: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor]:
    display = renderer.scene.display
    shape = renderer.shape
    col = (x_mm + display.width_mm / 2) / shape.pixel_mm[0] - 0.5 + shape.pad
    row = (display.height_mm / 2 - y_mm) / shape.pixel_mm[1] - 0.5 + shape.pad
    width, height = shape.width, shape.height
    return 2 * col / (width - 1) - 1, 2 * row / (height - 1) - 1
