"""Fitting stage of PolyFit: pad the partition, frame every patch, fit its jet.

The stages of :meth:`polygeo.patches.PatchSet.fit`, as pure functions over tensors:

1. :func:`pad_patches` packs the vertices of every patch into a padded ``(K, Pmax)`` index;
2. :func:`patch_reference_normals` gives each patch the input's side (input normals or the
   faces' area vectors);
3. :func:`polygeo.canonical.canonicalize` centres, scales and PCA-frames the patches and
   :func:`refine_rotations` applies the chosen orientation refinement (``orient``);
4. :func:`order_cap` bounds each patch's order by its point count, and :func:`fit_capped`
   (a fixed order) or :func:`fit_auto` (``order="auto"``) fit all jets in batched calls.

:func:`fit_partition` chains them; :func:`search_patch_count` drives the patch-count search
of ``target_rmse``. Shapes use ``K`` for the number of patches and ``Pmax`` for the largest
patch's point count; ``uv`` and heights are canonical (dimensionless).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from .. import jets
from ..canonical import canonicalize, height_residual, optimize_rotations
from ..checks import check_choice, check_int, check_positive
from ..partition import Partition, partition
from ..status import Status

__all__ = [
    "ORIENT_CHOICES",
    "FitSettings",
    "fit_settings",
    "partition_for_fit",
    "pad_patches",
    "patch_reference_normals",
    "refine_rotations",
    "order_cap",
    "fit_capped",
    "fit_auto",
    "uv_domain",
    "fit_partition",
    "search_patch_count",
]

#: Canonicalisation methods of :meth:`polygeo.patches.PatchSet.fit`.
ORIENT_CHOICES = ("pca", "stn", "optimize")


@dataclass(frozen=True)
class FitSettings:
    """Checked settings of one PolyFit fit (see :meth:`polygeo.patches.PatchSet.fit`).

    Attributes
    ----------
    order : int or "auto"
        Jet order in ``[1, 6]`` or ``"auto"``.
    orient : str
        One of :data:`ORIENT_CHOICES`.
    tol : float or None
        Height tolerance of ``order="auto"`` (input units); None: BIC.
    max_order : int
        Largest order tried by ``order="auto"``.
    min_points_per_coeff : float
        Order cap: points per jet coefficient a patch needs (0 disables the cap).
    stn_model : PatchSTN or None
        Network of ``orient="stn"`` (None: the shipped weights).
    optimize_steps : int
        Adam steps of ``orient="optimize"``.
    """

    order: int | str = 4
    orient: str = "pca"
    tol: float | None = None
    max_order: int = 6
    min_points_per_coeff: float = 2.0
    stn_model: Any = None
    optimize_steps: int = 40

    @property
    def auto(self) -> bool:
        """Whether the order is chosen per patch (``order="auto"``)."""
        return isinstance(self.order, str)

    @property
    def top_order(self) -> int:
        """Largest order a patch may get (``max_order`` for ``"auto"``)."""
        return self.max_order if self.auto else int(self.order)

    @property
    def residual_order(self) -> int:
        """Order whose height residual guides the frame refinement (4 for ``"auto"``)."""
        return 4 if self.auto else int(self.order)


def fit_settings(order: int | str, orient: str, tol: float | None, max_order: int,
                 min_points_per_coeff: float, stn_model: Any, optimize_steps: int) -> FitSettings:
    """Validate the options of :meth:`polygeo.patches.PatchSet.fit` into a :class:`FitSettings`.

    Parameters
    ----------
    order, orient, tol, max_order, min_points_per_coeff, stn_model, optimize_steps
        As in :meth:`polygeo.patches.PatchSet.fit`.

    Returns
    -------
    FitSettings

    Raises
    ------
    ValueError
        On an unknown ``orient`` or ``order`` string, an order outside ``[1, 6]``, or a
        negative tolerance or ratio.
    TypeError
        On a non-integer order.
    """
    check_choice(orient, "orient", ORIENT_CHOICES)
    if isinstance(order, str):
        check_choice(order, "order", ("auto",))
        max_order = check_int(max_order, "max_order", low=1, high=jets.MAX_ORDER)
    else:
        order = check_int(order, "order", low=1, high=jets.MAX_ORDER)
    if tol is not None:
        tol = check_positive(tol, "tol")
    ratio = check_positive(min_points_per_coeff, "min_points_per_coeff", strict=False)
    return FitSettings(order=order, orient=orient, tol=tol, max_order=max_order,
                       min_points_per_coeff=ratio, stn_model=stn_model,
                       optimize_steps=optimize_steps)


def partition_for_fit(v: torch.Tensor, f: torch.Tensor | None, n_patches: int | None,
                      seed: int, min_vertices: int) -> Partition:
    """Partition checked vertices (and faces) with :func:`polygeo.partition.partition`.

    Parameters
    ----------
    v : torch.Tensor
        ``(V, 3)`` float64 vertices.
    f : torch.Tensor or None
        ``(F, 3)`` int64 faces; None for a point cloud.
    n_patches : int or None
        Requested patch count (None: the default rule).
    seed : int
        Partition seed.
    min_vertices : int
        Smallest patch (in vertices) the partition may keep.

    Returns
    -------
    polygeo.partition.Partition
    """
    vn = v.cpu().numpy()
    if f is None:
        return partition(vn, None, n_patches, seed=seed, min_vertices=min_vertices)
    return partition(vn, f.cpu().numpy(), n_patches, seed=seed, min_vertices=min_vertices)


def pad_patches(labels: np.ndarray, n_patches: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Padded member lists of the patches of a labelling.

    Parameters
    ----------
    labels : np.ndarray
        ``(V,)`` int64 patch of every vertex, in ``[0, n_patches)``.
    n_patches : int
        K.

    Returns
    -------
    index : torch.Tensor
        ``(K, Pmax)`` int64 vertices of each patch in ascending order, -1 at padding.
    mask : torch.Tensor
        ``(K, Pmax)`` bool, ``index >= 0``.
    """
    counts = np.bincount(labels, minlength=n_patches)
    width = int(counts.max())
    perm = np.argsort(labels, kind="stable")
    starts = np.cumsum(counts) - counts
    pos = np.arange(len(labels)) - starts[labels[perm]]
    index_np = np.full((n_patches, width), -1, dtype=np.int64)
    index_np[labels[perm], pos] = perm
    index = torch.from_numpy(index_np)
    return index, index >= 0


def patch_reference_normals(v: torch.Tensor, f: torch.Tensor | None, normals: torch.Tensor | None,
                            labels: torch.Tensor, n_patches: int) -> torch.Tensor | None:
    """The input's side of every patch: summed input normals, else summed face area vectors.

    Parameters
    ----------
    v : torch.Tensor
        ``(V, 3)`` float64 vertices.
    f : torch.Tensor or None
        ``(F, 3)`` int64 faces (a face counts for the patch of its first corner).
    normals : torch.Tensor or None
        ``(V, 3)`` float64 input normals.
    labels : torch.Tensor
        ``(V,)`` int64 patch of every vertex.
    n_patches : int
        K.

    Returns
    -------
    torch.Tensor or None
        ``(K, 3)`` float64 directions (not normalised); None for a point cloud without
        normals (PCA's sign convention then applies).
    """
    if normals is not None:
        return torch.zeros(n_patches, 3, dtype=torch.float64).index_add_(0, labels, normals)
    if f is not None and len(f):
        pf = v[f]
        cr = torch.linalg.cross(pf[:, 1] - pf[:, 0], pf[:, 2] - pf[:, 0])
        return torch.zeros(n_patches, 3, dtype=torch.float64).index_add_(0, labels[f[:, 0]], cr)
    return None


def refine_rotations(local: torch.Tensor, mask: torch.Tensor, settings: FitSettings,
                     keep_side: bool) -> torch.Tensor | None:
    """Rotation ``Q`` refining each PCA frame, by the STN or by test-time optimisation.

    Parameters
    ----------
    local : torch.Tensor
        ``(K, Pmax, 3)`` canonical points (PCA frame, unit ball).
    mask : torch.Tensor
        ``(K, Pmax)`` bool valid points.
    settings : FitSettings
        ``orient`` (``"pca"``: no refinement), the residual order, the network and the steps.
    keep_side : bool
        Flip refined frames whose normal turned to the other side (the input's side is known).

    Returns
    -------
    torch.Tensor or None
        ``(K, 3, 3)`` rotations (the refined axes in the PCA frame), None for ``"pca"``. The
        STN's rotation is kept only where it lowers the height residual (never worse than PCA).
    """
    from .. import stn

    order = settings.residual_order
    if settings.orient == "stn":
        Q = stn.stn_rotations(local, mask, settings.stn_model)
        with torch.no_grad():
            r_pca, _ = height_residual(local, mask, None, order)
            r_stn, _ = height_residual(local, mask, Q, order)
        eye = torch.eye(3, dtype=Q.dtype).expand_as(Q)
        Q = torch.where((r_stn < r_pca)[:, None, None], Q, eye)
    elif settings.orient == "optimize":
        Q = optimize_rotations(local, mask, order, steps=settings.optimize_steps).rotation
    else:
        return None
    if keep_side:
        flip = Q[:, 2, 2] < 0
        Q = torch.where(flip[:, None, None], Q * torch.tensor([1.0, -1.0, -1.0]), Q)
    return Q


def order_cap(count: torch.Tensor, order: int, ratio: float) -> torch.Tensor:
    """Highest order ``o <= order`` with ``ratio * n_coeffs(o) <= count`` (at least 1).

    Parameters
    ----------
    count : torch.Tensor
        ``(K,)`` int64 points per patch.
    order : int
        Largest order wanted.
    ratio : float
        Points needed per jet coefficient (0: no cap).

    Returns
    -------
    torch.Tensor
        ``(K,)`` int64 cap per patch.
    """
    cap = torch.ones_like(count)
    for o in range(2, order + 1):
        cap = torch.where(ratio * jets.n_coeffs(o) <= count, torch.full_like(cap, o), cap)
    return cap


def fit_capped(uv: torch.Tensor, z: torch.Tensor, mask: torch.Tensor, order: int,
               cap: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Fit every patch at ``min(order, cap)`` (one batched call per distinct order).

    Parameters
    ----------
    uv : torch.Tensor
        ``(K, Pmax, 2)`` canonical parameters.
    z : torch.Tensor
        ``(K, Pmax)`` canonical heights.
    mask : torch.Tensor
        ``(K, Pmax)`` bool valid points.
    order : int
        Requested order.
    cap : torch.Tensor
        ``(K,)`` int64 largest order of every patch (:func:`order_cap`).

    Returns
    -------
    coeffs : torch.Tensor
        ``(K, M)`` float64 coefficients at ``order`` (zeros in the slots above a patch's own
        order).
    residual : torch.Tensor
        ``(K,)`` float64 RMS height residual (canonical units).
    status : torch.Tensor
        ``(K,)`` int64 :class:`polygeo.status.Status`; ``ORDER_REDUCED`` where the cap applied.
    orders : torch.Tensor
        ``(K,)`` int64 fitted order.
    """
    n_patches = uv.shape[0]
    M = jets.n_coeffs(order)
    coeffs = torch.zeros(n_patches, M, dtype=torch.float64)
    residual = torch.zeros(n_patches, dtype=torch.float64)
    status = torch.zeros(n_patches, dtype=torch.int64)
    orders = torch.zeros(n_patches, dtype=torch.int64)
    eff = cap.clamp(max=order)
    for o in torch.unique(eff).tolist():
        sel = (eff == o).nonzero().squeeze(1)
        jf = jets.fit(uv[sel], z[sel], int(o), mask=mask[sel])
        c = jf.coeffs.to(torch.float64)
        coeffs[sel, : c.shape[1]] = c
        residual[sel] = jf.residual.to(torch.float64)
        st = jf.status.to(torch.int64)
        if o < order:
            st = torch.where(st == int(Status.OK), int(Status.ORDER_REDUCED), st)
        status[sel] = st
        orders[sel] = jf.fitted_order.to(torch.int64)
    return coeffs, residual, status, orders


def _auto_choice(res: torch.Tensor, ok: torch.Tensor, n: torch.Tensor, s: torch.Tensor,
                 tol: float | None, max_order: int) -> torch.Tensor:
    """Index (order - 1) chosen per patch: lowest within ``tol``, else by BIC."""
    n_patches = res.shape[0]
    if tol is not None:
        good = ((res * s[:, None]) <= tol) & ok
        first = torch.where(good.any(1), good.to(torch.int8).argmax(1),
                            torch.full((n_patches,), -1))
        # no order meets tol: the highest well-posed order
        best_ok = torch.where(ok, torch.arange(max_order)[None, :], -1).amax(1).clamp_min(0)
        return torch.where(first >= 0, first, best_ok)
    m = torch.tensor([jets.n_coeffs(o) for o in range(1, max_order + 1)], dtype=torch.float64)
    rss = (res**2) * n[:, None]
    nn = n.clamp_min(1)[:, None]
    bic = nn * torch.log(rss.clamp_min(1e-300) / nn) + m[None, :] * torch.log(nn)
    bic = torch.where(ok & (n[:, None] > m[None, :]), bic, torch.full_like(bic, math.inf))
    return torch.where(
        torch.isfinite(bic).any(1), bic.argmin(1), torch.zeros(n_patches, dtype=torch.int64)
    )


def fit_auto(uv: torch.Tensor, z: torch.Tensor, mask: torch.Tensor, s: torch.Tensor,
             tol: float | None, max_order: int, cap: torch.Tensor
             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per patch the lowest order within ``tol`` (input units), or the order of least BIC.

    Parameters
    ----------
    uv, z, mask
        As in :func:`fit_capped`.
    s : torch.Tensor
        ``(K,)`` patch scales (input units per canonical unit), for ``tol``.
    tol : float or None
        Height tolerance in input units; None: the Bayesian information criterion
        ``n log(RSS / n) + M log(n)``.
    max_order : int
        Largest order tried.
    cap : torch.Tensor
        ``(K,)`` int64 largest order of every patch (:func:`order_cap`).

    Returns
    -------
    coeffs, residual, status, orders
        As :func:`fit_capped`, coefficients padded to ``max_order``.
    """
    n_patches = uv.shape[0]
    M = jets.n_coeffs(max_order)
    n = mask.sum(1).to(torch.float64)
    fits = [jets.fit(uv, z, o, mask=mask) for o in range(1, max_order + 1)]
    res = torch.stack([f.residual.to(torch.float64) for f in fits], 1)  # (K, O)
    fitted = torch.stack([f.fitted_order for f in fits], 1)
    ok = fitted == torch.arange(1, max_order + 1)[None, :]  # not reduced
    ok = ok & (torch.arange(1, max_order + 1)[None, :] <= cap[:, None])  # enough points
    ok[:, 0] = True  # order 1 (or its fallback) is always available
    choice = _auto_choice(res, ok, n, s, tol, max_order)
    coeffs = torch.zeros(n_patches, M, dtype=torch.float64)
    residual = torch.zeros(n_patches, dtype=torch.float64)
    status = torch.zeros(n_patches, dtype=torch.int64)
    orders = torch.zeros(n_patches, dtype=torch.int64)
    for o in range(max_order):
        sel = choice == o
        if bool(sel.any()):
            c = fits[o].coeffs.to(torch.float64)[sel]
            coeffs[sel, : c.shape[1]] = c
            residual[sel] = res[sel, o]
            status[sel] = fits[o].status[sel]
            orders[sel] = fits[o].fitted_order[sel]
    status = torch.where(
        (orders < 1) & (status == int(Status.OK)), int(Status.ORDER_REDUCED), status
    )
    return coeffs, residual, status, orders


def uv_domain(uv: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``(K, 4)`` uv bounding box ``(u_min, v_min, u_max, v_max)`` of each patch's points.

    Parameters
    ----------
    uv : torch.Tensor
        ``(K, Pmax, 2)`` canonical parameters.
    mask : torch.Tensor
        ``(K, Pmax)`` bool valid points.

    Returns
    -------
    torch.Tensor
        ``(K, 4)``, same dtype as ``uv``.
    """
    big = torch.finfo(torch.float64).max
    umin = torch.where(mask[..., None], uv, torch.full_like(uv, big)).amin(1)
    umax = torch.where(mask[..., None], uv, torch.full_like(uv, -big)).amax(1)
    return torch.cat([umin, umax], dim=-1)


def fit_partition(part: Partition, v: torch.Tensor, f: torch.Tensor | None,
                  normals: torch.Tensor | None, settings: FitSettings) -> dict[str, Any]:
    """Frame and fit one oriented jet per patch of a partition (the stages, in order).

    Parameters
    ----------
    part : polygeo.partition.Partition
        Partition of the ``V`` vertices.
    v : torch.Tensor
        ``(V, 3)`` float64 checked vertices (input units).
    f : torch.Tensor or None
        ``(F, 3)`` int64 checked faces, None for a point cloud.
    normals : torch.Tensor or None
        ``(V, 3)`` float64 checked input normals.
    settings : FitSettings
        Order, orientation and cap.

    Returns
    -------
    dict
        The fields of :class:`polygeo.patches.PatchSet` (tensors, float64 / int64 / bool).
    """
    labels_np = np.array(part.labels, np.int64)
    labels = torch.from_numpy(labels_np)
    n_patches = int(part.n_patches)
    # 1. padded members
    index, mask = pad_patches(labels_np, n_patches)
    pts = v[index.clamp_min(0)]  # (K, Pmax, 3)
    # 2.-3. the input's side, PCA frames, refinement
    ref = patch_reference_normals(v, f, normals, labels, n_patches)
    can = canonicalize(pts, mask, reference_normal=ref)
    local, ori = can.local, can.orientation
    R = ori.R
    Q = refine_rotations(local, mask, settings, keep_side=ref is not None)
    if Q is not None:
        local = local @ Q
        R = R @ Q
    uv = torch.where(mask[..., None], local[..., :2], torch.zeros_like(local[..., :2]))
    z = local[..., 2]
    s = ori.s
    # 4. capped jet fits
    cap = order_cap(mask.sum(1), settings.top_order, settings.min_points_per_coeff)
    if settings.auto:
        coeffs, residual, status, orders = fit_auto(uv, z, mask, s, settings.tol,
                                                    settings.max_order, cap)
    else:
        coeffs, residual, status, orders = fit_capped(uv, z, mask, settings.order, cap)
    return dict(
        scale=s,
        rotation=R,
        translation=ori.T,
        coeffs=coeffs,
        orders=orders.to(torch.int64),
        uv=uv,
        mask=mask,
        index=index,
        domain=uv_domain(uv, mask),
        residual=residual,
        status=status.to(torch.int64),
        labels=labels,
        vertices=v,
        faces=f,
        normals=normals,
        boundary_pairs=torch.from_numpy(np.array(part.boundary_pairs, np.int64)),
        orient=settings.orient,
        info={},
    )


def search_patch_count(fit_at: Callable[[int], tuple[Any, int, float]], start: int,
                       max_patches: int, target: float, order: int,
                       max_rounds: int = 12) -> tuple[Any, list[dict]]:
    """Grow the patch count until the overall height RMSE meets ``target``.

    The height error of an n-jet scales as ``h^(n+1)`` with the patch size ``h ~ K^(-1/2)``;
    each round grows K by that model (times 1.15, at least by one) up to ``max_patches``.

    Parameters
    ----------
    fit_at : callable
        ``fit_at(n_patches) -> (fitted, patches_obtained, height_rmse)``.
    start : int
        First patch count requested.
    max_patches : int
        Largest patch count requested.
    target : float
        Height RMSE target (input units).
    order : int
        Jet order of the error model.
    max_rounds : int
        Most fits.

    Returns
    -------
    fitted : object
        The last fit.
    search : list of dict
        Per round: ``requested``, ``patches`` and ``height_rmse``.
    """
    n_patches = min(start, max_patches)
    search: list[dict] = []
    best = None
    for _ in range(max_rounds):
        best, obtained, rmse = fit_at(n_patches)
        search.append({"requested": int(n_patches), "patches": obtained, "height_rmse": rmse})
        if rmse <= target or n_patches >= max_patches:
            break
        grow = (rmse / target) ** (2.0 / (order + 1)) * 1.15
        n_patches = int(min(max_patches, max(n_patches + 1, math.ceil(n_patches * grow))))
    return best, search
