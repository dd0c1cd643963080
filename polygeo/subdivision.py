"""Regular subdivision of triangulations as barycentric tables (resolution-agnostic resampling).

:func:`subdivide_barycentric` splits every triangle of a mesh into ``4**level`` triangles on a
barycentric lattice and returns, for every output vertex, the input corners and weights that
produce it. Evaluating any per-vertex quantity (positions, a parametric surface through its
patches, attributes) through that table gives the subdivided mesh; lattice points on an input
edge are shared by the triangles of that edge, so the result is as watertight as the input.

This is a topological operation on integer faces (NumPy in, NumPy out): it needs no vertex
positions, and it lives here rather than in :mod:`polygeo.mesh` (measurements and connectivity
of one given mesh) because its output is a recipe to be evaluated by a surface model.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .checks import check_faces, check_int

__all__ = ["subdivide_barycentric"]



def _edge_keys(a: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    return np.minimum(a, b).astype(np.int64) * n + np.maximum(a, b)


def subdivide_barycentric(
    faces: Any, n_vertices: int, level: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Regular 1-to-4^level subdivision of a triangulation, as barycentric combinations.

    Each triangle is split into ``(2^level)^2`` triangles on a barycentric lattice; lattice
    points on an edge are shared by the triangles of that edge and the original vertices
    come first (``0..V-1``), so a surface evaluated through this table is as watertight as
    the input triangulation.

    Parameters
    ----------
    faces : array_like, shape (F, 3), integer
        Triangles of the input.
    n_vertices : int
        V, number of input vertices.
    level : int
        Subdivision level ``>= 0`` (0 returns the input).

    Returns
    -------
    corners : np.ndarray, shape (V_out, 3), int64
        Input vertices whose combination gives each output vertex (for an original vertex:
        itself three times).
    weights : np.ndarray, shape (V_out, 3), float64
        Barycentric weights (rows sum to 1).
    out_faces : np.ndarray, shape (F * 4^level, 3), int64
        Triangles of the subdivided mesh, with the input's winding.

    Raises
    ------
    ValueError
        On bad shapes, out-of-range indices or a negative level.
    TypeError
        If ``faces`` is not an integer array.
    """
    level = check_int(level, "level", low=0, high=8)
    n_vertices = check_int(n_vertices, "n_vertices", low=0)
    f = check_faces(faces, n_vertices).cpu().numpy()
    nseg = 2**level
    V, F = n_vertices, len(f)
    # lattice points (i, j): weights (1 - (i + j)/N, i/N, j/N) on the corners (a, b, c)
    ii, jj = np.meshgrid(np.arange(nseg + 1), np.arange(nseg + 1), indexing="ij")
    keep = ii + jj <= nseg
    ii, jj = ii[keep], jj[keep]
    rest = nseg - ii - jj
    L = len(ii)
    lid = -np.ones((nseg + 1, nseg + 1), np.int64)
    lid[ii, jj] = np.arange(L)
    # local triangles of the lattice
    tri = []
    for i in range(nseg):
        for j in range(nseg - i):
            tri.append((lid[i, j], lid[i + 1, j], lid[i, j + 1]))
            if j < nseg - i - 1:
                tri.append((lid[i + 1, j], lid[i + 1, j + 1], lid[i, j + 1]))
    tri = np.asarray(tri, np.int64).reshape(-1, 3)
    # classify lattice points
    nz = (rest > 0).astype(int) + (ii > 0) + (jj > 0)
    is_corner = nz == 1
    is_edge = nz == 2
    is_inner = nz == 3
    n_inner = int(is_inner.sum())
    inner_rank = np.cumsum(is_inner) - 1
    # edges of the mesh
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    ekey = np.unique(_edge_keys(e[:, 0], e[:, 1], max(V, 1))) if F else np.zeros(0, np.int64)
    E = len(ekey)
    gid = np.empty((F, L), np.int64)
    corners = np.empty((F, L, 3), np.int64)
    weights = np.empty((F, L, 3))
    corners[:] = f[:, None, :]
    weights[:] = np.stack([rest, ii, jj], axis=1)[None] / nseg
    # corner points -> the original vertex
    cidx = np.flatnonzero(is_corner)
    which = np.argmax(np.stack([rest, ii, jj], 1)[cidx], axis=1)  # 0: a, 1: b, 2: c
    gid[:, cidx] = f[:, which]
    # edge points -> shared id from (edge, position measured from the lower vertex)
    eidx = np.flatnonzero(is_edge)
    if len(eidx) and F:
        wts = np.stack([rest, ii, jj], 1)[eidx]  # (Le, 3) integer weights
        zero_slot = np.argmin(wts, axis=1)
        s1 = (zero_slot + 1) % 3
        s2 = (zero_slot + 2) % 3
        p = f[:, s1]  # (F, Le)
        q = f[:, s2]
        wp = wts[np.arange(len(eidx)), s1]  # (Le,)
        wq = wts[np.arange(len(eidx)), s2]
        key = _edge_keys(p, q, max(V, 1))
        epos = np.searchsorted(ekey, key)
        w_hi = np.where(p > q, wp[None, :], wq[None, :])  # weight of the higher vertex id
        gid[:, eidx] = V + epos * (nseg - 1) + (w_hi - 1)
    if n_inner:
        iidx = np.flatnonzero(is_inner)
        gid[:, iidx] = V + E * (nseg - 1) + np.arange(F)[:, None] * n_inner + inner_rank[iidx]
    n_out = V + E * max(nseg - 1, 0) + F * n_inner
    out_corners = np.repeat(np.arange(V)[:, None], 3, axis=1)
    out_weights = np.tile(np.array([1.0, 0.0, 0.0]), (V, 1))
    all_c = np.empty((n_out, 3), np.int64)
    all_w = np.empty((n_out, 3))
    all_c[:V], all_w[:V] = out_corners, out_weights
    flat_g = gid.ravel()
    flat_c = corners.reshape(-1, 3)
    flat_w = weights.reshape(-1, 3)
    new = flat_g >= V
    all_c[flat_g[new]] = flat_c[new]
    all_w[flat_g[new]] = flat_w[new]
    out_faces = gid[:, tri].reshape(-1, 3) if F else np.zeros((0, 3), np.int64)
    return all_c, all_w, out_faces
