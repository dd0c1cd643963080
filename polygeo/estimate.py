"""Per-point differential quantities of a point cloud or a mesh: the one obvious call.

>>> import numpy as np, polygeo
>>> pts = np.random.default_rng(0).normal(size=(2000, 3))
>>> pts /= np.linalg.norm(pts, axis=1, keepdims=True)          # unit sphere
>>> dq = polygeo.differential_quantities(pts, k=20, order=2)
>>> float(np.median(dq.mean_curvature))                        # outward normals: H = -1/r
-1.0...

Pipeline (per point ``p``): neighbourhood (k nearest neighbours including ``p``, a radius
ball, or a mesh k-ring) -> coordinates relative to ``p`` in float64 *before anything else*
(so a cloud shifted by 1e8 loses nothing) -> exact duplicates of a neighbour dropped -> PCA
frame -> height coordinates ``(u, v, z)`` -> n-jet least-squares fit (Cazals & Pouget 2005,
:func:`polygeo.jets.fit`, rank-deficient items fall back to a lower order) -> normal, second
fundamental form, principal curvatures and directions at ``p`` (``(u, v) = 0``, as
:func:`polygeo.diffgeo.from_jet`) -> world frame -> consistent orientation -> curvature signs
follow the final normals.

Sign convention (project-wide, :mod:`polygeo.diffgeo`): curvature is positive where the
surface bends towards the normal; with outward normals a sphere of radius ``r`` has
``k1 = k2 = H = -1/r`` and ``K = 1/r^2``. ``k1 >= k2`` and ``(d1, d2, n)`` is right-handed.

Orientation (``orient="auto"``): input normals if given, else the mesh's faces (re-wound
consistently, outward for closed components), else propagation over the k-NN graph (minimum
spanning tree, seeded outward at the highest point of each component). Points a reference
cannot decide (no normal, unreferenced vertex) get the sign of their propagation component.

Status codes (:class:`polygeo.status.Status`): ``NONFINITE_INPUT`` (the point itself is
NaN/inf: its outputs are NaN and no other point uses it), ``TOO_FEW_POINTS`` (fewer distinct
neighbours than coefficients), ``ORDER_REDUCED`` (degenerate neighbourhood, e.g. a single
scan line or ring: fitted at a lower order), ``DEGENERATE`` (not even a plane could be
fitted: normal from PCA only, curvatures 0), ``ILL_CONDITIONED``. Values of flagged points
are finite fallbacks, never NaN (except ``NONFINITE_INPUT``).

Automatic settings (``k="auto"`` / ``order="auto"`` on a k-NN list without weights,
:mod:`polygeo._estimate_auto`): variances from the fits' residuals, bias from how each quantity
drifts with the neighbourhood size (for H also the attenuation by noise that small
neighbourhoods suffer), sizes capped where the fits of nested neighbourhoods stop agreeing
within ``AUTO_K_GAMMA`` standard deviations (ICI; for the curvatures not where the noise is
large against the neighbourhood, whose attenuation of H the ICI would read as a bias setting
in); every statistic pooled (median) over the
``AUTO_K_SMOOTH`` nearest neighbours, so that the choice depends neither on the chunk a point
is processed in nor on the unit. The curvatures (and ``order``, ``n_neighbors``, ``frame``,
``coeffs``) are those of the fixed ``(k, order)`` chosen for them; the normal is that of the
fixed setting chosen for it (with ``order="auto"`` possibly a plane), the curvatures' signs
and directions following it. Clean data get a 4-jet on small neighbourhoods, noisy data wider
ones and lower orders (figures: README, Performance). With both ``k="auto"`` and
``order="auto"`` the normals are then checked once per cloud against two fixed settings, the
default (``k=20``, order 2) and order 2 at the widest size tried, on held-out points
(:mod:`polygeo._estimate_check`): where one's tangent planes predict them clearly better (the
default on real scans with fine detail, the widest fit under noise comparable to the point
spacing), its normals are returned instead (the curvatures keep theirs, signs following).

Measured choices. ``max_cond`` defaults to ``MAX_COND = {1: 1e3, 2: 1e3, 3: 1e4, 4: 1e5}``:
well-spread 20-neighbourhoods measure about 6-30 at order 2 (up to a few 1e3 at order 4);
points on two scan lines measure 1e4 and more at order 2 and give curvatures that are guesses
across the lines. ``interpolate=True`` removes about a quarter of the curvatures' truncation
bias at order 2 on exact samples (median relative error of H, k = 20, 10k-vertex meshes: torus
1.7e-2 -> 1.3e-2, sphere 1.9e-3 -> 1.4e-3, open cylinder 1.4e-3 -> 1.1e-3); on noisy samples
(already at 0.01 % of the diagonal) it passes the jet through the query point's noise and about
doubles the curvature error, hence not the default. Re-fitting in the Monge frame of a first
fit changes nothing at order 2 (median errors within 3 %), so it is not offered.

Two execution paths compute the same quantities: a compiled one (numba, used when no gradient
is needed) and a torch one (differentiable with respect to the points, used when ``points``
is a tensor requiring grad, or with ``backend="torch"``).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import torch

from . import jets
from ._diffgeo_numba import jet_geometry
from ._estimate_auto import fit_auto
from ._estimate_check import check_normals
from ._estimate_output import extras, non_manifold_status, oriented_outputs
from ._estimate_stages import (
    AUTO_K_CANDIDATES,
    AUTO_K_GAMMA,
    AUTO_K_SMOOTH,
    AUTO_ORDERS,
    MAX_COND,
    Local,
    Neighbourhoods,
    Settings,
    empty_quantities,
    fit_compiled,
    fit_torch,
)
from ._numba_util import finite_rows
from .checks import as_tensor, check_choice, check_faces, check_int, check_positive, check_shape
from .status import Status

__all__ = [
    "DifferentialQuantities",
    "differential_quantities",
    "AUTO_K_CANDIDATES",
    "AUTO_K_GAMMA",
    "AUTO_K_SMOOTH",
    "AUTO_ORDERS",
    "MAX_COND",
    "height_frames",
    "origin_quantities",
]


def height_frames(points, query_index, neighbor_index, neighbor_distance, sizes) -> Local:
    """The frames stage on its own: each neighbourhood in its PCA height frame.

    The compiled pipeline fuses this stage with the fit; it is public for stage timings
    (``benchmarks/bm_jets.py``) and for users who fit jets of their own to the same frames.

    Parameters
    ----------
    points : (N, 3) float64 ndarray
        The cloud (any unit).
    query_index : (Q,) int64 ndarray
        The points whose neighbourhoods are framed.
    neighbor_index, neighbor_distance : (Q, K) int64 / float64 ndarrays
        Their neighbours nearest first (``-1`` / ``inf`` padding), the point itself first.
    sizes : int or (Q,) int64 ndarray
        Neighbours used per query (``<= K``).

    Returns
    -------
    Local
        ``uv (Q, K, 2)``, ``z (Q, K)`` height coordinates in the point's unit, ``valid (Q, K)``,
        frame rotations ``R (Q, 3, 3)`` (columns: two tangents and the normal), ``count (Q,)``
        and ``radius (Q,)``.
    """
    return Local(points, query_index, neighbor_index, neighbor_distance, sizes)


def origin_quantities(coeffs, rotations) -> dict:
    """The quantities stage on its own: geometry of jets at their frames' origins.

    Parameters
    ----------
    coeffs : (Q, M) float64 ndarray
        Jet coefficients in their height frames (``jets`` monomial order, ``M >= 6``
        for curvature; lower orders are padded with zeros).
    rotations : (Q, 3, 3) float64 ndarray
        The frames (as :func:`height_frames` returns them).

    Returns
    -------
    dict
        ``normals, d1, d2 (Q, 3)`` in world axes and ``k1, k2, mean_curvature,
        gaussian_curvature (Q,)`` in inverse units of the points (Monge sign convention).
    """
    return jet_geometry(coeffs, rotations)


@dataclass(frozen=True)
class DifferentialQuantities:
    """Per-point differential quantities (NumPy arrays for NumPy input, else torch tensors).

    Attributes
    ----------
    points : (N, 3)
        The input points (unchanged).
    normals : (N, 3)
        Oriented unit normals.
    k1, k2 : (N,)
        Principal curvatures, ``k1 >= k2`` (1 / length unit), signs following ``normals``.
    d1, d2 : (N, 3)
        Unit principal directions (``d2 = normals x d1``).
    mean_curvature, gaussian_curvature : (N,)
        ``H = (k1 + k2) / 2`` and ``K = k1 k2``.
    status : (N,) int64
        :class:`polygeo.status.Status` codes (0 = reliable).
    order : (N,) int64
        Jet order actually fitted per point (the requested one unless reduced or automatic).
    n_neighbors : (N,) int64
        Distinct points used by the fit (the point itself included: ``k + 1`` normally).
    residual : (N,)
        RMS height residual of the fit (length unit): a local noise estimate.
    frame : (N, 3, 3)
        Local fitting frames (columns ``e1, e2, e3``), world = ``frame @ (u, v, z) + point``,
        with ``e3`` on the side of the final normal.
    coeffs : (N, M)
        Jet coefficients in ``frame`` (:mod:`polygeo.jets` order, ``M`` of the largest
        order fitted; zeros above a point's own order).
    metric, second_form : (N, 2, 2) or None
        First and second fundamental forms of the jet at the point in the ``(u, v)``
        parametrisation of ``frame`` (when ``forms=True``).
    monge : dict or None
        When ``monge=True``: ``origin (N, 3)`` (the jet's point above ``p``), ``b (N, 4)``,
        ``c (N, 5)``: third and fourth order Monge coefficients in the oriented Monge frame
        ``(d1, d2, normals)`` (CGAL convention; zeros below order 3 / 4).
    """

    points: Any
    normals: Any
    k1: Any
    k2: Any
    d1: Any
    d2: Any
    mean_curvature: Any
    gaussian_curvature: Any
    status: Any
    order: Any
    n_neighbors: Any
    residual: Any
    frame: Any
    coeffs: Any
    metric: Any = None
    second_form: Any = None
    monge: Any = None

    def __len__(self) -> int:
        return int(self.status.shape[0])

    def summary(self) -> dict[str, Any]:
        """Counts per status and ranges of the curvatures of OK points (plain Python)."""
        st = np.asarray(_np(self.status))
        out: dict[str, Any] = {"n_points": int(st.size)}
        out["status"] = {Status(int(c)).name: int((st == c).sum()) for c in np.unique(st)}
        ok = st == 0
        for name in ("k1", "k2", "mean_curvature", "gaussian_curvature"):
            v = np.asarray(_np(getattr(self, name)))[ok]
            out[name] = (
                (float(np.min(v)), float(np.median(v)), float(np.max(v))) if v.size else None
            )
        return out


def _np(x: Any) -> Any:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else x



def differential_quantities(
    points: Any,
    faces: Any = None,
    normals: Any = None,
    *,
    k: int | str = 20,
    radius: float | None = None,
    rings: int | None = None,
    order: int | str = 2,
    weights: str | None = None,
    orient: str = "auto",
    monge: bool = False,
    forms: bool = False,
    batch_size: int = 131072,
    progress: bool | None = None,
    workers: int = -1,
    backend: str = "auto",
    k_candidates: tuple[int, ...] = AUTO_K_CANDIDATES,
    auto_orders: tuple[int, ...] = AUTO_ORDERS,
    alpha: float = 0.01,
    max_cond: float | None = None,
    interpolate: bool = False,
    normal_check: bool = True,
) -> DifferentialQuantities:
    """Per-point normals, principal curvatures and directions, H and K by n-jet fitting.

    Parameters
    ----------
    points : (N, 3) float array or tensor
        Points or mesh vertices (length unit L). Non-finite points are allowed: they get
        status ``NONFINITE_INPUT`` and NaN outputs and are nobody's neighbour.
    faces : (F, 3) int, optional
        Triangles when ``points`` are mesh vertices: orient the normals (module docstring)
        and, with ``rings``, give the neighbourhoods.
    normals : (N, 3) float, optional
        Input normals: only their signs are used, to orient the estimates.
    k : int or "auto"
        Nearest neighbours besides the point itself (each fit uses ``k + 1`` points, as CGAL's
        ``jet_estimate_normals``); clipped to the finite points; at least ``n_coeffs(order) -
        1`` (5 for order 2).
        ``"auto"``: per point, the order of ``auto_orders`` and the size of ``k_candidates``
        of least estimated error, apart for the normal and the curvatures (module docstring,
        "Automatic settings"; with weights, a radius or rings: ICI on sizes, F-test on orders).
    radius : float, optional
        Use all neighbours within this distance (L) instead of k nearest (``k`` then caps
        the count at ``k + 1`` points, nearest kept, unless ``k="auto"``).
    rings : int, optional
        With ``faces``: use the mesh ``rings``-ring of each vertex as its neighbourhood.
    order : int or "auto"
        Jet order 1..4 (1: plane; 2: osculating quadric; 3, 4: more accurate on clean data,
        more sensitive to noise). ``"auto"``: see ``k`` (order 1 only as the sole candidate;
        with weights, a radius or rings the F-test at ``alpha``).
    weights : {None, "gaussian"}
        Uniform least squares (CGAL) or Gaussian weights ``exp(-d^2 / rms^2)`` of distance.
    orient : {"auto", "input", "mesh", "propagate", "none"}
        Source of the normals' signs (see the module docstring); "none" keeps the fit's sign.
    monge, forms : bool
        Also return the Monge coefficients (``monge``), the fundamental forms (``metric``,
        ``second_form``).
    batch_size : int
        Points per chunk (bounds memory: about ``batch_size * k * 60`` bytes).
    progress : bool or None
        Show a progress bar; None: for inputs of at least 200 000 points.
    workers : int
        Threads for the k-d tree (``-1``: all cores; the kernels use numba's threads).
    backend : {"auto", "numba", "torch"}
        "torch" is differentiable w.r.t. ``points``; "auto" picks it when ``points`` is a
        tensor requiring grad.
    k_candidates, auto_orders, alpha : tuple of int, tuple of int, float
        Sizes tried by ``k="auto"``, orders by ``order="auto"``; the order F-test's level.
    max_cond : float, optional
        Largest accepted condition number of a neighbourhood's preconditioned, equilibrated
        least-squares system (:func:`polygeo.jets.fit`); default per order ``MAX_COND``
        (module docstring, "Measured choices"); above it a lower order, ``ORDER_REDUCED``.
    interpolate : bool
        Pass each jet through its query point (Cazals & Pouget's interpolation variant):
        for exact samples (analytic, CAD, subdivision surfaces); on noisy ones it about
        doubles the curvature error (module docstring, "Measured choices").
    normal_check : bool
        With ``k="auto", order="auto"``: check the normals once per cloud against the
        default's and the widest order-2 fit's on held-out points (module docstring; ~2x
        the time). Tiled runs: False.

    Returns
    -------
    DifferentialQuantities
        NumPy arrays when ``points`` is NumPy, else torch tensors of the points' dtype.

    Raises
    ------
    ValueError
        Bad shapes, ``k < n_coeffs(order)``, ``order`` outside 1..4, unknown options, a
        reference source that is missing (``orient="input"`` without normals, ...).
    TypeError
        Non-numeric input, non-integer faces.
    """
    # validate: points as a tensor, the options as one settings record
    pts_t, numpy_in = _as_points(points)
    s = _settings(k=k, radius=radius, rings=rings, order=order, weights=weights, orient=orient,
                  monge=monge, forms=forms, batch_size=batch_size, progress=progress,
                  workers=workers, backend=backend, k_candidates=k_candidates,
                  auto_orders=auto_orders, alpha=alpha, max_cond=max_cond, interpolate=interpolate,
                  requires_grad=pts_t.requires_grad, normal_check=normal_check)
    # inputs: float64 points (non-finite ones marked), faces and reference normals checked
    P, finite, faces_np, reference = _inputs(pts_t, faces, normals, settings=s)
    # neighbours: k-d tree, radius ball or mesh rings, nearest first, duplicates merged
    hoods = Neighbourhoods(P, finite, faces=faces_np, settings=s, graph=s.orient != "none")
    # frames -> fit -> quantities, chunk by chunk: compiled (fused where it can) or torch
    out = empty_quantities(P.shape[0], s.n_coeffs)
    parts = _fit_points(pts_t, hoods, out, s)
    # oriented outputs, optional fields, the non-manifold check
    dq = _outputs(out, parts, hoods, P, faces_np, reference, s, pts_t.dtype)
    result = DifferentialQuantities(points=pts_t, **dq)
    return _to_numpy(result, points) if numpy_in else result


def _outputs(out: Any, parts: list | None, hoods: Neighbourhoods, P: np.ndarray,
             faces_np: np.ndarray | None, reference: Any, s: Settings, dtype) -> dict:
    """The fields of :class:`DifferentialQuantities` from the fits in ``out``.

    Orientation (one sign per point from the input normals, the faces or propagation), the
    optional fundamental forms and Monge coefficients, and on a mesh the status of the points
    whose neighbourhood crosses a non-manifold edge (a fin).
    """
    orient_args = dict(P=P, graph=hoods.graph, reference=reference, faces=faces_np,
                       orient=s.orient, workers=s.workers)
    dq = oriented_outputs(out, parts, settings=s, orient_args=orient_args, dtype=dtype)
    dq.update(extras(dq, P, forms=s.forms, monge=s.monge, dtype=dtype))
    if faces_np is not None:
        dq["status"] = torch.from_numpy(
            non_manifold_status(P, faces_np, out, radius=s.radius, rings=s.rings))
    return dq


def _fit_points(pts_t: torch.Tensor, hoods: Neighbourhoods, out: Any, s: Settings
                ) -> list | None:
    """Fit every point into ``out`` (:func:`empty_quantities`).

    Returns the torch path's differentiable results (None on the compiled paths).
    """
    if _auto_compiled(s):  # automatic order / size on one k-NN list: two passes
        fit_auto(hoods, out, settings=s)
        if s.k == "auto" and s.order == "auto" and s.normal_check:  # default, widest
            check_normals(hoods.P, hoods.finite, out, s)
        return None
    parts = [] if s.use_torch else None
    for q in hoods.chunks(s.batch_size, s.progress):
        nbr, dist = hoods.query(q)
        if s.use_torch:
            parts.append(fit_torch(pts_t, hoods, q, nbr, dist, out, settings=s))
        else:
            fit_compiled(hoods, q, nbr, dist, out, settings=s)
    return parts


def _auto_compiled(s: Settings) -> bool:
    """Whether the automatic order/size rule of :mod:`polygeo._estimate_auto` applies."""
    auto = s.k == "auto" or (s.order == "auto" and len(s.auto_orders) > 1)
    return (auto and not s.use_torch and s.weights is None and s.radius is None
            and s.rings is None)


def _as_points(points: Any) -> tuple[torch.Tensor, bool]:
    numpy_in = not isinstance(points, torch.Tensor)
    t = as_tensor(points, "points")
    check_shape(t, "points", ("N", 3))
    return t, numpy_in


def _settings(*, k, radius, rings, order, weights, orient, monge, forms, batch_size, progress,
              workers, backend, k_candidates, auto_orders, alpha, max_cond, interpolate,
              requires_grad, normal_check=True) -> Settings:
    """The arguments of :func:`differential_quantities` checked (see its Raises)."""
    check_choice(orient, "orient", ("auto", "input", "mesh", "propagate", "none"))
    check_choice(weights, "weights", (None, "gaussian"))
    check_choice(backend, "backend", ("auto", "numba", "torch"))
    if not isinstance(interpolate, (bool, np.bool_)):
        raise TypeError(f"interpolate: expected a bool, got {interpolate!r}")
    if not isinstance(normal_check, (bool, np.bool_)):
        raise TypeError(f"normal_check: expected a bool, got {normal_check!r}")
    if isinstance(order, str):
        check_choice(order, "order", ("auto",))
        orders = tuple(check_int(o, "auto_orders", low=1, high=4) for o in auto_orders)
        if not orders:
            raise ValueError("auto_orders: expected at least one order")
        auto_orders = tuple(sorted(set(orders)))
        orders = auto_orders
    else:
        order = check_int(order, "order", low=1, high=4)
        orders = (order,)
    m_min = jets.n_coeffs(min(orders))
    if isinstance(k, str):
        check_choice(k, "k", ("auto",))
        # sizes: points per neighbourhood, the point itself included (k + 1)
        sizes = sorted({check_int(c, "k_candidates", low=m_min - 1) + 1 for c in k_candidates})
        if not sizes:
            raise ValueError("k_candidates: expected at least one size")
    else:
        k = check_int(k, "k", low=1)
        if k + 1 < m_min:
            raise ValueError(
                f"k: an order-{min(orders)} jet has {m_min} coefficients, so k must be at least "
                f"{m_min - 1} (k neighbours plus the point itself), got {k}"
            )
        sizes = [k + 1]
    if radius is not None:
        radius = check_positive(radius, "radius")
    batch_size = check_int(batch_size, "batch_size", low=1)
    if max_cond is not None:
        max_cond = check_positive(max_cond, "max_cond")
    alpha = float(alpha)
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha: expected a value in (0, 1), got {alpha}")
    needs_grad = torch.is_grad_enabled() and requires_grad
    use_torch = backend == "torch" or (backend == "auto" and needs_grad)
    if use_torch and (k == "auto" or order == "auto"):
        raise ValueError("backend: the differentiable path supports fixed k and order only")
    if rings is not None:
        rings = check_int(rings, "rings", low=1)
    return Settings(
        k=k, sizes=tuple(sizes), radius=radius, rings=rings, order=order,
        auto_orders=tuple(auto_orders), weights=weights,
        max_cond={o: max_cond or MAX_COND[o] for o in orders}, interpolate=bool(interpolate),
        alpha=alpha, orient=orient, batch_size=batch_size, progress=progress, workers=workers,
        use_torch=use_torch, monge=monge, forms=forms, normal_check=bool(normal_check),
    )


def _inputs(pts_t: torch.Tensor, faces: Any, normals: Any, *, settings: Settings):
    """``(P (N, 3) float64, finite (N,) bool, faces (F, 3) int64 or None, normals or None)``."""
    n = pts_t.shape[0]
    P = np.ascontiguousarray(pts_t.detach().cpu().to(torch.float64).numpy())
    finite = finite_rows(P)
    f_np = check_faces(faces, n).cpu().numpy() if faces is not None else None
    ref = None
    if normals is not None:
        nt = as_tensor(normals, "normals")
        check_shape(nt, "normals", (n, 3))
        ref = nt.detach().cpu().to(torch.float64).numpy()
    if settings.orient == "input" and ref is None:
        raise ValueError("orient: 'input' needs normals")
    if settings.orient == "mesh" and f_np is None:
        raise ValueError("orient: 'mesh' needs faces")
    if settings.rings is not None and f_np is None:
        raise ValueError("rings: mesh rings need faces")
    return P, finite, f_np, ref


def _to_numpy(result: DifferentialQuantities, points: Any) -> DifferentialQuantities:
    """The same result with NumPy arrays (``points`` as given)."""
    conv = {}
    for fld in fields(result):
        v = getattr(result, fld.name)
        if isinstance(v, torch.Tensor):
            conv[fld.name] = v.detach().cpu().numpy()
        elif isinstance(v, dict):
            conv[fld.name] = {a: b.detach().cpu().numpy() for a, b in v.items()}
    conv["points"] = points if isinstance(points, np.ndarray) else np.asarray(points)
    return DifferentialQuantities(**{**{f.name: getattr(result, f.name) for f in fields(result)},
                                     **conv})
