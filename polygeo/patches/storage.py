"""NPZ files of PolyFit patch sets (:meth:`polygeo.patches.PatchSet.save` / ``load``).

A file holds ``version`` (:data:`NPZ_VERSION`), ``orient`` (a string), ``numpy_io`` (a bool:
the set was fitted from NumPy input; absent in older files, read as False) and one array per
tensor field of the set; ``faces`` and ``normals`` only when present. Files are read with
``allow_pickle=False`` and replaced atomically when written.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..runs import atomic_write

__all__ = ["NPZ_VERSION", "TENSOR_FIELDS", "save_npz", "load_npz"]

#: Format version written by :func:`save_npz` and required by :func:`load_npz`.
NPZ_VERSION = 1

#: Tensor fields of a patch set, in file order (``faces`` and ``normals`` may be absent).
TENSOR_FIELDS = ("scale", "rotation", "translation", "coeffs", "orders", "uv", "mask", "index",
                 "domain", "residual", "status", "labels", "vertices", "boundary_pairs")
_OPTIONAL = ("faces", "normals")


def save_npz(path: str | os.PathLike, fields: dict[str, Any]) -> Path:
    """Write a patch set's fields to a compressed NPZ file, atomically replaced.

    Parameters
    ----------
    path : str or os.PathLike
        Destination; ``.npz`` is appended if missing. Parent folders are created.
    fields : dict
        ``orient`` (str), ``numpy_io`` (bool, optional: False when absent), every name of
        :data:`TENSOR_FIELDS` (tensors or arrays) and ``faces`` / ``normals`` (None to leave
        out).

    Returns
    -------
    pathlib.Path
        The path written.
    """
    p = Path(path)
    if p.suffix != ".npz":
        p = p.with_name(p.name + ".npz")
    arrays = {"version": np.array(NPZ_VERSION), "orient": np.array(fields["orient"]),
              "numpy_io": np.array(bool(fields.get("numpy_io", False)))}
    arrays.update({name: fields[name] for name in TENSOR_FIELDS})
    arrays.update({name: fields[name] for name in _OPTIONAL if fields[name] is not None})
    out = {
        name: (x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else x)
        for name, x in arrays.items()
    }
    return atomic_write(p, lambda fh: np.savez_compressed(fh, **out))


def load_npz(path: str | os.PathLike) -> dict[str, Any]:
    """Read the fields written by :func:`save_npz`.

    Parameters
    ----------
    path : str or os.PathLike
        NPZ file.

    Returns
    -------
    dict
        ``orient`` (str), ``numpy_io`` (bool), ``info`` (empty dict), every tensor field as a
        torch tensor and
        ``faces`` / ``normals`` (None when absent): the keyword arguments of
        :class:`polygeo.patches.PatchSet`.

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    ValueError
        If it is not a patch-set file (missing arrays or another version).
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"path: no such file {str(p)!r}")
    with np.load(p, allow_pickle=False) as z:
        need = ("version", "scale", "rotation", "translation", "coeffs", "labels")
        missing = [name for name in need if name not in z.files]
        if missing:
            raise ValueError(f"path: {str(p)!r} is not a PatchSet file (missing {missing})")
        if int(z["version"]) != NPZ_VERSION:
            raise ValueError(
                f"path: expected PatchSet version {NPZ_VERSION}, got {int(z['version'])}"
            )
        d = {name: z[name] for name in z.files}

    def tensor(name: str) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(d[name]))

    out: dict[str, Any] = {name: tensor(name) for name in TENSOR_FIELDS}
    out.update({name: tensor(name) if name in d else None for name in _OPTIONAL})
    out.update(orient=str(d["orient"]), numpy_io=bool(d.get("numpy_io", False)), info={})
    return out
