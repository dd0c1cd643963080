"""Helpers shared by the modules of :mod:`polygeo.mesh` (package-private: not public API)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ..checks import as_tensor, check_faces, check_shape, is_numpy_like


def faces_array(faces: Any, n_vertices: int | None = None) -> tuple[np.ndarray, bool]:
    """Checked faces as an int64 NumPy array, and whether the input was NumPy-like."""
    return check_faces(faces, n_vertices).cpu().numpy(), is_numpy_like(faces)


def unique_pairs(pairs: np.ndarray, inverse: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """``np.unique(pairs, axis=0, return_inverse=True)`` for (n, 2) non-negative int64 rows.

    Rows are encoded as one int64 key ``a * m + b`` (lexicographic order preserved) and sorted
    once, which is about 100 times faster than NumPy's row-wise unique on mesh-sized inputs.
    """
    m = int(pairs.max()) + 1
    key = pairs[:, 0] * m + pairs[:, 1]
    order = np.argsort(key, kind="stable") if inverse else None
    ks = key[order] if inverse else np.sort(key)
    first = np.empty(ks.shape, bool)
    first[:1] = True
    np.not_equal(ks[1:], ks[:-1], out=first[1:])
    keys = ks[first]
    inv = None
    if inverse:
        inv = np.empty(key.shape, np.int64)
        inv[order] = np.cumsum(first) - 1
    return np.stack([keys // m, keys % m], axis=1), inv


def as_output(arr: np.ndarray, numpy_in: bool) -> Any:
    return arr if numpy_in else torch.from_numpy(np.ascontiguousarray(arr))


def checked_vertices(vertices: Any) -> tuple[torch.Tensor, bool]:
    numpy_in = is_numpy_like(vertices)
    v = as_tensor(vertices, "vertices")
    check_shape(v, "vertices", ("...", "N", 3))
    return v, numpy_in


def faces_tensor(faces: Any, n: int) -> torch.Tensor:
    return check_faces(faces, n).cpu()


def safe_norm(x: torch.Tensor, eps: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Norm along the last axis and a mask ``norm > eps`` with NaN-free gradients."""
    sq = (x * x).sum(-1)
    ok = sq > eps * eps
    n = torch.sqrt(torch.where(ok, sq, torch.ones_like(sq)))
    return torch.where(ok, n, torch.zeros_like(n)), ok


def tiny_eps(v: torch.Tensor) -> float:
    return float(torch.finfo(v.dtype).tiny) ** 0.5


def corners(v: torch.Tensor, f: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    return v[..., f[:, 0], :], v[..., f[:, 1], :], v[..., f[:, 2], :]
