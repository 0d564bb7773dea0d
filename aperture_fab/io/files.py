"""The filesystem, for the pipeline and the CLI only: atomic writes, the output folder and
reading target images.

A crash or Ctrl-C never leaves a truncated file that looks valid: every file is written to a
temporary name in its folder, flushed to disk, then renamed over the old one.
"""

from __future__ import annotations

import contextlib
import os
import stat
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np

from aperture_fab.io.decode import decode_image
from aperture_fab.io.formats import PART_SUFFIXES
from aperture_fab.io.images import TargetOptions, fit_target

__all__ = ["created_folder", "folder_for", "load_targets", "output_folder", "read_text"]


#: How text files (configs, hole tables) are read: UTF-8, as TOML requires, with a byte-order
#: mark (as some Windows editors and spreadsheets save) dropped.
TEXT_ENCODING = "utf-8-sig"


def read_text(path: Path, what: str, fix: str) -> str:
    """The text of `path`; ValueError naming `what` (e.g. "--config"), the file and `fix` when
    it is not UTF-8 text. OSError (a missing file, no permission) is left to the caller."""
    try:
        return path.read_text(encoding=TEXT_ENCODING)
    except UnicodeDecodeError as err:
        raise ValueError(f"{what} {path} is not UTF-8 text (byte {err.object[err.start]:#04x} at "
                         f"offset {err.start} cannot be decoded); {fix}") from err


def _check_text_path(folder: Path) -> None:
    """Refuse a folder whose path is not valid UTF-8 (bytes a file system allows but text does
    not hold): the outputs record their folder as text (manifest.json, the assembly sheet)."""
    absolute = os.path.abspath(folder)
    try:
        absolute.encode("utf-8")
    except UnicodeEncodeError:
        shown = os.fsencode(absolute).decode("utf-8", "backslashreplace")
        raise ValueError(f"the output folder {shown} has a name that is not valid UTF-8 text; "
                         "the outputs record their folder as text. Rename it, or choose "
                         "another --out.") from None


def folder_for(out: Path) -> Path:
    """The folder for all outputs, not created: `out` itself, or its parent when `out` names a
    part file."""
    folder = out.parent if out.suffix.lower() in PART_SUFFIXES else out
    _check_text_path(folder)
    return folder


def output_folder(out: Path) -> Path:
    """`folder_for(out)`, created with its parents, and writable."""
    folder = folder_for(out)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(f"cannot create the output folder {folder}: {err.strerror}; choose "
                         "another --out.") from err
    if not os.access(folder, os.W_OK):
        raise ValueError(f"the output folder {folder} is not writable; choose another --out.")
    return folder


@contextlib.contextmanager
def created_folder(out: Path) -> Iterator[Path]:
    """`output_folder(out)` for a block; when the block fails, the folders it created are
    removed again while they are empty, so that a refused run leaves no empty folder behind (a
    checkpoint saved there keeps its folder)."""
    folder = folder_for(out)
    # Deepest first. os.path.exists: a name the system refuses (too long) is not there, and
    # output_folder says why (Path.exists raises).
    missing = [path for path in (folder, *folder.parents) if not os.path.exists(path)]
    output_folder(out)
    try:
        yield folder
    except BaseException:
        for path in missing:
            try:
                path.rmdir()
            except OSError:  # not empty (or gone): it and the folders above stay
                break
        raise


#: How a target image is opened. O_NONBLOCK: should the path become a FIFO after the check,
#: open returns at once (a blocking open waits for a writer) and fstat refuses it; it changes
#: nothing for a regular file. O_BINARY: Windows only.
TARGET_OPEN_FLAGS = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0)

#: What a file that is not a regular file is, in words, by its stat type test.
FILE_KINDS: tuple[tuple[Callable[[int], bool], str], ...] = (
    (stat.S_ISFIFO, "a named pipe (FIFO)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def _not_regular(path: Path, mode: int) -> ValueError:
    kind = next((words for test, words in FILE_KINDS if test(mode)), "not a regular file")
    return ValueError(f"target image {path} is {kind}, not a regular file; give a regular image "
                      "file (PNG, JPEG, ...), e.g. save what the pipe or device gives to a file "
                      "first.")


def _read_regular(path: Path) -> bytes:
    """The bytes of the target image at `path`, a regular file; any other kind of file is
    refused before it is read (reading a FIFO blocks until a writer comes, a device may never
    end)."""
    try:
        mode = os.stat(path).st_mode
        if stat.S_ISDIR(mode):
            raise ValueError(f"target image {path} is a folder; give an image file.")
        if not stat.S_ISREG(mode):
            raise _not_regular(path, mode)
        fd = os.open(path, TARGET_OPEN_FLAGS)
    except FileNotFoundError:
        raise ValueError(f"target image {path} does not exist; check the path.") from None
    except OSError as err:
        raise ValueError(f"cannot read target image {path}: {err.strerror}; check that the "
                         "path leads to an image file you may read.") from err
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise _not_regular(path, mode)
        with os.fdopen(fd, "rb", closefd=False) as f:
            return f.read()
    except OSError as err:
        raise ValueError(f"cannot read target image {path}: {err.strerror}; check that the "
                         "path leads to an image file you may read.") from err
    finally:
        os.close(fd)


def load_targets(paths: Sequence[Path], display_pixels: tuple[int, int] | None = None,
                 options: TargetOptions | None = None) -> tuple[list[np.ndarray], list[str]]:
    """Read and decode target images, each (3, H, W) float64 linear light; names are the file
    stems, made unique. options: the --alpha, --frame and --fit of TargetOptions (default its
    defaults); a fit other than stretch needs display_pixels (W, H)."""
    options = options if options is not None else TargetOptions()
    if options.fit != "stretch" and display_pixels is None:
        raise ValueError(f"--fit {options.fit} needs the display's pixel count; give "
                         "display_pixels.")
    images, names = [], []
    for path in paths:
        image = decode_image(_read_regular(path), str(path), alpha=options.alpha,
                             frame=options.frame)
        if display_pixels is not None:
            image = fit_target(image, display_pixels, options.fit)
        images.append(image)
        name = "".join(c if c.isalnum() or c in "-_" else "_" for c in path.stem) or "target"
        while name in names:
            name += "_"
        names.append(name)
    return images, names
