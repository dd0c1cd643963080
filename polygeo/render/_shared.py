"""Scene preparation and per-pixel interpolation shared by the rasterizers.

Package-private: :mod:`polygeo.render.soft` (the fast numba rasterizer),
:mod:`polygeo.render.reference` (the dense oracle) and :mod:`polygeo.render.texture` call
these functions, so the two rasterizers validate, project and shade their input the same way.
Users call the public front ends (:func:`polygeo.render.render`,
:func:`polygeo.render.project_faces`, :func:`polygeo.render.sample_texture`).
"""

from __future__ import annotations

import torch

from ..checks import as_tensor, check_choice, check_faces, check_finite, check_shape
from . import _kernels as K
from .camera import Camera
from .settings import RasterSettings

__all__ = [
    "prepare_scene",
    "vertex_attributes",
    "interp_at",
    "finish_output",
    "bilinear_sample",
]


def prepare_scene(vertices, faces, camera, settings, coords):
    """Validate the scene of a render call and project its faces to the screen.

    Returns ``(v, f, fv, cam, s, B, batched)``: the vertices as a tensor, the faces as an
    int64 tensor (see :func:`polygeo.checks.check_faces`), the screen-space face vertices
    ``fv`` (B, F, 3, 3) (x, y in pixels, z camera depth), the camera in the vertices' dtype,
    the settings, the batch size and whether the call was batched.
    """
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a polygeo.render.Camera, got {type(camera).__name__}")
    s = RasterSettings() if settings is None else settings
    if not isinstance(s, RasterSettings):
        raise TypeError(f"settings: expected RasterSettings or None, got {type(s).__name__}")
    check_choice(coords, "coords", ("world", "camera"))
    v = as_tensor(vertices, "vertices")
    check_shape(v, "vertices", ("...", 3))
    if v.ndim not in (2, 3):
        raise ValueError(f"vertices: expected shape (V, 3) or (B, V, 3), got {tuple(v.shape)}")
    check_finite(v.detach(), "vertices")
    f = check_faces(faces, v.shape[-2])
    cb = camera.batch_size
    vb = v.shape[0] if v.ndim == 3 else None
    if cb is not None and vb is not None and cb != vb:
        raise ValueError(f"vertices: expected a batch of {cb} (the camera batch), got {vb}")
    batched = cb is not None or vb is not None
    B = cb if cb is not None else (vb if vb is not None else 1)
    dtype = v.dtype
    cam = camera.to(dtype) if camera.dtype != dtype else camera
    vb3 = v if v.ndim == 3 else v.unsqueeze(0)
    pc = (
        (cam.world_to_camera(v) if cb is not None else cam.world_to_camera(vb3))
        if (coords == "world")
        else vb3
    )
    if pc.ndim == 2:
        pc = pc.unsqueeze(0)
    pc = pc.expand(B, *pc.shape[-2:]) if pc.shape[0] != B else pc
    z = pc[..., 2]
    # vertices behind the near plane only belong to culled faces: keep their projection
    # finite (and its gradient zero) by projecting a stand-in depth.
    front = z >= s.znear
    zs = torch.where(front, z, torch.ones_like(z))
    pcs = torch.cat([pc[..., :2], zs.unsqueeze(-1)], dim=-1)
    uv, _ = cam.project_camera(pcs)
    screen = torch.cat([uv, z.unsqueeze(-1)], dim=-1)  # (B, V, 3): x, y pixels; z depth
    fv = screen[:, f]  # (B, F, 3, 3)
    return v, f, fv, cam, s, B, batched


def vertex_attributes(colors, uvs, texture, v, f, B, s):
    """Validate colours or texture + UVs; return ``(attr, uv_f, tex, C, mode)``.

    ``attr`` (Ba, F, 3, C) per face-vertex colours or None, ``uv_f`` (1, F, 3, 2) per
    face-vertex UVs or None, ``tex`` the texture or None, ``C`` the channel count (0 for a
    silhouette) and the kernel mode.
    """
    if colors is not None and texture is not None:
        raise ValueError("colors, texture: expected at most one of them, got both")
    if texture is None and uvs is not None:
        raise ValueError("uvs: given without a texture")
    dtype = v.dtype
    nv, nf = v.shape[-2], f.shape[0]
    attr = uv_f = tex = None
    if colors is not None:
        c = as_tensor(colors, "colors", dtype=dtype)
        if c.ndim == 2:
            check_shape(c, "colors", (nv, "C"))
            c = c.unsqueeze(0)
        else:
            check_shape(c, "colors", (B, nv, "C"))
        check_finite(c.detach(), "colors")
        attr = c[:, f]  # (Ba, F, 3, C)
        C = c.shape[-1]
        mode = K.MODE_VERTEX
    elif texture is not None:
        tex = as_tensor(texture, "texture", dtype=dtype)
        check_shape(tex, "texture", ("Ht", "Wt", "C"))
        if tex.numel() == 0:
            raise ValueError(f"texture: expected a non-empty map, got shape {tuple(tex.shape)}")
        check_finite(tex.detach(), "texture")
        if uvs is None:
            raise ValueError("uvs: expected (V, 2) or (F, 3, 2) UV coordinates with a texture")
        u = as_tensor(uvs, "uvs", dtype=dtype)
        if u.ndim == 2:
            check_shape(u, "uvs", (nv, 2))
            uv_f = u[f].unsqueeze(0)
        else:
            check_shape(u, "uvs", (nf, 3, 2))
            uv_f = u.unsqueeze(0)
        check_finite(u.detach(), "uvs")
        C = tex.shape[-1]
        mode = K.MODE_TEXTURE
    else:
        C = 0
        mode = K.MODE_SILHOUETTE
    if C:
        s.background_for(C)  # validates the background's length
    return attr, uv_f, tex, C, mode


def interp_at(
    fv: torch.Tensor, idx: torch.Tensor, H: int, W: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Perspective-correct barycentrics and depth of face ``idx`` at every pixel centre.

    ``fv`` (B, F, 3, 3), ``idx`` (B, H, W) with -1 for none. Returns ``mask`` (B, H, W) bool,
    ``pb`` (B, H, W, 3) and ``depth`` (B, H, W) (0 and uniform weights where masked).
    """
    B = fv.shape[0]
    mask = idx >= 0
    safe = idx.clamp_min(0)
    if fv.shape[1] == 0:
        z = torch.zeros((B, H, W), dtype=fv.dtype)
        return mask, torch.full((B, H, W, 3), 1.0 / 3.0, dtype=fv.dtype), z
    bidx = torch.arange(B).view(B, 1, 1).expand(B, H, W)
    pv = fv[bidx, safe]  # (B, H, W, 3, 3)
    qy = (torch.arange(H, dtype=fv.dtype) + 0.5).view(1, H, 1)
    qx = (torch.arange(W, dtype=fv.dtype) + 0.5).view(1, 1, W)
    x = pv[..., 0] - qx.unsqueeze(-1)
    y = pv[..., 1] - qy.unsqueeze(-1)
    e0 = x[..., 1] * y[..., 2] - x[..., 2] * y[..., 1]
    e1 = x[..., 2] * y[..., 0] - x[..., 0] * y[..., 2]
    e2 = x[..., 0] * y[..., 1] - x[..., 1] * y[..., 0]
    area = e0 + e1 + e2
    area = torch.where(mask, area, torch.ones_like(area))
    w = torch.stack([e0, e1, e2], dim=-1) / area.unsqueeze(-1)
    w = w.clamp(0.0, 1.0)
    w = w / w.sum(-1, keepdim=True).clamp_min(1e-300)
    z = torch.where(mask.unsqueeze(-1), pv[..., 2], torch.ones_like(pv[..., 2]))
    u = w / z
    U = u.sum(-1)
    pb = u / U.unsqueeze(-1)
    depth = torch.where(mask, 1.0 / U, torch.zeros_like(U))
    pb = torch.where(mask.unsqueeze(-1), pb, torch.full_like(pb, 1.0 / 3.0))
    return mask, pb, depth


def finish_output(t: torch.Tensor | None, batched: bool, like: bool):
    """Drop the batch axis of an unbatched call; NumPy when the input was NumPy."""
    if t is None:
        return None
    if not batched:
        t = t[0]
    return t.detach().cpu().numpy() if like else t


def bilinear_sample(texture: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear lookup of ``texture`` at ``uv`` (no validation: inputs are checked tensors).

    ``texture`` (Ht, Wt, C) floating, ``uv`` (..., 2) in the module's convention (``u`` along
    columns, ``v`` down the rows, [0, 1] over the map, clamp to edge). Returns (..., C),
    differentiable w.r.t. both. The public, validating front end is
    :func:`polygeo.render.sample_texture`.
    """
    Ht, Wt, C = texture.shape
    X = (uv[..., 0] * Wt - 0.5).clamp(-1.0, float(Wt))
    Y = (uv[..., 1] * Ht - 0.5).clamp(-1.0, float(Ht))
    xf = torch.floor(X)
    yf = torch.floor(Y)
    fx = (X - xf).unsqueeze(-1)
    fy = (Y - yf).unsqueeze(-1)
    xa = xf.long().clamp(0, Wt - 1)
    xb = (xf.long() + 1).clamp(0, Wt - 1)
    ya = yf.long().clamp(0, Ht - 1)
    yb = (yf.long() + 1).clamp(0, Ht - 1)
    flat = texture.reshape(Ht * Wt, C)

    def at(yy: torch.Tensor, xx: torch.Tensor) -> torch.Tensor:
        return flat[(yy * Wt + xx).reshape(-1)].reshape(*yy.shape, C)

    top = (1 - fx) * at(ya, xa) + fx * at(ya, xb)
    bot = (1 - fx) * at(yb, xa) + fx * at(yb, xb)
    return (1 - fy) * top + fy * bot
