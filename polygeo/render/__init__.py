"""Differentiable soft rasterizer for the CPU (SoftRas-style, numba kernels).

Conventions: OpenCV pinhole camera (x right, y down, z forward; intrinsics in pixels; image
origin at the top-left pixel corner, pixel ``(i, j)`` centred at ``(j + 0.5, i + 0.5)``).
``sigma`` is in pixels² (see :class:`RasterSettings`). Public entry points accept NumPy or
torch and return the input's type.

Main entry points: :class:`Camera`, :class:`RasterSettings`, :func:`render`,
:func:`render_silhouette`, :func:`project_faces` (screen-space faces for
:func:`rasterize_faces`), the losses :func:`silhouette_loss`, :func:`rgb_loss`,
:func:`soft_iou`, and the dense oracle :func:`render_reference`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from polygeo.lazy import attach

if TYPE_CHECKING:
    from .camera import Camera
    from .losses import iou, rgb_loss, silhouette_loss, soft_iou
    from .reference import render_reference
    from .settings import RasterSettings, sigma_from_softras
    from .soft import RenderOutput, project_faces, rasterize_faces, render, render_silhouette
    from .texture import checkerboard, flip_v, sample_texture

__getattr__, __dir__ = attach(__name__, __file__)

__all__ = [
    "Camera",
    "RasterSettings",
    "RenderOutput",
    "render",
    "render_silhouette",
    "rasterize_faces",
    "project_faces",
    "render_reference",
    "silhouette_loss",
    "rgb_loss",
    "soft_iou",
    "iou",
    "sample_texture",
    "flip_v",
    "checkerboard",
    "sigma_from_softras",
]
