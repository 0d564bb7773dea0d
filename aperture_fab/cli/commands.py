"""The `design`, `validate`, `export`, `assembly`, `presets` and `processes` commands."""

from __future__ import annotations

import argparse

from aperture_fab.cli.flags import (
    fabrication_of,
    load_config,
    refuse_unmakeable,
    refuse_unmakeable_export,
    target_options,
)
from aperture_fab.cli.output import (
    Judgement,
    Output,
    print_design_tables,
    print_eye_distribution,
    report_forced,
)
from aperture_fab.cli.status import EXIT_OK, how_stopped

__all__ = ["cmd_assembly", "cmd_design", "cmd_export", "cmd_presets", "cmd_processes",
           "cmd_validate"]


def cmd_presets(args: argparse.Namespace) -> int:
    from aperture_fab.config.presets import DEFAULT_PRESET, PRESETS, preset_summary

    for name in PRESETS:
        print(preset_summary(name))
        print()
    args.output.result(f"{len(PRESETS)} presets: {', '.join(PRESETS)}; start from one with "
                       f"--preset NAME (default {DEFAULT_PRESET})")
    return 0


def cmd_processes(args: argparse.Namespace) -> int:
    from aperture_fab.fabrication.process import PROCESSES, process_summary

    for process in PROCESSES.values():
        print(process_summary(process))
        print()
    args.output.result(f"{len(PROCESSES)} processes: {', '.join(PROCESSES)}; choose one with "
                       "--process NAME")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from aperture_fab.io.formats import PART_FILE_SUFFIXES
    from aperture_fab.pipeline.export_job import part_format_of, read_export_inputs, run_export

    config_path = args.config or args.design.parent / "design.toml"
    # An --out that names a part file writes that one file, under the name given (its folder
    # is its parent); any other --out is a folder that gets every format.
    named = part_format_of(args.out, PART_FILE_SUFFIXES)
    open_fraction, config = read_export_inputs(args.design, config_path, args.preset)
    # The process design.toml records, or --process.
    fabrication = fabrication_of(args, config)
    if not fabrication.force:
        refuse_unmakeable_export(args, config, fabrication, config_path)
    exported = run_export(open_fraction, config, fabrication, args.out, named,
                          progress=args.output.progress, stage=args.output.stage)
    report_forced(args.output, exported.part, config, fabrication)
    args.output.result(f"wrote {exported.part.layout.count} holes, process "
                       f"{fabrication.process.name}: "
                       + ", ".join(str(p) for p in exported.written))
    return 0


def cmd_design(args: argparse.Namespace) -> int:
    from aperture_fab.io.files import folder_for
    from aperture_fab.optimize.optimizer import Interrupted
    from aperture_fab.pipeline.design_job import run_design

    config = load_config(args)
    fabrication = fabrication_of(args, config)
    if not fabrication.force:  # refused before any work, with the flags that make it possible
        refuse_unmakeable(fabrication.process, config.scene, args.command_line)
    validation = None if args.no_validate else config.validation.with_flags(
        tolerance_samples=args.tolerance_samples, mesh_samples=args.mesh_samples)
    from aperture_fab.io.formats import PART_SUFFIXES
    from aperture_fab.pipeline.export_job import part_format_of

    output: Output = args.output
    named = part_format_of(args.out, PART_SUFFIXES)
    folder = folder_for(args.out)  # run_design creates it (and removes it if refused)
    output.stage(f"design: {config.optimizer.iterations} iterations, then the part"
                 + ("" if validation is None else " and its validation")
                 + f", into {folder}/")
    try:
        result = run_design(args.targets, args.out, config, fabrication=fabrication,
                            target_options=target_options(args),
                            validation=validation, resume=args.resume, progress=output.progress,
                            command=args.command_line, stage=output.stage,
                            replace_validated=bool(args.force))
    except Interrupted as stop:
        how, code = how_stopped(stop)
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
        report_forced(output, result.part, config, fabrication)
    if not output.quiet:
        print_design_tables(result, fabrication, validated=validation is not None)
    if validation is None:  # no report: say so rather than let "wrote" read as a pass
        targets = " ".join(str(t) for t in args.targets)
        output.result(f"NOT VALIDATED: {wrote} - --no-validate: no report and no verdict; "
                      f"judge the part with `aperture-fab validate {folder / 'plate.stl'} "
                      f"{targets}`")
        return EXIT_OK
    judgement = Judgement.of(result.verdicts)
    output.result(judgement.line(wrote, folder / "report.html", args.strict))
    return judgement.status(args.strict)


def cmd_validate(args: argparse.Namespace) -> int:
    from aperture_fab.pipeline.validate_job import run_validate
    from aperture_fab.validation.report import eye_headline

    result = run_validate(args.part, args.targets, config_path=args.config, out=args.out,
                          target_options=target_options(args),
                          process=args.process, keep_display=args.keep_display,
                          tolerance_samples=args.tolerance_samples,
                          mesh_samples=args.mesh_samples, progress=args.output.progress,
                          stage=args.output.stage, command=args.command_line)
    metrics = result.validation.metrics
    layout = result.part.layout
    # The verdicts as published: the exit status follows the report the user will read.
    report = result.report
    output: Output = args.output
    output.timings(result.timings_s)
    if not output.quiet:
        print_eye_distribution({"eye_distribution": eye_headline(report)}, result.names,
                                validated=True, verdicts=report.verdicts)
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
    judgement = Judgement.of(report.verdicts)
    wrote = (f"wrote {result.folder}/ ({result.kind} {args.part}: {layout.count} holes, "
             f"display content {result.display_source})")
    output.result(judgement.line(wrote, result.folder / "report.html", args.strict))
    return judgement.status(args.strict)


def cmd_assembly(args: argparse.Namespace) -> int:
    from aperture_fab.pipeline.assembly_job import run_assembly

    path = run_assembly(args.design_folder, args.out)
    print(f"wrote {path} (print it at 100 %; the guide is docs/assembly.md)")
    return EXIT_OK
