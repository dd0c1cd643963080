"""A two-level control: the step's own Hessian on a coarse grid (Galerkin coarse space).

The DCT preconditioners (:mod:`~draping.fnopt.preconditioners`) model the step's Hessian by a
fixed constant-coefficient metric; where the sheet's actual low-mode stiffness differs (tension,
pins, folds, stiff bending) a few subspace iterations clear those slow modes slowly. This module
builds the Galerkin operator ``A_c = P^T H P`` of the step's Hessian ``H`` (at ``a = 0``) on the
bilinear hat functions ``P`` of a coarse grid whose longer side has ``K`` vertices
(:func:`draping.fnopt.coarse.coarse_shape`), zeroed at the sheet's handles, and its coarse
correction ``g -> P A_c^-1 P^T g`` (:func:`coarse_correction`), which
:func:`draping.fnopt.classical.solve_pcg` adds as one more direction of its subspace step
(``coarse=K``).

``A_c`` is assembled from ``s x s x 3`` Hessian products in one batched pass (colour probing:
the sum of the hat functions whose coarse indices agree modulo ``s`` along both axes, one
coordinate at a time), exact because the Hessian couples fine vertices at most two apart and
two hat functions of one colour are far enough apart that no third one sees both through
``H`` (:func:`probe_spacing`). It is banded (vertex-major ordering) and factored once per step
(banded Cholesky in float64, Jacobi scaled; a diagonal shift where the Hessian is indefinite,
:func:`_factor`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import torch

from polygeo.checks import check_int

from .coarse import coarse_shape, interpolation_matrix
from .step_problem import StepProblem

__all__ = ["CoarseSpace", "probe_spacing", "galerkin_space", "kept_space", "coarse_correction"]

#: How many fine vertices apart the step's Hessian couples two vertices (bending's stencil).
HESSIAN_REACH = 2


def probe_spacing(fine: int, coarse: int, reach: int = HESSIAN_REACH) -> int:
    """The colour count ``s`` along an axis for exact probing of ``P^T H P``.

    A hat function of coarse spacing ``h = (fine - 1) / (coarse - 1)`` fine cells is non-zero
    within ``h`` of its vertex, ``H`` times it within ``h + reach``; two hat functions ``j``
    coarse vertices apart therefore interact through ``H`` iff ``j h < 2 h + reach``. Same-colour
    hats ``s`` apart must not both interact with a third one: ``s = 2 r + 1`` with ``r`` the
    largest such ``j`` (at most ``coarse``: then every hat its own colour).
    """
    coarse = min(coarse, fine)
    if coarse < 2:
        return 1
    h = (fine - 1) / (coarse - 1)
    r = math.ceil(2 + reach / h) - 1
    return min(2 * r + 1, coarse)


@dataclass(frozen=True)
class CoarseSpace:
    """One step's coarse space: transfer matrices and the factored Galerkin operator.

    Attributes
    ----------
    ph, pw : torch.Tensor
        Prolongation ``(H, Hc)``, ``(W, Wc)`` (bilinear hat functions), float64.
    free : torch.Tensor
        ``(B or 1, H, W, 1)`` the fine free mask (the hats are zeroed at handles), float64.
    bands : list
        Per sheet, the lower banded Cholesky factor ``(u + 1, n)`` (LAPACK's ``pbtrf`` layout)
        of the Jacobi-scaled, shifted ``A_c``; ``n = 3 Hc Wc`` unknowns ordered
        ``(i, j, coordinate)``, ``u`` the bandwidth; float64 numpy arrays.
    scale : torch.Tensor
        ``(B, n)`` the Jacobi scaling (``A_c ~ D^-1 L L^T D^-1``, ``D = diag(scale)``).
    """

    ph: torch.Tensor
    pw: torch.Tensor
    free: torch.Tensor
    bands: list
    scale: torch.Tensor


def _hats(n_fine: int, n_coarse: int) -> torch.Tensor:
    """``(n_fine, n_coarse)`` bilinear hat functions (float64; the identity if no coarser)."""
    return interpolation_matrix(n_coarse, n_fine, torch.float64)


_BAND_INDEX: dict = {}


def _band_index(hc: int, wc: int, sh: int, sw: int) -> tuple:
    """Where the lower band of ``A_c`` comes from in the restricted probes, cached per shape.

    Returns ``(src, row, col, u)``: for every entry ``(row >= col)`` of ``A_c`` that the
    Hessian can make non-zero (coarse vertices at most ``sh // 2``, ``sw // 2`` apart), its
    flat index ``src`` in the restricted probes ``(sh, sw, 3, Hc, Wc, 3)`` (one sheet), and
    the bandwidth ``u`` of the ``(i, j, coordinate)`` ordering.
    """
    key = (hc, wc, sh, sw)
    if key not in _BAND_INDEX:
        ri, rj = sh // 2, sw // 2
        i, j, c, di, dj, c2 = np.meshgrid(np.arange(hc), np.arange(wc), np.arange(3),
                                          np.arange(-ri, ri + 1), np.arange(-rj, rj + 1),
                                          np.arange(3), indexing="ij")
        i2, j2 = i + di, j + dj
        ok = (i2 >= 0) & (i2 < hc) & (j2 >= 0) & (j2 < wc)
        col = ((i * wc + j) * 3 + c)[ok]
        row = ((i2 * wc + j2) * 3 + c2)[ok]
        src = (((((i % sh) * sw + j % sw) * 3 + c) * hc + i2) * wc + j2)[ok] * 3 + c2[ok]
        low = row >= col
        u = (ri * wc + rj) * 3 + 2
        _BAND_INDEX[key] = (src[low], row[low], col[low], u)
    return _BAND_INDEX[key]


def galerkin_space(p: StepProblem, hvp, k: int) -> CoarseSpace:
    """The :class:`CoarseSpace` of ``p`` on the grid whose longer side has ``k`` vertices.

    ``hvp``: the step's Hessian products (:meth:`StepProblem.grad_hvp`'s third value; its
    ``many`` is used, one batched pass of ``s_h s_w 3`` products, :func:`probe_spacing`).
    ``A_c[(I', J', c'), (I, J, c)] = phi_I'J'^T (H phi_IJ e_c)_c'`` exactly (up to rounding),
    held as a banded matrix (coarse vertices at most ``s // 2`` apart couple).

    Raises
    ------
    TypeError, ValueError
        If ``k`` is not an int >= 2; from :func:`_factor`.
    """
    check_int(k, "k", low=2)
    b, h, w, _ = p.x_prev.shape
    hc, wc = coarse_shape(h, w, k)
    ph, pw = _hats(h, hc), _hats(w, wc)
    sh, sw = probe_spacing(h, hc), probe_spacing(w, wc)
    dt = p.x_prev.dtype
    free = p.free.to(dt)
    fh = torch.stack([ph[:, torch.arange(hc) % sh == ci].sum(1) for ci in range(sh)])  # (sh, H)
    fw = torch.stack([pw[:, torch.arange(wc) % sw == cj].sum(1) for cj in range(sw)])  # (sw, W)
    f = (fh[:, None, :, None] * fw[None, :, None, :]).to(dt).reshape(sh * sw, 1, h, w, 1)
    eye = torch.eye(3, dtype=dt).reshape(1, 3, 1, 1, 1, 3)
    probes = (f[:, None] * eye * free[None, None]).reshape(sh * sw * 3, b, h, w, 3)
    hv = hvp.many(list(probes.unbind(0)))                            # (k, B, H, W, 3), * free
    x = hv.permute(0, 1, 4, 2, 3)                                    # (k, B, 3, H, W)
    r = (ph.T.to(dt) @ x @ pw.to(dt)).reshape(sh, sw, 3, b, 3, hc, wc)   # [.., c', I', J']
    r = r.permute(3, 0, 1, 2, 5, 6, 4).reshape(b, -1).double().numpy()   # (B, sh sw 3 Hc Wc 3)
    src, row, col, u = _band_index(hc, wc, sh, sw)
    n = 3 * hc * wc
    bands, scales = [], []
    for bi in range(b):
        ab = np.zeros((u + 1, n))
        ab[row - col, col] = r[bi, src]
        chol, scale = _factor(ab)
        bands.append(chol)
        scales.append(torch.from_numpy(scale))
    return CoarseSpace(ph, pw, p.free.double(), bands, torch.stack(scales))


def kept_space(p: StepProblem, hvp, k: int, every: int = 1,
               memory: dict | None = None) -> CoarseSpace:
    """:func:`galerkin_space` of ``p``, or the one kept in ``memory`` (a caller's dict).

    The kept one (``memory["coarse"]``) serves while it is younger than ``every`` calls and its
    grid and handles are ``p``'s; else it is rebuilt and kept. ``memory=None``: always built.
    """
    if memory is None:
        return galerkin_space(p, hvp, k)
    kept = memory.get("coarse")
    if (kept is None or kept[1] >= every or kept[2] != k or kept[3].shape != p.free.shape
            or not torch.equal(kept[3], p.free)):
        kept = (galerkin_space(p, hvp, k), 0, k, p.free.clone())
    memory["coarse"] = (kept[0], kept[1] + 1, *kept[2:])
    return kept[0]


def _factor(ab: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Banded Cholesky of the Jacobi-scaled ``A_c``, shifted until positive definite.

    ``ab``: ``(u + 1, n)`` lower band (``ab[i - j, j] = A[i, j]``), float64. Scaled
    ``S = D A D`` (``D = diag(A)^-1/2``, unit diagonal); if ``S`` is not positive definite (an
    indefinite Hessian: compressed edges), ``S + mu I`` with ``mu`` = 1e-8, then x10 up to
    1e2, the first that factors (the correction is a preconditioner; the subspace step that
    uses it weighs it by exact products). A diagonal entry <= 1e-10 of the largest (a hat
    function with no free vertex, whose row and column are zero up to rounding) gets its row
    and column zeroed and a unit scaled diagonal, so its unknown decouples (its right-hand
    side is zero, or rounding, too).

    Raises
    ------
    ValueError
        If ``A`` is not finite or has no positive diagonal entry, or no shift up to 1e2
        factors it.
    """
    diag = ab[0]
    big = diag.max(initial=0.0)
    if not np.isfinite(ab).all() or not big > 0:
        raise ValueError("coarse space: the Galerkin operator is not finite or has no positive "
                         "diagonal entry (a NaN state, or no free vertex)")
    empty = diag <= 1e-10 * big
    scale = 1.0 / np.sqrt(np.where(empty, big, diag))
    u1, n = ab.shape
    s = ab.copy()
    for d in range(u1):                      # s[d, j] = A[j + d, j] scale[j + d] scale[j]
        s[d, :n - d] *= scale[d:] * scale[:n - d]
        s[d, :n - d] *= ~(empty[d:] | empty[:n - d]) if d else 1.0
    s[0, empty] = 1.0
    mu = 0.0
    while True:
        t = s.copy()
        t[0] += mu
        try:
            return scipy.linalg.cholesky_banded(t, lower=True, check_finite=False), scale
        except np.linalg.LinAlgError:
            mu = 1e-8 if mu == 0.0 else mu * 10
            if mu > 1e2:
                raise ValueError("coarse space: the Galerkin operator does not factor with a "
                                 "shift up to 1e2") from None


def coarse_correction(space: CoarseSpace, g: torch.Tensor) -> torch.Tensor:
    """``P A_c^-1 P^T g`` ``(B, H, W, 3)`` in ``g``'s dtype (zero at handles).

    ``g``: the step's gradient ``(B, H, W, 3)`` (J per m/s^2). The coarse Newton step of the
    quadratic model at ``a = 0`` for the coarse part of ``g``; a descent direction is its
    negative.
    """
    b, h, w, _ = g.shape
    hc, wc = space.ph.shape[1], space.pw.shape[1]
    x = (g.double() * space.free).permute(0, 3, 1, 2)                # (B, 3, H, W)
    gc = (space.ph.T @ x @ space.pw).permute(0, 2, 3, 1).reshape(b, -1)  # (B, Hc Wc 3)
    rhs = (gc * space.scale).numpy()
    y = np.stack([scipy.linalg.cho_solve_banded((space.bands[i], True), rhs[i],
                                                check_finite=False) for i in range(b)])
    yc = (torch.from_numpy(y) * space.scale).reshape(b, hc, wc, 3).permute(0, 3, 1, 2)
    out = (space.ph @ yc @ space.pw.T).permute(0, 2, 3, 1) * space.free
    return out.to(g.dtype)
