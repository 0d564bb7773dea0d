"""The solid plate as a triangle mesh, built straight from the hole grid (linear in hole count).

Part coordinates: x right, y up (seen from the eye, +z), the bottom face at z = 0 faces the
display and the top face is at z = thickness. Cell (row i, col j) is centred at
x = (j - (nx - 1) / 2) px, y = ((ny - 1) / 2 - i) py. A hole's centre at height z is
centres_mm + (z - thickness / 2) * axes.

Convergent layouts (layout.converge_mm = (ex, ey, D), chief-ray holes): each face is tiled by
its own cell grid, the mid-plane grid scaled about E = (ex, ey) by 1 + t / 2D (bottom) and
1 - t / 2D (top) (HoleLayout.cell_edges_mm), so every hole stays centred in its cell at both
faces however far it is from the axis. The two faces' grids differ; they meet only through the
hole walls and the outline's side walls, which is all watertightness needs. The walls are
straight between the two faces' polygons, which is exact for an oblique circular cylinder: its
polygon vertices translate along the axis, and every z-section has the polygon's area, so the
volume stays outline area x t - sum(pi r^2 t).

Each cell is a tile whose four corners are grid vertices shared with its neighbours, so the mesh
is watertight by construction. A cell with a hole is the ring between its square and an n-gon;
each polygon edge is joined to the square corner that lies farthest along the edge's outward
normal. That corner always lies strictly beyond the edge's line when the polygon lies strictly
inside the square, so no triangle is inverted, whatever the hole's size, offset or tilt.
The topology depends only on n, so cells are built in numpy batches, one per segment count.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from aperture_fab.fabrication.layout import HoleLayout

__all__ = [
    "PlateMesh",
    "build_mesh",
    "outline_points_mm",
    "segment_count",
]

#: Segment counts are multiples of 4: with edges facing +-x and +-y, the polygon's extent along
#: the cell axes is its apothem, which is below r for an area-preserving polygon, so a hole whose
#: circle fits its cell also fits as a polygon.
SEGMENT_MULTIPLE = 4
#: Relative tolerance for calling a margin zero (outline equal to the cell grid).
MARGIN_RTOL = 1e-9


@dataclass(frozen=True)
class PlateMesh:
    """A closed triangle mesh in part coordinates.

    vertices: (V, 3) float64, mm.
    faces: (F, 3) int64, vertex indices; counter-clockwise seen from outside (outward normals).
    """

    vertices: np.ndarray
    faces: np.ndarray

    def __post_init__(self) -> None:
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3:
            raise ValueError(
                f"PlateMesh.vertices has shape {self.vertices.shape}; expected (V, 3)."
            )
        if self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise ValueError(f"PlateMesh.faces has shape {self.faces.shape}; expected (F, 3).")
        if self.vertices.dtype != np.float64 or self.faces.dtype != np.int64:
            raise TypeError(
                f"PlateMesh needs float64 vertices and int64 faces, got {self.vertices.dtype} "
                f"and {self.faces.dtype}."
            )
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= len(self.vertices)):
            raise ValueError(
                f"PlateMesh.faces index outside 0..{len(self.vertices) - 1}; faces must refer to "
                "existing vertices."
            )


def segment_count(
    radius_mm: np.ndarray, chord_tolerance_mm: float, segments_min: int, segments_max: int
) -> np.ndarray:
    """Polygon sides per hole, (K,) int64: the fewest multiple of 4 in [segments_min,
    segments_max] whose sagitta r (1 - cos(pi / n)) is at most chord_tolerance_mm (capped at
    segments_max, where the chord error may exceed the tolerance)."""
    if not (math.isfinite(chord_tolerance_mm) and chord_tolerance_mm > 0):
        raise ValueError(
            f"chord_tolerance_mm = {chord_tolerance_mm!r} must be > 0; give the largest allowed "
            "distance between a hole's circle and its polygon, e.g. 0.002 mm."
        )
    for name, value in (("segments_min", segments_min), ("segments_max", segments_max)):
        if not isinstance(value, int) or value < SEGMENT_MULTIPLE or value % SEGMENT_MULTIPLE:
            raise ValueError(
                f"{name} = {value!r} must be a multiple of {SEGMENT_MULTIPLE}, at least "
                f"{SEGMENT_MULTIPLE}, so polygon edges face the cell sides; e.g. 8 or 256."
            )
    if segments_max < segments_min:
        raise ValueError(
            f"segments_max = {segments_max} is below segments_min = {segments_min}; "
            "give segments_max >= segments_min."
        )
    radius = np.asarray(radius_mm, dtype=np.float64)
    half_angle = np.arccos(np.clip(1.0 - chord_tolerance_mm / radius, -1.0, 1.0))
    exact = np.pi / np.maximum(half_angle, np.finfo(np.float64).tiny)
    # The small slack keeps an exact quotient (e.g. 16.000000000001) from rounding up a step.
    n = np.ceil(exact / SEGMENT_MULTIPLE - 1e-9).astype(np.int64) * SEGMENT_MULTIPLE
    return np.clip(n, segments_min, segments_max)


def _polygon_radius_factor(n: int) -> float:
    """r_poly / r for a regular n-gon with the area of its circle."""
    return math.sqrt(2 * math.pi / (n * math.sin(2 * math.pi / n)))


def _hole_polygons(layout: HoleLayout, index: np.ndarray, n: int) -> np.ndarray:
    """(K, 2, n, 2) float64 mm: the n-gons of holes `index` at the bottom and top faces,
    counter-clockwise, vertex k at angle (2k + 1) pi / n, with the area of their circles."""
    angle = (2 * np.arange(n) + 1) * np.pi / n
    unit = np.stack([np.cos(angle), np.sin(angle)], axis=1)  # (n, 2)
    r_poly = layout.radii_mm[index] * _polygon_radius_factor(n)
    half_shift = 0.5 * layout.thickness_mm * layout.axes[index]
    centres = np.stack(
        [layout.centres_mm[index] - half_shift, layout.centres_mm[index] + half_shift], axis=1
    )  # (K, 2 faces, 2)
    return centres[:, :, None, :] + r_poly[:, None, None, None] * unit


def _ring_template(n: int) -> np.ndarray:
    """Top-face triangles of a hole cell, (n + 4, 3) int64, counter-clockwise seen from +z.

    Local indices: 0..n-1 the polygon (vertex k at angle (2k + 1) pi / n), n..n+3 the square's
    corners TR, TL, BL, BR. Edge k (vertex k to k + 1) has its outward normal at 2 pi (k + 1) / n
    and joins the corner of that normal's quadrant; one bridge triangle per square side joins
    the polygon vertex where the quadrant changes.
    """
    m = n // SEGMENT_MULTIPLE
    k = np.arange(n)
    quadrant = ((k + 1) // m) % 4
    fan = np.stack([(k + 1) % n, k, n + quadrant], axis=1)
    side = np.arange(4)
    bridge = np.stack([n + side, n + (side + 1) % 4, ((side + 1) * m - 1) % n], axis=1)
    return np.concatenate([fan, bridge]).astype(np.int64)


def _wall_template(n: int) -> np.ndarray:
    """Hole wall triangles, (2n, 3) int64, facing the hole axis; 0..n-1 bottom, n..2n-1 top."""
    k = np.arange(n)
    k1 = (k + 1) % n
    first = np.stack([k, n + k, k1], axis=1)
    second = np.stack([k1, n + k, n + k1], axis=1)
    return np.concatenate([first, second]).astype(np.int64)


def _grid_perimeter(nx: int, ny: int) -> np.ndarray:
    """Grid corner indices around the cell grid, counter-clockwise from its top-right corner:
    nx along the top, ny down the left, nx along the bottom, ny up the right side."""
    width = nx + 1
    top = np.arange(nx, 0, -1)
    left = np.arange(ny) * width
    bottom = ny * width + np.arange(nx)
    right = np.arange(ny, 0, -1) * width + nx
    return np.concatenate([top, left, bottom, right]).astype(np.int64)


def _frame_template(perimeter: np.ndarray, outer: np.ndarray, nx: int, ny: int) -> np.ndarray:
    """Top-face triangles of the margin frame, counter-clockwise seen from +z.

    outer: the outline's vertex indices, counter-clockwise from its top-right corner (4, or 5
    with the top-left corner cut). As for holes, each grid edge joins the outline corner beyond
    it (top edges the top-left, left edges the bottom-left, ...) and one triangle per outline
    side joins the grid corner where the choice changes.
    """
    tr, tl_first, tl_last, bl, br = outer[0], outer[1], outer[-3], outer[-2], outer[-1]
    side_corner = np.repeat(np.array([tl_first, bl, br, tr]), [nx, ny, nx, ny])
    fan = np.stack([np.roll(perimeter, -1), perimeter, side_corner], axis=1)
    grid_tr, grid_tl, grid_bl, grid_br = perimeter[[0, nx, nx + ny, 2 * nx + ny]]
    bridges = [[tr, tl_first, grid_tr]]
    if tl_first != tl_last:
        bridges.append([tl_first, tl_last, grid_tl])
    bridges += [[tl_last, bl, grid_tl], [bl, br, grid_bl], [br, tr, grid_br]]
    return np.concatenate([fan, np.array(bridges)]).astype(np.int64)


def _side_walls(bottom: np.ndarray, top: np.ndarray) -> np.ndarray:
    """Outer wall triangles for a counter-clockwise loop of vertex indices, (2m, 3) int64."""
    b1 = np.roll(bottom, -1)
    t1 = np.roll(top, -1)
    return np.concatenate(
        [np.stack([bottom, b1, t1], axis=1), np.stack([bottom, t1, top], axis=1)]
    ).astype(np.int64)


def outline_points_mm(layout: HoleLayout, corner_cut_mm: float) -> list[tuple[float, float]]:
    """The outline as a counter-clockwise loop from the top-right corner, with the optional
    top-left chamfer (as build_mesh cuts it)."""
    half_w, half_h = layout.outline_mm[0] / 2, layout.outline_mm[1] / 2
    if not (math.isfinite(corner_cut_mm) and 0 <= corner_cut_mm < min(2 * half_w, 2 * half_h)):
        raise ValueError(
            f"corner_cut_mm = {corner_cut_mm!r} must be >= 0 and below the outline's shorter "
            "side; use the value given to build_mesh."
        )
    points = [(half_w, half_h), (-half_w, half_h), (-half_w, -half_h), (half_w, -half_h)]
    if corner_cut_mm > 0:
        points[1:2] = [(-half_w + corner_cut_mm, half_h), (-half_w, half_h - corner_cut_mm)]
    return points


def _face_edges(layout: HoleLayout) -> list[tuple[np.ndarray, np.ndarray]]:
    """Cell edges (xs, ys) of the bottom face, then the top face (HoleLayout.cell_edges_mm)."""
    half = layout.thickness_mm / 2
    return [layout.cell_edges_mm(-half), layout.cell_edges_mm(half)]


def _check_layout(layout: HoleLayout, min_web_mm: float, corner_cut_mm: float) -> bool:
    """Validate grid, cells, outline and corner cut; return whether there is a margin frame."""
    nx, ny = layout.grid
    px, py = layout.pitch_mm
    width, height = layout.outline_mm
    if not (math.isfinite(min_web_mm) and min_web_mm >= 0):
        raise ValueError(f"min_web_mm = {min_web_mm!r} must be >= 0 (mm between holes).")
    if not (math.isfinite(corner_cut_mm) and corner_cut_mm >= 0):
        raise ValueError(f"corner_cut_mm = {corner_cut_mm!r} must be >= 0 (0: square corner).")
    rows, cols = layout.cells[:, 0], layout.cells[:, 1]
    bad = np.flatnonzero((rows < 0) | (rows >= ny) | (cols < 0) | (cols >= nx))
    if bad.size:
        cell = tuple(int(c) for c in layout.cells[bad[0]])
        raise ValueError(
            f"HoleLayout.cells has cell {cell} outside the grid of {ny} rows x {nx} columns."
        )
    counts = np.bincount(rows * nx + cols, minlength=nx * ny)
    if np.any(counts > 1):
        twice = int(np.argmax(counts > 1))
        raise ValueError(
            f"HoleLayout.cells lists cell {(twice // nx, twice % nx)} more than once; "
            "a cell has at most one hole."
        )
    # Margins (left, right, top, bottom) between each face's cell grid and the outline.
    margins = np.array([
        [xs[0] + width / 2, width / 2 - xs[-1], height / 2 - ys[0], ys[-1] + height / 2]
        for xs, ys in _face_edges(layout)
    ])
    tol = MARGIN_RTOL * max(width, height)
    if layout.converge_mm is not None and not np.all(margins > tol):
        face = ("bottom", "top")[int(np.argmin(margins.min(axis=1)))]
        raise ValueError(
            f"HoleLayout.outline_mm = {layout.outline_mm} does not contain the {face} face's "
            f"scaled cell grid with a margin (smallest margin {margins.min():.4g} mm; needed: > 0 "
            f"on every side of both faces, for converge_mm = {layout.converge_mm}). Widen the "
            "outline's margin."
        )
    if np.any(margins < -tol):
        raise ValueError(
            f"HoleLayout.outline_mm = {layout.outline_mm} is smaller than the cell grid "
            f"({nx * px:g} x {ny * py:g} mm); the outline must contain every cell."
        )
    zero = np.abs(margins) <= tol
    if np.any(zero) and not np.all(zero):
        raise ValueError(
            f"HoleLayout.outline_mm = {layout.outline_mm} leaves a margin on one axis only "
            f"(margins {margins[0, 0]:g}, {margins[0, 2]:g} mm); give a margin on both axes or "
            "neither."
        )
    frame = not np.all(zero)
    if corner_cut_mm > 0:
        # The chamfer must pass outside each face's top-left grid corner.
        top_left = float(np.min(margins[:, 0] + margins[:, 2]))
        limit = min(top_left, width, height) if frame else 0.0
        if not corner_cut_mm < limit:
            raise ValueError(
                f"corner_cut_mm = {corner_cut_mm:g} must be below {limit:g} mm (the margin "
                "frame's width at the top-left corner); widen the margin or cut less."
            )
    return frame


def _check_web(
    layout: HoleLayout, index: np.ndarray, polygon_xy: np.ndarray, min_web_mm: float
) -> None:
    """Raise ValueError naming the first cell whose polygon (either face) leaves less than
    min_web_mm / 2 to a side of its cell (so neighbouring holes keep min_web_mm between them),
    or touches a side when min_web_mm is 0.

    polygon_xy: (K, 2, n, 2) polygon vertices (bottom, top) of the holes in `index`.
    Each face's cells are that face's grid (scaled for convergent layouts), with sides taken
    from the same edges build_mesh puts the grid corner vertices on.
    """
    rows, cols = layout.cells[index, 0], layout.cells[index, 1]
    gaps = []
    for face, (xs, ys) in enumerate(_face_edges(layout)):
        x, y = polygon_xy[:, face, :, 0], polygon_xy[:, face, :, 1]
        gaps.append(np.stack([
            x.min(axis=1) - xs[cols], xs[cols + 1] - x.max(axis=1),
            y.min(axis=1) - ys[rows + 1], ys[rows] - y.max(axis=1),
        ]).min(axis=0))
    gap = np.minimum(gaps[0], gaps[1])
    bad = (gap < min_web_mm / 2) | (gap <= 0)
    if np.any(bad):
        first = int(np.argmax(bad))
        cell = (int(rows[first]), int(cols[first]))
        raise ValueError(
            f"Hole in cell {cell} (radius {layout.radii_mm[index[first]]:g} mm) comes within "
            f"{gap[first]:g} mm of its cell's side as a polygon at one face; allowed: at least "
            f"half the {min_web_mm:g} mm web, and more than 0. Make the hole smaller, its tilt "
            "smaller, or the pitch larger."
        )


def build_mesh(
    layout: HoleLayout,
    chord_tolerance_mm: float,
    segments_min: int = 8,
    segments_max: int = 256,
    min_web_mm: float = 0.0,
    corner_cut_mm: float = 0.0,
) -> PlateMesh:
    """The plate with its holes as one closed mesh, in part coordinates (module docstring).

    chord_tolerance_mm: largest sagitta between a hole's circle and its polygon (segment_count).
        Each polygon has the area of its circle, so volume and open area are exact.
    min_web_mm: material required between neighbouring holes; each polygon keeps half of it
        from its cell's sides at both faces (ValueError naming the cell otherwise). For a
        convergent layout a face's cells are its scaled grid (HoleLayout.cell_edges_mm).
    corner_cut_mm: legs of a 45-degree chamfer cut off the outline's top-left corner (-x, +y seen
        from the eye) so the plate can only be placed one way round; 0 for none. Needs a margin.
    """
    frame = _check_layout(layout, min_web_mm, corner_cut_mm)
    nx, ny = layout.grid
    thickness = layout.thickness_mm
    n_of_hole = segment_count(layout.radii_mm, chord_tolerance_mm, segments_min, segments_max)

    # Grid corner vertices of each face: index b * (nx + 1) + a for corner column a, corner
    # row b (top = 0); the two faces' grids differ for convergent layouts.
    grid_count = (nx + 1) * (ny + 1)
    bottom_xy, top_xy = (
        np.stack([g.ravel() for g in np.meshgrid(xs, ys)], axis=1) for xs, ys in _face_edges(layout)
    )

    # Outline loop, counter-clockwise from the top-right corner (the frame's outer boundary).
    if frame:
        outline_xy = np.array(outline_points_mm(layout, corner_cut_mm), dtype=np.float64)
    else:
        outline_xy = np.zeros((0, 2))

    layer_count = grid_count + len(outline_xy)  # grid and outline vertices on one face
    blocks_xy = [bottom_xy, outline_xy, top_xy, outline_xy]  # bottom layer, then top layer
    blocks_z = [np.zeros(layer_count), np.full(layer_count, thickness)]
    offset = 2 * layer_count
    groups: list[tuple[int, np.ndarray, int]] = []  # (n, hole indices, first vertex)
    for n in np.unique(n_of_hole).tolist():
        index = np.flatnonzero(n_of_hole == n)
        polygon = _hole_polygons(layout, index, n)
        _check_web(layout, index, polygon, min_web_mm)
        groups.append((n, index, offset))
        blocks_xy.append(polygon.reshape(-1, 2))
        face_z = np.repeat(np.array([0.0, thickness]), n)  # bottom polygon, then top polygon
        blocks_z.append(np.tile(face_z, len(index)))
        offset += polygon.shape[0] * 2 * n

    xy = np.concatenate(blocks_xy)
    z = np.concatenate(blocks_z)
    faces: list[np.ndarray] = []
    has_hole = np.zeros(ny * nx, dtype=bool)
    has_hole[layout.cells[:, 0] * nx + layout.cells[:, 1]] = True

    def cell_corners(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """(K, 4) grid indices of the cells' TR, TL, BL, BR corners (bottom layer)."""
        tl = rows * (nx + 1) + cols
        return np.stack([tl + 1, tl, tl + nx + 1, tl + nx + 2], axis=1)

    # Closed cells: two triangles per face.
    closed = np.flatnonzero(~has_hole)
    corners = cell_corners(closed // nx, closed % nx)
    top_quad = np.array([[0, 1, 2], [0, 2, 3]])
    faces.append((corners[:, top_quad] + layer_count).reshape(-1, 3))
    faces.append(corners[:, top_quad[:, ::-1]].reshape(-1, 3))

    # Hole cells, one batch per segment count.
    for n, index, first in groups:
        k_holes = len(index)
        corners = cell_corners(layout.cells[index, 0], layout.cells[index, 1])
        polygon_ids = (first + np.arange(k_holes * 2 * n)).reshape(k_holes, 2, n)
        bottom_table = np.concatenate([polygon_ids[:, 0], corners], axis=1)
        top_table = np.concatenate([polygon_ids[:, 1], corners + layer_count], axis=1)
        ring = _ring_template(n)
        faces.append(top_table[:, ring].reshape(-1, 3))
        faces.append(bottom_table[:, ring[:, ::-1]].reshape(-1, 3))
        wall_table = polygon_ids.reshape(k_holes, 2 * n)
        faces.append(wall_table[:, _wall_template(n)].reshape(-1, 3))

    perimeter = _grid_perimeter(nx, ny)
    if frame:
        outer = grid_count + np.arange(len(outline_xy))
        frame_top = _frame_template(perimeter, outer, nx, ny)
        faces.append(frame_top + layer_count)
        faces.append(frame_top[:, ::-1])
        loop = outer
    else:
        loop = perimeter
    faces.append(_side_walls(loop, loop + layer_count))

    vertices = np.column_stack([xy, z])
    return PlateMesh(vertices=vertices, faces=np.concatenate(faces).astype(np.int64))


