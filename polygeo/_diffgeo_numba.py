"""Compiled (numba) backend of :func:`polygeo.diffgeo.from_jet` at the jet's origin.

Normal, principal curvatures and directions of height jets ``z = f(u, v)`` at ``(u, v) = 0``,
rotated to world axes: the closed forms and conventions of
:func:`polygeo.diffgeo.from_derivatives` (normal on the ``+z`` side of the local frame; shape
operator diagonalised in ``t1 = x_u / |x_u|``, ``t2 = n x t1``; ``d1`` at angle
``atan2(2b, a - c) / 2`` from ``t1``, ``d1 = t1`` at umbilics; ``k1 >= k2``, ``(d1, d2, n)``
right-handed). Not differentiable; used by :mod:`polygeo.estimate` when no gradient is needed.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from ._numba_util import njit_pair

__all__ = ["origin_geometry", "origin_geometry_par", "origin_geometry_ser", "jet_geometry"]


@nb.njit(cache=True, inline="always")
def origin_geometry(coef, b, R, rb, normal, d1, d2, kk, ob):
    """Geometry of jet ``coef[b]`` (``M >= 3`` coefficients) in frame ``R[rb]`` into ``[ob]``.

    Outputs: ``normal``, ``d1``, ``d2`` (.., 3) in world axes; ``kk`` (.., 4): k1, k2, H, K.
    """
    M = coef.shape[1]
    a10 = coef[b, 1]
    a01 = coef[b, 2]
    a20 = coef[b, 3] if M > 3 else 0.0
    a11 = coef[b, 4] if M > 4 else 0.0
    a02 = coef[b, 5] if M > 5 else 0.0
    # x_u = (1, 0, a10), x_v = (0, 1, a01), x_uu = (0, 0, 2 a20), ...
    w = math.sqrt(1.0 + a10 * a10 + a01 * a01)
    nx, ny, nz = -a10 / w, -a01 / w, 1.0 / w
    L = 2.0 * a20 / w
    Mm = a11 / w
    Nn = 2.0 * a02 / w
    su = math.sqrt(1.0 + a10 * a10)
    t1x, t1y, t1z = 1.0 / su, 0.0, a10 / su
    t2x = ny * t1z - nz * t1y
    t2y = nz * t1x - nx * t1z
    t2z = nx * t1y - ny * t1x
    c11 = su
    c12 = a10 * a01 / su  # x_v . t1
    c22 = t2y + a01 * t2z  # x_v . t2
    i11 = 1.0 / c11
    i12 = -c12 / (c11 * c22)
    i22 = 1.0 / c22
    a = i11 * i11 * L
    b = i11 * (i12 * L + i22 * Mm)
    c = i12 * i12 * L + 2.0 * i12 * i22 * Mm + i22 * i22 * Nn
    m = 0.5 * (a + c)
    hd = 0.5 * (a - c)
    r2 = hd * hd + b * b
    r = math.sqrt(r2)
    if r2 > 1e-30 * max(m * m, 1e-300):
        theta = 0.5 * math.atan2(b, hd)
    else:
        theta = 0.0
    ct = math.cos(theta)
    st = math.sin(theta)
    ex = ct * t1x + st * t2x
    ey = ct * t1y + st * t2y
    ez = ct * t1z + st * t2z
    fx = ny * ez - nz * ey
    fy = nz * ex - nx * ez
    fz = nx * ey - ny * ex
    for rr in range(3):
        normal[ob, rr] = R[rb, rr, 0] * nx + R[rb, rr, 1] * ny + R[rb, rr, 2] * nz
        d1[ob, rr] = R[rb, rr, 0] * ex + R[rb, rr, 1] * ey + R[rb, rr, 2] * ez
        d2[ob, rr] = R[rb, rr, 0] * fx + R[rb, rr, 1] * fy + R[rb, rr, 2] * fz
    kk[ob, 0] = m + r
    kk[ob, 1] = m - r
    kk[ob, 2] = m
    kk[ob, 3] = a * c - b * b


def _origin_geometry_py(coef, R, normal, d1, d2, kk):
    for i in nb.prange(coef.shape[0]):
        origin_geometry(coef, i, R, i, normal, d1, d2, kk, i)


# parallel variant for large batches; the serial one avoids the thread-pool start-up cost
origin_geometry_par, origin_geometry_ser = njit_pair(_origin_geometry_py)
_PARALLEL_MIN = 4096


def jet_geometry(coeffs: np.ndarray, R: np.ndarray) -> dict[str, np.ndarray]:
    """Origin geometry of jets ``coeffs (Q, M)`` in frames ``R (Q, 3, 3)`` (float64 NumPy).

    Returns a dict of ``normals, d1, d2 (Q, 3)`` and ``k1, k2, mean_curvature,
    gaussian_curvature (Q,)``.
    """
    Q = coeffs.shape[0]
    normal = np.empty((Q, 3))
    d1 = np.empty((Q, 3))
    d2 = np.empty((Q, 3))
    kk = np.empty((Q, 4))
    if Q:
        c = np.ascontiguousarray(coeffs, dtype=np.float64)
        if c.shape[1] < 6:
            c = np.concatenate([c, np.zeros((Q, 6 - c.shape[1]))], 1)
        kernel = origin_geometry_par if Q >= _PARALLEL_MIN else origin_geometry_ser
        kernel(c, np.ascontiguousarray(R, dtype=np.float64), normal, d1, d2, kk)
    return {
        "normals": normal, "d1": d1, "d2": d2,
        "k1": kk[:, 0], "k2": kk[:, 1], "mean_curvature": kk[:, 2], "gaussian_curvature": kk[:, 3],
    }
