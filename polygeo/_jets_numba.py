"""Compiled (numba) backend of :func:`polygeo.jets.fit`.

Same algorithm as the torch backend in :mod:`polygeo.jets` (weighted moments of the
preconditioned parameters -> equilibrated normal equations -> Cholesky -> condition estimate ->
solve -> one refinement step -> order fallback), one item at a time inside a parallel loop over
chunks of items, with no temporary arrays proportional to the batch. Not differentiable: the
public ``fit`` uses it only when no gradient is required.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
import torch

from . import _numba_util  # noqa: F401  (cache keyed on all kernel sources; threading layer)
from ._jets_common import COLLINEAR_TOL, exponents_np
from .status import Status

__all__ = [
    "fit_numba",
    "fit_item",
    "fit_scratch",
    "accumulate_sample",
    "factor_normal",
    "solve_factored",
]

_OK = int(Status.OK)
_TOO_FEW = int(Status.TOO_FEW_POINTS)
_REDUCED = int(Status.ORDER_REDUCED)
_DEGENERATE = int(Status.DEGENERATE)
_ILL = int(Status.ILL_CONDITIONED)
_CHUNK = 256


@nb.njit(cache=True)
def _ncoef(o):
    return (o + 1) * (o + 2) // 2


def _make_small(mc: int):
    """Small dense routines for an m x m system; ``mc > 0`` fixes m at compile time (unrolled)."""

    @nb.njit(cache=True, inline="always" if mc > 0 else "never")
    def factor(mom, ep, eq, mv, N, D, L, Ld, Linv):
        """Equilibrate, factor and bound the condition; inf when singular / not PD."""
        m = mc if mc > 0 else mv
        for a in range(m):
            d = mom[2 * ep[a], 2 * eq[a]]
            if not d > 0.0:
                return math.inf
            D[a] = 1.0 / math.sqrt(d)
        for a in range(m):
            N[a, a] = 1.0
            for b in range(a):
                t = mom[ep[a] + ep[b], eq[a] + eq[b]] * D[a] * D[b]
                N[a, b] = t
                N[b, a] = t
        # Cholesky N = L L^T (Ld: reciprocal diagonal)
        for j in range(m):
            s = N[j, j]
            for k in range(j):
                s -= L[j, k] * L[j, k]
            if not s > 0.0:
                return math.inf
            ljj = math.sqrt(s)
            L[j, j] = ljj
            r = 1.0 / ljj
            Ld[j] = r
            for i in range(j + 1, m):
                t = N[i, j]
                for k in range(j):
                    t -= L[i, k] * L[j, k]
                L[i, j] = t * r
        # sqrt(||N||_F) ||L^{-1}||_F >= sqrt(cond_2(N)), within a factor sqrt(m)
        nf = 0.0
        lf = 0.0
        for j in range(m):
            Linv[j, j] = Ld[j]
            lf += Ld[j] * Ld[j]
            for i in range(j + 1, m):
                t = 0.0
                for k in range(j, i):
                    t -= L[i, k] * Linv[k, j]
                t *= Ld[i]
                Linv[i, j] = t
                lf += t * t
            for i in range(m):
                nf += N[i, j] * N[i, j]
        c = math.sqrt(math.sqrt(nf) * lf)
        if not c < math.inf:
            c = math.inf
        return c

    @nb.njit(cache=True, inline="always" if mc > 0 else "never")
    def solve(L, Ld, mv, b, x):
        """Solve L L^T x = b."""
        m = mc if mc > 0 else mv
        for i in range(m):
            s = b[i]
            for k in range(i):
                s -= L[i, k] * x[k]
            x[i] = s * Ld[i]
        for i in range(m - 1, -1, -1):
            s = x[i]
            for k in range(i + 1, m):
                s -= L[k, i] * x[k]
            x[i] = s * Ld[i]

    return factor, solve


_factor_any, _solve_any = _make_small(0)
_factor6, _solve6 = _make_small(6)


@nb.njit(cache=True, inline="always")
def factor_normal(mom, ep, eq, m, N, D, L, Ld, Linv):
    if m == 6:
        return _factor6(mom, ep, eq, m, N, D, L, Ld, Linv)
    return _factor_any(mom, ep, eq, m, N, D, L, Ld, Linv)


@nb.njit(cache=True, inline="always")
def solve_factored(L, Ld, m, b, x):
    if m == 6:
        _solve6(L, Ld, m, b, x)
    else:
        _solve_any(L, Ld, m, b, x)


@nb.njit(cache=True, inline="always")
def _is_valid(uv, z, w, has_w, mask, has_mask, b, k):
    if has_mask and not mask[b, k]:
        return False
    u = uv[b, k, 0]
    v = uv[b, k, 1]
    zz = z[b, k]
    # NaN fails every comparison; inf fails the bound
    if not (abs(u) < math.inf and abs(v) < math.inf and abs(zz) < math.inf):
        return False
    if has_w and not w[b, k] > 0.0:
        return False
    return True



@nb.njit(cache=True, inline="always")
def accumulate_sample(su, sv, wk, zk, mom, rhs, pu, pv, n2, M, ep, eq):
    """Add one weighted sample to the moments ``sum w su^p sv^q`` (p + q <= n2) and rhs."""
    pu[0] = wk
    pv[0] = 1.0
    for p in range(1, n2 + 1):
        pu[p] = pu[p - 1] * su
        pv[p] = pv[p - 1] * sv
    for p in range(n2 + 1):
        for q in range(n2 + 1 - p):
            mom[p, q] += pu[p] * pv[q]
    for j in range(M):
        rhs[j] += zk * pu[ep[j]] * pv[eq[j]]


@nb.njit(cache=True, inline="always")
def _sample_residual(uv, z, b, k, ih, x, m, o, pu, pv, ep, eq):
    """Height residual of sample ``k`` of item ``b`` against the scaled jet ``x[:m]``."""
    su = uv[b, k, 0] * ih
    sv = uv[b, k, 1] * ih
    pu[0] = 1.0
    pv[0] = 1.0
    for p in range(1, o + 1):
        pu[p] = pu[p - 1] * su
        pv[p] = pv[p - 1] * sv
    r = z[b, k]
    for j in range(m):
        r -= x[j] * pu[ep[j]] * pv[eq[j]]
    return r


@nb.njit(cache=True)
def _moments(uv, z, w, has_w, ok, b, K, ih, mom, rhs, pu, pv, n2, M, ep, eq):
    """Weighted moments sum w su^p sv^q (p + q <= n2) and right-hand side, any order."""
    for p in range(n2 + 1):
        for q in range(n2 + 1):
            mom[p, q] = 0.0
    for j in range(M):
        rhs[j] = 0.0
    for k in range(K):
        if not ok[k]:
            continue
        accumulate_sample(uv[b, k, 0] * ih, uv[b, k, 1] * ih, w[b, k] if has_w else 1.0,
                          z[b, k], mom, rhs, pu, pv, n2, M, ep, eq)


@nb.njit(cache=True, inline="always")
def _moments1(uv, z, w, has_w, ok, b, K, ih, mom, rhs):
    """Unrolled moments of a 1-jet (degree <= 2) and its right-hand side."""
    m00 = m10 = m01 = m20 = m11 = m02 = 0.0
    r0 = r1 = r2 = 0.0
    for k in range(K):
        if not ok[k]:
            continue
        su = uv[b, k, 0] * ih
        sv = uv[b, k, 1] * ih
        wk = w[b, k] if has_w else 1.0
        wu = wk * su
        wv = wk * sv
        m00 += wk
        m10 += wu
        m01 += wv
        m20 += wu * su
        m11 += wu * sv
        m02 += wv * sv
        zk = z[b, k]
        r0 += wk * zk
        r1 += wu * zk
        r2 += wv * zk
    mom[0, 0] = m00
    mom[1, 0] = m10
    mom[0, 1] = m01
    mom[2, 0] = m20
    mom[1, 1] = m11
    mom[0, 2] = m02
    rhs[0] = r0
    rhs[1] = r1
    rhs[2] = r2


@nb.njit(cache=True, inline="always")
def _moments2(uv, z, w, has_w, ok, b, K, ih, mom, rhs):
    """Unrolled moments of a 2-jet (degree <= 4) and its right-hand side."""
    m00 = m10 = m01 = m20 = m11 = m02 = 0.0
    m30 = m21 = m12 = m03 = m40 = m31 = m22 = m13 = m04 = 0.0
    r0 = r1 = r2 = r3 = r4 = r5 = 0.0
    for k in range(K):
        if not ok[k]:
            continue
        su = uv[b, k, 0] * ih
        sv = uv[b, k, 1] * ih
        wk = w[b, k] if has_w else 1.0
        wu = wk * su
        wv = wk * sv
        wuu = wu * su
        wuv = wu * sv
        wvv = wv * sv
        m00 += wk
        m10 += wu
        m01 += wv
        m20 += wuu
        m11 += wuv
        m02 += wvv
        m30 += wuu * su
        m21 += wuu * sv
        m12 += wuv * sv
        m03 += wvv * sv
        m40 += wuu * su * su
        m31 += wuu * su * sv
        m22 += wuu * sv * sv
        m13 += wuv * sv * sv
        m04 += wvv * sv * sv
        zk = z[b, k]
        r0 += wk * zk
        r1 += wu * zk
        r2 += wv * zk
        r3 += wuu * zk
        r4 += wuv * zk
        r5 += wvv * zk
    mom[0, 0] = m00
    mom[1, 0] = m10
    mom[0, 1] = m01
    mom[2, 0] = m20
    mom[1, 1] = m11
    mom[0, 2] = m02
    mom[3, 0] = m30
    mom[2, 1] = m21
    mom[1, 2] = m12
    mom[0, 3] = m03
    mom[4, 0] = m40
    mom[3, 1] = m31
    mom[2, 2] = m22
    mom[1, 3] = m13
    mom[0, 4] = m04
    rhs[0] = r0
    rhs[1] = r1
    rhs[2] = r2
    rhs[3] = r3
    rhs[4] = r4
    rhs[5] = r5


@nb.njit(cache=True)
def _residual(uv, z, w, has_w, ok, b, K, ih, x, m, o, pu, pv, ep, eq):
    """Weighted sum of squared residuals and of weights, any order."""
    sw = 0.0
    sr = 0.0
    for k in range(K):
        if not ok[k]:
            continue
        r = _sample_residual(uv, z, b, k, ih, x, m, o, pu, pv, ep, eq)
        wk = w[b, k] if has_w else 1.0
        sw += wk
        sr += wk * r * r
    return sr, sw


@nb.njit(cache=True, inline="always")
def _residual2(uv, z, w, has_w, ok, b, K, ih, x, m):
    """Unrolled residual of a jet of order <= 2 (m <= 6 coefficients, zero-padded)."""
    x0 = x[0]
    x1 = x[1] if m > 1 else 0.0
    x2 = x[2] if m > 2 else 0.0
    x3 = x[3] if m > 3 else 0.0
    x4 = x[4] if m > 4 else 0.0
    x5 = x[5] if m > 5 else 0.0
    sw = 0.0
    sr = 0.0
    for k in range(K):
        if not ok[k]:
            continue
        su = uv[b, k, 0] * ih
        sv = uv[b, k, 1] * ih
        r = z[b, k] - (x0 + su * (x1 + x3 * su + x4 * sv) + sv * (x2 + x5 * sv))
        wk = w[b, k] if has_w else 1.0
        sw += wk
        sr += wk * r * r
    return sr, sw


@nb.njit(cache=True, inline="always")
def _collinear(mom):
    """Whether the weighted parameter samples behind the moments ``mom`` are collinear."""
    m0 = mom[0, 0]
    if not m0 > 0.0:
        return True
    mu = mom[1, 0] / m0
    mv = mom[0, 1] / m0
    c20 = mom[2, 0] / m0 - mu * mu
    c02 = mom[0, 2] / m0 - mv * mv
    c11 = mom[1, 1] / m0 - mu * mv
    tr = c20 + c02
    return not (c20 * c02 - c11 * c11 > COLLINEAR_TOL * tr * tr)


@nb.njit(cache=True)
def fit_scratch(order, K):
    """Per-thread work arrays of :func:`fit_item` for jets of ``order`` and ``K`` samples."""
    M = _ncoef(order)
    n2 = 2 * order
    return (np.empty((n2 + 1, n2 + 1)), np.empty(M), np.empty(n2 + 1), np.empty(n2 + 1),
            np.empty((M, M)), np.empty((M, M)), np.empty((M, M)), np.empty(M), np.empty(M),
            np.empty(M), np.empty(M), np.empty(M), np.empty(K, dtype=np.bool_))


@nb.njit(cache=True, inline="always")
def fit_item(uv, z, w, has_w, mask, has_mask, b, h_given, order, fallback, max_cond,
             refine_above, interp, ep, eq, scratch, coeffs, ob):
    """Fit one item ``b`` of ``uv (B, K, 2)``, ``z (B, K)``; coefficients into ``coeffs[ob]``.

    ``h_given > 0`` is the preconditioning scale, else the largest ``|uv|``. Returns
    ``(fitted order, status, cond of the requested order, rms residual, h, count)``.
    """
    mom, rhs, pu, pv, N, L, Linv, D, Ld, x, g, y, ok = scratch
    K = uv.shape[1]
    M = _ncoef(order)
    n2 = 2 * order
    # validity, count and scale
    cnt = 0
    hmax = 0.0
    for k in range(K):
        vk = _is_valid(uv, z, w, has_w, mask, has_mask, b, k)
        ok[k] = vk
        if vk:
            cnt += 1
            r2 = uv[b, k, 0] * uv[b, k, 0] + uv[b, k, 1] * uv[b, k, 1]
            if r2 > hmax:
                hmax = r2
    if h_given > 0.0:
        h = h_given
    else:
        h = math.sqrt(hmax) if hmax > 0.0 else 1.0
    ih = 1.0 / h
    # weighted moments of the preconditioned parameters
    if order == 2:
        _moments2(uv, z, w, has_w, ok, b, K, ih, mom, rhs)
    elif order == 1:
        _moments1(uv, z, w, has_w, ok, b, K, ih, mom, rhs)
    else:
        _moments(uv, z, w, has_w, ok, b, K, ih, mom, rhs, pu, pv, n2, M, ep, eq)
    flat = _collinear(mom)
    # solve, falling back to lower orders
    o = order
    st = _OK
    creq = math.inf
    m = 0
    while True:
        if o == 0:
            x[0] = rhs[0] / mom[0, 0] if mom[0, 0] > 0.0 and not interp else 0.0
            m = 1
            st = _TOO_FEW if cnt < 3 else _DEGENERATE
            break
        m = _ncoef(o)
        success = False
        cc = math.inf
        if cnt >= m:
            cc = factor_normal(mom, ep, eq, m, N, D, L, Ld, Linv)
            success = cc <= max_cond and not flat
        if o == order:
            creq = cc
        if success:
            for j in range(m):
                g[j] = D[j] * rhs[j]
            solve_factored(L, Ld, m, g, y)
            for j in range(m):
                x[j] = D[j] * y[j]
            if cc > refine_above:
                for j in range(m):
                    g[j] = 0.0
                for k in range(K):
                    if not ok[k]:
                        continue
                    r = _sample_residual(uv, z, b, k, ih, x, m, o, pu, pv, ep, eq)
                    if has_w:
                        r *= w[b, k]
                    for j in range(m):
                        g[j] += r * pu[ep[j]] * pv[eq[j]]
                for j in range(m):
                    g[j] *= D[j]
                solve_factored(L, Ld, m, g, y)
                for j in range(m):
                    x[j] += D[j] * y[j]
            if interp:
                # constrained to x0 = 0: x - G e0 x0 / G00, G = D N^-1 D
                for j in range(m):
                    g[j] = 0.0
                g[0] = D[0]
                solve_factored(L, Ld, m, g, y)
                f = x[0] / (D[0] * y[0])
                for j in range(m):
                    x[j] -= D[j] * y[j] * f
                x[0] = 0.0
            st = _OK if o == order else _REDUCED
            break
        if not fallback:
            for j in range(M):
                x[j] = 0.0
            m = M
            st = _TOO_FEW if cnt < M else _ILL
            break
        o -= 1
    # residual of the final fit
    if m <= 6:
        sr, sw = _residual2(uv, z, w, has_w, ok, b, K, ih, x, m)
    else:
        sr, sw = _residual(uv, z, w, has_w, ok, b, K, ih, x, m, o, pu, pv, ep, eq)
    # unscale and store
    pu[0] = 1.0
    for p in range(1, order + 1):
        pu[p] = pu[p - 1] * ih
    for j in range(M):
        if j < m:
            coeffs[ob, j] = x[j] * pu[ep[j] + eq[j]]
        else:
            coeffs[ob, j] = 0.0
    return o, st, creq, (math.sqrt(sr / sw) if sw > 0.0 else 0.0), h, cnt


@nb.njit(cache=True, parallel=True)
def _fit_kernel(uv, z, w, has_w, mask, has_mask, scale, has_scale, order, fallback, max_cond,
                refine_above, interp, ep, eq, coeffs, fitted, status, cond, resid, hout, count,
                rank):
    B = uv.shape[0]
    K = uv.shape[1]
    M = _ncoef(order)
    nchunks = (B + _CHUNK - 1) // _CHUNK
    for c in nb.prange(nchunks):
        scratch = fit_scratch(order, K)
        for b in range(c * _CHUNK, min(B, (c + 1) * _CHUNK)):
            hg = scale[b] if has_scale else 0.0
            o, st, creq, rs, h, cnt = fit_item(uv, z, w, has_w, mask, has_mask, b, hg, order,
                                               fallback, max_cond, refine_above, interp, ep,
                                               eq, scratch, coeffs, b)
            fitted[b] = o
            status[b] = st
            cond[b] = creq
            resid[b] = rs
            hout[b] = h
            count[b] = cnt
            rank[b] = M if st == _OK else -1  # filled in by the caller


def fit_numba(uv, z, w, mask, s, order, fallback, max_cond, refine_above, interpolate=False):
    """Run the compiled kernel on torch inputs; return the tuple the torch backend returns.

    ``mask`` is the caller's bool mask or None; non-finite samples and zero weights are
    excluded inside the kernel. Two fields are left for the caller (:func:`polygeo.jets.fit`)
    to complete with the torch backend, so that this module never imports :mod:`polygeo.jets`:
    ``rank`` is -1 for the items not solved at full rank, and with ``fallback=False`` the
    coefficients and residuals of the items whose status is not OK are unset.
    """
    B, K = z.shape

    def arr(t, dtype):
        return np.ascontiguousarray(t.detach().cpu().numpy(), dtype=dtype)

    uv_np = arr(uv, np.float64)
    z_np = arr(z, np.float64)
    has_w = w is not None
    w_np = arr(w, np.float64) if has_w else np.ones((1, 1))
    has_mask = mask is not None
    m_np = arr(mask, np.bool_) if has_mask else np.ones((1, 1), dtype=np.bool_)
    has_scale = s is not None
    s_np = arr(s, np.float64) if has_scale else np.ones(1)
    e = exponents_np(order)
    ep = np.ascontiguousarray(e[:, 0])
    eq = np.ascontiguousarray(e[:, 1])
    M = len(e)
    coeffs = np.empty((B, M))
    fitted = np.empty(B, dtype=np.int64)
    status = np.empty(B, dtype=np.int64)
    cond = np.empty(B)
    resid = np.empty(B)
    h = np.empty(B)
    count = np.empty(B, dtype=np.int64)
    rank = np.empty(B, dtype=np.int64)
    if B > 0:
        _fit_kernel(uv_np, z_np, w_np, has_w, m_np, has_mask, s_np, has_scale, order,
                    bool(fallback), float(max_cond), float(refine_above), bool(interpolate), ep,
                    eq, coeffs, fitted, status, cond, resid, h, count, rank)
    return tuple(
        torch.from_numpy(a) for a in (coeffs, resid, rank, cond, h, status, fitted, count)
    )
