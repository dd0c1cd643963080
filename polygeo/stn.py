"""Canonical frames of surface patches: PCA, a rigid spatial transformer, test-time refinement.

PolyFit (thesis §5.2) represents a patch as ``p = s R phi(u, v) + T`` with
``phi(u, v) = (u, v, z(u, v))`` an n-jet height graph. The frame ``(s, R, T)`` decides whether
the patch is a good height graph: a tilted frame folds the patch over the uv plane (several
heights above one uv) and the jet residual grows. This module computes that frame in three
ways, all batched over patches (padded ``(B, P, 3)`` with a mask):

* :func:`canonicalize`: centroid, PCA rotation (``e3`` = smallest-variance direction) and the
  scale ``s`` = largest distance of a point from the centroid, so that canonical points lie
  in the unit ball;
* :class:`PatchSTN`: a small PointNet-style network (shared per-point MLP, masked max pool,
  MLP head) reading the canonical points and their k-nearest-neighbour normals, with the
  PCA axes' arbitrary signs canonicalised, and returning a unit quaternion ``q`` (a tilt of
  the height axis) that refines the PCA rotation, ``R = R_pca Q(q)``; initialised at the
  identity and trained (:func:`train_stn`) by minimising the height residual of the n-jet
  fit after the rotation, differentiably through the least-squares solve (thesis §5.5.1);
* :func:`optimize_rotations`: per-patch test-time refinement of the same rotation by Adam
  steps on the same residual (no learning), keeping each patch's best iterate, so that it
  never ends worse than where it started.

Weights of the network trained by ``polygeo train-stn`` ship in ``polygeo/data``
(:func:`load_pretrained`).

Units: canonical coordinates are dimensionless (unit ball); a residual times the patch scale
``s`` is a length in the input's units.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import nn

from . import jets
from .checks import as_tensor, check_finite, check_int, check_positive, check_shape
from .frames import (
    Orientation,
    axis_angle_to_matrix,
    pca_frames,
    quaternion_to_matrix,
    random_rotation,
)

__all__ = [
    "Canonical",
    "canonicalize",
    "height_residual",
    "PatchSTN",
    "stn_rotations",
    "load_pretrained",
    "pretrained_path",
    "optimize_rotations",
    "OptimizeResult",
    "TrainConfig",
    "train_stn",
    "training_batch",
    "mesh_patch_pool",
    "save_weights",
    "knn_normals",
]

_DATA = Path(__file__).resolve().parent / "data"
#: Name of the shipped weights file inside ``polygeo/data``.
WEIGHTS_FILE = "stn_weights.pt"


# --------------------------------------------------------------------------------------------
# PCA canonicalisation and the residual
# --------------------------------------------------------------------------------------------


class Canonical(NamedTuple):
    """Canonical (PCA) coordinates of padded patches.

    Attributes
    ----------
    local : torch.Tensor
        ``(B, P, 3)`` points in the frame, ``R^T (p - T) / s`` (zero at padded entries).
    orientation : polygeo.frames.Orientation
        ``(s, R, T)`` per patch: ``s`` (B,) the largest distance of a valid point from the
        centroid (1 for a patch with a single distinct point), ``R`` (B, 3, 3) the PCA
        rotation (columns e1, e2, normal), ``T`` (B, 3) the centroid.
    mask : torch.Tensor
        ``(B, P)`` bool, valid entries.
    """

    local: torch.Tensor
    orientation: Orientation
    mask: torch.Tensor


def _points_mask(points: Any, mask: Any, name: str = "points") -> tuple[torch.Tensor, torch.Tensor]:
    p = as_tensor(points, name)
    check_shape(p, name, ("B", "P", 3))
    if mask is None:
        m = torch.ones(p.shape[:2], dtype=torch.bool)
    else:
        m = as_tensor(mask, "mask", floating=False)
        if m.dtype != torch.bool:
            raise TypeError(f"mask: expected a bool array, got dtype {m.dtype}")
        check_shape(m, "mask", tuple(p.shape[:2]))
    if bool(m.any()):
        check_finite(p[m], name)
    return p, m


def canonicalize(points: Any, mask: Any = None, *, reference_normal: Any = None) -> Canonical:
    """PCA frame, centroid and unit-ball scale of each padded patch.

    Parameters
    ----------
    points : array_like or torch.Tensor
        ``(B, P, 3)`` patch points (length units), padded.
    mask : array_like or torch.Tensor, optional
        ``(B, P)`` bool, True for valid points (default: all valid).
    reference_normal : array_like or torch.Tensor, optional
        ``(B, 3)`` directions; the PCA normal is flipped (with ``e2``) to agree with them
        (e.g. the mean input normal of the patch), so that fitted normals keep the input's
        orientation.

    Returns
    -------
    Canonical
        Torch tensors in the points' floating dtype. Differentiable w.r.t. ``points``.

    Raises
    ------
    ValueError
        On bad shapes or non-finite valid points.
    TypeError
        On non-numeric points or a non-bool mask.
    """
    p, m = _points_mask(points, mask)
    return _canonicalize(p, m, reference_normal)


def _canonicalize(p: torch.Tensor, m: torch.Tensor, reference_normal: Any = None) -> Canonical:
    """:func:`canonicalize` without input validation (for already checked tensors)."""
    fr = pca_frames(p, mask=m, reference_normal=reference_normal)
    T, R = fr.centroid, fr.rotation
    d = torch.where(m[..., None], p - T[:, None, :], torch.zeros_like(p))
    r = d.norm(dim=-1).masked_fill(~m, 0.0).amax(-1) if p.shape[1] else p.new_zeros(p.shape[0])
    s = torch.where(r > 0, r, torch.ones_like(r))
    local = (d @ R) / s[:, None, None]
    local = torch.where(m[..., None], local, torch.zeros_like(local))
    return Canonical(local, Orientation(s, R, T), m)


def height_residual(
    local: torch.Tensor,
    mask: torch.Tensor,
    rotation: torch.Tensor | None,
    order: int,
    *,
    method: str = "envelope",
) -> tuple[torch.Tensor, jets.JetFit]:
    """RMS height residual of the n-jet fit after rotating canonical points.

    The rotated points are ``y = Q^T x`` (``Q`` = ``rotation``, the refined frame's axes in
    the canonical frame); the jet ``z(u, v)`` is fitted to ``(y_1, y_2) -> y_3`` by least
    squares and the residual is ``sqrt(mean_i (y_3,i - z(y_1,i, y_2,i))^2)`` over the valid
    points.

    Parameters
    ----------
    local : torch.Tensor
        ``(B, P, 3)`` canonical points (unit ball).
    mask : torch.Tensor
        ``(B, P)`` bool.
    rotation : torch.Tensor or None
        ``(B, 3, 3)`` refinement rotations (None: identity).
    order : int
        Jet order in ``[1, 6]``.
    method : {"envelope", "exact"}
        How the gradient reaches ``local`` and ``rotation``. ``"exact"`` differentiates
        through the least-squares solve (:func:`polygeo.jets.fit`, torch backend).
        ``"envelope"`` (default, several times cheaper) solves without a graph and
        differentiates ``|y_3 - A(y_1, y_2) c|`` with the optimal ``c`` held fixed: by the
        envelope theorem this is the same gradient wherever the fit is well posed (the
        derivative of a minimum w.r.t. a parameter is the partial derivative at the
        minimiser).

    Returns
    -------
    residual : torch.Tensor
        ``(B,)`` float64 RMS height residual in canonical units, differentiable w.r.t.
        ``local`` and ``rotation``.
    fit : polygeo.jets.JetFit
        The fit, in the rotated frame.

    Raises
    ------
    ValueError
        On a bad ``method`` or ``order``.
    """
    if method not in ("envelope", "exact"):
        raise ValueError(f"method: expected one of ['envelope', 'exact'], got {method!r}")
    y = local if rotation is None else local @ rotation.to(local.dtype)
    if method == "exact":
        f = jets.fit(y[..., :2], y[..., 2], order, mask=mask, backend="torch")
        return f.residual, f
    with torch.no_grad():
        f = jets.fit(y[..., :2].detach(), y[..., 2].detach(), order, mask=mask)
    y64 = y.to(torch.float64)
    uv = torch.where(mask[..., None], y64[..., :2], torch.zeros_like(y64[..., :2]))
    pred = (jets.monomials(uv, order) * f.coeffs.to(torch.float64)[:, None, :]).sum(-1)
    r = torch.where(mask, y64[..., 2] - pred, torch.zeros_like(pred))
    n = mask.sum(-1).clamp_min(1).to(torch.float64)
    ms = (r * r).sum(-1) / n
    safe = torch.where(ms > 0, ms, torch.ones_like(ms))
    return torch.where(ms > 0, safe.sqrt(), torch.zeros_like(ms)), f


# --------------------------------------------------------------------------------------------
# The network
# --------------------------------------------------------------------------------------------


STN_FEATURES = ("xyz", "normals")
STN_OUTPUTS = ("quaternion", "tilt")


def knn_normals(local: torch.Tensor, mask: torch.Tensor | None = None, k: int = 10) -> torch.Tensor:
    """Unoriented local normals of padded point sets, by PCA of each point's k nearest points.

    Parameters
    ----------
    local : torch.Tensor
        ``(B, P, 3)`` points (any floating dtype).
    mask : torch.Tensor, optional
        ``(B, P)`` bool valid points; padded points are never neighbours.
    k : int
        Neighbours per point, the point itself included (fewer where a patch has fewer
        valid points).

    Returns
    -------
    torch.Tensor
        ``(B, P, 3)`` unit normals (smallest-variance direction of the neighbourhood) in
        ``local``'s dtype, signed so that their third component is non-negative; zero at
        padded entries. No gradient.
    """
    B, P, _ = local.shape
    if mask is None:
        mask = torch.ones(B, P, dtype=torch.bool, device=local.device)
    if P == 0 or B == 0:
        return torch.zeros_like(local)
    kk = max(1, min(int(k), P))
    with torch.no_grad():
        x = local.detach()
        d = torch.cdist(x, x).masked_fill(~mask[:, None, :], torch.inf)
        dist, idx = d.topk(kk, dim=-1, largest=False)  # (B, P, k)
        valid = torch.isfinite(dist)  # (B, P, k) valid neighbours
        nb = x[torch.arange(B, device=x.device)[:, None, None], idx]  # (B, P, k, 3)
        frame = pca_frames(nb.reshape(B * P, kk, 3), mask=valid.reshape(B * P, kk))
        n = frame.rotation[..., 2].reshape(B, P, 3).to(x.dtype)
        n = torch.where(n[..., 2:3] < 0, -n, n)
        return torch.where(mask[..., None], n, torch.zeros_like(n))


def _axis_signs(local: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Per-patch axis signs ``(B, 3)`` making each coordinate's third moment non-negative."""
    m3 = torch.where(mask[..., None], local**3, torch.zeros_like(local)).sum(1)
    return torch.where(m3 < 0, -torch.ones_like(m3), torch.ones_like(m3))


def _masked_max(h: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Max over valid points ``(B, P, C) -> (B, C)`` (zero for a patch without points)."""
    g = h.masked_fill(~mask[..., None], -torch.inf).amax(1)
    return torch.where(torch.isfinite(g), g, torch.zeros_like(g))


class PatchSTN(nn.Module):
    """PointNet-style rigid spatial transformer: canonical patch points -> unit quaternion.

    A shared per-point MLP ``C -> widths`` (ReLU), a masked max pool over the points and an
    MLP head ``-> head -> out``. The last layer starts at zero weight (and bias
    ``(1, 0, 0, 0)`` for quaternions) so that an untrained network returns the identity.

    Per-point input (``features``): ``"xyz"`` the canonical coordinates (C = 3), or
    ``"normals"`` the coordinates and the unoriented k-nearest-neighbour normals
    (:func:`knn_normals`, C = 6), which show where the PCA plane cuts across a fold.

    Output (``output``): ``"quaternion"`` a free unit quaternion, or ``"tilt"`` a rotation
    vector ``(w_x, w_y, 0)``: only the direction of the new height axis matters (jets of
    order n are closed under rotations of the uv plane, so a spin about the normal leaves
    the height residual unchanged), so the network predicts just that tilt.

    With ``canonical_signs`` the network first flips each canonical axis so that the third
    moment of the coordinate is non-negative (the PCA axes' signs are arbitrary) and maps its
    output back (``w -> det(D) D w`` for the sign matrix ``D``). The height residual is
    invariant under such flips, so the network need not learn the eight sign variants.

    Parameters
    ----------
    widths : tuple of int
        Widths of the shared per-point layers.
    head : tuple of int
        Widths of the hidden head layers.
    features : {"xyz", "normals"}
        Per-point input.
    output : {"quaternion", "tilt"}
        Rotation parametrisation.
    canonical_signs : bool
        Canonicalise the axis signs by third moments.
    k : int
        Neighbours of the normals.
    context : bool
        Two-stage PointNet: the last shared layer reads each point's features together with
        the max-pooled features of the previous layers (global context).
    """

    def __init__(
        self,
        widths: tuple[int, ...] = (32, 64, 128),
        head: tuple[int, ...] = (64, 32),
        *,
        features: str = "normals",
        output: str = "tilt",
        canonical_signs: bool = True,
        k: int = 10,
        context: bool = False,
    ):
        super().__init__()
        from .checks import check_choice

        self.features = check_choice(features, "features", STN_FEATURES)
        self.output = check_choice(output, "output", STN_OUTPUTS)
        self.canonical_signs = bool(canonical_signs)
        self.k = int(k)
        self.context = bool(context) and len(widths) >= 2
        self.widths = tuple(int(w) for w in widths)
        self.head_widths = tuple(int(w) for w in head)
        layers: list[nn.Module] = []
        c = 3 if self.features == "xyz" else 6
        first = self.widths[:-1] if self.context else self.widths
        for w in first:
            layers += [nn.Linear(c, w), nn.ReLU()]
            c = w
        self.point_mlp = nn.Sequential(*layers)
        if self.context:  # last shared layer sees each point and the pooled first stage
            self.context_mlp = nn.Sequential(nn.Linear(2 * c, self.widths[-1]), nn.ReLU())
            c = self.widths[-1]
        hl: list[nn.Module] = []
        for w in self.head_widths:
            hl += [nn.Linear(c, w), nn.ReLU()]
            c = w
        self.head = nn.Sequential(*hl)
        self.out = nn.Linear(c, 4 if self.output == "quaternion" else 2)
        with torch.no_grad():
            self.out.weight.zero_()
            self.out.bias.zero_()
            if self.output == "quaternion":
                self.out.bias[0] = 1.0

    def point_features(self, local: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """Per-point input ``(B, P, C)`` of canonical points (no gradient through normals).

        Parameters
        ----------
        local : torch.Tensor
            ``(B, P, 3)`` canonical points.
        mask : torch.Tensor, optional
            ``(B, P)`` bool valid points.

        Returns
        -------
        torch.Tensor
            ``(B, P, 3)`` or ``(B, P, 6)`` in ``local``'s dtype.
        """
        if self.features == "xyz":
            return local
        return torch.cat([local, knn_normals(local, mask, self.k)], -1)

    def forward(
        self,
        local: torch.Tensor,
        mask: torch.Tensor | None = None,
        features: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Quaternions ``(w, x, y, z)``, unit, ``(B, 4)``, for canonical points ``(B, P, 3)``.

        Parameters
        ----------
        local : torch.Tensor
            ``(B, P, 3)`` canonical points (unit ball), the network's dtype.
        mask : torch.Tensor, optional
            ``(B, P)`` bool valid points (padded entries do not enter the max pool).
        features : torch.Tensor, optional
            Precomputed :meth:`point_features` of ``local`` (training caches them).

        Returns
        -------
        torch.Tensor
            ``(B, 4)`` unit quaternions (the refinement rotation of the PCA frame).
        """
        if mask is None:
            mask = torch.ones(local.shape[:2], dtype=torch.bool, device=local.device)
        feat = self.point_features(local, mask) if features is None else features
        feat = feat.to(self.out.weight.dtype)
        if self.canonical_signs:
            sg = _axis_signs(local.detach(), mask).to(feat.dtype)  # (B, 3)
            flip = sg.repeat(1, feat.shape[-1] // 3)[:, None, :]
            feat = feat * flip
            if self.features == "normals":  # normals stay unoriented: n_z >= 0
                n = feat[..., 3:]
                feat = torch.cat([feat[..., :3], torch.where(n[..., 2:3] < 0, -n, n)], -1)
        h = self.point_mlp(feat)  # (B, P, C)
        if self.context:
            g = _masked_max(h, mask)
            h = self.context_mlp(torch.cat([h, g[:, None, :].expand_as(h)], -1))
        g = _masked_max(h, mask)  # (B, C)
        o = self.out(self.head(g))
        if self.output == "quaternion":
            q = o / o.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            if self.canonical_signs:  # conjugation by D: vector part -> det(D) D v
                q = torch.cat([q[:, :1], sg.prod(-1, keepdim=True) * sg * q[:, 1:]], -1)
            return q
        w = torch.cat([o, torch.zeros_like(o[:, :1])], -1)
        if self.canonical_signs:
            w = sg.prod(-1, keepdim=True) * sg * w
        ang = w.norm(dim=-1, keepdim=True)
        half = 0.5 * ang
        # sin(a/2)/a, smooth at a = 0
        s = torch.where(ang > 1e-6, torch.sin(half) / ang.clamp_min(1e-6), 0.5 - ang**2 / 48)
        return torch.cat([torch.cos(half), s * w], -1)

    def config(self) -> dict:
        """Constructor arguments (stored with the weights)."""
        return {
            "widths": list(self.widths),
            "head": list(self.head_widths),
            "features": self.features,
            "output": self.output,
            "canonical_signs": self.canonical_signs,
            "k": self.k,
            "context": self.context,
        }


def pretrained_path() -> Path:
    """Path of the shipped weights (``polygeo/data/stn_weights.pt``)."""
    return _DATA / WEIGHTS_FILE


_PRETRAINED: dict[str, PatchSTN] = {}


def load_pretrained(path: str | os.PathLike | None = None) -> PatchSTN:
    """Load a trained :class:`PatchSTN` (default: the weights shipped with the package).

    Parameters
    ----------
    path : str or os.PathLike, optional
        A weights file written by :func:`train_stn` (``{"config", "state_dict", ...}``) or a
        training checkpoint. Default: :func:`pretrained_path`.

    Returns
    -------
    PatchSTN
        In eval mode, float32, gradients disabled; the default one is cached.

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    ValueError
        If the file does not hold STN weights.
    """
    key = str(pretrained_path() if path is None else Path(path))
    if path is None and key in _PRETRAINED:
        return _PRETRAINED[key]
    if not Path(key).is_file():
        raise FileNotFoundError(f"path: no STN weights at {key!r} (run `polygeo train-stn`)")
    blob = torch.load(key, map_location="cpu", weights_only=True)
    if not isinstance(blob, dict) or "state_dict" not in blob or "config" not in blob:
        raise ValueError(f"path: {key!r} does not hold STN weights (config + state_dict)")
    cfg = blob["config"]
    net = PatchSTN(  # weights written before the options existed: the original network
        tuple(cfg["widths"]),
        tuple(cfg["head"]),
        features=cfg.get("features", "xyz"),
        output=cfg.get("output", "quaternion"),
        canonical_signs=cfg.get("canonical_signs", False),
        k=cfg.get("k", 10),
        context=cfg.get("context", False),
    )
    sd = {k: v.float() for k, v in blob["state_dict"].items()}
    net.load_state_dict(sd)
    net.eval()
    for prm in net.parameters():
        prm.requires_grad_(False)
    if path is None:
        _PRETRAINED[key] = net
    return net


def stn_rotations(
    local: torch.Tensor,
    mask: torch.Tensor,
    model: PatchSTN | None = None,
    *,
    chunk: int = 4096,
) -> torch.Tensor:
    """Refinement rotations predicted by the STN for canonical patches.

    Parameters
    ----------
    local : torch.Tensor
        ``(B, P, 3)`` canonical points (:func:`canonicalize`).
    mask : torch.Tensor
        ``(B, P)`` bool.
    model : PatchSTN, optional
        Default: :func:`load_pretrained`.
    chunk : int
        Patches per forward pass (bounds memory).

    Returns
    -------
    torch.Tensor
        ``(B, 3, 3)`` rotations in ``local``'s dtype (no gradient).
    """
    net = load_pretrained() if model is None else model
    dt = next(net.parameters()).dtype
    out = []
    # bound the (chunk, P, P) neighbour distances of the normal features
    chunk = max(1, min(int(chunk), 2**25 // max(local.shape[1] ** 2, 1)))
    with torch.no_grad():
        for i in range(0, local.shape[0], chunk):
            q = net(local[i : i + chunk].to(dt), mask[i : i + chunk])
            out.append(quaternion_to_matrix(q.to(local.dtype)))
    if not out:
        return local.new_zeros(0, 3, 3)
    return torch.cat(out)


# --------------------------------------------------------------------------------------------
# Test-time refinement
# --------------------------------------------------------------------------------------------


class OptimizeResult(NamedTuple):
    """Result of :func:`optimize_rotations`.

    Attributes
    ----------
    rotation : torch.Tensor
        ``(B, 3, 3)`` best refinement rotation found per patch.
    residual : torch.Tensor
        ``(B,)`` its RMS height residual (canonical units).
    initial_residual : torch.Tensor
        ``(B,)`` residual of the starting rotation.
    """

    rotation: torch.Tensor
    residual: torch.Tensor
    initial_residual: torch.Tensor


def optimize_rotations(
    local: torch.Tensor,
    mask: torch.Tensor,
    order: int = 4,
    *,
    init: torch.Tensor | None = None,
    steps: int = 40,
    lr: float = 0.05,
    max_angle: float = math.pi / 3,
) -> OptimizeResult:
    """Refine each patch's rotation by Adam steps on its jet height residual.

    The rotation is ``Q = Q0 exp([w]_x)`` with ``w`` (B, 3) an axis-angle correction
    starting at zero and ``Q0`` the starting rotation (``init``, default identity). All
    patches move together (their losses are independent; Adam's per-coordinate step makes
    the batch behave like B separate optimisations); each patch keeps its best iterate, so
    its residual never ends above the starting one. Corrections are limited to ``max_angle``
    (the residual alone would reward turning a patch edge-on, where it stops being a
    surface over the uv plane).

    Parameters
    ----------
    local : torch.Tensor
        ``(B, P, 3)`` canonical points.
    mask : torch.Tensor
        ``(B, P)`` bool.
    order : int
        Jet order of the residual.
    init : torch.Tensor, optional
        ``(B, 3, 3)`` starting rotations (e.g. the STN's).
    steps : int
        Adam steps (0 returns the start).
    lr : float
        Adam learning rate (radians per step, roughly).
    max_angle : float
        Largest correction angle in radians.

    Returns
    -------
    OptimizeResult
        Rotations and residuals (no gradient).

    Raises
    ------
    ValueError
        On a negative step count or non-positive rates.
    """
    steps = check_int(steps, "steps", low=0)
    lr = check_positive(lr, "lr")
    max_angle = check_positive(max_angle, "max_angle")
    B = local.shape[0]
    x = local.detach().to(torch.float64)
    Q0 = (
        torch.eye(3, dtype=torch.float64).expand(B, 3, 3)
        if init is None
        else init.detach().to(torch.float64)
    )
    with torch.no_grad():
        r0, _ = height_residual(x, mask, Q0, order)
    best_r = r0.clone()
    best_Q = Q0.clone()
    if steps == 0 or B == 0:
        return OptimizeResult(best_Q.to(local.dtype), best_r, r0)
    w = torch.zeros(B, 3, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([w], lr=lr)
    for _ in range(steps):
        opt.zero_grad()
        ang = w.norm(dim=-1, keepdim=True)
        wc = torch.where(ang > max_angle, w * (max_angle / ang.clamp_min(1e-12)), w)
        Q = Q0 @ axis_angle_to_matrix(wc)
        r, _ = height_residual(x, mask, Q, order)
        with torch.no_grad():
            better = r < best_r
            best_r = torch.where(better, r, best_r)
            best_Q = torch.where(better[:, None, None], Q, best_Q)
        (r * r).sum().backward()
        opt.step()
    with torch.no_grad():
        ang = w.norm(dim=-1, keepdim=True)
        wc = torch.where(ang > max_angle, w * (max_angle / ang.clamp_min(1e-12)), w)
        Q = Q0 @ axis_angle_to_matrix(wc)
        r, _ = height_residual(x, mask, Q, order)
        better = r < best_r
        best_r = torch.where(better, r, best_r)
        best_Q = torch.where(better[:, None, None], Q, best_Q)
    return OptimizeResult(best_Q.to(local.dtype), best_r, r0)


# --------------------------------------------------------------------------------------------
# Training
# --------------------------------------------------------------------------------------------


@dataclass
class TrainConfig:
    """Settings of :func:`train_stn`.

    The defaults are those of the shipped weights (``polygeo/data/stn_weights.json`` records
    the CPU and wall time of that run). Training runs on one thread: on a shared two-core
    machine a second intra-op thread mostly spin-waits (measured: about six times the CPU
    seconds per step of a single thread).

    Attributes
    ----------
    steps : int
        Largest number of optimisation steps.
    batch_size : int
        Patches per step (thesis: 512).
    n_points : int
        Points per training patch.
    lr : float
        Adam learning rate (thesis: 1e-3), cosine-decayed to ``lr / 20`` over ``steps``.
    order : int
        Jet order of the residual (thesis: 4).
    mesh_share : float
        Share of the training patches cut from garment-like meshes (the rest are sums of the
        four synthetic families of §5.5.1).
    grid_share : float
        Share of the synthetic patches sampled on a jittered grid rather than irregularly
        (the grid patches of the tests and benchmark, many of which PCA folds over).
    noise : float
        Largest standard deviation of the positional noise of synthetic patches (canonical
        units, the patch spans [-1, 1]).
    widths, head : tuple of int
        Network size (:class:`PatchSTN`).
    features, output : str
        Input and rotation parametrisation of :class:`PatchSTN`.
    canonical_signs, context : bool
        Third-moment sign canonicalisation and global context of :class:`PatchSTN`.
    seed : int
        Seed of the network initialisation, the cached training set and every batch (batch
        ``i`` is drawn from ``(seed, i)``, so that a resumed run sees the same data).
    n_train : int
        Cached training patches, drawn once (the batches draw from them).
    n_val : int
        Held-out validation patches (other seeds, other meshes), for model selection and early
        stopping.
    eval_every : int
        Validation period in steps.
    checkpoint_every : int
        Checkpoint period in steps.
    patience : int
        Stop after this many validations without a better held-out residual (0: never);
        the best validated weights are returned.
    threads : int
        Torch intra-op threads during training (0: leave as is).
    mesh_seeds, val_mesh_seeds : tuple of int
        Seeds of the garment-like meshes of :func:`mesh_patch_pool` for training and for
        validation.
    """

    steps: int = 2000
    batch_size: int = 256
    n_points: int = 128
    lr: float = 2e-3
    order: int = 4
    mesh_share: float = 0.3
    grid_share: float = 0.2
    noise: float = 0.02
    widths: tuple[int, ...] = (32, 64, 128)
    head: tuple[int, ...] = (64, 32)
    features: str = "normals"
    output: str = "tilt"
    canonical_signs: bool = True
    context: bool = False
    seed: int = 0
    n_train: int = 16384
    n_val: int = 1024
    eval_every: int = 100
    checkpoint_every: int = 100
    patience: int = 5
    threads: int = 1
    mesh_seeds: tuple[int, ...] = field(default=(0, 1, 2, 3))
    val_mesh_seeds: tuple[int, ...] = field(default=(50,))


def _pad_patch(pts: np.ndarray, n_points: int, rng: np.random.Generator) -> tuple:
    """Subsample (or pad with a mask) one patch to ``n_points`` points."""
    out = np.zeros((n_points, 3))
    m = np.zeros(n_points, bool)
    if len(pts) >= n_points:
        sel = rng.choice(len(pts), n_points, replace=False)
        out[:] = pts[sel]
        m[:] = True
    else:
        out[: len(pts)] = pts
        m[: len(pts)] = True
    return out, m


def mesh_patch_pool(seeds: tuple[int, ...] = (0,), *, min_points: int = 20) -> list[np.ndarray]:
    """Patches of procedural garment-like meshes, partitioned with the default K.

    For each seed: a draped sheet, a skirt and a body-like closed surface (the latter only
    for seeds 0 and 100, where its shape does not depend on the seed), each partitioned by
    :func:`polygeo.partition.partition_mesh` with the thesis' default patch count.

    Parameters
    ----------
    seeds : tuple of int
        Mesh seeds (fold phases and depths, sheet and skirt sizes).
    min_points : int
        Patches with fewer vertices are dropped.

    Returns
    -------
    list of np.ndarray
        One ``(n_k, 3)`` float64 array of vertex positions per patch (metres).
    """
    from . import synthetic
    from .partition import partition_mesh

    pool: list[np.ndarray] = []
    for sd in seeds:
        rng = np.random.default_rng([sd, 7])
        meshes = [
            synthetic.draped_sheet_mesh(
                110,
                size=float(rng.uniform(0.8, 1.3)),
                n_folds=int(rng.integers(3, 7)),
                fold_depth=float(rng.uniform(0.02, 0.08)),
                seed=sd,
            ),
            synthetic.skirt_mesh(
                180,
                90,
                hem=float(rng.uniform(0.28, 0.42)),
                n_folds=int(rng.integers(6, 12)),
                fold_depth=float(rng.uniform(0.015, 0.05)),
                seed=sd,
            ),
        ]
        if sd in (0, 100):
            meshes.append(synthetic.body_mesh(5))
        for v, f in meshes:
            part = partition_mesh(v, f, seed=sd)
            order = np.argsort(part.labels, kind="stable")
            bounds = np.cumsum(np.bincount(part.labels, minlength=part.n_patches))[:-1]
            for idx in np.split(order, bounds):
                if len(idx) >= min_points:
                    pool.append(v[idx])
    return pool


def _grid_family_points(
    n: int, n_points: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Family sums on jittered m x m grids of [-1, 1]^2, randomly rotated.

    ``m`` is drawn in ``[m_max - 4, m_max]`` with ``m_max = floor(sqrt(n_points))``; the
    ``m^2`` points come first, the rest is padding. Returns points ``(n, n_points, 3)`` and
    the mask ``(n, n_points)``.
    """
    from . import synthetic

    m_hi = max(4, math.isqrt(n_points))
    par = synthetic._family_params(rng, n, synthetic.PATCH_FAMILIES, 0.5)
    ms = rng.integers(max(2, m_hi - 4), m_hi + 1, n)
    uv = np.zeros((n, n_points, 2))
    msk = np.zeros((n, n_points), bool)
    for i, m in enumerate(ms):
        t = np.linspace(-1.0, 1.0, int(m))
        g = np.stack(np.meshgrid(t, t, indexing="ij"), -1).reshape(-1, 2)
        g = g + rng.uniform(-0.25, 0.25, g.shape) * (2.0 / (m - 1))
        k = min(len(g), n_points)
        uv[i, :k] = g[:k]
        msk[i, :k] = True
    z, _ = synthetic._family_height_grad(uv, par)
    local = np.concatenate([uv, z[..., None]], -1)
    rot = synthetic._random_rotations_np(rng, n, np.pi)
    pts = np.einsum("bij,bpj->bpi", rot, local)
    return np.where(msk[..., None], pts, 0.0), msk


def training_batch(
    n: int,
    n_points: int,
    rng: np.random.Generator,
    *,
    pool: list[np.ndarray] | None = None,
    mesh_share: float = 0.0,
    grid_share: float = 0.0,
    noise: float = 0.02,
) -> tuple[torch.Tensor, torch.Tensor]:
    """A batch of canonical training patches (synthetic families and mesh patches).

    Parameters
    ----------
    n : int
        Patches.
    n_points : int
        Points per patch (mesh patches are subsampled or padded with the mask).
    rng : numpy.random.Generator
        Randomness.
    pool : list of np.ndarray, optional
        Mesh patches (:func:`mesh_patch_pool`); required when ``mesh_share > 0``.
    mesh_share : float
        Share of mesh patches in the batch.
    grid_share : float
        Share of the synthetic patches sampled on jittered grids (the rest irregularly).
    noise : float
        Largest noise standard deviation of synthetic patches (canonical units).

    Returns
    -------
    local : torch.Tensor
        ``(n, n_points, 3)`` float64 canonical points (:func:`canonicalize`).
    mask : torch.Tensor
        ``(n, n_points)`` bool.
    """
    from . import synthetic

    n_mesh = int(round(n * mesh_share)) if pool else 0
    n_syn = n - n_mesh
    n_grid = int(round(n_syn * grid_share))
    n_irr = n_syn - n_grid
    pts = np.zeros((n, n_points, 3))
    msk = np.zeros((n, n_points), bool)
    if n_irr:
        fp = synthetic.family_patches(n_irr, n_points, noise=0.0, seed=rng)
        pts[:n_irr] = fp.points
        msk[:n_irr] = True
    if n_grid:
        pts[n_irr:n_syn], msk[n_irr:n_syn] = _grid_family_points(n_grid, n_points, rng)
    if n_syn:
        sig = rng.uniform(0.0, noise, (n_syn, 1, 1))
        pts[:n_syn] += sig * rng.normal(size=(n_syn, n_points, 3)) * msk[:n_syn, :, None]
    if n_mesh:
        pick = rng.integers(0, len(pool), n_mesh)
        gen = torch.Generator().manual_seed(int(rng.integers(2**62)))
        rot = random_rotation(n_mesh, gen).to(torch.float64).numpy()
        for i, k in enumerate(pick):
            p, m = _pad_patch(pool[k], n_points, rng)
            pts[n_syn + i] = p @ rot[i].T
            msk[n_syn + i] = m
    c = canonicalize(torch.from_numpy(pts), torch.from_numpy(msk))
    return c.local, c.mask


def _atomic_save(obj: Any, path: Path) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def _cached_set(
    net: PatchSTN, n: int, cfg: TrainConfig, rng: np.random.Generator, pool, chunk: int = 1024
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``n`` canonical patches, their masks and the network's per-point features (float32)."""
    locs, masks, feats = [], [], []
    for i in range(0, n, chunk):
        b = min(chunk, n - i)
        loc, m = training_batch(
            b,
            cfg.n_points,
            rng,
            pool=pool,
            mesh_share=cfg.mesh_share,
            grid_share=cfg.grid_share,
            noise=cfg.noise,
        )
        locs.append(loc)
        masks.append(m)
        feats.append(net.point_features(loc.float(), m).float())
    return torch.cat(locs), torch.cat(masks), torch.cat(feats)


def train_stn(
    config: TrainConfig | None = None,
    *,
    checkpoint_dir: str | os.PathLike | None = None,
    resume: bool = True,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
) -> tuple[PatchSTN, dict]:
    """Train :class:`PatchSTN` on the height residual of n-jet fits (thesis §5.5.1).

    A training set of ``n_train`` patches is drawn once (sums of the four synthetic families,
    randomly rotated, irregularly or grid sampled, noisy; plus patches of garment-like
    meshes), canonicalised by PCA, with the network's per-point features cached. Every step
    draws a batch from it, predicts the refinement rotation, rotates, fits an n-jet and
    minimises the mean RMS height residual with Adam (the gradient of the least-squares
    solve by the envelope theorem, :func:`height_residual`). Every ``eval_every`` steps the
    mean residual on ``n_val`` held-out patches (other seeds, other meshes) is measured; the
    best validated weights are kept and training stops early after ``patience`` validations
    without improvement.

    Parameters
    ----------
    config : TrainConfig, optional
        Settings (default :class:`TrainConfig`).
    checkpoint_dir : str or os.PathLike, optional
        Folder of ``stn_checkpoint.pt`` (written every ``checkpoint_every`` steps, atomically)
        and ``history.json``; with ``resume=True`` an existing checkpoint is continued.
    resume : bool
        Continue from an existing checkpoint of the same configuration.
    progress : bool
        Show a tqdm bar.
    log : callable, optional
        Receives one line per validation.

    Returns
    -------
    model : PatchSTN
        The best validated network (eval mode).
    history : dict
        ``{"config", "val": [{"step", "pca", "stn", "ratio"}...], "loss": [...], "best",
        "stopped_at", "seconds", "cpu_seconds"}``; residuals are mean RMS heights in
        canonical units on the held-out set; ``seconds`` (wall) and ``cpu_seconds`` (this
        process, all threads) include drawing the cached data.

    Raises
    ------
    ValueError
        If a checkpoint was written with another configuration, or on bad settings.
    """
    cfg = TrainConfig() if config is None else config
    check_int(cfg.steps, "steps", low=0)
    check_int(cfg.batch_size, "batch_size", low=1)
    check_int(cfg.n_train, "n_train", low=1)
    check_int(cfg.n_val, "n_val", low=1)
    check_int(cfg.patience, "patience", low=0)
    t0, c0 = time.perf_counter(), time.process_time()
    if cfg.threads:
        torch.set_num_threads(int(cfg.threads))
    torch.manual_seed(cfg.seed)
    net = PatchSTN(
        tuple(cfg.widths),
        tuple(cfg.head),
        features=cfg.features,
        output=cfg.output,
        canonical_signs=cfg.canonical_signs,
        context=cfg.context,
    )
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    n_steps = max(cfg.steps, 1)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda i: 0.05 + 0.475 * (1 + math.cos(math.pi * min(i, n_steps) / n_steps))
    )
    cfg_dict = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(cfg).items()}
    history: dict = {
        "config": cfg_dict,
        "val": [],
        "loss": [],
        "best": None,
        "stopped_at": None,
        "seconds": 0.0,
        "cpu_seconds": 0.0,
    }
    state = {"best_state": None, "since_best": 0}
    start = 0
    ckpt = None
    if checkpoint_dir is not None:
        ckdir = Path(checkpoint_dir)
        ckdir.mkdir(parents=True, exist_ok=True)
        ckpt = ckdir / "stn_checkpoint.pt"
        if resume and ckpt.is_file():
            blob = torch.load(ckpt, map_location="cpu", weights_only=False)
            if blob["history"]["config"] != cfg_dict:
                raise ValueError(
                    f"checkpoint_dir: {str(ckpt)!r} was written with another configuration; "
                    "use another folder or resume=False"
                )
            net.load_state_dict(blob["state_dict"])
            opt.load_state_dict(blob["optimizer"])
            sched.load_state_dict(blob["scheduler"])
            history = blob["history"]
            state = blob["early_stopping"]
            start = int(blob["step"])
    pool = mesh_patch_pool(tuple(cfg.mesh_seeds)) if cfg.mesh_share > 0 else None
    val_pool = mesh_patch_pool(tuple(cfg.val_mesh_seeds)) if cfg.mesh_share > 0 else None
    with torch.no_grad():
        x_loc, x_mask, x_feat = _cached_set(
            net, cfg.n_train, cfg, np.random.default_rng([cfg.seed, 2]), pool
        )
        v_loc, v_mask, v_feat = _cached_set(
            net, cfg.n_val, cfg, np.random.default_rng([cfg.seed, 10**9]), val_pool
        )
        v_pca = float(height_residual(v_loc, v_mask, None, cfg.order)[0].mean())

    def clock() -> None:
        nonlocal t0, c0
        history["seconds"] += time.perf_counter() - t0
        history["cpu_seconds"] += time.process_time() - c0
        t0, c0 = time.perf_counter(), time.process_time()

    def validate(step: int) -> None:
        net.eval()
        with torch.no_grad():
            q = net(v_loc.float(), v_mask, v_feat)
            r = float(height_residual(v_loc, v_mask, quaternion_to_matrix(q.double()),
                                      cfg.order)[0].mean())
        net.train()
        rec = {"step": step, "pca": v_pca, "stn": r, "ratio": r / v_pca}
        history["val"].append(rec)
        if history["best"] is None or r < history["best"]["stn"]:
            history["best"] = rec
            state["best_state"] = {k: v.detach().clone() for k, v in net.state_dict().items()}
            state["since_best"] = 0
        else:
            state["since_best"] += 1
        if log is not None:
            log(
                f"step {step}: held-out height RMS pca {v_pca:.5f} stn {r:.5f} "
                f"(ratio {r / v_pca:.3f}; best {history['best']['ratio']:.3f} at step "
                f"{history['best']['step']})"
            )

    def save(step: int) -> None:
        if ckpt is None:
            return
        clock()
        _atomic_save(
            {
                "state_dict": net.state_dict(),
                "optimizer": opt.state_dict(),
                "scheduler": sched.state_dict(),
                "history": history,
                "early_stopping": state,
                "step": step,
                "config": net.config(),
            },
            ckpt,
        )
        (ckpt.parent / "history.json").write_text(json.dumps(history, indent=1))

    from tqdm.auto import tqdm

    net.train()
    stopped = history["stopped_at"] is not None
    bar = tqdm(
        range(start, cfg.steps),
        initial=start,
        total=cfg.steps,
        disable=not progress or stopped,
        desc="train-stn",
    )
    for step in bar:
        if stopped:
            break
        rng = np.random.default_rng([cfg.seed, step])
        idx = torch.from_numpy(rng.choice(cfg.n_train, min(cfg.batch_size, cfg.n_train),
                                          replace=False))
        local, mask = x_loc[idx], x_mask[idx]
        q = net(local.float(), mask, x_feat[idx])
        r, _ = height_residual(local, mask, quaternion_to_matrix(q.double()), cfg.order)
        loss = r.mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        history["loss"].append(float(loss.detach()))
        bar.set_postfix(loss=f"{float(loss.detach()):.4f}")
        done = step + 1
        if done % cfg.eval_every == 0 or done == cfg.steps:
            validate(done)
            if cfg.patience and state["since_best"] >= cfg.patience:
                history["stopped_at"] = done
                stopped = True
        if stopped or done % cfg.checkpoint_every == 0 or done == cfg.steps:
            save(done)
    bar.close()
    if not history["val"]:
        validate(start)
    clock()
    if state["best_state"] is not None:
        net.load_state_dict(state["best_state"])
    net.eval()
    return net, history


def save_weights(model: PatchSTN, path: str | os.PathLike, *, meta: dict | None = None) -> Path:
    """Write a small weights file (float32 state dict + config + metadata) atomically.

    Parameters
    ----------
    model : PatchSTN
        The network.
    path : str or os.PathLike
        Destination (``.pt``).
    meta : dict, optional
        JSON-able metadata (training settings, validation figures).

    Returns
    -------
    pathlib.Path
        The path written.
    """
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    sd = {k: v.detach().float().clone() for k, v in model.state_dict().items()}
    _atomic_save({"config": model.config(), "state_dict": sd, "meta": meta or {}}, p)
    return p
