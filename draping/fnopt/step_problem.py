"""One backward-Euler time step as an optimisation problem: :class:`StepProblem`.

Every optimiser works in the mass metric: the variable is the acceleration ``a`` (m/s^2) and
the *residual* ``r = M^-1 dL/da / dt^2`` (m/s^2, ``a - f / m`` when only inertia and forces
act) is what the learned optimiser sees and what the tolerances are stated in. That metric makes
step sizes resolution-independent: GD with ``lr = 1`` is exact for the inertia term alone at any
grid size. Also here: :func:`make_problem` (the problem of a state and its handles) and
:func:`subspace_solve` (the quadratic model minimised over a span of directions, the step of
PCG and of FNOpt). The optimisers are in :mod:`draping.fnopt.classical` and
:mod:`draping.fnopt.model`, the preconditioners in :mod:`draping.fnopt.preconditioners`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from . import cloth
from .handles import DT

__all__ = ["StepProblem", "make_problem", "subspace_solve", "free_rms", "autograd_free_call"]


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
            with torch.inference_mode(False):     # a normal tensor, also when built in one
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

    def autograd_free(self) -> bool:
        """Whether :meth:`grad_hvp` runs without autograd (closed forms, fused kernels).

        True with the closed-form products (``analytic_hvp``) and the fused loss and gradient
        (:meth:`_fusable`): then a solve may run under ``torch.inference_mode``
        (:func:`draping.fnopt.model.solve_fnopt` does); else the gradient comes from
        autograd, which that mode switches off.
        """
        return (self.analytic_hvp and self.extra is None and type(self).loss is StepProblem.loss
                and self._fusable())

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
        """RMS ``(B,)`` over the free vertices' residual components (:func:`free_rms`)."""
        return free_rms(r, self.free3)


def free_rms(f: torch.Tensor, free: torch.Tensor) -> torch.Tensor:
    """RMS ``(B,)`` of a field ``f`` ``(B, H, W, 3)`` over the components at free vertices.

    ``free``: a 0/1 mask ``(B or 1, H, W, 1 or 3)`` (1 at free vertices); the mean is over
    the free vertices' 3 components (over 1 if there is none, giving 0). The one home of this
    RMS: :meth:`StepProblem.residual_rms` (the fine grid's mask) and the coarse FNO grid's
    normalisation (:func:`draping.fnopt.coarse.free_rms`, the coarse mask) both call it.
    """
    n = free.expand(f.shape).sum((1, 2, 3)).clamp(min=1)
    return ((f * free).square().sum((1, 2, 3)) / n).sqrt()


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
    the step (m). ``hx``, ``hy``: floats or ``(B,)``. The problem holds normal tensors also
    when built under ``torch.inference_mode`` or from tensors made in it (copied then): its
    caches track tensor versions and autograd's solvers save its tensors for backward, neither
    of which inference tensors allow.

    Raises
    ------
    ValueError
        On non-grid or non-finite states, or handles out of range.
    """
    if torch.is_inference_mode_enabled() or any(
            _is_inference(t) for t in (x_prev, v_prev, target, hx, hy, *material.values())):
        with torch.inference_mode(False):
            return make_problem(_normal(x_prev), _normal(v_prev), idx, _normal(target),
                                _normal(hx), _normal(hy),
                                {k: _normal(v) for k, v in material.items()}, dt, extra)
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


def _is_inference(t) -> bool:
    return isinstance(t, torch.Tensor) and t.is_inference()


def _normal(t):
    """``t``, or a normal-tensor copy of it when it is an inference tensor."""
    return t.clone() if _is_inference(t) else t



def autograd_free_call(p: StepProblem, fn: Callable, *args, enabled: bool = True, **kw):
    """``fn(*args, **kw)`` under ``torch.inference_mode`` where ``p`` needs no autograd.

    The one home of that rule (:func:`draping.fnopt.model.solve_fnopt`, the classical solvers of
    :mod:`draping.fnopt.classical`, the rollout loop): where :meth:`StepProblem.autograd_free`
    holds and ``enabled`` (``False``: the caller's own work needs autograd, e.g. a solver given
    autograd's gradient) the same operations run without autograd's per-operation bookkeeping,
    the same arithmetic bit for bit (5-13 % less time per solve, session 14); else ``fn`` runs
    as it is. ``p`` must have been built outside that mode (its cached masks track versions).

    Returns
    -------
    ``fn``'s result; a tensor result made in that mode is returned as a normal tensor (a clone),
    so callers may use it in place or in autograd; other results (floats, tuples) as they are.
    """
    if not (enabled and p.autograd_free()):
        return fn(*args, **kw)
    with torch.inference_mode():
        out = fn(*args, **kw)
    return out.clone() if isinstance(out, torch.Tensor) else out
