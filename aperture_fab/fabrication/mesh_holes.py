"""The holes of a plate mesh, read from the mesh alone: boundary loops of its two flat faces.

A plate (aperture_fab.fabrication.mesh, part coordinates) has a flat bottom face at z = 0 and a flat
top face at z = thickness (the largest z); the eye looks at the top face from +z. Each face's
triangles form a region whose boundary edges (edges used by one triangle of that face) make closed
loops: the outer outline, the loop of largest area, and one loop per hole. The hole walls join each
hole's bottom loop to its top loop; they are matched through the wall triangles (mesh connectivity),
not by position, so a hole of any tilt is matched and a missing wall is reported.

Per loop: the polygon's area A and area centroid (shoelace sums over the loop's directed edges,
about the loop's vertex mean so float32 coordinates far from the origin lose nothing), the
area-equivalent radius sqrt(|A| / pi) and the circumscribed radius (largest vertex distance from
the centroid). build_mesh's polygons have their circle's area, so the area radius is the drawn
radius, and an oblique cylinder's centres at the two faces give its axis.

hole_layout_from_mesh turns the loops back into a HoleLayout (aperture_fab.fabrication.layout): a
hole's centre is the mean of its two loop centroids (the axis at mid-thickness), its cell is the
mid-plane cell that centre lies in (HoleLayout.cell_edges_mm(0), the same grid for straight and
convergent layouts), its axis (top - bottom) / thickness. """

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from aperture_fab.fabrication.layout import HoleLayout
from aperture_fab.fabrication.mesh import PlateMesh

__all__ = ["HoleLoops", "mesh_hole_loops", "hole_layout_from_mesh"]

#: A vertex lies on a flat face when its z is within this share of the thickness of the face.
FACE_RTOL = 1e-6
#: How far (per mm of z) measured axes may differ from a convergent layout's (E - c) / D: the
#: float32 rounding of an STL file moves a 0.1 mm thick plate's axes by ~1e-5 at most.
CONVERGE_MEASURE_TOL = 1e-4


@dataclass(frozen=True)
class HoleLoops:
    """The holes of a plate mesh, K of them (part coordinates, mm).

    bottom_centroid_mm, top_centroid_mm: (K, 2) float64, area centroid of each hole's loop on
        the bottom face (z = 0) and on the top face (z = thickness_mm); row k of both is one hole.
    bottom_area_radius_mm, top_area_radius_mm: (K,) float64, sqrt(loop area / pi).
    bottom_circum_radius_mm, top_circum_radius_mm: (K,) float64, largest distance from the loop's
        centroid to its vertices (every point of the loop lies within it).
    segments: (K,) int64, vertices of each hole's top loop.
    thickness_mm: z of the top face (the mesh's largest z).
    outline_min_mm, outline_max_mm: (2,) float64, (x, y) extent of the outer outline loops.
    """

    bottom_centroid_mm: np.ndarray
    top_centroid_mm: np.ndarray
    bottom_area_radius_mm: np.ndarray
    top_area_radius_mm: np.ndarray
    bottom_circum_radius_mm: np.ndarray
    top_circum_radius_mm: np.ndarray
    segments: np.ndarray
    thickness_mm: float
    outline_min_mm: np.ndarray
    outline_max_mm: np.ndarray

    @property
    def count(self) -> int:
        return len(self.segments)

    @property
    def axes(self) -> np.ndarray:
        """(K, 2) float64, lateral shift of each hole's centre per mm of +z."""
        return (self.top_centroid_mm - self.bottom_centroid_mm) / self.thickness_mm


@dataclass(frozen=True)
class _FaceLoops:
    """Boundary loops of one flat face: L loops, the outline at index `outline`."""

    vertex_loop: np.ndarray  # (V,) int64 loop of each vertex on the boundary, -1 elsewhere
    centroid: np.ndarray  # (L, 2)
    area: np.ndarray  # (L,) signed
    circum: np.ndarray  # (L,)
    segments: np.ndarray  # (L,)
    outline: int


def _single_edges(faces: np.ndarray, size: int) -> np.ndarray:
    """Directed edges (E, 2) of `faces` that no other face of the set shares (any direction)."""
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    key = directed.min(axis=1) * size + directed.max(axis=1)
    order = np.argsort(key, kind="stable")
    ordered = key[order]
    differs = ordered[1:] != ordered[:-1]
    alone = np.concatenate([[True], differs]) & np.concatenate([differs, [True]])
    return directed[order[alone]]


def _face_loops(mesh: PlateMesh, on_face: np.ndarray, name: str) -> _FaceLoops:
    """Boundary loops of the triangles whose three vertices lie on one face (on_face (V,))."""
    size = len(mesh.vertices)
    faces = mesh.faces[np.all(on_face[mesh.faces], axis=1)]
    if len(faces) == 0:
        raise ValueError(f"the mesh has no triangles on its {name} face; give a plate mesh in "
                         "part coordinates (flat bottom face at z = 0, top face at the largest z).")
    edges = _single_edges(faces, size)
    start, end = edges[:, 0], edges[:, 1]
    out_degree = np.bincount(start, minlength=size)
    in_degree = np.bincount(end, minlength=size)
    bad = np.flatnonzero((out_degree != in_degree) | (out_degree > 1))
    if bad.size:
        x, y, z = mesh.vertices[bad[0]]
        raise ValueError(
            f"a boundary loop of the {name} face is not closed at vertex ({x:g}, {y:g}, {z:g}) "
            f"mm ({bad.size} such vertices): boundary edges must form simple closed loops. The "
            "mesh has a gap, a flipped triangle or two holes touching; rebuild or repair it."
        )
    # Loop label: the smallest vertex index on the loop, by pointer doubling along successors.
    successor = np.arange(size)
    successor[start] = end
    label = np.arange(size)
    jump = successor.copy()
    for _ in range(max(1, math.ceil(math.log2(max(len(edges), 2))))):
        label = np.minimum(label, label[jump])
        jump = jump[jump]
    loops, loop = np.unique(label[start], return_inverse=True)
    count = len(loops)
    vertex_loop = np.full(size, -1, dtype=np.int64)
    vertex_loop[start] = loop
    segments = np.bincount(loop, minlength=count)

    xy = mesh.vertices[:, :2]
    reference = np.stack([np.bincount(loop, xy[start, i], count) for i in range(2)],
                         axis=1) / segments[:, None]
    a, b = xy[start] - reference[loop], xy[end] - reference[loop]
    cross = a[:, 0] * b[:, 1] - b[:, 0] * a[:, 1]
    area = 0.5 * np.bincount(loop, cross, count)
    moment = np.stack([np.bincount(loop, (a[:, i] + b[:, i]) * cross, count) for i in range(2)],
                      axis=1)
    if np.any(area == 0):
        raise ValueError(f"a boundary loop of the {name} face has zero area; the mesh has "
                         "degenerate triangles. Rebuild it.")
    centroid = reference + moment / (6 * area[:, None])
    circum = np.zeros(count)
    np.maximum.at(circum, loop, np.linalg.norm(xy[start] - centroid[loop], axis=1))
    outline = int(np.argmax(np.abs(area)))
    islands = np.flatnonzero(np.sign(area) == np.sign(area[outline]))
    if islands.size > 1:
        where = centroid[islands[islands != outline][0]]
        raise ValueError(
            f"a loop of the {name} face at ({where[0]:g}, {where[1]:g}) mm runs the same way as "
            "the outline, so it bounds a separate piece of face, not a hole; the mesh is not one "
            "plate with through-holes."
        )
    return _FaceLoops(vertex_loop, centroid, area, circum, segments, outline)


def _match_walls(mesh: PlateMesh, bottom: _FaceLoops, top: _FaceLoops) -> np.ndarray:
    """For each hole loop of the bottom face (outline excluded), its top loop, via the wall
    triangles' edges that join a bottom-loop vertex to a top-loop vertex. (H,) int64."""
    edges = mesh.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    lb = bottom.vertex_loop[edges]
    lt = top.vertex_loop[edges]
    down = (lb[:, 0] >= 0) & (lt[:, 1] >= 0)
    up = (lt[:, 0] >= 0) & (lb[:, 1] >= 0)
    links = np.concatenate([np.stack([lb[down, 0], lt[down, 1]], axis=1),
                            np.stack([lb[up, 1], lt[up, 0]], axis=1)])
    bottom_count, top_count = len(bottom.area), len(top.area)
    # Unique (bottom, top) pairs, by one integer key each (np.unique(axis=0) sorts rows as
    # structured records, ~10 x slower); same rows, same order.
    key = np.unique(links[:, 0] * top_count + links[:, 1])
    links = np.stack([key // top_count, key % top_count], axis=1)
    for face, column, count, loops in (("bottom", 0, bottom_count, bottom),
                                       ("top", 1, top_count, top)):
        partners = np.bincount(links[:, column], minlength=count)
        bad = np.flatnonzero(partners != 1)
        if bad.size:
            where = loops.centroid[bad[0]]
            what = "no wall reaching" if partners[bad[0]] == 0 else "walls to several loops of"
            other = "top" if face == "bottom" else "bottom"
            raise ValueError(
                f"the {face} face's loop at ({where[0]:g}, {where[1]:g}) mm has {what} the "
                f"{other} face ({bad.size} such loops); each hole's wall must join one loop on "
                "each face. The mesh is not a plate with through-holes; rebuild it."
            )
    partner = np.empty(bottom_count, dtype=np.int64)
    partner[links[:, 0]] = links[:, 1]
    if partner[bottom.outline] != top.outline:
        raise ValueError("the outline loops of the bottom and top faces are not joined by the "
                         "plate's side walls; the mesh is not one plate. Rebuild it.")
    holes = np.delete(np.arange(bottom_count), bottom.outline)
    return np.stack([holes, partner[holes]], axis=1)


def mesh_hole_loops(mesh: PlateMesh) -> HoleLoops:
    """The holes of a plate mesh (part coordinates), from its two flat faces' boundary loops
    (module docstring). ValueError names what is wrong when the mesh is not such a plate."""
    if len(mesh.faces) == 0:
        raise ValueError("mesh has no faces; give the plate's mesh (e.g. read_stl of plate.stl).")
    z = mesh.vertices[:, 2]
    thickness = float(z.max())
    if not (thickness > 0 and abs(float(z.min())) <= FACE_RTOL * thickness):
        raise ValueError(
            f"mesh spans z = {z.min():g} to {thickness:g} mm; a plate in part coordinates has its "
            "bottom face at z = 0 and its top face above it. Give it in part coordinates."
        )
    tol = FACE_RTOL * thickness
    bottom = _face_loops(mesh, np.abs(z) <= tol, "bottom")
    top = _face_loops(mesh, np.abs(z - thickness) <= tol, "top")
    pair = _match_walls(mesh, bottom, top)
    b, t = pair[:, 0], pair[:, 1]
    outline_xy = mesh.vertices[np.concatenate([
        np.flatnonzero(bottom.vertex_loop == bottom.outline),
        np.flatnonzero(top.vertex_loop == top.outline)]), :2]
    return HoleLoops(
        bottom_centroid_mm=bottom.centroid[b],
        top_centroid_mm=top.centroid[t],
        bottom_area_radius_mm=np.sqrt(np.abs(bottom.area[b]) / math.pi),
        top_area_radius_mm=np.sqrt(np.abs(top.area[t]) / math.pi),
        bottom_circum_radius_mm=bottom.circum[b],
        top_circum_radius_mm=top.circum[t],
        segments=top.segments[t].astype(np.int64),
        thickness_mm=thickness,
        outline_min_mm=outline_xy.min(axis=0),
        outline_max_mm=outline_xy.max(axis=0),
    )


def hole_layout_from_mesh(
    mesh: PlateMesh,
    pitch_mm: tuple[float, float],
    grid: tuple[int, int],
    converge_mm: tuple[float, float, float] | None = None,
) -> HoleLayout:
    """The HoleLayout a plate mesh was built from, recovered from the mesh (module docstring).

    pitch_mm: (px, py) cell pitch; grid: (nx, ny) cell count (the mesh does not record them).
    converge_mm: (ex, ey, D) for chief-ray holes; the measured axes must agree with
        ((ex, ey) - centres) / D to CONVERGE_MEASURE_TOL and are then set to it exactly.
    Holes come out in row-major cell order; ValueError when a hole lies outside the grid, two
    holes share a cell, or the mesh is not a plate (see mesh_hole_loops).
    """
    nx, ny = grid
    px, py = pitch_mm
    loops = mesh_hole_loops(mesh)
    thickness = loops.thickness_mm
    centres = 0.5 * (loops.bottom_centroid_mm + loops.top_centroid_mm)
    col = np.floor(centres[:, 0] / px + nx / 2).astype(np.int64)
    row = np.floor(ny / 2 - centres[:, 1] / py).astype(np.int64)
    outside = np.flatnonzero((col < 0) | (col >= nx) | (row < 0) | (row >= ny))
    if outside.size:
        x, y = centres[outside[0]]
        raise ValueError(
            f"a hole at ({x:g}, {y:g}) mm (mid-thickness) lies outside the grid of {nx} x {ny} "
            f"cells at pitch {pitch_mm} mm ({outside.size} such holes); give the grid and pitch "
            "the plate was designed with."
        )
    cell = row * nx + col
    order = np.argsort(cell, kind="stable")
    shared = np.flatnonzero(np.diff(cell[order]) == 0)
    if shared.size:
        first = int(cell[order[shared[0]]])
        raise ValueError(
            f"two holes lie in cell {(first // nx, first % nx)} ({shared.size} such cells); give "
            "the grid and pitch the plate was designed with (one hole per cell)."
        )
    centres = centres[order]
    axes = loops.axes[order]
    if converge_mm is not None:
        want = (np.asarray(converge_mm[:2], dtype=np.float64) - centres) / converge_mm[2]
        error = float(np.max(np.abs(axes - want))) if len(axes) else 0.0
        if not error <= CONVERGE_MEASURE_TOL:
            raise ValueError(
                f"the holes' axes differ from ((ex, ey) - centres) / D for converge_mm = "
                f"{converge_mm} by up to {error:.3g} per mm; allowed: {CONVERGE_MEASURE_TOL:g}. "
                "Give the point the holes were aimed at, or converge_mm = None."
            )
        axes = want
    radii = 0.5 * (loops.bottom_area_radius_mm + loops.top_area_radius_mm)[order]
    extent = loops.outline_max_mm - loops.outline_min_mm
    return HoleLayout(
        cells=np.stack([cell[order] // nx, cell[order] % nx], axis=1),
        centres_mm=centres,
        radii_mm=radii,
        axes=axes,
        pitch_mm=(px, py),
        grid=(nx, ny),
        outline_mm=(float(extent[0]), float(extent[1])),
        thickness_mm=thickness,
        converge_mm=converge_mm,
    )
