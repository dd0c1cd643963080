"""The torch back end of :func:`polygeo.jets.fit` (package-private).

Weighted least squares of a batch of n-jets in preconditioned parameters: the normal system,
equilibration, its condition number and numerical rank, a Cholesky solve with a minimum-norm
(pseudo-inverse) fallback for rank-deficient items, and iterative refinement. Differentiable
(gradients flow through the solve); the numba back end (``_jets_numba``) computes the same
quantities without gradients. Kept apart from :mod:`polygeo.jets` (its only caller), whose
public basis functions it uses.
"""

from __future__ import annotations

import math

import torch

from ._jets_common import COLLINEAR_TOL
from ._jets_common import exponents_np as _exponents_np
from .status import Status

__all__ = ["fit_torch_top", "normal_system", "equilibrate", "numerical_rank"]


def _monomials(su: torch.Tensor, order: int) -> torch.Tensor:
    from .jets import monomials  # deferred: polygeo.jets imports this module

    return monomials(su, order)


_TINY = 1e-300


def _default_scale(uv: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    r2 = (uv.detach() ** 2).sum(-1).masked_fill(~valid, 0.0)  # (B, K)
    h = r2.amax(-1).sqrt() if r2.shape[-1] > 0 else r2.new_zeros(r2.shape[0])
    return torch.where(h > 0, h, torch.ones_like(h))


def _unscale_factors(h: torch.Tensor, order: int) -> torch.Tensor:
    deg = torch.from_numpy(_exponents_np(order).sum(1)).to(h.dtype)  # (M,)
    return h[:, None] ** (-deg)  # (B, M)


def fit_torch_top(uv, z, w, valid, s, order, fallback, max_cond, refine, interpolate=False):
    B, K = z.shape
    uv = uv.to(torch.float64)
    z = z.to(torch.float64)
    # Zero invalid samples (torch.where keeps gradients of valid ones NaN-free).
    uv = torch.where(valid[..., None], uv, torch.zeros_like(uv))
    z = torch.where(valid, z, torch.zeros_like(z))
    if w is None:
        w = valid.to(torch.float64)
    else:
        w = torch.where(valid, w, torch.zeros_like(w))
    h = _default_scale(uv, valid) if s is None else s
    su = uv / h[:, None, None]  # (B, K, 2) preconditioned parameters
    count = valid.sum(-1)
    cs, fitted, status, cond, rank = _fit_torch_scaled(su, z, w, count, order, fallback,
                                                       max_cond, refine, interpolate)
    # Weighted RMS residual of the final fit (in scaled parameters; heights are unchanged).
    A = _monomials(su, order)  # (B, K, M)
    r = z - torch.einsum("bkm,bm->bk", A, cs)
    sw = w.sum(-1)
    ms = (w * r * r).sum(-1) / torch.where(sw > 0, sw, torch.ones_like(sw))
    residual = torch.sqrt(ms.clamp_min(_TINY))
    residual = torch.where(ms > 0, residual, torch.zeros_like(residual))
    coeffs = cs * _unscale_factors(h, order)
    return coeffs, residual, rank, cond, h, status, fitted, count


def normal_system(su, z, w, order):
    A = _monomials(su, order)  # (B, K, M)
    Aw = A * w[..., None]
    N = Aw.transpose(1, 2) @ A  # (B, M, M)
    rhs = (Aw * z[..., None]).sum(1)  # (B, M)
    return A, Aw, N, rhs


def _collinear(su: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Whether each item's weighted parameter samples lie on a line: ``(B,)`` bool.

    See ``COLLINEAR_TOL``: no plane, hence no jet of order >= 1, is defined by them.
    """
    m0 = w.sum(-1)
    safe = torch.where(m0 > 0, m0, torch.ones_like(m0))
    mean = (w[..., None] * su).sum(1) / safe[:, None]  # (B, 2)
    d = su - mean[:, None, :]
    c = torch.einsum("bk,bki,bkj->bij", w, d, d) / safe[:, None, None]  # (B, 2, 2)
    tr = c[:, 0, 0] + c[:, 1, 1]
    det = c[:, 0, 0] * c[:, 1, 1] - c[:, 0, 1] * c[:, 1, 0]
    return ~(det > COLLINEAR_TOL * tr * tr) | ~(m0 > 0)


def equilibrate(N):
    d = torch.diagonal(N, dim1=-2, dim2=-1)
    D = torch.where(d > 0, d.clamp_min(_TINY).rsqrt(), torch.ones_like(d))  # (B, M)
    return D, N * D[:, :, None] * D[:, None, :]


@torch.no_grad()
def _condition(Ne: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Cholesky success mask and the bound ``sqrt(||Ne||_F) ||L^{-1}||_F`` of sqrt(cond(Ne))."""
    L, info = torch.linalg.cholesky_ex(Ne)
    ok = info == 0
    cond = torch.full(Ne.shape[:1], math.inf, dtype=Ne.dtype)
    if bool(ok.any()):
        Lk = L[ok]
        eye = torch.eye(Lk.shape[-1], dtype=Lk.dtype).expand_as(Lk)
        Linv = torch.linalg.solve_triangular(Lk, eye, upper=False)
        nf = (Ne[ok] ** 2).sum((-2, -1))
        lf = (Linv**2).sum((-2, -1))
        c = torch.sqrt(nf.sqrt() * lf)
        cond[ok] = torch.where(torch.isfinite(c), c, torch.full_like(c, math.inf))
    return ok, cond


@torch.no_grad()
def numerical_rank(Ne: torch.Tensor, max_cond: float) -> torch.Tensor:
    lam = torch.linalg.eigvalsh(Ne)  # ascending
    top = lam[:, -1:].clamp_min(_TINY)
    return (lam > top / (max_cond * max_cond)).sum(-1).to(torch.int64)


def _fit_torch_scaled(su, z, w, count, order, fallback, max_cond, refine, interpolate=False):
    """Recursive torch solver in preconditioned parameters; returns scaled coefficients."""
    B = z.shape[0]
    M = len(_exponents_np(order))
    coeffs = su.new_zeros(B, M)
    fitted = torch.full((B,), order, dtype=torch.int64)
    status = torch.full((B,), int(Status.OK), dtype=torch.int64)
    rank = torch.full((B,), M, dtype=torch.int64)
    cond = torch.full((B,), math.inf, dtype=torch.float64)
    if B == 0:
        return coeffs, fitted, status, cond, rank
    A, Aw, N, rhs = normal_system(su, z, w, order)
    D, Ne = equilibrate(N)
    enough = (count >= M) & ~_collinear(su.detach(), w.detach())
    ok = enough.clone()
    if bool(enough.all()):
        chol_ok, cond = _condition(Ne.detach())
        ok = chol_ok & (cond <= max_cond)
    elif bool(enough.any()):
        idx = enough.nonzero().squeeze(1)
        chol_ok, c = _condition(Ne[idx].detach())
        cond[idx] = c
        ok[idx] = chol_ok & (c <= max_cond)
    good = ok.nonzero().squeeze(1)
    bad = (~ok).nonzero().squeeze(1)
    if good.numel():
        every = good.numel() == B

        def sel(t):
            return t if every else t.index_select(0, good)

        Dg, Neg = sel(D), sel(Ne)
        L = torch.linalg.cholesky(Neg)
        x = Dg * torch.cholesky_solve((Dg * sel(rhs))[..., None], L)[..., 0]
        need = sel(cond) > refine
        if bool(need.any()):
            r = sel(z) - torch.einsum("bkm,bm->bk", sel(A), x)
            g = torch.einsum("bkm,bk->bm", sel(Aw), r)
            dx = Dg * torch.cholesky_solve((Dg * g)[..., None], L)[..., 0]
            x = torch.where(need[:, None], x + dx, x)
        if interpolate:
            # constrained to x0 = 0: x - G e0 x0 / G00 with G = N^-1 = D Ne^-1 D
            e0 = torch.zeros_like(x)
            e0[:, 0] = 1.0
            col = Dg * torch.cholesky_solve((Dg * e0)[..., None], L)[..., 0]
            x = x - col * (x[:, :1] / col[:, :1])
        coeffs = x if every else coeffs.index_copy(0, good, x)
    if bad.numel():
        rank = rank.index_copy(0, bad, numerical_rank(Ne[bad].detach(), max_cond))
        if fallback:
            if order > 1:
                sub = _fit_torch_scaled(su[bad], z[bad], w[bad], count[bad], order - 1, True,
                                        max_cond, refine, interpolate)
                xs, fo, st = sub[0], sub[1], sub[2]
                st = torch.where(st == int(Status.OK), int(Status.ORDER_REDUCED), st)
            else:
                wb, zb = w[bad], z[bad]
                sw = wb.sum(-1)
                mean = (wb * zb).sum(-1) / torch.where(sw > 0, sw, torch.ones_like(sw))
                xs = torch.zeros_like(mean)[:, None] if interpolate else mean[:, None]
                fo = torch.zeros(bad.numel(), dtype=torch.int64)
                st = torch.where(count[bad] < 3, int(Status.TOO_FEW_POINTS),
                                 int(Status.DEGENERATE))
            xs = torch.nn.functional.pad(xs, (0, M - xs.shape[1]))
            coeffs = coeffs.index_copy(0, bad, xs)
            fitted = fitted.index_copy(0, bad, fo)
            status = status.index_copy(0, bad, st)
        else:
            coeffs = coeffs.index_copy(0, bad, _min_norm(A[bad], w[bad], z[bad], max_cond))
            st = torch.where(count[bad] < M, int(Status.TOO_FEW_POINTS),
                             int(Status.ILL_CONDITIONED))
            status = status.index_copy(0, bad, st)
    return coeffs, fitted, status, cond, rank


def _min_norm(A, w, z, max_cond):
    """Minimum-norm weighted least-squares solution (column-equilibrated, SVD cut-off)."""
    sw = w.clamp_min(0).sqrt()
    As = A * sw[..., None]  # (b, K, M)
    cn = As.detach().norm(dim=1)  # (b, M)
    D = torch.where(cn > 0, 1.0 / cn.clamp_min(_TINY), torch.ones_like(cn))
    pinv = torch.linalg.pinv(As * D[:, None, :], rtol=1.0 / max_cond)  # (b, M, K)
    y = torch.einsum("bmk,bk->bm", pinv, z * sw)
    return D * y
