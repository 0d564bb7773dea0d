"""Keep Numba's on-disk cache of compiled kernels from going stale.

Numba caches a compiled function under the content of the file that defines it, and nothing
else: a kernel that inlines functions from another module keeps its old machine code when only
that module changes (numba 0.62: the file's SHA-256; checked with a two-file case, whose edited
dependency was ignored until the entry file's own text changed). So each module that defines
cached kernels records a digest of the modules they inline (`INLINED_DIGEST`) and calls
`check_inlined` on import: when an inlined module changed, the import fails and names the new
digest, and writing it into the module changes that module, which makes Numba compile again.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from types import ModuleType

__all__ = ["check_inlined", "sources_digest"]

#: Hex digits of the SHA-256 kept: enough to tell edits apart, short enough to read.
DIGEST_CHARS = 16


def sources_digest(*modules: ModuleType) -> str | None:
    """SHA-256 (DIGEST_CHARS hex digits) of the modules' source files in order, line endings
    normalized (a checkout with CRLF reads the same); None when a source is not a readable .py
    file (an installation without sources: nothing to check against)."""
    digest = hashlib.sha256()
    for module in modules:
        path = Path(module.__file__ or "")
        if path.suffix != ".py":
            return None
        try:
            digest.update(path.read_bytes().replace(b"\r\n", b"\n"))
        except OSError:
            return None
    return digest.hexdigest()[:DIGEST_CHARS]


def check_inlined(module: str, recorded: str, *inlined: ModuleType) -> None:
    """Raise RuntimeError when the sources of `inlined` (the modules whose functions module's
    cached kernels inline) no longer match `recorded`, naming the digest to record."""
    actual = sources_digest(*inlined)
    if actual is None or actual == recorded:
        return
    names = ", ".join(m.__name__ for m in inlined)
    raise RuntimeError(
        f"{module} compiles kernels that inline {names}, whose source changed (digest {actual}, "
        f"recorded {recorded}); Numba's cache would go on running the old compiled code. Set "
        f'INLINED_DIGEST = "{actual}" in {module}: the edit makes Numba compile it again.')
