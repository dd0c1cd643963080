"""The GAPS regressor: a GRU from shape, pose and root velocity to garment displacements.

Part of :mod:`draping.gaps`; import from there. Thesis eq. (37):
``M_t = T(beta) + R(Phi_t, beta)`` (unposed, deformed garment) and
``M~_t = S(M_t, J(beta), theta_t, W~)`` (linear blend skinning with the garment's weights).
"""

from __future__ import annotations

import torch
from torch import nn

from draping.body import linear_blend_skinning
from polygeo.checks import as_tensor, check_finite, check_shape
from polygeo.frames import axis_angle_to_matrix

from .settings import POSE_BONES, GapsSettings

__all__ = ["GapsModel", "pose_features", "feature_size", "top_weights"]


def feature_size(n_bones: int = len(POSE_BONES)) -> int:
    """Input size of the GRU.

    6D rotations of the bones, up and velocity in the root frame, six phenotypes.
    """
    return 6 * n_bones + 3 + 3 + 6


def pose_features(
    rotations: torch.Tensor,
    velocity: torch.Tensor,
    shape: torch.Tensor,
    bones: torch.Tensor,
    up: torch.Tensor,
) -> torch.Tensor:
    """Per-frame inputs of the regressor (``Phi_t`` and ``beta``).

    Parameters
    ----------
    rotations : (..., T, J, 3) float tensor
        Axis-angle rotations of every body bone (radians); bone 0 is the root.
    velocity : (..., T, 3) float tensor
        Root velocity in the world frame (m/s).
    shape : (..., 6) float tensor
        Phenotypes in ``[0, 1]``.
    bones : (P,) int64 tensor
        The bones read (:data:`POSE_BONES`).
    up : (3,) float tensor
        World up direction (unit).

    Returns
    -------
    (..., T, 6 P + 12) float tensor
        Per frame: the first two columns of each bone's rotation matrix (6D), the up
        direction and the root velocity (m/s) in the root's frame, and ``2 beta - 1``.
        Invariant to a rotation of the whole motion about the vertical.
    """
    rot = axis_angle_to_matrix(rotations[..., bones, :])  # (..., T, P, 3, 3)
    six = rot[..., :, :2].reshape(*rot.shape[:-3], -1)  # (..., T, 6P)
    root = axis_angle_to_matrix(rotations[..., 0, :])  # (..., T, 3, 3)
    rt = root.transpose(-1, -2)
    up_local = (rt @ up.to(rt.dtype)[:, None])[..., 0]  # (..., T, 3)
    vel_local = (rt @ velocity[..., None])[..., 0]  # (..., T, 3)
    beta = (2.0 * shape - 1.0)[..., None, :].expand(*six.shape[:-1], 6)
    return torch.cat([six, up_local, vel_local, beta.to(six.dtype)], dim=-1)


def top_weights(weights: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``k`` largest blend weights of each vertex, renormalised.

    Parameters
    ----------
    weights : (V, J) float tensor
        Dense blend weights (rows summing to one).
    k : int
        Weights kept per vertex (``<= J``).

    Returns
    -------
    weights : (V, k) float tensor
    indices : (V, k) int64 tensor
    """
    k = min(int(k), weights.shape[1])
    w, i = torch.topk(weights, k, dim=1)
    return w / w.sum(1, keepdim=True).clamp_min(1e-12), i


class GapsModel(nn.Module):
    """GRU regressor of per-vertex displacements of an unposed garment, then skinning.

    Parameters
    ----------
    settings : GapsSettings
        Width, depth, rank, top bones.
    template : (V, 3) float tensor
        The garment on the default body shape (m); its vertex count fixes the output.
    faces : (F, 3) int64 tensor
        Its triangles (kept to recognise the garment the model was trained for).
    weights : (V, k) float tensor, indices : (V, k) int64 tensor
        Truncated skinning weights (:func:`top_weights`).
    unit : float
        Length scale of the output (m): the mean rest edge length, so the network's output is
        in edge lengths whatever the garment's unit.
    n_features : int
        Input size (:func:`feature_size`).

    Notes
    -----
    Output layer: ``width -> rank`` then a learnt basis ``rank -> 3 V`` (a low-rank linear
    output, ``rank * (width + 3 V)`` parameters instead of ``width * 3 V``); the basis starts at
    zero so that an untrained model gives the skinned garment.
    """

    def __init__(self, settings: GapsSettings, template: torch.Tensor, faces: torch.Tensor,
                 weights: torch.Tensor, indices: torch.Tensor, unit: float,
                 n_features: int | None = None):
        super().__init__()
        self.settings = settings
        n_v = int(template.shape[0])
        nf = feature_size() if n_features is None else int(n_features)
        self.gru = nn.GRU(nf, settings.width, num_layers=settings.depth, batch_first=True)
        if settings.rank > 0:
            self.reduce = nn.Linear(settings.width, settings.rank)
            self.basis = nn.Linear(settings.rank, 3 * n_v)
        else:
            self.reduce = nn.Identity()
            self.basis = nn.Linear(settings.width, 3 * n_v)
        nn.init.zeros_(self.basis.weight)
        nn.init.zeros_(self.basis.bias)
        self.register_buffer("template", template.detach().float().clone())
        self.register_buffer("faces", faces.detach().long().clone())
        self.register_buffer("weights", weights.detach().float().clone())
        self.register_buffer("indices", indices.detach().long().clone())
        self.unit = float(unit)

    @property
    def n_vertices(self) -> int:
        """Garment vertex count ``V``."""
        return int(self.template.shape[0])

    def zero_state(self, batch: int) -> torch.Tensor:
        """``(depth, batch, width)`` zero hidden state (inference)."""
        s = self.settings
        return torch.zeros(s.depth, batch, s.width, dtype=self.template.dtype,
                           device=self.template.device)

    def forward(self, features: torch.Tensor, hidden: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """Displacements of the unposed garment.

        Parameters
        ----------
        features : (B, T, D) float tensor
            From :func:`pose_features`.
        hidden : (depth, B, width) float tensor, optional
            Initial state (zero when None: inference).

        Returns
        -------
        displacement : (B, T, V, 3) float tensor
            ``R(Phi_t, beta)`` (m).
        hidden : (depth, B, width) float tensor
            Final state.
        """
        z, h = self.coefficients(features, hidden)
        return self.displacement(z), h

    def coefficients(self, features: torch.Tensor, hidden: torch.Tensor | None = None
                     ) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`forward` without its last layer.

        Returns the output basis' inputs ``(B, T, rank)`` (``width`` when ``rank = 0``) and the
        final ``(depth, B, width)`` state.
        """
        if hidden is None:
            hidden = self.zero_state(features.shape[0])
        y, h = self.gru(features.to(self.template.dtype), hidden)
        return self.reduce(y), h

    def displacement(self, coefficients: torch.Tensor) -> torch.Tensor:
        """The learnt output basis: displacements ``(..., V, 3)`` (m) of the unposed garment.

        ``coefficients`` ``(..., rank)``: from :meth:`coefficients`.
        """
        d = self.basis(coefficients) * self.unit  # (..., 3V)
        return d.reshape(*coefficients.shape[:-1], self.n_vertices, 3)

    def state(self, features: torch.Tensor, hidden: torch.Tensor | None = None) -> torch.Tensor:
        """The GRU state after reading ``features`` ``(B, T, D)`` (no output layer).

        ``hidden`` ``(depth, B, width)`` is the state before the first frame (zero when None,
        as at inference); returns the ``(depth, B, width)`` state after the last frame
        (``T >= 1``).
        """
        if hidden is None:
            hidden = self.zero_state(features.shape[0])
        return self.gru(features.to(self.template.dtype), hidden)[1]

    def skin(self, unposed: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
        """Pose unposed garments ``(N, V, 3)`` with bone transforms ``(N, J, 4, 4)``."""
        return linear_blend_skinning(unposed, self.weights.to(unposed.dtype), self.indices,
                                     transforms.to(unposed.dtype))


def check_pose_input(rotations, n_bones: int) -> torch.Tensor:
    """Validated ``(T, J, 3)`` rotations (finite)."""
    r = as_tensor(rotations, "rotations")
    check_shape(r, "rotations", ("T", n_bones, 3))
    check_finite(r, "rotations")
    return r
