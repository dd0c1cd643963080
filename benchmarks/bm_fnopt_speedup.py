"""The FNOpt benchmark's speed parts: iterations against time, L-BFGS at equal error, ratio.

``iters`` (error against ms per frame over iteration counts), ``lbfgs`` (the iterations each
L-BFGS variant needs for FNOpt N = 10's error) and ``ratio`` (the equal-error speed-up along
FNOpt's curve from the ``iters`` JSONs, :func:`equal_error_speedup`) of ``bm_fnopt.py``.
"""

from __future__ import annotations

import json
import math
import time

from bm_fnopt_common import (
    EQUAL_ERROR_METRIC,
    FNOPT_DEFAULT_ROW,
    LBFGS_VARIANTS,
    OUT,
    PRECONDITIONED,
    RANDOM_LAYOUTS,
    REFS,
    THESIS_LBFGS,
    _measure,
    _measure_starts,
    _plt,
    _step,
)

from draping.fnopt import solvers
from draping.fnopt.simulate import SimSettings, reference_rollout


def part_iters(args, net) -> dict:
    res = args.res
    s0 = SimSettings(res=(res, res), handles="corners", motion=args.motion, frames=args.frames,
                     speed=args.speed)
    t0 = time.process_time()
    ref = reference_rollout(s0, REFS)
    rec = {"res": res, "motion": args.motion, "frames": args.frames, "speed": args.speed,
           "starts": args.starts, "reference_cpu_s": time.process_time() - t0,
           "reference_tol_m_s2": solvers.REFERENCE_TOL, "runs": []}
    plan = [("fnopt", n) for n in (3, 5, 8, 10, 15, 20)] + \
        [("pcg", n) for n in (5, 10, 20)] + \
        [("pgd", n) for n in (10, 30)] + \
        [("lbfgs-wolfe", n) for n in (20, 50, 100, 200)] + \
        [("lbfgs", n) for n in (10, 30, 100, 200)] + \
        [("lbfgs-autograd", n) for n in (10, 30, 100, 200)] + \
        [("lbfgs-wolfe64", n) for n in (20, 30, 50, 75, 100, 150, 200)] + \
        [(m, n) for m in ("lbfgs-m10", "lbfgs-m20") for n in (30, 50, 75, 100, 150, 200)] + \
        [("lbfgs-pre", n) for n in (5, 10, 20, 30, 50)] + \
        [("adam", n) for n in (10, 100)] + [("gd", n) for n in (10, 100)]
    if args.counts:
        plan = [(m, int(n)) for m, n in (q.split(":") for q in args.counts.split(","))]
    if args.only:
        plan = [p for p in plan if p[0] in args.only.split(",")]
    for name, n in plan:
        if name.startswith("fnopt") and net is None:
            continue
        r = _measure_starts(s0, lambda name=name, n=n: _step(name, n, net), ref, args.every,
                            args.starts)
        r.update(optimizer=name, iters=n)
        rec["runs"].append(r)
        print(json.dumps(r), flush=True)
    return rec


def merge_iters(old: dict, rec: dict) -> dict:
    """``rec`` (an ``iters`` record) with the rows of ``old`` it did not run again.

    Rows are keyed by (optimizer, iterations), sorted by them; ``old`` counts only when its
    frames, motion, speed and number of starts (``--starts``; 1 when absent) are ``rec``'s
    (else ``rec`` is returned unchanged: single-start rows never mix with medians of several);
    ``merged_from`` records ``old``'s date (the kept rows' own run).
    """
    if (old.get("frames"), old.get("motion"), old.get("speed"), old.get("starts", 1)) != (
            rec["frames"], rec["motion"], rec["speed"], rec.get("starts", 1)):
        return rec
    key = {(r["optimizer"], r["iters"]) for r in rec["runs"]}
    runs = [r for r in old["runs"] if (r["optimizer"], r["iters"]) not in key] + rec["runs"]
    runs.sort(key=lambda r: (r["optimizer"], r["iters"]))
    return dict(rec, runs=runs, merged_from=old.get("merged_from") or old.get("date"))


def chart_fnopt_vs_pcg(rec: dict, path) -> dict | None:
    """FNOpt over N against PCG with the normal directions (``pcg-n``, no FNO) over its N.

    Two panels, e_CD x 1e3 and e_3D against the optimiser's own CPU ms per frame (both timed
    alike: under ``torch.inference_mode``, one thread); the title gives FNOpt's speed-up at
    equal e_3D (:func:`equal_error_speedup`; below 1: PCG reaches FNOpt's error in less time).
    Writes ``path`` (PNG) and returns those speed-ups, or ``None`` without both rows.
    """
    rows = {name: sorted((r for r in rec["runs"] if r["optimizer"] == name and "e_3d" in r),
                         key=lambda r: r["iters"]) for name in ("fnopt", "pcg-n")}
    if not all(rows.values()):
        return None
    sp = equal_error_speedup(rows["fnopt"], rows["pcg-n"])
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), dpi=100)
    for ax, (key, label) in zip(axes, (("e_cd", "mean e_CD x 1e3"), ("e_3d", "mean e_3D"))):
        _fnopt_pcg_panel(ax, plt, rows, key, f"{label} vs converged reference")
    eq = ", ".join(f"N{q['iters']} {q['speedup']:.2f}x" for q in sp if q["bound"] == "=")
    fig.suptitle(f"{rec['res']}x{rec['res']}, corners, {rec['motion']}, {rec['frames']} frames; "
                 f"FNOpt's speed-up over PCG-normal at equal e_3D: {eq or 'none bracketed'}",
                 fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return {"metric": "e_3d", "cost": "step_cpu_ms", "speedup": sp}


def _fnopt_pcg_panel(ax, plt, rows: dict, key: str, ylabel: str) -> None:
    """One log-log panel: ``key`` of the ``fnopt`` and ``pcg-n`` rows (``rows[name]``, sorted
    by N) against the optimiser's CPU ms per frame, each point labelled with its N."""
    for name, lab in (("fnopt", "FNOpt"), ("pcg-n", "PCG + normal directions, no FNO")):
        rs = rows[name]
        ax.plot([r["step_cpu_ms"] for r in rs], [r[key] for r in rs], marker="o", label=lab)
        for r in rs:
            ax.annotate(str(r["iters"]), (r["step_cpu_ms"], r[key]), fontsize=6,
                        xytext=(3, 3), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.xaxis.set_minor_formatter(plt.NullFormatter())
    ax.set_xlabel("optimiser CPU ms per frame (1 thread, inference mode)", fontsize=8)
    ax.set_ylabel(ylabel, fontsize=8)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)


def part_lbfgs(args, net) -> dict:
    """L-BFGS variants over their iteration counts against FNOpt N = 10 (equal error).

    Equal error: the fewest iterations at which a variant's mean e_3D (over the measured
    frames of the same rollout) is <= FNOpt N = 10's; speed-up: the ratio of their CPU
    milliseconds per frame (one thread, timed the same way).
    """
    s0 = SimSettings(res=(args.res, args.res), handles=args.layout, motion=args.motion,
                     frames=args.frames, speed=args.speed)
    ref = reference_rollout(s0, REFS)
    rec = {"res": args.res, "layout": args.layout, "motion": args.motion,
           "frames": args.frames, "speed": args.speed,
           "equal_error_metric": EQUAL_ERROR_METRIC, "runs": []}
    counts = [tuple(int(n) for n in part.split(",")) for part in args.lbfgs_iters.split(";")]
    plan = [("fnopt", "fnopt N", {}, (10,))] + \
        [(name, lab, kw, its) for (lab, name, kw), its in zip(LBFGS_VARIANTS, counts)]
    if args.variants:
        keep = {LBFGS_VARIANTS[int(i)][0] for i in args.variants.split(",")}
        plan = plan[:1] + [q for q in plan[1:] if q[1] in keep]
    fn = None
    for name, lab, kw, its in plan:
        for n in its:
            r = _measure(s0, _step(name, n, net, **kw), ref, args.every)
            r.update(optimizer=name, variant=lab, iters=n)
            rec["runs"].append(r)
            print(json.dumps(r), flush=True)
            if name == "fnopt":
                fn = r
            elif "e_3d" in r and r[EQUAL_ERROR_METRIC] <= fn[EQUAL_ERROR_METRIC]:
                break                   # reached: more iterations only cost time
    rec["equal_error"] = []
    for lab in [q[1] for q in plan[1:]]:
        rs = [r for r in rec["runs"] if r.get("variant") == lab and "e_cd" in r]
        hit = next((r for r in rs if r[EQUAL_ERROR_METRIC] <= fn[EQUAL_ERROR_METRIC]), None)
        rec["equal_error"].append({
            "variant": lab, "fnopt_e_3d": fn["e_3d"], "fnopt_e_cd": fn["e_cd"],
            "fnopt_cpu_ms": fn["cpu_ms_per_frame"],
            "iters_needed": hit["iters"] if hit else None,
            "lbfgs_e_3d": hit["e_3d"] if hit else None,
            "lbfgs_cpu_ms": hit["cpu_ms_per_frame"] if hit else None,
            "speedup": hit["cpu_ms_per_frame"] / fn["cpu_ms_per_frame"] if hit else None,
            "note": None if hit else f"not reached within {rs[-1]['iters'] if rs else 0} "
                                     "iterations"})
    return rec


def pareto_front(points: list, metric: str = EQUAL_ERROR_METRIC,
                 cost: str = "step_cpu_ms") -> list:
    """The runs not beaten by a cheaper one: sorted by ``cost``, errors strictly falling."""
    front = []
    for r in sorted((r for r in points if metric in r), key=lambda r: r[cost]):
        if not front or r[metric] < front[-1][metric]:
            front.append(r)
    return front


def equal_error_speedup(fast: list, slow: list, metric: str = EQUAL_ERROR_METRIC,
                        cost: str = "step_cpu_ms") -> list:
    """Speed-up of ``fast`` over ``slow`` at equal error, for every run of ``fast``.

    ``fast``, ``slow``: runs (dicts with ``metric`` and ``cost``, e.g. CPU ms per frame) of two
    optimisers over their iteration counts. For each ``fast`` run, the cost at which ``slow``
    reaches the same error is interpolated linearly in (log error, log cost) between the two
    runs of ``slow``'s Pareto front (:func:`pareto_front`) that bracket it; ``speedup`` is that
    cost over the ``fast`` run's. Outside the front no figure is invented: ``bound`` says
    ``"<="`` (``slow``'s cheapest run is already as accurate: the speed-up is at most the one
    given, computed with that run's cost) or ``">="`` (``slow`` never gets there: at least the
    one given, with its most expensive run's cost).

    Returns
    -------
    list of dict
        ``iters``, ``error``, ``cost``, ``slow_cost``, ``speedup``, ``bound`` (``"="``, ``"<="``
        or ``">="``) per ``fast`` run, in ``fast``'s order.
    """
    front = pareto_front(slow, metric, cost)
    if not front:
        raise ValueError("slow: expected at least one run with the error metric, got none")
    out = []
    for r in fast:
        if metric not in r:
            continue
        e = r[metric]
        j = next((k for k, q in enumerate(front) if q[metric] <= e), None)
        if j is None:
            c, bound = front[-1][cost], ">="
        elif j == 0:
            c, bound = front[0][cost], "<="
        else:
            a, b = front[j - 1], front[j]
            w = math.log(a[metric] / e) / math.log(a[metric] / b[metric])
            c = math.exp((1 - w) * math.log(a[cost]) + w * math.log(b[cost]))
            bound = "="
        out.append({"iters": r.get("iters"), "error": e, "cost": r[cost], "slow_cost": c,
                    "speedup": c / r[cost], "bound": bound})
    return out


#: One colour per optimiser in every panel of the ratio chart (a resolution without some rows
#: must not shift the others' colours); names not listed get matplotlib's next colour.
RATIO_COLORS = {"fnopt": "C0", "pcg": "C1", "pcg-n": "C2", "lbfgs": "C3", "lbfgs-pre": "C4",
                "lbfgs-wolfe": "C5", "lbfgs-wolfe64": "C6", "lbfgs-m10": "C7", "lbfgs-m20": "C8",
                "lbfgs-autograd": "C9"}


def ratio_tag(row: str) -> str:
    """The ratio part's output name: ``ratio`` for FNOpt's default row, ``ratio_<row>`` else."""
    return "ratio" if row == FNOPT_DEFAULT_ROW else f"ratio_{row}"


def part_ratio(args, net) -> dict:
    """FNOpt's speed-up over the L-BFGS variants at equal error along its curve (``iters`` JSONs).

    Per resolution of ``--ratio-res``: for each L-BFGS variant present, the speed-up of every
    FNOpt N of the ``--ratio-row`` rows (default :data:`FNOPT_DEFAULT_ROW`, ``polygeo
    simulate``'s FNOpt; ``fnopt``: the one-level step) (:func:`equal_error_speedup`, e_3D, the
    optimisers' own CPU ms per frame); the
    *baseline* is the variant needing the least time at FNOpt N = 10's error (the strongest);
    ``baseline_unpreconditioned`` the same among the variants without FNOpt's DCT
    preconditioner (the thesis' kind of baseline).
    ``speedup_vs_pcg``: the same against PCG (FNOpt's step without the FNO; below 1: PCG
    reaches FNOpt's error in less time); ``speedup_vs_pcg_n`` against ``pcg-n`` (PCG with the
    out-of-plane direction(s) of weights trained with them). ``thesis_lbfgs``: the thesis'
    L-BFGS configuration (:data:`THESIS_LBFGS`), labelled beside the strongest.
    """
    row = args.ratio_row
    rec = {"metric": EQUAL_ERROR_METRIC, "cost": "step_cpu_ms", "row": row, "res": {}}
    for res in (int(v) for v in args.ratio_res.split(",")):
        it = json.loads((OUT / f"bm_fnopt_iters_{res}.json").read_text())
        runs = [r for r in it["runs"] if "e_cd" in r]
        fast = sorted((r for r in runs if r["optimizer"] == row), key=lambda r: r["iters"])
        if not fast:
            raise ValueError(f"--ratio-row: no {row!r} rows in bm_fnopt_iters_{res}.json")
        names = sorted({r["optimizer"] for r in runs if r["optimizer"].startswith("lbfgs")})
        per = {}
        for name in names:
            per[name] = equal_error_speedup(fast, [r for r in runs if r["optimizer"] == name])
        at10 = {k: next((q for q in v if q["iters"] == 10 and q["bound"] != ">="), None)
                for k, v in per.items()}             # a variant that never gets there: out
        base = min((k for k in per if at10[k]), key=lambda k: at10[k]["slow_cost"],
                   default=None)
        plain = min((k for k in per if at10[k] and k not in PRECONDITIONED),
                    key=lambda k: at10[k]["slow_cost"], default=None)
        pcg = [r for r in runs if r["optimizer"] == "pcg"]
        pcg_n = [r for r in runs if r["optimizer"] == "pcg-n"]
        rec["res"][str(res)] = {"frames": it["frames"], "motion": it["motion"],
                                "iters_json": f"bm_fnopt_iters_{res}.json", "baseline": base,
                                "baseline_unpreconditioned": plain,
                                "thesis_lbfgs": THESIS_LBFGS if THESIS_LBFGS in per else None,
                                "speedup": per,
                                "speedup_vs_pcg": equal_error_speedup(fast, pcg) if pcg else None,
                                "speedup_vs_pcg_n": (equal_error_speedup(fast, pcg_n)
                                                     if pcg_n else None)}
    plt = _plt()
    keys = list(rec["res"])
    fig, axes = plt.subplots(1, len(keys), figsize=(5.5 * len(keys), 4), dpi=100, squeeze=False)
    for ax, res in zip(axes[0], keys):
        it = json.loads((OUT / f"bm_fnopt_iters_{res}.json").read_text())
        for name in [row, "pcg", "pcg-n"] + list(rec["res"][res]["speedup"]):
            rs = sorted((r for r in it["runs"] if r["optimizer"] == name and "e_3d" in r),
                        key=lambda r: r["iters"])
            if rs:
                ax.plot([r["step_cpu_ms"] for r in rs], [r["e_3d"] for r in rs], marker="o",
                        ms=3, label=name, lw=2.5 if name == row else 1.2,
                        color=RATIO_COLORS.get(name))
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_minor_formatter(plt.NullFormatter())
        ax.set_xlabel("optimiser CPU ms per frame (1 thread, shared machine)")
        ax.set_ylabel("mean e_3D vs converged reference")
        lines, tags = [], {}
        for key, tag in (("baseline", "strongest"), ("baseline_unpreconditioned",
                                                     "fastest un-preconditioned"),
                         ("thesis_lbfgs", "thesis config")):
            if rec["res"][res][key] is not None:    # None: no variant reaches FNOpt-10's error
                tags.setdefault(rec["res"][res][key], []).append(tag)
        for base, tag in tags.items():
            sp = [q for q in rec["res"][res]["speedup"].get(base, []) if q["bound"] == "="]
            lines.append(f"vs {base} ({', '.join(tag)}): " + ", ".join(
                f"N{q['iters']} {q['speedup']:.1f}x" for q in sp))
        ax.set_title(f"{res}x{res}, speed-up of {row} at equal e_3D\n" + "\n".join(lines),
                     fontsize=7)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(OUT / f"bm_fnopt_{ratio_tag(row)}.png")
    plt.close(fig)
    return rec


#: The ``hard`` part's cases: the three 64x64 cases of the ``general`` part where FNOpt-10 stays
#: far above the physical floor (diagonal, mid-edges, random-2; session 14's "trio"), as
#: ``(layout, motion, speed)`` of :func:`bm_fnopt_cases.general_cases`.
HARD_CASES = (("diagonal", "xy", 1.0), ("mid-edges", "xy", 1.0), ("random-2", "xy", 1.2))

#: The ``hard`` part's default rows: FNOpt and PCG with the normal directions over N.
HARD_PLAN = "fnopt:3,fnopt:5,fnopt:8,fnopt:10,fnopt:15,fnopt:20," \
    "pcg-n:3,pcg-n:5,pcg-n:8,pcg-n:10,pcg-n:15,pcg-n:20,pcg-n:24,pcg-n:30,pcg-n:40"


def part_hard(args, net) -> dict:
    """FNOpt-N against PCG-normal-N (``pcg-n``) on :data:`HARD_CASES` at ``--res``.

    Every row the median of ``--starts`` starts (:func:`_measure_starts`); ``--counts``
    replaces :data:`HARD_PLAN`. ``equal_error``: per case, FNOpt's speed-up over PCG-normal at
    equal e_3D (:func:`equal_error_speedup`; below 1: PCG-normal gets there in less time).
    """
    plan = [(m, int(n)) for m, n in (q.split(":") for q in (args.counts or HARD_PLAN).split(","))]
    rec = {"res": args.res, "frames": args.frames, "starts": args.starts,
           "cases": [list(c) for c in HARD_CASES], "random_layouts": RANDOM_LAYOUTS, "runs": []}
    for layout, motion, speed in HARD_CASES:
        s = SimSettings(res=(args.res, args.res), handles=RANDOM_LAYOUTS.get(layout, layout),
                        motion=motion, frames=args.frames, speed=speed)
        ref = reference_rollout(s, REFS)
        for name, n in plan:
            if name.startswith("fnopt") and net is None:
                continue
            r = _measure_starts(s, lambda name=name, n=n: _step(name, n, net), ref, args.every,
                                args.starts)
            r.update(layout=layout, motion=motion, speed=speed, optimizer=name, iters=n)
            rec["runs"].append(r)
            print(json.dumps(r), flush=True)
    rec["equal_error"] = []
    for case, rows in _hard_rows(rec).items():
        if rows["fnopt"] and rows["pcg-n"]:
            rec["equal_error"].append({"case": list(case), "metric": EQUAL_ERROR_METRIC,
                                       "speedup": equal_error_speedup(rows["fnopt"],
                                                                      rows["pcg-n"])})
    return rec


def _hard_rows(rec: dict) -> dict:
    """``{(layout, motion, speed): {"fnopt": rows, "pcg-n": rows}}``, rows sorted by N."""
    out = {}
    for c in rec["cases"]:
        rs = [r for r in rec["runs"] if [r["layout"], r["motion"], r["speed"]] == list(c)
              and "e_3d" in r]
        out[tuple(c)] = {name: sorted((r for r in rs if r["optimizer"] == name),
                                      key=lambda r: r["iters"]) for name in ("fnopt", "pcg-n")}
    return out


def chart_hard(rec: dict, path) -> None:
    """The ``hard`` record as a PNG at ``path``: e_CD x 1e3 (top) and e_3D (bottom) against the
    optimiser's CPU ms per frame, one column per case, FNOpt and PCG-normal over N (labelled);
    each column's title gives FNOpt's speed-up at equal e_3D for the bracketed N."""
    plt = _plt()
    rows = _hard_rows(rec)
    eq = {tuple(q["case"]): q["speedup"] for q in rec.get("equal_error", [])}
    fig, axes = plt.subplots(2, len(rows), figsize=(4.6 * len(rows), 7.4), dpi=100,
                             squeeze=False)
    for col, (case, rs) in enumerate(rows.items()):
        for row, (key, label) in enumerate((("e_cd", "mean e_CD x 1e3"), ("e_3d", "mean e_3D"))):
            _fnopt_pcg_panel(axes[row][col], plt, rs, key, f"{label} vs converged reference "
                             f"(median of {rec.get('starts', 1)} starts)")
        sp = ", ".join(f"N{q['iters']} {q['speedup']:.2f}x" for q in eq.get(case, [])
                       if q["bound"] == "=")
        axes[0][col].set_title(f"{case[0]} {case[1]} x{case[2]}, {rec['res']}x{rec['res']}, "
                               f"{rec['frames']} frames\nFNOpt's speed-up over PCG-normal at "
                               f"equal e_3D:\n{sp or 'none bracketed'}", fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
