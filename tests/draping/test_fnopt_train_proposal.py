"""Training for the first-iteration role (``draping.fnopt.train_proposal``)."""

import pytest
import torch
from fnopt_cases import TINY_TRAIN, tiny_fno, tiny_pool

from draping.fnopt import model, train, train_proposal
from draping.fnopt.classical import solve_pcg
from draping.fnopt.handles import DT
from draping.fnopt.train import TrainSettings

torch.set_num_threads(1)

TINY = TINY_TRAIN


def _net(zero=False):
    return tiny_fno(zero=zero)


def _problems(seed=0):
    """Tiny pool problems (float32 and float64) 0.3 s into their motion, and the pool."""
    pool = tiny_pool(seed)
    ids = torch.arange(4)
    p, _ = pool.problem(ids, analytic_hvp=True)
    p64, _ = pool.problem(ids, torch.float64, analytic_hvp=True)
    return pool, p, p64


def test_first_update_then_classical_iterations_is_the_inference_solve():
    # the training path (first update with the graph, K detached classical iterations) and
    # solve_fnopt(fno_every >= N, no guard) are two codes of one solve: the same iterate up to
    # float32 rounding (the graph path uses torch's products, inference the fused kernels)
    net = _net()
    _, p, _ = _problems()
    a1 = train_proposal.first_update(net, p)
    assert a1.requires_grad
    a_k, _ = train_proposal.classical_iterations(net, p, a1.detach(), a1.detach(), 4)
    want = model.solve_fnopt(net, p, 5, fno_every=5, guard=False)
    assert torch.allclose(p.compose(a_k), want, rtol=1e-4, atol=1e-5 * want.abs().max())


def test_with_a_zero_proposal_the_role_is_pcg_with_the_normal_directions():
    # independent implementation: classical.solve_pcg(normal=True) from a = 0
    net = _net(zero=True)
    _, p, _ = _problems()
    a1 = train_proposal.first_update(net, p).detach()
    a_k, _ = train_proposal.classical_iterations(net, p, a1, a1, 6)
    want = solve_pcg(p, 7, normal=True, split=net.config.normal_split)
    assert torch.allclose(p.compose(a_k), want, rtol=1e-4, atol=1e-5 * want.abs().max())
    a0, d0 = train_proposal.classical_iterations(net, p, a1, a1, 0)
    assert torch.equal(a0, a1) and torch.equal(d0, a1)


def test_the_loss_gradient_is_straight_through_the_classical_iterations():
    # d surrogate / d a_1 = g_K / gap, with g_K the float64 gradient at a_K; rel in (0, 1]
    net = _net()
    _, p, p64 = _problems()
    surrogate, rel, a_k = train_proposal.proposal_losses(net, p, p64, 3, 5)
    assert surrogate.shape == rel.shape == (4,) and surrogate.requires_grad
    assert torch.isfinite(rel).all() and (rel > 0).all() and (rel <= 1.0 + 1e-9).all()
    g_k = p64.loss_grad(a_k.double(), fused=True)[1]
    assert g_k.abs().max() > 0
    # after 1 + 3 iterations at least as good as 1 + 0 (monotone classical iterations)
    l_k = p64.loss(a_k.double())
    a1 = train_proposal.first_update(net, p).detach()
    assert (l_k <= p64.loss(a1.double()) + 1e-9 * l_k.abs()).all()
    # its parameter gradient is that of g_K . a_1 / gap, assembled here from the parts
    net.zero_grad()
    surrogate.sum().backward()
    got = torch.cat([q.grad.flatten() for q in net.parameters()])
    net.zero_grad()
    a1g = train_proposal.first_update(net, p)
    a_ref = train_proposal.classical_iterations(
        net, p, a_k, *train_proposal.classical_iterations(net, p, a1, a1, 3)[1:], 5)[0]
    l_ref = torch.minimum(p64.loss(a_ref.double()), l_k)
    gap = (l_k - l_ref).detach()
    ((g_k * a1g.double()).sum((1, 2, 3)) / gap).sum().backward()
    want = torch.cat([q.grad.flatten() for q in net.parameters()])
    assert want.abs().max() > 0
    assert torch.allclose(got, want, rtol=1e-5, atol=1e-8 * want.abs().max())
    with pytest.raises(ValueError, match="iters"):
        train_proposal.proposal_losses(net, p, p64, 0, 5)
    with pytest.raises(ValueError, match="extra"):
        train_proposal.proposal_losses(net, p, p64, 3, 0)


def test_proposal_step_advances_the_pool_one_frame_and_trains_the_model():
    net = _net()
    pool, _, _ = _problems()
    before = [q.detach().clone() for q in net.parameters()]
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    t0, f0, x0, v0 = pool.t.clone(), pool.frame.clone(), pool.x.clone(), pool.v.clone()
    loss = train_proposal.proposal_train_step(net, opt, pool, 3, 2, 4, 1e-3)
    assert 0.0 < loss <= 1.0 + 1e-9
    assert any(bool((q.detach() != b).any()) for q, b in zip(net.parameters(), before))
    assert torch.allclose(pool.t, t0 + DT) and torch.equal(pool.frame, f0 + 1)
    free = 1.0 - pool.hmask[..., None]
    # backward Euler: x1 = x0 + dt v1 on the free vertices; handles on their targets
    assert torch.allclose(pool.x * free, (x0 + DT * pool.v) * free, atol=1e-6)
    ids = torch.arange(4)
    assert torch.allclose(pool.x * (1 - free), pool.targets(ids, t0 + DT), atol=1e-6)
    assert not torch.equal(pool.v, v0)


def test_default_training_is_the_pool_step(tmp_path, monkeypatch):
    # proposal_iters = 0 (default, the shipped weights): the pool step, never the role's;
    # > 0: the role's step for every pool step, validated by the role's own solve
    calls, evals = [], []

    def fake(*args, **kw):
        calls.append(args[3:6])
        return 0.5

    monkeypatch.setattr(train, "proposal_train_step", fake)
    monkeypatch.setattr(train, "evaluate", lambda m, v, *a: evals.append(a) or 0.0)
    assert TrainSettings().proposal_iters == 0
    val = [{"problem": None}]
    train.train(TrainSettings(**{**TINY, "steps": 2}), tmp_path / "a", quiet=True,
                log=lambda *a: None, val=val)
    assert calls == [] and evals == [()]
    s = TrainSettings(**{**TINY, "steps": 3, "proposal_iters": 4, "proposal_extra": 2})
    res = train.train(s, tmp_path / "b", quiet=True, log=lambda *a: None, val=val)
    assert res["step"] == 3 and calls == [(4, 2, TINY["batch"])] * 3
    assert evals[-1] == (5, 5)


def test_proposal_settings_are_checked():
    for bad in (dict(proposal_iters=-1), dict(proposal_extra=0), dict(proposal_iters=1.5)):
        with pytest.raises((ValueError, TypeError), match=next(iter(bad))):
            TrainSettings(**bad)
