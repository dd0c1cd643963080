"""order="auto"/k="auto" on a surface with fine detail (the failure seen on real scans).

On the Stanford bunny scans, 75 % of the residual variance of a wide quadratic fit (k=100)
is shared by two independent scans: fine real detail, not correlated scanner noise. The
synthetic analogue: a gently curved patch with detail of a wavelength of 12 point spacings
(a sum of cosines in random directions), i.i.d. noise on top, and the analytic normals of
the detailed surface as the truth.
"""

from dataclasses import replace

import numpy as np
import pytest

import polygeo.estimate as E
from polygeo import _estimate_auto as ea
from polygeo import synthetic as sy
from polygeo._estimate_stages import AUTO_K_CANDIDATES, Neighbourhoods
from polygeo.estimate import _settings, differential_quantities


def detailed_patch(n_side=90, lam=12.0, slope=0.06, noise=0.07, radius=40.0, seed=0,
                   n_waves=24):
    """Jittered grid (spacing 1) of ``z = (x^2 + y^2) / (2 radius) + detail`` plus noise.

    The detail: ``n_waves`` cosines of wavelength ``lam`` in random directions and phases,
    RMS slope about ``slope`` (rad); i.i.d. Gaussian noise of ``noise`` along z. Returns the
    noisy points, the analytic unit normals of the detailed surface and the points at least
    12 spacings inside the patch.
    """
    rng = np.random.default_rng(seed)
    g = np.arange(n_side, dtype=float) - (n_side - 1) / 2
    x, y = (a.ravel() + rng.uniform(-0.3, 0.3, n_side * n_side) for a in np.meshgrid(g, g))
    th, ph = rng.uniform(0, 2 * np.pi, (2, n_waves))
    w = 2 * np.pi / lam
    wx, wy = w * np.cos(th), w * np.sin(th)
    arg = x[:, None] * wx + y[:, None] * wy + ph
    amp = 2.0 * slope / (w * np.sqrt(n_waves))
    z = (x * x + y * y) / (2 * radius) + amp * np.cos(arg).sum(1)
    zx = x / radius - amp * (np.sin(arg) * wx).sum(1)
    zy = y / radius - amp * (np.sin(arg) * wy).sum(1)
    normals = np.c_[-zx, -zy, np.ones_like(zx)]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    points = np.c_[x, y, z + rng.normal(scale=noise, size=x.size)]
    inner = (np.abs(x) < n_side / 2 - 12) & (np.abs(y) < n_side / 2 - 12)
    return points, normals, inner


def rms_angle(res, normals, sel=None) -> float:
    """RMS angle (deg) between the estimated and the true normal lines."""
    sel = np.arange(len(normals)) if sel is None else sel
    c = np.abs(np.einsum("ij,ij->i", np.asarray(res.normals)[sel], normals[sel]))
    ang = np.degrees(np.arccos(np.clip(c, 0.0, 1.0)))
    return float(np.sqrt(np.mean(ang * ang)))


def ici_mean_noise(val, gvar, rss, dof, ok, oi, o, sizes, s2):
    """The normal's noise as the order's ICI mean (the rule before ``_normal_noise``)."""
    return s2


def test_auto_normal_does_not_lose_to_the_default_on_fine_detail():
    P, normals, inner = detailed_patch()
    default = rms_angle(differential_quantities(P, k=20, order=2, orient="none"), normals,
                        inner)
    wide = rms_angle(differential_quantities(P, k=100, order=2, orient="none"), normals,
                     inner)
    got = rms_angle(differential_quantities(P, k="auto", order="auto", orient="none"),
                    normals, inner)
    assert wide > 1.3 * default  # smoothing the detail away loses: the case discriminates
    assert got <= default


@pytest.mark.parametrize("surface", ["torus", "sphere"])
def test_fine_detail_rules_cost_little_on_iid_noise(surface):
    """On i.i.d. noise (the benchmark grid's kind of data) the rules for fine detail cost
    little: the automatic normal is within 1.15x of the best of a few fixed settings.

    Measured (RMS deg): torus auto 1.13, best fixed 1.21 (k=50, order 2); sphere auto 0.343,
    best fixed 0.324 (k=100, order 2; every rule off gave 0.310).
    """
    s = getattr(sy, surface)(3000, seed=47, noise=1e-3)
    got = rms_angle(differential_quantities(s.noisy_points, k="auto", order="auto",
                                            orient="none"), s.normals)
    fixed = [rms_angle(differential_quantities(s.noisy_points, k=k, order=o, orient="none"),
                       s.normals) for k, o in ((20, 2), (50, 2), (100, 2), (50, 1), (100, 3))]
    assert got < 1.15 * min(fixed)


def test_measured_drift_is_the_squared_change_less_its_variance():
    Q, O, S = 2, 1, 4
    val = np.zeros((Q, O, S, 4))
    val[0, 0, :, 0] = [9.0, 1.0, 2.0, 4.0]  # slope a10 per size; a01 = 0
    val[1, 0, :, 1] = [0.0, 3.0, 3.0, 3.0]
    v3 = np.zeros((Q, O, S, 3))
    v3[..., :2] = np.array([4.0, 2.0, 1.0, 0.5])[None, None, :, None]
    ok = np.ones((Q, O, S), dtype=bool)
    dof = np.array([2, 18, 30, 60])[None, None, :].repeat(Q, 0)  # order 2: 6 coefficients
    ok[1, 0, 2] = False
    got = ea.measured_drift(val, v3, ok, dof, (2,))
    # reference: the first size with 3 residual degrees of freedom per coefficient (18)
    want0 = [np.nan, 0.0 - 0.0, (2 - 1) ** 2 - 2 * (2 - 1), (4 - 1) ** 2 - 2 * (2 - 0.5)]
    np.testing.assert_allclose(got[0, 0], want0)
    np.testing.assert_allclose(got[1, 0], [np.nan, 0.0, np.nan, -2 * (2 - 0.5)])


def test_measured_drift_is_nan_without_a_well_determined_fit():
    val = np.ones((1, 1, 3, 4))
    v3 = np.ones((1, 1, 3, 3))
    ok = np.ones((1, 1, 3), dtype=bool)
    dof = np.array([[[1, 2, 5]]])  # never 3 per coefficient of a plane (9)
    assert np.isnan(ea.measured_drift(val, v3, ok, dof, (1,))).all()


def test_a_setting_most_neighbours_cannot_fit_is_not_chosen():
    """Pooled error of a setting defined at 2 of 5 neighbours: infinite (the rule before:
    the median of the 2, which made it look best)."""
    sizes = np.array([13, 25])
    n = 5
    stats = {"size": np.ones((n, 1), dtype=np.int64), "var": np.ones((n, 1, 2, 2)),
             "u": np.zeros((n, 1, 2))}
    table = np.ones((1, 2, 2, n), dtype=np.float32)
    table[0, 0, :, :] = np.nan
    table[0, 0, :, :2] = 1e-6
    pool = np.arange(n)[None, :]
    score = ea.choose(stats, table, pool, sizes, (2,))
    order_i, k = ea.best_setting(score["normal"], sizes)
    assert k[0] == 25


@pytest.mark.parametrize("u, curvature_size", [(0.0, 13), (0.5 * ea._U_LIFT, 13),
                                                 (2.0 * ea._U_LIFT, 49)])
def test_the_ici_cap_of_the_curvatures_is_lifted_under_large_noise(u, curvature_size):
    """The pooled ICI size caps the normal's sizes always, the curvatures' only where the
    noise share u = sigma^2 / <r^2> at that size is below _U_LIFT (H's attenuation, which
    falls with the size, would read as a bias setting in)."""
    sizes = np.array([13, 25, 49])
    n = 5
    stats = {"size": np.zeros((n, 1), dtype=np.int64), "var": np.ones((n, 1, 3, 2)),
             "u": np.full((n, 1, 3), u)}
    table = np.ones((1, 3, 2, n), dtype=np.float32)
    table[0, 2] = 1e-3  # the widest size has the least error, for both quantities
    pool = np.arange(n)[None, :]
    score = ea.choose(stats, table, pool, sizes, (2,))
    assert ea.best_setting(score["normal"], sizes)[1][0] == 13  # capped at the ICI size
    assert ea.best_setting(score["curvature"], sizes)[1][0] == curvature_size
    stats["size"][:] = 2  # no cap: both take the widest
    score = ea.choose(stats, table, pool, sizes, (2,))
    assert ea.best_setting(score["normal"], sizes)[1][0] == 49
    assert ea.best_setting(score["curvature"], sizes)[1][0] == 49


def test_weak_floor_follows_the_truncation_scaling():
    sizes = np.array([13, 17, 25, 33])
    dof = np.array([7, 11, 19, 27])[None, None, :]  # order 2: 6 coefficients, 18 needed
    rss = np.array([0.0, 0.0, 38.0, 81.0])[None, None, :]  # first well-determined: s2 = 2
    ok = np.ones((1, 1, 4), dtype=bool)
    got = ea._weak_floor(rss, dof, ok, 0, 2, sizes)
    np.testing.assert_allclose(got[0], 2.0 * np.minimum(sizes / 25.0, 1.0) ** 3)
    none = ea._weak_floor(rss, np.minimum(dof, 17), ok, 0, 2, sizes)
    np.testing.assert_array_equal(none, 0.0)


def test_normal_noise_is_the_narrowest_well_determined_fits():
    """ICI accepts every size (equal slopes); the residual variance grows with the size (detail
    the wide fits cannot follow). The normal's noise: the fits up to the first with 3 degrees
    of freedom per coefficient (the rule before: the mean over every accepted size)."""
    sizes = np.array([13, 25, 49, 97])
    dof = np.array([7, 19, 43, 91])[None, None, :]  # order 2: 6 coefficients, 18 needed
    s2 = np.array([1.0, 1.0, 2.0, 4.0])  # residual variance per size
    rss = (s2 * dof[0, 0])[None, None, :]
    val = np.zeros((1, 1, 4, 3))  # slopes and H per size: equal, so ICI accepts every size
    gvar = np.ones((1, 1, 4, 3))
    ok = np.ones((1, 1, 4), dtype=bool)
    args = (val, gvar, rss, dof, ok, 0, 2, sizes, np.array([9.0]))
    # the first fit (weak, the only one until a well-determined one; its truncation floor
    # 1.0 (13 / 25)^3 does not bind) and the size-25 fit
    np.testing.assert_allclose(ea._normal_noise(*args), [1.0])
    np.testing.assert_allclose(ea._normal_noise(*args[:-3], 1, sizes, np.array([9.0])),
                               [9.0])  # the plane: the value it is given
    chosen, mean = ea._ici(val, gvar, rss, dof, ok, 0, 6)
    assert chosen[0] == 3
    np.testing.assert_allclose(mean, [(1.0 + 1.0 + 2.0 + 4.0) / 4])


def normal_noise(P, narrowest: bool, sel) -> np.ndarray:
    """Median over ``sel`` of the normal's noise variance of orders 2, 3, 4 (auto statistics).

    ``narrowest``: the normal's (:func:`polygeo._estimate_auto._normal_noise`); else the
    order's ICI mean over every accepted size (the rule before).
    """
    s = _settings(k="auto", radius=None, rings=None, order="auto", weights=None,
                  orient="none", monge=False, forms=False, batch_size=131072, progress=False,
                  workers=1, backend="auto", k_candidates=AUTO_K_CANDIDATES,
                  auto_orders=(2, 3, 4), alpha=0.01, max_cond=None, interpolate=False,
                  requires_grad=False)
    s = replace(s, max_cond={1: min(s.max_cond.values()), **s.max_cond})  # as fit_auto
    hoods = Neighbourhoods(P, np.isfinite(P).all(1), faces=None, settings=s, graph=False)
    (q,) = list(hoods.chunks(s.batch_size, False))
    nbr, dist = hoods.query(q)
    orders, sizes = ea.auto_orders(s), ea.candidate_sizes(hoods, s)
    st = ea.point_statistics(hoods, q, nbr, dist, orders=orders, sizes=sizes, settings=s)
    s2 = st["s2n" if narrowest else "s2"][sel[q]]
    return np.median(s2[:, [orders.index(o) for o in (2, 3, 4)]], 0)


def test_normal_noise_is_the_noise_not_the_truncation():
    """Truth: the variance of the added noise along the normal. On a coarse torus (3,000
    points) the wide fits' residuals hold truncation: their mean over the accepted sizes (the
    rule before) is 2-5x the noise; the narrowest well-determined fits' is the noise."""
    s = sy.torus(3000, seed=47, noise=1e-3)
    d = s.noisy_points - s.points
    sig2 = np.mean(np.einsum("ij,ij->i", d, s.normals) ** 2)
    every = np.ones(len(d), dtype=bool)
    new = normal_noise(s.noisy_points, True, every) / sig2
    old = normal_noise(s.noisy_points, False, every) / sig2
    assert np.all((new > 0.85) & (new < 1.2)), new
    assert np.all(old > 1.5), old


def test_normal_noise_does_not_count_the_fine_detail():
    """The same patch with and without its fine detail (same noise): the normal's noise from
    the narrowest fits barely moves; the mean over the accepted sizes grows with the detail."""
    P, _, inner = detailed_patch(n_side=60)
    flat, _, _ = detailed_patch(n_side=60, slope=0.0)
    for narrowest, lo, hi in ((True, 0.95, 1.06), (False, 1.1, np.inf)):
        ratio = (normal_noise(P, narrowest, inner)
                 / normal_noise(flat, narrowest, inner))
        assert np.all((ratio > lo) & (ratio < hi)), (narrowest, ratio)


@pytest.mark.parametrize("seed", [0, 1])
def test_normal_noise_from_the_narrowest_fits_on_fine_detail(monkeypatch, seed):
    """Against the detailed patch's analytic normals: the normal's noise from the narrowest
    well-determined fits is closer than the mean over the accepted sizes (measured RMS 0.93 vs
    0.99 deg, seed 0; 0.85 vs 0.93, seed 1, where the rule before lost to the default's
    0.93), and not worse than the default."""
    P, normals, inner = detailed_patch(seed=seed)
    default = rms_angle(differential_quantities(P, k=20, order=2, orient="none"), normals,
                        inner)
    # the per-point choice itself (no held-out check against the default, _estimate_check)
    monkeypatch.setattr(E, "check_normals", lambda *args: {})
    got = {}
    for narrowest in (True, False):
        if not narrowest:
            monkeypatch.setattr(ea, "_normal_noise", ici_mean_noise)
        res = differential_quantities(P, k="auto", order="auto", orient="none")
        got[narrowest] = rms_angle(res, normals, inner)
    assert got[True] < 0.96 * got[False]
    assert got[True] < default
