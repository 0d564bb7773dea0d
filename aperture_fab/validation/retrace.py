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

Whether a ray meets the mesh is decided exactly for every ray that could carry light (one that
lands on a lit pixel inside the outline): Embree casts it, unless hole sampling (below) finds it
inside its hole's clear cylinder, where it meets nothing without a cast. A hole's clear cylinder
is the oblique cylinder about the line through its two loop centroids
(aperture_fab.fabrication.mesh_holes), over the mesh's whole z range, of the largest radius rho
that no triangle of the mesh enters, whichever hole or face it belongs to: each triangle near
the hole is sheared along that line (x -> x - axis(z)), and rho is the least distance of the
sheared triangles' xy projections from the axis (at most the loops' circumscribed radius). A ray
that crosses the mesh's lowest and highest planes within rho - margin of the line stays within
it in between (the sheared ray is a straight segment between two points of one disk), so it
meets no triangle: it passes. The margin (CLEAR_RTOL of the mesh's size, at least 50 float32
steps of Embree's frame) keeps those rays well clear of where Embree's rounding could find a
hit, so a cast would say the same. For a polygonal hole rho is its inscribed radius: only rays
near a wall are cast (5 % of them through the 16- to 24-sided holes of the default plate).

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
pupil point u = (x_t - c - s_t v) / beta found (no ray when |u| > R), and the ray decided against
the whole mesh as above (its hole's clear cylinder, else an Embree cast). A sample's weight is
|lens| / (n pi (beta R)^2), n samples per pair
and replicate, and the pixel is the sum over its pairs. samples_per_pixel is then the rays per
(view pixel, hole) pair. For the same error it casts ~15 x fewer rays than "pupil" through a
near-eye plate of 24 % open area (12 per pair: ~38 dB against the model), more as the open area
shrinks.

Chords (hole sampling's default, where the display's light over a view box is a rectangle's
mean: no cover glass, no falloff): the lens is cut into chords along x, drawn stratified in y with
density proportional to their length (the area below them, inverted as above), and each chord is
integrated along x and over the view box B in closed form wherever no ray can meet the mesh:
the segment S of the chord inside a disk that lies within the hole's clear cylinder for every
direction of B (the cylinder's tests are affine in (x_t, v), so B's corners decide), inside the
pupil's footprint for every v of B, crossing inside the outline and in no other hole's lens.
For one x_t the rays over B land on a rectangle of the display (their landing is affine in v),
whose mean light G is bilinear between the breakpoints where the rectangle's edges cross pixel
edges; tabulated at those breakpoints with its integral J along a row (`_box_table`, from the
display's summed-area table), it gives the integral over S x B exactly. The rest R of the chord
is taken at one direction v drawn in B: in closed form where v's rays pass the clear cylinder
(the display row's summed-area table), and elsewhere (near the wall) by one ray drawn on R with
probability R's share of the chord, weighted by its inverse, decided against the mesh as above.
Integrating three of the four dimensions leaves a smooth function of the chord's height, whose
stratified error falls much faster than a ray's: on a Siemens star's dense edges ~7 dB better
than rays for the same time. rays_cast then counts the closed-form segments and the rays. A
pair whose rays all land where the display is dark is skipped (it adds 0), and where the view
box lands on under MIN_BOX_PX of a pixel (the eye focused near the display) rays are drawn.

Both: REPLICATES independent estimates per view pixel; the value is their mean and its standard
error their standard deviation / sqrt(REPLICATES), an unbiased variance estimate.

The per-ray arithmetic (a ray from its uniforms, the lens map, the landing, the outline and
clear-cylinder tests, the radiance and the sums) runs in Numba kernels (parallel over pairs;
compiled on first use and cached on disk, like aperture_fab.optics.kernels), a chunk of pairs or
rays at a time. The uniforms come from numpy's generator (default_rng(seed)) in one fixed order
whatever the chunking, the next chunk's drawn on a second thread while Embree casts this one's
rays, so a seed gives the same view.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Literal, NamedTuple

import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.extending import intrinsic

from aperture_fab.fabrication.mesh import PlateMesh
from aperture_fab.fabrication.mesh_holes import HoleLoops, mesh_hole_loops
from aperture_fab.optics.scene import Scene

__all__ = ["DEFAULT_SAMPLES", "REPLICATES", "SAMPLINGS", "Sampling", "TracedView",
           "trace_mesh_view"]

Sampling = Literal["holes", "pupil"]
SAMPLINGS: tuple[Sampling, ...] = ("holes", "pupil")
#: Default samples_per_pixel: rays per (view pixel, hole) pair ("holes"), per view pixel
#: ("pupil").
DEFAULT_SAMPLES: dict[Sampling, int] = {"holes": 12, "pupil": 256}
#: With samples_per_pixel None, hole sampling spends about this many rays (~3 s on 2 cores for
#: the default 0.005 mm photomask plate, whose rays nearly all pass through clear cylinders;
#: more for a thick plate, whose rays near a wall are cast) and at most MOST_SAMPLES per pair,
#: never fewer than DEFAULT_SAMPLES["holes"].
RAY_BUDGET = 30_000_000
MOST_SAMPLES = 256
#: With samples_per_pixel None, chord sampling spends about this many chords, at least
#: LEAST_CHORDS per pair (2 per replicate) and at most MOST_SAMPLES.
CHORD_BUDGET = 16_000_000
LEAST_CHORDS = 8
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
#: Intervals of the table that inverts a cap's area (_cap_theta): theta and d theta / d t at
#: equal steps of t = cbrt(1.5 area) (theta ~ t near 0), interpolated by cubic Hermite
#: polynomials: the area theta - sin theta cos theta is met within 3e-15 (float64 rounding).
CAP_TABLE = 8192
#: The mesh is scaled to a box this size before Embree's float32 sees it.
EMBREE_BOX = 100.0
#: A ray passes without a cast only this share of the mesh's largest extent inside a hole's
#: clear cylinder: 4e-4 in Embree's frame (EMBREE_BOX), at least 50 float32 steps (7.6e-6 below
#: 128) there, far above its rounding of the vertices and the rays.
CLEAR_RTOL = 4e-6
#: Random numbers per chord (chord sampling): its height in its stratum (1), the point of the
#: chord drawn where the chord is not integrated (1), its view direction in the box (2).
RANDOM_PER_CHORD = 4
#: Chord sampling integrates a view box only where it lands on a display rectangle at least this
#: many pixels (sub-columns) across (the eye not focused near the display), and a chord in
#: closed form only where it lands at least this many sub-columns long (else its midpoint's
#: box): below, the table's differences would lose digits to rounding.
MIN_BOX_PX = 0.01
MIN_SPAN_PX = 1e-3
#: The view box's table (`_box_table`) may take at most this many bytes (a 400 x 400 RGB
#: display: 31 MB); a larger display is traced by hole sampling.
MAX_BOX_TABLE_BYTES = 2**28
#: Pairs per task of the parallel hole kernel, rays per task of the shading kernel.
PAIR_BLOCK = 256
RAY_BLOCK = 4096


@dataclass(frozen=True)
class TracedView:
    """A view traced through a mesh.

    view: (C, ny, nx) float64, linear radiance, row 0 the top of the view.
    stderr: (C, ny, nx) float64, Monte Carlo standard error of each pixel of `view`.
    samples_per_pixel: rays per view pixel ("pupil") or chords (rays where the display has
        no chords) per (view pixel, hole) pair ("holes"), the request rounded up to a whole
        number per replicate.
    sampling: how the rays were drawn (module docstring).
    rays_cast: rays decided against the mesh in all (those that could carry light: cast with
        Embree, or passed through a hole's clear cylinder), and chord segments integrated.
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


# -- Numba kernels: the per-ray arithmetic ---------------------------------------------------------

#: Fast-math flags that keep NaN and infinity semantics, as aperture_fab.optics.kernels: the
#: geometry's tests all keep margins far above the rounding this can change.
_FAST = {"nsz", "arcp", "contract", "reassoc"}
_jit = njit(cache=True, error_model="numpy", fastmath=_FAST)
#: Per-ray helpers, inlined into the kernels (a call would cut the pipeline's overlap).
_inline = njit(cache=True, error_model="numpy", fastmath=_FAST, inline="always")
_parallel = njit(cache=True, error_model="numpy", fastmath=_FAST, parallel=True)

#: Fields of the shading geometry array (`_Rays.of`).
SHADE_FIELDS = ("cx", "cy", "q", "s_bottom", "s_display", "half_width", "half_height", "pixel_x",
                "pixel_y", "cover_glass", "glass_index_squared", "emission_power")
#: Fields of the hole kernel's per-row constants (`_trace_holes`).
PAIR_FIELDS = ("step_x", "step_y", "s_top", "beta", "scale", "thickness", "grow", "pupil_r2",
               "lens_norm", "z_low", "z_high")
#: Fields of the chord kernel's constants (`_chords_kernel`): PAIR_FIELDS, then the landing
#: rectangle's size (sub-columns, rows) and the landing's sub-columns per mm of x_t.
CHORD_FIELDS = (*PAIR_FIELDS, "box_cols", "box_rows", "cols_per_mm")


def _cap_area(theta: np.ndarray) -> np.ndarray:
    """theta - sin(theta) cos(theta) = (phi - sin phi) / 2, phi = 2 theta, to float64 precision:
    by its series where the difference would cancel (phi < 1; terms to phi^21)."""
    phi = 2 * theta
    series = np.full_like(phi, 1 / math.factorial(21))
    for k in range(9, 0, -1):  # 1 / 3! - phi^2 / 5! + phi^4 / 7! - ..., by Horner
        series = 1 / math.factorial(2 * k + 1) - phi**2 * series
    return np.where(phi < 1, 0.5 * phi**3 * series, 0.5 * (phi - np.sin(phi)))


def _cap_table() -> np.ndarray:
    """(CAP_TABLE + 1, 4): at equal steps of t = cbrt(1.5 g) from 0 to cbrt(0.75 pi), theta in
    [0, pi / 2] with theta - sin theta cos theta = g (bisection, then Newton steps to float64
    precision), d theta / d t = t^2 / sin^2 theta (1 at 0), sin theta and cos theta. The nodes
    are at most 3e-4 rad apart."""
    t = np.linspace(0.0, (0.75 * math.pi) ** (1 / 3), CAP_TABLE + 1)
    g = t**3 / 1.5
    lo, hi = np.zeros_like(t), np.full_like(t, math.pi / 2)
    for _ in range(64):
        mid = 0.5 * (lo + hi)
        below = _cap_area(mid) < g
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    theta = 0.5 * (lo + hi)
    for _ in range(3):
        sin = np.sin(theta)
        theta = theta - (_cap_area(theta) - g) / np.maximum(2 * sin * sin, 1e-300)
    sin = np.sin(theta)
    slope = np.where(t > 0, t * t / np.maximum(sin * sin, 1e-300), 1.0)
    return np.stack([theta, slope, sin, np.cos(theta)], axis=1)


_CAP_TABLE = _cap_table()
_CAP_SCALE = CAP_TABLE / (0.75 * math.pi) ** (1 / 3)  # table steps per unit of t


def _float_bits_typer(typingctx, x):
    """The bits of a float64 as an int64 (a bit cast, as C's memcpy)."""
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))
    return types.int64(types.float64), codegen


def _bits_float_typer(typingctx, i):
    """The float64 of an int64's bits."""
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())
    return types.float64(types.int64), codegen


_float_bits: Any = intrinsic(_float_bits_typer)
_bits_float: Any = intrinsic(_bits_float_typer)


@_inline
def _cbrt(y):
    """The cube root of y >= 0 (y below 1e-200 as 1e-200), to 2 float64 steps, without a call:
    the exponent divided by 3 in the bits (within 4 %), then 3 Halley steps (cubic: 4e-2,
    1e-4, 1e-12, exact). libm's cbrt is a call, which spills registers and stops the kernels'
    overlap of samples."""
    y = max(y, 1e-200)
    t = _bits_float(_float_bits(y) // 3 + 0x2A9F7893782DA1CE)
    for _ in range(3):
        t3 = t * t * t
        t = t * (t3 + 2.0 * y) / (2.0 * t3 + y)
    return t


@_inline
def _rotate(sin, cos, step):
    """(sin, cos) of theta + step from theta's, for |step| <= 1e-3 (the table's steps are
    3e-4): the series of sin(step) and cos(step) to step^5 are exact to float64 there."""
    s2 = step * step
    c_step = 1.0 - s2 * (0.5 - s2 / 24.0)
    s_step = step * (1.0 - s2 * (1.0 / 6.0 - s2 / 120.0))
    return sin * c_step + cos * s_step, cos * c_step - sin * s_step


@_inline
def _cap_theta(g, table, table_scale):
    """(theta, sin theta, cos theta), theta in [0, pi] with theta - sin(theta) cos(theta) = g
    (g in [0, pi]): the cap {x <= -cos(theta)} of the unit disk has area g. On the half below
    pi / 2 (the rest by symmetry): the table (_cap_table) interpolated in t = cbrt(1.5 g) by
    a cubic Hermite polynomial, to float64 precision, and the node's sine and cosine turned by
    the rest of the angle (_rotate). No sin or cos is called and nothing branches: the kernels
    are latency-bound, and a mispredicted branch would stop the next sample's overlap."""
    flip = g > 0.5 * math.pi
    g = max(min(g, math.pi - g), 0.0)
    size = table.shape[0] - 1
    t = _cbrt(1.5 * g) * table_scale
    i = min(int(t), size - 1)
    f = t - i
    h = 1.0 / table_scale
    f1 = 1.0 - f
    theta = (f1 * f1 * ((1.0 + 2.0 * f) * table[i, 0] + f * h * table[i, 1])
             + f * f * ((3.0 - 2.0 * f) * table[i + 1, 0] - f1 * h * table[i + 1, 1]))
    sin, cos = _rotate(table[i, 2], table[i, 3], theta - table[i, 0])
    return (math.pi - theta if flip else theta), sin, (-cos if flip else cos)


@_inline
def _concentric_point(a, b):
    """Shirley-Chiu area-preserving map of the unit square's (a, b) onto the unit disk."""
    a = 2.0 * a - 1.0
    b = 2.0 * b - 1.0
    if abs(a) > abs(b):
        radius = a
        angle = math.pi / 4 * (b / a)
    else:
        radius = b
        angle = math.pi / 2 - math.pi / 4 * (a / (b if b != 0.0 else 1.0))
    return radius * math.cos(angle), radius * math.sin(angle)


@_inline
def _lens_setup(ax, ay, r, bx, by, s):
    """The lens of disks (a, r) and (b, s): (kind, unit x, unit y, d, area of B's cap, lens
    area). kind 1: the circles cross; 2: one disk holds the other (area: the smaller one's);
    0: empty (area 0). unit: a to b (x axis when d = 0), d: their distance."""
    ox = bx - ax
    oy = by - ay
    d = math.hypot(ox, oy)
    ux, uy = (ox / d, oy / d) if d > 0 else (1.0, 0.0)
    if abs(r - s) < d < r + s:
        chord = (d * d + r * r - s * s) / (2 * d)
        theta_b = math.acos(min(max((d - chord) / s, -1.0), 1.0))
        theta_a = math.acos(min(max(chord / r, -1.0), 1.0))
        area_b = s * s * (theta_b - math.sin(theta_b) * math.cos(theta_b))
        total = area_b + r * r * (theta_a - math.sin(theta_a) * math.cos(theta_a))
        return 1, ux, uy, d, area_b, total
    if d <= abs(r - s):
        small = min(r, s)
        return 2, ux, uy, d, 0.0, math.pi * small * small
    return 0, ux, uy, d, 0.0, 0.0


@_inline
def _lens_point(kind, ax, ay, r, bx, by, s, ux, uy, d, area_b, total, a, b, table, table_scale):
    """The point of the lens (`_lens_setup`) for the unit square's (a, b) (see _lens_sample)."""
    if kind == 1:
        target = a * total
        in_b = target < area_b
        radius = s if in_b else r
        g = min(max((target if in_b else total - target) / (radius * radius), 0.0), math.pi)
        _, sin, cos = _cap_theta(g, table, table_scale)
        x = d - s * cos if in_b else r * cos
        y = (2 * b - 1) * radius * sin
        return ax + x * ux - y * uy, ay + x * uy + y * ux
    px, py = _concentric_point(a, b)
    if r <= s:
        return ax + r * px, ay + r * py
    return bx + s * px, by + s * py


@_inline
def _shade_ray(vx, vy, ux, uy, geo, hull, slack, display, offsets, out):
    """Whether the ray (v, u) could carry light: it lands on the display, crosses the bottom
    face's plane inside the outline (the mount) and its radiance (written to out (C,), with the
    display optics) is not all 0. geo: SHADE_FIELDS; hull (M, 4): the outline's edges a b
    counter-clockwise, as (a, b - a), with each edge's slack (M,) (OUTLINE_RTOL x its length);
    offsets: stripe centres (px; none: empty)."""
    cx, cy, q, s_bottom, s_display = geo[0], geo[1], geo[2], geo[3], geo[4]
    land_x = cx + s_display * vx + (1 - s_display * q) * ux
    land_y = cy + s_display * vy + (1 - s_display * q) * uy
    slope_x = vx - q * ux
    slope_y = vy - q * uy
    if geo[9] > 0:  # under the cover glass the ray lands short of its straight continuation
        n2 = geo[10]
        factor = 1 / math.sqrt(n2 + (n2 - 1) * (slope_x**2 + slope_y**2))
        short = geo[9] * (1 - factor)
        land_x = land_x - short * slope_x
        land_y = land_y - short * slope_y
    col_mm = (land_x + geo[5]) / geo[7]
    col_f = np.floor(col_mm)
    row_f = np.floor((geo[6] - land_y) / geo[8])
    if col_f < 0 or col_f >= display.shape[2] or row_f < 0 or row_f >= display.shape[1]:
        return False
    bottom_x = cx + s_bottom * vx + (1 - s_bottom * q) * ux
    bottom_y = cy + s_bottom * vy + (1 - s_bottom * q) * uy
    for e in range(hull.shape[0]):  # (a x, a y, b x - a x, b y - a y) per edge a b
        if hull[e, 2] * (bottom_y - hull[e, 1]) - hull[e, 3] * (bottom_x - hull[e, 0]) \
                < -slack[e]:
            return False
    col = int(col_f)
    row = int(row_f)
    stripes = offsets.size
    within = col_mm - col_f
    falloff = 1.0
    if geo[11] > 0:
        falloff = (1 + slope_x**2 + slope_y**2) ** (-geo[11] / 2)
    lit = False
    for c in range(display.shape[0]):
        value = display[c, row, col]
        if stripes > 0:
            on = abs(within - 0.5 - offsets[c]) < 0.5 / stripes
            value = value * stripes * (1.0 if on else 0.0)
        if geo[11] > 0:
            value = value * falloff
        out[c] = value
        lit = lit or value != 0
    return lit


@_parallel
def _shade_kernel(v_x, v_y, u_x, u_y, live, geo, hull, slack, display, offsets, values, cast):
    """values (C, N): the radiance of each live ray that could carry light (`_shade_ray`), else
    0; cast (N,) bool: those rays (still to be cast against the mesh)."""
    n = v_x.size
    for block in prange((n + RAY_BLOCK - 1) // RAY_BLOCK):
        radiance = np.empty(display.shape[0])
        for i in range(block * RAY_BLOCK, min(n, (block + 1) * RAY_BLOCK)):
            if live[i] and _shade_ray(v_x[i], v_y[i], u_x[i], u_y[i], geo, hull, slack,
                                      display, offsets, radiance):
                cast[i] = True
                for c in range(radiance.size):
                    values[c, i] = radiance[c]


@_parallel
def _holes_kernel(draw, pixel, hole, vx, vy, corner, size, top, top_r, bottom, bottom_r,
                  neighbours, axis_low, axis_high, clear2, pair_geo, geo, hull, slack, display,
                  offsets, table, table_scale, sums, cast, rays, contrib, counts):
    """Hole sampling of one chunk of (view pixel, hole) pairs of a view row (module docstring).

    draw (P, R n, RANDOM_PER_SAMPLE): the uniforms; pixel, hole (P,): the pairs; vx (nx,): view
    columns, vy: the row's tan. top, bottom (K, 2), top_r, bottom_r (K,): the disks;
    neighbours (K, M); axis_low, axis_high (K, 2): each clear cylinder's axis at the mesh's
    lowest and highest z; clear2 (K,): its usable radius squared (< 0: none). pair_geo:
    PAIR_FIELDS. Writes sums (P, R, C): each pair's and replicate's weighted radiance over the
    rays that pass through their hole's clear cylinder; for the other rays that could carry
    light cast[i] = True (i = (p R + r) n + k), rays[i] = (u_x, u_y, dx, dy) (pupil point and
    direction per unit depth) and contrib[i] (C,) their weighted radiance, added by the caller
    when the ray misses the mesh; counts (P,): rays that could carry light per pair."""
    n = corner.shape[0]
    reps = draw.shape[1] // n
    channels = display.shape[0]
    pairs = pixel.size
    step_x, step_y, s_top, beta, scale = (pair_geo[0], pair_geo[1], pair_geo[2], pair_geo[3],
                                          pair_geo[4])
    thickness, grow, pupil_r2, lens_norm = pair_geo[5], pair_geo[6], pair_geo[7], pair_geo[8]
    z_low, z_high = pair_geo[9], pair_geo[10]
    cx, cy, q, s_bottom = geo[0], geo[1], geo[2], geo[3]
    others = neighbours.shape[1]
    for block in prange((pairs + PAIR_BLOCK - 1) // PAIR_BLOCK):
        order = np.empty(draw.shape[1], dtype=np.int64)
        drawn = np.empty((draw.shape[1], 4))  # v (x, y), x_t (x, y) of the pair's rays
        radiance = np.empty(channels)
        for p in range(block * PAIR_BLOCK, min(pairs, (block + 1) * PAIR_BLOCK)):
            h = hole[p]
            for rep in range(reps):
                for c in range(channels):
                    sums[p, rep, c] = 0.0
            counts[p] = 0
            pvx = vx[pixel[p]]
            # The pair's lens: its top disk and its bottom disk seen along the rays, grown to
            # hold it for every direction in the box (module docstring).
            shift_x = thickness * (pvx + q * cx) / beta
            shift_y = thickness * (vy + q * cy) / beta
            ax, ay, r = top[h, 0], top[h, 1], top_r[h]
            bx = (bottom[h, 0] - shift_x) / scale
            by = (bottom[h, 1] - shift_y) / scale
            s = (bottom_r[h] + grow) / scale
            kind, ux, uy, d, area_b, area = _lens_setup(ax, ay, r, bx, by, s)
            if not area > 0:
                continue
            weight = area / lens_norm
            rho2 = clear2[h]
            count = 0
            # First every sample's ray (no unpredictable branch: the samples overlap in the
            # pipeline), then each ray's fate.
            for rep in range(reps):
                base = rep * n
                # The lens strata in the order of the permutation keys (an argsort).
                for k in range(n):
                    key = draw[p, base + k, 4]
                    m = k
                    while m > 0 and draw[p, base + order[base + m - 1], 4] > key:
                        order[base + m] = order[base + m - 1]
                        m -= 1
                    order[base + m] = k
            for rep in range(reps):
                for k in range(n):
                    j = rep * n + k
                    st = order[j]
                    v_x = pvx + (corner[k, 0] + size[k, 0] * draw[p, j, 0] - 0.5) * step_x
                    v_y = vy + (corner[k, 1] + size[k, 1] * draw[p, j, 1] - 0.5) * step_y
                    x_t, y_t = _lens_point(kind, ax, ay, r, bx, by, s, ux, uy, d, area_b, area,
                                           corner[st, 0] + size[st, 0] * draw[p, j, 2],
                                           corner[st, 1] + size[st, 1] * draw[p, j, 3],
                                           table, table_scale)
                    drawn[j, 0] = v_x
                    drawn[j, 1] = v_y
                    drawn[j, 2] = x_t
                    drawn[j, 3] = y_t
            for rep in range(reps):
                for j in range(rep * n, rep * n + n):
                    v_x, v_y, x_t, y_t = drawn[j, 0], drawn[j, 1], drawn[j, 2], drawn[j, 3]
                    # The pupil point of the ray through x_t in direction v.
                    u_x = (x_t - cx - s_top * v_x) / beta
                    u_y = (y_t - cy - s_top * v_y) / beta
                    if u_x * u_x + u_y * u_y > pupil_r2:
                        continue
                    if not _shade_ray(v_x, v_y, u_x, u_y, geo, hull, slack, display, offsets,
                                      radiance):
                        continue
                    count += 1
                    w = weight
                    if others:  # 1 / the number of lenses holding the point
                        x_b = scale * x_t + shift_x
                        y_b = scale * y_t + shift_y
                        holders = 1.0
                        for m in range(others):
                            o = neighbours[h, m]
                            if o < 0:
                                break
                            if ((x_t - top[o, 0]) ** 2 + (y_t - top[o, 1]) ** 2 <= top_r[o] ** 2
                                    and (x_b - bottom[o, 0]) ** 2 + (y_b - bottom[o, 1]) ** 2
                                    <= (bottom_r[o] + grow) ** 2):
                                holders += 1.0
                        w = w * (1.0 / holders)
                    dx = v_x - q * u_x
                    dy = v_y - q * u_y
                    clear = False
                    if rho2 > 0:  # the ray at the mesh's lowest and highest z, off the axis
                        lx = cx + u_x + (s_bottom - z_low) * dx - axis_low[h, 0]
                        ly = cy + u_y + (s_bottom - z_low) * dy - axis_low[h, 1]
                        hx = cx + u_x + (s_bottom - z_high) * dx - axis_high[h, 0]
                        hy = cy + u_y + (s_bottom - z_high) * dy - axis_high[h, 1]
                        clear = lx * lx + ly * ly < rho2 and hx * hx + hy * hy < rho2
                    if clear:
                        for c in range(channels):
                            sums[p, rep, c] += radiance[c] * w
                    else:
                        i = p * reps * n + j
                        cast[i] = True
                        rays[i, 0] = u_x
                        rays[i, 1] = u_y
                        rays[i, 2] = dx
                        rays[i, 3] = dy
                        for c in range(channels):
                            contrib[i, c] = radiance[c] * w
            counts[p] = count


@_inline
def _chord(cx, cy, radius2, y, lo, hi):
    """(lo, hi) cut to the chord at height y of the disk about (cx, cy) of squared radius
    radius2 (empty: hi <= lo)."""
    rest = radius2 - (y - cy) ** 2
    if not rest > 0:
        return lo, lo
    half = math.sqrt(rest)
    return max(lo, cx - half), min(hi, cx + half)


@_inline
def _inside_outline(x, y, hull, slack):
    """Whether the point (x, y) of the bottom face's plane is inside the outline (with slack)."""
    for e in range(hull.shape[0]):
        if hull[e, 2] * (y - hull[e, 1]) - hull[e, 3] * (x - hull[e, 0]) < -slack[e]:
            return False
    return True


@_inline
def _segment_inside(x0, x1, y, v_x, v_y, half_x, half_y, geo, beta, s_top, hull, slack):
    """Whether the rays from the top-face segment x0..x1 at height y, in every direction of the
    box (v_x, v_y) +- (half_x, half_y), cross the bottom face's plane inside the outline: the
    crossings are affine in (x, v) and the outline convex, so the 8 corners decide."""
    cx, cy, q, s_bottom = geo[0], geo[1], geo[2], geo[3]
    for corner in range(8):
        x_t = x1 if corner & 4 else x0
        d_x = v_x + (half_x if corner & 1 else -half_x)
        d_y = v_y + (half_y if corner & 2 else -half_y)
        u_x = (x_t - cx - s_top * d_x) / beta
        u_y = (y - cy - s_top * d_y) / beta
        if not _inside_outline(cx + u_x + s_bottom * (d_x - q * u_x),
                               cy + u_y + s_bottom * (d_y - q * u_y), hull, slack):
            return False
    return True


@_inline
def _meets_neighbour(h, y, x0, x1, neighbours, top, top_r, bottom, bottom_r, shift_x, shift_y,
                     scale, grow):
    """Whether another hole's lens (its top disk and its grown bottom disk seen from the top
    face) reaches the segment x0..x1 at height y of the top face's plane."""
    for m in range(neighbours.shape[1]):
        o = neighbours[h, m]
        if o < 0:
            break
        o0, o1 = _chord(top[o, 0], top[o, 1], top_r[o] ** 2, y, x0, x1)
        o0, o1 = _chord((bottom[o, 0] - shift_x) / scale, (bottom[o, 1] - shift_y) / scale,
                        ((bottom_r[o] + grow) / scale) ** 2, y, o0, o1)
        if o1 > o0:
            return True
    return False


@_inline
def _grid_cell(x, half, gap, count):
    """(m, t, length): the interval [p_m, p_m+1] of the box table's breakpoints p (`_box_table`:
    -half + k and -half + k + gap, k = 0, 1, ...; count of them) that holds x, x - p_m and
    the interval's length; m = -1 before the first breakpoint and count - 1 from the last."""
    y = x + half
    if not y >= 0:
        return -1, 0.0, 1.0
    k = int(y)
    f = y - k
    m, t, length = (2 * k, f, gap) if f < gap else (2 * k + 1, f - gap, 1.0 - gap)
    if m >= count - 1:
        return count - 1, 0.0, 1.0
    return m, t, length


@_inline
def _box_row(box, grid, row):
    """(m, w): the box table's row breakpoint interval [p_m, p_m+1] holding `row` and where in
    it (0 to 1); m = -1 where no light lands (the row beyond the display's reach)."""
    m, tr, lr = _grid_cell(row, grid[0], grid[1], box.shape[0])
    if m >= box.shape[0] - 1:
        return -1, 0.0
    return m, tr / lr


@_inline
def _box_light(box, grid, m, wr, col, out, sign, integral):
    """Adds sign x, from the box table (`_box_table`), to out (C,), at the row w of the way
    through row interval m (`_box_row`): with integral, the light of the view box's landing
    rectangle about (row, col) integrated over sub-columns up to col (J); else the rectangle's
    mean light there (G). Exact: J is linear in the row and quadratic in the column between
    breakpoints, G bilinear."""
    n, tc, lc = _grid_cell(col, grid[2], grid[3], box.shape[1])
    if n < 0:
        return
    if n >= box.shape[1] - 1:
        if integral:
            for c in range(out.size):
                out[c] += sign * ((1 - wr) * box[m, n, 0, c] + wr * box[m + 1, n, 0, c])
        return
    wc = tc / lc
    half = 0.5 * tc * wc
    for c in range(out.size):
        if integral:
            low = box[m, n, 0, c] + box[m, n, 1, c] * tc + (box[m, n + 1, 1, c]
                                                            - box[m, n, 1, c]) * half
            high = box[m + 1, n, 0, c] + box[m + 1, n, 1, c] * tc + (
                box[m + 1, n + 1, 1, c] - box[m + 1, n, 1, c]) * half
        else:
            low = box[m, n, 1, c] + (box[m, n + 1, 1, c] - box[m, n, 1, c]) * wc
            high = box[m + 1, n, 1, c] + (box[m + 1, n + 1, 1, c] - box[m + 1, n, 1, c]) * wc
        out[c] += sign * ((1 - wr) * low + wr * high)


@_inline
def _row_light(sat, row, col, out, sign):
    """Adds sign x the light of the display's row at `row` over sub-columns [0, col] to out
    (C,): the summed-area table's difference across that row, interpolated along it."""
    rows = sat.shape[1] - 1
    cols = sat.shape[2] - 1
    if not (0.0 <= row < rows):
        return
    i = int(row)
    col = min(max(col, 0.0), float(cols))
    j = min(int(col), cols - 1)
    fx = col - j
    for c in range(out.size):
        low = sat[c, i + 1, j] - sat[c, i, j]
        high = sat[c, i + 1, j + 1] - sat[c, i, j + 1]
        out[c] += sign * (low + fx * (high - low))


@_inline
def _dark(lit, row0, row1, col0, col1):
    """Whether no sub-pixel emits in the rectangle [row0, row1] x [col0, col1] (rows,
    sub-columns; grown to whole ones), from the table of lit sub-pixels `lit`."""
    rows = lit.shape[0] - 1
    cols = lit.shape[1] - 1
    i0 = min(max(math.floor(row0), 0), rows)
    i1 = min(max(math.ceil(row1), 0), rows)
    j0 = min(max(math.floor(col0), 0), cols)
    j1 = min(max(math.ceil(col1), 0), cols)
    return lit[i1, j1] - lit[i0, j1] - lit[i1, j0] + lit[i0, j0] == 0


@_parallel
def _chords_kernel(draw, pixel, hole, vx, vy, top, top_r, bottom, bottom_r, neighbours,
                   axis_low, axis_high, clear2, chord_geo, geo, hull, slack, display, offsets,
                   sat, box, grid, lit, hole_inside, table, table_scale, sums, cast, rays,
                   contrib, counts):
    """Chord sampling of one chunk of (view pixel, hole) pairs of a view row (module docstring).

    draw (P, R n, RANDOM_PER_CHORD): the uniforms; chord_geo: CHORD_FIELDS; sat, lit: the
    display's summed-area tables (`_summed_area`); box, grid: the view box's table
    (`_box_table`); hole_inside (K,): whether every ray through a hole's lens crosses the
    bottom face's plane inside the outline; the rest as `_holes_kernel`, whose outputs this writes
    the same way: sums (P, R, C) for what is integrated in closed form or passes through a
    clear cylinder, cast / rays / contrib for the rays Embree decides, counts (P,): chords
    integrated and rays that could carry light per pair."""
    reps = sums.shape[1]
    n = draw.shape[1] // reps
    channels = display.shape[0]
    pairs = pixel.size
    step_x, step_y, s_top, beta, scale = (chord_geo[0], chord_geo[1], chord_geo[2],
                                          chord_geo[3], chord_geo[4])
    thickness, grow, pupil_r2, lens_norm = (chord_geo[5], chord_geo[6], chord_geo[7],
                                            chord_geo[8])
    z_low, z_high = chord_geo[9], chord_geo[10]
    half_cols, half_rows, columns = grid[2], grid[0], chord_geo[13]
    cx, cy, q, s_bottom, s_display = geo[0], geo[1], geo[2], geo[3], geo[4]
    land = (1 - s_display * q) / beta  # the landing point moves by land per mm of x_t
    cols_per_mm = land / geo[7] * columns
    foot2 = beta * beta * pupil_r2
    low_reach = (1 - (s_bottom - z_low) * q) / beta  # x_t offsets to lowest-plane offsets
    others = neighbours.shape[1]
    for block in prange((pairs + PAIR_BLOCK - 1) // PAIR_BLOCK):
        radiance = np.empty(channels)
        light = np.empty(channels)
        # Per pair: the centres, on the top face's plane, of the pupil's footprint and of the
        # clear cylinder's lowest-plane disk, for the box's four corner directions.
        pupil_at = np.empty((4, 2))
        low_at = np.empty((4, 2))
        for p in range(block * PAIR_BLOCK, min(pairs, (block + 1) * PAIR_BLOCK)):
            h = hole[p]
            for rep in range(reps):
                for c in range(channels):
                    sums[p, rep, c] = 0.0
            counts[p] = 0
            pvx = vx[pixel[p]]
            shift_x = thickness * (pvx + q * cx) / beta
            shift_y = thickness * (vy + q * cy) / beta
            ax, ay, r = top[h, 0], top[h, 1], top_r[h]
            bx = (bottom[h, 0] - shift_x) / scale
            by = (bottom[h, 1] - shift_y) / scale
            s = (bottom_r[h] + grow) / scale
            if not (max(ay - r, by - s) < min(ay + r, by + s)
                    and max(ax - r, bx - s) < min(ax + r, bx + s)):
                continue
            # Chords are drawn with density proportional to their length across the smaller
            # disk D (which holds the lens): the area below them in D, stratified.
            dy_c, dr = (ay, r) if r <= s else (by, s)
            rho2 = clear2[h]
            low_r2 = rho2 / (low_reach * low_reach)
            inside = hole_inside[h]  # every ray through the hole crosses inside the outline
            for k in range(4):
                v_x = pvx + (0.5 if k & 1 else -0.5) * step_x
                v_y = vy + (0.5 if k & 2 else -0.5) * step_y
                pupil_at[k, 0] = cx + s_top * v_x
                pupil_at[k, 1] = cy + s_top * v_y
                # The ray's lowest-plane point is axis_low + low_reach (x_t - low_at).
                low_at[k, 0] = pupil_at[k, 0] + (axis_low[h, 0] - cx - (s_bottom - z_low)
                                                 * v_x) / low_reach
                low_at[k, 1] = pupil_at[k, 1] + (axis_low[h, 1] - cy - (s_bottom - z_low)
                                                 * v_y) / low_reach
            # S's disks: one inside the clear cylinder's top disk and its lowest-plane disks
            # for the four corner directions, and one inside their four pupil footprints.
            clear_x = 0.5 * axis_high[h, 0] + 0.125 * (low_at[0, 0] + low_at[1, 0] + low_at[2, 0]
                                                       + low_at[3, 0])
            clear_y = 0.5 * axis_high[h, 1] + 0.125 * (low_at[0, 1] + low_at[1, 1] + low_at[2, 1]
                                                       + low_at[3, 1])
            clear_r = -1.0
            if rho2 > 0:
                clear_r = math.sqrt(rho2) - math.hypot(clear_x - axis_high[h, 0],
                                                       clear_y - axis_high[h, 1])
                for k in range(4):
                    clear_r = min(clear_r, math.sqrt(low_r2) - math.hypot(
                        low_at[k, 0] - clear_x, low_at[k, 1] - clear_y))
            clear_r2 = clear_r * clear_r if clear_r > 0 else -1.0
            foot_x, foot_y = cx + s_top * pvx, cy + s_top * vy
            foot_r = beta * math.sqrt(pupil_r2) - 0.5 * s_top * math.hypot(step_x, step_y)
            # Whether the lens lies in every footprint: then no ray is cut by the pupil.
            x_lo, x_hi = max(ax - r, bx - s), min(ax + r, bx + s)
            y_lo, y_hi = max(ay - r, by - s), min(ay + r, by + s)
            in_pupil = foot_r > 0 and max(
                (x_lo - foot_x) ** 2, (x_hi - foot_x) ** 2) + max(
                (y_lo - foot_y) ** 2, (y_hi - foot_y) ** 2) <= foot_r * foot_r
            # The sub-column where the centre direction's ray from x_t = 0 would land.
            col_0 = (cx + s_display * pvx - land * (cx + s_top * pvx) + geo[5]) / geo[7] * columns
            # No light where every ray of the pair lands (the box's landing rectangle about
            # where the lens's bounding box lands): nothing to trace.
            row_lo = (geo[6] - (cy + s_display * vy + land * (y_hi - cy - s_top * vy))) / geo[8]
            row_hi = (geo[6] - (cy + s_display * vy + land * (y_lo - cy - s_top * vy))) / geo[8]
            c_lo, c_hi = col_0 + cols_per_mm * x_lo, col_0 + cols_per_mm * x_hi
            if _dark(lit, min(row_lo, row_hi) - half_rows - 1.0,
                     max(row_lo, row_hi) + half_rows + 1.0, min(c_lo, c_hi) - half_cols - 1.0,
                     max(c_lo, c_hi) + half_cols + 1.0):
                continue
            count = 0
            for rep in range(reps):
                for k in range(n):
                    j = rep * n + k
                    _, sin, cos = _cap_theta((k + draw[p, j, 0]) / n * math.pi, table,
                                             table_scale)
                    y_t = dy_c - dr * cos
                    if not sin > 0:
                        continue
                    # The chord's weight: 1 / its density, D's area over its length in D.
                    weight = 0.5 * math.pi * dr / (sin * lens_norm)
                    lo, hi = _chord(ax, ay, r * r, y_t, -np.inf, np.inf)
                    lo, hi = _chord(bx, by, s * s, y_t, lo, hi)
                    if not hi > lo:
                        continue
                    # S: where every ray from the chord over the whole box passes (within
                    # S's disks, which lie inside the sets that say so).
                    s0, s1 = _chord(clear_x, clear_y, clear_r2, y_t, lo, hi)
                    if not in_pupil:
                        for corner in range(4):
                            s0, s1 = _chord(pupil_at[corner, 0], pupil_at[corner, 1], foot2,
                                            y_t, s0, s1)
                    if s1 > s0 and not (inside or _segment_inside(
                            s0, s1, y_t, pvx, vy, 0.5 * step_x, 0.5 * step_y, geo, beta, s_top,
                            hull, slack)):
                        s1 = s0
                    if s1 > s0 and _meets_neighbour(h, y_t, s0, s1, neighbours, top, top_r,
                                                    bottom, bottom_r, shift_x, shift_y, scale,
                                                    grow):
                        s1 = s0
                    if s1 > s0:
                        count += 1
                        # The box's light along S: the light of the display rectangle the box
                        # lands on, integrated along the sub-columns the chord lands on.
                        row = (geo[6] - (cy + s_display * vy + land * (y_t - cy - s_top * vy))
                               ) / geo[8]
                        c0 = col_0 + cols_per_mm * s0
                        c1 = col_0 + cols_per_mm * s1
                        for c in range(channels):
                            light[c] = 0.0
                        m, wr = _box_row(box, grid, row)
                        if m < 0:
                            continue  # no light lands above or below the display's reach
                        if abs(c1 - c0) < MIN_SPAN_PX:
                            _box_light(box, grid, m, wr, 0.5 * (c0 + c1), light, 1.0, False)
                            factor = weight * (s1 - s0)
                        else:
                            _box_light(box, grid, m, wr, c1, light, 1.0, True)
                            _box_light(box, grid, m, wr, c0, light, -1.0, True)
                            factor = weight / cols_per_mm
                        for c in range(channels):
                            sums[p, rep, c] += light[c] * factor
                    else:
                        s0 = s1 = hi
                    # The rest R = [lo, s0) + [s1, hi), at one direction v of the box: in closed
                    # form where v's rays pass the clear cylinder (E), by a ray elsewhere, on
                    # this chord with probability R's share of it (roulette).
                    rest = (s0 - lo) + (hi - s1)
                    chance = min(1.0, rest / (hi - lo))
                    pick = draw[p, j, 1]
                    if in_pupil and not pick < chance:
                        continue  # within the footprints R is all near the wall: E is empty
                    v_x = pvx + (draw[p, j, 2] - 0.5) * step_x
                    v_y = vy + (draw[p, j, 3] - 0.5) * step_y
                    e0 = e1 = lo
                    if not in_pupil:
                        e0, e1 = _chord(cx + s_top * v_x, cy + s_top * v_y, foot2, y_t, lo, hi)
                    if rho2 > 0 and e1 > e0:
                        e0, e1 = _chord(axis_high[h, 0], axis_high[h, 1], rho2, y_t, e0, e1)
                        e0, e1 = _chord(cx + s_top * v_x + (axis_low[h, 0] - cx - (
                            s_bottom - z_low) * v_x) / low_reach, cy + s_top * v_y + (
                            axis_low[h, 1] - cy - (s_bottom - z_low) * v_y) / low_reach, low_r2,
                            y_t, e0, e1)
                    else:
                        e1 = e0
                    row = (geo[6] - (cy + s_display * v_y + land * (y_t - cy - s_top * v_y))
                           ) / geo[8]
                    col_v = ((cx + s_display * v_x - land * (cx + s_top * v_x) + geo[5])
                             / geo[7] * columns)
                    for piece in range(2):
                        a0 = max(e0, lo if piece == 0 else s1)
                        a1 = min(e1, s0 if piece == 0 else hi)
                        if not a1 > a0:
                            continue
                        if not (inside or _segment_inside(a0, a1, y_t, v_x, v_y, 0.0, 0.0, geo,
                                                          beta, s_top, hull, slack)):
                            continue
                        if _meets_neighbour(h, y_t, a0, a1, neighbours, top, top_r, bottom,
                                            bottom_r, shift_x, shift_y, scale, grow):
                            continue
                        count += 1
                        for c in range(channels):
                            light[c] = 0.0
                        if abs(cols_per_mm) * (a1 - a0) < MIN_SPAN_PX:
                            # The light of the sub-column it lands in.
                            mid = math.floor(col_v + cols_per_mm * 0.5 * (a0 + a1))
                            _row_light(sat, row, mid + 1.0, light, 1.0)
                            _row_light(sat, row, mid, light, -1.0)
                            factor = weight * (a1 - a0)
                        else:
                            _row_light(sat, row, col_v + cols_per_mm * a1, light, 1.0)
                            _row_light(sat, row, col_v + cols_per_mm * a0, light, -1.0)
                            factor = weight / cols_per_mm
                        for c in range(channels):
                            sums[p, rep, c] += light[c] * factor
                    # The rest of R (near the wall, or where the closed form did not apply):
                    # one ray at a point drawn on R.
                    if not pick < chance:
                        continue
                    x_t = lo + pick / chance * rest
                    if x_t >= s0:
                        x_t += s1 - s0
                    if e0 <= x_t < e1:
                        inner = x_t < s0
                        a0 = max(e0, lo if inner else s1)
                        a1 = min(e1, s0 if inner else hi)
                        if (inside or _segment_inside(a0, a1, y_t, v_x, v_y, 0.0, 0.0, geo, beta,
                                                      s_top, hull, slack)) and not \
                                _meets_neighbour(h, y_t, a0, a1, neighbours, top, top_r, bottom,
                                                 bottom_r, shift_x, shift_y, scale, grow):
                            continue  # in a piece counted in closed form
                    u_x = (x_t - cx - s_top * v_x) / beta
                    u_y = (y_t - cy - s_top * v_y) / beta
                    if u_x * u_x + u_y * u_y > pupil_r2:
                        continue
                    if not _shade_ray(v_x, v_y, u_x, u_y, geo, hull, slack, display, offsets,
                                      radiance):
                        continue
                    count += 1
                    w = weight * rest / chance
                    if others:  # 1 / the number of lenses holding the point
                        x_b = scale * x_t + shift_x
                        y_b = scale * y_t + shift_y
                        holders = 1.0
                        for m in range(others):
                            o = neighbours[h, m]
                            if o < 0:
                                break
                            if ((x_t - top[o, 0]) ** 2 + (y_t - top[o, 1]) ** 2 <= top_r[o] ** 2
                                    and (x_b - bottom[o, 0]) ** 2 + (y_b - bottom[o, 1]) ** 2
                                    <= (bottom_r[o] + grow) ** 2):
                                holders += 1.0
                        w = w * (1.0 / holders)
                    dx = v_x - q * u_x
                    dy = v_y - q * u_y
                    clear = False
                    if rho2 > 0:
                        lx = cx + u_x + (s_bottom - z_low) * dx - axis_low[h, 0]
                        ly = cy + u_y + (s_bottom - z_low) * dy - axis_low[h, 1]
                        hx = cx + u_x + (s_bottom - z_high) * dx - axis_high[h, 0]
                        hy = cy + u_y + (s_bottom - z_high) * dy - axis_high[h, 1]
                        clear = lx * lx + ly * ly < rho2 and hx * hx + hy * hy < rho2
                    if clear:
                        for c in range(channels):
                            sums[p, rep, c] += radiance[c] * w
                    else:
                        i = p * reps * n + j
                        cast[i] = True
                        rays[i, 0] = u_x
                        rays[i, 1] = u_y
                        rays[i, 2] = dx
                        rays[i, 3] = dy
                        for c in range(channels):
                            contrib[i, c] = radiance[c] * w
            counts[p] = count


@_jit
def _segment_distance2(ax, ay, bx, by):
    """Squared distance from the origin to the segment a b."""
    ex = bx - ax
    ey = by - ay
    length2 = ex * ex + ey * ey
    t = 0.0 if length2 == 0 else min(max(-(ax * ex + ay * ey) / length2, 0.0), 1.0)
    px = ax + t * ex
    py = ay + t * ey
    return px * px + py * py


@_jit
def _clear_kernel(vertices, faces, axis_low, axis_high, z_low, z_high, box, grid_origin, cell,
                  grid_shape, grid_start, grid_holes, clear2):
    """clear2 (K,): lowered to the squared distance from each hole's axis of every triangle
    whose xy bounding box meets the hole's `box` (K, 4: x0, y0, x1, y1), the triangle sheared
    along the axis (x -> x - axis(z), axis linear from axis_low at z_low to axis_high at
    z_high) and projected on xy (0 when it covers the axis). Holes are found through a grid of
    square cells (grid_start (cells + 1,), grid_holes: CSR of the holes whose box meets each
    cell, row-major over grid_shape (columns, rows))."""
    span = z_high - z_low
    gx, gy = grid_shape[0], grid_shape[1]
    for f in range(faces.shape[0]):
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        x_lo = min(vertices[i0, 0], vertices[i1, 0], vertices[i2, 0])
        x_hi = max(vertices[i0, 0], vertices[i1, 0], vertices[i2, 0])
        y_lo = min(vertices[i0, 1], vertices[i1, 1], vertices[i2, 1])
        y_hi = max(vertices[i0, 1], vertices[i1, 1], vertices[i2, 1])
        c0 = max(0, math.floor((x_lo - grid_origin[0]) / cell))
        c1 = min(gx - 1, math.floor((x_hi - grid_origin[0]) / cell))
        r0 = max(0, math.floor((y_lo - grid_origin[1]) / cell))
        r1 = min(gy - 1, math.floor((y_hi - grid_origin[1]) / cell))
        for row in range(r0, r1 + 1):
            for col in range(c0, c1 + 1):
                g = row * gx + col
                for e in range(grid_start[g], grid_start[g + 1]):
                    h = grid_holes[e]
                    if x_hi < box[h, 0] or x_lo > box[h, 2] or y_hi < box[h, 1] \
                            or y_lo > box[h, 3]:
                        continue
                    ox0, oy0 = axis_low[h, 0], axis_low[h, 1]
                    ex, ey = axis_high[h, 0] - ox0, axis_high[h, 1] - oy0
                    w0 = (vertices[i0, 2] - z_low) / span
                    w1 = (vertices[i1, 2] - z_low) / span
                    w2 = (vertices[i2, 2] - z_low) / span
                    p0x = vertices[i0, 0] - (ox0 + ex * w0)
                    p0y = vertices[i0, 1] - (oy0 + ey * w0)
                    p1x = vertices[i1, 0] - (ox0 + ex * w1)
                    p1y = vertices[i1, 1] - (oy0 + ey * w1)
                    p2x = vertices[i2, 0] - (ox0 + ex * w2)
                    p2y = vertices[i2, 1] - (oy0 + ey * w2)
                    s0 = p0x * p1y - p0y * p1x
                    s1 = p1x * p2y - p1y * p2x
                    s2 = p2x * p0y - p2y * p0x
                    if (s0 >= 0 and s1 >= 0 and s2 >= 0) or (s0 <= 0 and s1 <= 0 and s2 <= 0):
                        dist2 = 0.0  # the projection covers the axis
                    else:
                        dist2 = min(_segment_distance2(p0x, p0y, p1x, p1y),
                                    _segment_distance2(p1x, p1y, p2x, p2y),
                                    _segment_distance2(p2x, p2y, p0x, p0y))
                    if dist2 < clear2[h]:
                        clear2[h] = dist2


@_jit
def _cap_kernel(area, table, table_scale, out):
    for i in range(area.size):
        out[i] = _cap_theta(area[i], table, table_scale)[0]


@_jit
def _concentric_kernel(a, b, x, y):
    for i in range(a.size):
        x[i], y[i] = _concentric_point(a[i], b[i])


@_jit
def _lens_kernel(a, r, b, s, square, table, table_scale, points, area):
    for p in range(r.size):
        kind, ux, uy, d, area_b, total = _lens_setup(a[p, 0], a[p, 1], r[p], b[p, 0], b[p, 1],
                                                     s[p])
        area[p] = total
        for k in range(square.shape[1]):
            points[p, k, 0], points[p, k, 1] = _lens_point(
                kind, a[p, 0], a[p, 1], r[p], b[p, 0], b[p, 1], s[p], ux, uy, d, area_b, total,
                square[p, k, 0], square[p, k, 1], table, table_scale)


def _cap_angle(area: np.ndarray) -> np.ndarray:
    """theta in [0, pi] with theta - sin(theta) cos(theta) = area (area in [0, pi]): the cap
    {x <= -cos(theta)} of the unit disk has that area (`_cap_theta`)."""
    flat = np.ascontiguousarray(area, dtype=np.float64).ravel()
    out = np.empty_like(flat)
    _cap_kernel(flat, _CAP_TABLE, _CAP_SCALE, out)
    return out.reshape(np.shape(area))


def _concentric_disk(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shirley-Chiu area-preserving map of the unit square onto the unit disk."""
    a, b = np.broadcast_arrays(np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64))
    x, y = np.empty(a.size), np.empty(a.size)
    _concentric_kernel(np.ascontiguousarray(a).ravel(), np.ascontiguousarray(b).ravel(), x, y)
    return x.reshape(a.shape), y.reshape(a.shape)


def _lens_sample(a: np.ndarray, r: np.ndarray, b: np.ndarray, s: np.ndarray,
                 square: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points uniform in the lens (intersection) of disks (a (P, 2), r (P,)) and (b, s): m
    points per lens (P, m, 2) from points `square` (P, m, 2) of the unit square, and the lens's
    area (P,) (0 when empty; the smaller disk when one holds the other).

    Along the line of centres (a at 0, b at d) the lens is B's cap x <= X then A's cap x >= X,
    X the common chord. The first square coordinate is the area fraction from B's end, so x
    solves a cap-area equation (_cap_angle); the second places y uniformly across the lens at
    x. The map is monotone in both, so strata of the square stay compact in the lens. One disk
    inside the other: the smaller one, by the concentric map."""
    def c64(x: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(x, dtype=np.float64)

    square = c64(square)
    points = np.empty(square.shape)
    area = np.empty(len(r))
    _lens_kernel(c64(a), c64(r), c64(b), c64(s), square, _CAP_TABLE, _CAP_SCALE, points, area)
    return points, area


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
    display: np.ndarray  # (C, H, W) linear radiance, C-contiguous
    centre: tuple[float, float]  # pupil centre c
    q: float  # 1 / focus distance
    s_bottom: float  # pupil to the bottom face (the pupil's part z)
    hull: np.ndarray  # outline's edges a b, counter-clockwise, as (a, b - a) (M, 4)
    slack: np.ndarray  # (M,) each outline edge's slack for a ray on it (OUTLINE_RTOL)
    geo: np.ndarray  # SHADE_FIELDS
    offsets: np.ndarray  # stripe centres (px) per channel, empty without stripes
    blocked: Occluder
    #: (C, H + 1, S W + 1) summed-area table of what the display emits (`_summed_area`), S
    #: columns per pixel; None where the light of a view box is not a rectangle's mean (cover
    #: glass, falloff).
    sat: np.ndarray | None
    lit: np.ndarray | None  # (H + 1, S W + 1) summed-area table of the sub-pixels that emit
    columns_per_pixel: int

    @classmethod
    def of(cls, mesh: PlateMesh, scene: Scene, display: np.ndarray,
           position: int) -> _Rays:
        eye, disp = scene.eye, scene.display
        q = 0.0 if eye.focus_mm is None else 1.0 / eye.focus_mm
        hull = _outline_hull(mesh.vertices[:, :2])
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
            sat, lit, columns = _summed_area(np.asarray(display, dtype=np.float64), offsets_px)
        return cls(scene, np.ascontiguousarray(display, dtype=np.float64), centre, q, s_bottom,
                   np.ascontiguousarray(np.concatenate([hull, edge], axis=1)),
                   tol * np.hypot(edge[:, 0], edge[:, 1]), geo, offsets_px, _occluder(mesh), sat,
                   lit, columns)

    def cast(self, rays: np.ndarray) -> np.ndarray:
        """blocked (N,) bool of rays (N, 4): pupil point u (x, y) and direction per unit depth
        (dx, dy), from the pupil (z = s_bottom) toward -z."""
        cx, cy = self.centre
        origin = np.stack([cx + rays[:, 0], cy + rays[:, 1], np.full(len(rays), self.s_bottom)],
                          axis=1)
        direction = np.stack([rays[:, 2], rays[:, 3], -np.ones(len(rays))], axis=1)
        return self.blocked(origin, direction)


def _summed_area(display: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """What the display emits as a summed-area table (C, H + 1, S W + 1), where it emits as
    one (H + 1, S W + 1), and S, its sub-columns per pixel.

    sat[c, i, j]: the light of channel c over rows < i and sub-columns < j (pixel units). The
    display is piecewise constant, so its integral F(row, col) over [0, row] x [0, col] is
    bilinear in each cell: bilinear interpolation of sat is exact (`_sat_grid`). Without
    stripes S = 1; with stripes (offsets: the S channels' stripe centres, px from the pixel
    centre, each stripe 1 / S of the pixel) channel c lights only its stripe's sub-column, at S
    times the value, as `_shade_ray` does per ray. lit: the sub-pixels where some channel is not
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


def _box_table(sat: np.ndarray, box_rows: float, box_cols: float
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


def _shade(rays: _Rays, v_x: np.ndarray, v_y: np.ndarray, u_x: np.ndarray, u_y: np.ndarray,
           live: np.ndarray) -> tuple[np.ndarray, int]:
    """Radiance x pass (C, N) of the rays (v, u), flat (N,) arrays, of which only `live` ones
    count (others give 0); also how many rays were cast against the mesh."""
    values = np.zeros((rays.display.shape[0], v_x.size), dtype=np.float64)
    cast = np.zeros(v_x.size, dtype=bool)
    _shade_kernel(v_x, v_y, u_x, u_y, np.ascontiguousarray(live), rays.geo, rays.hull,
                  rays.slack, rays.display, rays.offsets, values, cast)
    index = np.flatnonzero(cast)  # only rays that could carry light are cast
    q = rays.q
    ux, uy = u_x[index], u_y[index]
    blocked = rays.cast(np.stack([ux, uy, v_x[index] - q * ux, v_y[index] - q * uy], axis=1))
    values[:, index[blocked]] = 0.0
    return values, int(index.size)


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


@dataclass(frozen=True)
class _Disks:
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
    def of(cls, loops: HoleLoops, mesh: PlateMesh) -> _Disks:
        top = loops.top_centroid_mm
        radius = loops.top_circum_radius_mm * (1 + DISK_MARGIN)
        bottom_radius = loops.bottom_circum_radius_mm * (1 + DISK_MARGIN)
        z_low, z_high = float(mesh.vertices[:, 2].min()), float(mesh.vertices[:, 2].max())
        axis_high = np.ascontiguousarray(top, dtype=np.float64)
        axis_low = np.ascontiguousarray(
            loops.bottom_centroid_mm + loops.axes * z_low, dtype=np.float64)
        rho = _clear_radius(mesh, axis_low, axis_high, (z_low, z_high),
                            np.maximum(radius, bottom_radius))
        margin = CLEAR_RTOL * float(np.ptp(mesh.vertices, axis=0).max())
        usable = rho - margin
        return cls(top, radius, loops.bottom_centroid_mm, bottom_radius,
                   _disk_neighbours(top, radius), np.argsort(top[:, 1], kind="stable"),
                   axis_low, axis_high, np.where(usable > 0, usable**2, -1.0), (z_low, z_high))


def _clear_radius(mesh: PlateMesh, axis_low: np.ndarray, axis_high: np.ndarray,
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
    _clear_kernel(np.ascontiguousarray(mesh.vertices, dtype=np.float64),
                  np.ascontiguousarray(mesh.faces, dtype=np.int64), axis_low, axis_high,
                  z_range[0], z_range[1], box, np.ascontiguousarray(origin, dtype=np.float64),
                  cell, shape, start, np.ascontiguousarray(hole[order]), clear2)
    return np.sqrt(clear2)


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
    pixel, hole = pixel[near], hole[near]
    # Hole by hole, in bands of holes one hole wide across the plate, each band left to right,
    # and each hole's pixels in order: the rays of neighbouring pairs land near each other on
    # the display, so the kernels find its tables in cache.
    band_mm = 2 * float(disks.top_radius.max(initial=0.0)) or 1.0
    x, y = disks.top[hole, 0], disks.top[hole, 1]
    order = np.lexsort((pixel, x, np.floor(y / band_mm)))
    return pixel[order], hole[order]


class _Chunk(NamedTuple):
    """A chunk of a view row's (view pixel, hole) pairs (`_trace_holes`)."""

    row: int
    row_pixel: np.ndarray  # (Q,) the view pixel (column) of each of the row's pairs
    row_sums: np.ndarray  # (Q, R, C) the row's pair sums
    pixel: np.ndarray  # (P,) the chunk's pairs: view pixel
    hole: np.ndarray  # (P,) and hole
    sums: np.ndarray  # (P, R, C) the chunk's part of row_sums
    ends_row: bool


def _trace_holes(rays: _Rays, loops: HoleLoops, mesh: PlateMesh, samples: int | None,
                 rng: np.random.Generator, estimates: np.ndarray, max_rays: int,
                 progress: Callable[[int, int], None] | None) -> tuple[int, int, int]:
    """Hole sampling, by chords where the display allows (module docstring): adds to estimates
    (C, pixels, REPLICATES); returns the rays and chords decided (against the mesh, by a clear
    cylinder or by Embree), the (view pixel, hole) pairs and the samples per pair and replicate
    (samples None: the budget's, `_budget`)."""
    eye = rays.scene.eye
    centre = np.array(rays.centre, dtype=np.float64)
    q, thickness = rays.q, loops.thickness_mm
    s_top = rays.s_bottom - thickness  # the mesh's own top face
    beta = 1 - s_top * q
    scale = (1 - rays.s_bottom * q) / beta  # top-face offsets to bottom-face offsets
    pupil_radius = eye.pupil_mm / 2
    foot = beta * pupil_radius  # the pupil's footprint on the top face's plane
    disks = _Disks.of(loops, mesh)
    vx, vy = eye.view_directions()
    step_x, step_y = eye.view_step
    nx, ny = eye.view_pixels
    half = (0.5 * s_top * step_x, 0.5 * s_top * step_y)
    row_pairs = [_row_pairs(disks, centre[0] + s_top * vx, centre[1] + s_top * vy[j], half,
                            foot) for j in range(ny)]
    box_cols, box_rows = _landing_box(rays, s_top, beta)
    chords = rays.sat is not None and rays.lit is not None and box_cols > 0
    if samples is None:
        samples = _budget(sum(pixel.size for pixel, _ in row_pairs), chords)
    n = math.ceil(samples / REPLICATES)
    corner, size = _strata(n)
    corner, size = np.ascontiguousarray(corner), np.ascontiguousarray(size)
    grow = 0.5 * thickness * math.hypot(step_x, step_y) / beta  # bottom-plane slack
    pair_geo = np.array([step_x, step_y, s_top, beta, scale, thickness, grow, pupil_radius**2,
                         n * np.pi * foot**2, *disks.z_range], dtype=np.float64)
    box, grid = np.zeros((1, 1, 2, 1)), np.zeros(4)
    if chords:
        assert rays.sat is not None
        box, grid = _box_table(rays.sat, box_rows, box_cols)
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
                _chords_kernel(draw, chunk.pixel, chunk.hole, vx, float(vy[chunk.row]), top,
                               disks.top_radius, bottom, disks.bottom_radius, disks.neighbours,
                               disks.axis_low, disks.axis_high, disks.clear2, chord_geo,
                               rays.geo, rays.hull, rays.slack, rays.display, rays.offsets,
                               rays.sat, box, grid, rays.lit, hole_inside, _CAP_TABLE,
                               _CAP_SCALE, chunk.sums,
                               to_cast, ray, contrib, counts)
            else:
                _holes_kernel(draw, chunk.pixel, chunk.hole, vx, float(vy[chunk.row]), corner,
                              size, top, disks.top_radius, bottom, disks.bottom_radius,
                              disks.neighbours, disks.axis_low, disks.axis_high, disks.clear2,
                              pair_geo, rays.geo, rays.hull, rays.slack, rays.display,
                              rays.offsets, _CAP_TABLE, _CAP_SCALE, chunk.sums, to_cast, ray,
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


def _landing_box(rays: _Rays, s_top: float, beta: float) -> tuple[float, float]:
    """(sub-columns, rows) across the display rectangle that the rays from one top-face point
    reach over a view pixel's box of directions: the landing point moves by H v, H = s_display -
    s_top (1 - s_display q) / beta. (0, 0) where chord sampling does not apply: a display whose
    light is not a rectangle's mean (cover glass, falloff: `_Rays.sat` None) or a rectangle
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


def _budget(pairs: int, chords: bool) -> int:
    """Samples per (view pixel, hole) pair: about CHORD_BUDGET chords (chord sampling) or
    RAY_BUDGET rays (hole sampling) over the view's `pairs`, at least LEAST_CHORDS or
    DEFAULT_SAMPLES["holes"], at most MOST_SAMPLES: a sparse plate, with few holes behind each
    view pixel, gets more per pair."""
    budget, least = (CHORD_BUDGET, LEAST_CHORDS) if chords else (RAY_BUDGET,
                                                                DEFAULT_SAMPLES["holes"])
    return int(min(MOST_SAMPLES, max(least, budget // max(pairs, 1))))


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
    position: which of the eye's positions_mm. samples_per_pixel: chords (or rays) per (view
    pixel, hole) pair for sampling "holes", rays per view pixel for "pupil" (rounded up to a
    multiple of REPLICATES); None: "holes" spends a budget (CHORD_BUDGET chords or RAY_BUDGET
    rays), "pupil" DEFAULT_SAMPLES["pupil"]. seed: random seed. max_rays: rays per chunk
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
    display = _check_inputs(mesh, scene, display, position,
                            2 * REPLICATES if samples_per_pixel is None else samples_per_pixel,
                            max_rays, sampling)
    eye = scene.eye
    rays = _Rays.of(mesh, scene, display, position)
    nx, ny = eye.view_pixels
    channels = display.shape[0]
    rng = np.random.default_rng(seed)
    estimates = np.zeros((channels, nx * ny, REPLICATES), dtype=np.float64)
    if loops is not None:
        cast, pairs, n = _trace_holes(rays, loops, mesh, samples_per_pixel, rng, estimates,
                                      max_rays, progress)
    else:
        samples = DEFAULT_SAMPLES["pupil"] if samples_per_pixel is None else samples_per_pixel
        n = math.ceil(samples / REPLICATES)
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
