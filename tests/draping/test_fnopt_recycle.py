"""FNOpt's inference-only options: the recycled subspace across frames
(``solve_fnopt(recycle=k, memory=...)``) and the FNO on every E-th iteration (``fno_every``)."""


import pytest
import torch
from fnopt_cases import quadratic_problem

from draping.fnopt import cloth, model, solvers
from draping.fnopt.cloth import Material, Sheet
from draping.fnopt.simulate import SimSettings, run

torch.set_num_threads(1)


def _springs(res=(8, 7)):
    """Isotropic grid springs: ``L(a) = 1/2 m dt^2 |a|^2 + 1/2 k |grid differences|^2 - b . a``."""
    return quadratic_problem(res, 300.0, 1.0, 0, anisotropic=False)


def _dense_minimiser(p):
    """The exact minimiser from the dense Hessian of ``p.loss`` over the free entries."""
    a0 = torch.zeros_like(p.x_prev)
    free = p.free3.expand(a0.shape).reshape(-1) > 0.5
    f = lambda v: p.loss(v.view(a0.shape))[0]                               # noqa: E731
    h = torch.autograd.functional.hessian(f, a0.reshape(-1))[free][:, free]
    g = torch.autograd.functional.jacobian(f, a0.reshape(-1))[free]
    a = torch.zeros(a0.numel(), dtype=torch.float64)
    a[free] = torch.linalg.solve(h, -g)
    return a.view(a0.shape)


def _net(seed=0, gain=1.0, dtype=torch.float64):
    torch.manual_seed(seed)
    net = model.FNO(model.FNOConfig(width=8, modes=4, layers=2, projection=8)).to(dtype)
    with torch.no_grad():
        net.proj2.weight.mul_(gain)
    return net


def _rel(a, b, p):
    return float(((a - b) * p.free3).norm() / (b * p.free3).norm())


def test_a_basis_holding_the_minimiser_solves_a_quadratic_in_one_iteration():
    p = _springs()
    want = _dense_minimiser(p)
    net = _net(1)
    assert _rel(model.solve_fnopt(net, p, 1), want, p) > 0.1            # not by itself
    memory = {"basis": [want / want.norm()], "x_next": p.x_prev.clone()}
    got = model.solve_fnopt(net, p, 1, recycle=1, memory=memory)
    assert _rel(got, want, p) < 1e-8


def test_recycle_zero_is_the_default_solve_bit_for_bit():
    net = _net(0, dtype=torch.float32)
    memory = {}

    def step(**kw):
        return lambda p, a0: model.solve_fnopt(net, p, 5, **kw)

    ros = [solvers.rollout(Sheet(10, 12), Material(), "diagonal", "xyz", 6, s, speed=2.0)
           for s in (step(), step(recycle=0, memory=memory))]
    assert torch.equal(ros[0].positions, ros[1].positions)
    assert memory == {}


def test_the_basis_is_orthonormal_free_at_handles_and_spans_the_updates():
    g = torch.Generator().manual_seed(3)
    free = torch.ones(2, 6, 5, 1, dtype=torch.float64)
    free[:, 0, 0] = free[:, 3, 2] = 0.0
    free3 = free.expand(2, 6, 5, 3)
    ups = [torch.randn(2, 6, 5, 3, generator=g, dtype=torch.float64) * free3 for _ in range(3)]
    ups.append(2.0 * ups[1] - ups[0])                                    # dependent: dropped
    w = model.recycled_basis(ups, free3)
    assert len(w) == 3
    q = torch.stack(w, -1).reshape(2, -1, 3)
    assert torch.allclose(q.transpose(1, 2) @ q, torch.eye(3, dtype=torch.float64).expand(2, 3, 3),
                          atol=1e-12)
    assert all(float((wi * (1 - free3)).abs().max()) == 0.0 for wi in w)
    for u in ups:                                             # each update lies in the span
        uf = u.reshape(2, -1, 1)
        assert float((uf - q @ (q.transpose(1, 2) @ uf)).norm()) < 1e-10 * float(uf.norm())
    assert model.recycled_basis([], free3) == []


def test_the_basis_is_carried_only_to_the_frame_that_follows():
    net = _net(0, dtype=torch.float32)
    memory, seen = {}, []

    def step(p, a0):
        seen.append((p, len(model.carried_basis(p, memory))))
        return model.solve_fnopt(net, p, 4, recycle=3, memory=memory)

    solvers.rollout(Sheet(10, 12), Material(), "diagonal", "xyz", 4, step, speed=2.0)
    assert [n for _, n in seen] == [0, 3, 3, 3]                # none at the first frame
    assert len(memory["basis"]) == 3
    # another rollout (or a repeated frame) does not continue the last solve: no basis
    assert model.carried_basis(seen[0][0], memory) == []
    assert model.carried_basis(seen[2][0], memory) == []


def test_recycling_never_lets_a_step_raise_the_energy_past_the_guard():
    # wild proposals and a random basis on a nonlinear cloth step: the energy after n
    # iterations does not rise with n (the guard keeps the classical step's decrease)
    sheet = Sheet(12, 12)
    ro = solvers.rollout(sheet, Material(), "diagonal", "xyz", 6,
                         lambda p, a0: solvers.solve_pcg(p, 10), speed=2.0, dtype=torch.float64)
    idx = cloth.handle_indices("diagonal", 12, 12)
    x = ro.positions[-2][None]
    v = (ro.positions[-2] - ro.positions[-3])[None] / solvers.DT
    p = solvers.make_problem(x, v, idx, ro.positions[-1][None][:, idx[:, 0], idx[:, 1]],
                             sheet.hx, sheet.hy, Material().tensors(1, torch.float64))
    gen = torch.Generator().manual_seed(5)
    rand = [torch.randn(x.shape, generator=gen, dtype=torch.float64) * 50.0 for _ in range(4)]
    basis = model.recycled_basis(rand, p.free3)
    net = _net(1, gain=3000.0)
    losses = [float(p.loss(torch.zeros_like(x))[0])]
    for n in range(1, 9):
        memory = {"basis": list(basis), "x_next": p.x_prev.clone()}
        losses.append(float(p.loss(model.solve_fnopt(net, p, n, recycle=4, memory=memory))[0]))
    assert all(b <= a + 1e-12 * abs(a) for a, b in zip(losses, losses[1:]))
    assert losses[-1] < losses[0]


@pytest.mark.parametrize("bad, err", [(-1, ValueError), (model.RECYCLE_MAX + 1, ValueError),
                                      (2.0, TypeError), (True, TypeError)])
def test_bad_recycle_raises(bad, err):
    p = _springs()
    with pytest.raises(err, match="recycle"):
        model.solve_fnopt(_net(), p, 2, recycle=bad, memory={})
    with pytest.raises(err, match="recycle"):
        SimSettings(recycle=bad)


def test_recycle_needs_memory_and_the_subspace_step():
    p = _springs()
    with pytest.raises(ValueError, match="memory"):
        model.solve_fnopt(_net(), p, 2, recycle=2)
    with pytest.raises(ValueError, match="subspace"):
        model.solve_fnopt(_net(), p, 2, recycle=2, memory={}, step="line")


def test_simulate_carries_the_basis_across_frames():
    net = _net(0, dtype=torch.float32)
    s = SimSettings(res=(10, 10), handles="diagonal", motion="xyz", frames=5, recycle=2,
                    coarse=0)                          # the one-level step's options
    got = run(s, model=net)
    memory = {}
    want = solvers.rollout(s.sheet(), s.material, s.handles, s.motion, s.frames,
                           lambda p, a0: model.solve_fnopt(net, p, s.iters, recycle=2,
                                                           memory=memory), s.speed)
    plain = run(SimSettings(res=(10, 10), handles="diagonal", motion="xyz", frames=5, coarse=0),
                model=net)
    assert torch.equal(got.positions, want.positions)
    assert not torch.equal(got.positions, plain.positions)
    assert "recycle" not in s.key()


def _cloth_step(res=12):
    """A nonlinear cloth step (float64): frame 6 of a fast diagonal/xyz PCG rollout."""
    sheet = Sheet(res, res)
    ro = solvers.rollout(sheet, Material(), "diagonal", "xyz", 6,
                         lambda p, a0: solvers.solve_pcg(p, 10), speed=2.0, dtype=torch.float64)
    idx = cloth.handle_indices("diagonal", res, res)
    x = ro.positions[-2][None]
    v = (ro.positions[-2] - ro.positions[-3])[None] / solvers.DT
    return solvers.make_problem(x, v, idx, ro.positions[-1][None][:, idx[:, 0], idx[:, 1]],
                                sheet.hx, sheet.hy, Material().tensors(1, torch.float64))


def test_fno_every_calls_the_fno_on_every_eth_iteration_only(monkeypatch):
    p = _cloth_step()
    calls = []
    real = model.fno_correction

    def counted(*args, **kw):
        calls.append(1)
        return real(*args, **kw)

    monkeypatch.setattr(model, "fno_correction", counted)
    for every, want in ((1, 7), (2, 4), (3, 3), (7, 1), (50, 1)):
        calls.clear()
        model.solve_fnopt(_net(1), p, 7, fno_every=every)
        assert len(calls) == want


def test_the_iterations_without_the_fno_are_the_classical_steps():
    # a network whose proposal is zero makes FNOpt the classical PCG iterate by iterate, so the
    # same solve with the FNO skipped on most iterations must equal both: the skipped
    # iterations keep the classical directions and memory; a live network does differ
    p = _cloth_step()
    zero = _net(1)
    with torch.no_grad():
        zero.proj2.weight.zero_()
        zero.proj2.bias.zero_()
    pcg = solvers.solve_pcg(p, 6)
    for every in (1, 2, 4):
        assert _rel(model.solve_fnopt(zero, p, 6, fno_every=every), pcg, p) < 1e-9
    live = [model.solve_fnopt(_net(1, gain=30.0), p, 6, fno_every=e) for e in (1, 2, 6)]
    assert min(_rel(live[0], live[1], p), _rel(live[1], live[2], p),
               _rel(live[2], pcg, p)) > 1e-6


def test_fno_every_never_lets_a_step_raise_the_energy():
    p = _cloth_step()
    net = _net(1, gain=3000.0)                                         # wild proposals
    losses = [float(p.loss(torch.zeros_like(p.x_prev))[0])]
    for n in range(1, 9):
        losses.append(float(p.loss(model.solve_fnopt(net, p, n, fno_every=3))[0]))
    assert all(b <= a + 1e-12 * abs(a) for a, b in zip(losses, losses[1:]))
    assert losses[-1] < losses[0]


@pytest.mark.parametrize("bad, err", [(0, ValueError), (-2, ValueError), (2.0, TypeError),
                                      (True, TypeError)])
def test_bad_fno_every_raises(bad, err):
    with pytest.raises(err, match="fno_every"):
        model.solve_fnopt(_net(), _springs(), 2, fno_every=bad)


def test_fno_every_needs_the_subspace_step_and_inference():
    p = _springs()
    with pytest.raises(ValueError, match="subspace"):
        model.solve_fnopt(_net(), p, 2, fno_every=2, step="line")
    a = torch.zeros_like(p.x_prev)
    _, g, hvp = p.grad_hvp(a)
    z = torch.ones_like(a)
    with pytest.raises(ValueError, match="proposal"):
        model.subspace_update(_net(), p, g, hvp, z, z, z, create_graph=True, proposal=False)


def test_simulate_passes_fno_every_and_checks_it():
    net = _net(0, dtype=torch.float32)
    s = SimSettings(res=(10, 10), handles="diagonal", motion="xyz", frames=4, iters=6,
                    fno_every=6, coarse=0)
    want = solvers.rollout(s.sheet(), s.material, s.handles, s.motion, s.frames,
                           lambda p, a0: model.solve_fnopt(net, p, 6, fno_every=6), s.speed)
    assert torch.equal(run(s, model=net).positions, want.positions)
    assert "fno_every" not in s.key()
    with pytest.raises(ValueError, match="fno_every"):
        SimSettings(fno_every=0)
