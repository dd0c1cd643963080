"""FNOpt's inference fast paths (session 12) against the reference arithmetic.

The FNO's inference forward (1x1 convolutions as batched products, the spectral inverse
transform accumulated into the pointwise path) against the training forward; the training
forward and its gradients against an independent re-implementation of the pre-session one;
the kernels' cached per-problem constants; the DCT solves by matrices against ``scipy.fft``;
the classical solvers' fused-gradient option; a 32x32 solve with and without the kernels.
"""

import math

import numpy as np
import pytest
import torch
from fnopt_cases import random_problem
from torch import nn

from draping.fnopt import cloth, model, preconditioners, solvers
from draping.fnopt.cloth import Material, Sheet
from draping.fnopt.handles import DT

torch.set_num_threads(1)

F64 = torch.float64


def _net(dtype, width=16, modes=8, layers=4, projection=64, seed=0):
    torch.manual_seed(seed)
    net = model.FNO(model.FNOConfig(width=width, modes=modes, layers=layers,
                                    projection=projection)).to(dtype)
    with torch.no_grad():
        for q in net.parameters():
            q.normal_(0.0, 0.3)
    return net


@pytest.mark.parametrize("dtype,rtol", [(F64, 1e-12), (torch.float32, 2e-5)])
@pytest.mark.parametrize("shape", [(1, 32, 32), (2, 64, 48), (1, 33, 20), (3, 7, 5)])
def test_inference_forward_equals_the_training_forward(dtype, rtol, shape):
    b, h, w = shape
    net = _net(dtype)
    x = torch.randn(b, model.N_INPUTS, h, w, generator=torch.Generator().manual_seed(1),
                    dtype=F64).to(dtype)
    full = net(x).detach()                             # gradients on: FFTs, Conv2d
    with torch.no_grad():
        infer = net(x)
    assert infer.shape == (b, 3, h, w) and infer.dtype == dtype
    assert float(full.abs().max()) > 1e-3
    err = float((infer.double() - full.double()).abs().max() / full.double().abs().max())
    assert err < rtol


def _reference_forward(net: model.FNO, x: torch.Tensor) -> torch.Tensor:
    """The training forward as it was before session 12, written out independently."""

    def spectral(sp, y):
        bb, _, h, w = y.shape
        f = torch.fft.rfft2(y)
        m1, m2 = min(sp.modes, h // 2), min(sp.modes, w // 2 + 1)
        out = torch.zeros(bb, sp.w.shape[2], h, w // 2 + 1, dtype=f.dtype)
        wc = torch.view_as_complex(sp.w)
        out[:, :, :m1, :m2] = torch.einsum("bixy,ioxy->boxy", f[:, :, :m1, :m2],
                                           wc[0, :, :, :m1, :m2])
        out[:, :, h - m1:, :m2] = torch.einsum("bixy,ioxy->boxy", f[:, :, h - m1:, :m2],
                                               wc[1, :, :, :m1, :m2])
        return torch.fft.irfft2(out, s=(h, w))

    def conv(c, y):
        return nn.functional.conv2d(y, c.weight, c.bias)

    y = conv(net.lift, x)
    for k, (sp, pw) in enumerate(zip(net.spectral, net.pointwise)):
        y = spectral(sp, y) + conv(pw, y)
        if k < len(net.spectral) - 1:
            y = nn.functional.gelu(y)
    return conv(net.proj2, nn.functional.gelu(conv(net.proj1, y)))


@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_training_forward_and_gradients_are_unchanged(dtype):
    net = _net(dtype, seed=3)
    x = torch.randn(2, model.N_INPUTS, 20, 17, generator=torch.Generator().manual_seed(4),
                    dtype=F64).to(dtype)
    out = net(x)
    grads = torch.autograd.grad((out * out).sum(), list(net.parameters()))
    ref = _reference_forward(net, x)
    ref_grads = torch.autograd.grad((ref * ref).sum(), list(net.parameters()))
    assert torch.equal(out, ref)
    for g, r in zip(grads, ref_grads):
        assert torch.equal(g, r)


def test_training_forward_passes_gradcheck():
    net = _net(F64, width=3, modes=2, layers=2, projection=4, seed=5)
    x = torch.randn(1, model.N_INPUTS, 6, 5, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: net(t), (x,), eps=1e-6, atol=1e-6)


@pytest.mark.parametrize("k,j,kept", [(0, 0, True), (1, 2, True), (2, 1, True), (10, 1, True),
                                        (9, 2, True), (3, 1, False), (1, 3, False),
                                        (8, 0, False), (0, 4, False)])
def test_spectral_layer_passes_exactly_the_kept_modes(k, j, kept):
    # analytic truth: with unit weights the layer projects onto its kept Fourier modes (rows
    # 0..m1-1 and H-m1..H-1, columns 0..m2-1), so a plane wave at a kept frequency comes out
    # unchanged and one at a dropped frequency comes out zero; both transforms (FFT and the
    # interleaved DFT matrices) and both directions of the wave (cos and sin)
    h, w = 12, 10
    conv = model.SpectralConv2d(1, 1, 3).double()
    with torch.no_grad():
        conv.w.zero_()
        conv.w[..., 0] = 1.0
    yy, xx = torch.meshgrid(torch.arange(h, dtype=F64), torch.arange(w, dtype=F64),
                            indexing="ij")
    phase = 2 * math.pi * (k * yy / h + j * xx / w)
    x = torch.stack([torch.cos(phase), torch.sin(phase)])[:, None]       # (2, 1, H, W)
    want = x if kept else torch.zeros_like(x)
    fft = conv(x).detach()
    with torch.no_grad():
        dft = conv.forward_dft(x)
        acc = conv.forward_dft(x, acc=torch.zeros_like(x))
    for got in (fft, dft, acc):
        assert torch.allclose(got, want, rtol=0, atol=1e-12)


def test_spectral_accumulation_adds_in_place():
    torch.manual_seed(6)
    conv = model.SpectralConv2d(3, 4, 4).double()
    x = torch.randn(2, 3, 12, 10, dtype=F64)
    acc = torch.randn(2, 4, 12, 10, dtype=F64)
    with torch.no_grad():
        want = conv.forward_dft(x) + acc
        got = conv.forward_dft(x, acc=acc)
    assert got is acc
    assert torch.allclose(got, want, rtol=0, atol=1e-13 * float(want.abs().max()))


def _problem(n=9, dtype=F64, seed=0):
    return random_problem(n, dtype, seed, layout="corners")


def test_kernel_constants_are_built_once_and_follow_material_changes():
    p = _problem()
    a = 0.1 * torch.randn(p.x_prev.shape, generator=torch.Generator().manual_seed(1), dtype=F64)
    first = p._kernel_constants()
    assert p._kernel_constants() is first
    val, g = p.loss_grad(a, fused=True)
    want_val, want_g = p.loss_grad(a)                  # autograd
    assert torch.allclose(val, want_val, rtol=1e-13, atol=0)
    assert torch.allclose(g, want_g, rtol=1e-13, atol=1e-13 * float(want_g.abs().max()))
    p.material["stretch"].mul_(2.0)                     # in place: rebuilt, not stale
    assert p._kernel_constants() is not first
    val2, g2 = p.loss_grad(a, fused=True)
    want_val2, want_g2 = p.loss_grad(a)
    assert not torch.allclose(g2, g)
    assert torch.allclose(g2, want_g2, rtol=1e-13, atol=1e-13 * float(want_g2.abs().max()))
    p.material = {**p.material, "bend": p.material["bend"] * 3.0}     # replaced: rebuilt
    _, g3 = p.loss_grad(a, fused=True)
    assert torch.allclose(g3, p.loss_grad(a)[1], rtol=1e-13, atol=1e-13 * float(g3.abs().max()))


def test_fused_gradient_option_falls_back_where_the_kernel_does_not_apply():
    p = _problem()
    p.extra = lambda x: (x[..., 2] ** 2).sum((1, 2))   # an extra energy: autograd
    a = torch.zeros_like(p.x_prev)
    evals = p.evals
    val, g = p.loss_grad(a, fused=True)
    want_val, want_g = p.loss_grad(a)
    assert torch.equal(val, want_val) and torch.equal(g, want_g)
    assert p.evals == evals + 2


@pytest.mark.parametrize("shape", [(2, 7, 5), (1, 32, 32), (2, 33, 20, 3), (1, 12, 14, 1)])
def test_dct_solve_by_matrices_equals_scipy(shape):
    from scipy.fft import dctn, idctn

    rng = np.random.default_rng(0)
    z = rng.standard_normal(shape)
    den = rng.random(shape[:3]) + 0.5
    d = den if len(shape) == 3 else den[..., None]
    want = idctn(dctn(z, type=2, axes=(1, 2), norm="ortho") / d, type=2, axes=(1, 2),
                 norm="ortho")
    got = preconditioners._dct_solve(z, den)
    assert got.shape == want.shape and got.flags.c_contiguous
    assert np.abs(got - want).max() <= 1e-13 * np.abs(want).max()


@pytest.mark.parametrize("name,kw", [("lbfgs", {"iters": 30}), ("gd", {"iters": 10, "lr": 2e-3}),
                                     ("adam", {"iters": 10, "lr": 0.1})])
def test_classical_solvers_with_the_fused_gradient_equal_autograd_ones(name, kw):
    p = _problem(12)
    fn = solvers.CLASSICAL[name]
    got = fn(p, fused_grad=True, **kw)
    want = fn(p, **kw)
    assert bool(torch.isfinite(want).all())
    assert float((got - want).abs().max()) <= 1e-9 * float(want.abs().max())
    assert not torch.equal(got, p.compose(torch.zeros_like(got)))   # it moved


def _state_32(dtype):
    sheet, mat = Sheet(32, 32), Material()
    ro = solvers.rollout(sheet, mat, "corners", "xy", 4,
                         lambda p, a0: solvers.solve_pcg(p, 20), dtype=F64)
    idx = cloth.handle_indices("corners", 32, 32)
    x = ro.positions[-2][None]
    v = (ro.positions[-2] - ro.positions[-3])[None] / DT
    tgt = ro.positions[-1][None][:, idx[:, 0], idx[:, 1]]
    return solvers.make_problem(x.to(dtype), v.to(dtype), idx, tgt.to(dtype), sheet.hx,
                                sheet.hy, mat.tensors(1, dtype))


def test_32x32_shipped_solve_with_the_fast_paths_equals_the_torch_one():
    """float64 (the shipped weights cast): the kernels, the numba subspace solve and the FNO's
    inference forward against torch's closed forms, autograd and the same weights; 10
    guarded iterations, equal to rounding."""
    if not model.WEIGHTS.is_file():
        pytest.skip("no shipped FNOpt weights")
    net = model.load_pretrained().double()
    p = _state_32(F64)
    p.fused = True
    got = model.solve_fnopt(net, p, 10)
    p.fused = False
    want = model.solve_fnopt(net, p, 10)
    assert math.isfinite(float(want.abs().max()))
    assert torch.allclose(got, want, rtol=1e-9, atol=1e-9 * float(want.abs().max()))


def test_benchmark_gives_the_classical_rows_the_fused_gradient(monkeypatch, script):
    """``bm_fnopt._step``: ``lbfgs`` (and GD, Adam, our L-BFGS variants) with the fused
    gradient, ``<name>-autograd`` with autograd's; the strong-Wolfe rows unchanged."""
    bm = script("benchmarks/bm_fnopt.py")
    seen = []

    def spy(name):
        def f(p, n, **kw):
            seen.append((name, kw.get("fused_grad")))
            return p.x_prev
        return f

    for name in ("solve_lbfgs", "solve_gd", "solve_adam", "solve_lbfgs_wolfe"):
        monkeypatch.setattr(solvers, name, spy(name))
    monkeypatch.setitem(solvers.CLASSICAL, "gd", spy("solve_gd"))
    monkeypatch.setitem(solvers.CLASSICAL, "adam", spy("solve_adam"))
    monkeypatch.setitem(bm.LBFGS_NAMED, "lbfgs-pre", (solvers.solve_lbfgs, {"history": 20}))
    p = _problem()
    for name in ("lbfgs", "lbfgs-autograd", "gd", "adam-autograd", "lbfgs-pre", "lbfgs-wolfe"):
        bm._step(name, 3)(p, None)
    assert seen == [("solve_lbfgs", True), ("solve_lbfgs", False), ("solve_gd", True),
                    ("solve_adam", False), ("solve_lbfgs", True), ("solve_lbfgs_wolfe", None)]


def test_free3_is_the_expanded_mask_and_follows_changes():
    p = _problem()
    f3 = p.free3
    assert f3.shape == p.free.shape[:-1] + (3,) and f3.is_contiguous()
    assert torch.equal(f3, p.free.expand_as(f3))
    assert p.free3 is f3                                   # cached
    a = torch.randn(p.x_prev.shape, generator=torch.Generator().manual_seed(2), dtype=F64)
    assert torch.equal(p.compose(a), a * p.free + p.a_fixed)
    p.free[0, 0, 1, 0] = 0.0                               # in place: rebuilt
    assert float(p.free3[0, 0, 1].abs().sum()) == 0.0
    p.free = torch.ones_like(p.free)                       # replaced: rebuilt
    assert bool((p.free3 == 1).all())


def test_free_rms_is_one_rms_for_both_grids():
    """``free_rms`` (the one home of ``StepProblem.residual_rms`` and ``coarse.free_rms``):
    analytic values with a 1- or 3-channel mask, 0 without free vertices."""
    from draping.fnopt import coarse
    from draping.fnopt.step_problem import free_rms

    assert coarse.free_rms is free_rms
    free = torch.zeros(1, 4, 5, 1)
    free[0, 1:3, 1:4] = 1.0                                   # 6 free vertices
    f = torch.full((2, 4, 5, 3), 7.0)
    f[1] = 0.0
    f[1, 1:3, 1:4] = torch.tensor([1.0, 2.0, 2.0])            # each free vertex: |.|^2 = 9
    f[1, 0, 0] = 100.0                                        # at a handle: ignored
    want = torch.tensor([7.0, math.sqrt(9.0 / 3)])
    assert torch.allclose(free_rms(f, free), want, rtol=1e-6)
    assert torch.equal(free_rms(f, free.expand(1, 4, 5, 3).contiguous()), free_rms(f, free))
    assert torch.equal(free_rms(f, torch.zeros_like(free)), torch.zeros(2))
    p = _problem()
    r = torch.randn(p.x_prev.shape, generator=torch.Generator().manual_seed(3), dtype=F64)
    n = float(p.free.sum()) * 3
    assert torch.allclose(p.residual_rms(r), ((r * p.free) ** 2).sum((1, 2, 3)).div(n).sqrt())


def _solve_pair(net, p, **kw):
    """``solve_fnopt`` (inference mode where it applies) and the same solve without it."""
    mem_a, mem_b = {}, {}
    fast = model.solve_fnopt(net, p, 6, memory=mem_a if kw.get("recycle") else None, **kw)
    args = dict(a0=None, step="subspace", guard=True, info=None, coarse_res=0, stiffness_res=0,
                recycle=0, memory=mem_b if kw.get("recycle") else None, fno_every=1)
    args.update(kw)
    with torch.no_grad():
        plain = model._solve(net, p, 6, *args.values())
    return fast, plain, mem_a, mem_b


@pytest.mark.parametrize("kw", [{}, {"fno_every": 2}, {"coarse_res": 5}, {"recycle": 3},
                                {"step": "line"}])
def test_the_inference_mode_solve_is_the_plain_solve_bit_for_bit(kw):
    net = model.load_pretrained()
    p = random_problem(9, torch.float32, 7)
    assert p.autograd_free()
    fast, plain, mem_a, mem_b = _solve_pair(net, p, **kw)
    assert torch.equal(fast, plain) and not fast.is_inference()
    fast.add_(1.0)                                      # the caller may change it in place
    if kw.get("recycle"):
        assert len(mem_a["basis"]) == len(mem_b["basis"]) > 0
        for u, v in zip(mem_a["basis"] + [mem_a["x_next"]], mem_b["basis"] + [mem_b["x_next"]]):
            assert torch.equal(u, v) and not u.is_inference()


def test_a_problem_that_needs_autograd_is_solved_without_inference_mode():
    net = model.load_pretrained()
    p = random_problem(9, torch.float32, 8)
    p.fused = False                                     # the gradient comes from autograd
    assert not p.autograd_free()
    fast, plain, _, _ = _solve_pair(net, p)
    assert torch.equal(fast, plain)


def test_an_inference_solve_leaves_caches_that_training_can_use():
    # caches built during an inference-mode solve (kept weights, DFT / DCT matrices, the
    # expanded mask) are normal tensors: training on the same grid afterwards backpropagates
    from draping.fnopt import tbptt

    net = model.load_pretrained()
    p = random_problem(11, torch.float32, 9)
    model._DFT_CACHE.clear()
    preconditioners._DCT_ROWS.clear()
    for sp in net.spectral:
        sp.__dict__.pop("_kept", None)
    model.solve_fnopt(net, p, 3)
    cached = [p.free3, *preconditioners._DCT_ROWS.values(),
              *(t for v in model._DFT_CACHE.values() for t in v),
              *(sp._kept[1] for sp in net.spectral)]
    assert cached and not any(t.is_inference() for t in cached)
    a, _ = tbptt.unrolled_solve(net, p, 2)
    a.square().sum().backward()
    assert all(q.grad is not None for q in net.spectral.parameters())
