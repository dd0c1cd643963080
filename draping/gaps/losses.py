"""GAPS training losses, eq. (38)-(46), as calls of the shared :mod:`draping.physics` energies.

Part of :mod:`draping.gaps`; import from there.
"""

from __future__ import annotations

import numpy as np
import torch

from draping import physics
from draping.collision import MeshQuery

from .data import ShapeCase
from .pinch import PinchQuery, pinch_factor, push_normal
from .settings import GapsSettings, TrainSettings

__all__ = ["TERMS", "Contacts", "body_contacts", "loss_terms"]

#: Loss terms, in the order they are logged.
TERMS = ("strain", "bending", "gravity", "collision", "inertia", "inext")


class Contacts:
    """Closest body points and normals of garment vertices (detached; eq. (40)'s ``d(x)``).

    Attributes
    ----------
    anchor : (N, V, 3) float tensor
        Closest body point (m), the vertex itself where the body is farther than the radius.
    normal : (N, V, 3) float tensor
        Outward body normal there (zero when far); at pinched cloth, when asked
        (``body_contacts(push=True)``), the normalised sum of the two facing parts' normals.
    near : (N, V) bool tensor
        Within the query radius.
    pinched : (N, V) bool tensor or None
        Cloth within the clearance of an arm and of the rest of the body at once
        (:class:`draping.gaps.PinchQuery`); None when not asked for.
    """

    def __init__(self, anchor: torch.Tensor, normal: torch.Tensor, near: torch.Tensor,
                 pinched: torch.Tensor | None = None):
        self.anchor, self.normal, self.near, self.pinched = anchor, normal, near, pinched

    def distance(self, x: torch.Tensor, far: float) -> torch.Tensor:
        """Signed distance ``(N, V)`` linear in ``x``, ``far`` (m) where the body is out of reach.

        :func:`draping.physics.plane_distance` to the closest body point.
        """
        d = physics.plane_distance(x, self.anchor, self.normal)
        return torch.where(self.near, d, torch.full_like(d, far))


def body_contacts(x: torch.Tensor, body_vertices: torch.Tensor, query: MeshQuery,
                  radius: float, pinch: PinchQuery | None = None,
                  eps: float = 0.0, push: bool = False) -> Contacts:
    """Query each frame's posed body at the garment positions.

    Parameters
    ----------
    x : (N, V, 3) float tensor
        Garments (m); detached inside.
    body_vertices : (N, Vb, 3) float tensor
        Posed bodies (m), the topology of ``query``.
    query : MeshQuery
        Refitted to each frame in turn.
    radius : float
        Query radius (m).
    pinch : PinchQuery or None
        Also flag the cloth pinched between an arm and the rest of the body (``pinched``).
    eps : float
        Clearance (m) of the pinch test; > 0 with ``pinch``.
    push : bool
        At pinched cloth, the contact normal is :func:`draping.gaps.push_normal`'s (the
        collision penetration measured along the bisector of the two facing normals;
        ``TrainSettings.pinch_push``). Needs ``pinch``.

    Raises
    ------
    ValueError
        ``push`` without ``pinch``.
    """
    if push and pinch is None:
        raise ValueError("push: needs a PinchQuery (pinch)")
    xs = x.detach().double().cpu().numpy()
    n, v, _ = xs.shape
    anchor = np.empty((n, v, 3))
    normal = np.zeros((n, v, 3))
    near = np.zeros((n, v), dtype=bool)
    pinched = None if pinch is None else np.zeros((n, v), dtype=bool)
    for i in range(n):
        bv = body_vertices[i].detach()
        query.update(bv)
        r = query.query(xs[i], max_distance=radius)
        ok = np.isfinite(r.distance)
        near[i] = ok
        anchor[i] = np.where(ok[:, None], r.closest, xs[i])
        normal[i, ok] = r.normal[ok]
        if pinch is not None:
            pinched[i], other = pinch.facing(bv, xs[i], r.distance, r.face, normal[i], eps)
            if push:
                normal[i] = push_normal(normal[i], other, pinched[i])
    t = x.dtype
    return Contacts(torch.from_numpy(anchor).to(t), torch.from_numpy(normal).to(t),
                    torch.from_numpy(near), None if pinched is None else torch.from_numpy(pinched))


def loss_terms(x: torch.Tensor, case: ShapeCase, model: GapsSettings, train: TrainSettings,
               contacts: Contacts, epoch: int, dt: float) -> dict:
    """Every term of eq. (46) per window frame.

    Parameters
    ----------
    x : (B, L, V, 3) float tensor
        Posed garments of ``B`` windows of ``L`` frames (m).
    case : ShapeCase
        The body shape's garment and rest geometry.
    model : GapsSettings
        Method (bending form, inextensibility mode).
    train : TrainSettings
        Collision stiffness and clearance, ``k_ext`` rings, ``k_i``, query radius,
        ``pinch_inext`` (applied where ``contacts.pinched`` is given).
    contacts : Contacts
        Of the ``B * L`` frames, in the order of ``x.reshape(B * L, V, 3)``.
    epoch : int
        Epoch of the ``k_ext`` schedule (eq. (45)).
    dt : float
        Time step (s).

    Returns
    -------
    dict of (B, L) float tensors
        Energies (J; ``inext`` in ``k_i`` units): strain (38), bending (41) or (17), gravity
        (39), collision (40), inertia (42, zero on the first two frames) and inext (44).
    """
    b, n_l, v, _ = x.shape
    rest = case.rest
    d = contacts.distance(x.reshape(b * n_l, v, 3), far=10.0 * train.query_radius)
    d = d.reshape(b, n_l, v)
    out = {"strain": physics.stvk_energy(x, rest)}
    if model.method == "gaps":
        out["bending"] = physics.gaps_bending_energy(x, rest, case.alpha)
    else:
        out["bending"] = physics.bending_energy(x, rest)
    out["gravity"] = physics.gravity_energy(x, rest)
    out["collision"] = physics.collision_energy(d, train.collision_stiffness, train.collision_eps)
    inertia = torch.zeros_like(out["strain"])
    if n_l >= 3:
        prev = x[:, 1:-1].detach()
        vel = (x[:, 1:-1] - x[:, :-2]).detach() / dt
        inertia = torch.cat([inertia[:, :2], physics.inertia_energy(x[:, 2:], prev, vel, rest, dt)],
                            dim=1)
    out["inertia"] = inertia
    mode = model.inext_mode
    if mode == "none":
        out["inext"] = torch.zeros_like(out["strain"])
    else:
        k_ext = (physics.k_ext_schedule(d, epoch, train.collision_eps, rest, train.k_ext_rings)
                 if mode == "schedule" else 1.0)
        w = None
        if train.pinch_inext != 1.0 and contacts.pinched is not None:
            w = pinch_factor(contacts.pinched.reshape(b, n_l, v), rest, train.k_ext_rings,
                             train.pinch_inext).to(x.dtype)
        out["inext"] = physics.inextensibility_energy(x, rest, k_ext, train.inext_weight, w)
    return out
