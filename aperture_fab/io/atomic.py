"""Atomic files: each written whole or not at all (a temporary file beside it, then a rename),
and the temporaries of writers that died found by their pid. The standard library only, so the
command line can name a file in its messages without loading the image stack."""

from __future__ import annotations

import contextlib
import glob
import os
import re
import secrets
from pathlib import Path

__all__ = ["TEMPORARY_NAME", "pid_alive", "remove_orphan_temporaries", "write_atomic"]


#: write_atomic's temporary file beside its target: ".<name>.<pid>-<12 hex>.tmp". The writer's
#: pid tells a later run one whose writer died (SIGKILL, power loss) from one being written.
TEMPORARY_NAME = re.compile(r"\.(?P<name>.+)\.(?P<pid>\d+)-[0-9a-f]{12}\.tmp")


def write_atomic(path: Path, data: bytes | str) -> None:
    """Write via a temporary file in the same folder and rename: never a truncated file. Once
    written, the temporaries of `path` that a killed writer left are removed."""
    payload = data.encode() if isinstance(data, str) else data
    tmp = path.parent / f".{path.name}.{os.getpid()}-{secrets.token_hex(6)}.tmp"
    try:  # the open too: an interrupt between it and the block would leave the file behind
        # os.open with 0o666 honours the umask, unlike mkstemp's private 0o600.
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        with os.fdopen(fd, "wb") as f:
            f.write(payload)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):  # the error that got here is the one to report
            tmp.unlink()
        raise
    remove_orphan_temporaries(path.parent, path.name)


def pid_alive(pid: int) -> bool:
    """Whether process `pid` still runs (another user's counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's
        return True
    return True


def remove_orphan_temporaries(folder: Path, name: str | None = None) -> None:
    """write_atomic's temporary files in `folder` (of the file `name` alone, when given) whose
    writer no longer runs; a live writer's are left alone."""
    pattern = ".*.tmp" if name is None else f".{glob.escape(name)}.*.tmp"
    for path in folder.glob(pattern):
        match = TEMPORARY_NAME.fullmatch(path.name)
        if match and (name is None or match["name"] == name) and path.is_file() \
                and not path.is_symlink() and not pid_alive(int(match["pid"])):
            with contextlib.suppress(OSError):  # another run removed it first
                path.unlink()
