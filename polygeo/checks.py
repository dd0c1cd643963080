"""Input validation and array-type helpers, public for every layer built on polygeo.

Every public function of ``polygeo``, ``sft`` and ``draping`` validates its user-facing
inputs through these helpers so that messages are uniform: they name the argument, what
was expected and what was received. ``ValueError`` is raised for bad shapes and values,
``TypeError`` for bad types and dtypes. No bare ``assert`` is used for user input (it
vanishes under ``python -O``).

Examples
--------
>>> import numpy as np
>>> from polygeo.checks import as_tensor, check_faces, check_shape
>>> v = as_tensor(np.zeros((4, 3)), "vertices")
>>> check_shape(v, "vertices", ("N", 3))
>>> check_faces(np.array([[0, 1, 2], [0, 2, 3]]), n_vertices=4).dtype
torch.int64
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # torch is imported on first use: `polygeo <command> --help` stays torch-free
    import torch

    from .types import Array, ArrayLike, DeviceLike

__all__ = [
    "as_tensor",
    "check_shape",
    "check_finite",
    "check_positive",
    "check_int",
    "check_choice",
    "check_faces",
    "check_mask",
    "to_like",
    "is_numpy_like",
]


def _is_tensor(x: Any) -> bool:
    # a torch tensor exists only once torch is imported: no import needed to answer
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(x, torch.Tensor)


def is_numpy_like(x: ArrayLike) -> bool:
    """Return True when ``x`` is not a torch tensor (NumPy array, list, scalar)."""
    return not _is_tensor(x)


def as_tensor(
    x: ArrayLike,
    name: str,
    *,
    dtype: torch.dtype | None = None,
    device: DeviceLike | None = None,
    floating: bool = True,
) -> torch.Tensor:
    """Convert ``x`` (NumPy array, torch tensor, nested sequence) to a torch tensor.

    Parameters
    ----------
    x : array_like or torch.Tensor
        The input.
    name : str
        Argument name used in error messages.
    dtype : torch.dtype, optional
        Target dtype. When None, floating tensors keep their dtype and other numeric
        inputs become float64 (``floating=True``) or keep their integer dtype.
    device : torch.device or str, optional
        Target device; defaults to the tensor's own device (CPU for NumPy input).
    floating : bool
        Whether a floating dtype is required.

    Returns
    -------
    torch.Tensor
        A tensor sharing memory with ``x`` where possible (NumPy float arrays are not copied).

    Raises
    ------
    TypeError
        If ``x`` cannot be converted, is complex or boolean where floats are expected.
    """
    import torch

    if isinstance(x, torch.Tensor):
        t = x
    else:
        try:
            arr = np.asarray(x)
        except Exception as exc:  # pragma: no cover - exotic inputs
            raise TypeError(f"{name}: expected an array or tensor, got {type(x).__name__}") from exc
        if arr.dtype == object:
            raise TypeError(f"{name}: expected a numeric array, got an object array")
        if np.iscomplexobj(arr):
            raise TypeError(f"{name}: expected a real array, got dtype {arr.dtype}")
        if arr.dtype.kind not in "biuf":
            raise TypeError(f"{name}: expected a numeric array, got dtype {arr.dtype}")
        if arr.dtype.kind == "f" and arr.dtype.itemsize < 4:
            arr = arr.astype(np.float32)
        if not arr.flags.writeable or not arr.flags.c_contiguous:
            arr = np.ascontiguousarray(arr).copy()
        t = torch.from_numpy(arr)
    if t.is_complex():
        raise TypeError(f"{name}: expected a real tensor, got dtype {t.dtype}")
    if floating:
        if t.dtype == torch.bool:
            raise TypeError(f"{name}: expected floating-point values, got dtype bool")
        if dtype is None and not t.is_floating_point():
            dtype = torch.float64
    if dtype is not None or device is not None:
        t = t.to(dtype=dtype or t.dtype, device=device or t.device)
    return t


def check_shape(t: Array, name: str, shape: Sequence[int | str | None]) -> None:
    """Check ``t``'s shape against a pattern.

    Parameters
    ----------
    t : torch.Tensor or np.ndarray
        The array to check.
    name : str
        Argument name used in the error message.
    shape : sequence of int, str or None
        Expected shape. ``None`` or a string (a named dimension such as ``"N"``) matches any
        size; a string used twice must match the same size both times. A leading ``"..."``
        matches any number of leading dimensions.

    Raises
    ------
    ValueError
        If the number of dimensions or a fixed size differs.
    """
    got = tuple(t.shape)
    pattern = list(shape)
    ellipsis = bool(pattern) and pattern[0] == "..."
    if ellipsis:
        pattern = pattern[1:]
        ok = len(got) >= len(pattern)
        tail = got[len(got) - len(pattern) :] if ok else got
    else:
        ok = len(got) == len(pattern)
        tail = got
    named: dict[str, int] = {}
    if ok:
        for g, p in zip(tail, pattern):
            if p is None:
                continue
            if isinstance(p, str):
                if p in named and named[p] != g:
                    ok = False
                    break
                named[p] = g
            elif g != p:
                ok = False
                break
    if not ok:
        want = "(" + ", ".join("..." if p == "..." else str(p) for p in shape) + ")"
        raise ValueError(f"{name}: expected shape {want}, got {got}")


def check_finite(t: torch.Tensor, name: str) -> None:
    """Raise ``ValueError`` if ``t`` holds NaN or infinite values (counting them)."""
    import torch

    bad = ~torch.isfinite(t)
    if bool(bad.any()):
        raise ValueError(f"{name}: expected finite values, got {int(bad.sum())} NaN/inf entries")


def check_mask(mask: ArrayLike, name: str, shape: Sequence[int | str | None]) -> torch.Tensor:
    """A boolean validity mask as a tensor, checked for dtype and shape.

    Parameters
    ----------
    mask : array_like or torch.Tensor
        Boolean mask (``True`` = valid).
    name : str
        Argument name used in the error message.
    shape : sequence of int, str or None
        Expected shape, as in :func:`check_shape`.

    Returns
    -------
    torch.Tensor
        The mask as a ``torch.bool`` tensor.

    Raises
    ------
    TypeError
        If the mask is not boolean.
    ValueError
        If its shape does not match.
    """
    import torch

    m = as_tensor(mask, name, floating=False)
    if m.dtype != torch.bool:
        raise TypeError(f"{name}: expected a bool array, got dtype {m.dtype}")
    check_shape(m, name, shape)
    return m


def check_positive(value: float, name: str, *, strict: bool = True) -> float:
    """Check that a scalar is (strictly) positive and finite; return it as float."""
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{name}: expected a real number, got {value!r}") from exc
    if not np.isfinite(v) or (v <= 0 if strict else v < 0):
        rel = "> 0" if strict else ">= 0"
        raise ValueError(f"{name}: expected a finite value {rel}, got {value!r}")
    return v


def check_int(value: Any, name: str, *, low: int | None = None, high: int | None = None) -> int:
    """Check that ``value`` is an integer within ``[low, high]``; return it as int."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        if _is_tensor(value) and value.numel() == 1 and not value.is_floating_point():
            value = int(value)
        else:
            raise TypeError(f"{name}: expected an integer, got {type(value).__name__} {value!r}")
    v = int(value)
    if (low is not None and v < low) or (high is not None and v > high):
        lo = "-inf" if low is None else low
        hi = "inf" if high is None else high
        raise ValueError(f"{name}: expected an integer in [{lo}, {hi}], got {v}")
    return v


def check_choice(value: Any, name: str, choices: Sequence[Any]) -> Any:
    """Check that ``value`` is one of ``choices``; return it."""
    if value not in choices:
        raise ValueError(f"{name}: expected one of {list(choices)}, got {value!r}")
    return value


def check_faces(
    faces: ArrayLike, n_vertices: int | None = None, name: str = "faces"
) -> torch.Tensor:
    """Check a triangle list and return it as an int64 tensor.

    The one faces validator of the library (mesh, neighbours, partition, patches, estimate
    and the rasterizer all call it), so a bad triangle list gets the same message everywhere.

    Parameters
    ----------
    faces : array_like or torch.Tensor, shape (F, 3), integer dtype
        Triangles as vertex indices. NumPy arrays, nested sequences and torch tensors (on
        any device) are accepted; ``F = 0`` is allowed.
    n_vertices : int, optional
        Number of vertices ``N``; when given, every index must lie in ``[0, N)``. When None
        only negative indices are refused.
    name : str
        Argument name used in error messages.

    Returns
    -------
    torch.Tensor
        ``(F, 3)`` int64 tensor on the input's device (CPU for NumPy or sequences). It may
        share memory with ``faces`` (an int64 tensor comes back as is): do not modify it in
        place. Call ``.cpu().numpy()`` for a NumPy array.

    Raises
    ------
    TypeError
        If ``faces`` is not numeric or has a floating-point, complex or boolean dtype, or
        ``n_vertices`` is not an integer.
    ValueError
        If the shape is not ``(F, 3)``, an index is negative or (with ``n_vertices``) is
        ``>= n_vertices``, or ``n_vertices`` is negative.
    """
    import torch

    t = as_tensor(faces, name, floating=False)
    if t.is_floating_point() or t.dtype == torch.bool:
        raise TypeError(f"{name}: expected an integer array, got dtype {t.dtype}")
    check_shape(t, name, ("F", 3))
    if n_vertices is not None:
        n_vertices = check_int(n_vertices, "n_vertices", low=0)
    t = t.to(torch.int64)
    if t.numel():
        lo, hi = int(t.min()), int(t.max())
        if lo < 0 or (n_vertices is not None and hi >= n_vertices):
            want = (
                "non-negative vertex indices"
                if n_vertices is None
                else f"vertex indices in [0, {n_vertices - 1}] (n_vertices={n_vertices})"
            )
            raise ValueError(f"{name}: expected {want}, got values in [{lo}, {hi}]")
    return t


def to_like(t: torch.Tensor, like_numpy: bool) -> Array:
    """Return ``t`` detached as a NumPy array when ``like_numpy`` else unchanged."""
    if like_numpy:
        return t.detach().cpu().numpy()
    return t
