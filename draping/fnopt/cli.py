"""``polygeo train-fnopt`` and ``polygeo simulate`` (grid cloth, FNOpt or classical)."""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, fields
from pathlib import Path

__all__ = ["register", "register_simulate", "run_train", "run_simulate"]


def _threads(n: int) -> None:
    import torch

    torch.set_num_threads(max(int(n), 1))


def _res(s: str) -> tuple[int, int]:
    try:
        parts = [int(p) for p in s.lower().split("x")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected N or HxW, got {s!r}") from None
    if len(parts) == 1:
        parts = parts * 2
    if len(parts) != 2 or min(parts) < 3:
        raise argparse.ArgumentTypeError(f"expected N or HxW with N, H, W >= 3, got {s!r}")
    return parts[0], parts[1]


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``train-fnopt`` to the ``polygeo`` sub-parsers."""
    from .settings import TrainSettings

    p = sub.add_parser(
        "train-fnopt",
        help="meta-train the FNOpt cloth optimiser (data-pool scheme, 32x32 grids)",
        description="Meta-train the FNO optimiser of FNOpt on 32x32 grid cloth with the "
        "data-pool scheme. Writes OUT/checkpoint.pt (an interrupted run resumes with the same "
        "settings), OUT/log.jsonl, OUT/training.png, OUT/fnopt_model.pt and its JSON record "
        "(config, command, minutes, figures). Copy both into draping/data/ to ship them.",
    )
    p.add_argument("-o", "--out", required=True, help="run folder")
    g = p.add_argument_group("settings (defaults: draping.fnopt.settings.TrainSettings)")
    for f in fields(TrainSettings):
        if isinstance(f.default, bool):         # --normal / --no-normal
            g.add_argument("--" + f.name.replace("_", "-"), dest=f.name, default=f.default,
                           action=argparse.BooleanOptionalAction,
                           help=f"default {f.default!r}")
            continue
        g.add_argument("--" + f.name.replace("_", "-"), dest=f.name,
                       type=type(f.default), default=f.default,
                       help=f"default {f.default!r}")
    p.add_argument("--max-minutes", type=float, default=None,
                   help="stop (checkpointed) after this many wall-clock minutes; run again to "
                   "resume (default: no limit, run all steps)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_train)


def run_train(args: argparse.Namespace) -> int:
    """Body of ``polygeo train-fnopt``."""
    from polygeo import runs

    from .. import viz
    from .train import TrainSettings, train

    _threads(args.threads)
    s = TrainSettings(**{f.name: getattr(args, f.name) for f in fields(TrainSettings)})
    out = Path(args.out)
    res = train(s, out, quiet=args.quiet, max_minutes=args.max_minutes)
    hist = res["history"]
    if hist:
        viz.plot_curves({"validation sub-optimality (N=10)": [h["val_subopt"] for h in hist],
                         "training loss (EMA) + 1": [1.0 + h["loss_ema"] for h in hist]},
                        out / "training.png", x={k: [h["step"] for h in hist] for k in (
                            "validation sub-optimality (N=10)", "training loss (EMA) + 1")},
                        xlabel="step", logy=True, title="FNOpt meta-training")
    import torch

    torch.save(res["model"].state_dict(), out / "fnopt_model.pt")
    record = {"config": {k: s_ for k, s_ in asdict(res["model"].config).items()},
              "settings": res["settings"], "parameters": res["parameters"],
              "command": "polygeo train-fnopt " + runs.record_command(sys.argv[2:]),
              "minutes": res["minutes"], "cpu_minutes": res["cpu_minutes"],
              "steps": res["step"], "finished": res["finished"],
              "val_subopt": res["val_subopt"], "history": hist,
              "torch": torch.__version__, "threads": args.threads,
              "date": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime())}
    runs.atomic_write_json(out / "fnopt_model.json", record)
    print(f"trained {res['step']} steps in {res['minutes']:.1f} min; validation "
          f"sub-optimality {res['val_subopt']}; weights {out / 'fnopt_model.pt'}")
    return 0


def register_simulate(sub: argparse._SubParsersAction) -> None:
    """Add ``simulate``."""
    from .settings import (
        COARSE_EVERY,
        FNOPT_COARSE,
        FNOPT_COARSE_EVERY,
        FNOPT_COARSE_FROM,
        LAYOUTS,
        MOTIONS,
        OPTIMIZERS,
    )

    p = sub.add_parser(
        "simulate",
        help="grid cloth rollout with FNOpt or a classical inner optimiser",
        description="Simulate a grid cloth held by handles (backward Euler, L_cloth minimised "
        "per frame by the chosen optimiser). Writes OUT/meshes/000000.ply ..., "
        "OUT/metrics.json (per frame e_CD x 1e3 and e_3D against the converged reference "
        "rollout, L_cloth in J, wall and CPU ms per frame), OUT/errors.png and OUT/rollout.gif.",
    )
    p.add_argument("--res", type=_res, default=(64, 64), help="N or HxW grid (default 64)")
    p.add_argument("--size", type=float, default=1.0, help="sheet width, m (default 1)")
    p.add_argument("--handles", choices=sorted(LAYOUTS), default="corners",
                   help="handle layout: grid vertices whose trajectories are prescribed "
                   "(default corners: the two corners of the first grid row)")
    p.add_argument("--motion", choices=list(MOTIONS), default="xy",
                   help="handle trajectory: translation along x, y, z, xy, xyz or a rotation "
                   "(rot-a, rot-b and their reverses), 60 fps (default xy)")
    p.add_argument("--speed", type=float, default=1.0,
                   help="factor on the trajectory's base speed (default 1.0)")
    p.add_argument("--frames", type=int, default=120, help="frames at 60 fps (default 120)")
    p.add_argument("--optimizer", choices=list(OPTIMIZERS), default="fnopt",
                   help="inner optimiser of each backward-Euler step; pcg: FNOpt's step "
                   "without the FNO (PCG with the normal directions); reference: solved to "
                   "convergence (default fnopt: the shipped learned optimiser)")
    p.add_argument("--iters", type=int, default=10,
                   help="inner iterations per frame (default 10)")
    p.add_argument("--fno-coarse", type=int, default=0,
                   help="fnopt: run the FNO on the grid whose longer side has this many "
                   "vertices (0: the sheet's own grid; default 0)")
    p.add_argument("--recycle", type=int, default=0,
                   help="fnopt: carry the span of each solve's last K updates to the next "
                   "frame's solve as extra directions (0: off; default 0)")
    p.add_argument("--weights", default=None, metavar="FILE",
                   help="fnopt: weights written by `polygeo train-fnopt` (RUN/fnopt_model.pt, "
                   "its JSON record beside it; default: the shipped weights)")
    p.add_argument("--fno-every", type=int, default=1,
                   help="fnopt: the FNO's proposal on every E-th iteration only, the classical "
                   "step between (E >= --iters: the first iteration only; default 1)")
    p.add_argument("--coarse", type=int, default=None,
                   help="pcg, fnopt: the two-level coarse correction (the step's Hessian on the "
                   "grid whose longer side has K vertices; 0: off; default fnopt "
                   f"{FNOPT_COARSE}, pcg 0)")
    p.add_argument("--coarse-every", type=int, default=None,
                   help="with a coarse grid: rebuild the coarse space every F frames (1: every "
                   f"frame; default fnopt {FNOPT_COARSE_EVERY}, pcg {COARSE_EVERY})")
    p.add_argument("--coarse-from", type=int, default=None,
                   help="fnopt with a coarse grid: the coarse direction joins inner iterations "
                   f"k >= this (0: every iteration; default {FNOPT_COARSE_FROM})")
    p.add_argument("--lr", type=float, default=None,
                   help="gd/adam step size, lbfgs step scale (default gd: per sheet the "
                   "stable step from a curvature bound, adam 0.1, lbfgs 1.0)")
    p.add_argument("--stretch", type=float, default=300.0,
                   help="stretch stiffness, N/m (authors' range 100..1000; default 300)")
    p.add_argument("--shear", type=float, default=10.0,
                   help="shear stiffness, N/m (range 1..100; default 10)")
    p.add_argument("--bend", type=float, default=1.0,
                   help="bending stiffness, mJ (range 0.01..10; default 1)")
    p.add_argument("--repulsion", type=float, default=0.0,
                   help="weight (J) of the repulsion term, eq. (28); 0: off (default 0)")
    p.add_argument("--no-reference", action="store_true",
                   help="skip the converged reference (no e_CD / e_3D)")
    p.add_argument("--gif-every", type=int, default=2,
                   help="GIF frame stride (default 2)")
    p.add_argument("-o", "--out", required=True, help="output folder")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_simulate)


def run_simulate(args: argparse.Namespace) -> int:
    """Body of ``polygeo simulate``."""
    from polygeo import runs

    from .cloth import Material
    from .simulate import SimSettings, reference_rollout, run, write_outputs

    _threads(args.threads)
    s = SimSettings(res=args.res, size=args.size, handles=args.handles, motion=args.motion,
                    speed=args.speed, frames=args.frames, optimizer=args.optimizer,
                    iters=args.iters, lr=args.lr,
                    material=Material(args.stretch, args.shear, args.bend),
                    repulsion=args.repulsion, fno_coarse=args.fno_coarse,
                    recycle=args.recycle, fno_every=args.fno_every, coarse=args.coarse,
                    coarse_every=args.coarse_every, coarse_from=args.coarse_from)
    model = None
    if args.weights is not None:
        if s.optimizer != "fnopt":
            raise ValueError(f"--weights: only with --optimizer fnopt, got {s.optimizer!r}")
        from .model import load_pretrained

        model = load_pretrained(args.weights)
    out = Path(args.out)
    bar = runs.progress(total=s.frames, desc=s.optimizer, quiet=args.quiet)
    ro = run(s, model=model, progress=lambda: bar.update(1))
    bar.close()
    ref = None
    if not args.no_reference:
        if s.optimizer == "reference" and s.repulsion == 0:
            ref = ro
        else:
            bar = runs.progress(total=s.frames, desc="reference", quiet=args.quiet)
            ref = reference_rollout(s, out, progress=lambda: bar.update(1))
            bar.close()
    res = write_outputs(out, s, ro, ref, gif_every=args.gif_every, weights=args.weights)
    print(json.dumps(res["mean"]))
    return 0
