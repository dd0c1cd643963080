"""Image comparison losses for render-and-compare fitting (silhouette and RGB), with masks.

All losses are weighted means over pixels: with a mask ``m`` (weights in [0, 1], e.g. the
valid region of a frame), ``loss = sum(m * err) / sum(m)``; pixels with ``m = 0`` do not
contribute and an all-zero mask gives a loss of 0 (never NaN). Leading dimensions are a
batch; ``reduction="mean"`` averages the per-image losses, ``"none"`` returns them.
"""

from __future__ import annotations

from typing import Any

import torch

from ..checks import as_tensor, check_choice, is_numpy_like, to_like

__all__ = ["silhouette_loss", "rgb_loss", "soft_iou", "iou"]

_EPS = 1e-12


def _pair(pred: Any, target: Any, name_p: str, name_t: str, tail: int):
    p = as_tensor(pred, name_p)
    t = as_tensor(target, name_t, dtype=p.dtype)
    if p.ndim < tail:
        raise ValueError(
            f"{name_p}: expected at least {tail} dimensions, got shape {tuple(p.shape)}"
        )
    if t.shape != p.shape:
        raise ValueError(
            f"{name_t}: expected shape {tuple(p.shape)} (as {name_p}), got {tuple(t.shape)}"
        )
    return p, t


def _mask(mask: Any, like: torch.Tensor, image_ndim: int) -> torch.Tensor:
    """Mask broadcast to ``like``'s leading + (H, W) dims."""
    if mask is None:
        return torch.ones(like.shape[: like.ndim - image_ndim + 2], dtype=like.dtype)
    m = as_tensor(mask, "mask", dtype=like.dtype)
    hw = tuple(like.shape[like.ndim - image_ndim : like.ndim - image_ndim + 2])
    if m.ndim < 2 or tuple(m.shape[-2:]) != hw:
        raise ValueError(f"mask: expected shape (..., {hw[0]}, {hw[1]}), got {tuple(m.shape)}")
    lead = like.shape[: like.ndim - image_ndim]
    try:
        return m.expand(*lead, *hw)
    except RuntimeError as exc:
        raise ValueError(
            f"mask: expected leading dimensions broadcastable to {tuple(lead)}, "
            f"got {tuple(m.shape[:-2])}"
        ) from exc


def _reduce(x: torch.Tensor, reduction: str) -> torch.Tensor:
    check_choice(reduction, "reduction", ("mean", "none"))
    return x.mean() if reduction == "mean" else x


def silhouette_loss(
    pred: Any, target: Any, mask: Any = None, *, kind: str = "l2", reduction: str = "mean"
) -> Any:
    """Compare a rendered silhouette with a target mask.

    Parameters
    ----------
    pred : array_like or torch.Tensor, shape (..., H, W)
        Rendered coverage in [0, 1] (e.g. ``render(...).alpha``).
    target : array_like or torch.Tensor, shape (..., H, W)
        Target silhouette in [0, 1] (binary or soft).
    mask : array_like or torch.Tensor, shape (..., H, W), optional
        Per-pixel weights (broadcast over the leading dimensions).
    kind : {"l2", "l1", "iou"}
        Squared error, absolute error, or ``1 - soft IoU`` (SoftRas' IoU loss).
    reduction : {"mean", "none"}
        Mean over the leading dimensions, or one value per image (shape ``...``).

    Returns
    -------
    array or torch.Tensor
        Scalar or per-image loss, dimensionless; type of ``pred``.

    Raises
    ------
    ValueError
        On mismatched shapes or an unknown ``kind`` / ``reduction``.
    """
    like = is_numpy_like(pred)
    check_choice(kind, "kind", ("l2", "l1", "iou"))
    p, t = _pair(pred, target, "pred", "target", 2)
    m = _mask(mask, p, 2)
    if kind == "iou":
        out = 1.0 - soft_iou(p, t, m)
    else:
        err = (p - t).abs() if kind == "l1" else (p - t) ** 2
        out = (m * err).sum((-1, -2)) / m.sum((-1, -2)).clamp_min(_EPS)
    return to_like(_reduce(out, reduction), like)


def rgb_loss(
    pred: Any, target: Any, mask: Any = None, *, kind: str = "l1", reduction: str = "mean"
) -> Any:
    """Compare a rendered image with a target image.

    Parameters
    ----------
    pred : array_like or torch.Tensor, shape (..., H, W, C)
        Rendered colours (e.g. ``render(...).rgb``).
    target : array_like or torch.Tensor, shape (..., H, W, C)
        Target colours, same unit.
    mask : array_like or torch.Tensor, shape (..., H, W), optional
        Per-pixel weights (e.g. the target silhouette), broadcast over channels and the
        leading dimensions.
    kind : {"l1", "l2"}
        Mean absolute or squared error per channel.
    reduction : {"mean", "none"}

    Returns
    -------
    array or torch.Tensor
        Scalar or per-image loss in (colour unit) or (colour unit)²; type of ``pred``.

    Raises
    ------
    ValueError
        On mismatched shapes or an unknown ``kind`` / ``reduction``.
    """
    like = is_numpy_like(pred)
    check_choice(kind, "kind", ("l1", "l2"))
    p, t = _pair(pred, target, "pred", "target", 3)
    m = _mask(mask, p, 3)
    err = (p - t).abs() if kind == "l1" else (p - t) ** 2
    num = (m.unsqueeze(-1) * err).sum((-1, -2, -3))
    den = m.sum((-1, -2)).clamp_min(_EPS) * p.shape[-1]
    return to_like(_reduce(num / den, reduction), like)


def soft_iou(pred: Any, target: Any, mask: Any = None) -> Any:
    """Soft intersection over union ``sum(m p t) / sum(m (p + t - p t))`` per image.

    Parameters
    ----------
    pred, target : array_like or torch.Tensor, shape (..., H, W)
        Values in [0, 1].
    mask : array_like or torch.Tensor, shape (..., H, W), optional
        Per-pixel weights.

    Returns
    -------
    array or torch.Tensor, shape (...)
        IoU in [0, 1]; 1 where both are empty. Type of ``pred``.

    Raises
    ------
    ValueError
        On mismatched shapes.
    """
    like = is_numpy_like(pred)
    p, t = _pair(pred, target, "pred", "target", 2)
    m = _mask(mask, p, 2)
    inter = (m * p * t).sum((-1, -2))
    union = (m * (p + t - p * t)).sum((-1, -2))
    out = torch.where(union > _EPS, inter / union.clamp_min(_EPS), torch.ones_like(union))
    return to_like(out, like)


def iou(pred: Any, target: Any, threshold: float = 0.5) -> Any:
    """Hard IoU of two masks after thresholding (``value > threshold``), per image.

    Parameters
    ----------
    pred, target : array_like or torch.Tensor, shape (..., H, W)
    threshold : float

    Returns
    -------
    array or torch.Tensor, shape (...)
        IoU in [0, 1]; 1 where both masks are empty. Type of ``pred``; not differentiable.

    Raises
    ------
    ValueError
        On mismatched shapes.
    """
    like = is_numpy_like(pred)
    p, t = _pair(pred, target, "pred", "target", 2)
    a = p.detach() > threshold
    b = t.detach() > threshold
    inter = (a & b).sum((-1, -2)).to(torch.float64)
    union = (a | b).sum((-1, -2)).to(torch.float64)
    out = torch.where(union > 0, inter / union.clamp_min(1.0), torch.ones_like(union))
    return to_like(out, like)
