"""Neighbourhoods of point clouds and meshes: k-NN, radius balls, mesh k-rings.

All functions accept NumPy arrays or torch tensors and return the input's array type
(torch tensors come back on the CPU, as int64 / the input's floating dtype). Variable-size
neighbourhoods are padded with ``-1`` in ``index`` and ``False`` in ``mask``, never truncated
silently.

Non-finite points (NaN/inf coordinates) are never returned as neighbours of anything, and a
non-finite query gets an empty neighbourhood (all ``-1``); this is what lets one NaN point
among valid ones leave every other estimate untouched.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numba as nb
import numpy as np
import scipy.sparse as sp
import torch
from scipy.spatial import cKDTree

from ._numba_util import finite_rows, njit_pair
from .checks import (
    as_tensor,
    check_choice,
    check_faces,
    check_int,
    check_positive,
    check_shape,
    is_numpy_like,
)
from .mesh import vertex_adjacency

__all__ = [
    "PointIndex",
    "Neighbors",
    "KRing",
    "knn",
    "radius_neighbors",
    "mesh_k_ring",
    "reaches_non_manifold",
    "vertex_adjacency",  # re-exported from polygeo.mesh, its home
]


class Neighbors(NamedTuple):
    """Padded neighbourhoods of ``Q`` query points.

    Attributes
    ----------
    index : (Q, K) int64
        Indices into the searched points, nearest first; ``-1`` marks padding.
    distance : (Q, K) float
        Euclidean distances, same unit as the coordinates; ``inf`` where padded.
    mask : (Q, K) bool
        ``index >= 0``.
    """

    index: Any
    distance: Any
    mask: Any


class KRing(NamedTuple):
    """Padded mesh k-rings of every vertex.

    Attributes
    ----------
    index : (N, K) int64
        Vertex indices sorted by hop count then index; the vertex itself first when
        ``include_self``; ``-1`` marks padding.
    hops : (N, K) int64
        Graph distance (number of edges) of each entry; ``-1`` where padded.
    mask : (N, K) bool
        ``index >= 0``.
    """

    index: Any
    hops: Any
    mask: Any


# --------------------------------------------------------------------------- helpers


def _points_np(x: Any, name: str) -> tuple[np.ndarray, bool, torch.dtype | None]:
    """Validate an (N, 3) coordinate array; return float64 NumPy, numpy-ness and dtype."""
    numpy_in = is_numpy_like(x)
    t = as_tensor(x, name)
    check_shape(t, name, ("N", 3))
    return t.detach().cpu().to(torch.float64).numpy(), numpy_in, t.dtype


def _out(arr: np.ndarray, numpy_in: bool, dtype: torch.dtype | None = None) -> Any:
    if numpy_in:
        return arr
    t = torch.from_numpy(np.ascontiguousarray(arr))
    return t.to(dtype) if dtype is not None else t


def _workers(workers: int) -> int:
    w = check_int(workers, "workers")
    if w == 0 or w < -1:
        raise ValueError(f"workers: expected -1 (all cores) or a positive integer, got {w}")
    return w


def _put_self_first(index: np.ndarray, dist: np.ndarray, self_idx: np.ndarray) -> None:
    """In place: make column 0 of each row the query point itself (rows of finite queries)."""
    if index.shape[1] == 0 or self_idx.size == 0:
        return
    rows = np.arange(index.shape[0])
    bad = index[:, 0] != self_idx
    if not bad.any():
        return
    r = rows[bad]
    sub = index[r]
    hit = sub == self_idx[bad, None]
    found = hit.any(axis=1)
    pos = np.where(found, hit.argmax(axis=1), index.shape[1] - 1)
    # shift entries [0, pos) right by one and put self at 0 (a swap would break the sort)
    k = index.shape[1]
    cols = np.arange(k)
    src = np.where(cols[None, :] <= pos[:, None], cols[None, :] - 1, cols[None, :])
    src[:, 0] = 0
    new_idx = np.take_along_axis(sub, np.maximum(src, 0), axis=1)
    new_dist = np.take_along_axis(dist[r], np.maximum(src, 0), axis=1)
    new_idx[:, 0] = self_idx[bad]
    new_dist[:, 0] = 0.0
    index[r] = new_idx
    dist[r] = new_dist


# --------------------------------------------------------------------------- uniform grid k-NN

_GRID_CHUNK = 64  # queries per parallel task


def _grid_query_py(P, order, cstart, lo, h, nx, ny, nz, Q, qorder, k, out_i, out_d):
    """Exact k-NN by expanding shells of cells of a uniform grid.

    ``P`` holds the points sorted by cell (``P[s]`` is original point ``order[s]``).

    The search stops after shell r once the k-th best distance is within r * h plus the
    query's distance to its own cell's faces: every unvisited point is farther than that.
    The sorted best-k list lives in small per-task arrays (in L1) and is copied out once.
    """
    nq = Q.shape[0]
    maxr = max(nx, max(ny, nz))
    nchunk = (nq + _GRID_CHUNK - 1) // _GRID_CHUNK
    for ch in nb.prange(nchunk):
        ld = np.empty(k)
        li = np.empty(k, dtype=np.int64)
        # previous query of this task and its k-th distance: by the triangle inequality the
        # k-th distance of the next query is at most kprev + |q - qprev| (a pruning bound)
        px = py = pz = 0.0
        kprev = -1.0
        for t in range(ch * _GRID_CHUNK, min(nq, (ch + 1) * _GRID_CHUNK)):
            qi = qorder[t]
            qx, qy, qz = Q[qi, 0], Q[qi, 1], Q[qi, 2]
            fx = (qx - lo[0]) / h
            fy = (qy - lo[1]) / h
            fz = (qz - lo[2]) / h
            cx = min(max(int(fx), 0), nx - 1)
            cy = min(max(int(fy), 0), ny - 1)
            cz = min(max(int(fz), 0), nz - 1)
            bx = min(fx - cx, cx + 1 - fx)
            by = min(fy - cy, cy + 1 - fy)
            bz = min(fz - cz, cz + 1 - fz)
            b0 = max(min(bx, min(by, bz)), 0.0) * h
            cap = np.inf
            if kprev >= 0.0:
                dq = math.sqrt((qx - px) ** 2 + (qy - py) ** 2 + (qz - pz) ** 2)
                cap = ((kprev + dq) * (1.0 + 1e-9)) ** 2 + 1e-300
            cnt = 0
            for attempt in range(2):
                if attempt == 1:
                    if cnt == k or cap == np.inf:
                        break
                    cap = np.inf  # rounding defeated the bound: search again without it
                    cnt = 0
                worst = cap  # while cnt < k: the pruning bound, then the k-th best
                for r in range(maxr + 1):
                    z0 = max(cz - r, 0)
                    z1 = min(cz + r, nz - 1)
                    y0 = max(cy - r, 0)
                    y1 = min(cy + r, ny - 1)
                    for z in range(z0, z1 + 1):
                        for y in range(y0, y1 + 1):
                            edge = abs(z - cz) == r or abs(y - cy) == r
                            x = cx - r
                            while x <= cx + r:
                                if x >= 0 and x < nx:
                                    c = x + nx * (y + ny * z)
                                    for s in range(cstart[c], cstart[c + 1]):
                                        ex = P[s, 0] - qx  # P sorted by cell: contiguous reads
                                        ey = P[s, 1] - qy
                                        ez = P[s, 2] - qz
                                        d2 = ex * ex + ey * ey + ez * ez
                                        if d2 > worst:
                                            continue
                                        p = order[s]
                                        if cnt < k:
                                            j = cnt
                                            cnt += 1
                                        elif d2 < worst or p < li[k - 1]:
                                            j = k - 1
                                        else:
                                            continue
                                        while j > 0 and (
                                            ld[j - 1] > d2
                                            or (ld[j - 1] == d2 and li[j - 1] > p)
                                        ):
                                            ld[j] = ld[j - 1]
                                            li[j] = li[j - 1]
                                            j -= 1
                                        ld[j] = d2
                                        li[j] = p
                                        if cnt == k:
                                            worst = ld[k - 1]
                                if edge or r == 0:
                                    x += 1
                                else:
                                    x += 2 * r
                    bound = r * h + b0
                    if cnt == k and worst <= bound * bound:
                        break
            for j in range(cnt):
                out_d[qi, j] = math.sqrt(ld[j])
                out_i[qi, j] = li[j]
            for j in range(cnt, k):
                out_d[qi, j] = np.inf
                out_i[qi, j] = -1
            if cnt == k:
                px, py, pz = qx, qy, qz
                kprev = math.sqrt(ld[k - 1])
            else:
                kprev = -1.0


_grid_query_par, _grid_query_ser = njit_pair(_grid_query_py)


@nb.njit(cache=True)
def _bbox(pts):
    """Per-axis minimum and maximum of the finite ``(N, 3)`` points (as ``min(0)``, ``max(0)``)."""
    lo = pts[0].copy()
    hi = pts[0].copy()
    for i in range(1, pts.shape[0]):
        for j in range(3):
            v = pts[i, j]
            if v < lo[j]:
                lo[j] = v
            if v > hi[j]:
                hi[j] = v
    return lo, hi


@nb.njit(cache=True)
def _cell_keys(pts, lo, h, nx, ny, nz):
    """Flat cell index of each point (x fastest), as ``min(int((p - lo) / h), dim - 1)``."""
    n = pts.shape[0]
    key = np.empty(n, dtype=np.int64)
    for i in range(n):
        ix = min(int((pts[i, 0] - lo[0]) / h), nx - 1)
        iy = min(int((pts[i, 1] - lo[1]) / h), ny - 1)
        iz = min(int((pts[i, 2] - lo[2]) / h), nz - 1)
        key[i] = ix + nx * (iy + ny * iz)
    return key


@nb.njit(cache=True)
def _counting_sort(pts, key, size):
    """Stable order of the points by cell, cell start offsets and the sorted points."""
    n = key.shape[0]
    cstart = np.zeros(size + 1, dtype=np.int64)
    for i in range(n):
        cstart[key[i] + 1] += 1
    for c in range(size):
        cstart[c + 1] += cstart[c]
    fill = cstart[:-1].copy()
    order = np.empty(n, dtype=np.int64)
    sorted_pts = np.empty((n, 3))
    for i in range(n):
        s = fill[key[i]]
        fill[key[i]] = s + 1
        order[s] = i
        sorted_pts[s, 0] = pts[i, 0]
        sorted_pts[s, 1] = pts[i, 1]
        sorted_pts[s, 2] = pts[i, 2]
    return order, cstart, sorted_pts


@nb.njit(cache=True)
def _query_order(q, lo, h, nx, ny, nz):
    """Queries ordered by the grid cell containing (or nearest to) them; stable."""
    n = q.shape[0]
    key = np.empty(n, dtype=np.int64)
    for i in range(n):
        ix = int(min(max((q[i, 0] - lo[0]) / h, 0.0), nx - 1.0))
        iy = int(min(max((q[i, 1] - lo[1]) / h, 0.0), ny - 1.0))
        iz = int(min(max((q[i, 2] - lo[2]) / h, 0.0), nz - 1.0))
        key[i] = ix + nx * (iy + ny * iz)
    fill = np.zeros(nx * ny * nz + 1, dtype=np.int64)
    for i in range(n):
        fill[key[i] + 1] += 1
    for c in range(nx * ny * nz):
        fill[c + 1] += fill[c]
    order = np.empty(n, dtype=np.int64)
    for i in range(n):
        order[fill[key[i]]] = i
        fill[key[i]] += 1
    return order


class _Grid:
    """Uniform grid over finite points, sized for about ``ppc`` points per occupied cell."""

    def __init__(self, pts: np.ndarray, ppc: float) -> None:
        n = pts.shape[0]
        self.ok = False
        if n == 0:
            return
        lo, hi = _bbox(pts)
        ext = np.maximum(hi - lo, 1e-300)
        # a surface in a cube of G cells occupies about G^(2/3) of them
        g = min((n / ppc) ** 1.5, 4.0 * n + 8)
        h = float((np.prod(ext) / g) ** (1 / 3))
        h = max(h, float(ext.max()) * 1e-6)
        key = dims = None
        occ = 0.0
        for _ in range(10):
            dims = np.maximum(np.ceil(ext / h).astype(np.int64), 1)
            if float(np.prod(dims.astype(np.float64))) > 8.0 * n + 64:
                h *= 1.26
                continue
            key = _cell_keys(pts, lo, h, int(dims[0]), int(dims[1]), int(dims[2]))
            occ = n / max(int(np.count_nonzero(np.bincount(key))), 1)
            if occ >= ppc / 2:
                break
            h *= min((ppc / occ) ** 0.5, 2.0)
        if key is None or occ > 16 * ppc:
            return  # very uneven density (outliers): the k-d tree is safer
        size = int(np.prod(dims))
        # a stable counting sort by cell (same order as a stable argsort of the keys)
        self.order, self.cstart, self.sorted_pts = _counting_sort(pts, key, size)
        self.lo, self.h, self.dims = lo, h, dims
        self.ok = True

    def query(self, q: np.ndarray, k: int, parallel: bool) -> tuple[np.ndarray, np.ndarray]:
        nq = q.shape[0]
        out_i = np.empty((nq, k), dtype=np.int64)
        out_d = np.empty((nq, k))
        if nq == 0:
            return out_i, out_d
        nx, ny, nz = (int(d) for d in self.dims)
        qorder = _query_order(q, self.lo, self.h, nx, ny, nz)
        fn = _grid_query_par if parallel else _grid_query_ser
        fn(self.sorted_pts, self.order, self.cstart, self.lo, self.h, nx, ny, nz, q, qorder, k,
           out_i, out_d)
        return out_i, out_d



class PointIndex:
    """A k-d tree over the finite points of a cloud, queried many times (e.g. in chunks).

    Parameters
    ----------
    points : (N, 3) float64 ndarray
        Coordinates; non-finite rows are left out of the tree and never returned.
    method : {"auto", "grid", "kdtree"}
        k-NN engine: a uniform grid searched in expanding shells (compiled, parallel; about
        twice as fast as the k-d tree on surface samples) or ``scipy.spatial.cKDTree``.
        "auto" uses the grid unless the density is very uneven; radius queries always use
        the k-d tree. Both are exact (ties broken by lower index in the grid).

    Notes
    -----
    This is the reusable engine behind :func:`knn` and :func:`radius_neighbors`; it works on
    NumPy float64 arrays only (no validation, no type conversion).
    """

    def __init__(self, points: np.ndarray, method: str = "auto", ppc: float = 8.0) -> None:
        self.points = points
        fin = finite_rows(points)
        self.n_finite = int(fin.sum())
        self._all_finite = self.n_finite == points.shape[0]
        self._map = None if self._all_finite else np.flatnonzero(fin)
        data = points if self._all_finite else points[fin]
        self._data = np.ascontiguousarray(data)
        self.grid = _Grid(self._data, ppc) if method in ("auto", "grid") else None
        if self.grid is not None and not self.grid.ok:
            self.grid = None
        self._tree = None

    def spatial_order(self) -> np.ndarray | None:
        """Indices of all points ordered by grid cell (finite first), or None without a grid."""
        if self.grid is None:
            return None
        fin_idx = self.grid.order if self._map is None else self._map[self.grid.order]
        if self._map is None:
            return fin_idx
        rest = np.setdiff1d(np.arange(self.points.shape[0]), self._map, assume_unique=True)
        return np.concatenate([fin_idx, rest])

    @property
    def tree(self) -> cKDTree | None:
        """The k-d tree over the finite points (built on first use)."""
        if self._tree is None and self.n_finite:
            self._tree = cKDTree(self._data, balanced_tree=False, compact_nodes=False)
        return self._tree

    def query(
        self,
        queries: np.ndarray,
        k: int,
        *,
        workers: int = -1,
        upper: float = np.inf,
        self_index: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Return ``(index (Q, k) int64, distance (Q, k) float64)``, padded with -1 / inf.

        ``self_index`` (Q,) gives, for queries that are points of the cloud, their own index:
        it is then put in column 0 (ties among exact duplicates resolved in its favour).
        """
        qn = queries.shape[0]
        if k == 0 or self.n_finite == 0 or qn == 0:
            return np.full((qn, k), -1, dtype=np.int64), np.full((qn, k), np.inf)
        fin_q = finite_rows(queries)
        all_q = bool(fin_q.all())
        kk = min(k, self.n_finite)
        q_sel = queries if all_q else queries[fin_q]
        if self.grid is not None and not np.isfinite(upper) and kk <= 1024:
            # the grid kernel pads with -1 / inf itself and sees finite points only
            i, d = self.grid.query(np.ascontiguousarray(q_sel), kk, workers != 1)
            missing = i < 0 if self._map is not None else None
        else:
            d, i = self.tree.query(q_sel, k=kk, workers=workers, distance_upper_bound=upper)
            d = np.asarray(d, dtype=np.float64).reshape(q_sel.shape[0], kk)
            i = np.asarray(i, dtype=np.int64).reshape(q_sel.shape[0], kk)
            missing = i >= self.n_finite
            i[missing] = -1
            d[missing] = np.inf
        if self._map is not None:
            i = np.where(missing, -1, self._map[np.where(missing, 0, i)])
        if all_q and kk == k:
            index, dist = i, d
        else:
            index = np.full((qn, k), -1, dtype=np.int64)
            dist = np.full((qn, k), np.inf)
            index[fin_q, :kk] = i
            dist[fin_q, :kk] = d
        if self_index is not None:
            self_index = np.asarray(self_index, dtype=np.int64)
            bad = fin_q & (index[:, 0] != self_index)
            rows = np.flatnonzero(bad)
            if rows.size:
                sub_i, sub_d = index[rows], dist[rows]
                _put_self_first(sub_i, sub_d, self_index[rows])
                index[rows], dist[rows] = sub_i, sub_d
        return index, dist


def _tree_query(
    pts: np.ndarray,
    qry: np.ndarray,
    k: int,
    workers: int,
    upper: float = np.inf,
    self_first: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """k-NN of finite queries among finite points; pads with -1 / inf."""
    self_index = np.arange(qry.shape[0]) if self_first else None
    index = PointIndex(pts, "kdtree")
    return index.query(qry, k, workers=workers, upper=upper, self_index=self_index)


# --------------------------------------------------------------------------- public API


def knn(
    points: Any, k: int, queries: Any = None, *, workers: int = -1, method: str = "auto"
) -> Neighbors:
    """Find the k nearest neighbours with a k-d tree (``scipy.spatial.cKDTree``).

    Parameters
    ----------
    points : (N, 3) float array or tensor
        Searched points (any unit). Non-finite points are never returned as neighbours.
    k : int
        Neighbours per query, ``1 <= k``. When ``k`` exceeds the number of finite points the
        rows are padded (``index = -1``, ``distance = inf``, ``mask = False``): the shape is
        always ``(Q, k)`` and nothing is invented.
    queries : (Q, 3) float array or tensor, optional
        Query points. When None the queries are ``points`` themselves and column 0 of each
        finite point's row is the point itself (distance 0), also among exact duplicates.
    workers : int
        Threads for the tree query (``-1``: all cores; any value other than 1 lets the grid
        search use numba's threads).
    method : {"auto", "grid", "kdtree"}
        Search engine (see :class:`PointIndex`); results are identical up to the order of
        exactly equidistant neighbours.

    Returns
    -------
    Neighbors
        ``index (Q, k)`` int64, ``distance (Q, k)`` float64, ``mask (Q, k)`` bool, nearest
        first; the array type of ``points``. Non-finite queries get an all-padded row.

    Raises
    ------
    ValueError
        Bad shapes, ``k < 1``, a bad ``workers`` value or an unknown method.
    TypeError
        Non-numeric input or a non-integer ``k``.
    """
    pts, numpy_in, _ = _points_np(points, "points")
    k = check_int(k, "k", low=1)
    w = _workers(workers)
    check_choice(method, "method", ("auto", "grid", "kdtree"))
    qry = pts if queries is None else _points_np(queries, "queries")[0]
    self_index = np.arange(qry.shape[0]) if queries is None else None
    index, dist = PointIndex(pts, method).query(qry, k, workers=w, self_index=self_index)
    mask = index >= 0
    return Neighbors(_out(index, numpy_in), _out(dist, numpy_in), _out(mask, numpy_in))


def radius_neighbors(
    points: Any,
    r: float,
    queries: Any = None,
    max_neighbors: int | None = None,
    *,
    workers: int = -1,
) -> Neighbors:
    """All neighbours within a ball of radius ``r`` (inclusive), padded to a rectangle.

    Parameters
    ----------
    points : (N, 3) float array or tensor
        Searched points. Non-finite points are never returned.
    r : float
        Ball radius, same unit as ``points``; ``r > 0``.
    queries : (Q, 3) float array or tensor, optional
        Query points; when None, ``points`` themselves with the point itself in column 0.
    max_neighbors : int, optional
        Keep only the ``max_neighbors`` nearest inside the ball (an explicit cap chosen by the
        caller). When None the width is the largest ball count.
    workers : int
        Threads for the tree queries (``-1``: all cores).

    Returns
    -------
    Neighbors
        ``index (Q, Kmax)`` with ``-1`` padding, ``distance`` (``inf`` padding), ``mask``;
        sorted nearest first.

    Raises
    ------
    ValueError
        Bad shapes, ``r <= 0`` or ``max_neighbors < 1``.
    TypeError
        Non-numeric input.
    """
    pts, numpy_in, _ = _points_np(points, "points")
    r = check_positive(r, "r")
    w = _workers(workers)
    qry = pts if queries is None else _points_np(queries, "queries")[0]
    fin_p = np.isfinite(pts).all(axis=1)
    fin_q = np.isfinite(qry).all(axis=1)
    if max_neighbors is not None:
        kmax = check_int(max_neighbors, "max_neighbors", low=1)
    elif fin_p.any() and fin_q.any():
        tree = cKDTree(pts[fin_p])
        counts = tree.query_ball_point(qry[fin_q], r, workers=w, return_length=True)
        kmax = int(np.max(counts)) if len(counts) else 0
    else:
        kmax = 0
    kmax = max(kmax, 1) if qry.shape[0] else kmax
    # a relative tolerance makes the ball inclusive of points at exactly distance r
    upper = np.nextafter(r, np.inf) * (1 + 1e-12)
    index, dist = _tree_query(pts, qry, kmax, w, upper=upper, self_first=queries is None)
    mask = index >= 0
    return Neighbors(_out(index, numpy_in), _out(dist, numpy_in), _out(mask, numpy_in))


def mesh_k_ring(
    faces: Any,
    n_vertices: int,
    rings: int = 1,
    *,
    include_self: bool = True,
    max_neighbors: int | None = None,
) -> KRing:
    """k-ring neighbourhoods (``rings`` hops) of every vertex of a triangle mesh.

    Parameters
    ----------
    faces : (F, 3) int array or tensor
        Triangles.
    n_vertices : int
        Number of vertices ``N``.
    rings : int
        Ring radius in edges (the ``k`` of "k-ring"), ``rings >= 1``.
    include_self : bool
        Put the vertex itself first (hop 0).
    max_neighbors : int, optional
        Keep at most this many entries per row (lowest hop counts first). When None the
        width is the largest ring.

    Returns
    -------
    KRing
        ``index (N, K)``, ``hops (N, K)``, ``mask (N, K)``; NumPy unless ``faces`` is a
        tensor.

    Raises
    ------
    ValueError
        Bad shapes, out-of-range indices, ``rings < 1``.
    TypeError
        Non-integer faces.
    """
    n = check_int(n_vertices, "n_vertices", low=0)
    rings = check_int(rings, "rings", low=1)
    f, numpy_in = check_faces(faces, n).cpu().numpy(), is_numpy_like(faces)
    adj = vertex_adjacency(f, n)
    step = (adj + sp.identity(n, format="csr")).tocsr()
    reached = sp.identity(n, format="csr", dtype=np.float64)
    hop = sp.identity(n, format="csr", dtype=np.float64)  # data = hop + 1
    for h in range(1, rings + 1):
        nxt = (reached @ step).tocsr()
        nxt.data[:] = 1.0
        new = nxt - reached
        new.eliminate_zeros()
        if new.nnz == 0:
            break
        hop = hop + new * (h + 1)
        reached = nxt
    hop = hop.tocsr()
    hop.sort_indices()
    if not include_self:
        hop = hop - sp.diags(hop.diagonal())
        hop.eliminate_zeros()
    hop = hop.tocsr()
    counts = np.diff(hop.indptr)
    row = np.repeat(np.arange(n), counts)
    col = hop.indices.astype(np.int64)
    hv = hop.data.astype(np.int64) - 1
    order = np.lexsort((col, hv, row))
    row, col, hv = row[order], col[order], hv[order]
    pos = np.arange(row.size) - np.repeat(hop.indptr[:-1], counts)
    width = int(counts.max()) if counts.size else 0
    if max_neighbors is not None:
        width = min(width, check_int(max_neighbors, "max_neighbors", low=1))
    keep = pos < width
    index = np.full((n, width), -1, dtype=np.int64)
    hops = np.full((n, width), -1, dtype=np.int64)
    index[row[keep], pos[keep]] = col[keep]
    hops[row[keep], pos[keep]] = hv[keep]
    mask = index >= 0
    return KRing(_out(index, numpy_in), _out(hops, numpy_in), _out(mask, numpy_in))


def reaches_non_manifold(
    points: Any,
    faces: Any,
    n_neighbors: Any = None,
    *,
    radius: float | None = None,
    rings: int | None = None,
) -> np.ndarray:
    """Which vertices have a neighbourhood that reaches a non-manifold edge of the mesh.

    The faces around each edge shared by more than two faces (a fin hung on a surface,
    :func:`polygeo.mesh.non_manifold_edges`) are marked; a vertex is flagged when its
    neighbourhood holds a vertex of a marked face. Neighbourhoods are the ``rings``-ring,
    the ball of ``radius`` or, by default, the ``n_neighbors`` nearest points (the point
    itself included, as counted by :attr:`polygeo.estimate.DifferentialQuantities.n_neighbors`).

    Parameters
    ----------
    points : (N, 3) float array or tensor
        Vertex positions (any unit).
    faces : (F, 3) int array or tensor
        Triangles.
    n_neighbors : (N,) int array or int, optional
        Neighbourhood size per vertex (default 21: 20 neighbours and the point).
    radius : float, optional
        Ball radius (input units) instead of nearest neighbours.
    rings : int, optional
        Mesh rings instead of nearest neighbours.

    Returns
    -------
    np.ndarray
        ``(N,)`` bool, True where the neighbourhood reaches a non-manifold edge; all False
        on a manifold mesh (no search is run then).

    Raises
    ------
    ValueError
        Bad shapes or sizes.
    TypeError
        Non-numeric input.
    """
    from .mesh import edge_faces

    pts, _, _ = _points_np(points, "points")
    n = pts.shape[0]
    f = check_faces(faces, n).cpu().numpy()
    _, edge_id, count = edge_faces(f)
    edge_id, count = np.asarray(edge_id), np.asarray(count)
    if not (count > 2).any():
        return np.zeros(n, dtype=bool)
    half = np.flatnonzero((edge_id >= 0) & (count[np.maximum(edge_id, 0)] > 2))
    bad_faces = np.unique(half // 3)
    marked = np.zeros(n + 1, dtype=bool)
    marked[f[bad_faces].ravel()] = True
    if rings is not None:
        nb = np.asarray(mesh_k_ring(f, n, rings).index)
    elif radius is not None:
        nb = np.asarray(radius_neighbors(pts, radius).index)
    else:
        size = np.broadcast_to(np.asarray(21 if n_neighbors is None else n_neighbors), (n,))
        kmax = max(1, min(int(size.max()), n))
        nb = np.asarray(knn(pts, kmax).index)
        nb = np.where(np.arange(kmax)[None, :] < size[:, None], nb, -1)
    return marked[nb].any(axis=1) | marked[:n]
