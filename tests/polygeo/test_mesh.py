import numpy as np
import pytest
import torch
import trimesh

from polygeo import mesh


@pytest.fixture
def sphere():
    m = trimesh.creation.icosphere(subdivisions=2)
    return np.asarray(m.vertices), np.asarray(m.faces)


def grid(n=6, jitter=0.0, seed=0):
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], 1)
    interior = (x.ravel() > 0) & (x.ravel() < 1) & (y.ravel() > 0) & (y.ravel() < 1)
    v[interior, :2] += jitter * rng.uniform(-1, 1, (interior.sum(), 2)) / n
    f = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
            f += [[a, b, c], [a, c, d]]
    return v, np.array(f), interior


def test_edges_euler(sphere):
    v, f = sphere
    e = mesh.edges(f)
    assert len(e) == 3 * len(f) // 2
    assert len(v) - len(e) + len(f) == 2
    assert (e[:, 0] < e[:, 1]).all()


def test_lengths_areas_normals_against_trimesh(sphere):
    v, f = sphere
    m = trimesh.Trimesh(v, f, process=False)
    np.testing.assert_allclose(mesh.face_areas(v, f), m.area_faces, rtol=1e-12)
    fn = mesh.face_normals(v, f)
    np.testing.assert_allclose(fn.normals, m.face_normals, atol=1e-12)
    assert fn.valid.all()
    e = mesh.edges(f)
    np.testing.assert_allclose(
        mesh.edge_lengths(v, e), np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1)
    )


def test_unit_cube_area_and_dihedral():
    m = trimesh.creation.box()
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    assert mesh.face_areas(v, f).sum() == pytest.approx(6.0)
    d = mesh.dihedral_angles(v, f)
    ang = np.sort(np.abs(d.angle))
    # 12 creases at pi/2 (convex: positive), 6 face diagonals flat
    assert np.allclose(ang[:6], 0, atol=1e-12) and np.allclose(ang[6:], np.pi / 2)
    assert (d.angle > -1e-12).all()


def test_dihedral_sign_flips_with_winding(sphere):
    v, f = sphere
    d = mesh.dihedral_angles(v, f)
    d2 = mesh.dihedral_angles(v, f[:, ::-1])
    assert (d.angle > 0).all()  # convex with outward normals
    assert (d2.angle < 0).all()
    # magnitude: the angle between trimesh's face normals of the two faces
    fn = trimesh.Trimesh(v, f, process=False).face_normals
    cosang = np.einsum("ij,ij->i", fn[d.faces[:, 0]], fn[d.faces[:, 1]])
    np.testing.assert_allclose(d.angle, np.arccos(np.clip(cosang, -1, 1)), atol=1e-7)


def test_vertex_normals_converge_to_sphere_normals():
    errs = []
    for s in (2, 3, 4):
        m = trimesh.creation.icosphere(subdivisions=s)
        v, f = np.asarray(m.vertices), np.asarray(m.faces)
        for w in ("area", "angle", "uniform"):
            vn = mesh.vertex_normals(v, f, w)
            assert vn.valid.all()
        vn = mesh.vertex_normals(v, f, "angle").normals
        # trimesh weights face normals by corner angles too: an independent implementation
        np.testing.assert_allclose(vn, m.vertex_normals, atol=1e-10)
        errs.append(np.abs(vn - v / np.linalg.norm(v, axis=1, keepdims=True)).max())
    # first-order convergence: halving the edge length halves the error
    assert all(1.7 < a / b < 2.3 for a, b in zip(errs, errs[1:]))


def test_cotangent_weights_equilateral_and_linear_precision():
    v = np.array([[0, 0, 0], [1, 0, 0], [0.5, np.sqrt(3) / 2, 0]])
    cw = mesh.cotangent_weights(v, np.array([[0, 1, 2]]))
    np.testing.assert_allclose(cw.weight, 0.5 / np.sqrt(3))
    # the cotangent Laplacian reproduces linear functions at interior vertices
    v, f, interior = grid(7, jitter=0.25)
    cw = mesh.cotangent_weights(v, f)
    e, w = cw.edges, cw.weight
    lap = np.zeros_like(v)
    np.add.at(lap, e[:, 0], w[:, None] * (v[e[:, 1]] - v[e[:, 0]]))
    np.add.at(lap, e[:, 1], w[:, None] * (v[e[:, 0]] - v[e[:, 1]]))
    np.testing.assert_allclose(lap[interior], 0, atol=1e-12)


def test_degenerate_face_valid_mask_and_finite_gradients():
    v = torch.tensor([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]], dtype=torch.float64)
    v.requires_grad_(True)
    f = torch.tensor([[0, 1, 2], [0, 1, 3]])
    fn = mesh.face_normals(v, f)
    assert fn.valid.tolist() == [False, True]
    assert torch.isfinite(fn.normals).all() and (fn.normals[0] == 0).all()
    loss = fn.normals.sum() + mesh.face_areas(v, f).sum()
    loss = loss + mesh.vertex_normals(v, f, "angle").normals.sum()
    loss = loss + mesh.edge_lengths(v, torch.tensor([[0, 0], [0, 1]])).sum()
    loss.backward()
    assert torch.isfinite(v.grad).all()


def test_nan_vertex_does_not_spread():
    v, f, _ = grid(5)
    v = v.copy()
    v[0] = np.nan
    vn = mesh.vertex_normals(v, f)
    assert not vn.valid[0]
    assert np.isfinite(vn.normals).all()
    assert vn.valid[1:].all()


def test_gradcheck_geometry(gen):
    v = torch.rand(6, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    f = torch.tensor([[0, 1, 2], [1, 3, 2], [2, 3, 4], [3, 5, 4]])
    e = torch.tensor([[0, 1], [2, 5]])
    torch.autograd.gradcheck(lambda x: mesh.edge_lengths(x, e), (v,))
    torch.autograd.gradcheck(lambda x: mesh.face_areas(x, f), (v,))
    torch.autograd.gradcheck(lambda x: mesh.face_normals(x, f).normals, (v,))
    torch.autograd.gradcheck(lambda x: mesh.vertex_normals(x, f, "angle").normals, (v,))
    torch.autograd.gradcheck(lambda x: mesh.dihedral_angles(x, f).angle, (v,))
    torch.autograd.gradcheck(lambda x: mesh.cotangent_weights(x, f).weight, (v,))


def test_batched_equals_per_item(sphere, rng):
    v, f = sphere
    vb = np.stack([v, v * 2 + rng.normal(0, 0.01, v.shape)])
    for fn in (
        lambda x: mesh.face_areas(x, f),
        lambda x: mesh.face_normals(x, f).normals,
        lambda x: mesh.vertex_normals(x, f).normals,
        lambda x: mesh.dihedral_angles(x, f).angle,
        lambda x: mesh.cotangent_weights(x, f).weight,
    ):
        b = fn(vb)
        for i in range(2):
            np.testing.assert_allclose(b[i], fn(vb[i]), atol=1e-13)


def test_boundary_and_components(sphere):
    v, f = sphere
    assert len(mesh.boundary_edges(f)) == 0
    gv, gf, _ = grid(4)
    b = mesh.boundary_edges(gf)
    assert len(b) == 4 * 3
    # boundary edges directed as in their faces: each vertex appears once as start
    assert len(np.unique(b[:, 0])) == len(b)
    f2 = np.concatenate([f, f + len(v)])
    n, lab = mesh.connected_components(f2, 2 * len(v) + 1)
    assert n == 3 and (lab[: len(v)] == 0).all() and (lab[len(v) : -1] == 1).all()


def test_non_manifold_fin():
    f = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    nm = mesh.non_manifold_edges(f)
    assert nm.tolist() == [[0, 1]]
    out = mesh.orient_faces(f)
    assert out.faces.shape == (3, 3)


def test_weld_soup_restores_mesh(sphere, rng):
    v, f = sphere
    soup_v = v[f].reshape(-1, 3)
    soup_f = np.arange(len(soup_v)).reshape(-1, 3)
    w = mesh.weld_vertices(soup_v, soup_f)
    assert len(w.vertices) == len(v)
    np.testing.assert_allclose(w.vertices[w.faces], v[f])
    # with a tolerance, jittered copies merge too
    jit = soup_v + rng.uniform(-1e-9, 1e-9, soup_v.shape)
    w2 = mesh.weld_vertices(jit, soup_f, tol=1e-6)
    assert len(w2.vertices) == len(v)
    assert len(w2.faces) == len(f)


def test_weld_drops_collapsed_faces():
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 0], [0, 1, 0.0]])
    w = mesh.weld_vertices(v, np.array([[0, 1, 2], [0, 1, 3]]))
    assert w.kept_faces.tolist() == [1] and len(w.vertices) == 3


def test_remove_unreferenced():
    v = np.arange(15, dtype=float).reshape(5, 3)
    c = mesh.remove_unreferenced_vertices(v, np.array([[0, 2, 4]]))
    assert c.kept.tolist() == [0, 2, 4]
    assert c.mapping.tolist() == [0, -1, 1, -1, 2]
    np.testing.assert_allclose(c.vertices[c.faces], v[[[0, 2, 4]]])


def test_orient_faces_half_flipped_closed(sphere, rng):
    v, f = sphere
    fl = rng.random(len(f)) < 0.5
    g = f.copy()
    g[fl] = g[fl][:, ::-1]
    out = mesh.orient_faces(g, v)
    assert out.n_components == 1 and out.orientable.all()
    np.testing.assert_array_equal(out.faces, f)  # outward like the icosphere
    np.testing.assert_array_equal(out.flipped, fl)
    # inside-out input comes back outward too
    out2 = mesh.orient_faces(f[:, ::-1], v)
    np.testing.assert_array_equal(out2.faces, f)


def test_orient_faces_open_uses_fewest_flips(rng):
    _, f, _ = grid(6)
    fl = rng.random(len(f)) < 0.3
    g = f.copy()
    g[fl] = g[fl][:, ::-1]
    out = mesh.orient_faces(g)
    np.testing.assert_array_equal(out.faces, f)
    assert out.flipped.sum() == fl.sum()


def test_orient_faces_moebius_not_orientable():
    n = 12
    f = []
    for i in range(n):
        a, b = 2 * i, 2 * i + 1
        c, d = (2 * i + 2) % (2 * n), (2 * i + 3) % (2 * n)
        if i == n - 1:  # the half twist
            c, d = d, c
        f += [[a, b, d], [a, d, c]]
    out = mesh.orient_faces(np.array(f))
    assert out.n_components == 1 and not out.orientable[0]
    # the same band without the twist is an orientable annulus
    f[-2:] = [[2 * n - 2, 2 * n - 1, 1], [2 * n - 2, 1, 0]]
    out = mesh.orient_faces(np.array(f))
    assert out.orientable[0]


@pytest.mark.parametrize(
    "call, exc",
    [
        (lambda: mesh.edges(np.zeros((3, 4), dtype=int)), ValueError),
        (lambda: mesh.edges(np.zeros((3, 3))), TypeError),
        (lambda: mesh.edges(np.array([[0, -1, 2]])), ValueError),
        (lambda: mesh.face_areas(np.zeros((3, 2)), np.array([[0, 1, 2]])), ValueError),
        (lambda: mesh.face_areas(np.zeros((3, 3)), np.array([[0, 1, 3]])), ValueError),
        (lambda: mesh.vertex_normals(np.zeros((3, 3)), np.array([[0, 1, 2]]), "foo"), ValueError),
        (lambda: mesh.edge_lengths(np.zeros((3, 3)), np.array([[0, 3]])), ValueError),
        (lambda: mesh.edge_lengths(np.zeros((3, 3)), np.array([[0.0, 1]])), TypeError),
        (lambda: mesh.connected_components(np.array([[0, 1, 2]]), 2), ValueError),
        (lambda: mesh.weld_vertices(np.zeros((3, 3)), np.array([[0, 1, 2]]), tol=-1), ValueError),
        (lambda: mesh.orient_faces(np.array([[0, 1, 2]]), np.zeros((2, 3))), ValueError),
    ],
)
def test_validators(call, exc):
    with pytest.raises(exc):
        call()


def test_dihedral_hinges_reuse_matches_search():
    u, w = np.meshgrid(np.linspace(0, 1, 5), np.linspace(0, 1, 5), indexing="ij")
    v = np.stack([u.ravel(), w.ravel(), np.zeros(25)], 1)
    a = np.array([i * 5 + j for i in range(4) for j in range(4)])
    f = np.concatenate([np.stack([a, a + 5, a + 1], 1), np.stack([a + 1, a + 5, a + 6], 1)])
    x = torch.tensor(v) + 0.05 * torch.randn(25, 3, generator=torch.Generator().manual_seed(0),
                                              dtype=torch.float64)
    d = mesh.dihedral_angles(x, f)
    d2 = mesh.dihedral_angles(x, f, hinges=d)
    assert torch.equal(d.angle, d2.angle)
    with pytest.raises(TypeError, match="hinges"):
        mesh.dihedral_angles(x, f, hinges=(d.edges, d.faces))
    with pytest.raises(ValueError, match="hinges"):
        mesh.dihedral_angles(x[:6], f[:1], hinges=d)


def test_edge_length_energy_isometry_stretch_and_units(sphere, rng):
    v, f = sphere
    e = mesh.edges(f)
    rest = np.linalg.norm(v[e[:, 1]] - v[e[:, 0]], axis=1)  # independent of edge_lengths
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    moved = np.stack([v, v @ q.T + 2.0])  # rigid motions are free
    np.testing.assert_allclose(mesh.edge_length_energy(moved, e, rest), [0.0, 0.0], atol=1e-24)
    eps, scale = 0.02, 3.0  # uniform stretch: eps^2 sum (r / scale)^2
    got = mesh.edge_length_energy((1 + eps) * v, e, rest, scale)
    assert isinstance(got, np.ndarray) and got.shape == ()
    assert float(got) == pytest.approx(eps**2 * np.sum((rest / scale) ** 2), rel=1e-10)
    # scale-free: the same shape in millimetres with scale in millimetres
    mm = mesh.edge_length_energy(1000 * (1 + eps) * v, e, 1000 * rest, 1000 * scale)
    assert float(mm) == pytest.approx(float(got), rel=1e-10)
    # torch in, torch out; float32 vertices against float64 rest lengths
    t = mesh.edge_length_energy(torch.tensor((1 + eps) * v, dtype=torch.float32), e, rest,
                                scale)
    assert t.dtype == torch.float32 and float(t) == pytest.approx(float(got), rel=1e-4)


def test_edge_length_energy_gradcheck_and_zero_length_edge(gen):
    v, f, _ = grid(4, jitter=0.3)
    e = mesh.edges(f)
    rest = torch.rand(len(e), generator=gen, dtype=torch.float64) * 0.3
    x = (torch.tensor(v) + 0.05 * torch.randn(2, *v.shape, generator=gen,
                                              dtype=torch.float64)).requires_grad_(True)
    torch.autograd.gradcheck(lambda z: mesh.edge_length_energy(z, e, rest, 0.7), (x,))
    # a collapsed edge: finite energy and gradients (no NaN)
    y = torch.tensor(v).clone()
    y[e[0, 1]] = y[e[0, 0]]
    y.requires_grad_(True)
    mesh.edge_length_energy(y, e, rest).backward()
    assert torch.isfinite(y.grad).all()


@pytest.mark.parametrize("kwargs, exc, match", [
    (dict(rest_lengths=np.ones(3)), ValueError, "rest_lengths"),
    (dict(rest_lengths=-np.ones(10)), ValueError, "rest_lengths: expected values >= 0"),
    (dict(rest_lengths=np.full(10, np.nan)), ValueError, "rest_lengths: expected finite"),
    (dict(scale=0.0), ValueError, "scale: expected a finite value > 0"),
    (dict(scale="a"), TypeError, "scale"),
    (dict(vertices=np.ones((5, 2))), ValueError, "vertices"),
])
def test_edge_length_energy_validators(kwargs, exc, match):
    v, f, _ = grid(3)
    e = mesh.edges(f)[:10]
    args = {"vertices": v, "edge_index": e, "rest_lengths": np.ones(10), **kwargs}
    with pytest.raises(exc, match=match):
        mesh.edge_length_energy(**args)
