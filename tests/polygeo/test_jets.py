import math

import numpy as np
import pytest
import torch

from polygeo import diffgeo, jets
from polygeo.status import Status

BACKENDS = ["torch", "numba"]


def _disc(gen, B, K, radius=1.0, dtype=torch.float64):
    """B x K points uniform in a disc of the given radius."""
    r = radius * torch.rand(B, K, generator=gen, dtype=torch.float64).sqrt()
    t = 2 * math.pi * torch.rand(B, K, generator=gen, dtype=torch.float64)
    return torch.stack([r * torch.cos(t), r * torch.sin(t)], -1).to(dtype)


def _poly(coeffs, uv):
    """Independent evaluation of sum a_pq u^p v^q with explicit exponents."""
    order = jets.order_from_ncoeffs(coeffs.shape[1])
    out = torch.zeros(uv.shape[:2], dtype=coeffs.dtype)
    m = 0
    for i in range(order + 1):
        for j in range(i + 1):
            out = out + coeffs[:, m, None] * uv[..., 0] ** (i - j) * uv[..., 1] ** j
            m += 1
    return out


# ---------------------------------------------------------------- basis


def test_counts_and_exponents():
    assert [jets.n_coeffs(n) for n in range(7)] == [1, 3, 6, 10, 15, 21, 28]
    for n in range(7):
        assert jets.order_from_ncoeffs(jets.n_coeffs(n)) == n
    assert jets.exponents(2).tolist() == [[0, 0], [1, 0], [0, 1], [2, 0], [1, 1], [0, 2]]
    e = jets.exponents(6)
    assert e.dtype == torch.int64 and e.shape == (28, 2)
    assert (e.sum(1)[1:] >= e.sum(1)[:-1]).all()


@pytest.mark.parametrize("m", [0, 2, 4, 7, 11])
def test_order_from_ncoeffs_rejects_non_triangular(m):
    with pytest.raises(ValueError, match="m"):
        jets.order_from_ncoeffs(m)


def test_basis_validators():
    with pytest.raises(ValueError, match="order"):
        jets.n_coeffs(-1)
    with pytest.raises(TypeError, match="order"):
        jets.monomials(torch.zeros(3, 2), 2.0)
    with pytest.raises(ValueError, match="uv"):
        jets.monomials(torch.zeros(3, 3), 2)
    with pytest.raises(ValueError, match="order"):
        jets.exponents(13)
    with pytest.raises(ValueError, match="du"):
        jets.monomial_derivatives(torch.zeros(3, 2), 2, du=-1)


def test_monomials_match_explicit_powers(gen):
    uv = _disc(gen, 4, 7)
    for n in range(7):
        basis = jets.monomials(uv, n)
        for m, (p, q) in enumerate(jets.exponents(n).tolist()):
            torch.testing.assert_close(basis[..., m], uv[..., 0] ** p * uv[..., 1] ** q)


def test_monomial_derivatives_match_autograd(gen):
    uv = _disc(gen, 2, 5).requires_grad_(True)
    order = 5
    for m in range(jets.n_coeffs(order)):
        # d/du and d/dv of each monomial, then second derivatives
        basis = jets.monomials(uv, order)
        g = torch.autograd.grad(basis[..., m].sum(), uv, create_graph=True)[0]
        torch.testing.assert_close(g[..., 0], jets.monomial_derivatives(uv, order, 1, 0)[..., m])
        torch.testing.assert_close(g[..., 1], jets.monomial_derivatives(uv, order, 0, 1)[..., m])
        gg = torch.autograd.grad(g[..., 0].sum(), uv, create_graph=True, retain_graph=True)[0]
        torch.testing.assert_close(gg[..., 0], jets.monomial_derivatives(uv, order, 2, 0)[..., m])
        torch.testing.assert_close(gg[..., 1], jets.monomial_derivatives(uv, order, 1, 1)[..., m])
        ggg = torch.autograd.grad(gg[..., 1].sum(), uv, allow_unused=True)[0]
        torch.testing.assert_close(ggg[..., 1], jets.monomial_derivatives(uv, order, 1, 2)[..., m])
    assert jets.monomial_derivatives(uv, 2, 2, 1).abs().max() == 0


def test_evaluate_and_derivatives_agree(gen):
    c = torch.randn(3, jets.n_coeffs(4), generator=gen, dtype=torch.float64)
    uv = _disc(gen, 3, 6)
    torch.testing.assert_close(jets.evaluate(c, uv), _poly(c, uv))
    d = jets.derivatives(c, uv, max_order=5)
    assert len(d) == 21
    for (du, dv), val in d.items():
        torch.testing.assert_close(val, jets.evaluate(c, uv, du, dv))
    assert d[(5, 0)].abs().max() == 0
    # numpy in -> numpy out
    out = jets.evaluate(c.numpy(), uv.numpy())
    assert isinstance(out, np.ndarray)
    np.testing.assert_allclose(out, _poly(c, uv).numpy(), rtol=1e-12, atol=1e-14)


def test_evaluate_validators():
    with pytest.raises(ValueError, match="coeffs"):
        jets.evaluate(torch.zeros(2, 5), torch.zeros(2, 3, 2))
    with pytest.raises(ValueError, match="uv"):
        jets.evaluate(torch.zeros(2, 6), torch.zeros(3, 3, 2))
    with pytest.raises(ValueError, match="uv"):
        jets.derivatives(torch.zeros(2, 6), torch.zeros(2, 3))


# ---------------------------------------------------------------- exact recovery


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("order", [1, 2, 3, 4, 5, 6])
def test_exact_recovery(gen, order, backend):
    B, M = 40, jets.n_coeffs(order)
    K = 2 * M + 5
    # neighbourhoods of various sizes, off-centre, with unit-scale coefficients in scaled units
    radius = 10 ** torch.empty(B).uniform_(-2, 1, generator=gen).to(torch.float64)
    uv = _disc(gen, B, K) * radius[:, None, None] + 0.1 * radius[:, None, None]
    deg = jets.exponents(order).sum(1).to(torch.float64)
    c = torch.randn(B, M, generator=gen, dtype=torch.float64) / radius[:, None] ** deg
    z = _poly(c, uv)
    f = jets.fit(uv, z, order, backend=backend)
    assert (f.status == Status.OK).all() and (f.fitted_order == order).all()
    assert (f.rank == M).all() and (f.n_points == K).all()
    # error in the natural (scaled) units of each coefficient
    err = ((f.coeffs - c) * radius[:, None] ** deg).abs().max()
    assert err < 1e-10
    assert (f.residual < 1e-10 * z.abs().amax(1).clamp_min(1)).all()
    torch.testing.assert_close(f.scale, (uv**2).sum(-1).amax(-1).sqrt())


def test_backends_agree_on_noisy_and_degenerate_items(gen):
    B, K, order = 60, 30, 3
    uv = _disc(gen, B, K)
    z = torch.randn(B, K, generator=gen, dtype=torch.float64)
    w = torch.rand(B, K, generator=gen, dtype=torch.float64)
    mask = torch.rand(B, K, generator=gen) > 0.2
    # degenerate items: collinear, a ring, too few points, nothing valid
    uv[0, :, 1] = 0.3 * uv[0, :, 0]
    t = torch.linspace(0, 2 * math.pi, K + 1, dtype=torch.float64)[:-1]
    uv[1] = torch.stack([torch.cos(t), torch.sin(t)], -1)
    mask[2, 4:] = False
    mask[3] = False
    for fallback in (True, False):
        a = jets.fit(uv, z, order, weights=w, mask=mask, backend="torch", fallback=fallback)
        b = jets.fit(uv, z, order, weights=w, mask=mask, backend="numba", fallback=fallback)
        torch.testing.assert_close(a.coeffs, b.coeffs, rtol=1e-9, atol=1e-11)
        torch.testing.assert_close(a.residual, b.residual, rtol=1e-9, atol=1e-12)
        for name in ("status", "rank", "fitted_order", "n_points"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name
        fin = torch.isfinite(a.cond)
        assert torch.equal(fin, torch.isfinite(b.cond))
        torch.testing.assert_close(a.cond[fin], b.cond[fin], rtol=1e-6, atol=0)
        assert torch.isfinite(a.coeffs).all() and torch.isfinite(b.coeffs).all()


# ---------------------------------------------------------------- weights, masks, batching


@pytest.mark.parametrize("backend", BACKENDS)
def test_weighted_fit_matches_numpy_lstsq(gen, backend):
    B, K, order = 5, 25, 2
    uv = _disc(gen, B, K, radius=0.5)
    z = torch.randn(B, K, generator=gen, dtype=torch.float64)
    w = torch.rand(B, K, generator=gen, dtype=torch.float64) + 0.1
    f = jets.fit(uv, z, order, weights=w, backend=backend)
    for b in range(B):
        A = np.stack([uv[b, :, 0].numpy() ** p * uv[b, :, 1].numpy() ** q
                      for p, q in jets.exponents(order).tolist()], 1)
        sw = np.sqrt(w[b].numpy())
        ref = np.linalg.lstsq(A * sw[:, None], z[b].numpy() * sw, rcond=None)[0]
        np.testing.assert_allclose(f.coeffs[b].numpy(), ref, rtol=1e-9, atol=1e-11)
        r = z[b].numpy() - A @ ref
        rms = np.sqrt((w[b].numpy() * r * r).sum() / w[b].numpy().sum())
        np.testing.assert_allclose(f.residual[b].item(), rms, rtol=1e-9)


@pytest.mark.parametrize("backend", BACKENDS)
def test_integer_weights_equal_duplicated_points(gen, backend):
    uv = _disc(gen, 1, 12)
    z = torch.randn(1, 12, generator=gen, dtype=torch.float64)
    reps = torch.randint(1, 4, (12,), generator=gen)
    a = jets.fit(uv, z, 2, weights=reps[None].to(torch.float64), backend=backend)
    b = jets.fit(uv[:, torch.repeat_interleave(torch.arange(12), reps)],
                 z[:, torch.repeat_interleave(torch.arange(12), reps)], 2, backend=backend)
    torch.testing.assert_close(a.coeffs, b.coeffs, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("backend", BACKENDS)
def test_mask_padding_equals_packed_per_item(gen, backend):
    sizes = [7, 12, 20, 9]
    K = max(sizes)
    uv = torch.full((4, K, 2), 1e30, dtype=torch.float64)  # garbage padding
    z = torch.full((4, K), float("nan"), dtype=torch.float64)
    mask = torch.zeros(4, K, dtype=torch.bool)
    items = []
    for b, k in enumerate(sizes):
        u = _disc(gen, 1, k)
        h = torch.randn(1, k, generator=gen, dtype=torch.float64)
        uv[b, :k], z[b, :k], mask[b, :k] = u[0], h[0], True
        items.append(jets.fit(u, h, 2, backend=backend))
    f = jets.fit(uv, z, 2, mask=mask, backend=backend)
    for b, one in enumerate(items):
        torch.testing.assert_close(f.coeffs[b], one.coeffs[0], rtol=1e-11, atol=1e-13)
        torch.testing.assert_close(f.residual[b], one.residual[0], rtol=1e-10, atol=1e-14)
        assert f.status[b] == one.status[0] and f.n_points[b] == sizes[b]


def test_nonfinite_samples_are_masked_out(gen):
    uv = _disc(gen, 2, 15)
    z = torch.randn(2, 15, generator=gen, dtype=torch.float64)
    z_nan = z.clone()
    z_nan[0, 3] = float("nan")
    uv_inf = uv.clone()
    uv_inf[1, 5, 0] = float("inf")
    mask = torch.ones(2, 15, dtype=torch.bool)
    mask[0, 3] = False
    mask[1, 5] = False
    a = jets.fit(uv_inf, z_nan, 2)
    b = jets.fit(uv, z, 2, mask=mask)
    torch.testing.assert_close(a.coeffs, b.coeffs)
    assert (a.n_points == 14).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_batched_equals_per_item(gen, backend):
    uv = _disc(gen, 6, 18)
    z = torch.randn(6, 18, generator=gen, dtype=torch.float64)
    f = jets.fit(uv, z, 3, backend=backend)
    for b in range(6):
        one = jets.fit(uv[b : b + 1], z[b : b + 1], 3, backend=backend)
        torch.testing.assert_close(f.coeffs[b : b + 1], one.coeffs, rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(f.cond[b : b + 1], one.cond)


def test_float32_path(gen):
    uv = _disc(gen, 8, 30)
    c = torch.randn(8, 6, generator=gen, dtype=torch.float64)
    z = _poly(c, uv)
    f32 = jets.fit(uv.float(), z.float(), 2)
    assert f32.coeffs.dtype == torch.float32 and f32.residual.dtype == torch.float32
    torch.testing.assert_close(f32.coeffs.double(), c, rtol=0, atol=2e-5)
    g32 = jets.fit(uv.float(), z.float(), 2, backend="torch")
    torch.testing.assert_close(f32.coeffs, g32.coeffs)
    # mixed precision promotes
    assert jets.fit(uv.float(), z, 2).coeffs.dtype == torch.float64


def test_numpy_input(rng):
    uv = rng.uniform(-1, 1, (3, 10, 2))
    z = rng.normal(size=(3, 10))
    f = jets.fit(uv, z, 2)
    g = jets.fit(torch.from_numpy(uv), torch.from_numpy(z), 2)
    torch.testing.assert_close(f.coeffs, g.coeffs)


# ---------------------------------------------------------------- gradients


def test_gradcheck_fit_coefficients(gen):
    uv = _disc(gen, 2, 9).requires_grad_(True)
    z = torch.randn(2, 9, generator=gen, dtype=torch.float64).requires_grad_(True)
    w = (torch.rand(2, 9, generator=gen, dtype=torch.float64) + 0.5).requires_grad_(True)

    def f(uv, z, w):
        r = jets.fit(uv, z, 2, weights=w)
        return r.coeffs, r.residual

    assert torch.autograd.gradcheck(f, (uv, z, w))


def test_gradcheck_points_to_curvature(gen):
    # points in a local frame -> jet -> curvatures and normal at the origin
    uv = _disc(gen, 2, 12, radius=0.3)
    z0 = 0.5 * (0.8 * uv[..., 0] ** 2 - 0.3 * uv[..., 1] ** 2) + 0.1 * uv[..., 0] ** 3
    pts = torch.cat([uv, z0[..., None]], -1).requires_grad_(True)

    def f(p):
        r = jets.fit(p[..., :2], p[..., 2], 3)
        g = diffgeo.from_jet(r.coeffs)
        return g.k1, g.k2, g.normal, g.mean_curvature

    assert torch.autograd.gradcheck(f, (pts,))


def test_auto_backend_is_differentiable(gen):
    uv = _disc(gen, 3, 10)
    z = torch.randn(3, 10, generator=gen, dtype=torch.float64, requires_grad=True)
    f = jets.fit(uv, z, 2)
    assert f.coeffs.requires_grad
    with torch.no_grad():
        assert not jets.fit(uv, z, 2).coeffs.requires_grad


# ---------------------------------------------------------------- degenerate input


@pytest.mark.parametrize("backend", BACKENDS)
def test_nearly_collinear_samples_are_degenerate(backend):
    """Samples on a line up to rounding noise define no plane: equilibrating the normal
    equations makes the noise across the line look like a well-spread direction, so the
    collinearity is tested on the samples' covariance (COLLINEAR_TOL), the same on both
    backends. A thin but real strip (1e-3 of its length) is still fitted."""
    g = torch.Generator().manual_seed(3)
    t = torch.linspace(-1, 1, 30, dtype=torch.float64)
    line = torch.stack([t, 0.5 * t], -1)
    across = torch.randn(30, generator=g, dtype=torch.float64)[:, None] * torch.tensor(
        [-0.5, 1.0], dtype=torch.float64) / math.sqrt(1.25)
    uv = torch.stack([line, line + 1e-9 * across, line.float().double() + 1e-7 * across,
                      line + 1e-3 * across])
    z = 0.2 * uv[..., 0] + 0.1 * torch.randn(4, 30, generator=g, dtype=torch.float64)
    f = jets.fit(uv, z, 2, backend=backend)
    assert f.status.tolist() == [Status.DEGENERATE] * 3 + [Status.OK]
    assert f.fitted_order.tolist() == [0, 0, 0, 2]
    assert torch.isfinite(f.coeffs).all()



@pytest.mark.parametrize("backend", BACKENDS)
def test_fallback_statuses(gen, backend):
    K = 16
    t = torch.linspace(0, 2 * math.pi, K + 1, dtype=torch.float64)[:-1]
    ring = torch.stack([torch.cos(t), torch.sin(t)], -1)
    line = torch.stack([torch.linspace(-1, 1, K), 0.5 * torch.linspace(-1, 1, K)], -1).double()
    rand = _disc(gen, 1, K)[0]
    uv = torch.stack([ring, line, rand, rand, rand, rand])
    z = 0.3 + 0.2 * uv[..., 0] - 0.1 * uv[..., 1] + 0.5 * uv[..., 0] ** 2
    mask = torch.ones(6, K, dtype=torch.bool)
    mask[2, 5:] = False  # 5 points: too few for order 2 (6 coefficients)
    mask[3, 2:] = False  # 2 points: not even a plane
    mask[4] = False  # nothing
    f = jets.fit(uv, z, 2, mask=mask, backend=backend)
    assert torch.isfinite(f.coeffs).all() and torch.isfinite(f.residual).all()
    assert f.status.tolist() == [Status.ORDER_REDUCED, Status.DEGENERATE, Status.ORDER_REDUCED,
                                 Status.TOO_FEW_POINTS, Status.TOO_FEW_POINTS, Status.OK]
    assert f.fitted_order.tolist() == [1, 0, 1, 0, 0, 2]
    assert f.rank[0] == 5 and f.rank[1] == 3 and f.rank[5] == 6
    assert math.isinf(f.cond[1]) or f.cond[1] > 1e6
    # ring: exact plane through the ring points (z restricted to the ring is not quadratic
    # in u only, so compare with the least-squares plane)
    A = torch.stack([torch.ones(K, dtype=torch.float64), ring[:, 0], ring[:, 1]], 1)
    ref = torch.linalg.lstsq(A, z[0, :, None]).solution[:, 0]
    torch.testing.assert_close(f.coeffs[0, :3], ref)
    assert (f.coeffs[0, 3:] == 0).all()
    torch.testing.assert_close(f.coeffs[1, 0], z[1].mean())
    torch.testing.assert_close(f.coeffs[3, 0], z[3, :2].mean())
    assert (f.coeffs[4] == 0).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_no_fallback_gives_min_norm_and_status(gen, backend):
    K = 16
    line = torch.stack([torch.linspace(-1, 1, K), 0.5 * torch.linspace(-1, 1, K)], -1).double()
    uv = torch.stack([line, _disc(gen, 1, K)[0]])
    z = 1 + uv[..., 0]
    mask = torch.ones(2, K, dtype=torch.bool)
    mask[1, 4:] = False
    f = jets.fit(uv, z, 2, mask=mask, fallback=False, backend=backend)
    assert f.status.tolist() == [Status.ILL_CONDITIONED, Status.TOO_FEW_POINTS]
    assert (f.fitted_order == 2).all()
    assert torch.isfinite(f.coeffs).all()
    # the min-norm solution still interpolates the data
    assert (f.residual < 1e-9).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_duplicated_points(gen, backend):
    uv = _disc(gen, 1, 10)
    c = torch.randn(1, 6, generator=gen, dtype=torch.float64)
    z = _poly(c, uv)
    f = jets.fit(uv.repeat(1, 50, 1), z.repeat(1, 50), 2, backend=backend)
    assert f.status[0] == Status.OK
    torch.testing.assert_close(f.coeffs, c, rtol=0, atol=1e-10)
    same = jets.fit(torch.full((1, 30, 2), 0.2, dtype=torch.float64),
                    torch.full((1, 30), 0.7, dtype=torch.float64), 2, backend=backend)
    assert same.status[0] == Status.DEGENERATE and same.fitted_order[0] == 0
    torch.testing.assert_close(same.coeffs[0, 0], torch.tensor(0.7, dtype=torch.float64))


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("s", [1e-6, 1.0, 1e6])
def test_conditioning_scale_and_offset(gen, backend, s):
    uv = _disc(gen, 2, 30)
    c = torch.tensor([[0.0, 0.1, -0.2, 0.7, 0.2, -0.4]], dtype=torch.float64).repeat(2, 1)
    z = _poly(c, uv)
    # item 1 is offset by 1e6 in height (e.g. un-centred input); the data then only carry
    # ~1e6 * eps of absolute precision, so allow that much
    offset = torch.tensor([0.0, 1e6], dtype=torch.float64)
    # a similarity x -> s x of the surface: a_pq -> a_pq s^(1 - p - q)
    deg = jets.exponents(2).sum(1).to(torch.float64)
    f = jets.fit(uv * s, z * s + offset[:, None] * s, 2, backend=backend)
    got = f.coeffs / s ** (1 - deg)  # back to unit scale
    expect = c.clone()
    expect[:, 0] += offset
    err = (got - expect).abs()
    assert err[0].max() < 1e-12
    assert err[1, 0] < 1e-9 * 1e6 and err[1, 1:].max() < 1e-8
    assert (f.status == Status.OK).all()
    assert f.cond.max() < 100  # preconditioning removes the scale from the conditioning


def test_empty_inputs():
    for backend in BACKENDS:
        f = jets.fit(torch.zeros(0, 5, 2), torch.zeros(0, 5), 2, backend=backend)
        assert f.coeffs.shape == (0, 6) and f.status.shape == (0,)
        g = jets.fit(torch.zeros(3, 0, 2), torch.zeros(3, 0), 2, backend=backend)
        assert (g.status == Status.TOO_FEW_POINTS).all() and (g.coeffs == 0).all()


def test_fit_validators():
    uv, z = torch.zeros(2, 8, 2), torch.zeros(2, 8)
    with pytest.raises(ValueError, match="uv"):
        jets.fit(torch.zeros(2, 8, 3), z, 2)
    with pytest.raises(ValueError, match="z"):
        jets.fit(uv, torch.zeros(2, 7), 2)
    with pytest.raises(ValueError, match="order"):
        jets.fit(uv, z, 0)
    with pytest.raises(ValueError, match="order"):
        jets.fit(uv, z, 7)
    with pytest.raises(TypeError, match="order"):
        jets.fit(uv, z, 2.0)
    with pytest.raises(TypeError, match="mask"):
        jets.fit(uv, z, 2, mask=torch.ones(2, 8))
    with pytest.raises(ValueError, match="mask"):
        jets.fit(uv, z, 2, mask=torch.ones(2, 7, dtype=torch.bool))
    with pytest.raises(ValueError, match="weights"):
        jets.fit(uv, z, 2, weights=-torch.ones(2, 8))
    with pytest.raises(ValueError, match="weights"):
        jets.fit(uv, z, 2, weights=torch.full((2, 8), float("nan")))
    with pytest.raises(ValueError, match="scale"):
        jets.fit(uv, z, 2, scale=torch.tensor([1.0, 0.0]))
    with pytest.raises(ValueError, match="backend"):
        jets.fit(uv, z, 2, backend="cuda")
    with pytest.raises(ValueError, match="max_cond"):
        jets.fit(uv, z, 2, max_cond=-1)
    with pytest.raises(ValueError, match="refine_above"):
        jets.fit(uv, z, 2, refine_above=-1.0)
    with pytest.raises(TypeError, match="refine_above"):
        jets.fit(uv, z, 2, refine_above="always")
    with pytest.raises(TypeError, match="uv"):
        jets.fit(np.array([["a", "b"]]), z, 2)
    with pytest.raises(TypeError, match="z"):
        jets.fit(uv, torch.zeros(2, 8, dtype=torch.complex64), 2)


@pytest.mark.parametrize("backend", BACKENDS)
def test_refinement_helps_ill_conditioned_high_order(gen, backend):
    # order 6 on an off-centre sample (monomials nearly dependent): the normal equations
    # alone lose digits, one refinement step recovers them
    uv = 0.5 * _disc(gen, 20, 40) + torch.tensor([0.5, 0.0], dtype=torch.float64)
    c = torch.randn(20, 28, generator=gen, dtype=torch.float64)
    z = _poly(c, uv)
    plain = jets.fit(uv, z, 6, refine_above=math.inf, backend=backend)
    refined = jets.fit(uv, z, 6, refine_above=0.0, backend=backend)
    assert (plain.status == Status.OK).all() and plain.cond.min() > 1e4
    e_plain = (plain.coeffs - c).abs().max()
    e_ref = (refined.coeffs - c).abs().max()
    assert e_ref < e_plain / 100
    assert refined.residual.max() < 1e-13
    # the default threshold refines these items
    torch.testing.assert_close(jets.fit(uv, z, 6, backend=backend).coeffs, refined.coeffs)


def test_explicit_scale_does_not_change_coefficients(gen):
    uv = _disc(gen, 3, 20)
    z = torch.randn(3, 20, generator=gen, dtype=torch.float64)
    a = jets.fit(uv, z, 3)
    b = jets.fit(uv, z, 3, scale=torch.tensor([0.5, 2.0, 7.0], dtype=torch.float64))
    torch.testing.assert_close(a.coeffs, b.coeffs, rtol=1e-8, atol=1e-10)
    torch.testing.assert_close(b.scale, torch.tensor([0.5, 2.0, 7.0], dtype=torch.float64))


# ---------------------------------------------------------------- interpolation variant


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("order", [1, 2, 4])
def test_interpolating_fit_matches_constrained_lstsq(gen, backend, order):
    B, K = 6, 30
    uv = _disc(gen, B, K, radius=0.4)
    z = torch.randn(B, K, generator=gen, dtype=torch.float64)
    w = torch.rand(B, K, generator=gen, dtype=torch.float64) + 0.1
    f = jets.fit(uv, z, order, weights=w, backend=backend, interpolate=True)
    assert (f.status == 0).all()
    for b in range(B):
        # independent reference: weighted least squares without the constant column
        A = np.stack([uv[b, :, 0].numpy() ** p * uv[b, :, 1].numpy() ** q
                      for p, q in jets.exponents(order).tolist()[1:]], 1)
        sw = np.sqrt(w[b].numpy())
        ref = np.linalg.lstsq(A * sw[:, None], z[b].numpy() * sw, rcond=None)[0]
        assert abs(f.coeffs[b, 0].item()) < 1e-12
        np.testing.assert_allclose(f.coeffs[b, 1:].numpy(), ref, rtol=1e-9, atol=1e-11)
        r = z[b].numpy() - A @ ref
        rms = np.sqrt((w[b].numpy() * r * r).sum() / w[b].numpy().sum())
        np.testing.assert_allclose(f.residual[b].item(), rms, rtol=1e-9)


@pytest.mark.parametrize("backend", BACKENDS)
def test_interpolating_fit_exact_and_fallback(gen, backend):
    # an exact jet through the origin is recovered; an offset one is not interpolated away
    c = torch.randn(4, jets.n_coeffs(3), generator=gen, dtype=torch.float64)
    c[:, 0] = 0.0
    uv = _disc(gen, 4, 40)
    f = jets.fit(uv, _poly(c, uv), 3, backend=backend, interpolate=True)
    torch.testing.assert_close(f.coeffs, c, rtol=1e-9, atol=1e-10)
    # a single scan line (order 2 singular) falls back with the constraint kept
    u = torch.linspace(-1, 1, 12, dtype=torch.float64)
    uvl = torch.stack([u, torch.zeros_like(u)], -1)[None]
    zl = (0.5 + 0.3 * u)[None]
    g = jets.fit(uvl, zl, 2, backend=backend, interpolate=True)
    assert int(g.status[0]) in (int(Status.ORDER_REDUCED), int(Status.DEGENERATE))
    assert g.coeffs[0, 0].item() == pytest.approx(0.0, abs=1e-12)
    assert torch.isfinite(g.coeffs).all()


def test_interpolating_fit_gradcheck(gen):
    uv = _disc(gen, 2, 12, radius=0.5).requires_grad_()
    z = torch.randn(2, 12, generator=gen, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda a, b: jets.fit(a, b, 2, backend="torch", interpolate=True).coeffs, (uv, z)
    )


def test_interpolate_validator():
    with pytest.raises(TypeError, match="interpolate"):
        jets.fit(torch.zeros(1, 6, 2), torch.zeros(1, 6), 2, interpolate="yes")
