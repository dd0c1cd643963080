import numpy as np
import pytest
import scipy.sparse as sp
import torch
import trimesh
from scipy.sparse.csgraph import connected_components

from polygeo.partition import (
    Partition,
    default_n_patches,
    mesh_area,
    partition,
    partition_mesh,
    partition_points,
)


def _sphere(sub=4, radius=1.0):
    m = trimesh.creation.icosphere(subdivisions=sub, radius=radius)
    return np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int64)


def _edges(faces):
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.sort(e, axis=1)
    e = e[e[:, 0] != e[:, 1]]
    return np.unique(e, axis=0)


def _patch_components(labels, edges, k):
    """Number of connected pieces of every patch, via the within-patch edge graph."""
    n = len(labels)
    same = labels[edges[:, 0]] == labels[edges[:, 1]]
    e = edges[same]
    g = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    _, comp = connected_components(g, directed=False)
    pieces = np.zeros(k, int)
    for lab in range(k):
        pieces[lab] = len(np.unique(comp[labels == lab]))
    return pieces


def _check_valid(part: Partition, edges, n_vertices):
    k = part.n_patches
    assert part.labels.shape == (n_vertices,)
    assert part.labels.min() == 0 and part.labels.max() == k - 1
    assert (part.sizes > 0).all()
    assert (_patch_components(part.labels, edges, k) == 1).all()
    # boundary pairs are exactly the edges across patches
    across = edges[part.labels[edges[:, 0]] != part.labels[edges[:, 1]]]
    np.testing.assert_array_equal(part.boundary_pairs, across)
    pairs = {tuple(sorted((part.labels[i], part.labels[j]))) for i, j in across}
    assert {tuple(p) for p in part.adjacency} == pairs
    assert (part.adjacency[:, 0] < part.adjacency[:, 1]).all()
    a = part.adjacency_matrix()
    assert a.shape == (k, k) and (a != a.T).nnz == 0


def test_mesh_partition_properties():
    v, f = _sphere(4)
    part = partition_mesh(v, f, 60)
    _check_valid(part, _edges(f), len(v))
    assert abs(part.n_patches - 60) <= 6
    # near-equal areas: coefficient of variation of ACVD clusters on a uniform sphere
    assert part.area_cv < 0.15, f"area CV {part.area_cv:.3f}"
    np.testing.assert_allclose(part.areas.sum(), mesh_area(v, f), rtol=1e-12)
    np.testing.assert_allclose(mesh_area(v, f), 4 * np.pi, rtol=0.01)


def test_deterministic_for_seed_and_varied_across_seeds():
    v, f = _sphere(3)
    a = partition_mesh(v, f, 30, seed=3)
    b = partition_mesh(v, f, 30, seed=3)
    c = partition_mesh(v, f, 30, seed=4)
    np.testing.assert_array_equal(a.labels, b.labels)
    assert not np.array_equal(a.labels, c.labels)
    pa = partition_points(v, 30, seed=3)
    pb = partition_points(v, 30, seed=3)
    np.testing.assert_array_equal(pa.labels, pb.labels)


def test_callers_mesh_unchanged():
    v, f = _sphere(3)
    v0, f0 = v.copy(), f.copy()
    partition_mesh(v, f, 20)
    np.testing.assert_array_equal(v, v0)
    np.testing.assert_array_equal(f, f0)
    vt, ft = torch.from_numpy(v.copy()), torch.from_numpy(f.copy())
    partition_mesh(vt, ft, 20)
    assert torch.equal(vt, torch.from_numpy(v0)) and torch.equal(ft, torch.from_numpy(f0))


def test_single_patch_and_several_components():
    v, f = _sphere(2)
    one = partition_mesh(v, f, 1)
    assert one.n_patches == 1 and len(one.boundary_pairs) == 0
    # two disjoint spheres: K = 1 gives one patch per component; no patch spans both
    v2 = np.concatenate([v, v + [3.0, 0.0, 0.0]])
    f2 = np.concatenate([f, f + len(v)])
    two = partition_mesh(v2, f2, 1)
    assert two.n_patches == 2
    many = partition_mesh(v2, f2, 16)
    _check_valid(many, _edges(f2), len(v2))
    left = set(many.labels[: len(v)])
    right = set(many.labels[len(v) :])
    assert not left & right


def test_default_k_rule():
    assert default_n_patches(0.0) == 100
    assert default_n_patches(0.5) == 100
    assert default_n_patches(2.0) == 250
    assert default_n_patches(100.0) == 400
    # a sphere of area ~1.6 m^2 (r = 0.357 m) gets floor(area / 0.008) patches (before
    # connectivity post-processing, which may add or remove a few)
    v, f = _sphere(5, radius=0.357)
    part = partition_mesh(v, f)
    want = default_n_patches(mesh_area(v, f))
    assert 150 <= want <= 250
    assert abs(part.n_patches - want) <= 0.05 * want


def test_nonmanifold_degenerate_and_unreferenced():
    v, f = _sphere(2)
    n = len(v)
    extra = np.array([[0.0, 0.0, 3.0], [5.0, 5.0, 5.0]])  # fin tip, unreferenced vertex
    v2 = np.concatenate([v, extra])
    e0 = f[0]
    f2 = np.concatenate(
        [
            f,
            [[e0[0], e0[1], n]],  # a third face on edge (e0[0], e0[1]): non-manifold
            [[e0[0], e0[0], e0[1]]],  # repeated index: ignored
            [[e0[0], e0[1], e0[1]]],
        ]
    )
    part = partition_mesh(v2, f2, 10)
    assert part.labels.shape == (n + 2,)
    assert (part.labels >= 0).all() and (part.sizes > 0).all()
    # the unreferenced vertex joins the patch of its nearest referenced vertex
    d = np.linalg.norm(v2[: n + 1] - v2[n + 1], axis=1)
    assert part.labels[n + 1] == part.labels[int(np.argmin(d))]
    # zero-area faces (three collinear vertices) are accepted
    v3 = np.concatenate([v, [[0.0, 0.0, 0.0]]])
    f3 = np.concatenate([f, [[f[0, 0], f[0, 1], n]]])
    v3[n] = 0.5 * (v[f[0, 0]] + v[f[0, 1]])
    assert partition_mesh(v3, f3, 10).n_patches >= 1


def test_min_vertices_merges_small_pieces():
    v, f = _sphere(3)
    part = partition_mesh(v, f, 200, min_vertices=8)
    assert part.sizes.min() >= 8
    _check_valid(part, _edges(f), len(v))


def test_k_equal_to_vertex_count_is_answered():
    v, f = _sphere(1)
    part = partition_mesh(v, f, len(v))
    _check_valid(part, _edges(f), len(v))


def test_point_cloud_partition():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(3000, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    part = partition(x, None, 40, seed=1, k_neighbors=8)
    assert part.n_patches >= 30
    assert (part.sizes > 0).all()
    from scipy.spatial import cKDTree

    _, nb = cKDTree(x).query(x, k=9)
    e = np.sort(np.stack([np.repeat(np.arange(len(x)), 8), nb[:, 1:].ravel()], 1), axis=1)
    e = np.unique(e, axis=0)
    assert (_patch_components(part.labels, e, part.n_patches) == 1).all()
    assert part.area_cv < 0.4, f"area CV {part.area_cv:.3f}"
    np.testing.assert_allclose(part.areas.sum(), 4 * np.pi, rtol=0.2)


def test_bad_input():
    v, f = _sphere(1)
    with pytest.raises(TypeError, match="faces"):
        partition_mesh(v, f.astype(float), 4)
    with pytest.raises(ValueError, match="faces"):
        partition_mesh(v, f + 100, 4)
    with pytest.raises(ValueError, match="faces"):
        partition_mesh(v, f[:, :2], 4)
    with pytest.raises(ValueError, match="vertices"):
        partition_mesh(v[:, :2], f, 4)
    bad = v.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="vertices"):
        partition_mesh(bad, f, 4)
    with pytest.raises(ValueError, match="n_patches"):
        partition_mesh(v, f, 0)
    with pytest.raises(ValueError, match="n_patches"):
        partition_mesh(v, f, len(v) + 1)
    with pytest.raises(TypeError, match="n_patches"):
        partition_mesh(v, f, 2.5)
    with pytest.raises(ValueError, match="faces"):
        partition_mesh(v, np.array([[0, 0, 1]]), 1)
    with pytest.raises(ValueError, match="n_patches"):
        partition_points(v, len(v) + 1)
    with pytest.raises(ValueError, match="area"):
        default_n_patches(-1.0)
    part = partition_mesh(v, f, 4)
    with pytest.raises(ValueError, match="patch"):
        part.members(patch=part.n_patches)
