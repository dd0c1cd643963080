"""The physics reference solver: fused kernels against torch, descent, free fall, contact."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from draping import _minimize
from draping import physics as P
from draping import reference as R
from draping.physics import fused


def grid_sheet(n: int, size: float = 1.0, z: float = 0.0):
    u, v = np.meshgrid(
        np.linspace(-size / 2, size / 2, n), np.linspace(-size / 2, size / 2, n), indexing="ij"
    )
    verts = np.stack([u.ravel(), v.ravel(), np.full(n * n, z)], 1)
    a = np.array([i * n + j for i in range(n - 1) for j in range(n - 1)])
    faces = np.concatenate([np.stack([a, a + n, a + 1], 1), np.stack([a + 1, a + n, a + n + 1], 1)])
    return verts, faces


def noisy(v: np.ndarray, scale: float, seed: int) -> np.ndarray:
    return v + scale * np.random.default_rng(seed).standard_normal(v.shape)


# ---------------------------------------------------------------------- fused kernels


def test_fused_energies_and_gradients_match_torch():
    v, f = grid_sheet(6, 0.5)
    r = P.rest_state(v, f)
    m = r.material
    x = noisy(v, 0.03, 0)
    xt = torch.tensor(x, requires_grad=True)
    for torch_fn, fused_fn in [
        (
            lambda y: P.stvk_energy(y, r),
            lambda y: fused.membrane(
                y,
                r.faces.numpy(),
                r.dm_inv.numpy(),
                r.area.numpy(),
                m.thickness,
                m.lame_mu,
                m.lame_lambda,
            ),
        ),
        (
            lambda y: P.bending_energy(y, r),
            lambda y: fused.bending(
                y,
                fused.hinge_quads(f, r.hinges.edges, r.hinges.faces),
                r.hinge_weight.numpy(),
                m.bending_stiffness,
            ),
        ),
    ]:
        e = torch_fn(xt)
        (g,) = torch.autograd.grad(e, xt)
        ef, gf, _ = fused_fn(x)
        assert ef == pytest.approx(float(e.detach()), rel=1e-12)
        np.testing.assert_allclose(gf, g.numpy(), rtol=0, atol=1e-12 * np.abs(gf).max())


def test_fused_membrane_hessian_exact_when_stretched_and_psd_when_compressed():
    v, f = grid_sheet(4, 0.3)
    r = P.rest_state(v, f)
    m = r.material
    args = (
        r.faces.numpy(),
        r.dm_inv.numpy(),
        r.area.numpy(),
        m.thickness,
        m.lame_mu,
        m.lame_lambda,
    )
    n = v.shape[0]

    def dense(h):
        out = np.zeros((3 * n, 3 * n))
        for t, tri in enumerate(f):
            idx = (3 * tri[:, None] + np.arange(3)).ravel()
            out[np.ix_(idx, idx)] += h[t]
        return out

    x = v * np.array([1.2, 1.1, 1.0])  # stretched: S positive definite, the projection is exact
    _, _, h = fused.membrane(x, *args, want_hess=True)
    want = torch.autograd.functional.hessian(lambda y: P.stvk_energy(y, r), torch.tensor(x))
    np.testing.assert_allclose(
        dense(h), want.reshape(3 * n, 3 * n).numpy(), rtol=0, atol=1e-10 * np.abs(h).max()
    )
    xc = noisy(v * 0.8, 0.01, 1)  # compressed: the exact Hessian is indefinite, ours is not
    _, _, hc = fused.membrane(xc, *args, want_hess=True)
    exact = torch.autograd.functional.hessian(lambda y: P.stvk_energy(y, r), torch.tensor(xc))
    scale = np.abs(hc).max()
    assert np.linalg.eigvalsh(exact.reshape(3 * n, 3 * n).numpy()).min() < -1e-6 * scale
    assert np.linalg.eigvalsh(hc).min() > -1e-10 * scale


def test_fused_bending_gauss_newton_hessian_at_a_flat_hinge():
    """At theta = 0 the Gauss-Newton Hessian 2 k w grad(theta) grad(theta)^T is exact."""
    v = np.array([[0.0, 0, 0], [0, 1, 0], [1, 0.5, 0], [-1, 0.5, 0]])
    f = np.array([[0, 2, 1], [0, 1, 3]])
    r = P.rest_state(v, f)
    q = fused.hinge_quads(f, r.hinges.edges, r.hinges.faces)
    _, _, h = fused.bending(v, q, r.hinge_weight.numpy(), 1.0, want_hess=True)
    want = torch.autograd.functional.hessian(
        lambda y: P.bending_energy(y, r, stiffness=1.0), torch.tensor(v)
    )
    perm = (3 * q[0][:, None] + np.arange(3)).ravel()
    np.testing.assert_allclose(h[0], want.reshape(12, 12).numpy()[np.ix_(perm, perm)], atol=1e-12)


def test_objective_matches_frame_energy():
    v, f = grid_sheet(5, 0.4, z=0.31)
    r = P.rest_state(v, f)
    st = R.SolverSettings()
    query = R.sphere_query([0, 0, 0], 0.3)
    x_prev = torch.tensor(v)
    v_prev = torch.tensor(noisy(np.zeros_like(v), 0.1, 2))
    x = torch.tensor(noisy(v, 0.01, 3) - np.array([0.0, 0.0, 0.015]))
    motion = torch.tensor(noisy(np.zeros_like(v), 0.002, 4))
    pb = R._problem(r, st, query, None, x_prev, v_prev, 1 / 30, motion)
    ob = R._objective(pb, x.numpy())
    # vertices pressed into the ball have friction (sliding: slips of mm > friction_eps)
    assert ob.friction_weight is not None and (ob.friction_weight > 0).sum() >= 1
    e, g, h = _minimize.evaluate(ob, x.numpy(), want_hess=True)
    xt = x.clone().requires_grad_()
    et = R.frame_energy(
        xt,
        r,
        st,
        x_prev=x_prev,
        v_prev=v_prev,
        dt=1 / 30,
        anchor=torch.from_numpy(ob.anchor),
        normal=torch.from_numpy(ob.normal),
        friction_reference=x_prev + motion,
        friction_weight=torch.from_numpy(ob.friction_weight),
    )
    (gt,) = torch.autograd.grad(et, xt)
    assert e == pytest.approx(float(et.detach()), rel=1e-12)
    np.testing.assert_allclose(g, gt.numpy(), atol=1e-10 * np.abs(g).max())
    assert h.shape == (75, 75)
    # the projected Hessian is definite (mass term); the exact one equals autograd's
    assert np.linalg.eigvalsh(h.toarray()).min() > 0  # default: projected, definite
    ob_p, ob = ob, R._objective(pb._replace(settings=R.SolverSettings(hessian="exact")),
                                x.numpy())
    flat = x.reshape(-1).clone()
    h_t = torch.autograd.functional.hessian(
        lambda y: P.stvk_energy(y.reshape(-1, 3), r), flat).numpy()
    st_ = ob.st
    m = r.material
    _, _, h_m = fused.membrane(x.numpy(), st_.faces, st_.dm_inv, st_.area, m.thickness,
                               m.lame_mu, m.lame_lambda, True, project=False)
    dense = np.zeros((75, 75))
    for t_, tri in enumerate(st_.faces):
        idx = (3 * tri[:, None] + np.arange(3)).ravel()
        dense[np.ix_(idx, idx)] += h_m[t_]
    np.testing.assert_allclose(dense, h_t, atol=1e-9 * np.abs(h_t).max())
    assert ob_p.project_membrane and not ob.project_membrane


# ---------------------------------------------------------------------- solver behaviour


@pytest.mark.parametrize("method", ["newton", "pqn", "lbfgs"])
def test_energy_decreases_every_step(method):
    v, f = grid_sheet(9, 0.5, z=0.305)
    r = P.rest_state(v, f)
    st = R.SolverSettings(method=method, tol=1e-3, max_iter=300, requery_every=10_000)
    out = R.drape_static(r, v, R.sphere_query([0, 0, 0], 0.3), st, pinned=[40])
    tr = np.array(out.trace)
    assert len(tr) >= 2
    assert np.all(np.diff(tr) <= 1e-12 * np.abs(tr).max())
    assert out.converged or method != "newton"


def test_energy_decreases_every_step_of_a_dynamic_frame_on_a_body():
    v, f = grid_sheet(9, 0.5, z=0.305)
    r = P.rest_state(v, f)
    # one set of tangent planes and lagged friction forces (a re-query changes the energy)
    st = R.SolverSettings(tol=1e-4, max_iter=300, max_requery=0)
    v0 = np.tile([0.0, 0.0, -1.0], (81, 1))
    out = R.drape_step(r, v, v0, 1 / 30, R.sphere_query([0, 0, 0], 0.3), st)
    tr = np.array(out.trace)
    assert len(tr) >= 2 and out.converged
    assert np.all(np.diff(tr) <= 1e-12 * np.abs(tr).max())


@pytest.mark.parametrize("hessian", ["projected", "exact"])
def test_capped_inner_solves_reach_the_same_drape(hessian):
    v, f = grid_sheet(9, 0.5, z=0.305)
    r = P.rest_state(v, f)
    v0 = np.tile([0.0, 0.0, -1.0], (81, 1))
    q = R.sphere_query([0, 0, 0], 0.3)
    full = R.drape_step(r, v, v0, 1 / 30, q, R.SolverSettings(hessian=hessian))
    capped = R.drape_step(r, v, v0, 1 / 30, q, R.SolverSettings(hessian=hessian, cg_max_iter=3))
    assert full.converged and capped.converged  # the cap changes the path, not the rule
    for res in (full, capped):
        d, _ = q(res.x)
        assert float(d.min()) > -R.SolverSettings().collision_eps
    # same drape up to the 1 % scale of the stopping rule (buckling can pick another wrinkle)
    assert capped.energy == pytest.approx(full.energy, rel=1e-2)


def test_forcing_term_is_loose_far_from_and_tightens_near_convergence():
    ft = _minimize.forcing_term
    assert ft(1.0, 1.0) == 0.5  # residual force = the weight: the cap
    assert ft(0.03, 1.0) == 0.5  # 3 sqrt(0.03) = 0.52 > cap
    assert ft(1e-2, 1.0) == pytest.approx(0.3)  # 3 sqrt(1e-2)
    assert ft(1e-4, 2.0) == pytest.approx(3 * np.sqrt(5e-5))
    # scale-free: only the ratio |g| / |M g| counts
    assert ft(2e-3, 0.5) == pytest.approx(ft(4e-5, 1e-2))
    assert ft(1e-2, 1.0, cap=0.2) == 0.2 and ft(1e-2, 1.0, scale=1.0) == pytest.approx(0.1)


def test_tight_dynamic_solve_meets_the_rule_by_autograd():
    """The stopping rule checked independently: the torch energy's autograd gradient."""
    v, f = grid_sheet(9, 0.5, z=0.305)
    r = P.rest_state(v, f)
    st = R.SolverSettings(tol=1e-6, max_iter=500, max_requery=0, friction=0.0)
    v0 = np.tile([0.0, 0.0, -1.0], (81, 1))
    q = R.sphere_query([0, 0, 0], 0.3)
    x0 = R.project_outside(R.free_fall(v, v0, 1 / 30), q, st.collision_eps)
    out = R.drape_step(r, v, v0, 1 / 30, q, st, x0=x0)
    assert out.converged
    # the planes of the single query (max_requery 0) are those at the start
    anchor, normal = R._planes(x0, q)
    x = out.x.clone().requires_grad_(True)
    e = R.frame_energy(x, r, st, x_prev=torch.as_tensor(v), v_prev=torch.as_tensor(v0),
                       dt=1 / 30, anchor=anchor, normal=normal)
    (g,) = torch.autograd.grad(e, x)
    weight = float(torch.linalg.norm(r.mass)) * float(np.linalg.norm(st.gravity))
    assert float(torch.linalg.norm(g)) <= 1.01 * st.tol * weight
    assert float(torch.linalg.norm(g)) / weight == pytest.approx(out.residual, rel=1e-3, abs=1e-9)


def test_newton_gives_up_after_steps_that_do_not_lower_the_energy(monkeypatch):
    v, f = grid_sheet(5, 0.2, z=0.0)
    r = P.rest_state(v, f)
    pb = R._problem(r, R.SolverSettings(), None, None, None, None, None)
    x = noisy(v, 1e-3, 0)
    ob = R._objective(pb, x)
    e0, _, _ = _minimize.evaluate(ob, x)
    # a line search that "accepts" a step without moving (what rounding does at a singular
    # bending gradient): the minimiser must stop instead of running to max_iter
    monkeypatch.setattr(_minimize, "_line_search", lambda ob, x, e, g, d: (1e-3, x.copy(), e))
    pre = _minimize.laplacian_factor(ob, 0.05)
    out = _minimize.newton(ob, x, 1e-12, 1000, pre, pb.weight)
    assert out.iterations == _minimize.STALL_STEPS
    assert out.energy == pytest.approx(e0)


def test_x0_is_used_and_a_solve_started_inside_the_body_ends_outside():
    """A small sheet on top of a 0.1 m ball thrown down at 4 m/s: its free fall over one frame
    (0.14 m) lands it inside, below the centre, so a solve from there pushes it out of the
    bottom; started from its previous place (x0) it stays on top. Started from inside the upper
    half, it ends on top, outside."""
    v, f = grid_sheet(11, 0.1, z=0.102)
    r = P.rest_state(v, f)
    q = R.sphere_query([0, 0, 0], 0.1)
    v0 = np.tile([0.0, 0.0, -4.0], (121, 1))
    dt = 1 / 30
    st = R.SolverSettings(tol=1e-3)
    ff = R.free_fall(v, v0, dt)
    assert float(q(ff)[0].max()) < 0  # every vertex of the default start is inside
    below = R.drape_step(r, v, v0, dt, q, st)
    above = R.drape_step(r, v, v0, dt, q, st, x0=v)
    inside = R.drape_step(r, v, v0, dt, q, st, x0=v - [0.0, 0.0, 0.05])
    assert float(q(torch.from_numpy(v - [0.0, 0.0, 0.05]))[0].max()) < 0
    for res in (below, above, inside):
        assert res.converged
        assert float(q(res.x)[0].min()) > -1e-3  # outside (within the penalty's give)
    assert float(below.x[:, 2].max()) < -0.05
    assert float(above.x[:, 2].min()) > 0.05 and float(inside.x[:, 2].min()) > 0.05
    np.testing.assert_allclose(above.v.numpy(), (above.x.numpy() - v) / dt)
    with pytest.raises(ValueError, match="x0"):
        R.drape_step(r, v, v0, dt, q, st, x0=v[:-1])


def test_project_outside():
    q = R.sphere_query([0, 0, 0], 1.0)
    x = torch.tensor([[0.0, 0.0, 0.5], [0.0, 2.0, 0.0], [0.0, 0.0, 1.001], [-0.9, 0.0, 0.0]],
                     dtype=torch.float64)
    y = R.project_outside(x, q, 0.002)
    np.testing.assert_allclose(q(y)[0].numpy(), [0.002, 1.0, 0.002, 0.002], atol=1e-12)
    np.testing.assert_allclose(y[:, :2].numpy(), [[0, 0], [0, 2], [0, 0], [-1.002, 0]],
                               atol=1e-12)
    np.testing.assert_array_equal(R.project_outside(x, q).numpy()[1], x.numpy()[1])
    with pytest.raises(ValueError, match="clearance"):
        R.project_outside(x, q, -1.0)
    with pytest.raises(ValueError, match="x"):
        R.project_outside(x[:, :2], q)


def test_friction_energy_hand_values_and_gradcheck():
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64).expand(4, 3)
    ref = torch.zeros(4, 3, dtype=torch.float64)
    w = torch.tensor([2.0, 2.0, 0.5, 0.0], dtype=torch.float64)
    eps = 0.01
    # slips: 0.03 (sliding), 0.005 (static), 0.02 along x plus 0.7 along the normal (ignored)
    x = torch.tensor([[0.03, 0.0, 0.1], [0.0, 0.005, 0.0], [0.02, 0.0, 0.7], [1.0, 1.0, 1.0]],
                     dtype=torch.float64, requires_grad=True)
    e = P.friction_energy(x, ref, n, w, eps, reduction="none")
    s = 0.005
    static = -(s**3) / (3 * eps**2) + s**2 / eps + eps / 3
    np.testing.assert_allclose(e.detach().numpy(), [2 * 0.03, 2 * static, 0.5 * 0.02, 0.0])
    (g,) = torch.autograd.grad(e.sum(), x)
    # sliding: a force of magnitude mu lambda against the slip, none along the normal
    np.testing.assert_allclose(g[0].numpy(), [2.0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(g[2].numpy(), [0.5, 0, 0], atol=1e-12)
    assert 0 < float(g[1, 1]) < 2.0  # static: less than the sliding force
    gen = torch.Generator().manual_seed(6)
    y = (0.01 * torch.randn(4, 3, generator=gen, dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda z: P.friction_energy(z, ref, n, w, eps), (y,))
    with pytest.raises(ValueError, match="eps"):
        P.friction_energy(x, ref, n, w, 0.0)


def test_friction_carries_a_sheet_resting_on_a_moving_floor():
    """A sheet lying on a floor that jerks sideways by 1 cm in one frame: without friction it
    stays put; with a high friction coefficient it is carried along (within the static slip);
    with mu = 0.5 it slides, accelerated at mu g (Coulomb): moved by mu g dt^2."""
    v, f = grid_sheet(6, 0.3, z=0.002)
    r = P.rest_state(v, f)
    floor = R.plane_query([0, 0, 0], [0, 0, 1])
    motion = np.tile([0.01, 0.0, 0.0], (36, 1))  # 1 cm per frame along x
    zero = np.zeros_like(v)
    out = {}
    for mu in (0.0, 0.5, 2.0):
        st = R.SolverSettings(tol=1e-6, friction=mu)
        x, vel = torch.tensor(v), torch.zeros(36, 3, dtype=torch.float64)
        for _ in range(3):  # settle onto the floor first
            res = R.drape_step(r, x, vel, 1 / 30, floor, st, body_motion=zero)
            x, vel = res.x, res.v
        x_before = x.clone()
        res = R.drape_step(r, x, vel, 1 / 30, floor, st, body_motion=motion)
        out[mu] = float((res.x - x_before)[:, 0].mean())
    assert abs(out[0.0]) < 1e-6
    assert out[2.0] == pytest.approx(0.01, abs=2e-4)
    assert out[0.5] == pytest.approx(0.5 * 9.81 / 30**2, rel=0.05)


def test_free_fall_accelerates_at_g():
    v, f = grid_sheet(6, 0.4)
    r = P.rest_state(v, f)
    dt = 1 / 30
    st = R.SolverSettings(tol=1e-8)
    res = R.drape_sequence(r, v, [None] * 5, dt, st)
    g = np.array(P.GRAVITY)
    for k, fr in enumerate(res, start=1):
        np.testing.assert_allclose(fr.v.numpy(), np.tile(k * dt * g, (36, 1)), atol=1e-6)
    # positions of backward Euler under constant g: x_k = x_0 + dt^2 g k (k + 1) / 2
    np.testing.assert_allclose(res[-1].x.numpy(), v + dt * dt * g * 15, atol=1e-7)
    assert float(P.stvk_energy(res[-1].x, r)) < 1e-12


@pytest.mark.parametrize("method", ["newton", "pqn"])
def test_no_penetration_left_on_a_sheet_pressed_onto_a_sphere(method):
    v, f = grid_sheet(11, 0.4, z=0.3)
    r = P.rest_state(v, f)
    query = R.sphere_query([0, 0, 0], 0.3)
    st = R.SolverSettings(method=method, tol=1e-3)
    v0 = np.tile([0.0, 0.0, -1.5], (121, 1))  # thrown down at 1.5 m/s
    res = R.drape_sequence(r, v, [query] * 3, 1 / 30, st, v0=v0)
    for fr in res:
        d, _ = query(fr.x)
        assert float(d.min()) >= 0.0
        assert fr.converged


def test_sheet_over_sphere_reaches_a_plausible_rest_shape():
    """A tablecloth pinned at its centre on top of a ball (frictionless: unpinned, it slides)."""
    v, f = grid_sheet(13, 0.8, z=0.302)
    r = P.rest_state(v, f)
    query = R.sphere_query([0, 0, 0], 0.3)
    centre = 6 * 13 + 6
    out = R.drape_static(r, v, query, R.SolverSettings(tol=1e-3, max_iter=500), pinned=[centre])
    assert out.converged
    x = out.x.numpy()
    d, _ = query(out.x)
    ring = [centre - 1, centre + 1, centre - 13, centre + 13]
    assert np.all((d[ring].numpy() > -1e-4) & (d[ring].numpy() < 3e-3))  # lying on the ball
    assert float(d.min()) > -5e-4
    corners = [0, 12, 156, 168]
    assert np.all(x[corners, 2] < 0.2)  # the corners hang down the sides
    lengths = np.linalg.norm(x[r.edges[:, 1]] - x[r.edges[:, 0]], axis=1)
    strain = np.abs(lengths / r.edge_length.numpy() - 1)
    assert strain.mean() < 0.03


def test_pinned_vertices_stay_put():
    v, f = grid_sheet(7, 0.3)
    r = P.rest_state(v, f)
    pinned = np.array([0, 6])
    res = R.drape_sequence(r, v, [None] * 3, 1 / 30, R.SolverSettings(tol=1e-4), pinned=pinned)
    np.testing.assert_array_equal(res[-1].x.numpy()[pinned], v[pinned])
    assert float(res[-1].x[24, 2]) < -0.01  # the middle falls
    mask = np.zeros(49, dtype=bool)
    mask[pinned] = True
    res2 = R.drape_sequence(r, v, [None] * 3, 1 / 30, R.SolverSettings(tol=1e-4), pinned=mask)
    np.testing.assert_allclose(res2[-1].x.numpy(), res[-1].x.numpy(), atol=1e-9)


# ---------------------------------------------------------------------- validation


def test_settings_and_inputs_are_validated():
    with pytest.raises(ValueError, match="method"):
        R.SolverSettings(method="sgd")
    with pytest.raises(ValueError, match="tol"):
        R.SolverSettings(tol=0)
    with pytest.raises(ValueError, match="cg_max_iter"):
        R.SolverSettings(cg_max_iter=0)
    with pytest.raises(ValueError, match="hessian"):
        R.SolverSettings(hessian="diagonal")
    with pytest.raises(ValueError, match="max_iter"):
        R.SolverSettings(max_iter=0)
    with pytest.raises(ValueError, match="collision_eps"):
        R.SolverSettings(collision_eps=-1)
    with pytest.raises(ValueError, match="max_requery"):
        R.SolverSettings(max_requery=-1)
    with pytest.raises(TypeError, match="history"):
        R.SolverSettings(history=2.5)
    with pytest.raises(ValueError, match="gravity"):
        R.SolverSettings(gravity=(0.0, -9.81))
    v, f = grid_sheet(4, 0.3)
    r = P.rest_state(v, f)
    with pytest.raises(ValueError, match="x0"):
        R.drape_static(r, v[:5])
    with pytest.raises(ValueError, match="x0"):
        R.drape_static(r, np.full_like(v, np.nan))
    with pytest.raises(TypeError, match="rest"):
        R.drape_static("sheet", v)
    with pytest.raises(TypeError, match="settings"):
        R.drape_static(r, v, settings={"tol": 1})
    with pytest.raises(ValueError, match="dt"):
        R.drape_step(r, v, np.zeros_like(v), 0.0)
    with pytest.raises(ValueError, match="pinned"):
        R.drape_static(r, v, pinned=[99])
    with pytest.raises(ValueError, match="pinned"):
        R.drape_static(r, v, pinned=np.zeros(3, dtype=bool))
    with pytest.raises(ValueError, match="query"):
        R.drape_static(r, v, query=lambda p: (torch.zeros(3), torch.zeros(3, 3)))
    with pytest.raises(ValueError, match="query"):
        R.drape_static(r, v, query=lambda p: (torch.full((16,), np.nan), torch.zeros(16, 3)))
    with pytest.raises(ValueError, match="radius"):
        R.sphere_query([0, 0, 0], -1.0)
    with pytest.raises(ValueError, match="normal"):
        R.plane_query([0, 0, 0], [0, 0, 0])
    with pytest.raises(ValueError, match="pinned_positions"):
        R.drape_sequence(r, v, [None] * 2, 0.1, pinned=[0], pinned_positions=[v])


def test_analytic_queries():
    q = R.sphere_query([1.0, 0, 0], 0.5)
    d, n = q(torch.tensor([[1.0, 0, 1.0], [1.0, 0.25, 0.0], [1.0, 0.0, 0.0]]))
    np.testing.assert_allclose(d.numpy(), [0.5, -0.25, -0.5])
    np.testing.assert_allclose(n.numpy(), [[0, 0, 1], [0, 1, 0], [0, 0, 1]])
    p = R.plane_query([0, 0, 1.0], [0, 0, 2.0])
    d, n = p(torch.tensor([[3.0, 1, 1.5], [0.0, 0, 0.0]]))
    np.testing.assert_allclose(d.numpy(), [0.5, -1.0])
    np.testing.assert_allclose(n.numpy(), [[0, 0, 1], [0, 0, 1]])


def test_mesh_query_answers_are_accepted():
    """A draping.collision-style answer (distance, closest, normal, face) drives the contact."""
    from typing import NamedTuple

    class Answer(NamedTuple):
        distance: torch.Tensor
        closest: torch.Tensor
        normal: torch.Tensor
        face: torch.Tensor

    sphere = R.sphere_query([0, 0, 0], 0.3)

    def query(p):
        d, n = sphere(p)
        far = d > 0.05  # as MeshQuery.query(max_distance=0.05)
        closest = p - d[:, None] * n
        return Answer(
            torch.where(far, torch.inf, d),
            torch.where(far[:, None], torch.nan, closest),
            n,
            torch.zeros(len(d), dtype=torch.int64),
        )

    v, f = grid_sheet(11, 0.4, z=0.3)
    r = P.rest_state(v, f)
    v0 = np.tile([0.0, 0.0, -1.5], (121, 1))
    a = R.drape_sequence(r, v, [query] * 2, 1 / 30, R.SolverSettings(tol=1e-4), v0=v0)
    b = R.drape_sequence(r, v, [sphere] * 2, 1 / 30, R.SolverSettings(tol=1e-4), v0=v0)
    np.testing.assert_allclose(a[-1].x.numpy(), b[-1].x.numpy(), atol=1e-5)
    with pytest.raises(ValueError, match="query"):
        R.drape_static(r, v, query=lambda p: (torch.full((121,), np.nan), torch.zeros(121, 3)))
