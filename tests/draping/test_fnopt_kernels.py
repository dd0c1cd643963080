"""FNOpt's fused numba kernels (Hessian products, subspace Gram) against the torch functions."""

import pytest
import torch
from test_fnopt_hvp import _state

from draping.fnopt import cloth, model, solvers
from draping.fnopt.cloth import Material, Sheet
from draping.fnopt.handles import DT
from draping.fnopt.kernels import gram_fused, loss_hvp_fused

torch.set_num_threads(1)

F64 = torch.float64


def _args(p, a):
    return (p.compose(a), p.x_prev, p.v_prev, p.hx, p.hy, p.material, p.dt, p.mass)


@pytest.mark.parametrize("shape", [(7, 9), (5, 4), (3, 3), (16, 16)])
def test_fused_products_equal_the_torch_closed_form_in_float64(shape):
    p, a, dirs = _state(*shape)                   # two sheets, hx != hy, damping on one
    d = torch.stack(dirs)
    want = cloth.loss_hvp(d, *_args(p, a))
    got = loss_hvp_fused(d, *_args(p, a))
    assert got.dtype == F64 and got.shape == want.shape
    assert torch.allclose(got, want, rtol=1e-13, atol=1e-13 * float(want.abs().max()))
    one = loss_hvp_fused(dirs[1], *_args(p, a))      # a single direction (B, H, W, 3)
    assert torch.allclose(one, want[1], rtol=1e-13, atol=1e-13 * float(want.abs().max()))


def test_fused_products_have_each_term():
    """Stretch, shear, bend alone and inertia alone: each term, not only their sum, agrees."""
    p, a, dirs = _state(6, 7, seed=2)
    d = torch.stack(dirs)
    for name in ("stretch", "shear", "bend", "density"):
        mat = {k: (v if k in (name, "density") else torch.zeros_like(v))
               for k, v in p.material.items()}
        args = (p.compose(a), p.x_prev, p.v_prev, p.hx, p.hy, mat, p.dt, p.mass)
        want = cloth.loss_hvp(d, *args)
        got = loss_hvp_fused(d, *args)
        assert torch.allclose(got, want, rtol=1e-13, atol=1e-13 * float(want.abs().max()))


def test_float32_fused_products_agree_to_rounding():
    p, a, dirs = _state(16, 16, dtype=torch.float32)
    want = cloth.loss_hvp(torch.stack(dirs).double(), *_args(p, a.double()))
    got = loss_hvp_fused(torch.stack(dirs), *_args(p, a))
    assert got.dtype == torch.float32
    assert float((got.double() - want).norm() / want.norm()) < 1e-6


def test_fused_products_reject_bad_directions():
    p, a, dirs = _state(5, 6)
    with pytest.raises(ValueError, match="d: expected shape"):
        loss_hvp_fused(dirs[0][:, :4], *_args(p, a))
    z = torch.zeros(1, 2, 6, 3, dtype=F64)          # a 2 x 6 grid has no bending stencil
    with pytest.raises(ValueError, match="at least 3 x 3"):
        loss_hvp_fused(z, z, z, z, 0.1, 0.1, p.material, DT, torch.ones(1, 2, 6, dtype=F64))


def test_gram_equals_einsum_in_float64():
    gen = torch.Generator().manual_seed(4)
    dirs = [torch.randn(2, 6, 5, 3, generator=gen, dtype=F64) for _ in range(4)]
    hd = [torch.randn(2, 6, 5, 3, generator=gen, dtype=F64) for _ in range(4)]
    g = torch.randn(2, 6, 5, 3, generator=gen, dtype=F64)
    a, r = gram_fused(g, dirs, hd)
    want_a = torch.einsum("bihwc,bjhwc->bij", torch.stack(dirs, 1), torch.stack(hd, 1))
    want_r = -torch.einsum("bhwc,bihwc->bi", g, torch.stack(dirs, 1))
    assert torch.allclose(a, want_a, rtol=1e-13, atol=1e-13 * float(want_a.abs().max()))
    assert torch.allclose(r, want_r, rtol=1e-13, atol=1e-13 * float(want_r.abs().max()))
    a32, _ = gram_fused(g.float(), [d.float() for d in dirs], [h.float() for h in hd])
    assert a32.dtype == F64                          # float32 fields, float64 sums


def test_problem_uses_the_kernels_only_without_gradients():
    p, a, dirs = _state(7, 8, seed=1)
    _, _, hvp = p.grad_hvp(a)
    with torch.no_grad():
        fused = hvp.many(dirs)
    p.fused = False
    with torch.no_grad():
        plain = p.grad_hvp(a)[2].many(dirs)
    assert torch.allclose(fused, plain, rtol=1e-13, atol=1e-13 * float(plain.abs().max()))
    p.fused = True
    d = dirs[0].clone().requires_grad_(True)           # a differentiable direction: torch's
    out = p.grad_hvp(a)[2](d)
    assert out.requires_grad
    (gd,) = torch.autograd.grad(out.sum(), d)
    assert torch.isfinite(gd).all()


def _folding_state(dtype=F64):
    sheet = Sheet(12, 12)
    mat = Material()
    ro = solvers.rollout(sheet, mat, "diagonal", "rot-a", 5,
                         lambda p, a0: solvers.solve_pcg(p, 20), speed=1.5, dtype=F64)
    idx = cloth.handle_indices("diagonal", 12, 12)
    x = ro.positions[-2][None]
    v = (ro.positions[-2] - ro.positions[-3])[None] / DT
    tgt = ro.positions[-1][None][:, idx[:, 0], idx[:, 1]]
    return solvers.make_problem(x.to(dtype), v.to(dtype), idx, tgt.to(dtype), sheet.hx,
                                sheet.hy, mat.tensors(1, dtype))


def test_solves_with_the_kernels_match_torch_ones_in_float64():
    p = _folding_state()
    torch.manual_seed(0)
    net = model.FNO(model.FNOConfig(width=8, modes=4, layers=2, projection=16, normal=True,
                                    normal_split=2)).double()
    for solve in (lambda: model.solve_fnopt(net, p, 6),
                  lambda: solvers.solve_pcg(p, 8, normal=True, split=2)):
        p.fused = True
        got = solve()
        p.fused = False
        want = solve()
        assert torch.allclose(got, want, rtol=1e-9, atol=1e-9 * float(want.abs().max()))


def test_float32_fnopt_solve_with_the_kernels_is_as_good():
    """float32: the two paths round differently through ten guarded steps (stated tolerance:
    1e-3 relative in the solution, 1e-6 relative in L_cloth)."""
    p = _folding_state(torch.float32)
    net = model.load_pretrained()
    p.fused = True
    got = model.solve_fnopt(net, p, 10)
    p.fused = False
    want = model.solve_fnopt(net, p, 10)
    assert float((got - want).norm() / want.norm()) < 1e-3
    p.fused = True
    l_got, l_want = float(p.loss(got)[0]), float(p.loss(want)[0])
    assert abs(l_got - l_want) <= 1e-6 * abs(l_want)


@pytest.mark.parametrize("shape", [(2, 32, 32, 3), (1, 7, 5, 3), (1, 3, 9, 1)])
def test_low_modes_by_matrices_equal_the_full_dct(shape):
    from scipy.fft import dctn, idctn

    z = torch.randn(*shape, generator=torch.Generator().manual_seed(0), dtype=F64)
    c = dctn(z.numpy(), type=2, axes=(1, 2), norm="ortho")
    c[:, 4:] = 0.0
    c[:, :, 4:] = 0.0
    want = torch.from_numpy(idctn(c, type=2, axes=(1, 2), norm="ortho"))
    got = solvers.low_modes(z, 4)
    assert got.shape == z.shape and got.is_contiguous()
    assert torch.allclose(got, want, rtol=0, atol=1e-13 * float(z.abs().max()))


def test_fused_subspace_solve_equals_torch_one():
    """Gram by the kernel and the k x k solve in NumPy: torch's values, also with a zero
    direction, a repeated one and negative curvature (the shifted solve)."""
    gen = torch.Generator().manual_seed(6)
    g = torch.randn(2, 6, 5, 3, generator=gen, dtype=F64)
    d0 = torch.randn(2, 6, 5, 3, generator=gen, dtype=F64)
    d1 = torch.randn(2, 6, 5, 3, generator=gen, dtype=F64)
    dirs = [d0, d1, torch.zeros_like(d0), d0.clone()]
    for hd in ([2.0 * d for d in dirs],                                  # positive definite
               [2.0 * dirs[0], -3.0 * dirs[1], dirs[2], 2.0 * dirs[3]]):  # indefinite
        with torch.no_grad():
            (c, m), (cs, ms) = solvers.subspace_solve(g, dirs, hd, sub=2, fused=True)
            (c0, m0), (cs0, ms0) = solvers.subspace_solve(g, dirs, hd, sub=2)
        d = torch.stack(dirs, 1)
        # the step and the model value (how the repeated pair shares its weight is fixed only
        # by the 1e-12 shift, i.e. by rounding) and the other directions' coefficients
        for got, want in ((c, c0), (cs, cs0)):
            step, step0 = (torch.einsum("bi,bihwc->bhwc", cc, d) for cc in (got, want))
            assert torch.allclose(step, step0, rtol=1e-10, atol=1e-10 * float(step0.abs().max()))
            assert torch.allclose(got[:, 1:3], want[:, 1:3], rtol=1e-10, atol=1e-14)
        for got, want in ((m, m0), (ms, ms0)):
            assert got.dtype == F64 and got.shape == want.shape
            assert torch.allclose(got, want, rtol=1e-10, atol=0)
        assert float(c[:, 2].abs().max()) == 0.0                        # the zero direction
        assert bool((m <= 0).all())
    d = d0.clone().requires_grad_(True)           # a gradient needed: torch's path, differentiable
    (c, _), _ = solvers.subspace_solve(g, [d, d1], [2.0 * d, 2.0 * d1], sub=1, fused=True)
    assert c.requires_grad
