"""Compiling one kernel body both serial and parallel with numba's on-disk cache.

numba names a cached function's files after its qualified name and first line and does not
key its index on the ``parallel`` flag: two ``njit(cache=True)`` wrappers of the same Python
function (one ``parallel=True``) share one cache entry, so whichever was compiled first is
loaded for both and the "parallel" kernel can silently run on one thread. :func:`njit_pair`
compiles two renamed copies of the body instead, each with its own cache files.
"""

from __future__ import annotations

import types
from collections.abc import Callable

import numba as nb

__all__ = ["njit_pair"]


def _renamed(fn: Callable, suffix: str) -> Callable:
    g = types.FunctionType(fn.__code__, fn.__globals__, fn.__name__ + suffix, fn.__defaults__,
                           fn.__closure__)
    g.__qualname__ = fn.__qualname__ + suffix
    g.__doc__ = fn.__doc__
    g.__module__ = fn.__module__
    return g


def njit_pair(fn: Callable) -> tuple[Callable, Callable]:
    """Return ``(parallel, serial)`` cached numba compilations of the kernel body ``fn``."""
    par = nb.njit(cache=True, parallel=True)(_renamed(fn, "__par"))
    ser = nb.njit(cache=True)(_renamed(fn, "__ser"))
    return par, ser
