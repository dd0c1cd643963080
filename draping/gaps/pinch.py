"""Cloth pinched between two body parts, and the L_inext factor that frees it (GAPS dress).

Part of :mod:`draping.gaps`; import from there.

Where an arm swings against the torso, garment cloth caught between them cannot lie outside
both: the collision term pushes it out of one part into the other. GAPS's covariance
inextensibility (eq. (44)) holds that cloth in place where NCS-like, without the term, lets it
stretch out of the pinch (``benchmarks/gaps_contacts.py`` finds the remaining dress contacts of
GAPS mostly pinched between arm and torso). ``TrainSettings.pinch_inext`` scales L_inext at the
pinched cloth (0: off there); ``TrainSettings.pinch_push`` measures the collision penetration
there along the bisector of the two facing normals (:func:`push_normal`), out of the wedge
rather than into the other part. This module finds the pinched cloth.

Eq. (44) is ``|det(C - k_ext sigma I)|``, two-sided, so no ``k_ext`` frees a neighbourhood:
the lever is a per-vertex factor on the term, not a ``k_ext``.
"""

from __future__ import annotations

import numpy as np
import torch

from draping.collision import MeshQuery

__all__ = ["PARTS", "PinchQuery", "body_part", "face_parts", "pinch_factor", "push_normal"]

#: Body parts a face is attributed to (the dominant bone of its first vertex).
PARTS = ("torso", "legL", "legR", "armL", "armR")
_LEG = ("leg", "foot", "toe", "pelvis")
_ARM = ("arm", "wrist", "finger", "metacarpal", "shoulder", "clavicle")


def body_part(bone: str) -> str:
    """The part of :data:`PARTS` a bone of the Anny skeleton belongs to."""
    side = "L" if bone.endswith(".L") else "R" if bone.endswith(".R") else ""
    if side and any(k in bone for k in _LEG):
        return "leg" + side
    if side and any(k in bone for k in _ARM):
        return "arm" + side
    return "torso"


def face_parts(body) -> np.ndarray:
    """``(F,)`` part name (:data:`PARTS`) of every face of ``body`` (an ``AnnyBody``)."""
    si, sw = body.skin_indices.numpy(), body.skin_weights.numpy()
    vbone = si[np.arange(len(si)), sw.argmax(1)]
    names = body.bone_names
    return np.array([body_part(names[vbone[f[0]]]) for f in body.faces.numpy()])


class PinchQuery:
    """Finds garment vertices within a clearance of an arm and of the rest of the body at once.

    Parameters
    ----------
    vertices : (Vb, 3) float
        A body pose (m), to build the two part meshes; refitted per frame by :meth:`pinched`.
    faces : (F, 3) int
        The body's triangles.
    arm : (F,) bool
        True on the faces of the arms (:func:`face_parts` ``armL`` / ``armR``).

    Raises
    ------
    ValueError
        ``arm`` not one flag per face, or all or none of the faces arms.
    """

    def __init__(self, vertices, faces, arm):
        f = torch.as_tensor(faces)
        a = np.asarray(arm)
        if a.dtype != bool or a.shape != (f.shape[0],):
            raise ValueError(f"arm: expected a bool array of shape ({f.shape[0]},), got "
                             f"{a.dtype} {a.shape}")
        if a.all() or not a.any():
            raise ValueError("arm: expected both arm and non-arm faces")
        self.arm = a
        self.parts = (MeshQuery(vertices, f[torch.from_numpy(a)]),
                      MeshQuery(vertices, f[torch.from_numpy(~a)]))

    def pinched(self, body_vertices, x, distance, face, normal, eps: float) -> np.ndarray:
        """``(V,)`` bool: vertices within ``eps`` of an arm and of a non-arm face facing it.

        The first output of :meth:`facing`; same parameters.
        """
        return self.facing(body_vertices, x, distance, face, normal, eps)[0]

    def facing(self, body_vertices, x, distance, face, normal, eps: float):
        """Pinched vertices and the outward normal of the other part (the one not closest).

        Parameters
        ----------
        body_vertices : (Vb, 3) float
            The frame's posed body (m).
        x : (V, 3) float array
            Garment vertices (m).
        distance, face, normal : (V,), (V,), (V, 3) arrays
            The whole body's query at ``x`` (:class:`draping.collision.SignedDistance`;
            distance ``inf`` where out of reach).
        eps : float
            Clearance (m), > 0.

        Returns
        -------
        pinched : (V,) bool array
            Within ``eps`` (signed, so inside too) of its closest part, and within ``eps``
            (unsigned) of the other group, with outward normals facing (``n_a . n_b < 0``):
            where two parts merely meet (a shoulder), the normals agree and it is no pinch.
        other : (V, 3) float64 array
            Outward normal of the other group's closest face at pinched vertices, 0 elsewhere.

        Raises
        ------
        ValueError
            ``eps`` not a positive finite clearance.
        """
        if not (np.isfinite(eps) and eps > 0):
            raise ValueError(f"eps: expected a positive clearance, got {eps!r}")
        d = np.asarray(distance)
        out = np.zeros(d.shape, dtype=bool)
        other = np.zeros((d.shape[0], 3))
        cand = np.nonzero(d < eps)[0]
        if cand.size == 0:
            return out, other
        on_arm = self.arm[np.asarray(face)[cand]]
        xs = np.asarray(x)
        for k, q in enumerate(self.parts):  # k = 0: arm mesh, for candidates not on an arm
            sel = cand[on_arm == (k == 1)]
            if sel.size == 0:
                continue
            q.update(body_vertices)
            r = q.query(xs[sel], max_distance=eps)
            dd, nn = np.abs(np.asarray(r.distance)), np.asarray(r.normal)
            facing = (nn * np.asarray(normal)[sel]).sum(-1) < 0
            hit = np.isfinite(dd) & (dd < eps) & facing
            out[sel] = hit
            other[sel[hit]] = nn[hit]
        return out, other


def push_normal(normal, other, pinched) -> np.ndarray:
    """Collision normals that push pinched cloth out of the wedge between two body parts.

    At a pinched vertex the closest part's normal alone pushes the cloth into the other part;
    the normalised sum of the two facing normals points out of the wedge, along its bisector
    (``TrainSettings.pinch_push``). Where the sum is shorter than 1e-3 (parallel, opposite
    surfaces: no way out) the closest part's normal is kept.

    Parameters
    ----------
    normal : (V, 3) float array
        Outward normal of the closest body part (unit, or 0 out of reach).
    other : (V, 3) float array
        Outward normal of the other part (:meth:`PinchQuery.facing`).
    pinched : (V,) bool array

    Returns
    -------
    (V, 3) float64 array
        ``normal`` with the pinched rows replaced by ``normalise(normal + other)``.

    Raises
    ------
    ValueError
        Shapes that do not match, ``pinched`` not bool, or a non-finite normal.
    """
    n = np.asarray(normal, dtype=np.float64)
    o = np.asarray(other, dtype=np.float64)
    p = np.asarray(pinched)
    if n.ndim != 2 or n.shape[1] != 3 or o.shape != n.shape:
        raise ValueError(f"normal, other: expected two (V, 3) arrays, got {n.shape}, {o.shape}")
    if p.dtype != bool or p.shape != n.shape[:1]:
        raise ValueError(f"pinched: expected a bool array of shape ({n.shape[0]},), got "
                         f"{p.dtype} {p.shape}")
    if not (np.isfinite(n).all() and np.isfinite(o).all()):
        raise ValueError("normal, other: expected finite normals")
    s = n + o
    length = np.linalg.norm(s, axis=-1, keepdims=True)
    pushed = np.where(length > 1e-3, s / np.maximum(length, 1e-12), n)
    return np.where(p[:, None], pushed, n)


def pinch_factor(pinched, rest, rings: int, factor: float) -> torch.Tensor:
    """Per-vertex factor on L_inext: ``factor`` at pinched cloth and ``rings`` 1-rings round it.

    Parameters
    ----------
    pinched : (..., V) bool
        Pinched vertices (:meth:`PinchQuery.pinched` per frame).
    rest : draping.physics.RestState
        The garment's 1-rings.
    rings : int
        1-rings the flag spreads over (>= 0).
    factor : float
        In [0, 1]; 1 leaves L_inext as it is.

    Returns
    -------
    (..., V) float32 tensor
        ``factor`` where flagged, 1 elsewhere.

    Raises
    ------
    ValueError
        ``factor`` outside [0, 1], negative ``rings``, ``pinched`` not per garment vertex.
    """
    from draping.physics import spread_over_rings

    if not (0.0 <= float(factor) <= 1.0):
        raise ValueError(f"factor: expected a value in [0, 1], got {factor!r}")
    p = torch.as_tensor(pinched)
    if p.dtype != torch.bool:
        raise ValueError(f"pinched: expected a bool tensor, got {p.dtype}")
    flag = spread_over_rings(p.to(torch.float32), rest, rings) > 0
    return torch.where(flag, torch.tensor(float(factor)), torch.tensor(1.0))
