"""``polygeo simulate``'s classical optimisers and ``bm_fnopt``'s rows solve with the same
gradient (the fused closed form), and the benchmark's ``-autograd`` row names are all usable."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from fnopt_cases import random_problem

from draping.fnopt import classical
from draping.fnopt.simulate import SimSettings, step_function

F64 = torch.float64


@pytest.fixture(scope="module")
def bm(script):
    return script("benchmarks/bm_fnopt.py")


def _problem(n=9, dtype=torch.float32, seed=0):
    return random_problem(n, dtype, seed, layout="diagonal")


def test_simulate_cli_lbfgs_rollout_equals_the_benchmarks(bm, tmp_path):
    """The CLI's ``--optimizer lbfgs`` rollout is the benchmark's ``lbfgs`` row bit for bit
    (positions as written, float32, and per-frame L_cloth)."""
    from polygeo.cli import main
    from polygeo.io import read_mesh

    out = tmp_path / "sim"
    args = ["--res", "12", "--frames", "4", "--iters", "30", "--handles", "diagonal",
            "--motion", "xyz"]
    rc = main(["simulate", *args, "--optimizer", "lbfgs", "--no-reference", "-o", str(out),
               "--quiet", "--gif-every", "4"])
    assert rc in (0, None)
    s = SimSettings(res=(12, 12), frames=4, iters=30, handles="diagonal", motion="xyz",
                    optimizer="lbfgs")
    ro, err, _ = bm._rollout(s, bm._step("lbfgs", 30))
    assert err is None
    m = json.loads((out / "metrics.json").read_text())
    assert [r["L_cloth"] for r in m["frames"]] == ro.loss
    for k in range(5):
        got = np.asarray(read_mesh(out / "meshes" / f"{k:06d}.ply").points)
        assert np.array_equal(got, ro.positions[k].reshape(-1, 3).numpy()), k


@pytest.mark.parametrize("name", ["lbfgs", "gd", "adam"])
def test_simulate_classical_steps_take_the_fused_gradient(bm, name):
    """``simulate.step_function`` solves as ``bm_fnopt._step`` (fused) does, bit for bit, and
    not as the ``-autograd`` row does."""
    n = 6
    s = SimSettings(res=(9, 11), optimizer=name, iters=n, lr=1e-4 if name == "gd" else None)
    p = _problem()
    got = step_function(s)(p, None)
    want = bm._step(name, n, lr=s.lr)(_problem(), None)
    assert torch.equal(got, want)
    calls = []
    orig = classical.CLASSICAL[name]

    def spy(p, iters, **kw):
        calls.append(kw.get("fused_grad"))
        return orig(p, iters, **kw)

    try:
        classical.CLASSICAL[name] = spy
        step_function(s)(_problem(), None)
    finally:
        classical.CLASSICAL[name] = orig
    assert calls == [True]


@pytest.mark.parametrize("name", ["lbfgs-wolfe", "lbfgs-wolfe64"])
def test_strong_wolfe_autograd_rows_run(bm, name):
    """``lbfgs-wolfe-autograd`` / ``lbfgs-wolfe64-autograd`` (a TypeError before): the
    strong-Wolfe rows already use autograd's gradient, so they equal the plain rows."""
    got = bm._step(name + "-autograd", 4)(_problem(), None)
    want = bm._step(name, 4)(_problem(), None)
    assert torch.equal(got, want)


def test_strong_wolfe_fused_gradient_matches_autograd():
    p = _problem(dtype=F64)
    a = classical.solve_lbfgs_wolfe(p, 5, fused_grad=True)
    b = classical.solve_lbfgs_wolfe(_problem(dtype=F64), 5)
    assert torch.allclose(a, b, rtol=1e-9, atol=1e-9 * float(b.abs().max()))
    info = {}
    classical.solve_lbfgs_wolfe(_problem(), 3, float64=True, fused_grad=True, info=info)
    assert info["evaluations"] >= 3 and bool(torch.isfinite(info["residual"]).all())


@pytest.mark.parametrize("name", ["fnopt-autograd", "pcg-autograd", "pgd-autograd",
                                  "pcg-n-autograd"])
def test_rows_without_a_gradient_option_have_no_autograd_variant(bm, name):
    with pytest.raises(ValueError, match="no autograd variant"):
        bm._step(name, 3)


def test_curvature_bound_bounds_the_largest_eigenvalue():
    """Power iteration on the mass-metric Hessian ``M^-1 H / dt^2`` (closed-form products)
    stays below ``curvature_bound`` and within a factor of 3 of it."""
    from draping.fnopt.preconditioners import curvature_bound

    p = _problem(14, F64)
    _, _, hvp = p.grad_hvp(torch.zeros_like(p.x_prev))
    d = torch.randn(p.x_prev.shape, generator=torch.Generator().manual_seed(1), dtype=F64)
    d = d * p.free3
    lam = 0.0
    for _ in range(300):
        y = p.precondition(hvp(d)) * p.free3
        lam = float((y * d).sum() / (d * d).sum())
        d = y / y.norm()
    bound = float(curvature_bound(p)[0])
    assert bound / 3 < lam <= bound


def test_gd_default_step_is_stable_where_the_old_fixed_one_diverged():
    from draping.fnopt.simulate import run

    s = SimSettings(res=(32, 32), frames=4, optimizer="gd", iters=20, handles="diagonal",
                    motion="xyz")
    ro = run(s)                                    # default lr: the curvature bound's step
    assert all(np.isfinite(ro.loss)) and bool(torch.isfinite(ro.positions).all())
    with pytest.raises(ValueError, match="diverged"):
        run(SimSettings(res=(32, 32), frames=4, optimizer="gd", iters=20, lr=2e-3,
                        handles="diagonal", motion="xyz"))
    # GD lowers L_cloth below the zero-acceleration start on each step
    p = _problem(14)
    a = classical.solve_gd(p, 20, lr=None)
    assert float(p.loss(a)) < float(p.loss(torch.zeros_like(a)))


def test_simulate_cli_fnopt_coarse_every_reaches_the_solve(bm, tmp_path):
    """``polygeo simulate --optimizer fnopt --coarse 4 --coarse-every 1``: the rollout written is
    ``step_function(SimSettings(coarse=4, coarse_every=1))``'s bit for bit (shipped weights),
    and differs from the one rebuilt every ``COARSE_EVERY`` frames (the option is used)."""
    from polygeo.cli import main
    from polygeo.io import read_mesh

    out = tmp_path / "sim"
    args = ["--res", "12", "--frames", "4", "--iters", "3", "--handles", "diagonal",
            "--motion", "xyz"]
    rc = main(["simulate", *args, "--optimizer", "fnopt", "--coarse", "4", "--coarse-every",
               "1", "--no-reference", "-o", str(out), "--quiet", "--gif-every", "4"])
    assert rc in (0, None)
    kw = dict(res=(12, 12), frames=4, iters=3, handles="diagonal", motion="xyz",
              optimizer="fnopt", coarse=4)
    ro, err, _ = bm._rollout(SimSettings(**kw), step_function(SimSettings(**kw, coarse_every=1)))
    kept, _, _ = bm._rollout(SimSettings(**kw), step_function(SimSettings(**kw)))
    assert err is None
    got = np.stack([np.asarray(read_mesh(out / "meshes" / f"{k:06d}.ply").points)
                    for k in range(5)])
    assert np.array_equal(got, ro.positions.reshape(5, -1, 3).numpy())
    assert not np.array_equal(got, kept.positions.reshape(5, -1, 3).numpy())
