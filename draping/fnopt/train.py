"""Meta-training of the FNO optimiser with the data-pool scheme, at 32 x 32 only.

The pool holds sheets *in the middle of their inner optimisation*: a state ``(x, v)``, its
handles and their motion, the current acceleration ``a``, the previous residual and update,
and the inner-iteration count. A training step takes a batch of pool entries, makes
one update with the step used at inference (:func:`draping.fnopt.model.subspace_update`: the
quadratic model minimised over the PCG directions and the FNO's proposal, differentiated
through), and minimises the normalised decrease of ``L_cloth``::

    (L(a + Delta a) - L(a)) / (1/2 sum_i |dL/da_i|^2 / (m_i dt^2))

(-1 is the exact minimiser of the inertia term alone; the denominator makes every state and
iteration count equally), then writes the entries back. An entry whose inner count reaches
its ``N`` advances one backward-Euler step with the model's own acceleration (the pool grows
with the model's own rollouts); entries are re-drawn from random initial states (random sheet
size, material, handles, motion) after their rollout length or when they blow up.

Varying the physical sheet size at a fixed 32 x 32 grid varies the spacing ``h`` and so the
stiffness numbers ``dt^2 k / (rho h^2)`` the FNO sees: a 0.3 m sheet at 32 x 32 has the spacing
of a 1 m sheet at 100 x 100 (training stays at 32 x 32).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict
from functools import partial
from pathlib import Path

import torch

from . import cloth
from .handles import DT, ease
from .model import FNO, FNOConfig, n_parameters, optimizer_step, solve_fnopt, subspace_update
from .settings import HANDLE_DISTRIBUTIONS, TrainSettings
from .solvers import (
    StepProblem,
    laplace_preconditioner,
    make_problem,
    normal_directions,
    normal_preconditioner,
    rollout,
    solve_lbfgs,
    solve_reference,
)
from .tbptt import rollout_train_step
from .train_proposal import proposal_train_step
from .twolevel import coarse_correction, galerkin_space

__all__ = ["TrainSettings", "HANDLE_DISTRIBUTIONS", "random_handles", "folding_pair", "Pool",
           "train", "initial_weights", "validation_set", "evaluate", "coarse_directions"]


def _uniform(gen: torch.Generator) -> float:
    """One uniform draw in ``[0, 1)`` from ``gen`` (the handle distributions' coin)."""
    return float(torch.rand(1, generator=gen))


def random_handles(gen: torch.Generator, res: int, kind: str = "random") -> torch.Tensor:
    """A random set of pinned vertices ``(K, 2)`` (row, col) on a ``res x res`` grid.

    ``"random"``: the two top corners with probability 0.15; else 1 to 4 handles, each a grid
    corner (35 %), a point on a random boundary edge (35 %) or an interior point (30 %), and
    with probability 0.1 one of them grown into a run of 2 to ``res / 4`` vertices along its
    row or column; so the five named layouts are ordinary members of the distribution.
    ``"corners-interior"`` (the first shipped weights): the two top corners with probability
    0.4, else 1 to 3 uniform points. ``"folding"``: with probability 0.5 a two-pin set that folds
    the sheet between its pins (:func:`folding_pair`: opposite corners, points on opposite
    edges, or two points at least half the grid apart), else a ``"random"`` draw.

    Raises
    ------
    ValueError
        On an unknown ``kind``.
    """
    if kind not in HANDLE_DISTRIBUTIONS:
        raise ValueError(f"handles: expected one of {list(HANDLE_DISTRIBUTIONS)}, got {kind!r}")

    u = partial(_uniform, gen)
    m = res - 1
    if kind == "folding":
        if u() < 0.5:
            return folding_pair(gen, res)
        kind = "random"
    if kind == "corners-interior":
        if u() < 0.4:
            pts = [(0, 0), (0, m)]
        else:
            pts = [(round(u() * m), round(u() * m)) for _ in range(1 + int(u() * 3))]
        return torch.unique(torch.tensor(pts), dim=0)
    if u() < 0.15:
        return torch.tensor([[0, 0], [0, m]])
    pts = []
    for _ in range(1 + int(u() * 4)):
        v = u()
        if v < 0.35:
            pts.append((m * int(u() < 0.5), m * int(u() < 0.5)))
        elif v < 0.7:
            t, side = round(u() * m), int(u() * 4)
            pts.append(((0, t), (m, t), (t, 0), (t, m))[side])
        else:
            pts.append((round(u() * m), round(u() * m)))
    if u() < 0.1:
        r0, c0 = pts[0]
        n = 2 + int(u() * max(res // 4 - 1, 1))
        along_row = u() < 0.5
        for k in range(1, n):
            rr, cc = (r0, c0 + k) if along_row else (r0 + k, c0)
            if rr <= m and cc <= m:
                pts.append((rr, cc))
    return torch.unique(torch.tensor(pts), dim=0)


def folding_pair(gen: torch.Generator, res: int) -> torch.Tensor:
    """Two pinned vertices ``(2, 2)`` (row, col) far apart on a ``res x res`` grid.

    The layouts on which a sheet folds between its pins and an ``N = 10`` solve lags (the
    diagonal, mid-edges and 2-pin random cases of ``bm_fnopt``): with equal probability two
    opposite corners, one point on each of two opposite edges (each at 20-80 % along its edge,
    mid-edges among them), or two uniform grid points at least ``(res - 1) / 2`` apart
    (Chebyshev distance; the last of 20 draws if none is).

    Raises
    ------
    ValueError
        If ``res < 2``.
    """
    if res < 2:
        raise ValueError(f"res: expected >= 2, got {res!r}")

    u = partial(_uniform, gen)
    m = res - 1
    v = u()
    if v < 1 / 3:
        pts = [(0, 0), (m, m)] if u() < 0.5 else [(0, m), (m, 0)]
    elif v < 2 / 3:
        t1, t2 = (round((0.2 + 0.6 * u()) * m) for _ in range(2))
        pts = [(t1, 0), (t2, m)] if u() < 0.5 else [(0, t1), (m, t2)]
    else:
        for _ in range(20):
            pts = [(round(u() * m), round(u() * m)) for _ in range(2)]
            if max(abs(pts[0][0] - pts[1][0]), abs(pts[0][1] - pts[1][1])) >= m / 2:
                break
    return torch.unique(torch.tensor(pts), dim=0)


class Pool:
    """The data pool (all tensors ``(P, ...)`` at ``res x res``)."""

    def __init__(self, s: TrainSettings, gen: torch.Generator):
        self.s = s
        self.gen = gen
        n, r = s.pool, s.res
        self.x = torch.zeros(n, r, r, 3)
        self.v = torch.zeros(n, r, r, 3)
        self.a = torch.zeros(n, r, r, 3)
        self.r_prev = torch.zeros(n, r, r, 3)
        self.da = torch.zeros(n, r, r, 3)
        self.hmask = torch.zeros(n, r, r)
        self.hrest = torch.zeros(n, r, r, 3)
        self.kind = torch.zeros(n, dtype=torch.int64)       # 0 translate, 1 rotate
        self.vec = torch.zeros(n, 3)                        # displacement (m) or axis*angle
        self.duration = torch.ones(n)
        self.t = torch.zeros(n)
        self.size = torch.ones(n)
        self.it = torch.zeros(n, dtype=torch.int64)
        self.n_inner = torch.zeros(n, dtype=torch.int64)
        self.frame = torch.zeros(n, dtype=torch.int64)
        self.max_frame = torch.zeros(n, dtype=torch.int64)
        self.mat = {k: torch.zeros(n) for k in ("stretch", "shear", "bend", "density",
                                                "damping")}
        self.coarse_kept: dict = {}  # two-level spaces per entry (coarse_directions), not saved
        for i in range(n):
            self.reset(i)

    def _u(self, *shape) -> torch.Tensor:
        return torch.rand(*shape, generator=self.gen)

    def settle(self, ids: torch.Tensor, x: torch.Tensor, v: torch.Tensor, frames: int,
               ok: torch.Tensor) -> None:
        """Entries ``ids`` continue from ``x``, ``v`` ``(B, r, r, 3)`` after ``frames`` frames.

        An entry is re-drawn (:meth:`reset`) where ``ok`` ``(B,)`` is false, where it blew up
        (non-finite, or a speed above 50 m/s) or where it reached its length.
        """
        self.x[ids], self.v[ids] = x, v
        self.t[ids] += frames * DT
        self.frame[ids] += frames
        for j, i in enumerate(ids.tolist()):
            bad = not bool(ok[j]) or not bool(torch.isfinite(self.x[i]).all()) or \
                float(self.v[i].abs().max()) > 50.0
            if bad or self.frame[i] >= self.max_frame[i]:
                self.reset(i)

    def reset(self, i: int) -> None:
        """Draw entry ``i`` afresh: a sheet at rest, random material, handles and motion."""
        s, r = self.s, self.s.res
        size = math.exp(math.log(s.size_min) + float(self._u(1)) * math.log(
            s.size_max / s.size_min))
        sheet = cloth.Sheet(r, r, size)
        orient = "vertical" if float(self._u(1)) < 0.7 else "horizontal"
        x = cloth.rest_positions(sheet, orient)
        # a random smooth initial perturbation (low modes), up to a few % of the size
        if float(self._u(1)) < 0.5:
            uu = torch.linspace(0, math.pi, r)
            k1, k2 = int(self._u(1) * 3) + 1, int(self._u(1) * 3) + 1
            bump = torch.sin(k1 * uu)[:, None] * torch.sin(k2 * uu)[None, :]
            nrm = torch.tensor([0.0, 1.0, 0.0]) if orient == "vertical" else \
                torch.tensor([0.0, 0.0, 1.0])
            x = x + 0.05 * size * (2 * self._u(1) - 1) * bump[..., None] * nrm
        idx = random_handles(self.gen, r, s.handles)
        self.hmask[i] = cloth.handle_mask(idx, r, r)
        self.hrest[i] = x * self.hmask[i][..., None]
        self.x[i] = x
        self.v[i] = 0.0
        self.kind[i] = int(self._u(1) < 0.3)
        if self.kind[i] == 0:
            d = torch.randn(3, generator=self.gen)
            self.vec[i] = d / d.norm() * size * 0.6 * self._u(1)
        else:
            axes = torch.eye(3)
            ax = axes[2] if float(self._u(1)) < 0.5 else axes[1]
            if s.handles in ("random", "folding") and float(self._u(1)) < 0.4:   # any axis
                ax = torch.randn(3, generator=self.gen)
                ax = ax / ax.norm()
            self.vec[i] = ax * (2 * self._u(1) - 1) * 0.5 * math.pi
        speed = math.exp(math.log(0.5) + float(self._u(1)) * math.log(2.5 / 0.5))
        self.duration[i] = 2.0 / speed
        self.t[i] = -0.5 * float(self._u(1))
        self.size[i] = size
        m = cloth.sample_materials(1, self.gen)
        for k in self.mat:
            self.mat[k][i] = m[k][0]
        self.max_frame[i] = int(30 + self._u(1) * (s.max_frames - 30))
        self.frame[i] = 0
        self._reset_inner(i)

    def _reset_inner(self, i) -> None:
        self.a[i] = 0.0
        self.r_prev[i] = 0.0
        self.da[i] = 0.0
        self.it[i] = 0
        self.n_inner[i] = int(self.s.inner_min + self._u(1) * (self.s.inner_max -
                                                                self.s.inner_min + 1))

    def targets(self, ids: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """Handle target grids ``(B, r, r, 3)`` at times ``t`` ``(B,)`` (0 off the handles)."""
        out = []
        for j, i in enumerate(ids.tolist()):
            hm = self.hmask[i][..., None]
            rest = self.hrest[i]
            e = float(ease(float(t[j]), float(self.duration[i])))
            if self.kind[i] == 0:
                out.append((rest + e * self.vec[i]) * hm)
            else:
                c = rest.sum((0, 1)) / self.hmask[i].sum()
                ang = self.vec[i].norm() * e
                k = self.vec[i] / self.vec[i].norm().clamp(min=1e-12)
                p = rest - c
                cr, sr = math.cos(float(ang)), math.sin(float(ang))
                rot = p * cr + torch.cross(k.expand_as(p), p, dim=-1) * sr + \
                    k * (p @ k)[..., None] * (1 - cr)
                out.append((c + rot) * hm)
        return torch.stack(out)

    def problem(self, ids: torch.Tensor, dtype=torch.float32, state=None,
                analytic_hvp: bool = False) -> tuple[StepProblem, torch.Tensor]:
        """The step problems of entries ``ids`` and their handle target grids.

        ``state``: ``(x, v, t)`` (``(B, r, r, 3)`` m, m/s; ``(B,)`` s) to start from instead of
        the entries' stored ones (a graph they carry is kept; the rollout fine-tuning of
        :mod:`draping.fnopt.tbptt`). ``analytic_hvp``: closed-form Hessian products (default
        off: autograd's, the shipped weights' own arithmetic, bit for bit).
        """
        r = self.s.res
        x, v, t = (self.x[ids], self.v[ids], self.t[ids]) if state is None else state
        x, v = x.to(dtype), v.to(dtype)
        target = self.targets(ids, t + DT).to(dtype)
        hm = self.hmask[ids].to(dtype)
        h = (self.size[ids] / (r - 1)).to(dtype)
        mat = {k: m[ids].to(dtype) for k, m in self.mat.items()}
        mass = cloth.vertex_mass(r, r, h, h, mat["density"], dtype)
        free = (1.0 - hm)[..., None]
        a_fixed = ((target - x) / DT - v) / DT * hm[..., None]
        return StepProblem(x, v, h, h, mat, DT, free, a_fixed, mass,
                           analytic_hvp=analytic_hvp), target


def _lr(s: TrainSettings, step: int) -> float:
    c = 0.5 * (1 + math.cos(math.pi * min(step / max(s.steps, 1), 1.0)))
    return s.lr_final + (s.lr - s.lr_final) * c


def _rollout_lr(s: TrainSettings, step: int) -> float:
    """The fine-tuning phase's rate at its ``step``: cosine from ``rollout_lr`` to a tenth."""
    c = 0.5 * (1 + math.cos(math.pi * min(step / max(s.rollout_steps, 1), 1.0)))
    return s.rollout_lr * (0.1 + 0.9 * c)


def initial_weights(s: TrainSettings, model: FNO) -> None:
    """Load ``s.init`` (``"shipped"``: the package's weights; a path) into ``model``.

    Raises
    ------
    ValueError
        If the weights' config (their JSON record) is not ``model``'s.
    FileNotFoundError
        If the weights or their record are missing.
    """
    from .model import load_pretrained

    src = load_pretrained(None if s.init == "shipped" else s.init)
    if src.config != model.config:
        raise ValueError(f"init: weights of config {src.config} do not fit the settings' "
                         f"config {model.config}")
    model.load_state_dict(src.state_dict())


def coarse_directions(pool: Pool, ids: torch.Tensor, g: torch.Tensor, k: int) -> list:
    """``[-P A_c^-1 P^T g]``: the two-level direction of pool entries ``ids`` (a list of one).

    ``g``: their gradients ``(B, r, r, 3)``. Each entry's Galerkin space
    (:func:`draping.fnopt.twolevel.galerkin_space`, grid of ``k`` vertices a side) is built at
    ``a = 0`` of its current frame from its own step problem (closed-form products, one sheet
    at a time, so it does not depend on the batch) and kept in ``pool.coarse_kept`` while the
    entry stays on that frame (keyed by its time, size and duration); the kept spaces are not
    checkpointed, and rebuilding one gives the same space (it depends on the frame's state
    only). A sheet whose operator does not factor (a state far from any drape, the shift of
    :func:`draping.fnopt.twolevel._factor` not enough) gets a zero direction on that frame
    (the subspace step gives it no weight) instead of stopping the run. Returns
    ``(B, r, r, 3)`` in ``g``'s dtype, zero at handles.
    """
    kept = pool.coarse_kept
    out = []
    for j, i in enumerate(ids.tolist()):
        key = (float(pool.t[i]), float(pool.size[i]), float(pool.duration[i]), k)
        if i not in kept or kept[i][0] != key:
            pi, _ = pool.problem(torch.tensor([i]), analytic_hvp=True)
            _, _, hvp = pi.grad_hvp(torch.zeros_like(pi.x_prev))
            try:
                kept[i] = (key, galerkin_space(pi, hvp, k))
            except ValueError:
                kept[i] = (key, None)
        space = kept[i][1]
        out.append(torch.zeros_like(g[j:j + 1]) if space is None else
                   coarse_correction(space, g[j:j + 1]))
    return [-torch.cat(out)]


def train_step(model: FNO, opt, pool: Pool, s: TrainSettings, step: int) -> float:
    """One meta-training step on a random batch of the pool; returns the mean loss."""
    ids = torch.randperm(s.pool, generator=pool.gen)[:s.batch]
    p, target = pool.problem(ids)
    a = pool.a[ids]
    pre = laplace_preconditioner(p)
    _, g, hvp = p.grad_hvp(a)
    z = pre(g) * p.free
    zn = normal_directions(p, g, normal_preconditioner(p), s.normal_split) if s.normal \
        else None
    if s.two_level:
        zn = (zn or []) + coarse_directions(pool, ids, g, s.two_level)
    da = subspace_update(model, p, g, hvp, z, pool.r_prev[ids], pool.da[ids],
                         create_graph=True, zn=zn)[0]
    a_new = a + da
    p64, _ = pool.problem(ids, torch.float64)
    with torch.no_grad():
        l0 = p64.loss(a.double())
    l1 = p64.loss(a_new.double())
    # the decrease the metric's exact Newton step would give on a quadratic
    denom = 0.5 * (g.double() * z.double()).sum((1, 2, 3)).clamp(min=1e-30)
    q = (l1 - l0) / denom
    ok = torch.isfinite(q)
    q = torch.where(ok, q, torch.zeros_like(q))
    # a blown-up update still has a gradient, but a logarithmic one
    term = torch.where(q > 0, torch.log1p(q.clamp(min=0)), q)
    if s.iter_weight > 0:           # the late iterations (the N = 10 iterate) weigh more
        w = 1.0 + s.iter_weight * pool.it[ids].double() / 10.0
        loss = (w * term).sum() / (w * ok).sum().clamp(min=1.0)
    else:
        loss = term.sum() / max(int(ok.sum()), 1)
    optimizer_step(model, opt, loss, _lr(s, step))
    with torch.no_grad():
        pool.a[ids] = a_new.detach().float()
        pool.r_prev[ids] = z.detach()
        pool.da[ids] = da.detach().float()
        pool.it[ids] += 1
        for j in torch.nonzero(~ok | (q.detach() > 1.0))[:, 0].tolist():
            pool._reset_inner(int(ids[j]))      # worse than doing nothing: start the step again
        done = ids[pool.it[ids] >= pool.n_inner[ids]]
        if done.numel():
            k = torch.nonzero(pool.it[ids] >= pool.n_inner[ids])[:, 0]
            a_full = pool.a[done] * p.free[k] + p.a_fixed[k]
            v_new = pool.v[done] + DT * a_full
            x_new = pool.x[done] + DT * v_new
            hm = pool.hmask[done][..., None]
            x_new = x_new * (1 - hm) + target[k] * hm
            pool.x[done], pool.v[done] = x_new, v_new
            pool.t[done] += DT
            pool.frame[done] += 1
            for i in done.tolist():
                bad = not bool(torch.isfinite(pool.x[i]).all()) or \
                    float(pool.v[i].abs().max()) > 50.0
                if bad or pool.frame[i] >= pool.max_frame[i]:
                    pool.reset(i)
                else:
                    pool._reset_inner(i)
        if float(torch.rand(1, generator=pool.gen)) < s.reset_prob:
            pool.reset(int(torch.randint(s.pool, (1,), generator=pool.gen)))
    return float(loss.detach())


def validation_set(res: int = 32, frames: int = 20) -> list[dict]:
    """Fixed validation steps, each with its reference minimiser ``L*``.

    States of reference rollouts: 1 m and 0.4 m sheets, four layout/motion pairs, four
    materials, two frames each.
    """
    cases = [("corners", "xy", cloth.Material(300, 10, 1), 1.0),
             ("diagonal", "rot-a", cloth.Material(800, 50, 0.05), 1.0),
             ("mid-edges", "z", cloth.Material(150, 3, 5.0), 0.4),
             ("single", "xyz", cloth.Material(500, 20, 0.3), 0.4)]
    out = []
    for layout, motion, mat, size in cases:
        sheet = cloth.Sheet(res, res, size)
        ro = rollout(sheet, mat, layout, motion, frames,
                     lambda p, a0: solve_lbfgs(p, 60, line_search=True), speed=1.5)
        idx = cloth.handle_indices(layout, res, res)
        for f in (frames // 2, frames - 1):
            x = ro.positions[f][None]
            v = (ro.positions[f] - ro.positions[f - 1])[None] / DT
            tgt = ro.positions[f + 1][None][:, idx[:, 0], idx[:, 1]]
            p = make_problem(x, v, idx, tgt, sheet.hx, sheet.hy, mat.tensors(1), DT)
            a_star = solve_reference(p, None)
            p64 = make_problem(x.double(), v.double(), idx, tgt.double(), sheet.hx, sheet.hy,
                               mat.tensors(1, torch.float64), DT)
            out.append({"problem": p, "p64": p64,
                        "l_star": float(p64.loss(a_star.double())[0]),
                        "l_zero": float(p64.loss(torch.zeros_like(x).double())[0])})
    return out


def evaluate(model: FNO, val: list[dict], iters: int = 10, fno_every: int = 1,
             two_level: int = 0) -> float:
    """Mean relative sub-optimality ``(L(a_N) - L*) / (L(0) - L*)`` over the validation set.

    ``iters``, ``fno_every``, ``two_level``: the solve's
    (:func:`draping.fnopt.model.solve_fnopt`; ``two_level`` built for each step).
    """
    errs = []
    for c in val:
        a = solve_fnopt(model, c["problem"], iters, fno_every=fno_every, two_level=two_level)
        l_n = float(c["p64"].loss(a.double())[0])
        errs.append(max(l_n - c["l_star"], 0.0) / max(c["l_zero"] - c["l_star"], 1e-30))
    return float(sum(errs) / len(errs))


def train(s: TrainSettings, out_dir: str | Path, quiet: bool = False,
          max_minutes: float | None = None, log=print, val: list | None = None) -> dict:
    """Train (or resume) in ``out_dir``; returns a summary (see ``polygeo train-fnopt``).

    ``val``: the :func:`validation_set` (computed here when not given; a sweep passes one).
    """
    from polygeo import runs

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    gen = torch.Generator().manual_seed(s.seed)
    cfg = FNOConfig(s.width, s.modes, s.layers, s.projection, s.normal, s.normal_split)
    with torch.random.fork_rng(devices=[]):     # seeded initial weights; the caller's global
        torch.manual_seed(s.seed)               # RNG state is restored (nothing else draws
        model = FNO(cfg)                        # from it: the pool has its own generator)
    if s.init:
        initial_weights(s, model)
    opt = torch.optim.Adam(model.parameters(), lr=s.lr)
    opt2 = torch.optim.Adam(model.parameters(), lr=s.rollout_lr)    # the fine-tuning phase's
    total = s.steps + s.rollout_steps
    fp = runs.fingerprint(asdict(s))
    ck = runs.resume_state(out, fp)
    history: list = []
    elapsed = 0.0
    cpu_elapsed = 0.0
    if ck is None:
        pool = Pool(s, gen)
        step = 0
        runs.truncate_jsonl(out / "log.jsonl", lambda r: False)  # a run never checkpointed
    else:
        model.load_state_dict(ck.tensors["model"])
        opt.load_state_dict(ck.tensors["opt"])
        opt2.load_state_dict(ck.tensors["opt2"])
        pool = Pool.__new__(Pool)
        pool.s, pool.gen, pool.coarse_kept = s, gen, {}
        for k, v in ck.tensors["pool"].items():
            setattr(pool, k, v if k != "mat" else dict(v))
        gen.set_state(ck.tensors["gen"])
        step, history, elapsed = ck.meta["step"], ck.meta["history"], ck.meta["elapsed"]
        cpu_elapsed = ck.meta.get("cpu_elapsed", 0.0)
        # records of steps after the checkpoint (a run stopped between two) are done again
        runs.truncate_jsonl(out / "log.jsonl", lambda r: r.get("step", 0) <= step)
        log(f"resumed at step {step} ({elapsed / 60:.1f} min so far)")
    t_val = time.perf_counter()
    val = validation_set(s.res) if val is None else val
    log(f"validation set: {len(val)} steps ({time.perf_counter() - t_val:.0f} s); "
        f"model {n_parameters(model)} parameters")
    jlog = runs.JsonlLog(out / "log.jsonl")
    bar = runs.progress(total=total, initial=step, desc="train-fnopt", quiet=quiet)
    t0 = time.perf_counter() - elapsed
    c0 = time.process_time() - cpu_elapsed
    ema = None
    # the validation solve: N = 10, the FNO every iteration; the first-iteration role's own
    n_role = 1 + s.proposal_iters
    eval_solve = (n_role, n_role) if s.proposal_iters else ()
    pool_keys = ("x", "v", "a", "r_prev", "da", "hmask", "hrest", "kind", "vec",
                 "duration", "t", "size", "it", "n_inner", "frame", "max_frame", "mat")

    def save():
        runs.save_checkpoint(out / runs.CHECKPOINT_NAME, {
            "model": model.state_dict(), "opt": opt.state_dict(), "opt2": opt2.state_dict(),
            "pool": {k: getattr(pool, k) for k in pool_keys},
            "gen": gen.get_state()},
            {"fingerprint": fp, "step": step, "history": history,
             "elapsed": time.perf_counter() - t0, "cpu_elapsed": time.process_time() - c0,
             "settings": asdict(s)})

    stopped = False
    while step < total:
        if step < s.steps and s.proposal_iters:     # the first-iteration role
            loss = proposal_train_step(model, opt, pool, s.proposal_iters, s.proposal_extra,
                                       s.batch, _lr(s, step), s.reset_prob)
        elif step < s.steps:
            loss = train_step(model, opt, pool, s, step)
        else:                           # the rollout-level fine-tuning (rollout_steps > 0)
            if step == s.steps:
                ema = None              # another loss: its average starts afresh
            loss = rollout_train_step(model, opt2, pool, s.rollout_frames, s.rollout_iters,
                                      s.rollout_batch, s.rollout_extra,
                                      _rollout_lr(s, step - s.steps))
        step += 1
        ema = loss if ema is None else 0.98 * ema + 0.02 * loss
        bar.update(1)
        if step % 50 == 0:
            bar.set_postfix(loss=f"{ema:.3f}")
        if step % s.eval_every == 0 or step == total:
            v = evaluate(model, val, *eval_solve) if eval_solve else \
                evaluate(model, val, two_level=s.two_level) if s.two_level else \
                evaluate(model, val)
            rec = {"step": step, "phase": "pool" if step <= s.steps else "rollout",
                   "loss_ema": ema, "val_subopt": v,
                   "minutes": (time.perf_counter() - t0) / 60,
                   "cpu_minutes": (time.process_time() - c0) / 60}
            history.append(rec)
            jlog.append(rec)
            log(f"step {step}: loss {ema:.4f}  validation sub-optimality (N=10) {v:.4f}")
        if step % s.checkpoint_every == 0 or step == total:
            save()
        if max_minutes is not None and (time.perf_counter() - t0) > 60 * max_minutes:
            save()
            stopped = True
            log(f"stopped at step {step} after {max_minutes} min (resume to continue)")
            break
    bar.close()
    jlog.close()
    minutes = (time.perf_counter() - t0) / 60
    cpu_minutes = (time.process_time() - c0) / 60
    torch.save(model.state_dict(), out / "model.pt")
    return {"settings": asdict(s), "step": step, "minutes": minutes,
            "cpu_minutes": cpu_minutes, "history": history,
            "parameters": n_parameters(model), "finished": not stopped,
            "val_subopt": history[-1]["val_subopt"] if history else None, "model": model}
