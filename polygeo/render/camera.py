"""Pinhole camera in the OpenCV convention.

Camera axes: x right, y down, z forward (points in front of the camera have depth
``z > 0``). Intrinsics ``K`` are in pixels; the image origin is the top-left corner of the
top-left pixel, so the centre of pixel ``(row i, column j)`` is at ``(x, y) = (j + 0.5,
i + 0.5)``. Extrinsics map world to camera coordinates: ``X_cam = R @ X_world + t``.

A :class:`Camera` is either single (``K`` (3, 3), ``R`` (3, 3), ``t`` (3,)) or a batch of
``B`` cameras (any of them with a leading ``B`` dimension; the others are broadcast). All
transforms are plain differentiable torch operations, so ``R`` and ``t`` (and ``K``) may
require gradients.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from ..checks import as_tensor, check_finite, check_int, check_shape, is_numpy_like, to_like

__all__ = ["Camera"]

# Depths with a smaller magnitude are replaced by this (sign kept) before dividing, so that
# projections of points on the camera plane stay finite.
_TINY_DEPTH = 1e-12


def _batch_of(t: torch.Tensor, core_ndim: int, name: str) -> int | None:
    if t.ndim == core_ndim:
        return None
    if t.ndim == core_ndim + 1:
        return int(t.shape[0])
    raise ValueError(
        f"{name}: expected {core_ndim} dimensions or a leading batch dimension, "
        f"got shape {tuple(t.shape)}"
    )


def _apply(M: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """``M @ p`` for points ``p`` (..., 3), as a broadcast product and sum (no BLAS call).

    Tiny matrix products go through BLAS threads in torch, which is slow on a loaded
    machine; the elementwise form stays on the calling thread for small inputs.
    """
    return (p.unsqueeze(-2) * M).sum(-1)


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera (or a batch of ``B`` cameras) in the OpenCV convention.

    Parameters
    ----------
    K : array_like or torch.Tensor, shape (3, 3) or (B, 3, 3)
        Intrinsics in pixels, ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``; finite,
        invertible, last row ``(0, 0, 1)``.
    R : array_like or torch.Tensor, shape (3, 3) or (B, 3, 3)
        World-to-camera rotation (not checked for orthonormality), dimensionless.
    t : array_like or torch.Tensor, shape (3,) or (B, 3)
        World-to-camera translation, scene units.
    width, height : int
        Image size in pixels, >= 1.

    All three arrays are stored as torch tensors of one floating dtype (float64 unless one
    of them is a floating tensor, whose dtype is then used), without detaching them.

    Raises
    ------
    ValueError
        On wrong shapes, inconsistent batch sizes, non-finite values, a singular ``K`` or a
        last row of ``K`` other than ``(0, 0, 1)``, or image sizes < 1.
    TypeError
        On non-numeric arrays or non-integer sizes.
    """

    K: Any
    R: Any = None
    t: Any = None
    width: int = 0
    height: int = 0

    def __post_init__(self) -> None:
        dtype = None
        for v in (self.K, self.R, self.t):
            if isinstance(v, torch.Tensor) and v.is_floating_point():
                dtype = v.dtype if dtype is None else torch.promote_types(dtype, v.dtype)
        dtype = dtype or torch.float64
        K = as_tensor(self.K, "K", dtype=dtype)
        R = torch.eye(3, dtype=dtype) if self.R is None else as_tensor(self.R, "R", dtype=dtype)
        t = torch.zeros(3, dtype=dtype) if self.t is None else as_tensor(self.t, "t", dtype=dtype)
        check_shape(K, "K", ("...", 3, 3))
        check_shape(R, "R", ("...", 3, 3))
        check_shape(t, "t", ("...", 3))
        batches = {
            "K": _batch_of(K, 2, "K"),
            "R": _batch_of(R, 2, "R"),
            "t": _batch_of(t, 1, "t"),
        }
        sizes = {b for b in batches.values() if b is not None}
        if len(sizes) > 1:
            got = ", ".join(f"{k}: {v}" for k, v in batches.items())
            raise ValueError(f"K, R, t: expected one batch size, got {got}")
        for name, v in (("K", K), ("R", R), ("t", t)):
            check_finite(v.detach(), name)
        Kd = K.detach()
        last = Kd[..., 2, :]
        want = torch.tensor([0.0, 0.0, 1.0], dtype=Kd.dtype)
        if not torch.allclose(last, want.expand_as(last), rtol=0.0, atol=1e-12):
            raise ValueError(f"K: expected a last row (0, 0, 1), got {last.tolist()}")
        det = torch.linalg.det(Kd.to(torch.float64))
        scale = Kd.to(torch.float64).abs().amax(dim=(-1, -2)).clamp_min(1e-300)
        if bool((det.abs() <= 1e-12 * scale**2).any()):
            raise ValueError(f"K: expected an invertible matrix, got determinant {det.tolist()}")
        w = check_int(self.width, "width", low=1)
        h = check_int(self.height, "height", low=1)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "width", w)
        object.__setattr__(self, "height", h)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def look_at(
        cls,
        eye: Any,
        target: Any,
        *,
        focal: float,
        width: int,
        height: int,
        up: Any = (0.0, -1.0, 0.0),
    ) -> Camera:
        """A camera at ``eye`` looking at ``target`` with the principal point at the image centre.

        Parameters
        ----------
        eye, target : array_like, shape (3,)
            Camera centre and a point on its optical axis, world coordinates.
        focal : float
            Focal length in pixels (``fx = fy``), > 0.
        width, height : int
            Image size in pixels.
        up : array_like, shape (3,)
            World direction that appears *up* in the image (the camera's ``-y`` axis);
            default ``(0, -1, 0)``, i.e. world axes equal camera axes when looking along +z.

        Returns
        -------
        Camera
            Unbatched, float64.

        Raises
        ------
        ValueError
            If ``eye == target`` or ``up`` is parallel to the viewing direction.
        """
        e = as_tensor(eye, "eye", dtype=torch.float64).reshape(-1)
        c = as_tensor(target, "target", dtype=torch.float64).reshape(-1)
        u = as_tensor(up, "up", dtype=torch.float64).reshape(-1)
        for name, v in (("eye", e), ("target", c), ("up", u)):
            check_shape(v, name, (3,))
            check_finite(v, name)
        z = c - e
        if float(z.norm()) == 0.0:
            raise ValueError("target: expected a point different from eye, got the same point")
        z = z / z.norm()
        x = torch.linalg.cross(z, u)
        if float(x.norm()) <= 1e-12 * float(u.norm()):
            raise ValueError(
                f"up: expected a direction not parallel to the view axis, got {u.tolist()}"
            )
        x = x / x.norm()
        y = torch.linalg.cross(z, x)
        R = torch.stack([x, y, z])
        t = -R @ e
        f = float(focal)
        K = torch.tensor([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
        return cls(K=K, R=R, t=t, width=width, height=height)

    # ------------------------------------------------------------------ properties
    @property
    def batch_size(self) -> int | None:
        """``B`` for a batch of cameras, None for a single camera."""
        for v, core in ((self.K, 2), (self.R, 2), (self.t, 1)):
            if v.ndim > core:
                return int(v.shape[0])
        return None

    @property
    def dtype(self) -> torch.dtype:
        """Floating dtype of ``K``, ``R`` and ``t``."""
        return self.K.dtype

    def __len__(self) -> int:
        b = self.batch_size
        if b is None:
            raise TypeError("len() of an unbatched Camera")
        return b

    def __getitem__(self, i: int) -> Camera:
        """The ``i``-th camera of a batch (unbatched Camera)."""
        b = self.batch_size
        if b is None:
            raise TypeError("indexing an unbatched Camera")
        i = check_int(i, "i", low=-b, high=b - 1)
        return Camera(
            K=self.K[i] if self.K.ndim == 3 else self.K,
            R=self.R[i] if self.R.ndim == 3 else self.R,
            t=self.t[i] if self.t.ndim == 2 else self.t,
            width=self.width,
            height=self.height,
        )

    def to(self, dtype: torch.dtype) -> Camera:
        """The same camera with ``K``, ``R``, ``t`` cast to ``dtype`` (differentiably)."""
        if not dtype.is_floating_point:
            raise TypeError(f"dtype: expected a floating dtype, got {dtype}")
        cam = object.__new__(Camera)  # already validated: skip __post_init__
        for name in ("K", "R", "t"):
            object.__setattr__(cam, name, getattr(self, name).to(dtype))
        object.__setattr__(cam, "width", self.width)
        object.__setattr__(cam, "height", self.height)
        return cam

    # ------------------------------------------------------------------ transforms
    def _bcast(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """R, t, K shaped to broadcast against ``points`` (..., N, 3) or (N, 3)."""
        b = self.batch_size
        R, t, K = self.R, self.t, self.K
        if b is None:
            return R, t, K
        R = R.expand(b, 3, 3) if R.ndim == 2 else R
        t = t.expand(b, 3) if t.ndim == 1 else t
        K = K.expand(b, 3, 3) if K.ndim == 2 else K
        if points.ndim < 2:
            raise ValueError(
                f"points: expected shape (B, N, 3) or (N, 3) for a batch of {b} cameras, "
                f"got {tuple(points.shape)}"
            )
        return R[:, None], t[:, None], K[:, None]

    def world_to_camera(self, points: Any) -> Any:
        """Map world points to camera coordinates, ``X_cam = R X + t``.

        Parameters
        ----------
        points : array_like or torch.Tensor, shape (..., 3)
            World points (scene units). For a batch of ``B`` cameras: shape (B, N, 3) or
            (N, 3) (the same points seen by every camera).

        Returns
        -------
        array or torch.Tensor, shape (..., 3) or (B, N, 3)
            Camera coordinates, same type as ``points``.

        Raises
        ------
        ValueError
            If the last dimension is not 3.
        """
        like = is_numpy_like(points)
        p = as_tensor(points, "points", dtype=self.dtype)
        check_shape(p, "points", ("...", 3))
        R, t, _ = self._bcast(p)
        out = _apply(R, p) + t
        return to_like(out, like)

    def camera_to_world(self, points: Any) -> Any:
        """Map camera coordinates to world points, ``X = R^T (X_cam - t)``.

        Parameters
        ----------
        points : array_like or torch.Tensor, shape (..., 3)
            Camera coordinates (scene units); for a batch as in :meth:`world_to_camera`.

        Returns
        -------
        array or torch.Tensor, shape (..., 3)
            World points, same type as ``points``.

        Raises
        ------
        ValueError
            If the last dimension is not 3.
        """
        like = is_numpy_like(points)
        p = as_tensor(points, "points", dtype=self.dtype)
        check_shape(p, "points", ("...", 3))
        R, t, _ = self._bcast(p)
        out = _apply(R.transpose(-1, -2), p - t)
        return to_like(out, like)

    def project_camera(self, points_cam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Project camera-space points (torch only, no validation): ``uv`` (..., 2), depth (...)."""
        _, _, K = self._bcast(points_cam)
        z = points_cam[..., 2]
        tiny = torch.where(z < 0, -_TINY_DEPTH, _TINY_DEPTH).to(z.dtype)
        safe = torch.where(z.abs() < _TINY_DEPTH, tiny, z)
        p = _apply(K, points_cam)
        uv = p[..., :2] / safe.unsqueeze(-1)
        return uv, z

    def project(self, points: Any) -> tuple[Any, Any]:
        """Project world points to pixel coordinates.

        Parameters
        ----------
        points : array_like or torch.Tensor, shape (..., 3)
            World points (scene units); for a batch as in :meth:`world_to_camera`.

        Returns
        -------
        uv : array or torch.Tensor, shape (..., 2)
            Pixel coordinates ``(x, y)`` (x right along columns, y down along rows; pixel
            ``(i, j)`` covers ``[j, j + 1) x [i, i + 1)``). Finite everywhere, meaningful
            only where ``depth > 0`` (depths closer to 0 than 1e-12 are replaced by ±1e-12).
        depth : array or torch.Tensor, shape (...)
            Camera-space ``z`` (scene units); <= 0 behind the camera.

        Raises
        ------
        ValueError
            If the last dimension of ``points`` is not 3.
        """
        like = is_numpy_like(points)
        p = as_tensor(points, "points", dtype=self.dtype)
        check_shape(p, "points", ("...", 3))
        uv, z = self.project_camera(self.world_to_camera(p))
        return to_like(uv, like), to_like(z, like)
