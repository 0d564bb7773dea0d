"""The `render`, `display` and `measure` commands."""

from __future__ import annotations

import argparse
from typing import Any

from aperture_fab.cli.flags import parse_focus_mm, parse_pair_mm, target_options
from aperture_fab.cli.output import Output
from aperture_fab.cli.status import EXIT_OK

__all__ = ["cmd_display", "cmd_measure", "cmd_render"]


def cmd_render(args: argparse.Namespace) -> int:
    from aperture_fab.pipeline.render_job import run_render

    focus: Any = None
    if args.focus is not None:
        focus = "infinity" if args.focus == "infinity" else parse_focus_mm(args.focus)
    rendered = run_render(
        args.part, config_path=args.config, target=args.target, target_index=args.target_index,
        target_options=target_options(args),
        eye_mm=None if args.eye is None else parse_pair_mm(args.eye, "--eye"), pupil_mm=args.pupil,
        focus_mm=focus, mesh=args.mesh, mesh_samples=args.mesh_samples, process=args.process,
        out=args.out)
    x, y = rendered.eye_mm
    quality = "" if rendered.psnr_db is None else f"PSNR {rendered.psnr_db:.2f} dB after gain, "
    print(f"wrote {rendered.path}: eye at ({x:g}, {y:g}) mm, {quality}"
          f"light efficiency {rendered.light_efficiency:.3g}")
    return 0


def display_arguments(args: argparse.Namespace) -> None:
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
    result = run_refit(args.refit, targets, target_options=target_options(args),
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


def cmd_display(args: argparse.Namespace) -> int:
    from aperture_fab.pipeline.render_job import run_display

    display_arguments(args)
    if args.refit is not None:
        return _display_refit(args)
    focus: Any = None
    if args.focus is not None:
        focus = "infinity" if args.focus == "infinity" else parse_focus_mm(args.focus)
    frame = run_display(
        args.part, args.target[0], eye_mm=parse_pair_mm(args.eye, "--eye"), pupil_mm=args.pupil,
        target_options=target_options(args),
        focus_mm=focus, iterations=args.iterations, light_floor=args.light_floor,
        config_path=args.config,
        target_index=args.target_index, process=args.process, out=args.out)
    x, y = frame.eye_mm
    height, width = frame.display.shape[1:]
    focus_text = "infinity" if frame.focus_mm is None else f"{frame.focus_mm:g} mm"
    args.output.detail(f"PSNR after gain: {frame.start_psnr_db:.2f} dB untracked -> "
                       f"{frame.psnr_db:.2f} dB tracked ({frame.iterations} iterations, solved "
                       f"in {frame.solve_s:.2f} s); light at the eye {frame.light_share:.2f} "
                       f"of the untracked display's (floor {frame.light_floor:g})")
    args.output.result(f"wrote {frame.path}: {width} x {height} display frame for the eye at "
                       f"({x:g}, {y:g}) mm, pupil {frame.pupil_mm:g} mm, focus {focus_text}")
    return 0


def cmd_measure(args: argparse.Namespace) -> int:
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
