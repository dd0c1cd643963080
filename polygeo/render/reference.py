"""Naive dense soft rasterizer in pure torch: the correctness oracle and speed baseline.

Every pixel is compared with every face through broadcast ``(B, P, F)`` tensors and the
gradients come from torch's autograd: nothing is shared with the numba kernels except the
definition of the result (same coverage, cut-off, culling and colour blending, see
:mod:`polygeo.render.soft`). Memory grows as ``pixels x faces``; ``chunk_rows`` renders a
band of image rows at a time under activation checkpointing to bound it (at the price of
recomputing the forward pass during the backward pass).
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as tnf
from torch.utils.checkpoint import checkpoint

from ..checks import is_numpy_like
from ._shared import (
    bilinear_sample,
    finish_output,
    interp_at,
    prepare_scene,
    vertex_attributes,
)
from .camera import Camera
from .settings import RasterSettings
from .soft import RenderOutput

__all__ = ["soft_rasterize_dense", "nearest_face_dense", "render_reference"]


def _pixel_centres(H: int, W: int, row0: int, row1: int, dtype: torch.dtype) -> torch.Tensor:
    ys = torch.arange(row0, row1, dtype=dtype) + 0.5
    xs = torch.arange(W, dtype=dtype) + 0.5
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([gx.reshape(-1), gy.reshape(-1)], dim=-1)  # (P, 2)


def _valid_faces(fv: torch.Tensor, s: RasterSettings) -> tuple[torch.Tensor, torch.Tensor]:
    p = fv[..., :2]
    area2 = (p[..., 1, 0] - p[..., 0, 0]) * (p[..., 2, 1] - p[..., 0, 1]) - (
        p[..., 2, 0] - p[..., 0, 0]
    ) * (p[..., 1, 1] - p[..., 0, 1])
    valid = (fv[..., 2] >= s.znear).all(-1) & (area2.abs() > 2.0 * s.min_area)
    if s.cull_backfaces:
        valid = valid & (area2 <= 0)
    return valid, area2


def _band(fv, q, s, attr, uvs, tex, bg):
    """Dense soft rasterization of the pixels ``q`` (P, 2); returns alpha (B, P), rgb (B, P, C)."""
    valid, area2 = _valid_faces(fv, s)  # (B, F)
    xy = fv[..., :2].unsqueeze(1) - q.view(1, -1, 1, 1, 2)  # (B, P, F, 3, 2) vertex - q
    x, y = xy[..., 0], xy[..., 1]
    e0 = x[..., 1] * y[..., 2] - x[..., 2] * y[..., 1]
    e1 = x[..., 2] * y[..., 0] - x[..., 0] * y[..., 2]
    e2 = x[..., 0] * y[..., 1] - x[..., 1] * y[..., 0]
    a_safe = torch.where(valid, area2, torch.ones_like(area2)).unsqueeze(1)
    w = torch.stack([e0, e1, e2], dim=-1) / a_safe.unsqueeze(-1)  # (B, P, F, 3)
    inside = (w >= 0).all(-1)
    # distance to the three edges (vertex k -> vertex k + 1)
    a = fv[..., :2]  # (B, F, 3, 2)
    b = torch.roll(a, shifts=-1, dims=-2)
    e = b - a
    l2 = (e * e).sum(-1)  # (B, F, 3)
    l2 = torch.where(l2 > 0, l2, torch.ones_like(l2))
    qa = -xy  # q - a, (B, P, F, 3, 2)
    t = ((qa * e.unsqueeze(1)).sum(-1) / l2.unsqueeze(1)).clamp(0.0, 1.0)
    r = qa - t.unsqueeze(-1) * e.unsqueeze(1)
    d2 = (r * r).sum(-1).amin(-1)  # (B, P, F)
    margin = s.blur_margin
    cutoff = margin * margin
    used = valid.unsqueeze(1) & (inside | (d2 <= cutoff))
    xarg = torch.where(inside, d2, -d2) / s.sigma
    log_keep = torch.where(used, tnf.logsigmoid(-xarg), torch.zeros_like(xarg))
    alpha = 1.0 - torch.exp(log_keep.sum(-1))
    if attr is None and tex is None:
        return alpha, None
    c = w.clamp(0.0, 1.0)
    c = c / c.sum(-1, keepdim=True).clamp_min(1e-300)
    c = torch.where(used.unsqueeze(-1), c, torch.full_like(c, 1.0 / 3.0))  # unused: any finite
    z = torch.where(valid.unsqueeze(-1), fv[..., 2], torch.ones_like(fv[..., 2])).unsqueeze(1)
    u = c / z
    U = u.sum(-1)
    pb = u / U.unsqueeze(-1)  # (B, P, F, 3)
    zp = 1.0 / U
    zn = (s.zfar - zp) / (s.zfar - s.znear)
    if attr is not None:
        col = torch.einsum("bpfk,bfkc->bpfc", pb, attr.expand(fv.shape[0], *attr.shape[1:]))
    else:
        uvb = uvs.expand(fv.shape[0], *uvs.shape[1:])
        col = bilinear_sample(tex, torch.einsum("bpfk,bfkc->bpfc", pb, uvb))
    logit = torch.where(used, zn, torch.full_like(zn, -torch.inf))
    m = torch.maximum(logit.amax(-1), torch.full_like(logit[..., 0], s.background_depth))
    m = m.detach().unsqueeze(-1)
    ez = torch.exp(torch.where(used, (zn - m) / s.gamma, torch.full_like(zn, -torch.inf)))
    wgt = torch.sigmoid(xarg) * ez  # (B, P, F)
    wbg = torch.exp((s.background_depth - m[..., 0]) / s.gamma)  # (B, P)
    num = (wgt.unsqueeze(-1) * col).sum(-2) + wbg.unsqueeze(-1) * bg
    den = wgt.sum(-1) + wbg
    return alpha, num / den.unsqueeze(-1)


def soft_rasterize_dense(
    face_verts: torch.Tensor,
    height: int,
    width: int,
    settings: RasterSettings | None = None,
    *,
    face_colors: torch.Tensor | None = None,
    face_uvs: torch.Tensor | None = None,
    texture: torch.Tensor | None = None,
    chunk_rows: int | None = None,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Dense counterpart of :func:`polygeo.render.rasterize_faces` (same arguments).

    Parameters
    ----------
    face_verts : torch.Tensor, shape (B, F, 3, 3)
        Per face and vertex ``(x, y, z)``: pixels and camera depth.
    height, width : int
        Image size in pixels.
    settings : RasterSettings, optional
    face_colors : torch.Tensor, shape (B or 1, F, 3, C), optional
    face_uvs : torch.Tensor, shape (B or 1, F, 3, 2), optional
    texture : torch.Tensor, shape (Ht, Wt, C), optional
    chunk_rows : int, optional
        Render this many image rows at a time with activation checkpointing (bounded
        memory); None renders the whole image at once.

    Returns
    -------
    alpha : torch.Tensor, shape (B, H, W)
    rgb : torch.Tensor, shape (B, H, W, C) or None
    """
    s = RasterSettings() if settings is None else settings
    B = face_verts.shape[0]
    H, W = int(height), int(width)
    dtype = face_verts.dtype
    C = (
        face_colors.shape[-1]
        if face_colors is not None
        else (texture.shape[-1] if texture is not None else 0)
    )
    bg = torch.as_tensor(s.background_for(C) if C else [0.0], dtype=dtype)
    rows = H if chunk_rows is None else max(1, int(chunk_rows))
    alphas, rgbs = [], []
    for r0 in range(0, H, rows):
        r1 = min(H, r0 + rows)
        q = _pixel_centres(H, W, r0, r1, dtype)
        if chunk_rows is None:
            al, rg = _band(face_verts, q, s, face_colors, face_uvs, texture, bg)
        else:
            al, rg = checkpoint(
                _band, face_verts, q, s, face_colors, face_uvs, texture, bg, use_reentrant=False
            )
        alphas.append(al.reshape(B, r1 - r0, W))
        if rg is not None:
            rgbs.append(rg.reshape(B, r1 - r0, W, -1))
    alpha = torch.cat(alphas, dim=1)
    rgb = torch.cat(rgbs, dim=1) if rgbs else None
    return alpha, rgb


def nearest_face_dense(
    face_verts: torch.Tensor, height: int, width: int, settings: RasterSettings | None = None
) -> torch.Tensor:
    """Dense z-buffer: index of the nearest face containing each pixel centre (-1 if none).

    Parameters
    ----------
    face_verts : torch.Tensor, shape (B, F, 3, 3)
    height, width : int
    settings : RasterSettings, optional
        Culling settings (``znear``, ``min_area``, ``cull_backfaces``).

    Returns
    -------
    torch.Tensor, shape (B, H, W), int64
    """
    s = RasterSettings() if settings is None else settings
    fv = face_verts.detach()
    B, F = fv.shape[:2]
    H, W = int(height), int(width)
    if F == 0:
        return torch.full((B, H, W), -1, dtype=torch.long)
    q = _pixel_centres(H, W, 0, H, fv.dtype)
    valid, area2 = _valid_faces(fv, s)
    xy = fv[..., :2].unsqueeze(1) - q.view(1, -1, 1, 1, 2)
    x, y = xy[..., 0], xy[..., 1]
    e = torch.stack(
        [
            x[..., 1] * y[..., 2] - x[..., 2] * y[..., 1],
            x[..., 2] * y[..., 0] - x[..., 0] * y[..., 2],
            x[..., 0] * y[..., 1] - x[..., 1] * y[..., 0],
        ],
        dim=-1,
    )
    a_safe = torch.where(valid, area2, torch.ones_like(area2)).view(B, 1, F, 1)
    w = e / a_safe
    inside = (w >= 0).all(-1) & valid.unsqueeze(1)
    z = torch.where(valid.unsqueeze(-1), fv[..., 2], torch.ones_like(fv[..., 2])).unsqueeze(1)
    zp = 1.0 / (w / z).sum(-1)
    zp = torch.where(inside, zp, torch.full_like(zp, torch.inf))
    best = zp.argmin(-1)
    idx = torch.where(inside.any(-1), best, torch.full_like(best, -1))
    return idx.view(B, H, W)


def render_reference(
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
    chunk_rows: int | None = None,
) -> RenderOutput:
    """Dense counterpart of :func:`polygeo.render.render` (same arguments and result).

    Parameters
    ----------
    vertices, faces, camera, settings, colors, uvs, texture, return_depth, return_face_index, coords
        As :func:`polygeo.render.render`.
    chunk_rows : int, optional
        Rows per checkpointed band (bounded memory), None for the whole image at once.

    Returns
    -------
    RenderOutput

    Raises
    ------
    ValueError, TypeError
        As :func:`polygeo.render.render`.
    """
    like = is_numpy_like(vertices)
    v, f, fv, cam, s, B, batched = prepare_scene(vertices, faces, camera, settings, coords)
    attr, uv_f, tex, C, mode = vertex_attributes(colors, uvs, texture, v, f, B, s)
    H, W = cam.height, cam.width
    depth = idx = None
    if s.hard:
        idx = nearest_face_dense(fv, H, W, s)
        mask, pb, dep = interp_at(fv, idx, H, W)
        alpha = mask.to(v.dtype)
        if C == 0:
            rgb = torch.zeros((B, H, W, 0), dtype=v.dtype)
        else:
            bg = torch.as_tensor(s.background_for(C), dtype=v.dtype)
            safe = idx.clamp_min(0)
            bidx = torch.arange(B).view(B, 1, 1).expand(B, H, W)
            if attr is not None and attr.shape[1] > 0:
                pa = attr.expand(B, *attr.shape[1:])[bidx, safe]
                col = (pb.unsqueeze(-1) * pa).sum(-2)
            elif uv_f is not None and uv_f.shape[1] > 0:
                pu = uv_f.expand(B, *uv_f.shape[1:])[bidx, safe]
                col = bilinear_sample(tex, (pb.unsqueeze(-1) * pu).sum(-2))
            else:
                col = bg.expand(B, H, W, C)
            rgb = torch.where(mask.unsqueeze(-1), col, bg)
        depth = dep if return_depth else None
    else:
        alpha, rgb = soft_rasterize_dense(
            fv, H, W, s, face_colors=attr, face_uvs=uv_f, texture=tex, chunk_rows=chunk_rows
        )
        if rgb is None:
            rgb = torch.zeros((B, H, W, 0), dtype=v.dtype)
        if return_depth or return_face_index:
            idx = nearest_face_dense(fv, H, W, s)
            if return_depth:
                depth = interp_at(fv, idx, H, W)[2]
    return RenderOutput(
        rgb=finish_output(rgb, batched, like),
        alpha=finish_output(alpha, batched, like),
        depth=finish_output(depth, batched, like),
        face_index=finish_output(idx, batched, like) if return_face_index else None,
    )
