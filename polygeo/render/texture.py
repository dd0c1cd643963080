"""Texture maps: the UV convention, bilinear sampling in torch, and a checkerboard.

UV convention (shared by the numba kernels and this module): ``u`` runs along the texture's
columns (left to right) and ``v`` along its rows **top to bottom**, both in ``[0, 1]``
across the whole map; texel ``(row r, column c)`` of an ``(Ht, Wt)`` map has its centre at
``(u, v) = ((c + 0.5) / Wt, (r + 0.5) / Ht)``. Samples are bilinear between texel centres
and clamp to the edge outside. OBJ/OpenGL files store ``v`` upwards: convert with
``v -> 1 - v`` (:func:`flip_v`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ..checks import as_tensor, check_int, check_shape, is_numpy_like, to_like
from ._shared import bilinear_sample

__all__ = ["sample_texture", "flip_v", "checkerboard"]


def sample_texture(texture: Any, uv: Any) -> Any:
    """Bilinearly sample a texture map at UV coordinates (differentiable in torch).

    Parameters
    ----------
    texture : array_like or torch.Tensor, shape (Ht, Wt, C)
        Texture values (any unit, e.g. RGB in [0, 1]), floating.
    uv : array_like or torch.Tensor, shape (..., 2)
        Coordinates in the module's convention (``u`` along columns, ``v`` down the rows,
        [0, 1] over the map; clamp to edge outside).

    Returns
    -------
    array or torch.Tensor, shape (..., C)
        Samples, in the type of ``uv`` and the dtype of ``texture``.

    Raises
    ------
    ValueError
        On wrong shapes or an empty texture.
    TypeError
        On non-numeric input.
    """
    like = is_numpy_like(uv)
    tex = as_tensor(texture, "texture")
    check_shape(tex, "texture", ("Ht", "Wt", "C"))
    if tex.numel() == 0:
        raise ValueError(f"texture: expected a non-empty map, got shape {tuple(tex.shape)}")
    u = as_tensor(uv, "uv", dtype=tex.dtype)
    check_shape(u, "uv", ("...", 2))
    return to_like(bilinear_sample(tex, u), like)


def flip_v(uv: Any) -> Any:
    """Convert UVs between the OBJ/OpenGL (``v`` up) and this module's (``v`` down) convention.

    Parameters
    ----------
    uv : array_like or torch.Tensor, shape (..., 2)

    Returns
    -------
    array or torch.Tensor, shape (..., 2)
        ``(u, 1 - v)``, same type as ``uv``.
    """
    like = is_numpy_like(uv)
    u = as_tensor(uv, "uv")
    check_shape(u, "uv", ("...", 2))
    out = torch.stack([u[..., 0], 1.0 - u[..., 1]], dim=-1)
    return to_like(out, like)


def checkerboard(
    size: int = 256,
    checks: int = 8,
    colors: Any = ((0.9, 0.2, 0.1), (0.1, 0.3, 0.9)),
    *,
    smooth: bool = False,
) -> np.ndarray:
    """A checkerboard texture, useful for SfT-like tests and benchmarks.

    Parameters
    ----------
    size : int
        Side in texels, >= 1.
    checks : int
        Number of squares along each side, >= 1.
    colors : array_like, shape (2, C)
        Colours of the two kinds of squares.
    smooth : bool
        Multiply by a smooth low-frequency shading so that no two squares look alike.

    Returns
    -------
    np.ndarray, shape (size, size, C), float64

    Raises
    ------
    ValueError
        If ``colors`` is not (2, C) or the sizes are < 1.
    """
    n = check_int(size, "size", low=1)
    k = check_int(checks, "checks", low=1)
    col = np.asarray(colors, dtype=np.float64)
    if col.ndim != 2 or col.shape[0] != 2:
        raise ValueError(f"colors: expected shape (2, C), got {col.shape}")
    r = (np.arange(n) + 0.5) / n
    cell = (np.floor(r * k)[:, None] + np.floor(r * k)[None, :]).astype(np.int64) % 2
    tex = col[cell]
    if smooth:
        shade = 0.75 + 0.25 * np.sin(2 * np.pi * r)[:, None] * np.cos(3 * np.pi * r)[None, :]
        tex = tex * shade[..., None]
    return tex
