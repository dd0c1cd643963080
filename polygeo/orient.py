"""Consistent orientation of unoriented normals.

A fitted normal (PCA or jet) is defined up to its sign. Three sources decide the sign, in
the order the estimator tries them:

1. given normals (from the file or the caller): flip each estimate to agree with its own
   reference (:func:`orient_to_reference`);
2. a mesh: faces are re-wound consistently per component (outward for closed ones), the
   area-weighted vertex normals serve as references (:func:`mesh_reference_normals`);
3. a bare point cloud: propagation over the k-NN graph (:func:`propagate_orientation`),
   after Hoppe et al. (1992): a minimum spanning tree on weights ``1 - |n_i . n_j|`` so
   that the sign travels across nearly parallel normals first, seeded per connected
   component at its point of largest ``z`` (the extreme point of a closed surface, whose
   outward normal has ``n_z > 0``), whose normal is made to point to ``+z``. Generalised
   here: of the six extreme points along +-x, +-y, +-z the seed is the one whose normal is
   best aligned with the direction from the component's centroid, and its normal is made
   to point away from the centroid (an open cylinder is then seeded on its side, a single
   scan ring outward).

Functions accept NumPy or torch and return the input's type. Orientation is a sign choice
per point: it is applied with a multiplication by +-1, so gradients pass through.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree

from .checks import as_tensor, check_faces, check_int, check_shape, is_numpy_like, to_like
from .mesh import orient_faces, vertex_normals
from .neighbors import knn

__all__ = [
    "Oriented",
    "orient_to_reference",
    "mesh_reference_normals",
    "propagate_orientation",
]


class Oriented(NamedTuple):
    """Oriented normals.

    Attributes
    ----------
    normals : (N, 3) float
        The input normals multiplied by ``sign``.
    sign : (N,) float
        +1 or -1 per point (+1 where nothing could be decided).
    component : (N,) int64
        Component of the graph the orientation travelled through (-1 for points left out:
        non-finite or zero normals). For :func:`orient_to_reference` every valid point is its
        own component 0.
    """

    normals: Any
    sign: Any
    component: Any


def _normals(x: Any, name: str) -> torch.Tensor:
    t = as_tensor(x, name)
    check_shape(t, name, ("N", 3))
    return t


def orient_to_reference(normals: Any, reference: Any) -> Oriented:
    """Flip each normal that points away from its reference (``n_i . r_i < 0``).

    Parameters
    ----------
    normals : (N, 3) float
        Unoriented normals.
    reference : (N, 3) float
        Reference directions (need not be unit). Where the reference is zero or non-finite,
        or orthogonal to the normal, the normal is kept as is.

    Returns
    -------
    Oriented
        Normals, signs and ``component`` (0 where a reference decided, -1 elsewhere).

    Raises
    ------
    ValueError
        Shapes differ or are not (N, 3).
    TypeError
        Non-numeric input.
    """
    numpy_in = is_numpy_like(normals)
    n = _normals(normals, "normals")
    r = _normals(reference, "reference").to(n.dtype)
    if r.shape != n.shape:
        raise ValueError(f"reference: expected shape {tuple(n.shape)}, got {tuple(r.shape)}")
    dot = (n.detach() * r).sum(-1)
    decided = torch.isfinite(dot) & (dot != 0)
    sign = torch.where(decided & (dot < 0), -1.0, 1.0).to(n.dtype)
    comp = torch.where(decided, 0, -1).to(torch.int64)
    return Oriented(
        to_like(n * sign[:, None], numpy_in), to_like(sign, numpy_in), to_like(comp, numpy_in)
    )


def mesh_reference_normals(vertices: Any, faces: Any) -> tuple[Any, Any]:
    """Area-weighted vertex normals of a mesh after making its winding consistent.

    Faces are re-wound with :func:`polygeo.mesh.orient_faces` (outward for closed
    components, fewest flips for open ones), so a mesh with half its faces flipped still gives
    coherent normals. Non-finite vertices and their faces are ignored.

    Parameters
    ----------
    vertices : (N, 3) float
        Vertex coordinates.
    faces : (F, 3) int
        Triangles.

    Returns
    -------
    normals : (N, 3) float
        Unit vertex normals, zero where undefined.
    valid : (N,) bool
        False for unreferenced vertices, vertices touching only degenerate or non-finite
        faces, or cancelling normals.

    Raises
    ------
    ValueError
        Bad shapes or face indices.
    TypeError
        Non-numeric input.
    """
    numpy_in = is_numpy_like(vertices)
    v = as_tensor(vertices, "vertices")
    check_shape(v, "vertices", ("N", 3))
    fin = torch.isfinite(v).all(-1)
    vf = torch.where(fin[:, None], v, torch.zeros_like(v))
    f = check_faces(faces, v.shape[0])
    good_face = fin[f].all(-1) if f.numel() else torch.zeros(0, dtype=torch.bool)
    fk = f[good_face].numpy()
    oriented = orient_faces(fk, vf.detach().cpu().to(torch.float64).numpy())
    vn = vertex_normals(vf, torch.from_numpy(np.ascontiguousarray(oriented.faces)), "area")
    valid = vn.valid & fin
    return to_like(vn.normals, numpy_in), to_like(valid, numpy_in)


def _group_argmax(key: np.ndarray, comp: np.ndarray, ncomp: int) -> np.ndarray:
    """Index of the largest ``key`` in each component (first one on ties), per component."""
    if ncomp == 1:
        return np.array([int(np.argmax(key))])
    mx = np.full(ncomp, -np.inf)
    np.maximum.at(mx, comp, key)
    hit = np.flatnonzero(key == mx[comp])
    _, first = np.unique(comp[hit], return_index=True)
    return hit[first]


def _parity_to_root(pred: np.ndarray, neg: np.ndarray) -> np.ndarray:
    """XOR of ``neg`` along each node's path to its tree root (pointer jumping, O(N log D))."""
    par = neg.copy()
    anc = pred.copy()
    active = anc >= 0
    while active.any():
        idx = np.flatnonzero(active)
        a = anc[idx]
        par[idx] ^= par[a]
        anc[idx] = anc[a]
        active[idx] = anc[idx] >= 0
    return par


def _knn_graph(idx: np.ndarray, nn: np.ndarray, ok: np.ndarray) -> sp.csr_matrix:
    """Directed k-NN graph ``(N, N)`` of the valid points, weights ``1 - |n_i . n_j|``."""
    npts = idx.shape[0]
    rows = np.repeat(np.arange(npts), idx.shape[1])
    cols = idx.reshape(-1)
    keep = (cols >= 0) & (cols != rows)
    rows, cols = rows[keep], cols[keep]
    keep = ok[rows] & ok[cols]
    rows, cols = rows[keep], cols[keep]
    w = 1.0 - np.abs(np.einsum("ij,ij->i", nn[rows], nn[cols])) + 1e-9
    return sp.coo_matrix((w, (rows, cols)), shape=(npts, npts)).tocsr()


def _component_seeds(pn, nn, ok, comp, ncomp):
    """Seed of each component: ``(seeds, score, direction from the centroid)``.

    Among the component's extreme points along +-x, +-y, +-z, the one whose normal is best
    aligned with the direction from the component's centroid (score ``|n . r| / |r|``, -1
    where no valid point was found); that normal is made to point away from the centroid.
    """
    cnt = np.bincount(comp, weights=ok.astype(float), minlength=ncomp)
    cen = np.stack(
        [np.bincount(comp, weights=np.where(ok, pn[:, a], 0.0), minlength=ncomp)
         for a in range(3)], 1,
    ) / np.maximum(cnt, 1)[:, None]
    best_score = np.full(ncomp, -1.0)
    seeds = np.zeros(ncomp, dtype=np.int64)
    for axis in range(3):
        for sgn in (1.0, -1.0):
            cand = _group_argmax(np.where(ok, sgn * pn[:, axis], -np.inf), comp, ncomp)
            radial = pn[cand] - cen[comp[cand]]
            rn = np.linalg.norm(radial, axis=1)
            dots = np.abs(np.einsum("ij,ij->i", nn[cand], radial))
            score = dots / np.where(rn > 0, rn, 1)
            better = score > best_score[comp[cand]] + 1e-12
            cc = comp[cand][better]
            best_score[cc] = score[better]
            seeds[cc] = cand[better]
    return seeds, best_score, pn[seeds] - cen[comp[seeds]]


def _tree_parity(tree: sp.csr_matrix, nn: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """Whether each normal disagrees an odd number of times with its ancestors in ``tree``.

    One breadth-first pass from a virtual root linked to every seed; ``False`` for points
    the pass does not reach.
    """
    npts = nn.shape[0]
    root = npts
    link = sp.coo_matrix(
        (np.ones(seeds.size), (np.full(seeds.size, root), seeds)),
        shape=(npts + 1, npts + 1),
    )
    big = sp.bmat([[tree, None], [None, sp.csr_matrix((1, 1))]]).tocsr() + link.tocsr()
    _, pr = breadth_first_order(big, root, directed=False, return_predecessors=True)
    pred = pr[:npts].astype(np.int64)
    pred[(pred == root) | (pred < 0)] = -1
    has = pred >= 0
    neg = np.zeros(npts, dtype=bool)
    neg[has] = np.einsum("ij,ij->i", nn[has], nn[pred[has]]) < 0
    return _parity_to_root(pred, neg)


def propagate_orientation(
    points: Any,
    normals: Any,
    k: int = 10,
    *,
    neighbors: Any = None,
    workers: int = -1,
) -> Oriented:
    """Orient normals consistently by propagation over the k-NN graph (Hoppe et al. 1992).

    Parameters
    ----------
    points : (N, 3) float
        Point coordinates.
    normals : (N, 3) float
        Unoriented unit normals. Points with non-finite or zero normals (or coordinates) are
        left out of the graph and keep their sign.
    k : int
        Neighbours per point of the graph (symmetrised), ``k >= 2``.
    neighbors : (N, K) int, optional
        Precomputed neighbour indices (``-1`` padding), used instead of a k-NN query.
    workers : int
        Threads of the k-NN query.

    Returns
    -------
    Oriented
        Normals, signs, and the connected component of each point in the graph. In each
        component the normal at the seed (the extreme point along one of +-x, +-y, +-z whose
        normal is best aligned with the direction from the component's centroid) points away
        from the centroid (outward on a closed surface) and every other normal agrees with
        its parent in the minimum spanning tree of weights ``1 - |n_i . n_j|``.

    Raises
    ------
    ValueError
        Bad shapes or ``k < 2``.
    TypeError
        Non-numeric input.
    """
    numpy_in = is_numpy_like(normals)
    p = _normals(points, "points")
    n = _normals(normals, "normals")
    if p.shape != n.shape:
        raise ValueError(f"normals: expected shape {tuple(p.shape)}, got {tuple(n.shape)}")
    k = check_int(k, "k", low=2)
    npts = p.shape[0]
    pn = p.detach().cpu().to(torch.float64).numpy()
    nn = n.detach().cpu().to(torch.float64).numpy()
    ok = np.isfinite(pn).all(1) & np.isfinite(nn).all(1) & (np.abs(nn).sum(1) > 0)
    if neighbors is None:
        pts = pn.copy()
        pts[~ok] = np.nan
        idx = knn(pts, min(k + 1, max(npts, 1)), workers=workers).index if npts else None
    else:
        it = as_tensor(neighbors, "neighbors", floating=False)
        check_shape(it, "neighbors", (npts, "K"))
        idx = it.to(torch.int64).numpy()
        if idx.size and idx.max() >= npts:
            raise ValueError(f"neighbors: expected indices < {npts}, got {idx.max()}")
    sign = np.ones(npts)
    comp_out = np.full(npts, -1, dtype=np.int64)
    if npts and idx is not None and idx.shape[1] > 0:
        g = _knn_graph(idx, nn, ok)
        ncomp, comp = connected_components(g, directed=False)
        tree = minimum_spanning_tree(g)  # treats the directed k-NN edges as undirected
        tree = tree.maximum(tree.T)
        seeds, best_score, seed_dir = _component_seeds(pn, nn, ok, comp, ncomp)
        parity = _tree_parity(tree, nn, seeds[(best_score >= 0) & ok[seeds]])
        seed_flip = np.einsum("ij,ij->i", nn[seeds], seed_dir) < 0
        flip = (parity ^ seed_flip[comp]) & ok
        sign = np.where(flip, -1.0, 1.0)
        comp_out = np.where(ok, comp, -1).astype(np.int64)
    s_t = torch.from_numpy(sign).to(n.dtype)
    return Oriented(
        to_like(n * s_t[:, None], numpy_in),
        to_like(s_t, numpy_in),
        to_like(torch.from_numpy(comp_out), numpy_in),
    )
