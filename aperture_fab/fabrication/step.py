"""A true B-rep STEP solid of the plate: planar faces and one exact surface per hole.

Plate coordinates: x right, y up, the part occupies z in [0, thickness] (bottom face z = 0), its
outline centred on the axis. A hole's centre at height z is
centres_mm + (z - thickness / 2) * axes. An optional alignment chamfer cuts the outline's top-left
corner (-x, +y) at 45 degrees with legs corner_cut_mm, as the mesh, DXF and SVG outputs do.

Hole walls:
- straight holes (axes == 0): a circular cylinder (STEP cylindrical_surface);
- tilted holes: the exact oblique circular cylinder, i.e. the bottom circle swept along the hole
  axis (STEP surface_of_linear_extrusion). Every z-plane cuts it in a circle of radius r (what the
  optical model and the hole table mean), so the hole removes pi r^2 t however tilted; its section
  normal to the axis is an ellipse.

Why the shell is built by hand: one planar face holding thousands of holes makes OCCT's STEP
writer and every STEP reader quadratic in holes per face, and sewing is slow. So the top and
bottom faces are each tiled into rectangles holding a few dozen holes (cut lines run in the
webs between holes), every edge is made once and shared by its two faces, and the faces go
straight into a shell and a solid. Time and memory are linear in the hole count. The chamfer is
one more planar side face; tile cut lines are kept off it, so it only turns each face's top-left
tile into a pentagon.
"""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np

from aperture_fab.fabrication.layout import HoleLayout
from aperture_fab.fabrication.step_layout import check_layout, hole_footprints, tile_grids

__all__ = ["StepSummary", "build_solid", "read_step_summary", "shape_summary", "step_bytes"]

#: OCCT modelling tolerance for the faces and edges built here.
TOLERANCE_MM = 1e-7
#: A hole whose axis moves less than this per mm of z is built as a true straight cylinder.
STRAIGHT_AXIS_LIMIT = 1e-12
#: Holes between progress reports.
PROGRESS_EVERY = 1000
#: Tile-corner index i of the chamfer's vertex on the top side (i = 0 is the left side's).
CHAMFER_TOP = -1
OCP_MISSING = (
    "STEP export needs OCCT's Python bindings: pip install cadquery-ocp==7.9.3.1.1 "
    "(the version cadquery 2.8 expects)."
)


@dataclass(frozen=True)
class StepSummary:
    """What an OCCT shape holds: a STEP file as read back, or build_solid's solid.

    solids: number of solids.
    valid: BRepCheck_Analyzer finds the shape valid.
    closed: every shell is closed (no free edges).
    faces: number of faces.
    cylindrical_faces: faces on a circular cylinder (straight holes).
    extrusion_faces: faces on a surface of linear extrusion (tilted holes).
    volume_mm3: enclosed volume (mm^3).
    area_mm2: surface area (mm^2).
    bounds_mm: (2, 3) float64, bounding box (min xyz, max xyz), mm; OCCT pads it slightly.
    cylinders_mm: (C, 3) float64, (x, y, radius) of each cylindrical face's axis where it
        crosses z = 0, mm, sorted by x then y.
    """

    solids: int
    valid: bool
    closed: bool
    faces: int
    cylindrical_faces: int
    extrusion_faces: int
    volume_mm3: float
    area_mm2: float
    bounds_mm: np.ndarray
    cylinders_mm: np.ndarray


def _import_ocp() -> None:
    try:
        import OCP  # noqa: F401
    except ImportError as error:
        raise ImportError(OCP_MISSING) from error


@contextmanager
def quiet_occt() -> Iterator[None]:
    """Hold back OCCT's progress chatter on stdout for the duration; restore the levels after."""
    from OCP.Message import Message, Message_Gravity

    printers = list(Message.DefaultMessenger_s().Printers())
    levels = [printer.GetTraceLevel() for printer in printers]
    for printer in printers:
        printer.SetTraceLevel(Message_Gravity.Message_Fail)
    try:
        yield
    finally:
        for printer, level in zip(printers, levels, strict=True):
            printer.SetTraceLevel(level)


Key = tuple[int, int, int]


class SharedTopology:
    """Vertices and straight edges made once and shared by both faces that meet there.

    A vertex key is (level, i, j): level 0 is the bottom face, 1 the top; (i, j) the tile corner.
    With a corner cut, the top-left corner (level, 0, ny) is the chamfer's end on the left side
    (y = H/2 - cut) and (level, CHAMFER_TOP, ny) its end on the top side (x = -W/2 + cut).
    """

    def __init__(self) -> None:
        from OCP.BRep import BRep_Builder

        self.builder = BRep_Builder()
        self.vertices: dict[Key, Any] = {}
        self.points: dict[Key, tuple[float, float, float]] = {}
        self.edges: dict[tuple[Key, Key], Any] = {}

    def vertex(self, key: Key, point: tuple[float, float, float]) -> None:
        from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeVertex
        from OCP.gp import gp_Pnt

        self.vertices[key] = BRepBuilderAPI_MakeVertex(gp_Pnt(*point)).Vertex()
        self.points[key] = point

    def edge(self, a: Key, b: Key) -> Any:
        """The straight edge between vertices a and b, oriented a -> b."""
        from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeEdge
        from OCP.TopAbs import TopAbs_FORWARD, TopAbs_REVERSED

        key, forward = ((a, b), True) if a < b else ((b, a), False)
        if key not in self.edges:
            made = BRepBuilderAPI_MakeEdge(self.vertices[key[0]], self.vertices[key[1]])
            self.edges[key] = made.Edge()
        return self.edges[key].Oriented(TopAbs_FORWARD if forward else TopAbs_REVERSED)

    def wire(self, edges: list[Any]) -> Any:
        """A closed wire of the given (oriented, connected, in order) edges."""
        from OCP.TopoDS import TopoDS_Wire

        wire = TopoDS_Wire()
        self.builder.MakeWire(wire)
        for edge in edges:
            self.builder.Add(wire, edge)
        wire.Closed(True)
        return wire

    def loop(self, keys: list[Key]) -> Any:
        """A closed polygonal wire through the vertices, in the given order."""
        pairs = zip(keys, keys[1:] + keys[:1], strict=True)
        return self.wire([self.edge(a, b) for a, b in pairs])

    def face(self, plane: Any, outer: Any, holes: list[Any]) -> Any:
        """A planar face: outer wire counter-clockwise about the plane normal, holes clockwise."""
        from OCP.TopoDS import TopoDS_Face

        face = TopoDS_Face()
        self.builder.MakeFace(face, plane, TOLERANCE_MM)
        self.builder.Add(face, outer)
        for hole in holes:
            self.builder.Add(face, hole)
        return face


def hole_wall(bottom: np.ndarray, axis: np.ndarray, radius: float, thickness: float) -> Any:
    """The hole wall, facing into the hole (out of the material), and its (bottom, top) circles.

    bottom: (2,) centre on z = 0, mm; axis: (2,) lateral shift per mm of z. The circles come
    back as edges oriented counter-clockwise seen from +z.
    """
    from OCP.BRepAdaptor import BRepAdaptor_Curve
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeFace
    from OCP.Geom import Geom_Circle, Geom_CylindricalSurface, Geom_SurfaceOfLinearExtrusion
    from OCP.GeomAbs import GeomAbs_Circle
    from OCP.gp import gp_Ax2, gp_Ax3, gp_Dir, gp_Pnt
    from OCP.TopAbs import TopAbs_EDGE, TopAbs_FORWARD
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS

    origin = gp_Pnt(float(bottom[0]), float(bottom[1]), 0.0)
    up = gp_Dir(0.0, 0.0, 1.0)
    if float(np.max(np.abs(axis))) <= STRAIGHT_AXIS_LIMIT:
        surface: Any = Geom_CylindricalSurface(gp_Ax3(origin, up), radius)
        length = thickness
    else:
        # v runs along the unit axis direction: the top circle is at v = t * |(ax, ay, 1)|.
        circle = Geom_Circle(gp_Ax2(origin, up), radius)
        surface = Geom_SurfaceOfLinearExtrusion(
            circle, gp_Dir(float(axis[0]), float(axis[1]), 1.0)
        )
        length = thickness * math.sqrt(1.0 + float(axis[0]) ** 2 + float(axis[1]) ** 2)
    face = BRepBuilderAPI_MakeFace(surface, 0.0, 2 * math.pi, 0.0, length, TOLERANCE_MM).Face()
    circles: dict[bool, Any] = {}
    explorer = TopExp_Explorer(face, TopAbs_EDGE)
    while explorer.More():
        edge = TopoDS.Edge_s(explorer.Current())
        curve = BRepAdaptor_Curve(edge)
        if curve.GetType() == GeomAbs_Circle:
            is_top = curve.Value(curve.FirstParameter()).Z() > thickness / 2
            circles[is_top] = edge.Oriented(TopAbs_FORWARD)
        explorer.Next()
    if len(circles) != 2:  # pragma: no cover - OCCT's MakeFace contract
        raise RuntimeError("OCCT built a hole wall without its two circles.")
    # The surface normal points away from the axis, into the material: reverse the face.
    return face.Reversed(), circles[False], circles[True]


def planar_tiles(
    topology: SharedTopology,
    level: int,
    z_mm: float,
    grid: tuple[np.ndarray, np.ndarray],
    centres: np.ndarray,
    circles: list[Any],
    chamfered: bool,
) -> list[Any]:
    """The tiles of the bottom (level 0) or top (level 1) face, each with its holes.

    centres: (K, 2) hole centres on this face, mm; circles: their K circle edges.
    chamfered: the top-left tile is a pentagon through the chamfer's two vertices.
    """
    from OCP.Geom import Geom_Plane
    from OCP.gp import gp_Ax3, gp_Dir, gp_Pnt
    from OCP.TopAbs import TopAbs_REVERSED

    xs, ys = grid
    nx, ny = len(xs) - 1, len(ys) - 1
    normal = 1.0 if level else -1.0
    plane = Geom_Plane(gp_Ax3(gp_Pnt(0.0, 0.0, z_mm), gp_Dir(0.0, 0.0, normal)))
    # Cuts never cross a hole, so a hole's centre tells its tile.
    tile_of_hole = (np.searchsorted(xs, centres[:, 0]) - 1) * ny + np.searchsorted(
        ys, centres[:, 1]
    ) - 1
    members = np.argsort(tile_of_hole, kind="stable")
    starts = np.searchsorted(tile_of_hole[members], np.arange(nx * ny + 1))
    faces = []
    for i in range(nx):
        for j in range(ny):
            corners = [(level, i, j), (level, i + 1, j), (level, i + 1, j + 1), (level, i, j + 1)]
            if chamfered and (i, j) == (0, ny - 1):
                corners.insert(3, (level, CHAMFER_TOP, ny))
            if normal < 0:
                corners.reverse()
            tile = i * ny + j
            # Circles run counter-clockwise seen from +z: already clockwise about the bottom
            # face's -z normal; the top face needs them reversed.
            holes = [
                topology.wire([circles[k].Oriented(TopAbs_REVERSED) if level else circles[k]])
                for k in members[starts[tile] : starts[tile + 1]]
            ]
            faces.append(topology.face(plane, topology.loop(corners), holes))
    return faces


def side_faces(topology: SharedTopology, bottom_shape: tuple[int, int],
               top_shape: tuple[int, int], chamfered: bool) -> list[Any]:
    """The outer walls (four, five with the chamfer), each counter-clockwise about its outward
    normal.

    bottom_shape, top_shape: tile counts (nx, ny) of the bottom and top faces.
    """
    from OCP.Geom import Geom_Plane
    from OCP.gp import gp_Ax3, gp_Dir, gp_Pnt

    (bx, by), (tx, ty) = bottom_shape, top_shape
    # The back wall ends where the top-left corner, or the chamfer, starts.
    end = CHAMFER_TOP if chamfered else 0
    # (outward normal, bottom corners, top corners), both runs in the loop's direction along
    # the bottom, which goes counter-clockwise seen from +z: front, right, back, left.
    sides = [
        ((0.0, -1.0, 0.0), [(0, i, 0) for i in range(bx + 1)], [(1, i, 0) for i in range(tx + 1)]),
        ((1.0, 0.0, 0.0), [(0, bx, j) for j in range(by + 1)], [(1, tx, j) for j in range(ty + 1)]),
        ((0.0, 1.0, 0.0), [(0, i, by) for i in range(bx, 0, -1)] + [(0, end, by)],
         [(1, i, ty) for i in range(tx, 0, -1)] + [(1, end, ty)]),
        ((-1.0, 0.0, 0.0), [(0, 0, j) for j in range(by, -1, -1)],
         [(1, 0, j) for j in range(ty, -1, -1)]),
    ]
    if chamfered:
        sides.append(((-1.0, 1.0, 0.0), [(0, CHAMFER_TOP, by), (0, 0, by)],
                      [(1, CHAMFER_TOP, ty), (1, 0, ty)]))
    faces = []
    for normal, bottom_run, top_run in sides:
        plane = Geom_Plane(gp_Ax3(gp_Pnt(*topology.points[bottom_run[0]]), gp_Dir(*normal)))
        faces.append(topology.face(plane, topology.loop(bottom_run + top_run[::-1]), []))
    return faces


def build_solid(layout: HoleLayout, progress: Callable[[int], None] | None = None,
                *, corner_cut_mm: float = 0.0) -> Any:
    """The plate as one OCCT solid (TopoDS_Solid); see the module docstring.

    corner_cut_mm: legs of the 45-degree chamfer on the outline's top-left corner (-x, +y); 0 for
        none. It must stay CLEARANCE_MM clear of every hole (on the margin).
    """
    _import_ocp()
    from OCP.TopoDS import TopoDS_Shell, TopoDS_Solid

    check_layout(layout, corner_cut_mm)
    chamfered = corner_cut_mm > 0
    thickness = float(layout.thickness_mm)
    radii = np.asarray(layout.radii_mm, dtype=np.float64)
    axes = np.asarray(layout.axes, dtype=np.float64)
    footprints = hole_footprints(layout)
    topology = SharedTopology()
    faces: list[Any] = []

    # Hole walls first: their circle edges become the inner wires of the planar tiles.
    circles: list[list[Any]] = [[], []]
    for k in range(layout.count):
        wall, bottom_circle, top_circle = hole_wall(footprints[0][k], axes[k], radii[k], thickness)
        faces.append(wall)
        circles[0].append(bottom_circle)
        circles[1].append(top_circle)
        if progress is not None and (k + 1) % PROGRESS_EVERY == 0:
            progress(k + 1)

    grids = tile_grids(layout, corner_cut_mm)
    for level, z_mm in ((0, 0.0), (1, thickness)):
        xs, ys = grids[level]
        for i, x in enumerate(xs):
            for j, y in enumerate(ys):
                topology.vertex((level, i, j), (float(x), float(y), z_mm))
        if chamfered:
            ny = len(ys) - 1
            topology.vertex((level, 0, ny), (float(xs[0]), float(ys[-1]) - corner_cut_mm, z_mm))
            topology.vertex((level, CHAMFER_TOP, ny),
                            (float(xs[0]) + corner_cut_mm, float(ys[-1]), z_mm))
        faces += planar_tiles(topology, level, z_mm, grids[level], footprints[level],
                              circles[level], chamfered)
    shapes = [(len(xs) - 1, len(ys) - 1) for xs, ys in grids]
    faces += side_faces(topology, shapes[0], shapes[1], chamfered)

    shell = TopoDS_Shell()
    topology.builder.MakeShell(shell)
    for face in faces:
        topology.builder.Add(shell, face)
    shell.Closed(True)
    solid = TopoDS_Solid()
    topology.builder.MakeSolid(solid)
    topology.builder.Add(solid, shell)
    if progress is not None:
        progress(layout.count)
    return solid


def step_bytes(layout: HoleLayout, progress: Callable[[int], None] | None = None,
               *, corner_cut_mm: float = 0.0) -> bytes:
    """The plate as an AP214 STEP file (mm): one closed solid, exact hole surfaces.

    progress, if given, is called with the number of holes built so far (every 1000 holes and
    once at the end, before the file is written). corner_cut_mm: the alignment chamfer's legs
    (build_solid).
    """
    _import_ocp()
    from OCP.IFSelect import IFSelect_RetDone
    from OCP.Interface import Interface_Static
    from OCP.STEPControl import STEPControl_AsIs, STEPControl_Writer

    solid = build_solid(layout, progress, corner_cut_mm=corner_cut_mm)
    # OCCT keeps these settings in process-wide statics: set them on every call.
    Interface_Static.SetCVal_s("write.step.unit", "MM")
    Interface_Static.SetCVal_s("write.step.schema", "AP214IS")
    # The writer only writes to a path: use a private temporary directory.
    with quiet_occt(), tempfile.TemporaryDirectory(prefix="aperture_fab_step_") as folder:
        writer = STEPControl_Writer()
        if writer.Transfer(solid, STEPControl_AsIs) != IFSelect_RetDone:
            raise RuntimeError("OCCT could not translate the plate solid to STEP.")
        path = os.path.join(folder, "plate.step")
        if writer.Write(path) != IFSelect_RetDone:
            raise RuntimeError("OCCT could not write the STEP file.")
        with open(path, "rb") as handle:
            return handle.read()


def read_step_summary(data: bytes) -> StepSummary:
    """Read STEP bytes with OCCT and summarise the shape (for tests and validation)."""
    _import_ocp()
    from OCP.IFSelect import IFSelect_RetDone
    from OCP.STEPControl import STEPControl_Reader

    reader = STEPControl_Reader()
    with quiet_occt(), tempfile.TemporaryDirectory(prefix="aperture_fab_step_") as folder:
        path = os.path.join(folder, "plate.step")
        with open(path, "wb") as handle:
            handle.write(data)
        if reader.ReadFile(path) != IFSelect_RetDone:
            raise ValueError("The data is not a STEP file OCCT can read.")
        reader.TransferRoots()
    return shape_summary(reader.OneShape())


def shape_summary(shape: Any) -> StepSummary:
    """Summarise an OCCT shape (TopoDS_Shape), e.g. build_solid's, before any file round trip.

    STEP readers heal some faults (wire orientation) on the way in, so check the solid itself too.
    """
    _import_ocp()
    from OCP.Bnd import Bnd_Box
    from OCP.BRep import BRep_Tool
    from OCP.BRepAdaptor import BRepAdaptor_Surface
    from OCP.BRepBndLib import BRepBndLib
    from OCP.BRepCheck import BRepCheck_Analyzer
    from OCP.BRepGProp import BRepGProp
    from OCP.GeomAbs import GeomAbs_Cylinder, GeomAbs_SurfaceOfExtrusion
    from OCP.GProp import GProp_GProps
    from OCP.TopAbs import TopAbs_FACE, TopAbs_SHELL, TopAbs_SOLID
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS

    def shapes(kind: Any) -> list[Any]:
        found = []
        explorer = TopExp_Explorer(shape, kind)
        while explorer.More():
            found.append(explorer.Current())
            explorer.Next()
        return found

    faces = shapes(TopAbs_FACE)
    cylinders, extrusions = [], 0
    for face in faces:
        surface = BRepAdaptor_Surface(TopoDS.Face_s(face))
        if surface.GetType() == GeomAbs_Cylinder:
            cylinder = surface.Cylinder()
            place, direction = cylinder.Location(), cylinder.Axis().Direction()
            step = -place.Z() / direction.Z()  # where the axis crosses z = 0
            cylinders.append((place.X() + step * direction.X(), place.Y() + step * direction.Y(),
                              cylinder.Radius()))
        elif surface.GetType() == GeomAbs_SurfaceOfExtrusion:
            extrusions += 1
    table = np.array(sorted(cylinders), dtype=np.float64).reshape(-1, 3)
    volume, area = GProp_GProps(), GProp_GProps()
    # OCCT's fixed Gauss rule: exact for the volume of these faces, ~1e-7 on tilted walls' area
    # (its adaptive variant was slower and less accurate here).
    BRepGProp.VolumeProperties_s(shape, volume)
    BRepGProp.SurfaceProperties_s(shape, area)
    box = Bnd_Box()
    BRepBndLib.Add_s(shape, box)
    bounds = np.array(box.Get()).reshape(2, 3) if not box.IsVoid() else np.zeros((2, 3))
    shells = shapes(TopAbs_SHELL)
    return StepSummary(
        solids=len(shapes(TopAbs_SOLID)),
        valid=bool(BRepCheck_Analyzer(shape).IsValid()),
        closed=bool(shells) and all(BRep_Tool.IsClosed_s(shell) for shell in shells),
        faces=len(faces),
        cylindrical_faces=len(cylinders),
        extrusion_faces=extrusions,
        volume_mm3=float(volume.Mass()),
        area_mm2=float(area.Mass()),
        bounds_mm=bounds,
        cylinders_mm=table,
    )
