"""Width/modes parsimony sweep of the FNOpt optimiser (short trainings at 32x32).

Each configuration is trained for --steps steps with the same seed and settings otherwise;
the validation sub-optimality (L(a_10) - L*) / (L(0) - L*) over fixed steps is recorded, with
the classical steps the FNOpt update is built on as baselines: PCG (its subspace step without
the FNO's proposal, what a zero FNO output gives) and preconditioned steepest descent.

    python benchmarks/fnopt_sweep.py --steps 2000
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from draping import viz
from draping.fnopt import solvers
from draping.fnopt.train import TrainSettings, train, validation_set

OUT = Path(__file__).resolve().parent / "results"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--configs", default="16x8,32x8,32x4,64x8")
    ap.add_argument("--work", default="/tmp/fnopt_sweep")
    args = ap.parse_args()
    torch.set_num_threads(1)
    val = validation_set()
    rec = {"steps": args.steps, "runs": []}
    for name, fn in (("pgd", solvers.solve_pgd), ("pcg", solvers.solve_pcg)):
        base = []
        for c in val:
            a = fn(c["problem"], 10)
            ln = float(c["p64"].loss(a.double())[0])
            base.append(max(ln - c["l_star"], 0) / (c["l_zero"] - c["l_star"]))
        rec[f"{name}_baseline_subopt"] = sum(base) / len(base)
        print(f"{name} (no FNO) validation sub-optimality", sum(base) / len(base), flush=True)
    for cfg in args.configs.split(","):
        w, m = (int(v) for v in cfg.split("x"))
        s = TrainSettings(width=w, modes=m, steps=args.steps, eval_every=args.steps // 4,
                          checkpoint_every=args.steps // 4)
        t0 = time.perf_counter()
        r = train(s, Path(args.work) / cfg, quiet=True, log=lambda *_: None, val=val)
        ms = []
        for c in val[:4]:
            t1 = time.process_time()
            from draping.fnopt.model import solve_fnopt
            solve_fnopt(r["model"], c["problem"], 10)
            ms.append(1e3 * (time.process_time() - t1))
        run = {"width": w, "modes": m, "parameters": r["parameters"],
               "val_subopt": r["val_subopt"], "history": r["history"],
               "train_wall_minutes": (time.perf_counter() - t0) / 60,
               "train_cpu_minutes": r["cpu_minutes"],
               "cpu_ms_per_step_n10": sum(ms) / len(ms)}
        rec["runs"].append(run)
        print(json.dumps({k: v for k, v in run.items() if k != "history"}), flush=True)
        OUT.mkdir(exist_ok=True)
        (OUT / "fnopt_sweep.json").write_text(json.dumps(rec, indent=1))
    curves = {f"w{r['width']} m{r['modes']} ({r['parameters'] // 1000}k)":
              [h["val_subopt"] for h in r["history"]] for r in rec["runs"]}
    xs = {k: [h["step"] for h in r["history"]] for k, r in zip(curves, rec["runs"])}
    for name in ("pgd", "pcg"):
        curves[f"{name.upper()} (no FNO)"] = [rec[f"{name}_baseline_subopt"]] * 2
        xs[f"{name.upper()} (no FNO)"] = [0, args.steps]
    viz.plot_curves(curves, OUT / "fnopt_sweep.png", x=xs, xlabel="training step",
                    ylabel="validation sub-optimality (N=10)", logy=True, markers=True,
                    title="FNOpt width/modes sweep (32x32)")


if __name__ == "__main__":
    main()
