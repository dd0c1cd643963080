"""The two-level control (:mod:`draping.fnopt.twolevel`, ``solve_pcg(coarse=K)``).

Truths: the probed Galerkin operator against ``P^T H P`` assembled column by column from the
problem's Hessian products (independent of the colouring); on the fine grid itself (``P = I``)
the correction is the Newton step ``H^-1 g`` on the free vertices; off by default and bit for
bit the old solve; stable over a rollout. No backward: ``solve_pcg`` is a no-gradient solver
(its coarse direction is numpy), so there is nothing to gradcheck.
"""

from __future__ import annotations

import pytest
import torch
from fnopt_cases import quadratic_problem, random_problem

from draping.fnopt import classical, cloth, solvers, twolevel
from draping.fnopt.cloth import Material, Sheet
from draping.fnopt.coarse import coarse_shape, interpolation_matrix

F64 = torch.float64


def _dense_correction(p, k):
    """``P A^-1 P^T g`` with ``A = P^T H P`` built from one Hessian product per coarse unknown."""
    _, g, hvp = p.grad_hvp(torch.zeros_like(p.x_prev))
    b, h, w, _ = p.x_prev.shape
    hc, wc = coarse_shape(h, w, k)
    ph, pw = interpolation_matrix(hc, h, F64), interpolation_matrix(wc, w, F64)
    free = p.free.double()
    n = 3 * hc * wc
    cols = []
    for q in range(n):
        e = torch.zeros(n, dtype=F64)
        e[q] = 1.0
        v = torch.einsum("hi,bijc,wj->bhwc", ph, e.reshape(1, hc, wc, 3), pw) * free
        cols.append(torch.einsum("hi,bhwc,wj->bijc", ph, hvp(v) * free, pw).reshape(-1))
    a = torch.stack(cols, 1)
    keep = torch.diagonal(a) > 1e-10 * torch.diagonal(a).max()
    gc = torch.einsum("hi,bhwc,wj->bijc", ph, g * free, pw).reshape(-1)
    ak = a[keep][:, keep]
    y = torch.zeros(n, dtype=F64)
    y[keep] = torch.linalg.solve(ak, gc[keep])
    spd = bool(torch.linalg.eigvalsh(ak)[0] > 0)
    return torch.einsum("hi,bijc,wj->bhwc", ph, y.reshape(1, hc, wc, 3), pw) * free, g, hvp, spd


@pytest.mark.parametrize("n, k, layout", [(12, 4, "corners"), (12, 5, "diagonal"),
                                          (9, 5, "mid-edges")])
def test_probed_galerkin_correction_equals_the_dense_one(n, k, layout):
    """Colour-probed ``A_c`` (``s x s x 3`` products) against the column-by-column
    ``P^T H P``, on an ``n x (n + 2)`` sheet (not square) with handles, where that ``A_c`` is
    positive definite (no shift; stated: 1e-10 relative; float64)."""
    p = random_problem(n, F64, 3, layout=layout)
    want, g, hvp, spd = _dense_correction(p, k)
    assert spd
    got = twolevel.coarse_correction(twolevel.galerkin_space(p, hvp, k), g)
    assert float((got - want).norm() / want.norm()) < 1e-10


def test_an_indefinite_galerkin_operator_is_shifted_not_solved():
    """A near-rest sheet with 1 mm noise (compressed edges): ``A_c`` on a 5 x 6 grid is
    indefinite; the correction is finite, differs from the indefinite solve, and is a descent
    direction (``g . P S^-1 P^T g > 0`` for the shifted positive definite ``S``)."""
    p = random_problem(12, F64, 3, layout="diagonal")
    want, g, hvp, spd = _dense_correction(p, 6)
    assert not spd
    got = twolevel.coarse_correction(twolevel.galerkin_space(p, hvp, 6), g)
    assert bool(torch.isfinite(got).all())
    assert float((got - want).norm() / want.norm()) > 0.1
    assert float((got * g).sum()) > 0


def test_on_the_fine_grid_the_correction_is_the_newton_step():
    """``K`` = the grid's longer side: ``P`` is the identity on the free vertices, the
    correction ``H_ff^-1 g_f`` (zero at handles); checked by ``H d = g`` on the free ones
    (a quadratic problem, Hessian by autograd, 7 x 7 colours of 3 products)."""
    p = quadratic_problem((8, 10))             # SPD: inertia + anisotropic springs
    _, g, hvp = p.grad_hvp(torch.zeros_like(p.x_prev))
    d = twolevel.coarse_correction(twolevel.galerkin_space(p, hvp, 10), g)
    assert float((d * (1 - p.free3)).abs().max()) == 0.0
    assert float((hvp(d) - g).norm() / g.norm()) < 1e-9


@pytest.mark.parametrize("fine, coarse, want", [(64, 16, 5), (32, 16, 5), (10, 10, 7),
                                                (64, 2, 3), (5, 3, 3)])
def test_probe_spacing(fine, coarse, want):
    """Hat spacing ``h`` fine cells: two hats ``j`` apart interact through a reach-2 Hessian iff
    ``j h < 2 h + 2``: ``h = 4.2``: up to 2 (5 colours); ``h = 1``: up to 3 (7); ``h = 63``:
    up to 2, but 2 vertices: 2 colours at most... capped by the coarse count."""
    assert twolevel.probe_spacing(fine, coarse) == min(want, coarse)


def test_coarse_off_is_the_old_solve_and_on_changes_it():
    p = random_problem(12, torch.float32, 5, layout="diagonal")
    old = classical.solve_pcg(p, 6, normal=True, split=2)
    assert torch.equal(classical.solve_pcg(p, 6, normal=True, split=2, coarse=0), old)
    new = classical.solve_pcg(p, 6, normal=True, split=2, coarse=4)
    assert not torch.equal(new, old)
    assert bool(torch.isfinite(new).all())


def test_one_iteration_reaches_the_coarse_minimum_of_a_quadratic_problem():
    """On a quadratic problem (SPD, anisotropic springs: the DCT metric is not exact) the first
    iteration's span holds the coarse correction, the minimiser of ``L`` over the range of
    ``P``: ``L(a_1) <=`` that minimum (computed from the dense ``P^T H P``), and with ``P = I``
    (``K`` = the longer side) ``a_1`` is the exact minimiser (``L(a_1) - L* <= 1e-9 |L*|``),
    which one PCG iteration without it is not."""
    p = quadratic_problem((10, 12))
    want, _, _, spd = _dense_correction(p, 5)
    assert spd
    l_coarse = float(p.loss(-want)[0])
    l_1 = float(p.loss(classical.solve_pcg(p, 1, coarse=5) - p.a_fixed)[0])
    assert l_1 <= l_coarse + 1e-12 * abs(l_coarse)
    exact, _, _, _ = _dense_correction(p, 12)
    l_star = float(p.loss(-exact)[0])
    l_full = float(p.loss(classical.solve_pcg(p, 1, coarse=12) - p.a_fixed)[0])
    assert l_full - l_star <= 1e-9 * abs(l_star)
    l_plain = float(p.loss(classical.solve_pcg(p, 1) - p.a_fixed)[0])
    assert l_plain - l_star > 1e-3 * abs(l_star)


def test_coarse_space_is_reused_every_k_calls_and_rebuilt_on_new_handles(monkeypatch):
    built = []
    real = twolevel.galerkin_space

    def spy(*args, **kw):
        built.append(1)
        return real(*args, **kw)

    monkeypatch.setattr(twolevel, "galerkin_space", spy)
    p = random_problem(10, F64, 0)
    mem = {}
    outs = [classical.solve_pcg(p, 3, coarse=4, coarse_every=3, memory=mem) for _ in range(4)]
    assert len(built) == 2                                  # calls 1 and 4
    assert torch.equal(outs[0], outs[1]) and torch.equal(outs[0], outs[3])
    q = random_problem(10, F64, 0, layout="diagonal")       # other handles: rebuilt
    classical.solve_pcg(q, 3, coarse=4, coarse_every=3, memory=mem)
    assert len(built) == 3
    # without memory: every call builds its own
    classical.solve_pcg(p, 3, coarse=4)
    assert len(built) == 4


def test_rollout_with_the_coarse_direction_is_stable():
    """32x32, diagonal handles, xyz motion at speed 1.5, 150 frames (2.5 s), PCG-n-8 + coarse
    8 rebuilt every 8 frames: every state finite, within 1.2 m of the handles' centroid (1 m
    sheet), no edge stretched beyond 1.3x its rest length."""
    sheet = Sheet(32, 32)
    mem = {}
    ro = solvers.rollout(sheet, Material(), "diagonal", "xyz", 150,
                         lambda p, a0: solvers.solve_pcg(p, 8, normal=True, split=4, coarse=8,
                                                         coarse_every=8, memory=mem),
                         speed=1.5)
    x = ro.positions
    assert bool(torch.isfinite(x).all())
    idx = cloth.handle_indices("diagonal", 32, 32)
    centre = x[:, idx[:, 0], idx[:, 1]].mean(1, keepdim=True)
    assert float((x.reshape(x.shape[0], -1, 3) - centre).norm(dim=-1).max()) < 1.2
    du = (x[:, 1:] - x[:, :-1]).norm(dim=-1) / float(sheet.hy)
    dv = (x[:, :, 1:] - x[:, :, :-1]).norm(dim=-1) / float(sheet.hx)
    assert float(torch.maximum(du.max(), dv.max())) < 1.3


def test_bad_coarse_options_get_clear_errors():
    p = random_problem(8, F64, 0)
    with pytest.raises(ValueError, match="coarse"):
        classical.solve_pcg(p, 2, coarse=1)
    with pytest.raises(ValueError, match="coarse"):
        classical.solve_pcg(p, 2, coarse=-3)
    with pytest.raises(TypeError, match="coarse"):
        classical.solve_pcg(p, 2, coarse=2.5)
    with pytest.raises(ValueError, match="coarse_every"):
        classical.solve_pcg(p, 2, coarse=4, coarse_every=0, memory={})
    with pytest.raises(ValueError, match="memory"):
        classical.solve_pcg(p, 2, coarse=4, coarse_every=2)
    _, g, hvp = p.grad_hvp(torch.zeros_like(p.x_prev))

    class NaNProducts:
        @staticmethod
        def many(ds):
            return torch.full((len(ds), *ds[0].shape), float("nan"), dtype=ds[0].dtype)

    with pytest.raises(ValueError, match="not finite"):
        twolevel.galerkin_space(p, NaNProducts, 4)


def test_simulate_pcg_with_coarse():
    """``polygeo simulate --optimizer pcg --coarse K``: the settings' step is the two-level
    solve (its coarse space kept across frames), not the plain one; optimisers other than pcg
    and fnopt refuse it; the reference's key does not depend on it."""
    from draping.fnopt.simulate import COARSE_EVERY, SimSettings, step_function

    s = SimSettings(res=(10, 12), optimizer="pcg", iters=3, coarse=4)
    p = random_problem(10, torch.float32, 4)
    mem = {}
    want = classical.solve_pcg(p, 3, normal=True, split=4, coarse=4,
                               coarse_every=COARSE_EVERY, memory=mem)
    assert torch.equal(step_function(s)(p, None), want)
    plain = step_function(SimSettings(res=(10, 12), optimizer="pcg", iters=3))(p, None)
    assert not torch.equal(plain, want)
    assert s.key() == SimSettings(res=(10, 12), optimizer="pcg", iters=3).key()
    for name in ("gd", "adam", "lbfgs", "reference"):
        with pytest.raises(ValueError, match="coarse"):
            SimSettings(optimizer=name, coarse=4)
    with pytest.raises(ValueError, match="coarse"):
        SimSettings(optimizer="pcg", coarse=1)


def test_simulate_fnopt_with_coarse():
    """``polygeo simulate --optimizer fnopt --coarse K [--coarse-every F] [--coarse-from J]``:
    over three frames of a rollout the settings' step is ``solve_fnopt(two_level=K,
    two_level_every=F, two_level_from=J)`` (defaults ``FNOPT_COARSE_EVERY`` and
    ``FNOPT_COARSE_FROM``) with one memory kept across the frames (so the coarse space is kept,
    not rebuilt per frame, unless F = 1), bit for bit; ``coarse=0`` is the one-level FNOpt
    solve; the reference's key depends on none of them; a bad K or F raises."""
    from fnopt_cases import tiny_fno

    from draping.fnopt import model
    from draping.fnopt.settings import FNOPT_COARSE_EVERY, FNOPT_COARSE_FROM
    from draping.fnopt.simulate import SimSettings, step_function

    net = tiny_fno(normal=True)
    s = SimSettings(res=(10, 12), optimizer="fnopt", iters=3, coarse=4)
    step, mem = step_function(s, net), {}
    probs = [random_problem(10, torch.float32, seed, layout="diagonal") for seed in (4, 5, 6)]
    for p in probs:
        want = model.solve_fnopt(net, p, 3, memory=mem, two_level=4,
                                 two_level_every=FNOPT_COARSE_EVERY,
                                 two_level_from=FNOPT_COARSE_FROM)
        assert torch.equal(step(p, None), want)
    s1 = SimSettings(res=(10, 12), optimizer="fnopt", iters=3, coarse=4, coarse_every=1,
                     coarse_from=0)
    step1, mem1 = step_function(s1, net), {}
    for p in probs:                              # --coarse-every 1: rebuilt every frame
        want = model.solve_fnopt(net, p, 3, memory=mem1, two_level=4, two_level_every=1)
        assert torch.equal(step1(p, None), want)
    assert s1.key() == s.key()
    off = step_function(SimSettings(res=(10, 12), optimizer="fnopt", iters=3, coarse=0), net)
    assert torch.equal(off(probs[0], None), model.solve_fnopt(net, probs[0], 3))
    assert not torch.equal(off(probs[0], None), model.solve_fnopt(net, probs[0], 3,
                                                                  two_level=4))
    assert s.key() == SimSettings(res=(10, 12), optimizer="fnopt", iters=3, coarse=0).key()
    with pytest.raises(ValueError, match="coarse"):
        SimSettings(optimizer="fnopt", coarse=1)
    with pytest.raises(ValueError, match="coarse_every"):
        SimSettings(optimizer="fnopt", coarse=4, coarse_every=0)


def test_fnopt_with_the_two_level_direction():
    """``solve_fnopt(two_level=K)``: off is the default solve bit for bit; on, with a zeroed
    FNO (proposal 0, so the learned step is the classical one), it is ``solve_pcg(coarse=K)``
    with the same classical directions, iterate by iterate (up to float rounding of the
    subspace solves: stated 1e-4 of the largest, float32); bad options raise."""
    from fnopt_cases import tiny_fno

    from draping.fnopt import model

    p = random_problem(12, torch.float32, 6, layout="diagonal")
    net = tiny_fno(normal=True, zero=True)
    split = net.config.normal_split
    assert torch.equal(model.solve_fnopt(net, p, 5, two_level=0), model.solve_fnopt(net, p, 5))
    got = model.solve_fnopt(net, p, 5, two_level=4)
    want = classical.solve_pcg(p, 5, normal=True, split=split, coarse=4)
    assert float((got - want).abs().max()) <= 1e-4 * float(want.abs().max())
    assert not torch.equal(got, model.solve_fnopt(net, p, 5))
    with pytest.raises(ValueError, match="two_level"):
        model.solve_fnopt(net, p, 2, two_level=1)
    with pytest.raises(ValueError, match="two_level"):
        model.solve_fnopt(net, p, 2, two_level=4, two_level_every=3)
    with pytest.raises(ValueError, match="two_level"):
        model.solve_fnopt(net, p, 2, step="line", two_level=4)


def test_two_level_from_delays_the_coarse_direction():
    """``solve_fnopt(two_level_from=j)``: 0 is the default two-level solve bit for bit; the
    iterations before ``j`` are the plain FNOpt iterations (so ``j >= iters`` is the plain solve
    bit for bit, the coarse space still built and kept in ``memory`` as with ``j = 0``); from
    ``j`` on the coarse direction joins (the result differs from both); bad values raise."""
    from fnopt_cases import tiny_fno

    from draping.fnopt import model

    p = random_problem(12, torch.float32, 6, layout="diagonal")
    net = tiny_fno(normal=True)
    on = model.solve_fnopt(net, p, 4, two_level=4)
    assert torch.equal(model.solve_fnopt(net, p, 4, two_level=4, two_level_from=0), on)
    plain = model.solve_fnopt(net, p, 4)
    for j in (4, 7):
        mem = {}
        got = model.solve_fnopt(net, p, 4, two_level=4, two_level_every=2, two_level_from=j,
                                memory=mem)
        assert torch.equal(got, plain)
        assert mem["coarse"][1] == 1                 # built at iteration 0, kept for the next
    assert torch.equal(model.solve_fnopt(net, p, 1, two_level=4, two_level_from=1),
                       model.solve_fnopt(net, p, 1))
    late = model.solve_fnopt(net, p, 4, two_level=4, two_level_from=1)
    assert torch.isfinite(late).all()
    assert not torch.equal(late, plain) and not torch.equal(late, on)
    with pytest.raises(ValueError, match="two_level_from"):
        model.solve_fnopt(net, p, 2, two_level=4, two_level_from=-1)
    with pytest.raises(ValueError, match="two_level_from"):
        model.solve_fnopt(net, p, 2, two_level_from=1)
    with pytest.raises(TypeError, match="two_level_from"):
        model.solve_fnopt(net, p, 2, two_level=4, two_level_from=1.0)
