"""Deformation models of PolySfT: the template as oriented jet patches, and the per-vertex baseline.

PolySfT (thesis section 5.3) represents the template as PolyFit patches
``T_k = {O_k, phi_k(u, v)}`` with ``O_k = (s_k, R_k, T_k)`` and
``phi_k(u, v) = (u, v, sum_ij alpha_ij u^i v^j)``, and deforms it per frame with jet offsets
``Delta alpha``, per-point ``uv`` displacements ``Delta uv`` and a rigid motion
``(R_c, T_c)``::

    x = O_g( R_c O_g^-1( O_k( phi_k(u + Du, v + Dv; alpha_k + Dalpha_k) + r ) ) + T_c )

where ``O_g`` is the template's global PCA frame (for one patch ``O_g = O_k`` and this is the
thesis' ``O o (R_c phi(u + Du, v + Dv; alpha + Dalpha) + T_c)``) and ``r`` is the height
residual of the template fit along the patch normal, kept fixed so that zero parameters give the
template back exactly. With several patches each patch also has its own rigid motion
``(R_k, T_k)`` (about its origin, in the normalised global frame) between ``O_g^-1 O_k`` and
``R_c`` (:class:`JetModel`, ``patch_rigid``); the boundary term ties the patches together.

Units. Every patch frame is scaled so that its points lie in the unit ball around its
centroid (``s_k`` = the patch radius, :class:`polygeo.patches.PatchSet`); with one patch the
rigid motion acts in that frame (``O_g = O``, 15 cm for a 24 x 18 cm sheet), with several in
the template's PCA frame scaled to the unit disc. All parameters live in
these normalised units, which is what makes the thesis' learning rates (1e-3 for ``Delta uv``,
1e-2 for ``Delta alpha``, 1e-4 for the rigid motion) independent of the scene's units
(metres here).

The patches are a :class:`polygeo.patches.PatchSet` (PCA frames; several patches come from
its partition of the template). Each
vertex belongs to one patch; a vertex on a patch boundary is also represented as a secondary
sample in every adjacent patch, and the boundary-consistency term (thesis eq. (51)) pulls each
secondary sample onto its primary and aligns their jet normals.

Parameters of a frame are a ``dict`` of tensors (one frame) or of stacked tensors with a leading
frame dimension ``F`` (a window). A model maps them to vertices ``(F, V, 3)`` in camera
coordinates (scene units).
"""


from __future__ import annotations

import numpy as np
import torch

from polygeo import jets
from polygeo.checks import as_tensor, check_finite, check_int, check_shape
from polygeo.frames import Orientation, axis_angle_to_matrix, matrix_to_axis_angle, rigid_align

from .template import (
    MAX_TILT,
    ORDER_AUTO,
    PATCHES_AUTO,
    JetTemplate,
    _global_frame,
    jet_slopes,
)

__all__ = [
    "JetTemplate",
    "JetModel",
    "VertexModel",
    "DeformationModel",
    "build_model",
    "ORDER_AUTO",
    "PATCHES_AUTO",
    "jet_slopes",
]


def _rigid_local(y: torch.Tensor, frame: Orientation, rot: torch.Tensor, trans: torch.Tensor):
    """``O_g(R_c y + T_c)`` for ``y`` (F, V, 3) already in the normalised global frame."""
    Rc = axis_angle_to_matrix(rot)  # (F, 3, 3)
    moved = y @ Rc.transpose(-1, -2) + trans[:, None, :]
    return frame.s[0] * (moved @ frame.R[0].T) + frame.T[0]


class DeformationModel:
    """Interface of a deformation model (see :class:`JetModel`, :class:`VertexModel`).

    Attributes
    ----------
    name : str
        ``"polysft"`` or ``"vertex"``.
    groups : dict of str to str
        Parameter name -> learning-rate field of :class:`sft.settings.OptimiserSettings`
        (``"lr_uv"``, ``"lr_alpha"``, ``"lr_rigid"``, ``"lr_vertex"``).
    temporal : tuple of str
        Parameters entering the temporal-consistency term (thesis eq. (48)).
    scale : float
        The template radius ``s_g`` in scene units (normalised units -> scene units).
    """

    name: str
    groups: dict[str, str]
    temporal: tuple[str, ...]
    scale: float

    def init_params(self) -> dict[str, torch.Tensor]:
        """Zero parameters of one frame (the template)."""
        raise NotImplementedError

    def vertices(self, params: dict[str, torch.Tensor]) -> torch.Tensor:
        """``(F, V, 3)`` vertices from stacked parameters (leading dimension ``F``)."""
        raise NotImplementedError

    def regularizer(self, params: dict[str, torch.Tensor]) -> torch.Tensor:
        """Model-specific extra loss (boundary consistency), a scalar (0 when none)."""
        return torch.zeros((), dtype=self.dtype)

    def forward(self, params: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """``(vertices, regularizer)`` in one call (what the optimiser uses)."""
        return self.vertices(params), self.regularizer(params)

    def state(self) -> dict:
        """Mutable state to checkpoint (e.g. the active jet order)."""
        return {}

    def load_state(self, state: dict) -> None:
        """Restore :meth:`state`."""


def _per_sample_map(A: torch.Tensor, x: torch.Tensor, patch: torch.Tensor) -> torch.Tensor:
    """``A[patch[i]] @ x[..., i, :]`` for every point ``i``, without a batch of 3 x 3 products.

    ``A`` is ``(K, 3, 3)`` or ``(F, K, 3, 3)``, ``x`` ``(F, N, 3)``, ``patch`` ``(N,)``
    int64; returns ``(F, N, 3)``. Every point goes through all ``K`` maps in one matrix
    product and keeps its own: for the few patches of a model that is far cheaper (forward
    and backward) than gathering a ``3 x 3`` matrix per point.
    """
    K = A.shape[-3]
    At = A.transpose(-1, -2).transpose(-3, -2).reshape(*A.shape[:-3], 3, 3 * K)
    allk = (x @ At).unflatten(-1, (K, 3))  # (F, N, K, 3)
    return allk.gather(-2, patch.view(1, -1, 1, 1).expand(*allk.shape[:2], 1, 3))[..., 0, :]


class JetModel(DeformationModel):
    """PolySfT: jet offsets, ``uv`` displacements and a rigid motion per frame.

    Parameters
    ----------
    template : JetTemplate
        The fitted template (its order is the highest order the model can use).
    order : int or None
        Active jet order (``<= template.order``); None = ``template.order``. Coefficients of
        higher degree stay at the template's value (their offsets are masked).
    boundary_weight, boundary_normal_weight : float
        Weights of the boundary-consistency term (eq. (51)): positions (normalised units) and
        normals ``(1 - cos)^2``; unused for one patch.
    patch_rigid : bool
        With several patches, give each patch its own rigid motion relative to the global
        one: parameters ``p_rot`` ``(K, 3)`` (rotation vectors, radians, about the patch
        origin) and ``p_trans`` ``(K, 3)`` (normalised global units), learning rate
        ``lr_patch``. The boundary term is then what keeps the patches together. This lets
        a template bend or roll further than a height graph over one plane can (a sheet
        rolled by 200 degrees). Ignored for one patch.
    dtype : torch.dtype
        Dtype of the parameters and outputs (float32 by default: optimisation).
    """

    name = "polysft"
    groups = {"d_alpha": "lr_alpha", "d_uv": "lr_uv", "rot": "lr_rigid", "trans": "lr_rigid"}
    temporal = ("d_alpha", "d_uv")

    def __init__(
        self,
        template: JetTemplate,
        order: int | None = None,
        *,
        boundary_weight: float = 1.0,
        boundary_normal_weight: float = 0.1,
        patch_rigid: bool = True,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        self.template = template
        self.dtype = dtype
        self.max_order = template.order
        self.order = self.max_order if order is None else check_int(order, "order", low=1,
                                                                   high=self.max_order)
        self.boundary_weight = float(boundary_weight)
        self.boundary_normal_weight = float(boundary_normal_weight)
        t = template
        self.scale = float(t.frame.s[0])
        self._frame = t.frame.to(dtype)
        self._coeffs = t.coeffs.to(dtype)
        self._uv = t.uv.to(dtype)
        self._resid = t.residual.to(dtype)
        self._degree = jets.exponents(self.max_order).sum(1)  # (M,)
        self._slices = t.slices
        V = int(t.primary.shape[0])
        self._identity = bool(t.n_samples == V and torch.equal(t.primary, torch.arange(V)))
        # patch frames expressed in the normalised global frame: y = A_k p + b_k
        o, g = t.orientation, t.frame
        Rg = g.R[0]
        self._A = ((o.s / g.s[0])[:, None, None] * (Rg.T @ o.R)).to(dtype)  # (K, 3, 3)
        self._b = ((o.T - g.T[0]) @ Rg / g.s[0]).to(dtype)  # (K, 3): patch origins
        self.patch_rigid = bool(patch_rigid) and t.n_patches > 1
        if self.patch_rigid:
            self.groups = {**JetModel.groups, "p_rot": "lr_patch", "p_trans": "lr_patch"}
        #: ``(K,)`` steepest jet slope (degrees) of each patch of the template
        self.template_slopes = jet_slopes(t.coeffs, t.sample_patch, t.uv, t.order)

    def batch_of_one(self, params: dict) -> dict[str, torch.Tensor]:
        """One frame's parameters as a batch of one frame, as :meth:`vertices` takes them.

        Entries that are not parameters (e.g. optimiser state) are dropped.
        """
        return {k: params[k][None] for k in self.groups}

    @property
    def n_coeffs(self) -> int:
        """Coefficients per patch at the highest order."""
        return int(self._coeffs.shape[1])

    def set_order(self, order: int) -> None:
        """Change the active order (``1 .. template.order``)."""
        self.order = check_int(order, "order", low=1, high=self.max_order)

    def state(self) -> dict:
        """Active order."""
        return {"order": self.order}

    def load_state(self, state: dict) -> None:
        """Restore the active order."""
        if "order" in state:
            self.set_order(int(state["order"]))

    def init_params(self) -> dict[str, torch.Tensor]:
        """Zero offsets of one frame."""
        K, M, S = self.template.n_patches, self.n_coeffs, self.template.n_samples
        z = dict(dtype=self.dtype)
        out = {
            "d_alpha": torch.zeros(K, M, **z),
            "d_uv": torch.zeros(S, 2, **z),
            "rot": torch.zeros(3, **z),
            "trans": torch.zeros(3, **z),
        }
        if self.patch_rigid:
            out["p_rot"] = torch.zeros(K, 3, **z)
            out["p_trans"] = torch.zeros(K, 3, **z)
        return out

    def _active(self) -> torch.Tensor:
        return (self._degree <= self.order).to(self.dtype)  # (M,)

    def _patch_maps(self, params: dict[str, torch.Tensor]):
        """``(A, b)``: local patch coordinates -> normalised global frame, per frame.

        ``A`` is ``(K, 3, 3)`` or ``(F, K, 3, 3)`` (with per-patch rigid motions), ``b``
        ``(K, 3)`` or ``(F, K, 3)``.
        """
        if not self.patch_rigid:
            return self._A, self._b
        Rp = axis_angle_to_matrix(params["p_rot"])  # (F, K, 3, 3) about the patch origins
        return Rp @ self._A, self._b + params["p_trans"]

    def _evaluate(self, params: dict[str, torch.Tensor]):
        """Samples in the normalised global frame ``(F, S, 3)``, before the global rigid motion.

        Also returns the offset coefficients ``(F, K, M)``, displaced ``uv`` ``(F, S, 2)`` and
        the patch maps of :meth:`_patch_maps`.
        """
        uv = self._uv + params["d_uv"]  # (F, S, 2)
        coeff = self._coeffs + params["d_alpha"] * self._active()  # (F, K, M)
        A, b = self._patch_maps(params)
        mono = jets.monomials(uv, self.max_order)  # (F, S, M)
        if len(self._slices) == 1:
            z = (mono @ coeff[:, 0, :, None])[..., 0] + self._resid
            pts = torch.cat([uv, z[..., None]], dim=-1)  # (F, S, 3) local
            y = pts @ A[..., 0, :, :].transpose(-1, -2) + b[..., 0, None, :]
        else:  # every sample through its patch's jet and map at once (no loop over patches)
            sp = self.template.sample_patch
            # every patch's jet at every sample (one matmul), then each sample's own
            z_all = mono @ coeff.transpose(-1, -2)  # (F, S, K)
            z = z_all.gather(-1, sp.expand(z_all.shape[:-1])[..., None])[..., 0] + self._resid
            pts = torch.cat([uv, z[..., None]], dim=-1)
            y = _per_sample_map(A, pts, sp) + b.index_select(-2, sp)
        return y, coeff, uv, A

    def _boundary(self, y: torch.Tensor, coeff: torch.Tensor, uv: torch.Tensor,
                  A: torch.Tensor) -> torch.Tensor:
        t = self.template
        P = t.pairs.shape[0]
        idx = t.pairs.T.reshape(-1)  # (2P,): the primaries, then the secondaries
        ya, yb = y.index_select(1, idx).split(P, dim=1)
        d2 = (ya - yb).pow(2).sum(-1)  # (F, P), normalised units
        # jet normals at the pair samples: every patch's gradient there (one matmul per
        # derivative), then each sample's own patch's
        kp = t.sample_patch[idx]  # (2P,)
        q = uv.index_select(1, idx)  # (F, 2P, 2)
        ct = coeff.transpose(-1, -2)  # (F, M, K)
        grads = []
        for du, dv in ((1, 0), (0, 1)):
            g = jets.monomial_derivatives(q, self.max_order, du, dv) @ ct  # (F, 2P, K)
            grads.append(g.gather(-1, kp.expand(g.shape[:-1])[..., None])[..., 0])
        n = torch.stack([-grads[0], -grads[1], torch.ones_like(grads[0])], dim=-1)
        n = n / n.norm(dim=-1, keepdim=True)
        m = _per_sample_map(A, n, kp)  # (F, 2P, 3): A_k are scaled rotations
        m = m / m.norm(dim=-1, keepdim=True)
        ma, mb = m.split(P, dim=1)
        cos = (ma * mb).sum(-1)
        return (self.boundary_weight * d2
                + self.boundary_normal_weight * (1.0 - cos).pow(2)).mean()

    def vertices(self, params: dict[str, torch.Tensor]) -> torch.Tensor:
        """``(F, V, 3)`` camera-frame vertices (scene units) of stacked parameters."""
        return self.forward(params)[0]

    def regularizer(self, params: dict[str, torch.Tensor]) -> torch.Tensor:
        """Boundary consistency (eq. (51)) averaged over pairs and frames; 0 for one patch."""
        return self.forward(params)[1]

    def forward(self, params: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """Vertices ``(F, V, 3)`` and the boundary term (scalar) from one evaluation."""
        y, coeff, uv, A = self._evaluate(params)
        reg = (torch.zeros((), dtype=self.dtype) if len(self.template.pairs) == 0
               else self._boundary(y, coeff, uv, A))
        if not self._identity:
            y = y.index_select(1, self.template.primary)
        return _rigid_local(y, self._frame, params["rot"], params["trans"]), reg


    def tilt(self, params: dict[str, torch.Tensor]) -> np.ndarray:
        """``(K,)`` steepest slope (degrees) of each patch's jet in one frame (:func:`jet_slopes`).

        The jets with the frame's offsets (active order) at the displaced samples.
        ``params`` are one frame's (entries that are not parameters are ignored).
        """
        p = self.batch_of_one(params)
        coeff = (self._coeffs + p["d_alpha"] * self._active())[0]
        return jet_slopes(coeff, self.template.sample_patch, (self._uv + p["d_uv"])[0],
                          self.max_order)

    def params_for(self, verts) -> dict[str, torch.Tensor]:
        """Parameters of one frame whose surface is closest to ``verts`` (a projection).

        In closed form: the global rigid motion is the best rigid map (Kabsch) of the template
        onto ``verts``; with per-patch rigid motions each patch's is the best map of what is
        left; ``Delta uv`` puts every sample under its target in its patch's plane and
        ``Delta alpha`` is the least-squares jet (active order) through the targets' heights.
        Exact, to rounding, for any surface that each patch sees as a height graph of its
        order (the template itself gives zeros); otherwise the least-squares compromise.

        Parameters
        ----------
        verts : array_like
            ``(V, 3)`` vertices in camera coordinates (scene units), template vertex order.

        Returns
        -------
        dict of str to torch.Tensor
            Like :meth:`init_params`, in the model's dtype.

        Raises
        ------
        ValueError
            On a bad shape or non-finite vertices.
        """
        t = self.template
        V = int(t.primary.shape[0])
        X = as_tensor(verts, "verts", dtype=torch.float64).detach()
        check_shape(X, "verts", (V, 3))
        check_finite(X, "verts")
        g, o = t.frame, t.orientation
        sp = t.sample_patch
        ys = g.inverse_apply(X[None])[0][t.sample_vertex]  # (S, 3) targets, normalised global
        A = (o.s / g.s[0])[:, None, None] * (g.R[0].T @ o.R)  # (K, 3, 3)
        b = (o.T - g.T[0]) @ g.R[0] / g.s[0]  # (K, 3)
        deg = jets.exponents(self.max_order).sum(1)
        active = deg <= self.order
        z0 = (jets.monomials(t.uv, self.max_order) * t.coeffs[sp]).sum(-1) + t.residual
        local0 = torch.cat([t.uv, z0[:, None]], -1)
        y0 = (A[sp] @ local0[:, :, None])[:, :, 0] + b[sp]  # template samples
        Rc, Tc = rigid_align(y0[t.primary], ys[t.primary])
        yr = (ys - Tc) @ Rc  # R_c^T (y - T_c)
        K = t.n_patches
        p_rot = torch.zeros(K, 3, dtype=torch.float64)
        p_trans = torch.zeros(K, 3, dtype=torch.float64)
        d_uv = torch.zeros_like(t.uv)
        d_alpha = torch.zeros_like(t.coeffs)
        for k, sl in enumerate(t.slices):
            Ak = A[k]
            if self.patch_rigid:
                Rk, tk = rigid_align(y0[sl] - b[k], yr[sl] - b[k])
                p_rot[k], p_trans[k] = matrix_to_axis_angle(Rk), tk
                Ak = Rk @ Ak
            # A_k is a scaled rotation: its inverse is A_k^T / s^2
            loc = (yr[sl] - b[k] - p_trans[k]) @ Ak / (Ak[:, 0] @ Ak[:, 0])
            d_uv[sl] = loc[:, :2] - t.uv[sl]
            mono = jets.monomials(loc[:, :2], self.max_order)
            h = loc[:, 2] - t.residual[sl] - mono[:, ~active] @ t.coeffs[k, ~active]
            sol = torch.linalg.lstsq(mono[:, active], h[:, None], driver="gelsd").solution
            d_alpha[k, active] = sol[:, 0] - t.coeffs[k, active]
        out = {"d_alpha": d_alpha, "d_uv": d_uv, "rot": matrix_to_axis_angle(Rc), "trans": Tc}
        if self.patch_rigid:
            out.update(p_rot=p_rot, p_trans=p_trans)
        return {k: v.to(self.dtype) for k, v in out.items()}


class VertexModel(DeformationModel):
    """Per-vertex baseline: free offsets of every vertex plus the same rigid motion.

    ``x = O_g(R_c (O_g^-1(x_template) + Dx) + T_c)`` with ``Dx`` in normalised units.

    Parameters
    ----------
    verts : array_like
        ``(V, 3)`` template vertices.
    dtype : torch.dtype
        Dtype of parameters and outputs.
    """

    name = "vertex"
    groups = {"d_x": "lr_vertex", "rot": "lr_rigid", "trans": "lr_rigid"}
    temporal = ("d_x",)

    def __init__(self, verts, *, dtype: torch.dtype = torch.float32) -> None:
        v = as_tensor(verts, "verts", dtype=torch.float64).detach()
        check_shape(v, "verts", ("V", 3))
        check_finite(v, "verts")
        self.dtype = dtype
        frame = _global_frame(v)
        self.scale = float(frame.s[0])
        self._frame = frame.to(dtype)
        self._local = frame.inverse_apply(v[None])[0].to(dtype)  # (V, 3) normalised
        self.order = None

    def init_params(self) -> dict[str, torch.Tensor]:
        """Zero offsets of one frame."""
        z = dict(dtype=self.dtype)
        return {
            "d_x": torch.zeros(self._local.shape[0], 3, **z),
            "rot": torch.zeros(3, **z),
            "trans": torch.zeros(3, **z),
        }

    def vertices(self, params: dict[str, torch.Tensor]) -> torch.Tensor:
        """``(F, V, 3)`` camera-frame vertices of stacked parameters."""
        return _rigid_local(self._local + params["d_x"], self._frame, params["rot"],
                            params["trans"])


def build_model(
    method: str,
    verts,
    faces,
    *,
    order: int | str = 4,
    max_order: int = 6,
    patches: int | str = 1,
    max_tilt: float = MAX_TILT,
    max_patches: int = 64,
    boundary_weight: float = 1.0,
    boundary_normal_weight: float = 0.1,
    patch_rigid: bool = True,
    seed: int = 0,
    dtype: torch.dtype = torch.float32,
) -> DeformationModel:
    """Build a deformation model of a template.

    Parameters
    ----------
    method : {"polysft", "vertex"}
        Jet patches (PolySfT) or per-vertex offsets (baseline).
    verts, faces : array_like
        ``(V, 3)`` template vertices (scene units) and ``(F, 3)`` triangles.
    order : int or "auto"
        Jet order; ``"auto"`` starts at 2 and lets the optimiser raise it up to ``max_order``.
    max_order : int
        Highest order for ``"auto"``.
    patches : int or "auto"
        Number of jet patches, or ``"auto"`` (see :meth:`JetTemplate.fit`).
    max_tilt : float
        Largest tilt (degrees) of a triangle from its patch's axis for ``"auto"``.
    max_patches : int
        Most patches ``"auto"`` may choose.
    boundary_weight, boundary_normal_weight : float
        Boundary-consistency weights (several patches).
    patch_rigid : bool
        A rigid motion per patch (several patches, see :class:`JetModel`).
    seed : int
        Partition seed.
    dtype : torch.dtype
        Parameter dtype.

    Returns
    -------
    DeformationModel

    Raises
    ------
    ValueError
        On an unknown method or order.
    """
    if method == "vertex":
        return VertexModel(verts, dtype=dtype)
    if method != "polysft":
        raise ValueError(f"method: expected 'polysft' or 'vertex', got {method!r}")
    if order == ORDER_AUTO:
        top = check_int(max_order, "max_order", low=2, high=jets.MAX_ORDER)
        tmpl = JetTemplate.fit(verts, faces, top, patches, max_tilt=max_tilt,
                               max_patches=max_patches, seed=seed)
        return JetModel(tmpl, order=2, boundary_weight=boundary_weight,
                        boundary_normal_weight=boundary_normal_weight, patch_rigid=patch_rigid,
                        dtype=dtype)
    if isinstance(order, str):
        raise ValueError(f"order: expected an integer in [1, {jets.MAX_ORDER}] or 'auto', "
                         f"got {order!r}")
    tmpl = JetTemplate.fit(verts, faces, order, patches, max_tilt=max_tilt,
                           max_patches=max_patches, seed=seed)
    return JetModel(tmpl, boundary_weight=boundary_weight,
                    boundary_normal_weight=boundary_normal_weight, patch_rigid=patch_rigid,
                    dtype=dtype)

