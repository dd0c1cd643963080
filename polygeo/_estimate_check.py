"""Held-out check of the automatic normal against two fixed settings.

With ``k="auto"`` and ``order="auto"`` the normal's setting is chosen per point from modelled
errors (:mod:`polygeo._estimate_auto`). The model can be wrong both ways:

* where the data are not noisy it can be biased: on real range scans (the Stanford bunny) it
  chose wider fits than the default (``k=20``, order 2) with confidence, and lost to the
  default against both references (the other scan, the zippered reconstruction) by 1-2 %, by
  12 % on the zippered bunny with noise of 5 % of an edge;
* where the noise is large against the neighbourhoods (dense samples: the 100k-point torus
  of bm_jets at noise 1 % of the diagonal, about three point spacings) the model's variance
  of a fit (noise in height only) falls short of the truth by several times, the narrower
  sizes' noise reads as drift, and it chose 97-257 points where the widest candidate is
  better (normal error 9.8 deg against 5.9 at 385 points).

This module asks the data instead, once per cloud:

1. hold out a seeded share :data:`HOLD_OUT` of the finite points (``B``), fit the automatic
   setting and each alternative (:func:`alternatives`: the default, and order 2 at the
   widest size ``k="auto"`` tries) on the rest (``A``);
2. for each point ``a`` of ``A`` and its :data:`N_SCORED` nearest held-out points ``b``, the
   offset of ``b`` from the tangent plane of each setting at ``a``, over the distance:
   ``s = (n . (b - a))^2 / |b - a|^2``. The held-out point's noise is independent of the fit,
   the query's own enters both settings alike, and the surface's own offset (``II(t, t) / 2``,
   even in ``t = b - a``) does not correlate with the normal's error (odd in ``t``) on
   average, so that the mean of ``s_auto - s_alt`` estimates half the difference of the
   settings' mean squared normal errors (rad^2) without a model of either (attenuated where
   the noise is comparable to ``|b - a|``, which enlarges the denominator: 0.0023 for a true
   0.041 rad^2 on the dense noisy torus, at 6 standard errors);
3. an alternative's normal replaces the automatic one (the curvatures follow its sign,
   :func:`polygeo._estimate_auto.merge_normals`) where that estimate says it is better by
   more than :data:`Z_MIN` standard errors and, for the default, by more than
   :data:`REL_MIN` of its mean ``s`` (the criterion's own bias: on clean data the held-out
   points are the holes of ``A``'s sampling, which the default's truncation error follows;
   measured at most 4e-4 of it on bm_jets' clean grid, against 3 % on the bunny scans). The
   widest fit needs no such margin: on clean data that bias favours the narrower automatic
   fit, against the switch. Where both win, the one of lower mean score.

Measured (bm_jets' grid, 10k points; the mean of ``2 (s_auto - s_default)`` in deg^2 against
the true difference of mean squared errors): under noise both agree in sign in all 12 cells
(z from -3 to -23: the automatic normal kept); clean: torus -0.014 (true -0.004), cylinder
+6e-5 (2e-7), sphere +4e-4 (-1e-6), monge +8e-5 (-7e-6), each below 1e-3 of the level. Scans:
bun000 +1.9 (z 12, 3.4 % of the level), bun045 +1.4 (z 10, 2.9 %); zippered bunny with noise
of 5 % of an edge +2.8 (3.0 %; true +6.0 at the interior vertices), 20 %: -9.6 (kept).
The widest fit (z): chosen on the 10k cylinder at 0.1 % and 1 % (5.0, 4.8; median normal
0.218 -> 0.172 and 1.95 -> 1.69 deg, the best fixed 0.171 / 1.67) and on the 100k torus at
0.1 % and 1 % (5.1, 6.3; 0.630 -> 0.585 and 9.83 -> 5.92 deg); kept out of the other 14 grid
cells (clean -10 to -31) and the scans. Out of reach: noise of several spacings on small
clouds (an 8,000-point sphere at 5 %: z -1.4 where the widest fit is 1.3x better).

Cost: one more automatic fit and one fit of each alternative on ``A``, and one on all points
for an alternative that wins (about twice the automatic setting's time).
The choice is one per cloud: a point's normal then depends on the whole cloud (seeded, so the
same cloud gives the same result), not only on its neighbours.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from ._estimate_auto import fit_auto, merge_normals
from ._estimate_stages import MAX_COND, Neighbourhoods, Settings, empty_quantities, fit_compiled

__all__ = ["DEFAULT_K", "alternatives", "check_normals", "default_settings", "held_out_verdict",
           "offset_scores", "widest_settings"]

#: The default setting the automatic normal must not lose to: ``k`` (order 2).
DEFAULT_K = 20
#: Share of the finite points held out, and the seed of the split.
HOLD_OUT = 0.1
SEED = 0
#: Held-out points scored per fitted point (its nearest).
N_SCORED = 3
#: Fewest held-out points for a verdict (fewer: the automatic normal is kept).
MIN_HELD_OUT = 100
#: An alternative wins by more than this many standard errors of the mean difference ...
Z_MIN = 3.0
#: ... and the default by more than this share of its mean score (the criterion's bias on
#: clean data, which favours narrow fits).
REL_MIN = 0.01


def _order2(s: Settings, size: int) -> Settings:
    """Order 2 on ``size`` points (``k = size - 1``) with the other options of ``s``."""
    return replace(s, k=size - 1, sizes=(size,), order=2,
                   max_cond={2: s.max_cond.get(2, MAX_COND[2])}, progress=False)


def default_settings(s: Settings) -> Settings:
    """The default setting (``k=DEFAULT_K``, order 2) with the other options of ``s``."""
    return _order2(s, DEFAULT_K + 1)


def widest_settings(s: Settings, n_points: int) -> Settings:
    """Order 2 at the widest size ``s`` tries (``max(s.sizes)`` points), on ``n_points``."""
    return _order2(s, max(min(max(s.sizes), n_points), 2))


def alternatives(s: Settings, n_points: int) -> list[tuple[str, Settings, float]]:
    """The fixed settings the automatic normal is checked against.

    ``(name, settings, rel)`` each, ``rel`` the share of the alternative's mean score by
    which it must win (:func:`held_out_verdict`).
    """
    return [("default", default_settings(s), REL_MIN),
            ("widest", widest_settings(s, n_points), 0.0)]


def _fit(P: np.ndarray, s: Settings):
    """Normals and status of every point of ``P`` (all finite) at the settings ``s``."""
    hoods = Neighbourhoods(P, np.ones(P.shape[0], dtype=bool), faces=None, settings=s,
                           graph=False)
    out = empty_quantities(P.shape[0], s.n_coeffs)
    if s.k == "auto" or s.order == "auto":
        fit_auto(hoods, out, settings=s)
    else:
        for q in hoods.chunks(s.batch_size, False):
            nbr, dist = hoods.query(q)
            fit_compiled(hoods, q, nbr, dist, out, settings=s)
    return out


def offset_scores(P: np.ndarray, a: np.ndarray, b: np.ndarray, normals: list[np.ndarray],
                  m: int = N_SCORED) -> tuple[np.ndarray, np.ndarray]:
    """Held-out offsets from the tangent planes of the fitted points ``a``.

    ``P (N, 3)`` points; ``a (A,)``, ``b (B,)`` indices of the fitted and the held-out
    points; ``normals``: one ``(A, 3)`` array of unit normals per setting (NaN where not
    estimated). Returns ``scores (len(normals), A)``: per fitted point the mean over its
    ``m`` nearest held-out points of ``(n . (p_b - p_a))^2 / |p_b - p_a|^2`` (dimensionless;
    pairs at distance 0 skipped), and ``valid (A,)``: where every setting has a finite
    score.
    """
    m = min(m, b.size)
    _, j = cKDTree(P[b]).query(P[a], m)
    X = P[b][j.reshape(a.size, m)] - P[a][:, None, :]
    r2 = (X * X).sum(-1)
    use = r2 > 0
    scores = []
    for n in normals:
        with np.errstate(invalid="ignore", divide="ignore"):
            s = np.einsum("aj,amj->am", n, X) ** 2 / np.where(use, r2, 1.0)
            scores.append(np.where(use, s, 0.0).sum(1) / use.sum(1))
    scores = np.stack(scores)
    return scores, np.isfinite(scores).all(0)


def held_out_verdict(score_auto: np.ndarray, score_alt: np.ndarray, rel: float = REL_MIN) -> dict:
    """Whether an alternative's normal is better, from :func:`offset_scores` of both settings.

    Returns ``better`` (bool: by more than :data:`Z_MIN` standard errors and more than ``rel``
    of the level), ``dmse`` (the estimated mean squared normal error of the automatic setting
    less the alternative's, rad^2), ``se`` (its standard error), ``level`` (twice the
    alternative's mean score, rad^2) and ``n`` (points scored).
    """
    d = 2.0 * (score_auto - score_alt)
    n = d.size
    if n < 2:
        return dict(better=False, dmse=float("nan"), se=float("nan"), level=float("nan"), n=n)
    est, se = float(d.mean()), float(d.std(ddof=1) / np.sqrt(n))
    level = float(2.0 * score_alt.mean())
    better = est > Z_MIN * se and est > rel * level
    return dict(better=bool(better), dmse=est, se=se, level=level, n=n)


def check_normals(P: np.ndarray, finite: np.ndarray, out, s: Settings) -> dict:
    """The held-out check of the automatic normals in ``out`` (module docstring).

    ``P (N, 3)`` float64 points, ``finite (N,)`` which are; ``out``: the automatic fit
    (``Quantities``, changed in place where an alternative wins); ``s``: its settings.
    Returns ``chosen`` (``"auto"`` or the winning alternative's name) and each alternative's
    verdict (:func:`held_out_verdict`) under its name; ``skipped`` where too few points are
    held out.
    """
    idx = np.flatnonzero(finite)
    n_held = int(HOLD_OUT * idx.size)
    if n_held < MIN_HELD_OUT:
        return dict(chosen="auto", skipped=f"{n_held} held-out points (< {MIN_HELD_OUT})")
    rng = np.random.default_rng(SEED)
    held = np.zeros(idx.size, dtype=bool)
    held[rng.choice(idx.size, n_held, replace=False)] = True
    a, b = idx[~held], idx[held]
    alts = alternatives(s, a.size)
    fits = [_fit(P[a], replace(s, progress=False))] + [_fit(P[a], st) for _, st, _ in alts]
    scores, valid = offset_scores(P, a, b, [f.normals for f in fits])
    verdict: dict = {"chosen": "auto"}
    best = np.inf
    for i, (name, st, rel) in enumerate(alts, start=1):
        verdict[name] = held_out_verdict(scores[0, valid], scores[i, valid], rel)
        mean = float(scores[i, valid].mean()) if valid.any() else np.inf
        if verdict[name]["better"] and mean < best:
            verdict["chosen"], best, chosen = name, mean, st
    if verdict["chosen"] != "auto":
        full = _fit(P[idx], chosen)
        merge_normals(out, idx, full.normals, full.status)
    return verdict
