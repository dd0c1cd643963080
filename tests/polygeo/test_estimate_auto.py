"""Automatic order and neighbourhood size (order="auto", k="auto") against analytic truth."""

import numpy as np
import pytest

from polygeo import synthetic as sy
from polygeo.estimate import differential_quantities


def errors(res, s):
    """Median normal angle (deg, unoriented) and median relative error of |H|."""
    c = np.abs(np.einsum("ij,ij->i", res.normals, s.normals))
    ang = np.degrees(np.arccos(np.clip(c, 0.0, 1.0)))
    h = np.abs(np.abs(res.mean_curvature) - np.abs(s.mean_curvature)) / np.abs(s.mean_curvature)
    return float(np.median(ang)), float(np.median(h))


def best_fixed(P, s, orders=(2, 3, 4), ks=(16, 32, 64, 128)):
    out = [errors(differential_quantities(P, k=k, order=o, orient="none"), s)
           for o in orders for k in ks]
    return min(e[0] for e in out), min(e[1] for e in out)


@pytest.mark.parametrize("noise", [0.0, 1e-3])
def test_auto_close_to_best_fixed_setting(noise):
    """One call, no hint about the noise: within 2x of the best fixed (order, k) in hindsight."""
    s = sy.sphere(3000, seed=41, noise=noise)
    P = s.noisy_points
    auto = differential_quantities(P, k="auto", order="auto", orient="none")
    assert (auto.status == 0).mean() > 0.99
    n_auto, h_auto = errors(auto, s)
    n_best, h_best = best_fixed(P, s)
    floor_n, floor_h = 1e-5, 1e-8  # the metrics' float64 resolution
    assert max(n_auto, floor_n) < 2.0 * max(n_best, floor_n)
    assert max(h_auto, floor_h) < 2.0 * max(h_best, floor_h)


def test_auto_curvature_where_the_noise_spans_a_point_spacing():
    """Noise of about a point spacing (u = sigma^2 / <r^2> about 0.07 at the ICI size): H of
    every size is attenuated, less so the wider the fit, and the widest sizes win (order 2
    on 385 points); the ICI, which reads that recovery as a bias, no longer caps the
    curvature's size there (1.37x the best before)."""
    s = sy.cylinder(4000, seed=7, noise=0.05)
    P = s.noisy_points

    def h_err(r):
        sign = np.sign(np.einsum("ij,ij->i", r.normals, s.normals))
        return float(np.median(np.abs(r.mean_curvature * sign - s.mean_curvature)
                               / np.abs(s.mean_curvature)))

    auto = h_err(differential_quantities(P, k="auto", order="auto", orient="none",
                                         normal_check=False))
    best = min(h_err(differential_quantities(P, k=k, order=2, orient="none"))
               for k in (128, 256, 384))
    assert auto < 1.15 * best


def test_auto_higher_order_on_clean_wider_k_under_noise():
    clean = sy.torus(3000, seed=42)
    noisy = sy.torus(3000, seed=42, noise=3e-3)
    rc = differential_quantities(clean.points, k="auto", order="auto", orient="none")
    rn = differential_quantities(noisy.noisy_points, k="auto", order="auto", orient="none")
    assert np.median(rc.order) == 4
    assert np.median(rn.n_neighbors) > 2 * np.median(rc.n_neighbors)


def test_auto_does_not_depend_on_the_chunks():
    """k=auto chunk-independent: a point's choice pools its neighbours, whatever the chunk."""
    s = sy.torus(2500, seed=43, noise=1e-3)
    a = differential_quantities(s.noisy_points, k="auto", order="auto", orient="none")
    b = differential_quantities(s.noisy_points, k="auto", order="auto", orient="none",
                                batch_size=300)
    np.testing.assert_array_equal(a.order, b.order)
    np.testing.assert_array_equal(a.n_neighbors, b.n_neighbors)
    np.testing.assert_array_equal(a.normals, b.normals)
    np.testing.assert_array_equal(a.mean_curvature, b.mean_curvature)


def test_auto_equals_the_fixed_fits_it_chose():
    """Curvatures: the fixed fit at the reported (order, n_neighbors); normals: a fixed fit at
    one of the candidate settings (the normal has its own choice)."""
    s = sy.sphere(2000, seed=44, noise=2e-3)
    P = s.noisy_points
    cands = (12, 24, 48, 96)
    auto = differential_quantities(P, k="auto", order="auto", orient="none",
                                   k_candidates=cands)
    assert (auto.status == 0).all()
    pairs, counts = np.unique(np.c_[auto.order, auto.n_neighbors], axis=0, return_counts=True)
    o, n = pairs[np.argmax(counts)]
    sel = (auto.order == o) & (auto.n_neighbors == n)
    fixed = differential_quantities(P, k=int(n) - 1, order=int(o), orient="none")
    side = np.sign(np.einsum("ij,ij->i", auto.normals, fixed.normals))[sel]
    np.testing.assert_allclose(auto.mean_curvature[sel] * side, fixed.mean_curvature[sel],
                               rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(auto.gaussian_curvature[sel], fixed.gaussian_curvature[sel],
                               rtol=1e-9, atol=1e-12)
    # every normal is, up to its sign, that of a fixed fit at a candidate setting
    matched = np.zeros(len(P), dtype=bool)
    for order in (1, 2, 3, 4):
        for k in [c for c in cands if c + 1 >= (order + 1) * (order + 2) // 2]:
            f = differential_quantities(P, k=k, order=order, orient="none")
            matched |= np.abs(np.einsum("ij,ij->i", auto.normals, f.normals)) > 1 - 1e-12
    assert matched.all()
    # the principal directions stay orthonormal and tangent to the reported normal
    np.testing.assert_allclose(np.einsum("ij,ij->i", auto.d1, auto.normals), 0, atol=1e-12)
    np.testing.assert_allclose(np.cross(auto.normals, auto.d1), auto.d2, atol=1e-12)


@pytest.mark.parametrize("scale", [2.0**10, 2.0**-10])
def test_auto_choice_does_not_depend_on_the_unit(scale):
    """Scale-free: the same choices in other units (powers of 2: exact in floating point)."""
    s = sy.torus(2500, seed=45, noise=1e-3)
    a = differential_quantities(s.noisy_points, k="auto", order="auto", orient="none")
    b = differential_quantities(s.noisy_points * scale, k="auto", order="auto", orient="none")
    np.testing.assert_array_equal(a.order, b.order)
    np.testing.assert_array_equal(a.n_neighbors, b.n_neighbors)
    np.testing.assert_allclose(b.mean_curvature * scale, a.mean_curvature, rtol=1e-9,
                               atol=1e-9 * float(np.abs(a.mean_curvature).max()))
    np.testing.assert_allclose(b.normals, a.normals, atol=1e-9)


@pytest.mark.parametrize("noise", [0.0, 1e-3])
def test_auto_on_a_surface_family_outside_the_benchmark_grid(noise):
    """The wavy sheet (no part of bm_jets' grid, nothing tuned on it): within 1.5x of the best
    fixed (order, k) in hindsight, normal and H alike."""
    s = sy.wavy_sheet_mesh(70, 70, noise=noise, seed=46)
    P = s.noisy_points
    auto = differential_quantities(P, k="auto", order="auto", orient="none")
    n_auto, h_auto = errors(auto, s)
    n_best, h_best = best_fixed(P, s, orders=(1, 2, 3, 4), ks=(16, 32, 64, 128, 256))
    floor_n, floor_h = 1e-5, 1e-8
    assert max(n_auto, floor_n) < 1.5 * max(n_best, floor_n)
    assert max(h_auto, floor_h) < 1.5 * max(h_best, floor_h)


def test_pooled_median_equals_nanmedian():
    """The sorted-pool median of the choice equals NumPy's nanmedian (NaN, inf, padding)."""
    import warnings

    from polygeo._estimate_auto import _pooled_median

    rng = np.random.default_rng(47)
    a = rng.normal(size=(500, 4, 12, 2))
    a[rng.random(a.shape) < 0.3] = np.nan
    a[rng.random(a.shape) < 0.1] = np.inf
    pool = rng.integers(-1, 500, size=(300, 24))
    pool[:, 0] = np.arange(300)
    pool[5, 1:] = -1  # a pool of one
    a[pool[7]] = np.nan  # a pool with nothing valid
    x = np.where((pool < 0)[:, :, None, None, None], np.nan, a[np.maximum(pool, 0)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        ref = np.nanmedian(x, axis=1)
    got = _pooled_median(a, pool)
    assert np.isnan(got[7]).all()
    np.testing.assert_array_equal(got, ref)


def test_bias_rate_recovers_a_two_term_drift():
    """bias_rate: y_s = y_0 + B t_s + C u_s recovered exactly from noiseless values; the
    one-term fit recovers B of a pure t drift; too few well-posed sizes give NaN."""
    from polygeo._estimate_auto import bias_rate

    rng = np.random.default_rng(49)
    S, Q = 8, 5
    n = np.array([13, 17, 21, 25, 33, 49, 65, 97], dtype=np.float64)
    t = n / n[0]
    u = rng.uniform(0.5, 2.0, size=(Q, 1)) / n[None, :]
    y0, B, C = rng.normal(size=(Q, 1)), rng.normal(size=(Q, 1)), rng.normal(size=(Q, 1))
    v = 1.0 / n[None, :] ** 2 + np.zeros((Q, 1))
    ok = np.ones((Q, S), dtype=bool)
    coef, cov = bias_rate(y0 + B * t + C * u, v, ok, t, u)
    np.testing.assert_allclose(coef, np.c_[B, C], rtol=1e-8, atol=1e-10)
    assert (cov[:, :2] > 0).all()
    coef1, cov1 = bias_rate(y0 + B * t, v, ok, t)
    np.testing.assert_allclose(coef1[:, 0], B[:, 0], rtol=1e-10)
    assert (coef1[:, 1] == 0).all() and (cov1[:, 1:] == 0).all()
    ok2 = ok.copy()
    ok2[:, 2:] = False  # two sizes: one difference, not enough for two coefficients
    coef2, _ = bias_rate(y0 + B * t + C * u, v, ok2, t, u)
    assert np.isnan(coef2).all()
    coef3, _ = bias_rate(y0 + B * t, v, ok2, t)
    np.testing.assert_allclose(coef3[:, 0], B[:, 0], rtol=1e-10)


def test_noise_attenuates_small_neighbourhood_curvature():
    """The premise of the attenuation term: under noise, a small neighbourhood's H is biased
    towards 0 (noisy tangential coordinates), a bias that falls as the neighbourhood grows
    (mean of the oriented H over the true H, which is the same at every point)."""
    s = sy.sphere(4000, seed=50, noise=2e-2)
    ratios = []
    for k in (12, 100, 400):
        r = differential_quantities(s.noisy_points, k=k, order=2, orient="none")
        sign = np.sign(np.einsum("ij,ij->i", r.normals, s.normals))
        ratios.append(float(np.mean(r.mean_curvature * sign) / np.mean(s.mean_curvature)))
    assert ratios[0] < 0.5 < ratios[1] < ratios[2]
    assert ratios[2] > 0.8


def test_auto_normal_on_a_lattice_with_little_noise():
    """A structured cylinder (not bm_jets' size) at noise 1e-4: a plane fitted on a
    neighbourhood symmetric about the point has no bias, while a curved jet's normal moves
    with the point's own noise along the surface. Automatic normal within 1.5x of the best
    fixed (order, k) in hindsight, H as well."""
    s = sy.cylinder_mesh(120, noise=1e-4, seed=51)
    P = s.noisy_points
    auto = differential_quantities(P, k="auto", order="auto", orient="none")
    n_auto, h_auto = errors(auto, s)
    n_best, h_best = best_fixed(P, s, orders=(1, 2, 3, 4), ks=(16, 32, 64, 128, 256))
    assert n_auto < 1.5 * n_best
    assert h_auto < 1.5 * h_best


def test_curved_jet_normal_moves_with_the_tangential_noise():
    """The premise of the tangential term: with isotropic noise of deviation sigma, a wide
    quadratic fit's normal, taken where the noisy point lies, is off by about sigma |II|
    (``|II|^2 = k1^2 + k2^2``) however many neighbours average the heights."""
    s = sy.sphere(6000, seed=52, noise=2e-3)
    r = differential_quantities(s.noisy_points, k=400, order=2, orient="none")
    c = np.abs(np.einsum("ij,ij->i", r.normals, s.normals))
    msq = float(np.mean(np.arccos(np.clip(c, 0.0, 1.0)) ** 2))
    floor = s.noise_sigma**2 * float(np.mean(s.k1**2 + s.k2**2))
    assert 0.7 * floor < msq < 2.0 * floor


def test_plane_alias_and_the_share_that_follows():
    """plane_alias: the plane's slopes against the highest order's, less the variance of the
    difference; the share of tangential noise its neighbourhood follows is 0 for a wide
    margin, 1 for none, 1/2 where the margin equals sigma."""
    from polygeo._estimate_auto import _rank_gap, plane_alias

    Q, O, S = 3, 2, 4
    val = np.zeros((Q, O, S, 4))
    val[:, 0, :, 0] = 0.3  # the plane's slope a10
    val[:, 0, :, 1] = -0.1
    val[:, 1, :, 3] = 2.0  # |II|^2 of the curved fit
    v3 = np.zeros((Q, O, S, 3))
    v3[:, 0] = 0.001
    v3[:, 1] = 0.004
    ok = np.ones((Q, O, S), dtype=bool)
    ok[0, 1, 0] = False  # the curved fit not well posed at the smallest size of query 0
    s2 = np.array([0.5, 1.0, 2.0])
    gap = np.array([[0.0, np.sqrt(0.5), 1e6, np.inf]] * 3)
    out = plane_alias(val, v3, ok, s2, gap)
    expect = 0.3**2 + 0.1**2 - 2 * 0.003
    assert np.isnan(out["alias"][0, 0])
    np.testing.assert_allclose(out["alias"][1:], expect)
    np.testing.assert_allclose(out["alias"][0, 1:], expect)
    np.testing.assert_allclose(out["tangential"], 2.0 * s2)
    np.testing.assert_allclose(out["follow"][0], [1.0, 0.5, 0.0, 1.0], atol=1e-12)
    dist = np.array([[0.0, 1.0, 1.5, 3.0, np.inf]])
    np.testing.assert_allclose(_rank_gap(dist, np.array([1, 2, 4, 5])),
                               [[1.0, 0.5, np.inf, np.inf]])
