"""Rollout-level fine-tuning of the FNO optimiser: truncated back-propagation through frames.

The pool training of :mod:`draping.fnopt.train` scores one inner iteration at a time, each from
a stored state; the error an ``N``-iteration solve leaves in a frame, and what it does to the
next frames, is never in its loss. Here a training step runs ``K`` consecutive frames of the
model's own rollout, each with ``N`` inner iterations from ``a = 0`` (Algorithm 2), and keeps
the graph:

- within a frame, through every update (the FNO's proposal and the subspace coefficients) and
  the memory direction ``Delta a_{k-1}`` into the next iteration, so the loss sees the ``N``-th
  iterate and not one step;
- across a frame boundary, through the next state ``v' = v + dt a_N``, ``x' = x + dt v'``, which
  enters the next frame's energy (inertia, stretch, shear, bend at ``x' + dt v' + dt^2 a``).

What the graph leaves out (first-order, as in the pool training): the gradients, the
preconditioned gradients and the Hessian products are constants of each iteration (the graph
does not run through ``dL/da`` at the previous iterate or through the next frame's inputs).

The loss of frame ``k`` is its normalised sub-optimality
``(L_k(a_N) - L_k(a_ref)) / (1/2 g_0 . z_0)``: ``a_ref`` is ``a_N`` improved by ``extra``
classical iterations (:func:`draping.fnopt.solvers.solve_pcg` with the normal directions,
detached; ``extra = 0``: ``a_ref = 0``, the plain normalised decrease), both energies evaluated
in float64 on the frame's state *in the graph*; the denominator is the pool training's (the
decrease of the metric's Newton step from ``a = 0``, detached).
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
    solve_pcg,
)

__all__ = ["unrolled_solve", "rollout_losses", "rollout_train_step"]


def unrolled_solve(model: FNO, p: StepProblem, iters: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``iters`` FNOpt updates from ``a = 0`` with the graph kept through every update.

    ``p``: a problem whose state carries no graph (the inputs of each update are constants).
    Returns the free accelerations ``a_N`` ``(B, H, W, 3)`` (m/s^2, in the graph of the model's
    parameters) and the normalisation ``1/2 g_0 . z_0`` ``(B,)`` (J, float64, detached).
    """
    pre = laplace_preconditioner(p)
    pn = normal_preconditioner(p) if model.config.normal else None
    const = constant_features(p, p.x_prev.dtype)
    a = torch.zeros_like(p.x_prev)
    da = torch.zeros_like(a)
    z_prev = torch.zeros_like(a)
    denom = None
    for _ in range(iters):
        _, g, hvp = p.grad_hvp(a.detach())
        z = pre(g) * p.free
        if denom is None:
            denom = 0.5 * (g.double() * z.double()).sum((1, 2, 3)).clamp(min=1e-30)
        zn = normal_directions(p, g, pn, model.config.normal_split) if pn is not None else None
        da = subspace_update(model, p, g, hvp, z, z_prev, da, create_graph=True, zn=zn,
                             const=const)[0]
        a = a + da
        z_prev = z
    return a, denom


def rollout_losses(model: FNO, pool, ids: torch.Tensor, frames: int, iters: int,
                   extra: int = 20, detach_state: bool = False):
    """``frames`` consecutive frames of the model's rollout of pool entries ``ids``.

    Parameters
    ----------
    model : FNO
    pool : draping.fnopt.train.Pool
        Supplies the entries' states ``x, v`` ``(P, r, r, 3)``, times ``t``, handles, motion
        and material (read only).
    ids : torch.Tensor
        ``(B,)`` int64 entries.
    frames, iters : int
        ``K`` frames, ``N`` inner iterations each (>= 1).
    extra : int
        Classical iterations that improve ``a_N`` into the frame's baseline ``a_ref`` (>= 0).
    detach_state : bool
        Cut the graph at every frame boundary (the next frame starts from a detached state):
        the per-frame unrolled loss without the rollout-level path (for comparison and tests).

    Returns
    -------
    losses : list of torch.Tensor
        ``K`` tensors ``(B,)`` float64, each frame's normalised sub-optimality (see the module).
    state : tuple of torch.Tensor
        ``(x, v)`` ``(B, r, r, 3)`` after the last frame (in the graph unless ``detach_state``).

    Raises
    ------
    ValueError
        If ``frames`` or ``iters`` < 1 or ``extra`` < 0.
    """
    if int(frames) < 1 or int(iters) < 1:
        raise ValueError(f"frames, iters: expected >= 1, got {frames!r}, {iters!r}")
    if int(extra) < 0:
        raise ValueError(f"extra: expected >= 0, got {extra!r}")
    x, v = pool.x[ids].float(), pool.v[ids].float()
    t0 = pool.t[ids]
    losses = []
    for k in range(frames):
        t = t0 + k * DT
        p_in, target = pool.problem(ids, state=(x.detach(), v.detach(), t), analytic_hvp=True)
        a, denom = unrolled_solve(model, p_in, iters)
        # the frame's energy on its state in the graph (float64, as the pool training's)
        p_g, _ = pool.problem(ids, torch.float64, state=(x, v, t), analytic_hvp=True)
        l_n = p_g.loss(a.double())
        with torch.no_grad():
            a_ref = solve_pcg(p_in, extra, a0=a.detach(), normal=model.config.normal,
                              split=model.config.normal_split) if extra > 0 \
                else torch.zeros_like(a)
        losses.append((l_n - p_g.loss(a_ref.double())) / denom)
        # backward Euler with the model's own acceleration; handles on their targets
        hm = p_in.free.new_ones(()) - p_in.free
        v = v + DT * p_g.compose(a.double()).to(v.dtype)
        x = (x + DT * v) * (1 - hm) + target * hm
        if detach_state:
            x, v = x.detach(), v.detach()
    return losses, (x, v)


def rollout_train_step(model: FNO, opt, pool, frames: int, iters: int, batch: int,
                       extra: int, lr: float) -> float:
    """One fine-tuning step on ``batch`` random pool entries; returns the mean loss.

    The loss is the mean over entries and frames of each frame's normalised sub-optimality
    (:func:`rollout_losses`; a positive one through ``log1p``, a non-finite one dropped). The
    entries then continue from the rollout's last state (detached): the pool advances
    ``frames`` frames; an entry that blew up (non-finite, or a speed > 50 m/s) or reached its
    length is re-drawn (``pool.reset``).
    """
    ids = torch.randperm(pool.x.shape[0], generator=pool.gen)[:batch]
    losses, (x, v) = rollout_losses(model, pool, ids, frames, iters, extra)
    q = torch.stack(losses)                                         # (K, B)
    ok = torch.isfinite(q)
    q = torch.where(ok, q, torch.zeros_like(q))
    term = torch.where(q > 0, torch.log1p(q.clamp(min=0)), q)
    loss = term.sum() / max(int(ok.sum()), 1)
    optimizer_step(model, opt, loss, lr)
    with torch.no_grad():
        pool.settle(ids, x.detach().float(), v.detach().float(), frames, ok.all(0))
    return float(loss.detach())
