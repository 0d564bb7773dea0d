"""The `aperture-fab` argument parser: every command, its flags, its help and examples."""

from __future__ import annotations

import argparse
from pathlib import Path

from aperture_fab.cli.commands import (
    cmd_assembly,
    cmd_design,
    cmd_export,
    cmd_presets,
    cmd_processes,
    cmd_validate,
)
from aperture_fab.cli.flags import (
    add_config_flags,
    add_fabrication_flags,
    add_output_flags,
    add_strict_flag,
    add_target_flags,
    add_validation_flags,
)
from aperture_fab.cli.status import EXIT_CODES_HELP
from aperture_fab.cli.view_commands import cmd_display, cmd_measure, cmd_render

__all__ = ["build_parser"]


DESCRIPTION = """\
Design and fabricate coded pinhole apertures for slim near-eye displays.

A plate pierced by a grid of small holes sits a few millimetres in front of a display,
close to the eye. The eye cannot focus on the display, but through the holes it sees a
sharp picture. `design` optimizes the holes (and, by default, what the display shows) so
that the eye sees your target image.
"""


DESIGN_EPILOG = """\
examples:
  aperture-fab design examples/targets/natural.png --out outputs/natural/plate.stl
  aperture-fab design a.png b.png --preset seed --out outputs/seed
  aperture-fab design img.png --config my.toml --gap-mm 8 --iterations 500 --out outputs/x
  aperture-fab design img.png --out outputs/x --resume     # continue an interrupted run

Precedence, lowest first: the preset, then --config FILE.toml, then these flags. The fully
resolved config is written to design.toml beside the outputs: `--config design.toml`
re-runs it exactly. Ctrl-C saves a checkpoint; --resume continues it.

outputs (in the folder of --out): design.npz, design.toml, design.json, display_<target>.png
(what the display must show), target_/view_initial_/view_optimized_/view_open_/
view_regular_pinholes_<target>.png (views scaled by their best gain), loss.png.
"""


VALIDATE_EPILOG = """\
examples:
  aperture-fab validate outputs/x/holes.csv examples/targets/natural.png
  aperture-fab validate edited.stl a.png --config outputs/x/design.toml --out outputs/check
  aperture-fab validate outputs/x/design.npz a.png --process etched-foil

PART is a design.npz (quantized and built for the process, like `export`), a holes.csv or an
STL, perhaps edited by hand: holes that break the process's rules are validated anyway and
the broken rules listed. The part a design wrote (its plate.stl, holes.csv or design.npz,
unchanged) is judged exactly as `design` judged it: the same figures and verdicts. A part that
differs (edited, or another process) gets its display content re-fitted to it (the display is
software), from design.npz beside the config when there is one; --keep-display shows
design.npz's content unchanged. Outputs: report.json, report.html, views.npz and
display_<target>.png (the content to show with this part).
"""


RENDER_EPILOG = """\
examples:
  aperture-fab render outputs/x/plate.stl --eye 1.5,0 --out view.png
  aperture-fab render outputs/x/holes.csv examples/targets/natural.png --focus 500
  aperture-fab render outputs/x/design.npz --target-index 1 --mesh

The view uses the design's display content (design.npz beside the config), or the TARGET
itself when the config shows targets. Without --mesh the exact model with the holes as made
(the process's radius bias applied); with --mesh a ray trace of the part's mesh. The PNG is
scaled by the view's least-squares gain to TARGET when one is given, else so that its
99.5th percentile is white.
"""


DISPLAY_EPILOG = """\
examples:
  aperture-fab display outputs/x/design.npz img.png --eye 1.5,0 --pupil 4 --out frame.png
  aperture-fab display outputs/x/plate.stl img.png --eye 0,-1 --pupil 6 --focus 500 \\
      --iterations 10 --config outputs/x/design.toml --out frame.png
  aperture-fab display --refit outputs/x_made img.png

Tracked display: the device knows the pupil's position and size and shows content solved for
that eye state, starting from the design's (untracked) content; the plate stays as made (the
process's radius bias applied). The solver is MLEM (Richardson-Lucy), holding the frame's light
at the eye at --light-floor of the untracked content's (its brightest pixels saturate where
needed); it prints the PSNR after gain of the view with the untracked and the tracked content,
the frame's light as a share of the untracked content's, and the solve time (the first
solve of a process also loads the CPU kernels; per-frame latency: benchmarks/bench_display.py).
See docs/tracking.md. --refit MEASURED_FOLDER (what `measure` wrote) re-fits the untracked
content to the plate as made and prints how much of the tolerance loss (nominal as built
against the made plate with the design's content) that recovers; docs/measure.md.
"""


MEASURE_EPILOG = """\
examples:
  aperture-fab measure scan.png --design outputs/x --dpi 4800 --out outputs/x_made
  aperture-fab measure coupon.png --design outputs/x --coupon --out outputs/x_coupon

SCAN is a back-lit transmission scan of the made plate (a flatbed scanner's transparency unit,
2400 to 4800 dpi, saved linear: gamma 1.0), 8- or 16-bit, grey or RGB, PNG or TIFF. The holes
are fitted to sub-pixel (erf edge), registered to the design (rotation, mirror, scale,
translation) and compared with it. Outputs in --out: holes.csv (the holes as made, in the
design's format), measured.json (registration, per-hole deviations, defects, the process's
bias and sigma on this plate) and measured.html, with design.toml (the design's, the process's
bias and random errors 0) and design.npz: the folder reads as a design folder of the plate as
made, so `validate DIR/holes.csv TARGET` judges it. A scan that does not fit the design
(another plate, a wrong scale) or shows no holes exits 3; a mirrored scan is measured
mirrored, with a warning. With --coupon SCAN is of the design folder's calibration coupon:
--out gets process.toml (the design's config, its [process] as the coupon measured it: the
smallest drawn hole that came through, the radius bias and sigma, the position sigma), for
`design --config`. See docs/measure.md.
"""


def build_parser() -> argparse.ArgumentParser:
    from aperture_fab import __version__

    parser = argparse.ArgumentParser(
        prog="aperture-fab", description=DESCRIPTION, epilog=EXIT_CODES_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"aperture-fab {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("design", help="optimize a plate for target images",
                       description="Optimize a plate of pinholes (and the display content) so "
                       "that the eye sees the target images.", epilog=DESIGN_EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("targets", nargs="+", type=Path, metavar="TARGET",
                   help="target images (PNG/JPEG; several: one plate for all)")
    p.add_argument("--out", type=Path, default=Path("outputs/design/plate.stl"),
                   help="a part file (its folder gets every output) or a folder "
                   "(default outputs/design/plate.stl)")
    p.add_argument("--resume", action="store_true",
                   help="continue an interrupted run from its checkpoint in the output folder")
    add_config_flags(p)
    add_fabrication_flags(p)
    add_validation_flags(p)
    add_strict_flag(p)
    add_target_flags(p)
    p.set_defaults(func=cmd_design)

    p = sub.add_parser("export", help="rebuild part files from a saved design",
                       description="Rebuild the part from a design.npz (for another process or "
                       "format) without re-optimizing. The design's config is read from "
                       "design.toml beside it unless --config is given.",
                       epilog="examples:\n  aperture-fab export outputs/x/design.npz --out "
                       "outputs/x/plate.step\n  aperture-fab export outputs/x/design.npz "
                       "--process etched-foil --out outputs/foil/",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("design", type=Path, metavar="DESIGN.npz")
    p.add_argument("--out", type=Path, required=True,
                   help="a part file (.stl .3mf .dxf .svg .step .csv) or a folder (all formats)")
    p.add_argument("--config", type=Path, metavar="FILE.toml",
                   help="the design's config (default: design.toml beside DESIGN.npz)")
    p.add_argument("--preset", help=argparse.SUPPRESS)
    add_fabrication_flags(p)
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("validate", help="validate a part, perhaps edited by hand",
                       description="Validate a design.npz, holes.csv or STL for a config and "
                       "target images, and write the report.", epilog=VALIDATE_EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("part", type=Path, metavar="PART",
                   help="design.npz, holes.csv or an STL (.stl)")
    p.add_argument("targets", nargs="+", type=Path, metavar="TARGET",
                   help="target images, one per design display, in the design's order")
    p.add_argument("--config", type=Path, metavar="FILE.toml",
                   help="the design's config (default: design.toml beside PART)")
    p.add_argument("--out", type=Path, metavar="FOLDER",
                   help="output folder (default: validate_<PART stem> beside PART)")
    p.add_argument("--process", help="fabrication process (default: the config's, else resin)")
    p.add_argument("--keep-display", action="store_true",
                   help="show design.npz's display content unchanged (default: kept for "
                   "the design's own part, re-fitted to a part that differs)")
    p.add_argument("--tolerance-samples", type=int, metavar="N",
                   help="Monte Carlo samples of the tolerance analysis (0 skips it)")
    p.add_argument("--mesh-samples", type=int, metavar="N",
                   help="rays per (view pixel, hole) pair when re-tracing the mesh (0 skips it)")
    add_target_flags(p)
    add_strict_flag(p)
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser("render", help="the view through a part for an eye position",
                       description="Render what the eye sees through a design.npz, holes.csv "
                       "or STL with the design's display content, as an sRGB PNG.",
                       epilog=RENDER_EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("part", type=Path, metavar="PART",
                   help="design.npz, holes.csv or an STL (.stl)")
    p.add_argument("target", nargs="?", type=Path, metavar="TARGET",
                   help="target image: scales the PNG by the view's gain and reports the PSNR")
    p.add_argument("--config", type=Path, metavar="FILE.toml",
                   help="the design's config (default: design.toml beside PART)")
    p.add_argument("--target-index", type=int, default=0, metavar="N",
                   help="which of the design's display contents to show (default 0)")
    p.add_argument("--eye", metavar="X,Y", help="lateral eye position in mm (default: the "
                   "config's nominal one); may lie outside the config's eyebox")
    p.add_argument("--pupil", type=float, metavar="MM", help="pupil diameter in mm")
    p.add_argument("--focus", metavar="MM", help="eye focus distance in mm, or 'infinity'")
    p.add_argument("--mesh", action="store_true",
                   help="ray-trace the part's mesh instead of the exact hole model")
    p.add_argument("--mesh-samples", type=int, default=None, metavar="N",
                   help="rays per (view pixel, hole) pair with --mesh (default 12)")
    p.add_argument("--process", help="fabrication process (default: the config's, else resin)")
    p.add_argument("--out", type=Path, metavar="VIEW.png",
                   help="PNG to write (default: view_<PART stem>.png beside PART)")
    add_target_flags(p)
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("display", help="the display frame for a tracked eye state",
                       description="Solve the display content of a part for one eye state "
                       "(pupil position and size, as an eye tracker reports them), the plate "
                       "fixed, and write it as an sRGB PNG at the display's pixel count.",
                       epilog=DISPLAY_EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    # Optional here, required below (display_arguments): --refit takes neither PART nor --eye.
    p.add_argument("part", type=Path, nargs="?", metavar="PART",
                   help="design.npz, holes.csv or an STL (.stl); with --refit: a TARGET")
    p.add_argument("target", type=Path, nargs="*", metavar="TARGET",
                   help="the target image the eye should see (with --refit: the design's "
                   "targets, in its order)")
    p.add_argument("--refit", type=Path, metavar="MEASURED_FOLDER",
                   help="re-fit the display content to the plate as measured (the folder "
                   "`aperture-fab measure` wrote) and say how much of the tolerance loss it "
                   "recovers; writes refit.json and refit_display_<target>.png there")
    p.add_argument("--eye", metavar="X,Y",
                   help="pupil centre (x, y) in mm in the scene's frame (the config's nominal "
                   "eye position is usually 0,0); required without --refit")
    p.add_argument("--pupil", type=float, metavar="MM",
                   help="pupil diameter in mm; required without --refit")
    p.add_argument("--focus", metavar="MM", help="eye focus distance in mm, or 'infinity' "
                   "(default: the config's)")
    p.add_argument("--iterations", type=int, default=None, metavar="N",
                   help="solver iterations (default 5; 0: the untracked display)")
    p.add_argument("--light-floor", type=float, default=None, metavar="SHARE",
                   help="the share of the untracked display's light at the eye the frame "
                   "keeps (default 1: as bright as the untracked content; 0: no floor, the "
                   "sharpest frame, often several times darker)")
    p.add_argument("--config", type=Path, metavar="FILE.toml",
                   help="the design's config (default: design.toml beside PART)")
    p.add_argument("--target-index", type=int, default=0, metavar="N",
                   help="which of the design's display contents to start from (default 0)")
    p.add_argument("--process", help="fabrication process (default: the config's, else resin)")
    p.add_argument("--out", type=Path, metavar="FRAME.png",
                   help="PNG to write; required without --refit")
    add_target_flags(p)
    p.set_defaults(func=cmd_display, display_parser=p)

    p = sub.add_parser("assembly", help="the assembly sheet (HTML) of a design folder",
                       description="Write the printable assembly sheet of a design: the plate "
                       "drawing with its key, the frame, where and which way up the display "
                       "image goes, the calibration coupon and the steps (docs/assembly.md).",
                       epilog="example:\n  aperture-fab assembly outputs/x  # -> "
                       "outputs/x/assembly.html",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("design_folder", type=Path, metavar="DESIGN_FOLDER",
                   help="the folder `aperture-fab design` wrote (design.toml, design.npz)")
    p.add_argument("--out", type=Path, metavar="FILE.html",
                   help="where to write it (default: assembly.html in DESIGN_FOLDER)")
    p.set_defaults(func=cmd_assembly)

    p = sub.add_parser("measure", help="measure a made plate from a back-lit scan",
                       description="Measure the holes of a made plate from a back-lit scan and "
                       "compare them with its design.", epilog=MEASURE_EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scan", type=Path, metavar="SCAN", help="the scan (PNG or TIFF)")
    p.add_argument("--design", type=Path, required=True, metavar="FOLDER",
                   help="the design folder the plate was made from (design.toml, holes.csv)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    scale = p.add_mutually_exclusive_group()
    scale.add_argument("--dpi", type=float, default=4800.0,
                       help="the scan's resolution (default 4800)")
    scale.add_argument("--scale-mm-per-px", type=float, metavar="X",
                       help="the pixel size in mm (a microscope or camera image)")
    p.add_argument("--encoding", choices=("linear", "srgb"), default="linear",
                   help="how the scan's values encode light (default linear: gamma 1.0)")
    p.add_argument("--coupon", action="store_true",
                   help="the scan is of the design's calibration coupon (coupon.stl/svg): "
                   "write the process it shows as DIR/process.toml, a config design takes")
    p.set_defaults(func=cmd_measure)

    p = sub.add_parser("presets", help="list the presets with their key numbers")
    p.set_defaults(func=cmd_presets)
    p = sub.add_parser("processes", help="list the fabrication processes and their rules")
    p.set_defaults(func=cmd_processes)
    from aperture_fab.sweep.command import add_parser as add_sweep_parser

    add_sweep_parser(sub)
    for command in sub.choices.values():
        add_output_flags(command)
    return parser
