"""Resampling of a PolyFit surface as a triangle mesh at any resolution.

Pure functions over the patch tensors (``K`` patches; see :mod:`polygeo.patches.evaluation`):
:func:`resample_subdivided` evaluates a subdivided input triangulation through the patches
(watertight wherever the input was), :func:`resample_grid` samples every patch's uv box on a
lattice (for point clouds, not connected across patches). Both take and return torch tensors
(faces as int64 tensors on the patches' device); :meth:`polygeo.patches.PatchSet.resample`
converts both outputs to NumPy for a set fitted from NumPy input.
"""

from __future__ import annotations

import numpy as np
import torch

from ..subdivision import subdivide_barycentric
from .evaluation import evaluate_patches, project_to_patches

__all__ = ["resample_subdivided", "resample_grid"]


def resample_subdivided(coeffs: torch.Tensor, scale: torch.Tensor, rotation: torch.Tensor,
                        translation: torch.Tensor, labels: torch.Tensor, vertices: torch.Tensor,
                        faces: torch.Tensor, level: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The input triangulation subdivided ``level`` times and evaluated through the patches.

    Every new vertex, a barycentric combination of a triangle's corners
    (:func:`polygeo.subdivision.subdivide_barycentric`), is evaluated in each corner's patch
    at the same combination of the corners' uv (projected into that patch), and the three
    positions are blended with the barycentric weights. A vertex on an input edge depends
    only on that edge's ends, so the result is watertight wherever the input was.

    Parameters
    ----------
    coeffs, scale, rotation, translation : torch.Tensor
        The patches, ``(K, M)``, ``(K,)``, ``(K, 3, 3)``, ``(K, 3)``.
    labels : torch.Tensor
        ``(V,)`` int64 patch of every input vertex.
    vertices : torch.Tensor
        ``(V, 3)`` float64 input vertices (input units).
    faces : torch.Tensor
        ``(F, 3)`` int64 input triangles.
    level : int
        Subdivision level in ``[0, 8]`` (0: the input vertices through their own patches).

    Returns
    -------
    vertices : torch.Tensor
        ``(V_out, 3)`` float64 positions, differentiable w.r.t. the patch tensors.
    faces : torch.Tensor
        ``(F * 4**level, 3)`` int64 triangles.
    """
    corners, weights, out_faces = subdivide_barycentric(faces, vertices.shape[0], level)
    c = torch.from_numpy(corners)
    w = torch.from_numpy(weights)
    p = vertices[c]  # (N, 3, 3)
    lab = labels[c]  # (N, 3)
    out = torch.zeros(c.shape[0], 3, dtype=torch.float64)
    for slot in range(3):
        patch = lab[:, slot]
        # uv of the three corners in that patch, combined barycentrically
        uvs = torch.stack(
            [project_to_patches(p[:, j], scale, rotation, translation, patch) for j in range(3)],
            dim=1,
        )  # (N, 3, 2)
        uv = (w[..., None] * uvs).sum(1)
        x = evaluate_patches(coeffs, scale, rotation, translation, patch, uv)
        out = out + w[:, slot, None] * x
    return out, torch.from_numpy(np.ascontiguousarray(out_faces, dtype=np.int64)).to(
        vertices.device)


def resample_grid(coeffs: torch.Tensor, scale: torch.Tensor, rotation: torch.Tensor,
                  translation: torch.Tensor, domain: torch.Tensor,
                  n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Every patch sampled on an ``n x n`` lattice of its uv box and triangulated on its own.

    Parameters
    ----------
    coeffs, scale, rotation, translation : torch.Tensor
        The patches, ``(K, M)``, ``(K,)``, ``(K, 3, 3)``, ``(K, 3)``.
    domain : torch.Tensor
        ``(K, 4)`` uv boxes ``(u_min, v_min, u_max, v_max)``.
    n : int
        Lattice points per side (>= 2).

    Returns
    -------
    vertices : torch.Tensor
        ``(K * n * n, 3)`` float64 positions (patch by patch).
    faces : torch.Tensor
        ``(K * 2 (n - 1)**2, 3)`` int64 triangles.
    """
    n_patches = int(scale.shape[0])
    t = torch.linspace(0.0, 1.0, n, dtype=torch.float64)
    a, b = torch.meshgrid(t, t, indexing="ij")
    lo, hi = domain[:, :2], domain[:, 2:]
    u = lo[:, None, 0] + (hi - lo)[:, None, 0] * a.reshape(1, -1)
    vv = lo[:, None, 1] + (hi - lo)[:, None, 1] * b.reshape(1, -1)
    uv = torch.stack([u, vv], dim=-1).reshape(-1, 2)
    idx = torch.arange(n_patches).repeat_interleave(n * n)
    verts = evaluate_patches(coeffs, scale, rotation, translation, idx, uv)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    i, j = i.ravel(), j.ravel()
    q00, q10, q11, q01 = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
    one = np.concatenate([np.stack([q00, q10, q11], 1), np.stack([q00, q11, q01], 1)])
    faces = (one[None] + (np.arange(n_patches) * n * n)[:, None, None]).reshape(-1, 3)
    return verts, torch.from_numpy(faces.astype(np.int64)).to(verts.device)
