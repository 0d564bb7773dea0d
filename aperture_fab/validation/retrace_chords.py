"""The mesh re-trace's chord kernel (aperture_fab.validation.retrace): where a view pixel's box
lands on the display, the light along each chord of a hole, read from summed-area tables."""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from aperture_fab.kernel_sources import check_inlined
from aperture_fab.validation import retrace_kernels, retrace_sampling
from aperture_fab.validation.retrace_kernels import PAIR_BLOCK, PAIR_FIELDS, shade_ray
from aperture_fab.validation.retrace_sampling import cap_theta, inline_jit, parallel_jit

#: The digest of retrace_kernels.py and retrace_sampling.py: this kernel inlines their
#: functions, and Numba's cache does not see a change there (`aperture_fab.kernel_sources`).
INLINED_DIGEST = "1d078ded6f5b5a47"
check_inlined(__name__, INLINED_DIGEST, retrace_kernels, retrace_sampling)

#: Random numbers per chord (chord sampling): its height in its stratum (1), the point of the
#: chord drawn where the chord is not integrated (1), its view direction in the box (2).
RANDOM_PER_CHORD = 4


MIN_SPAN_PX = 1e-3


#: Fields of the chord kernel's constants (`chords_kernel`): PAIR_FIELDS, then the landing
#: rectangle's size (sub-columns, rows) and the landing's sub-columns per mm of x_t.
CHORD_FIELDS = (*PAIR_FIELDS, "box_cols", "box_rows", "cols_per_mm")


@inline_jit
def _chord(cx, cy, radius2, y, lo, hi):
    """(lo, hi) cut to the chord at height y of the disk about (cx, cy) of squared radius
    radius2 (empty: hi <= lo)."""
    rest = radius2 - (y - cy) ** 2
    if not rest > 0:
        return lo, lo
    half = math.sqrt(rest)
    return max(lo, cx - half), min(hi, cx + half)


@inline_jit
def _inside_outline(x, y, hull, slack):
    """Whether the point (x, y) of the bottom face's plane is inside the outline (with slack)."""
    for e in range(hull.shape[0]):
        if hull[e, 2] * (y - hull[e, 1]) - hull[e, 3] * (x - hull[e, 0]) < -slack[e]:
            return False
    return True


@inline_jit
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


@inline_jit
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


@inline_jit
def _grid_cell(x, half, gap, count):
    """(m, t, length): the interval [p_m, p_m+1] of the box table's breakpoints p (`box_table`:
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


@inline_jit
def _box_row(box, grid, row):
    """(m, w): the box table's row breakpoint interval [p_m, p_m+1] holding `row` and where in
    it (0 to 1); m = -1 where no light lands (the row beyond the display's reach)."""
    m, tr, lr = _grid_cell(row, grid[0], grid[1], box.shape[0])
    if m >= box.shape[0] - 1:
        return -1, 0.0
    return m, tr / lr


@inline_jit
def _box_light(box, grid, m, wr, col, out, sign, integral):
    """Adds sign x, from the box table (`box_table`), to out (C,), at the row w of the way
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


@inline_jit
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


@inline_jit
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


@parallel_jit
def chords_kernel(draw, pixel, hole, vx, vy, top, top_r, bottom, bottom_r, neighbours,
                   axis_low, axis_high, clear2, chord_geo, geo, hull, slack, display, offsets,
                   sat, box, grid, lit, hole_inside, table, table_scale, sums, cast, rays,
                   contrib, counts):
    """Chord sampling of one chunk of (view pixel, hole) pairs of a view row (module docstring).

    draw (P, R n, RANDOM_PER_CHORD): the uniforms; chord_geo: CHORD_FIELDS; sat, lit: the
    display's summed-area tables (`summed_area`); box, grid: the view box's table
    (`box_table`); hole_inside (K,): whether every ray through a hole's lens crosses the
    bottom face's plane inside the outline; the rest as `holes_kernel`, whose outputs this writes
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
                    _, sin, cos = cap_theta((k + draw[p, j, 0]) / n * math.pi, table,
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
                    if not shade_ray(v_x, v_y, u_x, u_y, geo, hull, slack, display, offsets,
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
