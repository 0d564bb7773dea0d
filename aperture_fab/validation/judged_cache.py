"""Judgements worth keeping between runs: the regular family's (`aperture_fab.validation.regular`)
and the baselines' a validation renders beside the part (`aperture_fab.validation.validate`).

The regular family a part is judged against depends on the process, the part's outline, the
targets, the eye states and the fit, not on the part: a design, its `validate`, a second design
of the same target with other optimizer settings and a sweep's points all judge the same family
(154 arrays and their display-fitted rivals on the default preset: most of the made-part
judgement's half minute). A `JudgedCache` keeps each array's judgement under a `digest` of every
value it came from, the library's own source included, so that any change to an input or to the
code misses instead of reading a stale figure. The pipeline passes one that lives in a folder
(`aperture_fab.pipeline.judged_folder`); the library's functions take None (no cache) by default.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import hashlib
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

__all__ = ["JudgedCache", "MemoryCache", "cached", "code_digest", "digest"]


class JudgedCache(Protocol):
    """Judgements by key (a `digest`), each a few named arrays (`made_quality.as_arrays` turns
    MadeQuality lists into them)."""

    def get(self, key: str) -> dict[str, np.ndarray] | None:
        """The arrays kept under `key`, or None."""
        ...

    def put(self, key: str, arrays: Mapping[str, np.ndarray]) -> None:
        """Keep `arrays` under `key`."""
        ...


class MemoryCache:
    """A JudgedCache in memory (for one process; tests)."""

    def __init__(self) -> None:
        self.kept: dict[str, dict[str, np.ndarray]] = {}

    def get(self, key: str) -> dict[str, np.ndarray] | None:
        kept = self.kept.get(key)
        return None if kept is None else {name: a.copy() for name, a in kept.items()}

    def put(self, key: str, arrays: Mapping[str, np.ndarray]) -> None:
        self.kept[key] = {name: np.array(a) for name, a in arrays.items()}


def cached(cache: JudgedCache | None, compute: Callable[[], dict[str, np.ndarray]],
           *values: Any) -> dict[str, np.ndarray]:
    """compute()'s arrays, kept in `cache` under a `digest` of `values` (every input they
    depend on; the first, a name for what is kept, keeps records of different kinds apart):
    read back when kept, computed and kept when not. cache None: computed."""
    if cache is None:
        return compute()
    key = digest(*values)
    kept = cache.get(key)
    if kept is not None:
        return kept
    arrays = compute()
    cache.put(key, arrays)
    return arrays


def _feed(h: Any, value: Any) -> None:
    """Feed a value's content, typed, into hash `h`: dataclasses field by field, arrays and
    tensors by dtype, shape and bytes, containers item by item."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        h.update(f"<{type(value).__qualname__}".encode())
        for field in dataclasses.fields(value):
            h.update(f"{field.name}=".encode())
            _feed(h, getattr(value, field.name))
        h.update(b">")
    elif isinstance(value, torch.Tensor):
        _feed(h, value.detach().cpu().numpy())
    elif isinstance(value, np.ndarray):
        h.update(f"<ndarray {value.dtype.str} {value.shape}>".encode())
        h.update(np.ascontiguousarray(value).tobytes())
    elif isinstance(value, (list, tuple)):
        h.update(f"<{type(value).__name__} {len(value)}>".encode())
        for item in value:
            _feed(h, item)
    elif isinstance(value, Mapping):
        h.update(f"<mapping {len(value)}>".encode())
        for key in sorted(value, key=repr):
            _feed(h, key)
            _feed(h, value[key])
    elif isinstance(value, (str, bytes, int, float, complex, bool, type(None), enum.Enum,
                            np.generic, torch.dtype, torch.device)):
        h.update(f"<{type(value).__name__} {value!r}>".encode())
    else:
        raise TypeError(f"digest: cannot digest a {type(value).__qualname__}; pass plain "
                        "values, arrays, tensors or dataclasses of them.")


def digest(*values: Any) -> str:
    """A hex key for values (plain values, arrays, tensors, dataclasses of them), the library's
    source (`code_digest`) included."""
    h = hashlib.sha256(code_digest().encode())
    for value in values:
        _feed(h, value)
    return h.hexdigest()


@functools.cache
def code_digest() -> str:
    """The SHA-256 of the package's Python source: a key made with it misses after any change
    to the code that judged."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(path.relative_to(root).as_posix().encode() + b"\0")
        h.update(path.read_bytes())
    return h.hexdigest()
