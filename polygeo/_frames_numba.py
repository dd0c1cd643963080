"""Compiled (numba) backend of :func:`polygeo.frames.pca_frames`.

Same result as the torch backend (weighted centroid, trace-normalised covariance, eigenvectors
with the documented sign convention), with the symmetric 3x3 eigenproblem solved per item by
cyclic Jacobi rotations (accurate to machine precision, including the small eigenvalue whose
eigenvector is the normal). Not differentiable.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

__all__ = ["pca_frames_numba"]

_CHUNK = 512


@nb.njit(cache=True)
def _jacobi3(a, v):
    """Diagonalise the symmetric 3x3 ``a`` in place; eigenvectors into the columns of ``v``."""
    for i in range(3):
        for j in range(3):
            v[i, j] = 1.0 if i == j else 0.0
    for _sweep in range(12):
        off = a[0, 1] * a[0, 1] + a[0, 2] * a[0, 2] + a[1, 2] * a[1, 2]
        scale = a[0, 0] * a[0, 0] + a[1, 1] * a[1, 1] + a[2, 2] * a[2, 2]
        if off <= 1e-36 * scale or off == 0.0:
            break
        for p in range(2):
            for q in range(p + 1, 3):
                apq = a[p, q]
                if apq == 0.0:
                    continue
                theta = (a[q, q] - a[p, p]) / (2.0 * apq)
                t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                if theta < 0.0:
                    t = -t
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for k in range(3):
                    akp = a[k, p]
                    akq = a[k, q]
                    a[k, p] = c * akp - s * akq
                    a[k, q] = s * akp + c * akq
                for k in range(3):
                    apk = a[p, k]
                    aqk = a[q, k]
                    a[p, k] = c * apk - s * aqk
                    a[q, k] = s * apk + c * aqk
                for k in range(3):
                    vkp = v[k, p]
                    vkq = v[k, q]
                    v[k, p] = c * vkp - s * vkq
                    v[k, q] = s * vkp + c * vkq


@nb.njit(cache=True)
def _sign_of_largest(x, y, z):
    """-1.0 when the largest-magnitude component (first on ties) is negative, else 1.0."""
    ax, ay, az = abs(x), abs(y), abs(z)
    if ax >= ay and ax >= az:
        return -1.0 if x < 0 else 1.0
    if ay >= az:
        return -1.0 if y < 0 else 1.0
    return -1.0 if z < 0 else 1.0


@nb.njit(cache=True, parallel=True)
def _pca_kernel(P, w, has_w, mask, has_mask, center, has_center, ref, has_ref, out_c, out_R,
                out_lam, out_count):
    B = P.shape[0]
    K = P.shape[1]
    nchunks = (B + _CHUNK - 1) // _CHUNK
    for ch in nb.prange(nchunks):
        a = np.empty((3, 3))
        v = np.empty((3, 3))
        for b in range(ch * _CHUNK, min(B, (ch + 1) * _CHUNK)):
            sw = 0.0
            cx = cy = cz = 0.0
            cnt = 0
            for k in range(K):
                if has_mask and not mask[b, k]:
                    continue
                x, y, z = P[b, k, 0], P[b, k, 1], P[b, k, 2]
                if not (abs(x) < math.inf and abs(y) < math.inf and abs(z) < math.inf):
                    continue
                cnt += 1
                wk = w[b, k] if has_w else 1.0
                sw += wk
                cx += wk * x
                cy += wk * y
                cz += wk * z
            swc = sw if sw > 0.0 else 1.0
            if has_center:
                cx, cy, cz = center[b, 0], center[b, 1], center[b, 2]
            else:
                cx, cy, cz = cx / swc, cy / swc, cz / swc
            sxx = sxy = sxz = syy = syz = szz = 0.0
            for k in range(K):
                if has_mask and not mask[b, k]:
                    continue
                x, y, z = P[b, k, 0], P[b, k, 1], P[b, k, 2]
                if not (abs(x) < math.inf and abs(y) < math.inf and abs(z) < math.inf):
                    continue
                wk = w[b, k] if has_w else 1.0
                dx, dy, dz = x - cx, y - cy, z - cz
                sxx += wk * dx * dx
                sxy += wk * dx * dy
                sxz += wk * dx * dz
                syy += wk * dy * dy
                syz += wk * dy * dz
                szz += wk * dz * dz
            out_c[b, 0], out_c[b, 1], out_c[b, 2] = cx, cy, cz
            out_count[b] = cnt
            tr = (sxx + syy + szz) / swc
            if not tr > 0.0:
                for i in range(3):
                    out_lam[b, i] = 0.0
                    for j in range(3):
                        out_R[b, i, j] = 1.0 if i == j else 0.0
                continue
            f = 1.0 / (swc * tr)
            a[0, 0], a[0, 1], a[0, 2] = sxx * f, sxy * f, sxz * f
            a[1, 0], a[1, 1], a[1, 2] = sxy * f, syy * f, syz * f
            a[2, 0], a[2, 1], a[2, 2] = sxz * f, syz * f, szz * f
            _jacobi3(a, v)
            # order eigenvalues descending
            l0, l1, l2 = a[0, 0], a[1, 1], a[2, 2]
            i0, i1, i2 = 0, 1, 2
            if l0 < l1:
                l0, l1, i0, i1 = l1, l0, i1, i0
            if l1 < l2:
                l1, l2, i1, i2 = l2, l1, i2, i1
            if l0 < l1:
                l0, l1, i0, i1 = l1, l0, i1, i0
            out_lam[b, 0] = max(l0, 0.0) * tr
            out_lam[b, 1] = max(l1, 0.0) * tr
            out_lam[b, 2] = max(l2, 0.0) * tr
            e1x, e1y, e1z = v[0, i0], v[1, i0], v[2, i0]
            s1 = _sign_of_largest(e1x, e1y, e1z)
            e1x, e1y, e1z = s1 * e1x, s1 * e1y, s1 * e1z
            e3x, e3y, e3z = v[0, i2], v[1, i2], v[2, i2]
            s3 = _sign_of_largest(e3x, e3y, e3z)
            if has_ref and s3 * (e3x * ref[b, 0] + e3y * ref[b, 1] + e3z * ref[b, 2]) < 0:
                s3 = -s3
            e3x, e3y, e3z = s3 * e3x, s3 * e3y, s3 * e3z
            # e2 = e3 x e1
            e2x = e3y * e1z - e3z * e1y
            e2y = e3z * e1x - e3x * e1z
            e2z = e3x * e1y - e3y * e1x
            out_R[b, 0, 0], out_R[b, 1, 0], out_R[b, 2, 0] = e1x, e1y, e1z
            out_R[b, 0, 1], out_R[b, 1, 1], out_R[b, 2, 1] = e2x, e2y, e2z
            out_R[b, 0, 2], out_R[b, 1, 2], out_R[b, 2, 2] = e3x, e3y, e3z


def pca_frames_numba(P, w, mask, center, ref):
    """Run the kernel on float64 NumPy arrays (None for absent options); return NumPy arrays."""
    B = P.shape[0]
    P = np.ascontiguousarray(P, dtype=np.float64)
    has_w, has_mask = w is not None, mask is not None
    has_center, has_ref = center is not None, ref is not None
    w = np.ascontiguousarray(w, dtype=np.float64) if has_w else np.ones((1, 1))
    mask = np.ascontiguousarray(mask, dtype=np.bool_) if has_mask else np.ones((1, 1), np.bool_)
    center = np.ascontiguousarray(center, dtype=np.float64) if has_center else np.zeros((1, 3))
    ref = np.ascontiguousarray(ref, dtype=np.float64) if has_ref else np.zeros((1, 3))
    out_c = np.empty((B, 3))
    out_R = np.empty((B, 3, 3))
    out_lam = np.empty((B, 3))
    out_count = np.empty(B, dtype=np.int64)
    if B:
        _pca_kernel(P, w, has_w, mask, has_mask, center, has_center, ref, has_ref, out_c, out_R,
                    out_lam, out_count)
    return out_c, out_R, out_lam, out_count
