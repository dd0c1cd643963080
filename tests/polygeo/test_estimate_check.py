"""The held-out check of the automatic normal against fixed settings (_estimate_check)."""

import numpy as np
import pytest

import polygeo.estimate as E
from polygeo import _estimate_check as ec
from polygeo import synthetic as sy
from polygeo.estimate import differential_quantities


def test_offset_score_is_the_squared_sine_of_the_tilt():
    """One fitted point at the origin, held-out points along x and y of a plane z = 0: a
    normal tilted by ``t`` about y gives ``sin(t)^2`` along x and 0 along y; a pair at
    distance 0 is skipped."""
    P = np.array([[0.0, 0, 0], [2.0, 0, 0], [0, 3.0, 0], [0, 0, 0]])
    t = 0.3
    n = np.array([[np.sin(t), 0.0, np.cos(t)]])
    scores, valid = ec.offset_scores(P, np.array([0]), np.array([1]), [n], m=1)
    np.testing.assert_allclose(scores, [[np.sin(t) ** 2]])
    scores, _ = ec.offset_scores(P, np.array([0]), np.array([2]), [n], m=1)
    np.testing.assert_allclose(scores, [[0.0]], atol=1e-30)
    scores, valid = ec.offset_scores(P, np.array([0]), np.array([1, 2, 3]), [n], m=3)
    np.testing.assert_allclose(scores, [[np.sin(t) ** 2 / 2]])  # the duplicate skipped
    assert valid.all()


def test_offset_scores_estimate_the_difference_of_mean_squared_errors():
    """A noisy plane, normals with random tilts of known spread (independent of the noise):
    twice the mean score difference is the difference of the mean squared normal errors
    (rad^2), whatever the noise adds to both."""
    rng = np.random.default_rng(0)
    n_side = 120
    g = np.arange(n_side, dtype=float)
    x, y = (c.ravel() + rng.uniform(-0.3, 0.3, n_side * n_side) for c in np.meshgrid(g, g))
    P = np.c_[x, y, rng.normal(scale=0.2, size=x.size)]
    held = rng.random(len(P)) < 0.1
    a, b = np.flatnonzero(~held), np.flatnonzero(held)
    normals, mse = [], []
    for tau in (0.02, 0.05):
        d = rng.normal(scale=tau, size=(a.size, 2))
        n = np.c_[d, np.ones(a.size)]
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        normals.append(n)
        mse.append(np.mean(np.arccos(n[:, 2]) ** 2))
    scores, valid = ec.offset_scores(P, a, b, normals)
    v = ec.held_out_verdict(scores[0, valid], scores[1, valid])
    assert v["dmse"] == pytest.approx(mse[0] - mse[1], rel=0.15)
    assert v["better"] is False  # the first ("automatic") is the better one
    v = ec.held_out_verdict(scores[1, valid], scores[0, valid])
    assert v["better"] is True and v["dmse"] > 3 * v["se"]


def test_verdict_needs_significance_and_size():
    rng = np.random.default_rng(1)
    base = rng.uniform(0.5, 1.5, 4000)
    # better by 5 % of the level and clearly significant: the default
    assert ec.held_out_verdict(base * 1.05, base)["better"] is True
    # significant but below REL_MIN of the level (the criterion's own bias): kept
    assert ec.held_out_verdict(base * (1 + ec.REL_MIN / 4), base)["better"] is False
    # large but not significant (the difference is noise): kept
    noisy = base + rng.normal(scale=5.0, size=base.size)
    assert ec.held_out_verdict(noisy + 0.05, base)["better"] is False
    v = ec.held_out_verdict(np.ones(1), np.zeros(1))
    assert v["better"] is False and np.isnan(v["dmse"])


def test_too_few_points_keep_the_automatic_normal():
    s = sy.sphere(500, seed=3, noise=1e-3)
    hoods_P = np.asarray(s.noisy_points, dtype=np.float64)
    v = ec.check_normals(hoods_P, np.ones(len(hoods_P), bool), None, None)
    assert v["chosen"] == "auto" and "held-out" in v["skipped"]


def _rms(res, truth, sel=None):
    sel = np.arange(len(truth)) if sel is None else sel
    c = np.abs(np.einsum("ij,ij->i", np.asarray(res.normals)[sel], truth[sel]))
    return float(np.sqrt(np.mean(np.degrees(np.arccos(np.clip(c, 0, 1))) ** 2)))


def test_check_keeps_the_automatic_normal_on_iid_noise(monkeypatch):
    """A noisy sphere (the automatic normal is 3x better than the default): kept."""
    got = {}

    def spy(*args):
        got.update(ec.check_normals(*args))
        return got

    monkeypatch.setattr(E, "check_normals", spy)
    s = sy.sphere(4000, seed=5, noise=1e-3)
    res = differential_quantities(s.noisy_points, k="auto", order="auto", orient="none")
    default = differential_quantities(s.noisy_points, orient="none")
    assert got["chosen"] == "auto" and got["default"]["dmse"] < 0
    assert _rms(res, s.normals) < 0.5 * _rms(default, s.normals)


def test_check_gives_the_default_normal_where_held_out_points_prefer_it(monkeypatch):
    """Forced verdict: the default's normals replace the automatic ones (lines equal), the
    curvatures follow their sign (H's magnitude unchanged)."""
    monkeypatch.setattr(ec, "held_out_verdict", lambda sa, sd, rel=0.0: dict(better=rel > 0))
    s = sy.torus(3000, seed=7, noise=1e-3)
    res = differential_quantities(s.noisy_points, k="auto", order="auto", orient="none")
    default = differential_quantities(s.noisy_points, orient="none")
    dot = np.einsum("ij,ij->i", res.normals, default.normals)
    ok = (res.status == 0) & (default.status == 0)
    np.testing.assert_allclose(np.abs(dot[ok]), 1.0, atol=1e-12)
    monkeypatch.setattr(ec, "held_out_verdict", lambda sa, sd, rel=0.0: dict(better=False))
    kept = differential_quantities(s.noisy_points, k="auto", order="auto", orient="none")
    np.testing.assert_allclose(np.abs(res.mean_curvature), np.abs(kept.mean_curvature))
    sign = np.sign(np.einsum("ij,ij->i", res.normals, kept.normals))
    np.testing.assert_allclose(res.mean_curvature, sign * kept.mean_curvature)


def test_normal_check_false_keeps_each_points_own_choice(monkeypatch):
    """``normal_check=False``: no check (a forced verdict for the default changes nothing)."""
    s = sy.torus(2000, seed=9, noise=1e-3)
    monkeypatch.setattr(ec, "held_out_verdict", lambda sa, sd, rel=0.0: dict(better=False))
    own = differential_quantities(s.noisy_points, k="auto", order="auto", orient="none")
    monkeypatch.setattr(ec, "held_out_verdict", lambda sa, sd, rel=0.0: dict(better=rel > 0))
    off = differential_quantities(s.noisy_points, k="auto", order="auto", orient="none",
                                  normal_check=False)
    np.testing.assert_array_equal(off.normals, own.normals)
    on = differential_quantities(s.noisy_points, k="auto", order="auto", orient="none")
    assert not np.array_equal(on.normals, own.normals)


def test_normal_check_must_be_a_bool():
    with pytest.raises(TypeError, match="normal_check"):
        differential_quantities(np.random.default_rng(0).normal(size=(50, 3)),
                                normal_check="yes")


def test_tiles_never_run_the_check():
    """One verdict per cloud, never per tile: tiled runs pass ``normal_check=False``."""
    from polygeo.tiling import TileSettings

    assert TileSettings(k="auto", order="auto").estimator_kwargs()["normal_check"] is False
    assert "normal_check" not in TileSettings(k="auto").estimator_kwargs()


def test_widest_alternative_is_order_2_at_the_largest_size_tried(monkeypatch):
    from polygeo._estimate_stages import AUTO_K_CANDIDATES

    seen = []
    monkeypatch.setattr(E, "check_normals", lambda P, finite, out, s: seen.append(s) or {})
    pts = sy.sphere(600, seed=2, noise=1e-3).noisy_points
    differential_quantities(pts, k="auto", order="auto", orient="none")
    (s,) = seen
    w = ec.widest_settings(s, 10_000)
    assert (w.k, w.sizes, w.order) == (max(AUTO_K_CANDIDATES), (max(AUTO_K_CANDIDATES) + 1,), 2)
    assert w.max_cond == {2: s.max_cond[2]} and w.progress is False
    w = ec.widest_settings(s, 100)  # capped by the points there are
    assert (w.k, w.sizes) == (99, (100,))
    assert [name for name, _, _ in ec.alternatives(s, 10_000)] == ["default", "widest"]
    assert [rel for _, _, rel in ec.alternatives(s, 10_000)] == [ec.REL_MIN, 0.0]


def test_check_gives_the_widest_normal_where_held_out_points_prefer_it(monkeypatch):
    """Forced verdict for the widest fit: its normals (order 2 on the widest size tried)
    replace the automatic ones."""
    monkeypatch.setattr(ec, "held_out_verdict", lambda sa, sd, rel=0.0: dict(better=rel == 0))
    s = sy.torus(3000, seed=7, noise=1e-3)
    res = differential_quantities(s.noisy_points, k="auto", order="auto", orient="none")
    wide = differential_quantities(s.noisy_points, k=384, order=2, orient="none")
    dot = np.einsum("ij,ij->i", res.normals, wide.normals)
    ok = (res.status == 0) & (wide.status == 0)
    np.testing.assert_allclose(np.abs(dot[ok]), 1.0, atol=1e-12)


def test_check_takes_the_widest_fit_under_noise_comparable_to_the_spacing(monkeypatch):
    """bm_jets' open cylinder (10k vertices) at noise 0.1 % of the diagonal: the per-point
    choice leaves the normal 27 % worse than the widest quadratic (median 0.218 against 0.171
    deg); the held-out points prefer the widest fit (z about 5) and the checked normal is
    within 5 % of it, against the analytic normals."""
    got = {}

    def spy(*args):
        got.update(ec.check_normals(*args))
        return got

    monkeypatch.setattr(E, "check_normals", spy)
    s = sy.cylinder_mesh(174, noise=1e-3, seed=0)
    P = s.noisy_points

    def med(res):
        c = np.abs(np.einsum("ij,ij->i", np.asarray(res.normals), s.normals))
        return float(np.median(np.degrees(np.arccos(np.clip(c, 0, 1)))))

    checked = med(differential_quantities(P, k="auto", order="auto", orient="none"))
    own = med(differential_quantities(P, k="auto", order="auto", orient="none",
                                      normal_check=False))
    wide = med(differential_quantities(P, k=384, order=2, orient="none"))
    assert got["chosen"] == "widest" and got["widest"]["dmse"] > 3 * got["widest"]["se"]
    assert own > 1.15 * wide  # the per-point choice alone loses here
    assert checked <= 1.05 * wide
