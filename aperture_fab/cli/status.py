"""Exit statuses of the `aperture-fab` command line, and which error gets which."""

from __future__ import annotations

import argparse
import errno
import signal
from typing import Any

from aperture_fab.errors import Refused, Unreachable

__all__ = ["EXIT_BAD_INPUT", "EXIT_CANNOT_WRITE", "EXIT_CODES_HELP", "EXIT_FAILED",
           "EXIT_INTERRUPTED", "EXIT_NO_CLUSTER", "EXIT_OK", "EXIT_REPORT_FAIL", "EXIT_REPORT_WARN",
           "EXIT_TERMINATED", "EXIT_USAGE", "Stop", "exit_code", "how_stopped",
           "missing_package", "missing_package_message", "os_error_message"]


#: Exit statuses: distinct, so that scripts can tell a bad input from a refused part.
EXIT_OK = 0


# The tool judged and refused: the process cannot make the plate, or it diverged.
EXIT_FAILED = Refused.exit_status


EXIT_USAGE = 2  # argparse's own status for a bad command line; also a missing package


EXIT_BAD_INPUT = 3


EXIT_CANNOT_WRITE = 4


# The part's files and its report are written either way (the user needs the report to see why);
# only the status says that the report's overall verdict refuses the part.
EXIT_REPORT_FAIL = 5  # the report says FAIL: do not make the part as it is


EXIT_REPORT_WARN = 6  # with --strict only: the report says WARN


# `sweep`: the Ray cluster at --address could not be reached.
EXIT_NO_CLUSTER = Unreachable.exit_status


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



#: The package's import name: an ImportError inside it is a bug, not a missing package.
PACKAGE_NAME = "aperture_fab"


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread so that it stops a command the way Ctrl-C does: a
    design saves its checkpoint, every file written so far is whole."""


class Stop:
    """The SIGINT and SIGTERM handler: raises KeyboardInterrupt (Terminated for SIGTERM), as
    Python's own SIGINT handler does, and remembers the first signal. A raise that lands inside
    a ctypes callback (Numba's compiler, LLVM) is printed and dropped there, and the command
    goes on or fails for another reason; main still exits as stopped by that signal."""

    def __init__(self) -> None:
        self.signum: int | None = None

    def __call__(self, signum: int, frame: Any) -> None:
        if self.signum is None:
            self.signum = signum
        raise Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()

    @property
    def how(self) -> tuple[str, int]:
        """The stop's name and exit status, as `how_stopped` gives them."""
        if self.signum == signal.SIGTERM:
            return "SIGTERM", EXIT_TERMINATED
        return "Ctrl-C", EXIT_INTERRUPTED


def how_stopped(err: BaseException) -> tuple[str, int]:
    """How a command was stopped ("Ctrl-C" or "SIGTERM") and its exit status; `err` is the
    KeyboardInterrupt or an exception raised while handling one (the design's Interrupted)."""
    stop = err if isinstance(err, KeyboardInterrupt) else err.__context__
    if isinstance(stop, Terminated):
        return "SIGTERM", EXIT_TERMINATED
    return "Ctrl-C", EXIT_INTERRUPTED


def exit_code(err: BaseException) -> int:
    """The status an error class carries (aperture_fab.errors: a job the tool refused, a
    cluster out of reach), else EXIT_CANNOT_WRITE for a file system error, else
    EXIT_BAD_INPUT."""
    if isinstance(err, Refused | Unreachable):
        return err.exit_status
    if isinstance(err, OSError) and not isinstance(err, FileNotFoundError):
        return EXIT_CANNOT_WRITE
    return EXIT_BAD_INPUT


def _file_asked_for(path: str) -> str:
    """`path`, or the file write_atomic was writing when `path` is its temporary file."""
    from aperture_fab.io.atomic import TEMPORARY_NAME

    folder, _, name = path.rpartition("/")
    match = TEMPORARY_NAME.fullmatch(name)
    return path if match is None else f"{folder}/{match['name']}" if folder else match["name"]


def os_error_message(err: OSError, args: argparse.Namespace) -> str:
    """One line for a file the tool could not read or write: the file, why, and the fix."""
    out = getattr(args, "out", None)
    # write_atomic writes a temporary file and renames it: name the file the user asked for.
    what = (_file_asked_for(str(err.filename)) if err.filename
            else f"an output of --out {out}" if out is not None else "a file")
    why = err.strerror or str(err) or type(err).__name__
    fix = OS_ERROR_FIXES.get(err.errno or 0, "check the path and its permissions, then try again")
    return f"cannot write or read {what}: {why}; {fix}."


def missing_package(err: ImportError) -> bool:
    """Whether an ImportError says that a package is not installed (an optional extra such as
    the STEP writer's OCP, or a dependency), not that the tool's own code is broken."""
    return not (err.name or "").startswith(f"{PACKAGE_NAME}.")


def missing_package_message(err: ImportError) -> str:
    """One line for a package that is not installed: the tool's own message, which names the
    package and its install line, or Python's, completed with the fix."""
    if err.name is None:  # raised by the tool, e.g. "STEP export needs OCCT's Python bindings"
        return str(err)
    return (f"this command needs the Python package {err.name!r}, which is not installed "
            f"({err}); install it, or reinstall aperture-fab with its extras "
            "(./dev setup installs them all).")
