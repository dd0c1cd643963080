"""Compiling one kernel body both serial and parallel with numba's on-disk cache.

numba names a cached function's files after its qualified name and first line and does not
key its index on the ``parallel`` flag: two ``njit(cache=True)`` wrappers of the same Python
function (one ``parallel=True``) share one cache entry, so whichever was compiled first is
loaded for both and the "parallel" kernel can silently run on one thread. :func:`njit_pair`
compiles two renamed copies of the body instead, each with its own cache files.

:func:`finite_rows` is a one-pass ``np.isfinite(a).all(axis=1)`` for ``(N, 3)`` arrays
(numpy's row-wise reduction over 3 columns is several times slower).
"""

from __future__ import annotations

import math
import types
from collections.abc import Callable

import numba as nb
import numpy as np

__all__ = ["njit_pair", "finite_rows"]


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


@nb.njit(cache=True)
def finite_rows(a):
    """``(N,)`` bool: whether every entry of row ``i`` of the ``(N, C)`` float array is finite."""
    n = a.shape[0]
    out = np.empty(n, dtype=np.bool_)
    for i in range(n):
        ok = True
        for j in range(a.shape[1]):
            if not math.isfinite(a[i, j]):
                ok = False
        out[i] = ok
    return out
