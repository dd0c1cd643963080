"""Rollouts: a sheet simulated from rest, each time step solved by a given optimiser."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import torch

from . import cloth
from .handles import DT, trajectory
from .step_problem import make_problem

__all__ = ["Rollout", "rollout", "energy_record"]


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
    positions, for sensitivity studies (0: off). The ``L_cloth`` recorded per frame is
    :func:`energy_record`'s (float64, without the repulsion term); ``step`` decides for itself
    whether it runs under ``torch.inference_mode`` (the solvers of
    :mod:`~draping.fnopt.classical` and ``solve_fnopt`` do where their problem allows).

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
    record = energy_record(sheet, material, idx, dt)
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
        losses.append(record(a, x, v, target))
        x, v = cloth.advance(a, x, v, dt, idx, target)
        if not bool(torch.isfinite(x).all()) or not math.isfinite(losses[-1]):
            raise ValueError(f"rollout diverged at frame {f} (non-finite state)")
        a_prev = a
        out.append(x[0].clone())
        if progress is not None:
            progress()
    return Rollout(torch.stack(out), losses, ms, traj, cpu_ms=cpu_ms)


def energy_record(sheet: cloth.Sheet, material: cloth.Material, idx: torch.Tensor,
                  dt: float = DT) -> Callable:
    """The per-frame metric ``L_cloth``: ``(a, x_prev, v_prev, target) -> float`` (J).

    ``L_cloth`` (eq. (61), no repulsion) of accelerations ``a`` ``(1, H, W, 3)`` from the state
    ``x_prev``, ``v_prev`` ``(1, H, W, 3)`` with the handles ``idx`` ``(K, 2)`` moved to
    ``target`` ``(1, K, 3)``, all in float64 whatever their dtype: the value of
    ``make_problem(x.double(), ..., material.tensors(1, float64)).loss(a.double())`` (the
    rollout's record before session 15) up to float64 rounding (~1e-14 relative), by the fused
    kernel (:func:`~draping.fnopt.kernels.loss_grad_fused`) with the masses and kernel
    constants built once here instead of a problem per frame: 0.08 / 0.19 / 0.47 ms a frame at
    32 / 64 / 100 against 0.71 / 1.52 / 3.30 (session 15). The handles' accelerations are
    :func:`~draping.fnopt.cloth.handle_accel`'s, whatever ``a`` holds there (as the problem's
    ``compose``). Grids of at least 3 x 3 (every rollout's: :func:`make_problem` checks).
    """
    from .kernels import kernel_constants, loss_grad_fused  # numba: loaded when first used

    h, w = sheet.height, sheet.width
    mat = material.tensors(1, torch.float64)
    hx = torch.tensor([sheet.hx], dtype=torch.float64)
    hy = torch.tensor([sheet.hy], dtype=torch.float64)
    mass = cloth.vertex_mass(h, w, hx, hy, mat["density"], torch.float64)
    consts = kernel_constants(1, h, w, hx, hy, mat)
    rows, cols = idx[:, 0], idx[:, 1]

    def record(a: torch.Tensor, x_prev: torch.Tensor, v_prev: torch.Tensor,
               target: torch.Tensor) -> float:
        x64, v64 = x_prev.detach().double(), v_prev.detach().double()
        a64 = a.detach().to(torch.float64, copy=True)
        a64[:, rows, cols] = cloth.handle_accel(x64, v64, idx, target.detach().double(), dt)
        return float(loss_grad_fused(a64, x64, v64, hx, hy, mat, dt, mass, consts)[0][0])

    return record
