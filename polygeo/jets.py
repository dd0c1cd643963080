"""n-jets: the monomial basis, batched weighted least-squares fitting and evaluation.

An n-jet is the bivariate polynomial height function of a surface over a local frame,

::

    z(u, v) = sum_{i=0..n} sum_{j=0..i} a_{i-j,j} u^{i-j} v^j,

with its ``M = (n+1)(n+2)/2`` coefficients stored in that order (for ``n = 2``:
``[1, u, v, u^2, uv, v^2]``). This module is the one home of the monomial basis and its
derivatives (DESIGN.md).

Fitting follows Cazals & Pouget (2005, "Estimating differential quantities using polynomial
fitting of osculating jets"): the parameters are divided by a per-item scale ``h`` (by default
the largest distance of a valid point from the origin of the ``uv`` plane) so that the
preconditioned points lie in the unit disc, the weighted least-squares problem is solved there
and the coefficients are unscaled (``a_pq /= h**(p+q)``). The solver forms the normal equations
from the weighted moments, equilibrates them (unit diagonal), factors them by Cholesky, estimates
the condition number, and applies one step of iterative refinement with the true residual to
the items whose condition number calls for it (accuracy close to a QR solve at a fraction of its
cost). Items whose system is singular or too ill-conditioned for the requested order are
answered with the highest lower order that is well posed (``fallback=True``) or with the
minimum-norm solution (``fallback=False``), and flagged through :class:`polygeo.status.Status`;
no item ever returns NaN.

Two interchangeable backends compute the same thing: a pure-torch one (differentiable end to end
with respect to ``uv``, ``z`` and ``weights``) and a compiled numba one (used when no gradient is
needed; tens of times faster for large batches, multi-threaded with numba's thread count; the
first call compiles it, later processes load it from numba's on-disk cache).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import numpy as np
import torch

from ._jets_common import exponents_np as _exponents_np
from ._jets_torch import equilibrate, fit_torch_top, normal_system, numerical_rank
from .checks import as_tensor, check_choice, check_int, check_mask, check_positive, check_shape
from .status import Status
from .types import ArrayLike

__all__ = [
    "MAX_ORDER",
    "JetFit",
    "n_coeffs",
    "order_from_ncoeffs",
    "exponents",
    "as_coeffs",
    "monomials",
    "monomial_derivatives",
    "fit",
    "evaluate",
    "derivatives",
]

#: Highest jet order accepted by :func:`fit`.
MAX_ORDER = 6
# Highest order of the monomial basis helpers (moments of a 6-jet need degree 12).
_MAX_BASIS_ORDER = 2 * MAX_ORDER
# Default largest accepted condition number of the preconditioned, equilibrated design matrix.
_DEFAULT_MAX_COND = 1e6


# --------------------------------------------------------------------------------------------
# Monomial basis
# --------------------------------------------------------------------------------------------


def n_coeffs(order: int) -> int:
    """Number of coefficients ``(n+1)(n+2)/2`` of an n-jet.

    Parameters
    ----------
    order : int
        Jet order ``n >= 0``.

    Returns
    -------
    int

    Raises
    ------
    TypeError
        If ``order`` is not an integer.
    ValueError
        If ``order`` is negative.
    """
    n = check_int(order, "order", low=0)
    return (n + 1) * (n + 2) // 2


def order_from_ncoeffs(m: int) -> int:
    """Inverse of :func:`n_coeffs`.

    Parameters
    ----------
    m : int
        Number of coefficients.

    Returns
    -------
    int
        The order ``n`` with ``n_coeffs(n) == m``.

    Raises
    ------
    ValueError
        If ``m`` is not a triangular number ``(n+1)(n+2)/2``.
    """
    m = check_int(m, "m", low=1)
    n = int(round((math.sqrt(8 * m + 1) - 3) / 2))
    if n < 0 or (n + 1) * (n + 2) // 2 != m:
        raise ValueError(
            f"m: expected a triangular number (n+1)(n+2)/2 of coefficients (1, 3, 6, 10, 15, ...), "
            f"got {m}"
        )
    return n


def _check_basis_order(order: int, name: str = "order") -> int:
    return check_int(order, name, low=0, high=_MAX_BASIS_ORDER)


def exponents(order: int) -> torch.Tensor:
    """Exponents ``(p, q)`` of the monomials ``u^p v^q`` of an n-jet, in storage order.

    Parameters
    ----------
    order : int
        Jet order ``n`` in ``[0, 12]``.

    Returns
    -------
    torch.Tensor
        ``(M, 2)`` int64, ``M = n_coeffs(order)``.

    Raises
    ------
    TypeError, ValueError
        If ``order`` is not an integer in range.
    """
    return torch.from_numpy(_exponents_np(_check_basis_order(order)).copy())


def _powers(x: torch.Tensor, n: int) -> torch.Tensor:
    """(..., n+1) stack of x**0 .. x**n by repeated products (exact, differentiable)."""
    out = [torch.ones_like(x)]
    for _ in range(n):
        out.append(out[-1] * x)
    return torch.stack(out, dim=-1)


def _as_uv(uv, name: str = "uv") -> torch.Tensor:
    t = as_tensor(uv, name)
    check_shape(t, name, ("...", 2))
    return t


def monomials(uv, order: int) -> torch.Tensor:
    """Monomials ``u^p v^q`` of an n-jet at the given parameters.

    Parameters
    ----------
    uv : array_like or torch.Tensor
        ``(..., 2)`` floating parameters ``(u, v)`` (length units of the jet's frame).
    order : int
        Jet order ``n`` in ``[0, 12]``.

    Returns
    -------
    torch.Tensor
        ``(..., M)`` in the storage order of :func:`exponents`, same dtype as ``uv``.

    Raises
    ------
    ValueError
        If ``uv``'s last dimension is not 2 or ``order`` is out of range.
    TypeError
        If ``uv`` is not real floating-point convertible or ``order`` is not an integer.
    """
    order = _check_basis_order(order)
    t = _as_uv(uv)
    u, v = t[..., 0:1], t[..., 1:2]
    # degree-i block [u^i, u^(i-1) v, ..., v^i] = [u * (degree i-1 block), v * v^(i-1)]
    last = torch.ones_like(u)
    blocks = [last]
    for _ in range(order):
        last = torch.cat([last * u, last[..., -1:] * v], dim=-1)
        blocks.append(last)
    return torch.cat(blocks, dim=-1)


@cache
def _derivative_table(order: int, du: int, dv: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Factors and shifted exponents of d^(du+dv)/du^du dv^dv of each monomial."""
    e = _exponents_np(order)
    p, q = e[:, 0], e[:, 1]
    fac = np.ones(len(e), dtype=np.float64)
    for k in range(du):
        fac *= np.maximum(p - k, 0)
    for k in range(dv):
        fac *= np.maximum(q - k, 0)
    return fac, np.maximum(p - du, 0), np.maximum(q - dv, 0)


def monomial_derivatives(uv, order: int, du: int = 0, dv: int = 0) -> torch.Tensor:
    """Partial derivatives ``d^(du+dv) / du^du dv^dv`` of each monomial of an n-jet.

    Closed form with falling factorials: ``d^a/du^a u^p = p!/(p-a)! u^(p-a)`` (zero when
    ``a > p``).

    Parameters
    ----------
    uv : array_like or torch.Tensor
        ``(..., 2)`` floating parameters.
    order : int
        Jet order ``n`` in ``[0, 12]``.
    du, dv : int
        Derivative orders (>= 0) in ``u`` and ``v``.

    Returns
    -------
    torch.Tensor
        ``(..., M)``, same dtype as ``uv``.

    Raises
    ------
    ValueError, TypeError
        On bad ``uv`` shape/type or negative / non-integer derivative orders.
    """
    order = _check_basis_order(order)
    du = check_int(du, "du", low=0)
    dv = check_int(dv, "dv", low=0)
    t = _as_uv(uv)
    e = _exponents_np(order)
    if du + dv > order:
        return t.new_zeros(t.shape[:-1] + (len(e),))
    fac, sp, sq = _derivative_table(order, du, dv)
    pu = _powers(t[..., 0], order)
    pv = _powers(t[..., 1], order)
    base = pu.index_select(-1, torch.from_numpy(sp)) * pv.index_select(-1, torch.from_numpy(sq))
    return base * torch.from_numpy(fac).to(t.dtype)


# --------------------------------------------------------------------------------------------
# Evaluation
# --------------------------------------------------------------------------------------------


def as_coeffs(coeffs: ArrayLike, name: str = "coeffs") -> tuple[torch.Tensor, int]:
    """Check a batch of jet coefficients and read off the jet order.

    Parameters
    ----------
    coeffs : array_like or torch.Tensor, shape (B, M), floating
        Coefficients in the storage order of DESIGN.md §4, ``M = (n+1)(n+2)/2``.
    name : str
        Argument name used in error messages.

    Returns
    -------
    coeffs : torch.Tensor, shape (B, M)
        The coefficients as a floating tensor (see :func:`polygeo.checks.as_tensor`).
    order : int
        The jet order ``n`` (at most 12).

    Raises
    ------
    ValueError
        If ``coeffs`` is not 2-D, ``M`` is not a triangular number or ``n > 12``.
    TypeError
        On non-numeric input.
    """
    c = as_tensor(coeffs, name)
    check_shape(c, name, ("B", "M"))
    m = c.shape[1]
    n = int(round((math.sqrt(8 * m + 1) - 3) / 2))
    if m < 1 or (n + 1) * (n + 2) // 2 != m:
        raise ValueError(f"{name}: expected shape (B, M) with M = (n+1)(n+2)/2 (1, 3, 6, 10, "
                         f"15, ...), got {tuple(c.shape)}")
    if n > _MAX_BASIS_ORDER:
        raise ValueError(f"{name}: expected a jet order <= {_MAX_BASIS_ORDER}, got {n}")
    return c, n


def _as_eval_uv(uv, batch: int, name: str = "uv") -> torch.Tensor:
    t = as_tensor(uv, name)
    check_shape(t, name, ("B", "P", 2))
    if t.shape[0] != batch:
        raise ValueError(f"{name}: expected shape ({batch}, P, 2) matching coeffs, got "
                         f"{tuple(t.shape)}")
    return t


def evaluate(coeffs, uv, du: int = 0, dv: int = 0):
    """Height ``z(u, v)`` of jets, or one of its partial derivatives, at given parameters.

    Parameters
    ----------
    coeffs : array_like or torch.Tensor
        ``(B, M)`` jet coefficients (storage order of :func:`exponents`).
    uv : array_like or torch.Tensor
        ``(B, P, 2)`` parameters at which to evaluate each jet.
    du, dv : int
        Derivative orders; ``(0, 0)`` evaluates the height.

    Returns
    -------
    torch.Tensor or numpy.ndarray
        ``(B, P)`` in the promoted dtype; NumPy when ``coeffs`` is NumPy.

    Raises
    ------
    ValueError
        If ``M`` is not triangular or the batch sizes differ.
    TypeError
        On non-numeric input.
    """
    numpy_in = not isinstance(coeffs, torch.Tensor)
    c, order = as_coeffs(coeffs)
    t = _as_eval_uv(uv, c.shape[0])
    dtype = torch.promote_types(c.dtype, t.dtype)
    c, t = c.to(dtype), t.to(dtype)
    basis = monomial_derivatives(t, order, du, dv)  # (B, P, M)
    out = torch.einsum("bpm,bm->bp", basis, c)
    return out.detach().cpu().numpy() if numpy_in else out


def derivatives(coeffs, uv, max_order: int = 2) -> dict:
    """All partial derivatives of jets up to a total order, computed together.

    Parameters
    ----------
    coeffs : array_like or torch.Tensor
        ``(B, M)`` jet coefficients.
    uv : array_like or torch.Tensor
        ``(B, P, 2)`` parameters.
    max_order : int
        Highest total derivative order ``du + dv`` (0..12).

    Returns
    -------
    dict
        ``{(du, dv): (B, P)}`` for every ``du + dv <= max_order`` (``(0, 0)`` is the height).
        Derivatives above the jet's order are zero. NumPy arrays when ``coeffs`` is NumPy.

    Raises
    ------
    ValueError, TypeError
        On bad shapes, types or ``max_order``.
    """
    numpy_in = not isinstance(coeffs, torch.Tensor)
    max_order = _check_basis_order(max_order, "max_order")
    c, order = as_coeffs(coeffs)
    t = _as_eval_uv(uv, c.shape[0])
    dtype = torch.promote_types(c.dtype, t.dtype)
    c, t = c.to(dtype), t.to(dtype)
    pu = _powers(t[..., 0], order)  # (B, P, n+1)
    pv = _powers(t[..., 1], order)
    out = {}
    for d in range(max_order + 1):
        for dv in range(d + 1):
            du = d - dv
            if d > order:
                out[(du, dv)] = t.new_zeros(t.shape[:-1])
                continue
            fac, sp, sq = _derivative_table(order, du, dv)
            keep = np.nonzero(fac)[0]
            w = c[:, torch.from_numpy(keep)] * torch.from_numpy(fac[keep]).to(dtype)  # (B, m)
            basis = pu[..., torch.from_numpy(sp[keep])] * pv[..., torch.from_numpy(sq[keep])]
            out[(du, dv)] = torch.einsum("bpm,bm->bp", basis, w)
    if numpy_in:
        out = {k: v.detach().cpu().numpy() for k, v in out.items()}
    return out


# --------------------------------------------------------------------------------------------
# Fitting
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class JetFit:
    """Result of :func:`fit` (all tensors share the batch dimension ``B``).

    Attributes
    ----------
    coeffs : torch.Tensor
        ``(B, M)`` jet coefficients in the caller's (unscaled) units, ``M = n_coeffs(order)``;
        items fitted at a lower order carry zeros in the higher-order slots.
    residual : torch.Tensor
        ``(B,)`` weighted RMS of the height residual ``sqrt(sum w r^2 / sum w)`` (units of z).
    rank : torch.Tensor
        ``(B,)`` int64 numerical rank of the requested-order design matrix (``M`` when well
        posed; an eigenvalue count of the equilibrated normal matrix otherwise).
    cond : torch.Tensor
        ``(B,)`` condition number estimate of the preconditioned, equilibrated weighted design
        matrix ``A`` of the requested order: ``sqrt(||N||_F) ||L^{-1}||_F`` with ``N = A^T W A``
        (unit diagonal) and ``L`` its Cholesky factor, an upper bound of ``cond_2(A)`` that
        exceeds it by at most a factor ``sqrt(M)``; ``inf`` where that system is singular or has
        fewer points than coefficients.
    scale : torch.Tensor
        ``(B,)`` preconditioning scale ``h`` used (length units; 1 where no point was valid).
    status : torch.Tensor
        ``(B,)`` int64 :class:`polygeo.status.Status` codes.
    fitted_order : torch.Tensor
        ``(B,)`` int64 order actually fitted (``order`` unless reduced; 0 means only the mean
        height could be fitted).
    n_points : torch.Tensor
        ``(B,)`` int64 number of valid points (finite, unmasked, positive weight).
    order : int
        The requested order.
    """

    coeffs: torch.Tensor
    residual: torch.Tensor
    rank: torch.Tensor
    cond: torch.Tensor
    scale: torch.Tensor
    status: torch.Tensor
    fitted_order: torch.Tensor
    n_points: torch.Tensor
    order: int

    def __len__(self) -> int:
        return int(self.coeffs.shape[0])


def _valid_mask(uv: torch.Tensor, z: torch.Tensor, w: torch.Tensor | None,
                mask: torch.Tensor | None) -> torch.Tensor:
    """(B, K) bool: finite sample, inside the caller's mask, positive weight."""
    valid = torch.isfinite(uv.detach()).all(-1) & torch.isfinite(z.detach())
    if mask is not None:
        valid = valid & mask
    if w is not None:
        valid = valid & (w.detach() > 0)
    return valid


def _prepare_fit_inputs(uv, z, order, weights, mask, scale, max_cond, refine_above):
    order = check_int(order, "order", low=1, high=MAX_ORDER)
    max_cond = check_positive(max_cond, "max_cond")
    if isinstance(refine_above, bool) or not isinstance(refine_above, (int, float)):
        raise TypeError(f"refine_above: expected a real number, got {refine_above!r}")
    if not refine_above >= 0:
        raise ValueError(f"refine_above: expected a value >= 0 (inf allowed), got {refine_above}")
    refine_above = float(refine_above)
    uv_t = as_tensor(uv, "uv")
    z_t = as_tensor(z, "z")
    check_shape(uv_t, "uv", ("B", "K", 2))
    check_shape(z_t, "z", ("B", "K"))
    if tuple(z_t.shape) != tuple(uv_t.shape[:2]):
        raise ValueError(f"z: expected shape {tuple(uv_t.shape[:2])} matching uv, got "
                         f"{tuple(z_t.shape)}")
    B, K = z_t.shape
    out_dtype = torch.promote_types(uv_t.dtype, z_t.dtype)
    if out_dtype not in (torch.float32, torch.float64):
        out_dtype = torch.float32
    m = None
    if mask is not None:
        m = check_mask(mask, "mask", (B, K))
    w = None
    if weights is not None:
        w = as_tensor(weights, "weights")
        check_shape(w, "weights", (B, K))
        wd = w.detach()
        # weights of masked-out or non-finite samples are ignored
        used = torch.isfinite(uv_t.detach()).all(-1) & torch.isfinite(z_t.detach())
        if m is not None:
            used = used & m
        bad = (~torch.isfinite(wd) | (wd < 0)) & used
        if bool(bad.any()):
            raise ValueError(f"weights: expected finite values >= 0, got {int(bad.sum())} "
                             f"negative or non-finite entries")
        w = w.to(torch.float64)
    s = None
    if scale is not None:
        s = as_tensor(scale, "scale").detach()
        check_shape(s, "scale", (B,))
        if not bool((torch.isfinite(s) & (s > 0)).all()):
            raise ValueError("scale: expected finite values > 0 for every item")
        s = s.to(torch.float64)
    return order, max_cond, refine_above, uv_t, z_t, w, m, s, out_dtype


def fit(
    uv,
    z,
    order: int,
    *,
    weights=None,
    mask=None,
    scale=None,
    fallback: bool = True,
    max_cond: float = _DEFAULT_MAX_COND,
    refine_above: float = 100.0,
    backend: str = "auto",
    interpolate: bool = False,
) -> JetFit:
    """Fit n-jets to batches of height samples by weighted least squares.

    Parameters
    ----------
    uv : array_like or torch.Tensor
        ``(B, K, 2)`` parameters of the samples in each item's local frame (length units).
        Points with a non-finite ``u``, ``v`` or ``z`` are treated as masked out (never an
        error): the caller's query point handling decides what a NaN point means.
    z : array_like or torch.Tensor
        ``(B, K)`` heights (length units).
    order : int
        Requested jet order ``n`` in ``[1, 6]``.
    weights : array_like or torch.Tensor, optional
        ``(B, K)`` non-negative finite weights (zero weight = masked out). Default: all 1.
    mask : array_like or torch.Tensor, optional
        ``(B, K)`` bool, True for valid samples (padding of variable-size neighbourhoods).
    scale : array_like or torch.Tensor, optional
        ``(B,)`` positive preconditioning scale ``h``; default: the largest ``|uv|`` of each
        item's valid samples (1 if there is none or all sit at the origin). The coefficients
        do not depend on ``h`` mathematically; it only conditions the solve.
    fallback : bool
        When True (default) an item that is singular or too ill-conditioned for ``order``
        is fitted at the highest lower order that is well posed (status ``ORDER_REDUCED``;
        ``DEGENERATE`` / ``TOO_FEW_POINTS`` when even order 1 is impossible, the coefficients
        then hold the weighted mean height only). When False such an item gets the minimum-norm
        least-squares solution of the requested order (status ``TOO_FEW_POINTS`` or
        ``ILL_CONDITIONED``).
    max_cond : float
        Largest accepted condition number of the preconditioned equilibrated design matrix
        (default 1e6); above it an item counts as rank deficient.
    refine_above : float
        Items whose condition number (see ``JetFit.cond``) exceeds this get one step of
        iterative refinement with the true residual (default 100: below it the normal equations
        already give about 1e-12 relative accuracy in float64); 0 refines every item, ``inf``
        none.
    backend : {"auto", "torch", "numba"}
        "torch" is differentiable; "numba" is fast and not differentiable; "auto" uses torch
        when a gradient is required (grad mode on and an input requires grad), else numba.
    interpolate : bool
        When True the jet is constrained to pass through the origin ``(u, v, z) = 0``
        (constant coefficient fixed to 0: Cazals & Pouget's interpolation variant, for
        samples expressed relative to a point that lies on the surface). The solution is the
        equality-constrained least-squares one, obtained from the unconstrained solve as
        ``x - G e0 x0 / G00`` with ``G`` the inverse normal matrix (same conditioning tests
        and fallbacks; an order-0 fallback then gives the zero jet). On exact samples this
        reduces the order-``n`` truncation bias (for an order-2 fit on a sphere it removes a
        quarter of the bias of the curvature); on noisy samples it passes the jet through the
        noise of the origin sample and roughly doubles the curvature error. Items solved by the
        minimum-norm path (``fallback=False`` and rank deficient) are not constrained.

    Returns
    -------
    JetFit
        Tensors (``coeffs`` and ``residual`` in float32 if both ``uv`` and ``z`` are float32,
        else float64; computations run in float64). NumPy inputs give torch outputs too.

    Raises
    ------
    ValueError
        On bad shapes, ``order`` out of ``[1, 6]``, negative or non-finite weights,
        non-positive scales.
    TypeError
        On non-numeric input, a non-bool mask or a non-integer order.

    Notes
    -----
    Items with fewer valid points than coefficients are never solved at the requested order.
    ``B = 0`` and ``K = 0`` are answered (empty results; every item ``TOO_FEW_POINTS``).
    """
    check_choice(backend, "backend", ("auto", "torch", "numba"))
    if not isinstance(interpolate, (bool, np.bool_)):
        raise TypeError(f"interpolate: expected a bool, got {interpolate!r}")
    order, max_cond, refine_above, uv_t, z_t, w, m, s, out_dtype = _prepare_fit_inputs(
        uv, z, order, weights, mask, scale, max_cond, refine_above
    )
    if backend == "auto":
        needs_grad = torch.is_grad_enabled() and (
            uv_t.requires_grad or z_t.requires_grad or (w is not None and w.requires_grad)
        )
        backend = "torch" if needs_grad else "numba"
    if backend == "numba":
        from ._jets_numba import fit_numba

        res = fit_numba(uv_t, z_t, w, m, s, order, fallback, max_cond, refine_above,
                        interpolate=bool(interpolate))
        res = _complete_numba_fit(res, uv_t, z_t, w, m, s, order, fallback, max_cond,
                                  refine_above)
    else:
        valid = _valid_mask(uv_t, z_t, w, m)
        res = fit_torch_top(uv_t, z_t, w, valid, s, order, fallback, max_cond, refine_above,
                             interpolate=bool(interpolate))
    coeffs, residual, rank, cond, h, status, fitted, count = res
    return JetFit(
        coeffs=coeffs.to(out_dtype),
        residual=residual.to(out_dtype),
        rank=rank,
        cond=cond.to(torch.float64),
        scale=h,
        status=status,
        fitted_order=fitted,
        n_points=count,
        order=order,
    )


def _complete_numba_fit(res, uv, z, w, mask, s, order, fallback, max_cond, refine_above):
    """Fill in what the compiled kernel leaves to the torch backend (rare items).

    The numerical rank of the items not solved at full rank (``rank == -1``) and, with
    ``fallback=False``, the minimum-norm solutions of the items whose status is not OK.
    """
    out = list(res)
    rank, status = out[2], out[5]
    flagged = torch.nonzero(rank < 0)[:, 0]
    if flagged.numel():
        # numerical rank of the (rare) rank-deficient items, as the torch backend computes it
        bt = flagged
        uvb, zb = uv[bt].detach().to(torch.float64), z[bt].detach().to(torch.float64)
        wb = None if w is None else w[bt].detach()
        vb = _valid_mask(uvb, zb, wb, None if mask is None else mask[bt])
        uvb = torch.where(vb[..., None], uvb, torch.zeros_like(uvb))
        zb = torch.where(vb, zb, torch.zeros_like(zb))
        wb = vb.to(torch.float64) if wb is None else torch.where(vb, wb, torch.zeros_like(wb))
        su = uvb / out[4][bt][:, None, None]
        Ne = equilibrate(normal_system(su, zb, wb, order)[2])[1]
        out[2][bt] = numerical_rank(Ne, max_cond)
    if not fallback:
        bad = torch.nonzero(status != int(Status.OK))[:, 0]
        if bad.numel():
            # Minimum-norm solutions of the rare rank-deficient items, via the torch backend.
            bt = bad
            wb = None if w is None else w[bt]
            vb = _valid_mask(uv[bt], z[bt], wb, None if mask is None else mask[bt])
            sub = fit_torch_top(uv[bt], z[bt], wb, vb, None if s is None else s[bt], order,
                                 False, max_cond, refine_above)
            out[0][bt] = sub[0].detach()
            out[1][bt] = sub[1].detach()
    return tuple(out)
