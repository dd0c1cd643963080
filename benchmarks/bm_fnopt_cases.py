"""The FNOpt benchmark's case sets: ``general`` (unseen layouts and speeds) and ``validation``.

The 13 ``general`` cases with their floor rows and merging of partial runs, the validation
case lists and the candidate-free screen that made the screened set (``bm_fnopt.py --part
general`` / ``--part validation``).
"""

from __future__ import annotations

import json
import math
import time

import numpy as np
import torch
from bm_fnopt_common import (
    FLOOR_PERTURB,
    RANDOM_LAYOUTS,
    REFS,
    ROOT,
    _fno_options,
    _measure,
    _measure_starts,
    _plt,
    _step,
)

from draping.fnopt import solvers
from draping.fnopt.model import load_pretrained
from draping.fnopt.simulate import SimSettings, frame_metrics, reference_rollout
from polygeo.runs import record_path


def general_cases(motion: str = "xy") -> list:
    """The ``general`` part's 13 cases ``(layout, motion, speed)`` (random layouts by name)."""
    return [("corners", motion, sp) for sp in (1.0, 1.2, 1.5, 2.0)] + \
        [(lay, motion, 1.0) for lay in ("diagonal", "mid-edges", "corner-centre", "single")] + \
        [("diagonal", "rot-a", 1.5), ("single", "xyz", 2.0)] + \
        [(lay, mo, 1.2) for lay, mo in zip(RANDOM_LAYOUTS, ("rot-b", "xy", "z"))]


def _pins(seed: int, n: int) -> list:
    return [tuple(round(float(v), 3) for v in pt) for pt in np.random.default_rng(seed).random(
        (n, 2))]


#: Validation rollouts for choosing weights (``validation`` part), never a benchmark case:
#: other motions and speeds on the named layouts, and random pin sets from generators of their
#: own (the first two from one generator, seed 77, as drawn in session 6).
VALIDATION_CASES = (
    ("diagonal", "z", 1.3), ("mid-edges", "rot-b", 1.0), ("corner-centre", "xyz", 1.3),
    (_pins(77, 7)[:2], "xy-rev", 1.0), (_pins(77, 7)[2:5], "rot-a", 1.0),
    ("corners", "xyz", 1.7), ("corner-centre", "rot-b-rev", 1.0), (_pins(78, 2), "y", 1.2))

#: Validation cases kept by :func:`screen_case` (sessions 13-14; 48x48, 45 frames): five of
#: :data:`VALIDATION_CASES` (diagonal/z x1.3, mid-edges/rot-b and corner-centre/rot-b-rev fail:
#: their physical floors are 34-48) and every fresh draw k = 1..13 that passed (k = 5, 6, 8, 11,
#: 13 failed), random pin sets ``_pins(1300 + k, 2 + k % 4)`` with motions and speeds drawn from
#: ``default_rng(1300)``, in draw order. The rule depends on no candidate, and all passing draws
#: are in (none chosen by a solver's error). ``--part validation --case-set screened``; never a
#: benchmark case.
SCREENED_VALIDATION_CASES = tuple(VALIDATION_CASES[i] for i in (2, 3, 4, 5, 7)) + (
    (_pins(1301, 3), "z-rev", 1.5), (_pins(1302, 4), "xy-rev", 1.0),
    (_pins(1303, 5), "y-rev", 1.5), (_pins(1304, 2), "xy", 1.0),
    (_pins(1307, 5), "y-rev", 1.5), (_pins(1309, 3), "y", 1.2),
    (_pins(1310, 4), "z-rev", 1.3), (_pins(1312, 2), "xyz", 1.2))

#: Seed of :func:`fresh_cases` (session 19's rule L9: drawn once, for choosing FNOpt's default
#: step on inputs no earlier choice had seen).
FRESH_SEED = 20261126
#: Starts (m) of the ``fresh`` part: every other of :data:`STARTS`.
FRESH_STARTS = (0.0, 1e-7, 1e-5)
_NAMED = ("corners", "diagonal", "mid-edges", "corner-centre", "single")


def fresh_cases(seed: int = FRESH_SEED, n64: int = 24, n100: int = 12) -> list:
    """Random cases ``(res, frames, layout, motion, speed, Material)``: ``n64`` at 64x64 (60
    frames), then ``n100`` at 100x100 (30 frames).

    Per case, from one ``numpy.random.default_rng(seed)`` in this order: the layout uniform over
    the five named layouts and a random pin set (1-5 pins uniform in the unit square), the
    motion uniform over ``MOTIONS``, the speed uniform over 1.0, 1.1, ..., 2.0, and stretch /
    shear / bend log-uniform in the authors' ranges ([100, 1000] N/m, [1, 100] N/m, [0.01, 10]
    mJ; density and damping default).
    """
    from draping.fnopt.cloth import Material
    from draping.fnopt.settings import MOTIONS

    rng = np.random.default_rng(seed)
    out = []
    for i in range(n64 + n100):
        k = int(rng.integers(6))
        lay = _NAMED[k] if k < 5 else [tuple(round(float(v), 3) for v in pt)
                                       for pt in rng.random((int(rng.integers(1, 6)), 2))]
        mo = MOTIONS[int(rng.integers(len(MOTIONS)))]
        sp = round(1.0 + 0.1 * int(rng.integers(11)), 1)
        st, sh, be = (round(float(np.exp(rng.uniform(np.log(lo), np.log(hi)))), nd)
                      for (lo, hi), nd in (((100, 1000), 2), ((1, 100), 3), ((0.01, 10), 4)))
        res, frames = (64, 60) if i < n64 else (100, 30)
        out.append((res, frames, lay, mo, sp, Material(stretch=st, shear=sh, bend=be)))
    return out


def part_fresh(args, net) -> dict:
    """The ``--plan`` rows on :func:`fresh_cases` (``--cases``: indices), each the median of
    e_CD over :data:`FRESH_STARTS`: how session 19 chose FNOpt's default step (rule L9).

    Per plan row: the per-case medians, how many are <= 5 and their geometric mean.
    """
    from dataclasses import asdict

    cases = fresh_cases()
    idx = [int(i) for i in args.cases.split(",")] if args.cases else range(len(cases))
    plan = [(name, int(n)) for name, n in (p.split(":") for p in args.plan.split(","))]
    rec = {"seed": FRESH_SEED, "starts_m": list(FRESH_STARTS), "cases": [], "runs": []}
    for i in idx:
        res, frames, lay, mo, sp, mat = cases[i]
        s = SimSettings(res=(res, res), handles=lay, motion=mo, frames=frames, speed=sp,
                        material=mat)
        rec["cases"].append({"case": i, "res": res, "frames": frames, "layout": lay,
                             "motion": mo, "speed": sp, "material": asdict(mat)})
        ref = reference_rollout(s, REFS)
        for name, n in plan:
            m = _measure_starts(s, lambda name=name, n=n: _step(name, n, net), ref, args.every,
                                perturbs=FRESH_STARTS)
            cd = [math.inf if q["e_cd"] is None else q["e_cd"] for q in m["starts"]]
            ms = [math.nan if q["step_cpu_ms"] is None else q["step_cpu_ms"] for q in m["starts"]]
            r = {"case": i, "optimizer": name, "iters": n, "e_cd": float(np.median(cd)),
                 "e_cd_starts": cd, "step_cpu_ms": float(np.median(ms))}
            rec["runs"].append(r)
            print(json.dumps(r), flush=True)
    rec["summary"] = fresh_summary(rec["runs"])
    return rec


def fresh_summary(runs: list) -> dict:
    """Per ``optimizer:iters``: the cases, how many medians are <= 5, their geometric mean."""
    out = {}
    for key in dict.fromkeys(f"{r['optimizer']}:{r['iters']}" for r in runs):
        cd = [r["e_cd"] for r in runs if f"{r['optimizer']}:{r['iters']}" == key]
        out[key] = {"cases": len(cd), "at_most_5": sum(c <= 5 for c in cd),
                    "gmean_e_cd": float(np.exp(np.mean(np.log(cd))))}
    return out


#: Tolerance (m/s^2) of the looser reference in :func:`screen_case`: 100x REFERENCE_TOL.
SCREEN_TOL = 5e-3


def screen_case(s: SimSettings, threshold: float = 1.0, every: int = 3) -> dict:
    """Whether a case can judge a solver by e_CD: a rule that depends on no candidate.

    Kept iff (R1) the converged reference re-solved from the 0.1 mm perturbed start
    (:data:`FLOOR_PERTURB`, the ``floor-ref`` row) and (R2) the reference solved to
    :data:`SCREEN_TOL` both stay within mean e_CD x 1e3 <= ``threshold`` of the reference (frames
    1, 1 + ``every``, ...). R1 fails where a 0.1 mm difference picks another fold, R2 where a
    per-step error far below any N = 10 solve's does; R2 is run only where R1 passes.
    Returns ``{"r1_e_cd", "r2_e_cd" (absent when not run), "kept"}``.
    """
    ref = reference_rollout(s, REFS)
    r1 = _measure(s, lambda p, a0: solvers.solve_reference(p, a0), ref, every, FLOOR_PERTURB,
                  warm_start=True, dtype=torch.float64)
    out = {"r1_e_cd": r1.get("e_cd", float("inf"))}
    if out["r1_e_cd"] <= threshold:
        loose = reference_rollout(s, REFS, tol=SCREEN_TOL)
        out["r2_e_cd"] = float(np.mean(frame_metrics(loose, ref, every)["e_cd"]))
    out["kept"] = out["r1_e_cd"] <= threshold and out.get("r2_e_cd", math.inf) <= threshold
    return out


def part_validation(args, net) -> dict:
    """N = ``--val-iters`` (default 10) rollouts of :data:`VALIDATION_CASES` at ``--res`` (45
    frames) per candidate.

    ``--candidates``: comma-separated weight paths (``shipped``: the package's). Per candidate
    the per-case e_CD x 1e3 / e_3D, their geometric means and the worst e_CD: how weights are
    chosen (by seeds and settings) without looking at the benchmark's cases.
    """
    cases = SCREENED_VALIDATION_CASES if args.case_set == "screened" else VALIDATION_CASES
    rec = {"res": args.res, "frames": 45, "iters": args.val_iters, "case_set": args.case_set,
           "fno_options": _fno_options(args),
           "cases": [list(c) for c in cases], "runs": []}
    for w in args.candidates.split(","):
        model = load_pretrained(None if w == "shipped" else w)
        cd, e3 = [], []
        for lay, mo, sp in cases:
            s = SimSettings(res=(args.res, args.res), handles=lay, motion=mo, frames=45,
                            speed=sp)
            r = _measure(s, _step("fnopt", args.val_iters, model, fno=_fno_options(args)),
                         reference_rollout(s, REFS), 3)
            cd.append(r.get("e_cd", float("inf")))
            e3.append(r.get("e_3d", float("inf")))
        rec["runs"].append({"weights": record_path(w, ROOT), "e_cd": cd, "e_3d": e3,
                            "gmean_e_cd": float(np.exp(np.mean(np.log(cd)))),
                            "worst_e_cd": max(cd),
                            "gmean_e_3d": float(np.exp(np.mean(np.log(e3))))})
        print(json.dumps(rec["runs"][-1]), flush=True)
    return rec


def part_general(args, net) -> dict:
    rec = {"res": args.res, "frames": args.frames, "runs": []}
    cases = general_cases(args.motion)
    if args.cases:
        cases = [cases[int(i)] for i in args.cases.split(",")]
    plan = [p.split(":") for p in args.plan.split(",")]
    rec["random_layouts"] = RANDOM_LAYOUTS
    for layout, motion, speed in cases:
        s = SimSettings(res=(args.res, args.res), handles=RANDOM_LAYOUTS.get(layout, layout),
                        motion=motion, frames=args.frames, speed=speed)
        t0 = time.process_time()
        ref = reference_rollout(s, REFS)
        print(f"reference {layout} {motion} x{speed}: {time.process_time() - t0:.1f} s CPU",
              flush=True)
        for name, n in plan:
            n = int(n)
            if name.startswith("fnopt") and net is None:
                continue
            if name == "floor":         # sensitivity: PCG-n from a 0.1 mm perturbed start
                r = _measure(s, _step("pcg", n), ref, args.every, FLOOR_PERTURB)
            elif name == "floor-ref":   # the physical floor: the reference, perturbed start
                r = _measure(s, lambda p, a0: solvers.solve_reference(p, a0), ref, args.every,
                             FLOOR_PERTURB, warm_start=True, dtype=torch.float64)
            else:
                r = _measure(s, _step(name, n, net, fno=_fno_options(args)), ref, args.every)
            r.update(layout=layout, motion=motion, speed=speed, optimizer=name, iters=n)
            rec["runs"].append(r)
            print(json.dumps(r), flush=True)
    rec["floors"] = floor_table(rec["runs"])
    return rec


def floor_table(runs: list) -> list:
    """Per case: FNOpt N = 10's e_CD beside the case's floors (``floor``, ``floor-ref`` rows).

    ``over_floor``: FNOpt's e_CD minus the physical floor (``floor-ref``) -- the part of the
    error an optimiser can be blamed for; ``None`` where a row is missing.
    """
    out = []
    cases = list(dict.fromkeys((r["layout"], r["motion"], r["speed"]) for r in runs))
    for case in cases:
        rs = {(r["optimizer"], r["iters"]): r for r in runs
              if (r["layout"], r["motion"], r["speed"]) == case and "e_cd" in r}
        fn = rs.get(("fnopt", 10))
        pcg_floor = next((r for (o, _), r in rs.items() if o == "floor"), None)
        ref_floor = next((r for (o, _), r in rs.items() if o == "floor-ref"), None)
        row = {"layout": case[0], "motion": case[1], "speed": case[2],
               "fnopt_e_cd": fn["e_cd"] if fn else None,
               "floor_pcg_e_cd": pcg_floor["e_cd"] if pcg_floor else None,
               "floor_ref_e_cd": ref_floor["e_cd"] if ref_floor else None}
        row["over_floor"] = (row["fnopt_e_cd"] - row["floor_ref_e_cd"]
                             if fn and ref_floor else None)
        out.append(row)
    return out


def merge_general(old: dict, rec: dict) -> dict:
    """``rec`` (a ``general`` record) with the rows of ``old`` it did not run again.

    Rows are keyed by (layout, motion, speed, optimizer, iterations); ``old`` counts only when
    its resolution and frame count are ``rec``'s (else ``rec`` is returned unchanged). The
    floors table is rebuilt; ``merged_from`` records ``old``'s date.
    """
    if (old.get("res"), old.get("frames")) != (rec["res"], rec["frames"]):
        return rec

    def key(r):
        return json.dumps(r["layout"]), r["motion"], r["speed"], r["optimizer"], r["iters"]

    new = {key(r) for r in rec["runs"]}
    out = dict(rec, runs=[r for r in old["runs"] if key(r) not in new] + rec["runs"],
               merged_from=old.get("date"))
    out["floors"] = floor_table(out["runs"])
    return out


def chart_general(rec: dict, path) -> None:
    """Bar chart (PNG at ``path``) of the ``general`` record's e_CD per case and optimiser."""
    rs = [r for r in rec["runs"] if "e_cd" in r]
    names = sorted({r["optimizer"] for r in rs})
    cases = list(dict.fromkeys((r["layout"], r["motion"], r["speed"]) for r in rs))
    labels = [f"{lay} {mo} x{sp}" for lay, mo, sp in cases]
    val = {(r["layout"], r["motion"], r["speed"], r["optimizer"]): r["e_cd"] for r in rs}
    curves = {n: [val.get((*c, n), float("nan")) for c in cases] for n in names}
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 4), dpi=100)
    w = 0.8 / max(len(names), 1)
    for i, n in enumerate(names):
        ax.bar(np.arange(len(curves[n])) + i * w, curves[n], w, label=n)
    ax.set_xticks(np.arange(len(labels)) + 0.4 - w / 2)
    ax.set_xticklabels(labels, rotation=30, fontsize=7)
    ax.set_ylabel("e_CD x 1e3")
    ax.set_yscale("log")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
