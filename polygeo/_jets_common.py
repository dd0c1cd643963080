"""Constants and tables shared by :mod:`polygeo.jets` and its compiled kernels.

Package-private ground floor of the jet fit: it imports neither :mod:`polygeo.jets` nor
:mod:`polygeo._jets_numba`, so the kernels (and :mod:`polygeo.diffgeo`,
:mod:`polygeo.estimate`) read the same constants without importing the public module they
serve (no import cycle).

The numba kernels freeze ``COLLINEAR_TOL`` into their compiled code: this file mentions
numba so that :mod:`polygeo._numba_cache` counts it among the kernel sources whose change
invalidates the on-disk kernel cache.
"""

from __future__ import annotations

from functools import cache

import numpy as np

__all__ = ["COLLINEAR_TOL", "exponents_np"]

#: Parameter samples whose covariance has ``det <= COLLINEAR_TOL * trace^2`` lie on a line
#: (their spread across it is below 1e-5 of their spread along it): no plane, hence no jet of
#: order >= 1, is defined, whatever the equilibration of the normal equations makes of the
#: rounding noise across the line. Such items fall back to order 0 with status DEGENERATE.
COLLINEAR_TOL = 1e-10


@cache
def exponents_np(order: int) -> np.ndarray:
    """Exponents ``(p, q)`` of the monomials ``u^p v^q`` up to total degree ``order``.

    Parameters
    ----------
    order : int
        Total degree ``n >= 0`` (not validated: callers pass checked orders).

    Returns
    -------
    numpy.ndarray
        ``(M, 2)`` int64, ``M = (n+1)(n+2)/2``, in the storage order of DESIGN.md §4
        (``(n, 0), (n-1, 1), ..., (0, n)`` within each degree). Cached and shared between
        callers: do not modify it (the public :func:`polygeo.jets.exponents` returns a copy).
    """
    e = np.array([(i - j, j) for i in range(order + 1) for j in range(i + 1)], dtype=np.int64)
    e = e.reshape(-1, 2)
    return e
