"""Canonical frames of surface patches: PCA, the jet height residual, test-time refinement.

PolyFit (thesis §5.2) represents a patch as ``p = s R phi(u, v) + T`` with
``phi(u, v) = (u, v, z(u, v))`` an n-jet height graph. The frame ``(s, R, T)`` decides whether
the patch is a good height graph: a tilted frame folds the patch over the uv plane (several
heights above one uv) and the jet residual grows. This module holds what does not learn,
all batched over patches (padded ``(B, P, 3)`` with a mask):

* :func:`canonicalize`: centroid, PCA rotation (``e3`` = smallest-variance direction) and the
  scale ``s`` = largest distance of a point from the centroid, so that canonical points lie
  in the unit ball;
* :func:`height_residual`: the RMS height residual of the n-jet fit after a refinement
  rotation ``R = R_pca Q``, differentiable w.r.t. the points and ``Q`` (the loss of the STN,
  :mod:`polygeo.stn`, and of the test-time refinement);
* :func:`optimize_rotations`: per-patch test-time refinement of ``Q`` by Adam steps on that
  residual (no learning), keeping each patch's best iterate, so that it never ends worse
  than where it started.

The learned refinement (a rigid spatial transformer) lives in :mod:`polygeo.stn`, its
training in :mod:`polygeo.stn_train`.

Units: canonical coordinates are dimensionless (unit ball); a residual times the patch scale
``s`` is a length in the input's units.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import torch

from . import jets
from .checks import as_tensor, check_finite, check_int, check_mask, check_positive, check_shape
from .frames import Orientation, axis_angle_to_matrix, pca_frames

__all__ = ["Canonical", "canonicalize", "height_residual", "OptimizeResult", "optimize_rotations"]


class Canonical(NamedTuple):
    """Canonical (PCA) coordinates of padded patches.

    Attributes
    ----------
    local : torch.Tensor
        ``(B, P, 3)`` points in the frame, ``R^T (p - T) / s`` (zero at padded entries).
    orientation : polygeo.frames.Orientation
        ``(s, R, T)`` per patch: ``s`` (B,) the largest distance of a valid point from the
        centroid (1 for a patch with a single distinct point), ``R`` (B, 3, 3) the PCA
        rotation (columns e1, e2, normal), ``T`` (B, 3) the centroid.
    mask : torch.Tensor
        ``(B, P)`` bool, valid entries.
    """

    local: torch.Tensor
    orientation: Orientation
    mask: torch.Tensor


def _points_mask(points: Any, mask: Any, name: str = "points") -> tuple[torch.Tensor, torch.Tensor]:
    p = as_tensor(points, name)
    check_shape(p, name, ("B", "P", 3))
    if mask is None:
        m = torch.ones(p.shape[:2], dtype=torch.bool)
    else:
        m = check_mask(mask, "mask", tuple(p.shape[:2]))
    if bool(m.any()):
        check_finite(p[m], name)
    return p, m


def canonicalize(points: Any, mask: Any = None, *, reference_normal: Any = None) -> Canonical:
    """PCA frame, centroid and unit-ball scale of each padded patch.

    Parameters
    ----------
    points : array_like or torch.Tensor
        ``(B, P, 3)`` patch points (length units), padded.
    mask : array_like or torch.Tensor, optional
        ``(B, P)`` bool, True for valid points (default: all valid).
    reference_normal : array_like or torch.Tensor, optional
        ``(B, 3)`` directions; the PCA normal is flipped (with ``e2``) to agree with them
        (e.g. the mean input normal of the patch), so that fitted normals keep the input's
        orientation.

    Returns
    -------
    Canonical
        Torch tensors in the points' floating dtype. Differentiable w.r.t. ``points``.

    Raises
    ------
    ValueError
        On bad shapes or non-finite valid points.
    TypeError
        On non-numeric points or a non-bool mask.
    """
    p, m = _points_mask(points, mask)
    fr = pca_frames(p, mask=m, reference_normal=reference_normal)
    T, R = fr.centroid, fr.rotation
    d = torch.where(m[..., None], p - T[:, None, :], torch.zeros_like(p))
    r = d.norm(dim=-1).masked_fill(~m, 0.0).amax(-1) if p.shape[1] else p.new_zeros(p.shape[0])
    s = torch.where(r > 0, r, torch.ones_like(r))
    local = (d @ R) / s[:, None, None]
    local = torch.where(m[..., None], local, torch.zeros_like(local))
    return Canonical(local, Orientation(s, R, T), m)


def height_residual(
    local: torch.Tensor,
    mask: torch.Tensor,
    rotation: torch.Tensor | None,
    order: int,
    *,
    method: str = "envelope",
) -> tuple[torch.Tensor, jets.JetFit]:
    """RMS height residual of the n-jet fit after rotating canonical points.

    The rotated points are ``y = Q^T x`` (``Q`` = ``rotation``, the refined frame's axes in
    the canonical frame); the jet ``z(u, v)`` is fitted to ``(y_1, y_2) -> y_3`` by least
    squares and the residual is ``sqrt(mean_i (y_3,i - z(y_1,i, y_2,i))^2)`` over the valid
    points.

    Parameters
    ----------
    local : torch.Tensor
        ``(B, P, 3)`` canonical points (unit ball).
    mask : torch.Tensor
        ``(B, P)`` bool.
    rotation : torch.Tensor or None
        ``(B, 3, 3)`` refinement rotations (None: identity).
    order : int
        Jet order in ``[1, 6]``.
    method : {"envelope", "exact"}
        How the gradient reaches ``local`` and ``rotation``. ``"exact"`` differentiates
        through the least-squares solve (:func:`polygeo.jets.fit`, torch backend).
        ``"envelope"`` (default, several times cheaper) solves without a graph and
        differentiates ``|y_3 - A(y_1, y_2) c|`` with the optimal ``c`` held fixed: by the
        envelope theorem this is the same gradient wherever the fit is well posed (the
        derivative of a minimum w.r.t. a parameter is the partial derivative at the
        minimiser).

    Returns
    -------
    residual : torch.Tensor
        ``(B,)`` float64 RMS height residual in canonical units, differentiable w.r.t.
        ``local`` and ``rotation``.
    fit : polygeo.jets.JetFit
        The fit, in the rotated frame.

    Raises
    ------
    ValueError
        On a bad ``method`` or ``order``.
    """
    if method not in ("envelope", "exact"):
        raise ValueError(f"method: expected one of ['envelope', 'exact'], got {method!r}")
    y = local if rotation is None else local @ rotation.to(local.dtype)
    if method == "exact":
        f = jets.fit(y[..., :2], y[..., 2], order, mask=mask, backend="torch")
        return f.residual, f
    with torch.no_grad():
        f = jets.fit(y[..., :2].detach(), y[..., 2].detach(), order, mask=mask)
    y64 = y.to(torch.float64)
    uv = torch.where(mask[..., None], y64[..., :2], torch.zeros_like(y64[..., :2]))
    pred = (jets.monomials(uv, order) * f.coeffs.to(torch.float64)[:, None, :]).sum(-1)
    r = torch.where(mask, y64[..., 2] - pred, torch.zeros_like(pred))
    n = mask.sum(-1).clamp_min(1).to(torch.float64)
    ms = (r * r).sum(-1) / n
    safe = torch.where(ms > 0, ms, torch.ones_like(ms))
    return torch.where(ms > 0, safe.sqrt(), torch.zeros_like(ms)), f


class OptimizeResult(NamedTuple):
    """Result of :func:`optimize_rotations`.

    Attributes
    ----------
    rotation : torch.Tensor
        ``(B, 3, 3)`` best refinement rotation found per patch.
    residual : torch.Tensor
        ``(B,)`` its RMS height residual (canonical units).
    initial_residual : torch.Tensor
        ``(B,)`` residual of the starting rotation.
    """

    rotation: torch.Tensor
    residual: torch.Tensor
    initial_residual: torch.Tensor


def optimize_rotations(
    local: torch.Tensor,
    mask: torch.Tensor,
    order: int = 4,
    *,
    init: torch.Tensor | None = None,
    steps: int = 40,
    lr: float = 0.05,
    max_angle: float = math.pi / 3,
) -> OptimizeResult:
    """Refine each patch's rotation by Adam steps on its jet height residual.

    The rotation is ``Q = Q0 exp([w]_x)`` with ``w`` (B, 3) an axis-angle correction
    starting at zero and ``Q0`` the starting rotation (``init``, default identity). All
    patches move together (their losses are independent; Adam's per-coordinate step makes
    the batch behave like B separate optimisations); each patch keeps its best iterate, so
    its residual never ends above the starting one. Corrections are limited to ``max_angle``
    (the residual alone would reward turning a patch edge-on, where it stops being a
    surface over the uv plane).

    Parameters
    ----------
    local : torch.Tensor
        ``(B, P, 3)`` canonical points.
    mask : torch.Tensor
        ``(B, P)`` bool.
    order : int
        Jet order of the residual.
    init : torch.Tensor, optional
        ``(B, 3, 3)`` starting rotations (e.g. the STN's).
    steps : int
        Adam steps (0 returns the start).
    lr : float
        Adam learning rate (radians per step, roughly).
    max_angle : float
        Largest correction angle in radians.

    Returns
    -------
    OptimizeResult
        Rotations and residuals (no gradient).

    Raises
    ------
    ValueError
        On a negative step count or non-positive rates.
    """
    steps = check_int(steps, "steps", low=0)
    lr = check_positive(lr, "lr")
    max_angle = check_positive(max_angle, "max_angle")
    B = local.shape[0]
    x = local.detach().to(torch.float64)
    Q0 = (
        torch.eye(3, dtype=torch.float64).expand(B, 3, 3)
        if init is None
        else init.detach().to(torch.float64)
    )
    with torch.no_grad():
        r0, _ = height_residual(x, mask, Q0, order)
    best_r = r0.clone()
    best_Q = Q0.clone()
    if steps == 0 or B == 0:
        return OptimizeResult(best_Q.to(local.dtype), best_r, r0)
    w = torch.zeros(B, 3, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([w], lr=lr)
    for i in range(steps + 1):  # the last pass only scores the final iterate
        Q = Q0 @ axis_angle_to_matrix(_clamp_angle(w, max_angle))
        r, _ = height_residual(x, mask, Q, order)
        with torch.no_grad():
            better = r < best_r
            best_r = torch.where(better, r, best_r)
            best_Q = torch.where(better[:, None, None], Q, best_Q)
        if i == steps:
            break
        opt.zero_grad()
        (r * r).sum().backward()
        opt.step()
    return OptimizeResult(best_Q.detach().to(local.dtype), best_r.detach(), r0)


def _clamp_angle(w: torch.Tensor, max_angle: float) -> torch.Tensor:
    """Rotation vectors ``(B, 3)`` shortened to at most ``max_angle`` radians."""
    ang = w.norm(dim=-1, keepdim=True)
    return torch.where(ang > max_angle, w * (max_angle / ang.clamp_min(1e-12)), w)
