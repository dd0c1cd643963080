import math

import numpy as np
import pytest
import torch

from polygeo import diffgeo, synthetic

SAMPLERS = {
    "sphere": lambda **kw: synthetic.sphere(300, radius=1.7, **kw),
    "cylinder": lambda **kw: synthetic.cylinder(300, radius=0.8, height=1.5, **kw),
    "torus": lambda **kw: synthetic.torus(300, R=1.2, r=0.4, **kw),
    "monge_patch": lambda **kw: synthetic.monge_patch(300, 1.0, -0.5, (0.2, 0.1, -0.3, 0.4),
                                                      (0.5, 0.2, 0.1, -0.2, 0.3), **kw),
    "plane": lambda **kw: synthetic.plane(300, **kw),
}
MESHES = {
    "sphere_mesh": lambda: synthetic.sphere_mesh(3, radius=1.3),
    "cylinder_mesh": lambda: synthetic.cylinder_mesh(24, radius=0.6, height=1.0),
    "torus_mesh": lambda: synthetic.torus_mesh(40, R=1.0, r=0.3),
    "monge_patch_mesh": lambda: synthetic.monge_patch_mesh(12, 0.8, 0.2, (0.1, 0, 0, 0.2)),
    "plane_mesh": lambda: synthetic.plane_mesh(6),
    "wavy_sheet_mesh": lambda: synthetic.wavy_sheet_mesh(20, 15),
}


def _implicit_residual(s):
    """Distance-like residual of the points to their analytic surface."""
    p = s.points
    if s.name == "sphere":
        return np.linalg.norm(p, axis=1) - np.linalg.norm(p, axis=1).mean()
    if s.name == "cylinder":
        r = np.linalg.norm(p[:, :2], axis=1)
        return r - r.mean()
    if s.name == "torus":
        R = 1.2 if len(s) == 300 else 1.0
        q = np.linalg.norm(p[:, :2], axis=1) - R
        d = np.sqrt(q**2 + p[:, 2] ** 2)
        return d - d.mean()
    return np.zeros(len(p))


def _check_consistency(s):
    n = len(s)
    for name in ("points", "normals", "d1", "d2", "noisy_points"):
        arr = getattr(s, name)
        assert arr.shape == (n, 3) and arr.dtype == np.float64, name
    for name in ("k1", "k2", "mean_curvature", "gaussian_curvature"):
        assert getattr(s, name).shape == (n,)
    np.testing.assert_allclose(np.linalg.norm(s.normals, axis=1), 1, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(s.d1, axis=1), 1, atol=1e-12)
    np.testing.assert_allclose(np.cross(s.d1, s.d2), s.normals, atol=1e-12)
    assert np.abs((s.d1 * s.normals).sum(1)).max() < 1e-12
    assert (s.k1 >= s.k2 - 1e-12).all()
    np.testing.assert_allclose(s.mean_curvature, (s.k1 + s.k2) / 2)
    np.testing.assert_allclose(s.gaussian_curvature, s.k1 * s.k2)
    assert np.abs(_implicit_residual(s)).max() < 1e-12


@pytest.mark.parametrize("name", sorted(SAMPLERS))
def test_samplers_are_consistent_and_seeded(name):
    a = SAMPLERS[name](seed=3)
    b = SAMPLERS[name](seed=3)
    c = SAMPLERS[name](seed=4)
    assert len(a) == 300 and a.faces is None
    np.testing.assert_array_equal(a.points, b.points)
    assert not np.allclose(a.points, c.points)
    _check_consistency(a)
    np.testing.assert_array_equal(a.noisy_points, a.points)
    g = SAMPLERS[name](seed=0, grid=True)
    _check_consistency(g)
    assert abs(len(g) - 300) < 60


@pytest.mark.parametrize("name", sorted(MESHES))
def test_meshes_are_oriented_like_normals(name):
    s = MESHES[name]()
    _check_consistency(s)
    f = s.faces
    assert f.dtype == np.int64 and f.min() >= 0 and f.max() == len(s) - 1
    assert len(np.unique(f)) == len(s)  # no unreferenced vertex
    tri = s.points[f]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert (np.linalg.norm(fn, axis=1) > 0).all()  # no degenerate triangle
    assert ((fn * s.normals[f].mean(1)).sum(1) > 0).all()
    # every edge is shared by at most two faces, in opposite directions (consistent manifold)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    assert len({tuple(x) for x in e.tolist()}) == len(e)


def test_closed_meshes_gauss_bonnet():
    # sum of K * (vertex area) approximates the integral of K: 4 pi (sphere), 0 (torus)
    for s, expect in ((synthetic.sphere_mesh(4, radius=2.0), 4 * math.pi),
                      (synthetic.torus_mesh(80), 0.0)):
        tri = s.points[s.faces]
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        va = np.zeros(len(s))
        np.add.at(va, s.faces.ravel(), np.repeat(area / 3, 3))
        total = float((s.gaussian_curvature * va).sum())
        assert abs(total - expect) < 0.02 * 4 * math.pi


def test_exact_quantities_match_diffgeo_on_graphs():
    s = synthetic.wavy_sheet_mesh(9, 7)
    x, y = s.uv[:, 0], s.uv[:, 1]
    # derivatives of 0.1 sin(3x) cos(2y), checked against central differences first
    def f(x, y):
        return 0.1 * np.sin(3 * x) * np.cos(2 * y)

    fx = 0.3 * np.cos(3 * x) * np.cos(2 * y)
    fy = -0.2 * np.sin(3 * x) * np.sin(2 * y)
    eps = 1e-6
    np.testing.assert_allclose((f(x + eps, y) - f(x - eps, y)) / (2 * eps), fx, atol=1e-8)
    np.testing.assert_allclose((f(x, y + eps) - f(x, y - eps)) / (2 * eps), fy, atol=1e-8)
    np.testing.assert_allclose(s.points[:, 2], f(x, y), atol=1e-15)
    fxx, fxy, fyy = -0.9 * np.sin(3 * x) * np.cos(2 * y), -0.6 * np.cos(3 * x) * np.sin(2 * y), \
        -0.4 * np.sin(3 * x) * np.cos(2 * y)
    o, one = np.zeros_like(x), np.ones_like(x)
    g = diffgeo.from_derivatives(*(torch.from_numpy(np.stack(v, 1)) for v in (
        (one, o, fx), (o, one, fy), (o, o, fxx), (o, o, fxy), (o, o, fyy))))
    np.testing.assert_allclose(g.k1.numpy(), s.k1, atol=1e-12)
    np.testing.assert_allclose(g.k2.numpy(), s.k2, atol=1e-12)
    np.testing.assert_allclose(g.normal.numpy(), s.normals, atol=1e-12)
    dots = np.abs((g.d1.numpy() * s.d1).sum(1))
    aniso = s.k1 - s.k2 > 1e-6
    np.testing.assert_allclose(dots[aniso], 1, atol=1e-9)


def test_known_values():
    s = synthetic.sphere(50, radius=2.0)
    np.testing.assert_allclose(s.k1, -0.5)
    np.testing.assert_allclose(s.gaussian_curvature, 0.25)
    np.testing.assert_allclose(s.normals, s.points / 2.0, atol=1e-15)
    c = synthetic.cylinder(50, radius=0.5)
    np.testing.assert_allclose(c.k1, 0.0)
    np.testing.assert_allclose(c.k2, -2.0)
    np.testing.assert_allclose(c.d1, np.tile([0, 0, 1.0], (50, 1)))
    m = synthetic.monge_patch(10, 0.3, 0.9, extent=1e-9)  # near the origin: k's given
    np.testing.assert_allclose(m.k1, 0.9, atol=1e-12)
    np.testing.assert_allclose(m.k2, 0.3, atol=1e-12)
    np.testing.assert_allclose(np.abs(m.d1[:, 1]), 1.0, atol=1e-9)
    p = synthetic.plane(20)
    assert np.all(p.k1 == 0) and np.all(p.points[:, 2] == 0)
    np.testing.assert_allclose(p.normals, np.tile([0, 0, 1.0], (20, 1)))


def test_uniform_area_sampling_on_torus():
    R, r, n = 1.0, 0.5, 20000
    s = synthetic.torus(n, R=R, r=r, seed=1)
    outer = np.cos(s.uv[:, 1]) > 0
    # area fraction of the outer half: (pi R + 2 r) / (2 pi R)
    expect = (math.pi * R + 2 * r) / (2 * math.pi * R)
    assert abs(outer.mean() - expect) < 4 * math.sqrt(expect * (1 - expect) / n)
    assert abs(outer.mean() - 0.5) > 0.1  # a uniform-in-angle sampler would give 0.5


def test_noise_is_separate_and_scaled():
    s = synthetic.torus(5000, noise=0.01, seed=2)
    clean = synthetic.torus(5000, seed=2)
    np.testing.assert_array_equal(s.points, clean.points)
    diag = np.linalg.norm(s.points.max(0) - s.points.min(0))
    assert s.noise_sigma == pytest.approx(0.01 * diag)
    d = s.noisy_points - s.points
    assert abs(d.std() / s.noise_sigma - 1) < 0.05


def test_validators():
    with pytest.raises(ValueError, match="n"):
        synthetic.sphere(-1)
    with pytest.raises(TypeError, match="n"):
        synthetic.sphere(10.5)
    with pytest.raises(ValueError, match="radius"):
        synthetic.sphere(10, radius=0)
    with pytest.raises(ValueError, match="r"):
        synthetic.torus(10, R=1.0, r=1.5)
    with pytest.raises(ValueError, match="b"):
        synthetic.monge_patch(10, b=(1, 2, 3))
    with pytest.raises(ValueError, match="noise"):
        synthetic.plane(10, noise=-0.1)
    with pytest.raises(ValueError, match="resolution"):
        synthetic.cylinder_mesh(2)
    with pytest.raises(ValueError, match="subdivisions"):
        synthetic.sphere_mesh(9)
    assert len(synthetic.sphere(0)) == 0


def test_family_patches_on_given_uv_is_the_family_surface():
    # trig family only, amplitude a, no rotation: the height is a cos(theta r) exactly
    grid = synthetic.plane_mesh(9)
    uv = grid.points[:, :2]
    f = synthetic.family_patches(3, families=("trig",), uv=uv, max_angle=0.0, seed=4)
    assert f.points.shape == (3, 81, 3)
    np.testing.assert_array_equal(f.points[..., :2], np.broadcast_to(uv, (3, 81, 2)))
    r = np.linalg.norm(uv, axis=1)
    # recover (a, theta) of each patch from r = 0 and r = 0.25 (theta r <= pi/2 there)
    i0, i1 = np.argmin(r), int(np.argmin(np.abs(r - 0.25)))
    for b in range(3):
        z = f.points[b, :, 2]
        a = z[i0]
        assert 0 < abs(a) <= 0.5
        theta = np.arccos(z[i1] / a) / r[i1]
        assert np.pi <= theta <= 2 * np.pi
        np.testing.assert_allclose(z, a * np.cos(theta * r), atol=1e-12)


def test_family_patches_uv_validation():
    with pytest.raises(ValueError, match="uv"):
        synthetic.family_patches(2, uv=np.zeros((5, 3)))
    with pytest.raises(ValueError, match="uv"):
        synthetic.family_patches(2, uv=np.zeros((3, 5, 2)))  # 3 sets for 2 patches
    with pytest.raises(ValueError, match="uv"):
        synthetic.family_patches(2, uv=np.full((5, 2), np.nan))
    with pytest.raises(TypeError, match="uv"):
        synthetic.family_patches(2, uv=np.array([["a", "b"]]))


def test_family_grid_patches_padding_and_grid():
    pts, mask = synthetic.family_grid_patches(6, 40, seed=1)
    assert pts.shape == (6, 40, 3) and mask.shape == (6, 40)
    counts = mask.sum(1)
    # m in [2, 6] (m_max = 6): min(m^2, 40) points first, zero padding after
    assert set(counts) <= {4, 9, 16, 25, 36}
    for b in range(6):
        assert mask[b, : counts[b]].all() and not mask[b, counts[b] :].any()
        assert (pts[b, counts[b] :] == 0).all()
    again, _ = synthetic.family_grid_patches(6, 40, seed=1)
    np.testing.assert_array_equal(pts, again)
    with pytest.raises(ValueError, match="n_points"):
        synthetic.family_grid_patches(2, 0)
