"""Training with the two-level coarse direction in the subspace (``TrainSettings.two_level``)."""

import pytest
import torch
from fnopt_cases import TINY_TRAIN, tiny_fno, tiny_pool

from draping.fnopt import model, train, twolevel
from draping.fnopt.classical import solve_pcg
from draping.fnopt.train import TrainSettings

torch.set_num_threads(1)

K = 4          # the tiny pool's sheets are 8 x 8: a 4 x 4 coarse grid


def test_the_space_is_kept_per_frame_and_rebuilt_the_same(monkeypatch):
    pool = tiny_pool()
    ids = torch.tensor([1, 3])
    g = torch.randn(2, 8, 8, 3, generator=torch.Generator().manual_seed(2))
    builds = []
    real = train.galerkin_space
    monkeypatch.setattr(train, "galerkin_space", lambda *a: builds.append(1) or real(*a))
    (d1,) = train.coarse_directions(pool, ids, g, K)
    (d2,) = train.coarse_directions(pool, ids, g, K)
    assert len(builds) == 2 and torch.equal(d1, d2)          # kept: no rebuild on the frame
    pool.coarse_kept.clear()                                 # as after a resume
    (d3,) = train.coarse_directions(pool, ids, g, K)
    assert len(builds) == 4 and torch.equal(d1, d3)          # the frame's state alone decides
    pool.t[3] += 1 / 60                                      # entry 3 on its next frame
    train.coarse_directions(pool, ids, g, K)
    assert len(builds) == 5


def test_a_sheet_whose_operator_does_not_factor_gets_no_direction(monkeypatch):
    pool = tiny_pool()
    ids = torch.tensor([1, 3])
    g = torch.randn(2, 8, 8, 3, generator=torch.Generator().manual_seed(5))
    (want,) = train.coarse_directions(pool, ids, g, K)
    pool.coarse_kept.pop(3)
    calls = []

    def fail(*a):
        calls.append(1)
        raise ValueError("coarse space: the Galerkin operator does not factor")

    monkeypatch.setattr(train, "galerkin_space", fail)
    (d,) = train.coarse_directions(pool, ids, g, K)
    assert torch.equal(d[0], want[0]) and torch.equal(d[1], torch.zeros_like(d[1]))
    train.coarse_directions(pool, ids, g, K)                 # not tried again on that frame
    assert len(calls) == 1


def test_with_a_zero_proposal_the_training_update_is_the_two_level_pcg_step():
    # independent implementation: classical.solve_pcg(normal=True, coarse=K), one iteration
    # (seed 1: on seed 0 one sheet, its handles 0.3 s of motion away in one step, gets a step
    # worse than none and is restarted, as the pool step does)
    s = TrainSettings(**{**TINY_TRAIN, "two_level": K})
    pool = tiny_pool(1)
    net = tiny_fno(zero=True)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    gen = torch.Generator()
    gen.set_state(pool.gen.get_state())
    ids = torch.randperm(s.pool, generator=gen)[:s.batch]
    p, _ = pool.problem(ids, analytic_hvp=True)
    want = solve_pcg(p, 1, normal=True, split=s.normal_split, coarse=K) * p.free3
    train.train_step(net, opt, pool, s, 0)
    assert torch.equal(pool.it[ids], torch.ones_like(pool.it[ids]))
    got = pool.a[ids] * p.free3
    assert torch.allclose(got, want, rtol=0, atol=1e-4 * want.abs().max())
    # without the option the step is another one (the coarse direction matters here)
    pool0 = tiny_pool(1)
    s0 = TrainSettings(**TINY_TRAIN)
    net0 = tiny_fno(zero=True)
    train.train_step(net0, torch.optim.Adam(net0.parameters(), lr=1e-3), pool0, s0, 0)
    assert not torch.allclose(pool0.a[ids] * p.free3, want, rtol=0, atol=1e-3 * want.abs().max())


def test_gradcheck_through_the_subspace_with_the_coarse_direction(monkeypatch):
    # the training loss's backward: the update as a function of the FNO's proposal f, with the
    # coarse direction among the classical ones (float64, closed-form products). Sheets 0.05 s
    # into their motion, where the subspace model is positive definite: where it is not
    # (tiny_pool's 0.3 s), subspace_solve's shift is a constant of the backward by design
    pool = tiny_pool()
    pool.t[:] = 0.05
    ids = torch.tensor([0, 2])
    p, _ = pool.problem(ids, torch.float64, analytic_hvp=True)
    _, g, hvp = p.grad_hvp(torch.zeros_like(p.x_prev))
    z = g / p.mass[..., None] * p.free
    zn = train.coarse_directions(pool, ids, g, K)
    gen = torch.Generator().manual_seed(3)
    f0 = torch.randn(p.x_prev.shape, generator=gen, dtype=torch.float64) * p.free3
    prev = torch.randn(p.x_prev.shape, generator=gen, dtype=torch.float64) * 1e-2 * p.free3
    w = torch.randn(p.x_prev.shape, generator=gen, dtype=torch.float64)

    def update(f):
        monkeypatch.setattr(model, "fno_correction", lambda *a, **k: f)
        da = model.subspace_update(None, p, g, hvp, z, z, prev, create_graph=True, zn=zn)[0]
        return (da * w).sum()

    assert torch.autograd.gradcheck(update, (f0.requires_grad_(True),), eps=1e-6, atol=1e-7)


def test_training_validates_with_the_option_and_the_default_is_unchanged(tmp_path, monkeypatch):
    evals, steps = [], []
    monkeypatch.setattr(train, "evaluate", lambda m, v, *a, **k: evals.append((a, k)) or 0.0)
    real = train.coarse_directions
    monkeypatch.setattr(train, "coarse_directions",
                        lambda *a: steps.append(a[3]) or real(*a))
    assert TrainSettings().two_level == 0
    val = [{"problem": None}]
    train.train(TrainSettings(**{**TINY_TRAIN, "steps": 2}), tmp_path / "a", quiet=True,
                log=lambda *a: None, val=val)
    assert evals == [((), {})] and steps == []
    res = train.train(TrainSettings(**{**TINY_TRAIN, "steps": 3, "two_level": K}), tmp_path / "b",
                      quiet=True, log=lambda *a: None, val=val)
    assert res["step"] == 3 and steps == [K] * 3 and evals[-1] == ((), {"two_level": K})


def test_an_interrupted_two_level_run_resumes_to_the_same_weights(tmp_path, monkeypatch):
    # the kept coarse spaces are not checkpointed: rebuilt after the resume, the same ones
    s = TrainSettings(**{**TINY_TRAIN, "steps": 6, "two_level": K})
    val = [{"problem": None}]
    monkeypatch.setattr(train, "evaluate", lambda *a, **k: 0.0)
    train.train(s, tmp_path / "whole", quiet=True, log=lambda *a: None, val=val)
    first = train.train(s, tmp_path / "parts", quiet=True, log=lambda *a: None, val=val,
                        max_minutes=0.0)
    assert not first["finished"] and first["step"] < s.steps
    train.train(s, tmp_path / "parts", quiet=True, log=lambda *a: None, val=val)
    a = torch.load(tmp_path / "whole" / "model.pt", weights_only=True)
    b = torch.load(tmp_path / "parts" / "model.pt", weights_only=True)
    assert all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.parametrize("bad", [dict(two_level=1), dict(two_level=-2), dict(two_level=2.5),
                                 dict(two_level=4, proposal_iters=3),
                                 dict(two_level=4, rollout_steps=5)])
def test_two_level_settings_are_checked(bad):
    with pytest.raises((ValueError, TypeError), match="two_level"):
        TrainSettings(**bad)


def test_the_direction_is_each_sheets_own_galerkin_correction():
    # each entry's kept space is twolevel.galerkin_space of its own step problem at a = 0
    # (tested against P^T H P assembled column by column in test_fnopt_twolevel.py), whatever
    # the batch it comes in; zero at the handles
    pool = tiny_pool()
    ids = torch.tensor([2, 0, 3])
    g = torch.randn(3, 8, 8, 3, generator=torch.Generator().manual_seed(4))
    (d,) = train.coarse_directions(pool, ids, g, K)
    for j, i in enumerate(ids.tolist()):
        p, _ = pool.problem(torch.tensor([i]), analytic_hvp=True)
        _, _, hvp = p.grad_hvp(torch.zeros_like(p.x_prev))
        want = -twolevel.coarse_correction(twolevel.galerkin_space(p, hvp, K), g[j:j + 1])
        assert torch.equal(d[j:j + 1], want)
        assert torch.equal(want * (1 - p.free3), torch.zeros_like(want))
        assert float(want.abs().max()) > 0
