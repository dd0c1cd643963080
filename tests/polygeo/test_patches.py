import numpy as np
import pytest
import torch
import trimesh

import polygeo.synthetic as syn
from polygeo import jets
from polygeo.frames import quaternion_to_matrix
from polygeo.partition import partition_mesh
from polygeo.patches import (
    PatchSet,
    chamfer_distance,
    chamfer_report,
    evaluate_patches,
    patch_geometry,
    subdivide_barycentric,
)
from polygeo.status import Status
from polygeo.stn import PatchSTN


@pytest.fixture(scope="module")
def sphere5():
    return syn.sphere_mesh(5)


def _rmse(ps):
    return ps.metrics(boundary=False).summary()["height_rmse_all"]


def _grid_sheet(nx=30, ny=20, hx=1.0, hy=0.6):
    x, y = np.meshgrid(np.linspace(-hx, hx, nx), np.linspace(-hy, hy, ny), indexing="ij")
    from polygeo.synthetic._common import grid_faces as _grid_faces

    return x.ravel(), y.ravel(), _grid_faces(nx, ny, False, False).astype(np.int64)


# ------------------------------------------------------------------ analytic truth


def test_single_patch_polynomial_height_is_exact():
    # an even polynomial over a symmetric rectangle: the PCA frame is the xyz frame, so the
    # quartic height is a quartic in the canonical uv and the order-4 fit is exact
    x, y, f = _grid_sheet()
    z = 0.1 * x**2 - 0.05 * y**2 + 0.03 * x**2 * y**2 - 0.02 * y**4
    v = np.stack([x, y, z], 1)
    ps = PatchSet.fit(v, f, n_patches=1, order=4)
    assert ps.n_patches == 1 and int(ps.status[0]) == Status.OK
    assert _rmse(ps) < 1e-13
    np.testing.assert_allclose(ps.fitted_vertices(), v, atol=1e-12)
    rv, rf = ps.resample(2)
    want = 0.1 * rv[:, 0] ** 2 - 0.05 * rv[:, 1] ** 2 + 0.03 * rv[:, 0] ** 2 * rv[:, 1] ** 2
    want -= 0.02 * rv[:, 1] ** 4
    np.testing.assert_allclose(rv[:, 2], want, atol=1e-12)
    # a flat sheet, arbitrarily placed, is exact at any order
    R = quaternion_to_matrix(torch.tensor([0.9, 0.2, -0.3, 0.1])).numpy()
    flat = np.stack([x, y, np.zeros_like(x)], 1) @ R.T + [0.3, -1.0, 2.0]
    for order in (1, 2, 4):
        pf = PatchSet.fit(flat, f, n_patches=1, order=order)
        assert _rmse(pf) < 1e-13
        np.testing.assert_allclose(pf.fitted_vertices(), flat, atol=1e-12)


def test_convergence_with_order_and_patch_count(sphere5):
    v, f = sphere5.points, sphere5.faces
    parts = {k: partition_mesh(v, f, k) for k in (16, 64)}
    err = {
        (k, o): _rmse(PatchSet.fit(v, f, partition=parts[k], order=o))
        for k in (16, 64)
        for o in (2, 4)
    }
    for k in (16, 64):
        assert err[(k, 4)] < 0.1 * err[(k, 2)], err
    # patch size h ~ K^(-1/2); an n-jet's height error is O(h^(n+1)) (O(h^(n+2)) for even n
    # on a sphere, by symmetry): quadrupling K divides it by at least 2^(n+1)
    for o in (2, 4):
        rate = np.log2(err[(16, o)] / err[(64, o)])
        assert rate > o + 0.7, f"order {o}: rate {rate:.2f}"


@pytest.mark.parametrize("name", ["torus", "cylinder", "wavy"])
def test_analytic_meshes_converge_and_resample_onto_the_surface(name):
    if name == "torus":
        m = syn.torus_mesh(96)
    elif name == "cylinder":
        m = syn.cylinder_mesh(96)
    else:
        m = syn.wavy_sheet_mesh(64, 64)
    part = partition_mesh(m.points, m.faces, 64, min_vertices=15)
    e2 = _rmse(PatchSet.fit(m.points, m.faces, partition=part, order=2))
    ps = PatchSet.fit(m.points, m.faces, partition=part, order=4)
    e4 = _rmse(ps)
    assert e4 < 0.2 * e2, (e2, e4)
    rv = ps.resample(1)[0]
    if name == "torus":
        rho = np.hypot(rv[:, 0], rv[:, 1])
        dist = np.abs(np.hypot(rho - 1.0, rv[:, 2]) - 0.3)
    elif name == "cylinder":
        dist = np.abs(np.hypot(rv[:, 0], rv[:, 1]) - 1.0)
    else:
        dist = np.abs(rv[:, 2] - 0.1 * np.sin(3 * rv[:, 0]) * np.cos(2 * rv[:, 1]))
    # new vertices (midpoints) are off the input samples: a few times the fit residual
    assert dist.max() < 2e-3, dist.max()
    assert np.sqrt(np.mean(dist**2)) < 10 * e4 + 1e-6
    met = ps.metrics().summary()
    assert met["boundary_gap_max"] < 5e-3
    assert met["foldover_mean"] == 0.0


def test_sphere_geometry_matches_analytic(sphere5):
    ps = PatchSet.fit(sphere5.points, sphere5.faces, n_patches=64, order=4)
    g = ps.geometry(ps.labels, ps._vertex_uv())
    np.testing.assert_allclose(g.positions.numpy(), sphere5.points, atol=1e-5)
    # outward normals, curvature -1/r (diffgeo's sign convention)
    cos = (g.geometry.normal.numpy() * sphere5.normals).sum(1)
    assert cos.min() > 0.9999
    np.testing.assert_allclose(g.geometry.k1.numpy(), -1.0, atol=2e-2)
    np.testing.assert_allclose(g.geometry.gaussian_curvature.numpy(), 1.0, atol=2e-2)
    # metric = J^T J
    J = g.geometry.jacobian
    torch.testing.assert_close(g.geometry.metric, J.transpose(-1, -2) @ J)
    met = ps.metrics()
    assert met.normal_error.max() < 0.5  # degrees (vertex normals of the mesh are O(h^2))
    assert met.boundary_gap.max() < 1e-5


def test_resample_is_watertight_and_consistent(sphere5):
    ps = PatchSet.fit(sphere5.points, sphere5.faces, n_patches=30, order=3)
    rv0, rf0 = ps.resample(0)
    np.testing.assert_allclose(rv0, ps.fitted_vertices(), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(rf0, sphere5.faces)
    rv, rf = ps.resample(2)
    assert rf.shape == (16 * len(sphere5.faces), 3)
    mesh = trimesh.Trimesh(rv, rf, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    # an open sheet keeps its boundary: 2^R boundary edges per input boundary edge
    w = syn.wavy_sheet_mesh(20, 20)
    pw = PatchSet.fit(w.points, w.faces, n_patches=8, order=3)
    _, wf = pw.resample(2)
    b_in = len(trimesh.Trimesh(w.points, w.faces, process=False).outline().entities)
    assert b_in == 1
    edges = np.sort(np.concatenate([wf[:, [0, 1]], wf[:, [1, 2]], wf[:, [2, 0]]]), axis=1)
    _, cnt = np.unique(edges, axis=0, return_counts=True)
    assert set(cnt) == {1, 2} and (cnt == 1).sum() == 4 * 19 * 4


def test_subdivision_table():
    f = np.array([[0, 1, 2], [2, 1, 3]])
    c, w, of = subdivide_barycentric(f, 4, 1)
    assert len(c) == 4 + 5 and of.shape == (8, 3)
    np.testing.assert_allclose(w.sum(1), 1.0)
    # the shared edge (1, 2) has one midpoint, used by both triangles
    mids = [i for i in range(4, 9) if set(c[i][w[i] > 0]) == {1, 2}]
    assert len(mids) == 1
    np.testing.assert_allclose(np.sort(w[mids[0]][w[mids[0]] > 0]), [0.5, 0.5])
    with pytest.raises(ValueError, match="level"):
        subdivide_barycentric(f, 4, -1)


def test_boundary_gap_shrinks_with_order(sphere5):
    g = [
        PatchSet.fit(sphere5.points, sphere5.faces, n_patches=25, order=o).metrics().summary()
        for o in (2, 4)
    ]
    assert g[1]["boundary_gap_mean"] < 0.2 * g[0]["boundary_gap_mean"]
    assert g[1]["boundary_normal_angle_mean"] < g[0]["boundary_normal_angle_mean"]


def test_foldover_detected_where_the_patch_is_not_a_height_graph():
    # a sheet bent into a 300-degree arc cannot be a graph over any plane
    x, y, f = _grid_sheet(40, 20, 1.0, 1.5)
    t = (x + 1) / 2 * np.deg2rad(300)
    v = np.stack([np.cos(t), y, np.sin(t)], 1)
    ps = PatchSet.fit(v, f, n_patches=1, order=4)
    assert ps.metrics().foldover[0] > 0.05
    flat = PatchSet.fit(np.stack([x, y, 0.1 * x**2], 1), f, n_patches=1, order=2)
    assert flat.metrics().foldover[0] == 0.0


@pytest.mark.parametrize("arc", [60.0, 150.0, 300.0])
def test_max_tilt_of_an_arc_is_half_the_arc_less_half_a_facet(arc):
    # a sheet bent into a circular arc (wide along the rulings, so that the PCA axis is the
    # arc's bisector): its steepest facet is the last one, whose normal is tilted by half
    # the arc less half a facet; above 90 degrees the triangles fold over the patch plane
    n = 41
    x, y, f = _grid_sheet(n, 12, 1.0, 2.0)
    t = x * np.deg2rad(arc) / 2
    v = np.stack([np.sin(t), y, 1.0 - np.cos(t)], 1)
    m = PatchSet.fit(v, f, n_patches=1, order=2).metrics(boundary=False)
    assert m.max_tilt[0] == pytest.approx(arc / 2 - arc / (n - 1) / 2, abs=1e-6)
    assert m.summary()["max_tilt"] == m.max_tilt[0]
    assert (m.foldover[0] > 0) == (arc / 2 > 90)
    assert PatchSet.fit(v, None, n_patches=1, order=2).metrics().max_tilt is None


# ------------------------------------------------------------------ independent / batched


def test_batched_fit_equals_per_patch_fits(sphere5):
    ps = PatchSet.fit(sphere5.points, sphere5.faces, n_patches=12, order=3)
    for k in (0, 5, 11):
        m = ps.mask[k]
        idx = ps.index[k][m]
        p = torch.from_numpy(sphere5.points)[idx]
        local = (p - ps.translation[k]) @ ps.rotation[k] / ps.scale[k]
        torch.testing.assert_close(local[:, :2], ps.uv[k][m])
        one = jets.fit(local[None, :, :2], local[None, :, 2], 3, backend="torch")
        torch.testing.assert_close(one.coeffs[0], ps.coeffs[k], atol=1e-9, rtol=1e-7)
    # batched evaluation equals per-item evaluation with an independent formula
    rng = np.random.default_rng(1)
    idx = torch.from_numpy(rng.integers(0, ps.n_patches, 7))
    uv = torch.from_numpy(rng.uniform(-0.5, 0.5, (7, 2)))
    got = ps.evaluate(idx, uv)
    for i in range(7):
        k = int(idx[i])
        u, v = float(uv[i, 0]), float(uv[i, 1])
        mono = [u ** (d - j) * v**j for d in range(4) for j in range(d + 1)]
        z = float(np.dot(ps.coeffs[k].numpy(), mono))
        want = ps.scale[k] * ps.rotation[k] @ torch.tensor([u, v, z], dtype=torch.float64)
        want = want + ps.translation[k]
        torch.testing.assert_close(got[i], want)


def test_numpy_in_numpy_out(sphere5):
    ps = PatchSet.fit(sphere5.points, sphere5.faces, n_patches=8, order=2)
    out = ps.evaluate(np.array([0, 1]), np.zeros((2, 2)))
    assert isinstance(out, np.ndarray) and out.shape == (2, 3)
    assert isinstance(ps.normals_at(0, np.zeros((3, 2))), np.ndarray)
    uv = ps.project(sphere5.points[:5], ps.labels[:5].numpy())
    np.testing.assert_allclose(uv, ps._vertex_uv()[:5].numpy(), atol=1e-12)


# ------------------------------------------------------------------ differentiability


def test_gradcheck_evaluate_wrt_coefficients_and_orientation():
    gen = torch.Generator().manual_seed(0)
    K, N = 3, 5
    c = (0.3 * torch.randn(K, 10, generator=gen, dtype=torch.float64)).requires_grad_()
    q = torch.randn(K, 4, generator=gen, dtype=torch.float64).requires_grad_()
    s = (1.0 + torch.rand(K, generator=gen, dtype=torch.float64)).requires_grad_()
    T = torch.randn(K, 3, generator=gen, dtype=torch.float64).requires_grad_()
    uv = (0.5 * torch.randn(N, 2, generator=gen, dtype=torch.float64)).requires_grad_()
    idx = torch.tensor([0, 2, 1, 2, 0])

    def pos(c, q, s, T, uv):
        return evaluate_patches(c, s, quaternion_to_matrix(q), T, idx, uv)

    assert torch.autograd.gradcheck(pos, (c, q, s, T, uv))

    def geo(c, q, uv):
        g = patch_geometry(c, s.detach(), quaternion_to_matrix(q), T.detach(), idx, uv)
        return g.geometry.normal, g.geometry.metric, g.geometry.mean_curvature

    assert torch.autograd.gradcheck(geo, (c, q, uv))


def test_resample_is_differentiable_wrt_coefficients(sphere5):
    ps = PatchSet.fit(torch.from_numpy(sphere5.points), torch.from_numpy(sphere5.faces),
                      n_patches=6, order=2)
    c = ps.coeffs.clone().requires_grad_()
    ps2 = PatchSet(**{**ps.__dict__, "coeffs": c})
    rv, _ = ps2.resample(1)
    rv.sum().backward()
    assert torch.isfinite(c.grad).all() and c.grad.abs().sum() > 0


# ------------------------------------------------------------------ parsimony


def test_order_auto_tolerance_and_bic():
    # half flat, half curved: flat patches need order 1, curved ones more
    x, y, f = _grid_sheet(60, 30, 1.0, 0.5)
    z = np.where(x > 0, 0.3 * x**3, 0.0)
    v = np.stack([x, y, z], 1)
    part = partition_mesh(v, f, 12, seed=0)
    tol = 1e-5
    auto = PatchSet.fit(v, f, partition=part, order="auto", tol=tol, max_order=5)
    fixed = PatchSet.fit(v, f, partition=part, order=5)
    met = auto.metrics(boundary=False)
    ok = met.height_rmse <= tol
    assert ok.all(), met.height_rmse
    assert met.order.min() == 1 and met.order.max() >= 3
    assert auto.n_coefficients < fixed.n_coefficients
    # the lower orders use a prefix of the coefficients: slots above the order are zero
    for k in range(auto.n_patches):
        o = int(auto.orders[k])
        assert torch.all(auto.coeffs[k, jets.n_coeffs(o) :] == 0)
    bic = PatchSet.fit(v, f, partition=part, order="auto", max_order=5)
    assert bic.metrics(boundary=False).order.min() <= 2
    assert bic.n_coefficients < fixed.n_coefficients


def test_target_rmse_chooses_patch_count(sphere5):
    ps = PatchSet.fit(sphere5.points, sphere5.faces, order=2, target_rmse=1e-4)
    assert ps.info["target_met"]
    assert _rmse(ps) <= 1e-4
    search = ps.info["search"]
    assert search[0]["height_rmse"] > 1e-4 and len(search) >= 2
    assert [r["requested"] for r in search] == sorted(r["requested"] for r in search)


# ------------------------------------------------------------------ other inputs


def test_point_cloud_fit_and_grid_resample():
    s = syn.sphere(3000, seed=0)
    ps = PatchSet.fit(s.points, None, n_patches=20, order=4, normals=s.normals)
    met = ps.metrics()
    assert met.foldover is None
    assert met.normal_error.max() < 0.5
    rv, rf = ps.resample(0, grid=5)
    assert rf.shape == (20 * 2 * 4 * 4, 3)
    np.testing.assert_allclose(np.linalg.norm(rv, axis=1), 1.0, atol=5e-3)


def test_optimize_orientation_is_never_worse_than_pca():
    v, f = syn.skirt_mesh(60, 30, seed=1)
    part = partition_mesh(v, f, 12, seed=0)
    pca = PatchSet.fit(v, f, partition=part, order=3)
    opt = PatchSet.fit(v, f, partition=part, order=3, orient="optimize", optimize_steps=15)
    assert (opt.residual <= pca.residual + 1e-12).all()
    assert opt.residual.mean() < pca.residual.mean()
    # orientations stay rotations and normals keep the input's side
    eye = torch.eye(3, dtype=torch.float64).expand(opt.n_patches, 3, 3)
    torch.testing.assert_close(opt.rotation.transpose(1, 2) @ opt.rotation, eye)
    assert ((opt.rotation[:, :, 2] * pca.rotation[:, :, 2]).sum(-1) > 0.5).all()


def test_save_load_roundtrip(tmp_path, sphere5):
    ps = PatchSet.fit(sphere5.points, sphere5.faces, n_patches=10, order="auto", max_order=4)
    path = ps.save(tmp_path / "set")
    assert path.name == "set.npz"
    assert [p.name for p in tmp_path.iterdir()] == ["set.npz"]  # no temporary file left
    back = PatchSet.load(path)
    for name in ("scale", "rotation", "translation", "coeffs", "orders", "uv", "mask", "index",
                 "labels", "faces", "boundary_pairs"):
        assert torch.equal(getattr(ps, name), getattr(back, name)), name
    assert back.orient == ps.orient and back.numpy_io and ps.numpy_io
    np.testing.assert_allclose(back.resample(1)[0], ps.resample(1)[0], rtol=0, atol=1e-15)
    with pytest.raises(FileNotFoundError):
        PatchSet.load(tmp_path / "missing.npz")
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(ValueError, match="PatchSet"):
        PatchSet.load(tmp_path / "other.npz")


def test_chamfer_distance_properties():
    s = syn.sphere_mesh(4)
    same = chamfer_distance(s.points, s.faces, s.points, s.faces, n_samples=4000)
    # two independent samplings of a surface of normalised area A: about 2 A / (pi n)
    floor = 2 * 4 * np.pi / (np.pi * 4000)
    assert 0.5 * floor < same < 1.5 * floor
    bigger = chamfer_distance(s.points, s.faces, 1.05 * s.points, s.faces, n_samples=4000)
    assert bigger > same + 0.5 * 0.05**2
    with pytest.raises(ValueError, match="normalize"):
        chamfer_distance(s.points, s.faces, s.points, s.faces, normalize="box")


def test_chamfer_dense_protocol_floor_and_report():
    # unit sphere, normalised area A = 4 pi: one side's floor is A / (pi n) = 4 / n
    s = syn.sphere_mesh(4)
    n, nb = 3000, 30000
    dense = chamfer_distance(s.points, s.faces, s.points, s.faces, n_samples=n, n_samples_b=nb)
    expect = 4.0 / n + 4.0 / nb
    assert 0.8 * expect < dense < 1.2 * expect
    rep = chamfer_report(s.points, s.faces, 1.02 * s.points, s.faces, n_samples=n, n_dense=nb)
    # a 2 % larger sphere: continuous Chamfer 2 * 0.02^2 (scaled into the unit ball by 1)
    assert rep.surface == pytest.approx(2 * 0.02**2, rel=0.1)
    assert rep.dense_floor < 0.7 * rep.points_floor
    assert rep.surface < rep.dense < rep.points
    d = rep.as_dict()
    assert d["points"] == pytest.approx(1e3 * rep.points) and d["n_dense"] == nb
    with pytest.raises(ValueError, match="n_samples_b"):
        chamfer_distance(s.points, s.faces, s.points, s.faces, n_samples_b=0)


# ------------------------------------------------------------------ failing inputs


def test_too_few_points_per_patch_is_flagged_not_nan():
    x, y, f = _grid_sheet(4, 4, 1.0, 1.0)
    v = np.stack([x, y, 0.2 * x**2 + 0.1 * y**3], 1)
    ps = PatchSet.fit(v, f, n_patches=1, order=6)  # 16 points < 28 coefficients
    assert int(ps.orders[0]) < 6
    assert int(ps.status[0]) in (Status.ORDER_REDUCED, Status.TOO_FEW_POINTS)
    assert torch.isfinite(ps.coeffs).all()
    assert np.isfinite(ps.resample(1)[0]).all()


def test_several_components_nonmanifold_and_degenerate_faces():
    s = syn.sphere_mesh(3)
    v = np.concatenate([s.points, s.points + [3.0, 0, 0]])
    f = np.concatenate([s.faces, s.faces + len(s.points)])
    f = np.concatenate([f, [[f[0, 0], f[0, 1], len(s.points) + 5]], [[0, 0, 1]]])
    ps = PatchSet.fit(v, f, n_patches=10, order=2)
    assert ps.n_patches >= 10
    assert torch.isfinite(ps.coeffs).all()
    m = ps.metrics()
    assert np.isfinite(m.height_rmse).all()


def test_bad_input(sphere5):
    v, f = sphere5.points, sphere5.faces
    with pytest.raises(ValueError, match="order"):
        PatchSet.fit(v, f, n_patches=4, order=7)
    with pytest.raises(ValueError, match="order"):
        PatchSet.fit(v, f, n_patches=4, order="best")
    with pytest.raises(TypeError, match="order"):
        PatchSet.fit(v, f, n_patches=4, order=2.5)
    with pytest.raises(ValueError, match="orient"):
        PatchSet.fit(v, f, n_patches=4, orient="svd")
    with pytest.raises(TypeError, match="faces"):
        PatchSet.fit(v, f.astype(float), n_patches=4)
    with pytest.raises(ValueError, match="faces"):
        PatchSet.fit(v, f + len(v), n_patches=4)
    bad = v.copy()
    bad[3] = np.inf
    with pytest.raises(ValueError, match="points"):
        PatchSet.fit(bad, f, n_patches=4)
    with pytest.raises(ValueError, match="points"):
        PatchSet.fit(v[:, :2], f, n_patches=4)
    with pytest.raises(ValueError, match="n_patches"):
        PatchSet.fit(v, f, n_patches=len(v) + 1)
    with pytest.raises(ValueError, match="partition"):
        PatchSet.fit(v[:-1], None, partition=partition_mesh(v, f, 4))
    with pytest.raises(ValueError, match="normals"):
        PatchSet.fit(v, f, n_patches=4, normals=np.ones((3, 3)))
    with pytest.raises(ValueError, match="target_rmse"):
        PatchSet.fit(v, f, target_rmse=-1.0)
    ps = PatchSet.fit(v, f, n_patches=4, order=2)
    with pytest.raises(ValueError, match="patch_idx"):
        ps.evaluate(np.array([0, 9]), np.zeros((2, 2)))
    with pytest.raises(ValueError, match="uv"):
        ps.evaluate(np.array([0, 1]), np.zeros((2, 3)))
    with pytest.raises(TypeError, match="patch_idx"):
        ps.evaluate(np.array([0.0, 1.0]), np.zeros((2, 2)))
    with pytest.raises(ValueError, match="resolution"):
        ps.resample(-1)


def test_surface_chamfer_matches_brute_force_point_to_triangle():
    from polygeo.patches import _closest_on_triangles, _point_to_mesh_sq

    rng = np.random.default_rng(0)
    a, b, c = rng.normal(size=(3, 400, 3))
    p = 2 * rng.normal(size=(400, 3))
    q = trimesh.triangles.closest_point(np.stack([a, b, c], 1), p)
    np.testing.assert_allclose(_closest_on_triangles(p, a, b, c), ((p - q) ** 2).sum(1),
                               atol=1e-12)
    s = syn.sphere_mesh(3)
    pts = rng.normal(size=(200, 3)) * 0.3 + 0.8 * s.normals[:200]
    m = trimesh.Trimesh(s.points, s.faces, process=False)
    _, dist, _ = trimesh.proximity.closest_point(m, pts)
    np.testing.assert_allclose(_point_to_mesh_sq(pts, s.points, s.faces), dist**2, atol=1e-12)
    # the surface variant has no sampling floor: a surface against itself is ~0
    assert chamfer_distance(s.points, s.faces, s.points, s.faces, mode="surface") < 1e-20
    d = chamfer_distance(s.points, s.faces, 1.05 * s.points, s.faces, mode="surface")
    # normalised by the reference's radius 1: every point is about 0.05 off, both ways
    np.testing.assert_allclose(d, 2 * 0.05**2, rtol=0.05)


def test_stn_orientation_is_never_worse_than_pca():
    v, f = syn.skirt_mesh(60, 30, seed=1)
    part = partition_mesh(v, f, 12, seed=0)
    pca = PatchSet.fit(v, f, partition=part, order=3)
    net = PatchSTN((8,), (8,))
    with torch.no_grad():
        net.out.weight.normal_(0, 1.0)  # a network that rotates patches at random
    st = PatchSet.fit(v, f, partition=part, order=3, orient="stn", stn_model=net)
    assert (st.residual <= pca.residual + 1e-12).all()


def test_order_cap_keeps_small_patches_from_swinging():
    # ~25 points per patch: an order-4 jet (15 coefficients) nearly interpolates them and
    # swings beyond its samples; the default cap (2 points per coefficient) lowers the order
    v, f = syn.body_mesh(4)
    part = partition_mesh(v, f, 100, min_vertices=15)
    free = PatchSet.fit(v, f, partition=part, order=4, min_points_per_coeff=0)
    capped = PatchSet.fit(v, f, partition=part, order=4)
    n = capped.mask.sum(1)
    o = capped.orders
    need = (o + 1) * (o + 2)  # 2 * n_coeffs(o)
    assert (need <= n).all()
    assert (capped.status[o < 4] == Status.ORDER_REDUCED).all()
    g_free = free.metrics().summary()["boundary_gap_max"]
    g_cap = capped.metrics().summary()["boundary_gap_max"]
    assert g_cap < 0.75 * g_free, (g_cap, g_free)
    c = [
        chamfer_distance(v, f, *ps.resample(1), mode="surface")
        for ps in (free, capped)
    ]
    assert c[1] < c[0]
    with pytest.raises(ValueError, match="min_points_per_coeff"):
        PatchSet.fit(v, f, partition=part, min_points_per_coeff=-1)


# ------------------------------------------------------------------ array types follow the input


def _kinds(*arrays):
    return {"numpy" if isinstance(a, np.ndarray) else "torch" if torch.is_tensor(a) else
            type(a).__name__ for a in arrays}


@pytest.mark.parametrize("cloud", [False, True], ids=["mesh", "cloud"])
def test_every_output_array_follows_the_input_type(cloud):
    # issue 17: resample returned torch vertices with NumPy faces; one type per call now
    s = syn.sphere_mesh(2)
    faces = None if cloud else s.faces
    ref = {}
    for as_torch in (False, True):
        pts = torch.from_numpy(s.points) if as_torch else s.points
        f = None if faces is None else (torch.from_numpy(faces) if as_torch else faces)
        ps = PatchSet.fit(pts, f, n_patches=4, order=2)
        want = {"torch" if as_torch else "numpy"}
        assert ps.numpy_io is (not as_torch)
        rv, rf = ps.resample(1)
        assert _kinds(rv, rf) == want
        assert rv.dtype in (np.float64, torch.float64) and rf.dtype in (np.int64, torch.int64)
        assert _kinds(ps.fitted_vertices()) == want
        uv = np.zeros((3, 2))
        idx = np.array([0, 1, 2])
        q = (torch.from_numpy(uv), torch.from_numpy(idx)) if as_torch else (uv, idx)
        assert _kinds(ps.evaluate(q[1], q[0]), ps.normals_at(q[1], q[0])) == want
        p3 = torch.from_numpy(s.points[:3]) if as_torch else s.points[:3]
        assert _kinds(ps.project(p3, q[1])) == want
        if as_torch:  # torch results stay differentiable w.r.t. the set's tensors
            c = ps.coeffs.clone().requires_grad_()
            PatchSet(**{**ps.__dict__, "coeffs": c}).resample(1)[0].sum().backward()
            assert c.grad.abs().sum() > 0
        # same surface whatever the input type
        if as_torch:
            np.testing.assert_allclose(rv.detach().numpy(), ref["v"], rtol=0, atol=1e-12)
            np.testing.assert_array_equal(rf.numpy(), ref["f"])
        else:
            ref.update(v=rv, f=rf)


def test_saved_set_keeps_its_array_type(tmp_path, sphere5):
    t = PatchSet.fit(torch.from_numpy(sphere5.points), torch.from_numpy(sphere5.faces),
                     n_patches=8, order=2)
    back = PatchSet.load(t.save(tmp_path / "t"))
    assert not back.numpy_io and _kinds(*back.resample(0)) == {"torch"}
    # a file of an older version (no numpy_io) reads as torch, as before
    with np.load(tmp_path / "t.npz") as z:
        old = {k: z[k] for k in z.files if k != "numpy_io"}
    np.savez(tmp_path / "old.npz", **old)
    assert _kinds(*PatchSet.load(tmp_path / "old.npz").resample(0)) == {"torch"}


def test_resampling_stages_return_torch_only(sphere5):
    from polygeo.patches.resampling import resample_grid, resample_subdivided

    ps = PatchSet.fit(torch.from_numpy(sphere5.points), torch.from_numpy(sphere5.faces),
                      n_patches=8, order=2)
    for out in (resample_subdivided(*ps._patches(), ps.labels, ps.vertices, ps.faces, 1),
                resample_grid(*ps._patches(), ps.domain, 3)):
        assert _kinds(*out) == {"torch"} and out[1].dtype == torch.int64
