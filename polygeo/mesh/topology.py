"""Connectivity of triangle meshes.

Edges, edge-to-face incidence, boundary and non-manifold edges, vertex adjacency, connected
components, and clean-up (welding coincident vertices, dropping unreferenced ones).

Integer ``faces (F, 3)`` in; NumPy arrays out (tensors when given tensors). Public names are
re-exported by :mod:`polygeo.mesh`, their documented home.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import connected_components as _cc

from ..checks import check_int, check_shape, to_like
from ._common import as_output, checked_vertices, faces_array, unique_pairs

__all__ = [
    "Welded",
    "Compacted",
    "edges",
    "edge_faces",
    "boundary_edges",
    "non_manifold_edges",
    "vertex_adjacency",
    "connected_components",
    "weld_vertices",
    "remove_unreferenced_vertices",
]


class Welded(NamedTuple):
    """Result of :func:`weld_vertices`.

    Attributes
    ----------
    vertices : (M, 3) float
        Merged vertices (the first occurrence of each cluster keeps its coordinates).
    faces : (F', 3) int64
        Re-indexed faces; faces that collapse (two equal corners) are dropped.
    mapping : (N,) int64
        Old vertex -> new vertex.
    kept_faces : (F',) int64
        Indices of the input faces that were kept.
    """

    vertices: Any
    faces: Any
    mapping: Any
    kept_faces: Any


class Compacted(NamedTuple):
    """Result of :func:`remove_unreferenced_vertices`.

    Attributes
    ----------
    vertices : (M, 3) float
        The referenced vertices in their original order.
    faces : (F, 3) int64
        Re-indexed faces.
    mapping : (N,) int64
        Old vertex -> new vertex, ``-1`` for removed ones.
    kept : (M,) int64
        Old indices of the kept vertices.
    """

    vertices: Any
    faces: Any
    mapping: Any
    kept: Any


def edges(faces: Any) -> Any:
    """Unique undirected edges of a triangle mesh.

    Parameters
    ----------
    faces : (F, 3) int array or tensor
        Triangles.

    Returns
    -------
    (E, 2) int64
        Edges ``(i, j)`` with ``i < j``, sorted lexicographically; degenerate corners
        (``i == j``) are skipped.

    Raises
    ------
    ValueError
        Bad shape or negative indices.
    TypeError
        Non-integer faces.
    """
    f, numpy_in = faces_array(faces)
    h = f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    e = np.stack([np.minimum(h[:, 0], h[:, 1]), np.maximum(h[:, 0], h[:, 1])], axis=1)
    e = e[e[:, 0] != e[:, 1]]
    e = unique_pairs(e, inverse=False)[0] if e.size else np.zeros((0, 2), dtype=np.int64)
    return as_output(e.astype(np.int64), numpy_in)


def edge_faces(faces: Any) -> tuple[Any, Any, Any]:
    """Directed half-edges grouped by undirected edge.

    Parameters
    ----------
    faces : (F, 3) int array or tensor
        Triangles.

    Returns
    -------
    edges : (E, 2) int64
        Unique undirected edges (as :func:`edges`).
    edge_id : (3F,) int64
        For half-edge ``3 * f + c`` (from corner ``c`` to corner ``c + 1`` of face ``f``),
        the index of its undirected edge, ``-1`` for degenerate corners.
    count : (E,) int64
        Number of half-edges (faces) on each edge: 1 on a boundary, 2 for a manifold
        interior edge, more at a non-manifold fin.

    Raises
    ------
    ValueError
        Bad shape or negative indices.
    TypeError
        Non-integer faces.
    """
    f, numpy_in = faces_array(faces)
    he = f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    key = np.sort(he, axis=1)
    ok = key[:, 0] != key[:, 1]
    edge_id = np.full(he.shape[0], -1, dtype=np.int64)
    if ok.any():
        e, inv = unique_pairs(key[ok])
        edge_id[ok] = inv.reshape(-1)
        count = np.bincount(inv.reshape(-1), minlength=e.shape[0]).astype(np.int64)
    else:
        e = np.zeros((0, 2), dtype=np.int64)
        count = np.zeros(0, dtype=np.int64)
    return (
        as_output(e.astype(np.int64), numpy_in),
        as_output(edge_id, numpy_in),
        as_output(count, numpy_in),
    )


def boundary_edges(faces: Any) -> Any:
    """Edges used by exactly one face, directed as in that face's winding.

    Parameters
    ----------
    faces : (F, 3) int array or tensor
        Triangles.

    Returns
    -------
    (B, 2) int64
        Boundary half-edges ``(a, b)``.

    Raises
    ------
    ValueError
        Bad shape or negative indices.
    TypeError
        Non-integer faces.
    """
    f, numpy_in = faces_array(faces)
    _, eid, count = edge_faces(f)
    he = f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    sel = eid >= 0  # degenerate corners (eid -1) are no edge
    sel[sel] = count[eid[sel]] == 1
    return as_output(he[sel].astype(np.int64), numpy_in)


def non_manifold_edges(faces: Any) -> Any:
    """Undirected edges shared by more than two faces (fins).

    Parameters
    ----------
    faces : (F, 3) int array or tensor
        Triangles.

    Returns
    -------
    (M, 2) int64
        The offending edges ``(i, j)``, ``i < j``.

    Raises
    ------
    ValueError
        Bad shape or negative indices.
    TypeError
        Non-integer faces.
    """
    f, numpy_in = faces_array(faces)
    e, _, count = edge_faces(f)
    return as_output(e[count > 2], numpy_in)


def vertex_adjacency(faces: Any, n_vertices: int) -> sp.csr_matrix:
    """Symmetric vertex adjacency of a triangle mesh (the library's one adjacency builder).

    :func:`polygeo.neighbors.mesh_k_ring` walks it and :func:`connected_components` labels it;
    ``polygeo.neighbors.vertex_adjacency`` is this function.

    Parameters
    ----------
    faces : (F, 3) int array or tensor
        Triangles as vertex indices in ``[0, n_vertices)``.
    n_vertices : int
        Number of vertices ``N`` (unreferenced vertices get empty rows).

    Returns
    -------
    scipy.sparse.csr_matrix
        ``(N, N)`` float64 matrix with 1 where two distinct vertices share an edge, zero
        diagonal (degenerate faces add no self loops).

    Raises
    ------
    ValueError
        Bad shape or out-of-range indices.
    TypeError
        Non-integer faces.
    """
    n = check_int(n_vertices, "n_vertices", low=0)
    f, _ = faces_array(faces, n)
    a = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    b = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    keep = a != b
    a, b = a[keep], b[keep]
    rows = np.concatenate([a, b])
    cols = np.concatenate([b, a])
    m = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n, n))
    m.sum_duplicates()
    m.data[:] = 1.0
    return m


def connected_components(faces: Any, n_vertices: int) -> tuple[int, Any]:
    """Vertex-connected components of a mesh.

    Parameters
    ----------
    faces : (F, 3) int array or tensor
        Triangles.
    n_vertices : int
        Number of vertices ``N``; unreferenced vertices form singleton components.

    Returns
    -------
    n_components : int
        Number of components.
    labels : (N,) int64
        Component of each vertex, numbered from 0 in order of first vertex.

    Raises
    ------
    ValueError
        Bad shapes or out-of-range indices.
    TypeError
        Non-integer faces.
    """
    n = check_int(n_vertices, "n_vertices", low=0)
    f, numpy_in = faces_array(faces, n)
    nc, labels = _cc(vertex_adjacency(f, n), directed=False)
    return int(nc), as_output(labels.astype(np.int64), numpy_in)


def weld_vertices(vertices: Any, faces: Any, tol: float = 0.0) -> Welded:
    """Merge duplicate vertices (an unwelded triangle soup becomes a connected mesh).

    Parameters
    ----------
    vertices : (N, 3) float
        Vertex coordinates.
    faces : (F, 3) int
        Triangles.
    tol : float
        Vertices closer than ``tol`` (same unit as ``vertices``) are merged, transitively
        (clusters of the ``tol``-graph). ``0`` merges exact duplicates only.

    Returns
    -------
    Welded
        Merged vertices, re-indexed faces (collapsed faces dropped), the old -> new vertex
        mapping and the kept face indices. Non-finite vertices are never merged.

    Raises
    ------
    ValueError
        Bad shapes, out-of-range indices or ``tol < 0``.
    TypeError
        Non-numeric input.
    """
    v, numpy_in = checked_vertices(vertices)
    check_shape(v, "vertices", ("N", 3))
    n = v.shape[0]
    f, _ = faces_array(faces, n)
    tol = float(tol)
    if not np.isfinite(tol) or tol < 0:
        raise ValueError(f"tol: expected a finite value >= 0, got {tol!r}")
    x = v.detach().cpu().to(torch.float64).numpy()
    fin = np.isfinite(x).all(axis=1)
    labels = np.arange(n)
    if tol == 0.0:
        idx = np.flatnonzero(fin)
        if idx.size:
            _, first, inv = np.unique(x[idx], axis=0, return_index=True, return_inverse=True)
            labels[idx] = idx[first][inv.reshape(-1)]
    else:
        from scipy.spatial import cKDTree

        idx = np.flatnonzero(fin)
        if idx.size:
            pairs = cKDTree(x[idx]).query_pairs(tol, output_type="ndarray")
            g = sp.coo_matrix(
                (np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(idx.size, idx.size)
            )
            _, lab = _cc(g, directed=False)
            first = np.full(lab.max() + 1, idx.size, dtype=np.int64)
            np.minimum.at(first, lab, np.arange(idx.size))
            labels[idx] = idx[first[lab]]
    keep_v, mapping = np.unique(labels, return_inverse=True)
    mapping = mapping.reshape(-1).astype(np.int64)
    nf = mapping[f] if f.size else f
    ok = (nf[:, 0] != nf[:, 1]) & (nf[:, 1] != nf[:, 2]) & (nf[:, 2] != nf[:, 0])
    kept_faces = np.flatnonzero(ok).astype(np.int64)
    new_v = v[torch.from_numpy(keep_v)]
    return Welded(
        to_like(new_v, numpy_in),
        as_output(nf[ok].astype(np.int64), numpy_in),
        as_output(mapping, numpy_in),
        as_output(kept_faces, numpy_in),
    )


def remove_unreferenced_vertices(vertices: Any, faces: Any) -> Compacted:
    """Drop vertices no face refers to and re-index the faces.

    Parameters
    ----------
    vertices : (N, 3) float
        Vertex coordinates (a leading batch ``(..., N, 3)`` is allowed).
    faces : (F, 3) int
        Triangles.

    Returns
    -------
    Compacted
        Kept vertices in original order, re-indexed faces, old -> new mapping (``-1`` for
        removed vertices) and the old indices of the kept vertices.

    Raises
    ------
    ValueError
        Bad shapes or out-of-range indices.
    TypeError
        Non-numeric input.
    """
    v, numpy_in = checked_vertices(vertices)
    n = v.shape[-2]
    f, _ = faces_array(faces, n)
    used = np.zeros(n, dtype=bool)
    used[f.reshape(-1)] = True
    kept = np.flatnonzero(used).astype(np.int64)
    mapping = np.full(n, -1, dtype=np.int64)
    mapping[kept] = np.arange(kept.size)
    new_v = v[..., torch.from_numpy(kept), :]
    return Compacted(
        to_like(new_v, numpy_in),
        as_output(mapping[f] if f.size else f.astype(np.int64), numpy_in),
        as_output(mapping, numpy_in),
        as_output(kept, numpy_in),
    )
