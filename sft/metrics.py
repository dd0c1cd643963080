"""Reconstruction metrics of SfT against ground truth.

Definitions (as in the evaluation of phi-SfT, Kairanda et al. 2022, and thesis Table 5.7):

``e_3d``   ``||X - X_gt||_F / ||X_gt||_F`` over all vertices (dimensionless). ``||X_gt||_F``
           includes the object's distance to the camera, so a far object scores low even
           with no reconstruction; always read it next to ``e_3d`` of the fixed template.
``e_n``    mean angle in degrees between corresponding vertex normals (area-weighted vertex
           normals of :func:`polygeo.mesh.vertex_normals`; signed, so a flipped normal
           counts 180 degrees).
``rmse``   ``sqrt(mean_i ||x_i - x_gt,i||^2)`` in scene units.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch

from polygeo.checks import as_tensor, check_shape

__all__ = ["FrameErrors", "e_3d", "e_n", "rmse", "frame_errors", "summarize"]


def _pair(x: Any, gt: Any) -> tuple[torch.Tensor, torch.Tensor]:
    a = as_tensor(x, "X", dtype=torch.float64).detach()
    b = as_tensor(gt, "X_gt", dtype=torch.float64).detach()
    check_shape(a, "X", ("...", "V", 3))
    check_shape(b, "X_gt", ("...", "V", 3))
    if a.shape[-2:] != b.shape[-2:]:
        raise ValueError(f"X, X_gt: expected the same (V, 3) shape, got {tuple(a.shape)} and "
                         f"{tuple(b.shape)}")
    return a, b


def e_3d(X: Any, X_gt: Any) -> np.ndarray:
    """Relative Frobenius error ``||X - X_gt||_F / ||X_gt||_F``.

    Parameters
    ----------
    X, X_gt : array_like
        ``(..., V, 3)`` reconstructed and ground-truth vertices (same units).

    Returns
    -------
    np.ndarray
        ``(...)`` float64, dimensionless.

    Raises
    ------
    ValueError
        On mismatched shapes or an all-zero ``X_gt``.
    """
    a, b = _pair(X, X_gt)
    den = torch.linalg.vector_norm(b, dim=(-2, -1))
    if bool((den == 0).any()):
        raise ValueError("X_gt: the ground truth is all zeros; e_3d is undefined")
    return (torch.linalg.vector_norm(a - b, dim=(-2, -1)) / den).numpy()


def rmse(X: Any, X_gt: Any) -> np.ndarray:
    """Root-mean-square vertex distance ``sqrt(mean ||x - x_gt||^2)`` in scene units.

    Parameters
    ----------
    X, X_gt : array_like
        ``(..., V, 3)``.

    Returns
    -------
    np.ndarray
        ``(...)`` float64.
    """
    a, b = _pair(X, X_gt)
    return ((a - b) ** 2).sum(-1).mean(-1).sqrt().numpy()


def e_n(X: Any, X_gt: Any, faces: Any, mask: Any = None) -> np.ndarray:
    """Mean angle (degrees) between corresponding vertex normals.

    Parameters
    ----------
    X, X_gt : array_like
        ``(..., V, 3)``.
    faces : array_like
        ``(F, 3)`` triangles shared by both meshes.
    mask : array_like, optional
        ``(..., V)`` bool: only these vertices enter the mean (e.g. the visible ones); the
        normals are still computed on the whole mesh.

    Returns
    -------
    np.ndarray
        ``(...)`` float64 in ``[0, 180]``; vertices whose normal is undefined in either mesh
        (isolated or cancelling) are left out of the mean; 0 when no vertex is left.

    Raises
    ------
    ValueError
        On mismatched shapes, or a ``mask`` that is not ``(..., V)``.
    """
    from polygeo.mesh import vertex_normals

    a, b = _pair(X, X_gt)
    na = vertex_normals(a, faces)
    nb = vertex_normals(b, faces)
    ok = na.valid & nb.valid
    if mask is not None:
        m = torch.as_tensor(np.asarray(mask), dtype=torch.bool)
        if m.shape[-1:] != ok.shape[-1:]:
            raise ValueError(f"mask: expected (..., {ok.shape[-1]}) booleans, got "
                             f"{tuple(m.shape)}")
        ok = ok & m
    cos = (na.normals * nb.normals).sum(-1).clamp(-1.0, 1.0)
    ang = torch.rad2deg(torch.arccos(cos))
    ang = torch.where(ok, ang, torch.zeros_like(ang))
    return (ang.sum(-1) / ok.sum(-1).clamp_min(1)).numpy()


@dataclass(frozen=True)
class FrameErrors:
    """Errors of one frame (see the module docstring).

    Attributes
    ----------
    e_3d, e_n, rmse : float
        Of the reconstruction.
    e_3d_template, e_n_template, rmse_template : float
        Of the template kept fixed (the reference a reconstruction must beat).
    """

    e_3d: float
    e_n: float
    rmse: float
    e_3d_template: float
    e_n_template: float
    rmse_template: float

    def as_dict(self) -> dict[str, float]:
        """Plain dict (for JSON)."""
        return asdict(self)


def frame_errors(X: Any, X_gt: Any, template: Any, faces: Any) -> FrameErrors:
    """All errors of one frame, of the reconstruction and of the fixed template.

    Parameters
    ----------
    X, X_gt, template : array_like
        ``(V, 3)`` reconstruction, ground truth and template vertices.
    faces : array_like
        ``(F, 3)``.

    Returns
    -------
    FrameErrors
    """
    return FrameErrors(
        e_3d=float(e_3d(X, X_gt)),
        e_n=float(e_n(X, X_gt, faces)),
        rmse=float(rmse(X, X_gt)),
        e_3d_template=float(e_3d(template, X_gt)),
        e_n_template=float(e_n(template, X_gt, faces)),
        rmse_template=float(rmse(template, X_gt)),
    )


def summarize(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Mean of every numeric field over per-frame rows (NaN-free fields only).

    Parameters
    ----------
    rows : list of dict
        Per-frame records.

    Returns
    -------
    dict
        ``{field: mean}`` for each field that is numeric in every row, plus ``frames``.
    """
    out: dict[str, float] = {"frames": len(rows)}
    if not rows:
        return out
    for k in rows[0]:
        vals = [r.get(k) for r in rows]
        if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in vals):
            if k == "frame":
                continue
            out[k] = float(np.mean(vals))
    return out
