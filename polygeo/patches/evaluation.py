"""Evaluation of oriented jet patches: positions, differential geometry, projection.

Pure, differentiable functions of the patch tensors (``K`` patches):
``coeffs (K, M)`` jet coefficients, ``scale (K,)``, ``rotation (K, 3, 3)``,
``translation (K, 3)``; a point ``(patch, uv)`` lies at ``s R (u, v, z(u, v)) + T``.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from .. import jets
from ..checks import as_tensor, check_shape
from ..diffgeo import SurfaceGeometry, from_derivatives

__all__ = [
    "evaluate_patches",
    "PatchGeometry",
    "patch_geometry",
    "project_to_patches",
    "vertex_uv",
]

def _gather_eval_inputs(coeffs, scale, rotation, translation, patch_idx, uv):
    c = as_tensor(coeffs, "coeffs")
    check_shape(c, "coeffs", ("K", "M"))
    n_patches = c.shape[0]
    s = as_tensor(scale, "scale")
    check_shape(s, "scale", (n_patches,))
    R = as_tensor(rotation, "rotation")
    check_shape(R, "rotation", (n_patches, 3, 3))
    T = as_tensor(translation, "translation")
    check_shape(T, "translation", (n_patches, 3))
    idx = as_tensor(patch_idx, "patch_idx", floating=False)
    if idx.is_floating_point() or idx.dtype == torch.bool:
        raise TypeError(f"patch_idx: expected an integer array, got dtype {idx.dtype}")
    check_shape(idx, "patch_idx", ("N",))
    idx = idx.to(torch.int64)
    if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= n_patches):
        raise ValueError(
            f"patch_idx: expected indices in [0, {n_patches - 1}], got values in "
            f"[{int(idx.min())}, {int(idx.max())}]"
        )
    t = as_tensor(uv, "uv")
    check_shape(t, "uv", (idx.shape[0], 2))
    dtype = c.dtype
    for x in (s, R, T, t):
        dtype = torch.promote_types(dtype, x.dtype)
    return c.to(dtype), s.to(dtype), R.to(dtype), T.to(dtype), idx, t.to(dtype)


def evaluate_patches(coeffs, scale, rotation, translation, patch_idx, uv) -> torch.Tensor:
    """World positions ``s R (u, v, z(u, v)) + T`` of points on oriented jet patches.

    Parameters
    ----------
    coeffs : array_like or torch.Tensor
        ``(K, M)`` jet coefficients (canonical units).
    scale : array_like or torch.Tensor
        ``(K,)`` patch scales ``s`` (input length units).
    rotation : array_like or torch.Tensor
        ``(K, 3, 3)`` patch rotations ``R`` (columns: u axis, v axis, height axis).
    translation : array_like or torch.Tensor
        ``(K, 3)`` patch origins ``T``.
    patch_idx : array_like or torch.Tensor
        ``(N,)`` integer patch of every query.
    uv : array_like or torch.Tensor
        ``(N, 2)`` canonical parameters of every query.

    Returns
    -------
    torch.Tensor
        ``(N, 3)`` positions in the promoted dtype; differentiable w.r.t. every float input.

    Raises
    ------
    ValueError
        On inconsistent shapes or out-of-range patch indices.
    TypeError
        On non-numeric input or a non-integer ``patch_idx``.
    """
    c, s, R, T, idx, t = _gather_eval_inputs(coeffs, scale, rotation, translation, patch_idx, uv)
    z = jets.evaluate(c[idx], t[:, None, :])[:, 0]  # (N,)
    local = torch.cat([t, z[:, None]], dim=-1)  # (N, 3)
    return s[idx, None] * (R[idx] @ local[..., None])[..., 0] + T[idx]


class PatchGeometry(NamedTuple):
    """Positions and differential geometry of points on patches (world coordinates).

    Attributes
    ----------
    positions : torch.Tensor
        ``(N, 3)``.
    geometry : polygeo.diffgeo.SurfaceGeometry
        Jacobian ``(N, 3, 2)`` (columns ``x_u, x_v``), metric ``(N, 2, 2)``, second form,
        unit normal ``(N, 3)``, shape operator, principal curvatures ``k1 >= k2`` and
        directions, mean and Gaussian curvature (1 / input length units), validity mask.
        Derivatives are w.r.t. the canonical ``uv``.
    """

    positions: torch.Tensor
    geometry: SurfaceGeometry


def patch_geometry(coeffs, scale, rotation, translation, patch_idx, uv) -> PatchGeometry:
    """Positions, normals, Jacobians, metrics and curvatures on oriented jet patches.

    Parameters
    ----------
    coeffs, scale, rotation, translation, patch_idx, uv
        As in :func:`evaluate_patches`.

    Returns
    -------
    PatchGeometry
        Differentiable w.r.t. every float input (curvatures away from umbilics).

    Raises
    ------
    ValueError, TypeError
        As :func:`evaluate_patches`.
    """
    c, s, R, T, idx, t = _gather_eval_inputs(coeffs, scale, rotation, translation, patch_idx, uv)
    d = jets.derivatives(c[idx], t[:, None, :], max_order=2)
    d = {key: val[:, 0] for key, val in d.items()}
    zero, one = torch.zeros_like(d[(0, 0)]), torch.ones_like(d[(0, 0)])
    Ri, si = R[idx], s[idx, None]

    def world(a, b, cc):  # s R (a, b, c)
        return si * (Ri @ torch.stack([a, b, cc], dim=-1)[..., None])[..., 0]

    pos = world(t[:, 0], t[:, 1], d[(0, 0)]) + T[idx]
    geom = from_derivatives(
        world(one, zero, d[(1, 0)]),
        world(zero, one, d[(0, 1)]),
        world(zero, zero, d[(2, 0)]),
        world(zero, zero, d[(1, 1)]),
        world(zero, zero, d[(0, 2)]),
    )
    return PatchGeometry(pos, geom)


def project_to_patches(points: torch.Tensor, scale: torch.Tensor, rotation: torch.Tensor,
                       translation: torch.Tensor, patch_idx: torch.Tensor) -> torch.Tensor:
    """Canonical uv of world points in given patches' frames (first two local coordinates).

    No validation (see :meth:`polygeo.patches.PatchSet.project` for the checked version).

    Parameters
    ----------
    points : torch.Tensor
        ``(N, 3)`` world positions (input units).
    scale, rotation, translation : torch.Tensor
        ``(K,)``, ``(K, 3, 3)``, ``(K, 3)`` patch orientations.
    patch_idx : torch.Tensor
        ``(N,)`` int64 patch of every point.

    Returns
    -------
    torch.Tensor
        ``(N, 2)`` canonical uv; differentiable.
    """
    d = points - translation[patch_idx]
    loc = (d[:, None, :] @ rotation[patch_idx])[:, 0] / scale[patch_idx, None]
    return loc[:, :2]


def vertex_uv(uv: torch.Tensor, mask: torch.Tensor, index: torch.Tensor,
              n_vertices: int) -> torch.Tensor:
    """Canonical uv of every input vertex in its own patch, from the padded per-patch uv.

    Parameters
    ----------
    uv : torch.Tensor
        ``(K, Pmax, 2)`` canonical uv of each patch's points.
    mask : torch.Tensor
        ``(K, Pmax)`` bool valid entries.
    index : torch.Tensor
        ``(K, Pmax)`` int64 vertex of each entry.
    n_vertices : int
        V.

    Returns
    -------
    torch.Tensor
        ``(V, 2)`` (zeros for a vertex in no patch).
    """
    out = torch.zeros(n_vertices, 2, dtype=uv.dtype)
    out[index[mask]] = uv[mask]
    return out
