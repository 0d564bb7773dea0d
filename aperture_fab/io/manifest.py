"""An output folder as one consistent set: a run writes into a staging folder, publishes every
file at once, and records them in `manifest.json`, which readers check.

Why: files written one by one into the output folder leave a mix of two runs behind when a run
is refused, skips a step or is killed (a new plate.stl beside the old plate.dxf). So a run
writes everything into `<folder>/.staging-<pid>-<random>/` (same filesystem: renames are
atomic), then `publish` renames each file into place, removes the files of an earlier run that
this run did not write (only names this tool writes, never the user's files), and writes
`manifest.json` LAST: each file's SHA-256 and size, the command, the tool version and the time.
A reader (`check_folder`) refuses a folder whose files do not match its manifest: a partial or
stale set. Until the new manifest is written, the folder holds a manifest marked incomplete, so
a run killed while publishing is refused too, never read as a set.
"""

from __future__ import annotations

import contextlib
import datetime
import fnmatch
import hashlib
import json
import os
import secrets
import shutil
from collections.abc import Collection, Iterator, Sequence
from pathlib import Path
from typing import Any

from aperture_fab.io.files import write_atomic
from aperture_fab.io.formats import PART_FORMATS

__all__ = [
    "MANIFEST_NAME",
    "check_folder",
    "file_sha256",
    "is_tool_file",
    "publish",
    "refuse_overwrite",
    "staging",
]

MANIFEST_NAME = "manifest.json"
MANIFEST_SCHEMA_VERSION = 1
STAGING_PREFIX = ".staging-"
#: Files this tool writes into an output folder (exact names, then patterns). A publish removes
#: these when an earlier run wrote them and this run did not; any other file is the user's.
TOOL_FILE_NAMES: tuple[str, ...] = (
    *(fmt.file_name for fmt in PART_FORMATS.values()),
    "report.json", "report.html", "views.npz", "loss.png", "assembly.html",
    "design.npz", "design.toml", "design.json", MANIFEST_NAME,
)
TOOL_FILE_PATTERNS: tuple[str, ...] = ("view_*.png", "display_*.png", "target_*.png")
#: Read files in blocks this large when hashing (a large STL need not fit in memory twice).
HASH_BLOCK_BYTES = 1 << 20


def is_tool_file(name: str) -> bool:
    """Whether a file name is one this tool writes into an output folder."""
    return name in TOOL_FILE_NAMES or any(fnmatch.fnmatchcase(name, p) for p in TOOL_FILE_PATTERNS)


def file_sha256(path: Path) -> str:
    """The SHA-256 of a file's bytes, as hex."""
    digest = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(HASH_BLOCK_BYTES), b""):
            digest.update(block)
    return digest.hexdigest()


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's
        return True
    return True


def _remove_orphans(folder: Path) -> None:
    """Staging folders of runs that died (SIGKILL, power loss): their pid no longer runs."""
    for path in folder.glob(f"{STAGING_PREFIX}*"):
        pid_text = path.name[len(STAGING_PREFIX):].split("-", 1)[0]
        if path.is_dir() and pid_text.isdigit() and not _pid_alive(int(pid_text)):
            shutil.rmtree(path, ignore_errors=True)


@contextlib.contextmanager
def staging(folder: Path) -> Iterator[Path]:
    """A fresh, empty staging folder inside `folder`, removed when the block ends (after
    `publish` it is empty; on an error the folder is left as it was)."""
    _remove_orphans(folder)
    stage = folder / f"{STAGING_PREFIX}{os.getpid()}-{secrets.token_hex(4)}"
    stage.mkdir()
    try:
        yield stage
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def _manifest_text(files: dict[str, dict[str, Any]], command: Sequence[str], complete: bool
                   ) -> str:
    from aperture_fab import __version__

    manifest = {
        "schema_version": MANIFEST_SCHEMA_VERSION,
        "complete": complete,
        "tool": "aperture-fab",
        "tool_version": __version__,
        "command": list(command),
        "created_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "files": files,
    }
    return json.dumps(manifest, indent=2) + "\n"


def _sync_folder(folder: Path) -> None:
    """Flush the folder's entries (the renames) to disk, where the OS allows it."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def publish(stage: Path, folder: Path, command: Sequence[str]) -> dict[str, dict[str, Any]]:
    """Move every file of `stage` into `folder`, remove the earlier run's tool files that this
    run did not write, and write manifest.json last. Returns the manifest's files block
    {name: {"sha256", "size_bytes"}}."""
    names = sorted(p.name for p in stage.iterdir() if p.is_file())
    files = {name: {"sha256": file_sha256(stage / name),
                    "size_bytes": (stage / name).stat().st_size} for name in names}
    # From here until the last line the folder is a mix: say so first, so a reader refuses it.
    write_atomic(folder / MANIFEST_NAME, _manifest_text(files, command, complete=False))
    for name in names:
        os.replace(stage / name, folder / name)
    for path in folder.iterdir():
        if path.name not in files and path.name != MANIFEST_NAME and is_tool_file(path.name) \
                and path.is_file():
            path.unlink()
    _sync_folder(folder)
    write_atomic(folder / MANIFEST_NAME, _manifest_text(files, command, complete=True))
    return files


def _refuse(folder: Path, problem: str, command: Sequence[str]) -> ValueError:
    rerun = " ".join(command) if command else "the command that wrote it"
    return ValueError(
        f"output folder {folder} does not match its {MANIFEST_NAME}: {problem}. It is a partial "
        f"or stale set (a run was interrupted, or files were changed or copied in); re-run "
        f"`{rerun}` into it, or, to use the files as they are, delete {folder / MANIFEST_NAME}.")


def check_folder(folder: Path, *, edited_ok: Collection[str] = ()) -> None:
    """Refuse (ValueError) an output folder whose files do not match its manifest.json: a
    listed file missing, of another size or SHA-256, or a manifest left incomplete. A folder
    without a manifest (written before manifests, or not by this tool) is not checked.

    edited_ok: names that may differ from the manifest (a part the user edited by hand and
    gives explicitly); they must still be present.
    """
    path = folder / MANIFEST_NAME
    if not path.is_file():
        return
    try:
        manifest = json.loads(path.read_text())
        files = manifest["files"]
        command = [str(c) for c in manifest.get("command", [])]
        complete = bool(manifest["complete"])
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise ValueError(f"{path}: not a manifest written by aperture-fab ({err}); re-run the "
                         f"design into {folder}, or delete {path}.") from err
    if not complete:
        raise _refuse(folder, "the run stopped while publishing its files", command)
    for name, entry in files.items():
        file = folder / name
        if not file.is_file():
            raise _refuse(folder, f"{name} is listed but missing", command)
        if name in edited_ok:
            continue
        size = file.stat().st_size
        if size != entry["size_bytes"] or file_sha256(file) != entry["sha256"]:
            raise _refuse(folder, f"{name} differs from the file the run wrote ({size} bytes, "
                          f"{entry['size_bytes']} listed)", command)


def refuse_overwrite(folder: Path, names: Collection[str], flag: str = "--out") -> None:
    """Refuse (ValueError) to write files over those a published set lists in folder's
    manifest.json: the set would no longer match its manifest."""
    path = folder / MANIFEST_NAME
    if not path.is_file():
        return
    try:
        listed = set(json.loads(path.read_text())["files"])
    except (OSError, ValueError, KeyError, TypeError):
        listed = set()
    clash = sorted(set(names) & listed)
    if clash:
        raise ValueError(
            f"{flag} {folder}: {', '.join(clash)} belong to the design set recorded in "
            f"{path}; writing over them would leave a mixed folder. Choose another {flag} (a new "
            "folder), or re-run `aperture-fab design` to change the set.")
