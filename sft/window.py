"""One window of PolySfT: its objective, its Adam optimiser and its iterations.

:func:`reconstruct_window` optimises a fixed set of frames from the template (no sliding);
:func:`sft.optimize.run_sft` slides the window over a sequence with the same pieces. One
Adam optimiser per window, with the learning rates of :class:`sft.settings.OptimiserSettings`
per parameter group; the parameters are in the model's normalised units (the template radius
is 1, see :mod:`sft.model`). A fresh Adam state ramps its learning rates up over its first
``warmup`` steps, and a window hands on its lowest-loss iterate (``keep_best``), not its last.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np
import torch

from .data import Sequence, load_sequence
from .losses import ImageTerms, Inextensibility, temporal_acceleration, temporal_consistency
from .model import ORDER_AUTO, DeformationModel, build_model
from .settings import SfTSettings

__all__ = ["reconstruct_window"]


class _Window:
    """Frames of the current window with their cached targets."""

    def __init__(self, seq: Sequence, terms: ImageTerms) -> None:
        self.seq, self.terms = seq, terms
        self.cache: dict[int, tuple[torch.Tensor, torch.Tensor | None]] = {}

    def targets(self, idx: list[int]):
        for j in idx:
            if j not in self.cache:
                self.cache[j] = self.terms.target(self.seq.frame(j), self.seq.mask(j))
        for j in list(self.cache):
            if j not in idx:
                del self.cache[j]
        t = torch.stack([self.cache[j][0] for j in idx])
        m = None
        if self.seq.has_masks:
            m = torch.stack([self.cache[j][1] for j in idx])
        return t, m


def _build_model(st: SfTSettings, template) -> DeformationModel:
    """The deformation model of ``st`` for a sequence's template."""
    m, w = st.model, st.losses
    return build_model(m.method, template.verts, template.faces, order=m.order,
                       max_order=m.max_order, patches=m.patches, max_tilt=m.max_tilt,
                       boundary_weight=w.boundary_weight,
                       boundary_normal_weight=w.boundary_normal_weight,
                       patch_rigid=m.patch_rigid, seed=m.seed, dtype=st.torch_dtype)


def _objective_parts(seq: Sequence, st: SfTSettings):
    """``(model, image terms, inextensibility)`` of a run with settings ``st`` on ``seq``."""
    t = seq.template
    model = _build_model(st, t)
    w = st.losses
    terms = ImageTerms(seq, st.raster, rgb_weight=w.rgb_weight,
                       silhouette_weight=w.silhouette_weight, rgb_kind=w.rgb_kind,
                       silhouette_kind=w.silhouette_kind, pyramid=w.pyramid,
                       dtype=st.torch_dtype)
    inext = Inextensibility(t.verts, t.faces, model.scale, w.inextensibility_weight)
    return model, terms, inext



def _initial(model: DeformationModel, st: SfTSettings, prev: dict | None,
             prev2: dict | None) -> dict[str, torch.Tensor]:
    """Parameters of a frame entering the window (see ``SfTSettings.init``)."""
    if prev is None:
        return model.init_params()
    out = {k: (v.clone() if isinstance(v, torch.Tensor) else v) for k, v in prev.items()}
    if st.optimiser.init == "extrapolate" and prev2 is not None:
        for k in model.init_params():  # the parameters; the Adam moments are copied
            out[k] = 2 * prev[k] - prev2[k]
    return out


def _window_loss(model: DeformationModel, terms: ImageTerms, inext: Inextensibility,
                 st: SfTSettings, params: dict, targets: torch.Tensor,
                 masks: torch.Tensor | None) -> torch.Tensor:
    """The window's objective (scalar tensor).

    Image terms and inextensibility summed over the window's frames, the model's regulariser,
    the temporal consistency between consecutive frames and the constant-velocity prior.
    """
    verts, reg = model.forward(params)
    img = terms(verts, targets, masks)
    per_frame = img["rgb"] + inext(verts)
    if "sil" in img:
        per_frame = per_frame + img["sil"]
    loss = per_frame.sum() + reg
    w = st.losses
    if w.consistency_weight > 0 and verts.shape[0] > 1:
        loss = loss + temporal_consistency(params, model.temporal, w.consistency_weight)
    if w.acceleration_weight > 0 and verts.shape[0] > 2:
        loss = loss + temporal_acceleration(params, model.groups, w.acceleration_weight)
    return loss


def _optimize_window(model: DeformationModel, terms: ImageTerms, inext: Inextensibility,
                     st: SfTSettings, pending: dict, idx: list[int], targets: torch.Tensor,
                     masks: torch.Tensor | None, callback=None) -> tuple[int, list[float], float]:
    """Optimise the frames ``idx`` in place in ``pending``; return (iterations, curve, loss).

    With ``st.keep_best`` the parameters left in ``pending`` are the iterate of the lowest
    loss of ``curve``, and ``loss`` is that value; without, they are those after the last
    step and ``loss`` is ``curve[-1]`` (the loss before that step).
    ``callback(iteration, params)`` is called after every step when given.
    """
    opt_st = st.optimiser
    names = list(model.init_params())
    params = {n: torch.stack([pending[j][n] for j in idx]) for n in names}
    free = [n for n in names if n not in opt_st.freeze]
    if not free:
        raise ValueError(f"freeze: every parameter of the model is frozen ({names})")
    for n in free:
        params[n].requires_grad_(True)
    opt = _FrameAdam(params, free, {n: getattr(opt_st, model.groups[n]) for n in free},
                     [pending[j] if opt_st.carry_adam else {} for j in idx], opt_st.warmup)
    best, since, curve = float("inf"), 0, []
    best_val, best_params = float("inf"), None  # the best iterate is what the window returns
    auto = st.model.method == "polysft" and st.model.order == ORDER_AUTO
    block_best = float("inf")  # running minimum at the start of the current block
    it = 0
    for it in range(1, opt_st.max_iterations + 1):  # noqa: B007 - `it` is reported after the loop
        for n in free:
            params[n].grad = None
        loss = _window_loss(model, terms, inext, st, params, targets, masks)
        val = float(loss.detach())
        if opt_st.keep_best and val < best_val:  # the parameters this loss was evaluated at
            best_val = val
            best_params = {n: params[n].detach().clone() for n in free}
        loss.backward()
        opt.step()
        curve.append(val)
        if callback is not None:
            callback(it, params)
        if val < best * (1.0 - opt_st.min_improvement):
            best, since = val, 0
        else:
            since += 1
        if auto and it % opt_st.patience == 0:
            # slow progress over the last block: the active order is the bottleneck
            if (model.order < model.max_order and np.isfinite(block_best)
                    and best > block_best * (1.0 - st.model.auto_gain)):
                model.set_order(model.order + 1)
                since = 0
            block_best = best
        if since >= opt_st.patience:
            if auto and model.order < model.max_order:
                model.set_order(model.order + 1)
                since = 0
                continue
            break
    if best_params is not None:  # the Adam moments stay those of the last step
        with torch.no_grad():
            for n in free:
                params[n].copy_(best_params[n])
    for k, j in enumerate(idx):
        pending[j] = {n: params[n][k].detach().clone() for n in names}
        pending[j].update(opt.state_of(k))
    final = best_val if best_params is not None else (curve[-1] if curve else float("nan"))
    return it, curve, final


class _FrameAdam:
    """Adam (the torch.optim.Adam update) with per-frame moments and step counts.

    The moments of a frame travel with it from window to window (``SfTSettings.carry_adam``)
    and a frame entering the window inherits those of the frame before it, so a new window
    does not restart every parameter with the lr-sized first steps of a fresh Adam. With
    ``warmup`` N > 0 the learning rate of a frame at its step t is ``lr * min(1, t / N)``
    (``torch.optim.lr_scheduler.LambdaLR`` with that factor): only fresh states ramp.
    """

    B1, B2, EPS = 0.9, 0.999, 1e-8

    def __init__(self, params: dict, names: list[str], lrs: dict, states: list[dict],
                 warmup: int = 0):
        self.params, self.names, self.lrs = params, names, lrs
        self.warmup = int(warmup)
        F = len(states)
        self.m = {n: torch.stack([s.get("_m:" + n, torch.zeros_like(params[n][k]))
                                  for k, s in enumerate(states)]) for n in names}
        self.v = {n: torch.stack([s.get("_v:" + n, torch.zeros_like(params[n][k]))
                                  for k, s in enumerate(states)]) for n in names}
        self.t = torch.tensor([float(s.get("_t", 0)) for s in states], dtype=torch.float64)
        self.t = self.t.reshape(F)

    @torch.no_grad()
    def step(self) -> None:
        self.t += 1.0
        bc1 = 1.0 - self.B1 ** self.t
        bc2 = 1.0 - self.B2 ** self.t
        if self.warmup > 0:  # linear ramp over a fresh state's first steps
            bc1 = bc1 / torch.clamp(self.t / self.warmup, max=1.0)
        for n in self.names:
            p, g = self.params[n], self.params[n].grad
            if g is None:
                continue
            shape = (-1,) + (1,) * (p.ndim - 1)
            m, v = self.m[n], self.v[n]
            m.mul_(self.B1).add_(g, alpha=1.0 - self.B1)
            v.mul_(self.B2).addcmul_(g, g, value=1.0 - self.B2)
            denom = (v.sqrt() / bc2.sqrt().to(p.dtype).view(shape)).add_(self.EPS)
            p.sub_((self.lrs[n] / bc1).to(p.dtype).view(shape) * m / denom)

    def state_of(self, k: int) -> dict:
        """Moments and step count of frame ``k`` of the window (checkpointed with it)."""
        out: dict[str, Any] = {"_t": int(self.t[k])}
        for n in self.names:
            out["_m:" + n] = self.m[n][k].clone()
            out["_v:" + n] = self.v[n][k].clone()
        return out


def reconstruct_window(
    sequence: Sequence | str | os.PathLike,
    frames: list[int],
    settings: SfTSettings | None = None,
    *,
    callback=None,
) -> tuple[np.ndarray, int]:
    """Optimise one window of frames, all starting from the template (no sliding).

    Parameters
    ----------
    sequence : Sequence or path
    frames : list of int
        Frame indices of the window, in order.
    settings : SfTSettings, optional
        ``optimiser.window`` is ignored; ``patience`` and ``max_iterations`` apply.
    callback : callable, optional
        ``callback(iteration, vertices)`` after every step, with ``(F, V, 3)`` float64
        vertices (computed only when given).

    Returns
    -------
    vertices : np.ndarray
        ``(F, V, 3)`` float64 reconstruction (scene units).
    iterations : int
    """
    st = settings or SfTSettings()
    seq = sequence if isinstance(sequence, Sequence) else load_sequence(sequence)
    model, terms, inext = _objective_parts(seq, st)
    targets, masks = _Window(seq, terms).targets(list(frames))
    pending = {j: model.init_params() for j in frames}
    cb = None
    if callback is not None:
        def cb(it, params):
            with torch.no_grad():
                callback(it, model.vertices(params).to(torch.float64).numpy())
    iters, _, _ = _optimize_window(model, terms, inext, st, pending, list(frames), targets,
                                   masks, cb)
    with torch.no_grad():
        p = {n: torch.stack([pending[j][n] for j in frames]) for n in model.init_params()}
        X = model.vertices(p).to(torch.float64).numpy()
    return X, iters
