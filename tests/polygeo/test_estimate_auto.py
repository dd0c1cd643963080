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


def test_auto_equals_the_fixed_fit_it_chose():
    s = sy.sphere(2000, seed=44, noise=2e-3)
    P = s.noisy_points
    auto = differential_quantities(P, k="auto", order="auto", orient="none")
    pairs, counts = np.unique(np.c_[auto.order, auto.n_neighbors], axis=0, return_counts=True)
    o, n = pairs[np.argmax(counts)]
    sel = (auto.order == o) & (auto.n_neighbors == n) & (auto.status == 0)
    fixed = differential_quantities(P, k=int(n) - 1, order=int(o), orient="none")
    np.testing.assert_allclose(auto.normals[sel], fixed.normals[sel], atol=1e-12)
    np.testing.assert_allclose(auto.mean_curvature[sel], fixed.mean_curvature[sel],
                               rtol=1e-9, atol=1e-12)
