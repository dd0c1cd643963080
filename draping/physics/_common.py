"""Helpers shared by the modules of :mod:`draping.physics` (package-private).

Their names are public inside the package; nothing outside ``draping.physics`` uses them.
"""

from __future__ import annotations

from typing import Any

import torch

from polygeo.checks import check_shape

__all__ = ["positions", "like", "reduce_terms"]


def positions(x: Any, n: int, name: str = "x") -> torch.Tensor:
    """Energies take torch tensors (they are differentiated), of shape (..., n, 3)."""
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name}: expected a torch tensor, got {type(x).__name__}")
    if not x.is_floating_point():
        raise TypeError(f"{name}: expected a floating tensor, got dtype {x.dtype}")
    check_shape(x, name, ("...", n, 3))
    return x


def like(t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``t`` in the dtype and on the device of ``x`` (rest data follow the positions)."""
    return t.to(dtype=x.dtype, device=x.device)


def reduce_terms(per: torch.Tensor, reduction: str) -> torch.Tensor:
    """Sum the last axis (``"sum"``) or keep the per-element terms (``"none"``)."""
    if reduction == "sum":
        return per.sum(-1)
    if reduction == "none":
        return per
    raise ValueError(f"reduction: expected 'sum' or 'none', got {reduction!r}")
