"""FNOpt benchmark: error against milliseconds per frame, for FNOpt and classical optimisers.

Parts (each writes benchmarks/results/bm_fnopt_<part>.json and a PNG; reference rollouts are
cached in benchmarks/results/fnopt_refs/):

- ``iters``: e_CD / e_3D against ms per frame for FNOpt N in {3, 5, 8, 10, 15, 20} and
  GD / Adam / L-BFGS (plain, and strong-Wolfe ``lbfgs-wolfe``; PCG, DCT-preconditioned descent) over
  their iteration counts, at 32, 64, 100 (Tables 6.6-6.7, Figure 6.10 analogues);
- ``lbfgs``: the equal-error comparison (mean e_3D) of L-BFGS variants against FNOpt N = 10;
- ``ratio``: from the ``iters`` JSONs of ``--ratio-res``: the speed-up of FNOpt over each
  L-BFGS variant at equal error along the whole FNOpt curve (N = 3 ... 20), the L-BFGS time
  interpolated log-log on its Pareto front (:func:`equal_error_speedup`), charted;
- ``hard``: FNOpt-N against PCG with the normal directions over N (``pcg-n``) on the three
  ``general`` cases where FNOpt-10 stays far from the floor (:data:`HARD_CASES`: diagonal,
  mid-edges, random-2), e_CD and e_3D against ms per frame, charted;
- ``--starts K`` (``iters``, ``hard``): every row the median of K rollouts from the first K
  starts of :data:`STARTS` (free vertices moved by 0, 10 nm, ..., 10 um; default 1, the
  unperturbed start alone), each start's figures kept in the row;
- ``reference``: the convergence of the reference over its tolerance;
- ``super``: FNOpt run at 64 against the 32 rollout upsampled bilinearly to 64 (Table 6.4);
- ``general``: speed factors 1.2 / 1.5 / 2, the five handle layouts and seeded random pin sets
  at ``--res`` (Figures 6.6-6.7); the plan entry ``floor:N`` is a sensitivity row: PCG with N
  iterations from an initial state perturbed by 0.1 mm (:data:`FLOOR_PERTURB`); ``floor-ref:0``
  the converged reference itself re-solved from that perturbed start: its error against the
  reference is what the case's physics alone makes of a tiny difference (the physical floor; a
  case whose floor is above 5 cannot separate optimisers by e_CD). ``floors`` in the JSON puts
  each case's FNOpt e_CD beside its floors (:func:`floor_table`);
- ``sweep``: the width/modes sweep (from benchmarks/fnopt_sweep.py's JSON), charted;
- ``stability``: a long FNOpt rollout (``--frames 500 --res 100``): finite and bounded.
- ``fresh``: the ``--plan`` rows on 36 random cases (:func:`fresh_cases`: layouts, motions,
  speeds and materials drawn from one seed, 24 at 64x64 and 12 at 100x100), medians over three
  starts; how FNOpt's default step was chosen (session 19).
- ``validation``: N = 10 rollouts of :data:`VALIDATION_CASES` (never a benchmark case) for
  each of ``--candidates`` (weight paths): how weights are chosen across seeds and settings.

The parts live in ``bm_fnopt_speedup.py`` (``iters``, ``lbfgs``, ``ratio``),
``bm_fnopt_cases.py`` (``general``, ``validation``, the case lists) and this file (``super``,
``stability``, ``reference``, the command line); ``bm_fnopt_common.py`` holds the optimiser rows
and the timed rollout they share. This file re-exports their public names.

All timings are CPU times of one thread on a shared, busy 2-core machine: ``cpu_ms_per_frame``
is the whole rollout's process time per frame (problem set-up, the float64 energy record and
the state update included), ``step_cpu_ms`` the optimiser's own thread time per frame (the
solvers run under ``torch.inference_mode`` where their problem needs no autograd, as in
``polygeo simulate``); every
timed rollout follows one untimed frame of the same optimiser (the process's one-time warm-up,
~0.6 s, is not a per-frame cost).

    python benchmarks/bm_fnopt.py --part iters --res 64 --frames 60
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))     # the split modules beside it

from bm_fnopt_cases import (  # noqa: E402,F401  (re-exported: the tests and scripts use them)
    FRESH_SEED,
    FRESH_STARTS,
    SCREEN_TOL,
    SCREENED_VALIDATION_CASES,
    VALIDATION_CASES,
    _pins,
    chart_general,
    floor_table,
    fresh_cases,
    fresh_summary,
    general_cases,
    merge_general,
    part_fresh,
    part_general,
    part_validation,
    screen_case,
)
from bm_fnopt_common import (  # noqa: E402,F401
    AUTOGRAD,
    EQUAL_ERROR_METRIC,
    FLOOR_PERTURB,
    FNOPT_DEFAULT_ROW,
    LBFGS_NAMED,
    LBFGS_VARIANTS,
    NO_GRADIENT_OPTION,
    OUT,
    PRECONDITIONED,
    RANDOM_LAYOUTS,
    REFS,
    ROOT,
    STARTS,
    THESIS_LBFGS,
    TWO_LEVEL_EVERY,
    _fno_options,
    _loglog_chart,
    _measure,
    _measure_starts,
    _plt,
    _rollout,
    _step,
    chart_iters,
)
from bm_fnopt_speedup import (  # noqa: E402,F401
    HARD_CASES,
    HARD_PLAN,
    _hard_rows,
    chart_fnopt_vs_pcg,
    chart_hard,
    equal_error_speedup,
    merge_iters,
    pareto_front,
    part_hard,
    part_iters,
    part_lbfgs,
    part_ratio,
    ratio_tag,
)

from draping import viz  # noqa: E402
from draping.fnopt import solvers  # noqa: E402
from draping.fnopt.model import load_pretrained  # noqa: E402
from draping.fnopt.simulate import SimSettings, frame_metrics, reference_rollout  # noqa: E402


def part_super(args, net) -> dict:
    s32 = SimSettings(res=(32, 32), motion=args.motion, frames=args.frames, speed=args.speed)
    s64 = SimSettings(res=(64, 64), motion=args.motion, frames=args.frames, speed=args.speed)
    ref = reference_rollout(s64, REFS)
    ro32, _, _ = _rollout(s32, _step("fnopt", 10, net))
    up = torch.nn.functional.interpolate(ro32.positions.permute(0, 3, 1, 2), size=(64, 64),
                                         mode="bilinear", align_corners=True).permute(0, 2, 3, 1)
    ro_up = solvers.Rollout(up, ro32.loss, ro32.ms, ro32.handles)
    m_up = frame_metrics(ro_up, ref, args.every)
    r64 = _measure(s64, _step("fnopt", 10, net), ref, args.every)
    return {"motion": args.motion, "frames": args.frames,
            "fnopt_64": r64, "upsampled_32": {"e_cd": float(np.mean(m_up["e_cd"])),
                                              "e_3d": float(np.mean(m_up["e_3d"]))}}


def part_stability(args, net) -> dict:
    """A long FNOpt rollout (``--frames``, default use 500) at ``--res``: finite and bounded.

    The step is ``polygeo simulate --optimizer fnopt``'s default (:data:`FNOPT_DEFAULT_ROW`).

    Recorded: whether every state is finite, the largest distance of a vertex from the
    handles' centroid (m; the sheet is 1 m wide), the largest edge length over its rest length
    (stretch), the largest per-frame ``L_cloth`` and the CPU ms per frame.
    """
    s = SimSettings(res=(args.res, args.res), handles=args.layout, motion=args.motion,
                    frames=args.frames, speed=args.speed)
    ro, err, cpu = _rollout(s, _step(FNOPT_DEFAULT_ROW, 10, net))
    if ro is None:
        return {"diverged": err, "row": FNOPT_DEFAULT_ROW}
    x = ro.positions
    sheet = s.sheet()
    hmid = ro.handles.mean(1)
    eu = (x[:, :, 1:] - x[:, :, :-1]).norm(dim=-1) / sheet.hx
    ev = (x[:, 1:] - x[:, :-1]).norm(dim=-1) / sheet.hy
    return {"row": FNOPT_DEFAULT_ROW, "res": args.res, "layout": args.layout, "motion": args.motion,
            "speed": args.speed, "frames": args.frames,
            "finite": bool(torch.isfinite(x).all()),
            "max_distance_from_handles_m": float((x - hmid[:, None, None]).norm(dim=-1).max()),
            "max_edge_stretch": float(max(eu.max(), ev.max())),
            "max_L_cloth": float(np.max(ro.loss)), "cpu_ms_per_frame": 1e3 * cpu / s.frames,
            "step_cpu_ms": float(np.mean(ro.cpu_ms))}


def part_reference(args, net) -> dict:
    """Convergence of the reference: rollouts solved to decreasing tolerances, compared.

    For consecutive tolerances: e_CD x 1e3 as in the metrics (point samples, with its sampling
    floor), the floor-free surface Chamfer x 1e3 (``mode="surface"``) and the largest vertex
    distance (m) over the measured frames.
    """
    from draping.fnopt import cloth
    from draping.fnopt.simulate import e_cd
    from polygeo.proximity import chamfer_distance

    tols = [float(t) for t in args.tols.split(",")]
    rec = {"res": args.res, "frames": args.frames, "motion": args.motion, "speed": args.speed,
           "tols_m_s2": tols, "shipped_tol_m_s2": solvers.REFERENCE_TOL, "cpu_s": {},
           "runs": []}
    f = cloth.grid_faces(args.res, args.res).numpy()
    for lay in args.layouts.split(","):
        s = SimSettings(res=(args.res, args.res), handles=lay, motion=args.motion,
                        frames=args.frames, speed=args.speed)
        ros = {}
        for tol in tols:
            t0 = time.process_time()
            ros[tol] = reference_rollout(s, REFS, tol=tol)
            rec["cpu_s"][f"{lay} {tol:g}"] = time.process_time() - t0
        ks = list(range(args.every, args.frames + 1, args.every))
        for t1, t2 in zip(tols, tols[1:]):
            a, b = ros[t1].positions, ros[t2].positions
            cd = [e_cd(a[k], b[k], f, f) for k in ks]
            sd = [1e3 * chamfer_distance(b[k].reshape(-1, 3).numpy(), f,
                                         a[k].reshape(-1, 3).numpy(), f, mode="surface")
                  for k in ks]
            dx = max(float((a[k] - b[k]).norm(dim=-1).max()) for k in ks)
            r = {"layout": lay, "tol": t1, "tighter": t2, "e_cd": float(np.mean(cd)),
                 "e_cd_max": float(np.max(cd)), "surface_cd": float(np.mean(sd)),
                 "surface_cd_max": float(np.max(sd)), "max_vertex_m": dx}
            rec["runs"].append(r)
            print(json.dumps(r), flush=True)
    return rec


def output_tag(args) -> str:
    """The output names' suffix: ``--tag``, else the validation part's ``--case-set`` other than
    ``all`` (``screened``: ``bm_fnopt_validation_<res>_screened``, never the default set's
    ``bm_fnopt_validation_<res>``), else none."""
    if args.tag:
        return args.tag
    return args.case_set if args.part == "validation" and args.case_set != "all" else ""


def main() -> None:
    """The command line: run one ``--part`` and write its JSON (and chart) to ``results/``."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--part", choices=("iters", "super", "general", "sweep", "lbfgs",
                                       "reference", "stability", "ratio", "validation",
                                       "hard", "fresh"),
                    default="iters")
    ap.add_argument("--res", type=int, default=32)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--motion", default="xy")
    ap.add_argument("--speed", type=float, default=1.0)
    ap.add_argument("--every", type=int, default=3, help="metric frame stride")
    ap.add_argument("--only", default="", help="comma-separated optimisers (iters part)")
    ap.add_argument("--counts", default="", help="iters / hard parts: optimiser:iterations "
                    "pairs, comma-separated, replacing the plan")
    ap.add_argument("--starts", type=int, default=1, help="iters / hard parts: each row the "
                    "median of this many starts (STARTS; 1: the unperturbed start only)")
    ap.add_argument("--ratio-row", default=FNOPT_DEFAULT_ROW,
                    help="ratio part: the FNOpt rows compared (default: the default step's, "
                    f"{FNOPT_DEFAULT_ROW}; fnopt: the one-level step)")
    ap.add_argument("--ratio-res", default="32,64", help="ratio part: resolutions whose iters "
                    "JSON is read")
    ap.add_argument("--weights", default=None)
    ap.add_argument("--candidates", default="shipped", help="validation part: comma-separated "
                    "weight paths ('shipped': the package's)")
    ap.add_argument("--cases", default="", help="general part: comma-separated case numbers")
    ap.add_argument("--case-set", choices=("all", "screened"), default="all",
                    help="validation part: VALIDATION_CASES, or SCREENED_VALIDATION_CASES (those "
                    "whose physical floors are <= 1, screen_case)")
    ap.add_argument("--plan", default="fnopt:10,pcg:10,pgd:10,lbfgs:100",
                    help="general part: optimiser:iterations, comma-separated")
    ap.add_argument("--tag", default="", help="suffix of the output names (validation part: "
                    "default the --case-set when not 'all')")
    ap.add_argument("--coarse-res", type=int, default=0, help="validation / general parts: "
                    "run the FNO on the grid whose longer side has this many vertices (0: off)")
    ap.add_argument("--stiffness-res", type=int, default=0, help="validation / general parts: "
                    "the FNO's stiffness numbers at that grid's spacing (0: off)")
    ap.add_argument("--recycle", type=int, default=0, help="validation / general parts: "
                    "carry the span of each solve's last K updates to the next frame's solve "
                    "(solve_fnopt(recycle=K); 0: off)")
    ap.add_argument("--fno-every", type=int, default=1, help="validation / general parts: "
                    "the FNO's proposal on every E-th iteration only, the classical step between "
                    "(solve_fnopt(fno_every=E); 1: every iteration)")
    ap.add_argument("--two-level", type=int, default=0, help="validation / general parts: the "
                    "two-level coarse direction on a grid of K vertices (longer side) in the "
                    "fnopt rows (solve_fnopt(two_level=K); 0: off, the default step)")
    ap.add_argument("--two-level-every", type=int, default=TWO_LEVEL_EVERY,
                    help="validation / general parts: with --two-level, rebuild the coarse "
                    f"space every F frames (default {TWO_LEVEL_EVERY})")
    ap.add_argument("--val-iters", type=int, default=10, help="validation part: FNOpt's "
                    "iterations per step")
    ap.add_argument("--merge", action="store_true", help="general part: replace only the rows "
                    "run now in the existing JSON (same res and frames), keep the others")
    ap.add_argument("--lbfgs-iters", default="20,50,100,150,200,300;20,50,100,150,200,300;"
                    "100,200,300;50,100,150,200,300",
                    help="lbfgs part: iteration counts per variant (';' between variants); each "
                    "variant stops at the first count reaching FNOpt's error")
    ap.add_argument("--layout", default="corners", help="lbfgs part: handle layout")
    ap.add_argument("--variants", default="", help="lbfgs part: comma-separated indices of "
                    "LBFGS_VARIANTS to run (default all)")
    ap.add_argument("--tols", default="5e-3,5e-4,5e-5,5e-6",
                    help="reference part: tolerances (m/s^2), loosest first")
    ap.add_argument("--layouts", default="corners,diagonal,mid-edges,corner-centre,single",
                    help="reference part: layouts")
    args = ap.parse_args()
    torch.set_num_threads(1)
    OUT.mkdir(parents=True, exist_ok=True)
    net = None
    try:
        net = load_pretrained(args.weights)
    except FileNotFoundError:
        print("no FNOpt weights: classical optimisers only")
    if args.part == "sweep":
        rec = json.loads((OUT / "fnopt_sweep.json").read_text())
        curves = {f"w{r['width']} m{r['modes']} ({r['parameters'] // 1000}k)":
                  [h["val_subopt"] for h in r["history"]] for r in rec["runs"]}
        xs = {k: [h["step"] for h in r["history"]] for k, r in zip(curves, rec["runs"])}
        for key, lab in (("pgd_baseline_subopt", "DCT-preconditioned descent (no FNO)"),
                         ("pcg_baseline_subopt", "PCG: the subspace step without the FNO")):
            if key in rec:
                curves[lab] = [rec[key]] * 2
                xs[lab] = [0, rec["steps"]]
        viz.plot_curves(curves, OUT / "bm_fnopt_sweep.png", x=xs, xlabel="training step",
                        ylabel="validation sub-optimality (N=10)", logy=True, markers=True,
                        title="FNOpt width/modes sweep (32x32)")
        return
    rec = {"part": args.part, "args": vars(args), "torch": torch.__version__,
           "note": "CPU times, 1 thread, shared busy 2-core machine"}
    rec.update({"iters": part_iters, "super": part_super, "general": part_general,
                "lbfgs": part_lbfgs, "reference": part_reference,
                "stability": part_stability, "ratio": part_ratio,
                "validation": part_validation, "hard": part_hard,
                "fresh": part_fresh}[args.part](args, net))
    rec.update(machine=platform.processor() or platform.machine(), python=platform.python_version(),
               date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
               load_average=os.getloadavg())
    tag = {"super": "super", "fresh": "fresh", "ratio": ratio_tag(args.ratio_row)}.get(
        args.part, f"{args.part}_{args.res}")
    tag += f"_{output_tag(args)}" if output_tag(args) else ""
    path = OUT / f"bm_fnopt_{tag}.json"
    if args.part == "general" and args.merge and path.is_file():
        rec = merge_general(json.loads(path.read_text()), rec)
    if args.part == "iters" and path.is_file():      # merge with the runs of other invocations
        rec = merge_iters(json.loads(path.read_text()), rec)
    path.write_text(json.dumps(rec, indent=1))
    if args.part in ("iters", "lbfgs"):
        chart_iters(rec, OUT / f"bm_fnopt_{tag}.png")
    if args.part == "iters":
        eq = chart_fnopt_vs_pcg(rec, OUT / f"bm_fnopt_{tag}_pcg.png")
        if eq is not None:
            print(json.dumps({"fnopt_vs_pcg_n": eq}), flush=True)
    elif args.part == "reference":
        lays = list(dict.fromkeys(r["layout"] for r in rec["runs"]))
        curves = {lay: [r["max_vertex_m"] for r in rec["runs"] if r["layout"] == lay]
                  for lay in lays}
        xs = {lay: [r["tol"] for r in rec["runs"] if r["layout"] == lay] for lay in lays}
        curves = {k: [max(v, 1e-7) for v in c] for k, c in curves.items()}
        _loglog_chart(curves, xs, OUT / f"bm_fnopt_{tag}.png",
                      "tolerance (RMS residual, m/s^2)",
                      "max vertex distance to the 10x tighter rollout (m)",
                      f"reference convergence, {args.res}x{args.res}, {args.frames} frames",
                      hline=1e-3)
    elif args.part == "general":
        chart_general(rec, OUT / f"bm_fnopt_{tag}.png")
    elif args.part == "hard":
        chart_hard(rec, OUT / f"bm_fnopt_{tag}.png")

if __name__ == "__main__":
    main()
