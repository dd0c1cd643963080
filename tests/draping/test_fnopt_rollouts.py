"""The rollout loop outside the solve: the per-frame ``L_cloth`` record
(``rollouts.energy_record``) and step problems built under ``torch.inference_mode``."""

from __future__ import annotations

import pytest
import torch
from fnopt_cases import random_problem

from draping.fnopt import classical, cloth
from draping.fnopt.cloth import Material, Sheet
from draping.fnopt.model import load_pretrained, solve_fnopt
from draping.fnopt.rollouts import energy_record, rollout
from draping.fnopt.step_problem import make_problem

torch.set_num_threads(1)

F64 = torch.float64


def _recorded_rollout(dtype, layout="diagonal", motion="xyz", repulsion=0.0, frames=5):
    """A PCG rollout of a damped 9 x 11 sheet, with every step's ``(x_prev, v_prev, a)``."""
    sheet, mat = Sheet(9, 11), Material(damping=0.3)
    steps = []

    def step(p, a0):
        a = classical.solve_pcg(p, 4)
        steps.append((p.x_prev.clone(), p.v_prev.clone(), a.clone()))
        return a

    ro = rollout(sheet, mat, layout, motion, frames, step, speed=1.5, dtype=dtype,
                 repulsion=repulsion)
    return sheet, mat, cloth.handle_indices(layout, 9, 11), ro, steps


@pytest.mark.parametrize("dtype,repulsion", [(torch.float32, 0.0), (F64, 0.0),
                                             (torch.float32, 1e-3)])
def test_the_record_is_the_float64_problems_l_cloth(dtype, repulsion):
    """Each frame's recorded L_cloth is the float64 problem's loss of that frame's solution
    (torch's energies, the record before session 15) to 1e-12 relative; without repulsion."""
    sheet, mat, idx, ro, steps = _recorded_rollout(dtype, repulsion=repulsion)
    assert len(ro.loss) == len(steps) == 5
    for f, (x, v, a) in enumerate(steps, start=1):
        target = ro.positions[f][idx[:, 0], idx[:, 1]][None]       # the handles' exact targets
        p64 = make_problem(x.double(), v.double(), idx, target.double(), sheet.hx, sheet.hy,
                           mat.tensors(1, F64))
        want = float(p64.loss(a.double())[0])
        assert ro.loss[f - 1] == pytest.approx(want, rel=1e-12, abs=1e-14)


def test_the_record_takes_the_handles_accelerations_from_their_targets():
    """What ``a`` holds at the handles does not matter (the problem's ``compose``); elsewhere
    it does."""
    p = random_problem(8, F64, 2, layout="corner-centre")
    idx = cloth.handle_indices("corner-centre", 8, 10)
    sheet, mat = Sheet(8, 10), Material(damping=0.3)
    target = p.x_prev[:, idx[:, 0], idx[:, 1]] + 1e-3
    rec = energy_record(sheet, mat, idx)
    a = torch.randn(p.x_prev.shape, generator=torch.Generator().manual_seed(1), dtype=F64)
    b = a.clone()
    b[:, idx[:, 0], idx[:, 1]] = 1e3
    assert rec(a, p.x_prev, p.v_prev, target) == rec(b, p.x_prev, p.v_prev, target)
    b[:, 3, 3] += 1.0
    assert rec(b, p.x_prev, p.v_prev, target) != rec(a, p.x_prev, p.v_prev, target)


def test_rollout_positions_are_the_plain_loop_bit_for_bit():
    """The rollout's states are those of the plain loop (problem, solve, advance): the record
    outside the solve changes nothing in them."""
    sheet, mat, idx, ro, _ = _recorded_rollout(torch.float32, layout="mid-edges", motion="rot-a")
    x = cloth.rest_positions(sheet, "vertical", F64)[None].float()
    v = torch.zeros_like(x)
    for f in range(1, 6):
        target = ro.handles[f][None].float()
        p = make_problem(x, v, idx, target, sheet.hx, sheet.hy, mat.tensors(1))
        x, v = cloth.advance(classical.solve_pcg(p, 4), x, v, p.dt, idx, target)
        assert torch.equal(x[0], ro.positions[f])


def _args(dtype=torch.float32):
    p = random_problem(8, F64, 5, layout="diagonal")
    idx = cloth.handle_indices("diagonal", 8, 10)
    tgt = p.x_prev[:, idx[:, 0], idx[:, 1]] + 1e-3
    mat = {k: t.to(dtype) for k, t in p.material.items()}
    return (p.x_prev.to(dtype), p.v_prev.to(dtype), idx, tgt.to(dtype), Sheet(8, 10).hx,
            Sheet(8, 10).hy, mat)


def test_make_problem_in_inference_mode_is_the_plain_problem():
    """Built under ``torch.inference_mode`` (or from tensors made in it) the problem holds
    normal tensors and solves bit for bit as the plain one: FNOpt, fused and autograd L-BFGS,
    and autograd's gradient outside that mode (failed before: free3's version counter)."""
    args = _args()
    plain = make_problem(*args)
    with torch.inference_mode():
        inside = make_problem(*args)
        made = [t.clone() if isinstance(t, torch.Tensor) else t for t in args[:2]]
        loss_inside = inside.loss(torch.zeros_like(args[0]))
    from_inference = make_problem(*made, *args[2:])
    net = load_pretrained(None)
    a0 = torch.zeros_like(args[0])
    for p in (inside, from_inference):
        for name in ("x_prev", "v_prev", "hx", "hy", "free", "a_fixed", "mass"):
            t = getattr(p, name)
            assert not t.is_inference() and torch.equal(t, getattr(plain, name)), name
        assert all(not t.is_inference() for t in p.material.values())
        assert torch.equal(solve_fnopt(net, p, 3), solve_fnopt(net, plain, 3))
        assert torch.equal(classical.solve_lbfgs(p, 4), classical.solve_lbfgs(plain, 4))
        assert torch.equal(classical.solve_lbfgs(p, 4, fused_grad=True),
                           classical.solve_lbfgs(plain, 4, fused_grad=True))
        assert torch.equal(p.loss_grad(a0)[1], plain.loss_grad(a0)[1])
    assert torch.equal(loss_inside, plain.loss(a0))
    with torch.inference_mode():                  # a solve inside the mode works too
        assert torch.equal(solve_fnopt(net, inside, 3), solve_fnopt(net, plain, 3))
