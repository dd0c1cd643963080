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

from ._numba_util import njit_pair

__all__ = ["pca_frames_numba", "height_frame", "height_frames_par", "height_frames_ser"]

_CHUNK = 512


@nb.njit(cache=True, inline="always")
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


@nb.njit(cache=True, inline="always")
def _sign_of_largest(x, y, z):
    """-1.0 when the largest-magnitude component (first on ties) is negative, else 1.0."""
    ax, ay, az = abs(x), abs(y), abs(z)
    if ax >= ay and ax >= az:
        return -1.0 if x < 0 else 1.0
    if ay >= az:
        return -1.0 if y < 0 else 1.0
    return -1.0 if z < 0 else 1.0


@nb.njit(cache=True, inline="always")
def _eigen_frame(sxx, sxy, sxz, syy, syz, szz, a, v, R, i, lam, refx, refy, refz, has_ref):
    """Frame of a (weighted, centred) 3x3 scatter matrix: the one PCA-frame convention.

    Writes into ``R[i]`` the columns ``e1, e2, e3`` (decreasing variance, ``e3`` the normal
    estimate), signs fixed so that the largest-magnitude component of ``e1`` and of ``e3`` is
    positive (``e3`` instead on the side of ``ref`` when ``has_ref``), ``e2 = e3 x e1``; and
    into ``lam[i]`` the eigenvalues in the scatter's units, descending. The scatter is
    trace-normalised before the Jacobi rotations. A zero or non-finite scatter gives the
    identity frame and zero eigenvalues. ``a`` and ``v`` are 3x3 scratch arrays.
    """
    tr = sxx + syy + szz
    if not (tr > 0.0 and tr < math.inf):
        for r in range(3):
            lam[i, r] = 0.0
            for c in range(3):
                R[i, r, c] = 1.0 if r == c else 0.0
        return
    f = 1.0 / tr
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
    lam[i, 0] = max(l0, 0.0) * tr
    lam[i, 1] = max(l1, 0.0) * tr
    lam[i, 2] = max(l2, 0.0) * tr
    e1x, e1y, e1z = v[0, i0], v[1, i0], v[2, i0]
    s1 = _sign_of_largest(e1x, e1y, e1z)
    e1x, e1y, e1z = s1 * e1x, s1 * e1y, s1 * e1z
    e3x, e3y, e3z = v[0, i2], v[1, i2], v[2, i2]
    s3 = _sign_of_largest(e3x, e3y, e3z)
    if has_ref and s3 * (e3x * refx + e3y * refy + e3z * refz) < 0:
        s3 = -s3
    e3x, e3y, e3z = s3 * e3x, s3 * e3y, s3 * e3z
    # e2 = e3 x e1
    e2x = e3y * e1z - e3z * e1y
    e2y = e3z * e1x - e3x * e1z
    e2z = e3x * e1y - e3y * e1x
    R[i, 0, 0], R[i, 1, 0], R[i, 2, 0] = e1x, e1y, e1z
    R[i, 0, 1], R[i, 1, 1], R[i, 2, 1] = e2x, e2y, e2z
    R[i, 0, 2], R[i, 1, 2], R[i, 2, 2] = e3x, e3y, e3z


@nb.njit(cache=True, inline="always")
def _usable(P, mask, has_mask, b, k):
    """Point ``k`` of item ``b`` is unmasked and finite."""
    if has_mask and not mask[b, k]:
        return False
    return abs(P[b, k, 0]) < math.inf and abs(P[b, k, 1]) < math.inf and abs(P[b, k, 2]) < math.inf


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
                if not _usable(P, mask, has_mask, b, k):
                    continue
                x, y, z = P[b, k, 0], P[b, k, 1], P[b, k, 2]
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
                if not _usable(P, mask, has_mask, b, k):
                    continue
                wk = w[b, k] if has_w else 1.0
                dx, dy, dz = P[b, k, 0] - cx, P[b, k, 1] - cy, P[b, k, 2] - cz
                sxx += wk * dx * dx
                sxy += wk * dx * dy
                sxz += wk * dx * dz
                syy += wk * dy * dy
                syz += wk * dy * dz
                szz += wk * dz * dz
            out_c[b, 0], out_c[b, 1], out_c[b, 2] = cx, cy, cz
            out_count[b] = cnt
            f = 1.0 / swc
            rx, ry, rz = (ref[b, 0], ref[b, 1], ref[b, 2]) if has_ref else (0.0, 0.0, 0.0)
            _eigen_frame(sxx * f, sxy * f, sxz * f, syy * f, syz * f, szz * f, a, v, out_R, b,
                         out_lam, rx, ry, rz, has_ref)


@nb.njit(cache=True, inline="always")
def height_frame(P, q, nbr_row, dist_row, kuse, uv, z, valid, b, R, ob, lam, a, v, kframe=-1):
    """PCA height frame of one query's neighbourhood, with duplicate screening.

    ``P`` (N, 3) points, ``q`` the query's index, ``nbr_row`` / ``dist_row`` (K,) its
    neighbours nearest first (-1 padding; only the first ``kuse`` used). Coordinates are taken
    relative to ``P[q]`` first (so large offsets cost nothing); copies of the query point and
    of an earlier equidistant neighbour are left out. Writes the height coordinates into
    ``uv[b] (K, 2)``, ``z[b] (K,)``, ``valid[b] (K,)`` (zeros where invalid), the frame (the
    :func:`_eigen_frame` convention, about the neighbourhood centroid) into ``R[ob]`` and its
    eigenvalues into ``lam[ob]``. ``kframe > 0``: the frame is that of the first ``kframe``
    rows only (the coordinates still cover ``kuse`` rows). Returns ``(count, rms distance to
    the query)`` of the rows used by the frame.
    """
    K = nbr_row.shape[0]
    px, py, pz = P[q, 0], P[q, 1], P[q, 2]
    finite_q = math.isfinite(px + py + pz)
    cnt = 0
    cx = cy = cz = 0.0
    rr = 0.0
    for j in range(K):
        idx = nbr_row[j]
        ok = idx >= 0 and j < kuse and finite_q
        dx = dy = dz = 0.0
        if ok:
            dx = P[idx, 0] - px
            dy = P[idx, 1] - py
            dz = P[idx, 2] - pz
            if idx != q and dx == 0.0 and dy == 0.0 and dz == 0.0:
                ok = False  # a copy of the query point
            else:
                l = j - 1
                while l >= 0 and dist_row[l] == dist_row[j]:
                    same = uv[b, l, 0] == dx and uv[b, l, 1] == dy and z[b, l] == dz
                    if valid[b, l] and same:
                        ok = False  # a copy of an earlier neighbour
                        break
                    l -= 1
        valid[b, j] = ok
        uv[b, j, 0] = dx
        uv[b, j, 1] = dy
        z[b, j] = dz
        if ok and (kframe <= 0 or j < kframe):
            cnt += 1
            cx += dx
            cy += dy
            cz += dz
            rr += dx * dx + dy * dy + dz * dz
    sxx = sxy = sxz = syy = syz = szz = 0.0
    if cnt > 0:
        cx /= cnt
        cy /= cnt
        cz /= cnt
        for j in range(K if kframe <= 0 else min(K, kframe)):
            if valid[b, j]:
                ex = uv[b, j, 0] - cx
                ey = uv[b, j, 1] - cy
                ez = z[b, j] - cz
                sxx += ex * ex
                sxy += ex * ey
                sxz += ex * ez
                syy += ey * ey
                syz += ey * ez
                szz += ez * ez
    _eigen_frame(sxx, sxy, sxz, syy, syz, szz, a, v, R, ob, lam, 0.0, 0.0, 0.0, False)
    e1x, e1y, e1z = R[ob, 0, 0], R[ob, 1, 0], R[ob, 2, 0]
    e2x, e2y, e2z = R[ob, 0, 1], R[ob, 1, 1], R[ob, 2, 1]
    e3x, e3y, e3z = R[ob, 0, 2], R[ob, 1, 2], R[ob, 2, 2]
    for j in range(K):
        if valid[b, j]:
            dx = uv[b, j, 0]
            dy = uv[b, j, 1]
            dz = z[b, j]
            uv[b, j, 0] = dx * e1x + dy * e1y + dz * e1z
            uv[b, j, 1] = dx * e2x + dy * e2y + dz * e2z
            z[b, j] = dx * e3x + dy * e3y + dz * e3z
        else:
            uv[b, j, 0] = 0.0
            uv[b, j, 1] = 0.0
            z[b, j] = 0.0
    return cnt, (math.sqrt(rr / cnt) if cnt > 0 else 0.0)


def _height_frames_py(P, qidx, nbr, dist, kuse, uv, z, valid, R, count, radius):
    """:func:`height_frame` of every query (rows of ``nbr``; ``kuse (Q,)`` rows each)."""
    Q = nbr.shape[0]
    lam = np.empty((Q, 3))
    nchunks = (Q + _CHUNK - 1) // _CHUNK
    for ch in nb.prange(nchunks):
        a = np.empty((3, 3))
        v = np.empty((3, 3))
        for i in range(ch * _CHUNK, min(Q, (ch + 1) * _CHUNK)):
            c, r = height_frame(P, qidx[i], nbr[i], dist[i], kuse[i], uv, z, valid, i, R, i, lam,
                                a, v)
            count[i] = c
            radius[i] = r


height_frames_par, height_frames_ser = njit_pair(_height_frames_py)


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
