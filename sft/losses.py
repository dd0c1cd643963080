"""Losses of PolySfT and of the per-vertex baseline.

- Photometric and silhouette terms between soft renders (:mod:`polygeo.render`) and the
  frames / masks, as in phi-SfT (Kairanda et al. 2022): an L1 colour loss over the image
  (the target composited over the renderer's background with its mask) and an L2 loss
  between the soft silhouette and the mask.
- Mesh inextensibility (thesis eq. (47)): ``w sum_e (e(M_P) - e(M_T))^2`` with edge lengths
  (:func:`polygeo.mesh.edge_length_energy`) in the model's normalised units (scene units
  divided by the template radius), so that the weight does not depend on the scene's units;
  the sum is nearly independent of the mesh resolution (for a uniform strain ``eps`` it is
  about ``3.5 eps^2`` times the normalised area).
- Temporal consistency (thesis eq. (48)): ``w / (W - 1) sum_t ||p_{t+1} - p_t||^2`` over
  consecutive frames of the window, for the parameters the model lists in ``temporal``.
- Temporal acceleration (a constant-velocity prior, ours): ``w / (W - 2) sum_t
  ||p_{t+1} - 2 p_t + p_{t-1}||^2`` over the window, for every parameter of the model.

When a sequence has no masks, the silhouette term is dropped and the colour loss compares
whole frames; :class:`ImageTerms` warns about it once: no mask is derived from the images.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch

from polygeo.mesh import edge_length_energy, edge_lengths, edges
from polygeo.render import Camera, RasterSettings, render, rgb_loss, silhouette_loss
from polygeo.render.texture import flip_v

__all__ = ["ImageTerms", "Inextensibility", "temporal_consistency", "temporal_acceleration",
           "prefilter_texture"]


def prefilter_texture(texture: np.ndarray, uvs: np.ndarray, verts: np.ndarray,
                      faces: np.ndarray, K: np.ndarray, texels_per_pixel: float = 2.0
                      ) -> np.ndarray:
    """Shrink a texture to about ``texels_per_pixel`` texels per image pixel (mip-mapping).

    The soft rasterizer samples the texture bilinearly at pixel centres; a texture much finer
    than the image would alias. The median ratio of texture area to projected image area over
    the template's faces gives the minification factor. Two texels per pixel matched
    anti-aliased (4 x 4 supersampled) reference renders best in our tests.

    Parameters
    ----------
    texture : np.ndarray
        ``(Ht, Wt, 3)`` float texture.
    uvs : np.ndarray
        Texture coordinates in ``[0, 1]``: ``(V, 2)`` per vertex or ``(F, 3, 2)`` per face
        corner.
    verts : np.ndarray
        ``(V, 3)`` camera-frame vertices.
    faces : np.ndarray
        ``(F, 3)``.
    K : np.ndarray
        ``(3, 3)`` intrinsics.
    texels_per_pixel : float
        Target density.

    Returns
    -------
    np.ndarray
        The texture, area-downsampled when it is finer than the target density.
    """
    import cv2

    Ht, Wt = texture.shape[:2]
    p = verts @ K.T
    px = p[:, :2] / p[:, 2:3]
    t = np.asarray(uvs) * np.array([Wt, Ht])

    def area(q):  # q: (F, 3, 2) triangle corners
        a, b, c = q[:, 0], q[:, 1], q[:, 2]
        return 0.5 * np.abs((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0])

    ai, at = area(px[faces]), area(t if t.ndim == 3 else t[faces])
    ok = ai > 1e-9
    if not ok.any():
        return texture
    ratio = float(np.sqrt(np.median(at[ok] / ai[ok]))) / texels_per_pixel
    if ratio <= 1.0:
        return texture
    size = (max(1, int(round(Wt / ratio))), max(1, int(round(Ht / ratio))))
    return cv2.resize(texture, size, interpolation=cv2.INTER_AREA)


class ImageTerms:
    """Renders meshes and compares them with frames and masks.

    Parameters
    ----------
    sequence : sft.data.Sequence
        Gives the camera, the template's faces and appearance.
    raster : RasterSettings
        Soft rasterizer settings.
    rgb_weight, silhouette_weight : float
        Weights of the colour and silhouette terms.
    rgb_kind : {"l1", "l2"}
    silhouette_kind : {"l2", "l1", "iou"}
    pyramid : int
        Coarser image levels added to both terms (0: full resolution only, as in phi-SfT).
        Level ``l`` compares ``2^l x 2^l`` block means (average pooling) of the render and
        of the target; the terms are averaged over the ``pyramid + 1`` levels, so the
        coarse levels give gradients from texture and silhouette a few pixels away (a wider
        basin for large inter-frame motion) while the fine level keeps the optimum.
    dtype : torch.dtype
        Dtype of the renders.
    """

    def __init__(self, sequence, raster: RasterSettings, *, rgb_weight: float = 1.0,
                 silhouette_weight: float = 1.0, rgb_kind: str = "l1",
                 silhouette_kind: str = "l2", pyramid: int = 0,
                 dtype: torch.dtype = torch.float32) -> None:
        t = sequence.template
        self.camera = Camera(torch.as_tensor(sequence.K, dtype=dtype), width=sequence.width,
                             height=sequence.height)
        self.faces = torch.as_tensor(t.faces, dtype=torch.int64)
        self.raster = raster
        self._hard = RasterSettings(**{**vars(raster), "hard": True})
        self.rgb_weight, self.silhouette_weight = float(rgb_weight), float(silhouette_weight)
        self.rgb_kind, self.silhouette_kind = rgb_kind, silhouette_kind
        self.pyramid = int(pyramid)
        self.dtype = dtype
        self.has_masks = sequence.has_masks
        if t.textured:
            tex = prefilter_texture(t.texture, t.uvs, t.verts, t.faces, sequence.K)
            self.appearance = {
                "uvs": torch.as_tensor(flip_v(t.uvs), dtype=dtype),
                "texture": torch.as_tensor(tex, dtype=dtype),
            }
        else:
            self.appearance = {"colors": torch.as_tensor(t.colors, dtype=dtype)}
        self.background = torch.as_tensor(raster.background_for(3), dtype=dtype)
        if not self.has_masks:
            warnings.warn(
                f"{sequence.root}: no masks/ folder: the silhouette loss is disabled and the "
                "colour loss compares whole frames (no mask is derived from the images)",
                stacklevel=2,
            )

    def target(self, frame: np.ndarray, mask: np.ndarray | None):
        """Target image ``(H, W, 3)`` (frame over the background where masked) and mask."""
        f = torch.as_tensor(frame, dtype=self.dtype)
        if mask is None:
            return f, None
        m = torch.as_tensor(mask, dtype=self.dtype)
        return f * m[..., None] + self.background * (1 - m[..., None]), m

    def render(self, verts: torch.Tensor, *, hard: bool = False):
        """Render ``(F, V, 3)`` camera-frame vertices: ``rgb (F, H, W, 3)``, ``alpha (F, H, W)``.

        The soft coverage is remapped, ``alpha' = clamp(2 alpha - 1/2, 0, 1)``, and the colour
        composited over the background with it. SoftRas' aggregation
        ``1 - prod_f (1 - D_f)`` gives ``D = 1/2`` on both sides of every *internal* edge, so
        the raw coverage dips to 3/4 inside the mesh (everywhere, on meshes with faces of a
        few pixels), which biases a silhouette loss against a binary mask, and the depth
        softmax with a small ``gamma`` paints face colours up to the blur margin outside the
        mesh. The remap sends every internal value (>= 3/4) to 1 and keeps a symmetric
        ramp around the silhouette (1/2 on the edge, 0 once ``D <= 1/4`` outside), so both
        terms are minimal at the true shape (checked against VTK renders).
        """
        if hard:
            out = render(verts, self.faces, self.camera, self._hard, coords="camera",
                         **self.appearance)
            return out.rgb, out.alpha
        out = render(verts, self.faces, self.camera, self.raster, coords="camera",
                     **self.appearance)
        a = (2.0 * out.alpha - 0.5).clamp(0.0, 1.0)
        rgb = out.rgb * a[..., None] + self.background * (1.0 - a[..., None])
        return rgb, a

    def __call__(self, verts: torch.Tensor, targets: torch.Tensor,
                 masks: torch.Tensor | None) -> dict[str, torch.Tensor]:
        """Per-frame losses ``{"rgb": (F,), "sil": (F,)}`` (weighted) of rendered vertices.

        Parameters
        ----------
        verts : torch.Tensor
            ``(F, V, 3)``.
        targets : torch.Tensor
            ``(F, H, W, 3)`` from :meth:`target`.
        masks : torch.Tensor or None
            ``(F, H, W)``.
        """
        rgb, alpha = self.render(verts)
        has_sil = masks is not None and self.silhouette_weight > 0
        levels = [(rgb, targets, alpha, masks)]
        if self.pyramid > 0:
            chw = (rgb.permute(0, 3, 1, 2), targets.permute(0, 3, 1, 2))
            for lv in range(1, self.pyramid + 1):
                k = 2**lv
                if k > min(rgb.shape[1], rgb.shape[2]):
                    break
                r, t = (torch.nn.functional.avg_pool2d(x, k).permute(0, 2, 3, 1) for x in chw)
                a = m = None
                if has_sil:
                    a, m = (torch.nn.functional.avg_pool2d(x[:, None], k)[:, 0]
                            for x in (alpha, masks))
                levels.append((r, t, a, m))
        n = len(levels)
        out = {"rgb": sum(rgb_loss(r, t, kind=self.rgb_kind, reduction="none")
                          for r, t, _, _ in levels) * (self.rgb_weight / n)}
        if has_sil:
            out["sil"] = sum(silhouette_loss(a, m, kind=self.silhouette_kind, reduction="none")
                             for _, _, a, m in levels) * (self.silhouette_weight / n)
        return out


@dataclass
class Inextensibility:
    """Mesh inextensibility (thesis eq. (47)) against the template's edge lengths.

    Parameters
    ----------
    verts : array_like
        ``(V, 3)`` template vertices (scene units).
    faces : array_like
        ``(F, 3)``.
    scale : float
        Normalising length (the template radius): lengths are divided by it.
    weight : float
        Weight of the term.
    """

    verts: np.ndarray
    faces: np.ndarray
    scale: float
    weight: float = 0.1

    def __post_init__(self) -> None:
        self.edges = torch.as_tensor(edges(np.asarray(self.faces)), dtype=torch.int64)
        v = torch.as_tensor(np.asarray(self.verts), dtype=torch.float64)
        self.rest = edge_lengths(v, self.edges)  # (E,) float64, scene units

    def __call__(self, verts: torch.Tensor) -> torch.Tensor:
        """Per-frame loss ``(F,)`` of ``(F, V, 3)`` vertices (scene units)."""
        return self.weight * edge_length_energy(verts, self.edges, self.rest, self.scale)


def _differences(params: dict[str, torch.Tensor], names, order: int) -> torch.Tensor:
    """``sum_names sum_t ||D^order p_t||^2 / (W - order)``: finite differences over frames."""
    names = list(names)
    first = params[names[0]]
    W = first.shape[0]
    total = first.new_zeros(())
    if W <= order:
        return total
    for n in names:
        d = params[n]
        for _ in range(order):
            d = d[1:] - d[:-1]
        total = total + d.pow(2).sum()
    return total / (W - order)


def temporal_consistency(params: dict[str, torch.Tensor], names, weight: float) -> torch.Tensor:
    """Temporal consistency (thesis eq. (48)) over a window of stacked parameters.

    Parameters
    ----------
    params : dict of str to torch.Tensor
        Stacked parameters, leading dimension ``W`` (frames of the window in order).
    names : iterable of str
        Parameters that enter the term (``Delta alpha`` and ``Delta uv`` for PolySfT).
    weight : float
        Weight of the term.

    Returns
    -------
    torch.Tensor
        Scalar ``weight / (W - 1) sum_t sum_names ||p_{t+1} - p_t||^2`` (0 when ``W < 2``).
    """
    return weight * _differences(params, names, 1)


def temporal_acceleration(params: dict[str, torch.Tensor], names,
                          weight: float) -> torch.Tensor:
    """Constant-velocity prior over a window: squared second differences of the parameters.

    Eq. (48) pulls each frame towards the one before it, i.e. towards stopping; this term
    only penalises changes of velocity, so that a part of the surface the images no longer
    constrain (turned away, or hidden behind the rest) keeps moving as it did while it was
    seen instead of freezing.

    Parameters
    ----------
    params : dict of str to torch.Tensor
        Stacked parameters, leading dimension ``W`` (frames of the window in order).
    names : iterable of str
        Parameters that enter the term (every parameter of the model by default).
    weight : float
        Weight of the term.

    Returns
    -------
    torch.Tensor
        Scalar ``weight / (W - 2) sum_t sum_names ||p_{t+1} - 2 p_t + p_{t-1}||^2`` (0 when
        ``W < 3``).
    """
    return weight * _differences(params, names, 2)
