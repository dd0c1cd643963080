"""One backward-Euler time step as an optimisation problem, classical inner optimisers, rollouts.

Every optimiser works in the mass metric: the variable is the acceleration ``a`` (m/s^2) and
the *residual* ``r = M^-1 dL/da / dt^2`` (m/s^2, ``a - f / m`` when only inertia and forces
act) is what the learned optimiser sees and what the tolerances are stated in. That metric makes
step sizes resolution-independent: GD with ``lr = 1`` is exact for the inertia term alone at any
grid size.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from . import cloth
from .handles import DT, trajectory

__all__ = ["StepProblem", "make_problem", "laplace_preconditioner", "normal_preconditioner",
           "low_modes", "normal_directions", "solve_pgd", "solve_pcg",
           "subspace_solve", "solve_gd", "solve_adam", "solve_lbfgs", "solve_lbfgs_wolfe",
           "solve_reference",
           "Rollout", "rollout", "CLASSICAL", "REFERENCE_TOL"]

#: Tolerance of the converged reference: RMS residual ``M^-1 dL/da / dt^2`` over the free
#: vertices, m/s^2 (5e-6 g). Set by a convergence study (``bm_fnopt.py --part reference``):
#: rollouts solved to 5e-2 and 5e-3 differ by up to 16 cm on the mid-edges layout (the fold
#: that the loose solves pick is not the converged one), 5e-4 and 5e-5 by 6 mm, 5e-5 and 5e-6
#: by 0.4 mm (32x32, 60 frames); the reference is solved in float64 with float64 states.
REFERENCE_TOL = 5e-5


@dataclass
class StepProblem:
    """``L_cloth(a)`` of one time step for a batch of sheets; handles fixed.

    Attributes
    ----------
    x_prev, v_prev : torch.Tensor
        State ``(B, H, W, 3)`` (m, m/s).
    hx, hy : torch.Tensor
        Spacings ``(B,)``, m.
    material : dict
        ``(B,)`` tensors stretch, shear, bend, density, damping (see :class:`cloth.Material`).
    dt : float
        Time step, s.
    free : torch.Tensor
        ``(B or 1, H, W, 1)`` 1 at free vertices, 0 at handles.
    a_fixed : torch.Tensor
        ``(B, H, W, 3)`` handle accelerations (0 at free vertices).
    mass : torch.Tensor
        Lumped masses ``(B, H, W)``, kg.
    extra : callable, optional
        ``x -> (B,)`` extra energy (J), e.g. repulsion.
    batched_hvp : bool
        :meth:`hessian_products` in one batched pass (default) or one product at a time.
    analytic_hvp : bool
        :meth:`grad_hvp`'s products in closed form (:func:`cloth.loss_hvp`; default, used when
        there is no ``extra`` energy and :meth:`loss` is ``L_cloth``'s, not a subclass's)
        instead of autograd's double-backward pass (equal up to rounding; training keeps the
        latter, so that it reproduces the shipped weights bit for bit).
    fused : bool
        Without gradients (inference), the closed-form products and the subspace step's Gram
        matrix come from the fused numba kernels of :mod:`draping.fnopt.kernels` (default;
        equal to the torch functions up to float rounding, 2.5-3x faster products at 64x64 and
        100x100), and so do :meth:`grad_hvp`'s loss and gradient where its products are in
        closed form (``analytic_hvp``; the gradient is detached either way); ``False``: the
        torch functions and autograd.
    """

    x_prev: torch.Tensor
    v_prev: torch.Tensor
    hx: torch.Tensor
    hy: torch.Tensor
    material: dict
    dt: float
    free: torch.Tensor
    a_fixed: torch.Tensor
    mass: torch.Tensor
    extra: Callable | None = None
    evals: int = field(default=0)
    batched_hvp: bool = True
    analytic_hvp: bool = True
    fused: bool = True

    @property
    def free3(self) -> torch.Tensor:
        """``free`` expanded to ``(B or 1, H, W, 3)``, contiguous, cached.

        Rebuilt when ``free`` is replaced or changed in place. The same products as with
        ``free``, but a product with a size-1 coordinate axis broadcast is 5-6x slower in torch
        than one broadcast over the batch only (a ``(5, 1, 64, 64, 3)`` field: 0.056 against
        0.009 ms).
        """
        key = (id(self.free), self.free._version)
        cache = self.__dict__.get("_free3")
        if cache is None or cache[0] != key:
            f = self.free
            cache = (key, f.expand(*f.shape[:-1], 3).contiguous(), f)
            self.__dict__["_free3"] = cache
        return cache[1]

    def compose(self, a: torch.Tensor) -> torch.Tensor:
        """Accelerations with the handles' ones in place."""
        return a * self.free3 + self.a_fixed

    def loss(self, a: torch.Tensor) -> torch.Tensor:
        """``L_cloth`` ``(B,)`` in J of (free) accelerations ``a``."""
        a = self.compose(a)
        out = cloth.cloth_loss(a, self.x_prev, self.v_prev, self.hx, self.hy, self.material,
                               self.dt, self.mass)
        if self.extra is not None:
            out = out + self.extra(cloth.positions_from_accel(a, self.x_prev, self.v_prev,
                                                              self.dt))
        return out

    def loss_grad(self, a: torch.Tensor, fused: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """``(L (B,), dL/da (B, H, W, 3))``, zero gradient at handles; both detached.

        ``fused``: from :func:`draping.fnopt.kernels.loss_grad_fused` (closed form, float64
        accumulation: autograd's values up to rounding) where it applies -- ``L_cloth``
        itself (no ``extra`` energy, :meth:`loss` not overridden), a grid of at least 3 x 3,
        the problem's ``fused`` flag on -- else (and by default) autograd.
        """
        if fused and self._fusable():
            return self._fused_loss_grad(self.compose(a.detach()))
        self.evals += 1
        with torch.enable_grad():
            a = a.detach().requires_grad_(True)
            val = self.loss(a)
            (g,) = torch.autograd.grad(val.sum(), a)
        return val.detach(), g * self.free3

    def grad_hvp(self, a: torch.Tensor):
        """``(L, g, hvp)`` at ``a``: loss ``(B,)``, gradient and ``d -> H d``.

        ``H d``: the Hessian of ``L_cloth`` times a direction (a double-backward pass per call,
        or in closed form with ``analytic_hvp``); ``hvp.many(ds)``: ``(k, B, H, W, 3)``, the
        products with ``k`` directions in one batched pass.
        """
        if self.analytic_hvp and self.extra is None and type(self).loss is StepProblem.loss:
            return self._grad_hvp_analytic(a)         # L_cloth itself: its closed form
        self.evals += 1
        with torch.enable_grad():
            a = a.detach().requires_grad_(True)
            val = self.loss(a)
            (g,) = torch.autograd.grad(val.sum(), a, create_graph=True)
        free = self.free

        def hvp(d: torch.Tensor, create_graph: bool = False) -> torch.Tensor:
            with torch.enable_grad():
                (hd,) = torch.autograd.grad(g, a, grad_outputs=d * free, retain_graph=True,
                                            create_graph=create_graph)
            return hd * free

        def many(ds: list) -> torch.Tensor:
            """``(k, B, H, W, 3)``: the products with ``k`` directions in one batched pass."""
            with torch.enable_grad():
                (hd,) = torch.autograd.grad(g, a, grad_outputs=torch.stack(ds) * free,
                                            retain_graph=True, is_grads_batched=True)
            return hd * free

        hvp.many = many
        return val.detach(), g.detach() * free, hvp

    def _fusable(self) -> bool:
        """The fused kernels apply: ``fused`` on, ``L_cloth`` itself, a grid >= 3 x 3."""
        return (self.fused and self.extra is None and type(self).loss is StepProblem.loss
                and min(self.x_prev.shape[1:3]) >= 3)

    def _fused_loss_grad(self, ac: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`loss_grad` by the fused kernel at composed accelerations ``ac``."""
        from .kernels import loss_grad_fused
        self.evals += 1
        val, g = loss_grad_fused(ac, self.x_prev, self.v_prev, self.hx, self.hy, self.material,
                                 self.dt, self.mass, self._kernel_constants())
        return val, g * self.free3

    def _kernel_constants(self) -> tuple:
        """:func:`draping.fnopt.kernels.kernel_constants` of this problem, built once.

        Rebuilt if ``hx``, ``hy`` or a material tensor is replaced or changed in place.
        """
        ts = (self.hx, self.hy, *self.material.values())
        key = tuple((id(t), getattr(t, "_version", None)) for t in ts) + (self.x_prev.shape,)
        cache = self.__dict__.get("_kconsts")
        if cache is None or cache[0] != key:
            from .kernels import kernel_constants
            b, h, w, _ = self.x_prev.shape
            cache = (key, kernel_constants(b, h, w, self.hx, self.hy, self.material), ts)
            self.__dict__["_kconsts"] = cache
        return cache[1]

    def _grad_hvp_analytic(self, a: torch.Tensor):
        """:meth:`grad_hvp` with the products of :func:`cloth.loss_hvp` (no kept graph).

        With ``fused`` (and a grid of at least 3 x 3), the loss and gradient too come from a
        fused kernel (:func:`draping.fnopt.kernels.loss_grad_fused`) instead of autograd.
        """
        ac = self.compose(a.detach())
        free = self.free3
        val, g = self._fused_loss_grad(ac) if self._fusable() else self.loss_grad(a)

        def many(ds: list) -> torch.Tensor:
            d = torch.stack(ds) if isinstance(ds, (list, tuple)) else ds
            fn = cloth.loss_hvp
            if self.fused and min(ac.shape[1:3]) >= 3 and not (
                    torch.is_grad_enabled() and d.requires_grad):
                from .kernels import loss_hvp_fused as fn
                return fn(d * free, ac, self.x_prev, self.v_prev, self.hx, self.hy,
                          self.material, self.dt, self.mass, self._kernel_constants()) * free
            return fn(d * free, ac, self.x_prev, self.v_prev, self.hx, self.hy,
                      self.material, self.dt, self.mass) * free

        def hvp(d: torch.Tensor, create_graph: bool = False) -> torch.Tensor:
            return many(d)          # linear in d: differentiable in d either way

        hvp.many = many
        return val, g, hvp

    def exact_step(self, g: torch.Tensor, d: torch.Tensor, hvp) -> torch.Tensor:
        """Minimiser ``(B, 1, 1, 1)`` of the quadratic model of ``L(a + t d)`` (``t >= 0``).

        Falls back to the inertia-only step when the curvature along ``d`` is not positive.
        """
        hd = hvp(d)
        gd = (g * d).sum((1, 2, 3))
        dhd = (d * hd).sum((1, 2, 3))
        dmd = ((self.mass[..., None] * self.dt * self.dt) * d * d * self.free).sum((1, 2, 3))
        curv = torch.where(dhd > 0, dhd, dmd).clamp(min=1e-30)
        return (-gd / curv).clamp(min=0.0)[:, None, None, None]

    def subspace_step(self, g: torch.Tensor, dirs: list, hvp) -> torch.Tensor:
        """Minimiser of the quadratic model of ``L`` over the span of ``dirs``.

        ``dirs``: ``k`` directions ``(B, H, W, 3)``; returns the step ``sum_i c_i d_i`` with the
        coefficients of :func:`subspace_solve` (a zero or repeated direction is harmless and
        the step never increases the quadratic model). With the single direction ``d`` this
        is :meth:`exact_step` (when the curvature along ``d`` is positive).
        """
        hd = self.hessian_products(dirs, hvp)
        c, _ = subspace_solve(g, dirs, hd, fused=self.fused)
        return torch.einsum("bi,ibhwc->bhwc", c.to(g.dtype), torch.stack(dirs))

    def hessian_products(self, dirs: list, hvp) -> list:
        """``[H d for d in dirs]``, in one batched double-backward pass when available."""
        many = getattr(hvp, "many", None) if self.batched_hvp else None
        if many is not None:
            return list(many(dirs).unbind(0))
        return [hvp(di) for di in dirs]

    def precondition(self, g: torch.Tensor) -> torch.Tensor:
        """The residual ``M^-1 g / dt^2`` (m/s^2)."""
        return g / (self.mass[..., None] * self.dt * self.dt)

    def residual_rms(self, r: torch.Tensor) -> torch.Tensor:
        """RMS ``(B,)`` over the free vertices' residual components."""
        n = (self.free.expand(r.shape[:-1] + (1,)).sum((1, 2, 3)) * 3).clamp(min=1)
        return ((r * self.free3).square().sum((1, 2, 3)) / n).sqrt()


def subspace_solve(g: torch.Tensor, dirs: list, hd: list, sub: int | None = None,
                   fused: bool = False):
    """Coefficients ``c`` ``(B, k)`` minimising the quadratic model over a span, and its value.

    The model is ``m(c) = g . D c + 1/2 c^T (D^T H D) c`` with ``D = [d_1 .. d_k]`` and
    ``hd[i] = H d_i``; it is solved in float64 after scaling each direction to unit curvature
    (Jacobi), with the shift ``mu = 2 max(0, -lambda_min) + eps`` (``eps`` 1e-5 for float32
    inputs, 1e-12 for float64: the rounding level of their Hessian products): with a positive
    definite model this is its exact minimiser over the span (up to ``eps``), with negative
    curvature a regularised step; in both cases ``m(c) <= 0``, so the step never increases the
    model, and a zero or repeated direction gets no weight of its own. Differentiable (the
    FNO is trained through it). ``sub``: also solve over the first ``sub`` directions alone.
    ``fused``: where no gradient is needed, the whole solve in one numba pass
    (:func:`draping.fnopt.kernels.subspace_coefficients`: the same float64 arithmetic, sums in
    another order).

    Returns
    -------
    c : torch.Tensor
        ``(B, k)`` float64 coefficients (``(B, sub)`` ones zero-padded when ``sub`` is given,
        as a second pair).
    m : torch.Tensor
        ``(B,)`` float64 model value ``m(c)`` (J); with ``sub``, ``((c, m), (c_sub, m_sub))``.
    """
    fused = fused and not (torch.is_grad_enabled()
                           and any(t.requires_grad for t in [g, *dirs, *hd]))
    eps = 1e-12 if g.dtype == torch.float64 else 1e-5
    if fused:
        from .kernels import subspace_coefficients

        return subspace_coefficients(g, dirs, hd, sub, eps)
    d = torch.stack(dirs, 1).double()                           # (B, k, H, W, 3)
    a = torch.einsum("bihwc,bjhwc->bij", d, torch.stack(hd, 1).double())
    rhs = -torch.einsum("bhwc,bihwc->bi", g.double(), d)
    a = 0.5 * (a + a.transpose(1, 2))

    def solve(a, rhs):
        diag = torch.diagonal(a, dim1=1, dim2=2).abs()
        big = diag.amax(1, keepdim=True).clamp(min=1e-300)
        inv = torch.where(diag > 1e-14 * big, diag.clamp(min=1e-300).rsqrt(),
                          torch.zeros_like(diag))               # zero direction: weight 0
        s = inv[:, :, None] * a * inv[:, None, :]
        lam = torch.linalg.eigvalsh(s.detach())
        mu = 2 * (-lam[:, :1]).clamp(min=0) + eps
        eye = torch.eye(s.shape[1], dtype=s.dtype)
        y = torch.linalg.solve(s + mu[:, :, None] * eye, (inv * rhs)[..., None])[..., 0]
        c = inv * y
        m = -(rhs * c).sum(1) + 0.5 * torch.einsum("bi,bij,bj->b", c, a, c)
        return c, m

    full = solve(a, rhs)
    if sub is None:
        return full
    cs, ms = solve(a[:, :sub, :sub], rhs[:, :sub])
    return full, (torch.cat([cs, torch.zeros_like(full[0][:, sub:])], 1), ms)


def make_problem(x_prev, v_prev, idx, target, hx, hy, material: dict, dt: float = DT,
                 extra=None) -> StepProblem:
    """Build the step problem of states ``(B, H, W, 3)`` with handles ``idx`` on ``target``.

    ``idx``: ``(K, 2)`` grid indices; ``target``: ``(B, K, 3)`` handle positions at the end of
    the step (m). ``hx``, ``hy``: floats or ``(B,)``.

    Raises
    ------
    ValueError
        On non-grid or non-finite states, or handles out of range.
    """
    b, h, w = cloth.check_grid(x_prev, "x_prev")
    cloth.check_grid(v_prev, "v_prev")
    if v_prev.shape != x_prev.shape:
        raise ValueError(f"v_prev: expected shape {tuple(x_prev.shape)}, got "
                         f"{tuple(v_prev.shape)}")
    idx = cloth.handle_indices(idx, h, w) if isinstance(idx, torch.Tensor) else \
        cloth.handle_indices(idx, h, w)
    dtype = x_prev.dtype
    target = torch.as_tensor(target, dtype=dtype).reshape(b, idx.shape[0], 3)
    if not bool(torch.isfinite(target).all()):
        raise ValueError("target: contains NaN or inf")
    hx = torch.as_tensor(hx, dtype=dtype).reshape(-1).expand(b)
    hy = torch.as_tensor(hy, dtype=dtype).reshape(-1).expand(b)
    mat = {k: torch.as_tensor(v, dtype=dtype).reshape(-1).expand(b) for k, v in material.items()}
    mass = cloth.vertex_mass(h, w, hx, hy, mat["density"], dtype)
    free = (1.0 - cloth.handle_mask(idx, h, w, dtype))[None, :, :, None]
    a_fixed = torch.zeros_like(x_prev)
    a_fixed[:, idx[:, 0], idx[:, 1]] = cloth.handle_accel(x_prev, v_prev, idx, target, dt)
    return StepProblem(x_prev, v_prev, hx, hy, mat, dt, free, a_fixed, mass, extra)


def solve_gd(p: StepProblem, iters: int, lr: float = 0.5, a0=None,
             fused_grad: bool = False) -> torch.Tensor:
    """Gradient descent in the mass metric: ``a -= lr * r`` (``lr`` dimensionless).

    ``fused_grad``: gradients by the fused kernel (:meth:`StepProblem.loss_grad`'s ``fused``).
    """
    a = torch.zeros_like(p.x_prev) if a0 is None else a0.clone()
    for _ in range(iters):
        _, g = p.loss_grad(a, fused=fused_grad)
        a = a - lr * p.precondition(g)
    return p.compose(a)


def solve_pgd(p: StepProblem, iters: int, k_eff: float = 1.0, a0=None) -> torch.Tensor:
    """Steepest descent in the metric of :func:`laplace_preconditioner`, exact quadratic step."""
    pre = laplace_preconditioner(p, k_eff)
    a = torch.zeros_like(p.x_prev) if a0 is None else a0.clone()
    for _ in range(iters):
        _, g, hvp = p.grad_hvp(a)
        d = -pre(g) * p.free3
        a = a + p.exact_step(g, d, hvp) * d
    return p.compose(a)


def solve_pcg(p: StepProblem, iters: int, k_eff: float = 1.0, a0=None,
              normal: bool = False, split: int = 0) -> torch.Tensor:
    """Preconditioned descent with memory (FNOpt's subspace step without the FNO).

    Each update minimises the quadratic model of ``L``
    over the span of the preconditioned gradient and the previous update (a nonlinear
    conjugate-gradient method with exact two-dimensional steps, DCT metric of
    :func:`laplace_preconditioner`). ``normal``: the span also holds the out-of-plane direction
    of :func:`normal_preconditioner` (three-dimensional steps; ``split``: that direction cut
    into its low and high DCT modes, :func:`normal_directions`).
    """
    pre = laplace_preconditioner(p, k_eff)
    pn = normal_preconditioner(p) if normal else None
    a = torch.zeros_like(p.x_prev) if a0 is None else a0.clone()
    da = torch.zeros_like(a)
    for _ in range(iters):
        _, g, hvp = p.grad_hvp(a)
        dirs = [-pre(g) * p.free3, da] + (normal_directions(p, g, pn, split) if normal else [])
        da = p.subspace_step(g, dirs, hvp)
        a = a + da
    return p.compose(a)


def solve_adam(p: StepProblem, iters: int, lr: float = 1.0, betas=(0.9, 0.999),
               eps: float = 1e-8, a0=None, fused_grad: bool = False) -> torch.Tensor:
    """Adam on the residual ``r`` (``lr`` in m/s^2 per iteration).

    ``fused_grad``: gradients by the fused kernel (:meth:`StepProblem.loss_grad`'s ``fused``).
    """
    a = torch.zeros_like(p.x_prev) if a0 is None else a0.clone()
    m = torch.zeros_like(a)
    v = torch.zeros_like(a)
    for k in range(1, iters + 1):
        _, g = p.loss_grad(a, fused=fused_grad)
        r = p.precondition(g)
        m = betas[0] * m + (1 - betas[0]) * r
        v = betas[1] * v + (1 - betas[1]) * r * r
        mh = m / (1 - betas[0] ** k)
        vh = v / (1 - betas[1] ** k)
        a = a - lr * mh / (vh.sqrt() + eps)
    return p.compose(a)


def laplace_preconditioner(p: StepProblem, k_eff: float = 1.0):
    """``g -> H0^-1 g``, a linear model of the step's Hessian inverted by DCT.

    ``H0 = m dt^2 + dt^4 (k_eff k_s L + 1e-3 k_b h^2 L^2)`` with ``L`` the Neumann grid
    Laplacian (``O(HW log HW)``): the inertia, the in-plane stiffness of a sheet at rest and
    the plate bending stiffness, per coordinate. A fixed, resolution-aware metric; the
    classical optimisers and the FNO use it through :func:`solve_pgd` and
    :func:`draping.fnopt.model.fno_update`.
    """
    den = _dct_metric(p, k_eff * p.material["stretch"].double().numpy())

    def apply(g: torch.Tensor) -> torch.Tensor:
        z = _dct_solve(g.detach().double().numpy(), den)
        return torch.from_numpy(z).to(g.dtype)

    return apply


def _dct_metric(p: StepProblem, ks) -> np.ndarray:
    """``(B, H, W)``: ``m dt^2 + dt^4 (ks L + 1e-3 k_b h^2 L^2)`` on the DCT-II modes.

    ``L`` the Neumann grid Laplacian's eigenvalues (1/m^2), ``ks (B,)`` the stiffness charged
    to the Laplacian term (N/m; 0: inertia and bending only), per sheet.
    """
    _, h, w, _ = p.x_prev.shape
    hx = p.hx.double().numpy()[:, None, None]
    hy = p.hy.double().numpy()[:, None, None]
    rho = p.material["density"].double().numpy()[:, None, None]
    ks = np.broadcast_to(np.asarray(ks, dtype=np.float64), hx.shape[:1])[:, None, None]
    kb = 1e-3 * p.material["bend"].double().numpy()[:, None, None]
    lam_r = (2 - 2 * np.cos(np.pi * np.arange(h) / h))[None, :, None]
    lam_c = (2 - 2 * np.cos(np.pi * np.arange(w) / w))[None, None, :]
    dt2 = p.dt * p.dt
    lap = lam_r / (hy * hy) + lam_c / (hx * hx)          # 1/m^2
    return rho * hx * hy * dt2 + dt2 * dt2 * hx * hy * (ks * lap + kb * lap * lap)


def _dct_solve(z: np.ndarray, den: np.ndarray) -> np.ndarray:
    """``idct(dct(z) / den)`` over the grid axes 1, 2 (orthonormal DCT-II), float64.

    ``z`` ``(B, H, W)`` or ``(B, H, W, C)``, ``den`` ``(B, H, W)``. The transforms as products
    with the cached ``H x H`` and ``W x W`` DCT-II matrices (:func:`_dct_matrix`): the FFT-based
    ``scipy.fft.dctn`` / ``idctn`` result up to float64 rounding, 2x / 1.5x faster on one
    sheet at 32x32 / 64x64 (the FFTs' per-call set-up dominated there).
    """
    ah, aw = _dct_matrix(z.shape[1]), _dct_matrix(z.shape[2])
    if z.ndim == 3:
        return ah.T @ ((ah @ z @ aw.T) / den) @ aw
    zc = np.moveaxis(z, 3, 1)                                     # (B, C, H, W) view
    out = ah.T @ ((ah @ zc @ aw.T) / den[:, None]) @ aw
    return np.ascontiguousarray(np.moveaxis(out, 1, 3))


_DCT_MATRIX: dict = {}


def _dct_matrix(n: int) -> np.ndarray:
    """The orthonormal DCT-II matrix ``(n, n)`` (float64, cached; rows: frequencies)."""
    if n not in _DCT_MATRIX:
        _DCT_MATRIX[n] = _dct_rows(n, n).numpy()
    return _DCT_MATRIX[n]


def normal_preconditioner(p: StepProblem):
    """``g -> n (D_n^-1 (n . g))``: the out-of-plane part of ``g`` in an inextensible metric.

    ``n``: unit normals ``(B, H, W, 3)`` of the predicted positions ``x_prev + dt v_prev``
    (central differences, one-sided at the border); ``D_n = m dt^2 + dt^4 1e-3 k_b h^2 L^2``
    (inertia and plate bending, no stretch; ``L`` the Neumann grid Laplacian, inverted by DCT).

    Why: :func:`laplace_preconditioner` charges every coordinate the in-plane stretch stiffness
    ``k_s``, but a sheet moves out of its plane at the cost of bending and its small tension
    only, so for the out-of-plane modes of wavelength 1/3 .. 1/8 of the sheet it is ~100x too
    stiff and 10 conjugate-gradient steps leave about half of a folding step undone (measured
    on the diagonal layout at 64x64: the step error is 84-93 % out-of-plane, 84-96 % in the
    8 x 8 lowest DCT modes, < 6 % a rotation about the handles' axis). Added as one more
    direction of the subspace step, the step's own quadratic model weighs it.
    """
    y = (p.x_prev + p.dt * p.v_prev).detach().double()
    xu = torch.cat([y[:, :, 1:2] - y[:, :, :1], y[:, :, 2:] - y[:, :, :-2],
                    y[:, :, -1:] - y[:, :, -2:-1]], 2)
    xv = torch.cat([y[:, 1:2] - y[:, :1], y[:, 2:] - y[:, :-2], y[:, -1:] - y[:, -2:-1]], 1)
    n = torch.cross(xu, xv, dim=-1)
    n = n / n.norm(dim=-1, keepdim=True).clamp(min=1e-300)
    den = _dct_metric(p, 0.0)

    def apply(g: torch.Tensor) -> torch.Tensor:
        z = _dct_solve((g.detach().double() * n).sum(-1).numpy(), den)
        return (n * torch.from_numpy(z)[..., None]).to(g.dtype)

    return apply


def low_modes(z: torch.Tensor, cut: int) -> torch.Tensor:
    """The part of a field ``(B, H, W, C)`` in its lowest ``cut x cut`` DCT-II modes.

    ``A_H^T A_H z A_W^T A_W`` with ``A_n`` the first ``cut`` rows of the orthonormal DCT-II
    matrix (cached per size; float64): the full transforms' result up to rounding, without
    transforming the ``n - cut`` modes that are dropped.
    """
    _, h, w, _ = z.shape
    ah, aw = _dct_rows(h, cut), _dct_rows(w, cut)
    zc = z.detach().double().permute(0, 3, 1, 2)                 # (B, C, H, W)
    low = ah.T @ ((ah @ zc) @ aw.T) @ aw
    return low.permute(0, 2, 3, 1).to(z.dtype).contiguous()


_DCT_ROWS: dict = {}


def _dct_rows(n: int, cut: int) -> torch.Tensor:
    """The first ``min(cut, n)`` rows ``(cut, n)`` of the orthonormal DCT-II matrix, float64."""
    k = min(cut, n)
    if (n, k) not in _DCT_ROWS:
        i = torch.arange(k, dtype=torch.float64)[:, None]
        j = torch.arange(n, dtype=torch.float64)[None]
        a = torch.cos(math.pi * i * (2 * j + 1) / (2 * n)) * math.sqrt(2.0 / n)
        a[0] /= math.sqrt(2.0)
        _DCT_ROWS[(n, k)] = a
    return _DCT_ROWS[(n, k)]


def normal_directions(p: StepProblem, g: torch.Tensor, pn, split: int = 0) -> list:
    """Descent directions from the out-of-plane preconditioned gradient ``pn(g)``.

    ``split = 0``: ``[-pn(g)]``; ``split > 0``: its lowest ``split x split`` DCT modes and
    the rest as two directions (a coarse-level part the subspace step scales on its own).
    """
    zn = pn(g)
    if split <= 0:
        return [-zn * p.free3]
    lo = low_modes(zn, split)
    return [-lo * p.free3, -(zn - lo) * p.free3]


def _two_loop(g, s_hist, y_hist, h0=None):
    q = g.clone()
    alphas = []
    for s, y in zip(reversed(s_hist), reversed(y_hist)):
        rho = 1.0 / (y * s).sum((1, 2, 3), keepdim=True).clamp(min=1e-30)
        al = rho * (s * q).sum((1, 2, 3), keepdim=True)
        q = q - al * y
        alphas.append((rho, al))
    if h0 is not None:
        q = h0(q)
    elif s_hist:
        s, y = s_hist[-1], y_hist[-1]
        gamma = (s * y).sum((1, 2, 3), keepdim=True) / (y * y).sum(
            (1, 2, 3), keepdim=True).clamp(min=1e-30)
        q = q * gamma
    for (s, y), (rho, al) in zip(zip(s_hist, y_hist), reversed(alphas)):
        be = rho * (y * q).sum((1, 2, 3), keepdim=True)
        q = q + s * (al - be)
    return q


def solve_lbfgs(p: StepProblem, iters: int, history: int = 5, step: float = 1.0,
                a0=None, line_search: bool = False, tol: float = 0.0,
                info: dict | None = None, precondition: float = 0.0,
                fused_grad: bool = False) -> torch.Tensor:
    """L-BFGS (two-loop recursion) in the mass-scaled variable ``b = sqrt(m) dt a``.

    ``line_search=False`` (the thesis' baseline): fixed ``step``, no line search.
    ``line_search=True``: Armijo backtracking, per sheet. Stops early when the RMS residual of
    every sheet is <= ``tol`` (m/s^2). ``info`` receives ``iterations`` and ``residual``.
    ``precondition > 0``: the initial inverse Hessian is the grid-Laplacian model of the
    stretch stiffness (``precondition`` times ``k_s``), solved by DCT, instead of a scaled
    identity. ``fused_grad``: energies and gradients by the fused kernel
    (:meth:`StepProblem.loss_grad`'s ``fused``; autograd's values up to rounding, 2.7x
    cheaper L-BFGS iterations at 64x64), the like-for-like baseline of FNOpt, whose
    inference uses it too.
    """
    sq = (p.mass[..., None].sqrt() * p.dt)              # b = sq * a
    h0 = None
    if precondition > 0:
        pa = laplace_preconditioner(p, precondition)

        def h0(qb):
            return sq * pa(sq * qb) * p.free3
    a = torch.zeros_like(p.x_prev) if a0 is None else (a0 * p.free3).clone()
    val, g = p.loss_grad(a, fused=fused_grad)
    gb = g / sq * p.free3
    s_hist, y_hist = [], []
    it = 0
    res = p.residual_rms(p.precondition(g))
    for it in range(1, iters + 1):
        if tol > 0 and bool((res <= tol).all()):
            it -= 1
            break
        d = -_two_loop(gb, s_hist, y_hist, h0) * p.free3
        t = torch.full((a.shape[0], 1, 1, 1), step, dtype=a.dtype)
        if line_search:
            slope = (gb * d).sum((1, 2, 3))
            bad = slope >= 0                           # not a descent direction: restart
            if bool(bad.any()):
                d = torch.where(bad[:, None, None, None], -gb, d)
                slope = (gb * d).sum((1, 2, 3))
                s_hist, y_hist = [], []
            for _ in range(30):
                new_val = p.loss(a + t * d / sq)
                # Armijo, with room for rounding once the decrease is below float precision
                ok = new_val <= val + 1e-4 * t[:, 0, 0, 0] * slope + 1e-13 * val.abs()
                if bool(ok.all()):
                    break
                t = torch.where(ok[:, None, None, None], t, 0.5 * t)
        a_new = a + t * d / sq
        val_new, g_new = p.loss_grad(a_new, fused=fused_grad)
        gb_new = g_new / sq * p.free3
        s, y = (a_new - a) * sq, gb_new - gb
        if bool(((s * y).sum((1, 2, 3)) > 1e-30).all()):
            s_hist.append(s)
            y_hist.append(y)
            if len(s_hist) > history:
                s_hist.pop(0)
                y_hist.pop(0)
        a, val, gb, g = a_new, val_new, gb_new, g_new
        res = p.residual_rms(p.precondition(g))
    if info is not None:
        info["iterations"] = it
        info["residual"] = res
    return p.compose(a)


def _as_float64(p: StepProblem) -> StepProblem:
    return StepProblem(p.x_prev.double(), p.v_prev.double(), p.hx.double(), p.hy.double(),
                       {k: v.double() for k, v in p.material.items()}, p.dt, p.free.double(),
                       p.a_fixed.double(), p.mass.double(), p.extra,
                       batched_hvp=p.batched_hvp, analytic_hvp=p.analytic_hvp, fused=p.fused)


def solve_lbfgs_wolfe(p: StepProblem, iters: int, history: int = 10, a0=None,
                      max_eval: int | None = None, info: dict | None = None,
                      float64: bool = False) -> torch.Tensor:
    """L-BFGS with a strong-Wolfe line search (``torch.optim.LBFGS``), the fair baseline.

    PyTorch's own implementation (two-loop recursion, cubic-interpolation strong-Wolfe line
    search, initial Hessian scaled by ``s^T y / y^T y``) run on the mass-scaled variable
    ``b = sqrt(m) dt a`` (the same diagonal scaling as :func:`solve_lbfgs`; the identity is then
    the inertia term's Hessian). ``iters``: L-BFGS iterations; ``max_eval``: gradient
    evaluations allowed in all (default ``2 * iters``, the line search's extra ones included);
    ``info`` receives ``evaluations`` and ``residual`` (RMS, m/s^2). ``float64``: solve in
    float64 (in float32 the line search stops once the decrease is below the loss' rounding).
    """
    if float64 and p.x_prev.dtype != torch.float64:
        p64 = _as_float64(p)
        a0 = None if a0 is None else a0.double()
        out = solve_lbfgs_wolfe(p64, iters, history, a0, max_eval, info)
        p.evals += p64.evals
        return out.to(p.x_prev.dtype)
    sq = p.mass[..., None].sqrt() * p.dt
    a = torch.zeros_like(p.x_prev) if a0 is None else (a0 * p.free3).clone()
    b = (a * sq).detach().clone().requires_grad_(True)
    opt = torch.optim.LBFGS([b], lr=1.0, max_iter=iters, max_eval=max_eval or 2 * iters,
                            tolerance_grad=0.0, tolerance_change=0.0, history_size=history,
                            line_search_fn="strong_wolfe")
    evals0 = p.evals

    def closure():
        val, g = p.loss_grad(b.detach() / sq)
        b.grad = g / sq * p.free3
        return val.sum()

    opt.step(closure)
    a = b.detach() / sq
    if info is not None:
        info["evaluations"] = p.evals - evals0
        info["residual"] = p.residual_rms(p.precondition(p.loss_grad(a)[1]))
    return p.compose(a)


def solve_reference(p: StepProblem, a0=None, tol: float = REFERENCE_TOL,
                    max_iter: int = 5000, info: dict | None = None,
                    precondition: float = 0.5) -> torch.Tensor:
    """The converged reference: L-BFGS (history 20) with Armijo line search in float64.

    Stopping rule: the RMS residual ``M^-1 dL/da / dt^2`` over the free vertices of every sheet
    is <= ``tol`` m/s^2 (default :data:`REFERENCE_TOL`). A solve that reaches ``max_iter``
    iterations first warns (``info["residual"]`` says by how much it missed).
    """
    dtype = p.x_prev.dtype
    info = {} if info is None else info
    if dtype != torch.float64:
        p64 = _as_float64(p)
        a0 = None if a0 is None else a0.double()
        out = solve_lbfgs(p64, max_iter, history=20, a0=a0, line_search=True, tol=tol,
                          info=info, precondition=precondition).to(dtype)
        p.evals += p64.evals
    else:
        out = solve_lbfgs(p, max_iter, history=20, a0=a0, line_search=True, tol=tol,
                          info=info, precondition=precondition)
    worst = float(info["residual"].max())
    if worst > tol:
        warnings.warn(f"solve_reference: not converged in {max_iter} iterations (RMS residual "
                      f"{worst:.3g} m/s^2 > tol {tol:.3g})", RuntimeWarning, stacklevel=2)
    return out


#: The classical optimisers by name: ``f(problem, iters, **kw) -> a``.
CLASSICAL = {"gd": solve_gd, "adam": solve_adam, "lbfgs": solve_lbfgs}


@dataclass
class Rollout:
    """A rollout: positions ``(F+1, H, W, 3)`` (m), per-frame ``L_cloth`` (J), ms per frame.

    ``ms``: wall-clock milliseconds of the optimiser per frame; ``cpu_ms``: CPU milliseconds of
    the calling thread (the figure to compare on a shared machine).
    """

    positions: torch.Tensor
    loss: list
    ms: list
    handles: torch.Tensor
    accel: torch.Tensor | None = None
    cpu_ms: list | None = None


def rollout(sheet: cloth.Sheet, material: cloth.Material, layout, motion: str, frames: int,
            step: Callable, speed: float = 1.0, dt: float = DT, orientation: str = "vertical",
            repulsion: float = 0.0, warm_start: bool = False, dtype=torch.float32,
            progress: Callable | None = None, perturb: float = 0.0) -> Rollout:
    """Simulate ``frames`` steps from rest; ``step(problem, a_prev) -> a`` solves each step.

    ``warm_start``: ``a_prev`` is the previous frame's acceleration (else ``None``: the
    solver starts from zero, Algorithm 2). ``repulsion``: weight (J) of eq. (28) with
    ``delta`` the grid spacing (0: off). ``progress``: called after each frame. ``perturb``:
    standard deviation (m) of Gaussian noise (seed 0) added to the free vertices' initial
    positions, for sensitivity studies (0: off).

    Raises
    ------
    ValueError
        On a non-finite state (the solver diverged), an unknown layout or motion.
    """
    h, w = sheet.height, sheet.width
    idx = cloth.handle_indices(layout, h, w)
    x = cloth.rest_positions(sheet, orientation, torch.float64)[None]
    traj = trajectory(x[0, idx[:, 0], idx[:, 1]], motion, frames, speed, dt)
    if perturb > 0:
        noise = torch.randn(x.shape, generator=torch.Generator().manual_seed(0),
                            dtype=torch.float64)
        x = x + perturb * noise * (1.0 - cloth.handle_mask(idx, h, w, torch.float64))[..., None]
    x = x.to(dtype)
    v = torch.zeros_like(x)
    mat = material.tensors(1, dtype)
    out = [x[0].clone()]
    losses, ms, cpu_ms = [], [], []
    a_prev = None
    delta = min(sheet.hx, sheet.hy)
    for f in range(1, frames + 1):
        target = traj[f][None].to(dtype)
        extra = None
        if repulsion > 0:
            pairs = cloth.repulsion_pairs(x[0] + dt * v[0], 2 * delta)

            def extra(xx, pairs=pairs):
                return cloth.repulsion_energy(xx[0], pairs, delta, repulsion)[None]
        p = make_problem(x, v, idx, target, sheet.hx, sheet.hy, mat, dt, extra)
        t0, c0 = time.perf_counter(), time.thread_time()
        a = step(p, a_prev if warm_start else None)
        ms.append(1e3 * (time.perf_counter() - t0))
        cpu_ms.append(1e3 * (time.thread_time() - c0))
        with torch.no_grad():
            p64 = make_problem(x.double(), v.double(), idx, target.double(), sheet.hx,
                               sheet.hy, material.tensors(1, torch.float64), dt)
            losses.append(float(p64.loss(a.double())[0]))
        x, v = cloth.advance(a, x, v, dt, idx, target)
        if not bool(torch.isfinite(x).all()) or not math.isfinite(losses[-1]):
            raise ValueError(f"rollout diverged at frame {f} (non-finite state)")
        a_prev = a
        out.append(x[0].clone())
        if progress is not None:
            progress()
    return Rollout(torch.stack(out), losses, ms, traj, cpu_ms=cpu_ms)
