"""Type aliases used in the signatures of polygeo's public functions.

One home for the aliases, so that every module spells an input the same way:

``ArrayLike``
    Anything a public geometry function accepts as an array: a NumPy array, a torch
    tensor, a nested sequence of numbers or a scalar. Functions convert it with
    :func:`polygeo.checks.as_tensor`.
``Array``
    An array in one of the two back ends, NumPy or torch. Public geometry functions
    return NumPy when given NumPy and torch when given torch (see
    :func:`polygeo.checks.to_like`).
``DeviceLike``
    A torch device or its name (``"cpu"``, ``"cuda:0"``).
``DTypeLike``
    A torch floating or integer dtype.

The aliases are plain ``typing`` unions, for readers and type checkers; nothing checks
them at run time (the validators in :mod:`polygeo.checks` do).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, TypeAlias

import numpy as np

if TYPE_CHECKING:  # the aliases are for readers and type checkers: no torch import at run time
    import torch

__all__ = ["ArrayLike", "Array", "DeviceLike", "DTypeLike"]

Array: TypeAlias = "np.ndarray | torch.Tensor"
ArrayLike: TypeAlias = "np.ndarray | torch.Tensor | Sequence[Any] | float | int"
DeviceLike: TypeAlias = "torch.device | str"
DTypeLike: TypeAlias = "torch.dtype"
