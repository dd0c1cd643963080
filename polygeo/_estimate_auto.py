"""Automatic jet order and neighbourhood size (``order="auto"`` and/or ``k="auto"``).

Used by :func:`polygeo.estimate.differential_quantities` on one k-NN list (no weights, radius
or rings; those keep the stage-by-stage rule of :mod:`polygeo._estimate_stages`). Two passes
over the chunks of points, so that a point's choice depends on its neighbours only, never on
the chunk (or tile) it is processed in:

1. statistics per point (:func:`point_statistics`): in one PCA frame, jets of every candidate
   order fitted on nested neighbourhoods of every candidate size
   (:func:`polygeo._estimate_numba.auto_statistics`: slopes, H, their variances over the noise
   variance, residuals). Per order, an intersection-of-confidence-intervals rule (ICI) over
   the sizes gives the largest size whose slopes and H agree with those of all smaller sizes
   within ``AUTO_K_GAMMA`` standard deviations; each lower order is then compared with the
   highest order at that size (nested models on the same points: the variance of the
   difference is the difference of the variances), giving a standardised squared difference
   ``z`` (about 1 without bias, larger with it).
2. choice per point (:func:`choose`), pooled over its ``AUTO_K_SMOOTH`` nearest neighbours
   (itself included), every statistic taken as the median over them: the mean squared error
   of each order is estimated as its variance at its ICI size plus a squared bias
   ``max(median z - m0, 0) * variance of the difference`` (``m0`` the median of ``z`` without
   bias); the order with the least ``log MSE(normal) + log MSE(H)`` wins and the size is the
   pooled (geometric median) ICI size of that order.

The point is then fitted at the chosen order and size by the fused kernel, exactly as a fixed
``(k, order)`` call would fit it.
"""

from __future__ import annotations

import numpy as np

from . import jets
from ._estimate_numba import PARALLEL_MIN, Quantities, auto_statistics
from ._estimate_stages import AUTO_K_GAMMA, AUTO_K_SMOOTH, Neighbourhoods, Settings, fit_fused

__all__ = ["fit_auto", "point_statistics", "choose"]

#: Medians of ``z`` for unbiased fits: normals (mean of two chi2_1: chi2_2 / 2), H (chi2_1).
_Z0 = np.array([0.693, 0.455])
#: Degrees of freedom (in coefficients) from which a fit's residual enters the noise estimate.
_MIN_DOF = 3


def candidate_sizes(hoods: Neighbourhoods, settings: Settings) -> np.ndarray:
    """Sizes tried (points per neighbourhood, the point itself included), capped by the data."""
    return np.array(sorted({min(c, hoods.k_query) for c in settings.sizes}), dtype=np.int64)


def auto_orders(settings: Settings) -> tuple[int, ...]:
    """Orders tried: ``settings.orders`` without order 1 when a curvature order is present."""
    orders = settings.orders
    return tuple(o for o in orders if o >= 2) or orders


def _ici(val, gvar, rss, dof, ok, oi, m):
    """ICI over the sizes of order index ``oi``: ``(chosen size index, noise variance)``."""
    Q, _, S = ok.shape
    lo = np.full((Q, 3), -np.inf)
    hi = np.full((Q, 3), np.inf)
    s2sum = np.zeros(Q)
    s2n = np.zeros(Q)
    sig2 = np.zeros(Q)
    alive = np.ones(Q, dtype=bool)
    chosen = np.full(Q, -1)
    for si in range(S):
        okc = ok[:, oi, si] & alive
        d = dof[:, oi, si]
        # residual variances of the fits so far with enough degrees of freedom (the first
        # well-posed fit's until there is one)
        add = okc & ((d >= _MIN_DOF * m) | ((s2n == 0) & (d > 0)))
        s2sum = np.where(add, s2sum + rss[:, oi, si] / np.maximum(d, 1), s2sum)
        s2n = np.where(add, s2n + 1, s2n)
        sig2 = np.where(s2n > 0, s2sum / np.maximum(s2n, 1), 0.0)
        sd = AUTO_K_GAMMA * np.sqrt(sig2[:, None] * gvar[:, oi, si, :])
        nlo = np.maximum(lo, val[:, oi, si] - sd)
        nhi = np.minimum(hi, val[:, oi, si] + sd)
        take = okc & ((chosen < 0) | (nlo <= nhi).all(1))
        lo = np.where(take[:, None], nlo, lo)
        hi = np.where(take[:, None], nhi, hi)
        chosen = np.where(take, si, chosen)
        alive &= ~(okc & ~take)  # the intervals stopped intersecting: bias dominates
    return chosen, sig2


def point_statistics(hoods: Neighbourhoods, q, nbr, dist, *, orders, sizes,
                     settings: Settings) -> dict:
    """Per point of the chunk ``q``: the pooled quantities of :func:`choose` (float64).

    Returns ``size (Q, O)`` ICI size index per order, ``var (Q, O, 2)`` variances of the
    normal (sum over both slopes) and of H at that size, ``z (Q, O, 2)`` standardised squared
    difference with the highest order at that size and ``vd (Q, O, 2)`` the variance of that
    difference (NaN where not defined; the highest order's own ``z`` is NaN).
    """
    O, S = len(orders), sizes.size
    m_top = jets.n_coeffs(orders[-1])
    kframe = int(min(sizes, key=lambda c: abs(int(c) - 4 * m_top)))
    st = auto_statistics(hoods.hoods(q, nbr, dist, None), orders=np.array(orders),
                         max_conds=np.array([settings.max_cond[o] for o in orders]),
                         interpolate=settings.interpolate, sizes=sizes, kframe=kframe)
    val, gvar, rss, dof, ok = st["val"], st["gvar"], st["rss"], st["dof"], st["ok"]
    Q = q.size
    qi = np.arange(Q)
    size = np.zeros((Q, O), dtype=np.int64)
    var = np.full((Q, O, 2), np.inf)
    s2 = np.zeros((Q, O))
    for oi, o in enumerate(orders):
        chosen, s2[:, oi] = _ici(val, gvar, rss, dof, ok, oi, jets.n_coeffs(o))
        c = np.maximum(chosen, 0)
        size[:, oi] = np.where(chosen >= 0, c, S - 1)
        g = gvar[qi, oi, c]
        good = chosen >= 0
        var[:, oi, 0] = np.where(good, s2[:, oi] * (g[:, 0] + g[:, 1]), np.inf)
        var[:, oi, 1] = np.where(good, s2[:, oi] * g[:, 2], np.inf)
    z = np.full((Q, O, 2), np.nan)
    vd = np.full((Q, O, 2), np.nan)
    s2t = s2[:, -1]
    for oi in range(O - 1):
        c = size[:, oi]
        both = ok[qi, oi, c] & ok[qi, -1, c] & (s2t > 0)
        dv = val[qi, -1, c] - val[qi, oi, c]
        dg = np.maximum(gvar[qi, -1, c] - gvar[qi, oi, c], 1e-300)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            zn = (dv[:, 0] ** 2 / dg[:, 0] + dv[:, 1] ** 2 / dg[:, 1]) / (2.0 * s2t)
            zh = dv[:, 2] ** 2 / (dg[:, 2] * s2t)
        z[:, oi, 0] = np.where(both, zn, np.nan)
        z[:, oi, 1] = np.where(both, zh, np.nan)
        vd[:, oi, 0] = np.where(both, s2t * (dg[:, 0] + dg[:, 1]), np.nan)
        vd[:, oi, 1] = np.where(both, s2t * dg[:, 2], np.nan)
    return dict(size=size, var=var, z=z, vd=vd)


def choose(stats: dict, pool: np.ndarray, sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Order index and size (rows) per query from the statistics of its ``pool`` ``(Q, P)``.

    ``pool`` holds row indices into ``stats`` (the query first; ``-1`` padding ignored).
    """
    Q, P = pool.shape
    idx = np.maximum(pool, 0)
    pad = pool < 0
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slices: no pooled value

            def med(a):
                x = a[idx]
                x = np.where(pad.reshape((Q, P) + (1,) * (x.ndim - 2)), np.nan, x)
                return np.nanmedian(x, axis=1)

            var = med(np.where(np.isfinite(stats["var"]), stats["var"], np.nan))
            b2 = np.maximum(med(stats["z"]) - _Z0, 0.0) * med(stats["vd"])
    var = np.where(np.isfinite(var), var, np.inf)
    mse = var + np.nan_to_num(b2, nan=0.0, posinf=np.inf)
    tiny = np.finfo(np.float64).tiny
    with np.errstate(divide="ignore"):
        score = np.log(np.maximum(mse[..., 0], tiny)) + np.log(np.maximum(mse[..., 1], tiny))
    if mse.shape[1] and not np.any(mse[..., 1] > 0):
        score = np.log(np.maximum(mse[..., 0], tiny))  # order 1 alone: normals only
    score = np.where(np.isnan(score), np.inf, score)
    order_i = np.argmin(score, axis=1)
    # the size: geometric median of the pooled ICI sizes of that order
    s_idx = np.take_along_axis(stats["size"][idx], order_i[:, None, None], axis=2)[..., 0]
    rows = np.log(sizes[s_idx].astype(np.float64))
    rows[pad] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        kuse = np.exp(np.nanmedian(rows, axis=1))
    kuse = np.clip(np.rint(kuse), 1, sizes[-1]).astype(np.int64)
    return order_i, kuse


def fit_auto(hoods: Neighbourhoods, out: Quantities, *, settings: Settings) -> None:
    """Both passes (statistics, then pooled choice and fused fit) over all finite points."""
    orders = auto_orders(settings)
    sizes = candidate_sizes(hoods, settings)
    n = hoods.P.shape[0]
    stats: dict | None = None
    for q in hoods.chunks(settings.batch_size, settings.progress):
        nbr, dist = hoods.query(q)
        part = point_statistics(hoods, q, nbr, dist, orders=orders, sizes=sizes,
                                settings=settings)
        if stats is None:
            stats = {k: np.full((n,) + v.shape[1:], np.nan if v.dtype.kind == "f" else 0,
                                dtype=v.dtype) for k, v in part.items()}
        for k, v in part.items():
            stats[k][q] = v
    if stats is None:
        return
    n_pool = max(int(AUTO_K_SMOOTH), 1)
    for q in hoods.chunks(settings.batch_size, settings.progress):
        nbr, dist = hoods.query(q)
        # the pool: the point and its nearest neighbours (the k-NN list starts with the point)
        pool = nbr[:, :n_pool]
        order_i, kuse = choose(stats, pool, sizes)
        for oi, o in enumerate(orders):
            sel = order_i == oi
            if not sel.any():
                continue
            qs = q[sel]
            fit_fused(hoods, qs, nbr[sel], dist[sel], kuse[sel], out, order=o, gaussian=False,
                      settings=settings, parallel_min=PARALLEL_MIN // 8)
