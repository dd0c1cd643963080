"""Stages of :func:`polygeo.estimate.differential_quantities` (DESIGN.md §3).

neighbours (:class:`Neighbourhoods`) -> frames -> fit -> quantities, per chunk of points, by
one of three stage functions:

* :func:`fit_fused` — the compiled kernels of :mod:`polygeo._estimate_numba` (one size and one
  order per point, given per point by :mod:`polygeo._estimate_auto` for ``k="auto"``);
* :func:`fit_unfused` — the same stages one after the other over the chunk (NumPy frames,
  :func:`polygeo.jets.fit`, :func:`polygeo._diffgeo_numba.jet_geometry`): several sizes
  (``k="auto"`` with weights, a radius or rings) and several orders (``order="auto"``, the
  F-test of :func:`select_order`); also the reference the fused kernels are tested against;
* :func:`fit_torch` — differentiable with respect to the points (frames, jets and diffgeo in
  torch).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from . import jets
from ._diffgeo_numba import jet_geometry
from ._estimate_numba import (
    PARALLEL_MIN,
    Hoods,
    JetSettings,
    Quantities,
    frames_fit_quantities,
)
from ._frames_numba import height_frames_par, height_frames_ser
from ._jets_common import exponents_np
from .neighbors import PointIndex, mesh_k_ring
from .status import Status

#: Neighbour counts tried by ``k="auto"`` (besides the point itself; capped by the data).
AUTO_K_CANDIDATES = (12, 16, 20, 24, 32, 48, 64, 96, 128, 192, 256, 384)
#: Width (in standard deviations) of the confidence intervals of ``k="auto"``.
AUTO_K_GAMMA = 2.5
#: Neighbours whose automatic sizes are pooled (median) per point by ``k="auto"``.
AUTO_K_SMOOTH = 24
#: Jet orders tried by ``order="auto"``.
AUTO_ORDERS = (2, 3, 4)
#: Default largest condition number accepted per jet order (see ``max_cond``).
MAX_COND = {1: 1e3, 2: 1e3, 3: 1e4, 4: 1e5}

#: Width of the ICI confidence intervals of the unfused ``k="auto"`` (standard deviations).
_ICI_GAMMA = 3.0
#: Standard deviation of an order-2 fit's H in units of sigma / (r^2 sqrt(n)).
_ICI_H_FACTOR = 3.0


@dataclass(frozen=True)
class Settings:
    """Validated settings of one :func:`~polygeo.estimate.differential_quantities` call.

    ``sizes``: candidate neighbourhood sizes in points, the point itself included (``k + 1``
    for an integer ``k``); ``max_cond``: the accepted condition number per order fitted.
    The other fields are the call's arguments of the same names.
    """

    k: int | str
    sizes: tuple[int, ...]
    radius: float | None
    rings: int | None
    order: int | str
    auto_orders: tuple[int, ...]
    weights: str | None
    max_cond: dict[int, float]
    interpolate: bool
    alpha: float
    orient: str
    batch_size: int
    progress: bool | None
    workers: int
    use_torch: bool
    monge: bool
    forms: bool
    normal_check: bool = True

    @property
    def orders(self) -> tuple[int, ...]:
        """The orders fitted: ``(order,)``, or ``auto_orders`` for ``order="auto"``."""
        return self.auto_orders if self.order == "auto" else (self.order,)

    @property
    def n_coeffs(self) -> int:
        """Coefficients of the largest order fitted (width of the ``coeffs`` output)."""
        return jets.n_coeffs(max(self.orders))


# ----------------------------------------------------------------------------- neighbours


class Neighbourhoods:
    """Neighbours of the finite points, nearest first: a k-d tree, a radius or mesh rings.

    Queried chunk by chunk (:meth:`query`). Exact duplicates are merged the first time a
    query meets one: the tree then keeps one copy per location and every copy is answered as
    its representative ``source[i]``. ``graph`` collects the first (up to 6) neighbours of
    every point for the orientation (when ``graph=True``).
    """

    def __init__(self, P: np.ndarray, finite: np.ndarray, *, faces: np.ndarray | None,
                 settings: Settings, graph: bool):
        n = P.shape[0]
        self.P, self.finite, self.workers = P, finite, settings.workers
        self.auto_k = settings.k == "auto"
        self.source = np.arange(n)  # representative of each point among exact duplicates
        self.deduped = False
        self.index = PointIndex(P) if settings.rings is None else None
        self.ring = None
        kmax = max(settings.sizes)
        if settings.rings is not None:
            cap = None if self.auto_k else settings.sizes[0]
            self.ring = _sorted_rings(P, finite, faces, settings.rings, cap)
            kmax = self.ring[0].shape[1]
        if self.auto_k and settings.rings is None:
            kmax += 1  # one beyond the widest size: its margin (_estimate_auto._rank_gap)
        self.kmax = kmax
        #: neighbours queried per point (the point itself included)
        self.k_query = min(kmax, max(int(finite.sum()), 1))
        radius = settings.radius
        self.upper = np.inf if radius is None else np.nextafter(radius, np.inf) * (1 + 1e-12)
        self.graph = np.full((n if graph else 0, min(6, self.k_query)), -1, dtype=np.int64)

    def chunks(self, batch_size: int, progress: bool | None):
        """Finite query points in chunks of at most ``batch_size``, in grid-cell order.

        ``k="auto"`` caps the chunks at about 4e6 neighbour rows.
        """
        n = self.P.shape[0]
        if self.auto_k:
            batch_size = min(batch_size, max(1024, 4_000_000 // max(self.k_query, 1)))
        # neighbouring queries share neighbours (cache)
        visit = self.index.spatial_order() if self.index is not None else None
        if visit is None or visit.size != n:
            visit = np.arange(n)
        starts = range(0, n, batch_size)
        if (n >= 200_000) if progress is None else bool(progress):
            from tqdm.auto import tqdm

            starts = tqdm(starts, total=math.ceil(n / batch_size), desc="jets", unit="chunk")
        for start in starts:
            q = visit[start : start + batch_size]
            q = q[self.finite[q]]
            if q.size:
                yield q

    def query(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(nbr, dist)`` ``(Q, K)`` of the points ``q``: indices (-1 padding), distances."""
        if self.ring is not None:
            nbr, dist = self.ring[0][q], self.ring[1][q]
        else:
            wk = self.workers if q.size >= PARALLEL_MIN else 1
            nbr, dist = self.index.query(self.P[q], self.k_query, workers=wk, upper=self.upper,
                                         self_index=self.source[q])
            if not self.deduped and nbr.shape[1] > 1 and bool((dist[:, 1] == 0).any()):
                self._merge_duplicates()
                nbr, dist = self.index.query(self.P[q], self.k_query, workers=wk,
                                             upper=self.upper, self_index=self.source[q])
        if self.graph.shape[0]:
            k_graph = self.graph.shape[1]
            self.graph[q, : min(k_graph, nbr.shape[1])] = nbr[:, :k_graph]
        return nbr, dist

    def query_more(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(nbr, dist)`` of extra points ``q`` (no orientation graph, no merging)."""
        if self.ring is not None:
            return self.ring[0][q], self.ring[1][q]
        wk = self.workers if q.size >= PARALLEL_MIN else 1
        return self.index.query(self.P[q], self.k_query, workers=wk, upper=self.upper,
                                self_index=self.source[q])

    def _merge_duplicates(self) -> None:
        """Keep one copy per location in the tree; answer all copies as that one."""
        P, finite = self.P, self.finite
        n = P.shape[0]
        self.deduped = True
        self.source = _representatives(P, finite)
        Pt = P.copy()
        Pt[self.source != np.arange(n)] = np.nan
        self.index = PointIndex(Pt)
        n_distinct = int((self.source[finite] == np.flatnonzero(finite)).sum())
        self.k_query = min(self.kmax, max(n_distinct, 1))

    def hoods(self, q, nbr, dist, kuse) -> Hoods:
        """The :class:`~polygeo._estimate_numba.Hoods` record of a chunk (contiguous)."""
        c = np.ascontiguousarray
        return Hoods(points=self.P, source=c(self.source[q]), row=c(q), nbr=c(nbr),
                     dist=c(dist), kuse=kuse)


def _sorted_rings(P, finite, faces, rings, cap):
    """Mesh ``rings``-rings of every vertex sorted by distance (at most ``cap`` entries)."""
    n = P.shape[0]
    ring = mesh_k_ring(faces, n, rings)
    r_idx = np.where(ring.mask & finite[np.maximum(ring.index, 0)], ring.index, -1)
    # nearest first, so that the duplicate scan and the k cap see the nearest first
    r_d = np.linalg.norm(P[np.maximum(r_idx, 0)] - P[:, None, :], axis=-1)
    r_d = np.where(r_idx >= 0, r_d, np.inf)
    o = np.argsort(r_d, axis=1, kind="stable")
    r_idx = np.take_along_axis(r_idx, o, 1)
    r_d = np.take_along_axis(r_d, o, 1)
    if cap is not None and r_idx.shape[1] > cap:
        r_idx, r_d = r_idx[:, :cap], r_d[:, :cap]
    return r_idx, r_d


def _representatives(P: np.ndarray, finite: np.ndarray) -> np.ndarray:
    """Index of the first copy of each point among exact duplicates (itself if unique)."""
    n = P.shape[0]
    rep = np.arange(n)
    idx = np.flatnonzero(finite)
    if idx.size:
        _, first, inv = np.unique(P[idx], axis=0, return_index=True, return_inverse=True)
        rep[idx] = idx[first][inv.reshape(-1)]
    return rep


def candidate_sizes(hoods: Neighbourhoods, nbr: np.ndarray, settings: Settings) -> list[int]:
    """Neighbourhood sizes tried for a chunk (one unless ``k="auto"``)."""
    sizes = [c for c in settings.sizes if c <= nbr.shape[1]] or [nbr.shape[1]]
    if hoods.auto_k and settings.radius is None and hoods.ring is None:
        sizes = sorted({min(c, hoods.k_query) for c in settings.sizes})
    return sizes


def empty_quantities(n: int, n_coeffs: int) -> Quantities:
    """Output arrays for ``n`` points: NaN (status ``NONFINITE_INPUT``) until estimated."""
    return Quantities(
        normals=np.full((n, 3), np.nan), d1=np.full((n, 3), np.nan),
        d2=np.full((n, 3), np.nan), curvatures=np.full((n, 4), np.nan),
        status=np.full(n, int(Status.NONFINITE_INPUT), dtype=np.int64),
        fitted_order=np.zeros(n, dtype=np.int64), n_neighbors=np.zeros(n, dtype=np.int64),
        residual=np.full(n, np.nan), frame=np.full((n, 3, 3), np.nan),
        coeffs=np.zeros((n, n_coeffs)),
    )


# ----------------------------------------------------------------------------- fused stages


def jet_settings(order: int, *, gaussian: bool, max_cond: float,
                 interpolate: bool) -> JetSettings:
    """The kernels' :class:`~polygeo._estimate_numba.JetSettings` for jets of ``order``."""
    e = exponents_np(order)
    return JetSettings(order=order, gaussian=gaussian, max_cond=float(max_cond),
                       interpolate=interpolate, ep=np.ascontiguousarray(e[:, 0]),
                       eq=np.ascontiguousarray(e[:, 1]))


def fit_compiled(hoods: Neighbourhoods, q, nbr, dist, out: Quantities, *,
                 settings: Settings) -> None:
    """Frames -> fit -> quantities of the chunk ``q`` into ``out`` (compiled, not differentiable).

    Fused (:func:`fit_fused`) for one size and one order per point, else stage by stage
    (:func:`fit_unfused`). (``k="auto"`` / ``order="auto"`` on one k-NN list without weights
    never come here: :func:`polygeo._estimate_auto.fit_auto`.)
    """
    orders = settings.orders
    sizes = candidate_sizes(hoods, nbr, settings)
    if len(sizes) == 1 and len(orders) == 1:
        kuse = np.full(q.size, int(sizes[0]), dtype=np.int64)
        fit_fused(hoods, q, nbr, dist, kuse, out, order=orders[0],
                  gaussian=settings.weights == "gaussian", settings=settings)
        return
    fit_unfused(hoods, q, nbr, dist, sizes, out, settings=settings)


def fit_fused(hoods: Neighbourhoods, q, nbr, dist, kuse, out: Quantities, *, order: int,
              gaussian: bool, settings: Settings, parallel_min: int = PARALLEL_MIN) -> None:
    """Frames -> fit -> quantities of the chunk ``q`` in one compiled pass, into ``out``.

    ``kuse (Q,)``: rows of ``nbr`` used per query; jets of ``order``.
    """
    jet = jet_settings(order, gaussian=gaussian, max_cond=float(settings.max_cond[order]),
                       interpolate=settings.interpolate)
    frames_fit_quantities(hoods.hoods(q, nbr, dist, kuse), jet, out, parallel_min=parallel_min)


# ----------------------------------------------------------------------------- unfused stages


class Local:
    """Height coordinates of a chunk of neighbourhoods (NumPy, float64): the frames stage.

    ``kuse``: rows of ``nbr`` used, one for all or one per query.
    """

    def __init__(self, P, qidx, nbr, dist, kuse):
        Q, K = nbr.shape
        self.uv = np.empty((Q, K, 2))
        self.z = np.empty((Q, K))
        self.valid = np.zeros((Q, K), dtype=np.bool_)
        self.R = np.empty((Q, 3, 3))
        self.count = np.zeros(Q, dtype=np.int64)
        self.radius = np.zeros(Q)
        if Q:
            ku = np.broadcast_to(np.asarray(kuse, dtype=np.int64), (Q,)).copy()
            kernel = height_frames_par if Q >= PARALLEL_MIN else height_frames_ser
            kernel(P, qidx, nbr, dist, ku, self.uv, self.z, self.valid, self.R,
                   self.count, self.radius)


def gaussian_weights(local: Local) -> np.ndarray:
    """``(Q, K)`` weights ``exp(-d^2 / rms^2)`` of the distance to the query (0 if invalid)."""
    r2 = (local.uv**2).sum(-1) + local.z**2
    h2 = np.maximum(local.radius**2, 1e-300)[:, None]
    return np.where(local.valid, np.exp(-r2 / h2), 0.0)


def fit_local(local: Local, order: int, weights: np.ndarray | None, max_cond: float,
              interpolate: bool = False) -> jets.JetFit:
    """The fit stage on height coordinates: :func:`polygeo.jets.fit` (numba backend)."""
    return jets.fit(
        torch.from_numpy(local.uv),
        torch.from_numpy(local.z),
        order,
        mask=torch.from_numpy(local.valid),
        weights=None if weights is None else torch.from_numpy(weights),
        max_cond=max_cond,
        backend="numba",
        interpolate=interpolate,
    )


def select_order(fits: list[jets.JetFit], orders: tuple[int, ...], alpha: float) -> np.ndarray:
    """Index into ``orders`` per item: the lowest order no higher one beats by an F-test."""
    from scipy.stats import f as fdist

    n = fits[0].n_points.numpy().astype(np.float64)
    rss = [f.residual.double().numpy() ** 2 * n for f in fits]
    ok = [f.status.numpy() == 0 for f in fits]
    cur = np.zeros(n.shape[0], dtype=np.int64)
    for j in range(1, len(orders)):
        mc = np.array([jets.n_coeffs(orders[c]) for c in range(len(orders))])[cur]
        mj = jets.n_coeffs(orders[j])
        rss_c = np.choose(cur, rss)
        dof = n - mj
        good = ok[j] & (dof > 0) & (mj > mc)
        num = (rss_c - rss[j]) / np.maximum(mj - mc, 1)
        den = rss[j] / np.maximum(dof, 1)
        scale = np.maximum(rss_c, 1e-300)
        exact = rss_c <= 1e-24 * scale + 1e-300  # the current model is already exact
        with np.errstate(divide="ignore", invalid="ignore"):
            F = np.where(den > 0, num / den, np.inf)
        crit = fdist.ppf(1.0 - alpha, np.maximum(mj - mc, 1), np.maximum(dof, 1))
        better = good & ~exact & (F > crit)
        cur = np.where(better, j, cur)
    return cur


def ici_select(
    normals: list[np.ndarray],
    delta: list[np.ndarray],
    gamma: float,
    scalars: list[np.ndarray] | None = None,
    scalar_deltas: list[np.ndarray] | None = None,
) -> np.ndarray:
    """Pick a neighbourhood size by intersection of confidence intervals (ICI).

    Over increasing k: the last candidate whose normal stays within ``gamma (delta_i +
    delta_j)`` of every smaller neighbourhood's normal (and, when given, whose scalar, e.g.
    the mean curvature, stays within ``gamma`` times the sum of the scalar deltas).
    """
    Q = normals[0].shape[0]
    chosen = np.zeros(Q, dtype=np.int64)
    alive = np.ones(Q, dtype=bool)
    for c in range(1, len(normals)):
        ok = alive.copy()
        for j in range(c):
            cosang = np.abs(np.einsum("ij,ij->i", normals[c], normals[j]))
            ang = np.arccos(np.clip(cosang, 0.0, 1.0))
            ok &= ang <= gamma * (delta[c] + delta[j])
            if scalars is not None:
                gap = np.abs(scalars[c] - scalars[j])
                ok &= gap <= gamma * (scalar_deltas[c] + scalar_deltas[j])
        ok &= np.isfinite(delta[c])
        chosen = np.where(ok, c, chosen)
        alive = ok
    return chosen


@dataclass
class _SizeFit:
    """The fits of a chunk at one neighbourhood size (the order test already applied)."""

    local: Local
    coeffs: np.ndarray  # (Q, M)
    status: np.ndarray  # (Q,)
    fitted_order: np.ndarray  # (Q,)
    residual: np.ndarray  # (Q,)
    n_neighbors: np.ndarray  # (Q,)


def _fit_orders(local: Local, *, settings: Settings, n_coeffs: int) -> _SizeFit:
    """Fit stage at every order of ``settings.orders``; per point the order the F-test keeps."""
    orders = settings.orders
    w = gaussian_weights(local) if settings.weights == "gaussian" else None
    fits = [fit_local(local, o, w, settings.max_cond[o], settings.interpolate) for o in orders]
    Q = local.uv.shape[0]
    pick = select_order(fits, orders, settings.alpha) if len(orders) > 1 else np.zeros(Q, int)
    co = np.zeros((Q, n_coeffs))
    for j, fj in enumerate(fits):
        sel = pick == j
        if sel.any():
            c = fj.coeffs.double().numpy()
            co[sel, : c.shape[1]] = c[sel]
    return _SizeFit(
        local=local, coeffs=co,
        status=np.choose(pick, [f.status.numpy() for f in fits]),
        fitted_order=np.choose(pick, [f.fitted_order.numpy() for f in fits]),
        residual=np.choose(pick, [f.residual.double().numpy() for f in fits]),
        n_neighbors=fits[0].n_points.numpy(),
    )


def _choose_size(per_size: list[_SizeFit]) -> np.ndarray:
    """Index into ``per_size`` per point: normals and H agree within their noise (ICI)."""
    geoms = [jet_geometry(ps.coeffs, ps.local.R) for ps in per_size]
    deltas, deltas_h, hs = [], [], []
    n_ref = geoms[0]["normals"]
    for ps, g in zip(per_size, geoms):
        npts = ps.n_neighbors
        mm = np.array([jets.n_coeffs(max(o, 1)) for o in ps.fitted_order])
        dof = np.maximum(npts - mm, 1)
        sigma = ps.residual * np.sqrt(npts / dof)
        r = np.maximum(ps.local.radius, 1e-300)
        with np.errstate(divide="ignore", invalid="ignore"):
            d = sigma / (r * np.sqrt(np.maximum(npts, 1)))
        ok_s = ps.status == 0
        deltas.append(np.where(ok_s, d, np.inf))
        # H of an order-2 fit has a standard deviation of a few sigma / (r^2 sqrt(n))
        deltas_h.append(np.where(ok_s, _ICI_H_FACTOR * d / r, np.inf))
        side = np.sign(np.einsum("ij,ij->i", g["normals"], n_ref))
        hs.append(g["mean_curvature"] * np.where(side == 0, 1.0, side))
    return ici_select([g["normals"] for g in geoms], deltas, gamma=_ICI_GAMMA, scalars=hs,
                      scalar_deltas=deltas_h)


def fit_unfused(hoods: Neighbourhoods, q, nbr, dist, sizes, out: Quantities, *,
                settings: Settings) -> None:
    """Frames -> fit -> quantities of the chunk ``q`` stage by stage, into ``out``.

    Every size of ``sizes`` (an int, or ``(Q,)`` rows per query) and every order of
    ``settings.orders`` is fitted; per point the order test (:func:`select_order`) and, with
    several sizes, the size test (:func:`ici_select`) keep one fit.
    """
    per_size = []
    for size in sizes:
        # frames: PCA height coordinates of the first ``size`` rows
        local = Local(hoods.P, hoods.source[q], nbr, dist, size)
        # fit: one jet per order, the F-test keeps one
        per_size.append(_fit_orders(local, settings=settings, n_coeffs=out.coeffs.shape[1]))
    choice = _choose_size(per_size) if len(per_size) > 1 else np.zeros(q.size, dtype=np.int64)
    for s_i, ps in enumerate(per_size):
        sel = choice == s_i
        if not sel.any():
            continue
        # quantities at the jet's origin, in world axes
        g = jet_geometry(ps.coeffs[sel], ps.local.R[sel])
        qs = q[sel]
        out.normals[qs], out.d1[qs], out.d2[qs] = g["normals"], g["d1"], g["d2"]
        for c, key in enumerate(("k1", "k2", "mean_curvature", "gaussian_curvature")):
            out.curvatures[qs, c] = g[key]
        out.status[qs] = ps.status[sel]
        out.fitted_order[qs] = ps.fitted_order[sel]
        out.n_neighbors[qs] = ps.n_neighbors[sel]
        out.residual[qs] = ps.residual[sel]
        out.frame[qs] = ps.local.R[sel]
        out.coeffs[qs] = ps.coeffs[sel]


# ----------------------------------------------------------------------------- torch stages


def fit_torch(points: torch.Tensor, hoods: Neighbourhoods, q, nbr, dist, out: Quantities, *,
              settings: Settings) -> tuple[np.ndarray, Any, Any, Any]:
    """Differentiable frames -> fit -> quantities of the chunk ``q`` (one order, one size).

    Returns ``(q, fit, geometry, frames)`` (torch, differentiable w.r.t. ``points``); the
    integer outputs go into ``out``.
    """
    from .diffgeo import from_jet, to_world
    from .frames import pca_frames

    order = settings.order
    local = Local(hoods.P, hoods.source[q], nbr, dist, nbr.shape[1])
    w = gaussian_weights(local) if settings.weights == "gaussian" else None
    qt = torch.from_numpy(hoods.source[q])
    idx = torch.from_numpy(np.where(local.valid, nbr, 0))
    m = torch.from_numpy(local.valid)
    p64 = points.to(torch.float64)
    # frames: centred on the query point first, then PCA
    rel = p64[idx] - p64[qt][:, None, :]
    rel = torch.where(m[..., None], rel, torch.zeros_like(rel))
    R = pca_frames(rel, mask=m).rotation
    uvz = rel @ R
    # fit
    wt = None if w is None else torch.from_numpy(w)
    fit = jets.fit(
        uvz[..., :2], uvz[..., 2], order, mask=m, weights=wt, max_cond=settings.max_cond[order],
        backend="torch", interpolate=settings.interpolate,
    )
    # quantities at the jet's origin, in world axes
    geom = to_world(from_jet(fit.coeffs).squeeze(1), R)
    out.status[q] = fit.status.numpy()
    out.fitted_order[q] = fit.fitted_order.numpy()
    out.n_neighbors[q] = fit.n_points.numpy()
    return q, fit, geom, R
