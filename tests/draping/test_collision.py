import numpy as np
import pytest
import torch
import trimesh

from draping.body import AnnyBody
from draping.collision import MeshQuery, signed_distance, winding_numbers


@pytest.fixture(scope="module")
def body():
    return AnnyBody.load(dtype=torch.float64)


@pytest.fixture(scope="module")
def sphere():
    m = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    return np.asarray(m.vertices), np.asarray(m.faces)


def _brute_distance(points, vertices, faces):
    # independent reference: trimesh's vectorised point-triangle closest point, all triangles
    tris = vertices[faces]
    out = []
    for p in points:
        c = trimesh.triangles.closest_point(tris, np.repeat(p[None], len(tris), 0))
        out.append(np.linalg.norm(c - p, axis=1).min())
    return np.array(out)


def test_sphere_signs_and_distances(sphere):
    v, f = sphere
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(3000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    radii = rng.uniform(0.0, 0.6, 3000)
    pts = dirs * radii[:, None]
    res = MeshQuery(v, f).query(pts)
    assert isinstance(res.distance, np.ndarray)
    # the inscribed and circumscribed radii of the polyhedron bound the ambiguous shell
    r_in = float(np.abs((v[f].mean(1) * trimesh.Trimesh(v, f).face_normals).sum(1)).min())
    clear = (radii < r_in - 1e-9) | (radii > 0.3 + 1e-9)
    assert clear.sum() > 2500
    assert np.array_equal(res.distance[clear] < 0, radii[clear] < 0.3)
    ref = _brute_distance(pts[:150], v, f)
    assert np.allclose(np.abs(res.distance[:150]), ref, atol=1e-9)
    assert np.allclose((res.normal * (pts - res.closest)).sum(1), res.distance, atol=1e-12)
    assert np.allclose(np.linalg.norm(res.normal, axis=1), 1.0)


def test_points_on_the_surface_get_distance_zero_and_the_face_normal(sphere):
    v, f = sphere
    centroids = v[f].mean(1)
    res = MeshQuery(v, f).query(centroids)
    fn = trimesh.Trimesh(v, f).face_normals
    assert np.abs(res.distance).max() < 1e-12
    assert np.allclose(res.normal, fn, atol=1e-9)


def test_body_one_millimetre_inside_outside(body):
    v, f = body.rest_vertices.numpy(), body.faces.numpy()
    vn = trimesh.Trimesh(v, f, process=False).vertex_normals
    rng = np.random.default_rng(1)
    idx = rng.choice(len(v), 10000)
    side = np.where(rng.random(10000) < 0.5, 1.0, -1.0)
    pts = v[idx] + 1e-3 * side[:, None] * vn[idx]
    res = MeshQuery(v, f).query(pts)
    agree = np.sign(res.distance) == side
    # Offsetting along a vertex normal crosses the surface where two parts nearly touch (lips,
    # ears, toes): there the winding number (an independent, robust test) is the truth.
    sub = np.concatenate([np.flatnonzero(~agree), rng.choice(10000, 400, replace=False)])
    wind = winding_numbers(pts[sub], v, f).numpy()
    truth_inside = wind > 0.5
    toes = np.array([body.bone_names[int(body.skin_indices[i, 0])].startswith("toe")
                     for i in idx[sub]])
    ours_inside = res.distance[sub] < 0
    # the rest mesh's 4th and 5th toes overlap: the only place the pseudonormal sign may differ
    assert np.array_equal(ours_inside[~toes], truth_inside[~toes])
    assert agree.mean() > 0.995
    assert np.all(np.abs(res.distance) <= 1e-3 + 1e-9)


def test_body_distances_match_brute_force(body):
    v, f = body.rest_vertices.numpy(), body.faces.numpy()
    rng = np.random.default_rng(2)
    pts = v[rng.choice(len(v), 120)] + rng.normal(scale=0.02, size=(120, 3))
    res = MeshQuery(v, f).query(pts)
    ref = _brute_distance(pts, v, f)
    # trimesh's reference is exact to ~1e-6 m on these slivers; ours is never farther
    assert np.all(np.abs(res.distance) <= ref + 1e-12)
    assert np.allclose(np.abs(res.distance), ref, atol=5e-6)


def test_refit_equals_rebuild_and_batched_equals_single(body):
    g = torch.Generator().manual_seed(3)
    rot = 0.3 * torch.randn(2, body.num_bones, 3, generator=g, dtype=torch.float64)
    posed = body.pose(None, rot).vertices
    pts = posed[:, ::50] + 0.01 * torch.randn(2, len(posed[0, ::50]), 3, generator=g,
                                              dtype=torch.float64)
    q = MeshQuery(body.rest_vertices, body.faces)
    batched = signed_distance(pts, posed, body.faces)
    for b in range(2):
        q.update(posed[b])
        refit = q.query(pts[b])
        fresh = MeshQuery(posed[b], body.faces).query(pts[b])
        assert torch.allclose(refit.distance, fresh.distance, atol=1e-14)
        assert torch.equal(refit.face, fresh.face) or torch.allclose(
            refit.closest, fresh.closest, atol=1e-12)
        assert torch.allclose(batched.distance[b], refit.distance, atol=1e-14)
    assert batched.distance.dtype == torch.float64 and batched.closest.shape == pts.shape
    d, n = q(pts[1])  # the reference solver's QueryFn protocol
    assert torch.equal(d, refit.distance) and torch.equal(n, refit.normal)


def test_max_distance_cuts_far_points(sphere):
    v, f = sphere
    pts = np.array([[0.0, 0.0, 0.31], [0.0, 0.0, 2.0], [0.0, 0.0, 0.0]])
    full = MeshQuery(v, f).query(pts)
    cut = MeshQuery(v, f).query(pts, max_distance=0.05)
    assert np.isinf(cut.distance[1]) and cut.face[1] == -1 and np.isnan(cut.closest[1]).all()
    assert np.isinf(cut.distance[2])  # the centre is 0.3 from the surface
    assert cut.distance[0] == pytest.approx(full.distance[0])


def test_winding_numbers_sphere(sphere):
    v, f = sphere
    w = winding_numbers(np.array([[0.0, 0.0, 0.0], [0.1, 0.1, 0.0], [0.5, 0, 0]]), v, f)
    assert torch.allclose(w, torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64), atol=1e-9)


def test_bad_inputs(sphere):
    v, f = sphere
    q = MeshQuery(v, f)
    with pytest.raises(ValueError, match="points"):
        q.query(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="points"):
        q.query(np.array([[0.0, np.nan, 0.0]]))
    with pytest.raises(ValueError, match="max_distance"):
        q.query(np.zeros((1, 3)), max_distance=-1.0)
    with pytest.raises(ValueError, match="vertices"):
        q.update(v[:-1])
    with pytest.raises(ValueError, match="faces"):
        MeshQuery(v, f + len(v))
    with pytest.raises(ValueError, match="faces"):
        MeshQuery(v, np.zeros((0, 3), dtype=np.int64))
    with pytest.raises(ValueError, match="batch"):
        signed_distance(np.zeros((2, 5, 3)), np.stack([v] * 3), f)
