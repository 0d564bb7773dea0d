"""File exports read back with independent parsers: 3MF, DXF, SVG, CSV, STL."""

from __future__ import annotations

import csv
import io
import re
import struct
import xml.etree.ElementTree as ElementTree
import zipfile

import numpy as np
import pytest

from aperture_fab.fabrication.layout import HoleLayout
from aperture_fab.fabrication.mesh import build_mesh
from aperture_fab.fabrication.mesh_checks import check_mesh
from aperture_fab.io.formats import (
    dxf_bytes,
    holes_csv,
    read_stl,
    stl_bytes,
    svg_text,
    threemf_bytes,
)

CORE = "{http://schemas.microsoft.com/3dmanufacturing/core/2015/02}"
SVG = "{http://www.w3.org/2000/svg}"


@pytest.fixture
def layout() -> HoleLayout:
    """4 x 3 cells of 1 mm, eight holes, some tilted, 1.5 mm margin."""
    rng = np.random.default_rng(3)
    nx, ny, pitch = 4, 3, 1.0
    rows, cols = np.divmod(rng.choice(nx * ny, size=8, replace=False), nx)
    centres = np.stack([(cols - (nx - 1) / 2) * pitch, ((ny - 1) / 2 - rows) * pitch], axis=1)
    return HoleLayout(
        cells=np.stack([rows, cols], axis=1).astype(np.int64),
        centres_mm=centres,
        radii_mm=rng.uniform(0.05, 0.35, 8),
        axes=rng.uniform(-0.05, 0.05, (8, 2)),
        pitch_mm=(pitch, pitch),
        grid=(nx, ny),
        outline_mm=(nx * pitch + 3.0, ny * pitch + 3.0),
        thickness_mm=0.8,
    )


def test_stl_layout_is_binary_with_unit_normals(layout: HoleLayout) -> None:
    mesh = build_mesh(layout, 1e-3)
    data = stl_bytes(mesh)
    assert not data.startswith(b"solid")
    (count,) = struct.unpack_from("<I", data, 80)
    assert count == len(mesh.faces) and len(data) == 84 + 50 * count
    first = struct.unpack_from("<12fH", data, 84)
    normal, corners = np.array(first[:3]), np.array(first[3:12]).reshape(3, 3)
    np.testing.assert_allclose(corners, mesh.vertices[mesh.faces[0]], rtol=1e-6, atol=1e-6)
    edge_normal = np.cross(corners[1] - corners[0], corners[2] - corners[0])
    np.testing.assert_allclose(normal, edge_normal / np.linalg.norm(edge_normal), atol=1e-6)


def test_read_stl_refuses_truncated_data(layout: HoleLayout) -> None:
    data = stl_bytes(build_mesh(layout, 1e-3))
    with pytest.raises(ValueError, match="truncated"):
        read_stl(data[:-10])
    with pytest.raises(ValueError, match="at least 84"):
        read_stl(data[:50])


def test_read_stl_merges_only_equal_vertices(layout: HoleLayout) -> None:
    mesh = build_mesh(layout, 1e-3)
    again = read_stl(stl_bytes(mesh))
    assert len(again.vertices) == len(mesh.vertices)
    assert check_mesh(again).genus == layout.count


def test_3mf_has_millimetre_unit_and_every_vertex_and_triangle(layout: HoleLayout) -> None:
    from lxml import etree

    mesh = build_mesh(layout, 1e-3)
    with zipfile.ZipFile(io.BytesIO(threemf_bytes(mesh))) as package:
        names = set(package.namelist())
        assert {"[Content_Types].xml", "_rels/.rels", "3D/3dmodel.model"} <= names
        rels = etree.fromstring(package.read("_rels/.rels"))
        targets = [r.get("Target") for r in rels]
        assert "/3D/3dmodel.model" in targets
        model = etree.fromstring(package.read("3D/3dmodel.model"))
    assert model.tag == f"{CORE}model"
    assert model.get("unit") == "millimeter"
    vertices = model.findall(f"{CORE}resources/{CORE}object/{CORE}mesh/{CORE}vertices/{CORE}vertex")
    triangles = model.findall(
        f"{CORE}resources/{CORE}object/{CORE}mesh/{CORE}triangles/{CORE}triangle"
    )
    assert len(vertices) == len(mesh.vertices)
    assert len(triangles) == len(mesh.faces)
    xyz = np.array([[float(v.get(k)) for k in "xyz"] for v in vertices])
    np.testing.assert_allclose(xyz, mesh.vertices, atol=1e-6)
    tri = np.array([[int(t.get(k)) for k in ("v1", "v2", "v3")] for t in triangles])
    np.testing.assert_array_equal(tri, mesh.faces)
    items = model.findall(f"{CORE}build/{CORE}item")
    assert [i.get("objectid") for i in items] == ["1"]


@pytest.mark.parametrize("cut", [0.0, 1.0])
def test_dxf_has_mm_units_one_circle_per_hole_and_the_outline(
    layout: HoleLayout, cut: float
) -> None:
    import ezdxf
    from ezdxf.entities import LWPolyline

    doc = ezdxf.read(io.StringIO(dxf_bytes(layout, corner_cut_mm=cut).decode("utf-8")))
    assert doc.header["$INSUNITS"] == 4
    circles = doc.modelspace().query("CIRCLE")
    assert len(circles) == layout.count
    assert {c.dxf.layer for c in circles} == {"HOLES"}
    got = sorted((c.dxf.center.x, c.dxf.center.y, c.dxf.radius) for c in circles)
    want = sorted(zip(*layout.centres_mm.T, layout.radii_mm, strict=True))
    np.testing.assert_allclose(np.array(got), np.array(want), atol=1e-12)
    (outline,) = doc.modelspace().query("LWPOLYLINE")
    assert isinstance(outline, LWPolyline)
    assert outline.dxf.layer == "OUTLINE" and outline.closed
    points = np.array([p[:2] for p in outline.get_points()])
    x = np.append(points[:, 0], points[0, 0])
    y = np.append(points[:, 1], points[0, 1])
    area = 0.5 * np.sum(x[:-1] * y[1:] - x[1:] * y[:-1])
    width, height = layout.outline_mm
    assert area == pytest.approx(width * height - cut**2 / 2)


@pytest.mark.parametrize(
    ("polarity", "plate", "hole"),
    [("holes_black", "white", "black"), ("holes_white", "black", "white")],
)
def test_svg_is_one_to_one_in_mm(
    layout: HoleLayout, polarity: str, plate: str, hole: str
) -> None:
    root = ElementTree.fromstring(svg_text(layout, polarity))  # type: ignore[arg-type]
    width, height = layout.outline_mm
    assert root.get("width") == f"{width:g}mm" and root.get("height") == f"{height:g}mm"
    assert [float(v) for v in root.get("viewBox", "").split()] == [0, 0, width, height]
    circles = root.findall(f".//{SVG}circle")
    assert len(circles) == layout.count
    svg_xyr = np.array([[float(c.get(k, "nan")) for k in ("cx", "cy", "r")] for c in circles])
    np.testing.assert_allclose(svg_xyr[:, 0] - width / 2, layout.centres_mm[:, 0], atol=1e-6)
    np.testing.assert_allclose(height / 2 - svg_xyr[:, 1], layout.centres_mm[:, 1], atol=1e-6)
    np.testing.assert_allclose(svg_xyr[:, 2], layout.radii_mm, atol=1e-6)
    assert root.find(f"{SVG}polygon").get("fill") == plate  # type: ignore[union-attr]
    assert root.find(f"{SVG}g").get("fill") == hole  # type: ignore[union-attr]


def test_svg_refuses_unknown_polarity(layout: HoleLayout) -> None:
    with pytest.raises(ValueError, match="polarity"):
        svg_text(layout, "grey")  # type: ignore[arg-type]


def test_csv_lists_every_hole(layout: HoleLayout) -> None:
    text = holes_csv(layout)
    # The last line is a comment stating the outline (readers skip "#" lines).
    rows = list(csv.DictReader(line for line in io.StringIO(text) if not line.startswith("#")))
    assert text.splitlines()[0] == "row,col,x_mm,y_mm,radius_mm,axis_x,axis_y"
    assert len(rows) == layout.count
    cells = np.array([[int(r["row"]), int(r["col"])] for r in rows])
    np.testing.assert_array_equal(cells, layout.cells)
    numbers = np.array(
        [[float(r[k]) for k in ("x_mm", "y_mm", "radius_mm", "axis_x", "axis_y")] for r in rows]
    )
    np.testing.assert_allclose(numbers[:, :2], layout.centres_mm, atol=1e-6)
    np.testing.assert_allclose(numbers[:, 2], layout.radii_mm, atol=1e-6)
    np.testing.assert_allclose(numbers[:, 3:], layout.axes, atol=1e-9)


def test_exports_of_an_empty_plate() -> None:
    empty = HoleLayout(
        cells=np.zeros((0, 2), dtype=np.int64),
        centres_mm=np.zeros((0, 2)),
        radii_mm=np.zeros(0),
        axes=np.zeros((0, 2)),
        pitch_mm=(1.0, 1.0),
        grid=(2, 2),
        outline_mm=(2.0, 2.0),
        thickness_mm=1.0,
    )
    header, outline = holes_csv(empty).splitlines()  # no rows: the header and the outline
    assert header.startswith("row,col") and outline.startswith("# plate outline_mm 2.000000")
    assert len(re.findall("<circle", svg_text(empty, "holes_black"))) == 0
    mesh = build_mesh(empty, 1e-3)
    assert check_mesh(read_stl(stl_bytes(mesh))).volume_mm3 == pytest.approx(4.0)
    with zipfile.ZipFile(io.BytesIO(threemf_bytes(mesh))) as package:
        assert package.read("3D/3dmodel.model").count(b"<triangle ") == len(mesh.faces)
