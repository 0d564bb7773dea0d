"""The command line's shared flags and what they resolve to: config, fabrication, --out."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from aperture_fab.cli.status import EXIT_REPORT_FAIL, EXIT_REPORT_WARN

__all__ = ["OVERRIDES", "add_config_flags", "add_fabrication_flags", "add_output_flags",
           "add_strict_flag", "add_target_flags", "add_validation_flags", "fabrication_of",
           "load_config", "parse_focus_mm", "parse_pair_mm", "refuse_empty_arguments",
           "refuse_unmakeable", "refuse_unmakeable_export", "target_options"]


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
    ("--lattice", "optimizer.lattice", ("fixed", "rival"),
     "rival (default): when the part as made beats the best regular pinhole array by under "
     "2 dB, design again on that array's coarser lattice from its holes and keep the better "
     "part; fixed: --cells only"),
    ("--seed", "optimizer.seed", int, "random seed"),
    ("--precision", "optimizer.precision", ("float32", "float64"), "floating point precision"),
    ("--device", "optimizer.device", str, "auto (CUDA when available), cpu, cuda or cuda:N"),
)


def add_config_flags(parser: argparse.ArgumentParser) -> None:
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


def load_config(args: argparse.Namespace) -> Any:
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


def add_fabrication_flags(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("fabrication")
    group.add_argument("--process", help="fabrication process (see `aperture-fab processes`); "
                       "default: the config's [process] (design.toml records it), else resin")
    group.add_argument("--force", action="store_true", default=None,
                       help="write parts the process cannot make, with the violations "
                       "listed; replace a design in --out that was validated (its validation "
                       "folders go with it)")
    group.add_argument("--step", action="store_true", default=None,
                       help="also write plate.step (a .step --out implies it)")


def add_validation_flags(parser: argparse.ArgumentParser) -> None:
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


def add_target_flags(parser: argparse.ArgumentParser) -> None:
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


def target_options(args: argparse.Namespace) -> Any:
    """The TargetOptions of --alpha, --fit and --frame."""
    from aperture_fab.io.images import TargetOptions

    return TargetOptions(alpha=args.alpha, fit=args.fit, frame=args.frame)


def add_strict_flag(parser: Any) -> None:
    """--strict, on the commands that judge a part (design, validate)."""
    parser.add_argument("--strict", action="store_true",
                        help=f"exit with status {EXIT_REPORT_WARN} when the report says WARN "
                        f"(a FAIL exits {EXIT_REPORT_FAIL} always); the files are written either "
                        "way")


def fabrication_of(args: argparse.Namespace, config: Any) -> Any:
    """The config's fabrication settings with the flags --process, --force and --step."""
    return config.fabrication.with_flags(args.process, args.force, args.step)


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


def refuse_unmakeable(process: Any, scene: Any, command: list[str], why: str = "") -> None:
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


def refuse_unmakeable_export(args: argparse.Namespace, config: Any, fabrication: Any,
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
    refuse_unmakeable(
        fabrication.process, config.scene, command,
        f" {args.design} holds open fractions optimized through its own "
        f"{plate.thickness_mm:g} mm plate of {pitch} mm cells (the hole walls clip oblique "
        "light by the thickness; the cells are the design's grid), so export cannot re-make "
        f"them in another plate. TARGET: the image(s) the design was made for{which}.")


def parse_pair_mm(text: str, flag: str) -> tuple[float, float]:
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"{flag} {text!r}: give two numbers in mm as X,Y, e.g. 1.5,-0.5.") \
            from None
    return (x, y)


def parse_focus_mm(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"--focus {text!r}: give a distance in mm or 'infinity'.") from None


def add_output_flags(parser: argparse.ArgumentParser) -> None:
    """-q/--quiet and -v/--verbose, on every command (one that defines its own is left alone)."""
    if "--quiet" in parser._option_string_actions:
        return
    group = parser.add_argument_group("output").add_mutually_exclusive_group()
    group.add_argument("-q", "--quiet", action="store_true",
                       help="print only errors and the final one-line result; no progress")
    group.add_argument("-v", "--verbose", action="store_true",
                       help="tracebacks for errors, and the time of each stage")


def refuse_empty_arguments(parser: argparse.ArgumentParser, argv: Sequence[str]) -> None:
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
