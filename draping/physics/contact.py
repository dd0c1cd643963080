"""Body collision, self repulsion and the GAPS covariance inextensibility (SI units, J).

Part of :mod:`draping.physics`; import from there.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from polygeo import covariance, neighbors
from polygeo.checks import check_int, check_positive

from ._common import like, positions, reduce_terms
from .rest import RestState

__all__ = [
    "friction_energy",
    "collision_energy",
    "plane_distance",
    "repulsion_pairs",
    "repulsion_energy",
    "inextensibility_energy",
    "k_ext_schedule",
    "spread_over_rings",
]


# ---------------------------------------------------------------------- collisions


def collision_energy(
    distance: torch.Tensor, stiffness: float = 1e4, eps: float = 2e-3, reduction: str = "sum"
) -> torch.Tensor:
    """Cubic body-collision penalty, thesis eq. (27) with p = 3, eq. (40).

    ``sum_i k_c max(eps - d_i, 0)^3`` on the signed distances ``d_i`` of the garment vertices to
    the body (positive outside). The caller computes ``d`` from its body query so that it
    carries the gradient it wants, e.g. :func:`plane_distance` on the closest point and normal
    (SNUG, GAPS) for a distance linear in ``x``.

    Parameters
    ----------
    distance : (..., V) float tensor
        Signed distances (m), positive outside the body.
    stiffness : float
        ``k_c`` (J/m^3), >= 0; the penalty force is ``3 k_c (eps - d)^2`` (N).
    eps : float
        Clearance ``epsilon`` (m), >= 0; 2 mm as SNUG and GAPS.
    reduction : {"sum", "none"}
        Per frame ``(...)`` or per vertex ``(..., V)``.

    Returns
    -------
    float tensor
        Energy (J).

    Raises
    ------
    ValueError
        Negative stiffness or clearance, an unknown reduction.
    TypeError
        ``distance`` not a floating tensor.
    """
    if not isinstance(distance, torch.Tensor) or not distance.is_floating_point():
        raise TypeError(f"distance: expected a floating tensor, got {type(distance).__name__}")
    k = check_positive(stiffness, "stiffness", strict=False)
    e = check_positive(eps, "eps", strict=False)
    pen = torch.clamp(e - distance, min=0.0)
    return reduce_terms(k * pen**3, reduction)


def plane_distance(x: torch.Tensor, anchor: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """Signed distance to the tangent plane of the body: ``n . (x - p)``.

    With ``p`` the closest body point and ``n`` the outward unit normal there (from the body
    query at a nearby position), this is the body's signed distance to first order, linear in
    ``x``: its gradient is ``n``.

    Parameters
    ----------
    x : (..., V, 3) float tensor
        Garment positions (m).
    anchor : (..., V, 3) float tensor
        Closest body points ``p`` (m).
    normal : (..., V, 3) float tensor
        Outward unit normals ``n``.

    Returns
    -------
    (..., V) float tensor
        Signed distances (m).

    Raises
    ------
    ValueError
        Shapes that do not broadcast.
    """
    try:
        return ((x - anchor) * normal).sum(-1)
    except RuntimeError as exc:
        raise ValueError(
            f"anchor, normal: expected shapes broadcastable to x {tuple(x.shape)}, got "
            f"{tuple(anchor.shape)} and {tuple(normal.shape)}"
        ) from exc


def friction_energy(
    x: torch.Tensor,
    reference: torch.Tensor,
    normal: torch.Tensor,
    weight: torch.Tensor,
    eps: float = 1e-4,
    reduction: str = "sum",
) -> torch.Tensor:
    """Lagged, smoothed Coulomb friction against the body (IPC's ``f0``, Li et al. 2020).

    ``sum_i w_i f0(|u_i|)`` with ``u_i = (I - n_i n_i^T)(x_i - r_i)`` the tangential slip of
    vertex ``i`` against where it would be had it moved with the body (``r_i``), ``w_i = mu
    lambda_i`` (friction coefficient times the lagged normal force) and ``f0(s) = s`` for
    ``s >= eps``, ``-s^3 / (3 eps^2) + s^2 / eps + eps / 3`` below (static friction: C^1 at
    ``eps``, zero force at zero slip). The force is ``w_i`` in magnitude once slipping.

    Parameters
    ----------
    x, reference : (..., V, 3) and (V, 3) float tensors
        Positions and sticking positions (m).
    normal : (V, 3) float tensor
        Unit body normals (the contact planes).
    weight : (V,) float tensor
        ``mu lambda`` (N), >= 0 (0 where there is no contact).
    eps : float
        Slip (m) below which friction is static, > 0.
    reduction : {"sum", "none"}
        Per frame ``(...)`` or per vertex ``(..., V)``.

    Returns
    -------
    float tensor
        Energy (J).

    Raises
    ------
    ValueError
        ``eps <= 0``, an unknown reduction.
    """
    e = check_positive(eps, "eps")
    dx = x - reference
    u = dx - (dx * normal).sum(-1, keepdim=True) * normal
    s2 = (u * u).sum(-1)
    s = torch.sqrt(torch.where(s2 > 0, s2, torch.ones_like(s2)))
    s = torch.where(s2 > 0, s, torch.zeros_like(s))
    f0 = torch.where(s < e, -(s**3) / (3 * e * e) + s * s / e + e / 3, s)
    return reduce_terms(weight * f0, reduction)


def repulsion_pairs(x: Any, rest: RestState, delta: float, k: int = 16) -> torch.Tensor:
    """Non-adjacent vertex pairs closer than ``delta`` (the set ``A_i`` of thesis eq. (28)).

    Parameters
    ----------
    x : (V, 3) float array or tensor
        Current positions of one frame (m).
    rest : RestState
        Gives the 1-ring (adjacent vertices are excluded).
    delta : float
        Threshold ``delta`` (m), > 0.
    k : int
        At most ``k`` nearest candidates per vertex (memory ``O(V k)``).

    Returns
    -------
    (V, k) int64 tensor
        Partner indices, ``-1`` where none; each pair appears from both ends.

    Raises
    ------
    ValueError
        Bad shapes, ``delta <= 0`` or ``k < 1``.
    """
    delta = check_positive(delta, "delta")
    k = check_int(k, "k", low=1)
    xt = torch.as_tensor(x).detach().cpu().to(torch.float64)
    positions(xt, rest.n_vertices)
    nb = neighbors.knn(xt.numpy(), int(k) + rest.ring_index.shape[1])
    idx = np.asarray(nb.index)
    ok = np.asarray(nb.mask) & (np.asarray(nb.distance) < delta)
    ring = rest.ring_index.numpy()
    adjacent = (idx[:, :, None] == ring[:, None, :]).any(-1)  # includes the vertex itself
    ok &= ~adjacent
    out = np.full((idx.shape[0], int(k)), -1, dtype=np.int64)
    order = np.argsort(~ok, axis=1, kind="stable")[:, : int(k)]
    take = np.take_along_axis(idx, order, 1)
    keep = np.take_along_axis(ok, order, 1)
    out[keep] = take[keep]
    return torch.from_numpy(out)


def repulsion_energy(
    x: torch.Tensor, pairs: torch.Tensor, delta: float, weight: float = 1.0
) -> torch.Tensor:
    """Self-repulsion, thesis eq. (28).

    ``lambda sum_i sum_{j in A_i} -log(|x_i - x_j|^2 / delta^2)``.

    The ``delta^2`` makes each term vanish at the threshold (eq. (28) up to a constant per
    pair, continuous where a pair enters or leaves ``A_i``); pairs farther than ``delta`` in
    ``x`` contribute nothing. Distances are floored at ``1e-3 delta`` (no infinite energy).

    Parameters
    ----------
    x : (..., V, 3) float tensor
        Positions (m).
    pairs : (V, k) int64 tensor
        Partners from :func:`repulsion_pairs`, ``-1`` padding.
    delta : float
        Threshold (m), > 0.
    weight : float
        ``lambda_rep`` (J), >= 0.

    Returns
    -------
    (...) float tensor
        Energy (J).

    Raises
    ------
    ValueError
        Bad shapes or parameters.
    """
    delta = check_positive(delta, "delta")
    w = check_positive(weight, "weight", strict=False)
    if pairs.ndim != 2 or pairs.shape[0] != x.shape[-2]:
        raise ValueError(f"pairs: expected shape ({x.shape[-2]}, k), got {tuple(pairs.shape)}")
    positions(x, pairs.shape[0])
    ok = pairs >= 0
    d = x[..., pairs.clamp_min(0), :] - x[..., :, None, :]  # (..., V, k, 3)
    r2 = (d * d).sum(-1).clamp_min((1e-3 * delta) ** 2) / (delta * delta)
    term = torch.where(ok & (r2 < 1.0), -torch.log(torch.clamp(r2, max=1.0)), torch.zeros_like(r2))
    return w * term.sum((-1, -2))


# ---------------------------------------------------------------------- GAPS inextensibility


def inextensibility_energy(
    x: torch.Tensor, rest: RestState, k_ext: Any = 1.0, weight: float = 2e8,
    vertex_weight: Any = None,
) -> torch.Tensor:
    """GAPS covariance inextensibility, thesis eq. (44), on the 1-rings of the template.

    ``k_i sum_i sum_j |det(C_i - k_ext sigma_ij I)|`` with ``C_i`` the covariance of the
    deformed 1-ring of vertex ``i`` and ``sigma_ij`` the singular values of its rest covariance
    (:mod:`polygeo.covariance`).

    Parameters
    ----------
    x : (..., V, 3) float tensor
        Positions (m).
    rest : RestState
        1-rings and rest singular values.
    k_ext : float or (..., V) float
        Allowed extension (>= 0): 1 inextensible, > 1 stretch (see :func:`k_ext_schedule`).
    weight : float
        ``k_i``; 2e8 as in GAPS (a loss weight, J/m^6 when ``x`` is in metres).
    vertex_weight : (..., V) float or None
        Optional factor on each vertex's term, >= 0 (GAPS ``pinch_inext``:
        :func:`draping.gaps.pinch_factor`); None: 1 everywhere.

    Returns
    -------
    (...) float tensor
        Energy (``k_i`` times m^6).

    Raises
    ------
    ValueError
        Bad shapes, negative ``k_ext`` or ``vertex_weight``.
    """
    positions(x, rest.n_vertices)
    cov = covariance.vertex_covariance(x, rest.ring_index, rest.ring_mask)
    per = covariance.inextensibility_residual(
        cov,
        like(rest.ring_sigma, x),
        k_ext,
        weight=check_positive(weight, "weight", strict=False),
        reduction="none",
    )
    if vertex_weight is not None:
        w = torch.as_tensor(vertex_weight, dtype=per.dtype, device=per.device)
        if (w.ndim < 1 or w.shape[-1] != rest.n_vertices
                or not bool((torch.isfinite(w) & (w >= 0)).all())):
            raise ValueError(f"vertex_weight: expected finite values >= 0 of shape (..., "
                             f"{rest.n_vertices}), got {tuple(w.shape)}")
        per = per * w
    return per.sum(-1)


def k_ext_schedule(
    distance: Any, epoch: int, eps: float = 2e-3, rest: RestState | None = None, rings: int = 0
) -> torch.Tensor:
    """GAPS collision-aware extension, thesis eq. (45): ``1 + min(10 d_c, 0.03) min(e, 100)``.

    ``d_c = max(eps - d, 0)`` (m) is the penetration of each vertex, ``e`` the epoch: the
    garment is allowed to stretch (up to ``1 + 0.03 * 100 = 4``) only where it collides, and
    only gradually.

    With ``rings > 0`` the allowance also reaches the cloth around a contact, which has to
    stretch for the contact to clear: a vertex that does not collide itself takes the largest
    ``d_c`` of the colliding vertices within ``rings`` 1-rings of it (of the template graph in
    ``rest``; :func:`spread_over_rings`). Colliding vertices keep eq. (45) exactly.

    Parameters
    ----------
    distance : (..., V) float
        Signed distances to the body (m), positive outside.
    epoch : int
        Training epoch ``e`` >= 0.
    eps : float
        Clearance (m) of the collision term.
    rest : RestState or None
        The garment's 1-rings; required when ``rings > 0``.
    rings : int
        How many 1-rings around each contact share its allowance (0: eq. (45) as written).

    Returns
    -------
    (..., V) float tensor
        ``k_ext`` per vertex (detached: a schedule, not a loss).

    Raises
    ------
    ValueError
        Negative epoch, clearance or ``rings``; ``rings > 0`` without ``rest``, or a
        ``distance`` whose last axis is not the garment's vertices.
    """
    epoch = check_int(epoch, "epoch", low=0)
    e = check_positive(eps, "eps", strict=False)
    rings = check_int(rings, "rings", low=0)
    d = torch.as_tensor(distance).detach()
    dc = torch.clamp(e - d, min=0.0)
    if rings > 0:
        if rest is None:
            raise ValueError(f"rest: expected the garment's RestState with rings={rings}, got None")
        dc = torch.where(dc > 0, dc, spread_over_rings(dc, rest, rings))
    return 1.0 + torch.clamp(10.0 * dc, max=0.03) * min(int(epoch), 100)


def spread_over_rings(values: Any, rest: RestState, rings: int) -> torch.Tensor:
    """Largest value within ``rings`` 1-rings of each vertex (a max-dilation on the mesh graph).

    Parameters
    ----------
    values : (..., V) float
        Per-vertex values (any units).
    rest : RestState
        Gives the 1-rings (``ring_index``, ``ring_mask``; the vertex itself included).
    rings : int
        Number of dilation steps, >= 0 (0 returns the values).

    Returns
    -------
    (..., V) float tensor
        ``max`` of ``values`` over the vertices at most ``rings`` edges away.

    Raises
    ------
    ValueError
        Negative ``rings``, a last axis that is not the garment's vertices.
    """
    rings = check_int(rings, "rings", low=0)
    v = torch.as_tensor(values)
    if v.ndim < 1 or v.shape[-1] != rest.n_vertices:
        raise ValueError(
            f"values: expected shape (..., {rest.n_vertices}), got {tuple(v.shape)}"
        )
    idx = rest.ring_index.to(v.device).clamp_min(0)
    mask = rest.ring_mask.to(v.device)
    low = torch.finfo(v.dtype).min if v.is_floating_point() else torch.iinfo(v.dtype).min
    for _ in range(rings):
        v = torch.where(mask, v[..., idx], torch.full_like(v[..., idx], low)).amax(-1)
    return v
