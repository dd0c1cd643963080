"""Preconditioners of the step problem: DCT-inverted linear models of its Hessian.

:func:`laplace_preconditioner` (inertia, in-plane stretch and plate bending per coordinate),
:func:`normal_preconditioner` (the out-of-plane part in an inextensible metric) and
:func:`normal_directions` (its descent directions, optionally cut into low and high DCT modes
by :func:`low_modes`); the DCT solves as products with cached DCT-II matrices.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .step_problem import StepProblem

__all__ = ["laplace_preconditioner", "normal_preconditioner", "low_modes", "normal_directions",
           "curvature_bound"]


def laplace_preconditioner(p: StepProblem, k_eff: float = 1.0):
    """``g -> H0^-1 g``, a linear model of the step's Hessian inverted by DCT.

    ``H0 = m dt^2 + dt^4 (k_eff k_s L + 1e-3 k_b h^2 L^2)`` with ``L`` the Neumann grid
    Laplacian (``O(HW log HW)``): the inertia, the in-plane stiffness of a sheet at rest and
    the plate bending stiffness, per coordinate. A fixed, resolution-aware metric; the
    classical optimisers and the FNO use it through :func:`solve_pgd` and
    :func:`draping.fnopt.model.fno_update`.
    """
    den = _dct_metric(p, k_eff * p.material["stretch"].double().numpy())

    def apply(g: torch.Tensor) -> torch.Tensor:
        z = _dct_solve(g.detach().double().numpy(), den)
        return torch.from_numpy(z).to(g.dtype)

    return apply


def _dct_metric(p: StepProblem, ks) -> np.ndarray:
    """``(B, H, W)``: ``m dt^2 + dt^4 (ks L + 1e-3 k_b h^2 L^2)`` on the DCT-II modes.

    ``L`` the Neumann grid Laplacian's eigenvalues (1/m^2), ``ks (B,)`` the stiffness charged
    to the Laplacian term (N/m; 0: inertia and bending only), per sheet.
    """
    _, h, w, _ = p.x_prev.shape
    hx = p.hx.double().numpy()[:, None, None]
    hy = p.hy.double().numpy()[:, None, None]
    rho = p.material["density"].double().numpy()[:, None, None]
    ks = np.broadcast_to(np.asarray(ks, dtype=np.float64), hx.shape[:1])[:, None, None]
    kb = 1e-3 * p.material["bend"].double().numpy()[:, None, None]
    lam_r = (2 - 2 * np.cos(np.pi * np.arange(h) / h))[None, :, None]
    lam_c = (2 - 2 * np.cos(np.pi * np.arange(w) / w))[None, None, :]
    dt2 = p.dt * p.dt
    lap = lam_r / (hy * hy) + lam_c / (hx * hx)          # 1/m^2
    return rho * hx * hy * dt2 + dt2 * dt2 * hx * hy * (ks * lap + kb * lap * lap)


def curvature_bound(p: StepProblem) -> torch.Tensor:
    """``(B,)``: a bound of the largest eigenvalue of the step's Hessian in the mass metric.

    ``max`` over the DCT modes of :func:`laplace_preconditioner`'s model ``H0`` (``k_eff = 1``)
    divided by the inertia term ``m dt^2`` (dimensionless; ``r = M^-1 g / dt^2`` changes by
    at most this times a change of ``a``). Measured against power iteration on the Hessian at
    the converged step from rest (corners, 8x8 - 100x100, stretch 300 and 1000 N/m): the
    largest eigenvalue is 0.51 - 0.72 of this bound, so a gradient-descent step ``1 / bound``
    is stable there (GD diverges above ``2 / lambda_max``: 1.2e-4 at 64x64, stretch 300).
    """
    den = _dct_metric(p, p.material["stretch"].double().numpy())       # (B, H, W)
    inertia = (p.material["density"].double() * p.hx.double() * p.hy.double()
               * p.dt * p.dt).numpy()
    return torch.from_numpy(den.reshape(den.shape[0], -1).max(1) / inertia)


def _dct_solve(z: np.ndarray, den: np.ndarray) -> np.ndarray:
    """``idct(dct(z) / den)`` over the grid axes 1, 2 (orthonormal DCT-II), float64.

    ``z`` ``(B, H, W)`` or ``(B, H, W, C)``, ``den`` ``(B, H, W)``. The transforms as products
    with the cached ``H x H`` and ``W x W`` DCT-II matrices (:func:`_dct_matrix`): the FFT-based
    ``scipy.fft.dctn`` / ``idctn`` result up to float64 rounding, 2x / 1.5x faster on one
    sheet at 32x32 / 64x64 (the FFTs' per-call set-up dominated there).
    """
    ah, aw = _dct_matrix(z.shape[1]), _dct_matrix(z.shape[2])
    if z.ndim == 3:
        return ah.T @ ((ah @ z @ aw.T) / den) @ aw
    zc = np.moveaxis(z, 3, 1)                                     # (B, C, H, W) view
    out = ah.T @ ((ah @ zc @ aw.T) / den[:, None]) @ aw
    return np.ascontiguousarray(np.moveaxis(out, 1, 3))


_DCT_MATRIX: dict = {}


def _dct_matrix(n: int) -> np.ndarray:
    """The orthonormal DCT-II matrix ``(n, n)`` (float64, cached; rows: frequencies)."""
    if n not in _DCT_MATRIX:
        _DCT_MATRIX[n] = _dct_rows(n, n).numpy()
    return _DCT_MATRIX[n]


def normal_preconditioner(p: StepProblem):
    """``g -> n (D_n^-1 (n . g))``: the out-of-plane part of ``g`` in an inextensible metric.

    ``n``: unit normals ``(B, H, W, 3)`` of the predicted positions ``x_prev + dt v_prev``
    (central differences, one-sided at the border); ``D_n = m dt^2 + dt^4 1e-3 k_b h^2 L^2``
    (inertia and plate bending, no stretch; ``L`` the Neumann grid Laplacian, inverted by DCT).

    Why: :func:`laplace_preconditioner` charges every coordinate the in-plane stretch stiffness
    ``k_s``, but a sheet moves out of its plane at the cost of bending and its small tension
    only, so for the out-of-plane modes of wavelength 1/3 .. 1/8 of the sheet it is ~100x too
    stiff and 10 conjugate-gradient steps leave about half of a folding step undone (measured
    on the diagonal layout at 64x64: the step error is 84-93 % out-of-plane, 84-96 % in the
    8 x 8 lowest DCT modes, < 6 % a rotation about the handles' axis). Added as one more
    direction of the subspace step, the step's own quadratic model weighs it.
    """
    y = (p.x_prev + p.dt * p.v_prev).detach().double()
    xu = torch.cat([y[:, :, 1:2] - y[:, :, :1], y[:, :, 2:] - y[:, :, :-2],
                    y[:, :, -1:] - y[:, :, -2:-1]], 2)
    xv = torch.cat([y[:, 1:2] - y[:, :1], y[:, 2:] - y[:, :-2], y[:, -1:] - y[:, -2:-1]], 1)
    n = torch.cross(xu, xv, dim=-1)
    n = n / n.norm(dim=-1, keepdim=True).clamp(min=1e-300)
    den = _dct_metric(p, 0.0)

    def apply(g: torch.Tensor) -> torch.Tensor:
        z = _dct_solve((g.detach().double() * n).sum(-1).numpy(), den)
        return (n * torch.from_numpy(z)[..., None]).to(g.dtype)

    return apply


def low_modes(z: torch.Tensor, cut: int) -> torch.Tensor:
    """The part of a field ``(B, H, W, C)`` in its lowest ``cut x cut`` DCT-II modes.

    ``A_H^T A_H z A_W^T A_W`` with ``A_n`` the first ``cut`` rows of the orthonormal DCT-II
    matrix (cached per size; float64): the full transforms' result up to rounding, without
    transforming the ``n - cut`` modes that are dropped.
    """
    _, h, w, _ = z.shape
    ah, aw = _dct_rows(h, cut), _dct_rows(w, cut)
    zc = z.detach().double().permute(0, 3, 1, 2)                 # (B, C, H, W)
    low = ah.T @ ((ah @ zc) @ aw.T) @ aw
    return low.permute(0, 2, 3, 1).to(z.dtype).contiguous()


_DCT_ROWS: dict = {}


def _dct_rows(n: int, cut: int) -> torch.Tensor:
    """The first ``min(cut, n)`` rows ``(cut, n)`` of the orthonormal DCT-II matrix, float64."""
    k = min(cut, n)
    if (n, k) not in _DCT_ROWS:
        with torch.inference_mode(False):         # a normal tensor, also when built in one
            i = torch.arange(k, dtype=torch.float64)[:, None]
            j = torch.arange(n, dtype=torch.float64)[None]
            a = torch.cos(math.pi * i * (2 * j + 1) / (2 * n)) * math.sqrt(2.0 / n)
            a[0] /= math.sqrt(2.0)
        _DCT_ROWS[(n, k)] = a
    return _DCT_ROWS[(n, k)]


def normal_directions(p: StepProblem, g: torch.Tensor, pn, split: int = 0) -> list:
    """Descent directions from the out-of-plane preconditioned gradient ``pn(g)``.

    ``split = 0``: ``[-pn(g)]``; ``split > 0``: its lowest ``split x split`` DCT modes and
    the rest as two directions (a coarse-level part the subspace step scales on its own).
    """
    zn = pn(g)
    if split <= 0:
        return [-zn * p.free3]
    lo = low_modes(zn, split)
    return [-lo * p.free3, -(zn - lo) * p.free3]

