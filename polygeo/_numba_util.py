"""Set-up shared by every module of compiled (numba) kernels, and two kernel helpers.

Importing this module (every kernel module does, before decorating its kernels) does two
things for the process, neither at ``import polygeo`` and neither through ``os.environ``:

* numba's disk cache of the package's kernels is keyed on all their sources
  (:mod:`polygeo._numba_cache`), so that a kernel inlining a changed function from another
  module is recompiled instead of loaded stale;
* numba's threading layer is set to ``"workqueue"`` in ``numba.config`` (not in the
  environment) unless the user chose one (``NUMBA_THREADING_LAYER``, a ``.numba_config.yaml``,
  or ``numba.config.THREADING_LAYER`` set before) or numba's threads are already running.
  With the OpenMP layer, idle worker threads spin-wait: on a machine whose cores are busy with
  other work, a 128 x 128 soft render measured 115 ms (median) instead of 9-11 ms. The
  workqueue layer must not be entered from several Python threads at once; use processes for
  that kind of parallelism (or choose another layer before importing the kernels).

Compiling one kernel body both serial and parallel with numba's on-disk cache:

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
import os
import types
from collections.abc import Callable
from pathlib import Path

import numba as nb
import numpy as np

from . import _numba_cache

__all__ = ["njit_pair", "finite_rows", "prefer_workqueue"]


def prefer_workqueue() -> bool:
    """Select numba's workqueue threading layer unless the user chose a layer.

    Returns
    -------
    bool
        Whether the layer was set (False: the user's choice, or numba's threads already run).
    """
    from numba.np.ufunc import parallel

    if "NUMBA_THREADING_LAYER" in os.environ or parallel._is_initialized:
        return False
    if str(nb.config.THREADING_LAYER).lower() != "default":
        return False
    nb.config.THREADING_LAYER = "workqueue"
    return True


# before any kernel of the package is decorated (numba picks its cache locator then)
_numba_cache.install(Path(__file__).resolve().parent)
prefer_workqueue()


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
