"""Differentiable soft rasterization on the CPU (SoftRas-style), with numba kernels.

For every pixel centre ``q`` and every face ``f`` whose projected triangle comes within the
blur margin of ``q``:

* coverage ``D_f = sigmoid(delta * d² / sigma)``, ``d`` the distance in pixels from ``q``
  to the triangle's boundary, ``delta`` = +1 inside and -1 outside;
* silhouette ``alpha = 1 - prod_f (1 - D_f)``;
* colour: perspective-correct barycentrics (clamped to the triangle and renormalised
  outside it) interpolate per-vertex colours or UVs (then a bilinear texture lookup), and
  the colours are blended by the SoftRas softmax over normalised depth
  ``zn = (zfar - z) / (zfar - znear)`` with weights ``D_f exp(zn_f / gamma)`` plus a
  background term ``exp(background_depth / gamma)``.

Faces are binned into screen tiles by their bounding boxes grown by the blur margin, so
the work is proportional to the faces that reach each tile. The forward pass keeps only
per-pixel aggregates; the backward pass recomputes the per-face terms (no per-pixel x
per-face tensor is ever stored). Faces with any vertex closer than ``znear`` are culled
(not clipped); faces with a projected area below ``min_area`` are skipped. Every face
within the blur margin of a pixel is aggregated (exact SoftRas; there is no top-K cap).

Threads: the kernels run in parallel over tiles on ``numba.get_num_threads()`` threads
(small renders run on the calling thread). On an oversubscribed machine (more busy
processes than cores) one thread is usually faster: ``numba.set_num_threads(1)``, or set
``OMP_WAIT_POLICY=PASSIVE`` before starting Python when numba uses the OpenMP layer.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any, NamedTuple

import numba
import numpy as np
import torch

from ..checks import check_shape, is_numpy_like
from . import _kernels as K
from ._shared import (
    bilinear_sample,
    finish_output,
    interp_at,
    prepare_scene,
    vertex_attributes,
)
from .camera import Camera
from .settings import RasterSettings

__all__ = ["RenderOutput", "render", "render_silhouette", "rasterize_faces", "project_faces"]


class RenderOutput(NamedTuple):
    """Result of :func:`render` (leading ``B`` only for batched input).

    Attributes
    ----------
    rgb : array or torch.Tensor, shape ([B,] H, W, C)
        Colour (same unit as the colours or texture), background where nothing is drawn.
    alpha : array or torch.Tensor, shape ([B,] H, W)
        Soft silhouette in [0, 1] (binary in hard mode).
    depth : array or torch.Tensor, shape ([B,] H, W), optional
        Camera depth of the nearest face whose triangle contains the pixel centre (scene
        units), 0 where there is none. Differentiable w.r.t. vertex positions.
    face_index : array or torch.Tensor, shape ([B,] H, W), int64, optional
        Index of that face, -1 where there is none.
    """

    rgb: Any
    alpha: Any
    depth: Any = None
    face_index: Any = None


class _Config:
    """Everything the kernels need besides tensors (kept on ``ctx``)."""

    def __init__(self, settings: RasterSettings, H: int, W: int, mode: int, C: int):
        self.s = settings
        self.H = H
        self.W = W
        self.mode = mode
        self.C = C
        margin = settings.blur_margin
        self.margin = margin
        self.cutoff = margin * margin if np.isfinite(margin) else np.inf
        # the kernels index the background only in colour modes; keep one value otherwise
        self.bg = settings.background_for(C) if C else np.zeros(1)


def _setup(fv_np: np.ndarray, s: RasterSettings, H: int, W: int, margin: float):
    B, F = fv_np.shape[:2]
    fd = np.zeros((B, F, K.NFD))
    valid = np.zeros((B, F), dtype=np.uint8)
    K.face_setup(fv_np, s.znear, 2.0 * s.min_area, bool(s.cull_backfaces), fd, valid)
    bin_off, bin_f = K.bin_faces(fd, valid, H, W, s.tile_size, margin)
    return fd, bin_off, bin_f


# Below this many (pixel, candidate face) pairs a kernel runs on the calling thread only:
# starting the parallel region costs more than it saves (a lot more on a loaded machine).
_SERIAL_WORK = 1 << 16


@contextmanager
def _threads(work: int) -> Iterator[int]:
    """Run the enclosed numba kernels on 1 thread for small work, else on the current setting."""
    n = numba.get_num_threads()
    use = 1 if work < _SERIAL_WORK else n
    if use != n:
        numba.set_num_threads(use)
    try:
        yield use
    finally:
        if use != n:
            numba.set_num_threads(n)


def _work(bin_f: np.ndarray, ts: int) -> int:
    return int(bin_f.shape[0]) * ts * ts


def _np64(t: torch.Tensor | None, shape: tuple[int, ...]) -> np.ndarray:
    if t is None:
        return np.zeros(shape)
    return np.ascontiguousarray(t.detach().cpu().to(torch.float64).numpy())


class _SoftRasterize(torch.autograd.Function):
    """Private autograd function: face vertices in screen space -> (alpha, rgb)."""

    @staticmethod
    def forward(ctx, fv, attr, uvs, tex, cfg):  # noqa: D102
        s = cfg.s
        fv_np = _np64(fv, ())
        B = fv_np.shape[0]
        H, W, C = cfg.H, cfg.W, cfg.C
        fd, bin_off, bin_f = _setup(fv_np, s, H, W, cfg.margin)
        attr_np = _np64(attr, (1, 1, 3, 1))
        uvs_np = _np64(uvs, (1, 1, 3, 2))
        tex_np = _np64(tex, (1, 1, 1))
        P = np.empty((B, H, W))
        if cfg.mode == K.MODE_SILHOUETTE:
            m = Z = np.empty((1, 1, 1))
            rgb = np.empty((1, 1, 1, 1))
        else:
            m = np.empty((B, H, W))
            Z = np.empty((B, H, W))
            rgb = np.empty((B, H, W, C))
        with _threads(_work(bin_f, s.tile_size)):
            K.soft_forward(
                fd, bin_off, bin_f, H, W, s.tile_size, cfg.margin, cfg.cutoff, s.sigma,
                1.0 / s.gamma, s.znear, s.zfar, s.background_depth, cfg.bg, cfg.mode,
                attr_np, uvs_np, tex_np, P, m, Z, rgb,
            )  # fmt: skip
        ctx.cfg = cfg
        ctx.arrays = (fd, bin_off, bin_f, attr_np, uvs_np, tex_np, P, m, Z, rgb)
        ctx.shapes = (fv.shape, fv.dtype)
        ctx.has = (attr is not None, uvs is not None, tex is not None)
        dtype = fv.dtype
        alpha = torch.from_numpy(1.0 - P).to(dtype)
        if cfg.mode == K.MODE_SILHOUETTE:
            out_rgb = torch.zeros((B, H, W, 0), dtype=dtype)
        else:
            out_rgb = torch.from_numpy(rgb).to(dtype)
        return alpha, out_rgb

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_alpha, g_rgb):  # noqa: D102
        cfg = ctx.cfg
        s = cfg.s
        fd, bin_off, bin_f, attr_np, uvs_np, tex_np, P, m, Z, rgb = ctx.arrays
        fv_shape, dtype = ctx.shapes
        B, F = fv_shape[0], fv_shape[1]
        H, W, C = cfg.H, cfg.W, cfg.C
        has_attr, has_uv, has_tex = ctx.has
        need_attr = has_attr and ctx.needs_input_grad[1]
        need_uv = has_uv and ctx.needs_input_grad[2]
        need_tex = has_tex and ctx.needs_input_grad[3]
        ga = _np64(g_alpha, (B, H, W)) if g_alpha is not None else np.zeros((B, H, W))
        if cfg.mode == K.MODE_SILHOUETTE or g_rgb is None:
            gr = np.zeros((B, H, W, max(C, 1)) if cfg.mode != K.MODE_SILHOUETTE else (1, 1, 1, 1))
        else:
            gr = _np64(g_rgb, ())
        with _threads(_work(bin_f, s.tile_size)) as nthreads:
            nch = max(1, min(nthreads, bin_off.shape[0] - 1))  # one gradient buffer per chunk
            g_fv = np.zeros((nch, B, F, 3, 3))
            g_attr = np.zeros((nch, *attr_np.shape)) if need_attr else np.zeros((nch, 1, 1, 3, 1))
            g_uv = np.zeros((nch, *uvs_np.shape)) if need_uv else np.zeros((nch, 1, 1, 3, 2))
            g_tex = np.zeros((nch, *tex_np.shape)) if need_tex else np.zeros((nch, 1, 1, 1))
            K.soft_backward(
                fd, bin_off, bin_f, H, W, s.tile_size, cfg.margin, cfg.cutoff, s.sigma,
                1.0 / s.gamma, s.znear, s.zfar, cfg.mode, attr_np, uvs_np, tex_np, P, m, Z, rgb,
                ga, gr, need_attr, need_uv, need_tex, g_fv, g_attr, g_uv, g_tex,
            )  # fmt: skip
        out_fv = torch.from_numpy(g_fv.sum(0)).to(dtype) if ctx.needs_input_grad[0] else None
        out_attr = torch.from_numpy(g_attr.sum(0)).to(dtype) if need_attr else None
        out_uv = torch.from_numpy(g_uv.sum(0)).to(dtype) if need_uv else None
        out_tex = torch.from_numpy(g_tex.sum(0)).to(dtype) if need_tex else None
        return out_fv, out_attr, out_uv, out_tex, None


# ---------------------------------------------------------------------------- helpers


def _nearest(fv: torch.Tensor, s: RasterSettings, H: int, W: int, margin: float) -> torch.Tensor:
    fv_np = _np64(fv, ())
    fd, bin_off, bin_f = _setup(fv_np, s, H, W, margin)
    B = fv_np.shape[0]
    idx = np.empty((B, H, W), dtype=np.int64)
    depth = np.empty((B, H, W))
    K.nearest_face(fd, bin_off, bin_f, H, W, s.tile_size, idx, depth)
    return torch.from_numpy(idx)


def _shade_hard(
    pb: torch.Tensor,
    idx: torch.Tensor,
    mask: torch.Tensor,
    attr: torch.Tensor | None,
    uvs: torch.Tensor | None,
    tex: torch.Tensor | None,
    bg: torch.Tensor,
) -> torch.Tensor:
    B, H, W = idx.shape
    safe = idx.clamp_min(0)
    if attr is not None:
        ab = torch.arange(B).view(B, 1, 1) if attr.shape[0] > 1 else torch.zeros(1, 1, 1).long()
        if attr.shape[1] == 0:
            col = bg.expand(B, H, W, -1)
        else:
            pa = attr[ab.expand(B, H, W), safe]  # (B, H, W, 3, C)
            col = (pb.unsqueeze(-1) * pa).sum(-2)
    else:
        ub = torch.arange(B).view(B, 1, 1) if uvs.shape[0] > 1 else torch.zeros(1, 1, 1).long()
        if uvs.shape[1] == 0:
            col = bg.expand(B, H, W, -1)
        else:
            pu = uvs[ub.expand(B, H, W), safe]  # (B, H, W, 3, 2)
            col = bilinear_sample(tex, (pb.unsqueeze(-1) * pu).sum(-2))
    return torch.where(mask.unsqueeze(-1), col, bg.to(col.dtype))


# ---------------------------------------------------------------------------- public API


def rasterize_faces(
    face_verts: torch.Tensor,
    height: int,
    width: int,
    settings: RasterSettings | None = None,
    *,
    face_colors: torch.Tensor | None = None,
    face_uvs: torch.Tensor | None = None,
    texture: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Low-level soft rasterization of screen-space triangles (torch only).

    Parameters
    ----------
    face_verts : torch.Tensor, shape (B, F, 3, 3)
        Per face and vertex ``(x, y, z)``: pixel coordinates and camera depth (scene units).
    height, width : int
        Image size in pixels.
    settings : RasterSettings, optional
        Defaults to ``RasterSettings()``. ``hard`` is ignored here.
    face_colors : torch.Tensor, shape (B or 1, F, 3, C), optional
        Per face-vertex colours.
    face_uvs : torch.Tensor, shape (B or 1, F, 3, 2), optional
        Per face-vertex UVs (with ``texture``).
    texture : torch.Tensor, shape (Ht, Wt, C), optional

    Returns
    -------
    alpha : torch.Tensor, shape (B, H, W)
    rgb : torch.Tensor, shape (B, H, W, C) or None
        None when neither colours nor a texture are given.

    Raises
    ------
    ValueError
        On inconsistent shapes.
    """
    s = RasterSettings() if settings is None else settings
    check_shape(face_verts, "face_verts", ("B", "F", 3, 3))
    if face_colors is not None:
        mode, C = K.MODE_VERTEX, int(face_colors.shape[-1])
        check_shape(face_colors, "face_colors", (None, face_verts.shape[1], 3, "C"))
    elif texture is not None:
        mode, C = K.MODE_TEXTURE, int(texture.shape[-1])
        if face_uvs is None:
            raise ValueError("face_uvs: expected (B, F, 3, 2) UVs with a texture, got None")
        check_shape(face_uvs, "face_uvs", (None, face_verts.shape[1], 3, 2))
        check_shape(texture, "texture", ("Ht", "Wt", "C"))
    else:
        mode, C = K.MODE_SILHOUETTE, 0
    cfg = _Config(s, int(height), int(width), mode, C)
    alpha, rgb = _SoftRasterize.apply(face_verts, face_colors, face_uvs, texture, cfg)
    return alpha, (rgb if mode != K.MODE_SILHOUETTE else None)


def render(
    vertices: Any,
    faces: Any,
    camera: Camera,
    settings: RasterSettings | None = None,
    *,
    colors: Any = None,
    uvs: Any = None,
    texture: Any = None,
    return_depth: bool = False,
    return_face_index: bool = False,
    coords: str = "world",
) -> RenderOutput:
    """Render a triangle mesh (or a batch of ``B`` meshes/frames) with soft rasterization.

    Parameters
    ----------
    vertices : array_like or torch.Tensor, shape (V, 3) or (B, V, 3)
        Vertex positions (scene units) in world coordinates, or camera coordinates when
        ``coords="camera"``. Must be finite.
    faces : array_like or torch.Tensor, shape (F, 3), integer
        Vertex indices of the triangles (shared by the batch). ``F = 0`` is allowed.
    camera : Camera
        Single or batched (``B`` cameras); image size ``(camera.height, camera.width)``.
    settings : RasterSettings, optional
        Defaults to ``RasterSettings()``.
    colors : array_like or torch.Tensor, shape (V, C) or (B, V, C), optional
        Per-vertex colours (any unit), interpolated perspective-correctly.
    uvs : array_like or torch.Tensor, shape (V, 2) or (F, 3, 2), optional
        Texture coordinates (see :mod:`polygeo.render.texture` for the convention), per
        vertex or per face corner; required with ``texture``.
    texture : array_like or torch.Tensor, shape (Ht, Wt, C), optional
        Texture map, sampled bilinearly. Give ``colors`` or ``texture`` (not both); with
        neither, ``rgb`` is an empty (..., 0) array (use :func:`render_silhouette`).
    return_depth, return_face_index : bool
        Also return the hard (z-buffer) depth and face index per pixel.
    coords : {"world", "camera"}
        Frame of ``vertices``.

    Returns
    -------
    RenderOutput
        ``rgb`` ([B,] H, W, C), ``alpha`` ([B,] H, W), optionally ``depth`` and
        ``face_index``; NumPy arrays when ``vertices`` is a NumPy array, else tensors of the
        dtype of ``vertices``, differentiable w.r.t. ``vertices``, ``colors``, ``uvs``,
        ``texture`` and the camera's tensors.

    Raises
    ------
    ValueError
        On wrong shapes, non-finite values, out-of-range face indices, both ``colors`` and
        ``texture``, ``uvs`` without ``texture`` (or the reverse), or a background colour
        whose length does not match ``C``.
    TypeError
        On a camera that is not a :class:`Camera`, settings that are not
        :class:`RasterSettings` or non-integer faces.
    """
    like = is_numpy_like(vertices)
    v, f, fv, cam, s, B, batched = prepare_scene(vertices, faces, camera, settings, coords)
    attr, uv_f, tex, C, mode = vertex_attributes(colors, uvs, texture, v, f, B, s)
    H, W = cam.height, cam.width
    depth = idx = None
    if s.hard:
        idx = _nearest(fv, s, H, W, 0.0)
        mask, pb, dep = interp_at(fv, idx, H, W)
        alpha = mask.to(v.dtype)
        if mode == K.MODE_SILHOUETTE:
            rgb = torch.zeros((B, H, W, 0), dtype=v.dtype)
        else:
            bg = torch.as_tensor(s.background_for(C), dtype=v.dtype)
            rgb = _shade_hard(pb, idx, mask, attr, uv_f, tex, bg)
        depth = dep if return_depth else None
    else:
        cfg = _Config(s, H, W, mode, C)
        alpha, rgb = _SoftRasterize.apply(fv, attr, uv_f, tex, cfg)
        if return_depth or return_face_index:
            idx = _nearest(fv, s, H, W, 0.0)
            if return_depth:
                depth = interp_at(fv, idx, H, W)[2]
    return RenderOutput(
        rgb=finish_output(rgb, batched, like),
        alpha=finish_output(alpha, batched, like),
        depth=finish_output(depth, batched, like),
        face_index=finish_output(idx, batched, like) if return_face_index else None,
    )


def render_silhouette(
    vertices: Any,
    faces: Any,
    camera: Camera,
    settings: RasterSettings | None = None,
    *,
    coords: str = "world",
) -> Any:
    """Soft silhouette ``alpha = 1 - prod_f (1 - D_f)`` of a mesh (or a batch).

    Parameters
    ----------
    vertices : array_like or torch.Tensor, shape (V, 3) or (B, V, 3)
        Vertex positions (scene units), world or camera coordinates (``coords``).
    faces : array_like or torch.Tensor, shape (F, 3), integer
    camera : Camera
    settings : RasterSettings, optional
    coords : {"world", "camera"}

    Returns
    -------
    array or torch.Tensor, shape ([B,] H, W)
        Coverage in [0, 1]; binary in hard mode. Type of ``vertices``.

    Raises
    ------
    ValueError, TypeError
        As :func:`render`.
    """
    return render(vertices, faces, camera, settings, coords=coords).alpha


def project_faces(
    vertices: Any,
    faces: Any,
    camera: Camera,
    settings: RasterSettings | None = None,
    *,
    coords: str = "world",
) -> Any:
    """Screen-space face vertices of a mesh: the input of :func:`rasterize_faces`.

    Parameters
    ----------
    vertices : array_like or torch.Tensor, shape (V, 3) or (B, V, 3)
        Vertex positions (scene units), world or camera coordinates (``coords``). Finite.
    faces : array_like or torch.Tensor, shape (F, 3), integer
        Vertex indices of the triangles. ``F = 0`` is allowed.
    camera : Camera
        Single or batched (``B`` cameras).
    settings : RasterSettings, optional
        Only ``znear`` is read: vertices closer than it are projected at depth 1 (they
        belong to faces the rasterizer culls), so the result stays finite.
    coords : {"world", "camera"}
        Frame of ``vertices``.

    Returns
    -------
    array or torch.Tensor, shape ([B,] F, 3, 3)
        Per face and corner ``(x, y, z)``: pixel coordinates (origin at the top-left image
        corner) and camera depth (scene units; the true depth, also for culled faces).
        Type and dtype of ``vertices``; differentiable w.r.t. ``vertices`` and the camera.

    Raises
    ------
    ValueError, TypeError
        As :func:`render`.
    """
    like = is_numpy_like(vertices)
    _, _, fv, _, _, _, batched = prepare_scene(vertices, faces, camera, settings, coords)
    return finish_output(fv, batched, like)
