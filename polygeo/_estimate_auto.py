"""Automatic jet order and neighbourhood size (``order="auto"`` and/or ``k="auto"``).

Used by :func:`polygeo.estimate.differential_quantities` on one k-NN list (no weights, radius
or rings; those keep the stage-by-stage rule of :mod:`polygeo._estimate_stages`). The normal
and the curvatures get their own choice (the best setting for one is rarely the best for the
other: normals prefer wide low-order fits, curvature needs a quadratic term and loses more to
noise). Passes over the chunks of points, so that a point's choice depends on its neighbours
only, never on the chunk (or tile) it is processed in:

1. statistics per point (:func:`point_statistics`): in one PCA frame, jets of every candidate
   order fitted on nested neighbourhoods of every candidate size
   (:func:`polygeo._estimate_numba.auto_statistics`: slopes, H, their variances over the noise
   variance, residuals). Per order, the noise variance from the residuals and an
   intersection-of-confidence-intervals size (ICI: the largest size whose slopes and H agree
   with those of all smaller sizes within ``AUTO_K_GAMMA`` standard deviations), and a bias
   rate: the least-squares slope ``B`` of each quantity against ``t_s = (n_s / n_0)^(p / 2)``
   over the sizes (``n_s`` points; ``p`` the power of the neighbourhood radius the leading
   bias of that order grows with, for evenly spread points: 2 for the slopes of orders 1-2
   and H of orders 2-3, 4 above), from the differences with the largest size (nested fits on
   the same points: the variance of a difference is the difference of the variances).
   For H also a second drift model, ``y_s = y_0 + B t_s + C u_s`` with ``u_s = sigma^2 /
   <r^2>_s`` (noise variance over the mean squared distance of the size's points): under
   noise the coordinates within the tangent plane are noisy too, which attenuates the fitted
   curvature towards 0 by a relative amount of the order of ``u_s`` (errors in variables),
   a bias that *falls* with the size. Read as a truncation bias ``B t_s``, that drift would
   be extrapolated to a large error at the widest sizes (measured: on bm_jets' torus at 1 %
   noise the order-2 H drifts from 63 % too small at 13 points to 6 % too large at 385,
   predicted bias^2 at 385 points 8x the measured total error).
   The plane (order 1, for the normal) is modelled apart (:func:`plane_alias`): its residual
   holds the quadratic term, so its noise variance is the quadratic fit's, and its bias is
   measured directly as its difference with the highest order on the same points (the
   alias of the curved terms on the slopes, which vanishes on a neighbourhood symmetric
   about the point whatever its size, so no drift with the size describes it). Noise along
   the surface moves the point where a curved jet's normal is taken (``sigma^2 |II|^2``);
   the plane's normal is its neighbourhood's mean and moves only as far as the
   neighbourhood follows the point. Measured on bm_jets' open cylinder at noise 1e-4 (a
   structured grid): the plane on 257 points is 0.010 deg off (interior median), the
   quadratic on 385 0.014 deg, about ``sigma |II|``; the residual-variance model had
   predicted 300 times the quadratic's error for that plane.
2. per point (:func:`point_mse`), with ``B`` and its variance pooled (median) over the
   ``AUTO_K_SMOOTH`` nearest neighbours: the mean squared error of every order and size,
   ``max(b_s^2 - var(b_s), 0) + variance`` with the bias ``b_s = B t_s`` (the normal: both
   slopes summed; H), for H ``b_s = B t_s + C u_s`` where the pooled ``C`` attenuates
   (``C H < 0``) by less than ``_ATTEN_MAX`` times ``|H| u_s``; the normal of a curved
   order adds ``sigma^2 |II|^2``, the plane's bias is its pooled alias, plus or minus that
   term by the share its neighbourhood follows. The variances use the noise variance
   pooled (median) over the same neighbours: a residual on few degrees of freedom (an
   order-3 fit on 13 points has 3) can be small by chance, and made a point's fit look
   exact (measured on the bunny scan bun000: 47 points chose an order-3 normal on 13-17
   points, 37-61 deg off the other scan's). The normal's squared bias is at least its
   measured drift (:func:`measured_drift`, pooled): the change of its slopes from the
   narrowest well-determined size of its order, less the variance of that change. Fine
   real detail breaks the modelled drift (one power of the size, a rate shared by the
   neighbours): on the bunny scans 75 % of the residual variance of a 101-point quadratic
   is shared by two independent scans (residual correlation 0.49 between them, 0.57
   between neighbouring points of one scan, against about 0 for i.i.d. noise), so what
   the wide fits leave is detail both see, whose bias turns from one point to the next.
   The normal's noise variance is also no less than its order's truncation scaling allows
   from its first well-determined fit (:func:`_weak_floor`): fits on a few degrees of
   freedom with a zero residual on the scanner's rows had looked exact. And it comes from
   the fits up to that first well-determined one (:func:`_normal_noise`), not from every
   size the ICI accepts: a wider fit's residual also holds the detail it smooths away, which
   overstated the noise, made the narrow fits' normals look noisier than they are and
   hid the wide fits' measured drift under the variance subtracted from it.
3. choice per point (:func:`choose`): the per-point errors pooled (median) again over the
   same neighbours, a neighbour that cannot fit a setting counting as an infinite error;
   per quantity the (order, size) of least error, the sizes of an order capped by its
   pooled (geometric median) ICI size -- for the curvatures only where the noise is small
   against the neighbourhood (pooled ``u = sigma^2 / <r^2>`` at the ICI size below
   ``_U_LIFT``). Where it is not, a narrow fit's H is attenuated towards 0 by a share of the
   order of ``u`` that falls with the size (the ``C u_s`` term above): H's confidence
   intervals stop intersecting where the wider fits *recover* from a bias, which the ICI,
   built for a bias that grows with the size, reads as one setting in; H's error model holds
   both drifts and judges the wider sizes itself. On cleaner data the cap stays: the
   model's one-power drift misses the turning bias of a wavy surface, which the ICI's direct
   interval test catches (clean wavy sheet: 1.68x the best fixed H without the cap, ``u``
   about 4e-8 there). Measured on bm_jets' 100k-point cylinder at 1 % (noise of about
   three point spacings, ``u`` about 0.1): median relative error of H 4.65 -> 3.38 against
   2.90 for the best fixed setting.

The point is then fitted at the chosen curvature setting by the fused kernel, exactly as a
fixed ``(k, order)`` call would fit it; where the normal's setting differs, the normal comes
from a fit at that setting (the curvatures' sign and principal directions follow it).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from . import jets
from ._estimate_numba import PARALLEL_MIN, Quantities, auto_statistics
from ._estimate_output import coeff_signs, flip_frame
from ._estimate_stages import (
    AUTO_K_GAMMA,
    AUTO_K_SMOOTH,
    Neighbourhoods,
    Settings,
    fit_fused,
)

__all__ = ["fit_auto", "point_statistics", "point_mse", "store_mse", "choose", "best_setting",
           "merge_normals"]

#: Next-best settings tried where the fused fit flags the chosen one.
_RETRIES = 3
#: Degrees of freedom (in coefficients) from which a fit's residual enters the noise estimate.
_MIN_DOF = 3
#: Largest noise-induced (attenuation) bias of H accepted, in units of ``|H| sigma^2 / <r^2>``
#: (errors-in-variables theory gives a factor of order one; a larger ``C`` is shape read as
#: noise, e.g. on clean data where ``sigma^2`` is a truncation residual). Measured on bm_jets'
#: grid: 3, 10 and 30 give the same cells within 1.5x of the best; no bound breaks clean H.
_ATTEN_MAX = 10.0
#: Noise share ``sigma^2 / <r^2>`` (pooled, at the ICI size) from which the ICI no longer caps
#: the curvatures' sizes (:func:`choose`): H's attenuation is then about 1 % of H or more.
#: Measured at the ICI size (order 2, median): clean wavy sheet 4e-8, bm_jets' 10k cells at
#: 0.01-0.1 % 2e-6-2e-4, at 1 % 0.013; a 4k cylinder with noise of a spacing 0.07.
_U_LIFT = 0.01
#: Power of the neighbourhood radius of the leading bias, per order: slopes (normal), H.
_BIAS_POWER = {"normal": {1: 2, 2: 2, 3: 4, 4: 4}, "H": {1: 2, 2: 2, 3: 2, 4: 4}}
def candidate_sizes(hoods: Neighbourhoods, settings: Settings) -> np.ndarray:
    """Sizes tried (points per neighbourhood, the point itself included), capped by the data."""
    return np.array(sorted({min(c, hoods.k_query) for c in settings.sizes}), dtype=np.int64)


def auto_orders(settings: Settings) -> tuple[int, ...]:
    """Orders fitted: ``settings.orders``, and order 1 with ``order="auto"``.

    The plane (order 1) serves the normal only (:func:`choose`): its slopes have the least
    variance, and on a neighbourhood symmetric about the point their bias is of second order.
    """
    orders = settings.orders
    if settings.order == "auto" and 1 not in orders:
        orders = (1,) + tuple(orders)
    return tuple(orders)


def _ici(val, gvar, rss, dof, ok, oi, m, floor=None, narrowest=False):
    """ICI over the sizes of order index ``oi``: ``(chosen size index, noise variance)``.

    ``floor (Q, S)`` (optional): the least residual variance a fit of each size may claim
    before the order has a fit with ``_MIN_DOF`` degrees of freedom per coefficient
    (:func:`_weak_floor`).
    """
    Q, _, S = ok.shape
    lo = np.full((Q, 3), -np.inf)
    hi = np.full((Q, 3), np.inf)
    s2sum = np.zeros(Q)
    s2n = np.zeros(Q)
    sig2 = np.zeros(Q)
    alive = np.ones(Q, dtype=bool)
    chosen = np.full(Q, -1)
    done = np.zeros(Q, dtype=bool)
    for si in range(S):
        okc = ok[:, oi, si] & alive
        d = dof[:, oi, si]
        # residual variances of the fits so far with enough degrees of freedom (the first
        # well-posed fit's until there is one)
        add = okc & ((d >= _MIN_DOF * m) | ((s2n == 0) & (d > 0))) & ~done
        if narrowest:
            done |= okc & (d >= _MIN_DOF * m)
        s2 = rss[:, oi, si] / np.maximum(d, 1)
        if floor is not None:
            s2 = np.where(d >= _MIN_DOF * m, s2, np.maximum(s2, floor[:, si]))
        s2sum = np.where(add, s2sum + s2, s2sum)
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


def _weak_floor(rss, dof, ok, oi, order, sizes) -> np.ndarray:
    """``(Q, S)``: the least residual variance each size of an order may claim.

    From the order's first fit with ``_MIN_DOF`` degrees of freedom per coefficient (0 where
    it has none): that fit's residual variance ``s2_f`` (``n_f`` points) is noise, or
    truncation, or both; a narrower fit's on ``n`` points is at least ``s2_f (n /
    n_f)^(order + 1)`` (a truncation residual of an order-``p`` jet grows like
    ``r^(p + 1)``, its variance like ``n^(p + 1)``; noise does not fall with the size).
    Below it, a residual on a few degrees of freedom is too small to be either: chance, or
    a degenerate sampling (the scanner's rows of the bunny scans, where order-3 fits on 13
    points had a zero residual).
    """
    Q, _, S = ok.shape
    good = ok[:, oi] & (dof[:, oi] >= _MIN_DOF * jets.n_coeffs(order))
    f = np.argmax(good, 1)
    qi = np.arange(Q)
    s2f = np.where(good.any(1), rss[qi, oi, f] / np.maximum(dof[qi, oi, f], 1), 0.0)
    ratio = sizes[None, :].astype(np.float64) / sizes[f][:, None]
    return s2f[:, None] * np.minimum(ratio, 1.0) ** (order + 1)


def _normal_noise(val, gvar, rss, dof, ok, oi, o, sizes, s2) -> np.ndarray:
    """``(Q,)``: the noise variance the normal of order index ``oi`` (order ``o``) uses.

    ``s2 (Q,)``: the order's ICI noise variance (returned for the plane, ``o < 2``, and when
    neither rule below applies). The residual variance of a fit is the noise variance plus
    what the jet cannot follow (truncation, and fine real detail), which grows with the
    size; the mean over the sizes the ICI accepts (:func:`_ici`) therefore overstates the
    noise where the surface has detail the wide fits smooth away (the bunny scans: an
    order-4 fit's residual variance grows 1.46x from 21 to 65 points, 1.12x on i.i.d. noise
    on a sphere), and an overstated noise makes a narrow fit's normal look noisier than it
    is and a wide fit's drift smaller (its variance is subtracted from the measured drift,
    :func:`measured_drift`). So only the fits up to the narrowest with ``_MIN_DOF``
    degrees of freedom per coefficient count: the least truncation
    among the well-determined fits. On i.i.d. noise this costs little precision: nested
    fits share their points, so their residual variances are strongly correlated and their
    mean is hardly less variable than the narrowest one; it is pooled (median) over the
    neighbours besides (:func:`point_mse`). Fits below that size claim no less than their
    truncation scaling allows (:func:`_weak_floor`). Not for the curvatures: clean data
    need an order-4 jet on 21 points, whose H the floor would cost (measured: clean torus
    H 1.39 -> 1.63x the best).
    """
    if o < 2:
        return s2
    floor = _weak_floor(rss, dof, ok, oi, o, sizes)
    return _ici(val, gvar, rss, dof, ok, oi, jets.n_coeffs(o), floor, True)[1]


def bias_rate(y, v, ok, t, u=None):
    """Per query: the drift of a quantity with the neighbourhood size, and its covariance.

    ``y, v, ok (Q, S)``: a quantity, its variance and whether the fit is well posed, per size;
    ``t (S,)``: the growth of the truncation bias; ``u (Q, S)`` (optional): the decay of the
    noise-induced bias. Weighted least squares of ``y_s - y_L = B (t_s - t_L) [+ C (u_s -
    u_L)]`` over the differences with the largest well-posed size ``L``, weighted by the
    inverse of their variance ``v_s - v_L`` (nested fits). Returns ``coef (Q, 2)`` = ``(B,
    C)`` (``C = 0`` without ``u``) and ``cov (Q, 3)`` = ``(var B, var C, cov(B, C))``; NaN
    where the sizes do not determine them (fewer differences than coefficients, or a
    singular system).
    """
    Q, S = y.shape
    has = ok.any(1)
    L = np.where(has, S - 1 - np.argmax(ok[:, ::-1], 1), 0)
    qi = np.arange(Q)
    D = y - y[qi, L][:, None]
    vd = np.maximum(v - v[qi, L][:, None], 1e-3 * v)
    use = ok & (np.arange(S)[None, :] != L[:, None]) & (vd > 0)
    w = np.where(use, 1.0 / np.where(use, vd, 1.0), 0.0)
    X = [np.broadcast_to(t[None, :] - t[L][:, None], (Q, S))]
    if u is not None:
        X.append(u - u[qi, L][:, None])
    m = len(X)
    Dw = w * np.where(use, D, 0.0)
    A = np.eye(2)[None].repeat(Q, 0)
    b = np.zeros((Q, 2))
    for a in range(m):
        b[:, a] = (X[a] * Dw).sum(1)
        for c in range(m):
            A[:, a, c] = (w * X[a] * X[c]).sum(1)
    det = A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]
    scale = A[:, 0, 0] * A[:, 1, 1]
    good = (use.sum(1) >= m) & (scale > 0) & (det > 1e-12 * scale)
    det = np.where(good, det, 1.0)
    cov = np.stack([A[:, 1, 1] / det, A[:, 0, 0] / det, -A[:, 0, 1] / det], 1)
    if m == 1:
        cov[:, 1:] = 0.0
    coef = np.stack([cov[:, 0] * b[:, 0] + cov[:, 2] * b[:, 1],
                     cov[:, 2] * b[:, 0] + cov[:, 1] * b[:, 1]], 1)
    return np.where(good[:, None], coef, np.nan), np.where(good[:, None], cov, np.nan)


def _mean_sq_distance(dist: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """``(Q, S)``: mean squared distance of the first ``sizes[s]`` neighbours (padding left)."""
    fin = np.isfinite(dist)
    csum = np.cumsum(np.where(fin, dist * dist, 0.0), axis=1)
    cnt = np.cumsum(fin, axis=1)
    kk = np.minimum(sizes - 1, dist.shape[1] - 1)
    return csum[:, kk] / np.maximum(cnt[:, kk], 1)


def point_statistics(hoods: Neighbourhoods, q, nbr, dist, *, orders, sizes,
                     settings: Settings) -> dict:
    """Per point of the chunk ``q``: what :func:`point_mse` and :func:`choose` pool (float64).

    Returns ``size (Q, O)`` ICI size index per order (the largest where none is well posed),
    ``var (Q, O, S, 2)`` variances of the normal (both slopes summed) and of H per size
    (``inf`` where the fit is not well posed), ``B, varB (Q, O, 3)`` bias rates of the slopes
    and of H and their variances (NaN where not defined), and for H the two-term drift:
    ``BC (Q, O, 2)`` ``(B, C)``, ``covBC (Q, O, 3)`` (:func:`bias_rate`), ``u (Q, O, S)``
    (``sigma^2 / <r^2>_s``) and ``H (Q, O)`` (at the largest well-posed size). With a plane
    among ``orders`` and a curved order above it (see :func:`plane_alias`): ``alias (Q, S)``
    and ``tangential (Q,)``.
    """
    O, S = len(orders), sizes.size
    m_top = jets.n_coeffs(orders[-1])
    kframe = int(min(sizes, key=lambda c: abs(int(c) - 4 * m_top)))
    st = auto_statistics(hoods.hoods(q, nbr, dist, None), orders=np.array(orders),
                         max_conds=np.array([settings.max_cond[o] for o in orders]),
                         interpolate=settings.interpolate, sizes=sizes, kframe=kframe)
    val, gvar, rss, dof, ok = st["val"][..., :3], st["gvar"], st["rss"], st["dof"], st["ok"]
    Q = q.size
    size = np.zeros((Q, O), dtype=np.int64)
    var = np.full((Q, O, S, 2), np.inf)
    v3 = np.full((Q, O, S, 3), np.inf)
    B = np.full((Q, O, 3), np.nan)
    varB = np.full((Q, O, 3), np.nan)
    BC = np.full((Q, O, 2), np.nan)
    covBC = np.full((Q, O, 3), np.nan)
    u = np.full((Q, O, S), np.nan)
    H = np.full((Q, O), np.nan)
    s2o = np.zeros((Q, O))
    s2no = np.zeros((Q, O))
    n_rel = sizes.astype(np.float64) / float(sizes[0])
    r2 = _mean_sq_distance(dist, sizes)
    ici = [_ici(val, gvar, rss, dof, ok, oi, jets.n_coeffs(o)) for oi, o in enumerate(orders)]
    plane = orders[0] == 1 and O > 1
    for oi, o in enumerate(orders):
        chosen, s2 = ici[oi]
        if plane and o == 1:
            # the plane's residual holds the quadratic term, which plane_alias accounts
            # for: its noise variance is that of the quadratic fit
            s2 = np.where(ici[1][1] > 0, ici[1][1], s2)
        s2o[:, oi] = s2
        size[:, oi] = np.where(chosen >= 0, chosen, S - 1)
        okc = ok[:, oi]
        # the normal's noise (the plane: the quadratic's, as above)
        s2n = _normal_noise(val, gvar, rss, dof, ok, oi, o, sizes, s2) if o >= 2 else s2
        s2no[:, oi] = s2n
        v = s2[:, None, None] * gvar[:, oi]  # (Q, S, 3)
        v[..., :2] = s2n[:, None, None] * gvar[:, oi, :, :2]  # the slopes: the normal's noise
        v3[:, oi] = np.where(okc[..., None], v, np.inf)
        var[:, oi, :, 0] = np.where(okc, s2n[:, None] * (gvar[:, oi, :, 0] + gvar[:, oi, :, 1]),
                                    np.inf)
        var[:, oi, :, 1] = np.where(okc, v[..., 2], np.inf)
        for j, quantity in ((0, "normal"), (1, "normal"), (2, "H")):
            t = n_rel ** (_BIAS_POWER[quantity][o] / 2.0)
            coef, cov = bias_rate(val[:, oi, :, j], v[..., j], okc, t)
            B[:, oi, j], varB[:, oi, j] = coef[:, 0], cov[:, 0]
        # H: the truncation drift and the noise-induced attenuation together
        u[:, oi] = s2[:, None] / np.where(r2 > 0, r2, np.inf)
        t = n_rel ** (_BIAS_POWER["H"][o] / 2.0)
        BC[:, oi], covBC[:, oi] = bias_rate(val[:, oi, :, 2], v[..., 2], okc, t, u[:, oi])
        last = np.where(okc, np.arange(S)[None, :], -1).max(1)
        H[:, oi] = np.where(last >= 0, val[np.arange(Q), oi, np.maximum(last, 0), 2], np.nan)
    out = dict(size=size, var=var, B=B, varB=varB, BC=BC, covBC=covBC, u=u, H=H, s2=s2o,
               s2n=s2no, drift=measured_drift(val, v3, ok, dof, orders))
    if plane:
        s2c = np.stack([ici[oi][1] for oi in range(1, O)], 1)  # curved orders' noise
        s2c = np.where(s2c > 0, s2c, np.inf).min(1)
        out.update(plane_alias(st["val"], v3, ok, np.where(np.isfinite(s2c), s2c, 0.0),
                               _rank_gap(dist, sizes)))
    return out


def measured_drift(val, v3, ok, dof, orders) -> np.ndarray:
    """``(Q, O, S)``: squared drift of the normal of each order and size, measured.

    Per order, the slopes at each size are compared with those of the narrowest size of
    that order whose fit has at least ``_MIN_DOF`` degrees of freedom per coefficient (its
    reference: the least smoothed well-determined fit): the squared difference of both
    slopes less its variance ``v_ref - v_s`` (nested fits), an unbiased estimate of the
    squared change of the bias from the reference to the size (NaN at the sizes below the
    reference and where a fit is not well posed). No model of how the bias grows with the
    size: the drift :func:`bias_rate` fits assumes one power of the radius and a bias that
    neighbours share (its rate is pooled), which fine detail of a real surface breaks (its
    bias turns with the detail from one point to the next, and saturates with the size).
    """
    Q, O, S = ok.shape
    out = np.full((Q, O, S), np.nan)
    qi = np.arange(Q)
    for oi, o in enumerate(orders):
        good = ok[:, oi] & (dof[:, oi] >= _MIN_DOF * jets.n_coeffs(o))
        has = good.any(1)
        r = np.argmax(good, 1)
        use = ok[:, oi] & has[:, None] & (np.arange(S)[None, :] >= r[:, None])
        with np.errstate(invalid="ignore"):  # inf - inf where a fit is not well posed
            d = val[:, oi, :, :2] - val[qi, oi, r, :2][:, None, :]
            vd = np.maximum(v3[qi, oi, r, :2][:, None, :] - v3[:, oi, :, :2], 0.0)
            out[:, oi] = np.where(use, (d * d - np.where(use[..., None], vd, 0.0)).sum(-1),
                                  np.nan)
    return out


def _rank_gap(dist: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """``(Q, S)``: distance from the last point of each size to the first point left out.

    ``inf`` where nothing is left out (the list ends there; the share that follows is then
    taken as 1, the case without a margin).
    """
    K = dist.shape[1]
    inner = dist[:, np.minimum(sizes - 1, K - 1)]
    outer = np.where((sizes < K)[None, :], dist[:, np.minimum(sizes, K - 1)], np.inf)
    with np.errstate(invalid="ignore"):
        gap = outer - inner
    return np.where(np.isfinite(gap), np.maximum(gap, 0.0), np.inf)


def plane_alias(val, v3, ok, s2, gap) -> dict:
    """The plane's normal error beyond its variance, per point and size (see point_mse).

    ``val (Q, O, S, 4)`` (:func:`polygeo._estimate_numba.auto_statistics`), ``v3 (Q, O, S,
    3)`` variances of its first three values (``inf`` where not well posed), ``ok (Q, O,
    S)``; order index 0 is the plane, the last the highest curved order; ``s2 (Q,)`` the
    noise variance. Returns ``alias (Q, S)``: the squared difference of the plane's slopes
    with the highest order's on the same points, less its variance ``v_top - v_plane``
    (nested fits), an unbiased estimate of the squared bias of the plane relative to that
    order (the alias of the curved terms on the slopes: zero on a neighbourhood symmetric
    about the point, whatever its size; NaN where the highest order is not well posed), and
    ``tangential (Q,)``: ``sigma^2 |II|^2``, the squared normal error of a curved jet from
    the query's own noise along the surface (isotropic noise of variance ``sigma^2`` moves
    the point where the jet's normal is taken; the plane's normal is the mean over its
    neighbourhood and does not move with it), ``|II|^2 = k1^2 + k2^2`` from the quadratic
    fit of the widest well-posed size. The plane's neighbourhood is chosen by the noisy
    distances: it follows the query's own tangential noise when that noise is large against
    ``gap (Q, S)`` (:func:`_rank_gap`, the margin by which its last point is in), and not at
    all when it is small; ``follow (Q, S) = sigma^2 / (sigma^2 + gap^2)`` is the share that
    follows. With the share ``f`` the plane's normal is off by ``II (a + f delta)`` and the
    difference with the jet's by ``II (a - (1 - f) delta)`` (``a``: the offset of its
    neighbourhood's centre), so its squared bias is ``alias + (2 f - 1) sigma^2 |II|^2``
    (:func:`point_mse`).
    """
    Q, O, S, _ = val.shape
    d = val[:, 0, :, :2] - val[:, -1, :, :2]
    vd = np.maximum(v3[:, -1, :, :2] - v3[:, 0, :, :2], 0.0)
    both = ok[:, 0] & ok[:, -1]
    with np.errstate(invalid="ignore"):
        alias = np.where(both, (d * d - np.where(both[..., None], vd, 0.0)).sum(-1), np.nan)
    last = np.where(ok[:, 1], np.arange(S)[None, :], -1).max(1)
    ii = np.where(last >= 0, val[np.arange(Q), 1, np.maximum(last, 0), 3], np.nan)
    g2 = gap * gap
    with np.errstate(invalid="ignore"):
        follow = np.where(s2[:, None] + g2 > 0, s2[:, None] / (s2[:, None] + g2), 1.0)
    follow = np.where(np.isinf(gap), 1.0, follow)  # nothing left out: no margin known
    return dict(alias=alias, tangential=s2 * ii, follow=follow)


def _pooled_median(a: np.ndarray, pool: np.ndarray) -> np.ndarray:
    """Median of ``a[pool]`` over the pool axis (``-1`` padding and NaN ignored; NaN if none).

    Sorted along the pool (NaN last) and the middle of the valid values taken: the same values
    as ``np.nanmedian``, many times faster on these small pools.
    """
    x = a[np.maximum(pool, 0)]
    pad = (pool < 0).reshape(pool.shape + (1,) * (x.ndim - 2))
    x = np.sort(np.moveaxis(np.where(pad, np.nan, x), 1, -1), axis=-1)
    n = (~np.isnan(x)).sum(-1)
    lo = np.take_along_axis(x, np.maximum((n - 1) // 2, 0)[..., None], -1)[..., 0]
    hi = np.take_along_axis(x, np.maximum(n // 2, 0)[..., None], -1)[..., 0]
    with np.errstate(invalid="ignore"):
        med = 0.5 * (lo + hi)
    return np.where(n > 0, med, np.nan)


def _pooled_median_t(at: np.ndarray, pool: np.ndarray) -> np.ndarray:
    """:func:`_pooled_median` of ``at (F, N)`` (points last): ``(F, Q)``.

    The pool axis comes out last and contiguous: no transposed copy of the gathered values.
    """
    x = at[:, np.maximum(pool, 0)]  # (F, Q, P)
    if (pool < 0).any():
        x[:, pool < 0] = np.nan
    x.sort(axis=-1)  # NaN last
    n = x.shape[-1] - np.isnan(x).sum(-1)
    lo = np.take_along_axis(x, np.maximum((n - 1) // 2, 0)[..., None], -1)[..., 0]
    hi = np.take_along_axis(x, np.maximum(n // 2, 0)[..., None], -1)[..., 0]
    with np.errstate(invalid="ignore"):
        med = 0.5 * (lo + hi)
    return np.where(n > 0, med, np.nan)


def store_mse(table: np.ndarray, rows: np.ndarray, mse: np.ndarray) -> None:
    """Write :func:`point_mse` of ``rows`` into ``table (O, S, 2, N)`` (``inf`` as NaN)."""
    table[..., rows] = np.moveaxis(np.where(np.isfinite(mse), mse, np.nan), 0, -1)


def _pool_factor(s2: np.ndarray, rows: np.ndarray, pool: np.ndarray) -> np.ndarray:
    """``(Q, O)``: a noise variance ``s2 (N, O)`` pooled over ``pool``, over the point's own.

    The pooled value is the median (:func:`_pooled_median`); 1 where the point's own is 0 or
    the ratio is not finite.
    """
    own, pooled = s2[rows], _pooled_median(s2, pool)
    with np.errstate(invalid="ignore", divide="ignore"):
        f = np.where(own > 0, pooled / np.where(own > 0, own, 1.0), 1.0)
    return np.where(np.isfinite(f), f, 1.0)


def point_mse(stats: dict, rows: np.ndarray, pool: np.ndarray, sizes: np.ndarray,
              orders: tuple[int, ...]) -> np.ndarray:
    """``(Q, O, S, 2)`` estimated mean squared error of the normal and of H of ``rows``.

    ``pool (Q, P)``: row indices into ``stats`` (the point first; ``-1`` padding): the bias
    rates are pooled over it (median of each coefficient, median of each (co)variance). H
    takes the two-term drift where its pooled ``C`` attenuates (``C H < 0``, the point's own
    ``H``) and ``|C| < _ATTEN_MAX |H|``, else the truncation drift alone. With the plane's
    statistics (:func:`plane_alias`), a curved order's normal adds ``sigma^2 |II|^2`` and
    the plane's bias is ``max(alias, 0) + (2 f - 1) sigma^2 |II|^2`` (pooled values; ``f``
    the share that follows), where its alias is measured.
    """
    Bp = _pooled_median(stats["B"], pool)  # (Q, O, 3)
    vBp = _pooled_median(stats["varB"], pool)
    b2 = np.maximum(np.nan_to_num(Bp * Bp - vBp, nan=0.0), 0.0)
    BCp = _pooled_median(stats["BC"], pool)  # (Q, O, 2)
    cvp = np.nan_to_num(_pooled_median(stats["covBC"], pool), nan=0.0)  # (Q, O, 3)
    h, C = stats["H"][rows], BCp[..., 1]
    with np.errstate(invalid="ignore"):
        att = np.isfinite(C) & (C * h < 0) & (np.abs(C) < _ATTEN_MAX * np.abs(h))
    BCp = np.nan_to_num(BCp, nan=0.0)
    n_rel = sizes.astype(np.float64) / float(sizes[0])
    mse = np.array(stats["var"][rows], dtype=np.float64, copy=True)
    # the noise variance pooled like the rest: one point's residual on few degrees of
    # freedom can be small by chance, and its variance with it
    f = np.stack([_pool_factor(stats[key], rows, pool) for key in ("s2n", "s2")], -1)
    f = f[:, :, None, :]  # (Q, O, 1, 2): the normal's and H's noise
    with np.errstate(invalid="ignore"):  # both branches are evaluated: inf * 0 where
        mse = np.where(np.isfinite(mse), mse * f, mse)  # mse is inf is not taken
    plane = "alias" in stats
    if plane:
        alias = _pooled_median(stats["alias"], pool)  # (Q, S)
        tang = np.nan_to_num(_pooled_median(stats["tangential"], pool), nan=0.0)  # (Q,)
        follow = np.nan_to_num(_pooled_median(stats["follow"], pool), nan=1.0)  # (Q, S)
    # the measured drift, pooled like the rest, then clamped: an unbiased b^2 estimate
    meas = np.maximum(np.nan_to_num(_pooled_median(stats["drift"], pool), nan=0.0), 0.0)
    for oi, o in enumerate(orders):
        t2n = n_rel ** _BIAS_POWER["normal"][o]
        t2h = n_rel ** _BIAS_POWER["H"][o]
        drift = (b2[:, oi, 0] + b2[:, oi, 1])[:, None] * t2n[None, :]
        if plane and o == 1:  # the plane: its alias where measured
            plane_b2 = np.maximum(alias, 0.0) + (2.0 * follow - 1.0) * tang[:, None]
            drift = np.where(np.isfinite(alias), np.maximum(plane_b2, 0.0),
                             drift)
        elif plane:  # a curved jet: its normal moves with the query's own tangential noise
            drift = drift + tang[:, None]
        drift = np.maximum(drift, meas[:, oi])
        mse[:, oi, :, 0] += drift
        # H: b_s = B t_s + C u_s and its variance, where the attenuation term applies
        t, uu = np.sqrt(t2h)[None, :], np.nan_to_num(stats["u"][rows, oi], nan=0.0)
        b = BCp[:, oi, :1] * t + BCp[:, oi, 1:] * uu
        vb = cvp[:, oi, :1] * t * t + cvp[:, oi, 1:2] * uu * uu + 2.0 * cvp[:, oi, 2:] * t * uu
        mse[:, oi, :, 1] += np.where(att[:, oi, None], np.maximum(b * b - vb, 0.0),
                                     b2[:, oi, 2][:, None] * t2h[None, :])
    return mse


def choose(stats: dict, table: np.ndarray, pool: np.ndarray, sizes: np.ndarray,
           orders: tuple[int, ...]) -> dict:
    """Per query, the pooled errors of every setting for the normal and for the curvatures.

    ``table (O, S, 2, N)``: :func:`point_mse` of every point (:func:`store_mse`; NaN where not
    defined), pooled (median) over ``pool (Q, P)`` (the query first; ``-1`` padding ignored;
    a NaN counts as an infinite error, so that a setting most neighbours cannot fit is not
    judged by the few that can); per order the sizes above the pooled (geometric median) ICI
    size (for the curvatures only where the pooled ``u`` at that size is below
    ``_U_LIFT``: module docstring, 3.), those the query itself cannot fit and, for the
    curvatures, order 1 (when a higher order is tried) get ``inf``. Returns
    ``normal`` and ``curvature``, each ``(Q, O * S)`` (order-major; :func:`best_setting`).
    """
    Q = pool.shape[0]
    O, S = table.shape[0], table.shape[1]
    flat_table = table.reshape(O * S * 2, -1)
    # a setting a neighbour cannot fit counts as an infinite error there
    flat_table = np.where(np.isnan(flat_table), np.inf, flat_table)
    m = _pooled_median_t(flat_table, pool)  # (O * S * 2, Q)
    m = np.moveaxis(m.reshape(O, S, 2, Q), -1, 0)
    m = np.where(np.isnan(m), np.inf, m)
    logs = np.log(sizes.astype(np.float64))
    cap = np.exp(_pooled_median(logs[stats["size"]], pool))  # (Q, O)
    allowed = sizes[None, None, :] <= cap[:, :, None] * (1 + 1e-9)
    allowed[:, :, 0] = True
    # the curvatures' cap lifted where the noise is large against the neighbourhood
    u_ici = np.take_along_axis(stats["u"], stats["size"][..., None], -1)[..., 0]  # (N, O)
    with np.errstate(invalid="ignore"):
        lift = _pooled_median(u_ici, pool) >= _U_LIFT  # (Q, O); NaN: not lifted
    own = stats["var"][np.maximum(pool[:, 0], 0)]  # (Q, O, S, 2): the point's own fits
    flat = np.array([o < 2 for o in orders]) & any(o >= 2 for o in orders)
    out = {}
    for c, name in enumerate(("normal", "curvature")):
        ok = np.isfinite(own[..., c])  # a setting the point itself can fit
        ok &= allowed if c == 0 else (allowed | lift[:, :, None])
        if c == 1:
            ok &= ~flat[None, :, None]  # curvature from a curved jet when there is one
        out[name] = np.where(ok, m[..., c], np.inf).reshape(Q, O * S)
    return out


def best_setting(score: np.ndarray, sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(order index (Q,), rows (Q,))`` of least ``score (Q, O * S)`` per query.

    Where no setting is finite: the lowest order at the widest size.
    """
    S = sizes.size
    j = np.argmin(score, axis=1)
    none = ~np.isfinite(score[np.arange(score.shape[0]), j])
    return np.where(none, 0, j // S), sizes[np.where(none, S - 1, j % S)]


def merge_normals(out: Quantities, rows: np.ndarray, normals: np.ndarray,
                  status: np.ndarray) -> None:
    """Give ``rows`` of ``out`` the ``normals`` of another fit, curvatures following them.

    Where the normals point to the other side of the curvature fit's, its curvatures, frame
    and coefficients flip with them (``k1, k2 -> -k2, -k1``, ``d1 <-> d2``); ``d1`` is then
    projected onto the new tangent plane and ``d2 = n x d1``. Rows whose normal fit is
    flagged (``status != 0``) keep their own normal.
    """
    keep = status == 0  # a flagged normal fit: the curvature fit's normal stays
    rows, normals = rows[keep], normals[keep]
    if rows.size == 0:
        return
    n_old = out.normals[rows]
    neg = np.einsum("ij,ij->i", n_old, normals) < 0
    k1, k2 = out.curvatures[rows, 0].copy(), out.curvatures[rows, 1].copy()
    d1, d2 = out.d1[rows].copy(), out.d2[rows].copy()
    out.curvatures[rows, 0] = np.where(neg, -k2, k1)
    out.curvatures[rows, 1] = np.where(neg, -k1, k2)
    out.curvatures[rows, 2] = np.where(neg, -1.0, 1.0) * out.curvatures[rows, 2]
    d1 = np.where(neg[:, None], d2, d1)
    s = np.where(neg, -1.0, 1.0)
    out.frame[rows] = flip_frame(out.frame[rows], s)
    order = next(o for o in range(1, 5) if jets.n_coeffs(o) == out.coeffs.shape[1])
    out.coeffs[rows] = out.coeffs[rows] * coeff_signs(torch.from_numpy(s), order).numpy()
    d1 = d1 - np.einsum("ij,ij->i", d1, normals)[:, None] * normals
    nd = np.linalg.norm(d1, axis=1, keepdims=True)
    d1 = np.where(nd > 0, d1 / np.where(nd > 0, nd, 1.0), d1)
    out.d1[rows] = d1
    out.d2[rows] = np.cross(normals, d1)
    out.normals[rows] = normals


def _fit_choice(hoods, out, q, nbr, dist, order_i, kuse, orders, settings) -> None:
    """Fused fits of the queries ``q`` at their chosen order index and size, into ``out``."""
    for oi, o in enumerate(orders):
        sel = order_i == oi
        if sel.any():
            fit_fused(hoods, q[sel], nbr[sel], dist[sel], kuse[sel], out, order=o,
                      gaussian=False, settings=settings, parallel_min=PARALLEL_MIN // 8)


def fit_auto(hoods: Neighbourhoods, out: Quantities, *, settings: Settings) -> None:
    """All passes (statistics, errors, pooled choice and fused fits) over all finite points."""
    orders = auto_orders(settings)
    if 1 not in settings.max_cond:  # the plane added for the normal: the strictest bound
        settings = replace(settings, max_cond={1: min(settings.max_cond.values()),
                                               **settings.max_cond})
    sizes = candidate_sizes(hoods, settings)
    n = hoods.P.shape[0]
    n_pool = max(int(AUTO_K_SMOOTH), 1)
    stats: dict | None = None
    pools = np.full((n, n_pool), -1, dtype=np.int64)
    for q in hoods.chunks(settings.batch_size, settings.progress):
        nbr, dist = hoods.query(q)
        part = point_statistics(hoods, q, nbr, dist, orders=orders, sizes=sizes,
                                settings=settings)
        if stats is None:
            stats = {k: np.full((n,) + v.shape[1:], np.nan if v.dtype.kind == "f" else 0,
                                dtype=v.dtype) for k, v in part.items()}
        for k, v in part.items():
            stats[k][q] = v
        # the pool: the point and its nearest neighbours (the k-NN list starts with the point)
        pools[q, : min(n_pool, nbr.shape[1])] = nbr[:, :n_pool]
    if stats is None:
        return
    table = np.full(stats["var"].shape[1:] + (n,), np.nan, dtype=np.float32)
    for q in hoods.chunks(settings.batch_size, False):
        store_mse(table, q, point_mse(stats, q, pools[q], sizes, orders))
    for q in hoods.chunks(settings.batch_size, settings.progress):
        nbr, dist = hoods.query(q)
        score = choose(stats, table, pools[q], sizes, orders)
        on, kn = best_setting(score["normal"], sizes)
        oc, kc = best_setting(score["curvature"], sizes)
        other = (on != oc) | (kn != kc)
        # the normal's setting first (kept for the points whose curvature setting differs)
        _fit_choice(hoods, out, q[other], nbr[other], dist[other], on[other], kn[other],
                    orders, settings)
        rows = q[other]
        n_nrm, n_st = out.normals[rows].copy(), out.status[rows].copy()
        _fit_choice(hoods, out, q, nbr, dist, oc, kc, orders, settings)
        # a setting the fused fit flags (its own frame found the system degenerate): the
        # next best, a few times
        sc = score["curvature"]
        for _ in range(_RETRIES):
            bad = np.flatnonzero(out.status[q] != 0)
            if bad.size == 0:
                break
            sc[bad, np.searchsorted(sizes, kc[bad]) + oc[bad] * sizes.size] = np.inf
            ob, kb = best_setting(sc[bad], sizes)
            fin = np.isfinite(sc[bad]).any(1)
            bad, ob, kb = bad[fin], ob[fin], kb[fin]
            oc[bad], kc[bad] = ob, kb
            _fit_choice(hoods, out, q[bad], nbr[bad], dist[bad], ob, kb, orders, settings)
        merge_normals(out, rows, n_nrm, n_st)
