"""Checks of a plate mesh as a solid: its volume, whether it is closed and manifold with one
shell and the genus of its holes (check_mesh), and the same verdict from the manifold3d
kernel, independent of ours (manifold_check)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aperture_fab.fabrication.mesh import PlateMesh

__all__ = ["ManifoldReport", "MeshReport", "check_mesh", "manifold_check", "mesh_volume_mm3"]


@dataclass(frozen=True)
class MeshReport:
    """Topology and volume of a mesh, computed from the faces alone.

    watertight: every edge is used by exactly two faces.
    consistently_oriented: watertight and the two faces at each edge run it in opposite ways.
    boundary_edges, nonmanifold_edges, misoriented_edges: counts of edges used by one face, by
        more than two faces, and twice in the same direction.
    degenerate_faces: faces with a repeated vertex or zero area.
    euler_characteristic: V - E + F over the vertices that faces use.
    bodies: connected pieces.
    genus: total genus, bodies - chi / 2 (through-holes of a single closed body).
    volume_mm3: enclosed volume by the divergence theorem (positive for outward normals).
    """

    vertex_count: int
    face_count: int
    edge_count: int
    boundary_edges: int
    nonmanifold_edges: int
    misoriented_edges: int
    degenerate_faces: int
    watertight: bool
    consistently_oriented: bool
    euler_characteristic: int
    bodies: int
    genus: int
    volume_mm3: float
    positive_volume: bool

    @property
    def ok(self) -> bool:
        """A printable solid: one closed, oriented, non-degenerate body of positive volume."""
        return (
            self.consistently_oriented
            and self.degenerate_faces == 0
            and self.bodies == 1
            and self.positive_volume
        )


@dataclass(frozen=True)
class ManifoldReport:
    """What manifold3d makes of a mesh (vertices cast to float32).

    status: manifold3d's error name, "NoError" when the mesh is a valid manifold.
    genus, volume_mm3, triangle_count: as manifold3d computes them.
    """

    status: str
    genus: int
    volume_mm3: float
    triangle_count: int

    @property
    def ok(self) -> bool:
        return self.status == "NoError"


def mesh_volume_mm3(mesh: PlateMesh) -> float:
    """Enclosed volume by the divergence theorem, mm^3 (about the bounding-box centre, which
    keeps the sum well conditioned)."""
    if len(mesh.faces) == 0:
        return 0.0
    centre = 0.5 * (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0))
    v = mesh.vertices - centre
    a, b, c = v[mesh.faces[:, 0]], v[mesh.faces[:, 1]], v[mesh.faces[:, 2]]
    return float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)


def _component_count(a: np.ndarray, b: np.ndarray, nodes: np.ndarray, size: int) -> int:
    """Connected components among `nodes` of the graph with edges (a, b): min-label hooking
    with pointer jumping, a few numpy passes."""
    labels = np.arange(size)
    while True:
        la, lb = labels[a], labels[b]
        if np.array_equal(la, lb):
            break
        np.minimum.at(labels, np.maximum(la, lb), np.minimum(la, lb))
        while True:
            jumped = labels[labels]
            if np.array_equal(jumped, labels):
                break
            labels = jumped
    return len(_sorted_unique(labels[nodes])[0])


def _sorted_unique(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct values and their counts by sorting (numpy's hash-based unique is far slower on
    tens of millions of int64 keys)."""
    ordered = np.sort(keys)
    starts = np.flatnonzero(np.concatenate([[True], ordered[1:] != ordered[:-1]]))
    counts = np.diff(np.append(starts, len(ordered)))
    return ordered[starts], counts


def check_mesh(mesh: PlateMesh) -> MeshReport:
    """Topology and volume of any triangle mesh, from its faces alone (not from how it was
    built)."""
    faces = mesh.faces
    size = len(mesh.vertices)
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    lo, hi = directed.min(axis=1), directed.max(axis=1)
    undirected, counts = _sorted_unique(lo * size + hi)
    directed_unique = len(_sorted_unique(directed[:, 0] * size + directed[:, 1])[0])
    boundary = int(np.sum(counts == 1))
    nonmanifold = int(np.sum(counts > 2))
    misoriented = len(directed) - directed_unique
    v = mesh.vertices
    area2 = np.linalg.norm(
        np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]]), axis=1
    )
    repeated = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (
        faces[:, 2] == faces[:, 0]
    )
    degenerate = int(np.sum(repeated | (area2 == 0)))
    is_used = np.zeros(size, dtype=bool)
    is_used[faces] = True
    used = np.flatnonzero(is_used)
    chi = len(used) - len(undirected) + len(faces)
    bodies = _component_count(undirected // size, undirected % size, used, size) if size else 0
    volume = mesh_volume_mm3(mesh)
    watertight = boundary == 0 and nonmanifold == 0
    return MeshReport(
        vertex_count=len(used),
        face_count=len(faces),
        edge_count=len(undirected),
        boundary_edges=boundary,
        nonmanifold_edges=nonmanifold,
        misoriented_edges=misoriented,
        degenerate_faces=degenerate,
        watertight=watertight,
        consistently_oriented=watertight and misoriented == 0,
        euler_characteristic=int(chi),
        bodies=bodies,
        genus=(2 * bodies - int(chi)) // 2,
        volume_mm3=volume,
        positive_volume=volume > 0,
    )


def manifold_check(mesh: PlateMesh) -> ManifoldReport:
    """Load the mesh into manifold3d (float32 vertices) and report its verdict."""
    try:
        import manifold3d
    except ImportError as error:
        raise ImportError(
            "manifold_check needs the manifold3d package: pip install manifold3d"
        ) from error
    solid = manifold3d.Manifold(
        manifold3d.Mesh(
            vert_properties=mesh.vertices.astype(np.float32),
            tri_verts=mesh.faces.astype(np.uint32),
        )
    )
    return ManifoldReport(
        status=solid.status().name,
        genus=int(solid.genus()),
        volume_mm3=float(solid.volume()),
        triangle_count=int(solid.num_tri()),
    )
