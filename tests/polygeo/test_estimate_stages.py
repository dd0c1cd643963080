"""The stages of polygeo.estimate: fused compiled kernels against the unfused reference."""

import numpy as np
import pytest

from polygeo import synthetic as sy
from polygeo._estimate_auto import (
    auto_orders,
    best_setting,
    candidate_sizes,
    choose,
    point_mse,
    point_statistics,
    store_mse,
)
from polygeo._estimate_numba import Quantities
from polygeo._estimate_stages import (
    Neighbourhoods,
    empty_quantities,
    fit_fused,
    fit_unfused,
)
from polygeo.estimate import _settings, differential_quantities
from polygeo.status import Status


def settings(**kw):
    base = dict(k=20, radius=None, rings=None, order=2, weights=None, orient="none",
                monge=False, forms=False, batch_size=131072, progress=False, workers=1,
                backend="auto", k_candidates=(12, 24, 48), auto_orders=(2, 3, 4), alpha=0.01,
                max_cond=None, interpolate=False, requires_grad=False)
    base.update(kw)
    return _settings(**base)


def noisy_sphere(n=600, noise=1e-3, seed=0):
    rng = np.random.default_rng(seed)
    P = sy.sphere(n, seed=seed).points
    return np.ascontiguousarray(P + noise * rng.normal(size=P.shape))


def one_chunk(P, s):
    hoods = Neighbourhoods(P, np.isfinite(P).all(1), faces=None, settings=s, graph=False)
    (q,) = list(hoods.chunks(s.batch_size, False))
    nbr, dist = hoods.query(q)
    return hoods, q, nbr, dist


def assert_same(a: Quantities, b: Quantities, rtol=1e-9):
    for name in Quantities._fields:
        x, y = getattr(a, name), getattr(b, name)
        if x.dtype.kind in "iub":
            np.testing.assert_array_equal(x, y, err_msg=name)
        else:
            scale = max(float(np.nanmax(np.abs(x))), 1e-300)
            np.testing.assert_allclose(x, y, rtol=rtol, atol=rtol * scale, err_msg=name)


@pytest.mark.parametrize("order", [1, 2, 3, 4])
@pytest.mark.parametrize("weights, interpolate", [(None, False), ("gaussian", False),
                                                  (None, True)])
def test_fused_stage_equals_unfused_reference(order, weights, interpolate):
    P = noisy_sphere()
    s = settings(order=order, weights=weights, interpolate=interpolate)
    hoods, q, nbr, dist = one_chunk(P, s)
    fused = empty_quantities(len(P), s.n_coeffs)
    kuse = np.full(q.size, 21, dtype=np.int64)
    fit_fused(hoods, q, nbr, dist, kuse, fused, order=order, gaussian=weights == "gaussian",
              settings=s)
    ref = empty_quantities(len(P), s.n_coeffs)
    fit_unfused(hoods, q, nbr, dist, [21], ref, settings=s)
    assert (fused.status == Status.OK).mean() > 0.95
    assert_same(fused, ref)


def auto_sizes(hoods, q, nbr, dist, s):
    """The live ``k="auto"`` choice on one chunk: (order index, rows) for the curvatures."""
    orders, sizes = auto_orders(s), candidate_sizes(hoods, s)
    stats = point_statistics(hoods, q, nbr, dist, orders=orders, sizes=sizes, settings=s)
    full = {k: np.zeros((len(hoods.P),) + v.shape[1:], v.dtype) for k, v in stats.items()}
    for k, v in stats.items():
        full[k][q] = v  # rows of the statistics: point indices (the chunk is in grid order)
    pool = nbr[:, :24]
    table = np.full(stats["var"].shape[1:] + (len(hoods.P),), np.nan, dtype=np.float32)
    store_mse(table, q, point_mse(full, q, pool, sizes, orders))
    return best_setting(choose(full, table, pool, sizes, orders)["curvature"], sizes)


@pytest.mark.parametrize("parallel_min", [1, 10**9])
def test_fused_stage_per_query_sizes_parallel_and_serial(parallel_min):
    """k="auto"'s fit: a size per query, the same fused (both compilations) and unfused."""
    P = noisy_sphere(800, noise=3e-3, seed=1)
    s = settings(k="auto", order=2, k_candidates=(8, 12, 16, 24, 32, 48, 64, 96, 128))
    hoods, q, nbr, dist = one_chunk(P, s)
    order_i, kuse = auto_sizes(hoods, q, nbr, dist, s)
    assert (order_i == 0).all()
    assert kuse.shape == q.shape and kuse.min() >= 1 and kuse.max() <= nbr.shape[1]
    assert np.unique(kuse).size > 1  # the test exercises several sizes
    fused = empty_quantities(len(P), s.n_coeffs)
    fit_fused(hoods, q, nbr, dist, kuse, fused, order=2, gaussian=False, settings=s,
              parallel_min=parallel_min)
    ref = empty_quantities(len(P), s.n_coeffs)
    fit_unfused(hoods, q, nbr, dist, [kuse], ref, settings=s)
    assert_same(fused, ref)


def test_auto_k_sizes_grow_with_noise():
    """The live k="auto" rule: noisier data -> larger neighbourhoods (order 2 fixed)."""
    sizes = []
    for noise in (0.0, 1e-2):
        P = noisy_sphere(3000, noise=noise, seed=2)
        r = differential_quantities(P, k="auto", order=2, orient="none",
                                    k_candidates=(12, 24, 48, 96, 192))
        assert (r.order == 2).all()
        sizes.append(np.median(r.n_neighbors))
    assert sizes[1] > sizes[0]


def test_settings_keep_order_and_k():
    s = settings(order=3, k=15)
    assert (s.order, s.orders, s.k, s.sizes) == (3, (3,), 15, (16,))
    s = settings(order="auto", auto_orders=(4, 2, 2), k="auto", k_candidates=(24, 12))
    assert (s.order, s.orders, s.k, s.sizes) == ("auto", (2, 4), "auto", (13, 25))
    assert s.n_coeffs == 15


def test_driver_chunking_does_not_change_results():
    """Chunks of 97 points (serial kernels, many duplicate-free chunks) equal one chunk."""
    P = noisy_sphere(1500, seed=3)
    a = differential_quantities(P, k=20, order=3)
    b = differential_quantities(P, k=20, order=3, batch_size=97)
    for name in ("normals", "k1", "k2", "coeffs", "frame", "residual"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(a.status, b.status)
