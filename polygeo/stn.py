"""A rigid spatial transformer refining the PCA frames of surface patches (PolyFit).

:class:`PatchSTN` is a small PointNet-style network (shared per-point MLP, masked max pool,
MLP head) reading canonical patch points (:func:`polygeo.canonical.canonicalize`) and their
k-nearest-neighbour normals, with the PCA axes' arbitrary signs canonicalised, and returning
a unit quaternion ``q`` (a tilt of the height axis) that refines the PCA rotation,
``R = R_pca Q(q)``. It is initialised at the identity and trained
(:func:`polygeo.stn_train.train_stn`) by minimising the height residual of the n-jet fit
after the rotation (:func:`polygeo.canonical.height_residual`, thesis §5.5.1).

This module holds the network, its inference (:func:`stn_rotations`) and its weights files
(:func:`save_weights`, :func:`load_pretrained`). Weights of the network trained by
``polygeo train-stn`` ship in ``polygeo/data`` (:func:`pretrained_path`); weights files are
read without executing code (``torch.load(weights_only=True)``, :mod:`polygeo.runs`).

Units: canonical coordinates are dimensionless (unit ball).
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
from torch import nn

from . import runs
from .checks import check_choice
from .frames import pca_frames, quaternion_to_matrix

__all__ = [
    "PatchSTN",
    "stn_rotations",
    "load_pretrained",
    "pretrained_path",
    "save_weights",
    "knn_normals",
    "WEIGHTS_FILE",
]

_DATA = Path(__file__).resolve().parent / "data"
#: Name of the shipped weights file inside ``polygeo/data``.
WEIGHTS_FILE = "stn_weights.pt"


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


_PRETRAINED: dict[str, PatchSTN] = {}


def _legacy_weights(path: str) -> dict | None:
    """A weights file of the first layout (a bare ``torch.save`` of plain data), or None."""
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)  # plain data only
    except Exception:
        return None
    if isinstance(blob, dict) and "state_dict" in blob and "config" in blob:
        return blob
    return None


def _read_weights(path: str) -> tuple[dict, dict]:
    """``(config, state_dict)`` of a weights file or training checkpoint, read safely."""
    try:
        tensors, meta = runs.load_checkpoint(path)
    except runs.CheckpointError as exc:
        blob = _legacy_weights(path)  # the shipped file predates polygeo.runs
        if blob is None:
            raise ValueError(f"path: {path!r} does not hold STN weights ({exc})") from exc
        return blob["config"], blob["state_dict"]
    cfg, sd = meta.get("config"), tensors.get("state_dict")
    if not isinstance(cfg, dict) or not isinstance(sd, dict):
        raise ValueError(f"path: {path!r} does not hold STN weights (config + state_dict)")
    return cfg, sd


def load_pretrained(path: str | os.PathLike | None = None) -> PatchSTN:
    """Load a trained :class:`PatchSTN` (default: the weights shipped with the package).

    Parameters
    ----------
    path : str or os.PathLike, optional
        A weights file written by :func:`save_weights` or a training checkpoint of
        :func:`polygeo.stn_train.train_stn`. Default: :func:`pretrained_path`. Files are read
        without executing code; a file carrying pickled objects is refused.

    Returns
    -------
    PatchSTN
        In eval mode, float32, gradients disabled; the default one is cached.

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    ValueError
        If the file does not hold STN weights, or carries pickled objects.
    """
    key = str(pretrained_path() if path is None else Path(path))
    if path is None and key in _PRETRAINED:
        return _PRETRAINED[key]
    if not Path(key).is_file():
        raise FileNotFoundError(f"path: no STN weights at {key!r} (run `polygeo train-stn`)")
    cfg, state = _read_weights(key)
    net = PatchSTN(  # weights written before the options existed: the original network
        tuple(cfg["widths"]),
        tuple(cfg["head"]),
        features=cfg.get("features", "xyz"),
        output=cfg.get("output", "quaternion"),
        canonical_signs=cfg.get("canonical_signs", False),
        k=cfg.get("k", 10),
        context=cfg.get("context", False),
    )
    sd = {k: v.float() for k, v in state.items()}
    net.load_state_dict(sd)
    net.eval()
    for prm in net.parameters():
        prm.requires_grad_(False)
    if path is None:
        _PRETRAINED[key] = net
    return net


def save_weights(model: PatchSTN, path: str | os.PathLike, *, meta: dict | None = None) -> Path:
    """Write a small weights file (float32 state dict + config + metadata) atomically.

    The file is a :func:`polygeo.runs.save_checkpoint` checkpoint: tensors
    ``{"state_dict"}``, metadata ``{"config": model.config(), "meta": meta}``.

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

    Raises
    ------
    TypeError
        If ``meta`` is not JSON-able.
    """
    sd = {k: v.detach().float().clone() for k, v in model.state_dict().items()}
    return runs.save_checkpoint(path, {"state_dict": sd},
                                {"config": model.config(), "meta": dict(meta or {})})


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
