"""The FNO's coarse grid: running the learned proposal at (about) its training resolution.

The shipped FNO is trained on 32 x 32 grids. :func:`draping.fnopt.model.solve_fnopt` can run it on
a coarser grid than the sheet's (``coarse=K``: the grid whose longer side has ``K`` vertices,
:func:`coarse_shape`): the step's fields are restricted to that grid (:func:`restrict`: bilinear
sampling at the coarse vertices' positions, exact on bilinear fields), the FNO runs there with
the stiffness numbers of the coarse spacing, and its proposal is prolonged back (:func:`prolong`:
bilinear interpolation, exact on bilinear fields) and zeroed at the sheet's handles. The grid is
defined by a vertex count, not a length, so the option does not depend on units or sheet size.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from polygeo.checks import check_int

from .step_problem import free_rms  # the one home; re-exported

__all__ = ["check_grid_option", "coarse_shape", "interpolation_matrix", "coarse_free",
           "FNOGrid", "fno_grid", "restrict", "prolong", "coarse_spacing", "free_rms"]


def check_grid_option(value, name: str) -> int:
    """A coarse-grid option (``coarse_res``, ``fno_coarse``, ``coarse`` ...): 0 or an int >= 2.

    The FNO's grid (``coarse_res``, ``stiffness_res``, ``fno_coarse``) or the two-level
    control's (``coarse``, :mod:`draping.fnopt.twolevel`).

    0 means off; otherwise the number of vertices of the coarse grid's longer side.

    Raises
    ------
    TypeError
        If ``value`` is not an int.
    ValueError
        If ``value`` is negative or 1.
    """
    if check_int(value, name, low=0) == 1:
        raise ValueError(f"{name}: expected 0 (off) or an int >= 2, got 1")
    return value


def coarse_shape(h: int, w: int, longer: int) -> tuple[int, int]:
    """The coarse grid ``(Hc, Wc)`` whose longer side has ``longer`` vertices.

    The spacing ratio ``(n - 1) / (longer - 1)`` of the longer side ``n = max(h, w)`` is kept
    on the shorter side (rounded, at least 2 vertices); a grid already no longer than
    ``longer`` is its own coarse grid.

    Raises
    ------
    ValueError
        If ``longer`` is not an int >= 2.
    """
    check_int(longer, "longer", low=2)
    n = max(h, w)
    if longer >= n:
        return h, w
    f = (longer - 1) / (n - 1)
    return max(2, round((h - 1) * f) + 1), max(2, round((w - 1) * f) + 1)


def interpolation_matrix(n_from: int, n_to: int, dtype=torch.float32) -> torch.Tensor:
    """Linear interpolation ``(n_to, n_from)`` from ``n_from`` to ``n_to`` equispaced points.

    Both point sets span the same segment (end points on end points); row ``j`` interpolates
    at the position ``j (n_from - 1) / (n_to - 1)`` of the ``n_from`` points. Rows sum to 1
    (constants are kept) and linear sequences are reproduced; ``n_to == n_from`` gives the
    identity. Built in float64, returned in ``dtype``.
    """
    t = torch.arange(n_to, dtype=torch.float64) * ((n_from - 1) / max(n_to - 1, 1))
    i0 = t.floor().clamp(max=n_from - 2).long() if n_from > 1 else torch.zeros(n_to).long()
    m = torch.zeros(n_to, n_from, dtype=torch.float64)
    if n_from == 1:
        m[:, 0] = 1.0
        return m.to(dtype)
    wgt = t - i0
    rows = torch.arange(n_to)
    m[rows, i0] = 1.0 - wgt
    m[rows, i0 + 1] += wgt
    return m.to(dtype)


def coarse_free(free: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    """The coarse grid's free mask ``(B, Hc, Wc, 1)`` of a fine one ``free`` ``(B, H, W, 1)``.

    Each fine handle (``free == 0``) pins the coarse vertex nearest to it (rounded fractional
    grid position), so a layout keeps one pin per handle where they do not merge.
    """
    b, h, w, _ = free.shape
    hc, wc = shape
    ri = torch.round(torch.arange(h, dtype=torch.float64) * ((hc - 1) / (h - 1))).long()
    rj = torch.round(torch.arange(w, dtype=torch.float64) * ((wc - 1) / (w - 1))).long()
    out = torch.ones(b, hc, wc, 1, dtype=free.dtype)
    bb, ii, jj = torch.nonzero(free[..., 0] < 0.5, as_tuple=True)
    out[bb, ri[ii], rj[jj], 0] = 0.0
    return out


def coarse_spacing(hx: torch.Tensor, hy: torch.Tensor, fine: tuple[int, int],
                   shape: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Spacings ``(hx_c, hy_c)`` ``(B,)`` (m) of the same sheet on the ``shape`` grid."""
    h, w = fine
    hc, wc = shape
    return hx * ((w - 1) / (wc - 1)), hy * ((h - 1) / (hc - 1))


@dataclass(frozen=True)
class FNOGrid:
    """The transfer operators between a sheet's grid and the FNO's coarse grid.

    Attributes
    ----------
    rh, rw : torch.Tensor
        Restriction ``(Hc, H)``, ``(Wc, W)`` (bilinear sampling).
    ph, pw : torch.Tensor
        Prolongation ``(H, Hc)``, ``(W, Wc)`` (bilinear interpolation).
    free : torch.Tensor
        Coarse free mask ``(B, Hc, Wc, 1)`` (:func:`coarse_free`).
    const : torch.Tensor
        The FNO's constant input channels on the coarse grid ``(B, 6, Hc, Wc)``
        (:func:`draping.fnopt.model.constant_features` at the coarse spacing).
    """

    rh: torch.Tensor
    rw: torch.Tensor
    ph: torch.Tensor
    pw: torch.Tensor
    free: torch.Tensor
    const: torch.Tensor


def fno_grid(free: torch.Tensor, shape: tuple[int, int], const: torch.Tensor,
             dtype: torch.dtype) -> FNOGrid:
    """The :class:`FNOGrid` from a fine free mask ``(B, H, W, 1)`` to the ``shape`` grid."""
    _, h, w, _ = free.shape
    hc, wc = shape
    return FNOGrid(interpolation_matrix(h, hc, dtype), interpolation_matrix(w, wc, dtype),
                   interpolation_matrix(hc, h, dtype), interpolation_matrix(wc, w, dtype),
                   coarse_free(free, shape).to(dtype), const)


def restrict(f: torch.Tensor, grid: FNOGrid) -> torch.Tensor:
    """A field ``(B, H, W, C)`` sampled bilinearly on the coarse grid ``(B, Hc, Wc, C)``."""
    return torch.einsum("ih,bhwc,jw->bijc", grid.rh, f, grid.rw)


def prolong(f: torch.Tensor, grid: FNOGrid) -> torch.Tensor:
    """A coarse field ``(B, Hc, Wc, C)`` interpolated bilinearly to the fine grid."""
    return torch.einsum("ih,bhwc,jw->bijc", grid.ph, f, grid.pw)
