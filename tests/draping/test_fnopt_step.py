"""FNOpt's subspace step against the classical PCG step it is built on; training through it."""

import pytest
import torch
from fnopt_cases import quadratic_problem

from draping.fnopt import cloth, model, solvers
from draping.fnopt.cloth import Material, Sheet

torch.set_num_threads(1)


def _quadratic(seed=0, res=(12, 10)):
    return quadratic_problem(res, 400.0, 10.0, seed)


def _net(seed=0, gain=1.0):
    torch.manual_seed(seed)
    net = model.FNO(model.FNOConfig(width=8, modes=4, layers=2, projection=8)).double()
    with torch.no_grad():
        net.proj2.weight.mul_(gain)
    return net


def _zero_net():
    net = _net()
    with torch.no_grad():
        net.proj2.weight.zero_()
        net.proj2.bias.zero_()
    return net


def _cloth_problem(dtype=torch.float64):
    sheet = Sheet(12, 12)
    ro = solvers.rollout(sheet, Material(), "diagonal", "xyz", 6,
                         lambda p, a0: solvers.solve_pcg(p, 10), speed=2.0, dtype=dtype)
    idx = cloth.handle_indices("diagonal", 12, 12)
    x = ro.positions[-2][None]
    v = (ro.positions[-2] - ro.positions[-3])[None] / solvers.DT
    return solvers.make_problem(x, v, idx, ro.positions[-1][None][:, idx[:, 0], idx[:, 1]],
                                sheet.hx, sheet.hy, Material().tensors(1, dtype))


@pytest.mark.parametrize("problem", ["quadratic", "cloth"])
def test_a_zero_fno_output_reproduces_pcg(problem):
    p = _quadratic() if problem == "quadratic" else _cloth_problem()
    for n in (1, 4, 10):
        a_pcg = solvers.solve_pcg(p, n)
        a_fn = model.solve_fnopt(_zero_net(), p, n)
        assert torch.allclose(a_fn, a_pcg, rtol=1e-7, atol=1e-7 * float(a_pcg.abs().max()))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_random_fno_step_is_never_worse_than_the_pcg_step_on_a_quadratic(seed):
    p = _quadratic(seed)
    net = _net(seed, gain=300.0)                    # proposals as large as the residual
    g0 = torch.Generator().manual_seed(10 + seed)
    pre = solvers.laplace_preconditioner(p)
    for _ in range(3):
        a = torch.randn(p.x_prev.shape, generator=g0, dtype=torch.float64) * p.free
        da_prev = torch.randn(a.shape, generator=g0, dtype=torch.float64) * p.free
        z_prev = torch.randn(a.shape, generator=g0, dtype=torch.float64) * p.free
        val, g, hvp = p.grad_hvp(a)
        z = pre(g) * p.free
        with torch.no_grad():
            da, da_pcg, m, m_pcg = model.subspace_update(net, p, g, hvp, z, z_prev, da_prev)
        # the classical step is solve_pcg's: the model minimiser over (-z, previous update)
        assert torch.allclose(da_pcg, p.subspace_step(g, [-z * p.free, da_prev], hvp),
                              rtol=1e-8, atol=1e-12 * float(da_pcg.abs().max()))
        l_fn, l_pcg = float(p.loss(a + da)[0]), float(p.loss(a + da_pcg)[0])
        assert l_fn <= l_pcg + 1e-10 * abs(float(val[0]))
        assert l_pcg < float(val[0])
        # on a quadratic the model is the function: its predicted decreases are exact
        assert float(m[0]) == pytest.approx(l_fn - float(val[0]), rel=1e-6)
        assert float(m_pcg[0]) == pytest.approx(l_pcg - float(val[0]), rel=1e-6)
        # the proposal helps: a random direction lowers the model strictly
        assert l_fn < l_pcg


def test_a_useless_proposal_gets_no_weight(monkeypatch):
    p = _quadratic(3)
    a = torch.zeros_like(p.x_prev)
    val, g, hvp = p.grad_hvp(a)
    z = solvers.laplace_preconditioner(p)(g) * p.free
    da_prev = 0.1 * z
    for useless in (lambda z, d: -3.0 * z, lambda z, d: 2.0 * d - 0.5 * z,
                    lambda z, d: torch.zeros_like(z)):
        monkeypatch.setattr(model, "fno_correction",
                            lambda net, p, z, z_prev, d, const=None, grid=None, f=useless: f(z, d))
        da, da_pcg, m, m_pcg = model.subspace_update(None, p, g, hvp, z, z, da_prev)
        assert torch.allclose(da, da_pcg, rtol=1e-8, atol=1e-10 * float(da_pcg.abs().max()))
        assert float(m[0]) == pytest.approx(float(m_pcg[0]), rel=1e-9)


def test_the_guard_keeps_every_iteration_at_least_as_good_as_the_pcg_model():
    # quadratic: nothing to replace; nonlinear cloth with wild proposals: monotone decrease
    info = {}
    model.solve_fnopt(_net(0, gain=300.0), _quadratic(), 10, info=info)
    assert info["replaced"] == 0
    p = _cloth_problem()
    net = _net(1, gain=3000.0)
    losses = [float(p.loss(torch.zeros_like(p.x_prev))[0])]
    for n in range(1, 9):
        losses.append(float(p.loss(model.solve_fnopt(net, p, n))[0]))
    assert all(b <= a + 1e-12 * abs(a) for a, b in zip(losses, losses[1:]))
    # unguarded, the same proposals are only as good as the quadratic model
    assert float(p.loss(model.solve_fnopt(net, p, 8, guard=False))[0]) < losses[0]


def test_subspace_solve_edge_cases():
    p = _quadratic()
    _, g, hvp = p.grad_hvp(torch.zeros_like(p.x_prev))
    d = -g / p.mass[..., None]
    z = torch.zeros_like(d)
    # zero direction: no weight, no NaN; a negative-curvature model still gets m <= 0
    c, m = solvers.subspace_solve(g, [d, z], [hvp(d), hvp(z)])
    assert bool(torch.isfinite(c).all()) and float(c[0, 1]) == 0.0 and float(m[0]) < 0
    c, m = solvers.subspace_solve(g, [d], [-hvp(d)])
    assert bool(torch.isfinite(c).all()) and float(m[0]) <= 0.0


def test_meta_training_step_differentiates_through_the_subspace_step():
    from draping.fnopt.train import Pool, TrainSettings, train_step

    s = TrainSettings(width=4, modes=2, layers=1, projection=4, res=8, pool=4, batch=2,
                      steps=3)
    gen = torch.Generator().manual_seed(0)
    pool = Pool(s, gen)
    torch.manual_seed(0)
    net = model.FNO(model.FNOConfig(4, 2, 1, 4))
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    before = [q.detach().clone() for q in net.parameters()]
    for k in range(3):
        loss = train_step(net, opt, pool, s, k)
        assert loss == loss and abs(loss) < 1e6           # finite
    moved = [bool((q.detach() != b).any()) for q, b in zip(net.parameters(), before)]
    assert all(moved)                                      # every weight got a gradient
    with pytest.raises(ValueError, match="step_rule"):
        TrainSettings(step_rule="line")


def test_iteration_weight_of_the_training_loss():
    # iter_weight > 0 weighs an entry at inner iteration k by 1 + iter_weight k / 10: with every
    # entry at the same k the weights cancel (the unweighted loss, to rounding); at k = 0 they
    # are all 1 (the same loss bit for bit)
    from draping.fnopt.train import Pool, TrainSettings, train_step

    def loss_at(k, w):
        s = TrainSettings(width=4, modes=2, layers=1, projection=4, res=8, pool=4, batch=4,
                          steps=3, iter_weight=w)
        pool = Pool(s, torch.Generator().manual_seed(0))
        pool.it[:] = torch.as_tensor(k)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(0)
            net = model.FNO(model.FNOConfig(4, 2, 1, 4))
        return train_step(net, torch.optim.Adam(net.parameters(), lr=1e-3), pool, s, 0)

    assert loss_at(0, 2.0) == loss_at(0, 0.0)
    assert loss_at(5, 2.0) == pytest.approx(loss_at(5, 0.0), rel=1e-6, abs=1e-12)
    mixed = [0, 0, 10, 10]                      # weights 1, 1, 3, 3: another mean
    assert abs(loss_at(mixed, 2.0) - loss_at(mixed, 0.0)) > 1e-6
    with pytest.raises(ValueError, match="iter_weight"):
        TrainSettings(iter_weight=-1.0)
    with pytest.raises(ValueError, match="iter_weight"):
        TrainSettings(iter_weight=float("nan"))


def test_rollout_perturbation_moves_free_vertices_only():
    sheet = Sheet(8, 8)

    def step(p, a0):
        return solvers.solve_pcg(p, 3)

    ro0 = solvers.rollout(sheet, Material(), "corners", "xy", 2, step)
    ro1 = solvers.rollout(sheet, Material(), "corners", "xy", 2, step, perturb=1e-3)
    idx = cloth.handle_indices("corners", 8, 8)
    d0 = (ro1.positions[0] - ro0.positions[0]).norm(dim=-1)
    assert float(d0[idx[:, 0], idx[:, 1]].max()) == 0.0
    assert 1e-4 < float(d0.max()) < 1e-2
    assert torch.equal(ro0.handles, ro1.handles)
    assert torch.equal(ro0.positions, solvers.rollout(sheet, Material(), "corners", "xy", 2,
                                                      step).positions)


def _solve_fnopt_unsimplified(net, p, iters, guard=True, info=None):
    """``solve_fnopt``'s subspace loop as it was before its branches were folded (d58f036)."""
    pre = solvers.laplace_preconditioner(p)
    a = torch.zeros_like(p.x_prev)
    z_prev = torch.zeros_like(a)
    da = torch.zeros_like(a)
    slack = 1e-6 if a.dtype != torch.float64 else 1e-12
    replaced = 0
    val, g, hvp = p.grad_hvp(a)
    for k in range(iters):
        last = k == iters - 1
        z = pre(g) * p.free
        with torch.no_grad():
            dn, dn_pcg, _, m_pcg = model.subspace_update(net, p, g, hvp, z, z_prev, da)
        a_new = a + dn
        if guard:
            if last:
                with torch.no_grad():
                    val_new = p.loss(a_new).detach()
            else:
                val_new, g_new, hvp_new = p.grad_hvp(a_new)
            bad = (val_new - val).double() > m_pcg + slack * val.abs().double()
            if bool(bad.any()):
                replaced += int(bad.sum())
                dn = torch.where(bad[:, None, None, None], dn_pcg, dn)
                a_new = a + dn
                if not last:
                    val_new, g_new, hvp_new = p.grad_hvp(a_new)
        elif not last:
            val_new, g_new, hvp_new = p.grad_hvp(a_new)
        a, da, z_prev = a_new, dn, z
        if not last:
            val, g, hvp = val_new, g_new, hvp_new
    if info is not None:
        info["replaced"] = replaced
    return p.compose(a)


@pytest.mark.parametrize("guard", [True, False])
@pytest.mark.parametrize("overshoot", [False, True])
def test_folded_guard_loop_is_bit_identical_on_a_rollout(guard, overshoot, monkeypatch):
    # overshoot: every other update tripled (past the model's minimum, so the energy rises and
    # the guard replaces it): the guard's branch on every iteration, the last one included
    net = _net(1).float()
    update = model.subspace_update
    calls = [0]

    def tripled(*args, **kw):
        da, da_pcg, m, m_pcg = update(*args, **kw)
        calls[0] += 1
        return (3.0 * da if overshoot and calls[0] % 2 else da), da_pcg, m, m_pcg

    monkeypatch.setattr(model, "subspace_update", tripled)
    counts = {"new": [0, 0], "old": [0, 0]}

    def step(kind):
        def f(p, a0):
            info = {}
            ev = p.evals
            if kind == "new":
                a = model.solve_fnopt(net, p, 5, guard=guard, info=info)
            else:
                a = _solve_fnopt_unsimplified(net, p, 5, guard=guard, info=info)
            counts[kind][0] += info["replaced"]
            counts[kind][1] += p.evals - ev
            return a
        return f

    ros = {}
    for k in ("new", "old"):
        calls[0] = 0
        ros[k] = solvers.rollout(Sheet(10, 12), Material(), "diagonal", "xyz", 5, step(k),
                                 speed=2.0)
    assert torch.equal(ros["new"].positions, ros["old"].positions)
    assert counts["new"] == counts["old"]
    assert (counts["new"][0] > 0) == (guard and overshoot)     # the guard's branch ran


def _net_normal(zero: bool = True):
    torch.manual_seed(0)
    net = model.FNO(model.FNOConfig(width=8, modes=4, layers=2, projection=8,
                                    normal=True)).double()
    if zero:
        with torch.no_grad():
            net.proj2.weight.zero_()
            net.proj2.bias.zero_()
    return net


def test_with_the_normal_direction_a_zero_fno_output_reproduces_pcg_with_it():
    p = _cloth_problem()
    for n in (1, 4, 10):
        a_pcg = solvers.solve_pcg(p, n, normal=True)
        a_fn = model.solve_fnopt(_net_normal(), p, n)
        assert torch.allclose(a_fn, a_pcg, rtol=1e-7, atol=1e-7 * float(a_pcg.abs().max()))
    # and the normal direction changes the step (it is not a copy of -z)
    assert not torch.allclose(solvers.solve_pcg(p, 4, normal=True), solvers.solve_pcg(p, 4))


def test_the_normal_direction_joins_the_classical_step():
    p = _cloth_problem()
    a = torch.zeros_like(p.x_prev)
    val, g, hvp = p.grad_hvp(a)
    z = solvers.laplace_preconditioner(p)(g) * p.free
    zn = solvers.normal_preconditioner(p)(g)
    da_prev = 0.1 * z
    with torch.no_grad():
        da, da_pcg, m, m_pcg = model.subspace_update(_net_normal(False), p, g, hvp, z, z,
                                                     da_prev, zn=[-zn * p.free])
    ref = p.subspace_step(g, [-z * p.free, da_prev, -zn * p.free], hvp)
    assert torch.allclose(da_pcg, ref, rtol=1e-8, atol=1e-12 * float(ref.abs().max()))
    assert float(m[0]) <= float(m_pcg[0]) + 1e-12 * abs(float(val[0]))


def _flat_problem(res=(9, 7), orientation="horizontal"):
    sheet = Sheet(*res)
    x = cloth.rest_positions(sheet, orientation, torch.float64)[None]
    idx = cloth.handle_indices("single", *res)
    return solvers.make_problem(x, torch.zeros_like(x), idx, x[:, idx[:, 0], idx[:, 1]],
                                sheet.hx, sheet.hy, Material(bend=2.0).tensors(1, torch.float64))


def test_normal_preconditioner_on_a_flat_sheet():
    p = _flat_problem()
    pn = solvers.normal_preconditioner(p)
    gen = torch.Generator().manual_seed(0)
    g = torch.randn(p.x_prev.shape, generator=gen, dtype=torch.float64)
    out = pn(g)
    # a horizontal sheet's normal is z: in-plane parts of g are ignored, the result is along z
    assert torch.equal(out[..., :2], torch.zeros_like(out[..., :2]))
    g_in = g.clone()
    g_in[..., 2] = 0.0
    assert float(pn(g_in).abs().max()) == 0.0
    # a uniform normal load is the constant DCT mode: no bending, inertia only (m dt^2)
    c = torch.zeros_like(g)
    c[..., 2] = 3.0
    rho, h = float(p.material["density"][0]), float(p.hx[0]) * 0.5 + float(p.hy[0]) * 0.5
    expect = 3.0 / (rho * float(p.hx[0]) * float(p.hy[0]) * p.dt ** 2)
    assert torch.allclose(pn(c)[..., 2], torch.full_like(c[..., 2], expect), rtol=1e-12)
    assert h > 0
    # a non-constant load is damped by the bending term: |P g| < |g| / (m dt^2)
    wave = torch.zeros_like(g)
    wave[..., 2] = torch.cos(torch.pi * torch.arange(p.x_prev.shape[2]) / 2.0)[None, None]
    assert float(pn(wave)[..., 2].abs().max()) < 0.999 * expect / 3.0


@pytest.mark.parametrize("orientation", ["horizontal", "vertical"])
def test_normal_preconditioner_is_symmetric_positive_semidefinite(orientation):
    p = _cloth_problem() if orientation == "vertical" else _flat_problem()
    pn = solvers.normal_preconditioner(p)
    gen = torch.Generator().manual_seed(1)
    u = torch.randn(p.x_prev.shape, generator=gen, dtype=torch.float64)
    v = torch.randn(p.x_prev.shape, generator=gen, dtype=torch.float64)
    uv, vu = float((u * pn(v)).sum()), float((v * pn(u)).sum())
    assert uv == pytest.approx(vu, rel=1e-10)
    assert float((u * pn(u)).sum()) > 0
    # the result is parallel to the normals of the predicted positions
    out = pn(u)[0]
    y = (p.x_prev + p.dt * p.v_prev)[0]
    n = torch.cross(y[1:-1, 2:] - y[1:-1, :-2], y[2:, 1:-1] - y[:-2, 1:-1], dim=-1)
    cr = torch.cross(out[1:-1, 1:-1], n, dim=-1).norm(dim=-1)
    assert float(cr.max()) <= 1e-9 * float(out.norm(dim=-1).max() * n.norm(dim=-1).max())


def test_fnoconfig_normal_must_be_a_bool():
    with pytest.raises(TypeError, match="FNOConfig.normal"):
        model.FNOConfig(normal=1)


def test_train_cli_parses_boolean_settings_as_flags():
    import argparse

    from draping.fnopt import cli
    from draping.fnopt.settings import TrainSettings

    ap = argparse.ArgumentParser()
    cli.register(ap.add_subparsers())
    assert ap.parse_args(["train-fnopt", "-o", "x"]).normal is TrainSettings().normal
    assert ap.parse_args(["train-fnopt", "-o", "x", "--normal"]).normal is True
    assert ap.parse_args(["train-fnopt", "-o", "x", "--no-normal"]).normal is False
    with pytest.raises(SystemExit):
        ap.parse_args(["train-fnopt", "-o", "x", "--normal", "False"])


def test_low_modes_and_the_split_normal_directions():
    gen = torch.Generator().manual_seed(2)
    z = torch.randn(2, 9, 7, 3, generator=gen, dtype=torch.float64)
    assert torch.allclose(solvers.low_modes(z, 9), z, atol=1e-12)
    # a field of two cosines: the low cut keeps the slow one only
    j = torch.arange(7, dtype=torch.float64)
    slow = torch.cos(torch.pi * (j + 0.5) / 7)[None, None, :, None].expand(2, 9, 7, 3)
    fast = torch.cos(5 * torch.pi * (j + 0.5) / 7)[None, None, :, None].expand(2, 9, 7, 3)
    assert torch.allclose(solvers.low_modes(slow + fast, 3), slow, atol=1e-12)
    p = _cloth_problem()
    pn = solvers.normal_preconditioner(p)
    _, g = p.loss_grad(torch.zeros_like(p.x_prev))
    (one,) = solvers.normal_directions(p, g, pn)
    lo, hi = solvers.normal_directions(p, g, pn, split=3)
    assert torch.allclose(lo + hi, one, atol=1e-12 * float(one.abs().max()))
    assert float(hi.abs().max()) > 0 and float(lo.abs().max()) > 0


def test_fnoconfig_normal_split_must_be_a_non_negative_int():
    with pytest.raises(ValueError, match="FNOConfig.normal_split"):
        model.FNOConfig(normal_split=-1)
