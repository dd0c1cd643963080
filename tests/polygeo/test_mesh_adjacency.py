import numpy as np
import pytest
import torch

import polygeo.synthetic as syn
from polygeo import mesh, neighbors


def _bfs_components(n, edge_list):
    nbrs = [[] for _ in range(n)]
    for a, b in edge_list:
        nbrs[a].append(b)
        nbrs[b].append(a)
    label = -np.ones(n, np.int64)
    count = 0
    for start in range(n):
        if label[start] >= 0:
            continue
        label[start] = count
        todo = [start]
        while todo:
            x = todo.pop()
            for y in nbrs[x]:
                if label[y] < 0:
                    label[y] = count
                    todo.append(y)
        count += 1
    return count, label


def test_one_adjacency_builder():
    assert neighbors.vertex_adjacency is mesh.vertex_adjacency


def test_vertex_adjacency_is_the_edge_set():
    s = syn.sphere_mesh(2)
    f = np.concatenate([s.faces, [[0, 0, 1]]])  # a degenerate face adds no self loop
    n = len(s.points) + 2  # two unreferenced vertices: empty rows
    a = mesh.vertex_adjacency(f, n)
    dense = a.toarray()
    np.testing.assert_array_equal(dense, dense.T)
    assert (np.diag(dense) == 0).all() and set(np.unique(dense)) <= {0.0, 1.0}
    e = mesh.edges(f)
    got = np.argwhere(np.triu(dense) > 0)
    np.testing.assert_array_equal(got, e)
    assert dense[-2:].sum() == 0
    np.testing.assert_array_equal(mesh.vertex_adjacency(torch.from_numpy(f), n).toarray(), dense)


def test_connected_components_match_a_breadth_first_search():
    s = syn.sphere_mesh(1)
    nv = len(s.points)
    f = np.concatenate([s.faces + nv, s.faces])  # second copy first: labels by first vertex
    n = 2 * nv + 3
    count, labels = mesh.connected_components(f, n)
    ref_count, ref = _bfs_components(n, mesh.edges(f))
    assert count == ref_count == 5
    np.testing.assert_array_equal(labels, ref)


@pytest.mark.parametrize(
    "args, err, msg",
    [
        ((np.array([[0, 1]]), 3), ValueError, "faces"),
        ((np.array([[0, 1, 3]]), 3), ValueError, "faces"),
        ((np.array([[0.0, 1.0, 2.0]]), 3), TypeError, "faces"),
        ((np.array([[0, 1, 2]]), -1), ValueError, "n_vertices"),
    ],
)
def test_vertex_adjacency_bad_input(args, err, msg):
    with pytest.raises(err, match=msg):
        mesh.vertex_adjacency(*args)


def test_edges_of_degenerate_faces():
    f = np.array([[0, 0, 0]])
    assert mesh.edges(f).shape == (0, 2)
    assert mesh.boundary_edges(f).shape == (0, 2)
    e, eid, count = mesh.edge_faces(np.array([[0, 1, 2], [2, 2, 3]]))
    np.testing.assert_array_equal(e, [[0, 1], [0, 2], [1, 2], [2, 3]])
    np.testing.assert_array_equal(eid, [0, 2, 1, -1, 3, 3])
    np.testing.assert_array_equal(count, [1, 1, 1, 2])
