"""Per-point differential quantities of a point cloud or a mesh: the one obvious call.

>>> import numpy as np, polygeo
>>> pts = np.random.default_rng(0).normal(size=(2000, 3))
>>> pts /= np.linalg.norm(pts, axis=1, keepdims=True)          # unit sphere
>>> dq = polygeo.differential_quantities(pts, k=20, order=2)
>>> float(np.median(dq.mean_curvature))                        # outward normals: H = -1/r
-1.0...

Pipeline (per point ``p``): neighbourhood (k nearest neighbours including ``p``, a radius
ball, or a mesh k-ring) -> coordinates relative to ``p`` in float64 *before anything else*
(so a cloud shifted by 1e8 loses nothing) -> exact duplicates of a neighbour dropped -> PCA
frame -> height coordinates ``(u, v, z)`` -> n-jet least-squares fit (Cazals & Pouget 2005,
:func:`polygeo.jets.fit`, rank-deficient items fall back to a lower order) -> normal, second
fundamental form, principal curvatures and directions at ``p`` (``(u, v) = 0``, as
:func:`polygeo.diffgeo.from_jet`) -> world frame -> consistent orientation -> curvature signs
follow the final normals.

Sign convention (project-wide, :mod:`polygeo.diffgeo`): curvature is positive where the
surface bends towards the normal; with outward normals a sphere of radius ``r`` has
``k1 = k2 = H = -1/r`` and ``K = 1/r^2``. ``k1 >= k2`` and ``(d1, d2, n)`` is right-handed.

Orientation (``orient="auto"``): input normals if given, else the mesh's faces (re-wound
consistently, outward for closed components), else propagation over the k-NN graph (minimum
spanning tree, seeded outward at the highest point of each component). Points a reference
cannot decide (no normal, unreferenced vertex) get the sign of their propagation component.

Status codes (:class:`polygeo.status.Status`): ``NONFINITE_INPUT`` (the point itself is
NaN/inf: its outputs are NaN and no other point uses it), ``TOO_FEW_POINTS`` (fewer distinct
neighbours than coefficients), ``ORDER_REDUCED`` (degenerate neighbourhood, e.g. a single
scan line or ring: fitted at a lower order), ``DEGENERATE`` (not even a plane could be
fitted: normal from PCA only, curvatures 0), ``ILL_CONDITIONED``. Values of flagged points
are finite fallbacks, never NaN (except ``NONFINITE_INPUT``).

Two execution paths compute the same quantities: a compiled one (numba, used when no gradient
is needed) and a torch one (differentiable with respect to the points, used when ``points``
is a tensor requiring grad, or with ``backend="torch"``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import numba as nb
import numpy as np
import torch

from . import jets
from ._diffgeo_numba import jet_geometry, origin_geometry
from ._frames_numba import height_frame, height_frames_par, height_frames_ser
from ._jets_common import exponents_np
from ._jets_numba import accumulate_sample, fit_item, fit_scratch
from ._jets_numba import factor_normal as _factor
from ._jets_numba import solve_factored as _solve
from ._numba_util import finite_rows, njit_pair
from .checks import as_tensor, check_choice, check_faces, check_int, check_positive, check_shape
from .neighbors import PointIndex, mesh_k_ring, reaches_non_manifold
from .status import Status

__all__ = [
    "DifferentialQuantities",
    "differential_quantities",
    "AUTO_K_CANDIDATES",
    "AUTO_K_GAMMA",
    "AUTO_K_SMOOTH",
    "AUTO_ORDERS",
    "MAX_COND",
]

#: Neighbour counts tried by ``k="auto"`` (besides the point itself; capped by the data).
AUTO_K_CANDIDATES = (12, 24, 48, 96, 192, 384)
#: Width (in standard deviations) of the confidence intervals of ``k="auto"``.
AUTO_K_GAMMA = 2.5
#: Neighbours whose automatic sizes are pooled (median) per point by ``k="auto"``.
AUTO_K_SMOOTH = 24
#: Jet orders tried by ``order="auto"``.
AUTO_ORDERS = (2, 3, 4)
#: Default largest condition number accepted per jet order (see ``max_cond``).
MAX_COND = {1: 1e3, 2: 1e3, 3: 1e4, 4: 1e5}


@dataclass(frozen=True)
class DifferentialQuantities:
    """Per-point differential quantities (NumPy arrays for NumPy input, else torch tensors).

    Attributes
    ----------
    points : (N, 3)
        The input points (unchanged).
    normals : (N, 3)
        Oriented unit normals.
    k1, k2 : (N,)
        Principal curvatures, ``k1 >= k2`` (1 / length unit), signs following ``normals``.
    d1, d2 : (N, 3)
        Unit principal directions (``d2 = normals x d1``).
    mean_curvature, gaussian_curvature : (N,)
        ``H = (k1 + k2) / 2`` and ``K = k1 k2``.
    status : (N,) int64
        :class:`polygeo.status.Status` codes (0 = reliable).
    order : (N,) int64
        Jet order actually fitted per point (the requested one unless reduced or automatic).
    n_neighbors : (N,) int64
        Distinct points used by the fit (the point itself included: ``k + 1`` normally).
    residual : (N,)
        RMS height residual of the fit (length unit): a local noise estimate.
    frame : (N, 3, 3)
        Local fitting frames (columns ``e1, e2, e3``), world = ``frame @ (u, v, z) + point``,
        with ``e3`` on the side of the final normal.
    coeffs : (N, M)
        Jet coefficients in ``frame`` (:mod:`polygeo.jets` order, ``M`` of the largest
        order fitted; zeros above a point's own order).
    metric, second_form : (N, 2, 2) or None
        First and second fundamental forms of the jet at the point in the ``(u, v)``
        parametrisation of ``frame`` (when ``forms=True``).
    monge : dict or None
        When ``monge=True``: ``origin (N, 3)`` (the jet's point above ``p``), ``b (N, 4)``,
        ``c (N, 5)``: third and fourth order Monge coefficients in the oriented Monge frame
        ``(d1, d2, normals)`` (CGAL convention; zeros below order 3 / 4).
    """

    points: Any
    normals: Any
    k1: Any
    k2: Any
    d1: Any
    d2: Any
    mean_curvature: Any
    gaussian_curvature: Any
    status: Any
    order: Any
    n_neighbors: Any
    residual: Any
    frame: Any
    coeffs: Any
    metric: Any = None
    second_form: Any = None
    monge: Any = None

    def __len__(self) -> int:
        return int(self.status.shape[0])

    def summary(self) -> dict[str, Any]:
        """Counts per status and ranges of the curvatures of OK points (plain Python)."""
        st = np.asarray(_np(self.status))
        out: dict[str, Any] = {"n_points": int(st.size)}
        out["status"] = {Status(int(c)).name: int((st == c).sum()) for c in np.unique(st)}
        ok = st == 0
        for name in ("k1", "k2", "mean_curvature", "gaussian_curvature"):
            v = np.asarray(_np(getattr(self, name)))[ok]
            out[name] = (
                (float(np.min(v)), float(np.median(v)), float(np.max(v))) if v.size else None
            )
        return out


def _np(x: Any) -> Any:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else x


# ----------------------------------------------------------------------------- kernels

# The per-point pieces live with their concepts: PCA height frames in polygeo._frames_numba,
# the jet fit in polygeo._jets_numba, the geometry at the jet's origin in
# polygeo._diffgeo_numba. The common case (one k, one order) runs them fused, item by item,
# in one parallel loop whose work arrays stay in cache.

_FUSED_CHUNK = 256


def _fused_py(P, qsrc, qdst, nbr, dist, kuse, order, gaussian, max_cond, interp, ep, eq,
              normal, d1, d2, kk, status, fitted, count, resid, frame, coeffs):
    """Frames -> fit -> origin geometry of each query ``i``, results into row ``qdst[i]``.

    ``kuse (Q,)``: rows of ``nbr`` used per query.
    """
    Q, K = nbr.shape
    M = coeffs.shape[1]
    nchunks = (Q + _FUSED_CHUNK - 1) // _FUSED_CHUNK
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
        for i in range(c * _FUSED_CHUNK, min(Q, (c + 1) * _FUSED_CHUNK)):
            b = 0
            o = qdst[i]
            _, rad = height_frame(P, qsrc[i], nbr[i], dist[i], kuse[i], uv, z, valid, b, Rl, b,
                                  lam, a, v)
            if gaussian:
                h2 = max(rad * rad, 1e-300)
                for j in range(K):
                    d2_ = uv[b, j, 0] ** 2 + uv[b, j, 1] ** 2 + z[b, j] ** 2
                    w[b, j] = math.exp(-d2_ / h2) if valid[b, j] else 0.0
            fo, st, _, rs, _, cnt = fit_item(uv, z, w, gaussian, valid, True, b, 0.0, order,
                                             True, max_cond, 100.0, interp, ep, eq, scratch,
                                             cf, b)
            origin_geometry(cf, b, Rl, b, normal, d1, d2, kk, o)
            for j in range(M):
                coeffs[o, j] = cf[b, j]
            for r in range(3):
                for cc in range(3):
                    frame[o, r, cc] = Rl[b, r, cc]
            status[o] = st
            fitted[o] = fo
            count[o] = cnt
            resid[o] = rs


@nb.njit(cache=True, inline="always")
def _g_column(L, Ld, D, m, a, g, y, col):
    """Column ``a`` of ``G = S^-1`` (S the moment matrix) from ``N = D S D = L L^T``."""
    for j in range(m):
        g[j] = 0.0
    g[a] = D[a]
    _solve(L, Ld, m, g, y)
    for j in range(m):
        col[j] = D[j] * y[j]


def _auto_k_py(P, qsrc, qdst, nbr, dist, sizes, kframe, order, max_cond, interp, gamma, min_dof,
               ep, eq, normal, d1, d2, kk, status, fitted, count, resid, frame, coeffs):
    """k="auto": nested neighbourhoods (first ``sizes[s]`` rows) of one sorted k-NN list.

    One frame per point (PCA of the first ``kframe`` rows), moments accumulated along the
    sorted list so that every candidate size costs one small solve; per size the slopes
    ``a10, a01`` and ``H`` with their standard deviations ``sigma sqrt(G_ii)`` (``G`` the
    inverse moment matrix, ``sigma^2`` the smallest ``RSS / (n - M)`` over the sizes with at
    least ``min_dof`` degrees of freedom); the chosen size is the largest whose confidence
    intervals ``value +- gamma sd`` still intersect those of every smaller size (ICI rule).
    """
    Q, K = nbr.shape
    M = ep.shape[0]
    S = sizes.shape[0]
    n2 = 2 * order
    nchunks = (Q + _FUSED_CHUNK - 1) // _FUSED_CHUNK
    for c in nb.prange(nchunks):
        uv = np.empty((1, K, 2))
        z = np.empty((1, K))
        valid = np.empty((1, K), dtype=np.bool_)
        w1 = np.ones((1, 1))
        Rl = np.empty((1, 3, 3))
        lam = np.empty((1, 3))
        a = np.empty((3, 3))
        v = np.empty((3, 3))
        mom = np.empty((n2 + 1, n2 + 1))
        rhs = np.empty(M)
        pu = np.empty(n2 + 1)
        pv = np.empty(n2 + 1)
        N = np.empty((M, M))
        L = np.empty((M, M))
        Linv = np.empty((M, M))
        D = np.empty(M)
        Ld = np.empty(M)
        x = np.empty(M)
        g = np.empty(M)
        y = np.empty(M)
        col = np.empty(M)
        cf = np.empty((1, M))
        st_rss = np.empty(S)
        st_dof = np.empty(S, dtype=np.int64)
        st_cnt = np.empty(S, dtype=np.int64)
        st_val = np.empty((S, 3))
        st_g = np.empty((S, 3))
        st_cf = np.empty((S, M))
        scratch = fit_scratch(order, K)
        for i in range(c * _FUSED_CHUNK, min(Q, (c + 1) * _FUSED_CHUNK)):
            o = qdst[i]
            height_frame(P, qsrc[i], nbr[i], dist[i], K, uv, z, valid, 0, Rl, 0, lam, a, v,
                         kframe)
            hmax = 0.0
            for j in range(K):
                if valid[0, j]:
                    hmax = max(hmax, uv[0, j, 0] ** 2 + uv[0, j, 1] ** 2)
            h = math.sqrt(hmax) if hmax > 0.0 else 1.0
            ih = 1.0 / h
            for p in range(n2 + 1):
                for q in range(n2 + 1):
                    mom[p, q] = 0.0
            for j in range(M):
                rhs[j] = 0.0
            zz = 0.0
            cnt = 0
            si = 0
            ns = 0  # well-posed sizes stored
            for j in range(K):
                if valid[0, j]:
                    accumulate_sample(uv[0, j, 0] * ih, uv[0, j, 1] * ih, 1.0, z[0, j], mom, rhs,
                                      pu, pv, n2, M, ep, eq)
                    zz += z[0, j] ** 2
                    cnt += 1
                if j + 1 < sizes[si] and j < K - 1:
                    continue
                si += 1
                cc = math.inf
                if cnt >= M:
                    cc = _factor(mom, ep, eq, M, N, D, L, Ld, Linv)
                if not cc <= max_cond:
                    if ns > 0 or si >= S:
                        break  # a larger neighbourhood turned degenerate: keep the smaller
                    continue
                for m in range(M):
                    g[m] = D[m] * rhs[m]
                _solve(L, Ld, M, g, y)
                for m in range(M):
                    x[m] = D[m] * y[m]
                if interp:
                    _g_column(L, Ld, D, M, 0, g, y, col)
                    f = x[0] / col[0]
                    for m in range(M):
                        x[m] -= col[m] * f
                    x[0] = 0.0
                # residual sum of squares from the moments
                xsx = 0.0
                xr = 0.0
                for m in range(M):
                    xr += x[m] * rhs[m]
                    for m2 in range(M):
                        xsx += x[m] * x[m2] * mom[ep[m] + ep[m2], eq[m] + eq[m2]]
                st_rss[ns] = max(zz - 2.0 * xr + xsx, 0.0)
                st_dof[ns] = cnt - M + (1 if interp else 0)
                st_cnt[ns] = cnt
                # slopes and H (to first order a20 + a02) and their variances / sigma^2
                _g_column(L, Ld, D, M, 1, g, y, col)
                st_g[ns, 0] = max(col[1], 0.0) * ih * ih
                _g_column(L, Ld, D, M, 2, g, y, col)
                st_g[ns, 1] = max(col[2], 0.0) * ih * ih
                st_val[ns, 0] = x[1] * ih
                st_val[ns, 1] = x[2] * ih
                st_val[ns, 2] = 0.0
                st_g[ns, 2] = 0.0
                if M >= 6:
                    _g_column(L, Ld, D, M, 3, g, y, col)
                    g33 = col[3]
                    g35 = col[5]
                    _g_column(L, Ld, D, M, 5, g, y, col)
                    st_g[ns, 2] = max(g33 + col[5] + 2.0 * g35, 0.0) * ih ** 4
                    w_ = math.sqrt(1.0 + st_val[ns, 0] ** 2 + st_val[ns, 1] ** 2)
                    st_val[ns, 2] = (x[3] + x[5]) * ih * ih / w_
                pu[0] = 1.0
                for p in range(1, order + 1):
                    pu[p] = pu[p - 1] * ih
                for m in range(M):
                    st_cf[ns, m] = x[m] * pu[ep[m] + eq[m]]
                ns += 1
                if si >= S:
                    break
            # noise level at step t: the mean residual variance of the fits so far that have
            # at least min_dof degrees of freedom (of the first well-posed one before them)
            chosen = -1
            lo_u = lo_v = lo_h = -math.inf
            hi_u = hi_v = hi_h = math.inf
            s2sum = 0.0
            s2n = 0
            sig2 = 0.0
            for t in range(ns):
                if st_dof[t] >= min_dof or (s2n == 0 and st_dof[t] > 0):
                    if st_dof[t] >= min_dof and s2n > 0 and t > 0 and st_dof[t - 1] < min_dof:
                        s2sum = 0.0  # drop the small-sample placeholder
                        s2n = 0
                    s2sum += st_rss[t] / st_dof[t]
                    s2n += 1
                    sig2 = s2sum / s2n
                sd_u = gamma * math.sqrt(sig2 * st_g[t, 0])
                sd_v = gamma * math.sqrt(sig2 * st_g[t, 1])
                sd_h = gamma * math.sqrt(sig2 * st_g[t, 2])
                lo_u = max(lo_u, st_val[t, 0] - sd_u)
                hi_u = min(hi_u, st_val[t, 0] + sd_u)
                lo_v = max(lo_v, st_val[t, 1] - sd_v)
                hi_v = min(hi_v, st_val[t, 1] + sd_v)
                lo_h = max(lo_h, st_val[t, 2] - sd_h)
                hi_h = min(hi_h, st_val[t, 2] + sd_h)
                if chosen >= 0 and (lo_u > hi_u or lo_v > hi_v or lo_h > hi_h):
                    break  # the intervals no longer intersect: bias dominates
                chosen = t
            chosen_n = -1
            chosen_rss = 0.0
            if chosen >= 0:
                chosen_n = st_cnt[chosen]
                chosen_rss = st_rss[chosen]
                for m in range(M):
                    cf[0, m] = st_cf[chosen, m]
            if chosen_n >= 0:
                status[o] = 0
                fitted[o] = order
                count[o] = chosen_n
                resid[o] = math.sqrt(chosen_rss / chosen_n)
            else:
                # no candidate well posed: the full list with the usual order fallback
                fo, st, _, rs, _, cn = fit_item(uv, z, w1, False, valid, True, 0, 0.0, order,
                                                True, max_cond, 100.0, interp, ep, eq, scratch,
                                                cf, 0)
                status[o] = st
                fitted[o] = fo
                count[o] = cn
                resid[o] = rs
            origin_geometry(cf, 0, Rl, 0, normal, d1, d2, kk, o)
            for m in range(M):
                coeffs[o, m] = cf[0, m]
            for r in range(3):
                for cc_ in range(3):
                    frame[o, r, cc_] = Rl[0, r, cc_]


_auto_k_par, _auto_k_ser = njit_pair(_auto_k_py)
_fused_par, _fused_ser = njit_pair(_fused_py)
_PARALLEL_MIN = 4096


# ----------------------------------------------------------------------------- helpers


class _Local:
    """Height coordinates of a chunk of neighbourhoods (NumPy, float64).

    ``kuse``: rows of ``nbr`` used, one for all or one per query.
    """

    def __init__(self, P, qidx, nbr, dist, kuse):
        Q, K = nbr.shape
        self.uv = np.empty((Q, K, 2))
        self.z = np.empty((Q, K))
        self.valid = np.zeros((Q, K), dtype=np.bool_)
        self.R = np.empty((Q, 3, 3))
        self.count = np.zeros(Q, dtype=np.int64)
        self.radius = np.zeros(Q)
        if Q:
            ku = np.broadcast_to(np.asarray(kuse, dtype=np.int64), (Q,)).copy()
            kernel = height_frames_par if Q >= _PARALLEL_MIN else height_frames_ser
            kernel(P, qidx, nbr, dist, ku, self.uv, self.z, self.valid, self.R,
                   self.count, self.radius)


def _fit(local: _Local, order: int, weights: np.ndarray | None, max_cond: float,
         interpolate: bool = False) -> jets.JetFit:
    return jets.fit(
        torch.from_numpy(local.uv),
        torch.from_numpy(local.z),
        order,
        mask=torch.from_numpy(local.valid),
        weights=None if weights is None else torch.from_numpy(weights),
        max_cond=max_cond,
        backend="numba",
        interpolate=interpolate,
    )


def _geometry(coeffs: np.ndarray, R: np.ndarray) -> dict[str, np.ndarray]:
    return jet_geometry(coeffs, R)


def _smooth_sizes(q: np.ndarray, chosen: np.ndarray, nbr: np.ndarray, n: int,
                  k_smooth: int) -> np.ndarray:
    """Rows of the k-NN list to use per query (pooled automatic choices).

    The geometric median of the chosen sizes of its ``k_smooth`` nearest neighbours that
    belong to the same chunk (itself included).
    """
    pos = np.full(n, -1, dtype=np.int64)
    pos[q] = np.arange(q.size)
    nb_ = nbr[:, : max(k_smooth, 1)]
    p_ = np.where(nb_ >= 0, pos[np.maximum(nb_, 0)], -1)
    vals = np.where(p_ >= 0, np.log(np.maximum(chosen[np.maximum(p_, 0)], 1)), np.nan)
    vals[:, 0] = np.log(np.maximum(chosen, 1))
    med = np.exp(np.nanmedian(vals, axis=1))
    return np.clip(np.rint(med), 1, nbr.shape[1]).astype(np.int64)


def _gaussian_weights(local: _Local) -> np.ndarray:
    r2 = (local.uv**2).sum(-1) + local.z**2
    h2 = np.maximum(local.radius**2, 1e-300)[:, None]
    return np.where(local.valid, np.exp(-r2 / h2), 0.0)


def _select_order(fits: list[jets.JetFit], orders: tuple[int, ...], alpha: float) -> np.ndarray:
    """Index into ``orders`` per item: the lowest order no higher one beats by an F-test."""
    from scipy.stats import f as fdist

    n = fits[0].n_points.numpy().astype(np.float64)
    rss = [f.residual.double().numpy() ** 2 * n for f in fits]
    ok = [f.status.numpy() == 0 for f in fits]
    cur = np.zeros(n.shape[0], dtype=np.int64)
    for j in range(1, len(orders)):
        mc = np.array([jets.n_coeffs(orders[c]) for c in range(len(orders))])[cur]
        mj = jets.n_coeffs(orders[j])
        rss_c = np.choose(cur, rss)
        dof = n - mj
        good = ok[j] & (dof > 0) & (mj > mc)
        num = (rss_c - rss[j]) / np.maximum(mj - mc, 1)
        den = rss[j] / np.maximum(dof, 1)
        scale = np.maximum(rss_c, 1e-300)
        exact = rss_c <= 1e-24 * scale + 1e-300  # the current model is already exact
        with np.errstate(divide="ignore", invalid="ignore"):
            F = np.where(den > 0, num / den, np.inf)
        crit = fdist.ppf(1.0 - alpha, np.maximum(mj - mc, 1), np.maximum(dof, 1))
        better = good & ~exact & (F > crit)
        cur = np.where(better, j, cur)
    return cur


#: Width of the ICI confidence intervals (in estimated standard deviations).
_ICI_GAMMA = 3.0
#: Standard deviation of an order-2 fit's H in units of sigma / (r^2 sqrt(n)).
_ICI_H_FACTOR = 3.0


def _ici_select(
    normals: list[np.ndarray],
    delta: list[np.ndarray],
    gamma: float,
    scalars: list[np.ndarray] | None = None,
    scalar_deltas: list[np.ndarray] | None = None,
) -> np.ndarray:
    """Pick a neighbourhood size by intersection of confidence intervals (ICI).

    Over increasing k: the last candidate whose normal stays within ``gamma (delta_i +
    delta_j)`` of every smaller neighbourhood's normal (and, when given, whose scalar, e.g.
    the mean curvature, stays within ``gamma`` times the sum of the scalar deltas).
    """
    Q = normals[0].shape[0]
    chosen = np.zeros(Q, dtype=np.int64)
    alive = np.ones(Q, dtype=bool)
    for c in range(1, len(normals)):
        ok = alive.copy()
        for j in range(c):
            cosang = np.abs(np.einsum("ij,ij->i", normals[c], normals[j]))
            ang = np.arccos(np.clip(cosang, 0.0, 1.0))
            ok &= ang <= gamma * (delta[c] + delta[j])
            if scalars is not None:
                gap = np.abs(scalars[c] - scalars[j])
                ok &= gap <= gamma * (scalar_deltas[c] + scalar_deltas[j])
        ok &= np.isfinite(delta[c])
        chosen = np.where(ok, c, chosen)
        alive = ok
    return chosen


# ----------------------------------------------------------------------------- torch path


def _torch_chunk(pts_t, qidx, nbr, valid, order, weights, max_cond, interpolate=False):
    """Differentiable path with J1's frames / jets / diffgeo (one chunk)."""
    from .diffgeo import from_jet, to_world
    from .frames import pca_frames

    q = torch.from_numpy(qidx)
    idx = torch.from_numpy(np.where(valid, nbr, 0))
    m = torch.from_numpy(valid)
    p64 = pts_t.to(torch.float64)
    local = p64[idx] - p64[q][:, None, :]  # centred on the query point first
    local = torch.where(m[..., None], local, torch.zeros_like(local))
    fr = pca_frames(local, mask=m)
    R = fr.rotation
    uvz = local @ R
    w = None if weights is None else torch.from_numpy(weights)
    fit = jets.fit(
        uvz[..., :2], uvz[..., 2], order, mask=m, weights=w, max_cond=max_cond, backend="torch",
        interpolate=interpolate,
    )
    geom = to_world(from_jet(fit.coeffs).squeeze(1), R)
    return fit, geom, R


# ----------------------------------------------------------------------------- public API


def _as_points(points: Any) -> tuple[torch.Tensor, bool]:
    numpy_in = not isinstance(points, torch.Tensor)
    t = as_tensor(points, "points")
    check_shape(t, "points", ("N", 3))
    return t, numpy_in


def differential_quantities(
    points: Any,
    faces: Any = None,
    normals: Any = None,
    *,
    k: int | str = 20,
    radius: float | None = None,
    rings: int | None = None,
    order: int | str = 2,
    weights: str | None = None,
    orient: str = "auto",
    monge: bool = False,
    forms: bool = False,
    batch_size: int = 131072,
    progress: bool | None = None,
    workers: int = -1,
    backend: str = "auto",
    k_candidates: tuple[int, ...] = AUTO_K_CANDIDATES,
    auto_orders: tuple[int, ...] = AUTO_ORDERS,
    alpha: float = 0.01,
    max_cond: float | None = None,
    interpolate: bool = False,
) -> DifferentialQuantities:
    """Per-point normals, principal curvatures and directions, H and K by n-jet fitting.

    Parameters
    ----------
    points : (N, 3) float array or tensor
        Points or mesh vertices (length unit L). Non-finite points are allowed: they get
        status ``NONFINITE_INPUT`` and NaN outputs and are nobody's neighbour.
    faces : (F, 3) int, optional
        Triangles when ``points`` are mesh vertices: used to orient the normals (winding made
        consistent, outward for closed components; duplicate vertices welded first) and, with
        ``rings``, as neighbourhoods.
    normals : (N, 3) float, optional
        Input normals: only their signs are used, to orient the estimates.
    k : int or "auto"
        Number of nearest neighbours besides the point itself, so that each fit uses
        ``k + 1`` points: the convention of CGAL's ``jet_estimate_normals`` (same k, same
        points, same result). Clipped to the number of finite points. Must be at least
        ``n_coeffs(order) - 1`` (5 for order 2).
        ``"auto"``: per point, the largest of ``k_candidates`` whose estimates still agree
        with those of all smaller neighbourhoods within their noise-driven confidence
        intervals (intersection of confidence intervals, ICI: a bias-variance rule). With one
        order and uniform weights this runs compiled on one k-NN list: one frame per point
        (PCA of the candidate nearest ``4 M`` points), moments accumulated along the sorted
        neighbours so that each candidate costs one small solve; intervals ``value +-
        AUTO_K_GAMMA * sd`` on the slopes ``a10, a01`` and on ``H``, with ``sd = sigma
        sqrt(G_ii)`` (``G`` the inverse moment matrix; ``sigma^2`` at each step the mean of
        ``RSS / (n - M)`` over the candidates so far with at least ``3 M`` degrees of freedom);
        the per-point choices are then pooled (geometric median over the ``AUTO_K_SMOOTH``
        nearest neighbours) and each point is refitted at the pooled size in its own PCA
        frame. With ``order="auto"`` the sizes are chosen at the lowest order, then the order
        test runs at those sizes. Measured (torus, 20k vertices, order 2; median normal error
        / median relative error of H): clean 0.039 deg / 0.0068 (k = 20: 0.042 deg / 0.008),
        0.1 % noise 0.73 deg / 0.096 (best fixed k: 0.66 deg at k = 200, 0.064 at k = 100),
        1 % noise 5.7 deg / 0.40 (best fixed: 5.4 deg / 0.18 at k = 400).
    radius : float, optional
        Use all neighbours within this distance (L) instead of k nearest (``k`` then caps
        the count at ``k + 1`` points, nearest kept, unless ``k="auto"``).
    rings : int, optional
        With ``faces``: use the mesh ``rings``-ring of each vertex as its neighbourhood.
    order : int or "auto"
        Jet order 1..4 (1: plane, zero curvature; 2: osculating quadric; 3, 4: cubic and
        quartic terms, more accurate on clean data, more sensitive to noise). ``"auto"``: per
        point, the lowest of ``auto_orders`` that no higher one improves significantly (F-test
        on the residuals at level ``alpha``).
    weights : {None, "gaussian"}
        Uniform least squares (CGAL) or Gaussian weights ``exp(-d^2 / rms^2)`` of the
        distance to the point.
    orient : {"auto", "input", "mesh", "propagate", "none"}
        Source of the normals' signs (see the module docstring); "none" keeps the fit's sign.
    monge : bool
        Also return the Monge coefficients (``monge`` field).
    forms : bool
        Also return the fundamental forms (``metric``, ``second_form`` fields).
    batch_size : int
        Points per chunk (bounds memory: about ``batch_size * k * 60`` bytes).
    progress : bool or None
        Show a progress bar; None: for inputs of at least 200 000 points.
    workers : int
        Threads for the k-d tree (``-1``: all cores; the compiled kernels use numba's threads).
    backend : {"auto", "numba", "torch"}
        "torch" is differentiable w.r.t. ``points``; "auto" picks it when ``points`` is a
        tensor requiring grad.
    k_candidates : tuple of int
        Neighbourhood sizes tried by ``k="auto"``.
    auto_orders : tuple of int
        Orders tried by ``order="auto"``.
    alpha : float
        Significance level of the order F-test.
    max_cond : float, optional
        Largest accepted condition number of a neighbourhood's preconditioned, equilibrated
        least-squares system (:func:`polygeo.jets.fit`); default per order
        ``MAX_COND = {1: 1e3, 2: 1e3, 3: 1e4, 4: 1e5}``. Well-spread 20-neighbourhoods
        measure about 6-30 at order 2 (up to a few 1e3 at order 4); points on two scan lines
        measure 1e4 and more at order 2 and give curvatures that are guesses across the
        lines, so they are fitted at a lower order and flagged ``ORDER_REDUCED``.
    interpolate : bool
        Constrain each jet to pass through its query point (Cazals & Pouget's interpolation
        variant, :func:`polygeo.jets.fit`). Default False (approximation: the jet's constant
        term is free). Use True for exact samples (vertices of analytic, CAD or subdivision
        surfaces): at order 2 it removes about a quarter of the truncation bias of the
        curvatures (measured median relative error of H, k = 20, 10k-vertex meshes: torus
        1.7e-2 -> 1.3e-2, sphere 1.9e-3 -> 1.4e-3, open cylinder 1.4e-3 -> 1.1e-3); on noisy
        samples (already at noise 0.01 % of the diagonal) it passes the jet through the noise
        of the query point and about doubles the curvature error, hence not the default.
        Re-fitting in the Monge frame of a first fit was measured too and changes nothing at
        order 2 (median errors within 3 %), so it is not offered.

    Returns
    -------
    DifferentialQuantities
        NumPy arrays when ``points`` is NumPy, else torch tensors of the points' dtype.

    Raises
    ------
    ValueError
        Bad shapes, ``k < n_coeffs(order)``, ``order`` outside 1..4, unknown options, a
        reference source that is missing (``orient="input"`` without normals, ...).
    TypeError
        Non-numeric input, non-integer faces.
    """
    pts_t, numpy_in = _as_points(points)
    out_dtype = pts_t.dtype
    n = pts_t.shape[0]
    check_choice(orient, "orient", ("auto", "input", "mesh", "propagate", "none"))
    check_choice(weights, "weights", (None, "gaussian"))
    check_choice(backend, "backend", ("auto", "numba", "torch"))
    if not isinstance(interpolate, (bool, np.bool_)):
        raise TypeError(f"interpolate: expected a bool, got {interpolate!r}")
    interpolate = bool(interpolate)
    auto_order = isinstance(order, str)
    if auto_order:
        check_choice(order, "order", ("auto",))
        orders = tuple(check_int(o, "auto_orders", low=1, high=4) for o in auto_orders)
        if not orders:
            raise ValueError("auto_orders: expected at least one order")
        orders = tuple(sorted(set(orders)))
    else:
        orders = (check_int(order, "order", low=1, high=4),)
    max_order = max(orders)
    m_min = jets.n_coeffs(min(orders))
    auto_k = isinstance(k, str)
    if auto_k:
        check_choice(k, "k", ("auto",))
        # kc: points per neighbourhood, the point itself included (k + 1)
        kc = sorted({check_int(c, "k_candidates", low=m_min - 1) + 1 for c in k_candidates})
        if not kc:
            raise ValueError("k_candidates: expected at least one size")
    else:
        k = check_int(k, "k", low=1)
        if k + 1 < m_min:
            raise ValueError(
                f"k: an order-{min(orders)} jet has {m_min} coefficients, so k must be at least "
                f"{m_min - 1} (k neighbours plus the point itself), got {k}"
            )
        kc = [k + 1]
    if radius is not None:
        radius = check_positive(radius, "radius")
    batch_size = check_int(batch_size, "batch_size", low=1)
    if max_cond is not None:
        max_cond = check_positive(max_cond, "max_cond")
    alpha = float(alpha)
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha: expected a value in (0, 1), got {alpha}")
    needs_grad = torch.is_grad_enabled() and pts_t.requires_grad
    use_torch = backend == "torch" or (backend == "auto" and needs_grad)
    if use_torch and (auto_k or auto_order):
        raise ValueError("backend: the differentiable path supports fixed k and order only")

    P = np.ascontiguousarray(pts_t.detach().cpu().to(torch.float64).numpy())
    finite = finite_rows(P)
    f_np = _faces_np(faces, n) if faces is not None else None
    ref = None
    if normals is not None:
        nt = as_tensor(normals, "normals")
        check_shape(nt, "normals", (n, 3))
        ref = nt.detach().cpu().to(torch.float64).numpy()
    if orient == "input" and ref is None:
        raise ValueError("orient: 'input' needs normals")
    if orient == "mesh" and f_np is None:
        raise ValueError("orient: 'mesh' needs faces")
    if rings is not None:
        rings = check_int(rings, "rings", low=1)
        if f_np is None:
            raise ValueError("rings: mesh rings need faces")

    # ---------------------------------------------------------------- neighbourhoods + fits
    n_fin = int(finite.sum())
    kmax = max(kc)
    index = PointIndex(P) if rings is None else None
    rep = np.arange(n)  # representative of each point among exact duplicates
    deduped = False
    ring = None
    if rings is not None:
        ring = mesh_k_ring(f_np, n, rings)
        r_idx = np.where(ring.mask & finite[np.maximum(ring.index, 0)], ring.index, -1)
        # sort each ring by distance so that the duplicate scan and k caps see nearest first
        r_d = np.linalg.norm(P[np.maximum(r_idx, 0)] - P[:, None, :], axis=-1)
        r_d = np.where(r_idx >= 0, r_d, np.inf)
        o = np.argsort(r_d, axis=1, kind="stable")
        r_idx = np.take_along_axis(r_idx, o, 1)
        r_d = np.take_along_axis(r_d, o, 1)
        if not auto_k and r_idx.shape[1] > kc[0]:
            r_idx, r_d = r_idx[:, : kc[0]], r_d[:, : kc[0]]
        kmax = r_idx.shape[1]
    kq = min(kmax, max(n_fin, 1))
    k_graph = min(6, kq)
    M = jets.n_coeffs(max_order)
    kk_all = np.full((n, 4), np.nan)  # k1, k2, H, K (the fused kernel's layout)
    res = {
        "normals": np.full((n, 3), np.nan), "d1": np.full((n, 3), np.nan),
        "d2": np.full((n, 3), np.nan), "k1": kk_all[:, 0], "k2": kk_all[:, 1],
        "mean_curvature": kk_all[:, 2], "gaussian_curvature": kk_all[:, 3],
    }
    status = np.full(n, int(Status.NONFINITE_INPUT), dtype=np.int64)
    fitted_order = np.zeros(n, dtype=np.int64)
    n_nb = np.zeros(n, dtype=np.int64)
    resid = np.full(n, np.nan)
    frame = np.full((n, 3, 3), np.nan)
    coeffs = np.zeros((n, M))
    # k-NN graph for the orientation (not needed, hence not filled, with orient="none")
    need_graph = orient != "none"
    graph = np.full((n if need_graph else 0, k_graph), -1, dtype=np.int64)
    torch_parts: list[tuple[np.ndarray, Any, Any, Any]] = []

    # k="auto" with one order: nested neighbourhoods of one k-NN list (compiled)
    fast_auto = (auto_k and weights is None and radius is None and ring is None
                 and not use_torch)
    if auto_k:
        batch_size = min(batch_size, max(1024, 4_000_000 // max(kq, 1)))
    # visit the points in grid-cell order: neighbouring queries share neighbours (cache)
    visit = index.spatial_order() if index is not None else None
    if visit is None or visit.size != n:
        visit = np.arange(n)
    chunks = range(0, n, batch_size)
    show = (n >= 200_000) if progress is None else bool(progress)
    if show:
        from tqdm.auto import tqdm

        chunks = tqdm(chunks, total=math.ceil(n / batch_size), desc="jets", unit="chunk")
    for start in chunks:
        q = visit[start : start + batch_size]
        q = q[finite[q]]
        if q.size == 0:
            continue
        if ring is not None:
            nbr, dist = r_idx[q], r_d[q]
        else:
            upper = np.inf if radius is None else np.nextafter(radius, np.inf) * (1 + 1e-12)
            wk = workers if q.size >= _PARALLEL_MIN else 1
            nbr, dist = index.query(P[q], kq, workers=wk, upper=upper, self_index=rep[q])
            if not deduped and nbr.shape[1] > 1 and bool((dist[:, 1] == 0).any()):
                # exact duplicates: keep one copy per location in the tree, answer all copies
                deduped = True
                rep = _representatives(P, finite)
                Pt = P.copy()
                Pt[rep != np.arange(n)] = np.nan
                index = PointIndex(Pt)
                n_distinct = int((rep[finite] == np.flatnonzero(finite)).sum())
                kq = min(kmax, max(n_distinct, 1))
                nbr, dist = index.query(P[q], kq, workers=wk, upper=upper, self_index=rep[q])
        if need_graph:
            graph[q, : min(k_graph, nbr.shape[1])] = nbr[:, :k_graph]
        if use_torch:
            local = _Local(P, rep[q], nbr, dist, nbr.shape[1])
            w = _gaussian_weights(local) if weights == "gaussian" else None
            mc = max_cond or MAX_COND[orders[0]]
            fit, geom, R = _torch_chunk(pts_t, rep[q], nbr, local.valid, orders[0], w, mc,
                                        interpolate)
            torch_parts.append((q, fit, geom, R))
            status[q] = fit.status.numpy()
            fitted_order[q] = fit.fitted_order.numpy()
            n_nb[q] = fit.n_points.numpy()
            continue
        # candidate neighbourhood sizes (one unless k="auto")
        sizes = [c for c in kc if c <= nbr.shape[1]] or [nbr.shape[1]]
        if auto_k and radius is None and ring is None:
            sizes = sorted({min(c, kq) for c in kc})
        if auto_k and fast_auto:
            # sizes chosen at the lowest order; with several orders, the F-test then runs at
            # the chosen sizes (general path below)
            o_ = orders[0]
            e = exponents_np(o_)
            sz = np.array(sorted({min(c, nbr.shape[1]) for c in kc}), dtype=np.int64)
            m_ = jets.n_coeffs(o_)
            kframe = int(min(sz, key=lambda c: abs(int(c) - 4 * m_)))
            kernel = _auto_k_par if q.size >= _PARALLEL_MIN // 8 else _auto_k_ser
            kernel(P, np.ascontiguousarray(rep[q]), np.ascontiguousarray(q),
                   np.ascontiguousarray(nbr), np.ascontiguousarray(dist), sz, kframe, o_,
                   float(max_cond or MAX_COND[o_]), interpolate, AUTO_K_GAMMA, 3 * m_,
                   np.ascontiguousarray(e[:, 0]), np.ascontiguousarray(e[:, 1]),
                   res["normals"], res["d1"], res["d2"], kk_all, status, fitted_order, n_nb,
                   resid, frame, coeffs)
            # per-point choices are noisy: refit at the (geometric) median choice of the
            # point's nearest neighbours in this chunk, with that neighbourhood's own frame
            kuse = _smooth_sizes(q, n_nb[q], nbr, n, AUTO_K_SMOOTH)
            if len(orders) > 1:
                sizes = [kuse]
        if auto_k and fast_auto and len(orders) == 1:
            kernel = _fused_par if q.size >= _PARALLEL_MIN // 8 else _fused_ser
            kernel(P, np.ascontiguousarray(rep[q]), np.ascontiguousarray(q),
                   np.ascontiguousarray(nbr), np.ascontiguousarray(dist), kuse, o_, False,
                   float(max_cond or MAX_COND[o_]), interpolate,
                   np.ascontiguousarray(e[:, 0]), np.ascontiguousarray(e[:, 1]),
                   res["normals"], res["d1"], res["d2"], kk_all, status, fitted_order, n_nb,
                   resid, frame, coeffs)
            continue
        if len(sizes) == 1 and len(orders) == 1:
            # the common case, fused: frames -> fit -> geometry straight into the outputs
            o_ = orders[0]
            e = exponents_np(o_)
            kernel = _fused_par if q.size >= _PARALLEL_MIN else _fused_ser
            kernel(P, np.ascontiguousarray(rep[q]), np.ascontiguousarray(q),
                   np.ascontiguousarray(nbr), np.ascontiguousarray(dist),
                   np.full(q.size, int(sizes[0]), dtype=np.int64), o_,
                   weights == "gaussian", float(max_cond or MAX_COND[o_]), interpolate,
                   np.ascontiguousarray(e[:, 0]), np.ascontiguousarray(e[:, 1]),
                   res["normals"], res["d1"], res["d2"], kk_all, status, fitted_order, n_nb,
                   resid, frame, coeffs)
            continue
        per_size = []
        for size in sizes:
            local = _Local(P, rep[q], nbr, dist, size)
            w = _gaussian_weights(local) if weights == "gaussian" else None
            fits = [_fit(local, o, w, max_cond or MAX_COND[o], interpolate) for o in orders]
            pick = _select_order(fits, orders, alpha) if len(orders) > 1 else np.zeros(q.size, int)
            co = np.zeros((q.size, M))
            for j, fj in enumerate(fits):
                sel = pick == j
                if sel.any():
                    c = fj.coeffs.double().numpy()
                    co[sel, : c.shape[1]] = c[sel]
            stat = np.choose(pick, [f.status.numpy() for f in fits])
            ford = np.choose(pick, [f.fitted_order.numpy() for f in fits])
            rres = np.choose(pick, [f.residual.double().numpy() for f in fits])
            npts = fits[0].n_points.numpy()
            per_size.append((local, co, stat, ford, rres, npts))
        if len(per_size) > 1:
            geoms = [_geometry(ps[1], ps[0].R) for ps in per_size]
            deltas, deltas_h, hs = [], [], []
            n_ref = geoms[0]["normals"]
            for ps, g in zip(per_size, geoms):
                local, _, _, ford, rres, npts = ps
                mm = np.array([jets.n_coeffs(max(o, 1)) for o in ford])
                dof = np.maximum(npts - mm, 1)
                sigma = rres * np.sqrt(npts / dof)
                r = np.maximum(local.radius, 1e-300)
                with np.errstate(divide="ignore", invalid="ignore"):
                    d = sigma / (r * np.sqrt(np.maximum(npts, 1)))
                ok_s = ps[2] == 0
                deltas.append(np.where(ok_s, d, np.inf))
                # H of an order-2 fit has a standard deviation of a few sigma / (r^2 sqrt(n))
                deltas_h.append(np.where(ok_s, _ICI_H_FACTOR * d / r, np.inf))
                side = np.sign(np.einsum("ij,ij->i", g["normals"], n_ref))
                hs.append(g["mean_curvature"] * np.where(side == 0, 1.0, side))
            choice = _ici_select(
                [g["normals"] for g in geoms], deltas, gamma=_ICI_GAMMA, scalars=hs,
                scalar_deltas=deltas_h,
            )
        else:
            choice = np.zeros(q.size, dtype=np.int64)
        for s_i, ps in enumerate(per_size):
            sel = choice == s_i
            if not sel.any():
                continue
            local, co, stat, ford, rres, npts = ps
            g = _geometry(co[sel], local.R[sel])
            qs = q[sel]
            for key in res:
                res[key][qs] = g[key]
            status[qs] = stat[sel]
            fitted_order[qs] = ford[sel]
            n_nb[qs] = npts[sel]
            resid[qs] = rres[sel]
            frame[qs] = local.R[sel]
            coeffs[qs] = co[sel]

    # ---------------------------------------------------------------- orientation
    if use_torch:
        out = _assemble_torch(torch_parts, n, M, out_dtype)
        res_t, frame_t, coeffs_t, resid_t = out
        nrm_np = res_t["normals"].detach().numpy()
    else:
        nrm_np = res["normals"]
    sign = _orientation(P, nrm_np, status, graph, ref, f_np, orient, workers)

    # ---------------------------------------------------------------- outputs
    if use_torch:
        s_t = torch.from_numpy(sign)
        res_t = _apply_sign_torch(res_t, s_t)
        frame_t = _flip_frame_torch(frame_t, s_t)
        coeffs_t = coeffs_t * _coeff_signs(torch.from_numpy(sign), max_order)
        dq = {k_: v.to(out_dtype) for k_, v in res_t.items()}
        extra = dict(frame=frame_t.to(out_dtype), coeffs=coeffs_t.to(out_dtype),
                     residual=resid_t.to(out_dtype))
    else:
        if (sign < 0).any():
            res = _apply_sign_np(res, sign)
            frame = _flip_frame_np(frame, sign)
            coeffs = coeffs * _coeff_signs(torch.from_numpy(sign), max_order).numpy()
        dq = {k_: torch.from_numpy(np.ascontiguousarray(v)).to(out_dtype)
              for k_, v in res.items()}
        extra = dict(
            frame=torch.from_numpy(frame).to(out_dtype),
            coeffs=torch.from_numpy(coeffs).to(out_dtype),
            residual=torch.from_numpy(resid).to(out_dtype),
        )
    metric = second = None
    if forms:
        metric, second = _forms(extra["coeffs"].double())
        metric, second = metric.to(out_dtype), second.to(out_dtype)
    monge_out = None
    if monge:
        monge_out = _monge(extra["coeffs"].double(), extra["frame"].double(), P, out_dtype)
    if f_np is not None:  # a neighbourhood across a non-manifold edge (a fin) is flagged
        reach = reaches_non_manifold(P, f_np, n_nb, radius=radius, rings=rings)
        status = np.where(reach & (status == int(Status.OK)), int(Status.NON_MANIFOLD), status)
    result = DifferentialQuantities(
        points=pts_t,
        status=torch.from_numpy(status),
        order=torch.from_numpy(fitted_order),
        n_neighbors=torch.from_numpy(n_nb),
        metric=metric,
        second_form=second,
        monge=monge_out,
        **dq,
        **extra,
    )
    if numpy_in:
        conv = {}
        for fld in fields(result):
            v = getattr(result, fld.name)
            if isinstance(v, torch.Tensor):
                conv[fld.name] = v.detach().cpu().numpy()
            elif isinstance(v, dict):
                conv[fld.name] = {a: b.detach().cpu().numpy() for a, b in v.items()}
        conv["points"] = points if isinstance(points, np.ndarray) else np.asarray(points)
        result = DifferentialQuantities(**{**{f.name: getattr(result, f.name)
                                              for f in fields(result)}, **conv})
    return result


# ----------------------------------------------------------------------------- pieces


def _representatives(P: np.ndarray, finite: np.ndarray) -> np.ndarray:
    """Index of the first copy of each point among exact duplicates (itself if unique)."""
    n = P.shape[0]
    rep = np.arange(n)
    idx = np.flatnonzero(finite)
    if idx.size:
        _, first, inv = np.unique(P[idx], axis=0, return_index=True, return_inverse=True)
        rep[idx] = idx[first][inv.reshape(-1)]
    return rep


def _faces_np(faces: Any, n: int) -> np.ndarray:
    return check_faces(faces, n).cpu().numpy()


def _orientation(P, nrm, status, graph, ref, faces, orient, workers) -> np.ndarray:
    """Sign (+1/-1) per point making the estimated normals consistent (see module doc)."""
    from . import orient as ori
    from .mesh import weld_vertices

    n = P.shape[0]
    sign = np.ones(n)
    if orient == "none" or n == 0:
        return sign
    usable = np.isfinite(nrm).all(1) & (status != Status.NONFINITE_INPUT)
    ref_dir = None
    if orient in ("auto", "input") and ref is not None:
        ref_dir = np.where(np.isfinite(ref), ref, 0.0)
    elif orient in ("auto", "mesh") and faces is not None:
        Pw = np.where(np.isfinite(P), P, np.nan)
        w = weld_vertices(Pw, faces)
        wn, wvalid = ori.mesh_reference_normals(w.vertices, w.faces)
        ref_dir = np.where(wvalid[:, None], wn, 0.0)[w.mapping]
    nz = np.where(usable[:, None], nrm, 0.0)
    decided = np.zeros(n, dtype=bool)
    if ref_dir is not None:
        dot = np.einsum("ij,ij->i", nz, ref_dir)
        decided = usable & (dot != 0)
        sign = np.where(decided & (dot < 0), -1.0, 1.0)
        if decided.all() or not (usable & ~decided).any():
            return sign
    # propagate through reliable estimates only: a flagged normal (scan line, too few
    # points) may be far off and would flip everything behind it
    good = usable & (status == Status.OK)
    if not good.any():
        good = usable
    nz_good = np.where(good[:, None], nz, 0.0)
    prop = ori.propagate_orientation(P, nz_good, neighbors=graph, workers=workers)
    s_prop = np.where(good, prop.sign, 1.0)
    comp = np.where(good, prop.component, -1)
    if ref_dir is not None and decided.any():
        # per component: agree with the majority of decided points
        ok = decided & (comp >= 0)
        vote = np.zeros(max(int(comp.max()) + 1, 1))
        dot = np.abs(np.einsum("ij,ij->i", nz, ref_dir))
        np.add.at(vote, comp[ok], (sign[ok] * s_prop[ok]) * dot[ok])
        comp_sign = np.where(vote < 0, -1.0, 1.0)
        rest = good & ~decided & (comp >= 0)
        sign[rest] = s_prop[rest] * comp_sign[comp[rest]]
    else:
        sign = s_prop.copy()
    # flagged points: agree with the oriented normals of their reliable graph neighbours
    rest = usable & ~good & ~decided
    if rest.any():
        nb = graph[rest]
        valid = (nb >= 0) & good[np.maximum(nb, 0)]
        oriented = nz[np.maximum(nb, 0)] * (sign[np.maximum(nb, 0)] * valid)[..., None]
        ref_rest = oriented.sum(1)
        d = np.einsum("ij,ij->i", nz[rest], ref_rest)
        sign[rest] = np.where(d < 0, -1.0, 1.0)
    return np.where(usable, sign, 1.0)


def _apply_sign_np(res: dict, s: np.ndarray) -> dict:
    neg = s < 0
    out = dict(res)
    out["normals"] = res["normals"] * s[:, None]
    out["k1"] = np.where(neg, -res["k2"], res["k1"])
    out["k2"] = np.where(neg, -res["k1"], res["k2"])
    out["d1"] = np.where(neg[:, None], res["d2"], res["d1"])
    out["d2"] = np.where(neg[:, None], res["d1"], res["d2"])
    out["mean_curvature"] = res["mean_curvature"] * s
    return out


def _apply_sign_torch(res: dict, s: torch.Tensor) -> dict:
    neg = s < 0
    out = dict(res)
    out["normals"] = res["normals"] * s[:, None].to(res["normals"].dtype)
    out["k1"] = torch.where(neg, -res["k2"], res["k1"])
    out["k2"] = torch.where(neg, -res["k1"], res["k2"])
    out["d1"] = torch.where(neg[:, None], res["d2"], res["d1"])
    out["d2"] = torch.where(neg[:, None], res["d1"], res["d2"])
    out["mean_curvature"] = res["mean_curvature"] * s.to(res["mean_curvature"].dtype)
    return out


def _coeff_signs(s: torch.Tensor, order: int) -> torch.Tensor:
    """Factors turning jet coefficients in (e1, e2, e3) into ones in (e1, -e2, -e3).

    With ``v' = -v`` and ``z' = -z``: ``a'_pq = -(-1)^q a_pq`` where the sign is flipped.
    """
    q = jets.exponents(order)[:, 1].to(torch.float64)  # (M,)
    s = s.to(torch.float64)[:, None]
    return torch.where(s < 0, -((-1.0) ** q)[None, :], torch.ones_like(q)[None, :])


def _flip_frame_np(frame: np.ndarray, s: np.ndarray) -> np.ndarray:
    # flipping e3 keeps a right-handed frame when e2 flips too
    f = frame.copy()
    f[:, :, 1] *= s[:, None]
    f[:, :, 2] *= s[:, None]
    return f


def _flip_frame_torch(frame: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    m = torch.stack([torch.ones_like(s), s, s], -1).to(frame.dtype)
    return frame * m[:, None, :]


def _assemble_torch(parts, n, M, dtype):
    keys = ("normals", "d1", "d2", "k1", "k2", "mean_curvature", "gaussian_curvature")
    shapes = {"normals": (3,), "d1": (3,), "d2": (3,)}
    res = {
        k_: torch.full((n, *shapes.get(k_, ())), float("nan"), dtype=torch.float64)
        for k_ in keys
    }
    frame = torch.full((n, 3, 3), float("nan"), dtype=torch.float64)
    coeffs = torch.zeros((n, M), dtype=torch.float64)
    resid = torch.full((n,), float("nan"), dtype=torch.float64)
    for q, fit, geom, R in parts:
        qt = torch.from_numpy(q)
        for k_ in keys:
            name = "normal" if k_ == "normals" else k_
            res[k_] = res[k_].index_copy(0, qt, getattr(geom, name).to(torch.float64))
        frame = frame.index_copy(0, qt, R.to(torch.float64))
        c = fit.coeffs.to(torch.float64)
        cpad = torch.zeros((c.shape[0], M), dtype=torch.float64)
        cpad[:, : c.shape[1]] = c
        coeffs = coeffs.index_copy(0, qt, cpad)
        resid = resid.index_copy(0, qt, fit.residual.to(torch.float64))
    return res, frame, coeffs, resid


def _forms(coeffs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    from .diffgeo import from_jet

    g = from_jet(coeffs).squeeze(1)
    return g.metric, g.second_form


def _monge(coeffs, frame, P, dtype) -> dict[str, torch.Tensor]:
    from .diffgeo import monge_form

    ok = torch.isfinite(frame).all(-1).all(-1)
    origin_p = torch.from_numpy(np.where(np.isfinite(P), P, 0.0))
    R = torch.where(ok[:, None, None], frame, torch.eye(3, dtype=frame.dtype))
    mf = monge_form(coeffs, R, origin_p)
    # the coefficients/frame are already oriented (the jet's +z side is the final normal)
    nan = torch.tensor(float("nan"), dtype=coeffs.dtype)
    out = {
        "origin": torch.where(ok[:, None], mf.origin, nan),
        "b": torch.where(ok[:, None], mf.b, nan),
        "c": torch.where(ok[:, None], mf.c, nan),
    }
    return {k_: v.to(dtype) for k_, v in out.items()}
