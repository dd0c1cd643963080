"""Rollout-level fine-tuning (``draping.fnopt.tbptt``): the unrolled solve, the frame boundary."""

import pytest
import torch
from fnopt_cases import TINY_TRAIN, tiny_fno, tiny_pool

from draping.fnopt import model, tbptt, train
from draping.fnopt.handles import DT
from draping.fnopt.train import TrainSettings

torch.set_num_threads(1)

TINY = TINY_TRAIN
_net, _pool = tiny_fno, tiny_pool


def test_unrolled_solve_is_the_inference_solve_without_its_guard():
    # the training unroll and Algorithm 2 (solve_fnopt, no guard) are two codes of one
    # iteration: the same iterates up to float32 rounding
    net, pool = _net(), _pool()
    ids = torch.arange(4)
    p, _ = pool.problem(ids, state=(pool.x[ids], pool.v[ids], pool.t[ids]), analytic_hvp=True)
    a, denom = tbptt.unrolled_solve(net, p, 4)
    want = model.solve_fnopt(net, p, 4, guard=False)
    assert torch.allclose(p.compose(a.detach()), want, rtol=1e-4, atol=1e-5 * want.abs().max())
    assert (denom > 0).all()
    assert a.requires_grad                       # in the graph of the model's parameters


def test_the_gradient_reaches_through_the_frame_boundary():
    # the second frame's loss depends on the first frame's model output through the state
    # (x1, v1): its gradient with the boundary kept differs from the one with it cut (with
    # the boundary cut, as the pool training, only frame 2's own iterations remain)
    net, pool = _net(), _pool()
    ids = torch.arange(4)

    def grads(detach):
        net.zero_grad()
        losses, _ = tbptt.rollout_losses(net, pool, ids, 2, 3, extra=2, detach_state=detach)
        losses[1].sum().backward()
        return torch.cat([q.grad.flatten() for q in net.parameters()])

    kept, cut = grads(False), grads(True)
    assert torch.isfinite(kept).all() and torch.isfinite(cut).all()
    assert cut.abs().max() > 0                   # frame 2's own iterations
    assert (kept - cut).abs().max() > 1e-3 * kept.abs().max()
    # the state after a frame is backward Euler with the frame's own acceleration
    x0 = pool.x[ids].clone()
    _, (x1, v1) = tbptt.rollout_losses(net, pool, ids, 1, 3, extra=0)
    assert x1.requires_grad and v1.requires_grad
    free = 1.0 - pool.hmask[ids][..., None]
    target = pool.targets(ids, pool.t[ids] + DT)
    assert torch.allclose(x1 * free, (x0 + DT * v1) * free, atol=1e-6)
    assert torch.allclose(x1 * (1 - free), target, atol=1e-6)      # handles on their targets


def test_frame_loss_is_the_normalised_suboptimality():
    # extra = 0: (L(a_N) - L(0)) / (1/2 g0.z0) < 0 (the solve lowers L); extra > 0: the gap
    # to a_N improved by classical iterations, >= 0 up to rounding and smaller in size
    net, pool = _net(), _pool()
    ids = torch.arange(4)
    (dec,), _ = tbptt.rollout_losses(net, pool, ids, 1, 3, extra=0)
    (gap,), _ = tbptt.rollout_losses(net, pool, ids, 1, 3, extra=10)
    assert (dec < 0).all()
    assert (gap > -1e-6).all() and (gap < dec.abs()).all()
    with pytest.raises(ValueError, match="frames"):
        tbptt.rollout_losses(net, pool, ids, 0, 3)
    with pytest.raises(ValueError, match="extra"):
        tbptt.rollout_losses(net, pool, ids, 1, 3, extra=-1)


def test_rollout_step_advances_the_pool_and_trains_every_weight():
    net, pool = _net(), _pool()
    before = [q.detach().clone() for q in net.parameters()]
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    t0, f0 = pool.t.clone(), pool.frame.clone()
    loss = tbptt.rollout_train_step(net, opt, pool, 2, 3, 4, 2, 1e-3)
    assert loss == loss and abs(loss) < 1e3
    assert all(bool((q.detach() != b).any()) for q, b in zip(net.parameters(), before))
    assert torch.allclose(pool.t, t0 + 2 * DT) and torch.equal(pool.frame, f0 + 2)


def test_default_training_never_fine_tunes(tmp_path, monkeypatch):
    # rollout_steps = 0 (the default, the shipped weights): no rollout step; > 0: that many,
    # after the pool steps
    calls = []

    def fake(*args, **kw):
        calls.append(args[-1])
        return 0.0

    monkeypatch.setattr(train, "rollout_train_step", fake)
    assert TrainSettings().rollout_steps == 0 and TrainSettings().init == ""
    val = [{"problem": None}]
    monkeypatch.setattr(train, "evaluate", lambda m, v: 0.0)
    s = TrainSettings(**{**TINY, "steps": 2})
    train.train(s, tmp_path / "a", quiet=True, log=lambda *a: None, val=val)
    assert calls == []
    s = TrainSettings(**{**TINY, "steps": 2, "rollout_steps": 3, "rollout_lr": 1e-3,
                         "eval_every": 2})
    res = train.train(s, tmp_path / "b", quiet=True, log=lambda *a: None, val=val)
    assert len(calls) == 3 and res["step"] == 5
    assert calls[0] == pytest.approx(1e-3) and calls[-1] < calls[0]     # cosine decay
    assert [h["phase"] for h in res["history"]] == ["pool", "rollout", "rollout"]


def test_fine_tuning_settings_and_initial_weights(tmp_path):
    for bad in (dict(rollout_frames=0), dict(rollout_iters=0), dict(rollout_batch=0),
                dict(rollout_steps=-1), dict(rollout_extra=-1), dict(rollout_lr=0.0)):
        with pytest.raises(ValueError, match=next(iter(bad))):
            TrainSettings(**bad)
    s = TrainSettings(init="shipped")               # the shipped weights' own config
    net = model.FNO(model.FNOConfig(s.width, s.modes, s.layers, s.projection, s.normal,
                                    s.normal_split))
    train.initial_weights(s, net)
    ship = model.load_pretrained()
    assert all(torch.equal(a, b) for a, b in zip(net.state_dict().values(),
                                                  ship.state_dict().values()))
    with pytest.raises(ValueError, match="init"):
        train.initial_weights(TrainSettings(init="shipped", width=4), _net())
