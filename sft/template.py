"""The PolySfT template: a mesh as oriented jet patches (PolyFit), sampled at its vertices.

:class:`JetTemplate` fits :class:`polygeo.patches.PatchSet` patches (PCA frames) to a
template mesh and samples them at its vertices (a vertex on a patch boundary is also a
secondary sample of every adjacent patch); :func:`jet_slopes` measures how steep each patch's
jet has grown. The deformation models that move a template live in :mod:`sft.model`.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, replace

import numpy as np
import torch

from polygeo import jets
from polygeo.checks import (
    as_tensor,
    check_choice,
    check_finite,
    check_int,
    check_shape,
)
from polygeo.frames import Orientation, pca_frames

from .settings import MAX_TILT, ORDER_AUTO, PATCHES_AUTO, _check_patches

__all__ = ["JetTemplate", "jet_slopes", "ORDER_AUTO", "PATCHES_AUTO", "MAX_TILT"]


def jet_slopes(coeffs: torch.Tensor, sample_patch: torch.Tensor, uv: torch.Tensor,
               order: int) -> np.ndarray:
    """``(K,)`` steepest slope (degrees) of each patch's jet over its plane at its samples.

    ``atan |grad z|`` of ``z(u, v) = sum_ij c_ij u^i v^j``, maximised over the samples of each
    patch: a height graph folds over its plane at 90 degrees, so this is how much room a
    patch has left to bend. Unlike the tilt of a mesh's triangles it does not see noise of
    single triangles.

    Parameters
    ----------
    coeffs : torch.Tensor
        ``(K, M)`` jet coefficients (normalised local units) at ``order``.
    sample_patch : torch.Tensor
        ``(S,)`` int64 patch of each sample.
    uv : torch.Tensor
        ``(S, 2)`` sample parameters in their patch.
    order : int
        Jet order of ``coeffs``.

    Returns
    -------
    np.ndarray
        ``(K,)`` float64 degrees in ``[0, 90)``; 0 for a patch without samples.
    """
    with torch.no_grad():
        c, q = coeffs[sample_patch], uv[:, None, :]  # one jet per sample, at its point
        zu, zv = (jets.evaluate(c, q, 1, 0)[:, 0], jets.evaluate(c, q, 0, 1)[:, 0])
        ang = torch.rad2deg(torch.atan(torch.hypot(zu, zv))).to(torch.float64)
        out = torch.zeros(coeffs.shape[0], dtype=torch.float64)
        return out.scatter_reduce(0, sample_patch, ang, "amax").numpy()


def _global_frame(verts: torch.Tensor) -> Orientation:
    """PCA frame of all vertices, scaled so that their ``uv`` projections fit the unit disc."""
    fr = pca_frames(verts[None])
    local = (verts - fr.centroid) @ fr.rotation[0]  # (V, 3)
    s = local[:, :2].norm(dim=-1).max().clamp_min(1e-12)
    return Orientation(s.reshape(1), fr.rotation, fr.centroid)


@dataclass(frozen=True)
class JetTemplate:
    """A template mesh as ``K`` oriented jet patches (PolyFit), sampled at its vertices.

    Attributes
    ----------
    orientation : Orientation
        ``K`` patch frames ``O_k`` (local -> camera coordinates, scene units).
    coeffs : torch.Tensor
        ``(K, M)`` template jet coefficients at ``order`` (normalised local units).
    order : int
        Jet order of ``coeffs``.
    sample_patch : torch.Tensor
        ``(S,)`` int64 patch of each sample (``S >= V``).
    sample_vertex : torch.Tensor
        ``(S,)`` int64 template vertex of each sample.
    uv : torch.Tensor
        ``(S, 2)`` sample parameters in their patch (normalised, in the unit disc).
    residual : torch.Tensor
        ``(S,)`` template height minus the fitted jet at ``uv`` (normalised units).
    primary : torch.Tensor
        ``(V,)`` int64 sample that gives each vertex its position. Samples are sorted by
        patch (each patch is a contiguous slice, see :attr:`slices`).
    pairs : torch.Tensor
        ``(P, 2)`` int64 (primary, secondary) sample pairs on patch boundaries (``P = 0``
        for a single patch).
    frame : Orientation
        The global frame ``O_g`` (one item).
    fit_rms : float
        RMS of ``residual`` in scene units (how far the jets are from the template).
    max_tilt : float
        Largest angle (degrees) between a template triangle and the axis of a patch it
        touches (:attr:`polygeo.patches.PatchMetrics.max_tilt`); above 90 a patch folds over
        its plane. With ``fit(..., tilt="jet")`` the steepest jet slope (:func:`jet_slopes`)
        instead. NaN when not computed.
    """

    orientation: Orientation
    coeffs: torch.Tensor
    order: int
    sample_patch: torch.Tensor
    sample_vertex: torch.Tensor
    uv: torch.Tensor
    residual: torch.Tensor
    primary: torch.Tensor
    pairs: torch.Tensor
    frame: Orientation
    fit_rms: float
    max_tilt: float = float("nan")

    @property
    def n_patches(self) -> int:
        """Number of patches ``K``."""
        return len(self.orientation)

    @property
    def slices(self) -> list[slice]:
        """Sample slice of each patch."""
        counts = torch.bincount(self.sample_patch, minlength=self.n_patches).tolist()
        ends = np.cumsum(counts)
        return [slice(int(e - c), int(e)) for c, e in zip(counts, ends)]

    @property
    def n_samples(self) -> int:
        """Number of samples ``S``."""
        return int(self.uv.shape[0])

    @classmethod
    def fit(
        cls,
        verts,
        faces,
        order: int = 4,
        patches: int | str = 1,
        *,
        max_tilt: float = MAX_TILT,
        max_patches: int = 64,
        tilt: str = "mesh",
        seed: int = 0,
    ) -> JetTemplate:
        """Fit PolyFit patches (:class:`polygeo.patches.PatchSet`, PCA frames) to a template.

        Parameters
        ----------
        verts : array_like
            ``(V, 3)`` template vertices (camera coordinates, scene units).
        faces : array_like
            ``(F, 3)`` triangles.
        order : int
            Jet order in ``[1, 6]``.
        patches : int or "auto"
            Number of patches ``K`` (1: the whole template is one patch), or ``"auto"``: the
            fewest of 1, 2, ..., 8, 12, 18, ... (at most ``max_patches``) for which every
            triangle lies within ``max_tilt`` of the axis of each patch it touches, i.e.
            every patch is a height graph with room to bend further. A sheet that is not
            bent past about twice ``max_tilt`` gets one patch (the thesis' model); a tube, a
            cap or a crumpled cloth gets several.
        max_tilt : float
            Largest tilt in degrees, in ``(0, 90)``, for ``"auto"``.
        max_patches : int
            Largest count tried by ``"auto"`` (also capped so that every patch keeps at least
            twice as many vertices as jet coefficients). When even that count leaves a steeper
            triangle, it is used and a ``RuntimeWarning`` says so.
        tilt : {"mesh", "jet"}
            What ``"auto"`` bounds by ``max_tilt``: the triangles' angle to their patch's axis
            (a patch's mesh stays a height graph), or the slope of each fitted jet
            (:func:`jet_slopes`; for a reconstructed surface, whose single triangles can be
            rough while the surface is smooth).
        seed : int
            Seed of the partition (``patches > 1``).

        Returns
        -------
        JetTemplate
            In float64.

        Raises
        ------
        ValueError
            On bad shapes, non-finite vertices, an order out of range, a bad ``patches``,
            ``max_tilt`` or ``max_patches``, or fewer vertices in the template than
            coefficients of the jet.
        """
        from polygeo.patches import PatchSet

        v = as_tensor(verts, "verts", dtype=torch.float64).detach()
        check_shape(v, "verts", ("V", 3))
        check_finite(v, "verts")
        order = check_int(order, "order", low=1, high=jets.MAX_ORDER)
        m = jets.n_coeffs(order)
        if v.shape[0] < m:
            raise ValueError(
                f"verts: the template has {v.shape[0]} vertices, fewer than the {m} "
                f"coefficients of an order-{order} jet; use a lower order"
            )
        f = np.asarray(faces)
        patches, max_tilt = _check_patches(patches, max_tilt)

        measure = check_choice(tilt, "tilt", ("mesh", "jet"))

        def fit_k(k: int) -> tuple[JetTemplate, float]:
            """The template on ``k`` patches and its steepest tilt (``measure``)."""
            ps = PatchSet.fit(v, f, n_patches=k, order=order, orient="pca", seed=seed)
            tmpl = cls.from_patchset(ps, v)
            if measure == "jet":
                steep = jet_slopes(tmpl.coeffs, tmpl.sample_patch, tmpl.uv, order).max()
            else:
                tl = ps.metrics(boundary=False).max_tilt
                steep = float("nan") if tl is None else tl.max()
            return tmpl, float(steep)

        if patches == PATCHES_AUTO:
            cap = min(check_int(max_patches, "max_patches", low=1),
                      max(1, v.shape[0] // (2 * m)))
            k = 1
            while True:
                tmpl, steep = fit_k(k)
                if not steep > max_tilt or k >= cap:
                    break
                # the partition is area-driven, not curvature-driven: a count one higher can
                # place its cuts better, so small counts are tried one by one
                k = min(k + 1 if k < 8 else math.ceil(1.5 * k), cap)
            if steep > max_tilt:
                warnings.warn(
                    f"patches='auto': {tmpl.n_patches} patches (the most tried) still leave a "
                    f"{'jet slope' if measure == 'jet' else 'triangle'} {steep:.0f} degrees "
                    f"from its patch's axis (max_tilt {max_tilt:g}); the template is rough or "
                    "folded at the scale of its patches", RuntimeWarning, stacklevel=2)
        else:
            tmpl, steep = fit_k(check_int(patches, "patches", high=max(1, v.shape[0])))
        return replace(tmpl, max_tilt=steep)

    @classmethod
    def from_patchset(cls, ps, verts=None) -> JetTemplate:
        """Sample a :class:`polygeo.patches.PatchSet` at the template's vertices.

        Every vertex is a primary sample of its own patch (``ps.labels``); the ends of every
        boundary edge (``ps.boundary_pairs``) are also secondary samples of the other patch.
        ``uv`` is the projection on each patch's plane and ``residual`` the height left
        over by the jet, so that zero offsets give the vertices back exactly.

        Parameters
        ----------
        ps : PatchSet
            Patches fitted to the template.
        verts : array_like, optional
            ``(V, 3)`` template vertices (default: ``ps.vertices``).

        Returns
        -------
        JetTemplate
        """
        v = ps.vertices if verts is None else as_tensor(verts, "verts", dtype=torch.float64)
        v = v.detach().to(torch.float64)
        V = v.shape[0]
        labels = ps.labels.cpu().numpy().astype(np.int64)
        bpairs = ps.boundary_pairs.cpu().numpy().astype(np.int64).reshape(-1, 2)
        K = ps.n_patches
        # samples: every vertex in its own patch, boundary vertices also in adjacent patches
        sp, sv = [labels], [np.arange(V)]
        if len(bpairs):
            la, lb = labels[bpairs[:, 0]], labels[bpairs[:, 1]]
            extra = np.unique(np.concatenate([np.stack([bpairs[:, 0], lb], 1),
                                              np.stack([bpairs[:, 1], la], 1)]), axis=0)
        else:
            extra = np.zeros((0, 2), dtype=np.int64)
        sp.append(extra[:, 1])
        sv.append(extra[:, 0])
        sp_np, sv_np = np.concatenate(sp), np.concatenate(sv)
        is_primary = np.arange(len(sp_np)) < V
        # order the samples by patch (contiguous slices), primaries first within a patch
        order_ = np.lexsort((~is_primary, sp_np))
        where = np.empty_like(order_)
        where[order_] = np.arange(len(order_))
        sample_patch = torch.from_numpy(sp_np[order_]).long()
        sample_vertex = torch.from_numpy(sv_np[order_]).long()
        primary = torch.from_numpy(where[:V]).long()
        sec = where[V:]
        pairs = torch.stack([primary[sample_vertex[sec]], torch.from_numpy(sec).long()], 1)
        orient = Orientation(ps.scale.to(torch.float64), ps.rotation.to(torch.float64),
                             ps.translation.to(torch.float64))
        coeffs = ps.coeffs.to(torch.float64).detach()
        pts = v[sample_vertex]
        s_, R_, T_ = (orient.s[sample_patch], orient.R[sample_patch], orient.T[sample_patch])
        local = ((pts - T_)[:, None, :] @ R_)[:, 0] / s_[:, None]  # (S, 3) canonical
        uv = local[:, :2].contiguous()
        z = (jets.monomials(uv, jets.order_from_ncoeffs(coeffs.shape[1]))
             * coeffs[sample_patch]).sum(-1)
        resid = local[:, 2] - z
        frame = orient[0] if K == 1 else _global_frame(v)
        fit_rms = float((resid * s_).pow(2).mean().sqrt())
        return cls(
            orientation=orient,
            coeffs=coeffs,
            order=jets.order_from_ncoeffs(coeffs.shape[1]),
            sample_patch=sample_patch,
            sample_vertex=sample_vertex,
            uv=uv,
            residual=resid,
            primary=primary,
            pairs=pairs,
            frame=frame,
            fit_rms=fit_rms,
        )
