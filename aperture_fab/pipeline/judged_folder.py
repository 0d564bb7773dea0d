"""The judged cache on disk: judgements kept between runs (`aperture_fab.validation.judged_cache`),
one small .npz per key, written atomically.

The folder is `APERTURE_FAB_CACHE_DIR` when set (`off` keeps nothing), else
`$XDG_CACHE_HOME/aperture-fab/judged` (`~/.cache/aperture-fab/judged`). A key holds every input
and the library's source, so nothing there goes stale; deleting the folder only costs the next
run its time. A file that cannot be read is judged again and replaced; a folder that cannot be
written is no cache (the run judges everything, as without one).
"""

from __future__ import annotations

import io
import logging
import os
import zipfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from aperture_fab.io.atomic import write_atomic

__all__ = ["ENV_CACHE_DIR", "OFF", "FolderCache", "default_cache"]

#: Environment variable naming the cache folder, or OFF.
ENV_CACHE_DIR = "APERTURE_FAB_CACHE_DIR"
OFF = "off"

log = logging.getLogger(__name__)


class FolderCache:
    """A JudgedCache in `folder` (made on the first write): `<key[:2]>/<key>.npz` per key."""

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)
        self._writable = True

    def _path(self, key: str) -> Path:
        return self.folder / key[:2] / f"{key}.npz"

    def get(self, key: str) -> dict[str, np.ndarray] | None:
        path = self._path(key)
        try:
            with np.load(path, allow_pickle=False) as data:
                return {name: np.array(data[name]) for name in data.files}
        except FileNotFoundError:
            return None
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as error:
            log.info("judged cache: %s is unreadable (%s); judging again", path, error)
            return None

    def put(self, key: str, arrays: Mapping[str, np.ndarray]) -> None:
        if not self._writable:
            return
        buffer = io.BytesIO()
        np.savez(buffer, allow_pickle=False, **arrays)
        path = self._path(key)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            write_atomic(path, buffer.getvalue())
        except OSError as error:
            self._writable = False  # say it once; the run goes on without keeping
            log.warning("judged cache: cannot write %s (%s); set %s to a writable folder, or "
                        "to %r to keep nothing", self.folder, error, ENV_CACHE_DIR, OFF)


def default_cache() -> FolderCache | None:
    """The cache folder the environment names (module docstring), or None when it is OFF."""
    setting = os.environ.get(ENV_CACHE_DIR, "").strip()
    if setting.lower() == OFF:
        return None
    if setting:
        return FolderCache(Path(setting).expanduser())
    home = os.environ.get("XDG_CACHE_HOME", "").strip() or Path.home() / ".cache"
    return FolderCache(Path(home) / "aperture-fab" / "judged")
