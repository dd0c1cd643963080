import math

import numpy as np
import pytest
import torch

from polygeo import diffgeo, frames, jets, synthetic
from polygeo.synthetic.analytic import _cylinder_from_params, _torus_from_params


def _t(x):
    return torch.as_tensor(np.asarray(x), dtype=torch.float64)


def _assert_dir(a, b, atol=1e-10):
    """Unit vectors equal up to sign."""
    dot = (a * b).sum(-1).abs()
    assert (1 - dot).abs().max() < atol


# ---------------------------------------------------------------- analytic parametric patches


def _sphere_derivs(r, th, ph, shear=0.0):
    """Derivatives of x(u, v) = sphere(theta = u + shear v, phi = v)."""
    st, ct, sp, cp = torch.sin(th), torch.cos(th), torch.sin(ph), torch.cos(ph)
    x_t = r * torch.stack([ct * cp, ct * sp, -st], -1)
    x_p = r * torch.stack([-st * sp, st * cp, torch.zeros_like(st)], -1)
    x_tt = r * torch.stack([-st * cp, -st * sp, -ct], -1)
    x_tp = r * torch.stack([-ct * sp, ct * cp, torch.zeros_like(st)], -1)
    x_pp = r * torch.stack([-st * cp, -st * sp, torch.zeros_like(st)], -1)
    # chain rule for theta = u + shear v, phi = v
    xu, xv = x_t, shear * x_t + x_p
    xuu = x_tt
    xuv = shear * x_tt + x_tp
    xvv = shear**2 * x_tt + 2 * shear * x_tp + x_pp
    return xu, xv, xuu, xuv, xvv


@pytest.mark.parametrize("shear", [0.0, 0.7])
def test_sphere_at_random_points(gen, shear):
    r = 2.5
    th = 0.2 + 2.7 * torch.rand(50, generator=gen, dtype=torch.float64)
    ph = 2 * math.pi * torch.rand(50, generator=gen, dtype=torch.float64)
    g = diffgeo.from_derivatives(*_sphere_derivs(r, th, ph, shear))
    pos = r * torch.stack([torch.sin(th) * torch.cos(ph), torch.sin(th) * torch.sin(ph),
                           torch.cos(th)], -1)
    assert g.valid.all()
    torch.testing.assert_close(g.normal, pos / r)  # outward for this parametrisation
    torch.testing.assert_close(g.k1, torch.full_like(th, -1 / r))
    torch.testing.assert_close(g.k2, torch.full_like(th, -1 / r))
    torch.testing.assert_close(g.mean_curvature, torch.full_like(th, -1 / r))
    torch.testing.assert_close(g.gaussian_curvature, torch.full_like(th, 1 / r**2))
    # umbilic: d1, d2 any orthonormal tangent pair, right-handed with n
    torch.testing.assert_close(torch.linalg.cross(g.d1, g.d2), g.normal)
    assert (g.d1 * g.normal).sum(-1).abs().max() < 1e-12
    # metric and shape operator
    torch.testing.assert_close(g.shape_operator, -torch.eye(2, dtype=torch.float64) / r *
                               torch.ones(50, 1, 1, dtype=torch.float64))
    torch.testing.assert_close(g.metric, g.jacobian.transpose(-1, -2) @ g.jacobian)


def test_cylinder_at_random_points(gen):
    r = 0.7
    th = 2 * math.pi * torch.rand(40, generator=gen, dtype=torch.float64)
    z = torch.rand(40, generator=gen, dtype=torch.float64)
    zero = torch.zeros_like(th)
    xu = r * torch.stack([-torch.sin(th), torch.cos(th), zero], -1)
    xv = torch.stack([zero, zero, torch.ones_like(th)], -1)
    xuu = r * torch.stack([-torch.cos(th), -torch.sin(th), zero], -1)
    g = diffgeo.from_derivatives(xu, xv, xuu, torch.zeros_like(xu), torch.zeros_like(xu))
    s = _cylinder_from_params(th.numpy(), z.numpy(), r, None, 0.0, 0)
    torch.testing.assert_close(g.normal, _t(s.normals))
    torch.testing.assert_close(g.k1, _t(s.k1))
    torch.testing.assert_close(g.k2, _t(s.k2))
    _assert_dir(g.d1, _t(s.d1))
    _assert_dir(g.d2, _t(s.d2))
    torch.testing.assert_close(g.gaussian_curvature, torch.zeros_like(th), rtol=0, atol=1e-14)


def _torus_derivs(R, r, u, v):
    cu, su, cv, sv = torch.cos(u), torch.sin(u), torch.cos(v), torch.sin(v)
    a = R + r * cv
    zero = torch.zeros_like(u)
    xu = torch.stack([-a * su, a * cu, zero], -1)
    xv = torch.stack([-r * sv * cu, -r * sv * su, r * cv], -1)
    xuu = torch.stack([-a * cu, -a * su, zero], -1)
    xuv = torch.stack([r * sv * su, -r * sv * cu, zero], -1)
    xvv = torch.stack([-r * cv * cu, -r * cv * su, -r * sv], -1)
    return xu, xv, xuu, xuv, xvv


def test_torus_matches_closed_form_and_flips_with_normal(gen):
    R, r = 1.0, 0.35
    u = 2 * math.pi * torch.rand(60, generator=gen, dtype=torch.float64)
    v = 2 * math.pi * torch.rand(60, generator=gen, dtype=torch.float64)
    d = _torus_derivs(R, r, u, v)
    g = diffgeo.from_derivatives(*d)
    s = _torus_from_params(u.numpy(), v.numpy(), R, r, None, 0.0, 0)
    torch.testing.assert_close(g.normal, _t(s.normals))
    torch.testing.assert_close(g.k1, _t(s.k1))
    torch.testing.assert_close(g.k2, _t(s.k2))
    torch.testing.assert_close(g.mean_curvature, _t(s.mean_curvature))
    torch.testing.assert_close(g.gaussian_curvature, _t(s.gaussian_curvature))
    _assert_dir(g.d1, _t(s.d1))
    _assert_dir(g.d2, _t(s.d2))
    # swapping u and v flips the normal: k's and H flip (and swap), K is unchanged
    xu, xv, xuu, xuv, xvv = d
    h = diffgeo.from_derivatives(xv, xu, xvv, xuv, xuu)
    torch.testing.assert_close(h.normal, -g.normal)
    torch.testing.assert_close(h.k1, -g.k2)
    torch.testing.assert_close(h.k2, -g.k1)
    torch.testing.assert_close(h.gaussian_curvature, g.gaussian_curvature)


def test_from_jet_matches_graph_formulas_at_random_points():
    k1, k2, b, c = 0.9, -0.4, (0.3, -0.2, 0.5, 0.1), (1.0, -0.5, 0.2, 0.7, -1.2)
    s = synthetic.monge_patch(60, k1, k2, b, c, extent=0.6, seed=1)
    coeffs = _t([[0, 0, 0, k1 / 2, 0, k2 / 2, b[0] / 6, b[1] / 2, b[2] / 2, b[3] / 6,
                  c[0] / 24, c[1] / 6, c[2] / 4, c[3] / 6, c[4] / 24]])
    g = diffgeo.from_jet(coeffs, _t(s.uv)[None])
    torch.testing.assert_close(g.normal[0], _t(s.normals))
    torch.testing.assert_close(g.k1[0], _t(s.k1))
    torch.testing.assert_close(g.k2[0], _t(s.k2))
    _assert_dir(g.d1[0], _t(s.d1))
    torch.testing.assert_close(g.gaussian_curvature[0], _t(s.gaussian_curvature))
    # origin fast path == general path at uv = 0
    o = diffgeo.from_jet(coeffs)
    z = diffgeo.from_jet(coeffs, torch.zeros(1, 1, 2, dtype=torch.float64))
    for name in ("k1", "k2", "normal", "d1", "d2", "second_form", "metric"):
        torch.testing.assert_close(getattr(o, name), getattr(z, name))
    assert o.squeeze().k1.shape == (1,)


def test_planar_and_singular_cases_are_finite():
    # plane z = 0.3 u - 0.2 v: zero curvature, normal (-0.3, 0.2, 1)/|.|
    c = _t([[1.0, 0.3, -0.2, 0, 0, 0]])
    g = diffgeo.from_jet(c).squeeze()
    assert g.valid.all()
    for name in ("k1", "k2", "mean_curvature", "gaussian_curvature"):
        assert getattr(g, name).abs().max() == 0
    n = _t([-0.3, 0.2, 1.0])
    torch.testing.assert_close(g.normal[0], n / n.norm())
    assert torch.isfinite(g.d1).all()
    # singular metric: x_u parallel to x_v
    xu = _t([[1.0, 0, 0], [0, 0, 0]])
    h = diffgeo.from_derivatives(xu, 2 * xu, xu, xu, xu)
    assert not h.valid.any()
    for f in h.__dataclass_fields__:
        assert torch.isfinite(getattr(h, f).to(torch.float64)).all(), f
    assert h.k1.abs().max() == 0 and h.normal.abs().max() == 0


def test_gradcheck_from_derivatives(gen):
    u = torch.tensor([0.3, 2.0], dtype=torch.float64)
    v = torch.tensor([1.1, -0.4], dtype=torch.float64)
    d = [t.clone().requires_grad_(True) for t in _torus_derivs(1.0, 0.4, u, v)]

    def f(*args):
        g = diffgeo.from_derivatives(*args)
        return g.k1, g.k2, g.d1, g.d2, g.normal, g.mean_curvature, g.gaussian_curvature

    assert torch.autograd.gradcheck(f, tuple(d))


def test_umbilic_gradient_is_finite():
    c = torch.tensor([[0.0, 0.0, 0.0, 0.5, 0.0, 0.5]], dtype=torch.float64, requires_grad=True)
    g = diffgeo.from_jet(c)
    (g.k1.sum() + g.d1.sum() + g.mean_curvature.sum()).backward()
    assert torch.isfinite(c.grad).all()
    torch.testing.assert_close(g.k1, g.k2)


def test_to_world_matches_transformed_patch(gen):
    u = 2 * math.pi * torch.rand(5, generator=gen, dtype=torch.float64)
    v = 2 * math.pi * torch.rand(5, generator=gen, dtype=torch.float64)
    d = _torus_derivs(1.0, 0.3, u, v)
    Rm = frames.random_rotation(5, gen)
    s = torch.rand(5, generator=gen, dtype=torch.float64) + 0.5
    world = diffgeo.from_derivatives(*[s[:, None] * (Rm @ t[..., None])[..., 0] for t in d])
    mapped = diffgeo.to_world(diffgeo.from_derivatives(*d), Rm, s)
    for f in world.__dataclass_fields__:
        a, b = getattr(world, f), getattr(mapped, f)
        if f in ("d1", "d2"):
            _assert_dir(a, b)
        elif a.dtype == torch.bool:
            assert torch.equal(a, b)
        else:
            torch.testing.assert_close(a, b)
    with pytest.raises(ValueError, match="scale"):
        diffgeo.to_world(world, Rm, -s)


def test_from_derivatives_validators():
    z = torch.zeros(4, 3)
    with pytest.raises(ValueError, match="xv"):
        diffgeo.from_derivatives(z, torch.zeros(4, 2), z, z, z)
    with pytest.raises(ValueError, match="coeffs"):
        diffgeo.from_jet(torch.zeros(2, 5))
    with pytest.raises(ValueError, match="uv"):
        diffgeo.from_jet(torch.zeros(2, 6), torch.zeros(3, 1, 2))
    with pytest.raises(ValueError, match="at"):
        diffgeo.monge_form(torch.zeros(2, 6), at=torch.zeros(2, 3))
    with pytest.raises(ValueError, match="frame_rotation"):
        diffgeo.monge_form(torch.zeros(2, 6), frame_rotation=torch.zeros(2, 3))


# ---------------------------------------------------------------- Monge form


def _monge_coeffs(k1, k2, b, c):
    return _t([[0, 0, 0, k1 / 2, 0, k2 / 2, b[0] / 6, b[1] / 2, b[2] / 2, b[3] / 6,
                c[0] / 24, c[1] / 6, c[2] / 4, c[3] / 6, c[4] / 24]])


def test_monge_form_at_origin_is_exact():
    k1, k2, b, c = 0.7, -0.3, (0.1, 0.2, -0.3, 0.4), (0.5, -0.6, 0.7, 0.8, -0.9)
    m = diffgeo.monge_form(_monge_coeffs(k1, k2, b, c))
    torch.testing.assert_close(m.k1, _t([k1]))
    torch.testing.assert_close(m.k2, _t([k2]))
    torch.testing.assert_close(m.b, _t([b]))
    torch.testing.assert_close(m.c, _t([c]))
    torch.testing.assert_close(m.d1, _t([[1.0, 0, 0]]))
    torch.testing.assert_close(m.normal, _t([[0, 0, 1.0]]))
    assert m.has_cubic and m.has_quartic and m.valid.all()
    # lower orders: b, c zero and flagged
    m2 = diffgeo.monge_form(_monge_coeffs(k1, k2, b, c)[:, :6])
    assert not m2.has_cubic and (m2.b == 0).all() and (m2.c == 0).all()
    m3 = diffgeo.monge_form(_monge_coeffs(k1, k2, b, c)[:, :10])
    assert m3.has_cubic and not m3.has_quartic and (m3.c == 0).all()
    torch.testing.assert_close(m3.b, _t([b]))


def test_monge_form_of_rotated_patch(gen):
    """A Monge patch rotated about its normal: same k, b, c in the rotated Monge frame."""
    k1, k2, b, c = 1.2, 0.4, (0.3, -0.1, 0.2, 0.5), (0.4, 0.1, -0.3, 0.2, 0.6)
    alpha = 0.6
    ca, sa = math.cos(alpha), math.sin(alpha)
    # z(u, v) = f(x, y) with (x, y) = rotation by -alpha of (u, v); sample and fit exactly
    uv = 0.5 * (2 * torch.rand(1, 40, 2, generator=gen, dtype=torch.float64) - 1)
    x = ca * uv[..., 0] + sa * uv[..., 1]
    y = -sa * uv[..., 0] + ca * uv[..., 1]
    z = jets.evaluate(_monge_coeffs(k1, k2, b, c), torch.stack([x, y], -1))
    coeffs = jets.fit(uv, z, 4).coeffs
    m = diffgeo.monge_form(coeffs)
    flip = float((m.d1[0] * _t([ca, sa, 0.0])).sum()) < 0  # d1 is only defined up to sign
    sign = -1.0 if flip else 1.0
    torch.testing.assert_close(m.d1[0], sign * _t([ca, sa, 0.0]))
    torch.testing.assert_close(m.k1, _t([k1]))
    torch.testing.assert_close(m.k2, _t([k2]))
    torch.testing.assert_close(m.b, sign * _t([b]), rtol=0, atol=1e-9)
    torch.testing.assert_close(m.c, _t([c]), rtol=0, atol=1e-9)


def test_monge_form_at_a_generic_point_describes_the_surface(gen):
    """Independent check of the Monge frame and coefficients away from the origin.

    Express exact surface points near p0 in the returned frame (x, y, w): w must match the
    Monge polynomial up to O(rho^5) (a wrong b gives O(rho^3), a wrong c O(rho^4)).
    """
    coeffs = torch.randn(1, 15, generator=gen, dtype=torch.float64) * 0.5
    at = _t([[0.15, -0.1]])
    R = frames.random_rotation(1, gen)
    o = _t([[1.0, 2.0, 3.0]])
    m = diffgeo.monge_form(coeffs, frame_rotation=R, frame_origin=o, at=at)
    assert (m.k1 >= m.k2).all()
    torch.testing.assert_close(torch.linalg.cross(m.d1, m.d2), m.normal)
    errs = []
    rhos = [0.02, 0.01, 0.005]
    dirs = torch.randn(1, 30, 2, generator=gen, dtype=torch.float64)
    for rho in rhos:
        uv = at[:, None, :] + rho * dirs
        zz = jets.evaluate(coeffs, uv)
        pw = (R @ torch.cat([uv, zz[..., None]], -1).transpose(1, 2)).transpose(1, 2) + o
        q = pw - m.origin[:, None]
        x, y, w = (q * m.d1[:, None]).sum(-1), (q * m.d2[:, None]).sum(-1), \
            (q * m.normal[:, None]).sum(-1)
        b, c = m.b[0], m.c[0]
        pred = 0.5 * (m.k1 * x**2 + m.k2 * y**2) + (b[0] * x**3 + 3 * b[1] * x**2 * y
                                                    + 3 * b[2] * x * y**2 + b[3] * y**3) / 6 \
            + (c[0] * x**4 + 4 * c[1] * x**3 * y + 6 * c[2] * x**2 * y**2 + 4 * c[3] * x * y**3
               + c[4] * y**4) / 24
        errs.append(float((w - pred).abs().max()))
    slope = np.polyfit(np.log(rhos), np.log(errs), 1)[0]
    assert slope > 4.5, (errs, slope)
    # the point itself is on the surface, in world coordinates
    p_local = torch.cat([at, jets.evaluate(coeffs, at[:, None])], -1)
    torch.testing.assert_close(m.origin, (R @ p_local[..., None])[..., 0] + o)


def test_monge_form_nonfinite_coefficients_are_flagged():
    c = _monge_coeffs(0.5, 0.1, (1, 2, 3, 4), (1, 2, 3, 4, 5)).repeat(2, 1)
    c[1, 7] = float("nan")
    m = diffgeo.monge_form(c)
    assert m.valid.tolist() == [True, False]
    for t in (m.k1, m.k2, m.b, m.c, m.d1, m.d2, m.normal):
        assert torch.isfinite(t).all()
    assert (m.b[1] == 0).all() and (m.k1[1] == 0)


def test_monge_form_batched_equals_per_item(gen):
    coeffs = torch.randn(4, 15, generator=gen, dtype=torch.float64)
    at = 0.1 * torch.randn(4, 2, generator=gen, dtype=torch.float64)
    m = diffgeo.monge_form(coeffs, at=at)
    for i in range(4):
        one = diffgeo.monge_form(coeffs[i : i + 1], at=at[i : i + 1])
        torch.testing.assert_close(m.b[i], one.b[0])
        torch.testing.assert_close(m.c[i], one.c[0])


# ---------------------------------------------------------------- convergence (Cazals-Pouget)


def _torus_neighbourhood(h, gen_dirs, u0=0.7, v0=2.1, R=1.0, r=0.4, tilt=0.3):
    """Exact torus samples within ~h of p0, in a frame tilted by `tilt` rad from the normal."""
    u0, v0 = torch.tensor(u0, dtype=torch.float64), torch.tensor(v0, dtype=torch.float64)
    du = gen_dirs[:, 0] * h / (R + r * torch.cos(v0))
    dv = gen_dirs[:, 1] * h / r
    u, v = u0 + du, v0 + dv
    pts = torch.stack([(R + r * torch.cos(v)) * torch.cos(u), (R + r * torch.cos(v)) *
                       torch.sin(u), r * torch.sin(v)], -1)
    s = _torus_from_params(np.array([u0.item()]), np.array([v0.item()]), R, r, None,
                                     0.0, 0)
    p0, n0, t0 = _t(s.points[0]), _t(s.normals[0]), _t(s.d1[0])
    Rt = frames.axis_angle_to_matrix(tilt * t0)
    e3 = Rt @ n0
    e1 = torch.linalg.cross(_t([0.3, 0.5, 0.8]), e3)
    e1 = e1 / e1.norm()
    frame = torch.stack([e1, torch.linalg.cross(e3, e1), e3], -1)
    loc = (pts - p0) @ frame
    return loc, frame, s


@pytest.mark.parametrize("order", [1, 2, 3, 4])
def test_convergence_order(gen, order):
    dirs = 2 * torch.rand(80, 2, generator=gen, dtype=torch.float64) - 1
    hs = [0.08, 0.04, 0.02, 0.01]
    nerr, kerr = [], []
    for h in hs:
        loc, frame, s = _torus_neighbourhood(h, dirs)
        f = jets.fit(loc[None, :, :2], loc[None, :, 2], order)
        g = diffgeo.from_jet(f.coeffs).squeeze()
        n = frame @ g.normal[0]
        n0 = _t(s.normals[0])
        nerr.append(float(torch.atan2(torch.linalg.cross(n, n0).norm(), (n * n0).sum())))
        kerr.append(max(abs(float(g.k1[0]) - s.k1[0]), abs(float(g.k2[0]) - s.k2[0])))
    ns = np.polyfit(np.log(hs), np.log(nerr), 1)[0]
    assert ns > order - 0.25, (nerr, ns)
    if order >= 2:
        ks = np.polyfit(np.log(hs), np.log(kerr), 1)[0]
        assert ks > order - 1 - 0.25, (kerr, ks)
