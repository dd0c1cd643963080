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

from .status import Status

__all__ = ["fit_numba"]

_OK = int(Status.OK)
_TOO_FEW = int(Status.TOO_FEW_POINTS)
_REDUCED = int(Status.ORDER_REDUCED)
_DEGENERATE = int(Status.DEGENERATE)
_ILL = int(Status.ILL_CONDITIONED)
_CHUNK = 256


@nb.njit(cache=True, inline="always")
def _ncoef(o):
    return (o + 1) * (o + 2) // 2


@nb.njit(cache=True)
def _build_normal(mom, ep, eq, m, N, D):
    """Equilibrated normal matrix of the first m monomials; False if a diagonal is zero."""
    for a in range(m):
        d = mom[2 * ep[a], 2 * eq[a]]
        if not d > 0.0:
            return False
        D[a] = 1.0 / math.sqrt(d)
    for a in range(m):
        for b in range(m):
            N[a, b] = mom[ep[a] + ep[b], eq[a] + eq[b]] * D[a] * D[b]
    return True


@nb.njit(cache=True)
def _cholesky(N, L, m):
    """Lower Cholesky factor of N[:m, :m] into L; False when not positive definite."""
    for j in range(m):
        s = N[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            return False
        ljj = math.sqrt(s)
        L[j, j] = ljj
        for i in range(j + 1, m):
            t = N[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / ljj
        for i in range(j):
            L[i, j] = 0.0
    return True


@nb.njit(cache=True)
def _chol_solve(L, m, b, x):
    """Solve L L^T x = b (first m entries)."""
    for i in range(m):
        s = b[i]
        for k in range(i):
            s -= L[i, k] * x[k]
        x[i] = s / L[i, i]
    for i in range(m - 1, -1, -1):
        s = x[i]
        for k in range(i + 1, m):
            s -= L[k, i] * x[k]
        x[i] = s / L[i, i]


@nb.njit(cache=True)
def _cond1(N, L, m, Linv):
    """sqrt(||N||_1 ||N^{-1}||_1) with N^{-1} = L^{-T} L^{-1}."""
    for j in range(m):
        for i in range(m):
            Linv[i, j] = 0.0
        Linv[j, j] = 1.0 / L[j, j]
        for i in range(j + 1, m):
            s = 0.0
            for k in range(j, i):
                s -= L[i, k] * Linv[k, j]
            Linv[i, j] = s / L[i, i]
    n1 = 0.0
    i1 = 0.0
    for j in range(m):
        cn = 0.0
        ci = 0.0
        for i in range(m):
            cn += abs(N[i, j])
            # (L^{-T} L^{-1})[i, j] = sum_k Linv[k, i] Linv[k, j], k >= max(i, j)
            s = 0.0
            for k in range(max(i, j), m):
                s += Linv[k, i] * Linv[k, j]
            ci += abs(s)
        n1 = max(n1, cn)
        i1 = max(i1, ci)
    c = math.sqrt(n1 * i1)
    if not c < math.inf:
        c = math.inf
    return c


@nb.njit(cache=True)
def _rank(mom, ep, eq, m, max_cond):
    """Numerical rank of the equilibrated normal matrix (eigenvalue count)."""
    N = np.zeros((m, m))
    D = np.ones(m)
    for a in range(m):
        d = mom[2 * ep[a], 2 * eq[a]]
        if d > 0.0:
            D[a] = 1.0 / math.sqrt(d)
    for a in range(m):
        for b in range(m):
            N[a, b] = mom[ep[a] + ep[b], eq[a] + eq[b]] * D[a] * D[b]
    lam = np.linalg.eigvalsh(N)
    top = max(lam[m - 1], 1e-300)
    r = 0
    for i in range(m):
        if lam[i] > top / (max_cond * max_cond):
            r += 1
    return r


@nb.njit(cache=True, parallel=True)
def _fit_kernel(uv, z, w, valid, scale, has_scale, order, fallback, max_cond, refine, ep, eq,
                coeffs, fitted, status, cond, resid, hout, count, rank):
    B = uv.shape[0]
    K = uv.shape[1]
    M = _ncoef(order)
    n2 = 2 * order
    nchunks = (B + _CHUNK - 1) // _CHUNK
    for c in nb.prange(nchunks):
        mom = np.empty((n2 + 1, n2 + 1))
        rhs = np.empty(M)
        pu = np.empty(n2 + 1)
        pv = np.empty(n2 + 1)
        N = np.empty((M, M))
        L = np.empty((M, M))
        Linv = np.empty((M, M))
        D = np.empty(M)
        x = np.empty(M)
        g = np.empty(M)
        y = np.empty(M)
        for b in range(c * _CHUNK, min(B, (c + 1) * _CHUNK)):
            # scale and count
            cnt = 0
            hmax = 0.0
            for k in range(K):
                if valid[b, k]:
                    cnt += 1
                    r2 = uv[b, k, 0] * uv[b, k, 0] + uv[b, k, 1] * uv[b, k, 1]
                    if r2 > hmax:
                        hmax = r2
            if has_scale:
                h = scale[b]
            else:
                h = math.sqrt(hmax) if hmax > 0.0 else 1.0
            ih = 1.0 / h
            # weighted moments of the preconditioned parameters
            for p in range(n2 + 1):
                for q in range(n2 + 1):
                    mom[p, q] = 0.0
            for j in range(M):
                rhs[j] = 0.0
            for k in range(K):
                if not valid[b, k]:
                    continue
                su = uv[b, k, 0] * ih
                sv = uv[b, k, 1] * ih
                wk = w[b, k]
                pu[0] = wk
                pv[0] = 1.0
                for p in range(1, n2 + 1):
                    pu[p] = pu[p - 1] * su
                    pv[p] = pv[p - 1] * sv
                for p in range(n2 + 1):
                    for q in range(n2 + 1 - p):
                        mom[p, q] += pu[p] * pv[q]
                zk = z[b, k]
                for j in range(M):
                    rhs[j] += zk * pu[ep[j]] * pv[eq[j]]
            # solve, falling back to lower orders
            o = order
            st = _OK
            creq = math.inf
            m = 0
            while True:
                if o == 0:
                    x[0] = rhs[0] / mom[0, 0] if mom[0, 0] > 0.0 else 0.0
                    m = 1
                    st = _TOO_FEW if cnt < 3 else _DEGENERATE
                    break
                m = _ncoef(o)
                success = False
                if cnt >= m:
                    if _build_normal(mom, ep, eq, m, N, D) and _cholesky(N, L, m):
                        cc = _cond1(N, L, m, Linv)
                        if o == order:
                            creq = cc
                        success = cc <= max_cond
                if success:
                    for j in range(m):
                        g[j] = D[j] * rhs[j]
                    _chol_solve(L, m, g, y)
                    for j in range(m):
                        x[j] = D[j] * y[j]
                    if refine:
                        for j in range(m):
                            g[j] = 0.0
                        for k in range(K):
                            if not valid[b, k]:
                                continue
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
                            r *= w[b, k]
                            for j in range(m):
                                g[j] += r * pu[ep[j]] * pv[eq[j]]
                        for j in range(m):
                            g[j] *= D[j]
                        _chol_solve(L, m, g, y)
                        for j in range(m):
                            x[j] += D[j] * y[j]
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
            sw = 0.0
            sr = 0.0
            for k in range(K):
                if not valid[b, k]:
                    continue
                su = uv[b, k, 0] * ih
                sv = uv[b, k, 1] * ih
                pu[0] = 1.0
                pv[0] = 1.0
                for p in range(1, order + 1):
                    pu[p] = pu[p - 1] * su
                    pv[p] = pv[p - 1] * sv
                r = z[b, k]
                for j in range(m):
                    r -= x[j] * pu[ep[j]] * pv[eq[j]]
                sw += w[b, k]
                sr += w[b, k] * r * r
            resid[b] = math.sqrt(sr / sw) if sw > 0.0 else 0.0
            # unscale and store
            for j in range(M):
                if j < m:
                    coeffs[b, j] = x[j] * ih ** (ep[j] + eq[j])
                else:
                    coeffs[b, j] = 0.0
            fitted[b] = o
            status[b] = st
            cond[b] = creq
            hout[b] = h
            count[b] = cnt
            rank[b] = M if st == _OK else _rank(mom, ep, eq, M, max_cond)


def fit_numba(uv, z, w, valid, s, order, fallback, max_cond, refine):
    """Run the compiled kernel on torch inputs; return the tuple the torch backend returns."""
    from .jets import _exponents_np

    B, K = z.shape
    uv_np = np.ascontiguousarray(uv.detach().cpu().numpy(), dtype=np.float64)
    z_np = np.ascontiguousarray(z.detach().cpu().numpy(), dtype=np.float64)
    valid_np = np.ascontiguousarray(valid.cpu().numpy())
    if w is None:
        w_np = np.ones((B, K))
    else:
        w_np = np.ascontiguousarray(w.detach().cpu().numpy(), dtype=np.float64)
    has_scale = s is not None
    s_np = (np.ascontiguousarray(s.cpu().numpy(), dtype=np.float64) if has_scale
            else np.ones(B))
    e = _exponents_np(order)
    ep = np.ascontiguousarray(e[:, 0])
    eq = np.ascontiguousarray(e[:, 1])
    M = len(e)
    coeffs = np.zeros((B, M))
    fitted = np.zeros(B, dtype=np.int64)
    status = np.zeros(B, dtype=np.int64)
    cond = np.zeros(B)
    resid = np.zeros(B)
    h = np.ones(B)
    count = np.zeros(B, dtype=np.int64)
    rank = np.zeros(B, dtype=np.int64)
    if B > 0:
        _fit_kernel(uv_np, z_np, w_np, valid_np, s_np, has_scale, order, bool(fallback),
                    float(max_cond), bool(refine), ep, eq, coeffs, fitted, status, cond, resid,
                    h, count, rank)
    out = [torch.from_numpy(a) for a in (coeffs, resid, rank, cond, h, status, fitted, count)]
    if not fallback:
        bad = np.nonzero(status != _OK)[0]
        if bad.size:
            # Minimum-norm solutions of the rare rank-deficient items, via the torch backend.
            from .jets import _fit_torch_top

            sub = _fit_torch_top(uv[bad], z[bad], None if w is None else w[bad], valid[bad],
                                 None if s is None else s[bad], order, False, max_cond, refine)
            bt = torch.from_numpy(bad)
            out[0][bt] = sub[0].detach()
            out[1][bt] = sub[1].detach()
    return tuple(out)
