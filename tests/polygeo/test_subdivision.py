import numpy as np
import pytest

import polygeo.synthetic as syn
from polygeo.mesh import edges
from polygeo.subdivision import subdivide_barycentric


@pytest.mark.parametrize("level", [0, 1, 2, 3])
def test_vertex_and_face_counts(level):
    s = syn.sphere_mesh(1)
    f = s.faces
    V, F, E = len(s.points), len(f), len(edges(f))
    n = 2**level
    corners, weights, out = subdivide_barycentric(f, V, level)
    # V + (n - 1) points per edge + (n - 1)(n - 2) / 2 inner points per face
    assert len(corners) == V + E * (n - 1) + F * (n - 1) * (n - 2) // 2
    assert out.shape == (F * 4**level, 3)
    assert out.min() >= 0 and out.max() < len(corners)
    # a closed surface stays closed: every edge in exactly two triangles, Euler 2
    e = np.sort(out[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), 1)
    _, count = np.unique(e, axis=0, return_counts=True)
    assert (count == 2).all()
    assert len(corners) - len(count) + len(out) == 2


def test_points_lie_on_the_input_triangles():
    s = syn.sphere_mesh(1)
    v, f = s.points, s.faces
    corners, weights, out = subdivide_barycentric(f, len(v), 3)
    assert np.all(weights >= 0)
    np.testing.assert_allclose(weights.sum(1), 1.0, atol=1e-15)
    # originals first, as themselves
    np.testing.assert_array_equal(corners[: len(v), 0], np.arange(len(v)))
    np.testing.assert_array_equal(weights[: len(v)], np.tile([1.0, 0, 0], (len(v), 1)))
    # every new vertex combines the corners of one input triangle
    faces = {tuple(sorted(t)) for t in f.tolist()}
    assert all(tuple(sorted(c)) in faces for c in corners[len(v):].tolist())
    p = np.einsum("nk,nkd->nd", weights, v[corners])
    # distinct positions: lattice points on shared edges are shared, not duplicated
    rounded = np.round(p, 12)
    assert len(np.unique(rounded, axis=0)) == len(p)
    # winding kept: every output triangle's normal agrees with its parent's
    parent = np.repeat(np.arange(len(f)), 4**3)
    n_out = np.cross(p[out[:, 1]] - p[out[:, 0]], p[out[:, 2]] - p[out[:, 0]])
    n_in = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    assert (np.einsum("ij,ij->i", n_out, n_in[parent]) > 0).all()


def test_level_zero_is_identity_and_empty_faces():
    s = syn.sphere_mesh(1)
    c, w, out = subdivide_barycentric(s.faces, len(s.points), 0)
    np.testing.assert_array_equal(out, s.faces)
    assert len(c) == len(s.points)
    c, w, out = subdivide_barycentric(np.zeros((0, 3), np.int64), 4, 2)
    assert len(c) == 4 and out.shape == (0, 3)


@pytest.mark.parametrize(
    "args, err, msg",
    [
        (([[0, 1, 2]], 3, -1), ValueError, "level"),
        (([[0, 1, 2]], 3, 9), ValueError, "level"),
        (([[0.0, 1.0, 2.0]], 3, 1), TypeError, "faces"),
        (([[0, 1, 3]], 3, 1), ValueError, "faces"),
        (([[0, 1]], 3, 1), ValueError, "faces"),
        (([[0, 1, 2]], -1, 1), ValueError, "n_vertices"),
    ],
)
def test_bad_input(args, err, msg):
    with pytest.raises(err, match=msg):
        subdivide_barycentric(*args)
