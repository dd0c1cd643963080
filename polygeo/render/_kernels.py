"""Numba kernels of the soft rasterizer (private).

Everything here works on NumPy float64 arrays in screen space (pixels) and is wrapped by
:mod:`polygeo.render.soft`. Layouts:

``fv``      (B, F, 3, 3)  per face, per vertex ``(x, y, z)``: pixel coordinates and
                          camera depth.
``fd``      (B, F, NFD)   per-face constants computed by :func:`face_setup` (see the
                          ``_X0`` ... indices below).
``valid``   (B, F) uint8  1 where the face is drawn (not culled, not degenerate).
``bin_off`` (B * T + 1,)  CSR offsets of the faces binned into each of the ``T`` tiles of
``bin_f``   (nnz,) int32  each image, tiles in row-major order.

Per pixel and face the coverage is ``D = sigmoid(delta * d² / sigma)``; faces with
``D < blur_threshold`` (outside and ``d² > cutoff``) are ignored. The silhouette is
``alpha = 1 - P`` with ``P = prod(1 - D)``, and the colour the SoftRas softmax
``(sum_f a_f c_f + b c_bg) / Z`` with ``a_f = D_f exp((zn_f - m) / gamma)``,
``b = exp((zn_bg - m) / gamma)`` and ``m`` the running maximum of the normalised depths.
The forward pass stores only per-pixel aggregates (``P``, ``m``, ``Z``, the colour); the
backward pass recomputes the per-face terms over the same binned face lists.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .. import _numba_util  # noqa: F401  (cache keyed on all kernel sources; threading layer)

__all__: list[str] = []

_X0, _Y0, _X1, _Y1, _X2, _Y2 = 0, 1, 2, 3, 4, 5
_Z0, _Z1, _Z2 = 6, 7, 8
_A, _INVA = 9, 10
_XMIN, _XMAX, _YMIN, _YMAX = 11, 12, 13, 14
_IL0 = 15  # 15, 16, 17: 1 / |edge k|², edge k from vertex k to vertex (k + 1) % 3
_IZ0 = 18  # 18, 19, 20: 1 / z_k
NFD = 21

MODE_SILHOUETTE = 0
MODE_VERTEX = 1
MODE_TEXTURE = 2


@njit(cache=True)
def face_setup(fv, znear, min_area2, cull_back, fd, valid):
    """Fill ``fd`` and ``valid`` from face vertices ``fv``; return the number of valid faces."""
    B, F = fv.shape[0], fv.shape[1]
    n = 0
    for b in range(B):
        for f in range(F):
            x0, y0, z0 = fv[b, f, 0, 0], fv[b, f, 0, 1], fv[b, f, 0, 2]
            x1, y1, z1 = fv[b, f, 1, 0], fv[b, f, 1, 1], fv[b, f, 1, 2]
            x2, y2, z2 = fv[b, f, 2, 0], fv[b, f, 2, 1], fv[b, f, 2, 2]
            A = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
            ok = z0 >= znear and z1 >= znear and z2 >= znear and abs(A) > min_area2
            if cull_back and A > 0.0:
                ok = False
            valid[b, f] = 1 if ok else 0
            d = fd[b, f]
            d[_X0], d[_Y0], d[_X1], d[_Y1], d[_X2], d[_Y2] = x0, y0, x1, y1, x2, y2
            d[_Z0], d[_Z1], d[_Z2] = z0, z1, z2
            d[_IZ0] = 1.0 / z0 if ok else 0.0
            d[_IZ0 + 1] = 1.0 / z1 if ok else 0.0
            d[_IZ0 + 2] = 1.0 / z2 if ok else 0.0
            d[_A] = A
            d[_INVA] = 1.0 / A if ok else 0.0
            d[_XMIN] = min(x0, x1, x2)
            d[_XMAX] = max(x0, x1, x2)
            d[_YMIN] = min(y0, y1, y2)
            d[_YMAX] = max(y0, y1, y2)
            for k in range(3):
                ax, ay = fv[b, f, k, 0], fv[b, f, k, 1]
                bx, by = fv[b, f, (k + 1) % 3, 0], fv[b, f, (k + 1) % 3, 1]
                l2 = (bx - ax) ** 2 + (by - ay) ** 2
                d[_IL0 + k] = 1.0 / l2 if l2 > 1e-300 else 0.0
            if ok:
                n += 1
    return n


@njit(cache=True)
def _pix_range(lo, hi, margin, n):
    """Pixel indices whose centres ``k + 0.5`` lie in ``[lo - margin, hi + margin]``."""
    a = lo - margin - 0.5
    c = hi + margin - 0.5
    if a < 0.0:
        a = 0.0
    if c > n - 1.0:
        c = n - 1.0
    if c < a:
        return 1, 0
    return int(math.ceil(a)), int(math.floor(c))


@njit(cache=True)
def bin_faces(fd, valid, H, W, ts, margin):
    """Assign faces to ``ts``-pixel tiles by their bounding boxes grown by ``margin`` pixels.

    Returns ``(bin_off, bin_f)``: CSR offsets of length ``B * TH * TW + 1`` and face indices.
    """
    B, F = valid.shape[0], valid.shape[1]
    TH = (H + ts - 1) // ts
    TW = (W + ts - 1) // ts
    T = TH * TW
    counts = np.zeros(B * T + 1, dtype=np.int64)
    for b in range(B):
        for f in range(F):
            if valid[b, f] == 0:
                continue
            j0, j1 = _pix_range(fd[b, f, _XMIN], fd[b, f, _XMAX], margin, W)
            i0, i1 = _pix_range(fd[b, f, _YMIN], fd[b, f, _YMAX], margin, H)
            if j0 > j1 or i0 > i1:
                continue
            for ty in range(i0 // ts, i1 // ts + 1):
                for tx in range(j0 // ts, j1 // ts + 1):
                    counts[b * T + ty * TW + tx + 1] += 1
    for k in range(B * T):
        counts[k + 1] += counts[k]
    bin_f = np.empty(counts[B * T], dtype=np.int32)
    cur = counts[:-1].copy()
    for b in range(B):
        for f in range(F):
            if valid[b, f] == 0:
                continue
            j0, j1 = _pix_range(fd[b, f, _XMIN], fd[b, f, _XMAX], margin, W)
            i0, i1 = _pix_range(fd[b, f, _YMIN], fd[b, f, _YMAX], margin, H)
            if j0 > j1 or i0 > i1:
                continue
            for ty in range(i0 // ts, i1 // ts + 1):
                for tx in range(j0 // ts, j1 // ts + 1):
                    k = b * T + ty * TW + tx
                    bin_f[cur[k]] = f
                    cur[k] += 1
    return counts, bin_f


@njit(cache=True, inline="always")
def _geometry(d, qx, qy):
    """Barycentrics, inside flag and squared distance to the boundary of one face at q.

    Returns ``(w0, w1, w2, inside, d2, kmin, tmin, rx, ry)`` where ``kmin`` is the closest
    edge, ``tmin`` the clamped parameter of the closest point on it and ``(rx, ry)`` the
    vector from that point to q.
    """
    x0, y0, x1, y1, x2, y2 = d[_X0], d[_Y0], d[_X1], d[_Y1], d[_X2], d[_Y2]
    inva = d[_INVA]
    w0 = ((x1 - qx) * (y2 - qy) - (x2 - qx) * (y1 - qy)) * inva
    w1 = ((x2 - qx) * (y0 - qy) - (x0 - qx) * (y2 - qy)) * inva
    w2 = ((x0 - qx) * (y1 - qy) - (x1 - qx) * (y0 - qy)) * inva
    inside = w0 >= 0.0 and w1 >= 0.0 and w2 >= 0.0
    d2 = np.inf
    kmin = 0
    tmin = 0.0
    rxm = 0.0
    rym = 0.0
    for k in range(3):
        if k == 0:
            ax, ay, bx, by = x0, y0, x1, y1
        elif k == 1:
            ax, ay, bx, by = x1, y1, x2, y2
        else:
            ax, ay, bx, by = x2, y2, x0, y0
        ex = bx - ax
        ey = by - ay
        t = ((qx - ax) * ex + (qy - ay) * ey) * d[_IL0 + k]
        if t < 0.0:
            t = 0.0
        elif t > 1.0:
            t = 1.0
        rx = qx - (ax + t * ex)
        ry = qy - (ay + t * ey)
        dd = rx * rx + ry * ry
        if dd < d2:
            d2 = dd
            kmin = k
            tmin = t
            rxm = rx
            rym = ry
    return w0, w1, w2, inside, d2, kmin, tmin, rxm, rym


@njit(cache=True, inline="always")
def _coverage(inside, d2, inv_sigma):
    """``(D, 1 - D)`` for ``D = sigmoid(+-d2 / sigma)`` with a single exponential."""
    if inside:
        e = math.exp(-d2 * inv_sigma)
        D = 1.0 / (1.0 + e)
        return D, e * D
    e = math.exp(-d2 * inv_sigma)
    om = 1.0 / (1.0 + e)
    return e * om, om


@njit(cache=True, inline="always")
def _clip_bary(w0, w1, w2):
    k0 = min(max(w0, 0.0), 1.0)
    k1 = min(max(w1, 0.0), 1.0)
    k2 = min(max(w2, 0.0), 1.0)
    s = k0 + k1 + k2
    return k0 / s, k1 / s, k2 / s, s


@njit(cache=True)
def _tex_sample(tex, u, v, out):
    """Bilinear sample (clamp to edge) of ``tex`` (Ht, Wt, C) at ``(u, v)`` into ``out``."""
    Ht, Wt, C = tex.shape[0], tex.shape[1], tex.shape[2]
    X = min(max(u * Wt - 0.5, -1.0), float(Wt))
    Y = min(max(v * Ht - 0.5, -1.0), float(Ht))
    xf = math.floor(X)
    yf = math.floor(Y)
    fx = X - xf
    fy = Y - yf
    xa = min(max(int(xf), 0), Wt - 1)
    xb = min(max(int(xf) + 1, 0), Wt - 1)
    ya = min(max(int(yf), 0), Ht - 1)
    yb = min(max(int(yf) + 1, 0), Ht - 1)
    for c in range(C):
        out[c] = (1.0 - fy) * ((1.0 - fx) * tex[ya, xa, c] + fx * tex[ya, xb, c]) + fy * (
            (1.0 - fx) * tex[yb, xa, c] + fx * tex[yb, xb, c]
        )


@njit(cache=True)
def _tex_sample_grad(tex, u, v, out, gcol, gtex, need_tex):
    """Sample like :func:`_tex_sample`; scatter ``gcol`` into ``gtex``; return d/d(u, v)."""
    Ht, Wt, C = tex.shape[0], tex.shape[1], tex.shape[2]
    Xr = u * Wt - 0.5
    Yr = v * Ht - 0.5
    X = min(max(Xr, -1.0), float(Wt))
    Y = min(max(Yr, -1.0), float(Ht))
    xf = math.floor(X)
    yf = math.floor(Y)
    fx = X - xf
    fy = Y - yf
    xa = min(max(int(xf), 0), Wt - 1)
    xb = min(max(int(xf) + 1, 0), Wt - 1)
    ya = min(max(int(yf), 0), Ht - 1)
    yb = min(max(int(yf) + 1, 0), Ht - 1)
    gu = 0.0
    gv = 0.0
    for c in range(C):
        t00 = tex[ya, xa, c]
        t01 = tex[ya, xb, c]
        t10 = tex[yb, xa, c]
        t11 = tex[yb, xb, c]
        out[c] = (1.0 - fy) * ((1.0 - fx) * t00 + fx * t01) + fy * ((1.0 - fx) * t10 + fx * t11)
        g = gcol[c]
        gu += g * ((1.0 - fy) * (t01 - t00) + fy * (t11 - t10))
        gv += g * ((1.0 - fx) * (t10 - t00) + fx * (t11 - t01))
        if need_tex:
            gtex[ya, xa, c] += g * (1.0 - fy) * (1.0 - fx)
            gtex[ya, xb, c] += g * (1.0 - fy) * fx
            gtex[yb, xa, c] += g * fy * (1.0 - fx)
            gtex[yb, xb, c] += g * fy * fx
    # the clamp of X, Y to [-1, W] only acts where the sample is constant anyway
    return gu * Wt, gv * Ht


@njit(cache=True, inline="always")
def _tile_range(lo, hi, margin, t0, t1):
    """Pixels ``k`` in ``[t0, t1)`` with centres ``k + 0.5`` in ``[lo - margin, hi + margin]``."""
    a = lo - margin - 0.5
    c = hi + margin - 0.5
    if a < t0:
        a = float(t0)
    if c > t1 - 1.0:
        c = t1 - 1.0
    if c < a:
        return 1, 0
    return int(math.ceil(a)), int(math.floor(c))


@njit(cache=True, parallel=True)
def soft_forward(
    fd, bin_off, bin_f, H, W, ts, margin, cutoff, sigma, inv_gamma, znear, zfar, bg_depth, bg,
    mode, attr, uvs, tex, out_P, out_m, out_Z, out_rgb,
):  # fmt: skip
    """Soft silhouette (and colour when ``mode`` > 0) of every pixel; fills the ``out_*`` arrays.

    Tiles run in parallel; inside a tile the loop is face-major (each binned face visits
    the tile pixels within its grown bounding box) and the per-pixel aggregates live in
    tile-local arrays. Every pixel still sees its faces in bin order, so the result does
    not depend on the tiling.
    """
    B = fd.shape[0]
    TH = (H + ts - 1) // ts
    TW = (W + ts - 1) // ts
    T = TH * TW
    C = out_rgb.shape[3]
    Ba = attr.shape[0]
    Bu = uvs.shape[0]
    rgb_mode = mode != MODE_SILHOUETTE
    inv_sigma = 1.0 / sigma
    inv_range = 1.0 / (zfar - znear)
    for bt in prange(B * T):
        b = bt // T
        tile = bt - b * T
        ty = tile // TW
        tx = tile - ty * TW
        i0 = ty * ts
        i1 = min(H, i0 + ts)
        j0 = tx * ts
        j1 = min(W, j0 + ts)
        s0 = bin_off[bt]
        s1 = bin_off[bt + 1]
        ba = b if Ba > 1 else 0
        bu = b if Bu > 1 else 0
        tP = np.ones((i1 - i0, j1 - j0))
        tm = np.full((i1 - i0, j1 - j0), bg_depth)
        tZ = np.ones((i1 - i0, j1 - j0))
        tacc = np.empty((i1 - i0, j1 - j0, C))
        for li in range(i1 - i0):
            for lj in range(j1 - j0):
                for c in range(C):
                    tacc[li, lj, c] = bg[c]
        col = np.empty(C)
        for k in range(s0, s1):
            f = bin_f[k]
            d = fd[b, f]
            ja, jb = _tile_range(d[_XMIN], d[_XMAX], margin, j0, j1)
            ia, ib = _tile_range(d[_YMIN], d[_YMAX], margin, i0, i1)
            for i in range(ia, ib + 1):
                qy = i + 0.5
                li = i - i0
                for j in range(ja, jb + 1):
                    qx = j + 0.5
                    lj = j - j0
                    w0, w1, w2, inside, d2, _k, _t, _rx, _ry = _geometry(d, qx, qy)
                    if not inside and d2 > cutoff:
                        continue
                    D, omD = _coverage(inside, d2, inv_sigma)
                    tP[li, lj] *= omD
                    if not rgb_mode:
                        continue
                    c0, c1, c2, _s = _clip_bary(w0, w1, w2)
                    u0 = c0 * d[_IZ0]
                    u1 = c1 * d[_IZ0 + 1]
                    u2 = c2 * d[_IZ0 + 2]
                    zp = 1.0 / (u0 + u1 + u2)
                    p0 = u0 * zp
                    p1 = u1 * zp
                    p2 = u2 * zp
                    zn = (zfar - zp) * inv_range
                    if mode == MODE_VERTEX:
                        for c in range(C):
                            col[c] = (
                                p0 * attr[ba, f, 0, c]
                                + p1 * attr[ba, f, 1, c]
                                + p2 * attr[ba, f, 2, c]
                            )
                    else:
                        uu = p0 * uvs[bu, f, 0, 0] + p1 * uvs[bu, f, 1, 0] + p2 * uvs[bu, f, 2, 0]
                        vv = p0 * uvs[bu, f, 0, 1] + p1 * uvs[bu, f, 1, 1] + p2 * uvs[bu, f, 2, 1]
                        _tex_sample(tex, uu, vv, col)
                    m = tm[li, lj]
                    if zn > m:
                        sc = math.exp((m - zn) * inv_gamma)
                        tZ[li, lj] *= sc
                        for c in range(C):
                            tacc[li, lj, c] *= sc
                        m = zn
                        tm[li, lj] = zn
                    a = D * math.exp((zn - m) * inv_gamma)
                    tZ[li, lj] += a
                    for c in range(C):
                        tacc[li, lj, c] += a * col[c]
        for i in range(i0, i1):
            for j in range(j0, j1):
                out_P[b, i, j] = tP[i - i0, j - j0]
                if rgb_mode:
                    Zt = tZ[i - i0, j - j0]
                    out_m[b, i, j] = tm[i - i0, j - j0]
                    out_Z[b, i, j] = Zt
                    for c in range(C):
                        out_rgb[b, i, j, c] = tacc[i - i0, j - j0, c] / Zt


@njit(cache=True, inline="always")
def _edge_fn_grad(g, ax, ay, bx, by, qx, qy, gv, ia, ib):
    """Add ``g * d cross(a - q, b - q) / d(a, b)`` to ``gv[ia]`` and ``gv[ib]`` (x, y rows)."""
    gv[ia, 0] += g * (by - qy)
    gv[ia, 1] -= g * (bx - qx)
    gv[ib, 0] -= g * (ay - qy)
    gv[ib, 1] += g * (ax - qx)


@njit(cache=True, inline="always")
def _tile_cache(b, i0, i1, j0, j1, rgb_mode, P_img, m_img, Z_img, rgb_img, g_alpha, g_rgb,
                tgaP, tgdot, tinvZ, tm, tany):
    """Load a tile's per-pixel upstream terms; whether any pixel has a non-zero gradient."""
    C = rgb_img.shape[3]
    live = False
    for i in range(i0, i1):
        for j in range(j0, j1):
            li = i - i0
            lj = j - j0
            gaP = g_alpha[b, i, j] * P_img[b, i, j]
            tgaP[li, lj] = gaP
            any_rgb = False
            gdotI = 0.0
            if rgb_mode:
                tinvZ[li, lj] = 1.0 / Z_img[b, i, j]
                tm[li, lj] = m_img[b, i, j]
                for c in range(C):
                    gc = g_rgb[b, i, j, c]
                    if gc != 0.0:
                        any_rgb = True
                    gdotI += gc * rgb_img[b, i, j, c]
            tgdot[li, lj] = gdotI
            tany[li, lj] = any_rgb
            if gaP != 0.0 or any_rgb:
                live = True
    return live


@njit(cache=True, inline="always")
def _vertex_colour_grad(attr, ba, f, p0, p1, p2, col, gcol, gat, need_attr):
    """Per-vertex colours: fill ``col``, scatter into ``gat``; return d/d(p0, p1, p2)."""
    gp0 = 0.0
    gp1 = 0.0
    gp2 = 0.0
    for c in range(col.shape[0]):
        a0 = attr[ba, f, 0, c]
        a1 = attr[ba, f, 1, c]
        a2 = attr[ba, f, 2, c]
        col[c] = p0 * a0 + p1 * a1 + p2 * a2
        gp0 += gcol[c] * a0
        gp1 += gcol[c] * a1
        gp2 += gcol[c] * a2
        if need_attr:
            gat[ba, f, 0, c] += gcol[c] * p0
            gat[ba, f, 1, c] += gcol[c] * p1
            gat[ba, f, 2, c] += gcol[c] * p2
    return gp0, gp1, gp2


@njit(cache=True, inline="always")
def _uv_colour_grad(uvs, bu, f, p0, p1, p2, tex, col, gcol, gtx, guv, need_tex, need_uv):
    """Texture colours: fill ``col``, scatter into ``gtx``/``guv``; return d/d(p0, p1, p2)."""
    ua0, va0 = uvs[bu, f, 0, 0], uvs[bu, f, 0, 1]
    ua1, va1 = uvs[bu, f, 1, 0], uvs[bu, f, 1, 1]
    ua2, va2 = uvs[bu, f, 2, 0], uvs[bu, f, 2, 1]
    uu = p0 * ua0 + p1 * ua1 + p2 * ua2
    vv = p0 * va0 + p1 * va1 + p2 * va2
    gu, gvv = _tex_sample_grad(tex, uu, vv, col, gcol, gtx, need_tex)
    if need_uv:
        guv[bu, f, 0, 0] += gu * p0
        guv[bu, f, 0, 1] += gvv * p0
        guv[bu, f, 1, 0] += gu * p1
        guv[bu, f, 1, 1] += gvv * p1
        guv[bu, f, 2, 0] += gu * p2
        guv[bu, f, 2, 1] += gvv * p2
    return gu * ua0 + gvv * va0, gu * ua1 + gvv * va1, gu * ua2 + gvv * va2


@njit(cache=True, inline="always")
def _interp_grad(d, qx, qy, gp0, gp1, gp2, gzp, p0, p1, p2, zp, u0, u1, u2, c0, c1, c2, s,
                 w0, w1, w2, gv):
    """Chain d/d(perspective weights p_i, depth zp) back to the face's x, y, z into ``gv``."""
    iz0 = d[_IZ0]
    iz1 = d[_IZ0 + 1]
    iz2 = d[_IZ0 + 2]
    inva = d[_INVA]
    # p_i = u_i / U, zp = 1 / U
    sp = gp0 * p0 + gp1 * p1 + gp2 * p2
    gu0 = (gp0 - sp) * zp - gzp * zp * zp
    gu1 = (gp1 - sp) * zp - gzp * zp * zp
    gu2 = (gp2 - sp) * zp - gzp * zp * zp
    # u_i = c_i / z_i
    gv[0, 2] -= gu0 * u0 * iz0
    gv[1, 2] -= gu1 * u1 * iz1
    gv[2, 2] -= gu2 * u2 * iz2
    gc0 = gu0 * iz0
    gc1 = gu1 * iz1
    gc2 = gu2 * iz2
    # c_i = clamp(w_i) / s
    sc = gc0 * c0 + gc1 * c1 + gc2 * c2
    gw0 = (gc0 - sc) / s if 0.0 <= w0 <= 1.0 else 0.0
    gw1 = (gc1 - sc) / s if 0.0 <= w1 <= 1.0 else 0.0
    gw2 = (gc2 - sc) / s if 0.0 <= w2 <= 1.0 else 0.0
    # w_i = E_i / A, A = E0 + E1 + E2
    gA = -(gw0 * w0 + gw1 * w1 + gw2 * w2) * inva
    x0, y0, x1, y1, x2, y2 = d[0], d[1], d[2], d[3], d[4], d[5]
    _edge_fn_grad(gw0 * inva + gA, x1, y1, x2, y2, qx, qy, gv, 1, 2)
    _edge_fn_grad(gw1 * inva + gA, x2, y2, x0, y0, qx, qy, gv, 2, 0)
    _edge_fn_grad(gw2 * inva + gA, x0, y0, x1, y1, qx, qy, gv, 0, 1)


@njit(cache=True, inline="always")
def _distance_grad(gd2, kmin, tmin, rx, ry, gv):
    """Chain d/d(squared distance to the nearest edge kmin at parameter tmin) into ``gv``."""
    ka = kmin
    kb = (kmin + 1) % 3
    gv[ka, 0] -= gd2 * 2.0 * (1.0 - tmin) * rx
    gv[ka, 1] -= gd2 * 2.0 * (1.0 - tmin) * ry
    gv[kb, 0] -= gd2 * 2.0 * tmin * rx
    gv[kb, 1] -= gd2 * 2.0 * tmin * ry


@njit(cache=True, parallel=True)
def soft_backward(
    fd, bin_off, bin_f, H, W, ts, margin, cutoff, sigma, inv_gamma, znear, zfar,
    mode, attr, uvs, tex, P_img, m_img, Z_img, rgb_img, g_alpha, g_rgb,
    need_attr, need_uv, need_tex, g_fv, g_attr, g_uv, g_tex,
):  # fmt: skip
    """Gradients of the soft render; accumulates into per-chunk buffers ``g_*[chunk]``.

    ``g_fv`` (n_chunks, B, F, 3, 3) receives d/d(x, y, z) of every face vertex. Chunk ``c``
    handles tiles ``c, c + n_chunks, ...`` (no two threads write the same buffer); inside a
    tile the loop is face-major and a face's gradient is summed over the tile's pixels
    before it is written.
    """
    B = fd.shape[0]
    TH = (H + ts - 1) // ts
    TW = (W + ts - 1) // ts
    T = TH * TW
    C = rgb_img.shape[3]
    Ba = attr.shape[0]
    Bu = uvs.shape[0]
    nch = g_fv.shape[0]
    rgb_mode = mode != MODE_SILHOUETTE
    inv_sigma = 1.0 / sigma
    inv_range = 1.0 / (zfar - znear)
    for ch in prange(nch):
        col = np.empty(C)
        gcol = np.empty(C)
        gv = np.zeros((3, 3))
        tgaP = np.empty((ts, ts))
        tgdot = np.empty((ts, ts))
        tinvZ = np.empty((ts, ts))
        tm = np.empty((ts, ts))
        tany = np.zeros((ts, ts), dtype=np.bool_)
        gfv = g_fv[ch]
        gat = g_attr[ch]
        guv = g_uv[ch]
        gtx = g_tex[ch]
        for bt in range(ch, B * T, nch):
            b = bt // T
            tile = bt - b * T
            ty = tile // TW
            tx = tile - ty * TW
            s0 = bin_off[bt]
            s1 = bin_off[bt + 1]
            if s0 == s1:
                continue
            i0 = ty * ts
            i1 = min(H, i0 + ts)
            j0 = tx * ts
            j1 = min(W, j0 + ts)
            ba = b if Ba > 1 else 0
            bu = b if Bu > 1 else 0
            if not _tile_cache(b, i0, i1, j0, j1, rgb_mode, P_img, m_img, Z_img, rgb_img,
                               g_alpha, g_rgb, tgaP, tgdot, tinvZ, tm, tany):
                continue
            for k in range(s0, s1):
                f = bin_f[k]
                d = fd[b, f]
                ja, jb = _tile_range(d[_XMIN], d[_XMAX], margin, j0, j1)
                ia, ib = _tile_range(d[_YMIN], d[_YMAX], margin, i0, i1)
                if ja > jb or ia > ib:
                    continue
                gv[:] = 0.0
                iz0 = d[_IZ0]
                iz1 = d[_IZ0 + 1]
                iz2 = d[_IZ0 + 2]
                for i in range(ia, ib + 1):
                    qy = i + 0.5
                    li = i - i0
                    for j in range(ja, jb + 1):
                        lj = j - j0
                        gaP = tgaP[li, lj]
                        any_rgb = tany[li, lj]
                        if gaP == 0.0 and not any_rgb:
                            continue
                        qx = j + 0.5
                        w0, w1, w2, inside, d2, kmin, tmin, rx, ry = _geometry(d, qx, qy)
                        if not inside and d2 > cutoff:
                            continue
                        D, omD = _coverage(inside, d2, inv_sigma)
                        gx = gaP * D
                        if any_rgb:
                            invZ = tinvZ[li, lj]
                            c0, c1, c2, s = _clip_bary(w0, w1, w2)
                            u0 = c0 * iz0
                            u1 = c1 * iz1
                            u2 = c2 * iz2
                            U = u0 + u1 + u2
                            zp = 1.0 / U
                            p0 = u0 * zp
                            p1 = u1 * zp
                            p2 = u2 * zp
                            zn = (zfar - zp) * inv_range
                            ez = math.exp((zn - tm[li, lj]) * inv_gamma)
                            a = D * ez
                            for c in range(C):
                                gcol[c] = g_rgb[b, i, j, c] * a * invZ
                            if mode == MODE_VERTEX:
                                gp0, gp1, gp2 = _vertex_colour_grad(attr, ba, f, p0, p1, p2, col,
                                                                    gcol, gat, need_attr)
                            else:
                                gp0, gp1, gp2 = _uv_colour_grad(uvs, bu, f, p0, p1, p2, tex, col,
                                                                gcol, gtx, guv, need_tex, need_uv)
                            gdc = 0.0
                            for c in range(C):
                                gdc += g_rgb[b, i, j, c] * col[c]
                            ga = (gdc - tgdot[li, lj]) * invZ
                            gx += ga * ez * D * omD
                            gzp = -ga * a * inv_gamma * inv_range
                            _interp_grad(d, qx, qy, gp0, gp1, gp2, gzp, p0, p1, p2, zp, u0, u1,
                                         u2, c0, c1, c2, s, w0, w1, w2, gv)
                        # silhouette / coverage: x = +-d2 / sigma
                        gd2 = gx * inv_sigma if inside else -gx * inv_sigma
                        if gd2 != 0.0:
                            _distance_grad(gd2, kmin, tmin, rx, ry, gv)
                for r in range(3):
                    gfv[b, f, r, 0] += gv[r, 0]
                    gfv[b, f, r, 1] += gv[r, 1]
                    gfv[b, f, r, 2] += gv[r, 2]


@njit(cache=True, parallel=True)
def nearest_face(fd, bin_off, bin_f, H, W, ts, out_idx, out_depth):
    """Hard z-buffer: index of the nearest face whose triangle contains each pixel centre.

    Fills ``out_idx`` (B, H, W) with the face index (-1 where none) and ``out_depth`` with
    its perspective-correct depth (0 where none). Ties keep the lowest face index.
    """
    B = fd.shape[0]
    TH = (H + ts - 1) // ts
    TW = (W + ts - 1) // ts
    T = TH * TW
    for bt in prange(B * T):
        b = bt // T
        tile = bt - b * T
        ty = tile // TW
        tx = tile - ty * TW
        s0 = bin_off[bt]
        s1 = bin_off[bt + 1]
        for i in range(ty * ts, min(H, ty * ts + ts)):
            qy = i + 0.5
            for j in range(tx * ts, min(W, tx * ts + ts)):
                qx = j + 0.5
                best = -1
                bz = np.inf
                for k in range(s0, s1):
                    f = bin_f[k]
                    d = fd[b, f]
                    if qx < d[_XMIN] or qx > d[_XMAX] or qy < d[_YMIN] or qy > d[_YMAX]:
                        continue
                    x0, y0, x1, y1, x2, y2 = d[0], d[1], d[2], d[3], d[4], d[5]
                    inva = d[_INVA]
                    w0 = ((x1 - qx) * (y2 - qy) - (x2 - qx) * (y1 - qy)) * inva
                    w1 = ((x2 - qx) * (y0 - qy) - (x0 - qx) * (y2 - qy)) * inva
                    w2 = ((x0 - qx) * (y1 - qy) - (x1 - qx) * (y0 - qy)) * inva
                    if w0 < 0.0 or w1 < 0.0 or w2 < 0.0:
                        continue
                    zp = 1.0 / (w0 / d[_Z0] + w1 / d[_Z1] + w2 / d[_Z2])
                    if zp < bz or (zp == bz and f < best):
                        bz = zp
                        best = f
                out_idx[b, i, j] = best
                out_depth[b, i, j] = bz if best >= 0 else 0.0
