import numpy as np
import pytest
import torch

from polygeo import neighbors as nb


def brute_knn(p, q, k):
    d = np.linalg.norm(q[:, None, :] - p[None, :, :], axis=-1)
    d = np.where(np.isfinite(d), d, np.inf)
    order = np.argsort(d, axis=1, kind="stable")[:, :k]
    return order, np.take_along_axis(d, order, axis=1)


def test_knn_matches_brute_force(rng):
    p = rng.random((200, 3))
    q = rng.random((50, 3))
    res = nb.knn(p, 7, q)
    idx, dist = brute_knn(p, q, 7)
    np.testing.assert_allclose(res.distance, dist, rtol=1e-12)
    assert (res.index == idx).mean() > 0.99  # ties may reorder
    assert res.mask.all()


def test_knn_self_first_even_with_duplicates(rng):
    p = rng.random((30, 3))
    p = np.concatenate([p, np.repeat(p[:1], 12, axis=0)])  # 13 copies of point 0
    res = nb.knn(p, 5)
    assert (res.index[:, 0] == np.arange(len(p))).all()
    assert (res.distance[:, 0] == 0).all()
    # sorted distances
    assert (np.diff(res.distance, axis=1) >= 0).all()


def test_knn_nan_point_is_excluded_and_padded(rng):
    p = rng.random((40, 3))
    p[7] = np.nan
    res = nb.knn(p, 6)
    assert (res.index[7] == -1).all() and not res.mask[7].any()
    assert np.isinf(res.distance[7]).all()
    assert not (res.index == 7).any()
    ok = np.delete(np.arange(40), 7)
    ref = nb.knn(p[ok], 6)
    np.testing.assert_allclose(res.distance[ok], ref.distance)


def test_knn_k_larger_than_n_pads():
    p = np.eye(3)
    res = nb.knn(p, 5)
    assert res.index.shape == (3, 5)
    assert (res.mask.sum(1) == 3).all()
    assert (res.index[:, 3:] == -1).all()


def test_knn_torch_in_torch_out(rng):
    p = torch.from_numpy(rng.random((20, 3))).float()
    res = nb.knn(p, 4)
    assert isinstance(res.index, torch.Tensor) and res.index.dtype == torch.int64
    assert isinstance(res.mask, torch.Tensor)
    np_res = nb.knn(p.numpy(), 4)
    assert (res.index.numpy() == np_res.index).all()


def test_radius_neighbors_matches_brute_force(rng):
    p = rng.random((150, 3))
    r = 0.2
    res = nb.radius_neighbors(p, r)
    d = np.linalg.norm(p[:, None] - p[None], axis=-1)
    counts = (d <= r).sum(1)
    assert (res.mask.sum(1) == counts).all()
    assert res.index.shape[1] == counts.max()
    assert (res.index[:, 0] == np.arange(150)).all()
    for i in range(0, 150, 17):
        assert set(res.index[i][res.mask[i]]) == set(np.flatnonzero(d[i] <= r))


def test_radius_neighbors_cap_keeps_nearest(rng):
    p = rng.random((100, 3))
    full = nb.radius_neighbors(p, 0.3)
    cap = nb.radius_neighbors(p, 0.3, max_neighbors=4)
    assert cap.index.shape[1] == 4
    np.testing.assert_allclose(
        np.where(cap.mask, cap.distance, 0), np.where(full.mask[:, :4], full.distance[:, :4], 0)
    )


def test_radius_inclusive_boundary():
    p = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    res = nb.radius_neighbors(p, 1.0)
    assert res.mask[0].sum() == 2 and res.mask[1].sum() == 3


def strip_faces(n):
    # a strip of triangles over vertices 0..n-1: (i, i+1, i+2)
    return np.array([[i, i + 1, i + 2] for i in range(n - 2)])


def test_vertex_adjacency_symmetric():
    f = np.array([[0, 1, 2], [2, 1, 3], [0, 0, 4]])  # last face degenerate
    a = nb.vertex_adjacency(f, 6)
    d = a.toarray()
    assert (d == d.T).all() and (np.diag(d) == 0).all()
    assert d[0, 1] == 1 and d[1, 3] == 1 and d[0, 3] == 0 and d[0, 4] == 1
    assert d[5].sum() == 0


def test_mesh_k_ring_against_bfs():
    f = strip_faces(12)
    n = 13  # vertex 12 unreferenced
    adj = nb.vertex_adjacency(f, n).toarray() > 0
    for k in (1, 2, 3):
        ring = nb.mesh_k_ring(f, n, rings=k)
        for v in range(n):
            dist = np.full(n, -1)
            dist[v] = 0
            frontier = [v]
            for h in range(1, k + 1):
                nxt = []
                for a in frontier:
                    for b in np.flatnonzero(adj[a]):
                        if dist[b] < 0:
                            dist[b] = h
                            nxt.append(b)
                frontier = nxt
            want = np.flatnonzero(dist >= 0)
            got = ring.index[v][ring.mask[v]]
            assert set(got) == set(want)
            assert got[0] == v
            assert (ring.hops[v][ring.mask[v]] == dist[got]).all()
            assert (np.diff(ring.hops[v][ring.mask[v]]) >= 0).all()


def test_mesh_k_ring_exclude_self_and_torch():
    f = torch.tensor(strip_faces(6))
    ring = nb.mesh_k_ring(f, 6, 1, include_self=False)
    assert isinstance(ring.index, torch.Tensor)
    assert not (ring.index == torch.arange(6)[:, None]).any()


@pytest.mark.parametrize(
    "call, exc",
    [
        (lambda: nb.knn(np.zeros((5, 2)), 2), ValueError),
        (lambda: nb.knn(np.zeros((5, 3)), 0), ValueError),
        (lambda: nb.knn(np.zeros((5, 3)), 2.5), TypeError),
        (lambda: nb.knn(np.zeros((5, 3)), 2, np.zeros((4, 4))), ValueError),
        (lambda: nb.knn(np.zeros((5, 3)), 2, workers=0), ValueError),
        (lambda: nb.knn(np.zeros((5, 3)), 2, method="ball"), ValueError),
        (lambda: nb.knn(np.array([["a", "b", "c"]]), 1), TypeError),
        (lambda: nb.radius_neighbors(np.zeros((5, 3)), -1.0), ValueError),
        (lambda: nb.radius_neighbors(np.zeros((5, 3)), 1.0, max_neighbors=0), ValueError),
        (lambda: nb.mesh_k_ring(np.array([[0, 1, 5]]), 3), ValueError),
        (lambda: nb.mesh_k_ring(np.array([[0, 1, 2]]), 3, rings=0), ValueError),
        (lambda: nb.mesh_k_ring(np.array([[0.0, 1, 2]]), 3), TypeError),
        (lambda: nb.vertex_adjacency(np.array([[0, 1]]), 3), ValueError),
        (lambda: nb.vertex_adjacency(np.array([[0, -1, 2]]), 3), ValueError),
    ],
)
def test_validators(call, exc):
    with pytest.raises(exc):
        call()


def test_empty_inputs():
    res = nb.knn(np.zeros((0, 3)), 3)
    assert res.index.shape == (0, 3)
    ring = nb.mesh_k_ring(np.zeros((0, 3), dtype=int), 0)
    assert ring.index.shape[0] == 0


@pytest.mark.parametrize("kind", ["volume", "surface", "outlier", "duplicates"])
def test_grid_equals_kdtree(rng, kind):
    if kind == "volume":
        p = rng.random((3000, 3))
    elif kind == "surface":
        p = rng.normal(size=(3000, 3))
        p /= np.linalg.norm(p, axis=1, keepdims=True)
    elif kind == "outlier":
        p = np.vstack([rng.random((3000, 3)), [[1e6, -1e6, 5e5]]])
    else:
        p = np.repeat(rng.random((500, 3)), 4, axis=0)
    q = rng.random((200, 3)) * 1.2 - 0.1
    for queries in (None, q):
        g = nb.knn(p, 16, queries, method="grid")
        t = nb.knn(p, 16, queries, method="kdtree")
        np.testing.assert_allclose(g.distance, t.distance, rtol=1e-12)
        if kind != "duplicates":
            assert (g.index == t.index).mean() > 0.999
        if queries is None:
            assert (g.index[:, 0] == np.arange(len(p))).all()


def test_grid_pads_when_few_points():
    p = np.array([[0.0, 0, 0], [1, 0, 0], [np.nan, 0, 0]])
    g = nb.knn(p, 4, method="grid")
    assert (g.mask.sum(1) == [2, 2, 0]).all()
