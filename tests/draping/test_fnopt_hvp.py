"""FNOpt's closed-form Hessian products and in-place FNO inference against autograd."""

import pytest
import torch

from draping.fnopt import cloth, model, solvers
from draping.fnopt.cloth import Material, Sheet
from draping.fnopt.handles import DT

torch.set_num_threads(1)

F64 = torch.float64


def _state(h=7, w=9, seed=0, dtype=F64, damping=(0.2, 0.0)):
    """Two deformed, moving sheets with different materials and spacings (hx != hy)."""
    gen = torch.Generator().manual_seed(seed)
    sheet = Sheet(h, w, 0.8)
    x = cloth.rest_positions(sheet, "vertical", F64)[None].repeat(2, 1, 1, 1)
    x = x + 0.05 * torch.randn(x.shape, generator=gen, dtype=F64)      # stretched and sheared
    v = torch.randn(x.shape, generator=gen, dtype=F64)
    mat = {"stretch": torch.tensor([300.0, 800.0]), "shear": torch.tensor([10.0, 3.0]),
           "bend": torch.tensor([1.0, 5.0]), "density": torch.tensor([0.1, 0.3]),
           "damping": torch.tensor(damping)}
    mat = {k: t.to(dtype) for k, t in mat.items()}
    hy = torch.tensor([sheet.hy, 1.3 * sheet.hy])
    idx = torch.tensor([[0, 0], [0, w - 1]])
    tgt = x[:, idx[:, 0], idx[:, 1]] + 0.01
    p = solvers.make_problem(x.to(dtype), v.to(dtype), idx, tgt.to(dtype), sheet.hx, hy, mat,
                             DT)
    a = 3.0 * torch.randn(x.shape, generator=gen, dtype=F64).to(dtype)
    dirs = [torch.randn(x.shape, generator=gen, dtype=F64).to(dtype) for _ in range(3)]
    return p, a, dirs


def _autograd_products(p, a, dirs):
    p.analytic_hvp = False
    try:
        _, g, hvp = p.grad_hvp(a)
        return g, torch.stack([hvp(d) for d in dirs])
    finally:
        p.analytic_hvp = True


@pytest.mark.parametrize("shape", [(7, 9), (5, 4), (16, 16)])
def test_closed_form_products_match_autograd_in_float64(shape):
    p, a, dirs = _state(*shape)
    g_ref, want = _autograd_products(p, a, dirs)
    p.fused = False
    assert torch.equal(p.grad_hvp(a)[1], g_ref)             # torch path: autograd's own gradient
    p.fused = True
    val, g, hvp = p.grad_hvp(a)                             # fused: the closed form, to rounding
    assert torch.allclose(g, g_ref, rtol=1e-13, atol=1e-13 * float(g_ref.abs().max()))
    got = hvp.many(dirs)
    assert got.shape == want.shape
    assert torch.allclose(got, want, rtol=1e-12, atol=1e-12 * float(want.abs().max()))
    for k, d in enumerate(dirs):                            # one direction at a time
        assert torch.allclose(hvp(d), got[k], rtol=1e-13, atol=0)


def test_closed_form_products_match_finite_differences_of_the_gradient():
    p, a, dirs = _state(6, 8, seed=3)
    _, _, hvp = p.grad_hvp(a)
    for d in dirs:
        eps = 1e-6
        fd = (p.loss_grad(a + eps * d * p.free)[1] - p.loss_grad(a - eps * d * p.free)[1]) / (
            2 * eps)
        assert torch.allclose(hvp(d), fd, rtol=1e-5, atol=1e-7 * float(fd.abs().max()))


def test_each_energy_term_has_its_curvature():
    """Per term (stretch, shear, bend alone; inertia + damping alone) against autograd."""
    gen = torch.Generator().manual_seed(5)
    x = torch.randn(1, 6, 7, 3, generator=gen, dtype=F64)
    d = torch.randn(2, 1, 6, 7, 3, generator=gen, dtype=F64)
    zero = torch.zeros_like(x)
    names = ("stretch", "shear", "bend")
    for name in names:
        mat = {n: torch.tensor([float(n == name)], dtype=F64) for n in names}
        xx = x.clone().requires_grad_(True)
        e = cloth.internal_energies(xx, 0.1, 0.12, mat)[name].sum()
        (g,) = torch.autograd.grad(e, xx, create_graph=True)
        want = torch.stack([torch.autograd.grad(g, xx, dk, retain_graph=True)[0] for dk in d])
        got = cloth.loss_hvp(d, zero, x, zero, 0.1, 0.12, mat, 1.0, torch.zeros(1, 6, 7, dtype=F64))
        assert float(want.norm()) > 0
        assert torch.allclose(got, want, rtol=1e-12, atol=1e-12 * float(want.abs().max()))
    # no stiffness: H = (dt^2 + c dt^3) M exactly; a missing damping entry counts as 0
    mat = {n: torch.zeros(1, dtype=F64) for n in names}
    mass = torch.rand(1, 6, 7, generator=gen, dtype=F64)
    got = cloth.loss_hvp(d, zero, x, zero, 0.1, 0.12, {**mat, "damping": torch.tensor([0.5])},
                         0.02, mass)
    assert torch.allclose(got, (0.02 ** 2 + 0.5 * 0.02 ** 3) * mass[..., None] * d, rtol=1e-14)
    got = cloth.loss_hvp(d, zero, x, zero, 0.1, 0.12, mat, 0.02, mass)
    assert torch.allclose(got, 0.02 ** 2 * mass[..., None] * d, rtol=1e-14)


def test_float32_products_agree_with_autograd_to_float_rounding():
    p, a, dirs = _state(16, 16, dtype=torch.float32)
    _, want = _autograd_products(p, a, dirs)
    got = p.grad_hvp(a)[2].many(dirs)
    assert float((got - want).norm() / want.norm()) < 1e-5


def test_an_extra_energy_falls_back_to_autograd():
    """Repulsion has no closed form here: its curvature must still be in the products."""
    p, a, dirs = _state(6, 6, seed=1)

    def extra(x):                       # a stiff, non-quadratic extra energy
        return 50.0 * (x[..., 2] ** 4).sum((1, 2))

    p.extra = extra
    _, _, hvp = p.grad_hvp(a)
    d = dirs[0]
    eps = 1e-6
    fd = (p.loss_grad(a + eps * d * p.free)[1] - p.loss_grad(a - eps * d * p.free)[1]) / (2 * eps)
    assert torch.allclose(hvp(d), fd, rtol=1e-5, atol=1e-7 * float(fd.abs().max()))
    p.extra = None
    assert not torch.allclose(p.grad_hvp(a)[2](d), fd, rtol=1e-3)   # the term matters here


def test_training_problems_keep_autograd_products():
    from draping.fnopt.train import Pool, TrainSettings

    s = TrainSettings(pool=2, batch=2)
    pool = Pool(s, torch.Generator().manual_seed(0))
    p, _ = pool.problem(torch.arange(2))
    assert p.analytic_hvp is False


@pytest.mark.parametrize("shape", [(1, 32, 32), (2, 20, 28)])
def test_in_place_inference_forward_equals_the_out_of_place_layers(shape):
    """The no-grad forward (in place, the 1x1 convolutions accumulated by ``baddbmm``, the
    spectral layers by DFT matrices) equals the layers written out, to float64 rounding, and
    does not write to its input."""
    torch.manual_seed(0)
    net = model.FNO(model.FNOConfig(width=8, modes=4, layers=3, projection=16)).double()
    b, h, w = shape
    x = torch.randn(b, model.N_INPUTS, h, w, dtype=torch.float64)
    x0 = x.clone()
    gelu = torch.nn.functional.gelu
    with torch.no_grad():
        got = net(x)
        y = net.lift(x)                               # the out-of-place layers, written out
        for k, (sp, pw) in enumerate(zip(net.spectral, net.pointwise)):
            y = sp(y) + pw(y)
            y = gelu(y) if k < len(net.spectral) - 1 else y
        want = net.proj2(gelu(net.proj1(y)))
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
    assert not torch.equal(got, torch.zeros_like(got))
    assert torch.equal(x, x0)                         # the input is not written to
    # with gradients: the same layers out of place (training), differentiable
    out = net(x.requires_grad_(True))
    out.sum().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all()


def test_solve_fnopt_with_closed_form_products_matches_autograd_ones():
    torch.manual_seed(0)
    net = model.FNO(model.FNOConfig(width=8, modes=4, layers=2, projection=16))
    sheet = Sheet(12, 12)
    mat = Material()
    ro = solvers.rollout(sheet, mat, "corners", "xy", 4,
                         lambda p, a0: solvers.solve_pgd(p, 10), speed=1.5, dtype=F64)
    idx = cloth.handle_indices("corners", 12, 12)
    x = ro.positions[-2][None]
    v = (ro.positions[-2] - ro.positions[-3])[None] / DT
    tgt = ro.positions[-1][None][:, idx[:, 0], idx[:, 1]]
    p = solvers.make_problem(x, v, idx, tgt, sheet.hx, sheet.hy, mat.tensors(1, F64))
    net = net.double()
    got = model.solve_fnopt(net, p, 6)
    p.analytic_hvp = False
    want = model.solve_fnopt(net, p, 6)
    assert torch.allclose(got, want, rtol=1e-9, atol=1e-9 * float(want.abs().max()))
