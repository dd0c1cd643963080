import numpy as np
import pytest
import torch

import polygeo.synthetic as syn
from polygeo.proximity import (
    chamfer_distance,
    chamfer_report,
    closest_point_on_triangles,
    squared_distance_to_mesh,
)


def _closest_on_segments(p, a, b):
    d = b - a
    dd = np.maximum(np.einsum("...j,...j->...", d, d), 1e-300)
    t = np.clip(np.einsum("...j,...j->...", p - a, d) / dd, 0.0, 1.0)
    return a + t[..., None] * d


def _closest_reference(p, a, b, c):
    """Independent closest points (rows of triangles ``a, b, c`` (T, 3) to ``p`` (T, 3) or
    (3,)): the plane projection when it falls inside, else the nearest point of the edges."""
    p = np.broadcast_to(p, a.shape)
    cands = [_closest_on_segments(p, a, b), _closest_on_segments(p, b, c),
             _closest_on_segments(p, c, a)]
    n = np.cross(b - a, c - a)
    nn = np.einsum("ij,ij->i", n, n)
    ok = nn > 1e-24
    nn = np.where(ok, nn, 1.0)
    q = p - (np.einsum("ij,ij->i", p - a, n) / nn)[:, None] * n
    # barycentric coordinates of the projection by signed sub-triangle areas
    wa = np.einsum("ij,ij->i", np.cross(c - b, q - b), n) / nn
    wb = np.einsum("ij,ij->i", np.cross(a - c, q - c), n) / nn
    inside = ok & (np.minimum(np.minimum(wa, wb), 1.0 - wa - wb) >= 0)
    cands.append(np.where(inside[:, None], q, cands[0]))
    cands = np.stack(cands, 1)  # (T, 4, 3)
    d = ((cands - p[:, None]) ** 2).sum(-1)
    return cands[np.arange(len(a)), d.argmin(1)]


def _brute_mesh_sq(points, v, f):
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return np.array([((p - _closest_reference(p, a, b, c)) ** 2).sum(1).min() for p in points])


def test_closest_point_matches_independent_reference_on_random_triangles():
    rng = np.random.default_rng(0)
    a, b, c = rng.normal(size=(3, 500, 3))
    # every region: points far away, near the plane, and just outside the edges
    p = np.concatenate([3 * rng.normal(size=(250, 3)),
                        (a + b + c)[:250] / 3 + 0.1 * rng.normal(size=(250, 3))])
    res = closest_point_on_triangles(p, a, b, c)
    ref = _closest_reference(p, a, b, c)
    np.testing.assert_allclose(res.points, ref, atol=1e-10)
    np.testing.assert_allclose(res.sq_distance, np.sum((p - ref) ** 2, axis=1), atol=1e-10)
    # the answer lies on its triangle: no point of the triangle is closer (lattice check)
    w = np.array([(i, j, 20 - i - j) for i in range(21) for j in range(21 - i)]) / 20.0
    lattice = np.einsum("lk,nkd->nld", w, np.stack([a, b, c], 1))
    lat_d = ((lattice - p[:, None]) ** 2).sum(-1).min(1)
    assert (res.sq_distance <= lat_d + 1e-12).all()


def test_closest_point_degenerate_triangles_and_types():
    p = np.array([[0.5, 1.0, 0.0], [3.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    a = np.zeros((3, 3))
    b = np.array([[1.0, 0, 0], [1.0, 0, 0], [0, 0, 0]])
    c = np.array([[2.0, 0, 0], [2.0, 0, 0], [0, 0, 0]])  # collinear, collinear, a point
    res = closest_point_on_triangles(p, a, b, c)
    np.testing.assert_allclose(res.points, [[0.5, 0, 0], [2.0, 0, 0], [0, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(res.sq_distance, [1.0, 1.0, 4.0], atol=1e-12)
    assert np.isfinite(res.points).all()
    t = closest_point_on_triangles(torch.from_numpy(p), a, b, c)
    assert isinstance(t.points, torch.Tensor) and t.points.dtype == torch.float64
    np.testing.assert_array_equal(t.sq_distance.numpy(), res.sq_distance)


def test_squared_distance_to_mesh_matches_brute_force():
    s = syn.sphere_mesh(2)
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(60, 3)) * 0.2 + 0.9 * s.normals[rng.integers(0, len(s.points), 60)]
    d = squared_distance_to_mesh(pts, s.points, s.faces)
    np.testing.assert_allclose(d, _brute_mesh_sq(pts, s.points, s.faces), atol=1e-12)
    # a vertex without faces: the distance to it
    v = np.concatenate([s.points, [[5.0, 0.0, 0.0]]])
    d2 = squared_distance_to_mesh(np.array([[5.0, 0.0, 1.0]]), v, s.faces, k=1)
    np.testing.assert_allclose(d2, [1.0])
    dt = squared_distance_to_mesh(torch.from_numpy(pts), s.points, torch.from_numpy(s.faces))
    assert isinstance(dt, torch.Tensor)
    np.testing.assert_array_equal(dt.numpy(), d)


def _sample(v, f, n, rng):
    """Area-uniform samples (rejection on the unit square folded into the triangle)."""
    p = v[f]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    tri = rng.choice(len(f), size=n, p=area / area.sum())
    u, w = rng.uniform(size=(2, n))
    out = u + w > 1
    u[out], w[out] = 1 - u[out], 1 - w[out]
    t = p[tri]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + w[:, None] * (t[:, 2] - t[:, 0])


def test_surface_chamfer_matches_dense_brute_force():
    a = syn.sphere_mesh(2)
    va, fa = a.points, a.faces
    rng = np.random.default_rng(2)
    vb = va * (1.0 + 0.1 * rng.uniform(size=(len(va), 1))) + [0.05, 0.0, 0.0]
    fb = fa
    got = chamfer_distance(va, fa, vb, fb, mode="surface", normalize="none", n_samples=4000)
    sa, sb = _sample(va, fa, 800, rng), _sample(vb, fb, 800, rng)
    ref = _brute_mesh_sq(sa, vb, fb).mean() + _brute_mesh_sq(sb, va, fa).mean()
    # two Monte-Carlo estimates of one integral: a few percent apart
    np.testing.assert_allclose(got, ref, rtol=0.08)


def test_point_chamfer_of_parallel_squares_is_twice_the_squared_gap():
    s = syn.plane_mesh(8)
    v2 = s.points + [0.0, 0.0, 0.5]
    got = chamfer_distance(s.points, s.faces, v2, s.faces, normalize="none", n_samples=20000)
    # nearest sample of the other square: the gap squared plus a tiny in-plane floor
    assert 2 * 0.25 <= got <= 2 * 0.25 * (1 + 2e-3)
    # unit-sphere normalisation divides by the largest sample radius (about sqrt(2))
    g = chamfer_distance(s.points, s.faces, v2, s.faces, n_samples=20000)
    np.testing.assert_allclose(g, got / 2.0, rtol=0.01)


def test_chamfer_report_values_and_floors():
    s = syn.sphere_mesh(2)
    r = chamfer_report(s.points, s.faces, s.points, s.faces, n_samples=2000, n_dense=8000)
    assert r.surface < 1e-20
    assert r.points > 0 and r.points_floor > 0
    assert r.dense < r.points and r.dense_floor < r.points_floor
    d = r.as_dict()
    assert d["n_samples"] == 2000 and d["points"] == pytest.approx(1e3 * r.points)


@pytest.mark.parametrize(
    "call, err, msg",
    [
        (lambda: closest_point_on_triangles(np.zeros((3, 3)), np.zeros((2, 3)), np.zeros((3, 3)),
                                            np.zeros((3, 3))), ValueError, "a: expected shape"),
        (lambda: closest_point_on_triangles(np.zeros((3, 2)), *np.zeros((3, 3, 3))), ValueError,
         "points"),
        (lambda: squared_distance_to_mesh(np.zeros((1, 3)), np.eye(3), [[0, 1, 2]], k=0),
         ValueError, "k"),
        (lambda: squared_distance_to_mesh(np.zeros((1, 3)), np.eye(3), [[0.0, 1, 2]]),
         TypeError, "faces"),
        (lambda: squared_distance_to_mesh(np.zeros((1, 3)), np.eye(3), [[0, 1, 3]]),
         ValueError, "faces"),
        (lambda: squared_distance_to_mesh(np.zeros((1, 3)), np.zeros((0, 3)),
                                          np.zeros((0, 3), int)), ValueError, "vertices"),
        (lambda: chamfer_distance(np.eye(3), [[0, 1, 2]], np.eye(3), [[0, 1, 2]], mode="x"),
         ValueError, "mode"),
        (lambda: chamfer_distance(np.eye(3), [[0, 1, 2]], np.eye(3), [[0, 1, 2]],
                                  normalize="box"), ValueError, "normalize"),
        (lambda: chamfer_distance(np.eye(3), [[0, 1, 2]], np.eye(3), [[0, 1, 2]], n_samples=0),
         ValueError, "n_samples"),
        (lambda: chamfer_distance(np.zeros((3, 3)), [[0, 1, 2]], np.eye(3), [[0, 1, 2]]),
         ValueError, "zero area"),
    ],
)
def test_bad_input(call, err, msg):
    with pytest.raises(err, match=msg):
        call()
