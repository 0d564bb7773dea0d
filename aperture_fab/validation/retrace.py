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
edges; tabulated at those breakpoints with its integral J along a row (`box_table`, from the
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
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from aperture_fab.fabrication.mesh import PlateMesh
from aperture_fab.fabrication.mesh_holes import mesh_hole_loops
from aperture_fab.optics.scene import Scene
from aperture_fab.validation.retrace_holes import trace_holes
from aperture_fab.validation.retrace_kernels import (
    RANDOM_PER_SAMPLE,
)
from aperture_fab.validation.retrace_rays import Rays, shade
from aperture_fab.validation.retrace_sampling import (
    DEFAULT_SAMPLES,
    REPLICATES,
    SAMPLINGS,
    Sampling,
    concentric_disk,
    strata,
)

__all__ = ["DEFAULT_SAMPLES", "REPLICATES", "SAMPLINGS", "Sampling", "TracedView",
           "trace_mesh_view"]


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


def _trace_pupil(rays: Rays, n: int, rng: np.random.Generator, estimates: np.ndarray,
                 max_rays: int, progress: Callable[[int, int], None] | None) -> int:
    """Pupil sampling (module docstring): fills estimates (C, pixels, REPLICATES); returns the
    rays cast."""
    eye = rays.scene.eye
    corner, size = strata(n)
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
        u_x, u_y = concentric_disk(square[..., 0], square[..., 1])
        values, count = shade(rays, v_x.ravel(), v_y.ravel(), pupil_radius * u_x.ravel(),
                               pupil_radius * u_y.ravel(), np.ones(v_x.size, dtype=bool))
        cast += count
        estimates[:, index] = values.reshape(-1, *shape).mean(axis=-1)
        if progress is not None:
            progress(int(index[-1]) + 1, total)
    return cast


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
    rays = Rays.of(mesh, scene, display, position)
    nx, ny = eye.view_pixels
    channels = display.shape[0]
    rng = np.random.default_rng(seed)
    estimates = np.zeros((channels, nx * ny, REPLICATES), dtype=np.float64)
    if loops is not None:
        cast, pairs, n = trace_holes(rays, loops, mesh, samples_per_pixel, rng, estimates,
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
