"""Training the FNO for the first-iteration role: its proposal, then ``K`` classical iterations.

At equal CPU time on this machine the classical half of FNOpt's step is the better buy (session
14: one FNO call costs ~2.3 PCG-normal iterations and is worth about one), and the one place
where a learned call was not worse is a single proposal on the first iteration of a step,
followed by PCG with the normal directions (``solve_fnopt(fno_every >= N)``). The pool
training of :mod:`draping.fnopt.train` scores each proposal by the decrease of ``L_cloth`` it
gives in *one* update, so the first proposal spends itself on modes the next classical
iterations remove anyway. Here it is scored by the error left *after* them:

1. the first update ``a_1`` from ``a = 0`` (:func:`draping.fnopt.model.subspace_update`, the
   graph kept through the proposal and its subspace coefficient);
2. ``K`` classical iterations from ``a_1`` with ``a_1`` as their memory direction
   (:func:`classical_iterations`: the span of the preconditioned gradient, the previous update
   and the normal directions, exactly the non-learned iterations of
   :func:`draping.fnopt.model.solve_fnopt`), detached, giving ``a_K``;
3. ``extra`` more of them give ``a_ref``; the loss of a sheet is
   ``log(L(a_K) - L(a_ref))`` (float64 energies).

The gradient of that loss is taken *straight through* the ``K`` classical iterations: at
``a_1`` it is ``g_K / (L(a_K) - L(a_ref))`` with ``g_K = dL/da`` at ``a_K`` (the ``K``
iterations' Jacobian taken as the identity). For a quadratic energy and a fixed-polynomial
method ``e_K = P_K e_1`` the exact gradient is ``P_K^T g_K``, which differs from ``g_K`` by one
more application of the polynomial that damps the fast modes; both are dominated by the slow
modes the classical iterations leave, which are what the proposal should carry, and nothing
has to be kept through the ``K`` iterations (they run detached, without autograd).

The pool's sheets advance by ``a_K`` (the role's own rollouts); a sheet is re-drawn after its
length, on a blow-up or at random (``reset_prob``), as in the pool training.
"""

from __future__ import annotations

import torch

from .handles import DT
from .model import FNO, constant_features, optimizer_step, subspace_update
from .solvers import (
    StepProblem,
    laplace_preconditioner,
    normal_directions,
    normal_preconditioner,
)
from .step_problem import autograd_free_call

__all__ = ["classical_iterations", "first_update", "proposal_losses", "proposal_train_step"]


def _preconditioners(model: FNO, p: StepProblem):
    """``(P, P_n)`` of a step problem, built once and shared by its iterations.

    ``P``: :func:`laplace_preconditioner`; ``P_n``: :func:`normal_preconditioner` with
    ``model.config.normal``, else ``None``.
    """
    return laplace_preconditioner(p), (normal_preconditioner(p) if model.config.normal else None)


def classical_iterations(model: FNO, p: StepProblem, a: torch.Tensor, da: torch.Tensor,
                         iters: int, precond=None) -> tuple[torch.Tensor, torch.Tensor]:
    """``iters`` classical updates of FNOpt's step from ``a`` with memory ``da``: ``(a_K, da_K)``.

    The non-learned iterations of :func:`draping.fnopt.model.solve_fnopt` (the span of ``-P g``,
    the previous update and, with ``model.config.normal``, the normal directions), no graph;
    ``a``, ``da``: ``(B, H, W, 3)`` m/s^2 (free part); returned: the last iterate and the last
    update (the memory to continue from). ``iters = 0`` returns ``(a, da)``. ``precond``:
    :func:`_preconditioners` of ``(model, p)`` when the caller has them (else built here).
    """
    pre, pn = precond if precond is not None else _preconditioners(model, p)

    def run(a, da):
        a, da = a.detach().clone(), da.detach().clone()
        for _ in range(iters):
            _, g, hvp = p.grad_hvp(a)
            z = pre(g) * p.free3
            zn = normal_directions(p, g, pn, model.config.normal_split) if pn is not None \
                else None
            da = subspace_update(model, p, g, hvp, z, z, da, zn=zn, proposal=False)[0]
            a = a + da
        return a, da

    with torch.no_grad():
        a, da = autograd_free_call(p, run, a, da)
    return a.clone(), da.clone()


def first_update(model: FNO, p: StepProblem, precond=None) -> torch.Tensor:
    """FNOpt's first update from ``a = 0`` ``(B, H, W, 3)``, the graph kept through the proposal.

    ``precond``: :func:`_preconditioners` of ``(model, p)`` when the caller has them.
    """
    pre, pn = precond if precond is not None else _preconditioners(model, p)
    a = torch.zeros_like(p.x_prev)
    _, g, hvp = p.grad_hvp(a)
    z = pre(g) * p.free
    zn = normal_directions(p, g, pn, model.config.normal_split) if pn is not None else None
    return subspace_update(model, p, g, hvp, z, torch.zeros_like(a), torch.zeros_like(a),
                           create_graph=True, zn=zn, const=constant_features(p, a.dtype))[0]


def proposal_losses(model: FNO, p: StepProblem, p64: StepProblem, iters: int, extra: int):
    """Surrogate losses of the first-iteration role on the step problems ``p`` (float32).

    Parameters
    ----------
    p, p64 : StepProblem
        The same ``B`` step problems in float32 (solved) and float64 (energies).
    iters : int
        ``K`` >= 1 classical iterations after the first update.
    extra : int
        ``>= 1`` further classical iterations that give the reference ``a_ref``.

    Returns
    -------
    surrogate : torch.Tensor
        ``(B,)`` float64 in the graph of the model: ``g_K . a_1 / gap`` (its gradient is the
        straight-through gradient of ``log gap``; its value means nothing).
    rel : torch.Tensor
        ``(B,)`` float64, detached: ``gap / (L(0) - L(a_ref))``, the relative sub-optimality
        after ``1 + K`` iterations (non-finite where the solve blew up).
    a_k : torch.Tensor
        ``(B, H, W, 3)`` the free accelerations after ``1 + K`` iterations (detached).

    Raises
    ------
    ValueError
        If ``iters`` or ``extra`` < 1.
    """
    if int(iters) < 1 or int(extra) < 1:
        raise ValueError(f"iters, extra: expected >= 1, got {iters!r}, {extra!r}")
    precond = _preconditioners(model, p)
    a1 = first_update(model, p, precond)
    a1d = a1.detach()
    a_k, da_k = classical_iterations(model, p, a1d, a1d, iters, precond)
    a_ref = classical_iterations(model, p, a_k, da_k, extra, precond)[0]
    with torch.no_grad():
        l0 = p64.loss(torch.zeros_like(a_k).double())
        lk = p64.loss(a_k.double())
        lr = torch.minimum(p64.loss(a_ref.double()), lk)
    g_k = p64.loss_grad(a_k.double(), fused=True)[1].detach()
    scale = (l0 - lr).clamp(min=1e-30)
    gap = (lk - lr).clamp(min=1e-9 * scale + 1e-30)
    surrogate = (g_k * a1.double()).sum((1, 2, 3)) / gap
    return surrogate, gap / scale, a_k


def proposal_train_step(model: FNO, opt, pool, iters: int, extra: int, batch: int, lr: float,
                        reset_prob: float = 0.0) -> float:
    """One training step of the first-iteration role on ``batch`` random pool entries.

    Each entry's frame is solved by the first update and ``iters`` classical iterations
    (:func:`proposal_losses`); the model takes one Adam step at rate ``lr`` on the mean
    straight-through loss (non-finite sheets dropped, gradient norm clipped at 1); the entries
    advance one backward-Euler frame with ``a_K`` (handles on their targets) and are re-drawn
    after their length or on a blow-up (non-finite, or a speed > 50 m/s); with probability
    ``reset_prob`` one random entry is re-drawn. ``pool``: a :class:`draping.fnopt.train.Pool`.
    Returns the mean relative sub-optimality after ``1 + iters`` iterations (finite sheets).
    """
    ids = torch.randperm(pool.x.shape[0], generator=pool.gen)[:batch]
    p, target = pool.problem(ids, analytic_hvp=True)
    p64, _ = pool.problem(ids, torch.float64, analytic_hvp=True)
    surrogate, rel, a_k = proposal_losses(model, p, p64, iters, extra)
    ok = torch.isfinite(surrogate) & torch.isfinite(rel)
    loss = torch.where(ok, surrogate, torch.zeros_like(surrogate)).sum() / max(int(ok.sum()), 1)
    optimizer_step(model, opt, loss, lr)
    with torch.no_grad():
        hm = pool.hmask[ids][..., None]
        v_new = pool.v[ids] + DT * p.compose(a_k).float()
        x_new = (pool.x[ids] + DT * v_new) * (1 - hm) + target.float() * hm
        pool.settle(ids, x_new, v_new, 1, ok)
        if reset_prob > 0 and float(torch.rand(1, generator=pool.gen)) < reset_prob:
            pool.reset(int(torch.randint(pool.x.shape[0], (1,), generator=pool.gen)))
    return float(rel[ok].mean()) if bool(ok.any()) else 1.0    # none finite: "nothing done"
