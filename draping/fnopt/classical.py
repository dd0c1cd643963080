"""The classical inner optimisers of a step problem and the converged reference.

Gradient descent, Adam, L-BFGS (fixed step, the thesis' baseline, or Armijo backtracking;
optionally DCT-preconditioned), L-BFGS with PyTorch's strong-Wolfe line search, steepest descent
and PCG in the DCT metric (FNOpt's subspace step without the FNO), and :func:`solve_reference`,
the float64 L-BFGS solve to :data:`REFERENCE_TOL` that serves as ground truth. All work in the
mass metric of :class:`draping.fnopt.step_problem.StepProblem`.
"""

from __future__ import annotations

import functools
import inspect
import warnings

import torch

from polygeo.checks import check_int

from .coarse import check_grid_option
from .preconditioners import (
    curvature_bound,
    laplace_preconditioner,
    normal_directions,
    normal_preconditioner,
)
from .step_problem import StepProblem, autograd_free_call
from .twolevel import coarse_correction, kept_space

__all__ = ["solve_gd", "solve_pgd", "solve_pcg", "solve_adam", "solve_lbfgs",
           "solve_lbfgs_wolfe", "solve_reference", "CLASSICAL", "REFERENCE_TOL"]


#: Tolerance of the converged reference: RMS residual ``M^-1 dL/da / dt^2`` over the free
#: vertices, m/s^2 (5e-6 g). Set by a convergence study (``bm_fnopt.py --part reference``):
#: rollouts solved to 5e-2 and 5e-3 differ by up to 16 cm on the mid-edges layout (the fold
#: that the loose solves pick is not the converged one), 5e-4 and 5e-5 by 6 mm, 5e-5 and 5e-6
#: by 0.4 mm (32x32, 60 frames); the reference is solved in float64 with float64 states.
REFERENCE_TOL = 5e-5


def _autograd_free(gradient_option: bool):
    """Decorator: the solver runs by :func:`autograd_free_call`.

    So under ``torch.inference_mode`` where its problem needs no autograd, bit for bit the same
    answer. ``gradient_option``: the solver has a ``fused_grad`` argument and needs autograd
    unless it is true (false: its gradients come from autograd); else it uses only the
    problem's own gradient and Hessian products. Tensors the solver leaves in an ``info`` dict
    are returned as normal tensors too.
    """

    def wrap(fn):
        sig = inspect.signature(fn)

        @functools.wraps(fn)
        def run(p, *args, **kw):
            bound = sig.bind(p, *args, **kw)
            enabled = bound.arguments.get("fused_grad", False) if gradient_option else True
            out = autograd_free_call(p, fn, p, *args, enabled=enabled, **kw)
            info = bound.arguments.get("info")
            if info is not None:
                info.update({k: v.clone() for k, v in info.items()
                             if isinstance(v, torch.Tensor) and v.is_inference()})
            return out
        return run
    return wrap


@_autograd_free(gradient_option=True)
def solve_gd(p: StepProblem, iters: int, lr: float | None = 0.5, a0=None,
             fused_grad: bool = False) -> torch.Tensor:
    """Gradient descent in the mass metric: ``a -= lr * r`` (``lr`` dimensionless).

    ``lr=None``: per sheet ``1 /`` :func:`~draping.fnopt.preconditioners.curvature_bound`, a
    stable step at any resolution (a fixed one diverges on fine grids: the mass-metric
    curvature grows as ``1 / h^2``). ``fused_grad``: gradients by the fused kernel
    (:meth:`StepProblem.loss_grad`'s ``fused``).
    """
    if lr is None:
        lr = (1.0 / curvature_bound(p)).to(p.x_prev.dtype)[:, None, None, None]
    a = torch.zeros_like(p.x_prev) if a0 is None else a0.clone()
    for _ in range(iters):
        _, g = p.loss_grad(a, fused=fused_grad)
        a = a - lr * p.precondition(g)
    return p.compose(a)


@_autograd_free(gradient_option=False)
def solve_pgd(p: StepProblem, iters: int, k_eff: float = 1.0, a0=None) -> torch.Tensor:
    """Steepest descent in the metric of :func:`laplace_preconditioner`, exact quadratic step."""
    pre = laplace_preconditioner(p, k_eff)
    a = torch.zeros_like(p.x_prev) if a0 is None else a0.clone()
    for _ in range(iters):
        _, g, hvp = p.grad_hvp(a)
        d = -pre(g) * p.free3
        a = a + p.exact_step(g, d, hvp) * d
    return p.compose(a)


@_autograd_free(gradient_option=False)
def solve_pcg(p: StepProblem, iters: int, k_eff: float = 1.0, a0=None,
              normal: bool = False, split: int = 0, coarse: int = 0, coarse_every: int = 1,
              memory: dict | None = None) -> torch.Tensor:
    """Preconditioned descent with memory (FNOpt's subspace step without the FNO).

    Each update minimises the quadratic model of ``L``
    over the span of the preconditioned gradient and the previous update (a nonlinear
    conjugate-gradient method with exact two-dimensional steps, DCT metric of
    :func:`laplace_preconditioner`). ``normal``: the span also holds the out-of-plane direction
    of :func:`normal_preconditioner` (three-dimensional steps; ``split``: that direction cut
    into its low and high DCT modes, :func:`normal_directions`). ``coarse`` (0, the default:
    off): the span also holds the two-level coarse correction ``-P A_c^-1 P^T g`` of
    :mod:`draping.fnopt.twolevel` on the grid whose longer side has ``coarse`` vertices (``A_c``
    the Galerkin operator of the Hessian at the start ``a0``, built and factored once per call).
    ``coarse_every`` with ``memory`` (a dict the caller keeps across the frames of a rollout):
    the coarse space is rebuilt only every ``coarse_every``-th call and reused in between (its
    build, ~75 Hessian products, costs about as much as 20 iterations at 64x64; the sheet
    changes little from frame to frame and the subspace step weighs the direction by exact
    products, so an older ``A_c`` still serves as a preconditioner).

    Raises
    ------
    TypeError, ValueError
        If ``coarse`` is not 0 or an int >= 2 (:func:`draping.fnopt.coarse.check_grid_option`),
        ``coarse_every`` not an int >= 1, or ``coarse_every > 1`` without ``memory``.
    """
    check_grid_option(coarse, "coarse")
    check_int(coarse_every, "coarse_every", low=1)
    if coarse_every > 1 and memory is None:
        raise ValueError(f"coarse_every: {coarse_every} needs a memory dict (got None)")
    pre = laplace_preconditioner(p, k_eff)
    pn = normal_preconditioner(p) if normal else None
    a = torch.zeros_like(p.x_prev) if a0 is None else a0.clone()
    da = torch.zeros_like(a)
    space = None
    for _ in range(iters):
        _, g, hvp = p.grad_hvp(a)
        dirs = [-pre(g) * p.free3, da] + (normal_directions(p, g, pn, split) if normal else [])
        if coarse:
            space = space or kept_space(p, hvp, coarse, coarse_every, memory)
            dirs.append(-coarse_correction(space, g))
        da = p.subspace_step(g, dirs, hvp)
        a = a + da
    return p.compose(a)


@_autograd_free(gradient_option=True)
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


@_autograd_free(gradient_option=True)
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
                      float64: bool = False, fused_grad: bool = False) -> torch.Tensor:
    """L-BFGS with a strong-Wolfe line search (``torch.optim.LBFGS``), the fair baseline.

    PyTorch's own implementation (two-loop recursion, cubic-interpolation strong-Wolfe line
    search, initial Hessian scaled by ``s^T y / y^T y``) run on the mass-scaled variable
    ``b = sqrt(m) dt a`` (the same diagonal scaling as :func:`solve_lbfgs`; the identity is then
    the inertia term's Hessian). ``iters``: L-BFGS iterations; ``max_eval``: gradient
    evaluations allowed in all (default ``2 * iters``, the line search's extra ones included);
    ``info`` receives ``evaluations`` and ``residual`` (RMS, m/s^2). ``float64``: solve in
    float64 (in float32 the line search stops once the decrease is below the loss' rounding).
    ``fused_grad``: energies and gradients by the fused kernel (:meth:`StepProblem.loss_grad`'s
    ``fused``; default autograd).
    """
    if float64 and p.x_prev.dtype != torch.float64:
        p64 = _as_float64(p)
        a0 = None if a0 is None else a0.double()
        out = solve_lbfgs_wolfe(p64, iters, history, a0, max_eval, info,
                                fused_grad=fused_grad)
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
        val, g = p.loss_grad(b.detach() / sq, fused=fused_grad)
        b.grad = g / sq * p.free3
        return val.sum()

    opt.step(closure)
    a = b.detach() / sq
    if info is not None:
        info["evaluations"] = p.evals - evals0
        info["residual"] = p.residual_rms(p.precondition(p.loss_grad(a, fused=fused_grad)[1]))
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
