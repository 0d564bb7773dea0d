"""The assembly sheet: one printable HTML page that says how to make and put together the device
for one design (docs/assembly.md explains it).

Values in, HTML text out: the part as built, the design's scene, the process and the design's
target names. The page holds the plate drawing (outline, alignment key, thickness, holes), the
device in section (display, frame, plate, eye), where and which way up the display image goes on
the panel, the calibration coupon of docs/processes.md and a numbered procedure. Its drawings are
inline SVG in millimetres (aperture_fab.report.assembly_drawings); printed at 100 % on A4
they hold their stated scale, which the page's 1:1 scale bar lets the reader check.

The commands it prints (the cad/ scripts for the frame and a STEP coupon) run as printed: in
the design folder the sheet names, with the Python and the script paths of `CommandSetup`, each
with what it needs (the cad extra) and how to install it.
"""

from __future__ import annotations

import base64
import html
import math
import shlex
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from aperture_fab.fabrication.coupon import Coupon, calibration_coupon
from aperture_fab.fabrication.layout import HoleLayout, layout_stats
from aperture_fab.fabrication.part import Part
from aperture_fab.fabrication.process import Process
from aperture_fab.optics.scene import Scene
from aperture_fab.report.assembly_drawings import (
    StackSizes,
    coupon_drawing,
    placement_drawing,
    plate_drawing,
    scale_bar,
    stack_drawing,
)

__all__ = ["AssemblyFacts", "CommandSetup", "assembly_facts", "assembly_html",
           "calibration_coupon"]

#: The frame's ledge assumed in the section drawing (cad/mount_frame.py's default), mm.
FRAME_LEDGE_MM = 1.0
MM_PER_INCH = 25.4
#: The files the sheet's set puts beside it in the design folder (aperture_fab.pipeline.
#: assembly_job writes them): the coupon as a mesh, as a 2D map, and its hole table.
COUPON_STL, COUPON_SVG, COUPON_CSV = "coupon.stl", "coupon.svg", "coupon_holes.csv"
#: What the cad/ scripts write when run as the sheet prints them (in the design folder; names
#: that no design set uses, so they never clash with its files).
FRAME_OUT, COUPON_STEP_OUT = "frame.stl", "coupon.step"
#: The optional dependency the cad/ scripts need (pyproject.toml) and its installed size.
CAD_EXTRA = "cad"
CAD_EXTRA_SIZE = "about 1.3 GB installed: CadQuery, OCCT and VTK"
CAD_INSTALL = f"pip install 'aperture-fab[{CAD_EXTRA}]'"
#: The frame command's example display module: the panel's active area (or the plate, if
#: wider) plus this border each side, and a bezel this high (cad/mount_frame.py's default).
EXAMPLE_BORDER_MM = 5.0
EXAMPLE_BEZEL_MM = 0.5

CSP = "default-src 'none'; img-src data:; style-src 'unsafe-inline'"
CSS = """
body { font: 14px/1.45 system-ui, sans-serif; color: #222; margin: 0; background: #fafafa; }
main { max-width: 190mm; margin: 0 auto; padding: 1rem 1.5rem 3rem; background: #fff; }
h1 { font-size: 1.5rem; } h2 { border-bottom: 1px solid #ccc; margin-top: 2rem; }
table { border-collapse: collapse; margin: 0.5rem 0; }
th, td { border: 1px solid #ddd; padding: 0.15rem 0.5rem; text-align: left; }
td.n { text-align: right; font-variant-numeric: tabular-nums; }
.note { background: #fff6d6; border-left: 4px solid #e0b000; padding: 0.4rem 0.8rem; }
figure { margin: 0.8rem 0; } figcaption { font-size: 0.9em; color: #555; }
svg.drawing { display: block; overflow: visible; }
svg text { fill: #222; font-family: system-ui, sans-serif; }
svg .outline { fill: #e8eef6; stroke: #123; }
svg .grid { fill: none; stroke: #88a; stroke-dasharray: 0.4 0.3; }
svg .holes circle { fill: #000; }
svg .dim, svg .ext, svg .leader, svg .bar { stroke: #333; }
svg .key { fill: #b00; font-weight: bold; }
svg .display { fill: #333; stroke: none; }
svg .frame { fill: #ccc; stroke: #888; }
svg .plate-section { fill: #123; stroke: #123; }
svg .pupil { stroke: #06c; } svg .eyebox { stroke: #06c; stroke-dasharray: 0.5 0.5; }
svg .image { fill: #f4f4f4; stroke: #333; } svg .first-pixel { fill: #b00; }
svg .plate-over { fill: none; stroke: #123; stroke-dasharray: 1 0.5; }
svg .axis { stroke: #b00; }
.thumbs img { width: 40mm; image-rendering: pixelated; border: 1px solid #999; }
.thumbs figure { display: inline-block; margin-right: 1rem; }
pre { font-size: 0.8em; max-height: 12rem; overflow: auto; background: #f4f4f4; }
pre.command { white-space: pre-wrap; word-break: break-all; padding: 0.3rem 0.5rem; }
p.needs { font-size: 0.9em; color: #444; margin-top: 0; }
@page { size: A4; margin: 12mm; }
@media print {
  body { background: #fff; font-size: 10.5pt; }
  main { max-width: none; padding: 0; }
  section, figure, table { break-inside: avoid; }
  h2 { break-after: avoid; }
  details > pre { max-height: none; overflow: visible; }
}
"""


@dataclass(frozen=True)
class AssemblyFacts:
    """The numbers the sheet states (mm unless named otherwise).

    hole_count, smallest_hole_mm, largest_hole_mm: holes as drawn (None without holes).
    made_bias_mm: the process's radius bias (made = drawn + bias).
    open_area_fraction: open area over the cell grid's area.
    eye_face_grid_mm, display_face_grid_mm: the hole pattern's width at each face.
    pixel_mm: the display's pixel pitch (x, y). ppi: pixels per inch along x.
    view_step_mm: one view pixel's footprint on the panel (gap x view step in tan).
    scale_tolerance: largest relative scale (or rotation, in radians) error of the image on
        the panel that keeps the mismatch at the hole grid's corner below half view_step_mm.
    """

    hole_count: int
    smallest_hole_mm: float | None
    largest_hole_mm: float | None
    made_bias_mm: float
    open_area_fraction: float
    eye_face_grid_mm: float
    display_face_grid_mm: float
    pixel_mm: tuple[float, float]
    ppi: float
    view_step_mm: float
    scale_tolerance: float


@dataclass(frozen=True)
class CommandSetup:
    """Where and with what the sheet's commands run, so that they run as printed.

    folder: the design folder; every command runs there and names its files relative to it
        (absolute when the sheet is written by a job; aperture_fab.pipeline.assembly_job).
    python: the Python that has aperture-fab installed (the one that wrote the sheet).
    cad_folder: the folder of the cad/ scripts; relative ("cad") where this installation has
        none (installed without its source tree): the sheet then says where they come from.
    cad_install: the command that installs the cad extra into that Python.
    """

    folder: Path
    python: str = "python"
    cad_folder: Path = Path("cad")
    cad_install: str = CAD_INSTALL


@dataclass(frozen=True)
class SheetCommand:
    """One command the sheet prints: its words, what it writes, whether it needs the cad
    extra."""

    argv: tuple[str, ...]
    writes: str
    needs_cad: bool


def assembly_facts(layout: HoleLayout, scene: Scene, process: Process) -> AssemblyFacts:
    """The sheet's numbers for a layout in its scene."""
    stats = layout_stats(layout)
    display, plate, eye = scene.display, scene.plate, scene.eye
    grid_w = layout.grid[0] * layout.pitch_mm[0]
    grid_h = layout.grid[1] * layout.pitch_mm[1]
    pixel = (display.width_mm / display.pixels[0], display.height_mm / display.pixels[1])
    tan_step = 2 * math.tan(math.radians(eye.fov_deg[0]) / 2) / eye.view_pixels[0]
    view_step = plate.gap_mm * tan_step
    return AssemblyFacts(
        hole_count=layout.count,
        smallest_hole_mm=stats["smallest_hole_diameter_mm"],
        largest_hole_mm=stats["largest_hole_diameter_mm"],
        made_bias_mm=process.radius_bias_mm,
        open_area_fraction=float(stats["open_area_fraction"]),
        eye_face_grid_mm=grid_w * layout.grid_scale(layout.thickness_mm / 2),
        display_face_grid_mm=grid_w * layout.grid_scale(-layout.thickness_mm / 2),
        pixel_mm=pixel,
        ppi=MM_PER_INCH / pixel[0],
        view_step_mm=view_step,
        scale_tolerance=(view_step / 2) / (math.hypot(grid_w, grid_h) / 2),
    )


def _e(value: object) -> str:
    return html.escape(str(value), quote=True)


def _mm(value: float | None, digits: int = 3) -> str:
    return "none" if value is None else f"{value:.{digits}f} mm"


def _table(rows: Sequence[tuple[str, str]]) -> str:
    return "<table>" + "".join(f"<tr><th>{_e(k)}</th><td>{_e(v)}</td></tr>"
                               for k, v in rows) + "</table>"


def _figure(svg: str, caption: str) -> str:
    return f"<figure>{svg}<figcaption>{_e(caption)}</figcaption></figure>"


def _number(value: float) -> str:
    """A length for a command line: up to 4 decimals, no trailing zeros (22, 0.6, 21.25)."""
    return f"{value:.4f}".rstrip("0").rstrip(".")


def _where(setup: CommandSetup) -> str:
    """The folder the commands run in, as the sheet states it."""
    if setup.folder.is_absolute():
        return f"the design folder ({shlex.join(['cd', str(setup.folder)])})"
    return f"the design folder ({setup.folder})"


def _cad_script(setup: CommandSetup, name: str) -> str:
    return str(setup.cad_folder / name)


def _command(command: SheetCommand, setup: CommandSetup) -> str:
    """A command as the sheet prints it: one line to copy, then where to run it and, for the
    cad/ scripts, what it needs and how to install it."""
    needs = "cad" if command.needs_cad else ""
    line = shlex.join(command.argv)
    notes = [f"Run in {_e(_where(setup))}; it writes {_e(command.writes)} there."]
    if command.needs_cad:
        notes.append(
            f"Needs the <b>{CAD_EXTRA}</b> extra ({_e(CAD_EXTRA_SIZE)}), not installed with "
            f"aperture-fab itself: <code>{_e(setup.cad_install)}</code>.")
        if not setup.cad_folder.is_absolute():
            notes.append(f"The script is in the {_e(setup.cad_folder)}/ folder of aperture-fab's "
                         "source tree; give its path there.")
    return (f'<pre class="command" data-cwd="{_e(setup.folder)}" data-needs="{needs}">'
            f'{_e(line)}</pre><p class="needs">{" ".join(notes)}</p>')


def _example_module_mm(scene: Scene, part: Part) -> tuple[float, float]:
    """The frame command's example display module outline: the panel's active area, or the
    plate where it is wider, rounded up to whole mm, plus EXAMPLE_BORDER_MM each side."""
    display = scene.display
    width, height = part.layout.outline_mm
    return (math.ceil(max(display.width_mm, width)) + 2 * EXAMPLE_BORDER_MM,
            math.ceil(max(display.height_mm, height)) + 2 * EXAMPLE_BORDER_MM)


def _frame_command(scene: Scene, part: Part, setup: CommandSetup) -> SheetCommand:
    """cad/mount_frame.py for this design, with an example display module that fits it."""
    module = _example_module_mm(scene, part)
    argv = (setup.python, _cad_script(setup, "mount_frame.py"), "--design", ".", "--display",
            _number(module[0]), _number(module[1]), "--bezel-height", _number(EXAMPLE_BEZEL_MM),
            "--out", FRAME_OUT)
    return SheetCommand(argv, FRAME_OUT, needs_cad=True)


def _coupon_command(coupon: Coupon, setup: CommandSetup) -> SheetCommand:
    """cad/plate_from_csv.py for the coupon: a STEP B-rep from its hole table."""
    width, height = coupon.outline_mm
    argv = (setup.python, _cad_script(setup, "plate_from_csv.py"), COUPON_CSV, "--width",
            _number(width), "--height", _number(height), "--thickness",
            _number(coupon.thickness_mm), "--corner-cut", _number(coupon.corner_cut_mm),
            "--out", COUPON_STEP_OUT)
    return SheetCommand(argv, COUPON_STEP_OUT, needs_cad=True)


def _thumbs(displays: Mapping[str, bytes]) -> str:
    items = "".join(
        f'<figure><img alt="{_e(name)}" src="data:image/png;base64,'
        f'{base64.b64encode(data).decode()}"><figcaption>display_{_e(name)}.png, top-left '
        "corner = pixel (row 0, column 0)</figcaption></figure>"
        for name, data in displays.items())
    return f'<div class="thumbs">{items}</div>' if items else ""


def _plate_section(part: Part, scene: Scene, process: Process, facts: AssemblyFacts) -> str:
    layout, plate = part.layout, scene.plate
    width, height = layout.outline_mm
    cut = part.corner_cut_mm
    tilted = plate.hole_axis == "chief_ray"
    face = ("the eye-side face is the one whose hole pattern is smaller "
            f"({facts.eye_face_grid_mm:.3f} mm across against {facts.display_face_grid_mm:.3f} "
            "mm on the display side): the holes lean toward the eye" if tilted else
            "the holes are straight, so only the chamfer tells the faces apart")
    bias = ("" if facts.made_bias_mm == 0 else
            f" (made about {2 * facts.made_bias_mm:+.3f} mm on the diameter: the process's bias)")
    rows = [
        ("outline", f"{width:g} x {height:g} mm (cell grid {layout.grid[0]} x {layout.grid[1]} "
                    f"of {layout.pitch_mm[0]:g} x {layout.pitch_mm[1]:g} mm, plus the margin)"),
        ("alignment key", f"{cut:.3f} mm x {cut:.3f} mm 45-degree chamfer on the top-left "
                          "corner, seen from the eye" if cut > 0 else
                          "none (fabrication.alignment_cut = false): mark the top-left corner"),
        ("thickness", f"{layout.thickness_mm:g} mm"),
        ("holes", f"{facts.hole_count}; drawn diameters {_mm(facts.smallest_hole_mm)} to "
                  f"{_mm(facts.largest_hole_mm)}{bias}"),
        ("hole axes", "tilted toward the eye (chief ray)" if tilted else "straight"),
        ("open area", f"{100 * facts.open_area_fraction:.2f} % of the hole grid"),
        ("process", f"{process.name}: smallest hole {process.min_hole_for(plate.thickness_mm):g}"
                    f" mm, web {process.min_web_for(plate.thickness_mm):g} mm"),
        ("faces", f"plate.stl's top face (z = {layout.thickness_mm:g} mm in the file) faces the "
                  f"eye; {face}"),
    ]
    return (
        '<section id="plate"><h2>1. The plate</h2>' + _table(rows)
        + _figure(plate_drawing(layout, cut),
                  "The plate seen from the eye side. Holes black (at the eye-side face); dashed: "
                  "the cell grid. The chamfered corner is top-left only when the eye-side face "
                  "is toward you and the image's top is up; turned over it is top-right.")
        + "<p>plate.svg and plate.dxf are drawn the same way (seen from the eye). A film or "
          "sheet cut from them may be used either way up only if, once mounted, the chamfer is "
          "top-left seen from the eye.</p></section>")


def _stack_section(scene: Scene, part: Part, setup: CommandSetup) -> str:
    plate, eye, display = scene.plate, scene.eye, scene.display
    eyebox = float(eye.eyebox_mm[0]) if eye.eyebox_mm is not None else 0.0
    sizes = StackSizes(display.width_mm, part.layout.outline_mm[0], plate.gap_mm,
                       plate.thickness_mm, eye.eye_relief_mm, eye.pupil_mm, eyebox,
                       FRAME_LEDGE_MM)
    module = _example_module_mm(scene, part)
    return (
        '<section id="frame"><h2>2. The frame and the stack</h2>'
        + _figure(stack_drawing(sizes),
                  "Section through the device: the frame (grey, schematic) rests on the display "
                  "and holds the plate on a ledge with its display-side face at the gap.")
        + _table([("gap", f"{plate.gap_mm:g} mm: display emitting surface to the plate's "
                          "display-side face"),
                  ("eye relief", f"{eye.eye_relief_mm:g} mm: plate's eye-side face to the pupil"),
                  ("plate top above the display", f"{plate.gap_mm + plate.thickness_mm:g} mm")])
        + "<p>Make the frame with cad/mount_frame.py:</p>"
        + _command(_frame_command(scene, part, setup), setup)
        + f"<p>--display {_number(module[0])} {_number(module[1])} and --bezel-height "
          f"{_number(EXAMPLE_BEZEL_MM)} are an example (the panel's active area, "
          f"{display.width_mm:g} x {display.height_mm:g} mm, or the plate if wider, with a "
          f"{EXAMPLE_BORDER_MM:g} mm border): give your display module's "
          "measured outline (width, height) and how far its bezel stands above the emitting "
          "surface. It reads the plate's outline, thickness, gap and chamfer from the design; "
          "its pocket has a matching key, so the plate seats only the right way round. Measure "
          "the printed gap (the ledge's height above the display surface); the design's "
          "sharpness is set by it.</p></section>")


def _display_section(scene: Scene, part: Part, facts: AssemblyFacts, names: Sequence[str],
                     displays: Mapping[str, bytes]) -> str:
    scene = scene
    display, plate = scene.display, scene.plate
    files = ", ".join(f"display_{n}.png" for n in names)
    step_px = facts.view_step_mm / facts.pixel_mm[0]
    rows = [
        ("image files", files),
        ("image size", f"{display.pixels[0]} x {display.pixels[1]} pixels"),
        ("physical size", f"{display.width_mm:g} x {display.height_mm:g} mm on the panel"),
        ("panel pixel pitch", f"{facts.pixel_mm[0]:.4f} x {facts.pixel_mm[1]:.4f} mm "
                              f"({facts.ppi:.0f} ppi)"),
        ("orientation", "as the file reads, not mirrored, seen from the eye: row 0 at the top, "
                        "column 0 at the left (the plate's chamfered corner is over the image's "
                        "top-left)"),
        ("centre", "the image's centre on the plate's centre (the optical axis)"),
        ("one view pixel", f"{facts.view_step_mm:.4f} mm on the panel ({step_px:.2f} panel "
                           "pixels)"),
        ("scale and rotation", f"within {100 * facts.scale_tolerance:.2f} % and "
                               f"{math.degrees(facts.scale_tolerance):.2f} degrees"),
    ]
    return (
        '<section id="display"><h2>3. The display image on the panel</h2>'
        + '<p class="note">Show the image <b>1:1, pixel for pixel</b>: one image pixel on one '
          "panel pixel, no scaling, no filtering, no colour management or dimming tricks. The "
          f"design assumes a panel of {facts.pixel_mm[0]:.4f} mm pixels; if yours differ, set "
          "display.width_mm, height_mm and pixels in design.toml to your panel's and design "
          "again.</p>"
        + _table(rows)
        + _figure(placement_drawing((display.width_mm, display.height_mm), display.pixels,
                                    part.layout, part.corner_cut_mm),
                  "The image on the panel seen from the eye, with the plate's outline over it "
                  "(dashed). Red: the image's first pixel (row 0, column 0).")
        + _thumbs(displays)
        + "<p>Why 1:1: through each hole the eye sees a small patch of the panel, the display "
          f"point at tan(angle) = (x_display - x_hole) / gap. Moving the image by "
          f"{facts.view_step_mm:.4f} mm moves the picture by one view pixel; a scale or "
          "rotation error moves each hole's patch by an amount that grows toward the edges, "
          "so patches and holes no longer match and the picture blurs and doubles. The limits "
          f"above keep that mismatch below half a view pixel at the hole grid's corners "
          f"(gap {plate.gap_mm:g} mm).</p>"
        + "<p>Checking alignment: (1) with calipers, the image measures "
          f"{display.width_mm:g} x {display.height_mm:g} mm on the panel; (2) look through the "
          "plate (or put a phone camera where the eye goes, focused far): a design of the "
          "marker target (examples/make_targets.py writes marker-F.png) must show an upright, "
          "unmirrored F; a mirrored F means the image or the plate is flipped; (3) if the "
          "picture is doubled or soft, shift the image on the panel a whole pixel at a time "
          "(left/right, up/down) and keep the sharpest; (4) turn the panel's brightness up: "
          f"the plate passes about {100 * facts.open_area_fraction:.2f} % of the panel's "
          "light.</p></section>")


def _coupon_section(coupon: Coupon, process: Process, setup: CommandSetup) -> str:
    width, height = coupon.outline_mm
    sizes = ", ".join(f"{1000 * d:.0f}" for d in coupon.diameters_mm)
    return (
        '<section id="coupon"><h2>4. Calibration coupon (print it first)</h2>'
        + f"<p>The {_e(process.name)} numbers are planning numbers (docs/processes.md, "
          "\"Calibration print\"). Before the plate, make this coupon with the same machine, "
          f"material and settings: blocks of {coupon.repeat} x {coupon.repeat} holes at the "
          f"design's pitch ({coupon.pitch_mm:g} mm) and thickness ({coupon.thickness_mm:g} mm), "
          f"drawn diameters {sizes} um, smallest on the left (chamfer top-left).</p>"
        + f"<p>The design folder holds it as a part: <b>{COUPON_STL}</b> (the solid, "
          f"{width:.2f} x {height:.2f} x {coupon.thickness_mm:g} mm, for a printer), "
          f"<b>{COUPON_SVG}</b> (1:1, seen from above, for film or a laser, drawn like "
          f"plate.svg) and <b>{COUPON_CSV}</b> (its hole table). They need nothing beyond "
          "aperture-fab. For a STEP B-rep to edit in CAD:</p>"
        + _command(_coupon_command(coupon, setup), setup)
        + _figure(coupon_drawing(coupon), "The calibration coupon seen from above.")
        + "<p>Hold it against a light under a loupe or microscope. The smallest drawn size "
          "whose holes are <i>all</i> open gives min_hole_mm (its measured diameter); for each "
          "size, (measured - drawn) / 2 is radius_bias_mm; the spread within a size is "
          "radius_sigma_mm; the thinnest web that survived is min_web_mm. Put them in a "
          "[process] table of the config and design again.</p>"
        + "<table><tr><th>drawn (um)</th><th>all open?</th><th>measured diameter (um)</th>"
          "<th>webs intact?</th></tr>"
        + "".join(f'<tr><td class="n">{1000 * d:.0f}</td><td></td><td></td><td></td></tr>'
                  for d in coupon.diameters_mm) + "</table></section>")


def _procedure(scene: Scene, names: Sequence[str]) -> str:
    plate = scene.plate
    first = f"display_{names[0]}.png" if names else "the display image"
    steps = [
        "Print this sheet at 100 % (no \"fit to page\"); the scale bar must measure 50 mm.",
        f"Make the calibration coupon ({COUPON_STL} or {COUPON_SVG}; section 4), measure it, "
        "update the config's [process] table if the numbers differ, and design again.",
        f"Make the plate (plate.stl, or plate.svg / plate.dxf for cutting or masks). Check its "
        f"thickness ({plate.thickness_mm:g} mm), that the holes are open and the chamfer is "
        "there.",
        "Make the frame with section 2's command (your display module's outline and bezel "
        "height in it). Check the gap with calipers.",
        f"Show {first} on the panel 1:1 (section 3) and measure its size on the panel.",
        "Seat the frame on the display, centred on the image.",
        "Lay the plate in the pocket, eye-side face up, the chamfer into the frame's key "
        "(top-left seen from the eye).",
        "Look through the plate at the eye relief: check orientation and sharpness as in "
        "section 3; shift the image by whole pixels until sharpest.",
    ]
    return ('<section id="procedure"><h2>5. Assembly procedure</h2><ol>'
            + "".join(f"<li>{_e(s)}</li>" for s in steps) + "</ol></section>")


def assembly_html(part: Part, scene: Scene, process: Process, names: Sequence[str], *,
                  design_name: str = "design", displays: Mapping[str, bytes] | None = None,
                  commands: CommandSetup | None = None) -> str:
    """The assembly sheet for a part built for `scene` by `process`.

    names: the design's target names (its display images are display_<name>.png).
    design_name: how the page names the design (its folder, say). displays: optional PNG bytes
    per name, shown as thumbnails. commands: where and with what the printed commands run
    (default: "python" in a folder named design_name, the scripts in cad/).
    """
    setup = commands if commands is not None else CommandSetup(Path(design_name))
    if part.layout.grid != scene.plate.cells:
        raise ValueError(f"the part's grid {part.layout.grid} is not the scene's plate.cells "
                         f"{scene.plate.cells}; give the config the part was made with.")
    facts = assembly_facts(part.layout, scene, process)
    coupon = calibration_coupon(process, scene.plate)
    title = f"Assembly sheet: {design_name}"
    width, height = part.layout.outline_mm
    summary = (f"Plate {width:g} x {height:g} x {scene.plate.thickness_mm:g} mm, "
               f"{facts.hole_count} holes, {process.name}; gap {scene.plate.gap_mm:g} mm; "
               f"display image {scene.display.pixels[0]} x "
               f"{scene.display.pixels[1]} px on {scene.display.width_mm:g} x "
               f"{scene.display.height_mm:g} mm.")
    body = "\n".join([
        f"<h1>{_e(title)}</h1>",
        f"<p>{_e(summary)}</p>",
        '<p class="note">Print at <b>100 %</b> (actual size, no "fit to page") on A4. Each '
        "drawing states its scale; this bar is 50 mm at 1:1. Measure it before trusting any "
        "drawing.</p>",
        scale_bar(),
        f"<p>The commands on this sheet run in {_e(_where(setup))}, with the Python that has "
        f"aperture-fab installed ({_e(setup.python)}); each says what it needs.</p>",
        _plate_section(part, scene, process, facts),
        _stack_section(scene, part, setup),
        _display_section(scene, part, facts, names, displays or {}),
        _coupon_section(coupon, process, setup),
        _procedure(scene, names),
        "<p>Generated by aperture-fab; the guide is docs/assembly.md.</p>",
    ])
    return (f'<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
            f'<meta http-equiv="Content-Security-Policy" content="{CSP}">\n'
            f"<title>{_e(title)}</title>\n<style>{CSS}</style>\n</head>\n<body>\n<main>\n"
            f"{body}\n</main>\n</body>\n</html>\n")
