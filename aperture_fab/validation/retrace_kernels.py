"""The mesh re-trace's ray kernels (aperture_fab.validation.retrace): rays sampled per (view
pixel, hole) pair and shaded from the display, and the wall-clearance test of a hole."""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from aperture_fab.kernel_sources import check_inlined
from aperture_fab.validation import retrace_sampling
from aperture_fab.validation.retrace_sampling import (
    fast_jit,
    inline_jit,
    lens_point,
    lens_setup,
    parallel_jit,
)

#: retrace_sampling.py's digest: these kernels inline its functions, and Numba's cache does not
#: see a change there (`aperture_fab.kernel_sources`).
INLINED_DIGEST = "eb907acde1380ec8"
check_inlined(__name__, INLINED_DIGEST, retrace_sampling)

#: Random numbers per sample: view box (2), pupil or lens square (2), permutation key (1).
#: Drawn as one array per chunk in a fixed order, so the result does not depend on chunk size.
RANDOM_PER_SAMPLE = 5


#: Relative slack (of the outline's size) for a ray crossing exactly on the outline's edge.
OUTLINE_RTOL = 1e-9


#: Pairs per task of the parallel hole kernel, rays per task of the shading kernel.
PAIR_BLOCK = 256


RAY_BLOCK = 4096


#: Fields of the shading geometry array (`retrace_rays.Rays.of`).
SHADE_FIELDS = ("cx", "cy", "q", "s_bottom", "s_display", "half_width", "half_height", "pixel_x",
                "pixel_y", "cover_glass", "glass_index_squared", "emission_power")


#: Fields of the hole kernel's per-row constants (`retrace_holes.trace_holes`).
PAIR_FIELDS = ("step_x", "step_y", "s_top", "beta", "scale", "thickness", "grow", "pupil_r2",
               "lens_norm", "z_low", "z_high")


@inline_jit
def shade_ray(vx, vy, ux, uy, geo, hull, slack, display, offsets, out):
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


@parallel_jit
def shade_kernel(v_x, v_y, u_x, u_y, live, geo, hull, slack, display, offsets, values, cast):
    """values (C, N): the radiance of each live ray that could carry light (`shade_ray`), else
    0; cast (N,) bool: those rays (still to be cast against the mesh)."""
    n = v_x.size
    for block in prange((n + RAY_BLOCK - 1) // RAY_BLOCK):
        radiance = np.empty(display.shape[0])
        for i in range(block * RAY_BLOCK, min(n, (block + 1) * RAY_BLOCK)):
            if live[i] and shade_ray(v_x[i], v_y[i], u_x[i], u_y[i], geo, hull, slack,
                                      display, offsets, radiance):
                cast[i] = True
                for c in range(radiance.size):
                    values[c, i] = radiance[c]


@parallel_jit
def holes_kernel(draw, pixel, hole, vx, vy, corner, size, top, top_r, bottom, bottom_r,
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
            kind, ux, uy, d, area_b, area = lens_setup(ax, ay, r, bx, by, s)
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
                    x_t, y_t = lens_point(kind, ax, ay, r, bx, by, s, ux, uy, d, area_b, area,
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
                    if not shade_ray(v_x, v_y, u_x, u_y, geo, hull, slack, display, offsets,
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


@fast_jit
def _segment_distance2(ax, ay, bx, by):
    """Squared distance from the origin to the segment a b."""
    ex = bx - ax
    ey = by - ay
    length2 = ex * ex + ey * ey
    t = 0.0 if length2 == 0 else min(max(-(ax * ex + ay * ey) / length2, 0.0), 1.0)
    px = ax + t * ex
    py = ay + t * ey
    return px * px + py * py


@fast_jit
def clear_kernel(vertices, faces, axis_low, axis_high, z_low, z_high, box, grid_origin, cell,
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
