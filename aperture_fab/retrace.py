"""An independent view through the triangle mesh that was written: rays cast against the mesh.

The optical model (aperture_fab.model) integrates ideal circular holes in closed form; this module
shares none of that. It takes the mesh as made (e.g. read back from the STL file), places it in the
scene and casts rays from the eye's pupil to the display with trimesh's Embree intersector, so it
sees the polygonal holes, their tilts, the plate's real thickness and the outline.

Geometry (docs/model.md, millimetres): the display at z = 0, the mesh in part coordinates (bottom
face at z = 0) shifted up by gap_mm, the pupil centre c = eye.positions_mm[position] at
z_e = gap + thickness + eye_relief, q = 1 / focus_mm (0 at infinity). The ray for view direction
v (tan) and pupil point u is at lateral position x(s) = c + s v + (1 - s q) u at depth s below
the pupil and meets the display at s = z_e. The rays are cast in part coordinates (z - gap).

A ray counts as blocked if it meets the mesh anywhere between the pupil and the display, or if it
crosses the plane of the plate's bottom face outside the plate's outline (the convex hull of the
mesh's xy footprint): there the mount that holds the plate over the display stops it. Otherwise
it carries the radiance of the display pixel it lands on (pixels uniformly lit, row 0 at +y,
black outside the display).

A view pixel's value is the mean over its box of view directions and the pupil disk (uniform
weights). Sampling: REPLICATES independent estimates per view pixel, each with n samples: the view
box is cut into n equal-area strata and so is the pupil (the unit square's strata mapped onto the
disk by the area-preserving concentric map, which keeps strata compact), one jittered sample per
stratum, view and pupil strata paired by a random permutation. The value is the replicates' mean
and its standard error their standard deviation / sqrt(REPLICATES), an unbiased variance estimate.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from aperture_fab.mesh import PlateMesh
from aperture_fab.scene import Scene

__all__ = ["REPLICATES", "TracedView", "trace_mesh_view"]

#: Independent estimates per view pixel; their spread gives the standard error (REPLICATES - 1
#: degrees of freedom per pixel).
REPLICATES = 4
#: Random numbers per sample: view box (2), pupil square (2), permutation key (1). Drawn as one
#: array per chunk, so the result does not depend on the chunk size.
RANDOM_PER_SAMPLE = 5
#: Relative slack (of the outline's size) for a ray crossing exactly on the outline's edge.
OUTLINE_RTOL = 1e-9


@dataclass(frozen=True)
class TracedView:
    """A view traced through a mesh.

    view: (C, ny, nx) float64, linear radiance, row 0 the top of the view.
    stderr: (C, ny, nx) float64, Monte Carlo standard error of each pixel of `view`.
    samples_per_pixel: rays actually traced per view pixel (the request rounded up to a whole
        number per replicate).
    """

    view: np.ndarray
    stderr: np.ndarray
    samples_per_pixel: int


def _intersector(mesh: PlateMesh) -> Any:
    """trimesh's Embree ray intersector for the mesh (part coordinates)."""
    try:
        import trimesh
        from trimesh.ray.ray_pyembree import RayMeshIntersector
    except ImportError as error:
        raise ImportError(
            "trace_mesh_view needs the trimesh and embreex packages: pip install trimesh embreex"
        ) from error
    solid = trimesh.Trimesh(vertices=mesh.vertices, faces=mesh.faces, process=False, validate=False)
    return RayMeshIntersector(solid)


def _outline_hull(xy: np.ndarray) -> np.ndarray:
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


def _inside(hull: np.ndarray, x: np.ndarray, y: np.ndarray, tol_mm: float) -> np.ndarray:
    """Whether points (x, y) lie in the convex counter-clockwise polygon `hull` (edges count)."""
    inside = np.ones(x.shape, dtype=bool)
    for a, b in zip(hull, np.roll(hull, -1, axis=0), strict=True):
        length = math.hypot(b[0] - a[0], b[1] - a[1])
        inside &= (b[0] - a[0]) * (y - a[1]) - (b[1] - a[1]) * (x - a[0]) >= -tol_mm * length
    return inside


def _strata(n: int) -> tuple[np.ndarray, np.ndarray]:
    """n equal-area strata of the unit square: lower corners (n, 2) and sizes (n, 2).

    About sqrt(n) columns; column j holds b_j strata and is b_j / n wide, so every stratum has
    area 1 / n and an aspect ratio near 1, for any n.
    """
    columns = max(1, round(math.sqrt(n)))
    counts = np.full(columns, n // columns) + (np.arange(columns) < n % columns)
    column = np.repeat(np.arange(columns), counts)
    row = np.arange(n) - np.repeat(np.cumsum(counts) - counts, counts)
    left = np.concatenate([[0], np.cumsum(counts)])[:-1] / n
    corner = np.stack([left[column], row / counts[column]], axis=1)
    size = np.stack([counts[column] / n, 1.0 / counts[column]], axis=1)
    return corner, size


def _concentric_disk(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shirley-Chiu area-preserving map of the unit square onto the unit disk."""
    a, b = 2 * a - 1, 2 * b - 1
    outer_a = np.abs(a) > np.abs(b)
    safe_a = np.where(a == 0, 1.0, a)
    safe_b = np.where(b == 0, 1.0, b)
    radius = np.where(outer_a, a, b)
    angle = np.where(outer_a, np.pi / 4 * (b / safe_a), np.pi / 2 - np.pi / 4 * (a / safe_b))
    return radius * np.cos(angle), radius * np.sin(angle)


def _check_inputs(mesh: PlateMesh, scene: Scene, display: np.ndarray, position: int,
                  samples_per_pixel: int, max_rays: int) -> np.ndarray:
    pixels = (scene.display.pixels[1], scene.display.pixels[0])
    display = np.asarray(display, dtype=np.float64)
    if display.ndim != 3 or display.shape[1:] != pixels:
        raise ValueError(
            f"display has shape {display.shape}; expected (C, {pixels[0]}, {pixels[1]}) for "
            f"scene.display.pixels {scene.display.pixels}."
        )
    if not np.all(np.isfinite(display)):
        raise ValueError("display holds NaN or infinite values; give finite linear radiance.")
    count = len(scene.eye.positions_mm)
    if not (isinstance(position, int) and 0 <= position < count):
        raise ValueError(
            f"position = {position!r} is out of range; allowed: 0 to {count - 1} (the scene's "
            "eye positions)."
        )
    if not (isinstance(samples_per_pixel, int) and samples_per_pixel >= 2 * REPLICATES):
        raise ValueError(
            f"samples_per_pixel = {samples_per_pixel!r}; allowed: a whole number >= "
            f"{2 * REPLICATES} ({REPLICATES} replicates of at least 2 samples)."
        )
    if not (isinstance(max_rays, int) and max_rays >= 1):
        raise ValueError(f"max_rays = {max_rays!r}; allowed: a whole number >= 1.")
    if len(mesh.faces) == 0:
        raise ValueError("mesh has no faces; give the plate's mesh (e.g. read_stl of plate.stl).")
    reach = scene.plate_distance_mm
    if mesh.vertices[:, 2].max() >= reach or mesh.vertices[:, 2].min() < -scene.plate.gap_mm:
        raise ValueError(
            f"mesh spans z = {mesh.vertices[:, 2].min():g} to {mesh.vertices[:, 2].max():g} mm; "
            f"in part coordinates it must lie between the display (-{scene.plate.gap_mm:g}) "
            f"and the pupil ({reach:g}); give it with its bottom face at z = 0."
        )
    return display


def trace_mesh_view(
    mesh: PlateMesh,
    scene: Scene,
    display: np.ndarray,
    position: int = 0,
    samples_per_pixel: int = 256,
    seed: int = 0,
    max_rays: int = 2_000_000,
    progress: Callable[[int, int], None] | None = None,
) -> TracedView:
    """The eye's view through `mesh` onto `display`, by casting rays (see the module docstring).

    mesh: the plate in part coordinates (bottom face at z = 0), e.g. read_stl of the written file.
    scene: display, plate (gap, thickness) and eye; display: (C, H, W) linear radiance.
    position: which of the eye's positions_mm. samples_per_pixel: rays per view pixel (rounded
    up to a multiple of REPLICATES). seed: random seed. max_rays: rays per chunk (bounds memory;
    a chunk holds at least one view pixel). progress: called with (view pixels done, total).
    """
    display = _check_inputs(mesh, scene, display, position, samples_per_pixel, max_rays)
    eye = scene.eye
    channels = display.shape[0]
    n = math.ceil(samples_per_pixel / REPLICATES)
    rays_per_pixel = REPLICATES * n
    corner, size = _strata(n)
    q = 0.0 if eye.focus_mm is None else 1.0 / eye.focus_mm
    cx, cy = eye.positions_mm[position]
    pupil_radius = eye.pupil_mm / 2
    s_bottom = scene.plate_distance_mm  # pupil to the bottom face's plane (part z = 0)
    s_display = scene.display_distance_mm
    intersector = _intersector(mesh)
    hull = _outline_hull(mesh.vertices[:, :2])
    hull_tol = OUTLINE_RTOL * float(np.ptp(hull, axis=0).max())
    disp = scene.display
    pixel_x, pixel_y = disp.pixel_mm

    vx, vy = eye.view_directions()
    step_x, step_y = eye.view_step
    nx, ny = eye.view_pixels
    total = nx * ny
    rng = np.random.default_rng(seed)
    estimates = np.zeros((channels, total, REPLICATES), dtype=np.float64)
    per_chunk = max(1, max_rays // rays_per_pixel)
    for first in range(0, total, per_chunk):
        index = np.arange(first, min(first + per_chunk, total))
        shape = (index.size, REPLICATES, n)
        draw = rng.random((*shape, RANDOM_PER_SAMPLE))
        pupil_stratum = np.argsort(draw[..., 4], axis=-1)
        # View directions: one jittered sample per stratum of the pixel's tan box.
        box = corner + size * draw[..., 0:2]  # (P, R, n, 2) in [0, 1)
        v_x = vx[index % nx][:, None, None] + (box[..., 0] - 0.5) * step_x
        v_y = vy[index // nx][:, None, None] + (box[..., 1] - 0.5) * step_y
        # Pupil points: the strata in a random order, mapped onto the disk.
        square = corner[pupil_stratum] + size[pupil_stratum] * draw[..., 2:4]
        u_x, u_y = _concentric_disk(square[..., 0], square[..., 1])
        u_x, u_y = pupil_radius * u_x, pupil_radius * u_y

        # Where each ray lands on the display, and the radiance there.
        land_x = cx + s_display * v_x + (1 - s_display * q) * u_x
        land_y = cy + s_display * v_y + (1 - s_display * q) * u_y
        col = np.floor((land_x + disp.width_mm / 2) / pixel_x).astype(np.int64)
        row = np.floor((disp.height_mm / 2 - land_y) / pixel_y).astype(np.int64)
        on_display = (col >= 0) & (col < disp.pixels[0]) & (row >= 0) & (row < disp.pixels[1])
        radiance = np.zeros((channels, *shape), dtype=np.float64)
        radiance[:, on_display] = display[:, row[on_display], col[on_display]]

        # The mount: rays crossing the bottom face's plane outside the outline are blocked.
        bottom_x = cx + s_bottom * v_x + (1 - s_bottom * q) * u_x
        bottom_y = cy + s_bottom * v_y + (1 - s_bottom * q) * u_y
        open_ray = _inside(hull, bottom_x, bottom_y, hull_tol) & np.any(radiance != 0, axis=0)

        # Only rays that could carry light are cast; origins on the pupil plane, part z.
        passes = open_ray.reshape(-1)
        cast = np.flatnonzero(passes)
        if cast.size:
            ux, uy = u_x.reshape(-1)[cast], u_y.reshape(-1)[cast]
            origin = np.stack([cx + ux, cy + uy, np.full(cast.size, s_bottom)], axis=1)
            direction = np.stack([v_x.reshape(-1)[cast] - q * ux, v_y.reshape(-1)[cast] - q * uy,
                                  -np.ones(cast.size)], axis=1)
            direction /= np.linalg.norm(direction, axis=1, keepdims=True)
            passes[cast] = ~np.asarray(intersector.intersects_any(origin, direction), dtype=bool)
        estimates[:, index] = (radiance * passes.reshape(shape)).mean(axis=-1)
        if progress is not None:
            progress(int(index[-1]) + 1, total)

    view = estimates.mean(axis=-1)
    stderr = estimates.std(axis=-1, ddof=1) / math.sqrt(REPLICATES)
    return TracedView(
        view=view.reshape(channels, ny, nx),
        stderr=stderr.reshape(channels, ny, nx),
        samples_per_pixel=rays_per_pixel,
    )
