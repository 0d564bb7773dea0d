"""An independent view through the triangle mesh that was written: rays cast against the mesh.

The optical model (aperture_fab.optics.model) integrates ideal circular holes in closed form; this
module shares none of that. It takes the mesh as made (e.g. read back from the STL file), places it
in the scene and casts rays from the eye's pupil to the display with Embree (the embreex package,
which trimesh also uses), so it sees the polygonal holes, their tilts, the plate's real thickness
and the outline.

Geometry (docs/model.md, millimetres): the display at z = 0, the mesh in part coordinates (bottom
face at z = 0) shifted up by gap_mm, the pupil centre c = eye.positions_mm[position] at
z_e = gap + thickness + eye_relief, q = 1 / focus_mm (0 at infinity). The ray for view direction
v (tan) and pupil point u is at lateral position x(s) = c + s v + (1 - s q) u at depth s below
the pupil and meets the display at s = z_e. The rays are cast in part coordinates (z - gap).

A ray counts as blocked if it meets the mesh anywhere between the pupil and the display, or if it
crosses the plane of the plate's bottom face outside the plate's outline (the convex hull of the
mesh's xy footprint): there the mount that holds the plate over the display stops it. Otherwise
it carries the radiance of the display pixel it lands on (pixels uniformly lit, row 0 at +y,
black outside the display). Display-side optics (docs/model.md) act on each ray exactly: under a
cover glass (0 <= z <= cover_glass_mm, below the plate) the ray refracts at the glass's top face
and lands short of its straight continuation; a striped RGB display lights each channel only on
its stripe (a third of the pixel, at 3 times the value); falloff weighs the radiance by cos^k of
the ray's angle in air.

A view pixel's value is the mean over its box of view directions B and the pupil disk P (radius
R, uniform weights): V = (1 / |B|) int_B dv (1 / (pi R^2)) int_P du f(v, u), f = pass x radiance.

Sampling "pupil": (v, u) drawn over B x P. Each view pixel gets n samples per replicate: the view
box is cut into n equal-area strata and so is the pupil (the unit square's strata mapped onto the
disk by the area-preserving concentric map, which keeps strata compact), one jittered sample per
stratum, view and pupil strata paired by a random permutation. Most of these rays hit the plate
when its holes pass a few % of the light.

Sampling "holes" (default): only rays that can pass are drawn. For one v, the map u -> x_t =
c + s_t v + beta u, beta = 1 - s_t q, takes the pupil to the top face's plane (s_t: pupil to the
top face, the mesh's largest z); it is a scaling by beta, so du = dx_t / beta^2 and the pupil's
footprint F(v) there is the disk of radius beta R about c + s_t v, of area pi (beta R)^2:

    (1 / (pi R^2)) int_P f du = (1 / (pi (beta R)^2)) int_F(v) f dx_t.

Where f can be non-zero: the top face is solid between the hole loops
(aperture_fab.fabrication.mesh_holes,
read from the mesh) and the side walls close the outline, so a ray that passes crosses the top
face's plane inside some hole's top loop; that hole's wall joins the loop to the hole's bottom
loop, with solid between holes, so the ray then crosses the bottom face's plane inside the same
hole's bottom loop. The ray through x_t in direction v crosses the bottom plane at
x_b = m x_t + t (v + q c) / beta, m = (1 - s_b q) / beta (t: the mesh's thickness). With D_top,
D_bottom the loops' circumscribed disks (about their centroids, a tiny margin), f = 0 outside
the union over holes of the lenses L_h(v) = {x_t in D_top, x_b in D_bottom}: the integral over
F(v) is the sum over holes of the integrals over L_h(v) ∩ F(v), exactly (where lenses overlap,
each counts a point with weight 1 / the number of lenses holding it). Nothing is lost: the rays
left out are rays that meet the top face, or the wall or bottom face of the hole they enter.
So that a pair's lens does not depend on v, D_bottom is grown by t h / beta (h: half the view
box's diagonal, tan), which holds L_h(v) for every v of the box.

For each (view pixel, hole) pair whose top disk reaches the footprint of some v in the box (the
box of footprint centres grown by beta R), v is drawn stratified over B as above and x_t
uniformly over the pair's lens (exactly, by inverting the lens's area along its axis; the unit
square's strata are mapped onto the lens, paired with the box's by a random permutation), the
pupil point u = (x_t - c - s_t v) / beta found (no ray when |u| > R), and the ray cast against
the whole mesh as before. A sample's weight is |lens| / (n pi (beta R)^2), n samples per pair
and replicate, and the pixel is the sum over its pairs. samples_per_pixel is then the rays per
(view pixel, hole) pair. For the same error it casts ~15 x fewer rays than "pupil" through a
near-eye plate of 24 % open area (12 per pair: ~38 dB against the model), more as the open area
shrinks.

Both: REPLICATES independent estimates per view pixel; the value is their mean and its standard
error their standard deviation / sqrt(REPLICATES), an unbiased variance estimate.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np

from aperture_fab.fabrication.mesh import PlateMesh
from aperture_fab.fabrication.mesh_holes import HoleLoops, mesh_hole_loops
from aperture_fab.optics.scene import Display, Scene

__all__ = ["DEFAULT_SAMPLES", "REPLICATES", "SAMPLINGS", "Sampling", "TracedView",
           "trace_mesh_view"]

Sampling = Literal["holes", "pupil"]
SAMPLINGS: tuple[Sampling, ...] = ("holes", "pupil")
#: Default samples_per_pixel: rays per (view pixel, hole) pair ("holes"), per view pixel
#: ("pupil").
DEFAULT_SAMPLES: dict[Sampling, int] = {"holes": 12, "pupil": 256}
#: With samples_per_pixel None, hole sampling spends about this many rays (~20 s on one core)
#: and at most MOST_SAMPLES per pair, never fewer than DEFAULT_SAMPLES["holes"].
RAY_BUDGET = 30_000_000
MOST_SAMPLES = 256
#: Independent estimates per view pixel; their spread gives the standard error (REPLICATES - 1
#: degrees of freedom per pixel).
REPLICATES = 4
#: Random numbers per sample: view box (2), pupil or lens square (2), permutation key (1).
#: Drawn as one array per chunk in a fixed order, so the result does not depend on chunk size.
RANDOM_PER_SAMPLE = 5
#: Relative slack (of the outline's size) for a ray crossing exactly on the outline's edge.
OUTLINE_RTOL = 1e-9
#: Relative margin on a hole's circumscribed radius, so its loop's vertices lie inside the disk.
DISK_MARGIN = 1e-6
#: Newton steps solving for a cap's angle (from the series start, 3 reach float64 precision).
NEWTON_STEPS = 3
#: The mesh is scaled to a box this size before Embree's float32 sees it.
EMBREE_BOX = 100.0


@dataclass(frozen=True)
class TracedView:
    """A view traced through a mesh.

    view: (C, ny, nx) float64, linear radiance, row 0 the top of the view.
    stderr: (C, ny, nx) float64, Monte Carlo standard error of each pixel of `view`.
    samples_per_pixel: rays per view pixel ("pupil") or per (view pixel, hole) pair ("holes"),
        the request rounded up to a whole number per replicate.
    sampling: how the rays were drawn (module docstring).
    rays_cast: rays cast against the mesh in all (those that could carry light).
    pairs: (view pixel, hole) pairs traced ("holes"; 0 for "pupil").
    """

    view: np.ndarray
    stderr: np.ndarray
    samples_per_pixel: int
    sampling: Sampling
    rays_cast: int
    pairs: int


Occluder = Callable[[np.ndarray, np.ndarray], np.ndarray]


def _occluder(mesh: PlateMesh) -> Occluder:
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
                  samples_per_pixel: int, max_rays: int, sampling: Sampling) -> np.ndarray:
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
    if sampling not in SAMPLINGS:
        raise ValueError(f"sampling = {sampling!r} is not allowed; choose one of {SAMPLINGS}.")
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


@dataclass(frozen=True)
class _Rays:
    """What casting and shading a ray needs (module docstring), part coordinates."""

    scene: Scene
    display: np.ndarray  # (C, H, W) linear radiance
    centre: tuple[float, float]  # pupil centre c
    q: float  # 1 / focus distance
    s_bottom: float  # pupil to the bottom face (the pupil's part z)
    hull: np.ndarray  # outline, counter-clockwise (M, 2)
    hull_tol: float
    blocked: Occluder


def _refracted_landing(display: Display, x_mm: np.ndarray, y_mm: np.ndarray,
                       slope_x: np.ndarray, slope_y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where rays of slopes (x, y) in air, whose straight continuation meets z = 0 at (x, y),
    meet the emitting surface under the cover glass: in the glass (Snell) the slope is
    w / sqrt(n^2 + (n^2 - 1) |w|^2), so each lands t_g w (1 - that factor) short."""
    n2 = display.cover_glass_index**2
    factor = 1 / np.sqrt(n2 + (n2 - 1) * (slope_x**2 + slope_y**2))
    short = display.cover_glass_mm * (1 - factor)
    return x_mm - short * slope_x, y_mm - short * slope_y


def _display_optics(display: Display, radiance: np.ndarray, within_px: np.ndarray,
                    slope_x: np.ndarray, slope_y: np.ndarray) -> np.ndarray:
    """Radiance (C, N) of the pixels the rays land on, as the display's sub-pixel stripes and
    emission falloff make it, per ray: a striped channel is lit, at 3 times its value, only on
    its stripe (within_px: where in its pixel the ray lands, 0 to 1 along +x); falloff
    multiplies by cos^k of the ray's angle in air."""
    offsets = display.subpixel_offsets_px(radiance.shape[0])
    if offsets is not None:
        stripes = np.stack([np.abs(within_px - 0.5 - o) < 0.5 / len(offsets) for o in offsets])
        radiance = radiance * len(offsets) * stripes
    if display.emission_power > 0:
        radiance = radiance * (1 + slope_x**2 + slope_y**2) ** (-display.emission_power / 2)
    return radiance


def _shade(rays: _Rays, v_x: np.ndarray, v_y: np.ndarray, u_x: np.ndarray, u_y: np.ndarray,
           live: np.ndarray) -> tuple[np.ndarray, int]:
    """Radiance x pass (C, N) of the rays (v, u), flat (N,) arrays, of which only `live` ones
    count (others give 0); also how many rays were cast against the mesh."""
    scene, (cx, cy), q = rays.scene, rays.centre, rays.q
    disp = scene.display
    s_display = scene.display_distance_mm
    values = np.zeros((rays.display.shape[0], v_x.size), dtype=np.float64)
    index = np.flatnonzero(live)
    vx, vy, ux, uy = v_x[index], v_y[index], u_x[index], u_y[index]
    # Where each ray lands on the display, and the radiance there.
    land_x = cx + s_display * vx + (1 - s_display * q) * ux
    land_y = cy + s_display * vy + (1 - s_display * q) * uy
    if disp.cover_glass_mm > 0:
        land_x, land_y = _refracted_landing(disp, land_x, land_y, vx - q * ux, vy - q * uy)
    col_mm = (land_x + disp.width_mm / 2) / disp.pixel_mm[0]
    col = np.floor(col_mm).astype(np.int64)
    row = np.floor((disp.height_mm / 2 - land_y) / disp.pixel_mm[1]).astype(np.int64)
    keep = (col >= 0) & (col < disp.pixels[0]) & (row >= 0) & (row < disp.pixels[1])
    # The mount: rays crossing the bottom face's plane outside the outline are blocked.
    s_bottom = rays.s_bottom
    bottom_x = cx + s_bottom * vx + (1 - s_bottom * q) * ux
    bottom_y = cy + s_bottom * vy + (1 - s_bottom * q) * uy
    keep &= _inside(rays.hull, bottom_x, bottom_y, rays.hull_tol)
    radiance = rays.display[:, row[keep], col[keep]]
    if disp.has_optics:
        radiance = _display_optics(disp, radiance, col_mm[keep] - col[keep],
                                   vx[keep] - q * ux[keep], vy[keep] - q * uy[keep])
    lit = np.any(radiance != 0, axis=0)
    cast = np.flatnonzero(keep)[lit]  # only rays that could carry light are cast
    # Origins on the pupil plane, directions d x / d s = v - q u, toward -z.
    origin = np.stack([cx + ux[cast], cy + uy[cast], np.full(cast.size, s_bottom)], axis=1)
    direction = np.stack([vx[cast] - q * ux[cast], vy[cast] - q * uy[cast],
                          -np.ones(cast.size)], axis=1)
    passes = ~rays.blocked(origin, direction)
    values[:, index[cast[passes]]] = radiance[:, lit][:, passes]
    return values, int(cast.size)


def _trace_pupil(rays: _Rays, n: int, rng: np.random.Generator, estimates: np.ndarray,
                 max_rays: int, progress: Callable[[int, int], None] | None) -> int:
    """Pupil sampling (module docstring): fills estimates (C, pixels, REPLICATES); returns the
    rays cast."""
    eye = rays.scene.eye
    corner, size = _strata(n)
    pupil_radius = eye.pupil_mm / 2
    vx, vy = eye.view_directions()
    step_x, step_y = eye.view_step
    nx, ny = eye.view_pixels
    total = nx * ny
    cast = 0
    per_chunk = max(1, max_rays // (REPLICATES * n))
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
        values, count = _shade(rays, v_x.ravel(), v_y.ravel(), pupil_radius * u_x.ravel(),
                               pupil_radius * u_y.ravel(), np.ones(v_x.size, dtype=bool))
        cast += count
        estimates[:, index] = values.reshape(-1, *shape).mean(axis=-1)
        if progress is not None:
            progress(int(index[-1]) + 1, total)
    return cast


def _disk_neighbours(centre: np.ndarray, radius: np.ndarray) -> np.ndarray:
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


def _cap_angle(area: np.ndarray) -> np.ndarray:
    """theta in [0, pi] with theta - sin(theta) cos(theta) = area (area in [0, pi]): the cap
    {x <= -cos(theta)} of the unit disk has that area. Newton's method from the series
    theta^3 (2/3 - 2 theta^2 / 15), on the half below pi / 2 (the rest by symmetry)."""
    flip = area > np.pi / 2
    g = np.where(flip, np.pi - area, area)
    t = np.cbrt(1.5 * g)
    theta = np.minimum(t * (1 + t * t / 15), np.pi / 2)
    for _ in range(NEWTON_STEPS):
        sin = np.sin(theta)
        theta = theta - (theta - sin * np.cos(theta) - g) / np.maximum(2 * sin * sin, 1e-300)
        theta = np.clip(theta, 0.0, np.pi / 2)
    return np.where(flip, np.pi - theta, theta)


def _lens_sample(a: np.ndarray, r: np.ndarray, b: np.ndarray, s: np.ndarray,
                 square: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points uniform in the lens (intersection) of disks (a (P, 2), r (P,)) and (b, s): m
    points per lens (P, m, 2) from points `square` (P, m, 2) of the unit square, and the lens's
    area (P,) (0 when empty; the smaller disk when one holds the other).

    Along the line of centres (a at 0, b at d) the lens is B's cap x <= X then A's cap x >= X,
    X the common chord. The first square coordinate is the area fraction from B's end, so x
    solves a cap-area equation (_cap_angle); the second places y uniformly across the lens at
    x. The map is monotone in both, so strata of the square stay compact in the lens."""
    offset = b - a
    d = np.hypot(offset[:, 0], offset[:, 1])
    unit = np.where((d > 0)[:, None], offset / np.where(d > 0, d, 1.0)[:, None], [1.0, 0.0])
    crossing = (d > np.abs(r - s)) & (d < r + s)
    safe_d = np.where(crossing, d, 1.0)
    chord = (safe_d**2 + r**2 - s**2) / (2 * safe_d)
    theta_b = np.arccos(np.clip((safe_d - chord) / s, -1.0, 1.0))
    theta_a = np.arccos(np.clip(chord / r, -1.0, 1.0))
    area_b = s**2 * (theta_b - np.sin(theta_b) * np.cos(theta_b))
    total = area_b + r**2 * (theta_a - np.sin(theta_a) * np.cos(theta_a))
    target = square[..., 0] * total[:, None]
    in_b = target < area_b[:, None]
    radius = np.where(in_b, s[:, None], r[:, None])
    theta = _cap_angle(np.clip(np.where(in_b, target, total[:, None] - target) / radius**2,
                               0.0, np.pi))
    x = np.where(in_b, safe_d[:, None] - s[:, None] * np.cos(theta), r[:, None] * np.cos(theta))
    y = (2 * square[..., 1] - 1) * radius * np.sin(theta)
    normal = np.stack([-unit[:, 1], unit[:, 0]], axis=1)
    points = a[:, None] + x[..., None] * unit[:, None] + y[..., None] * normal[:, None]
    # One disk inside the other: the smaller one, by the concentric map.
    inside = np.flatnonzero(d <= np.abs(r - s))
    small = np.minimum(r, s)
    if inside.size:
        centre = np.where((r <= s)[inside, None], a[inside], b[inside])
        disk_x, disk_y = _concentric_disk(square[inside, :, 0], square[inside, :, 1])
        points[inside] = centre[:, None] + small[inside, None, None] * np.stack(
            [disk_x, disk_y], axis=-1)
    area = np.where(crossing, total, np.where(d <= np.abs(r - s), np.pi * small**2, 0.0))
    return points, area


def _lens_share(x_t: np.ndarray, x_b: np.ndarray, hole: np.ndarray, disks: _Disks,
                grow: float) -> np.ndarray:
    """1 / (number of holes whose lens holds the point) for points drawn in the lens of `hole`
    (N,): x_t (N, 2) on the top face's plane, x_b (N, 2) where the ray of the pixel's central
    direction through x_t crosses the bottom face's plane (lenses as _trace_holes draws them)."""
    count = np.ones(len(hole), dtype=np.float64)
    for m in range(disks.neighbours.shape[1]):
        other = disks.neighbours[hole, m]
        safe = np.where(other >= 0, other, 0)
        inside = (np.sum((x_t - disks.top[safe]) ** 2, axis=1) <= disks.top_radius[safe] ** 2) & (
            np.sum((x_b - disks.bottom[safe]) ** 2, axis=1)
            <= (disks.bottom_radius[safe] + grow) ** 2)
        count += (other >= 0) & inside
    return 1.0 / count


@dataclass(frozen=True)
class _Disks:
    """Each hole's loops as disks (circumscribed, with DISK_MARGIN) on its two faces."""

    top: np.ndarray  # (K, 2) mm, top loop centroids
    top_radius: np.ndarray  # (K,) mm
    bottom: np.ndarray  # (K, 2) mm, bottom loop centroids
    bottom_radius: np.ndarray  # (K,) mm
    neighbours: np.ndarray  # (K, M) holes whose top disk overlaps, -1 padded
    by_y: np.ndarray  # (K,) holes sorted by top centre y

    @classmethod
    def of(cls, loops: HoleLoops) -> _Disks:
        top = loops.top_centroid_mm
        radius = loops.top_circum_radius_mm * (1 + DISK_MARGIN)
        return cls(top, radius, loops.bottom_centroid_mm,
                   loops.bottom_circum_radius_mm * (1 + DISK_MARGIN),
                   _disk_neighbours(top, radius), np.argsort(top[:, 1], kind="stable"))


def _row_pairs(disks: _Disks, centre_x: np.ndarray, centre_y: float, half: tuple[float, float],
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
    return pixel[near], hole[near]


def _trace_holes(rays: _Rays, loops: HoleLoops, n: int, rng: np.random.Generator,
                 estimates: np.ndarray, max_rays: int,
                 progress: Callable[[int, int], None] | None) -> tuple[int, int]:
    """Hole sampling (module docstring): adds to estimates (C, pixels, REPLICATES); returns the
    rays cast and the (view pixel, hole) pairs."""
    eye = rays.scene.eye
    centre = np.array(rays.centre, dtype=np.float64)
    q, thickness = rays.q, loops.thickness_mm
    s_top = rays.s_bottom - thickness  # the mesh's own top face
    beta = 1 - s_top * q
    scale = (1 - rays.s_bottom * q) / beta  # top-face offsets to bottom-face offsets
    pupil_radius = eye.pupil_mm / 2
    foot = beta * pupil_radius  # the pupil's footprint on the top face's plane
    disks = _Disks.of(loops)
    corner, size = _strata(n)
    vx, vy = eye.view_directions()
    step_x, step_y = eye.view_step
    nx, ny = eye.view_pixels
    half = (0.5 * s_top * step_x, 0.5 * s_top * step_y)
    grow = 0.5 * thickness * math.hypot(step_x, step_y) / beta  # bottom-plane slack
    channels = estimates.shape[0]
    flat = estimates.reshape(channels, -1)
    per_chunk = max(1, max_rays // (REPLICATES * n))
    cast = pairs = 0
    for j in range(ny):
        pixel_in_row, hole_of_row = _row_pairs(disks, centre[0] + s_top * vx,
                                               centre[1] + s_top * vy[j], half, foot)
        pairs += pixel_in_row.size
        # Pair sums of the whole row, summed into pixels at once: chunking keeps the same sums.
        pair_sums = np.zeros((channels, pixel_in_row.size, REPLICATES))
        for first in range(0, pixel_in_row.size, per_chunk):
            pixel = pixel_in_row[first:first + per_chunk]
            hole = hole_of_row[first:first + per_chunk]
            shape = (pixel.size, REPLICATES, n)
            draw = rng.random((*shape, RANDOM_PER_SAMPLE)).reshape(pixel.size, -1,
                                                                   RANDOM_PER_SAMPLE)
            box = corner + size * draw.reshape(*shape, -1)[..., 0:2]
            v = np.stack([vx[pixel][:, None] + (box[..., 0].reshape(pixel.size, -1) - 0.5)
                          * step_x, vy[j] + (box[..., 1].reshape(pixel.size, -1) - 0.5)
                          * step_y], axis=-1)  # (P, R n, 2)
            # The pair's lens: its top disk and its bottom disk seen along the rays, grown
            # to hold it for every direction in the box (module docstring).
            shift = thickness * (np.stack([vx[pixel], np.full(pixel.size, vy[j])], axis=1)
                                 + q * centre) / beta
            stratum = np.argsort(draw[..., 4].reshape(pixel.size, -1, n), axis=-1)
            square = corner[stratum] + size[stratum] * draw[..., 2:4].reshape(
                pixel.size, -1, n, 2)
            x_t, area = _lens_sample(disks.top[hole], disks.top_radius[hole],
                                     (disks.bottom[hole] - shift) / scale,
                                     (disks.bottom_radius[hole] + grow) / scale,
                                     square.reshape(pixel.size, -1, 2))
            # The pupil point of the ray through x_t in direction v.
            u = (x_t - centre - s_top * v) / beta
            live = ((area > 0)[:, None] & (np.sum(u**2, axis=-1) <= pupil_radius**2)).ravel()
            v, u, x_t = v.reshape(-1, 2), u.reshape(-1, 2), x_t.reshape(-1, 2)
            values, count = _shade(rays, v[:, 0], v[:, 1], u[:, 0], u[:, 1], live)
            cast += count
            weight = np.repeat(area / (n * np.pi * foot**2), REPLICATES * n)  # |lens| / ...
            if disks.neighbours.shape[1]:
                weight = weight * _lens_share(
                    x_t, scale * x_t + np.repeat(shift, REPLICATES * n, axis=0),
                    np.repeat(hole, REPLICATES * n), disks, grow)
            pair_sums[:, first:first + pixel.size] = (values * weight).reshape(
                channels, *shape).sum(axis=-1)
        target = ((j * nx + pixel_in_row)[:, None] * REPLICATES + np.arange(REPLICATES)).ravel()
        for c in range(channels):
            flat[c] += np.bincount(target, pair_sums[c].ravel(), flat.shape[1])
        if progress is not None:
            progress((j + 1) * nx, nx * ny)
    return cast, pairs


def _budget_samples(loops: HoleLoops, scene: Scene, least: int) -> int:
    """Rays per pair for about RAY_BUDGET rays in all (at least `least`, at most
    MOST_SAMPLES): a sparse plate, with few holes behind each view pixel, gets more per pair."""
    # The share of the plate's holes behind one view pixel: the pupil's footprint (grown by
    # a hole) over the plate's area.
    reach = scene.eye.pupil_mm / 2 + float(loops.top_circum_radius_mm.max(initial=0.0))
    extent = loops.outline_max_mm - loops.outline_min_mm
    share = min(1.0, math.pi * reach**2 / float(extent[0] * extent[1]))
    nx, ny = scene.eye.view_pixels
    pairs = max(1.0, nx * ny * loops.count * share)
    return int(min(MOST_SAMPLES, max(least, RAY_BUDGET // pairs)))


def trace_mesh_view(
    mesh: PlateMesh,
    scene: Scene,
    display: np.ndarray,
    position: int = 0,
    samples_per_pixel: int | None = None,
    seed: int = 0,
    max_rays: int = 2_000_000,
    progress: Callable[[int, int], None] | None = None,
    sampling: Sampling = "holes",
) -> TracedView:
    """The eye's view through `mesh` onto `display`, by casting rays (see the module docstring).

    mesh: the plate in part coordinates (bottom face at z = 0), e.g. read_stl of the written file.
    scene: display, plate (gap, thickness) and eye; display: (C, H, W) linear radiance.
    position: which of the eye's positions_mm. samples_per_pixel: rays per (view pixel, hole)
    pair for sampling "holes", per view pixel for "pupil" (rounded up to a multiple of
    REPLICATES); None: DEFAULT_SAMPLES[sampling]. seed: random seed. max_rays: rays per chunk
    (bounds memory; a chunk holds at least one view pixel or pair). progress: called with (view
    pixels done, total). sampling: "holes" (importance sampling over the mesh's holes, for
    plates passing little light) or "pupil" (uniform over the pupil, needs no hole structure).
    """
    loops = None
    if sampling == "holes":
        try:
            loops = mesh_hole_loops(mesh)
        except ValueError as error:
            raise ValueError(f"{error} (sampling='holes' needs the plate's hole loops; "
                             "sampling='pupil' traces any mesh)") from error
    if samples_per_pixel is None:
        samples_per_pixel = DEFAULT_SAMPLES.get(sampling, 0)
        if loops is not None:
            samples_per_pixel = _budget_samples(loops, scene, samples_per_pixel)
    display = _check_inputs(mesh, scene, display, position, samples_per_pixel, max_rays,
                            sampling)
    eye = scene.eye
    q = 0.0 if eye.focus_mm is None else 1.0 / eye.focus_mm
    hull = _outline_hull(mesh.vertices[:, :2])
    rays = _Rays(scene, display, eye.positions_mm[position], q, scene.plate_distance_mm, hull,
                 OUTLINE_RTOL * float(np.ptp(hull, axis=0).max()), _occluder(mesh))
    n = math.ceil(samples_per_pixel / REPLICATES)
    nx, ny = eye.view_pixels
    channels = display.shape[0]
    rng = np.random.default_rng(seed)
    estimates = np.zeros((channels, nx * ny, REPLICATES), dtype=np.float64)
    if loops is not None:
        cast, pairs = _trace_holes(rays, loops, n, rng, estimates, max_rays, progress)
    else:
        cast, pairs = _trace_pupil(rays, n, rng, estimates, max_rays, progress), 0
    view = estimates.mean(axis=-1)
    stderr = estimates.std(axis=-1, ddof=1) / math.sqrt(REPLICATES)
    return TracedView(
        view=view.reshape(channels, ny, nx),
        stderr=stderr.reshape(channels, ny, nx),
        samples_per_pixel=REPLICATES * n,
        sampling=sampling,
        rays_cast=cast,
        pairs=pairs,
    )
