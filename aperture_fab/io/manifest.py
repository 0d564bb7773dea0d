"""An output folder as one consistent set: a run writes into a staging folder, publishes every
file at once, and records them in `manifest.json`, which readers check.

Why: files written one by one into the output folder leave a mix of two runs behind when a run
is refused, skips a step or is killed (a new plate.stl beside the old plate.dxf). So a run
writes everything into `<folder>/.staging-<pid>-<random>/` (same filesystem: renames are
atomic), then `publish` renames each file into place, removes the files of the earlier set that
this run did not write, and writes `manifest.json` LAST: each file's SHA-256 and size, the
command, the tool version and the time (and for a TOML file the SHA-256 of its parsed content).
A reader (`check_folder`) refuses a folder whose files do not match its manifest: a partial or
stale set; a TOML file whose content is unchanged matches (a comment added to design.toml is
harmless, a changed value is not). Until the new manifest is written, the folder
holds a manifest marked incomplete, so a run killed while publishing is refused too, never read
as a set.

The tool deletes only what its own manifest lists: a file is the earlier run's because the
folder's manifest.json names it and it still has the listed SHA-256, never because its name
looks like ours (a user's view_holiday.png, or a target image kept in the folder, stays). The
incomplete manifest names the earlier set too, so what a killed publish left is removed by the
next one. Publishing holds an advisory lock (`.publish.lock`, fcntl.flock), so two runs into
one folder publish one after the other and the folder ends up as the later one's set.
"""

from __future__ import annotations

import contextlib
import datetime
import fcntl
import hashlib
import json
import os
import re
import secrets
import shutil
import time
import tomllib
from collections.abc import Collection, Iterator, Sequence
from pathlib import Path
from typing import Any

from aperture_fab.io.atomic import pid_alive, remove_orphan_temporaries, write_atomic

__all__ = [
    "MANIFEST_NAME",
    "check_folder",
    "file_sha256",
    "listed_files",
    "publish",
    "refuse_overwrite",
    "remove_listed",
    "staging",
]

MANIFEST_NAME = "manifest.json"
MANIFEST_SCHEMA_VERSION = 1
STAGING_PREFIX = ".staging-"
#: A staging folder's whole name (pid, 8 hex digits): only such folders are removed as orphans.
STAGING_PATTERN = re.compile(re.escape(STAGING_PREFIX) + r"(\d+)-[0-9a-f]{8}")
#: The advisory lock a publish holds (its holder removes it; see `_publish_lock`).
LOCK_NAME = ".publish.lock"
#: How long a publish waits for another run's publish into the same folder (renames and
#: hashing: seconds, even for a large STL).
LOCK_WAIT_S = 120.0
LOCK_POLL_S = 0.05
#: Read files in blocks this large when hashing (a large STL need not fit in memory twice).
HASH_BLOCK_BYTES = 1 << 20


def file_sha256(path: Path) -> str:
    """The SHA-256 of a file's bytes, as hex."""
    digest = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(HASH_BLOCK_BYTES), b""):
            digest.update(block)
    return digest.hexdigest()


def _remove_orphans(folder: Path) -> None:
    """Staging folders and temporary files (a checkpoint's, written straight into the folder)
    of runs that died (SIGKILL, power loss): their pid no longer runs."""
    for path in folder.glob(f"{STAGING_PREFIX}*"):
        match = STAGING_PATTERN.fullmatch(path.name)
        if match and path.is_dir() and not path.is_symlink() \
                and not pid_alive(int(match.group(1))):
            shutil.rmtree(path, ignore_errors=True)
    remove_orphan_temporaries(folder)


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


def _manifest_text(files: dict[str, dict[str, Any]], command: Sequence[str], complete: bool,
                   previous: dict[str, dict[str, Any]] | None = None) -> str:
    from aperture_fab import __version__

    manifest: dict[str, Any] = {
        "schema_version": MANIFEST_SCHEMA_VERSION,
        "complete": complete,
        "tool": "aperture-fab",
        "tool_version": __version__,
        "command": list(command),
        "created_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "files": files,
    }
    if not complete:  # the earlier set, so that the next publish removes what this one left
        manifest["previous"] = previous or {}
    return json.dumps(manifest, indent=2) + "\n"


def _sync_folder(folder: Path) -> None:
    """Flush the folder's entries (the renames) to disk, where the OS allows it."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def listed_files(folder: Path) -> dict[str, dict[str, Any]]:
    """The files folder's manifest.json says this tool wrote there, {name: {"sha256",
    "size_bytes"}} (of a publish cut short: its new set and the earlier one); empty without a
    readable manifest. Only plain names count: a manifest edited to name ../x or a/b lists
    nothing."""
    try:
        manifest = json.loads((folder / MANIFEST_NAME).read_text())
        entries = {**manifest.get("previous", {}), **manifest["files"]}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}
    return {name: entry for name, entry in entries.items()
            if isinstance(name, str) and name == Path(name).name and isinstance(entry, dict)
            and name not in ("", ".", "..", MANIFEST_NAME)}


def _remove(folder: Path, entries: dict[str, dict[str, Any]]) -> None:
    """Remove the listed files that are still what the tool wrote (size and SHA-256): a file
    the user has since edited or put in its place is theirs now, and stays."""
    for name, entry in sorted(entries.items()):
        path = folder / name
        if path.is_file() and not path.is_symlink() \
                and path.stat().st_size == entry.get("size_bytes") \
                and file_sha256(path) == entry.get("sha256"):
            path.unlink()


def remove_listed(folder: Path) -> None:
    """Remove the files folder's manifest.json lists (those still as written), then the
    manifest: the earlier set goes and nothing else in the folder, whatever its name."""
    _remove(folder, listed_files(folder))
    (folder / MANIFEST_NAME).unlink(missing_ok=True)


@contextlib.contextmanager
def _publish_lock(folder: Path, wait_s: float) -> Iterator[None]:
    """Hold folder's publish lock (an advisory fcntl.flock on LOCK_NAME), waiting up to wait_s
    for another run's publish, else ValueError naming the folder. The holder removes the lock
    file when done (no litter), so a waiter checks that the file it locked is still in place."""
    path = folder / LOCK_NAME
    deadline = time.monotonic() + wait_s
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            if time.monotonic() >= deadline:
                raise ValueError(
                    f"output folder {folder}: another aperture-fab run is publishing into it "
                    f"({path} has been locked for over {wait_s:g} s); wait until it finishes "
                    "and run again, or give another --out.") from None
            time.sleep(LOCK_POLL_S)
            continue
        with contextlib.suppress(FileNotFoundError):
            if os.fstat(fd).st_ino == os.stat(path).st_ino:
                break
        os.close(fd)  # the previous holder removed the file we locked: lock the current one
    try:
        yield
    finally:
        path.unlink(missing_ok=True)
        os.close(fd)


def publish(stage: Path, folder: Path, command: Sequence[str], *,
            wait_s: float = LOCK_WAIT_S, add: bool = False) -> dict[str, dict[str, Any]]:
    """Move every file of `stage` into `folder`, remove the files folder's earlier manifest
    lists that this run did not write (any other file is the user's and stays), and write
    manifest.json last; all under folder's publish lock (waiting up to wait_s for another
    run's). Returns the manifest's files block {name: {"sha256", "size_bytes"}}.

    add: the staged files join the published set instead of replacing it (`aperture-fab
    assembly` adding its sheet to a design's set): they replace their namesakes, the set's
    other files stay listed as they are, and the manifest keeps the command that wrote the
    set. Check the folder first (check_folder): the kept entries are taken as listed."""
    names = sorted(p.name for p in stage.iterdir() if p.is_file())
    files = {name: _entry(stage / name) for name in names}
    with _publish_lock(folder, wait_s):
        earlier = listed_files(folder)
        if add:
            files = {**{n: e for n, e in earlier.items() if n not in files}, **files}
            command = _listed_command(folder) or command
        # From here until the last line the folder is a mix: say so first, so a reader refuses
        # it, and name the earlier set, so that a publish killed midway is cleaned up next time.
        write_atomic(folder / MANIFEST_NAME,
                     _manifest_text(files, command, complete=False, previous=earlier))
        for name in names:
            os.replace(stage / name, folder / name)
        _remove(folder, {n: e for n, e in earlier.items() if n not in files})
        _sync_folder(folder)
        write_atomic(folder / MANIFEST_NAME, _manifest_text(files, command, complete=True))
    return files


def _listed_command(folder: Path) -> list[str]:
    """The command folder's manifest.json records (empty without a readable one)."""
    try:
        command = json.loads((folder / MANIFEST_NAME).read_text())["command"]
    except (OSError, ValueError, KeyError, TypeError):
        return []
    return [str(c) for c in command] if isinstance(command, list) else []


def _toml_content_sha256(path: Path) -> str | None:
    """SHA-256 of a TOML file's content (its parsed tables, as sorted JSON), blind to comments
    and layout; None when it does not parse."""
    try:
        content = tomllib.loads(path.read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return None
    canonical = json.dumps(content, sort_keys=True, default=str).encode()
    return hashlib.sha256(canonical).hexdigest()


def _entry(path: Path) -> dict[str, Any]:
    """A file's manifest entry: SHA-256 and size, and for a TOML file the SHA-256 of its
    content (so a comment the user adds to design.toml does not make the set stale)."""
    entry: dict[str, Any] = {"sha256": file_sha256(path), "size_bytes": path.stat().st_size}
    if path.suffix == ".toml":
        content = _toml_content_sha256(path)
        if content is not None:
            entry["content_sha256"] = content
    return entry


def _matches(path: Path, entry: dict[str, Any]) -> bool:
    """Whether a file is what its manifest entry says: the same bytes, or for a TOML file the
    same content (comments and layout aside)."""
    if path.stat().st_size == entry.get("size_bytes") and file_sha256(path) == entry.get("sha256"):
        return True
    content = entry.get("content_sha256")
    return content is not None and _toml_content_sha256(path) == content


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
        if not _matches(file, entry):
            size = file.stat().st_size
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
