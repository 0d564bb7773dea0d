"""The `aperture-fab` command line."""

from __future__ import annotations

import argparse
import errno
import re
import signal
import sys
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["EXIT_CODES_HELP", "main"]

#: Exit statuses: distinct, so that scripts can tell a bad input from a refused part.
EXIT_OK = 0
EXIT_FAILED = 1  # the tool judged and refused: the process cannot make the plate, or it diverged
EXIT_USAGE = 2  # argparse's own status for a bad command line; also a missing package
EXIT_BAD_INPUT = 3
EXIT_CANNOT_WRITE = 4
# The part's files and its report are written either way (the user needs the report to see why);
# only the status says that the report's overall verdict refuses the part.
EXIT_REPORT_FAIL = 5  # the report says FAIL: do not make the part as it is
EXIT_REPORT_WARN = 6  # with --strict only: the report says WARN
EXIT_NO_CLUSTER = 7  # `sweep`: the Ray cluster at --address could not be reached
EXIT_INTERRUPTED = 130  # 128 + SIGINT, what shells report for Ctrl-C
EXIT_TERMINATED = 143  # 128 + SIGTERM: stopped like Ctrl-C (a job scheduler's or `kill`'s stop)

EXIT_CODES_HELP = f"""\
exit status:
  {EXIT_OK}    success; for `design` and `validate`: the part's report says PASS, or WARN
       without --strict
  {EXIT_FAILED}    the tool refused the job: the process cannot make the plate (--force writes it
       anyway), the optimization diverged, or the job needs more memory than the machine has;
       for `sweep`, some points failed
  {EXIT_USAGE}    usage error: an unknown command or flag, a flag's value of the wrong type or
       empty, or a package the command needs is not installed (e.g. the step extra for STEP)
  {EXIT_BAD_INPUT}    bad input: a missing or wrong file, a value out of range
  {EXIT_CANNOT_WRITE}    a file could not be written or read (no permission, disk full, read-only)
  {EXIT_REPORT_FAIL}    `design`, `validate`: the part and its report were written, but the report
       says FAIL: do not make the part as it is (report.html says why and what to change)
  {EXIT_REPORT_WARN}    `design`, `validate` with --strict: the report says WARN (usable, with
       reservations); without --strict a WARN exits {EXIT_OK}
  {EXIT_NO_CLUSTER}    `sweep`: the Ray cluster at --address could not be reached within
       --connect-timeout (the message names the address and the fix)
  {EXIT_INTERRUPTED}  interrupted (Ctrl-C); `design` saves a checkpoint first (--resume goes on)
  {EXIT_TERMINATED}  stopped by SIGTERM (`kill`, a job scheduler), handled like Ctrl-C

-q/--quiet prints only errors and the final one-line result, which is also the last line
without it; for `design` and `validate` it starts with the report's verdict (PASS, WARN, FAIL;
NOTE when nothing was judged, NOT VALIDATED with --no-validate). -v/--verbose adds tracebacks to
errors and the time of each stage. Progress bars appear only when stderr is a terminal; in a log
each stage is one plain line instead.
"""

#: (module, class) of the errors that are a failure the tool judged (EXIT_FAILED). Matched by
#: name so that the light commands need not import the optimizer (torch) to check.
JUDGED_FAILURES: tuple[tuple[str, str], ...] = (
    ("aperture_fab.fabrication.process", "UnmakeableError"),
    ("aperture_fab.optimize.optimizer", "DivergedError"),
)

#: (module, class) of the errors that say a Ray cluster could not be reached (EXIT_NO_CLUSTER):
#: a connection error, not a file error, though both are OSErrors.
UNREACHABLE: tuple[tuple[str, str], ...] = (("aperture_fab.sweep.cluster", "ClusterUnreachable"),)

#: What to do about a file system error, by errno.
OS_ERROR_FIXES: dict[int, str] = {
    errno.ENOSPC: "the disk is full: free some space, or give --out on another disk",
    errno.EDQUOT: "the disk quota is used up: free some space, or give --out on another disk",
    errno.EACCES: "no permission: choose an --out you can write (e.g. under your home folder)",
    errno.EPERM: "no permission: choose an --out you can write (e.g. under your home folder)",
    errno.EROFS: "the file system is read-only: choose an --out on a writable disk",
    errno.EISDIR: "it is a folder: give a file name inside it",
    errno.ENOTDIR: "a part of the path is a file, not a folder: choose another --out",
}

#: The temporary name write_atomic gives a file while it writes it, and the file's own name.
TEMP_NAME = re.compile(r"\.([^/\\]+)\.[0-9a-f]{12}\.tmp$")

#: Warnings raised from this package's files are the tool's own (printed as one line).
PACKAGE_DIR = str(Path(__file__).resolve().parent)
#: The package's import name: an ImportError inside it is a bug, not a missing package.
PACKAGE_NAME = "aperture_fab"

#: What the report's overall verdict says of the part, in the one-line result.
VERDICT_WORDS = {
    "fail": "do not make this part as it is",
    "warn": "usable, with reservations",
    "pass": "every check passed",
    "info": "no check was judged",
}
#: A sentence ends at . ! or ? before a capital: not inside "0.92 %" or "(e.g. the".
SENTENCE_END = re.compile(r"(?<=[.!?])\s+(?=[A-Z])")
#: The one-line result quotes the deciding verdict's first sentence up to this many characters, a
#: guard against a text without a sentence end; report.html holds the whole text and the fix.
REASON_CHARS = 400


@dataclass(frozen=True)
class Output:
    """How much the command prints, chosen once in `main` and passed down (args.output).

    quiet: only errors and the final one-line result. verbose: tracebacks and stage timings.
    terminal: stderr is a terminal, so progress bars may redraw it; otherwise (a log) each
    stage is one plain line.
    """

    quiet: bool
    verbose: bool
    terminal: bool

    @property
    def progress(self) -> bool:
        """Whether to draw progress bars (tqdm writes carriage returns, unreadable in a log)."""
        return self.terminal and not self.quiet

    def result(self, line: str) -> None:
        """The final one-line result: the last line printed, and the only one with --quiet."""
        print(line)

    def detail(self, line: str) -> None:
        """A result line beyond the final one (tables, notes): not with --quiet."""
        if not self.quiet:
            print(line)

    def stage(self, line: str) -> None:
        """A stage starting, as a plain line on stderr when there are no progress bars."""
        if not self.quiet and not self.terminal:
            print(f"aperture-fab: {line}", file=sys.stderr, flush=True)

    def timings(self, timings_s: dict[str, float]) -> None:
        """Seconds per stage, with --verbose."""
        if self.verbose and timings_s:
            print("timings: " + ", ".join(f"{k.removesuffix('_s')} {v:.2f} s"
                                          for k, v in timings_s.items()), file=sys.stderr)

    def warn(self, line: str) -> None:
        if not self.quiet:
            print(f"aperture-fab: warning: {line}", file=sys.stderr)

    def interrupted(self, line: str) -> None:
        """Ctrl-C: not an error, but said even with --quiet."""
        print(f"aperture-fab: interrupted {line}", file=sys.stderr)

    def error(self, line: str) -> None:
        print(f"aperture-fab: error: {line}", file=sys.stderr)

    def traceback(self) -> None:
        """The traceback of the exception being handled, with --verbose."""
        if self.verbose:
            import traceback

            traceback.print_exc()

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

# (flag, dotted config key, type, help)
OVERRIDES: tuple[tuple[str, str, Any, str], ...] = (
    ("--cells", "plate.cells", "pair_int", "plate cell grid NX NY"),
    ("--pitch-mm", "plate.pitch_mm", float, "cell pitch in mm (square cells)"),
    ("--gap-mm", "plate.gap_mm", float, "display to the plate's bottom face, mm"),
    ("--thickness-mm", "plate.thickness_mm", float, "plate thickness, mm"),
    ("--hole-axis", "plate.hole_axis", ("straight", "chief_ray"), "hole axes"),
    ("--pupil-mm", "eye.pupil_mm", float, "eye pupil diameter, mm"),
    ("--eye-relief-mm", "eye.eye_relief_mm", float, "plate top face to the pupil, mm"),
    ("--focus-mm", "eye.focus_mm", "focus", "eye focus distance in mm, or 'infinity'"),
    ("--view-pixels", "eye.view_pixels", "pair_int", "view grid NX NY"),
    ("--method", "optimizer.method", ("adam", "sgd"), "optimizer"),
    ("--lr", "optimizer.learning_rate", float, "learning rate"),
    ("--iterations", "optimizer.iterations", int, "most iterations"),
    ("--init", "optimizer.init", ("pinholes", "random", "uniform"), "starting mask"),
    ("--display-mode", "optimizer.display", ("optimized", "target"),
     "optimize the display content, or show the target as is"),
    ("--efficiency-weight", "optimizer.efficiency_weight", float,
     "trade image quality for light (0 ignores light level)"),
    ("--seed", "optimizer.seed", int, "random seed"),
    ("--precision", "optimizer.precision", ("float32", "float64"), "floating point precision"),
    ("--device", "optimizer.device", str, "auto (CUDA when available), cpu, cuda or cuda:N"),
)


def _add_config_flags(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("configuration")
    group.add_argument("--preset", help="preset to start from (see `aperture-fab presets`); "
                       "default near-eye")
    group.add_argument("--config", type=Path, metavar="FILE.toml",
                       help="TOML config; overrides the preset")
    for flag, key, kind, text in OVERRIDES:
        dest = key.replace(".", "__")
        if kind == "pair_int":
            group.add_argument(flag, dest=dest, type=int, nargs=2, metavar=("NX", "NY"),
                               help=text)
        elif kind == "focus":
            group.add_argument(flag, dest=dest, metavar="MM", help=text)
        elif isinstance(kind, tuple):
            group.add_argument(flag, dest=dest, choices=kind, help=text)
        else:
            group.add_argument(flag, dest=dest, type=kind, help=text)


def _overrides(args: argparse.Namespace) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for flag, key, kind, _ in OVERRIDES:
        value = getattr(args, key.replace(".", "__"))
        if value is None:
            continue
        if kind == "pair_int":
            value = list(value)
        elif kind == "focus" and value != "infinity":
            try:
                value = float(value)
            except ValueError:
                raise ValueError(
                    f"{flag} {value!r}: give a distance in mm or 'infinity'."
                ) from None
        elif key == "plate.pitch_mm":
            value = [value, value]
        out[key] = value
    return out


def _load_config(args: argparse.Namespace) -> Any:
    from aperture_fab.config.config import parse_toml, resolve
    from aperture_fab.io.files import read_text

    file_dict = None
    if args.config is not None:
        try:
            text = read_text(args.config, "--config", "give a TOML config file saved as UTF-8 "
                             "text, e.g. a design's design.toml.")
        except OSError as err:
            raise ValueError(f"--config {args.config}: cannot read it ({err.strerror}); give "
                             "the path of a TOML config file.") from err
        file_dict = parse_toml(text, str(args.config))
    return resolve(args.preset, file_dict, _overrides(args),
                   file_source=None if args.config is None else str(args.config))


def _cmd_presets(args: argparse.Namespace) -> int:
    from aperture_fab.config.presets import DEFAULT_PRESET, PRESETS, preset_summary

    for name in PRESETS:
        print(preset_summary(name))
        print()
    args.output.result(f"{len(PRESETS)} presets: {', '.join(PRESETS)}; start from one with "
                       f"--preset NAME (default {DEFAULT_PRESET})")
    return 0


def _add_fabrication_flags(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("fabrication")
    group.add_argument("--process", help="fabrication process (see `aperture-fab processes`); "
                       "default: the config's [process] (design.toml records it), else resin")
    group.add_argument("--force", action="store_true", default=None,
                       help="write parts the process cannot make, with the violations "
                       "listed; replace a design in --out that was validated (its validation "
                       "folders go with it)")
    group.add_argument("--step", action="store_true", default=None,
                       help="also write plate.step (a .step --out implies it)")


def _add_validation_flags(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("validation")
    group.add_argument("--no-validate", action="store_true",
                       help="skip validation and the report (report.json/html, views.npz)")
    group.add_argument("--tolerance-samples", type=int, metavar="N",
                       help="Monte Carlo samples of the tolerance analysis (0 skips it)")
    group.add_argument("--mesh-samples", type=int, metavar="N",
                       help="rays per (view pixel, hole) pair when re-tracing the written mesh "
                       "(default 12; 0 skips it)")


#: The choices of --alpha and --fit: aperture_fab.io.images' ALPHA_BACKGROUNDS and TARGET_FITS,
#: written out as the parser is built without importing images (PIL is heavy).
ALPHA_CHOICES = ("black", "white", "refuse")
FIT_CHOICES = ("stretch", "pad", "crop")


def _add_target_flags(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("target images")
    group.add_argument("--alpha", choices=ALPHA_CHOICES,
                       help="what a target's transparent pixels are composited on, or refuse "
                       "one that has any (default black, with a warning: black is no light on "
                       "a display, as the transparent areas show nothing)")
    group.add_argument("--fit", choices=FIT_CHOICES, default="stretch",
                       help="a target of another aspect than the display's: stretch it (the "
                       "default, with a warning: every pixel kept, as earlier designs were "
                       "made), pad it with black (letterbox, centred) or crop its centre. Give "
                       "validate, render and display the --fit the design was made with")
    group.add_argument("--frame", type=int, metavar="N",
                       help="the frame of an animated target (GIF, APNG, multi-page TIFF) to "
                       "use, 0 the first (default: the first, with a warning)")


def _target_options(args: argparse.Namespace) -> Any:
    """The TargetOptions of --alpha, --fit and --frame."""
    from aperture_fab.io.images import TargetOptions

    return TargetOptions(alpha=args.alpha, fit=args.fit, frame=args.frame)


def _add_strict_flag(parser: Any) -> None:
    """--strict, on the commands that judge a part (design, validate)."""
    parser.add_argument("--strict", action="store_true",
                        help=f"exit with status {EXIT_REPORT_WARN} when the report says WARN "
                        f"(a FAIL exits {EXIT_REPORT_FAIL} always); the files are written either "
                        "way")


def _fabrication(args: argparse.Namespace, extra: Any) -> Any:
    from aperture_fab.fabrication.part import fabrication_settings

    return fabrication_settings(extra, {"process": args.process, "force": args.force,
                                        "step": args.step})


def _part_out(out: Path, allowed: tuple[str, ...]) -> Any:
    """The part format an --out names (a PartFormat), or None when it is a folder: an existing
    folder or a name without a suffix. Any other suffix is refused (not made a folder of that
    name, which is what a typo such as plate.stk would otherwise give)."""
    from aperture_fab.io.formats import PART_FORMATS

    suffix = out.suffix.lower()
    if not suffix or out.is_dir():
        return None
    if suffix not in allowed:
        raise ValueError(
            f"--out {out}: {out.suffix!r} is not a part file suffix; allowed: "
            f"{' '.join(allowed)} (that one file), or a folder without a suffix (every "
            f"format). Give e.g. --out {out.with_suffix('.stl')} (a file) or --out "
            f"{out.with_suffix('')} (a folder).")
    return next(f for f in PART_FORMATS.values() if suffix in f.suffixes)


def _report_forced(output: Output, part: Any, config: Any, fabrication: Any) -> None:
    """With --force, say honestly how many holes break which of the process's rules (the part
    is written as designed, not fixed): quantize's resolved violations undercount them."""
    from aperture_fab.fabrication.rules import layout_violations

    if not fabrication.force:
        return
    broken = layout_violations(part.layout, config.scene.plate, fabrication.process)
    if not broken:
        return
    holes: dict[str, set[Any]] = {}
    for v in broken:
        holes.setdefault(v.rule, set()).add(v.cell)
    rules = ", ".join(f"{rule}: {'the whole plate' if cells == {None} else f'{len(cells)} holes'}"
                      for rule, cells in holes.items())
    cells = {c for v in broken if v.cell is not None for c in [v.cell]}
    output.warn(f"--force: {len(cells)} of {part.layout.count} holes break process "
                f"{fabrication.process.name}'s rules ({rules}); written anyway, as designed. The "
                "process may not make them: see `aperture-fab processes`, or drop --force.")


def _cmd_processes(args: argparse.Namespace) -> int:
    from aperture_fab.fabrication.process import PROCESSES, process_summary

    for process in PROCESSES.values():
        print(process_summary(process))
        print()
    args.output.result(f"{len(PROCESSES)} processes: {', '.join(PROCESSES)}; choose one with "
                       "--process NAME")
    return 0


def _makeable_flags(process: Any, scene: Any) -> tuple[list[str], str]:
    """The design flags that give `process` a plate it makes (rules.makeable_settings; [] when
    it makes this one), and a note for what no flag sets (a non-square pitch: --pitch-mm gives
    square cells)."""
    from aperture_fab.fabrication.rules import makeable_settings

    flags: list[str] = []
    note = ""
    for key, value in makeable_settings(process, scene.plate, scene.eye.eye_relief_mm).items():
        if key == "plate.thickness_mm":
            flags += ["--thickness-mm", f"{value:g}"]
        elif key == "plate.cells":
            flags += ["--cells", *(str(n) for n in value)]
        elif value[0] == value[1]:  # plate.pitch_mm, square
            flags += ["--pitch-mm", f"{value[0]:g}"]
        else:
            note = (f", with [plate] pitch_mm = [{value[0]:g}, {value[1]:g}] in the --config "
                    "file (--pitch-mm gives square cells)")
    return flags, note


def _refuse_unmakeable(process: Any, scene: Any, command: list[str], why: str = "") -> None:
    """Raise check_plate's UnmakeableError for a scene's plate `process` cannot make, completed
    with `why` and the design command (`command` plus the flags of _makeable_flags) that makes
    a plate it can."""
    import shlex

    from aperture_fab.fabrication.process import UnmakeableError
    from aperture_fab.fabrication.rules import check_plate

    try:
        check_plate(process, scene.plate, scene.eye.eye_relief_mm)
    except UnmakeableError as err:
        flags, note = _makeable_flags(process, scene)
        if not flags and not note:
            raise
        raise UnmakeableError(
            f"{err}{why} Design a plate {process.name} makes: `{shlex.join([*command, *flags])}`"
            f"{note}; or give --force to write this plate anyway, its broken rules listed."
        ) from None


def _refuse_unmakeable_export(args: argparse.Namespace, config: Any, fabrication: Any,
                              config_path: Path) -> None:
    """Refuse an export whose process cannot make the design's plate, naming the design
    command that makes a plate for it: the holes were optimized through this plate (its
    thickness, its cells), so export cannot change the plate honestly."""
    import json

    plate = config.scene.plate
    name = fabrication.process.name
    folder = args.design.parent
    try:
        targets = json.loads((folder / "design.json").read_text())["targets"]
        which = f", in its order: {', '.join(targets)}"
    except (OSError, ValueError, KeyError, TypeError):
        which = ""
    pitch = " x ".join(f"{p:g}" for p in plate.pitch_mm)
    command = ["aperture-fab", "design", "TARGET", "--config", str(config_path),
               "--process", name, "--out", str(folder.with_name(f"{folder.name}-{name}"))]
    _refuse_unmakeable(
        fabrication.process, config.scene, command,
        f" {args.design} holds open fractions optimized through its own "
        f"{plate.thickness_mm:g} mm plate of {pitch} mm cells (the hole walls clip oblique "
        "light by the thickness; the cells are the design's grid), so export cannot re-make "
        f"them in another plate. TARGET: the image(s) the design was made for{which}.")


def _cmd_export(args: argparse.Namespace) -> int:
    from aperture_fab.config.config import parse_toml, resolve
    from aperture_fab.fabrication.part import make_part
    from aperture_fab.io.files import output_folder, read_text, write_atomic
    from aperture_fab.io.formats import PART_FORMATS, part_files
    from aperture_fab.io.manifest import refuse_overwrite
    from aperture_fab.pipeline.design_job import write_part
    from aperture_fab.pipeline.saved import check_sources, read_design

    config_path = args.config or args.design.parent / "design.toml"
    named = _part_out(args.out, tuple(s for f in PART_FORMATS.values() for s in f.suffixes))
    open_fraction = read_design(args.design).open_fraction  # checked: a whole file, 0..1
    try:
        text = read_text(config_path, "the design's config", "give the design's design.toml "
                         "with --config.")
    except OSError as err:
        raise ValueError(f"{config_path}: cannot read the design's config ({err.strerror}); give "
                         "it with --config.") from err
    config = resolve(args.preset, parse_toml(text, str(config_path)),
                     file_source=str(config_path))
    check_sources(config_path, args.design, "design")
    fabrication = _fabrication(args, config.extra)  # the process design.toml records, or --process
    if not fabrication.force:
        _refuse_unmakeable_export(args, config, fabrication, config_path)
    # An --out that names a part file writes that one file, under the name given (its folder
    # is its parent); any other --out is a folder that gets every format.
    folder = output_folder(args.out.parent if named else args.out)
    formats = ((named.name,) if named else
               tuple(name for name in PART_FORMATS if name != "step" or fabrication.step))
    refuse_overwrite(folder, [args.out.name] if named else
                     [PART_FORMATS[name].file_name for name in formats])
    part = make_part(open_fraction, config.scene, fabrication)
    args.output.stage(f"writing {', '.join(formats)} for {part.layout.count} holes")
    if named:
        # Written straight under the name given: a rename afterwards could replace a file of
        # the standard name (plate.stl) that a design left in the same folder.
        data = part_files(part, formats, fabrication)[named.file_name]
        write_atomic(args.out, data)
        written = [args.out]
    else:
        written = write_part(folder, part, fabrication, formats, progress=args.output.progress)
    _report_forced(args.output, part, config, fabrication)
    args.output.result(f"wrote {part.layout.count} holes, process {fabrication.process.name}: "
                       + ", ".join(str(p) for p in written))
    return 0


#: Width of a column of the eye-distribution table ("28.1 / 30.4 / 31.2").
EYE_COLUMN = 22


def _print_eye_distribution(metrics: dict[str, Any], names: Sequence[str], *,
                            validated: bool, verdicts: Sequence[dict[str, str]] = ()) -> None:
    """The design table's lead: PSNR p10 / median / p90 over the eye distribution per variant
    and target, then the eye-distribution verdict (or why there is none), the part as made
    against the best regular array, the report's other warnings and failures, and the fix the
    report recommends (its others are in the report)."""
    import textwrap

    from aperture_fab.validation.report import Verdict
    from aperture_fab.validation.report_html import LEVEL_WORDS, NOT_JUDGED
    from aperture_fab.validation.verdicts import MADE_TOPIC, fix_plan

    headline = metrics.get("eye_distribution")
    if headline is None:
        why = NOT_JUDGED if validated else (
            "Not judged over the eye distribution (--no-validate): the PSNR below is for the "
            "nominal eye point only.")
        print(textwrap.fill("eye distribution: " + why, 100, subsequent_indent="  "))
    else:
        _print_eye_table(headline, names)
    # The part as made against the best regular array, whatever its level; then the report's
    # other judged findings that need action (light, contrast, tolerances...), which the final
    # line's verdict may name even when the eye distribution was not judged.
    for other in verdicts:
        if other["topic"] == MADE_TOPIC or (other["level"] in ("fail", "warn")
                                            and other["topic"] != "eye distribution"):
            print(textwrap.fill(f"{other['topic']}: {LEVEL_WORDS[other['level']]}: "
                                f"{other['text']}", 100, subsequent_indent="  "))
    plan = fix_plan([Verdict(v["topic"], v["level"], v["text"], tuple(v.get("fixes", ())))
                     for v in verdicts])
    if plan.recommended is not None and plan.deciding is not None:
        others = (f" ({len(plan.alternatives)} other fixes in the report)"
                  if plan.alternatives else "")
        print(textwrap.fill(f"recommended fix ({plan.deciding.topic}): {plan.recommended}"
                            + others, 100, subsequent_indent="  "))


def _print_eye_table(headline: dict[str, Any], names: Sequence[str]) -> None:
    """PSNR p10 / median / p90 over the eye distribution per variant and target, and its
    verdict."""
    import textwrap

    from aperture_fab.validation.report_html import LEVEL_WORDS

    variants = headline["variants"]
    print(f"PSNR over the eye distribution (dB), p10 / median / p90, {headline['states']} "
          "states:")
    print(f"  {'target':<16}" + "".join(f"{v:>{EYE_COLUMN}}" for v in variants))
    for t, name in enumerate(names):
        cells = []
        for values in variants.values():
            psnr = values["psnr_db"]
            cell = " / ".join("-" if psnr[k][t] is None else f"{psnr[k][t]:.1f}"
                              for k in ("p10", "p50", "p90"))
            cells.append(f"{cell:>{EYE_COLUMN}}")
        print(f"  {name:<16}" + "".join(cells))
    verdict = headline.get("verdict")
    if verdict is not None:
        print(textwrap.fill(f"eye distribution: {LEVEL_WORDS[verdict['level']]}: "
                            f"{verdict['text']}", 100, subsequent_indent="  "))


@dataclass(frozen=True)
class Judgement:
    """A report's overall verdict, for the exit status and the one-line result.

    level: fail, warn, pass or info: the report page's headline (report_html.overall_level, its
    worst judged verdict), so the terminal and the page always agree. deciding: the first
    verdict at that level (the report lists the most important first), None for info.
    count: how many verdicts are at that level.
    """

    level: str
    deciding: Mapping[str, str] | None
    count: int

    @classmethod
    def of(cls, verdicts: Sequence[Mapping[str, str]]) -> Judgement:
        from aperture_fab.validation.report import Verdict
        from aperture_fab.validation.report_html import overall_level

        level = overall_level([Verdict(v["topic"], v["level"], v["text"]) for v in verdicts])
        at_level = [v for v in verdicts if v["level"] == level]
        return cls(level, at_level[0] if level != "info" else None, len(at_level))

    def status(self, strict: bool) -> int:
        """EXIT_REPORT_FAIL for FAIL; EXIT_REPORT_WARN for WARN with --strict; else EXIT_OK."""
        if self.level == "fail":
            return EXIT_REPORT_FAIL
        return EXIT_REPORT_WARN if self.level == "warn" and strict else EXIT_OK

    def line(self, wrote: str, report: Path, strict: bool) -> str:
        """The one-line result: the verdict, what was written, where the report is and, for
        FAIL or WARN, the deciding check's topic and the first sentence of its reason."""
        from aperture_fab.validation.verdicts import LEVEL_WORDS

        words = VERDICT_WORDS[self.level]
        if self.level == "warn" and strict:
            words += f" (--strict refuses it: exit status {EXIT_REPORT_WARN})"
        text = f"{LEVEL_WORDS[self.level]}: {wrote} - {report} says {words}"
        if self.deciding is None or self.level == "pass":
            return text
        reason = " ".join(SENTENCE_END.split(self.deciding["text"].strip(), 1)[0].split())
        if len(reason) > REASON_CHARS:
            reason = reason[:REASON_CHARS].rsplit(" ", 1)[0] + " ..."
        topic = self.deciding["topic"]
        if self.count > 1:
            topic = f"{self.count} checks {self.level}, first {topic}"
        return f"{text}; {topic}: {reason}"


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread so that it stops a command the way Ctrl-C does: a
    design saves its checkpoint, every file written so far is whole."""


class _Sigterm:
    """The SIGTERM handler: raises Terminated, and remembers that it did. A raise that lands
    inside a ctypes callback (Numba's compiler, LLVM) is printed and dropped there, and the
    command goes on or fails for another reason; main still exits as stopped by SIGTERM."""

    def __init__(self) -> None:
        self.received = False

    def __call__(self, signum: int, frame: Any) -> None:
        self.received = True
        raise Terminated()


def _how_stopped(err: BaseException) -> tuple[str, int]:
    """How a command was stopped ("Ctrl-C" or "SIGTERM") and its exit status; `err` is the
    KeyboardInterrupt or an exception raised while handling one (the design's Interrupted)."""
    stop = err if isinstance(err, KeyboardInterrupt) else err.__context__
    if isinstance(stop, Terminated):
        return "SIGTERM", EXIT_TERMINATED
    return "Ctrl-C", EXIT_INTERRUPTED


def _cmd_design(args: argparse.Namespace) -> int:
    from aperture_fab.io.files import output_folder
    from aperture_fab.optimize.optimizer import Interrupted
    from aperture_fab.pipeline.design_job import run_design
    from aperture_fab.validation.validate import validation_settings

    config = _load_config(args)
    fabrication = _fabrication(args, config.extra)
    if not fabrication.force:  # refused before any work, with the flags that make it possible
        _refuse_unmakeable(fabrication.process, config.scene, args.command_line)
    validation = None if args.no_validate else validation_settings(
        config.extra, {"tolerance_samples": args.tolerance_samples,
                       "mesh_samples": args.mesh_samples})
    from aperture_fab.io.formats import PART_SUFFIXES

    output: Output = args.output
    named = _part_out(args.out, PART_SUFFIXES)
    folder = output_folder(args.out)
    output.stage(f"design: {config.optimizer.iterations} iterations, then the part"
                 + ("" if validation is None else " and its validation")
                 + f", into {folder}/")
    try:
        result = run_design(args.targets, args.out, config, fabrication=fabrication,
                            target_options=_target_options(args),
                            validation=validation, resume=args.resume, progress=output.progress,
                            command=args.command_line, stage=output.stage,
                            replace_validated=bool(args.force))
    except Interrupted as stop:
        how, code = _how_stopped(stop)
        output.interrupted(f"at iteration {stop.state['iteration']} ({how}); checkpoint saved in "
                           f"{folder}. Continue with the same command and --resume.")
        return code
    wrote = (f"wrote {folder}/ ({len(result.design.loss_history)} iterations, "
             f"stopped: {result.design.stopped})")
    output.timings(result.timings_s)
    if named is not None and args.out.name != named.file_name:
        # A design folder's files have fixed names (validate and export find them by name).
        output.warn(f"--out {args.out}: the part is written as {folder / named.file_name}, the "
                    "design folder's fixed name; for another name run `aperture-fab export "
                    f"{folder / 'design.npz'} --out {args.out}`.")
    if result.part is not None:
        _report_forced(output, result.part, config, fabrication)
    if not output.quiet:
        _print_design_tables(result, fabrication, validated=validation is not None)
    if validation is None:  # no report: say so rather than let "wrote" read as a pass
        targets = " ".join(str(t) for t in args.targets)
        output.result(f"NOT VALIDATED: {wrote} - --no-validate: no report and no verdict; "
                      f"judge the part with `aperture-fab validate {folder / 'plate.stl'} "
                      f"{targets}`")
        return EXIT_OK
    judgement = Judgement.of(result.verdicts)
    output.result(judgement.line(wrote, folder / "report.html", args.strict))
    return judgement.status(args.strict)


def _print_design_tables(result: Any, fabrication: Any, *, validated: bool) -> None:
    """design's tables: the verdicts (as validate prints them), the nominal PSNR and the part."""
    m = result.metrics
    _print_eye_distribution(m, result.names, validated=validated, verdicts=result.verdicts)
    nominal = [v for v in m if v != "eye_distribution"]
    print("PSNR after gain (dB), nominal eye position:")
    header = f"  {'target':<16}" + "".join(f"{v:>18}" for v in nominal)
    print(header)
    for t, name in enumerate(result.names):
        print(f"  {name:<16}" + "".join(f"{m[v]['psnr_db'][t]:>18.2f}" for v in nominal))
    if result.part is None:
        return
    layout = result.part.layout
    if fabrication.force:  # nothing was resolved: the warning above counts what breaks
        print(f"part: {layout.count} holes as designed (--force); "
              f"{result.part.report.face_count} triangles, watertight")
        return
    print(f"part: {layout.count} holes, {len(layout.violations)} rule violation(s) resolved; "
          f"{result.part.report.face_count} triangles, watertight")
    for v in layout.violations[:10]:
        print(f"  {v.rule}: {v.resolution}")


def _cmd_validate(args: argparse.Namespace) -> int:
    import json

    from aperture_fab.pipeline.validate_job import run_validate
    from aperture_fab.validation.report import eye_headline

    result = run_validate(args.part, args.targets, config_path=args.config, out=args.out,
                          target_options=_target_options(args),
                          process=args.process, keep_display=args.keep_display,
                          tolerance_samples=args.tolerance_samples,
                          mesh_samples=args.mesh_samples, progress=args.output.progress,
                          stage=args.output.stage, command=args.command_line)
    metrics = result.validation.metrics
    layout = result.part.layout
    # The verdicts as published: the exit status follows the report the user will read.
    report = json.loads((result.folder / "report.json").read_text())
    output: Output = args.output
    output.timings(result.timings_s)
    if not output.quiet:
        _print_eye_distribution({"eye_distribution": eye_headline(report)}, result.names,
                                validated=True, verdicts=report["verdicts"])
        print("PSNR after gain (dB), nominal eye position:")
        print(f"  {'variant':<22}" + "".join(f"{name:>16}" for name in result.names))
        for variant, per_target in metrics.items():
            print(f"  {variant:<22}" + "".join(f"{per_target[name]['psnr_db']:>16.2f}"
                                               for name in result.names))
        if layout.violations:
            print(f"{len(layout.violations)} process rule violation(s):")
            for v in layout.violations[:10]:
                print(f"  {v.rule}" + ("" if v.cell is None else f" cell {v.cell}")
                      + f": {v.resolution}")
    judgement = Judgement.of(report["verdicts"])
    wrote = (f"wrote {result.folder}/ ({result.kind} {args.part}: {layout.count} holes, "
             f"display content {result.display_source})")
    output.result(judgement.line(wrote, result.folder / "report.html", args.strict))
    return judgement.status(args.strict)


def _cmd_assembly(args: argparse.Namespace) -> int:
    from aperture_fab.pipeline.assembly_job import run_assembly

    path = run_assembly(args.design_folder, args.out)
    print(f"wrote {path} (print it at 100 %; the guide is docs/assembly.md)")
    return EXIT_OK


def _pair_mm(text: str, flag: str) -> tuple[float, float]:
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"{flag} {text!r}: give two numbers in mm as X,Y, e.g. 1.5,-0.5.") \
            from None
    return (x, y)


def _cmd_render(args: argparse.Namespace) -> int:
    from aperture_fab.pipeline.render_job import run_render

    focus: Any = None
    if args.focus is not None:
        focus = "infinity" if args.focus == "infinity" else _focus_mm(args.focus)
    rendered = run_render(
        args.part, config_path=args.config, target=args.target, target_index=args.target_index,
        target_options=_target_options(args),
        eye_mm=None if args.eye is None else _pair_mm(args.eye, "--eye"), pupil_mm=args.pupil,
        focus_mm=focus, mesh=args.mesh, mesh_samples=args.mesh_samples, process=args.process,
        out=args.out)
    x, y = rendered.eye_mm
    quality = "" if rendered.psnr_db is None else f"PSNR {rendered.psnr_db:.2f} dB after gain, "
    print(f"wrote {rendered.path}: eye at ({x:g}, {y:g}) mm, {quality}"
          f"light efficiency {rendered.light_efficiency:.3g}")
    return 0


def _display_arguments(args: argparse.Namespace) -> None:
    """display's usage, checked as argparse would (exit 2): PART, one TARGET, --eye, --pupil
    and --out, or --refit with TARGETs and none of PART's flags."""
    parser: argparse.ArgumentParser = args.display_parser
    if args.refit is not None:
        given = [flag for flag, value in (("--eye", args.eye), ("--pupil", args.pupil),
                                          ("--out", args.out), ("--focus", args.focus),
                                          ("--config", args.config), ("--process", args.process))
                 if value is not None]
        if given:
            parser.error(f"--refit re-fits the untracked display content and writes into "
                         f"MEASURED_FOLDER; drop {', '.join(given)}. For a tracked frame of the "
                         "measured plate: aperture-fab display MEASURED_FOLDER/holes.csv TARGET "
                         "--eye X,Y --pupil MM --out FRAME.png")
        if args.part is None:
            parser.error("the following arguments are required: TARGET (with --refit: the "
                         "design's targets)")
        return
    missing = [name for name, value in (("PART", args.part), ("TARGET", args.target or None),
                                        ("--eye", args.eye), ("--pupil", args.pupil),
                                        ("--out", args.out)) if value is None]
    if missing:
        parser.error(f"the following arguments are required: {', '.join(missing)}")
    if len(args.target) > 1:
        parser.error(f"unrecognized arguments: {' '.join(map(str, args.target[1:]))} (display "
                     "takes one TARGET; several only with --refit)")


def _display_refit(args: argparse.Namespace) -> int:
    """display --refit: the display content re-fitted to the measured plate (issue 17)."""
    from aperture_fab.measure.job import run_refit

    targets = [args.part, *args.target]
    result = run_refit(args.refit, targets, target_options=_target_options(args),
                       iterations=args.iterations, progress=args.output.progress,
                       command=args.command_line)
    r = result.refit
    output: Output = args.output
    output.timings(result.timings_s)
    recovered = ("no tolerance loss to recover (the made plate scores at least the nominal)"
                 if r.recovered is None else f"the refit recovers {r.recovered:.0%} of the "
                 f"{r.loss_db:.2f} dB tolerance loss ({r.left_db:.2f} dB left against the "
                 f"nominal plate re-fitted alike, {r.nominal_refit_db:.2f} dB)")
    output.result(f"wrote {result.folder}/refit.json and {len(result.paths)} refit display "
                  f"image(s): PSNR after gain {r.nominal_db:.2f} dB nominal, {r.made_db:.2f} dB "
                  f"made (design's content), {r.refit_db:.2f} dB made (refit, {r.iterations} "
                  f"iterations): {recovered}")
    return EXIT_OK


def _cmd_display(args: argparse.Namespace) -> int:
    from aperture_fab.pipeline.render_job import run_display

    _display_arguments(args)
    if args.refit is not None:
        return _display_refit(args)
    focus: Any = None
    if args.focus is not None:
        focus = "infinity" if args.focus == "infinity" else _focus_mm(args.focus)
    frame = run_display(
        args.part, args.target[0], eye_mm=_pair_mm(args.eye, "--eye"), pupil_mm=args.pupil,
        target_options=_target_options(args),
        focus_mm=focus, iterations=args.iterations, config_path=args.config,
        target_index=args.target_index, process=args.process, out=args.out)
    x, y = frame.eye_mm
    height, width = frame.display.shape[1:]
    focus_text = "infinity" if frame.focus_mm is None else f"{frame.focus_mm:g} mm"
    args.output.detail(f"PSNR after gain: {frame.start_psnr_db:.2f} dB untracked -> "
                       f"{frame.psnr_db:.2f} dB tracked ({frame.iterations} iterations, solved "
                       f"in {frame.solve_s:.2f} s)")
    args.output.result(f"wrote {frame.path}: {width} x {height} display frame for the eye at "
                       f"({x:g}, {y:g}) mm, pupil {frame.pupil_mm:g} mm, focus {focus_text}")
    return 0


def _cmd_measure(args: argparse.Namespace) -> int:
    from aperture_fab.measure.job import run_measure
    from aperture_fab.measure.transform import mm_per_px_of_dpi

    if args.scale_mm_per_px is not None:
        if not args.scale_mm_per_px > 0:
            raise ValueError(f"--scale-mm-per-px {args.scale_mm_per_px:g}: give the pixel size "
                             "in mm (> 0), e.g. 0.00529 for 4800 dpi.")
        mm_per_px = args.scale_mm_per_px
    else:
        mm_per_px = mm_per_px_of_dpi(args.dpi)
    if args.coupon:
        return _measure_coupon(args, mm_per_px)
    result = run_measure(args.scan, args.design, args.out, mm_per_px, args.encoding,
                         command=args.command_line)
    m = result.measurement
    output: Output = args.output
    output.timings(result.timings_s)
    for note in result.notes:  # the mirror is a mistake to fix next time: a warning
        if "mirrored" in note:
            output.warn(note)
        else:
            output.detail(note)
    output.detail(f"process on this plate: radius bias {m.bias_mm * 1000:.2f} um, sigma "
                  f"{m.sigma_mm * 1000:.2f} um; registration residual "
                  f"{m.registration.residual_mm * 1000:.2f} um RMS")
    output.result(f"wrote {result.folder}/ (holes.csv, measured.json, measured.html, "
                  "design.toml: a design folder of the plate as made): "
                  f"{m.count('ok')} of {m.design.count} holes measured, {m.count('blocked')} "
                  f"blocked, {len(m.extra_index)} extra opening(s)")
    return EXIT_OK


def _measure_coupon(args: argparse.Namespace, mm_per_px: float) -> int:
    """measure --coupon: the process as the calibration coupon's scan shows it."""
    from aperture_fab.measure.job import PROCESS_NAME, run_measure_coupon

    result = run_measure_coupon(args.scan, args.design, args.out, mm_per_px, args.encoding,
                                command=args.command_line)
    output: Output = args.output
    output.timings(result.timings_s)
    for note in result.notes:
        (output.warn if "mirrored" in note else output.detail)(note)
    for block in result.calibration.blocks:
        output.detail(f"  {block.drawn_diameter_mm * 1000:7.2f} um drawn: {block.opened} of "
                      f"{block.holes} came through, made radius "
                      + ("n/a" if block.measured == 0 else
                         f"{block.radius_mean_mm * 1000:.2f} um"))
    values = ", ".join(f"{k} = {v:g}" for k, v in result.process.items())
    output.result(f"wrote {result.folder}/{PROCESS_NAME} ([process] {values}; design "
                  f"--config takes it), coupon_holes.csv, measured.json, measured.html")
    return EXIT_OK


def _focus_mm(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"--focus {text!r}: give a distance in mm or 'infinity'.") from None


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
process's radius bias applied). The solver is MLEM (Richardson-Lucy); it prints the PSNR after
gain of the view with the untracked and the tracked content, and the solve time (the first
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
    _add_config_flags(p)
    _add_fabrication_flags(p)
    _add_validation_flags(p)
    _add_strict_flag(p)
    _add_target_flags(p)
    p.set_defaults(func=_cmd_design)

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
    _add_fabrication_flags(p)
    p.set_defaults(func=_cmd_export)

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
    _add_target_flags(p)
    _add_strict_flag(p)
    p.set_defaults(func=_cmd_validate)

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
    _add_target_flags(p)
    p.set_defaults(func=_cmd_render)

    p = sub.add_parser("display", help="the display frame for a tracked eye state",
                       description="Solve the display content of a part for one eye state "
                       "(pupil position and size, as an eye tracker reports them), the plate "
                       "fixed, and write it as an sRGB PNG at the display's pixel count.",
                       epilog=DISPLAY_EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    # Optional here, required below (_display_arguments): --refit takes neither PART nor --eye.
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
    p.add_argument("--config", type=Path, metavar="FILE.toml",
                   help="the design's config (default: design.toml beside PART)")
    p.add_argument("--target-index", type=int, default=0, metavar="N",
                   help="which of the design's display contents to start from (default 0)")
    p.add_argument("--process", help="fabrication process (default: the config's, else resin)")
    p.add_argument("--out", type=Path, metavar="FRAME.png",
                   help="PNG to write; required without --refit")
    _add_target_flags(p)
    p.set_defaults(func=_cmd_display, display_parser=p)

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
    p.set_defaults(func=_cmd_assembly)

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
    p.set_defaults(func=_cmd_measure)

    p = sub.add_parser("presets", help="list the presets with their key numbers")
    p.set_defaults(func=_cmd_presets)
    p = sub.add_parser("processes", help="list the fabrication processes and their rules")
    p.set_defaults(func=_cmd_processes)
    from aperture_fab.sweep.command import add_parser as add_sweep_parser

    add_sweep_parser(sub)
    for command in sub.choices.values():
        _add_output_flags(command)
    return parser


def _add_output_flags(parser: argparse.ArgumentParser) -> None:
    """-q/--quiet and -v/--verbose, on every command (one that defines its own is left alone)."""
    if "--quiet" in parser._option_string_actions:
        return
    group = parser.add_argument_group("output").add_mutually_exclusive_group()
    group.add_argument("-q", "--quiet", action="store_true",
                       help="print only errors and the final one-line result; no progress")
    group.add_argument("-v", "--verbose", action="store_true",
                       help="tracebacks for errors, and the time of each stage")


def _exit_code(err: BaseException) -> int:
    """EXIT_FAILED for a failure the tool judged (JUDGED_FAILURES), EXIT_NO_CLUSTER for a Ray
    cluster out of reach (UNREACHABLE), EXIT_CANNOT_WRITE for a file system error, else
    EXIT_BAD_INPUT."""
    for module, name in JUDGED_FAILURES:
        loaded = sys.modules.get(module)  # not imported: the error cannot be one of its classes
        if loaded is not None and isinstance(err, getattr(loaded, name)):
            return EXIT_FAILED
    for module, name in UNREACHABLE:
        loaded = sys.modules.get(module)
        if loaded is not None and isinstance(err, getattr(loaded, name)):
            return EXIT_NO_CLUSTER
    if isinstance(err, OSError) and not isinstance(err, FileNotFoundError):
        return EXIT_CANNOT_WRITE
    return EXIT_BAD_INPUT


def _os_error_message(err: OSError, args: argparse.Namespace) -> str:
    """One line for a file the tool could not read or write: the file, why, and the fix."""
    out = getattr(args, "out", None)
    # write_atomic writes .NAME.<12 hex>.tmp and renames it: name the file the user asked for.
    what = (TEMP_NAME.sub(r"\1", str(err.filename)) if err.filename
            else f"an output of --out {out}" if out is not None else "a file")
    why = err.strerror or str(err) or type(err).__name__
    fix = OS_ERROR_FIXES.get(err.errno or 0, "check the path and its permissions, then try again")
    return f"cannot write or read {what}: {why}; {fix}."


def _refuse_empty_arguments(parser: argparse.ArgumentParser, argv: Sequence[str]) -> None:
    """A usage error for an empty argument ("" or --flag=): no value of any flag is empty, and
    an empty path would be read as the current folder (--out "$OUT" with OUT unset would write
    the part there)."""
    for n, arg in enumerate(argv):
        if arg.startswith("--") and arg.endswith("="):
            what = f"{arg.removesuffix('=')} is given an empty value"
        elif arg == "":
            before = argv[n - 1] if n else ""
            what = (f"{before} is given an empty value" if before.startswith("-")
                    else f"argument {n + 1} is empty")
        else:
            continue
        parser.error(f"{what}; give a value (a file or folder name, a number or a choice; an "
                     "unset shell variable gives an empty one).")


def _missing_package(err: ImportError) -> bool:
    """Whether an ImportError says that a package is not installed (an optional extra such as
    the STEP writer's OCP, or a dependency), not that the tool's own code is broken."""
    return not (err.name or "").startswith(f"{PACKAGE_NAME}.")


def _missing_package_message(err: ImportError) -> str:
    """One line for a package that is not installed: the tool's own message, which names the
    package and its install line, or Python's, completed with the fix."""
    if err.name is None:  # raised by the tool, e.g. "STEP export needs OCCT's Python bindings"
        return str(err)
    return (f"this command needs the Python package {err.name!r}, which is not installed "
            f"({err}); install it, or reinstall aperture-fab with its extras "
            "(./dev setup installs them all).")


def _show_warning(output: Output, default: Any) -> Any:
    """A warnings.showwarning that prints the tool's own warnings as one line each (not with -q)
    and leaves every other library's warning to `default`."""

    def show(message: Warning | str, category: type[Warning], filename: str, lineno: int,
             file: Any = None, line: str | None = None) -> None:
        if filename.startswith(PACKAGE_DIR):
            output.warn(str(message))
        else:
            default(message, category, filename, lineno, file, line)

    return show


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command; returns one of the EXIT_* codes (listed in EXIT_CODES_HELP)."""
    parser = build_parser()
    _refuse_empty_arguments(parser, sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(argv)  # a usage error exits with EXIT_USAGE (argparse's 2)
    if getattr(args, "strict", False) and getattr(args, "no_validate", False):
        # --strict judges the report, which --no-validate does not write: one flag is a mistake.
        parser.error("--strict exits on the report's WARN, but --no-validate writes no report: "
                     "drop one of them.")
    # Recorded in an output folder's manifest.json: how to re-run what wrote it.
    args.command_line = ["aperture-fab", *(sys.argv[1:] if argv is None else argv)]
    output = Output(quiet=bool(getattr(args, "quiet", False)),
                    verbose=bool(getattr(args, "verbose", False)),
                    terminal=sys.stderr.isatty())
    args.output = output
    main_thread = threading.current_thread() is threading.main_thread()
    sigterm = _Sigterm()
    before = signal.signal(signal.SIGTERM, sigterm) if main_thread else None
    try:
        code = _run(args, output)
    finally:
        if main_thread:  # None: the handler was not set from Python, i.e. the default
            signal.signal(signal.SIGTERM, signal.SIG_DFL if before is None else before)
    if sigterm.received and code != EXIT_TERMINATED:  # its Terminated was dropped on the way
        output.interrupted(f"(SIGTERM) during `{args.command}`, which went on past it inside a "
                           "compiled library; every file already written is whole. Run the "
                           "command again to finish it.")
        return EXIT_TERMINATED
    return code


def _run(args: argparse.Namespace, output: Output) -> int:
    """Run the parsed command; its exit status, with each error class's message."""
    import warnings

    try:
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning(output, warnings.showwarning)
            return int(args.func(args))
    except KeyboardInterrupt as err:
        output.traceback()
        how, code = _how_stopped(err)
        output.interrupted(f"({how}) during `{args.command}`; every file already written is "
                           "whole (each is written completely or not at all). Run the command "
                           "again to finish it.")
        return code
    except MemoryError:
        output.traceback()
        output.error(f"`{args.command}` ran out of memory: the job is larger than this machine "
                     "can hold. Make it smaller (fewer view_pixels, eye states, tolerance or "
                     "mesh samples, a smaller display or plate) or run it on a larger machine.")
        return EXIT_FAILED
    except ImportError as err:
        if not _missing_package(err):
            raise  # the tool's own code is broken: its traceback is the report
        output.traceback()
        output.error(_missing_package_message(err))
        return EXIT_USAGE
    except (ValueError, TypeError, OSError, FloatingPointError) as err:
        output.traceback()
        code = _exit_code(err)
        output.error(_os_error_message(err, args) if isinstance(err, OSError)
                     and code == EXIT_CANNOT_WRITE else str(err))
        return code


if __name__ == "__main__":
    sys.exit(main())
