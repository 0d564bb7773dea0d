"""The mesh re-trace's hole sampling (aperture_fab.validation.retrace): per view row, the (view
pixel, hole) pairs whose lens may pass light, each hole's wall clearance, and the rays or
chords traced through them in chunks."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from aperture_fab.fabrication.mesh import PlateMesh
from aperture_fab.fabrication.mesh_holes import HoleLoops
from aperture_fab.validation.retrace_chords import RANDOM_PER_CHORD, chords_kernel
from aperture_fab.validation.retrace_kernels import (
    RANDOM_PER_SAMPLE,
    clear_kernel,
    holes_kernel,
)
from aperture_fab.validation.retrace_rays import Rays, box_table
from aperture_fab.validation.retrace_sampling import (
    CAP_LOOKUP,
    CAP_LOOKUP_SCALE,
    REPLICATES,
    sample_budget,
    strata,
)

#: Relative margin on a hole's circumscribed radius, so its loop's vertices lie inside the disk.
DISK_MARGIN = 1e-6


#: A ray passes without a cast only this share of the mesh's largest extent inside a hole's
#: clear cylinder: 4e-4 in Embree's frame (EMBREE_BOX), at least 50 float32 steps (7.6e-6 below
#: 128) there, far above its rounding of the vertices and the rays.
CLEAR_RTOL = 4e-6


#: Chord sampling integrates a view box only where it lands on a display rectangle at least this
#: many pixels (sub-columns) across (the eye not focused near the display), and a chord in
#: closed form only where it lands at least this many sub-columns long (else its midpoint's
#: box): below, the table's differences would lose digits to rounding.
MIN_BOX_PX = 0.01


#: The view box's table (`box_table`) may take at most this many bytes (a 400 x 400 RGB
#: display: 31 MB); a larger display is traced by hole sampling.
MAX_BOX_TABLE_BYTES = 2**28


def disk_neighbours(centre: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """(K, M) int64: for each disk, the other disks that overlap it, padded with -1 (M may be 0).

    Candidates come from a strip in x (disks sorted by x), so the work is K x the disks in a
    strip of width 4 max(radius)."""
    k = len(radius)
    if k < 2:
        return np.zeros((k, 0), dtype=np.int64)
    order = np.argsort(centre[:, 0], kind="stable")
    xs = centre[order, 0]
    reach = 2 * float(radius.max())
    lo = np.searchsorted(xs, xs - reach, side="left")
    hi = np.searchsorted(xs, xs + reach, side="right")
    counts = hi - lo
    first = np.repeat(np.arange(k), counts)
    second = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts - lo, counts)
    i, j = order[first], order[second]
    gap = np.linalg.norm(centre[i] - centre[j], axis=1)
    overlap = (i != j) & (gap < radius[i] + radius[j])
    i, j = i[overlap], j[overlap]
    ordered = np.argsort(i, kind="stable")
    i, j = i[ordered], j[ordered]
    per = np.bincount(i, minlength=k)
    table = np.full((k, int(per.max(initial=0))), -1, dtype=np.int64)
    table[i, np.arange(i.size) - np.repeat(np.cumsum(per) - per, per)] = j
    return table


@dataclass(frozen=True)
class Disks:
    """Each hole's loops as disks (circumscribed, with DISK_MARGIN) on its two faces, and its
    clear cylinder (module docstring)."""

    top: np.ndarray  # (K, 2) mm, top loop centroids
    top_radius: np.ndarray  # (K,) mm
    bottom: np.ndarray  # (K, 2) mm, bottom loop centroids
    bottom_radius: np.ndarray  # (K,) mm
    neighbours: np.ndarray  # (K, M) holes whose top disk overlaps, -1 padded
    by_y: np.ndarray  # (K,) holes sorted by top centre y
    axis_low: np.ndarray  # (K, 2) mm, the clear cylinder's axis at the mesh's lowest z
    axis_high: np.ndarray  # (K, 2) mm, and at its highest z (the top centroid)
    clear2: np.ndarray  # (K,) mm^2, (rho - margin)^2, -1 where rho <= margin
    z_range: tuple[float, float]  # the mesh's lowest and highest z

    @classmethod
    def of(cls, loops: HoleLoops, mesh: PlateMesh) -> Disks:
        top = loops.top_centroid_mm
        radius = loops.top_circum_radius_mm * (1 + DISK_MARGIN)
        bottom_radius = loops.bottom_circum_radius_mm * (1 + DISK_MARGIN)
        z_low, z_high = float(mesh.vertices[:, 2].min()), float(mesh.vertices[:, 2].max())
        axis_high = np.ascontiguousarray(top, dtype=np.float64)
        axis_low = np.ascontiguousarray(
            loops.bottom_centroid_mm + loops.axes * z_low, dtype=np.float64)
        rho = clear_radius(mesh, axis_low, axis_high, (z_low, z_high),
                            np.maximum(radius, bottom_radius))
        margin = CLEAR_RTOL * float(np.ptp(mesh.vertices, axis=0).max())
        usable = rho - margin
        return cls(top, radius, loops.bottom_centroid_mm, bottom_radius,
                   disk_neighbours(top, radius), np.argsort(top[:, 1], kind="stable"),
                   axis_low, axis_high, np.where(usable > 0, usable**2, -1.0), (z_low, z_high))


def clear_radius(mesh: PlateMesh, axis_low: np.ndarray, axis_high: np.ndarray,
                  z_range: tuple[float, float], cap: np.ndarray) -> np.ndarray:
    """(K,) mm: each hole's clear-cylinder radius rho (module docstring), at most `cap` (K,):
    the least distance from the axis (axis_low at z_range[0] to axis_high at z_range[1]) of
    the sheared xy projections of the mesh's triangles near it. Triangles are matched to holes
    through a grid of cells one hole box wide, so each triangle meets a few holes."""
    k = len(cap)
    if k == 0:
        return np.zeros(0)
    lo = np.minimum(axis_low, axis_high) - cap[:, None]
    hi = np.maximum(axis_low, axis_high) + cap[:, None]
    box = np.ascontiguousarray(np.concatenate([lo, hi], axis=1))
    origin = lo.min(axis=0)
    cell = max(float((hi - lo).max()), 1e-300)
    shape = (np.floor((hi.max(axis=0) - origin) / cell).astype(np.int64) + 1)
    first = np.floor((lo - origin) / cell).astype(np.int64)
    last = np.minimum(np.floor((hi - origin) / cell).astype(np.int64), shape - 1)
    # A box is at most one cell wide, so it meets at most 2 x 2 cells.
    holes, cells = [], []
    for dx in (0, 1):
        for dy in (0, 1):
            col, row = first[:, 0] + dx, first[:, 1] + dy
            meets = (col <= last[:, 0]) & (row <= last[:, 1])
            holes.append(np.flatnonzero(meets))
            cells.append(row[meets] * shape[0] + col[meets])
    hole = np.concatenate(holes)
    cell_of = np.concatenate(cells)
    order = np.argsort(cell_of, kind="stable")
    start = np.concatenate([[0], np.cumsum(np.bincount(cell_of, minlength=int(shape.prod())))])
    clear2 = cap.astype(np.float64) ** 2
    clear_kernel(np.ascontiguousarray(mesh.vertices, dtype=np.float64),
                  np.ascontiguousarray(mesh.faces, dtype=np.int64), axis_low, axis_high,
                  z_range[0], z_range[1], box, np.ascontiguousarray(origin, dtype=np.float64),
                  cell, shape, start, np.ascontiguousarray(hole[order]), clear2)
    return np.sqrt(clear2)


def _row_pairs(disks: Disks, centre_x: np.ndarray, centre_y: float, half: tuple[float, float],
               foot: float) -> tuple[np.ndarray, np.ndarray]:
    """(view pixel in the row, hole) pairs, each (N,) int64: the top disks that reach the
    footprint of some direction in the pixel's box, i.e. the box of footprint centres
    (centre_x[i] +- half[0], centre_y +- half[1]) grown by the footprint radius `foot`."""
    reach = foot + float(disks.top_radius.max(initial=0.0))
    ys = disks.top[disks.by_y, 1]
    lo, hi = np.searchsorted(ys, [centre_y - half[1] - reach, centre_y + half[1] + reach],
                             side="left")
    band = disks.by_y[lo:hi]
    band = band[np.argsort(disks.top[band, 0], kind="stable")]
    xs = disks.top[band, 0]
    first = np.searchsorted(xs, centre_x - half[0] - reach, side="left")
    counts = np.searchsorted(xs, centre_x + half[0] + reach, side="right") - first
    pixel = np.repeat(np.arange(centre_x.size), counts)
    hole = band[np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts - first, counts)]
    dx = np.maximum(np.abs(disks.top[hole, 0] - centre_x[pixel]) - half[0], 0.0)
    dy = np.maximum(np.abs(disks.top[hole, 1] - centre_y) - half[1], 0.0)
    near = dx**2 + dy**2 <= (foot + disks.top_radius[hole]) ** 2
    pixel, hole = pixel[near], hole[near]
    # Hole by hole, in bands of holes one hole wide across the plate, each band left to right,
    # and each hole's pixels in order: the rays of neighbouring pairs land near each other on
    # the display, so the kernels find its tables in cache.
    band_mm = 2 * float(disks.top_radius.max(initial=0.0)) or 1.0
    x, y = disks.top[hole, 0], disks.top[hole, 1]
    order = np.lexsort((pixel, x, np.floor(y / band_mm)))
    return pixel[order], hole[order]


class _Chunk(NamedTuple):
    """A chunk of a view row's (view pixel, hole) pairs (`trace_holes`)."""

    row: int
    row_pixel: np.ndarray  # (Q,) the view pixel (column) of each of the row's pairs
    row_sums: np.ndarray  # (Q, R, C) the row's pair sums
    pixel: np.ndarray  # (P,) the chunk's pairs: view pixel
    hole: np.ndarray  # (P,) and hole
    sums: np.ndarray  # (P, R, C) the chunk's part of row_sums
    ends_row: bool


def trace_holes(rays: Rays, loops: HoleLoops, mesh: PlateMesh, samples: int | None,
                 rng: np.random.Generator, estimates: np.ndarray, max_rays: int,
                 progress: Callable[[int, int], None] | None) -> tuple[int, int, int]:
    """Hole sampling, by chords where the display allows (module docstring): adds to estimates
    (C, pixels, REPLICATES); returns the rays and chords decided (against the mesh, by a clear
    cylinder or by Embree), the (view pixel, hole) pairs and the samples per pair and replicate
    (samples None: the budget's, `sample_budget`)."""
    eye = rays.scene.eye
    centre = np.array(rays.centre, dtype=np.float64)
    q, thickness = rays.q, loops.thickness_mm
    s_top = rays.s_bottom - thickness  # the mesh's own top face
    beta = 1 - s_top * q
    scale = (1 - rays.s_bottom * q) / beta  # top-face offsets to bottom-face offsets
    pupil_radius = eye.pupil_mm / 2
    foot = beta * pupil_radius  # the pupil's footprint on the top face's plane
    disks = Disks.of(loops, mesh)
    vx, vy = eye.view_directions()
    step_x, step_y = eye.view_step
    nx, ny = eye.view_pixels
    half = (0.5 * s_top * step_x, 0.5 * s_top * step_y)
    row_pairs = [_row_pairs(disks, centre[0] + s_top * vx, centre[1] + s_top * vy[j], half,
                            foot) for j in range(ny)]
    box_cols, box_rows = _landing_box(rays, s_top, beta)
    chords = rays.sat is not None and rays.lit is not None and box_cols > 0
    if samples is None:
        samples = sample_budget(sum(pixel.size for pixel, _ in row_pairs), chords)
    n = math.ceil(samples / REPLICATES)
    corner, size = strata(n)
    corner, size = np.ascontiguousarray(corner), np.ascontiguousarray(size)
    grow = 0.5 * thickness * math.hypot(step_x, step_y) / beta  # bottom-plane slack
    pair_geo = np.array([step_x, step_y, s_top, beta, scale, thickness, grow, pupil_radius**2,
                         n * np.pi * foot**2, *disks.z_range], dtype=np.float64)
    box, grid = np.zeros((1, 1, 2, 1)), np.zeros(4)
    if chords:
        assert rays.sat is not None
        box, grid = box_table(rays.sat, box_rows, box_cols)
    # A ray through a hole's lens crosses the bottom face's plane within 2 grow of its bottom
    # disk (grow for the lens, grow for the box's spread about the pixel's centre direction).
    hole_inside = _disks_inside(disks.bottom, disks.bottom_radius + 2 * grow, rays.hull,
                                rays.slack)
    chord_geo = np.array([*pair_geo, box_cols, box_rows, rays.columns_per_pixel],
                         dtype=np.float64)
    randoms = RANDOM_PER_CHORD if chords else RANDOM_PER_SAMPLE
    channels = estimates.shape[0]
    flat = estimates.reshape(channels, -1)
    per_chunk = max(1, max_rays // (REPLICATES * n))
    top = np.ascontiguousarray(disks.top, dtype=np.float64)
    bottom = np.ascontiguousarray(disks.bottom, dtype=np.float64)

    def chunks() -> Iterator[_Chunk]:
        """The chunks, row by row (a row without pairs gives one empty chunk: every row ends
        once)."""
        for j, (pixel_in_row, hole_of_row) in enumerate(row_pairs):
            # Pair sums of the whole row, summed into pixels at once: chunking keeps the sums.
            pair_sums = np.zeros((pixel_in_row.size, REPLICATES, channels))
            for first in range(0, pixel_in_row.size, per_chunk) or range(1):
                end = first + per_chunk
                yield _Chunk(j, pixel_in_row, pair_sums, pixel_in_row[first:end],
                             hole_of_row[first:end], pair_sums[first:end],
                             end >= pixel_in_row.size)

    def draws(pixels: int) -> np.ndarray:
        """The uniforms of a chunk of `pixels` pairs, (P, R n, RANDOM_PER_CHORD or
        RANDOM_PER_SAMPLE)."""
        return rng.random((pixels, REPLICATES * n, randoms))

    cast = pairs = 0
    # The uniforms of the next chunk are drawn on a second thread while Embree casts this
    # chunk's rays (both release the GIL): the same numbers in the same order as drawn inline.
    with ThreadPoolExecutor(max_workers=1) as pool:
        upcoming = chunks()
        first = next(upcoming)
        drawn = pool.submit(draws, first.pixel.size)
        chunk: _Chunk | None = first
        while chunk is not None:
            draw = drawn.result()
            samples = chunk.pixel.size * REPLICATES * n
            to_cast = np.zeros(samples, dtype=bool)
            ray = np.empty((samples, 4))
            contrib = np.empty((samples, channels))
            counts = np.empty(chunk.pixel.size, dtype=np.int64)
            if chords:
                chords_kernel(draw, chunk.pixel, chunk.hole, vx, float(vy[chunk.row]), top,
                               disks.top_radius, bottom, disks.bottom_radius, disks.neighbours,
                               disks.axis_low, disks.axis_high, disks.clear2, chord_geo,
                               rays.geo, rays.hull, rays.slack, rays.display, rays.offsets,
                               rays.sat, box, grid, rays.lit, hole_inside, CAP_LOOKUP,
                               CAP_LOOKUP_SCALE, chunk.sums,
                               to_cast, ray, contrib, counts)
            else:
                holes_kernel(draw, chunk.pixel, chunk.hole, vx, float(vy[chunk.row]), corner,
                              size, top, disks.top_radius, bottom, disks.bottom_radius,
                              disks.neighbours, disks.axis_low, disks.axis_high, disks.clear2,
                              pair_geo, rays.geo, rays.hull, rays.slack, rays.display,
                              rays.offsets, CAP_LOOKUP, CAP_LOOKUP_SCALE, chunk.sums, to_cast, ray,
                              contrib, counts)
            done, chunk = chunk, next(upcoming, None)
            if chunk is not None:
                drawn = pool.submit(draws, chunk.pixel.size)
            cast += int(counts.sum())
            # The rays near a wall: Embree decides, and those that miss the mesh count.
            index = np.flatnonzero(to_cast)
            passing = index[~rays.cast(ray[index])]
            group = done.sums.reshape(-1, channels)
            for c in range(channels):
                group[:, c] += np.bincount(passing // n, contrib[passing, c], group.shape[0])
            if done.ends_row:  # the row's pair sums into its pixels (the row's estimates only)
                pairs += done.row_pixel.size
                target = (done.row_pixel[:, None] * REPLICATES + np.arange(REPLICATES)).ravel()
                row = slice(done.row * nx * REPLICATES, (done.row + 1) * nx * REPLICATES)
                for c in range(channels):
                    flat[c, row] += np.bincount(target, done.row_sums[..., c].ravel(),
                                                nx * REPLICATES)
                if progress is not None:
                    progress((done.row + 1) * nx, nx * ny)
    return cast, pairs, n


def _disks_inside(centre: np.ndarray, radius: np.ndarray, hull: np.ndarray, slack: np.ndarray
                  ) -> np.ndarray:
    """(K,) bool: whether each disk (centre (K, 2), radius (K,)) lies inside the outline (hull
    (M, 4): its edges a b counter-clockwise as (a, b - a)), a disk's distance inside each edge
    at least its radius (the edge's slack aside)."""
    edge = hull[:, 2:]
    length = np.hypot(edge[:, 0], edge[:, 1])
    inward = (edge[None, :, 0] * (centre[:, None, 1] - hull[None, :, 1])
              - edge[None, :, 1] * (centre[:, None, 0] - hull[None, :, 0]))
    return np.all(inward + slack[None] >= radius[:, None] * length[None], axis=1)


def _landing_box(rays: Rays, s_top: float, beta: float) -> tuple[float, float]:
    """(sub-columns, rows) across the display rectangle that the rays from one top-face point
    reach over a view pixel's box of directions: the landing point moves by H v, H = s_display -
    s_top (1 - s_display q) / beta. (0, 0) where chord sampling does not apply: a display whose
    light is not a rectangle's mean (cover glass, falloff: `Rays.sat` None) or a rectangle
    under MIN_BOX_PX (the eye focused near the display)."""
    if rays.sat is None:
        return 0.0, 0.0
    step_x, step_y = rays.scene.eye.view_step
    pixel_x, pixel_y = rays.scene.display.pixel_mm
    s_display = rays.scene.display_distance_mm
    spread = abs(s_display - s_top * (1 - s_display * rays.q) / beta)
    cols = spread * step_x / pixel_x * rays.columns_per_pixel
    rows = spread * step_y / pixel_y
    channels, height, width = rays.sat.shape
    table_bytes = (8 * 2 * channels * (2 * (height + math.ceil(rows)) + 1)
                   * (2 * (width + math.ceil(cols)) + 1))
    if min(cols, rows) < MIN_BOX_PX or table_bytes > MAX_BOX_TABLE_BYTES:
        return 0.0, 0.0
    return cols, rows
