"""File formats for the plate: meshes (STL, 3MF), 2D hole maps (DXF, SVG), the hole table and
the STEP B-rep, and `PART_FORMATS`, the one registry of the files a part is written as (adding a
format is one entry there).

Every function returns bytes or str; writing them to disk is the caller's job. All lengths are
millimetres. 2D maps use the part's x right, y up (seen from the eye) and draw each hole at its
mid-thickness centre: for a laser or etch that cuts straight through, that is the best single
position for a tilted hole (it is off by at most thickness / 2 * |axis| at either face).
"""

from __future__ import annotations

import csv
import io
import itertools
import math
import zipfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np

from aperture_fab.fabrication.layout import HoleLayout
from aperture_fab.fabrication.mesh import PlateMesh, outline_points_mm
from aperture_fab.optics.scene import Plate

if TYPE_CHECKING:
    from aperture_fab.config.stages import FabricationSettings
    from aperture_fab.fabrication.part import Part

__all__ = [
    "PART_FORMATS",
    "PART_SUFFIXES",
    "PART_FILE_SUFFIXES",
    "FormatName",
    "PartFormat",
    "Polarity",
    "part_files",
    "dxf_bytes",
    "holes_csv",
    "read_holes_csv",
    "read_stl",
    "stl_bytes",
    "svg_text",
    "threemf_bytes",
]

Polarity = Literal["holes_black", "holes_white"]
POLARITIES: tuple[Polarity, ...] = ("holes_black", "holes_white")

STL_HEADER_BYTES = 80
#: Binary STL record: normal, three vertices (float32), attribute byte count (uint16): 50 bytes.
STL_RECORD = np.dtype([("normal", "<f4", (3,)), ("vertices", "<f4", (3, 3)), ("attribute", "<u2")])
#: Header text; must not start with "solid", which marks ASCII STL to some readers.
STL_HEADER = b"aperture-fab plate, binary STL, units: mm"
#: Decimals written for millimetre coordinates in text formats: 1 nm, far below any process.
MM_DECIMALS = 6
#: Decimals for hole axis slopes (mm per mm).
AXIS_DECIMALS = 9
#: Rows formatted per batch in text mesh formats (bounds the temporary Python objects).
TEXT_BATCH_ROWS = 200_000

THREEMF_CORE_NS = "http://schemas.microsoft.com/3dmanufacturing/core/2015/02"
THREEMF_MODEL_PATH = "3D/3dmodel.model"
THREEMF_CONTENT_TYPES = (
    '<?xml version="1.0" encoding="UTF-8"?>\n'
    '<Types xmlns="http://schemas.openxmlformats.org/package/2006/content-types">'
    '<Default Extension="rels" '
    'ContentType="application/vnd.openxmlformats-package.relationships+xml"/>'
    '<Default Extension="model" '
    'ContentType="application/vnd.ms-package.3dmanufacturing-3dmodel+xml"/>'
    "</Types>\n"
)
THREEMF_RELS = (
    '<?xml version="1.0" encoding="UTF-8"?>\n'
    '<Relationships xmlns="http://schemas.openxmlformats.org/package/2006/relationships">'
    f'<Relationship Target="/{THREEMF_MODEL_PATH}" Id="rel0" '
    'Type="http://schemas.microsoft.com/3dmanufacturing/2013/01/3dmodel"/>'
    "</Relationships>\n"
)
#: Fast deflate: the model text is large and compresses well even at level 1.
ZIP_LEVEL = 1
#: Upper estimates of the model text per vertex and per triangle, and the size above which the
#: zip entry must be Zip64 (streamed entries are sized before they are written).
VERTEX_TEXT_BYTES = 80
TRIANGLE_TEXT_BYTES = 64
ZIP32_SAFE_BYTES = 2**31


def _unit_normals(mesh: PlateMesh) -> np.ndarray:
    """(F, 3) float64 unit face normals (zero for degenerate faces)."""
    v = mesh.vertices
    a, b, c = (v[mesh.faces[:, k]] for k in range(3))
    e1, e2 = b - a, c - a
    # Written out: np.cross is several times slower on millions of rows.
    normal = np.empty_like(e1)
    normal[:, 0] = e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1]
    normal[:, 1] = e1[:, 2] * e2[:, 0] - e1[:, 0] * e2[:, 2]
    normal[:, 2] = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    length = np.sqrt(np.einsum("ij,ij->i", normal, normal))[:, None]
    return np.divide(normal, length, out=np.zeros_like(normal), where=length > 0)


# Binary STL is one numpy record array, as numpy-stl and trimesh hold it inside; both were
# measured (issue 21) and neither kept: numpy-stl stamps the time into the header (no two files
# alike), writes normals that are not unit length and needs python-utils; trimesh (4.8 MB)
# writes a blank header, and reading with it merges vertices to a tolerance (process=True, 5x
# slower than read_stl on 0.5 M triangles), where read_stl merges exactly equal float32 bits.
def stl_bytes(mesh: PlateMesh) -> bytes:
    """Binary STL (little-endian float32, mm) with per-facet unit normals."""
    records = np.zeros(len(mesh.faces), dtype=STL_RECORD)
    records["vertices"] = mesh.vertices.astype(np.float32)[mesh.faces]
    records["normal"] = _unit_normals(mesh)
    header = STL_HEADER.ljust(STL_HEADER_BYTES, b" ")
    count = np.array([len(records)], dtype="<u4").tobytes()
    return header + count + records.tobytes()


def read_stl(data: bytes) -> PlateMesh:
    """Parse binary or ASCII STL, merging vertices whose float32 coordinates are exactly equal
    (ASCII coordinates are rounded to float32 first, as a binary STL stores them)."""
    count = (int(np.frombuffer(data, dtype="<u4", count=1, offset=STL_HEADER_BYTES)[0])
             if len(data) >= STL_HEADER_BYTES + 4 else -1)
    expected = STL_HEADER_BYTES + 4 + count * STL_RECORD.itemsize
    if len(data) != expected and data.lstrip()[:5].lower() == b"solid":
        # A binary STL's header may also start with "solid"; the size decides.
        corners = _ascii_stl_corners(data)
    elif count < 0:
        raise ValueError(f"STL data has {len(data)} bytes; a binary STL has at least 84. "
                         "Export the mesh again as STL.")
    elif len(data) != expected:
        raise ValueError(
            f"STL data has {len(data)} bytes but its header promises {count} facets "
            f"({expected} bytes); it is truncated. Export the mesh again as STL."
        )
    else:
        records = np.frombuffer(data, dtype=STL_RECORD, count=count,
                                offset=STL_HEADER_BYTES + 4)
        corners = records["vertices"].reshape(-1, 3)
    if not np.all(np.isfinite(corners)):
        raise ValueError("STL data has non-finite vertex coordinates (NaN or infinite); "
                         "allowed: finite millimetres. Export the mesh again as STL.")
    # Adding 0 turns -0.0 into 0.0, so equal numbers have equal bits.
    bits = (corners + np.float32(0)).view(np.uint32)
    order = np.lexsort((bits[:, 2], bits[:, 1], bits[:, 0]))
    ordered = bits[order]
    first = np.ones(len(order), dtype=bool)
    first[1:] = np.any(ordered[1:] != ordered[:-1], axis=1)
    inverse = np.empty(len(order), dtype=np.int64)
    inverse[order] = np.cumsum(first) - 1
    vertices = corners[order[first]].astype(np.float64)
    return PlateMesh(vertices=vertices, faces=inverse.reshape(-1, 3))


def _ascii_stl_corners(data: bytes) -> np.ndarray:
    """The facet corners (3K, 3) float32 of an ASCII STL ("solid ... facet ... vertex x y z")."""
    try:
        text = data.decode("ascii")
    except UnicodeDecodeError:
        raise ValueError("STL data starts with 'solid' but is neither ASCII STL nor a binary "
                         "STL of the size its header gives; export the mesh again.") from None
    rows = [line.split()[1:] for line in text.splitlines()
            if line.strip().lower().startswith("vertex")]
    try:
        corners = np.array(rows, dtype=np.float64)
    except ValueError:
        raise ValueError("ASCII STL has a vertex line without three numbers; export the mesh "
                         "again.") from None
    if not rows or corners.shape[1:] != (3,) or len(corners) % 3:
        raise ValueError(f"ASCII STL has {len(rows)} vertex lines; a mesh needs three per facet "
                         "and at least one facet. Export the mesh again.")
    return corners.astype(np.float32)


def _mm_text(value: float) -> str:
    """A length in mm to MM_DECIMALS places without trailing zeros."""
    return f"{value:.{MM_DECIMALS}f}".rstrip("0").rstrip(".")


def _row_batches(values: np.ndarray, row_format: str) -> Iterator[str]:
    """Each row of a 2D array formatted with row_format (%-style), a batch of rows at a time."""
    for start in range(0, len(values), TEXT_BATCH_ROWS):
        batch = values[start : start + TEXT_BATCH_ROWS]
        yield (row_format * len(batch)) % tuple(batch.ravel().tolist())


def _rows_text(values: np.ndarray, row_format: str) -> str:
    return "".join(_row_batches(values, row_format))


def _split_once(text: str, marker: str) -> tuple[str, str]:
    before, found, after = text.partition(marker)
    if not found:
        raise RuntimeError(f"3MF skeleton lacks the placeholder {marker}.")
    return before, after


# lib3mf (6.9 MB, native) was measured (issue 21) and not kept: its Python binding builds a
# ctypes object per vertex and triangle (21 s against 2.6 s here for 0.5 M triangles) and it
# stores coordinates as float32; the core 3MF package is three small XML parts.
def threemf_bytes(mesh: PlateMesh) -> bytes:
    """3MF package (zip) holding the mesh as one object, unit millimetre."""
    try:
        from lxml import etree
    except ImportError as error:
        raise ImportError("threemf_bytes needs the lxml package: pip install lxml") from error
    model = etree.Element(f"{{{THREEMF_CORE_NS}}}model", nsmap={None: THREEMF_CORE_NS})
    model.set("unit", "millimeter")
    model.set("{http://www.w3.org/XML/1998/namespace}lang", "en-US")
    title = etree.SubElement(model, f"{{{THREEMF_CORE_NS}}}metadata", name="Title")
    title.text = "aperture-fab plate"
    resources = etree.SubElement(model, f"{{{THREEMF_CORE_NS}}}resources")
    body = etree.SubElement(resources, f"{{{THREEMF_CORE_NS}}}object", id="1", type="model")
    body.set("name", "plate")
    mesh_element = etree.SubElement(body, f"{{{THREEMF_CORE_NS}}}mesh")
    etree.SubElement(mesh_element, f"{{{THREEMF_CORE_NS}}}vertices")
    etree.SubElement(mesh_element, f"{{{THREEMF_CORE_NS}}}triangles")
    build = etree.SubElement(model, f"{{{THREEMF_CORE_NS}}}build")
    etree.SubElement(build, f"{{{THREEMF_CORE_NS}}}item", objectid="1")
    skeleton = etree.tostring(model, xml_declaration=True, encoding="UTF-8").decode("utf-8")
    # Millions of vertex elements are streamed as text: one lxml element each would take minutes.
    head, after_vertices = _split_once(skeleton, "<vertices/>")
    middle, tail = _split_once(after_vertices, "<triangles/>")
    mm = f"%.{MM_DECIMALS}f"
    pieces = itertools.chain(
        [head, "<vertices>"],
        _row_batches(mesh.vertices, f'<vertex x="{mm}" y="{mm}" z="{mm}"/>'),
        ["</vertices>", middle, "<triangles>"],
        _row_batches(mesh.faces, '<triangle v1="%d" v2="%d" v3="%d"/>'),
        ["</triangles>", tail],
    )
    stream = io.BytesIO()
    with zipfile.ZipFile(stream, "w", zipfile.ZIP_DEFLATED, compresslevel=ZIP_LEVEL) as package:
        package.writestr("[Content_Types].xml", THREEMF_CONTENT_TYPES)
        package.writestr("_rels/.rels", THREEMF_RELS)
        # Zip64 only when needed: some 3MF readers reject it.
        text_bytes = len(mesh.vertices) * VERTEX_TEXT_BYTES + len(mesh.faces) * TRIANGLE_TEXT_BYTES
        large = text_bytes > ZIP32_SAFE_BYTES
        with package.open(THREEMF_MODEL_PATH, "w", force_zip64=large) as model_file:
            for piece in pieces:
                model_file.write(piece.encode("utf-8"))
    return stream.getvalue()


def holes_csv(layout: HoleLayout) -> str:
    """One line per hole: row,col,x_mm,y_mm,radius_mm,axis_x,axis_y (mid-thickness centres),
    then one comment line (HOLES_CSV_COMMENT) with the plate's outline and thickness: last, so
    that the column header stays the first line for CSV readers that expect it there."""
    lines = ["row,col,x_mm,y_mm,radius_mm,axis_x,axis_y\n"]
    table = np.column_stack([layout.cells, layout.centres_mm, layout.radii_mm, layout.axes])
    mm = f"%.{MM_DECIMALS}f"
    axis = f"%.{AXIS_DECIMALS}f"
    lines.append(_rows_text(table, f"%d,%d,{mm},{mm},{mm},{axis},{axis}\n"))
    width, height = layout.outline_mm
    # No commas: a CSV reader that ignores comments sees one stray field, not a fake hole.
    lines.append(f"{HOLES_CSV_COMMENT} plate outline_mm {width:.{MM_DECIMALS}f} x "
                 f"{height:.{MM_DECIMALS}f} (width x height centred on the axis) thickness_mm "
                 f"{layout.thickness_mm:.{MM_DECIMALS}f}\n")
    return "".join(lines)


HOLES_CSV_COLUMNS = ("row", "col", "x_mm", "y_mm", "radius_mm", "axis_x", "axis_y")
#: A hole table line that starts with this is a comment (holes_csv writes the outline there).
HOLES_CSV_COMMENT = "#"
#: How far (per mm of z) a hole table's axes may differ from (E_xy - centres) / D and still be
#: read as convergent: the table rounds centres to 1 nm and axes to 1e-9, far inside this.
CSV_CONVERGE_AXIS_TOL = 1e-6


def _csv_number(text: str, column: str, where: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{where}: {column} = {text!r} is not a number; write a decimal "
                         "number, e.g. 0.125.") from None
    if not math.isfinite(value):
        raise ValueError(f"{where}: {column} = {text!r}; allowed: a finite number.")
    return value


def _csv_index(text: str, column: str, count: int, where: str) -> int:
    value = _csv_number(text, column, where)
    if not (value.is_integer() and 0 <= value < count):
        raise ValueError(f"{where}: {column} = {text!r}; allowed: a whole number from 0 to "
                         f"{count - 1} (the plate's grid has {count} {column}s).")
    return int(value)


def read_holes_csv(
    text: str,
    plate: Plate,
    *,
    outline_mm: tuple[float, float],
    converge_mm: tuple[float, float, float] | None = None,
    source: str = "holes.csv",
) -> HoleLayout:
    """The hole table that holes_csv writes, read back as a HoleLayout on `plate`'s grid
    (pitch, cell count, thickness); the inverse of holes_csv, also for tables edited by hand.

    The table holds neither the outline nor the point chief-ray holes aim at, so they are given:
    outline_mm (width, height) of the plate and converge_mm (ex, ey, D) (HoleLayout). When every
    axis is within CSV_CONVERGE_AXIS_TOL of (E_xy - centres) / D, the axes are set exactly to
    that (the table rounds them) and the layout keeps converge_mm; otherwise it gets the table's
    axes and converge_mm None. A hole is closed by deleting its line or setting its radius to 0.
    Columns may come in any order; blank lines and comment lines (starting with #, like the
    outline line holes_csv writes last) are skipped. source names the table in errors.
    """
    rows = [r for r in csv.reader(io.StringIO(text)) if any(field.strip() for field in r)
            and not r[0].lstrip().startswith(HOLES_CSV_COMMENT)]
    if not rows:
        raise ValueError(f"{source} is empty; a hole table starts with the header "
                         f"{','.join(HOLES_CSV_COLUMNS)}. Give the holes.csv a design wrote.")
    header = [name.strip().lower() for name in rows[0]]
    if sorted(header) != sorted(HOLES_CSV_COLUMNS):
        raise ValueError(f"{source}: the header is {','.join(rows[0])!r}; a hole table has the "
                         f"columns {','.join(HOLES_CSV_COLUMNS)} (any order), as holes_csv "
                         "writes them. Give the holes.csv a design wrote, its header kept.")
    index = {name: header.index(name) for name in HOLES_CSV_COLUMNS}
    nx, ny = plate.cells
    seen: dict[tuple[int, int], int] = {}
    cells, centres, radii, axes = [], [], [], []
    for number, fields in enumerate(rows[1:], start=2):
        where = f"{source} line {number}"
        if len(fields) != len(HOLES_CSV_COLUMNS):
            raise ValueError(f"{where} has {len(fields)} fields; every line needs "
                             f"{len(HOLES_CSV_COLUMNS)} ({','.join(HOLES_CSV_COLUMNS)}). Fix "
                             "that line.")
        row = _csv_index(fields[index["row"]], "row", ny, where)
        col = _csv_index(fields[index["col"]], "col", nx, where)
        x, y, radius, ax, ay = (_csv_number(fields[index[name]], name, where)
                                for name in HOLES_CSV_COLUMNS[2:])
        if radius < 0:
            raise ValueError(f"{where}: radius_mm = {radius:g}; allowed: >= 0 (0 closes the "
                             "hole).")
        if (row, col) in seen:
            raise ValueError(f"{where}: cell ({row}, {col}) is listed again (first on line "
                             f"{seen[row, col]}); give each cell at most one hole.")
        seen[row, col] = number
        if radius == 0:
            continue
        cells.append((row, col))
        centres.append((x, y))
        radii.append(radius)
        axes.append((ax, ay))
    centres_mm = np.asarray(centres, dtype=np.float64).reshape(-1, 2)
    axes_mm = np.asarray(axes, dtype=np.float64).reshape(-1, 2)
    if converge_mm is not None:
        ex, ey, distance = converge_mm
        want = (np.array([ex, ey]) - centres_mm) / distance
        if len(want) and float(np.max(np.abs(axes_mm - want))) > CSV_CONVERGE_AXIS_TOL:
            converge_mm = None  # edited axes: keep them as written
        else:
            axes_mm = want
    return HoleLayout(
        cells=np.asarray(cells, dtype=np.int64).reshape(-1, 2),
        centres_mm=centres_mm,
        radii_mm=np.asarray(radii, dtype=np.float64),
        axes=axes_mm,
        pitch_mm=plate.pitch_mm,
        grid=plate.cells,
        outline_mm=outline_mm,
        thickness_mm=plate.thickness_mm,
        converge_mm=converge_mm,
    )


def dxf_bytes(layout: HoleLayout, corner_cut_mm: float = 0.0) -> bytes:
    """DXF (R2010, $INSUNITS = 4, mm): the outline as a closed LWPOLYLINE on layer OUTLINE and
    each hole as a CIRCLE on layer HOLES at its mid-thickness centre (module docstring)."""
    try:
        import ezdxf
    except ImportError as error:
        raise ImportError("dxf_bytes needs the ezdxf package: pip install ezdxf") from error
    doc = ezdxf.new("R2010", units=ezdxf.units.MM)
    doc.header["$MEASUREMENT"] = 1  # metric
    doc.layers.add("OUTLINE", color=7)
    doc.layers.add("HOLES", color=1)
    space = doc.modelspace()
    space.add_lwpolyline(
        outline_points_mm(layout, corner_cut_mm), close=True, dxfattribs={"layer": "OUTLINE"}
    )
    for (x, y), radius in zip(layout.centres_mm.tolist(), layout.radii_mm.tolist(), strict=True):
        space.add_circle((x, y), radius, dxfattribs={"layer": "HOLES"})
    stream = io.StringIO()
    doc.write(stream)
    return stream.getvalue().encode(doc.output_encoding)


def svg_text(layout: HoleLayout, polarity: Polarity, corner_cut_mm: float = 0.0) -> str:
    """SVG at 1:1 (width and height in mm, viewBox in mm, y flipped so up is up): the plate
    filled in one colour and the holes (mid-thickness centres) in the other.

    polarity: "holes_black" (plate white, holes black) or "holes_white" (plate black, holes
        white), whichever the film or resist process needs.
    """
    if polarity not in POLARITIES:
        raise ValueError(f"polarity = {polarity!r} is not allowed; choose one of {POLARITIES}.")
    plate, hole = ("white", "black") if polarity == "holes_black" else ("black", "white")
    width, height = layout.outline_mm
    mm = f"%.{MM_DECIMALS}f"
    # Text, not an SVG library: only numbers and fixed colour names go in (nothing to escape),
    # and the circles are formatted in batches like the 3MF's vertices.
    # SVG y grows downward: svg = (x + width / 2, height / 2 - y).
    outline = " ".join(
        f"{x + width / 2:.{MM_DECIMALS}f},{height / 2 - y:.{MM_DECIMALS}f}"
        for x, y in outline_points_mm(layout, corner_cut_mm)
    )
    svg_xy = np.column_stack(
        [layout.centres_mm[:, 0] + width / 2, height / 2 - layout.centres_mm[:, 1]]
    )
    circles = _rows_text(
        np.column_stack([svg_xy, layout.radii_mm]),
        f'<circle cx="{mm}" cy="{mm}" r="{mm}"/>\n',
    )
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        f'<svg xmlns="http://www.w3.org/2000/svg" version="1.1" width="{_mm_text(width)}mm" '
        f'height="{_mm_text(height)}mm" viewBox="0 0 {_mm_text(width)} {_mm_text(height)}">\n'
        f'<polygon points="{outline}" fill="{plate}" stroke="none"/>\n'
        f'<g fill="{hole}" stroke="none">\n{circles}</g>\n'
        "</svg>\n"
    )


# -- the registry of part files -----------------------------------------------------------------

FormatName = Literal["stl", "3mf", "csv", "dxf", "svg", "step"]
#: Called with the number of holes done so far (STEP, the slow one, reports its progress).
Progress = Callable[[int], None]


@dataclass(frozen=True)
class PartFormat:
    """One file a part is written as.

    name: the format's key. file_name: its name in an output folder. suffixes: what `--out`
    may end with to name it (lower case). write: (part, settings, progress) -> the file's bytes.
    """

    name: FormatName
    file_name: str
    suffixes: tuple[str, ...]
    write: Callable[[Part, FabricationSettings, Progress | None], bytes]


def _step(part: Part, settings: FabricationSettings, progress: Progress | None) -> bytes:
    from aperture_fab.fabrication.step import step_bytes  # OCCT: an optional, heavy package

    return step_bytes(part.layout, progress, corner_cut_mm=part.corner_cut_mm)


#: Every format, in the order a design writes them (STEP only when asked for: it is slow).
PART_FORMATS: dict[FormatName, PartFormat] = {f.name: f for f in (
    PartFormat("stl", "plate.stl", (".stl",), lambda part, _s, _p: stl_bytes(part.mesh)),
    PartFormat("3mf", "plate.3mf", (".3mf",), lambda part, _s, _p: threemf_bytes(part.mesh)),
    PartFormat("csv", "holes.csv", (".csv",), lambda part, _s, _p: holes_csv(part.layout).encode()),
    PartFormat("dxf", "plate.dxf", (".dxf",),
               lambda part, _s, _p: dxf_bytes(part.layout, corner_cut_mm=part.corner_cut_mm)),
    PartFormat("svg", "plate.svg", (".svg",),
               lambda part, settings, _p: svg_text(part.layout, settings.svg_polarity,
                                                   corner_cut_mm=part.corner_cut_mm).encode()),
    PartFormat("step", "plate.step", (".step", ".stp"), _step),
)}
#: Suffixes that name a part file (an --out ending in one names the file, not a folder).
PART_SUFFIXES: tuple[str, ...] = tuple(
    suffix for fmt in PART_FORMATS.values() for suffix in fmt.suffixes if fmt.name != "csv")
#: Every format's suffixes, the hole table's too (what `export` writes).
PART_FILE_SUFFIXES: tuple[str, ...] = tuple(
    suffix for fmt in PART_FORMATS.values() for suffix in fmt.suffixes)


def part_files(part: Part, formats: tuple[FormatName, ...], settings: FabricationSettings,
               progress: Progress | None = None) -> dict[str, bytes]:
    """File name -> content for the requested formats."""
    return {PART_FORMATS[name].file_name: PART_FORMATS[name].write(part, settings, progress)
            for name in formats}

