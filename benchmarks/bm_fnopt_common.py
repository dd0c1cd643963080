"""Shared parts of the FNOpt benchmark (``bm_fnopt.py``): paths, optimiser rows, timed rollouts.

``_step`` builds an optimiser row by name, ``_measure`` times one rollout (after an untimed
warm-up frame) and scores it against the reference; the named L-BFGS variants and the
constants the parts share live here; charts common to several parts at the end.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from draping.fnopt import solvers
from draping.fnopt.model import solve_fnopt
from draping.fnopt.settings import COARSE_EVERY
from draping.fnopt.simulate import DEFAULT_LR, SimSettings, frame_metrics
from draping.viz import plot_curves

ROOT = Path(__file__).resolve().parents[1]
OUT = Path(__file__).resolve().parent / "results"
REFS = OUT / "fnopt_refs"


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


#: Unseen layouts of the ``general`` part: fractional (row, col) pins drawn once from a seeded
#: generator of its own (the training pool draws grid vertices from ``torch`` seed 0).
RANDOM_LAYOUTS = {
    f"random-{k}": [tuple(round(float(v), 3) for v in pt)
                    for pt in np.random.default_rng(2026 + k).random((n, 2))]
    for k, n in ((1, 3), (2, 2), (3, 4))}

#: L-BFGS variants of the ``lbfgs`` part: (label, optimiser, keyword arguments). The fair
#: baseline is PyTorch's L-BFGS with a strong-Wolfe line search (``solve_lbfgs_wolfe``).
LBFGS_VARIANTS = (("lbfgs m10 strong-Wolfe", "lbfgs-wolfe", {"history": 10}),
                  ("lbfgs m20 strong-Wolfe", "lbfgs-wolfe", {"history": 20}),
                  ("lbfgs m5 step 1", "lbfgs", {"history": 5}),
                  ("lbfgs m10 strong-Wolfe float64", "lbfgs-wolfe",
                   {"history": 10, "float64": True}))

#: Further L-BFGS variants of the ``iters`` part by name: (optimiser, keyword arguments).
#: ``lbfgs-wolfe64``: PyTorch's strong-Wolfe L-BFGS solved in float64; ``lbfgs-m10`` /
#: ``lbfgs-m20``: ours (unit step) with a longer memory; ``lbfgs-pre``: ours with Armijo line
#: search and the DCT grid-Laplacian initial inverse Hessian (the reference's algorithm, cut at N
#: iterations: L-BFGS given the preconditioner FNOpt uses).
LBFGS_NAMED = {
    "lbfgs-wolfe64": (solvers.solve_lbfgs_wolfe, {"history": 10, "float64": True}),
    "lbfgs-m10": (solvers.solve_lbfgs, {"history": 10}),
    "lbfgs-m20": (solvers.solve_lbfgs, {"history": 20}),
    "lbfgs-pre": (solvers.solve_lbfgs, {"history": 20, "line_search": True,
                                        "precondition": 0.5}),
}

#: The L-BFGS variants given the DCT preconditioner FNOpt itself uses.
PRECONDITIONED = ("lbfgs-pre",)

#: The thesis' L-BFGS (section 6.3: "standard two-loop recursion", "a fixed step size", "a
#: history size of m = 5", N iterations per time step, no line search, no stopping rule): our
#: ``solve_lbfgs(p, n, history=5, step=1.0)``, the ``lbfgs`` rows (run in the mass-scaled
#: variable, where the unit step is exact for the inertia term). The ratio part labels it
#: beside the strongest variant.
THESIS_LBFGS = "lbfgs"

#: Suffix of the classical rows solved with autograd's gradients (``lbfgs-autograd``, ...);
#: the rows without it get the fused closed-form gradient (``fused_grad``) since session 12.
AUTOGRAD = "-autograd"

#: The rows without a gradient option, so without an ``-autograd`` variant: FNOpt and the
#: DCT-metric methods take the step problem's own gradient and Hessian products.
NO_GRADIENT_OPTION = ("fnopt", "fnopt-line", "pgd", "pcg", "pcg-n", "pcg-nc", "fnopt-nc",
                      "fnopt-nc1", "fnopt-nc4", "fnopt-2l")

#: The two-level row ``pcg-nc``: ``pcg-n`` plus the Galerkin coarse correction on a grid of
#: this many vertices (longer side), rebuilt every :data:`TWO_LEVEL_EVERY` frames; ``fnopt-nc``:
#: FNOpt with the same direction (``solve_fnopt(two_level=...)``, the shipped weights), and
#: ``fnopt-nc1`` / ``fnopt-nc4`` the same rebuilt every frame / every 4 frames (session 18: both
#: meet e_CD <= 5 on the hard trio at N = 10; every 8 frames does not).
TWO_LEVEL_COARSE = 16
TWO_LEVEL_EVERY = COARSE_EVERY      # ``polygeo simulate --coarse``'s default rebuild period
#: The rebuild period of each FNOpt two-level row.
FNOPT_TWO_LEVEL_ROWS = {"fnopt-nc": TWO_LEVEL_EVERY, "fnopt-nc1": 1, "fnopt-nc4": 4}
#: ``polygeo simulate --optimizer fnopt``'s default step since session 19 (the options of a
#: default ``SimSettings``: the ``fnopt-nc4`` direction joining from inner iteration
#: ``FNOPT_COARSE_FROM`` on). The ``fnopt`` rows are the one-level step (``--coarse 0``).
FNOPT_DEFAULT_ROW = "fnopt-2l"

#: "Equal error": the metric compared (mean over the rollout's measured frames). e_3D, not
#: e_CD: e_CD x 1e3 with 10k samples has a sampling floor of about 0.13 that every converged
#: optimiser reaches, so it cannot rank them near convergence.
EQUAL_ERROR_METRIC = "e_3d"


def _fno_options(args) -> dict:
    """``solve_fnopt``'s options from ``--coarse-res`` / ``--stiffness-res`` / ``--recycle`` /
    ``--fno-every`` / ``--two-level`` / ``--two-level-every``."""
    return {"coarse_res": args.coarse_res, "stiffness_res": args.stiffness_res,
            "recycle": args.recycle, "fno_every": args.fno_every,
            "two_level": args.two_level, "two_level_every": args.two_level_every}


def _step(name: str, n: int, net=None, lr=None, fno: dict | None = None, **kw):
    """The optimiser row ``name`` with ``n`` iterations: a ``(problem, a0) -> a`` step.

    The solvers themselves run under ``torch.inference_mode`` where their problem needs no
    autograd (:func:`draping.fnopt.step_problem.autograd_free_call`: FNOpt, PCG / PGD and the
    rows on the fused gradient), as ``polygeo simulate`` runs them; ``<name>-autograd`` rows
    and PyTorch's strong-Wolfe L-BFGS keep autograd.
    """
    # the classical solvers get the fused closed-form gradient FNOpt's inference uses
    # (``fused_grad``, like for like); ``<name>-autograd``: the same with autograd's gradient
    if name.endswith(AUTOGRAD):
        base = name[:-len(AUTOGRAD)]
        if base in NO_GRADIENT_OPTION:
            raise ValueError(f"optimizer: {name!r}: {base} has no autograd variant (its "
                             f"gradient and products come from the step problem itself)")
        return _step(base, n, net, lr, fno, **{**kw, "fused_grad": False})
    if name in FNOPT_TWO_LEVEL_ROWS:  # the fnopt row with its two-level options
        return _step("fnopt", n, net, fno={"two_level": TWO_LEVEL_COARSE,
                                           "two_level_every": FNOPT_TWO_LEVEL_ROWS[name]})
    if name == FNOPT_DEFAULT_ROW:
        return _step("fnopt", n, net, fno=SimSettings().two_level_options())
    if name == "fnopt":
        fno = fno or {}
        memory = {}                 # the recycled basis / coarse space between frames
        return _keeping(lambda p, a0: solve_fnopt(net, p, n, memory=memory, **fno), memory)
    if name == "fnopt-line":
        return lambda p, a0: solve_fnopt(net, p, n, step="line")
    if name == "pgd":
        return lambda p, a0: solvers.solve_pgd(p, n)
    if name == "pcg":
        return lambda p, a0: solvers.solve_pcg(p, n)
    if name == "pcg-n":             # PCG with the classical directions of normal-config weights
        split = net.config.normal_split if net is not None else 0
        return lambda p, a0: solvers.solve_pcg(p, n, normal=True, split=split)
    if name == "pcg-nc":            # pcg-n + the two-level coarse correction (fnopt.twolevel)
        split = net.config.normal_split if net is not None else 0
        coarse = {}                 # the coarse space between frames
        return _keeping(lambda p, a0: solvers.solve_pcg(p, n, normal=True, split=split,
                                                        coarse=TWO_LEVEL_COARSE,
                                                        coarse_every=TWO_LEVEL_EVERY,
                                                        memory=coarse), coarse)
    if name == "lbfgs":
        return lambda p, a0: solvers.solve_lbfgs(p, n, step=lr or 1.0,
                                                 **{"fused_grad": True, **kw})
    if name == "lbfgs-wolfe":
        return lambda p, a0: solvers.solve_lbfgs_wolfe(p, n, **kw)
    if name in LBFGS_NAMED:
        fused = {"fused_grad": True} if LBFGS_NAMED[name][0] is solvers.solve_lbfgs else {}
        kw = {**fused, **LBFGS_NAMED[name][1], **kw}
        return lambda p, a0: LBFGS_NAMED[name][0](p, n, **kw)
    lr = lr if lr is not None else DEFAULT_LR[name]
    return lambda p, a0: solvers.CLASSICAL[name](p, n, lr=lr, **{"fused_grad": True, **kw})


#: Initial perturbation (m) of the ``floor`` rows of the ``general`` part: a 1 m sheet's free
#: vertices moved by 0.1 mm (Gaussian, seeded), then solved by PCG with 40 iterations.
FLOOR_PERTURB = 1e-4


def _rollout(s: SimSettings, step, perturb: float = 0.0, **kw):
    t0 = time.process_time()
    try:
        ro = solvers.rollout(s.sheet(), s.material, s.handles, s.motion, s.frames, step,
                             s.speed, perturb=perturb, **kw)
    except ValueError as exc:          # diverged
        return None, str(exc), time.process_time() - t0
    return ro, None, time.process_time() - t0


def _keeping(step, memory: dict):
    """``step`` with the dict it keeps between frames attached (``step.memory``), so that
    :func:`_measure` can empty it after its untimed warm-up frame."""
    step.memory = memory
    return step


def _measure(s: SimSettings, step, ref, every: int, perturb: float = 0.0, **kw) -> dict:
    # one untimed frame first: the process's one-time warm-up (numba loading its cached
    # kernels, the DFT / DCT matrix caches: ~0.6 s) is no per-frame cost; charged to the first
    # timed row it had inflated FNOpt N = 3 by ~9 ms per frame at 32x32 (60 frames). What the
    # step keeps between frames (``step.memory``: a recycled basis, a coarse space and its age)
    # is emptied after it, so the measured rollout starts as ``polygeo simulate``'s does (until
    # session 19 it did not: the two-level rows were rebuilt one frame out of the CLI's phase)
    _rollout(dataclasses.replace(s, frames=1), step, perturb, **kw)
    if getattr(step, "memory", None) is not None:
        step.memory.clear()
    ro, err, cpu = _rollout(s, step, perturb, **kw)
    if ro is None:
        return {"diverged": err, "cpu_ms_per_frame": 1e3 * cpu / s.frames}
    m = frame_metrics(ro, ref, every)
    return {"e_cd": float(np.mean(m["e_cd"])), "e_3d": float(np.mean(m["e_3d"])),
            "e_cd_last": m["e_cd"][-1], "L_cloth": float(np.mean(ro.loss)),
            "cpu_ms_per_frame": 1e3 * cpu / s.frames,
            "step_cpu_ms": float(np.mean(ro.cpu_ms)), "step_wall_ms": float(np.mean(ro.ms))}


#: Initial perturbations (m) of the free vertices for ``--starts K``: the first ``K`` of these
#: (0: the unperturbed start). A 10-iteration solve amplifies float32 rounding, so one rollout's
#: error is one sample of a spread (session 14: e_3D over these five starts 0.26-0.61e-3 at
#: 32x32 for FNOpt-10); the median of five is the figure the README quotes.
STARTS = (0.0, 1e-8, 1e-7, 1e-6, 1e-5)

#: The per-start fields of a ``--starts`` row, and those whose median the row reports.
START_FIELDS = ("e_cd", "e_3d", "step_cpu_ms")
MEDIAN_FIELDS = ("e_cd", "e_3d", "e_cd_last", "L_cloth", "cpu_ms_per_frame", "step_cpu_ms",
                 "step_wall_ms")


def _measure_starts(s: SimSettings, make_step, ref, every: int, starts: int = 1,
                    perturbs: tuple | None = None) -> dict:
    """:func:`_measure` over the first ``starts`` of :data:`STARTS`, a fresh step each.

    ``perturbs`` (m): these starts instead (``starts`` is then not used, and one start is a
    median of one, not the plain row).

    ``make_step()`` returns a new ``(problem, a0) -> a`` step (an FNOpt row's recycled memory
    must not cross starts). ``starts = 1``: :func:`_measure` of the unperturbed start, the row as
    before. Else each field of :data:`MEDIAN_FIELDS` is the median over the starts (error and
    cost medians taken separately), ``starts`` lists each start's ``perturb_m`` and
    :data:`START_FIELDS`, and a row with a diverged start reports ``diverged`` (how many, the
    first message) instead of medians.

    Raises
    ------
    ValueError
        If ``starts`` is not in 1..len(STARTS).
    """
    if perturbs is None:
        if not 1 <= starts <= len(STARTS):
            raise ValueError(f"starts: expected 1..{len(STARTS)}, got {starts}")
        if starts == 1:
            return _measure(s, make_step(), ref, every)
        perturbs = STARTS[:starts]
    starts = len(perturbs)
    rows = [dict(_measure(s, make_step(), ref, every, pert), perturb_m=pert)
            for pert in perturbs]
    bad = [r for r in rows if "diverged" in r]
    per = [{k: r.get(k) for k in ("perturb_m", *START_FIELDS)} for r in rows]
    if bad:
        return {"diverged": f"{len(bad)} of {starts} starts: {bad[0]['diverged']}",
                "starts": per}
    out = {k: float(np.median([r[k] for r in rows])) for k in MEDIAN_FIELDS}
    return dict(out, statistic=f"median of {starts} starts", starts=per)


def chart_iters(rec: dict, path: Path) -> None:
    curves, xs = {}, {}
    names = sorted({r.get("variant", r["optimizer"]) for r in rec["runs"]})
    for name in names:
        rs = [r for r in rec["runs"] if r.get("variant", r["optimizer"]) == name and "e_cd" in r]
        if rs:
            curves[f"{name} (N={','.join(str(r['iters']) for r in rs)})"] = \
                [r["e_cd"] for r in rs]
            xs[list(curves)[-1]] = [r["cpu_ms_per_frame"] for r in rs]
    _loglog_chart(curves, xs, path, "CPU ms per frame (1 thread, shared machine)",
                  "e_CD x 1e3 vs converged reference",
                  f"{rec['res']}x{rec['res']}, {rec.get('layout', 'corners')}, {rec['motion']}, "
                  f"{rec['frames']} frames",
                  hline=5.0)


def _loglog_chart(curves: dict, xs: dict, path: Path, xlabel: str, ylabel: str, title: str,
                  hline: float | None = None) -> None:
    """Log-log line chart of ``curves[k]`` over ``xs[k]`` (markers, legend), PNG at ``path``."""
    plot_curves(curves, path, xlabel=xlabel, ylabel=ylabel, title=title, logx=True, logy=True,
                x=xs, markers=True, hline=hline)
