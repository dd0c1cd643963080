"""Autograd-free solves under ``torch.inference_mode`` (``step_problem.autograd_free_call``, the
one home of the rule) for every optimiser of ``polygeo simulate``, and its ``pcg`` optimiser."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from fnopt_cases import random_problem

from draping.fnopt import classical, cloth
from draping.fnopt.settings import OPTIMIZERS
from draping.fnopt.simulate import PCG_NORMAL_SPLIT, SimSettings, run, step_function
from draping.fnopt.step_problem import StepProblem, autograd_free_call

torch.set_num_threads(1)


def _rollout(name: str, **kw):
    s = SimSettings(res=(8, 10), frames=4, optimizer=name, iters=3, handles="diagonal",
                    motion="xyz", **kw)
    return run(s)


@pytest.mark.parametrize("name", OPTIMIZERS)
def test_every_optimiser_rolls_out_bit_for_bit_as_without_inference_mode(name, monkeypatch):
    """The rollout (positions and per-frame float64 L_cloth) is the one computed with
    autograd's bookkeeping on everywhere (``autograd_free`` forced false); the solvers that may
    run in inference mode do, and return normal tensors."""
    seen = []
    grad_hvp, loss_grad = StepProblem.grad_hvp, StepProblem.loss_grad

    def spy(fn):
        def f(self, *a, **k):
            seen.append(torch.is_inference_mode_enabled())
            return fn(self, *a, **k)
        return f

    monkeypatch.setattr(StepProblem, "grad_hvp", spy(grad_hvp))
    monkeypatch.setattr(StepProblem, "loss_grad", spy(loss_grad))
    fast = _rollout(name)
    used = any(seen)
    monkeypatch.setattr(StepProblem, "autograd_free", lambda self: False)
    seen.clear()
    plain = _rollout(name)
    assert not any(seen)
    assert torch.equal(fast.positions, plain.positions) and fast.loss == plain.loss
    assert not fast.positions.is_inference()
    assert used == (name != "reference")        # the reference solves with autograd's gradient


def test_the_classical_solvers_use_inference_mode_only_where_no_autograd_is_needed():
    p = random_problem(9, torch.float32, 3, layout="diagonal")
    assert p.autograd_free()
    calls = []

    def record(fn):
        def f(*a, **k):
            calls.append(torch.is_inference_mode_enabled())
            return fn(*a, **k)
        return f

    p.loss_grad = record(p.loss_grad)
    p.grad_hvp = record(p.grad_hvp)
    cases = [(classical.solve_lbfgs, {"fused_grad": True}, True),
             (classical.solve_lbfgs, {}, False),            # autograd's gradient
             (classical.solve_gd, {"fused_grad": True}, True),
             (classical.solve_adam, {"fused_grad": False}, False),
             (classical.solve_pcg, {"normal": True, "split": 2}, True),
             (classical.solve_pgd, {}, True),
             (classical.solve_lbfgs_wolfe, {"fused_grad": True}, False)]   # torch.optim
    for fn, kw, want in cases:
        calls.clear()
        info = {} if fn is classical.solve_lbfgs else None
        a = fn(p, 3, **kw) if info is None else fn(p, 3, info=info, **kw)
        assert calls and set(calls) == {want}, (fn.__name__, kw)
        assert not a.is_inference()
        if info is not None:
            assert not info["residual"].is_inference()
        a.add_(1.0)                                  # the caller may change it in place


def test_autograd_free_call_keeps_autograd_where_the_problem_needs_it():
    p = random_problem(7, torch.float64, 4)
    p.fused = False
    assert not p.autograd_free()
    assert not autograd_free_call(p, torch.is_inference_mode_enabled)
    q = random_problem(7, torch.float64, 4)
    assert autograd_free_call(q, torch.is_inference_mode_enabled)
    assert not autograd_free_call(q, torch.is_inference_mode_enabled, enabled=False)


def test_pcg_is_fnopts_classical_step_with_the_shipped_split():
    """``optimizer="pcg"``: ``solve_pcg(normal=True, split=PCG_NORMAL_SPLIT)``, the split of the
    shipped weights' normal directions; it lowers L_cloth below the zero-acceleration start."""
    from draping.fnopt.model import load_pretrained

    assert load_pretrained().config.normal_split == PCG_NORMAL_SPLIT
    p = random_problem(12, torch.float32, 5, layout="diagonal")
    got = step_function(SimSettings(res=(12, 14), optimizer="pcg", iters=6))(p, None)
    want = classical.solve_pcg(random_problem(12, torch.float32, 5, layout="diagonal"), 6,
                               normal=True, split=PCG_NORMAL_SPLIT)
    assert torch.equal(got, want)
    assert not torch.equal(got, classical.solve_pcg(p, 6))       # the normal directions count
    zero = p.compose(torch.zeros_like(p.x_prev))
    assert float(p.loss(got)[0]) < float(p.loss(zero)[0])
    more = step_function(SimSettings(res=(12, 14), optimizer="pcg", iters=12))(p, None)
    assert float(p.loss(more)[0]) <= float(p.loss(got)[0]) + 1e-6 * abs(float(p.loss(got)[0]))


def test_simulate_pcg_rollout_is_finite_and_holds_its_handles():
    s = SimSettings(res=(10, 12), frames=12, optimizer="pcg", iters=8, handles="corner-centre",
                    motion="rot-a", speed=2.0)
    ro = run(s)
    assert bool(torch.isfinite(ro.positions).all()) and all(np.isfinite(ro.loss))
    assert float(ro.positions.abs().max()) < 3.0
    idx = cloth.handle_indices("corner-centre", 10, 12)
    got = ro.positions[:, idx[:, 0], idx[:, 1]].double()
    assert torch.allclose(got, ro.handles.double(), atol=1e-5)


def test_simulate_cli_runs_pcg(tmp_path):
    import json

    from polygeo.cli import main

    out = tmp_path / "pcg"
    rc = main(["simulate", "--res", "8", "--frames", "3", "--iters", "4", "--optimizer", "pcg",
               "--no-reference", "--quiet", "-o", str(out)])
    assert rc in (0, None)
    m = json.loads((out / "metrics.json").read_text())
    assert m["settings"]["optimizer"] == "pcg" and len(m["frames"]) == 3
    with pytest.raises(SystemExit):
        main(["simulate", "--optimizer", "pcg-n", "-o", str(tmp_path / "x")])


def test_simulate_cli_loads_trained_weights(tmp_path):
    """``--weights`` runs the given FNO: a zeroed copy of the shipped one changes the rollout."""
    import json
    import shutil

    from draping.fnopt.model import WEIGHTS
    from polygeo.cli import main

    zero = tmp_path / "run" / "fnopt_model.pt"
    zero.parent.mkdir()
    sd = torch.load(WEIGHTS, weights_only=True)
    torch.save({k: torch.zeros_like(v) for k, v in sd.items()}, zero)
    shutil.copy(WEIGHTS.with_suffix(".json"), zero.with_suffix(".json"))
    args = ["simulate", "--res", "8", "--frames", "3", "--iters", "3", "--no-reference",
            "--quiet"]
    assert main(args + ["-o", str(tmp_path / "shipped")]) in (0, None)
    assert main(args + ["--weights", str(WEIGHTS), "-o", str(tmp_path / "same")]) in (0, None)
    assert main(args + ["--weights", str(zero), "-o", str(tmp_path / "zero")]) in (0, None)
    m = {k: json.loads((tmp_path / k / "metrics.json").read_text())
         for k in ("shipped", "same", "zero")}
    assert m["shipped"]["weights"] is None and m["zero"]["weights"].endswith("fnopt_model.pt")
    loss = {k: [f["L_cloth"] for f in v["frames"]] for k, v in m.items()}
    assert loss["same"] == loss["shipped"]
    assert loss["zero"] != loss["shipped"]
    assert main(args + ["--weights", str(tmp_path / "missing.pt"), "-o",
                        str(tmp_path / "x")]) not in (0, None)
    assert main(args + ["--optimizer", "pcg", "--weights", str(WEIGHTS), "-o",
                        str(tmp_path / "y")]) not in (0, None)
