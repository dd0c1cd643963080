"""Fused CPU kernels of the membrane and bending energies, with gradients and PSD Hessians.

The same energies as :func:`draping.physics.stvk_energy` and
:func:`draping.physics.bending_energy` (flat rest, eq. (17)), evaluated for one frame in numba
loops instead of torch graphs, for solvers that evaluate them hundreds of times per frame
(:mod:`draping.reference`). The torch functions stay the reference: the tests compare energies
and gradients with them.

Hessians are positive semi-definite approximations, per element:

- membrane: ``d^2 psi / dF^2 = dF S + F dS(dF)``; the second part is positive semi-definite
  (``2 mu |sym(F^T dF)|^2 + lambda tr(F^T dF)^2``) and the first is made so by replacing the
  second Piola-Kirchhoff stress ``S`` with its positive part (compressed directions get no
  negative stiffness), exact for a stretched triangle;
- bending: the Gauss-Newton term ``2 k_b w grad(theta) grad(theta)^T``.

All arrays are float64; positions in metres, energies in joules.
"""

from __future__ import annotations

import numba as nb
import numpy as np

__all__ = ["membrane", "bending", "hinge_quads"]


def hinge_quads(faces: np.ndarray, hinge_edges: np.ndarray, hinge_faces: np.ndarray) -> np.ndarray:
    """Vertex quadruples ``(a, b, c, d)`` of each hinge.

    The edge ``a -> b`` as wound by the first face, ``c`` opposite in the first face, ``d``
    opposite in the second.

    Parameters
    ----------
    faces : (F, 3) int
        Triangles.
    hinge_edges, hinge_faces : (H, 2) int
        From :func:`polygeo.mesh.dihedral_angles`.

    Returns
    -------
    (H, 4) int64
    """
    f = np.asarray(faces, dtype=np.int64)
    e = np.asarray(hinge_edges, dtype=np.int64)
    hf = np.asarray(hinge_faces, dtype=np.int64)
    c = f[hf[:, 0]].sum(1) - e.sum(1)
    d = f[hf[:, 1]].sum(1) - e.sum(1)
    return np.stack([e[:, 0], e[:, 1], c, d], 1)


@nb.njit(cache=True)
def _membrane(
    x, faces, dm_inv, area, h, mu, lam, grad, blocks, bmap, want_grad, want_hess, project
):
    energy = 0.0
    nf = faces.shape[0]
    fm = np.empty((3, 2))
    cc = np.empty((3, 2))
    hf = np.empty((3, 2, 3, 2))
    for t in range(nf):
        i0, i1, i2 = faces[t, 0], faces[t, 1], faces[t, 2]
        d = dm_inv[t]
        for j in range(2):
            cc[1, j] = d[0, j]
            cc[2, j] = d[1, j]
            cc[0, j] = -d[0, j] - d[1, j]
        for i in range(3):
            a = x[i1, i] - x[i0, i]
            b = x[i2, i] - x[i0, i]
            for j in range(2):
                fm[i, j] = a * d[0, j] + b * d[1, j]
        c00 = fm[0, 0] * fm[0, 0] + fm[1, 0] * fm[1, 0] + fm[2, 0] * fm[2, 0]
        c01 = fm[0, 0] * fm[0, 1] + fm[1, 0] * fm[1, 1] + fm[2, 0] * fm[2, 1]
        c11 = fm[0, 1] * fm[0, 1] + fm[1, 1] * fm[1, 1] + fm[2, 1] * fm[2, 1]
        e00 = 0.5 * (c00 - 1.0)
        e01 = 0.5 * c01
        e11 = 0.5 * (c11 - 1.0)
        tr = e00 + e11
        w = area[t] * h
        energy += w * (mu * (e00 * e00 + 2 * e01 * e01 + e11 * e11) + 0.5 * lam * tr * tr)
        s00 = 2 * mu * e00 + lam * tr
        s01 = 2 * mu * e01
        s11 = 2 * mu * e11 + lam * tr
        if not want_grad:
            continue
        # gradient: dE/dx_v = w * P c_v, P = F S
        for i in range(3):
            p0 = fm[i, 0] * s00 + fm[i, 1] * s01
            p1 = fm[i, 0] * s01 + fm[i, 1] * s11
            for v in range(3):
                vi = faces[t, v]
                grad[vi, i] += w * (p0 * cc[v, 0] + p1 * cc[v, 1])
        if not want_hess:
            continue
        # positive part of S (2x2 symmetric)
        m = 0.5 * (s00 + s11)
        r = np.sqrt(0.25 * (s00 - s11) ** 2 + s01 * s01)
        l1 = m + r
        l2 = m - r
        # eigenvector of l1 from the row that avoids cancellation
        if s00 >= s11:
            u0 = l1 - s11
            u1 = s01
        else:
            u0 = s01
            u1 = l1 - s00
        nu = np.sqrt(u0 * u0 + u1 * u1)
        if nu > 1e-300:
            u0 /= nu
            u1 /= nu
        else:  # S is a multiple of the identity
            u0, u1 = 1.0, 0.0
        p1 = max(l1, 0.0) if project else l1
        p2 = max(l2, 0.0) if project else l2
        sp00 = p1 * u0 * u0 + p2 * u1 * u1
        sp01 = (p1 - p2) * u0 * u1
        sp11 = p1 * u1 * u1 + p2 * u0 * u0
        for i in range(3):
            for j in range(2):
                for k in range(3):
                    for l in range(2):
                        val = mu * fm[i, l] * fm[k, j] + lam * fm[i, j] * fm[k, l]
                        if l == j:
                            val += mu * (fm[i, 0] * fm[k, 0] + fm[i, 1] * fm[k, 1])
                        if i == k:
                            if j == 0 and l == 0:
                                val += sp00
                            elif j == 1 and l == 1:
                                val += sp11
                            else:
                                val += sp01
                        hf[i, j, k, l] = val
        for v in range(3):
            for u in range(3):
                blk = bmap[t, v, u]
                for i in range(3):
                    for k in range(3):
                        acc = 0.0
                        for j in range(2):
                            for l in range(2):
                                acc += cc[v, j] * cc[u, l] * hf[i, j, k, l]
                        blocks[blk, i, k] += w * acc
    return energy


@nb.njit(cache=True)
def _cross(u, v, out):  # pragma: no cover
    out[0] = u[1] * v[2] - u[2] * v[1]
    out[1] = u[2] * v[0] - u[0] * v[2]
    out[2] = u[0] * v[1] - u[1] * v[0]


@nb.njit(cache=True)
def _bending(x, quads, weight, kb, grad, blocks, bmap, want_grad, want_hess):  # pragma: no cover
    energy = 0.0
    nh = quads.shape[0]
    g = np.empty((4, 3))
    e = np.empty(3)
    ea = np.empty(3)
    eb = np.empty(3)
    na = np.empty(3)
    nbv = np.empty(3)
    cr = np.empty(3)
    q = np.empty(4, dtype=np.int64)
    for t in range(nh):
        a, b, c, d = quads[t, 0], quads[t, 1], quads[t, 2], quads[t, 3]
        for i in range(3):
            e[i] = x[b, i] - x[a, i]
            ea[i] = x[c, i] - x[a, i]
            eb[i] = x[d, i] - x[a, i]
        _cross(e, ea, na)
        _cross(eb, e, nbv)
        le2 = e[0] * e[0] + e[1] * e[1] + e[2] * e[2]
        la2 = na[0] * na[0] + na[1] * na[1] + na[2] * na[2]
        lb2 = nbv[0] * nbv[0] + nbv[1] * nbv[1] + nbv[2] * nbv[2]
        if le2 <= 1e-300 or la2 <= 1e-300 or lb2 <= 1e-300:
            continue  # degenerate hinge: no bending (as mesh.dihedral_angles' valid mask)
        le = np.sqrt(le2)
        la = np.sqrt(la2)
        lb = np.sqrt(lb2)
        _cross(na, nbv, cr)
        s = (cr[0] * e[0] + cr[1] * e[1] + cr[2] * e[2]) / (la * lb * le)
        co = (na[0] * nbv[0] + na[1] * nbv[1] + na[2] * nbv[2]) / (la * lb)
        th = np.arctan2(s, co)
        k = kb * weight[t]
        energy += k * th * th
        if not want_grad:
            continue
        ta = (ea[0] * e[0] + ea[1] * e[1] + ea[2] * e[2]) / le2
        tb = (eb[0] * e[0] + eb[1] * e[1] + eb[2] * e[2]) / le2
        for i in range(3):
            ga = -le * na[i] / la2
            gb = -le * nbv[i] / lb2
            g[2, i] = ga
            g[3, i] = gb
            g[0, i] = -(1.0 - ta) * ga - (1.0 - tb) * gb
            g[1, i] = -ta * ga - tb * gb
        q[0], q[1], q[2], q[3] = a, b, c, d
        for v in range(4):
            for i in range(3):
                grad[q[v], i] += 2.0 * k * th * g[v, i]
        if want_hess:
            for v in range(4):
                for u in range(4):
                    blk = bmap[t, v, u]
                    for i in range(3):
                        for j in range(3):
                            blocks[blk, i, j] += 2.0 * k * g[v, i] * g[u, j]
    return energy


def _element_blocks(n_elem: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    """One private 3x3 block per corner pair of each element (for element Hessians)."""
    bmap = np.arange(n_elem * k * k, dtype=np.int64).reshape(n_elem, k, k)
    return np.zeros((n_elem * k * k, 3, 3)), bmap


def _hess_out(blocks, bmap, n_elem, k):
    if blocks is None:
        blocks, bmap = _element_blocks(n_elem, k)
        return blocks, bmap, True
    return blocks, np.ascontiguousarray(bmap, dtype=np.int64), False


def membrane(
    x: np.ndarray,
    faces: np.ndarray,
    dm_inv: np.ndarray,
    area: np.ndarray,
    thickness: float,
    mu: float,
    lam: float,
    want_hess: bool = False,
    blocks: np.ndarray | None = None,
    block_map: np.ndarray | None = None,
    project: bool = True,
    want_grad: bool = True,
) -> tuple[float, np.ndarray, np.ndarray | None]:
    """StVK membrane energy (J), its gradient (V, 3) (N) and PSD Hessians.

    Parameters
    ----------
    x : (V, 3) float64
        Positions (m).
    faces : (F, 3) int64
        Triangles.
    dm_inv : (F, 2, 2) float64
        Inverse rest edge matrices (1/m).
    area : (F,) float64
        Rest areas (m^2).
    thickness, mu, lam : float
        ``h`` (m) and the Lame coefficients (Pa).
    want_hess : bool
        Also compute the Hessian.
    blocks : (NB, 3, 3) float64, optional
        Sparse 3x3 blocks the Hessian is added into (in place), at ``block_map``.
    block_map : (F, 3, 3) int64, optional
        Block of each corner pair ``(v, u)`` of each triangle.
    project : bool
        Positive part of the stress in the Hessian (positive semi-definite); False gives the
        exact Hessian, indefinite under compression.
    want_grad : bool
        Accumulate the gradient (else it comes back as zeros; energy-only line searches).

    Returns
    -------
    energy : float
    grad : (V, 3) float64
    hess : (F, 9, 9) float64, ``blocks`` or None
        Element Hessians (rows ``3 v + i``: corner ``v``, coordinate ``i``) when no
        ``blocks`` are given, else ``blocks``; None without ``want_hess``.
    """
    grad = np.zeros_like(x)
    nf = faces.shape[0]
    if want_hess:
        blocks, bmap, own = _hess_out(blocks, block_map, nf, 3)
    else:
        blocks, bmap, own = np.zeros((0, 3, 3)), np.zeros((0, 3, 3), dtype=np.int64), False
    e = _membrane(
        x,
        faces,
        dm_inv,
        area,
        thickness,
        mu,
        lam,
        grad,
        blocks,
        bmap,
        want_grad or want_hess,
        want_hess,
        project,
    )
    if not want_hess:
        return float(e), grad, None
    if own:
        return (
            float(e),
            grad,
            blocks.reshape(nf, 3, 3, 3, 3).transpose(0, 1, 3, 2, 4).reshape(nf, 9, 9),
        )
    return float(e), grad, blocks


def bending(
    x: np.ndarray,
    quads: np.ndarray,
    weight: np.ndarray,
    kb: float,
    want_hess: bool = False,
    blocks: np.ndarray | None = None,
    block_map: np.ndarray | None = None,
    want_grad: bool = True,
) -> tuple[float, np.ndarray, np.ndarray | None]:
    """Dihedral bending energy (J) with flat rest, its gradient and Gauss-Newton Hessians.

    Parameters
    ----------
    x : (V, 3) float64
        Positions (m).
    quads : (H, 4) int64
        From :func:`hinge_quads`.
    weight : (H,) float64
        ``l^2 / (8 (A_0 + A_1))`` at rest.
    kb : float
        Bending stiffness (J).
    want_hess : bool
        Also compute the Hessian.
    blocks : (NB, 3, 3) float64, optional
        Sparse blocks the Hessian is added into, at ``block_map (H, 4, 4)``.
    block_map : (H, 4, 4) int64, optional
    want_grad : bool
        Accumulate the gradient (else zeros).

    Returns
    -------
    energy : float
    grad : (V, 3) float64
    hess : (H, 12, 12) float64, ``blocks`` or None
        As :func:`membrane`, over the corners ``(a, b, c, d)``.
    """
    grad = np.zeros_like(x)
    nh = quads.shape[0]
    if want_hess:
        blocks, bmap, own = _hess_out(blocks, block_map, nh, 4)
    else:
        blocks, bmap, own = np.zeros((0, 3, 3)), np.zeros((0, 4, 4), dtype=np.int64), False
    e = _bending(x, quads, weight, kb, grad, blocks, bmap, want_grad or want_hess, want_hess)
    if not want_hess:
        return float(e), grad, None
    if own:
        return (
            float(e),
            grad,
            blocks.reshape(nh, 4, 4, 3, 3).transpose(0, 1, 3, 2, 4).reshape(nh, 12, 12),
        )
    return float(e), grad, blocks
