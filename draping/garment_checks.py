"""Checks of a garment mesh: what makes it unusable for cloth simulation.

:func:`check_garment` lists, as sentences, degenerate triangles, non-manifold edges or
vertices, inconsistent winding, self-intersections (:func:`crossing_pairs`) and vertices inside
the body; :mod:`draping.garments` uses it on every template it makes and every file it loads.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp
import torch
from scipy.spatial import cKDTree

from polygeo.checks import check_faces

__all__ = ["face_edges", "crossing_pairs", "check_garment"]


def face_edges(f: np.ndarray) -> np.ndarray:
    """Directed edges ``(3F, 2)`` of triangles ``f (F, 3)``, each in its face's winding order."""
    return np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])



def _corner_fans(f: np.ndarray, n: int) -> np.ndarray:
    """Number of separate face fans around each vertex (> 1: a non-manifold vertex)."""
    from scipy.sparse.csgraph import connected_components

    nf = len(f)
    corner = np.arange(3 * nf).reshape(nf, 3)  # corner id of (face, local vertex)
    rows, cols = [], []
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    ce = np.concatenate([corner[:, [0, 1]], corner[:, [1, 2]], corner[:, [2, 0]]])
    key = np.sort(e, 1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    ks = key[order]
    same = np.all(ks[1:] == ks[:-1], axis=1)
    for i in np.nonzero(same)[0]:
        a, b = order[i], order[i + 1]
        # Match the corners of the shared edge's two vertices in both faces.
        for va, ca in zip(e[a], ce[a]):
            cb = ce[b][e[b] == va]
            rows.append(ca)
            cols.append(cb[0])
    g = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(3 * nf, 3 * nf))
    _, lab = connected_components(g, directed=False)
    vert = f.ravel()
    pairs = np.unique(np.stack([vert, lab], 1), axis=0)
    return np.bincount(pairs[:, 0], minlength=n)


def _segment_hits(p0, p1, a, b, c) -> np.ndarray:
    """Whether segments ``p0 p1`` cross triangles ``a b c`` (Moller-Trumbore), all (P, 3)."""
    d = p1 - p0
    e1, e2 = b - a, c - a
    h = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, h)
    scale = np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1) * np.linalg.norm(d, axis=1)
    ok = np.abs(det) > 1e-12 * np.maximum(scale, 1e-300)
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = p0 - a
    u = inv * np.einsum("ij,ij->i", s, h)
    q = np.cross(s, e1)
    w = inv * np.einsum("ij,ij->i", d, q)
    t = inv * np.einsum("ij,ij->i", e2, q)
    return ok & (u > 0) & (w > 0) & (u + w < 1) & (t > 0) & (t < 1)


def crossing_pairs(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Pairs of triangles without a common vertex that cross each other.

    Parameters
    ----------
    vertices : (V, 3) float ndarray
        Positions.
    faces : (F, 3) int ndarray
        Triangles.

    Returns
    -------
    (P, 2) int64 ndarray
        Face index pairs where an edge of one passes through the interior of the other;
        empty for a mesh without self-intersections.
    """
    v, f = np.asarray(vertices, float), np.asarray(faces, np.int64)
    none = np.zeros((0, 2), np.int64)
    if len(f) < 2:
        return none
    tri = v[f]
    cen = tri.mean(1)
    rad = np.linalg.norm(tri - cen[:, None], axis=2).max(1)
    pairs = cKDTree(cen).query_pairs(2.0 * rad.max(), output_type="ndarray")
    if len(pairs) == 0:
        return none
    i, j = pairs[:, 0], pairs[:, 1]
    near = np.linalg.norm(cen[i] - cen[j], axis=1) <= rad[i] + rad[j]
    i, j = i[near], j[near]
    shared = (f[i][:, :, None] == f[j][:, None, :]).any((1, 2))
    i, j = i[~shared], j[~shared]
    hit = np.zeros(len(i), bool)
    for s, t in ((i, j), (j, i)):
        for k in range(3):
            p0, p1 = v[f[s, k]], v[f[s, (k + 1) % 3]]
            hit |= _segment_hits(p0, p1, v[f[t, 0]], v[f[t, 1]], v[f[t, 2]])
    return np.stack([i[hit], j[hit]], 1)


def check_garment(vertices: Any, faces: Any, query=None) -> list[str]:
    """What is wrong with a garment mesh, as sentences (empty when nothing is).

    Parameters
    ----------
    vertices : (V, 3) float array or tensor
        Garment vertices in the body's rest pose.
    faces : (F, 3) int array or tensor
        Triangles.
    query : callable, optional
        ``query(points) -> (signed_distance, closest, normal)`` against the rest body
        (negative inside); when given, vertices inside the body are reported.

    Returns
    -------
    list of str
        One sentence per problem: degenerate triangles, non-manifold edges or vertices,
        inconsistent winding, self-intersections, vertices inside the body.

    Raises
    ------
    ValueError, TypeError
        When the arrays themselves are malformed (shapes, indices, NaN coordinates).
    """
    v = np.asarray(torch.as_tensor(vertices).detach().cpu(), dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices: expected shape (V, 3), got {tuple(v.shape)}")
    if not np.isfinite(v).all():
        raise ValueError("vertices: expected finite coordinates")
    f = check_faces(faces, len(v)).cpu().numpy()
    problems = []
    if len(f) == 0:
        return ["the mesh has no triangles"]
    diag = float(np.linalg.norm(v.max(0) - v.min(0)))
    area2 = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    bad = int((area2 <= 1e-12 * diag**2).sum())
    if bad:
        problems.append(f"{bad} degenerate (zero-area) triangles")
    key = np.sort(face_edges(f), 1)
    _, cnt = np.unique(key, axis=0, return_counts=True)
    if (cnt > 2).any():
        problems.append(
            f"{int((cnt > 2).sum())} non-manifold edges (shared by more than two triangles)"
        )
    fans = _corner_fans(f, len(v))
    if (fans > 1).any():
        n_bad = int((fans > 1).sum())
        problems.append(f"{n_bad} non-manifold vertices (triangle fans touching at a vertex)")
    _, dcnt = np.unique(face_edges(f), axis=0, return_counts=True)
    if (dcnt > 1).any():
        n_bad = int((dcnt > 1).sum())
        problems.append(f"inconsistent winding: {n_bad} edges run the same way in both triangles")
    if not bad:
        n_cross = len(crossing_pairs(v, f))
        if n_cross:
            problems.append(f"{n_cross} pairs of triangles intersect each other")
    if query is not None:
        d = np.asarray(query(v)[0])
        inside = int((d < 0).sum())
        if inside:
            problems.append(f"{inside} of {len(v)} vertices lie inside the body")
    return problems
