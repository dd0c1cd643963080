"""FNOpt's fused loss and gradient (:func:`draping.fnopt.kernels.loss_grad_fused`) against
autograd through :func:`draping.fnopt.cloth.energies`, and the inference solve that uses it."""

import pytest
import torch
from test_fnopt_hvp import _state

from draping.fnopt import cloth, kernels, model, solvers
from draping.fnopt.cloth import Material, Sheet

torch.set_num_threads(1)

F64 = torch.float64


def _autograd(a, x_prev, v_prev, hx, hy, material, dt, mass, consts=None):
    """The reference: ``L_cloth`` and its gradient by autograd (float64 when the inputs are);
    ``consts`` (the kernel's cached constants) ignored. Callable from an inference-mode solve
    (``solve_fnopt``): autograd runs on a normal copy of ``a``."""
    with torch.inference_mode(False), torch.enable_grad():
        a = a.detach().clone().requires_grad_(True)
        val = cloth.cloth_loss(a, x_prev, v_prev, hx, hy, material, dt, mass)
        (g,) = torch.autograd.grad(val.sum(), a)
    return val.detach(), g


def _args(p, a, material=None):
    return (p.compose(a), p.x_prev, p.v_prev, p.hx, p.hy,
            p.material if material is None else material, p.dt, p.mass)


def _close(got, want, rtol=1e-13):
    return torch.allclose(got, want, rtol=rtol, atol=rtol * float(want.abs().max()))


@pytest.mark.parametrize("shape", [(7, 9), (5, 4), (3, 3), (16, 16), (12, 5)])
@pytest.mark.parametrize("seed", [0, 1])
def test_fused_gradient_equals_autograd_in_float64(shape, seed):
    p, a, _ = _state(*shape, seed=seed)      # two sheets, hx != hy, damping on one, two handles
    val, g = kernels.loss_grad_fused(*_args(p, a))
    want_val, want_g = _autograd(*_args(p, a))
    assert val.dtype == F64 and g.shape == a.shape
    assert _close(g, want_g) and _close(val, want_val)
    pv, pg = p.grad_hvp(a)[:2]                               # the problem's fused path: free only
    assert _close(pg, want_g * p.free) and _close(pv, want_val)
    assert float(pg[:, 0, 0].abs().max()) == 0.0             # zero at the handles


def test_fused_gradient_has_each_term():
    """Stretch, shear, bend alone, and the external terms alone (gravity, damping, inertia)."""
    p, a, _ = _state(6, 7, seed=2)
    for name in ("stretch", "shear", "bend", "density"):
        mat = {k: (v if k in (name, "density", "damping") else torch.zeros_like(v))
               for k, v in p.material.items()}
        val, g = kernels.loss_grad_fused(*_args(p, a, mat))
        want_val, want_g = _autograd(*_args(p, a, mat))
        assert _close(g, want_g) and _close(val, want_val), name
    mat = {k: v for k, v in p.material.items() if k != "damping"}    # no damping entry
    val, g = kernels.loss_grad_fused(*_args(p, a, mat))
    want_val, want_g = _autograd(*_args(p, a, mat))
    assert _close(g, want_g) and _close(val, want_val)


def test_float32_fused_gradient_agrees_to_rounding():
    p, a, _ = _state(16, 12, seed=4, dtype=torch.float32)
    val, g = kernels.loss_grad_fused(*_args(p, a))
    want_val, want_g = _autograd(*[t.double() if isinstance(t, torch.Tensor) else t
                                   for t in _args(p, a)[:5]], p.material, p.dt, p.mass.double())
    assert g.dtype == torch.float32
    assert _close(g.double(), want_g, rtol=1e-6) and _close(val.double(), want_val, rtol=1e-6)


def test_fused_gradient_rejects_bad_input():
    p, a, _ = _state(5, 6)
    args = list(_args(p, a))
    with pytest.raises(ValueError, match="v_prev"):
        kernels.loss_grad_fused(args[0], args[1], args[2][:, :4], *args[3:])
    with pytest.raises(ValueError, match="mass"):
        kernels.loss_grad_fused(*args[:7], args[7][:, :4])
    z = torch.zeros(1, 2, 6, 3, dtype=F64)
    with pytest.raises(ValueError, match="3 x 3"):
        kernels.loss_grad_fused(z, z, z, 0.1, 0.1, p.material, p.dt, torch.ones(1, 2, 6,
                                                                                dtype=F64))


def _frame32():
    """A 32x32 corners/xy frame after a few PCG steps (float32 states)."""
    sheet = Sheet(32, 32)
    mat = Material()
    ro = solvers.rollout(sheet, mat, "corners", "xy", 4,
                         lambda p, a0: solvers.solve_pcg(p, 10), speed=1.5)
    idx = cloth.handle_indices("corners", 32, 32)
    x = ro.positions[-2][None]
    v = (ro.positions[-2] - ro.positions[-3])[None] / solvers.DT
    tgt = ro.positions[-1][None][:, idx[:, 0], idx[:, 1]]
    return solvers.make_problem(x, v, idx, tgt, sheet.hx, sheet.hy, mat.tensors(1))


def test_fnopt_solve_with_the_fused_gradient_equals_the_autograd_one(monkeypatch):
    """Shipped weights, N = 10, float32, 32x32: the fused gradient against autograd's (the
    products fused in both) -- the same solve up to float32 rounding (stated tolerance: 5e-4
    relative in the solution, 1e-8 relative in L_cloth; seen: 1.6e-4 and 2e-10, and each of
    the two float32 solves is 1.2-1.3e-4 from the float64 solve)."""
    p = _frame32()
    net = model.load_pretrained()
    got = model.solve_fnopt(net, p, 10)
    l_got = float(cloth.cloth_loss(got.double(), p.x_prev.double(), p.v_prev.double(),
                                   p.hx.double(), p.hy.double(),
                                   {k: v.double() for k, v in p.material.items()}, p.dt)[0])
    monkeypatch.setattr(kernels, "loss_grad_fused", _autograd)
    want = model.solve_fnopt(net, p, 10)
    l_want = float(cloth.cloth_loss(want.double(), p.x_prev.double(), p.v_prev.double(),
                                    p.hx.double(), p.hy.double(),
                                    {k: v.double() for k, v in p.material.items()}, p.dt)[0])
    assert float((got - want).norm() / want.norm()) < 5e-4
    assert abs(l_got - l_want) <= 1e-8 * abs(l_want)
