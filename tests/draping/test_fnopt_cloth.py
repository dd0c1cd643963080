import math

import pytest
import torch

from draping.fnopt import cloth, handles, solvers
from draping.fnopt.cloth import Material, Sheet

torch.set_num_threads(1)


def _deformed(sheet, kind, eps, dtype=torch.float64):
    """An analytic deformation of the hanging sheet (u right, v down, both in metres)."""
    x = cloth.rest_positions(sheet, dtype=dtype)
    u, v = x[..., 0].clone(), -x[..., 2].clone()
    if kind == "stretch":
        return torch.stack([(1 + eps) * u, 0 * u, -v], -1)
    if kind == "shear":
        return torch.stack([u + eps * v, 0 * u, -v], -1)
    if kind == "bend":   # roll the sheet onto a cylinder of radius 1/eps (isometric)
        r = 1 / eps
        return torch.stack([r * torch.sin(u / r), r * (1 - torch.cos(u / r)), -v], -1)
    if kind == "smooth":
        return torch.stack([1.03 * u + 0.02 * v * v, 0.1 * torch.sin(3 * u) * torch.cos(2 * v),
                            -v + 0.05 * u * v], -1)
    raise AssertionError(kind)


def _energies(sheet, x):
    return cloth.internal_energies(x[None], sheet.hx, sheet.hy,
                                   Material().tensors(1, torch.float64))


def test_energies_zero_at_rest_and_rigid_motion():
    sheet = Sheet(12, 9)
    x = cloth.rest_positions(sheet, dtype=torch.float64)
    rot = torch.linalg.matrix_exp(torch.tensor([[0, -0.3, 0.2], [0.3, 0, -0.5], [-0.2, 0.5, 0]],
                                               dtype=torch.float64))
    for y in (x, x @ rot.T + torch.tensor([0.3, -1.0, 2.0], dtype=torch.float64)):
        e = _energies(sheet, y)
        for k in ("stretch", "shear", "bend"):
            assert abs(float(e[k][0])) < 1e-20, k


@pytest.mark.parametrize("kind,positive", [("stretch", "stretch"), ("shear", "shear"),
                                           ("bend", "bend")])
def test_energies_positive_under_their_deformation(kind, positive):
    sheet = Sheet(16, 16)
    e = _energies(sheet, _deformed(sheet, kind, 0.1 if kind != "bend" else 2.0))
    assert float(e[positive][0]) > 0
    if kind == "stretch":
        # analytic: k_s / 2 * e_uu^2 * area with e_uu = ((1+eps)^2 - 1) / 2
        euu = ((1.1) ** 2 - 1) / 2
        assert float(e["stretch"][0]) == pytest.approx(0.5 * 300 * euu ** 2, rel=1e-9)
        assert float(e["shear"][0]) == pytest.approx(0.0, abs=1e-20)
    if kind == "bend":
        # an isometric roll: no stretch to first order, bend = k_b / 2 * kappa^2 * area
        assert float(e["bend"][0]) == pytest.approx(0.5e-3 * 1.0 * 4.0, rel=2e-2)
        # the chords of the roll are shorter by O(h^2 kappa^2): a small stretch remains
        assert float(e["stretch"][0]) < 0.1 * float(e["bend"][0])


def test_energies_converge_under_refinement():
    vals = {}
    for n in (32, 64, 100):
        sheet = Sheet(n, n)
        e = _energies(sheet, _deformed(sheet, "smooth", 0))
        vals[n] = {k: float(v[0]) for k, v in e.items()}
    for k in ("stretch", "shear", "bend"):
        assert vals[64][k] == pytest.approx(vals[100][k], rel=0.02), k
        assert vals[32][k] == pytest.approx(vals[100][k], rel=0.06), k
        # the error shrinks with h
        assert abs(vals[64][k] - vals[100][k]) <= abs(vals[32][k] - vals[100][k]) + 1e-12
    m = {n: float(cloth.vertex_mass(n, n, 1 / (n - 1), 1 / (n - 1), 0.1).sum()) for n in (5, 64)}
    assert m[5] == pytest.approx(0.1) and m[64] == pytest.approx(0.1)


def test_gravity_and_inertia_agree_with_draping_physics():
    physics = pytest.importorskip("draping.physics")
    sheet = Sheet(6, 5)
    x = cloth.rest_positions(sheet, dtype=torch.float64)
    faces = cloth.grid_faces(6, 5)
    rest = physics.rest_state(x.reshape(-1, 3).numpy(), faces.numpy(),
                              physics.Material(density=100.0, thickness=1e-3))
    d = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    a = (d / (1 / 60) ** 2).expand(1, 6, 5, 3)
    mat = {**Material(damping=0.0).tensors(1, torch.float64)}
    e = cloth.energies(a, x[None], torch.zeros_like(x)[None], sheet.hx, sheet.hy, mat, 1 / 60)
    xf = (x + d).reshape(-1, 3)
    ine = physics.inertia_energy(xf, x.reshape(-1, 3), torch.zeros_like(xf), rest, 1 / 60)
    assert float(e["inertia"][0]) == pytest.approx(float(ine), rel=1e-9)
    # gravity of a uniform translation: the same total mass
    g0 = physics.gravity_energy(x.reshape(-1, 3), rest)
    g1 = physics.gravity_energy(xf, rest)
    e0 = cloth.energies(torch.zeros_like(a), x[None], torch.zeros_like(x)[None], sheet.hx,
                        sheet.hy, mat, 1 / 60)
    assert float(e["gravity"][0] - e0["gravity"][0]) == pytest.approx(float(g1 - g0), rel=1e-9)


def test_gradcheck_cloth_loss():
    torch.manual_seed(0)
    sheet = Sheet(5, 4)
    x = cloth.rest_positions(sheet, dtype=torch.float64)[None] + 0.01 * torch.randn(
        1, 5, 4, 3, dtype=torch.float64)
    v = 0.1 * torch.randn_like(x)
    mat = Material(200, 5, 2).tensors(1, torch.float64)
    a = torch.randn_like(x, requires_grad=True)

    def f(a):
        return cloth.cloth_loss(a, x, v, sheet.hx, sheet.hy, mat, 1 / 60)

    assert torch.autograd.gradcheck(f, (a,))


def test_free_fall_accelerates_at_g():
    sheet = Sheet(8, 6)
    x = cloth.rest_positions(sheet, "horizontal", torch.float64)[None]
    v = torch.zeros_like(x)
    none = torch.zeros(0, 2, dtype=torch.int64)
    mat = Material(damping=0.0).tensors(1, torch.float64)
    dt = handles.DT
    for _ in range(10):
        p = solvers.make_problem(x, v, none, torch.zeros(1, 0, 3, dtype=torch.float64),
                                 sheet.hx, sheet.hy, mat, dt)
        a = solvers.solve_reference(p, tol=1e-7, max_iter=200)
        assert torch.allclose(a[..., 2], torch.full_like(a[..., 2], -cloth.GRAVITY), atol=1e-6)
        assert torch.allclose(a[..., :2], torch.zeros_like(a[..., :2]), atol=1e-6)
        x, v = cloth.advance(a, x, v, dt)
    assert float(v[..., 2].mean()) == pytest.approx(-cloth.GRAVITY * 10 * dt, rel=1e-6)
    # backward Euler: z_10 = -g dt^2 (1 + 2 + ... + 10)
    assert float(x[..., 2].mean()) == pytest.approx(-cloth.GRAVITY * dt * dt * 55, rel=1e-6)


@pytest.mark.parametrize("layout,motion", [("corners", "xy"), ("diagonal", "rot-a"),
                                           ("single", "z"), ("corner-centre", "rot-b-rev")])
def test_handles_follow_their_trajectories_exactly(layout, motion):
    sheet = Sheet(9, 7)
    ro = solvers.rollout(sheet, Material(), layout, motion, 12,
                         lambda p, a0: solvers.solve_pgd(p, 3), speed=2.0)
    idx = cloth.handle_indices(layout, 9, 7)
    rest = cloth.rest_positions(sheet, dtype=torch.float64)[idx[:, 0], idx[:, 1]]
    for k in range(13):
        want = handles.handle_targets(rest, motion, k * handles.DT, 2.0)
        got = ro.positions[k][idx[:, 0], idx[:, 1]].double()
        assert torch.allclose(got, want, atol=1e-5), k
    # the rotations keep the handles' distances, the translations their offsets
    d0 = (rest[0] - rest[-1]).norm()
    assert float((ro.positions[-1][idx[0, 0], idx[0, 1]] - ro.positions[-1][
        idx[-1, 0], idx[-1, 1]]).double().norm()) == pytest.approx(float(d0), abs=1e-5)


def test_handle_trajectories_speed_and_rotation():
    rest = torch.tensor([[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0]], dtype=torch.float64)
    end = handles.handle_targets(rest, "xy", 10.0)
    assert torch.allclose(end - rest, torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64)
                          .expand(2, 3) * handles.AMPLITUDE / math.sqrt(2))
    # speed 2 reaches at t the point speed 1 reaches at 2 t
    assert torch.allclose(handles.handle_targets(rest, "x", 0.3, speed=2.0),
                          handles.handle_targets(rest, "x", 0.6))
    q = handles.handle_targets(rest, "rot-a", 10.0)        # quarter turn about z
    assert torch.allclose(q, torch.tensor([[0.0, -0.5, 0.0], [0.0, 0.5, 0.0]],
                                          dtype=torch.float64), atol=1e-12)
    qr = handles.handle_targets(rest, "rot-a-rev", 10.0)
    assert torch.allclose(qr, -q, atol=1e-12)


def test_classical_optimisers_lower_the_loss_and_reference_converges():
    sheet = Sheet(12, 12)
    ro = solvers.rollout(sheet, Material(), "corners", "xy", 6,
                         lambda p, a0: solvers.solve_reference(p, a0), warm_start=True)
    idx = cloth.handle_indices("corners", 12, 12)
    x = ro.positions[-2][None]
    v = (ro.positions[-2] - ro.positions[-3])[None] / handles.DT
    p = solvers.make_problem(x, v, idx, ro.positions[-1][None][:, idx[:, 0], idx[:, 1]],
                             sheet.hx, sheet.hy, Material().tensors(1))
    l0 = float(p.loss(torch.zeros_like(x))[0])
    info = {}
    a_ref = solvers.solve_reference(p, info=info)
    assert float(info["residual"][0]) <= solvers.REFERENCE_TOL
    l_ref = float(p.loss(a_ref)[0])
    for name, kw in (("gd", {"lr": 2e-3}), ("adam", {"lr": 0.1}), ("lbfgs", {})):
        a = solvers.CLASSICAL[name](p, 30, **kw)
        l_n = float(p.loss(a)[0])
        assert l_ref - 1e-6 <= l_n < l0, name
    l_pgd = float(p.loss(solvers.solve_pgd(p, 30))[0])
    assert l_ref - 1e-6 <= l_pgd < l0


def test_bad_input_errors():
    sheet = Sheet(6, 6)
    x = cloth.rest_positions(sheet)[None]
    mat = Material().tensors(1)
    with pytest.raises(ValueError, match="out of range"):
        cloth.handle_indices(torch.tensor([[0, 6]]), 6, 6)
    with pytest.raises(ValueError, match="layout"):
        cloth.handle_indices("three-corners", 6, 6)
    with pytest.raises(ValueError, match="layout"):
        cloth.layout_points([(0.0, 1.5)])
    bad = x.clone()
    bad[0, 2, 2, 1] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        solvers.make_problem(bad, torch.zeros_like(x), "corners", x[:, [0, 0], [0, 5]],
                             sheet.hx, sheet.hy, mat)
    with pytest.raises(ValueError, match=r"\(B, H, W, 3\)"):
        solvers.make_problem(x.reshape(1, 36, 3), torch.zeros(1, 36, 3), "corners",
                             x[:, [0, 0], [0, 5]], sheet.hx, sheet.hy, mat)
    with pytest.raises(TypeError):
        cloth.check_grid(x.numpy())
    with pytest.raises(ValueError, match="motion"):
        handles.handle_targets(x[0, 0, :2], "spin", 0.1)
    with pytest.raises(ValueError, match="speed"):
        handles.handle_targets(x[0, 0, :2], "x", 0.1, speed=0.0)
    with pytest.raises(ValueError, match="Material.stretch"):
        Material(stretch=-1.0)
    with pytest.raises(ValueError, match="Sheet.height"):
        Sheet(2, 5)


def test_repulsion_pushes_close_non_adjacent_vertices_apart():
    sheet = Sheet(6, 6)
    x = cloth.rest_positions(sheet, dtype=torch.float64)
    x[5, :, 1] = 0.01                  # fold the last row onto the first... close in y only
    x[5, :, 2] = x[0, :, 2] - 0.001
    pairs = cloth.repulsion_pairs(x, 0.05)
    assert pairs.shape[0] > 0
    r, c = pairs // 6, pairs % 6
    assert bool(((r[:, 0] - r[:, 1]).abs().maximum((c[:, 0] - c[:, 1]).abs()) > 1).all())
    xr = x.clone().requires_grad_(True)
    e = cloth.repulsion_energy(xr, pairs, 0.05, 1.0)
    assert float(e.detach()) > 0
    (g,) = torch.autograd.grad(e, xr)
    # moving the folded row away (+y) lowers the energy
    assert float(g[5, :, 1].sum()) < 0
    far = cloth.rest_positions(sheet, dtype=torch.float64)
    assert cloth.repulsion_pairs(far, 0.5 * sheet.hx).shape[0] == 0


def _brute_pairs(x, delta):
    h, w = x.shape[:2]
    p = x.reshape(-1, 3).to(torch.float64)
    i, j = torch.triu_indices(h * w, h * w, offset=1)
    d = (p[i] - p[j]).norm(dim=-1)
    far = ((i // w - j // w).abs().maximum((i % w - j % w).abs())) > 1
    keep = (d < delta) & far
    return torch.stack([i[keep], j[keep]], 1)


@pytest.mark.parametrize("shape", [(7, 9), (12, 5), (1, 6)])
def test_repulsion_pairs_equal_all_pairs_definition(shape):
    g = torch.Generator().manual_seed(3)
    x = 0.05 * torch.rand(*shape, 3, generator=g, dtype=torch.float64)  # crumpled: many close pairs
    for delta in (0.005, 0.02, 0.1):
        got = cloth.repulsion_pairs(x, delta)
        want = _brute_pairs(x, delta)
        assert got.dtype == torch.int64 and got.shape[1] == 2
        assert torch.equal(got, want), (shape, delta)
    assert cloth.repulsion_pairs(x.float(), 0.02).shape == _brute_pairs(x.float(), 0.02).shape


def test_repulsion_pairs_rejects_bad_input():
    x = torch.zeros(4, 4, 3)
    with pytest.raises(ValueError, match="delta"):
        cloth.repulsion_pairs(x, 0.0)
    with pytest.raises(ValueError, match="delta"):
        cloth.repulsion_pairs(x, float("nan"))
    with pytest.raises(ValueError, match="x: expected an"):
        cloth.repulsion_pairs(torch.zeros(16, 3), 0.1)
    x[1, 2, 0] = float("nan")
    with pytest.raises(ValueError, match="finite"):
        cloth.repulsion_pairs(x, 0.1)


def _step_problem(n=10, dtype=torch.float64):
    sheet = Sheet(n, n)
    ro = solvers.rollout(sheet, Material(), "corner-centre", "xyz", 5,
                         lambda p, a0: solvers.solve_pgd(p, 10), dtype=dtype)
    idx = cloth.handle_indices("corner-centre", n, n)
    x = ro.positions[-2][None]
    v = (ro.positions[-2] - ro.positions[-3])[None] / handles.DT
    return solvers.make_problem(x, v, idx, ro.positions[-1][None][:, idx[:, 0], idx[:, 1]],
                                sheet.hx, sheet.hy, Material().tensors(1, dtype))


def test_subspace_step_minimises_the_quadratic_model_over_the_span():
    p = _step_problem()
    g0 = torch.Generator().manual_seed(0)
    a = 0.1 * torch.randn(p.x_prev.shape, generator=g0, dtype=torch.float64) * p.free
    _, g, hvp = p.grad_hvp(a)
    d1 = -g / p.mass[..., None]
    d2 = torch.randn(p.x_prev.shape, generator=g0, dtype=torch.float64) * p.free

    def model(s):                     # quadratic model of L(a + s) - L(a)
        return float((g * s).sum() + 0.5 * (s * hvp(s)).sum())

    # one direction: the exact line step
    s1 = p.subspace_step(g, [d1], hvp)
    assert torch.allclose(s1, p.exact_step(g, d1, hvp) * d1, rtol=1e-9, atol=1e-15)
    # two directions: the model's gradient is orthogonal to both (independent check) ...
    s = p.subspace_step(g, [d1, d2], hvp)
    r = g + hvp(s)
    for d in (d1, d2):
        assert abs(float((r * d).sum())) < 1e-8 * float(g.norm() * d.norm())
    # ... and no combination on a grid of coefficients does better
    c1 = float((s * d1).sum() / (d1 * d1).sum())
    best = model(s)
    for t1 in (0.5, 0.9, 1.1, 2.0):
        for t2 in (-1.0, 0.0, 1.0):
            assert best <= model(t1 * c1 * d1 + t2 * 1e-3 * d2) + 1e-12
    # a zero or repeated direction changes nothing
    z = torch.zeros_like(d1)
    assert torch.allclose(p.subspace_step(g, [d1, z, d2, d1], hvp), s, rtol=1e-6, atol=1e-12)


def test_pcg_lowers_the_loss_at_least_as_well_as_preconditioned_descent():
    p = _step_problem(16, torch.float32)
    l0 = float(p.loss(torch.zeros_like(p.x_prev))[0])
    l_star = float(p.loss(solvers.solve_reference(p))[0])
    l_pgd = float(p.loss(solvers.solve_pgd(p, 10))[0])
    l_pcg = float(p.loss(solvers.solve_pcg(p, 10))[0])
    assert l_star - 1e-6 <= l_pcg < l0
    assert l_pcg <= l_pgd + 1e-6 * abs(l_pgd)
