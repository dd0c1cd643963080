"""Partition of a surface into K connected patches of near-equal area (ACVD-like).

Meshes are clustered with approximated centroidal Voronoi diagrams (Valette & Chassery 2004,
through ``pyacvd``) on a private copy of the mesh; point clouds (no connectivity) are
clustered by farthest-point seeds refined with k-means, connectivity coming from a symmetric
k-nearest-neighbour graph. Both are then post-processed so that every patch is non-empty
and connected: clusters that fall apart are split into their connected pieces, and pieces
that are too small (fewer than ``min_vertices`` vertices or less than ``merge_fraction`` of
the mean patch area) are merged into the neighbouring piece with which they share the most
edges. The result is deterministic for a given ``seed``.

Outputs are NumPy arrays (a partition is a discrete structure, not something one
differentiates through).

Conventions
-----------
* ``labels[i]`` is the patch of vertex ``i``; patches are numbered ``0..K-1`` in the order
  of their lowest vertex index.
* Vertices that no face references are given the patch of their nearest referenced vertex
  (they cannot be connected to anything, so they are not counted when checking
  connectivity).
* The number of patches returned can differ from the number requested: ACVD may return
  fewer clusters on small meshes, splitting adds pieces and merging removes them, and a
  mesh with C connected components always has at least C patches.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .checks import as_tensor, check_faces, check_finite, check_int, check_positive, check_shape
from .mesh import edges as mesh_edges

__all__ = [
    "Partition",
    "default_n_patches",
    "patch_count_for_vertices",
    "partition",
    "partition_mesh",
    "partition_points",
    "mesh_area",
]

#: Area (in squared scene units, metres for garments) per patch of the thesis' default rule.
AREA_PER_PATCH = 0.008


@dataclass(frozen=True)
class Partition:
    """A partition of the V vertices (or points) of a surface into K connected patches.

    Attributes
    ----------
    labels : np.ndarray, shape (V,), int64
        Patch of every vertex, in ``[0, K)``.
    n_patches : int
        K, the number of patches; every patch is non-empty.
    adjacency : np.ndarray, shape (A, 2), int64
        Pairs ``(a, b)`` with ``a < b`` of patches that share at least one edge, sorted
        lexicographically (an edge list of the patch graph; see :meth:`adjacency_matrix`).
    boundary_pairs : np.ndarray, shape (E_b, 2), int64
        Edges ``(i, j)``, ``i < j``, of the mesh (or of the k-NN graph for point clouds) whose
        ends lie in different patches, sorted lexicographically.
    areas : np.ndarray, shape (K,), float64
        Area of each patch in squared input units (sum of the barycentric vertex areas, or of
        the per-point area estimate for point clouds).
    """

    labels: np.ndarray
    n_patches: int
    adjacency: np.ndarray
    boundary_pairs: np.ndarray
    areas: np.ndarray

    @property
    def sizes(self) -> np.ndarray:
        """Number of vertices per patch, shape (K,), int64."""
        return np.bincount(self.labels, minlength=self.n_patches)

    @property
    def area_cv(self) -> float:
        """Coefficient of variation (std / mean) of the patch areas; 0 for a single patch."""
        mean = float(self.areas.mean())
        return float(self.areas.std() / mean) if mean > 0 else 0.0

    def members(self, patch: int) -> np.ndarray:
        """Indices of the vertices of patch ``patch``, shape (n,), int64, ascending."""
        patch = check_int(patch, "patch", low=0, high=self.n_patches - 1)
        return np.flatnonzero(self.labels == patch)

    def adjacency_matrix(self) -> sp.csr_matrix:
        """Symmetric (K, K) CSR matrix of the patch graph; entry = number of shared edges."""
        a = self.labels[self.boundary_pairs[:, 0]]
        b = self.labels[self.boundary_pairs[:, 1]]
        n = self.n_patches
        m = sp.coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n)).tocsr()
        return (m + m.T).tocsr()


def default_n_patches(area: float) -> int:
    """The thesis' default patch count ``max(100, min(400, floor(area / 0.008)))``.

    Parameters
    ----------
    area : float
        Surface area in square metres (garment scale).

    Returns
    -------
    int
        Number of patches K in [100, 400].

    Raises
    ------
    ValueError
        If ``area`` is negative or not finite.
    """
    a = check_positive(area, "area", strict=False)
    return int(max(100, min(400, np.floor(a / AREA_PER_PATCH))))


#: Vertices per jet coefficient of a patch under :func:`patch_count_for_vertices`.
VERTICES_PER_COEFF = 6.0


def patch_count_for_vertices(n_vertices: int, n_coeffs: int, *, high: int = 400) -> int:
    """A scale-free patch count: enough vertices in every patch for its jet.

    ``K = clip(floor(V / (6 M)), 1, high)`` for ``V`` vertices and jets of ``M``
    coefficients (15 for order 4): each patch holds about six vertices per coefficient, so
    the jet is fitted (not interpolated) whatever the units of the input, unlike
    :func:`default_n_patches`, whose area rule assumes metres.

    Parameters
    ----------
    n_vertices : int
        Number of vertices (or points) V >= 1.
    n_coeffs : int
        Coefficients per patch jet, M >= 1.
    high : int
        Largest count returned.

    Returns
    -------
    int
        K in ``[1, high]``.

    Raises
    ------
    ValueError
        If an argument is not a positive integer.
    """
    v = check_int(n_vertices, "n_vertices", low=1)
    m = check_int(n_coeffs, "n_coeffs", low=1)
    hi = check_int(high, "high", low=1)
    return int(max(1, min(hi, np.floor(v / (VERTICES_PER_COEFF * m)))))


# ----------------------------------------------------------------------------- helpers


def _vertices_np(x: Any, name: str) -> np.ndarray:
    t = as_tensor(x, name)
    check_shape(t, name, ("V", 3))
    check_finite(t, name)
    if t.shape[0] == 0:
        raise ValueError(f"{name}: expected at least one point, got shape {tuple(t.shape)}")
    return t.detach().cpu().numpy().astype(np.float64, copy=True)


def _clean_faces(faces: np.ndarray) -> np.ndarray:
    """Drop faces that repeat a vertex (no area, no orientation)."""
    ok = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    return faces[ok]


def _unique_pairs(pairs: np.ndarray) -> np.ndarray:
    """Unique unordered pairs ``(i, j)``, ``i <= j``, sorted lexicographically, shape (E, 2)."""
    if len(pairs) == 0:
        return np.zeros((0, 2), np.int64)
    lo = np.minimum(pairs[:, 0], pairs[:, 1]).astype(np.int64)
    hi = np.maximum(pairs[:, 0], pairs[:, 1]).astype(np.int64)
    n = int(hi.max()) + 1
    key = np.sort(lo * n + hi)
    key = key[np.concatenate([[True], key[1:] != key[:-1]])]
    return np.stack([key // n, key % n], axis=1)


def _vertex_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Barycentric vertex areas (one third of the incident triangle areas), shape (V,)."""
    if len(faces) == 0:
        return np.zeros(len(vertices))
    p = vertices[faces]
    fa = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    out = np.zeros(len(vertices))
    np.add.at(out, faces.ravel(), np.repeat(fa / 3.0, 3))
    return out


def mesh_area(vertices: Any, faces: Any) -> float:
    """Total area of a triangle mesh, in squared input units.

    Parameters
    ----------
    vertices : array_like, shape (V, 3)
        Vertex positions.
    faces : array_like, shape (F, 3), integer
        Triangles.

    Returns
    -------
    float
        Sum of the triangle areas.

    Raises
    ------
    ValueError
        On bad shapes, non-finite vertices or out-of-range indices.
    TypeError
        If ``faces`` is not an integer array.
    """
    v = _vertices_np(vertices, "vertices")
    f = check_faces(faces, len(v)).cpu().numpy()
    return float(_vertex_areas(v, f).sum())


def _split_and_merge(
    labels: np.ndarray,
    edges: np.ndarray,
    vertex_areas: np.ndarray,
    active: np.ndarray,
    min_vertices: int,
    min_area: float,
) -> np.ndarray:
    """Make every patch connected and not tiny.

    Parameters
    ----------
    labels : (V,) int64
        Initial cluster per vertex (any integers).
    edges : (E, 2) int64
        Graph edges.
    vertex_areas : (V,) float64
        Area carried by every vertex.
    active : (V,) bool
        Vertices that take part in the graph (inactive ones are relabelled afterwards).
    min_vertices, min_area
        Pieces below either threshold are merged into a neighbour (if they have one).

    Returns
    -------
    (V,) int64
        Piece id per active vertex, numbered by lowest vertex index; -1 for inactive ones.
    """
    n = len(labels)
    same = labels[edges[:, 0]] == labels[edges[:, 1]]
    e_in = edges[same]
    g = sp.coo_matrix((np.ones(len(e_in)), (e_in[:, 0], e_in[:, 1])), shape=(n, n))
    _, piece = connected_components(g, directed=False)
    piece = piece.astype(np.int64)
    # Union-find over pieces for the merges.
    n_pieces = int(piece.max()) + 1
    parent = np.arange(n_pieces)

    def find(a: np.ndarray) -> np.ndarray:
        a = a.copy()
        while True:
            p = parent[a]
            if np.array_equal(p, a):
                return a
            a = p

    for _ in range(64):
        root = find(piece)
        cnt = np.bincount(root, weights=active.astype(float), minlength=n_pieces)
        area = np.bincount(root, weights=vertex_areas, minlength=n_pieces)
        tiny = ((cnt < min_vertices) | (area < min_area)) & (cnt > 0)
        if not tiny.any():
            break
        ra, rb = root[edges[:, 0]], root[edges[:, 1]]
        cross = ra != rb
        ra, rb = ra[cross], rb[cross]
        if len(ra) == 0:
            break
        # shared-edge counts between pieces, symmetric
        pa = np.concatenate([ra, rb])
        pb = np.concatenate([rb, ra])
        w = sp.coo_matrix((np.ones(len(pa)), (pa, pb)), shape=(n_pieces, n_pieces)).tocsr()
        w.sum_duplicates()
        merged_any = False
        # smallest pieces first; each tiny piece joins its most connected neighbour
        order = np.flatnonzero(tiny)
        order = order[np.lexsort((order, area[order]))]
        for a in order:
            ra_ = find(np.array([a]))[0]
            row = w.getrow(a)
            if row.nnz == 0:
                continue
            nb = row.indices
            vals = row.data
            # prefer the strongest link; ties broken by the lowest piece id
            best = nb[np.lexsort((nb, -vals))[0]]
            rb_ = find(np.array([best]))[0]
            if rb_ != ra_:
                parent[ra_] = rb_
                merged_any = True
        if not merged_any:
            break
    root = find(piece)
    root[~active] = -1
    # renumber by the lowest active vertex index of each piece
    out = np.full(n, -1, np.int64)
    idx = np.flatnonzero(active)
    _, first = np.unique(root[idx], return_index=True)
    roots_in_order = root[idx][np.sort(first)]
    remap = np.full(n_pieces, -1, np.int64)
    remap[roots_in_order] = np.arange(len(roots_in_order))
    out[idx] = remap[root[idx]]
    return out


def _finish(
    labels: np.ndarray,
    edges: np.ndarray,
    vertex_areas: np.ndarray,
    points: np.ndarray,
    active: np.ndarray,
) -> Partition:
    """Give inactive vertices the patch of their nearest active vertex; build a Partition."""
    if (~active).any():
        idx = np.flatnonzero(active)
        _, nn = cKDTree(points[idx]).query(points[~active], k=1)
        labels = labels.copy()
        labels[~active] = labels[idx[np.asarray(nn, np.int64)]]
    n_patches = int(labels.max()) + 1
    diff = labels[edges[:, 0]] != labels[edges[:, 1]]
    bp = edges[diff]
    bp = _unique_pairs(bp)
    adj = _unique_pairs(np.stack([labels[bp[:, 0]], labels[bp[:, 1]]], axis=1))
    areas = np.bincount(labels, weights=vertex_areas, minlength=n_patches)
    for arr in (labels, bp, adj, areas):
        arr.setflags(write=False)
    return Partition(
        labels=labels,
        n_patches=n_patches,
        adjacency=adj.astype(np.int64),
        boundary_pairs=bp.astype(np.int64),
        areas=areas,
    )


def _check_n_patches(n_patches: Any, n_vertices: int) -> int:
    n = check_int(n_patches, "n_patches", low=1)
    if n > n_vertices:
        raise ValueError(
            f"n_patches: expected at most the number of vertices ({n_vertices}), got {n}"
        )
    return n


# ----------------------------------------------------------------------------- meshes


def partition_mesh(
    vertices: Any,
    faces: Any,
    n_patches: int | None = None,
    *,
    seed: int | None = 0,
    min_vertices: int = 1,
    merge_fraction: float = 0.25,
    maxiter: int = 100,
) -> Partition:
    """Cluster a triangle mesh into connected patches of near-equal area (ACVD).

    Parameters
    ----------
    vertices : array_like or torch.Tensor, shape (V, 3), float
        Vertex positions (any length unit; the default K assumes metres). Never modified.
    faces : array_like or torch.Tensor, shape (F, 3), integer
        Triangles. Faces repeating a vertex are ignored; non-manifold edges, zero-area faces,
        unreferenced vertices and several connected components are accepted.
    n_patches : int, optional
        Requested K in ``[1, V]``. Default: :func:`default_n_patches` of the mesh area. K = 1
        gives one patch per connected component.
    seed : int or None
        The vertex order seen by ACVD is permuted with this seed (None: input order), which
        makes the result deterministic for a seed and varied across seeds.
    min_vertices : int
        Pieces with fewer vertices are merged into a neighbour (e.g. the number of jet
        coefficients); 1 keeps every non-empty piece.
    merge_fraction : float
        Pieces with area below ``merge_fraction * area / K`` are merged into a neighbour.
    maxiter : int
        ACVD iterations.

    Returns
    -------
    Partition
        Labels, patch count, patch adjacency, boundary pairs (mesh edges across patches) and
        patch areas.

    Raises
    ------
    ValueError
        On bad shapes, non-finite vertices, out-of-range face indices, a mesh without any
        valid face, or ``n_patches`` outside ``[1, V]``.
    TypeError
        If ``faces`` is not an integer array or an integer argument is not an integer.
    """
    import pyacvd
    import pyvista as pv

    v = _vertices_np(vertices, "vertices")
    f = _clean_faces(check_faces(faces, len(v)).cpu().numpy())
    if len(f) == 0:
        raise ValueError("faces: expected at least one non-degenerate triangle, got none")
    min_vertices = check_int(min_vertices, "min_vertices", low=1)
    merge_fraction = check_positive(merge_fraction, "merge_fraction", strict=False)
    maxiter = check_int(maxiter, "maxiter", low=1)
    vert_area = _vertex_areas(v, f)
    total = float(vert_area.sum())
    if n_patches is None:
        n_patches = min(default_n_patches(total), len(v))
    else:
        n_patches = _check_n_patches(n_patches, len(v))

    # ACVD on a private, compact copy: referenced vertices only, permuted by the seed.
    used = np.zeros(len(v), bool)
    used[f.ravel()] = True
    used_idx = np.flatnonzero(used)
    if seed is not None:
        perm = np.random.default_rng(seed).permutation(len(used_idx))
        used_idx = used_idx[perm]
    local = np.full(len(v), -1, np.int64)
    local[used_idx] = np.arange(len(used_idx))
    lf = local[f]
    cells = np.hstack([np.full((len(lf), 1), 3, np.int64), lf]).ravel()
    poly = pv.PolyData(v[used_idx].copy(), cells)
    n_acvd = min(n_patches, len(used_idx))
    if n_acvd == 1:
        lab_local = np.zeros(len(used_idx), np.int64)
    else:
        with warnings.catch_warnings():  # pyacvd uses a deprecated pyvista accessor
            warnings.simplefilter("ignore")
            clus = pyacvd.Clustering(poly)
            lab_local = np.asarray(clus.cluster(n_acvd, maxiter=maxiter), np.int64)
    labels = np.full(len(v), -1, np.int64)
    labels[used_idx] = lab_local
    if (labels[used] < 0).any():  # ACVD left a vertex unassigned: give it its own cluster
        bad = used & (labels < 0)
        labels[bad] = labels.max() + 1 + np.arange(int(bad.sum()))

    edges = mesh_edges(f)
    min_area = merge_fraction * total / n_patches
    pieces = _split_and_merge(labels, edges, vert_area, used, min_vertices, min_area)
    return _finish(pieces, edges, vert_area, v, used)


# ----------------------------------------------------------------------------- point clouds


def _farthest_point_seeds(points: np.ndarray, n_seeds: int,
                          rng: np.random.Generator) -> np.ndarray:
    """Indices of ``n_seeds`` farthest-point samples, starting from a seeded random point."""
    n = len(points)
    idx = np.empty(n_seeds, np.int64)
    idx[0] = rng.integers(n)
    d = np.sum((points - points[idx[0]]) ** 2, axis=1)
    for i in range(1, n_seeds):
        idx[i] = int(np.argmax(d))
        d = np.minimum(d, np.sum((points - points[idx[i]]) ** 2, axis=1))
    return idx


def partition_points(
    points: Any,
    n_patches: int | None = None,
    *,
    k_neighbors: int = 10,
    seed: int | None = 0,
    kmeans_iters: int = 10,
    min_vertices: int = 1,
    merge_fraction: float = 0.25,
) -> Partition:
    """Cluster a point cloud (no connectivity) into connected patches of near-equal area.

    Farthest-point seeds (the first one drawn with ``seed``) are refined by Lloyd k-means
    iterations in 3-D; connectivity, boundary pairs and the connected-piece post-processing
    use the symmetric ``k_neighbors``-nearest-neighbour graph. The area of a point is
    estimated as ``pi * r**2 / k_neighbors`` with ``r`` the distance to its
    ``k_neighbors``-th neighbour.

    Parameters
    ----------
    points : array_like or torch.Tensor, shape (V, 3), float
        Sample positions. Never modified.
    n_patches : int, optional
        Requested K in ``[1, V]``; default :func:`default_n_patches` of the estimated area.
    k_neighbors : int
        Neighbours per point in the connectivity graph (>= 1).
    seed : int or None
        Seed of the first farthest-point seed (None: point 0).
    kmeans_iters : int
        Lloyd iterations after the farthest-point initialisation.
    min_vertices, merge_fraction
        As in :func:`partition_mesh`.

    Returns
    -------
    Partition
        ``boundary_pairs`` are k-NN graph edges across patches.

    Raises
    ------
    ValueError
        On bad shapes, non-finite points or ``n_patches`` outside ``[1, V]``.
    TypeError
        If an integer argument is not an integer.
    """
    p = _vertices_np(points, "points")
    n = len(p)
    k_nb = check_int(k_neighbors, "k_neighbors", low=1)
    kmeans_iters = check_int(kmeans_iters, "kmeans_iters", low=0)
    min_vertices = check_int(min_vertices, "min_vertices", low=1)
    merge_fraction = check_positive(merge_fraction, "merge_fraction", strict=False)
    kq = min(k_nb, n - 1)
    tree = cKDTree(p)
    if kq >= 1:
        dist, nb = tree.query(p, k=kq + 1)
        r = dist[:, -1]
        rows = np.repeat(np.arange(n), kq)
        edges = np.stack([rows, nb[:, 1:].ravel()], axis=1)
        edges = _unique_pairs(edges[edges[:, 0] != edges[:, 1]])
    else:
        r = np.zeros(n)
        edges = np.zeros((0, 2), np.int64)
    vert_area = np.pi * r**2 / max(kq, 1)
    total = float(vert_area.sum())
    if n_patches is None:
        n_patches = min(default_n_patches(total), n)
    else:
        n_patches = _check_n_patches(n_patches, n)
    rng = np.random.default_rng(seed)
    if n_patches == 1:
        labels = np.zeros(n, np.int64)
    else:
        seed_rng = rng if seed is not None else np.random.default_rng(0)
        seeds = _farthest_point_seeds(p, n_patches, seed_rng)
        if seed is None:
            seeds[0] = 0
        centers = p[seeds].copy()
        labels = np.zeros(n, np.int64)
        for it in range(kmeans_iters + 1):
            _, labels = cKDTree(centers).query(p, k=1)
            labels = np.asarray(labels, np.int64)
            if it == kmeans_iters:
                break
            cnt = np.bincount(labels, minlength=n_patches)
            sums = np.stack(
                [np.bincount(labels, weights=p[:, d], minlength=n_patches) for d in range(3)],
                axis=1,
            )
            nonempty = cnt > 0
            centers[nonempty] = sums[nonempty] / cnt[nonempty, None]
    active = np.ones(n, bool)
    pieces = _split_and_merge(
        labels, edges, vert_area, active, min_vertices, merge_fraction * total / n_patches
    )
    return _finish(pieces, edges, vert_area, p, active)


def partition(
    points: Any,
    faces: Any = None,
    n_patches: int | None = None,
    **kwargs: Any,
) -> Partition:
    """Partition a mesh (``faces`` given) or a point cloud (``faces=None``) into patches.

    Parameters
    ----------
    points : array_like or torch.Tensor, shape (V, 3), float
        Vertex or point positions.
    faces : array_like or torch.Tensor, shape (F, 3), integer, optional
        Triangles; None for a point cloud.
    n_patches : int, optional
        Requested K (default: the thesis rule on the surface area).
    **kwargs
        Passed to :func:`partition_mesh` or :func:`partition_points`.

    Returns
    -------
    Partition
        See :class:`Partition`.

    Raises
    ------
    ValueError, TypeError
        As the function called.
    """
    if faces is None:
        return partition_points(points, n_patches, **kwargs)
    return partition_mesh(points, faces, n_patches, **kwargs)
