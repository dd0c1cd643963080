"""The :class:`PatchSet` front end: K oriented n-jet patches representing a surface (PolyFit).

A thin frozen dataclass over the pure stages of :mod:`polygeo.patches.fitting`,
:mod:`~polygeo.patches.evaluation`, :mod:`~polygeo.patches.resampling`,
:mod:`~polygeo.patches.metrics` and :mod:`~polygeo.patches.storage`: its methods validate
user input, convert NumPy to torch and back, and call those functions with the set's tensors.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .. import jets
from ..checks import (
    as_tensor,
    check_faces,
    check_finite,
    check_int,
    check_positive,
    check_shape,
    is_numpy_like,
)
from ..frames import Orientation
from ..partition import Partition, patch_count_for_vertices
from .evaluation import (
    PatchGeometry,
    evaluate_patches,
    patch_geometry,
    project_to_patches,
    vertex_uv,
)
from .fitting import fit_partition, fit_settings, partition_for_fit, search_patch_count
from .metrics import (
    PatchMetrics,
    boundary_errors,
    boundary_geometry,
    foldover_share,
    max_tilt,
    normal_error,
)
from .resampling import resample_grid, resample_subdivided
from .storage import TENSOR_FIELDS, load_npz, save_npz

__all__ = ["PatchSet"]



def _checked_surface(points: Any, faces: Any, normals: Any):
    """``(V, 3)`` float64 copy of the points, int64 faces or None, float64 normals or None."""
    v = as_tensor(points, "points")
    check_shape(v, "points", ("V", 3))
    check_finite(v, "points")
    v = v.detach().to(torch.float64).clone()
    n_vertices = v.shape[0]
    if n_vertices == 0:
        raise ValueError("points: expected at least one point, got shape (0, 3)")
    f = None if faces is None else check_faces(faces, n_vertices).cpu()
    nrm = None
    if normals is not None:
        nrm = as_tensor(normals, "normals").detach().to(torch.float64)
        check_shape(nrm, "normals", (n_vertices, 3))
        check_finite(nrm, "normals")
    return v, f, nrm


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
    numpy_io : bool
        Whether :meth:`fit` was given NumPy (or other non-torch) points: then
        :meth:`resample` and :meth:`fitted_vertices` return NumPy arrays, else torch tensors
        (one array type per call, following the input; kept by :meth:`save` / :meth:`load`).
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
    numpy_io: bool = False
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

    def _patches(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        return self.coeffs, self.scale, self.rotation, self.translation

    def _out(self, x: torch.Tensor) -> Any:
        """``x`` as the fit's input type: a NumPy copy for NumPy input, else the tensor."""
        return x.detach().cpu().numpy() if self.numpy_io else x

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
            Requested number of patches K (a count; default: scale-free,
            :func:`polygeo.partition.patch_count_for_vertices`: about six vertices per
            coefficient of an order-``min(order, 4)`` jet, at most 400). Ignored when
            ``partition`` is given.
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
        settings = fit_settings(order, orient, tol, max_order, min_points_per_coeff, stn_model,
                                optimize_steps)
        numpy_io = is_numpy_like(points)
        v, f, nrm = _checked_surface(points, faces, normals)
        n_vertices = v.shape[0]
        if partition is not None and len(partition.labels) != n_vertices:
            raise ValueError(
                f"partition: expected labels for {n_vertices} vertices, got "
                f"{len(partition.labels)}"
            )
        min_pts = jets.n_coeffs(min(settings.top_order, 4))
        if target_rmse is None:
            part = partition
            if part is None and n_patches is None:
                n_patches = patch_count_for_vertices(n_vertices, min_pts)
            if part is None:
                part = partition_for_fit(v, f, n_patches, seed, min_pts)
            return cls(**fit_partition(part, v, f, nrm, settings), numpy_io=numpy_io)
        target = check_positive(target_rmse, "target_rmse")
        start = 16 if n_patches is None else check_int(n_patches, "n_patches", low=1)

        def fit_at(count: int) -> tuple[PatchSet, int, float]:
            part = partition_for_fit(v, f, count, seed, min_pts)
            ps = cls(**fit_partition(part, v, f, nrm, settings), numpy_io=numpy_io)
            return ps, ps.n_patches, ps.metrics(boundary=False).summary()["height_rmse_all"]

        best, search = search_patch_count(fit_at, start, max(1, n_vertices // min_pts), target,
                                          settings.residual_order)
        best.info["search"] = search
        best.info["target_rmse"] = target
        best.info["target_met"] = bool(search[-1]["height_rmse"] <= target)
        return best

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
        out = evaluate_patches(*self._patches(), idx, t)
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
        return patch_geometry(*self._patches(), idx, t)

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
        uv = project_to_patches(p, self.scale, self.rotation, self.translation, idx)
        return uv.detach().cpu().numpy() if numpy_in else uv

    def reference_normals(self) -> torch.Tensor | None:
        """Input normals ``(V, 3)`` used for the normal error, or None.

        The normals given to :meth:`fit`, else the mesh's area-weighted vertex normals, else
        None (a point cloud without normals).
        """
        if self.normals is not None:
            return self.normals
        if self.faces is None:
            return None
        from ..mesh import vertex_normals

        return vertex_normals(self.vertices, self.faces).normals.to(torch.float64)

    def _vertex_uv(self) -> torch.Tensor:
        """Canonical uv of every input vertex in its own patch, ``(V, 2)``."""
        return vertex_uv(self.uv, self.mask, self.index, self.vertices.shape[0])

    def fitted_vertices(self) -> Any:
        """Every input vertex evaluated through its own patch, ``(V, 3)`` float64.

        NumPy for a set fitted from NumPy input (:attr:`numpy_io`), else a torch tensor,
        differentiable w.r.t. the set's tensors.
        """
        return self._out(evaluate_patches(*self._patches(), self.labels, self._vertex_uv()))

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
        vertices : numpy.ndarray or torch.Tensor
            ``(V_out, 3)`` float64 positions (input units). NumPy for a set fitted from NumPy
            input (:attr:`numpy_io`); else a torch tensor, differentiable w.r.t. the set's
            tensors.
        faces : numpy.ndarray or torch.Tensor
            ``(F_out, 3)`` int64 triangles, of the same array type as ``vertices``.

        Raises
        ------
        ValueError
            On a bad resolution or grid.
        """
        level = check_int(resolution, "resolution", low=0, high=8)
        if self.faces is None:
            n = check_int(grid, "grid", low=2) * 2**level
            verts, faces = resample_grid(*self._patches(), self.domain, n)
        else:
            verts, faces = resample_subdivided(*self._patches(), self.labels, self.vertices,
                                               self.faces, level)
        return self._out(verts), self._out(faces)

    # ---------------------------------------------------------------- metrics

    def metrics(self, *, boundary: bool = True) -> PatchMetrics:
        """Per-patch height RMSE, normal error, boundary gap, foldover share and tilt.

        Parameters
        ----------
        boundary : bool
            Compute the boundary gaps (skip for speed: zeros).

        Returns
        -------
        PatchMetrics
        """
        n_patches = self.n_patches
        with torch.no_grad():
            vuv = self._vertex_uv()
            nerr = None
            ref_normals = self.reference_normals()
            if ref_normals is not None:
                g = patch_geometry(*self._patches(), self.labels, vuv).geometry
                nerr = normal_error(g.normal, ref_normals, self.labels, n_patches)
            gap, gang = np.zeros(n_patches), np.zeros(n_patches)
            if boundary and len(self.boundary_pairs):
                ends = boundary_geometry(*self._patches(), self.labels, self.vertices, vuv,
                                         self.boundary_pairs)
                gap, gang = boundary_errors(*ends, n_patches)
            fold = tilt = None
            if self.faces is not None and len(self.faces):
                tilt = max_tilt(self.vertices, self.faces, self.labels, self.rotation)
                fold = foldover_share(self.faces, self.labels, vuv, n_patches)
            return PatchMetrics(
                height_rmse=(self.residual * self.scale).cpu().numpy(),
                normal_error=nerr,
                boundary_gap=gap,
                boundary_normal_angle=gang,
                foldover=fold,
                max_tilt=tilt,
                n_points=self.mask.sum(1).cpu().numpy().astype(np.int64),
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
        return save_npz(path, {name: getattr(self, name) for name in
                               ("orient", "numpy_io", "faces", "normals", *TENSOR_FIELDS)})

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
        return cls(**load_npz(path))
