"""Fused compiled kernels of :func:`polygeo.estimate.differential_quantities`.

The per-point pieces live with their concepts: PCA height frames in
:mod:`polygeo._frames_numba`, the jet fit in :mod:`polygeo._jets_numba`, the geometry at the
jet's origin in :mod:`polygeo._diffgeo_numba`. The kernels here run them fused, item by item,
in one parallel loop whose work arrays stay in cache:

* :func:`frames_fit_quantities` — the stages frames -> fit -> quantities of the common case
  (one neighbourhood size per point, one order), results straight into the output arrays;
* :func:`auto_statistics` — ``order="auto"`` / ``k="auto"``: per point, jets of every
  candidate order on every candidate nested neighbourhood (slopes, H, their variances),
  the statistics :mod:`polygeo._estimate_auto` chooses from.

Their arguments come grouped in three small records (named tuples of arrays and scalars):
:class:`Hoods` (the neighbourhoods of a chunk of query points), :class:`JetSettings` (what
the fit needs) and :class:`Quantities` (the output arrays, one row per point of the cloud).
numba's parallel loops cannot take a tuple (its gufunc wrapper has no tuple arguments, numba
issue 2651; writes through a tuple of arrays are silently lost), so the records are unpacked
by field name at the call and each kernel has one parameter per field, of the same name.
"""

from __future__ import annotations

import math
from collections import namedtuple

import numba as nb
import numpy as np

from ._diffgeo_numba import origin_geometry
from ._frames_numba import height_frame
from ._jets_numba import accumulate_sample, factor_normal, fit_item, fit_scratch, solve_factored
from ._numba_util import njit_pair

__all__ = [
    "Hoods",
    "JetSettings",
    "Quantities",
    "PARALLEL_MIN",
    "frames_fit_quantities",
    "auto_statistics",
]

#: Neighbourhoods of a chunk of ``Q`` query points. ``points (N, 3)`` float64; ``source (Q,)``
#: row of ``points`` each query is centred on (its representative among exact duplicates);
#: ``row (Q,)`` output row of each query; ``nbr, dist (Q, K)`` neighbour indices (nearest
#: first, -1 padding) and distances (length unit); ``kuse (Q,)`` rows of ``nbr`` used per
#: query.
Hoods = namedtuple("Hoods", "points source row nbr dist kuse")

#: Settings of the jet fit: ``order`` (1..4), ``gaussian`` (Gaussian distance weights),
#: ``max_cond`` (largest accepted condition number), ``interpolate`` (jet through the query
#: point), ``ep, eq (M,)`` int64 exponents of ``u`` and ``v`` per coefficient.
JetSettings = namedtuple("JetSettings", "order gaussian max_cond interpolate ep eq")

#: Output arrays, one row per point of the cloud: ``normals, d1, d2 (N, 3)``, ``curvatures
#: (N, 4)`` (k1, k2, H, K), ``status, fitted_order, n_neighbors (N,)`` int64, ``residual
#: (N,)``, ``frame (N, 3, 3)``, ``coeffs (N, M)``.
Quantities = namedtuple(
    "Quantities",
    "normals d1 d2 curvatures status fitted_order n_neighbors residual frame coeffs",
)

#: Items per work unit of the parallel loops.
_CHUNK = 256
#: Queries from which the fused kernel runs on numba's threads (the auto-k kernel, 8x more
#: work per point, from ``PARALLEL_MIN // 8``).
PARALLEL_MIN = 4096


# ----------------------------------------------------------------------------- frames -> fit


@nb.njit(cache=True, inline="always")
def _gaussian_weights(uv, z, valid, radius, w):
    """``w[0, j] = exp(-d_j^2 / radius^2)`` for the valid rows of item 0 (else 0)."""
    h2 = max(radius * radius, 1e-300)
    for j in range(uv.shape[1]):
        d2_ = uv[0, j, 0] ** 2 + uv[0, j, 1] ** 2 + z[0, j] ** 2
        w[0, j] = math.exp(-d2_ / h2) if valid[0, j] else 0.0


def _frames_fit_quantities_py(points, source, row, nbr, dist, kuse, order, gaussian, max_cond,
                              interpolate, ep, eq, normals, d1, d2, curvatures, status,
                              fitted_order, n_neighbors, residual, frame, coeffs):
    """Frames -> fit -> quantities of each query ``i``, results into row ``row[i]``.

    The parameters are the fields of :class:`Hoods`, :class:`JetSettings` and
    :class:`Quantities` (see :func:`frames_fit_quantities`).
    """
    Q, K = nbr.shape
    M = coeffs.shape[1]
    nchunks = (Q + _CHUNK - 1) // _CHUNK
    for c in nb.prange(nchunks):
        # one item's work arrays, reused (row 0) so that they stay in L1
        uv = np.empty((1, K, 2))
        z = np.empty((1, K))
        valid = np.empty((1, K), dtype=np.bool_)
        w = np.ones((1, K))
        Rl = np.empty((1, 3, 3))
        lam = np.empty((1, 3))
        cf = np.empty((1, M))
        a = np.empty((3, 3))
        v = np.empty((3, 3))
        scratch = fit_scratch(order, K)
        for i in range(c * _CHUNK, min(Q, (c + 1) * _CHUNK)):
            o = row[i]
            # frame: PCA of the neighbourhood, height coordinates (u, v, z)
            _, rad = height_frame(points, source[i], nbr[i], dist[i], kuse[i], uv, z, valid, 0,
                                  Rl, 0, lam, a, v)
            if gaussian:
                _gaussian_weights(uv, z, valid, rad, w)
            # fit: the jet of the requested order (lower orders as fallback)
            fo, st, _, rs, _, cnt = fit_item(uv, z, w, gaussian, valid, True, 0, 0.0, order,
                                             True, max_cond, 100.0, interpolate, ep, eq, scratch,
                                             cf, 0)
            # quantities at the jet's origin, in world axes
            origin_geometry(cf, 0, Rl, 0, normals, d1, d2, curvatures, o)
            for j in range(M):
                coeffs[o, j] = cf[0, j]
            for r in range(3):
                for cc in range(3):
                    frame[o, r, cc] = Rl[0, r, cc]
            status[o] = st
            fitted_order[o] = fo
            n_neighbors[o] = cnt
            residual[o] = rs


frames_fit_quantities_par, frames_fit_quantities_ser = njit_pair(_frames_fit_quantities_py)


def frames_fit_quantities(hood: Hoods, jet: JetSettings, out: Quantities,
                          parallel_min: int = PARALLEL_MIN) -> None:
    """Run the fused frames -> fit -> quantities kernel (parallel from ``parallel_min``).

    The records' fields reach the kernel by name: numba's parallel loops cannot take tuples
    (writes through a tuple of arrays are lost, numba issue 2651), so the kernel has one
    parameter per field.
    """
    par = hood.nbr.shape[0] >= parallel_min
    kernel = frames_fit_quantities_par if par else frames_fit_quantities_ser
    kernel(**hood._asdict(), **jet._asdict(), **out._asdict())


# ----------------------------------------------------------------------------- auto order + k


@nb.njit(cache=True, inline="always")
def _g_column(L, Ld, D, m, a, g, y, col):
    """Column ``a`` of ``G = S^-1`` (S the moment matrix) from ``N = D S D = L L^T``."""
    for j in range(m):
        g[j] = 0.0
    g[a] = D[a]
    solve_factored(L, Ld, m, g, y)
    for j in range(m):
        col[j] = D[j] * y[j]


@nb.njit(cache=True, inline="always")
def _nested_fits(uv, z, valid, sizes, n_orders, orders, max_conds, interpolate, ep, eq, ws, i,
                 val, gvar, rss, dof, ok):
    """Fits of every order over the nested neighbourhoods (first ``sizes[s]`` rows) of item 0.

    One pass of moments (up to degree ``2 max(orders)``) along the sorted rows serves every
    order: per size and order one small solve. Writes, for query ``i``, order ``j`` and size
    ``s``: ``val[i, j, s] = (a10, a01, H, |II|^2)`` (``H`` to first order ``(a20 + a02) / w``,
    ``|II|^2 = k1^2 + k2^2`` to first order ``4 a20^2 + 2 a11^2 + 4 a02^2``; both 0 below
    order 2),
    ``gvar[i, j, s]`` their variances over ``sigma^2``, ``rss`` and ``dof`` of the fit, and
    ``ok`` (enough points and a condition number within ``max_conds[j]``).
    """
    mom, rhs, pu, pv, N, L, Linv, D, Ld, x, g, y, col = ws
    K = uv.shape[1]
    S = sizes.shape[0]
    omax = orders[n_orders - 1]
    n2 = 2 * omax
    MM = ep.shape[0]
    hmax = 0.0
    for j in range(K):
        if valid[0, j]:
            hmax = max(hmax, uv[0, j, 0] ** 2 + uv[0, j, 1] ** 2)
    h = math.sqrt(hmax) if hmax > 0.0 else 1.0
    ih = 1.0 / h
    for p in range(n2 + 1):
        for q in range(n2 + 1):
            mom[p, q] = 0.0
    for j in range(MM):
        rhs[j] = 0.0
    zz = 0.0
    cnt = 0
    si = 0
    for j in range(K):
        if valid[0, j]:
            accumulate_sample(uv[0, j, 0] * ih, uv[0, j, 1] * ih, 1.0, z[0, j], mom, rhs,
                              pu, pv, n2, MM, ep, eq)
            zz += z[0, j] ** 2
            cnt += 1
        while si < S and (j + 1 >= sizes[si] or j == K - 1):
            for oi in range(n_orders):
                M = (orders[oi] + 1) * (orders[oi] + 2) // 2
                ok[i, oi, si] = False
                if cnt < M + (1 if interpolate else 0):
                    continue
                cc = factor_normal(mom, ep, eq, M, N, D, L, Ld, Linv)
                if not cc <= max_conds[oi]:
                    continue
                for m in range(M):
                    g[m] = D[m] * rhs[m]
                solve_factored(L, Ld, M, g, y)
                for m in range(M):
                    x[m] = D[m] * y[m]
                if interpolate:
                    _g_column(L, Ld, D, M, 0, g, y, col)
                    f = x[0] / col[0]
                    for m in range(M):
                        x[m] -= col[m] * f
                    x[0] = 0.0
                xsx = 0.0
                xr = 0.0
                for m in range(M):
                    xr += x[m] * rhs[m]
                    for m2 in range(M):
                        xsx += x[m] * x[m2] * mom[ep[m] + ep[m2], eq[m] + eq[m2]]
                rss[i, oi, si] = max(zz - 2.0 * xr + xsx, 0.0)
                dof[i, oi, si] = cnt - M + (1 if interpolate else 0)
                _g_column(L, Ld, D, M, 1, g, y, col)
                gvar[i, oi, si, 0] = max(col[1], 0.0) * ih * ih
                _g_column(L, Ld, D, M, 2, g, y, col)
                gvar[i, oi, si, 1] = max(col[2], 0.0) * ih * ih
                val[i, oi, si, 0] = x[1] * ih
                val[i, oi, si, 1] = x[2] * ih
                val[i, oi, si, 2] = 0.0
                val[i, oi, si, 3] = 0.0
                gvar[i, oi, si, 2] = 0.0
                if M >= 6:
                    _g_column(L, Ld, D, M, 3, g, y, col)
                    g33 = col[3]
                    g35 = col[5]
                    _g_column(L, Ld, D, M, 5, g, y, col)
                    gvar[i, oi, si, 2] = max(g33 + col[5] + 2.0 * g35, 0.0) * ih ** 4
                    w_ = math.sqrt(1.0 + (x[1] * ih) ** 2 + (x[2] * ih) ** 2)
                    val[i, oi, si, 2] = (x[3] + x[5]) * ih * ih / w_
                    # |II|^2 = k1^2 + k2^2 to first order (second derivatives 2a20, a11, 2a02)
                    val[i, oi, si, 3] = (4.0 * x[3] ** 2 + 2.0 * x[4] ** 2
                                         + 4.0 * x[5] ** 2) * ih ** 4
                ok[i, oi, si] = True
            si += 1


def _auto_statistics_py(points, source, nbr, dist, orders, max_conds, interpolate, ep, eq,
                        sizes, kframe, val, gvar, rss, dof, ok):
    """Per query ``i``: :func:`_nested_fits` of every order and size in one PCA frame.

    The frame is that of the first ``kframe`` rows; ``ep, eq`` are the exponents of the
    largest order (the lower orders' are their prefixes).
    """
    Q, K = nbr.shape
    MM = ep.shape[0]
    O = orders.shape[0]
    n2 = 2 * orders[O - 1]
    nchunks = (Q + _CHUNK - 1) // _CHUNK
    for c in nb.prange(nchunks):
        uv = np.empty((1, K, 2))
        z = np.empty((1, K))
        valid = np.empty((1, K), dtype=np.bool_)
        Rl = np.empty((1, 3, 3))
        lam = np.empty((1, 3))
        a = np.empty((3, 3))
        v = np.empty((3, 3))
        ws = (np.empty((n2 + 1, n2 + 1)), np.empty(MM), np.empty(n2 + 1), np.empty(n2 + 1),
              np.empty((MM, MM)), np.empty((MM, MM)), np.empty((MM, MM)), np.empty(MM),
              np.empty(MM), np.empty(MM), np.empty(MM), np.empty(MM), np.empty(MM))
        for i in range(c * _CHUNK, min(Q, (c + 1) * _CHUNK)):
            height_frame(points, source[i], nbr[i], dist[i], K, uv, z, valid, 0, Rl, 0, lam, a,
                         v, kframe)
            _nested_fits(uv, z, valid, sizes, O, orders, max_conds, interpolate, ep, eq, ws, i,
                         val, gvar, rss, dof, ok)


auto_statistics_par, auto_statistics_ser = njit_pair(_auto_statistics_py)


def auto_statistics(hood: Hoods, *, orders: np.ndarray, max_conds: np.ndarray,
                    interpolate: bool, sizes: np.ndarray, kframe: int) -> dict:
    """Nested fits of every order and size per query (``order="auto"`` / ``k="auto"``).

    Returns ``val (Q, O, S, 4)`` (slopes ``a10, a01``, ``H`` and ``|II|^2 = k1^2 + k2^2`` in
    the query's PCA frame), ``gvar (Q, O, S, 3)`` (the variances of the first three over the
    noise variance), ``rss (Q, O, S)``, ``dof (Q, O, S)`` int64 and ``ok (Q, O, S)`` bool (the
    fit is well posed).
    """
    from ._jets_common import exponents_np

    Q = hood.nbr.shape[0]
    O, S = orders.shape[0], sizes.shape[0]
    e = exponents_np(int(orders[-1]))
    out = dict(val=np.zeros((Q, O, S, 4)), gvar=np.zeros((Q, O, S, 3)), rss=np.zeros((Q, O, S)),
               dof=np.zeros((Q, O, S), dtype=np.int64), ok=np.zeros((Q, O, S), dtype=np.bool_))
    par = Q >= PARALLEL_MIN // 8
    kernel = auto_statistics_par if par else auto_statistics_ser
    kernel(points=hood.points, source=hood.source, nbr=hood.nbr, dist=hood.dist,
           orders=np.ascontiguousarray(orders, dtype=np.int64),
           max_conds=np.ascontiguousarray(max_conds, dtype=np.float64),
           interpolate=bool(interpolate), ep=np.ascontiguousarray(e[:, 0]),
           eq=np.ascontiguousarray(e[:, 1]), sizes=np.ascontiguousarray(sizes, dtype=np.int64),
           kframe=int(kframe), **out)
    return out
