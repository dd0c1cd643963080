"""SMPL / SMPL+H / SMPL-X bodies from the user's own official ``.npz`` files.

Nothing is downloaded or shipped here: the SMPL family's licences require a sign-in and
forbid redistribution. Users who have the files (``SMPL_NEUTRAL.npz``, ``SMPLX_NEUTRAL.npz``,
...) load them behind the same interface as the Anny body (:class:`draping.body.BodyModel`).

Expected arrays (the official NPZ layout): ``v_template (V, 3)``, ``f (F, 3)``,
``shapedirs (V, 3, S)``, ``posedirs (V, 3, 9 (J - 1))`` (optional), ``J_regressor (J, V)``
(dense), ``weights (V, J)``, ``kintree_table (2, J)`` (first row: parents).

Coordinates are the files' own: metres, y up, facing +z, T-pose. AMASS motions
(``draping.motion.read_amass``) carry a root orientation that turns them z up.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from draping.body import (
    PosedBody,
    expand_batch,
    forward_kinematics,
    kinematic_levels,
    linear_blend_skinning,
    pose_inputs,
)
from polygeo.checks import as_tensor, check_finite, check_int, check_shape
from polygeo.frames import axis_angle_to_matrix

__all__ = ["SMPLBody", "smpl_joint_names"]

_SMPL_24 = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist", "left_hand", "right_hand",
)
_FINGERS = [f"{f}{i}" for f in ("index", "middle", "pinky", "ring", "thumb") for i in (1, 2, 3)]


def smpl_joint_names(n_joints: int) -> tuple[str, ...]:
    """Joint names of SMPL (24), SMPL+H (52) and SMPL-X (55); ``joint{i}`` otherwise."""
    if n_joints == 24:
        return _SMPL_24
    hands = [f"left_{f}" for f in _FINGERS] + [f"right_{f}" for f in _FINGERS]
    if n_joints == 52:
        return _SMPL_24[:22] + tuple(hands)
    if n_joints == 55:
        return _SMPL_24[:22] + ("jaw", "left_eye", "right_eye") + tuple(hands)
    return tuple(f"joint{i}" for i in range(n_joints))


def _sparse_weights(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Dense ``(V, J)`` weights as ``(V, K)`` weights and indices, K the most non-zeros."""
    k = max(1, int((w > 0).sum(1).max()))
    idx = np.argsort(-w, axis=1, kind="stable")[:, :k]
    return np.take_along_axis(w, idx, 1), idx


@dataclass(frozen=True, eq=False)
class SMPLBody:
    """An SMPL-family body; see :class:`draping.body.BodyModel` for the interface.

    Shape parameters are the first ``num_betas`` PCA coefficients (``betas``) of
    ``shapedirs``. Posing follows SMPL: pose blend shapes (``posedirs`` times the entries of
    ``R_j - I`` of the non-root joints) are added before linear blend skinning.
    """

    v_template: torch.Tensor
    faces: torch.Tensor
    shapedirs: torch.Tensor
    posedirs: torch.Tensor | None
    J_regressor: torch.Tensor
    parents: torch.Tensor
    skin_weights: torch.Tensor
    skin_indices: torch.Tensor
    bone_names: tuple[str, ...]
    shape_names: tuple[str, ...]
    levels: list = field(default_factory=list, repr=False)

    @classmethod
    def load(cls, path, num_betas: int = 10, dtype: torch.dtype = torch.float32) -> SMPLBody:
        """Read an official SMPL / SMPL+H / SMPL-X ``.npz``.

        Parameters
        ----------
        path : str or Path
        num_betas : int
            Shape coefficients kept (at most the file's).
        dtype : torch.dtype

        Raises
        ------
        ValueError
            On a missing array, inconsistent shapes, or a sparse/pickled ``J_regressor``.
        """
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                d = {k: z[k] for k in z.files}
        except ValueError as exc:
            raise ValueError(
                f"path: {path.name} holds pickled objects (e.g. a sparse J_regressor); save "
                "it again with dense arrays") from exc
        need = ("v_template", "f", "shapedirs", "J_regressor", "weights", "kintree_table")
        missing = [k for k in need if k not in d]
        if missing:
            raise ValueError(f"path: {path.name} is not an SMPL-family file (missing {missing})")
        v = np.asarray(d["v_template"], np.float64)
        V = v.shape[0]
        check_shape(v, "v_template", ("V", 3))
        sd = np.asarray(d["shapedirs"], np.float64)
        check_shape(sd, "shapedirs", (V, 3, "S"))
        num_betas = check_int(num_betas, "num_betas", low=0, high=sd.shape[2])
        jr = np.asarray(d["J_regressor"], np.float64)
        check_shape(jr, "J_regressor", ("J", V))
        J = jr.shape[0]
        w = np.asarray(d["weights"], np.float64)
        check_shape(w, "weights", (V, J))
        kt = np.asarray(d["kintree_table"]).astype(np.int64)
        check_shape(kt, "kintree_table", (2, J))
        parents = kt[0].copy()
        parents[0] = -1
        pd = d.get("posedirs")
        if pd is not None:
            pd = np.asarray(pd, np.float64)
            if pd.ndim == 2:  # (V * 3, P)
                pd = pd.reshape(V, 3, -1)
            check_shape(pd, "posedirs", (V, 3, 9 * (J - 1)))
        ws, wi = _sparse_weights(w)
        ws = ws / ws.sum(1, keepdims=True)

        def t(a):
            return torch.as_tensor(np.ascontiguousarray(a), dtype=dtype)

        par = torch.as_tensor(parents)
        return cls(
            v_template=t(v), faces=torch.as_tensor(np.asarray(d["f"]).astype(np.int64)),
            shapedirs=t(sd[:, :, :num_betas]), posedirs=None if pd is None else t(pd),
            J_regressor=t(jr), parents=par, skin_weights=t(ws),
            skin_indices=torch.as_tensor(wi), bone_names=smpl_joint_names(J),
            shape_names=tuple(f"beta{i}" for i in range(num_betas)),
            levels=kinematic_levels(par),
        )

    @property
    def dtype(self) -> torch.dtype:
        """Floating dtype of the model."""
        return self.v_template.dtype

    @property
    def num_bones(self) -> int:
        """Joint count ``J``."""
        return len(self.bone_names)

    @property
    def default_shape(self) -> torch.Tensor:
        """``(S,)`` zeros: the template."""
        return torch.zeros(len(self.shape_names), dtype=self.dtype)

    def _shape(self, shape) -> torch.Tensor:
        if shape is None:
            return self.default_shape[None]
        s = as_tensor(shape, "shape", dtype=self.dtype)
        if s.dim() == 1:
            s = s[None]
        check_shape(s, "shape", ("B", len(self.shape_names)))
        check_finite(s, "shape")
        return s

    def rest(self, shape=None) -> tuple[torch.Tensor, torch.Tensor]:
        """Shaped rest vertices ``(B, V, 3)`` and regressed joints ``(B, J, 3)`` (metres)."""
        b = self._shape(shape)
        v = self.v_template + torch.einsum("vcs,bs->bvc", self.shapedirs, b)
        return v, torch.einsum("jv,bvc->bjc", self.J_regressor, v)

    @property
    def rest_vertices(self) -> torch.Tensor:
        """``(V, 3)`` template."""
        return self.v_template

    @property
    def rest_joints(self) -> torch.Tensor:
        """``(J, 3)`` joints of the template."""
        return self.rest()[1][0]

    def pose(self, shape=None, rotations=None, translation=None) -> PosedBody:
        """Posed bodies (see :meth:`draping.body.AnnyBody.pose`; rotations ``(B, J, 3)``)."""
        r, t = pose_inputs(rotations, translation, self.num_bones, self.dtype)
        rv, rj = self.rest(shape)
        n = max(r.shape[0], rv.shape[0])
        if rv.shape[0] not in (1, n) or r.shape[0] not in (1, n):
            raise ValueError(
                f"shape: batch {rv.shape[0]} does not match rotations' batch {r.shape[0]}")
        r, t, rv, rj = expand_batch(n, r, t, rv, rj)
        R = axis_angle_to_matrix(r)
        v = rv
        if self.posedirs is not None:
            eye = torch.eye(3, dtype=R.dtype)
            feat = (R[:, 1:] - eye).reshape(n, -1)  # (B, 9 (J - 1))
            v = rv + torch.einsum("vcp,bp->bvc", self.posedirs, feat)
        transforms, frames = forward_kinematics(R, rj, self.parents, t, self.levels)
        verts = linear_blend_skinning(v, self.skin_weights, self.skin_indices, transforms)
        return PosedBody(verts, transforms, frames[..., :3, 3], rv, rj)
