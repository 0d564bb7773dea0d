"""The filesystem, for the pipeline and the CLI only: atomic writes, the output folder and
reading target images.

A crash or Ctrl-C never leaves a truncated file that looks valid: every file is written to a
temporary name in its folder, flushed to disk, then renamed over the old one.
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from aperture_fab.io.formats import PART_SUFFIXES
from aperture_fab.io.images import decode_image

__all__ = ["load_targets", "output_folder", "write_atomic"]


def write_atomic(path: Path, data: bytes | str) -> None:
    """Write via a temporary file in the same folder and rename: never a truncated file."""
    payload = data.encode() if isinstance(data, str) else data
    tmp = path.parent / f".{path.name}.{secrets.token_hex(6)}.tmp"
    # os.open with 0o666 honours the umask, unlike mkstemp's private 0o600.
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(payload)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def output_folder(out: Path) -> Path:
    """The folder for all outputs: `out` itself, or its parent when `out` names a part file."""
    folder = out.parent if out.suffix.lower() in PART_SUFFIXES else out
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(f"cannot create the output folder {folder}: {err.strerror}; choose "
                         "another --out.") from err
    if not os.access(folder, os.W_OK):
        raise ValueError(f"the output folder {folder} is not writable; choose another --out.")
    return folder


def load_targets(paths: Sequence[Path]) -> tuple[list[np.ndarray], list[str]]:
    """Read and decode target images; names are the file stems, made unique."""
    images, names = [], []
    for path in paths:
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            raise ValueError(f"target image {path} does not exist; check the path.") from None
        except IsADirectoryError:
            raise ValueError(f"target image {path} is a folder; give an image file.") from None
        except OSError as err:
            raise ValueError(f"cannot read target image {path}: {err.strerror}.") from err
        images.append(decode_image(data, str(path)))
        name = "".join(c if c.isalnum() or c in "-_" else "_" for c in path.stem) or "target"
        while name in names:
            name += "_"
        names.append(name)
    return images, names
