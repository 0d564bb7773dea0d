"""The mesh re-trace's shared setup (aperture_fab.validation.retrace): the mesh as an occluder
(Embree), the plate's outline, the display as summed-area and view-box tables, and shading
rays from them."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from aperture_fab.fabrication.mesh import PlateMesh
from aperture_fab.optics.scene import Scene
from aperture_fab.validation.retrace_kernels import (
    OUTLINE_RTOL,
    shade_kernel,
)

#: The mesh is scaled to a box this size before Embree's float32 sees it.
EMBREE_BOX = 100.0


Occluder = Callable[[np.ndarray, np.ndarray], np.ndarray]


def occluder(mesh: PlateMesh) -> Occluder:
    """blocked(origins (N, 3), directions (N, 3)) -> (N,) bool: whether each ray (part
    coordinates, directions of any length) meets a triangle of the mesh, by Embree."""
    try:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh
    except ImportError as error:
        raise ImportError(
            "trace_mesh_view needs the embreex package (Embree): pip install embreex"
        ) from error
    low = mesh.vertices.min(axis=0)
    scale = EMBREE_BOX / max(float(np.ptp(mesh.vertices, axis=0).max()), 1e-300)
    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene=scene, vertices=((mesh.vertices - low) * scale).astype(np.float32),
                 indices=mesh.faces.astype(np.int32))

    def blocked(origin: np.ndarray, direction: np.ndarray) -> np.ndarray:
        if len(origin) == 0:
            return np.zeros(0, dtype=bool)
        hit = scene.run(((origin - low) * scale).astype(np.float32),
                        direction.astype(np.float32), query="OCCLUDED")
        return np.asarray(hit) != -1

    return blocked


def outline_hull(xy: np.ndarray) -> np.ndarray:
    """Convex hull (M, 2) float64 of points (V, 2), counter-clockwise, collinear points dropped.

    Points strictly inside the octagon of extreme points cannot be on the hull and are dropped
    first (Akl-Toussaint), so the monotone chain runs over the outline's few points only.
    """
    directions = np.array([[1, 0], [1, 1], [0, 1], [-1, 1], [-1, 0], [-1, -1], [0, -1], [1, -1]],
                          dtype=np.float64)
    octagon = xy[np.argmax(xy @ directions.T, axis=0)]  # counter-clockwise by construction
    octagon = octagon[np.any(octagon != np.roll(octagon, -1, axis=0), axis=1)]  # no 0-length edge
    edge = np.roll(octagon, -1, axis=0) - octagon
    rel = xy[:, None, :] - octagon[None]
    cross = edge[None, :, 0] * rel[..., 1] - edge[None, :, 1] * rel[..., 0]
    candidates = np.unique(xy[~np.all(cross > 0, axis=1)], axis=0)  # sorted by x, then y

    def chain(points: np.ndarray) -> list[np.ndarray]:
        out: list[np.ndarray] = []
        for p in points:
            while len(out) >= 2:
                a, b = out[-2], out[-1]
                if (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0]) > 0:
                    break
                out.pop()
            out.append(p)
        return out

    lower = chain(candidates)
    upper = chain(candidates[::-1])
    return np.array(lower[:-1] + upper[:-1])


@dataclass(frozen=True)
class Rays:
    """What casting and shading a ray needs (module docstring), part coordinates."""

    scene: Scene
    display: np.ndarray  # (C, H, W) linear radiance, C-contiguous
    centre: tuple[float, float]  # pupil centre c
    q: float  # 1 / focus distance
    s_bottom: float  # pupil to the bottom face (the pupil's part z)
    hull: np.ndarray  # outline's edges a b, counter-clockwise, as (a, b - a) (M, 4)
    slack: np.ndarray  # (M,) each outline edge's slack for a ray on it (OUTLINE_RTOL)
    geo: np.ndarray  # SHADE_FIELDS
    offsets: np.ndarray  # stripe centres (px) per channel, empty without stripes
    blocked: Occluder
    #: (C, H + 1, S W + 1) summed-area table of what the display emits (`summed_area`), S
    #: columns per pixel; None where the light of a view box is not a rectangle's mean (cover
    #: glass, falloff).
    sat: np.ndarray | None
    lit: np.ndarray | None  # (H + 1, S W + 1) summed-area table of the sub-pixels that emit
    columns_per_pixel: int

    @classmethod
    def of(cls, mesh: PlateMesh, scene: Scene, display: np.ndarray,
           position: int) -> Rays:
        eye, disp = scene.eye, scene.display
        q = 0.0 if eye.focus_mm is None else 1.0 / eye.focus_mm
        hull = outline_hull(mesh.vertices[:, :2])
        tol = OUTLINE_RTOL * float(np.ptp(hull, axis=0).max())
        edge = np.roll(hull, -1, axis=0) - hull
        centre = eye.positions_mm[position]
        s_bottom = scene.plate_distance_mm
        geo = np.array([centre[0], centre[1], q, s_bottom, scene.display_distance_mm,
                        disp.width_mm / 2, disp.height_mm / 2, disp.pixel_mm[0],
                        disp.pixel_mm[1], disp.cover_glass_mm, disp.cover_glass_index**2,
                        disp.emission_power], dtype=np.float64)
        offsets = disp.subpixel_offsets_px(display.shape[0]) if disp.has_optics else None
        offsets_px = np.array(offsets if offsets is not None else (), dtype=np.float64)
        sat = lit = None
        columns = 1
        if disp.cover_glass_mm == 0 and disp.emission_power == 0:
            sat, lit, columns = summed_area(np.asarray(display, dtype=np.float64), offsets_px)
        return cls(scene, np.ascontiguousarray(display, dtype=np.float64), centre, q, s_bottom,
                   np.ascontiguousarray(np.concatenate([hull, edge], axis=1)),
                   tol * np.hypot(edge[:, 0], edge[:, 1]), geo, offsets_px, occluder(mesh), sat,
                   lit, columns)

    def cast(self, rays: np.ndarray) -> np.ndarray:
        """blocked (N,) bool of rays (N, 4): pupil point u (x, y) and direction per unit depth
        (dx, dy), from the pupil (z = s_bottom) toward -z."""
        cx, cy = self.centre
        origin = np.stack([cx + rays[:, 0], cy + rays[:, 1], np.full(len(rays), self.s_bottom)],
                          axis=1)
        direction = np.stack([rays[:, 2], rays[:, 3], -np.ones(len(rays))], axis=1)
        return self.blocked(origin, direction)


def summed_area(display: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """What the display emits as a summed-area table (C, H + 1, S W + 1), where it emits as
    one (H + 1, S W + 1), and S, its sub-columns per pixel.

    sat[c, i, j]: the light of channel c over rows < i and sub-columns < j (pixel units). The
    display is piecewise constant, so its integral F(row, col) over [0, row] x [0, col] is
    bilinear in each cell: bilinear interpolation of sat is exact (`_sat_grid`). Without
    stripes S = 1; with stripes (offsets: the S channels' stripe centres, px from the pixel
    centre, each stripe 1 / S of the pixel) channel c lights only its stripe's sub-column, at S
    times the value, as `shade_ray` does per ray. lit: the sub-pixels where some channel is not
    0 (1 each): none in a rectangle says that no light comes from there."""
    channels, height, width = display.shape
    columns = max(1, offsets.size)
    emitted = np.zeros((channels, height, width * columns))
    for c in range(channels):
        sub = 0 if offsets.size == 0 else round((0.5 + offsets[c]) * columns - 0.5)
        emitted[c, :, sub::columns] = display[c] * columns
    sat = np.zeros((channels, height + 1, width * columns + 1))
    sat[:, 1:, 1:] = emitted.cumsum(axis=1).cumsum(axis=2)
    lit = np.zeros(sat.shape[1:])
    lit[1:, 1:] = np.any(emitted != 0, axis=0).cumsum(axis=0).cumsum(axis=1)
    return sat, lit, columns


def _sat_grid(sat: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(C, M, N): F(rows[m], cols[n]), the display's light over [0, row] x [0, col], by
    bilinear interpolation of the summed-area table (exact), clamped to the display."""
    def weights(x: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
        x = np.clip(x, 0.0, size)
        i = np.minimum(x.astype(np.int64), size - 1)
        return i, x - i

    i, fy = weights(rows, sat.shape[1] - 1)
    along_rows = sat[:, i] * (1 - fy)[None, :, None] + sat[:, i + 1] * fy[None, :, None]
    j, fx = weights(cols, sat.shape[2] - 1)
    return along_rows[:, :, j] * (1 - fx) + along_rows[:, :, j + 1] * fx


def _breakpoints(half: float, size: int) -> np.ndarray:
    """Where a box of half-width `half` moving along an axis of `size` unit cells starts or
    stops meeting a cell edge: -half + k and -half + k + gap (gap = 2 half mod 1), k = 0, 1,
    ..., from -half (the box just off the start) to size + half (just off the end), sorted."""
    gap = (2 * half) % 1.0
    last = size + math.ceil(2 * half)
    k = np.arange(last + 1, dtype=np.float64)
    points = np.empty(2 * last + 1)
    points[0::2] = k - half
    points[1::2] = k[:-1] - half + gap
    return points


def box_table(sat: np.ndarray, box_rows: float, box_cols: float
               ) -> tuple[np.ndarray, np.ndarray]:
    """The view box's light on the display: the table (M, N, 2, C) and its grid (4,): half
    the box's rows and its row gap, half its sub-columns and its column gap (`_breakpoints`).

    G(row, col): the mean light of the display over the rectangle row +- box_rows / 2, col +-
    box_cols / 2 (the landing rectangle of a view box's rays from one top-face point); J(row,
    col): the integral of G over sub-columns up to col. G is bilinear between the breakpoints
    (where the rectangle's edges cross cell edges), so J is linear in the row and quadratic in
    the column there: table[m, n] = (J, G) at (row breakpoint m, column breakpoint n) gives
    both exactly (`_box_light`). J accumulates along each row by the trapezoid rule, exact for
    a G linear between nodes."""
    half_rows, half_cols = 0.5 * box_rows, 0.5 * box_cols
    rows = _breakpoints(half_rows, sat.shape[1] - 1)
    cols = _breakpoints(half_cols, sat.shape[2] - 1)
    mean = (_sat_grid(sat, rows + half_rows, cols + half_cols)
            - _sat_grid(sat, rows - half_rows, cols + half_cols)
            - _sat_grid(sat, rows + half_rows, cols - half_cols)
            + _sat_grid(sat, rows - half_rows, cols - half_cols)) / (box_rows * box_cols)
    integral = np.zeros_like(mean)
    integral[:, :, 1:] = np.cumsum(0.5 * (mean[:, :, 1:] + mean[:, :, :-1]) * np.diff(cols),
                                   axis=2)
    table = np.ascontiguousarray(np.stack([integral, mean], axis=-1).transpose(1, 2, 3, 0))
    grid = np.array([half_rows, (2 * half_rows) % 1.0, half_cols, (2 * half_cols) % 1.0])
    return table, grid


def shade(rays: Rays, v_x: np.ndarray, v_y: np.ndarray, u_x: np.ndarray, u_y: np.ndarray,
           live: np.ndarray) -> tuple[np.ndarray, int]:
    """Radiance x pass (C, N) of the rays (v, u), flat (N,) arrays, of which only `live` ones
    count (others give 0); also how many rays were cast against the mesh."""
    values = np.zeros((rays.display.shape[0], v_x.size), dtype=np.float64)
    cast = np.zeros(v_x.size, dtype=bool)
    shade_kernel(v_x, v_y, u_x, u_y, np.ascontiguousarray(live), rays.geo, rays.hull,
                  rays.slack, rays.display, rays.offsets, values, cast)
    index = np.flatnonzero(cast)  # only rays that could carry light are cast
    q = rays.q
    ux, uy = u_x[index], u_y[index]
    blocked = rays.cast(np.stack([ux, uy, v_x[index] - q * ux, v_y[index] - q * uy], axis=1))
    values[:, index[blocked]] = 0.0
    return values, int(index.size)
