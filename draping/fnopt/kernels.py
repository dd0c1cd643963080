"""Fused CPU kernels (numba) of FNOpt's inference loop: gradient, Hessian products, subspace Gram.

:func:`draping.fnopt.cloth.loss_hvp` builds ``H d`` from a few dozen tensor operations over
``(K, B, H, W, 3)`` arrays; each reads and writes the whole field, so at 64x64 / 100x100 five
products cost ~1.6 / ~3.6 ms, more than the FNO's forward. :func:`loss_hvp_fused` computes the
same products (the same quadrature, term by term) in one pass per direction, accumulating in
float64, :func:`loss_grad_fused` the loss and its gradient ``dL/da`` (the closed form of
:func:`draping.fnopt.cloth.energies`' derivative, instead of an autograd forward and backward
pass) in one pass, and :func:`gram_fused` the subspace step's ``D^T H D`` and ``g^T D`` in one
pass over the fields without float64 copies of them, and :func:`subspace_coefficients` that
Gram matrix with the subspace step's small shifted solves in one call. The per-problem constants
(:func:`kernel_constants`) can be built once and passed in. All are for inference: they are not
differentiable (training's pool steps keep the torch functions and autograd, so ``polygeo
train-fnopt`` is unchanged; the rollout fine-tuning option, whose products are closed form,
gets the fused gradient, detached there as before). The torch
functions stay the reference; the tests compare with them (float64: to rounding).
"""

from __future__ import annotations

import numba as nb
import numpy as np
import torch

from .cloth import GRAVITY, positions_from_accel

__all__ = ["loss_grad_fused", "loss_hvp_fused", "gram_fused", "kernel_constants",
           "subspace_coefficients"]


@nb.njit(cache=True)
def _hvp(d, x, mass, bx, by, ks, ksh, kb, damp, wr, wc, ir, ic, dt, out):
    """``out[k, b] = H_b d[k, b]``; see :func:`loss_hvp_fused`."""
    n_dir, n_b, h, w, _ = d.shape
    dt2 = dt * dt
    xu = np.empty((h, w - 1, 3))
    xv = np.empty((h - 1, w, 3))
    du = np.empty((h, w - 1, 3))
    dv = np.empty((h - 1, w, 3))
    qu = np.empty((h, w - 1, 3))
    qv = np.empty((h - 1, w, 3))
    su = np.empty((h, w - 1))
    sv = np.empty((h - 1, w))
    for b in range(n_b):
        ibx, iby = 1.0 / bx[b], 1.0 / by[b]
        for i in range(h):
            for j in range(w - 1):
                s = 0.0
                for c in range(3):
                    t = (np.float64(x[b, i, j + 1, c]) - np.float64(x[b, i, j, c])) * ibx
                    xu[i, j, c] = t
                    s += t * t
                su[i, j] = 0.5 * (s - 1.0)
        for i in range(h - 1):
            for j in range(w):
                s = 0.0
                for c in range(3):
                    t = (np.float64(x[b, i + 1, j, c]) - np.float64(x[b, i, j, c])) * iby
                    xv[i, j, c] = t
                    s += t * t
                sv[i, j] = 0.5 * (s - 1.0)
        for k in range(n_dir):
            for i in range(h):                                  # stretch along u
                for j in range(w - 1):
                    p = 0.0
                    for c in range(3):
                        t = dt2 * (np.float64(d[k, b, i, j + 1, c])
                                   - np.float64(d[k, b, i, j, c])) * ibx
                        du[i, j, c] = t
                        p += xu[i, j, c] * t
                    f = ks[b] * wr[i]
                    for c in range(3):
                        qu[i, j, c] = f * (su[i, j] * du[i, j, c] + p * xu[i, j, c])
            for i in range(h - 1):                              # stretch along v
                for j in range(w):
                    p = 0.0
                    for c in range(3):
                        t = dt2 * (np.float64(d[k, b, i + 1, j, c])
                                   - np.float64(d[k, b, i, j, c])) * iby
                        dv[i, j, c] = t
                        p += xv[i, j, c] * t
                    f = ks[b] * wc[j]
                    for c in range(3):
                        qv[i, j, c] = f * (sv[i, j] * dv[i, j, c] + p * xv[i, j, c])
            for i in range(h - 1):                              # shear, per cell
                for j in range(w - 1):
                    cc = 0.0
                    dc = 0.0
                    for c in range(3):
                        fu = 0.5 * (xu[i + 1, j, c] + xu[i, j, c])
                        fv = 0.5 * (xv[i, j + 1, c] + xv[i, j, c])
                        dfu = 0.5 * (du[i + 1, j, c] + du[i, j, c])
                        dfv = 0.5 * (dv[i, j + 1, c] + dv[i, j, c])
                        cc += fu * fv
                        dc += dfu * fv + fu * dfv
                    for c in range(3):
                        fu = 0.5 * (xu[i + 1, j, c] + xu[i, j, c])
                        fv = 0.5 * (xv[i, j + 1, c] + xv[i, j, c])
                        dfu = 0.5 * (du[i + 1, j, c] + du[i, j, c])
                        dfv = 0.5 * (dv[i, j + 1, c] + dv[i, j, c])
                        tu = 0.5 * ksh[b] * (dc * fv + cc * dfv)
                        tv = 0.5 * ksh[b] * (dc * fu + cc * dfu)
                        qu[i, j, c] += tu
                        qu[i + 1, j, c] += tu
                        qv[i, j, c] += tv
                        qv[i, j + 1, c] += tv
            for i in range(h):                                  # bend: x_uu
                for j in range(w - 2):
                    f = kb[b] * wr[i] * ic[j] * ibx * ibx
                    for c in range(3):
                        t = f * (du[i, j + 1, c] - du[i, j, c])
                        qu[i, j + 1, c] += t
                        qu[i, j, c] -= t
            for i in range(h - 1):                              # bend: x_uv
                for j in range(w - 1):
                    f = 2.0 * kb[b] * iby * iby
                    for c in range(3):
                        t = f * (du[i + 1, j, c] - du[i, j, c])
                        qu[i + 1, j, c] += t
                        qu[i, j, c] -= t
            for i in range(h - 2):                              # bend: x_vv
                for j in range(w):
                    f = kb[b] * wc[j] * ir[i] * iby * iby
                    for c in range(3):
                        t = f * (dv[i + 1, j, c] - dv[i, j, c])
                        qv[i + 1, j, c] += t
                        qv[i, j, c] -= t
            inert = dt2 + damp[b] * dt2 * dt
            for i in range(h):                                  # divergence, inertia, damping
                for j in range(w):
                    m = inert * np.float64(mass[b, i, j])
                    for c in range(3):
                        t = 0.0
                        if j > 0:
                            t += qu[i, j - 1, c] * ibx
                        if j < w - 1:
                            t -= qu[i, j, c] * ibx
                        if i > 0:
                            t += qv[i - 1, j, c] * iby
                        if i < h - 1:
                            t -= qv[i, j, c] * iby
                        out[k, b, i, j, c] = dt2 * t + m * np.float64(d[k, b, i, j, c])


def _weights(n: int, inner: bool) -> np.ndarray:
    """The quadrature weights of :mod:`draping.fnopt.cloth` (rim halved; ``inner``: interior).

    ``n`` samples with the rim's halved, or (``inner``) the ``n - 2`` interior ones with the
    rim's halves added.
    """
    if inner:
        wt = np.ones(n - 2)
        wt[0] += 0.5
        wt[-1] += 0.5
        return wt
    wt = np.ones(n)
    wt[0] = wt[-1] = 0.5
    return wt


def _per_sheet(v, b: int) -> np.ndarray:
    return np.ascontiguousarray(np.broadcast_to(
        torch.as_tensor(v).detach().double().reshape(-1).numpy(), (b,)))


def kernel_constants(b: int, h: int, w: int, hx, hy, material: dict) -> tuple:
    """The kernels' per-problem constants: spacings, stiffnesses times area, weights.

    ``(bx, by, ks, ksh, kb, damp, wr, wc, ir, ic)``: ``(B,)`` float64 arrays (spacings, m;
    stretch, shear and ``1e-3`` bend stiffness times the cell area; damping, 1/s) and the
    quadrature weights of :func:`_weights`. A caller that solves one problem many times (a
    :class:`draping.fnopt.solvers.StepProblem`) builds them once and passes them as
    ``consts`` to :func:`loss_grad_fused` / :func:`loss_hvp_fused`: ~16 small tensor-to-array
    conversions fewer per call.
    """
    bx, by = _per_sheet(hx, b), _per_sheet(hy, b)
    area = bx * by
    k = {n: _per_sheet(material.get(n, 0.0), b) for n in ("stretch", "shear", "bend", "damping")}
    return (bx, by, k["stretch"] * area, k["shear"] * area, 1e-3 * k["bend"] * area,
            k["damping"], _weights(h, False), _weights(w, False), _weights(h, True),
            _weights(w, True))


def loss_hvp_fused(d: torch.Tensor, a: torch.Tensor, x_prev: torch.Tensor, v_prev: torch.Tensor,
                   hx, hy, material: dict, dt: float, mass: torch.Tensor,
                   consts: tuple | None = None) -> torch.Tensor:
    """:func:`draping.fnopt.cloth.loss_hvp` in one fused numba pass (not differentiable).

    Parameters and units as there: ``d`` ``(K, B, H, W, 3)`` or ``(B, H, W, 3)`` directions
    (m/s^2), ``a``, ``x_prev``, ``v_prev`` ``(B, H, W, 3)``, ``mass`` ``(B, H, W)`` (kg).
    Returns ``H d`` like ``d`` (J s^4/m^2), computed in float64 and returned in ``d``'s dtype:
    equal to the torch function up to rounding (float64 inputs: ~1e-15 relative).
    ``consts``: :func:`kernel_constants` of ``hx``, ``hy``, ``material`` (built here when not
    given).

    Raises
    ------
    ValueError
        If ``d``'s trailing shape is not ``a``'s or the grid is smaller than 3 x 3.
    """
    single = d.dim() == 4
    dd = d[None] if single else d
    if dd.dim() != 5 or dd.shape[1:] != a.shape:
        raise ValueError(f"d: expected shape (K, *{tuple(a.shape)}) or {tuple(a.shape)}, got "
                         f"{tuple(d.shape)}")
    b, h, w, _ = a.shape
    if h < 3 or w < 3:
        raise ValueError(f"a: expected a grid of at least 3 x 3 vertices, got {h} x {w}")
    x = positions_from_accel(a.detach(), x_prev, v_prev, dt)
    consts = kernel_constants(b, h, w, hx, hy, material) if consts is None else consts
    out = np.empty(dd.shape, dtype=np.float64)
    _hvp(dd.detach().contiguous().numpy(), x.contiguous().numpy(),
         mass.detach().contiguous().numpy(), *consts, float(dt), out)
    res = torch.from_numpy(out).to(d.dtype)
    return res[0] if single else res


@nb.njit(cache=True)
def _grad(a, x, x_prev, mass, bx, by, ks, ksh, kb, damp, wr, wc, ir, ic, dt, grav, out, val):
    """``val[b] = L_b``, ``out[b] = dL_b/da``; see :func:`loss_grad_fused`."""
    n_b, h, w, _ = a.shape
    dt2 = dt * dt
    xu = np.empty((h, w - 1, 3))
    xv = np.empty((h - 1, w, 3))
    qu = np.empty((h, w - 1, 3))
    qv = np.empty((h - 1, w, 3))
    for b in range(n_b):
        ibx, iby = 1.0 / bx[b], 1.0 / by[b]
        e_st = 0.0
        for i in range(h):                                      # stretch along u
            for j in range(w - 1):
                s = 0.0
                for c in range(3):
                    t = (np.float64(x[b, i, j + 1, c]) - np.float64(x[b, i, j, c])) * ibx
                    xu[i, j, c] = t
                    s += t * t
                su = 0.5 * (s - 1.0)
                e_st += wr[i] * su * su
                f = ks[b] * wr[i] * su
                for c in range(3):
                    qu[i, j, c] = f * xu[i, j, c]
        for i in range(h - 1):                                  # stretch along v
            for j in range(w):
                s = 0.0
                for c in range(3):
                    t = (np.float64(x[b, i + 1, j, c]) - np.float64(x[b, i, j, c])) * iby
                    xv[i, j, c] = t
                    s += t * t
                sv = 0.5 * (s - 1.0)
                e_st += wc[j] * sv * sv
                f = ks[b] * wc[j] * sv
                for c in range(3):
                    qv[i, j, c] = f * xv[i, j, c]
        e_sh = 0.0
        for i in range(h - 1):                                  # shear, per cell
            for j in range(w - 1):
                cc = 0.0
                for c in range(3):
                    cc += 0.25 * (xu[i + 1, j, c] + xu[i, j, c]) * (xv[i, j + 1, c] + xv[i, j, c])
                e_sh += cc * cc
                f = 0.25 * ksh[b] * cc
                for c in range(3):
                    tu = f * (xv[i, j + 1, c] + xv[i, j, c])
                    tv = f * (xu[i + 1, j, c] + xu[i, j, c])
                    qu[i, j, c] += tu
                    qu[i + 1, j, c] += tu
                    qv[i, j, c] += tv
                    qv[i, j + 1, c] += tv
        e_b = 0.0
        for i in range(h):                                      # bend: x_uu
            for j in range(w - 2):
                f = kb[b] * wr[i] * ic[j] * ibx * ibx
                for c in range(3):
                    t = xu[i, j + 1, c] - xu[i, j, c]
                    e_b += f * t * t
                    qu[i, j + 1, c] += f * t
                    qu[i, j, c] -= f * t
        for i in range(h - 1):                                  # bend: x_uv
            for j in range(w - 1):
                f = 2.0 * kb[b] * iby * iby
                for c in range(3):
                    t = xu[i + 1, j, c] - xu[i, j, c]
                    e_b += f * t * t
                    qu[i + 1, j, c] += f * t
                    qu[i, j, c] -= f * t
        for i in range(h - 2):                                  # bend: x_vv
            for j in range(w):
                f = kb[b] * wc[j] * ir[i] * iby * iby
                for c in range(3):
                    t = xv[i + 1, j, c] - xv[i, j, c]
                    e_b += f * t * t
                    qv[i + 1, j, c] += f * t
                    qv[i, j, c] -= f * t
        e_ext = 0.0
        for i in range(h):                      # divergence; gravity, damping, inertia
            for j in range(w):
                m = np.float64(mass[b, i, j])
                e_ext += grav * m * np.float64(x[b, i, j, 2])
                for c in range(3):
                    t = 0.0
                    if j > 0:
                        t += qu[i, j - 1, c] * ibx
                    if j < w - 1:
                        t -= qu[i, j, c] * ibx
                    if i > 0:
                        t += qv[i - 1, j, c] * iby
                    if i < h - 1:
                        t -= qv[i, j, c] * iby
                    ac = np.float64(a[b, i, j, c])
                    dx = np.float64(x[b, i, j, c]) - np.float64(x_prev[b, i, j, c])
                    e_ext += 0.5 * m * (damp[b] / dt * dx * dx + dt2 * ac * ac)
                    t = dt2 * t + m * (damp[b] * dt * dx + dt2 * ac)
                    if c == 2:
                        t += dt2 * grav * m
                    out[b, i, j, c] = t
        val[b] = 0.5 * (ks[b] * e_st + ksh[b] * e_sh + e_b) + e_ext


def loss_grad_fused(a: torch.Tensor, x_prev: torch.Tensor, v_prev: torch.Tensor, hx, hy,
                    material: dict, dt: float, mass: torch.Tensor, consts: tuple | None = None
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """``L_cloth(a)`` and ``dL/da`` in one fused numba pass (closed form, not differentiable).

    The terms and quadrature of :func:`draping.fnopt.cloth.energies` (stretch, shear, bend,
    gravity, damping when ``material`` has it, inertia) and their derivative, accumulated in
    float64: ``dL/da = dt^2 dE/dx + dt^2 M (a + g e_z) + c dt M (x - x_prev)``.

    Parameters
    ----------
    a, x_prev, v_prev : torch.Tensor
        ``(B, H, W, 3)`` accelerations (m/s^2, handles' included), positions (m), velocities
        (m/s), one floating dtype.
    hx, hy : float or torch.Tensor
        Spacings, m (floats or ``(B,)``).
    material : dict
        ``(B,)`` tensors or floats ``stretch``, ``shear``, ``bend`` (and ``damping``, 1/s).
    dt : float
        Time step, s.
    mass : torch.Tensor
        ``(B, H, W)`` lumped masses, kg.
    consts : tuple, optional
        :func:`kernel_constants` of ``hx``, ``hy``, ``material`` (built here when not given).

    Returns
    -------
    tuple
        ``(L (B,) in J, dL/da (B, H, W, 3) in J s^2/m)`` in ``a``'s dtype: equal to
        :func:`draping.fnopt.cloth.cloth_loss` and its autograd gradient up to rounding
        (float64 inputs: ~1e-14 relative).

    Raises
    ------
    ValueError
        If the states' shapes differ, ``mass`` is not ``(B, H, W)`` or the grid is smaller
        than 3 x 3.
    """
    if a.dim() != 4 or a.shape[-1] != 3:
        raise ValueError(f"a: expected shape (B, H, W, 3), got {tuple(a.shape)}")
    for name, t in (("x_prev", x_prev), ("v_prev", v_prev)):
        if t.shape != a.shape:
            raise ValueError(f"{name}: expected shape {tuple(a.shape)}, got {tuple(t.shape)}")
    b, h, w, _ = a.shape
    if mass.shape != a.shape[:3]:
        raise ValueError(f"mass: expected shape {tuple(a.shape[:3])}, got {tuple(mass.shape)}")
    if h < 3 or w < 3:
        raise ValueError(f"a: expected a grid of at least 3 x 3 vertices, got {h} x {w}")
    a = a.detach()
    x = positions_from_accel(a, x_prev.detach(), v_prev.detach(), dt)
    consts = kernel_constants(b, h, w, hx, hy, material) if consts is None else consts
    out = np.empty(a.shape, dtype=np.float64)
    val = np.empty(b, dtype=np.float64)
    _grad(a.contiguous().numpy(), x.contiguous().numpy(), x_prev.detach().contiguous().numpy(),
          mass.detach().contiguous().numpy(), *consts, float(dt), GRAVITY, out, val)
    return torch.from_numpy(val).to(a.dtype), torch.from_numpy(out).to(a.dtype)


@nb.njit(cache=True, fastmath=True)
def _gram(d, hd, g, a, r):
    n_b, n_dir, n = d.shape
    for b in range(n_b):
        for i in range(n_dir):
            s = 0.0
            for q in range(n):
                s += np.float64(g[b, q]) * np.float64(d[b, i, q])
            r[b, i] = -s
            for j in range(n_dir):
                s = 0.0
                for q in range(n):
                    s += np.float64(d[b, i, q]) * np.float64(hd[b, j, q])
                a[b, i, j] = s


def gram_fused(g: torch.Tensor, dirs: list, hd: list) -> tuple[torch.Tensor, torch.Tensor]:
    """``(D^T H D (B, k, k), -g^T D (B, k))`` in float64 from float32 or float64 fields.

    ``dirs``, ``hd``: ``k`` fields ``(B, H, W, 3)`` (directions and their Hessian products),
    ``g`` ``(B, H, W, 3)``. The products of :func:`draping.fnopt.solvers.subspace_solve`'s
    model, summed in float64 (another order than torch's: equal up to rounding). Not
    differentiable.
    """
    a, r = _gram_arrays(g, dirs, hd)
    return torch.from_numpy(a), torch.from_numpy(r)


def _gram_arrays(g: torch.Tensor, dirs: list, hd: list) -> tuple[np.ndarray, np.ndarray]:
    """:func:`gram_fused`'s ``(D^T H D, -g^T D)`` as float64 NumPy arrays."""
    b, k = g.shape[0], len(dirs)
    d = torch.stack(dirs, 1).detach().reshape(b, k, -1).numpy()
    h = torch.stack(hd, 1).detach().reshape(b, k, -1).numpy()
    a = np.empty((b, k, k))
    r = np.empty((b, k))
    _gram(d, h, g.detach().reshape(b, -1).contiguous().numpy(), a, r)
    return a, r


@nb.njit(cache=True)
def _shifted_solve(a, rhs, k, eps, c):
    """Minimiser ``c[:k]`` over the first ``k`` directions of one sheet's model; returns ``m``.

    :func:`draping.fnopt.solvers.subspace_solve`'s arithmetic on the ``k x k`` block of the
    symmetrised ``a``: Jacobi scaling (a zero direction gets weight 0), the shift
    ``mu = 2 max(0, -lambda_min) + eps``, one dense solve.
    """
    big = 1e-300
    for i in range(k):
        big = max(big, abs(a[i, i]))
    inv = np.zeros(k)
    for i in range(k):
        di = abs(a[i, i])
        if di > 1e-14 * big:
            inv[i] = 1.0 / np.sqrt(max(di, 1e-300))
    s = np.empty((k, k))
    for i in range(k):
        for j in range(k):
            s[i, j] = inv[i] * a[i, j] * inv[j]
    lam = np.linalg.eigvalsh(s)
    mu = 2 * max(-lam[0], 0.0) + eps
    for i in range(k):
        s[i, i] += mu
    y = np.linalg.solve(s, inv * rhs[:k])
    m = 0.0
    for i in range(k):
        c[i] = inv[i] * y[i]
        m -= rhs[i] * c[i]
    q = 0.0
    for i in range(k):
        t = 0.0
        for j in range(k):
            t += a[i, j] * c[j]
        q += c[i] * t
    return m + 0.5 * q


@nb.njit(cache=True)
def _coefficients(a, r, sub, eps, c, m, cs, ms):
    n_b, n_dir, _ = a.shape
    for b in range(n_b):
        ab = np.empty((n_dir, n_dir))
        for i in range(n_dir):
            for j in range(n_dir):
                ab[i, j] = 0.5 * (a[b, i, j] + a[b, j, i])
        m[b] = _shifted_solve(ab, r[b], n_dir, eps, c[b])
        if sub > 0:
            ms[b] = _shifted_solve(np.ascontiguousarray(ab[:sub, :sub]), r[b], sub, eps, cs[b])


def subspace_coefficients(g: torch.Tensor, dirs: list, hd: list, sub: int | None, eps: float):
    """:func:`draping.fnopt.solvers.subspace_solve` in one fused pass (not differentiable).

    The Gram matrix and right-hand side of :func:`gram_fused`, symmetrised, and the shifted
    Jacobi-scaled solves over all ``k`` directions and (``sub``) the first ``sub`` ones, per
    sheet in one numba call: the same float64 arithmetic as the torch path up to the order of
    sums, without a dozen NumPy or torch operations per solve on ``k x k`` arrays.

    Returns
    -------
    tuple
        ``(c (B, k), m (B,))`` float64; with ``sub``, ``((c, m), (c_sub (B, k), m_sub))``,
        ``c_sub`` zero beyond its first ``sub`` entries.
    """
    b, k = g.shape[0], len(dirs)
    a, r = _gram_arrays(g, dirs, hd)
    c, m = np.zeros((b, k)), np.empty(b)
    cs, ms = np.zeros((b, k)), np.empty(b)
    _coefficients(a, r, 0 if sub is None else int(sub), float(eps), c, m, cs, ms)
    full = (torch.from_numpy(c), torch.from_numpy(m))
    return full if sub is None else (full, (torch.from_numpy(cs), torch.from_numpy(ms)))
