"""Local frames: PCA frames, quaternions, rotation vectors, orientations (s, R, T), alignment.

Conventions
-----------
- Rotation matrices act on column vectors, ``x_world = R @ x_local``; the columns of a frame's
  rotation are its axes ``e1, e2, e3`` expressed in world coordinates.
- Quaternions are ``(w, x, y, z)`` (scalar first), unit norm. ``q`` and ``-q`` give the same
  rotation (double cover); :func:`matrix_to_quaternion` returns the canonical one with
  ``w >= 0`` (and, when ``w == 0``, the first non-zero of ``x, y, z`` positive).
- An :class:`Orientation` maps local to world as ``x_world = s R x_local + T`` (PolyFit's
  ``O = (s, R, T)``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from .checks import as_tensor, check_choice, check_int, check_mask, check_shape

__all__ = [
    "PCAFrame",
    "pca_frames",
    "quaternion_to_matrix",
    "matrix_to_quaternion",
    "quaternion_multiply",
    "quaternion_conjugate",
    "quaternion_apply",
    "random_rotation",
    "axis_angle_to_matrix",
    "matrix_to_axis_angle",
    "rigid_align",
    "Orientation",
]


# --------------------------------------------------------------------------------------------
# PCA frames
# --------------------------------------------------------------------------------------------


class PCAFrame(NamedTuple):
    """Principal-component frame of each neighbourhood.

    Attributes
    ----------
    centroid : torch.Tensor
        ``(B, 3)`` weighted centroid of the valid points (or the given ``center``).
    rotation : torch.Tensor
        ``(B, 3, 3)`` columns ``e1, e2, e3``: directions of decreasing variance; ``e3`` is the
        normal estimate. Right-handed (``det = +1``).
    eigenvalues : torch.Tensor
        ``(B, 3)`` descending weighted variances along ``e1, e2, e3`` (length units squared).
    count : torch.Tensor
        ``(B,)`` int64 number of valid points.
    """

    centroid: torch.Tensor
    rotation: torch.Tensor
    eigenvalues: torch.Tensor
    count: torch.Tensor


def _fix_sign(v: torch.Tensor) -> torch.Tensor:
    """Flip each (..., 3) vector so that its largest-magnitude component is positive."""
    idx = v.detach().abs().argmax(-1, keepdim=True)
    s = torch.gather(v.detach(), -1, idx)
    return torch.where(s < 0, -v, v)


def pca_frames(points, mask=None, weights=None, center=None, *, reference_normal=None,
               backend: str = "auto"):
    """Batched PCA frames of point neighbourhoods.

    Parameters
    ----------
    points : array_like or torch.Tensor
        ``(B, K, 3)`` neighbourhood points (length units). Non-finite points are ignored.
    mask : array_like or torch.Tensor, optional
        ``(B, K)`` bool, True for valid points.
    weights : array_like or torch.Tensor, optional
        ``(B, K)`` non-negative finite weights.
    center : array_like or torch.Tensor, optional
        ``(B, 3)`` point about which the covariance is taken (e.g. the query point); it is
        then returned as ``centroid``. Default: the weighted centroid.
    reference_normal : array_like or torch.Tensor, optional
        ``(B, 3)`` directions: ``e3`` is flipped (with ``e2``) to have a non-negative dot
        product with them.
    backend : {"auto", "torch", "numba"}
        "torch" is differentiable; "numba" (compiled, per-item Jacobi eigen-solver) is much
        faster; "auto" uses torch when a gradient is required, else numba.

    Returns
    -------
    PCAFrame
        Torch tensors in the input's floating dtype (NumPy arrays when ``points`` is NumPy).

    Raises
    ------
    ValueError
        On bad shapes or negative / non-finite weights.
    TypeError
        On non-numeric input or a non-bool mask.

    Notes
    -----
    Sign convention (deterministic): ``e1`` and ``e3`` each have their largest-magnitude
    component positive (the first one on ties), then ``e2 = e3 x e1`` so that the frame is
    right-handed; ``reference_normal`` overrides the sign of ``e3``. Degenerate items (no
    valid point, or all valid points equal) get the identity rotation and zero eigenvalues;
    collinear points give ``e1`` along the line and a deterministic completion. Differentiable
    (through ``torch.linalg.eigh``) away from repeated eigenvalues.
    """
    check_choice(backend, "backend", ("auto", "torch", "numba"))
    numpy_in = not isinstance(points, torch.Tensor)
    p = as_tensor(points, "points")
    check_shape(p, "points", ("B", "K", 3))
    B, K, _ = p.shape
    m = None
    if mask is not None:
        m = check_mask(mask, "mask", (B, K))
    wt = None
    if weights is not None:
        wt = as_tensor(weights, "weights").to(p.dtype)
        check_shape(wt, "weights", (B, K))
        used = torch.isfinite(p.detach()).all(-1) if m is None else (
            torch.isfinite(p.detach()).all(-1) & m)
        bad = (~torch.isfinite(wt.detach()) | (wt.detach() < 0)) & used
        if bool(bad.any()):
            raise ValueError(f"weights: expected finite values >= 0, got {int(bad.sum())} "
                             "negative or non-finite entries")
    c = None
    if center is not None:
        c = as_tensor(center, "center").to(p.dtype)
        check_shape(c, "center", (B, 3))
    ref = None
    if reference_normal is not None:
        ref = as_tensor(reference_normal, "reference_normal").to(p.dtype)
        check_shape(ref, "reference_normal", (B, 3))
    if backend == "auto":
        needs_grad = torch.is_grad_enabled() and any(
            t is not None and t.requires_grad for t in (p, wt, c, ref))
        backend = "torch" if needs_grad else "numba"
    if backend == "numba":
        from ._frames_numba import pca_frames_numba

        def np64(t):
            return None if t is None else t.detach().cpu().numpy().astype(np.float64, copy=False)

        oc, oR, ol, on = pca_frames_numba(np64(p), np64(wt), None if m is None else m.numpy(),
                                          np64(c), np64(ref))
        out = PCAFrame(*(torch.from_numpy(a) for a in (oc, oR, ol, on)))
        if p.dtype != torch.float64:
            out = PCAFrame(*(t.to(p.dtype) for t in out[:3]), out.count)
    else:
        out = _pca_frames_torch(p, m, wt, c, ref)
    if numpy_in:
        out = PCAFrame(*(t.detach().cpu().numpy() for t in out))
    return out


def _pca_frames_torch(p, m, wt, c, ref) -> PCAFrame:
    B = p.shape[0]
    valid = torch.isfinite(p).all(-1)
    if m is not None:
        valid = valid & m
    w = valid.to(p.dtype) if wt is None else torch.where(valid, wt, torch.zeros_like(wt))
    p0 = torch.where(valid[..., None], p, torch.zeros_like(p))
    sw = w.sum(-1)  # (B,)
    swc = torch.where(sw > 0, sw, torch.ones_like(sw))
    if c is None:
        c = (w[..., None] * p0).sum(1) / swc[:, None]
    d = torch.where(valid[..., None], p0 - c[:, None, :], torch.zeros_like(p0))  # (B, K, 3)
    cov = ((w[..., None] * d).transpose(1, 2) @ d) / swc[:, None, None]
    # Scale-free decomposition (unit trace) so that tiny or huge neighbourhoods behave alike.
    tr = torch.diagonal(cov, dim1=-2, dim2=-1).sum(-1)
    ok = tr > 0
    trc = torch.where(ok, tr, torch.ones_like(tr))
    eye = torch.eye(3, dtype=p.dtype).expand(B, 3, 3)
    covn = torch.where(ok[:, None, None], cov / trc[:, None, None], eye)
    lam, vec = torch.linalg.eigh(covn)  # ascending
    lam = lam.flip(-1) * trc[:, None]
    lam = torch.where(ok[:, None], lam.clamp_min(0), torch.zeros_like(lam))
    e1 = _fix_sign(vec[..., :, 2])
    e3 = _fix_sign(vec[..., :, 0])
    if ref is not None:
        flip = (e3 * ref).sum(-1, keepdim=True) < 0
        e3 = torch.where(flip, -e3, e3)
    e2 = torch.linalg.cross(e3, e1)
    R = torch.stack([e1, e2, e3], dim=-1)
    R = torch.where(ok[:, None, None], R, eye)
    return PCAFrame(c, R, lam, valid.sum(-1))


# --------------------------------------------------------------------------------------------
# Quaternions
# --------------------------------------------------------------------------------------------


def _as_quat(q, name: str = "q") -> torch.Tensor:
    t = as_tensor(q, name)
    check_shape(t, name, ("...", 4))
    return t


def quaternion_to_matrix(q) -> torch.Tensor:
    """Rotation matrices of quaternions (normalised first).

    Parameters
    ----------
    q : array_like or torch.Tensor
        ``(..., 4)`` quaternions ``(w, x, y, z)``; need not be unit.

    Returns
    -------
    torch.Tensor
        ``(..., 3, 3)`` rotation matrices.

    Raises
    ------
    ValueError
        If a quaternion has zero (or non-finite) norm, or the last dimension is not 4.
    """
    t = _as_quat(q)
    n2 = (t * t).sum(-1)
    if bool((~torch.isfinite(n2) | (n2 <= 0)).any()):
        raise ValueError("q: expected non-zero finite quaternions, got a zero or non-finite one")
    t = t / n2.sqrt()[..., None]
    w, x, y, z = t.unbind(-1)
    R = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )
    return R.reshape(t.shape[:-1] + (3, 3))


def _canonical(q: torch.Tensor) -> torch.Tensor:
    """Pick the representative with w > 0, or the first non-zero of x, y, z positive.

    Components below 1e-12 of the largest count as zero.
    """
    qd = q.detach()
    nz = qd.abs() > 1e-12 * qd.abs().amax(-1, keepdim=True).clamp_min(1e-300)
    first = torch.argmax(nz.to(torch.int8), dim=-1, keepdim=True)
    s = torch.gather(qd, -1, first)
    q = torch.where(s < 0, -q, q)
    # a w below the tolerance (e.g. -6e-17 for a rotation by pi) is snapped to its magnitude
    return torch.cat([q[..., :1].abs(), q[..., 1:]], -1).where(~nz[..., :1], q)


def matrix_to_quaternion(R) -> torch.Tensor:
    """Unit quaternions of rotation matrices (Shepperd's method), canonical ``w >= 0``.

    Parameters
    ----------
    R : array_like or torch.Tensor
        ``(..., 3, 3)`` rotation matrices.

    Returns
    -------
    torch.Tensor
        ``(..., 4)`` unit quaternions ``(w, x, y, z)``.

    Raises
    ------
    ValueError
        If the trailing shape is not ``(3, 3)``.

    Notes
    -----
    For each matrix the largest of ``4w^2, 4x^2, 4y^2, 4z^2`` is computed from the diagonal
    and the other components from off-diagonal sums, which keeps full accuracy for any angle;
    the result is differentiable (the square roots are guarded for the branches not taken).
    """
    m = as_tensor(R, "R")
    check_shape(m, "R", ("...", 3, 3))
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    # 4 q_i^2 for each component
    cand = torch.stack(
        [
            1 + m00 + m11 + m22,
            1 + m00 - m11 - m22,
            1 - m00 + m11 - m22,
            1 - m00 - m11 + m22,
        ],
        dim=-1,
    )
    best = cand.detach().argmax(-1)  # (...)
    r = torch.sqrt(cand.clamp_min(1e-12))  # 2|q_i|, guarded
    qs = [
        torch.stack([r[..., 0], (m21 - m12) / r[..., 0], (m02 - m20) / r[..., 0],
                     (m10 - m01) / r[..., 0]], -1),
        torch.stack([(m21 - m12) / r[..., 1], r[..., 1], (m01 + m10) / r[..., 1],
                     (m02 + m20) / r[..., 1]], -1),
        torch.stack([(m02 - m20) / r[..., 2], (m01 + m10) / r[..., 2], r[..., 2],
                     (m12 + m21) / r[..., 2]], -1),
        torch.stack([(m10 - m01) / r[..., 3], (m02 + m20) / r[..., 3], (m12 + m21) / r[..., 3],
                     r[..., 3]], -1),
    ]
    q = qs[0]
    for i in (1, 2, 3):
        q = torch.where((best == i)[..., None], qs[i], q)
    q = 0.5 * q
    q = q / q.norm(dim=-1, keepdim=True)
    return _canonical(q)


def quaternion_multiply(a, b) -> torch.Tensor:
    """Hamilton product ``a * b`` (rotation ``b`` first, then ``a``).

    Parameters
    ----------
    a, b : array_like or torch.Tensor
        ``(..., 4)`` quaternions ``(w, x, y, z)`` (broadcast).

    Returns
    -------
    torch.Tensor
        ``(..., 4)``.

    Raises
    ------
    ValueError
        If a last dimension is not 4.
    """
    p = _as_quat(a, "a")
    q = _as_quat(b, "b")
    aw, ax, ay, az = p.unbind(-1)
    bw, bx, by, bz = q.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def quaternion_conjugate(q) -> torch.Tensor:
    """Conjugate ``(w, -x, -y, -z)`` (the inverse rotation for unit quaternions).

    Parameters
    ----------
    q : array_like or torch.Tensor
        ``(..., 4)``.

    Returns
    -------
    torch.Tensor
        ``(..., 4)``.

    Raises
    ------
    ValueError
        If the last dimension is not 4.
    """
    t = _as_quat(q)
    return torch.cat([t[..., :1], -t[..., 1:]], dim=-1)


def quaternion_apply(q, v) -> torch.Tensor:
    """Rotate vectors by unit quaternions: ``q v q*``.

    Parameters
    ----------
    q : array_like or torch.Tensor
        ``(..., 4)`` unit quaternions.
    v : array_like or torch.Tensor
        ``(..., 3)`` vectors (broadcast against ``q``).

    Returns
    -------
    torch.Tensor
        ``(..., 3)``.

    Raises
    ------
    ValueError
        On bad trailing dimensions.
    """
    t = _as_quat(q)
    x = as_tensor(v, "v")
    check_shape(x, "v", ("...", 3))
    w = t[..., :1]
    u = t[..., 1:]
    # v' = v + 2 w (u x v) + 2 u x (u x v)
    uv = torch.linalg.cross(u.expand(torch.broadcast_shapes(u.shape, x.shape)), x.expand(
        torch.broadcast_shapes(u.shape, x.shape)))
    return x + 2 * w * uv + 2 * torch.linalg.cross(u.expand_as(uv), uv)


def random_rotation(n: int, generator: torch.Generator | None = None, *,
                    dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Uniformly distributed random rotation matrices (Haar measure on SO(3)).

    Parameters
    ----------
    n : int
        Number of rotations (>= 0).
    generator : torch.Generator, optional
        Source of randomness (pass one for reproducible results).
    dtype : torch.dtype
        Output dtype (default float64).

    Returns
    -------
    torch.Tensor
        ``(n, 3, 3)`` rotation matrices.

    Raises
    ------
    ValueError, TypeError
        If ``n`` is not a non-negative integer.
    """
    n = check_int(n, "n", low=0)
    q = torch.randn(n, 4, generator=generator, dtype=torch.float64)
    bad = q.norm(dim=-1) < 1e-12
    q[bad] = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    return quaternion_to_matrix(q).to(dtype)


def axis_angle_to_matrix(axis_angle) -> torch.Tensor:
    """Rotation matrices of rotation vectors (axis times angle in radians), Rodrigues' formula.

    Parameters
    ----------
    axis_angle : array_like or torch.Tensor
        ``(..., 3)`` rotation vectors; the zero vector is the identity.

    Returns
    -------
    torch.Tensor
        ``(..., 3, 3)``.

    Raises
    ------
    ValueError
        If the last dimension is not 3.

    Notes
    -----
    Uses series expansions of ``sin(t)/t`` and ``(1-cos t)/t^2`` for small angles, so it is
    accurate and differentiable at zero.
    """
    r = as_tensor(axis_angle, "axis_angle")
    check_shape(r, "axis_angle", ("...", 3))
    t2 = (r * r).sum(-1)
    small = t2 < 1e-8
    t2s = torch.where(small, torch.ones_like(t2), t2)
    ts = t2s.sqrt()
    a = torch.where(small, 1 - t2 / 6 + t2 * t2 / 120, torch.sin(ts) / ts)
    b = torch.where(small, 0.5 - t2 / 24 + t2 * t2 / 720, (1 - torch.cos(ts)) / t2s)
    x, y, z = r.unbind(-1)
    zero = torch.zeros_like(x)
    Kx = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(r.shape[:-1] + (3, 3))
    eye = torch.eye(3, dtype=r.dtype, device=r.device).expand_as(Kx)
    return eye + a[..., None, None] * Kx + b[..., None, None] * (Kx @ Kx)


def matrix_to_axis_angle(R) -> torch.Tensor:
    """Rotation vectors (axis times angle in radians, angle in ``[0, pi]``) of rotations.

    The inverse of :func:`axis_angle_to_matrix` for angles below ``pi`` (at ``pi`` exactly the
    axis' sign is that of :func:`matrix_to_quaternion`'s canonical quaternion).

    Parameters
    ----------
    R : array_like or torch.Tensor
        ``(..., 3, 3)`` rotation matrices.

    Returns
    -------
    torch.Tensor
        ``(..., 3)``; the identity gives the zero vector.

    Raises
    ------
    ValueError
        If the trailing shape is not ``(3, 3)``.
    """
    q = matrix_to_quaternion(R)  # w >= 0: the angle 2 atan2(|xyz|, w) is in [0, pi]
    w, xyz = q[..., :1], q[..., 1:]
    n2 = (xyz * xyz).sum(-1, keepdim=True)
    small = n2 < 1e-12
    n = torch.where(small, torch.ones_like(n2), n2).sqrt()
    # angle / |xyz|; near the identity 2 atan2(n, w) / n = (2 / w)(1 - n^2 / (3 w^2) + ...)
    factor = torch.where(small, 2.0 / w * (1.0 - n2 / (3.0 * w * w)),
                         2.0 * torch.atan2(n, w) / n)
    return xyz * factor


def rigid_align(source, target, weights=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Rotation and translation that best map ``source`` onto ``target`` (Kabsch).

    Minimises ``sum_i w_i |R source_i + t - target_i|^2`` over rotations ``R`` (no
    reflection) and translations ``t``, from the SVD of the weighted cross-covariance.

    Parameters
    ----------
    source, target : array_like or torch.Tensor
        ``(..., N, 3)`` corresponding points (same shape, ``N >= 1``).
    weights : array_like or torch.Tensor, optional
        ``(..., N)`` non-negative weights (default: all 1); each batch item needs a positive
        total.

    Returns
    -------
    R : torch.Tensor
        ``(..., 3, 3)`` rotations.
    t : torch.Tensor
        ``(..., 3)`` translations.

    Raises
    ------
    ValueError
        On mismatched shapes, negative weights or a zero total weight.

    Notes
    -----
    Degenerate-but-answerable configurations (fewer than three points, collinear points)
    return one of the optimal rotations; the residual is still minimal.
    """
    p = as_tensor(source, "source")
    q = as_tensor(target, "target", dtype=p.dtype)
    check_shape(p, "source", ("...", "N", 3))
    if q.shape != p.shape:
        raise ValueError(f"target: expected the shape of source {tuple(p.shape)}, "
                         f"got {tuple(q.shape)}")
    if p.shape[-2] < 1:
        raise ValueError("source: expected at least one point")
    w = torch.ones(p.shape[:-1], dtype=p.dtype, device=p.device) if weights is None else \
        as_tensor(weights, "weights", dtype=p.dtype)
    if w.shape != p.shape[:-1]:
        raise ValueError(f"weights: expected shape {tuple(p.shape[:-1])}, got {tuple(w.shape)}")
    if bool((w < 0).any()):
        raise ValueError("weights: expected non-negative weights")
    tot = w.sum(-1, keepdim=True)
    if bool((tot <= 0).any()):
        raise ValueError("weights: every batch item needs a positive total weight")
    wn = (w / tot)[..., None]
    cp, cq = (wn * p).sum(-2), (wn * q).sum(-2)
    H = ((p - cp[..., None, :]) * wn).transpose(-1, -2) @ (q - cq[..., None, :])  # (..., 3, 3)
    U, _, Vh = torch.linalg.svd(H)
    d = torch.sign(torch.linalg.det(Vh.transpose(-1, -2) @ U.transpose(-1, -2)))
    d = torch.where(d == 0, torch.ones_like(d), d)
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
    R = Vh.transpose(-1, -2) @ D @ U.transpose(-1, -2)
    t = cq - (R @ cp[..., None])[..., 0]
    return R, t


# --------------------------------------------------------------------------------------------
# Orientation (s, R, T)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Orientation:
    """Batched similarity transforms ``x_world = s R x_local + T``.

    Attributes
    ----------
    s : torch.Tensor
        ``(B,)`` positive scales.
    R : torch.Tensor
        ``(B, 3, 3)`` rotations.
    T : torch.Tensor
        ``(B, 3)`` translations (length units).

    Notes
    -----
    Construction does not validate (so that it stays cheap inside optimisation loops); use
    :meth:`create` for validated construction from user input.
    """

    s: torch.Tensor
    R: torch.Tensor
    T: torch.Tensor

    @classmethod
    def create(cls, s, R, T) -> Orientation:
        """Validated constructor from arrays or tensors.

        Parameters
        ----------
        s : array_like or torch.Tensor
            ``(B,)`` positive scales.
        R : array_like or torch.Tensor
            ``(B, 3, 3)`` rotations.
        T : array_like or torch.Tensor
            ``(B, 3)`` translations.

        Returns
        -------
        Orientation

        Raises
        ------
        ValueError
            On inconsistent shapes, non-positive or non-finite scales.
        """
        st = as_tensor(s, "s")
        Rt = as_tensor(R, "R")
        Tt = as_tensor(T, "T")
        check_shape(st, "s", ("B",))
        check_shape(Rt, "R", (st.shape[0], 3, 3))
        check_shape(Tt, "T", (st.shape[0], 3))
        if not bool((torch.isfinite(st) & (st > 0)).all()):
            raise ValueError("s: expected finite scales > 0")
        dtype = torch.promote_types(torch.promote_types(st.dtype, Rt.dtype), Tt.dtype)
        return cls(st.to(dtype), Rt.to(dtype), Tt.to(dtype))

    @classmethod
    def identity(cls, B: int, *, dtype: torch.dtype = torch.float64,
                 device: torch.device | str | None = None) -> Orientation:
        """``B`` identity transforms (s = 1, R = I, T = 0)."""
        B = check_int(B, "B", low=0)
        return cls(
            torch.ones(B, dtype=dtype, device=device),
            torch.eye(3, dtype=dtype, device=device).expand(B, 3, 3).clone(),
            torch.zeros(B, 3, dtype=dtype, device=device),
        )

    def __len__(self) -> int:
        return int(self.s.shape[0])

    def __getitem__(self, idx) -> Orientation:
        """Select items; an integer index keeps a batch dimension of 1."""
        if isinstance(idx, int):
            idx = slice(idx, idx + 1) if idx != -1 else slice(-1, None)
        return Orientation(self.s[idx], self.R[idx], self.T[idx])

    def to(self, dtype: torch.dtype | None = None,
           device: torch.device | str | None = None) -> Orientation:
        """Copy to another dtype and/or device."""
        return Orientation(*(t.to(dtype=dtype or t.dtype, device=device or t.device)
                             for t in (self.s, self.R, self.T)))

    def apply(self, x) -> torch.Tensor:
        """Map local points to world: ``s R x + T``.

        Parameters
        ----------
        x : torch.Tensor
            ``(B, P, 3)`` local points.

        Returns
        -------
        torch.Tensor
            ``(B, P, 3)`` world points.
        """
        x = as_tensor(x, "x")
        check_shape(x, "x", (len(self), "P", 3))
        return self.s[:, None, None] * (x @ self.R.transpose(-1, -2)) + self.T[:, None, :]

    def apply_vectors(self, v) -> torch.Tensor:
        """Rotate direction vectors: ``R v`` (tangents and normals; the scale is ignored).

        Parameters
        ----------
        v : torch.Tensor
            ``(B, P, 3)``.

        Returns
        -------
        torch.Tensor
            ``(B, P, 3)``.
        """
        v = as_tensor(v, "v")
        check_shape(v, "v", (len(self), "P", 3))
        return v @ self.R.transpose(-1, -2)

    def inverse_apply(self, p) -> torch.Tensor:
        """Map world points to local: ``R^T (p - T) / s``.

        Parameters
        ----------
        p : torch.Tensor
            ``(B, P, 3)`` world points.

        Returns
        -------
        torch.Tensor
            ``(B, P, 3)`` local points.
        """
        p = as_tensor(p, "p")
        check_shape(p, "p", (len(self), "P", 3))
        return ((p - self.T[:, None, :]) @ self.R) / self.s[:, None, None]

    def invert(self) -> Orientation:
        """The inverse transform ``x -> (1/s) R^T x - (1/s) R^T T``."""
        Rt = self.R.transpose(-1, -2)
        si = 1.0 / self.s
        Ti = -si[:, None] * (Rt @ self.T[..., None])[..., 0]
        return Orientation(si, Rt, Ti)

    def compose(self, other: Orientation) -> Orientation:
        """``self ∘ other``: apply ``other`` first, then ``self``."""
        s = self.s * other.s
        R = self.R @ other.R
        T = self.s[:, None] * (self.R @ other.T[..., None])[..., 0] + self.T
        return Orientation(s, R, T)
