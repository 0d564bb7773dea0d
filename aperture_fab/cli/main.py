"""`aperture-fab`'s entry point: run one command, map its outcome to an exit status."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from collections.abc import Sequence

from aperture_fab.cli.flags import refuse_empty_arguments
from aperture_fab.cli.output import Output, show_warning
from aperture_fab.cli.parser import build_parser
from aperture_fab.cli.status import (
    EXIT_CANNOT_WRITE,
    EXIT_FAILED,
    EXIT_USAGE,
    Stop,
    exit_code,
    how_stopped,
    missing_package,
    missing_package_message,
    os_error_message,
)

__all__ = ["main"]

#: The signals that stop a command the way Ctrl-C does (a checkpoint, whole files).
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command; returns one of the EXIT_* codes (listed in EXIT_CODES_HELP)."""
    parser = build_parser()
    refuse_empty_arguments(parser, sys.argv[1:] if argv is None else argv)
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
    stop = Stop()
    before = {signum: signal.signal(signum, stop) for signum in STOP_SIGNALS} if main_thread \
        else {}
    try:
        code = _run(args, output)
    finally:
        for signum, handler in before.items():  # None: not set from Python, i.e. the default
            signal.signal(signum, signal.SIG_DFL if handler is None else handler)
    how, stopped = stop.how
    if stop.signum is not None and code != stopped:  # its exception was dropped on the way
        output.interrupted(f"({how}) during `{args.command}`, which went on past it inside a "
                           "compiled library; every file already written is whole. Run the "
                           "command again to finish it.")
        return stopped
    return code


def _run(args: argparse.Namespace, output: Output) -> int:
    """Run the parsed command; its exit status, with each error class's message."""
    import warnings

    try:
        with warnings.catch_warnings():
            warnings.showwarning = show_warning(output, warnings.showwarning)
            return int(args.func(args))
    except KeyboardInterrupt as err:
        output.traceback()
        how, code = how_stopped(err)
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
        if not missing_package(err):
            raise  # the tool's own code is broken: its traceback is the report
        output.traceback()
        output.error(missing_package_message(err))
        return EXIT_USAGE
    except (ValueError, TypeError, OSError, FloatingPointError) as err:
        output.traceback()
        code = exit_code(err)
        output.error(os_error_message(err, args) if isinstance(err, OSError)
                     and code == EXIT_CANNOT_WRITE else str(err))
        return code
