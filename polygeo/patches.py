r"""PolyFit: a surface as K oriented n-jet patches (thesis §5.2).

Every patch ``k`` is an orientation ``O_k = (s_k, R_k, T_k)`` and the coefficients ``a_k`` of
an n-jet height ``z_k(u, v)`` over a canonical uv plane:

.. math::

    p = s_k R_k \, (u, v, z_k(u, v))^T + T_k .

:meth:`PatchSet.fit` partitions the input (:mod:`polygeo.partition`), frames every patch
(PCA, optionally refined by the rigid STN or by test-time optimisation, :mod:`polygeo.stn`)
and fits all jets in one batched least-squares call (:func:`polygeo.jets.fit`, patches
padded with a mask). A :class:`PatchSet` then evaluates positions, normals, Jacobians,
metric tensors and curvatures at any ``(patch, uv)`` (differentiably, through
:func:`evaluate_patches` / :func:`patch_geometry`), resamples the whole surface as a mesh at
any resolution (watertight across patch boundaries where the input mesh was), reports
per-patch quality (:meth:`PatchSet.metrics`) and round-trips through NPZ.

Units and conventions
---------------------
* ``uv`` and heights are canonical (dimensionless): the patch's points lie in the unit ball
  around its centroid before the jet fit, so ``s_k`` is the patch radius in input units.
  Height RMSE, boundary gaps and the Chamfer distance are reported in input units (or as
  documented); normal errors in degrees.
* Jet coefficients are stored at the largest order of the set, ``(K, M)``; a patch of a
  lower order (``order="auto"`` or a reduced fit) has zeros in its higher slots (the monomial
  order of :mod:`polygeo.jets` is graded, so a lower-order jet is a prefix).
* Normals follow the input's orientation where it is known (mesh winding or given normals):
  each patch's frame is flipped so that its normal agrees with the mean input normal.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from . import jets
from .checks import (
    as_tensor,
    check_choice,
    check_faces,
    check_finite,
    check_int,
    check_positive,
    check_shape,
    is_numpy_like,
)
from .diffgeo import SurfaceGeometry, from_derivatives
from .frames import Orientation
from .partition import Partition, partition
from .status import Status

__all__ = [
    "PatchSet",
    "PatchMetrics",
    "PatchGeometry",
    "evaluate_patches",
    "patch_geometry",
    "subdivide_barycentric",
    "chamfer_distance",
    "chamfer_report",
    "ChamferReport",
    "ORIENT_CHOICES",
]

#: Canonicalisation methods of :meth:`PatchSet.fit`.
ORIENT_CHOICES = ("pca", "stn", "optimize")
_NPZ_VERSION = 1


# --------------------------------------------------------------------------------------------
# Pure, differentiable evaluation
# --------------------------------------------------------------------------------------------


def _gather_eval_inputs(coeffs, scale, rotation, translation, patch_idx, uv):
    c = as_tensor(coeffs, "coeffs")
    check_shape(c, "coeffs", ("K", "M"))
    k = c.shape[0]
    s = as_tensor(scale, "scale")
    check_shape(s, "scale", (k,))
    R = as_tensor(rotation, "rotation")
    check_shape(R, "rotation", (k, 3, 3))
    T = as_tensor(translation, "translation")
    check_shape(T, "translation", (k, 3))
    idx = as_tensor(patch_idx, "patch_idx", floating=False)
    if idx.is_floating_point() or idx.dtype == torch.bool:
        raise TypeError(f"patch_idx: expected an integer array, got dtype {idx.dtype}")
    check_shape(idx, "patch_idx", ("N",))
    idx = idx.to(torch.int64)
    if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= k):
        raise ValueError(
            f"patch_idx: expected indices in [0, {k - 1}], got values in "
            f"[{int(idx.min())}, {int(idx.max())}]"
        )
    t = as_tensor(uv, "uv")
    check_shape(t, "uv", (idx.shape[0], 2))
    dtype = c.dtype
    for x in (s, R, T, t):
        dtype = torch.promote_types(dtype, x.dtype)
    return c.to(dtype), s.to(dtype), R.to(dtype), T.to(dtype), idx, t.to(dtype)


def evaluate_patches(coeffs, scale, rotation, translation, patch_idx, uv) -> torch.Tensor:
    """World positions ``s R (u, v, z(u, v)) + T`` of points on oriented jet patches.

    Parameters
    ----------
    coeffs : array_like or torch.Tensor
        ``(K, M)`` jet coefficients (canonical units).
    scale : array_like or torch.Tensor
        ``(K,)`` patch scales ``s`` (input length units).
    rotation : array_like or torch.Tensor
        ``(K, 3, 3)`` patch rotations ``R`` (columns: u axis, v axis, height axis).
    translation : array_like or torch.Tensor
        ``(K, 3)`` patch origins ``T``.
    patch_idx : array_like or torch.Tensor
        ``(N,)`` integer patch of every query.
    uv : array_like or torch.Tensor
        ``(N, 2)`` canonical parameters of every query.

    Returns
    -------
    torch.Tensor
        ``(N, 3)`` positions in the promoted dtype; differentiable w.r.t. every float input.

    Raises
    ------
    ValueError
        On inconsistent shapes or out-of-range patch indices.
    TypeError
        On non-numeric input or a non-integer ``patch_idx``.
    """
    c, s, R, T, idx, t = _gather_eval_inputs(coeffs, scale, rotation, translation, patch_idx, uv)
    z = jets.evaluate(c[idx], t[:, None, :])[:, 0]  # (N,)
    local = torch.cat([t, z[:, None]], dim=-1)  # (N, 3)
    return s[idx, None] * (R[idx] @ local[..., None])[..., 0] + T[idx]


class PatchGeometry(NamedTuple):
    """Positions and differential geometry of points on patches (world coordinates).

    Attributes
    ----------
    positions : torch.Tensor
        ``(N, 3)``.
    geometry : polygeo.diffgeo.SurfaceGeometry
        Jacobian ``(N, 3, 2)`` (columns ``x_u, x_v``), metric ``(N, 2, 2)``, second form,
        unit normal ``(N, 3)``, shape operator, principal curvatures ``k1 >= k2`` and
        directions, mean and Gaussian curvature (1 / input length units), validity mask.
        Derivatives are w.r.t. the canonical ``uv``.
    """

    positions: torch.Tensor
    geometry: SurfaceGeometry


def patch_geometry(coeffs, scale, rotation, translation, patch_idx, uv) -> PatchGeometry:
    """Positions, normals, Jacobians, metrics and curvatures on oriented jet patches.

    Parameters
    ----------
    coeffs, scale, rotation, translation, patch_idx, uv
        As in :func:`evaluate_patches`.

    Returns
    -------
    PatchGeometry
        Differentiable w.r.t. every float input (curvatures away from umbilics).

    Raises
    ------
    ValueError, TypeError
        As :func:`evaluate_patches`.
    """
    c, s, R, T, idx, t = _gather_eval_inputs(coeffs, scale, rotation, translation, patch_idx, uv)
    d = jets.derivatives(c[idx], t[:, None, :], max_order=2)
    d = {k: v[:, 0] for k, v in d.items()}
    zero, one = torch.zeros_like(d[(0, 0)]), torch.ones_like(d[(0, 0)])
    Ri, si = R[idx], s[idx, None]

    def world(a, b, cc):  # s R (a, b, c)
        return si * (Ri @ torch.stack([a, b, cc], dim=-1)[..., None])[..., 0]

    pos = world(t[:, 0], t[:, 1], d[(0, 0)]) + T[idx]
    geom = from_derivatives(
        world(one, zero, d[(1, 0)]),
        world(zero, one, d[(0, 1)]),
        world(zero, zero, d[(2, 0)]),
        world(zero, zero, d[(1, 1)]),
        world(zero, zero, d[(0, 2)]),
    )
    return PatchGeometry(pos, geom)


# --------------------------------------------------------------------------------------------
# Subdivision (resolution-agnostic resampling) and Chamfer distance
# --------------------------------------------------------------------------------------------


def _edge_keys(a: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    return np.minimum(a, b).astype(np.int64) * n + np.maximum(a, b)


def subdivide_barycentric(
    faces: Any, n_vertices: int, level: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Regular 1-to-4^level subdivision of a triangulation, as barycentric combinations.

    Each triangle is split into ``(2^level)^2`` triangles on a barycentric lattice; lattice
    points on an edge are shared by the triangles of that edge and the original vertices
    come first (``0..V-1``), so a surface evaluated through this table is as watertight as
    the input triangulation.

    Parameters
    ----------
    faces : array_like, shape (F, 3), integer
        Triangles of the input.
    n_vertices : int
        V, number of input vertices.
    level : int
        Subdivision level ``>= 0`` (0 returns the input).

    Returns
    -------
    corners : np.ndarray, shape (V_out, 3), int64
        Input vertices whose combination gives each output vertex (for an original vertex:
        itself three times).
    weights : np.ndarray, shape (V_out, 3), float64
        Barycentric weights (rows sum to 1).
    out_faces : np.ndarray, shape (F * 4^level, 3), int64
        Triangles of the subdivided mesh, with the input's winding.

    Raises
    ------
    ValueError
        On bad shapes, out-of-range indices or a negative level.
    TypeError
        If ``faces`` is not an integer array.
    """
    level = check_int(level, "level", low=0, high=8)
    n_vertices = check_int(n_vertices, "n_vertices", low=0)
    f = _faces_np(faces, n_vertices)
    nseg = 2**level
    V, F = n_vertices, len(f)
    # lattice points (i, j): weights (1 - (i + j)/N, i/N, j/N) on the corners (a, b, c)
    ii, jj = np.meshgrid(np.arange(nseg + 1), np.arange(nseg + 1), indexing="ij")
    keep = ii + jj <= nseg
    ii, jj = ii[keep], jj[keep]
    kk = nseg - ii - jj
    L = len(ii)
    lid = -np.ones((nseg + 1, nseg + 1), np.int64)
    lid[ii, jj] = np.arange(L)
    # local triangles of the lattice
    tri = []
    for i in range(nseg):
        for j in range(nseg - i):
            tri.append((lid[i, j], lid[i + 1, j], lid[i, j + 1]))
            if j < nseg - i - 1:
                tri.append((lid[i + 1, j], lid[i + 1, j + 1], lid[i, j + 1]))
    tri = np.asarray(tri, np.int64).reshape(-1, 3)
    # classify lattice points
    nz = (kk > 0).astype(int) + (ii > 0) + (jj > 0)
    is_corner = nz == 1
    is_edge = nz == 2
    is_inner = nz == 3
    n_inner = int(is_inner.sum())
    inner_rank = np.cumsum(is_inner) - 1
    # edges of the mesh
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    ekey = np.unique(_edge_keys(e[:, 0], e[:, 1], max(V, 1))) if F else np.zeros(0, np.int64)
    E = len(ekey)
    gid = np.empty((F, L), np.int64)
    corners = np.empty((F, L, 3), np.int64)
    weights = np.empty((F, L, 3))
    corners[:] = f[:, None, :]
    weights[:] = np.stack([kk, ii, jj], axis=1)[None] / nseg
    # corner points -> the original vertex
    cidx = np.flatnonzero(is_corner)
    which = np.argmax(np.stack([kk, ii, jj], 1)[cidx], axis=1)  # 0: a, 1: b, 2: c
    gid[:, cidx] = f[:, which]
    # edge points -> shared id from (edge, position measured from the lower vertex)
    eidx = np.flatnonzero(is_edge)
    if len(eidx) and F:
        wts = np.stack([kk, ii, jj], 1)[eidx]  # (Le, 3) integer weights
        zero_slot = np.argmin(wts, axis=1)
        s1 = (zero_slot + 1) % 3
        s2 = (zero_slot + 2) % 3
        p = f[:, s1]  # (F, Le)
        q = f[:, s2]
        wp = wts[np.arange(len(eidx)), s1]  # (Le,)
        wq = wts[np.arange(len(eidx)), s2]
        key = _edge_keys(p, q, max(V, 1))
        epos = np.searchsorted(ekey, key)
        w_hi = np.where(p > q, wp[None, :], wq[None, :])  # weight of the higher vertex id
        gid[:, eidx] = V + epos * (nseg - 1) + (w_hi - 1)
    if n_inner:
        iidx = np.flatnonzero(is_inner)
        gid[:, iidx] = V + E * (nseg - 1) + np.arange(F)[:, None] * n_inner + inner_rank[iidx]
    n_out = V + E * max(nseg - 1, 0) + F * n_inner
    out_corners = np.repeat(np.arange(V)[:, None], 3, axis=1)
    out_weights = np.tile(np.array([1.0, 0.0, 0.0]), (V, 1))
    all_c = np.empty((n_out, 3), np.int64)
    all_w = np.empty((n_out, 3))
    all_c[:V], all_w[:V] = out_corners, out_weights
    flat_g = gid.ravel()
    flat_c = corners.reshape(-1, 3)
    flat_w = weights.reshape(-1, 3)
    new = flat_g >= V
    all_c[flat_g[new]] = flat_c[new]
    all_w[flat_g[new]] = flat_w[new]
    out_faces = gid[:, tri].reshape(-1, 3) if F else np.zeros((0, 3), np.int64)
    return all_c, all_w, out_faces


def _faces_np(faces: Any, n_vertices: int) -> np.ndarray:
    return check_faces(faces, n_vertices).cpu().numpy()


def _sample_surface(v: np.ndarray, f: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` points uniformly distributed (by area) on a triangle mesh."""
    p = v[f]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    if not area.sum() > 0:
        raise ValueError("faces: the mesh has zero area; cannot sample its surface")
    tri = rng.choice(len(f), size=n, p=area / area.sum())
    r1, r2 = rng.uniform(size=(2, n))
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    return np.einsum("ni,nij->nj", w, p[tri])


def _closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """Squared distance from points ``p`` (n, 3) to triangles ``(a, b, c)`` (n, 3) each.

    Region-based closest point on a triangle (vertex, edge and face regions), vectorised.
    """
    ab, ac, ap = b - a, c - a, p - a
    d1 = np.einsum("ij,ij->i", ab, ap)
    d2 = np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3 = np.einsum("ij,ij->i", ab, bp)
    d4 = np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5 = np.einsum("ij,ij->i", ab, cp)
    d6 = np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v = np.where(denom != 0, vb / denom, 0.0)
        w = np.where(denom != 0, vc / denom, 0.0)
        q = a + ab * v[:, None] + ac * w[:, None]  # face region
        # edge regions
        t_ab = np.where(d1 - d3 != 0, d1 / (d1 - d3), 0.0)
        t_ac = np.where(d2 - d6 != 0, d2 / (d2 - d6), 0.0)
        t_bc = np.where((d4 - d3) + (d5 - d6) != 0, (d4 - d3) / ((d4 - d3) + (d5 - d6)), 0.0)
    e_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    e_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    e_bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
    q = np.where(e_bc[:, None], b + (c - b) * t_bc[:, None], q)
    q = np.where(e_ac[:, None], a + ac * t_ac[:, None], q)
    q = np.where(e_ab[:, None], a + ab * t_ab[:, None], q)
    # vertex regions
    q = np.where(((d6 >= 0) & (d5 <= d6))[:, None], c, q)
    q = np.where(((d3 >= 0) & (d4 <= d3))[:, None], b, q)
    q = np.where(((d1 <= 0) & (d2 <= 0))[:, None], a, q)
    return np.sum((p - q) ** 2, axis=1)


def _point_to_mesh_sq(p: np.ndarray, v: np.ndarray, f: np.ndarray, k: int = 8) -> np.ndarray:
    """Squared distance from points to a triangle mesh.

    Searches the faces around the ``k`` nearest vertices: exact for the faces searched, an
    upper bound otherwise (exact on meshes whose nearest face touches a nearby vertex).
    """
    from scipy.spatial import cKDTree

    k = min(k, len(v))
    _, nn = cKDTree(v).query(p, k=k)
    nn = np.asarray(nn).reshape(len(p), k)
    # vertex -> incident faces (CSR)
    order = np.argsort(f.ravel(), kind="stable")
    face_of = order // 3
    counts = np.bincount(f.ravel(), minlength=len(v))
    start = np.concatenate([[0], np.cumsum(counts)])
    best = np.full(len(p), np.inf)
    for j in range(k):
        vid = nn[:, j]
        cnt = counts[vid]
        rows = np.repeat(np.arange(len(p)), cnt)
        offs = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        fid = face_of[start[vid][rows] + offs]
        tri = f[fid]
        d = _closest_on_triangles(p[rows], v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]])
        np.minimum.at(best, rows, d)
    no_face = ~np.isfinite(best)
    if no_face.any():  # points whose nearest vertices have no face: vertex distance
        best[no_face] = np.sum((p[no_face] - v[nn[no_face, 0]]) ** 2, axis=1)
    return best


def chamfer_distance(
    vertices_a: Any,
    faces_a: Any,
    vertices_b: Any,
    faces_b: Any,
    *,
    n_samples: int = 10000,
    normalize: str = "unit_sphere",
    mode: str = "points",
    seed: int = 0,
    n_samples_b: int | None = None,
) -> float:
    """Symmetric Chamfer distance between two triangle meshes, as in the thesis' Table 5.1.

    ``n_samples`` points are drawn uniformly (by area) on the reference surface ``a`` and
    ``n_samples_b`` (default: as many) on the compared surface ``b``; the distance is
    ``mean_a d(a, B)^2 + mean_b d(b, A)^2`` (squared distances, the AtlasNet protocol).
    Both surfaces are first normalised with one similarity computed from mesh ``a``:
    ``"unit_sphere"`` centres ``a``'s samples at their mean and scales them into the unit
    ball (largest distance 1), ``"none"`` keeps input units.

    ``mode="points"`` measures ``d`` to the other surface's *samples* (the point protocol of
    Table 5.1). That estimate has a sampling floor even for ``b == a``: a point's squared
    distance to the nearest of ``n`` uniform samples of a surface of (normalised) area ``A``
    averages about ``A / (pi n)``, so two independent samplings of one surface give about
    ``A / (pi n_samples) + A / (pi n_samples_b)``. AtlasNet compares all the points its
    charts produce against the ground-truth samples; with ``b`` a reconstruction, a large
    ``n_samples_b`` (the reconstruction densely sampled) plays that role and removes the
    first half of the floor; the second half, from the ``n_samples`` reference points,
    remains. Measure the floor of a setting with ``b = a`` and another ``seed``.
    ``mode="surface"`` measures ``d`` to the other *surface* (exact point-to-triangle
    distances to the faces around the 8 nearest vertices), an estimate of the continuous
    Chamfer distance without a sampling floor: the measure of the reconstruction itself.

    Parameters
    ----------
    vertices_a, faces_a : array_like
        Reference mesh ``(Va, 3)`` float and ``(Fa, 3)`` integer.
    vertices_b, faces_b : array_like
        Compared mesh.
    n_samples : int
        Samples on ``a`` (Table 5.1: 10 000).
    n_samples_b : int, optional
        Samples on ``b`` (default ``n_samples``).
    normalize : {"unit_sphere", "none"}
        Normalisation.
    mode : {"points", "surface"}
        Distance to the other samples or to the other surface.
    seed : int
        Sampling seed.

    Returns
    -------
    float
        The Chamfer distance (normalised units squared); multiply by 1e3 for Table 5.1's unit.

    Raises
    ------
    ValueError
        On bad shapes, a zero-area mesh or a bad option.
    TypeError
        On non-integer faces.
    """
    from scipy.spatial import cKDTree

    check_choice(normalize, "normalize", ("unit_sphere", "none"))
    check_choice(mode, "mode", ("points", "surface"))
    n = check_int(n_samples, "n_samples", low=1)
    nb = n if n_samples_b is None else check_int(n_samples_b, "n_samples_b", low=1)
    va = as_tensor(vertices_a, "vertices_a")
    vb = as_tensor(vertices_b, "vertices_b")
    check_shape(va, "vertices_a", ("V", 3))
    check_shape(vb, "vertices_b", ("V", 3))
    va = va.detach().cpu().numpy().astype(np.float64)
    vb = vb.detach().cpu().numpy().astype(np.float64)
    fa = _faces_np(faces_a, len(va))
    fb = _faces_np(faces_b, len(vb))
    rng = np.random.default_rng(seed)
    pa = _sample_surface(va, fa, n, rng)
    pb = _sample_surface(vb, fb, nb, rng)
    c, r = np.zeros(3), 1.0
    if normalize == "unit_sphere":
        c = pa.mean(0)
        r = float(np.linalg.norm(pa - c, axis=1).max()) or 1.0
    pa, pb, va, vb = ((x - c) / r for x in (pa, pb, va, vb))
    if mode == "points":
        da = cKDTree(pb).query(pa, k=1)[0] ** 2
        db = cKDTree(pa).query(pb, k=1)[0] ** 2
    else:
        da = _point_to_mesh_sq(pa, vb, fb)
        db = _point_to_mesh_sq(pb, va, fa)
    return float(np.mean(da) + np.mean(db))


class ChamferReport(NamedTuple):
    """Chamfer distances of a reconstruction against its input (:func:`chamfer_report`).

    All values are squared distances after the unit-sphere normalisation of the input (multiply
    by 1e3 for Table 5.1's unit).

    Attributes
    ----------
    points : float
        Table 5.1 point protocol: ``n_samples`` samples on each surface.
    points_floor : float
        That protocol's sampling floor for this input: the input against an independent
        sampling of itself (same counts, another seed).
    dense : float
        AtlasNet-style point protocol: ``n_samples`` input samples against ``n_dense`` samples
        of the reconstruction (all the points its charts produce, densely).
    dense_floor : float
        Its sampling floor (the input against ``n_dense`` samples of itself).
    surface : float
        Point-to-surface (continuous) Chamfer distance, ``n_samples`` per side: the measure
        of the reconstruction, without a sampling floor.
    n_samples : int
        Input (and point-protocol reconstruction) samples.
    n_dense : int
        Reconstruction samples of the dense protocol.
    """

    points: float
    points_floor: float
    dense: float
    dense_floor: float
    surface: float
    n_samples: int
    n_dense: int

    def as_dict(self, scale: float = 1e3) -> dict:
        """Values times ``scale`` (default: Table 5.1's x 1e3) and the sample counts."""
        d = {k: float(getattr(self, k)) * scale
             for k in ("points", "points_floor", "dense", "dense_floor", "surface")}
        d.update(n_samples=self.n_samples, n_dense=self.n_dense)
        return d


def chamfer_report(
    vertices: Any,
    faces: Any,
    rec_vertices: Any,
    rec_faces: Any,
    *,
    n_samples: int = 10000,
    n_dense: int = 100000,
    seed: int = 0,
) -> ChamferReport:
    """Chamfer distances of a reconstructed surface against the input, three ways.

    The point protocol of the thesis' Table 5.1 (AtlasNet: ``n_samples`` = 10 000 samples on
    each surface, unit-sphere normalisation, squared distances) has a sampling floor that
    depends on the input's normalised area and can exceed the reconstruction error itself:
    a large open surface (a skirt) scores about 3e-4 against an independent sampling of
    itself. This reports that protocol with its floor, the dense variant (the reconstruction
    densely sampled, as AtlasNet compares all the points its charts produce against the
    ground-truth samples) with its floor, and the point-to-surface Chamfer distance, which
    measures the reconstruction without a floor. See :func:`chamfer_distance`.

    Parameters
    ----------
    vertices, faces : array_like
        Input mesh ``(V, 3)``, ``(F, 3)``.
    rec_vertices, rec_faces : array_like
        Reconstruction (e.g. :meth:`PatchSet.resample`).
    n_samples : int
        Input samples (Table 5.1: 10 000).
    n_dense : int
        Reconstruction samples of the dense protocol.
    seed : int
        Sampling seed (the floors use ``seed + 1``).

    Returns
    -------
    ChamferReport

    Raises
    ------
    ValueError
        As :func:`chamfer_distance`.
    """
    kw = dict(n_samples=n_samples, seed=seed)
    fl = dict(n_samples=n_samples, seed=seed + 1)
    return ChamferReport(
        points=chamfer_distance(vertices, faces, rec_vertices, rec_faces, **kw),
        points_floor=chamfer_distance(vertices, faces, vertices, faces, **fl),
        dense=chamfer_distance(vertices, faces, rec_vertices, rec_faces, n_samples_b=n_dense,
                               **kw),
        dense_floor=chamfer_distance(vertices, faces, vertices, faces, n_samples_b=n_dense,
                                     **fl),
        surface=chamfer_distance(vertices, faces, rec_vertices, rec_faces, mode="surface",
                                 **kw),
        n_samples=int(n_samples),
        n_dense=int(n_dense),
    )


# --------------------------------------------------------------------------------------------
# PatchSet
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PatchMetrics:
    """Per-patch quality of a :class:`PatchSet` (arrays of shape (K,), NumPy float64).

    Attributes
    ----------
    height_rmse : np.ndarray
        RMS height residual of each patch's points, in input length units.
    normal_error : np.ndarray or None
        Mean unsigned angle (degrees) between the fitted normal and the input normal at the
        patch's points; None without input normals.
    boundary_gap : np.ndarray
        Mean distance (input units) between the positions that two adjacent patches give to
        the vertices of their boundary pairs (each end evaluated in both patches: its own at
        its uv, the neighbour at its projection); 0 for a patch without neighbours.
    boundary_normal_angle : np.ndarray
        Mean angle (degrees) between the two patches' normals at those vertices.
    foldover : np.ndarray or None
        Share of the patch's triangles (all three corners in the patch) whose orientation in
        the patch's uv plane is opposite to the patch's dominant orientation, i.e. where the
        height-graph assumption breaks; None for a point cloud.
    max_tilt : np.ndarray or None
        Largest angle (degrees, in ``[0, 180]``) between the normal of a triangle touching the
        patch (at least one corner in it) and the patch's axis (its frame's z, oriented like
        the triangles). Above 90 the triangle folds over the patch plane; near 90 the height
        graph is steep and ill-conditioned. None for a point cloud.
    n_points : np.ndarray
        Points per patch (int64).
    order : np.ndarray
        Jet order per patch (int64).
    """

    height_rmse: np.ndarray
    normal_error: np.ndarray | None
    boundary_gap: np.ndarray
    boundary_normal_angle: np.ndarray
    foldover: np.ndarray | None
    max_tilt: np.ndarray | None
    n_points: np.ndarray
    order: np.ndarray

    def summary(self) -> dict:
        """Scalar summary: means and maxima over patches (point-weighted height RMSE too)."""
        w = self.n_points.astype(float)
        out = {
            "patches": int(len(self.height_rmse)),
            "height_rmse_mean": float(self.height_rmse.mean()),
            "height_rmse_max": float(self.height_rmse.max()),
            "height_rmse_all": float(np.sqrt(np.sum(w * self.height_rmse**2) / w.sum())),
            "boundary_gap_mean": float(self.boundary_gap.mean()),
            "boundary_gap_max": float(self.boundary_gap.max()),
            "boundary_normal_angle_mean": float(self.boundary_normal_angle.mean()),
        }
        if self.normal_error is not None:
            out["normal_error_mean"] = float(np.sum(w * self.normal_error) / w.sum())
        if self.foldover is not None:
            out["foldover_mean"] = float(self.foldover.mean())
            out["foldover_patches"] = int((self.foldover > 0).sum())
        if self.max_tilt is not None:
            out["max_tilt"] = float(self.max_tilt.max())
        return out


def _max_tilt(v: torch.Tensor, f: torch.Tensor, labels: torch.Tensor,
              rotation: torch.Tensor) -> np.ndarray:
    """``(K,)`` largest angle (degrees) between a triangle touching a patch and its axis.

    Triangles without area are skipped; a patch without a triangle gets 0.
    """
    K = int(rotation.shape[0])
    p = v[f]
    n = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    ln = n.norm(dim=-1)
    ok = ln > 0
    n, fl = n[ok] / ln[ok, None], labels[f[ok]]  # (Fo, 3), (Fo, 3)
    out = torch.zeros(K, dtype=torch.float64)
    for c in range(3):
        axis = rotation[fl[:, c], :, 2]
        ang = torch.rad2deg(torch.arccos((n * axis).sum(-1).clamp(-1.0, 1.0)))
        out = out.scatter_reduce(0, fl[:, c], ang.to(torch.float64), "amax")
    return out.cpu().numpy()


def _angle_deg(a: torch.Tensor, b: torch.Tensor, unsigned: bool = True) -> torch.Tensor:
    c = (a * b).sum(-1) / (a.norm(dim=-1) * b.norm(dim=-1)).clamp_min(1e-300)
    c = c.abs() if unsigned else c
    return torch.rad2deg(torch.arccos(c.clamp(-1.0, 1.0)))


@dataclass(frozen=True)
class PatchSet:
    """K oriented n-jet patches representing a surface (PolyFit).

    Build with :meth:`fit` (or :meth:`load`). Tensors are torch, float64 unless noted.

    Attributes
    ----------
    scale : torch.Tensor
        ``(K,)`` patch scales ``s`` (input units; the patch radius).
    rotation : torch.Tensor
        ``(K, 3, 3)`` rotations ``R`` (columns u axis, v axis, height axis).
    translation : torch.Tensor
        ``(K, 3)`` patch origins ``T`` (centroids).
    coeffs : torch.Tensor
        ``(K, M)`` jet coefficients at the set's largest order (canonical units).
    orders : torch.Tensor
        ``(K,)`` int64 jet order of every patch.
    uv : torch.Tensor
        ``(K, Pmax, 2)`` canonical uv of each patch's points (zeros at padding).
    mask : torch.Tensor
        ``(K, Pmax)`` bool, valid entries of ``uv`` / ``index``.
    index : torch.Tensor
        ``(K, Pmax)`` int64 input vertex of each entry (-1 at padding).
    domain : torch.Tensor
        ``(K, 4)`` uv bounding box ``(u_min, v_min, u_max, v_max)`` of each patch's points.
    residual : torch.Tensor
        ``(K,)`` RMS height residual in canonical units (times ``scale`` = input units).
    status : torch.Tensor
        ``(K,)`` int64 :class:`polygeo.status.Status` of each jet fit.
    labels : torch.Tensor
        ``(V,)`` int64 patch of each input vertex.
    vertices : torch.Tensor
        ``(V, 3)`` input positions (the reference for resampling and metrics).
    faces : torch.Tensor or None
        ``(F, 3)`` int64 input triangles (None for a point cloud).
    normals : torch.Tensor or None
        ``(V, 3)`` input normals given to :meth:`fit` (None: the mesh's vertex normals are
        used where needed, see :meth:`reference_normals`).
    boundary_pairs : torch.Tensor
        ``(E_b, 2)`` int64 input edges whose ends lie in different patches.
    orient : str
        Canonicalisation used (``"pca"``, ``"stn"`` or ``"optimize"``).
    info : dict
        Fit details (patch-count search for ``target_rmse``, timings).
    """

    scale: torch.Tensor
    rotation: torch.Tensor
    translation: torch.Tensor
    coeffs: torch.Tensor
    orders: torch.Tensor
    uv: torch.Tensor
    mask: torch.Tensor
    index: torch.Tensor
    domain: torch.Tensor
    residual: torch.Tensor
    status: torch.Tensor
    labels: torch.Tensor
    vertices: torch.Tensor
    faces: torch.Tensor | None
    normals: torch.Tensor | None
    boundary_pairs: torch.Tensor
    orient: str = "pca"
    info: dict = field(default_factory=dict)

    # ---------------------------------------------------------------- basic properties

    @property
    def n_patches(self) -> int:
        """K, the number of patches."""
        return int(self.scale.shape[0])

    @property
    def order(self) -> int:
        """Largest jet order of the set (the order of ``coeffs``)."""
        return jets.order_from_ncoeffs(int(self.coeffs.shape[1]))

    @property
    def orientation(self) -> Orientation:
        """The patches' ``(s, R, T)`` as a :class:`polygeo.frames.Orientation`."""
        return Orientation(self.scale, self.rotation, self.translation)

    @property
    def n_coefficients(self) -> int:
        """Parameters used: jet coefficients of each patch's order plus 7 per orientation."""
        o = self.orders.cpu().numpy()
        return int(np.sum((o + 1) * (o + 2) // 2) + 7 * self.n_patches)

    # ---------------------------------------------------------------- fitting

    @classmethod
    def fit(
        cls,
        points: Any,
        faces: Any = None,
        partition: Partition | None = None,
        n_patches: int | None = None,
        order: int | str = 4,
        orient: str = "pca",
        *,
        normals: Any = None,
        target_rmse: float | None = None,
        tol: float | None = None,
        max_order: int = 6,
        stn_model: Any = None,
        optimize_steps: int = 40,
        min_points_per_coeff: float = 2.0,
        seed: int = 0,
    ) -> PatchSet:
        """Partition a surface and fit one oriented n-jet per patch, in one batched call.

        Parameters
        ----------
        points : array_like or torch.Tensor
            ``(V, 3)`` vertex (or point) positions, float. Never modified.
        faces : array_like or torch.Tensor, optional
            ``(F, 3)`` integer triangles; None for a point cloud.
        partition : Partition, optional
            A precomputed partition of these vertices (default: :func:`polygeo.partition.
            partition` with ``n_patches`` and ``seed``).
        n_patches : int, optional
            Requested K (default: the thesis rule ``max(100, min(400, area / 0.008))``).
            Ignored when ``partition`` is given.
        order : int or "auto"
            Jet order in ``[1, 6]``, or ``"auto"``: per patch the lowest order in
            ``[1, max_order]`` whose height RMSE is at most ``tol`` (input units), or, with
            ``tol=None``, the order minimising the Bayesian information criterion
            ``n log(RSS / n) + M log(n)``.
        orient : {"pca", "stn", "optimize"}
            Canonicalisation (see :mod:`polygeo.stn`): the PCA frame, refined by the STN
            (kept per patch only where it lowers the height residual of order ``order``, or
            4 for ``"auto"``) or by ``optimize_steps`` Adam steps on that residual.
        normals : array_like, optional
            ``(V, 3)`` input normals. They orient the patch frames (default: the faces' area
            vectors; PCA's sign convention for a point cloud) and score normal errors
            (default: the mesh's vertex normals).
        target_rmse : float, optional
            Choose K from an error target instead of a count: K grows (from ``n_patches`` or
            16) until the RMS height residual over all points is at most ``target_rmse``
            (input units), the search recorded in ``info["search"]``.
        tol : float, optional
            Height tolerance of ``order="auto"`` (input units).
        max_order : int
            Largest order tried by ``order="auto"``.
        stn_model : PatchSTN, optional
            Network for ``orient="stn"`` (default: the shipped weights).
        optimize_steps : int
            Adam steps of ``orient="optimize"``.
        min_points_per_coeff : float
            A patch gets at most the highest order whose coefficient count times this
            factor does not exceed its point count (status ``ORDER_REDUCED`` when this caps
            the requested order): a jet with nearly as many coefficients as points
            interpolates its samples but swings between and beyond them, which shows in
            resampled surfaces and boundary gaps. 0 disables the cap (orders are then only
            reduced for singular or ill-conditioned fits).
        seed : int
            Partition seed.

        Returns
        -------
        PatchSet

        Raises
        ------
        ValueError
            On bad shapes, non-finite points, out-of-range indices, a partition of another
            vertex count, ``n_patches`` larger than the vertex count or a bad option.
        TypeError
            On non-numeric input or non-integer faces.
        FileNotFoundError
            For ``orient="stn"`` without shipped weights.
        """
        check_choice(orient, "orient", ORIENT_CHOICES)
        auto = isinstance(order, str)
        if auto:
            check_choice(order, "order", ("auto",))
            max_order = check_int(max_order, "max_order", low=1, high=jets.MAX_ORDER)
        else:
            order = check_int(order, "order", low=1, high=jets.MAX_ORDER)
        if tol is not None:
            tol = check_positive(tol, "tol")
        ratio = check_positive(min_points_per_coeff, "min_points_per_coeff", strict=False)
        v = as_tensor(points, "points")
        check_shape(v, "points", ("V", 3))
        check_finite(v, "points")
        v = v.detach().to(torch.float64).clone()
        V = v.shape[0]
        if V == 0:
            raise ValueError("points: expected at least one point, got shape (0, 3)")
        f = None if faces is None else torch.from_numpy(_faces_np(faces, V))
        nrm = None
        if normals is not None:
            nrm = as_tensor(normals, "normals").detach().to(torch.float64)
            check_shape(nrm, "normals", (V, 3))
            check_finite(nrm, "normals")
        if partition is not None and len(partition.labels) != V:
            raise ValueError(
                f"partition: expected labels for {V} vertices, got {len(partition.labels)}"
            )
        fit_order = max_order if auto else order
        min_pts = jets.n_coeffs(min(fit_order, 4))
        kw = dict(
            v=v,
            f=f,
            nrm=nrm,
            ratio=ratio,
            order=order,
            orient=orient,
            tol=tol,
            max_order=max_order,
            stn_model=stn_model,
            optimize_steps=optimize_steps,
        )
        if target_rmse is None:
            part = partition
            if part is None:
                part = _partition(v, f, n_patches, seed, min_pts)
            return cls._fit_partition(part, **kw)
        target = check_positive(target_rmse, "target_rmse")
        k = 16 if n_patches is None else check_int(n_patches, "n_patches", low=1)
        k_max = max(1, V // min_pts)
        k = min(k, k_max)
        search = []
        p_order = 4 if auto else int(order)
        best = None
        for _ in range(12):
            part = _partition(v, f, k, seed, min_pts)
            ps = cls._fit_partition(part, **kw)
            rmse = ps.metrics(boundary=False).summary()["height_rmse_all"]
            search.append({"requested": int(k), "patches": ps.n_patches, "height_rmse": rmse})
            best = ps
            if rmse <= target or k >= k_max:
                break
            # height error of an n-jet ~ h^(n+1), patch size h ~ K^(-1/2)
            grow = (rmse / target) ** (2.0 / (p_order + 1)) * 1.15
            k = int(min(k_max, max(k + 1, math.ceil(k * grow))))
        best.info["search"] = search
        best.info["target_rmse"] = target
        best.info["target_met"] = bool(search[-1]["height_rmse"] <= target)
        return best

    @classmethod
    def _fit_partition(
        cls, part, *, v, f, nrm, ratio, order, orient, tol, max_order, stn_model, optimize_steps
    ) -> PatchSet:
        from . import canonical, stn

        lab_np = np.array(part.labels, np.int64)
        labels = torch.from_numpy(lab_np)
        K = int(part.n_patches)
        counts = np.bincount(lab_np, minlength=K)
        P = int(counts.max())
        perm = np.argsort(lab_np, kind="stable")
        starts = np.cumsum(counts) - counts
        pos = np.arange(len(lab_np)) - starts[lab_np[perm]]
        index_np = np.full((K, P), -1, dtype=np.int64)
        index_np[lab_np[perm], pos] = perm
        index = torch.from_numpy(index_np)
        mask = index >= 0
        pts = v[index.clamp_min(0)]  # (K, P, 3)
        ref = None
        if nrm is not None:
            ref = torch.zeros(K, 3, dtype=torch.float64).index_add_(0, labels, nrm)
        elif f is not None and len(f):
            # area vectors of the faces, summed per patch (of the first corner)
            pf = v[f]
            cr = torch.linalg.cross(pf[:, 1] - pf[:, 0], pf[:, 2] - pf[:, 0])
            ref = torch.zeros(K, 3, dtype=torch.float64).index_add_(0, labels[f[:, 0]], cr)
        can = canonical.canonicalize(pts, mask, reference_normal=ref)
        local, ori = can.local, can.orientation
        res_order = 4 if isinstance(order, str) else int(order)
        if orient == "stn":
            Q = stn.stn_rotations(local, mask, stn_model)
            # keep the network's frame only where it lowers the residual (never worse than PCA)
            with torch.no_grad():
                r_pca, _ = canonical.height_residual(local, mask, None, res_order)
                r_stn, _ = canonical.height_residual(local, mask, Q, res_order)
            eye = torch.eye(3, dtype=Q.dtype).expand_as(Q)
            Q = torch.where((r_stn < r_pca)[:, None, None], Q, eye)
        elif orient == "optimize":
            Q = canonical.optimize_rotations(local, mask, res_order, steps=optimize_steps).rotation
        else:
            Q = None
        R = ori.R
        if Q is not None:
            if ref is not None:  # keep the normal on the input's side
                flip = Q[:, 2, 2] < 0
                Q = torch.where(flip[:, None, None], Q * torch.tensor([1.0, -1.0, -1.0]), Q)
            local = local @ Q
            R = R @ Q
        uv = torch.where(mask[..., None], local[..., :2], torch.zeros_like(local[..., :2]))
        z = local[..., 2]
        s = ori.s
        top = max_order if isinstance(order, str) else int(order)
        cap = _order_cap(mask.sum(1), top, ratio)
        if isinstance(order, str):
            coeffs, residual, status, orders = _fit_auto(uv, z, mask, s, tol, max_order, cap)
        else:
            coeffs, residual, status, orders = _fit_capped(uv, z, mask, order, cap)
        big = torch.finfo(torch.float64).max
        umin = torch.where(mask[..., None], uv, torch.full_like(uv, big)).amin(1)
        umax = torch.where(mask[..., None], uv, torch.full_like(uv, -big)).amax(1)
        domain = torch.cat([umin, umax], dim=-1)
        return cls(
            scale=s,
            rotation=R,
            translation=ori.T,
            coeffs=coeffs,
            orders=orders.to(torch.int64),
            uv=uv,
            mask=mask,
            index=index,
            domain=domain,
            residual=residual,
            status=status.to(torch.int64),
            labels=labels,
            vertices=v,
            faces=f,
            normals=nrm,
            boundary_pairs=torch.from_numpy(np.array(part.boundary_pairs, np.int64)),
            orient=orient,
            info={},
        )

    # ---------------------------------------------------------------- evaluation

    def _query(self, patch_idx: Any, uv: Any) -> tuple[torch.Tensor, torch.Tensor, bool]:
        numpy_in = is_numpy_like(uv)
        t = as_tensor(uv, "uv")
        idx = as_tensor(patch_idx, "patch_idx", floating=False)
        if idx.ndim == 0:
            idx = idx.expand(t.shape[0]) if t.ndim == 2 else idx
        return idx, t, numpy_in

    def evaluate(self, patch_idx: Any, uv: Any) -> Any:
        """World positions of canonical ``uv`` on patches.

        Parameters
        ----------
        patch_idx : array_like or torch.Tensor
            ``(N,)`` integer patch per query (a scalar applies to every query).
        uv : array_like or torch.Tensor
            ``(N, 2)`` canonical parameters.

        Returns
        -------
        numpy.ndarray or torch.Tensor
            ``(N, 3)`` positions (input units), NumPy when ``uv`` is NumPy. Differentiable
            w.r.t. ``uv`` and, through :func:`evaluate_patches`, the set's tensors.

        Raises
        ------
        ValueError, TypeError
            As :func:`evaluate_patches`.
        """
        idx, t, numpy_in = self._query(patch_idx, uv)
        out = evaluate_patches(self.coeffs, self.scale, self.rotation, self.translation, idx, t)
        return out.detach().cpu().numpy() if numpy_in else out

    def geometry(self, patch_idx: Any, uv: Any) -> PatchGeometry:
        """Positions, normals, Jacobians, metric tensors and curvatures at ``(patch, uv)``.

        Parameters
        ----------
        patch_idx : array_like or torch.Tensor
            ``(N,)`` integer patch per query (a scalar applies to every query).
        uv : array_like or torch.Tensor
            ``(N, 2)`` canonical parameters.

        Returns
        -------
        PatchGeometry
            Torch tensors (see :func:`patch_geometry`).

        Raises
        ------
        ValueError, TypeError
            As :func:`evaluate_patches`.
        """
        idx, t, _ = self._query(patch_idx, uv)
        return patch_geometry(self.coeffs, self.scale, self.rotation, self.translation, idx, t)

    def normals_at(self, patch_idx: Any, uv: Any) -> Any:
        """Unit normals ``(N, 3)`` at ``(patch, uv)`` (NumPy when ``uv`` is NumPy)."""
        numpy_in = is_numpy_like(uv)
        n = self.geometry(patch_idx, uv).geometry.normal
        return n.detach().cpu().numpy() if numpy_in else n

    def project(self, points: Any, patch_idx: Any) -> Any:
        """Canonical uv of world points in given patches' frames (first two local coords).

        Parameters
        ----------
        points : array_like or torch.Tensor
            ``(N, 3)`` world positions.
        patch_idx : array_like or torch.Tensor
            ``(N,)`` integer patches.

        Returns
        -------
        numpy.ndarray or torch.Tensor
            ``(N, 2)`` uv (NumPy when ``points`` is NumPy).
        """
        numpy_in = is_numpy_like(points)
        p = as_tensor(points, "points").to(torch.float64)
        check_shape(p, "points", ("N", 3))
        idx = as_tensor(patch_idx, "patch_idx", floating=False).to(torch.int64)
        check_shape(idx, "patch_idx", (p.shape[0],))
        uv = self._project(p, idx)
        return uv.detach().cpu().numpy() if numpy_in else uv

    def _project(self, p: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        d = p - self.translation[idx]
        loc = (d[:, None, :] @ self.rotation[idx])[:, 0] / self.scale[idx, None]
        return loc[:, :2]

    def reference_normals(self) -> torch.Tensor | None:
        """Input normals ``(V, 3)`` used for the normal error, or None.

        The normals given to :meth:`fit`, else the mesh's area-weighted vertex normals, else
        None (a point cloud without normals).
        """
        if self.normals is not None:
            return self.normals
        if self.faces is None:
            return None
        from .mesh import vertex_normals

        return vertex_normals(self.vertices, self.faces).normals.to(torch.float64)

    def _vertex_uv(self) -> torch.Tensor:
        """Canonical uv of every input vertex in its own patch, ``(V, 2)``."""
        out = torch.zeros(self.vertices.shape[0], 2, dtype=self.uv.dtype)
        out[self.index[self.mask]] = self.uv[self.mask]
        return out

    def fitted_vertices(self) -> torch.Tensor:
        """Every input vertex evaluated through its own patch, ``(V, 3)`` (differentiable)."""
        return evaluate_patches(
            self.coeffs,
            self.scale,
            self.rotation,
            self.translation,
            self.labels,
            self._vertex_uv(),
        )

    # ---------------------------------------------------------------- resampling

    def resample(self, resolution: int = 0, *, grid: int = 8) -> tuple[Any, Any]:
        """The fitted surface as a triangle mesh at any resolution.

        With input faces, the input triangulation is subdivided ``resolution`` times (each
        triangle into ``4**resolution``) and every new vertex, a barycentric combination of
        a triangle's corners, is evaluated through the patches of those corners: in each
        corner's patch at the same combination of the corners' uv (projected into that
        patch), blended with the barycentric weights. A vertex on an input edge depends only
        on that edge's ends, so the result is watertight wherever the input was; at
        ``resolution=0`` the output vertices are the input vertices evaluated through their
        own patches.

        Without faces (a point cloud), each patch is sampled on a ``grid x grid`` lattice of
        its uv bounding box (refined ``2**resolution`` times) and triangulated per patch (not
        connected across patches).

        Parameters
        ----------
        resolution : int
            Subdivision level in ``[0, 8]``.
        grid : int
            Lattice size per patch for point clouds (>= 2).

        Returns
        -------
        vertices : torch.Tensor
            ``(V_out, 3)`` float64 positions (differentiable w.r.t. the set's tensors).
        faces : np.ndarray
            ``(F_out, 3)`` int64 triangles.

        Raises
        ------
        ValueError
            On a bad resolution or grid.
        """
        level = check_int(resolution, "resolution", low=0, high=8)
        if self.faces is None:
            return self._resample_grid(check_int(grid, "grid", low=2) * 2**level)
        corners, weights, out_faces = subdivide_barycentric(
            self.faces, self.vertices.shape[0], level
        )
        c = torch.from_numpy(corners)
        w = torch.from_numpy(weights)
        p = self.vertices[c]  # (N, 3, 3)
        lab = self.labels[c]  # (N, 3)
        out = torch.zeros(c.shape[0], 3, dtype=torch.float64)
        for slot in range(3):
            P = lab[:, slot]
            # uv of the three corners in patch P, combined barycentrically
            uvs = torch.stack([self._project(p[:, j], P) for j in range(3)], dim=1)  # (N,3,2)
            uv = (w[..., None] * uvs).sum(1)
            x = evaluate_patches(self.coeffs, self.scale, self.rotation, self.translation, P, uv)
            out = out + w[:, slot, None] * x
        return out, out_faces

    def _resample_grid(self, n: int) -> tuple[torch.Tensor, np.ndarray]:
        K = self.n_patches
        t = torch.linspace(0.0, 1.0, n, dtype=torch.float64)
        a, b = torch.meshgrid(t, t, indexing="ij")
        lo, hi = self.domain[:, :2], self.domain[:, 2:]
        u = lo[:, None, 0] + (hi - lo)[:, None, 0] * a.reshape(1, -1)
        vv = lo[:, None, 1] + (hi - lo)[:, None, 1] * b.reshape(1, -1)
        uv = torch.stack([u, vv], dim=-1).reshape(-1, 2)
        idx = torch.arange(K).repeat_interleave(n * n)
        verts = evaluate_patches(self.coeffs, self.scale, self.rotation, self.translation, idx, uv)
        i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
        i, j = i.ravel(), j.ravel()
        q00, q10, q11, q01 = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
        one = np.concatenate([np.stack([q00, q10, q11], 1), np.stack([q00, q11, q01], 1)])
        faces = (one[None] + (np.arange(K) * n * n)[:, None, None]).reshape(-1, 3)
        return verts, faces.astype(np.int64)

    # ---------------------------------------------------------------- metrics

    def metrics(self, *, boundary: bool = True) -> PatchMetrics:
        """Per-patch height RMSE, normal error, boundary gap and foldover share.

        Parameters
        ----------
        boundary : bool
            Compute the boundary gaps (skip for speed: zeros).

        Returns
        -------
        PatchMetrics
        """
        K = self.n_patches
        with torch.no_grad():
            n_pts = self.mask.sum(1)
            rmse = (self.residual * self.scale).cpu().numpy()
            vuv = self._vertex_uv()
            nerr = None
            ref_normals = self.reference_normals()
            if ref_normals is not None:
                g = patch_geometry(
                    self.coeffs, self.scale, self.rotation, self.translation, self.labels, vuv
                ).geometry
                ang = _angle_deg(g.normal, ref_normals)
                ok = ref_normals.norm(dim=-1) > 0
                s = torch.zeros(K, dtype=torch.float64).index_add_(0, self.labels[ok], ang[ok])
                c = torch.bincount(self.labels[ok], minlength=K).clamp_min(1)
                nerr = (s / c).cpu().numpy()
            gap = np.zeros(K)
            gang = np.zeros(K)
            if boundary and len(self.boundary_pairs):
                bp = self.boundary_pairs
                vid = torch.cat([bp[:, 0], bp[:, 1]])
                own = self.labels[vid]
                other = torch.cat([self.labels[bp[:, 1]], self.labels[bp[:, 0]]])
                args = (self.coeffs, self.scale, self.rotation, self.translation)
                ga = patch_geometry(*args, own, vuv[vid])
                pv = self.vertices[vid]
                gb = patch_geometry(*args, other, self._project(pv, other))
                d = (ga.positions - gb.positions).norm(dim=-1)
                a = _angle_deg(ga.geometry.normal, gb.geometry.normal, unsigned=False)
                for arr, val in ((gap, d), (gang, a)):
                    tot = torch.zeros(K, dtype=torch.float64)
                    tot.index_add_(0, own, val).index_add_(0, other, val)
                    cnt = torch.bincount(own, minlength=K) + torch.bincount(other, minlength=K)
                    arr[:] = (tot / cnt.clamp_min(1)).cpu().numpy()
            fold = tilt = None
            if self.faces is not None and len(self.faces):
                tilt = _max_tilt(self.vertices, self.faces, self.labels, self.rotation)
                f = self.faces
                lf = self.labels[f]
                inside = (lf[:, 0] == lf[:, 1]) & (lf[:, 1] == lf[:, 2])
                fi = f[inside]
                lab = lf[inside, 0]
                q = vuv[fi]  # (Fi, 3, 2)
                e1, e2 = q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]
                area = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
                tot = torch.zeros(K, dtype=torch.float64).index_add_(0, lab, area)
                dom = torch.sign(tot)[lab]
                flipped = (area * dom < 0).to(torch.float64)
                nf = torch.bincount(lab, minlength=K).clamp_min(1)
                fold = (
                    (torch.zeros(K, dtype=torch.float64).index_add_(0, lab, flipped) / nf)
                    .cpu()
                    .numpy()
                )
        return PatchMetrics(
            height_rmse=rmse,
            normal_error=nerr,
            boundary_gap=gap,
            boundary_normal_angle=gang,
            foldover=fold,
            max_tilt=tilt,
            n_points=n_pts.cpu().numpy().astype(np.int64),
            order=self.orders.cpu().numpy().astype(np.int64),
        )

    # ---------------------------------------------------------------- serialisation

    def save(self, path: str | os.PathLike) -> Path:
        """Write the set to an NPZ file (atomically replaced).

        Parameters
        ----------
        path : str or os.PathLike
            Destination; ``.npz`` is appended if missing.

        Returns
        -------
        pathlib.Path
            The path written.
        """
        p = Path(path)
        if p.suffix != ".npz":
            p = p.with_name(p.name + ".npz")
        arrays = {
            "version": np.array(_NPZ_VERSION),
            "orient": np.array(self.orient),
            "scale": self.scale,
            "rotation": self.rotation,
            "translation": self.translation,
            "coeffs": self.coeffs,
            "orders": self.orders,
            "uv": self.uv,
            "mask": self.mask,
            "index": self.index,
            "domain": self.domain,
            "residual": self.residual,
            "status": self.status,
            "labels": self.labels,
            "vertices": self.vertices,
            "boundary_pairs": self.boundary_pairs,
        }
        if self.faces is not None:
            arrays["faces"] = self.faces
        if self.normals is not None:
            arrays["normals"] = self.normals
        out = {
            k: (v.detach().cpu().numpy() if isinstance(v, torch.Tensor) else v)
            for k, v in arrays.items()
        }
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp = p.with_name(p.name + ".tmp.npz")
        np.savez_compressed(tmp, **out)
        os.replace(tmp, p)
        return p

    @classmethod
    def load(cls, path: str | os.PathLike) -> PatchSet:
        """Read a set written by :meth:`save`.

        Parameters
        ----------
        path : str or os.PathLike
            NPZ file.

        Returns
        -------
        PatchSet

        Raises
        ------
        FileNotFoundError
            If the file does not exist.
        ValueError
            If it is not a PatchSet file (missing arrays or another version).
        """
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"path: no such file {str(p)!r}")
        with np.load(p, allow_pickle=False) as z:
            need = ("version", "scale", "rotation", "translation", "coeffs", "labels")
            missing = [k for k in need if k not in z.files]
            if missing:
                raise ValueError(f"path: {str(p)!r} is not a PatchSet file (missing {missing})")
            if int(z["version"]) != _NPZ_VERSION:
                raise ValueError(
                    f"path: expected PatchSet version {_NPZ_VERSION}, got {int(z['version'])}"
                )
            d = {k: z[k] for k in z.files}

        def t(name):
            return torch.from_numpy(np.ascontiguousarray(d[name]))

        return cls(
            scale=t("scale"),
            rotation=t("rotation"),
            translation=t("translation"),
            coeffs=t("coeffs"),
            orders=t("orders"),
            uv=t("uv"),
            mask=t("mask"),
            index=t("index"),
            domain=t("domain"),
            residual=t("residual"),
            status=t("status"),
            labels=t("labels"),
            vertices=t("vertices"),
            faces=t("faces") if "faces" in d else None,
            normals=t("normals") if "normals" in d else None,
            boundary_pairs=t("boundary_pairs"),
            orient=str(d["orient"]),
            info={},
        )


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------


def _partition(v, f, n_patches, seed, min_vertices) -> Partition:
    vn = v.cpu().numpy()
    if f is None:
        return partition(vn, None, n_patches, seed=seed, min_vertices=min_vertices)
    return partition(vn, f.cpu().numpy(), n_patches, seed=seed, min_vertices=min_vertices)


def _order_cap(count: torch.Tensor, order: int, ratio: float) -> torch.Tensor:
    """Highest order ``o <= order`` with ``ratio * n_coeffs(o) <= count`` (at least 1)."""
    cap = torch.ones_like(count)
    for o in range(2, order + 1):
        cap = torch.where(ratio * jets.n_coeffs(o) <= count, torch.full_like(cap, o), cap)
    return cap


def _fit_capped(uv, z, mask, order, cap):
    """Fit every patch at ``min(order, cap)`` (one batched call per distinct order)."""
    K = uv.shape[0]
    M = jets.n_coeffs(order)
    coeffs = torch.zeros(K, M, dtype=torch.float64)
    residual = torch.zeros(K, dtype=torch.float64)
    status = torch.zeros(K, dtype=torch.int64)
    orders = torch.zeros(K, dtype=torch.int64)
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


def _fit_auto(uv, z, mask, s, tol, max_order, cap):
    """Per-patch lowest order within ``tol`` (input units) or by BIC; padded coefficients."""
    K = uv.shape[0]
    M = jets.n_coeffs(max_order)
    n = mask.sum(1).to(torch.float64)
    fits = [jets.fit(uv, z, o, mask=mask) for o in range(1, max_order + 1)]
    res = torch.stack([f.residual.to(torch.float64) for f in fits], 1)  # (K, O)
    fitted = torch.stack([f.fitted_order for f in fits], 1)
    ok = fitted == torch.arange(1, max_order + 1)[None, :]  # not reduced
    ok = ok & (torch.arange(1, max_order + 1)[None, :] <= cap[:, None])  # enough points
    ok[:, 0] = True  # order 1 (or its fallback) is always available
    if tol is not None:
        good = ((res * s[:, None]) <= tol) & ok
        first = torch.where(good.any(1), good.to(torch.int8).argmax(1), torch.full((K,), -1))
        # no order meets tol: the highest well-posed order
        best_ok = torch.where(ok, torch.arange(max_order)[None, :], -1).amax(1).clamp_min(0)
        choice = torch.where(first >= 0, first, best_ok)
    else:
        m = torch.tensor([jets.n_coeffs(o) for o in range(1, max_order + 1)], dtype=torch.float64)
        rss = (res**2) * n[:, None]
        nn = n.clamp_min(1)[:, None]
        bic = nn * torch.log(rss.clamp_min(1e-300) / nn) + m[None, :] * torch.log(nn)
        bic = torch.where(ok & (n[:, None] > m[None, :]), bic, torch.full_like(bic, math.inf))
        choice = torch.where(
            torch.isfinite(bic).any(1), bic.argmin(1), torch.zeros(K, dtype=torch.int64)
        )
    coeffs = torch.zeros(K, M, dtype=torch.float64)
    residual = torch.zeros(K, dtype=torch.float64)
    status = torch.zeros(K, dtype=torch.int64)
    orders = torch.zeros(K, dtype=torch.int64)
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
