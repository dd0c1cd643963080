"""Per-patch quality of a PolyFit patch set: height, normal, boundary and foldover errors.

Pure functions over the tensors of a :class:`polygeo.patches.PatchSet`; every result is a
``(K,)`` NumPy float64 array (``K`` patches). Units: heights and gaps in input length units,
angles in degrees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .evaluation import PatchGeometry, patch_geometry, project_to_patches

__all__ = [
    "PatchMetrics",
    "angle_deg",
    "normal_error",
    "boundary_errors",
    "foldover_share",
    "max_tilt",
    "boundary_geometry",
]


@dataclass(frozen=True)
class PatchMetrics:
    """Per-patch quality of a :class:`PatchSet` (arrays of shape (K,), NumPy float64).

    Attributes
    ----------
    height_rmse : np.ndarray
        RMS height residual of each patch's points, in input length units.
    normal_error : np.ndarray or None
        Mean unsigned angle (degrees) between the fitted normal and the input normal at the
        patch's points; None without input normals.
    boundary_gap : np.ndarray
        Mean distance (input units) between the positions that two adjacent patches give to
        the vertices of their boundary pairs (each end evaluated in both patches: its own at
        its uv, the neighbour at its projection); 0 for a patch without neighbours.
    boundary_normal_angle : np.ndarray
        Mean angle (degrees) between the two patches' normals at those vertices.
    foldover : np.ndarray or None
        Share of the patch's triangles (all three corners in the patch) whose orientation in
        the patch's uv plane is opposite to the patch's dominant orientation, i.e. where the
        height-graph assumption breaks; None for a point cloud.
    max_tilt : np.ndarray or None
        Largest angle (degrees, in ``[0, 180]``) between the normal of a triangle touching the
        patch (at least one corner in it) and the patch's axis (its frame's z, oriented like
        the triangles). Above 90 the triangle folds over the patch plane; near 90 the height
        graph is steep and ill-conditioned. None for a point cloud.
    n_points : np.ndarray
        Points per patch (int64).
    order : np.ndarray
        Jet order per patch (int64).
    """

    height_rmse: np.ndarray
    normal_error: np.ndarray | None
    boundary_gap: np.ndarray
    boundary_normal_angle: np.ndarray
    foldover: np.ndarray | None
    max_tilt: np.ndarray | None
    n_points: np.ndarray
    order: np.ndarray

    def summary(self) -> dict:
        """Scalar summary: means and maxima over patches (point-weighted height RMSE too)."""
        w = self.n_points.astype(float)
        out = {
            "patches": int(len(self.height_rmse)),
            "height_rmse_mean": float(self.height_rmse.mean()),
            "height_rmse_max": float(self.height_rmse.max()),
            "height_rmse_all": float(np.sqrt(np.sum(w * self.height_rmse**2) / w.sum())),
            "boundary_gap_mean": float(self.boundary_gap.mean()),
            "boundary_gap_max": float(self.boundary_gap.max()),
            "boundary_normal_angle_mean": float(self.boundary_normal_angle.mean()),
        }
        if self.normal_error is not None:
            out["normal_error_mean"] = float(np.sum(w * self.normal_error) / w.sum())
        if self.foldover is not None:
            out["foldover_mean"] = float(self.foldover.mean())
            out["foldover_patches"] = int((self.foldover > 0).sum())
        if self.max_tilt is not None:
            out["max_tilt"] = float(self.max_tilt.max())
        return out


def angle_deg(a: torch.Tensor, b: torch.Tensor, unsigned: bool = True) -> torch.Tensor:
    """Angle in degrees between vectors ``a`` and ``b`` along the last axis.

    Parameters
    ----------
    a, b : torch.Tensor
        ``(..., 3)`` vectors (any length; a zero vector gives 90 degrees).
    unsigned : bool
        Treat ``b`` and ``-b`` alike (angle in ``[0, 90]``); otherwise ``[0, 180]``.

    Returns
    -------
    torch.Tensor
        ``(...)`` angles in degrees.
    """
    c = (a * b).sum(-1) / (a.norm(dim=-1) * b.norm(dim=-1)).clamp_min(1e-300)
    c = c.abs() if unsigned else c
    return torch.rad2deg(torch.arccos(c.clamp(-1.0, 1.0)))


def _patch_mean(values: torch.Tensor, patch: torch.Tensor, n_patches: int) -> torch.Tensor:
    total = torch.zeros(n_patches, dtype=torch.float64).index_add_(0, patch, values)
    return total / torch.bincount(patch, minlength=n_patches).clamp_min(1)


def normal_error(fitted: torch.Tensor, reference: torch.Tensor, labels: torch.Tensor,
                 n_patches: int) -> np.ndarray:
    """Mean unsigned angle (degrees) per patch between fitted and reference vertex normals.

    Parameters
    ----------
    fitted : torch.Tensor
        ``(V, 3)`` fitted normals.
    reference : torch.Tensor
        ``(V, 3)`` input normals; zero rows (unknown) are skipped.
    labels : torch.Tensor
        ``(V,)`` int64 patch of every vertex.
    n_patches : int
        K.

    Returns
    -------
    np.ndarray
        ``(K,)`` float64 degrees (0 for a patch without a known normal).
    """
    ang = angle_deg(fitted, reference)
    ok = reference.norm(dim=-1) > 0
    return _patch_mean(ang[ok], labels[ok], n_patches).cpu().numpy()


def boundary_errors(own: PatchGeometry, other: PatchGeometry, own_patch: torch.Tensor,
                    other_patch: torch.Tensor, n_patches: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean gap (input units) and normal angle (degrees) per patch at boundary vertices.

    Parameters
    ----------
    own, other : PatchGeometry
        ``(B,)`` boundary vertices evaluated in their own patch and in the neighbour's.
    own_patch, other_patch : torch.Tensor
        ``(B,)`` int64 the two patches of each evaluation.
    n_patches : int
        K.

    Returns
    -------
    gap, angle : np.ndarray
        ``(K,)`` float64, each evaluation counted for both patches; 0 without neighbours.
    """
    d = (own.positions - other.positions).norm(dim=-1)
    a = angle_deg(own.geometry.normal, other.geometry.normal, unsigned=False)
    cnt = (torch.bincount(own_patch, minlength=n_patches)
           + torch.bincount(other_patch, minlength=n_patches))
    out = []
    for val in (d, a):
        tot = torch.zeros(n_patches, dtype=torch.float64)
        tot.index_add_(0, own_patch, val).index_add_(0, other_patch, val)
        out.append((tot / cnt.clamp_min(1)).cpu().numpy())
    return out[0], out[1]


def foldover_share(faces: torch.Tensor, labels: torch.Tensor, vertex_uv: torch.Tensor,
                   n_patches: int) -> np.ndarray:
    """Share of each patch's inner triangles whose uv orientation opposes the patch's own.

    Parameters
    ----------
    faces : torch.Tensor
        ``(F, 3)`` int64 triangles.
    labels : torch.Tensor
        ``(V,)`` int64 patch of every vertex.
    vertex_uv : torch.Tensor
        ``(V, 2)`` canonical uv of every vertex in its own patch.
    n_patches : int
        K.

    Returns
    -------
    np.ndarray
        ``(K,)`` float64 in ``[0, 1]`` (0 for a patch without inner triangles).
    """
    lf = labels[faces]
    inside = (lf[:, 0] == lf[:, 1]) & (lf[:, 1] == lf[:, 2])
    fi = faces[inside]
    lab = lf[inside, 0]
    q = vertex_uv[fi]  # (Fi, 3, 2)
    e1, e2 = q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]
    area = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    tot = torch.zeros(n_patches, dtype=torch.float64).index_add_(0, lab, area)
    dom = torch.sign(tot)[lab]
    flipped = (area * dom < 0).to(torch.float64)
    nf = torch.bincount(lab, minlength=n_patches).clamp_min(1)
    folded = torch.zeros(n_patches, dtype=torch.float64).index_add_(0, lab, flipped)
    return (folded / nf).cpu().numpy()


def max_tilt(v: torch.Tensor, f: torch.Tensor, labels: torch.Tensor,
             rotation: torch.Tensor) -> np.ndarray:
    """``(K,)`` largest angle (degrees) between a triangle touching a patch and its axis.

    Parameters
    ----------
    v : torch.Tensor
        ``(V, 3)`` vertices.
    f : torch.Tensor
        ``(F, 3)`` int64 triangles.
    labels : torch.Tensor
        ``(V,)`` int64 patch of every vertex.
    rotation : torch.Tensor
        ``(K, 3, 3)`` patch rotations (third column: the patch axis).

    Returns
    -------
    np.ndarray
        ``(K,)`` float64 degrees in ``[0, 180]``. Triangles without area are skipped; a patch
        without a triangle gets 0.
    """
    n_patches = int(rotation.shape[0])
    p = v[f]
    n = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    ln = n.norm(dim=-1)
    ok = ln > 0
    n, fl = n[ok] / ln[ok, None], labels[f[ok]]  # (Fo, 3), (Fo, 3)
    out = torch.zeros(n_patches, dtype=torch.float64)
    for c in range(3):
        axis = rotation[fl[:, c], :, 2]
        ang = torch.rad2deg(torch.arccos((n * axis).sum(-1).clamp(-1.0, 1.0)))
        out = out.scatter_reduce(0, fl[:, c], ang.to(torch.float64), "amax")
    return out.cpu().numpy()


def boundary_geometry(coeffs: torch.Tensor, scale: torch.Tensor, rotation: torch.Tensor,
                      translation: torch.Tensor, labels: torch.Tensor, vertices: torch.Tensor,
                      vertex_uv: torch.Tensor, boundary_pairs: torch.Tensor):
    """Both ends of every boundary pair evaluated in their own patch and in the other one.

    Parameters
    ----------
    coeffs, scale, rotation, translation : torch.Tensor
        The patches (as :func:`polygeo.patches.evaluate_patches`).
    labels : torch.Tensor
        ``(V,)`` int64 patch of every vertex.
    vertices : torch.Tensor
        ``(V, 3)`` input vertices.
    vertex_uv : torch.Tensor
        ``(V, 2)`` uv of every vertex in its own patch.
    boundary_pairs : torch.Tensor
        ``(E_b, 2)`` int64 edges across patches.

    Returns
    -------
    own, other : PatchGeometry
        ``(2 E_b,)`` evaluations (first ends, then second ends).
    own_patch, other_patch : torch.Tensor
        ``(2 E_b,)`` int64 patches of those evaluations.
    """
    bp = boundary_pairs
    vid = torch.cat([bp[:, 0], bp[:, 1]])
    own_patch = labels[vid]
    other_patch = torch.cat([labels[bp[:, 1]], labels[bp[:, 0]]])
    args = (coeffs, scale, rotation, translation)
    own = patch_geometry(*args, own_patch, vertex_uv[vid])
    uv_other = project_to_patches(vertices[vid], scale, rotation, translation, other_patch)
    other = patch_geometry(*args, other_patch, uv_other)
    return own, other, own_patch, other_patch
