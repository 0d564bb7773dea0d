"""The `aperture-fab` command line: `main` runs one command and returns its exit status.

Modules: `parser` (every command's flags and help), `flags` (the shared flags and what they
resolve to), `commands` and `view_commands` (one function per command: parse, call the
pipeline, print), `output` (what is printed), `status` (exit statuses), `main` (the entry
point: signals, warnings, each error class's status).
"""

from __future__ import annotations

from aperture_fab.cli.main import main
from aperture_fab.cli.parser import build_parser
from aperture_fab.cli.status import (
    EXIT_BAD_INPUT,
    EXIT_CANNOT_WRITE,
    EXIT_CODES_HELP,
    EXIT_FAILED,
    EXIT_INTERRUPTED,
    EXIT_NO_CLUSTER,
    EXIT_OK,
    EXIT_REPORT_FAIL,
    EXIT_REPORT_WARN,
    EXIT_TERMINATED,
    EXIT_USAGE,
)

__all__ = ["EXIT_BAD_INPUT", "EXIT_CANNOT_WRITE", "EXIT_CODES_HELP", "EXIT_FAILED",
           "EXIT_INTERRUPTED", "EXIT_NO_CLUSTER", "EXIT_OK", "EXIT_REPORT_FAIL",
           "EXIT_REPORT_WARN", "EXIT_TERMINATED", "EXIT_USAGE", "build_parser", "main"]
