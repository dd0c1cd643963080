"""numba's on-disk kernel cache keyed on every kernel source of the package.

numba keys a cached kernel on the source of the file that defines it, not on the functions it
inlines or calls from other modules: after a change to ``_jets_numba.fit_item`` (inlined into
the fused kernel of ``estimate.py``), the cached fused kernel kept running the old fit. The
same happens after an upgrade that leaves old cache files beside changed sources (pip does not
record them, so it does not remove them).

:func:`install` registers numba cache *locators* (numba's own extension point, consulted when a
``cache=True`` kernel is decorated) for the files under a package folder. They put the cache
where numba would (``NUMBA_CACHE_DIR`` if set, else ``__pycache__`` beside the source if it is
writable, else the user's cache folder, e.g. ``~/.cache/numba``) and differ from numba's in one
thing: the stamp of a kernel is a hash of every source file of the package that defines numba
kernels (:func:`sources_hash`), so that any change to any kernel source makes every cached
kernel of the package stale. numba then recompiles it and overwrites the stale entry; nothing
is deleted, and nothing happens at ``import polygeo`` (the locators are installed when the
first kernel module is imported, and files are written only when a kernel is compiled).

Kernels of files outside the registered folders keep numba's own locators. A user who sets
``NUMBA_CACHE_LOCATOR_CLASSES`` chooses the locators themselves (then this has no effect).
"""

from __future__ import annotations

import functools
import hashlib
import os
from pathlib import Path

from numba.core import caching

__all__ = ["install", "sources_hash", "locator_classes"]

_MARKERS = (b"njit", b"numba")
_ROOTS: list[Path] = []
_CACHE_IMPL = getattr(caching, "CacheImpl", None) or caching._CacheImpl  # numba < 0.61


def _numba_locator(*names: str) -> type | None:
    for n in names:
        cls = getattr(caching, n, None)
        if cls is not None:
            return cls
    return None


@functools.cache
def sources_hash(root: Path) -> str:
    """SHA-1 of the kernel sources under ``root`` (computed once per process and folder).

    Relative paths and contents of the ``.py`` files that mention numba, in sorted order.
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


def _root_of(py_file: str) -> Path | None:
    try:
        p = Path(py_file).resolve()
    except OSError:
        return None
    for root in _ROOTS:
        if p.is_relative_to(root):
            return root
    return None


class _PackageStamp:
    """Mixin: only for files under a registered folder; stamped by all its kernel sources."""

    def get_source_stamp(self):
        root = _root_of(self._py_file)
        return ("polygeo-kernel-sources", str(root), sources_hash(root))

    @classmethod
    def from_function(cls, py_func, py_file):
        if _root_of(py_file) is None:
            return None
        return super().from_function(py_func, py_file)


def _stamped(base: type | None) -> type | None:
    if base is None:
        return None
    return type(f"PackageStamped{base.__name__.lstrip('_')}", (_PackageStamp, base), {})


@functools.lru_cache(maxsize=1)
def locator_classes() -> tuple[type, ...]:
    """The stamped variants of numba's file-backed locators, in numba's order."""
    bases = (
        _numba_locator("UserProvidedCacheLocator", "_UserProvidedCacheLocator"),
        _numba_locator("InTreeCacheLocator", "_InTreeCacheLocator"),
        _numba_locator("UserWideCacheLocator", "_UserWideCacheLocator"),
    )
    return tuple(c for c in map(_stamped, bases) if c is not None)


def install(root: str | os.PathLike) -> None:
    """Key numba's cache of the kernels under ``root`` on all their sources (idempotent).

    Must run before the kernels are decorated (numba picks a kernel's locator then).

    Parameters
    ----------
    root : str or path-like
        The package folder.
    """
    r = Path(root).resolve()
    if r not in _ROOTS:
        _ROOTS.append(r)
    ours = locator_classes()
    current = list(_CACHE_IMPL._locator_classes)
    if current[: len(ours)] != list(ours):
        _CACHE_IMPL._locator_classes = [*ours, *(c for c in current if c not in ours)]
