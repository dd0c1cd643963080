"""Width/modes parsimony sweep of the FNOpt optimiser (trainings at 32x32, the shipped budget).

Each configuration is trained for --steps steps with the same seed and settings otherwise;
the validation sub-optimality (L(a_10) - L*) / (L(0) - L*) over fixed steps is recorded, with
the classical steps the FNOpt update is built on as baselines: PCG (its subspace step without
the FNO's proposal, what a zero FNO output gives) and preconditioned steepest descent. Then each
trained model (and, with --shipped, the shipped weights, whose settings are the defaults) runs
the 64x64 rollouts of --eval-layouts (xy, 60 frames, N = 10) against the converged reference:
e_CD x 1e3 and e_3D. The pick (:func:`parsimony_pick`) is the smallest model whose validation
sub-optimality is within 10 % of the best one's.

    python benchmarks/fnopt_sweep.py --steps 7000 --configs 16x4,32x4,32x8,64x4 --shipped
    python benchmarks/fnopt_sweep.py --evaluate-only --shipped     # models already trained
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from draping import viz
from draping.fnopt import solvers
from draping.fnopt.model import FNO, RECORD, FNOConfig, load_pretrained, solve_fnopt
from draping.fnopt.simulate import SimSettings, frame_metrics, reference_rollout
from draping.fnopt.train import TrainSettings, train, validation_set

OUT = Path(__file__).resolve().parent / "results"
REFS = OUT / "fnopt_refs"


def parsimony_pick(runs: list, key: str = "val_subopt", tol: float = 0.1) -> dict:
    """The run with the fewest ``parameters`` whose ``key`` (lower is better) is within ``tol``
    (relative) of the best run's.

    Raises
    ------
    ValueError
        If no run has a finite ``key``.
    """
    ok = [r for r in runs if r.get(key) is not None and np.isfinite(r[key])]
    if not ok:
        raise ValueError(f"runs: expected at least one run with a finite {key!r}, got none")
    best = min(r[key] for r in ok)
    return min((r for r in ok if r[key] <= (1 + tol) * best), key=lambda r: r["parameters"])


def row_config(row: dict) -> FNOConfig:
    """The FNO config a sweep row was trained with: its width and modes, the step rule it
    records (rows written before the rule was recorded: no normal direction, as they were
    trained) and the training defaults' layers and projection."""
    s = TrainSettings(width=row["width"], modes=row["modes"])
    return FNOConfig(row["width"], row["modes"], row.get("layers", s.layers),
                     row.get("projection", s.projection), row.get("normal", False),
                     row.get("normal_split", 0))


def trained_net(row: dict, weights: Path) -> FNO:
    """The trained FNO of a sweep row (weights: its ``model.pt``), in evaluation mode."""
    net = FNO(row_config(row))
    net.load_state_dict(torch.load(weights, weights_only=True))
    return net.eval()


def evaluate_64(net, layouts: list, frames: int = 60) -> dict:
    """e_CD x 1e3, e_3D (means over every 3rd frame) and CPU ms per frame of FNOpt N = 10."""
    out = {}
    for lay in layouts:
        s = SimSettings(res=(64, 64), handles=lay, motion="xy", frames=frames)
        ref = reference_rollout(s, REFS)
        ro = solvers.rollout(s.sheet(), s.material, s.handles, s.motion, s.frames,
                             lambda p, a0: solve_fnopt(net, p, 10), s.speed)
        m = frame_metrics(ro, ref, 3)
        out[lay] = {"e_cd": float(np.mean(m["e_cd"])), "e_3d": float(np.mean(m["e_3d"])),
                    "step_cpu_ms": float(np.mean(ro.cpu_ms))}
    return out


def _chart(rec: dict, path: Path) -> None:
    curves = {f"w{r['width']} m{r['modes']} ({r['parameters'] // 1000}k)":
              [h["val_subopt"] for h in r["history"]] for r in rec["runs"]}
    xs = {k: [h["step"] for h in r["history"]] for k, r in zip(curves, rec["runs"])}
    for name in ("pgd", "pcg"):
        curves[f"{name.upper()} (no FNO)"] = [rec[f"{name}_baseline_subopt"]] * 2
        xs[f"{name.upper()} (no FNO)"] = [0, rec["steps"]]
    viz.plot_curves(curves, path, x=xs, xlabel="training step",
                    ylabel="validation sub-optimality (N=10)", logy=True, markers=True,
                    title=f"FNOpt width/modes sweep (32x32, {rec['steps']} steps)")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=7000)
    ap.add_argument("--configs", default="16x4,32x4,32x8,64x4")
    ap.add_argument("--work", default="/tmp/fnopt_sweep")
    ap.add_argument("--out", default="fnopt_sweep.json", help="JSON name in benchmarks/results")
    ap.add_argument("--eval-layouts", default="corners,diagonal")
    ap.add_argument("--shipped", action="store_true",
                    help="add the shipped weights as the row of their (default) settings")
    ap.add_argument("--evaluate-only", action="store_true",
                    help="no training: evaluate the models of --work listed in --out")
    args = ap.parse_args()
    torch.set_num_threads(1)
    path = OUT / args.out
    lays = args.eval_layouts.split(",")
    if args.evaluate_only:
        rec = json.loads(path.read_text())
    else:
        val = validation_set()
        rec = {"steps": args.steps, "runs": []}
        for name, fn in (("pgd", solvers.solve_pgd), ("pcg", solvers.solve_pcg)):
            base = []
            for c in val:
                a = fn(c["problem"], 10)
                ln = float(c["p64"].loss(a.double())[0])
                base.append(max(ln - c["l_star"], 0) / (c["l_zero"] - c["l_star"]))
            rec[f"{name}_baseline_subopt"] = sum(base) / len(base)
        for cfg in args.configs.split(","):
            w, m = (int(v) for v in cfg.split("x"))
            s = TrainSettings(width=w, modes=m, steps=args.steps)
            t0 = time.perf_counter()
            r = train(s, Path(args.work) / cfg, quiet=True, log=lambda *_: None, val=val)
            rec["runs"].append({"width": w, "modes": m, "layers": s.layers,
                                "projection": s.projection, "normal": s.normal,
                                "normal_split": s.normal_split, "parameters": r["parameters"],
                                "val_subopt": r["val_subopt"], "history": r["history"],
                                "train_wall_minutes": (time.perf_counter() - t0) / 60,
                                "train_cpu_minutes": r["cpu_minutes"]})
            print(json.dumps({k: v for k, v in rec["runs"][-1].items() if k != "history"}),
                  flush=True)
            path.write_text(json.dumps(rec, indent=1))
    for r in rec["runs"]:
        if "eval_64" not in r and r.get("source") != "shipped":
            net = trained_net(r, Path(args.work) / f"{r['width']}x{r['modes']}" / "model.pt")
            r["eval_64"] = evaluate_64(net, lays)
            print(r["width"], r["modes"], json.dumps(r["eval_64"]), flush=True)
    if args.shipped and not any(r.get("source") == "shipped" for r in rec["runs"]):
        shipped = json.loads(RECORD.read_text())
        cfg = shipped["config"]
        rec["runs"].append({"width": cfg["width"], "modes": cfg["modes"], "source": "shipped",
                            "parameters": shipped["parameters"],
                            "val_subopt": shipped["val_subopt"],
                            "history": shipped["history"],
                            "train_cpu_minutes": shipped["cpu_minutes"],
                            "eval_64": evaluate_64(load_pretrained(), lays)})
    rec["runs"].sort(key=lambda r: r["parameters"])
    pick = parsimony_pick(rec["runs"])
    rec["pick"] = {"rule": "fewest parameters with validation sub-optimality within 10 % of "
                           "the best", "width": pick["width"], "modes": pick["modes"]}
    rec["eval_64_settings"] = {"layouts": lays, "motion": "xy", "frames": 60, "iters": 10}
    path.write_text(json.dumps(rec, indent=1))
    _chart(rec, OUT / (Path(args.out).stem.replace("fnopt_sweep", "bm_fnopt_sweep") + ".png"))
    print("pick", json.dumps(rec["pick"]))


if __name__ == "__main__":
    main()
