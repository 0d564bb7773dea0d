"""The judged cache on disk: the regular family's judgements kept between runs
(`aperture_fab.validation.judged_cache`), one small .npz per array, written atomically.

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
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from aperture_fab.io.atomic import write_atomic
from aperture_fab.validation.made_quality import MadeQuality

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

    def get(self, key: str) -> list[MadeQuality] | None:
        path = self._path(key)
        try:
            with np.load(path, allow_pickle=False) as data:
                return [MadeQuality(np.array(data[f"psnr_db_{i}"]), float(efficiency),
                                    float(level))
                        for i, (efficiency, level) in enumerate(zip(
                            data["efficiency"], data["eye_level"], strict=True))]
        except FileNotFoundError:
            return None
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as error:
            log.info("judged cache: %s is unreadable (%s); judging again", path, error)
            return None

    def put(self, key: str, judged: Sequence[MadeQuality]) -> None:
        if not self._writable:
            return
        buffer = io.BytesIO()
        arrays = {f"psnr_db_{i}": q.psnr_db for i, q in enumerate(judged)}
        arrays["efficiency"] = np.array([q.efficiency for q in judged])
        arrays["eye_level"] = np.array([q.eye_level for q in judged])
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
