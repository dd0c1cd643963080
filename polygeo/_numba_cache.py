"""Dropping numba's on-disk kernel cache when the kernels' sources change.

numba keys a cached kernel on the modification time of the file that defines it, not on the
functions it inlines or calls from other modules: after a change to ``_jets_numba.fit_item``
(inlined into the fused kernel of ``estimate.py``), the cached fused kernel kept running the old
fit. The same happens after an upgrade that leaves the old cache files beside the new sources
(pip does not record them, so it does not remove them). :func:`drop_stale` keeps a hash of
every source file that defines numba kernels next to the cache and deletes the package's cache
files when the hash changes, so that the kernels are compiled again from the current sources.

Only the default cache location (``__pycache__`` beside the sources) is handled; with
``NUMBA_CACHE_DIR`` set, clearing that folder after an upgrade is left to its owner.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

__all__ = ["drop_stale", "STAMP_NAME"]

#: Name of the stamp file written in the package's top ``__pycache__``.
STAMP_NAME = "numba-sources.sha1"

_MARKERS = (b"njit", b"numba")


def sources_hash(root: Path) -> str:
    """SHA-1 of the kernel sources under ``root``.

    Relative paths and contents of the ``.py`` files that mention numba; each file is read
    once.
    """
    h = hashlib.sha1()
    for p in sorted(root.rglob("*.py")):
        if "__pycache__" in p.parts:
            continue
        try:
            text = p.read_bytes()
        except OSError:
            continue
        if any(m in text for m in _MARKERS):
            h.update(p.relative_to(root).as_posix().encode())
            h.update(b"\0")
            h.update(text)
            h.update(b"\0")
    return h.hexdigest()


def drop_stale(root: str | os.PathLike) -> int:
    """Delete numba's cache files under ``root`` if its kernel sources changed.

    Parameters
    ----------
    root : str or path-like
        The package folder (its ``__pycache__`` holds the stamp).

    Returns
    -------
    int
        Number of cache files deleted (0 when the stamp matches, or when the folder is not
        writable: nothing is done then).
    """
    if os.environ.get("NUMBA_CACHE_DIR"):
        return 0
    root = Path(root)
    stamp = root / "__pycache__" / STAMP_NAME
    try:
        digest = sources_hash(root)
        if stamp.is_file() and stamp.read_text().strip() == digest:
            return 0
        n = 0
        for cache in root.rglob("__pycache__"):
            for f in list(cache.glob("*.nbi")) + list(cache.glob("*.nbc")):
                f.unlink()
                n += 1
        stamp.parent.mkdir(exist_ok=True)
        tmp = stamp.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(digest + "\n")
        os.replace(tmp, stamp)
        return n
    except OSError:  # read-only install, a concurrent process: leave everything as it is
        return 0
