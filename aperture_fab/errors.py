"""The error classes that carry their own exit status: the command line maps an error to its
status by the class, not by its name or module, so a new failure of one of these kinds gets
its status by subclassing. Every other ValueError or TypeError is a bad input, an OSError a
file that could not be read or written (aperture_fab.cli.status)."""

from __future__ import annotations

from typing import ClassVar

__all__ = ["Refused", "Unreachable"]


class Refused(Exception):
    """The tool judged the job and refused it: the process cannot make the plate, the
    optimization diverged. Mixed into the concrete class beside its Python kind
    (`class UnmakeableError(Refused, ValueError)`)."""

    exit_status: ClassVar[int] = 1


class Unreachable(Exception):
    """A service the job needs (a Ray cluster) could not be reached: a connection error, not a
    file error, though both are OSErrors."""

    exit_status: ClassVar[int] = 7
