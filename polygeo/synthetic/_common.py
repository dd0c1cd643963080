"""Helpers shared by the modules of :mod:`polygeo.synthetic` (package-private: not public API)."""

from __future__ import annotations

import numpy as np


def grid_faces(nu: int, nv: int, wrap_u: bool, wrap_v: bool) -> np.ndarray:
    """Triangles of an nu x nv vertex grid (index i * nv + j), oriented like d/du x d/dv."""
    iu = np.arange(nu if wrap_u else nu - 1)
    jv = np.arange(nv if wrap_v else nv - 1)
    I, J = np.meshgrid(iu, jv, indexing="ij")
    I, J = I.ravel(), J.ravel()
    I1 = (I + 1) % nu
    J1 = (J + 1) % nv
    a = I * nv + J
    b = I1 * nv + J
    c = I1 * nv + J1
    d = I * nv + J1
    return np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)], 0)
