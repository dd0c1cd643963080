"""``polygeo train-drape`` and ``polygeo drape`` (entry-point plug-ins of ``polygeo.commands``).

``--help`` and argument errors import no torch: the method names come from the torch-free
:mod:`draping.gaps.settings`, the garment, motion and phenotype names from :mod:`draping.names`
(their one homes), and the body and motion options from :func:`draping.cli.add_scene_arguments`
(shared with ``polygeo drape-reference``). The commands import the rest when they run.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from ..cli import add_scene_arguments
from ..names import GARMENTS
from .settings import INEXTENSIBILITY as _INEXTENSIBILITY
from .settings import METHODS as _METHODS

__all__ = [
    "register_train", "register_drape", "run_train", "run_drape", "held_out_record",
    "check_record",
]



def register_train(sub: argparse._SubParsersAction) -> None:
    """Add ``train-drape`` to the ``polygeo`` sub-parsers."""
    p = sub.add_parser(
        "train-drape",
        help="self-supervised training of a GAPS (or SNUG-/NCS-like) garment draping model",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=(
            "Train a garment-specific recurrent draping model without data (GAPS, thesis\n"
            "ch. 4): a GRU maps body shape (6 Anny phenotypes), pose and root velocity to\n"
            "displacements of the unposed garment, skinned to the body; the losses are the\n"
            "cloth energies (StVK strain, bending, gravity, body collision, inertia over\n"
            "3-frame windows, covariance inextensibility with the collision-aware k_ext) on\n"
            "procedural motions (walk, arms, squat, random seeds < 1000) and random body\n"
            "shapes. Held back for evaluation: the turn motion, random seeds >= 1000, shapes\n"
            "drawn with seeds >= 1000, an untrained walking speed; jumping jacks (arms\n"
            "overhead) as a stress case reported apart.\n\n"
            "Writes OUT/checkpoint.pt (every 100 steps; --resume continues), OUT/log.jsonl\n"
            "(loss terms in J per frame, stage CPU seconds), OUT/curves.png, OUT/model.pt\n"
            "(load with draping.gaps.load_model or polygeo drape --model) and OUT/model.json\n"
            "(settings, command, CPU and wall minutes, held-out eps_e / eps_a / eps_c in %,\n"
            "inference CPU ms per frame). One CPU thread."
        ),
        epilog="example: polygeo train-drape --method gaps --garment tshirt --minutes 30 -o RUN",
    )
    p.add_argument("--method", default="gaps", choices=_METHODS,
                   help="gaps: RBF body-participation skinning (smoothed over the garment, "
                   "--skin-smoothing), GAPS bending, inextensibility with the k_ext schedule; "
                   "snug: nearest-vertex skinning, no inextensibility; "
                   "ncs: Laplacian-smoothed skinning, no inextensibility (default gaps)")
    p.add_argument("--garment", default="tshirt", metavar="NAME",
                   help=f"garment template, one of {', '.join(GARMENTS)} (default tshirt)")
    p.add_argument("--garment-file", default=None, metavar="FILE",
                   help="garment mesh (OBJ/PLY/OFF/STL, metres) in the rest pose of the default "
                   "body; checked (manifold, no self-intersection, outside the body)")
    p.add_argument("--inextensibility", default="auto", choices=_INEXTENSIBILITY,
                   help="L_inext: schedule (eq. 45), one (k_ext = 1), none; auto: schedule for "
                   "gaps, none for the baselines (default auto)")
    p.add_argument("--width", type=int, default=None, help="GRU width (default 32)")
    p.add_argument("--depth", type=int, default=None, help="GRU layers (default 1)")
    p.add_argument("--rank", type=int, default=None,
                   help="output basis size, 0 for a full width x 3V layer (default 64)")
    p.add_argument("--skin-smoothing", type=int, default=None, metavar="N",
                   help="gaps: Laplacian smoothing steps over the garment's edges applied to the "
                   "RBF skinning weights; 0: the thesis' weights (default 20)")
    p.add_argument("--steps", type=int, default=None, metavar="N",
                   help="total optimiser steps (default 3000)")
    p.add_argument("--minutes", type=float, default=None, metavar="M",
                   help="wall-clock budget in minutes: stop (checkpointed, exported) when spent "
                   "(default: none, --steps decides)")
    p.add_argument("--batch", type=int, default=None, help="windows per step (default 4)")
    p.add_argument("--seed", type=int, default=0, help="seed of shapes, windows, init (default 0)")
    p.add_argument("--init", default=None, metavar="FILE",
                   help="start from this model.pt (same garment and architecture): fine-tuning "
                   "(default: none, random initialisation from --seed)")
    p.add_argument("--random-motions", type=int, default=None, metavar="N",
                   help="seeded random training motions, seeds 0..N-1 < 1000 (default 12)")
    p.add_argument("--lr", type=float, default=None,
                   help="Adam learning rate of the first 10 epochs (default 1e-3; 1e-4 after)")
    p.add_argument("--lr-epochs", type=int, default=None, metavar="E",
                   help="epochs (60 steps each) at --lr before 1e-4 (default 10)")
    p.add_argument("--burn-in", type=int, default=None, metavar="F",
                   help="frames of motion the GRU reads (no gradient) before each training "
                   "window, from a zero state at the motion's start as at inference; 0: the "
                   "paper's random state at the window (default 90)")
    p.add_argument("--grad-clip", type=float, default=None, metavar="C",
                   help="clip each step's gradient norm at C times the running mean of the "
                   "previous (clipped) norms; 0: no clipping (default 3)")
    p.add_argument("--shapes", type=int, default=None, metavar="N",
                   help="training body shapes, phenotypes drawn uniformly in [0, 1] (default "
                   "128)")
    p.add_argument("--collision-stiffness", type=float, default=None, metavar="K",
                   help="k_c of the cubic body-collision loss, eq. (40), in J/m^3 (default 1e4; "
                   "the shipped dress uses 1e5)")
    p.add_argument("--collision-eps", type=float, default=None, metavar="M",
                   help="clearance epsilon of the collision loss, eq. (40), and of the k_ext "
                   "schedule, eq. (45), in metres (default 0.002)")
    p.add_argument("--k-ext-rings", type=int, default=None, metavar="R",
                   help="GAPS: let the cloth within R 1-rings of a contact stretch as the "
                   "contact does (the k_ext schedule, eq. (45)); default 0: only the colliding "
                   "vertices")
    p.add_argument("--pinch-inext", type=float, default=None, metavar="W",
                   help="GAPS: factor in [0, 1] on L_inext at cloth pinched between an arm and "
                   "the rest of the body (within the clearance of both) and the --k-ext-rings "
                   "1-rings round it; 0: off there (default 1: no pinch test)")
    p.add_argument("--pinch-push", action="store_true", default=None,
                   help="GAPS: at cloth pinched between an arm and the rest of the body, measure "
                   "the collision penetration along the sum of the two facing normals (out of "
                   "the pinch) instead of the closest part's (default: off)")
    p.add_argument("--replay", type=float, default=None, metavar="P",
                   help="hard-example replay: probability that a step trains again on a recent "
                   "step whose collision loss was in the top decile (default 0)")
    p.add_argument("--average-from", type=int, default=None, metavar="STEP",
                   help="export the uniform mean of the network weights after every step past "
                   "STEP (the last weights go to DIR/model_last.pt); training is unchanged, so "
                   "a run's checkpoint at or before STEP continues with --resume (default: "
                   "off, the last weights)")
    p.add_argument("-o", "--out", required=True, metavar="DIR", help="run folder")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in DIR (same settings); without it DIR starts afresh")
    p.add_argument("--eval-frames", type=int, default=60, metavar="T",
                   help="frames of each held-out evaluation case (default 60; 0: no evaluation)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_train)


def _settings(args):
    from .settings import GapsSettings, TrainSettings

    mk = {"garment": args.garment, "garment_file": args.garment_file, "method": args.method,
          "inextensibility": args.inextensibility}
    for k in ("width", "depth", "rank", "skin_smoothing"):
        if getattr(args, k) is not None:
            mk[k] = getattr(args, k)
    tk = {"seed": args.seed, "init": args.init}
    for k in ("random_motions", "lr", "lr_epochs", "burn_in", "shapes", "grad_clip",
              "collision_stiffness", "collision_eps", "k_ext_rings", "replay", "pinch_inext",
              "pinch_push", "average_from"):
        if getattr(args, k) is not None:
            tk[k] = getattr(args, k)
    if args.batch is not None:
        tk["batch"] = args.batch
    return TrainSettings(GapsSettings(**mk), **tk)


def held_out_record(model, frames: int = 60, stress: bool = False) -> dict:
    """Held-out (or stress) metrics of a model, JSON-able.

    With the load average when measured (CPU ms per frame on a shared machine depend on it).
    """
    import os

    from .data import held_out_cases, stress_cases
    from .infer import evaluate

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    ev = evaluate(model, (stress_cases if stress else held_out_cases)(frames))
    ev["load_average"] = load
    return ev


def check_record(model) -> dict:
    """Mean metrics on :func:`draping.gaps.check_case` (what the shipped-model test redoes)."""
    import numpy as np

    from draping.body import AnnyBody

    from .data import check_case
    from .infer import drape_case, frame_metrics

    body = AnnyBody.load()
    case = check_case()
    m = frame_metrics(drape_case(model, body, case), body)
    return {"case": case._asdict(),
            **{k: float(np.mean(m[k])) for k in ("eps_e", "eps_a", "eps_c")}}


def run_train(args: argparse.Namespace) -> int:
    """Run ``polygeo train-drape``; bad input raises ``ValueError`` (exit status 2)."""
    import torch

    from draping.body import AnnyBody
    from polygeo.runs import CheckpointError, atomic_write_json, record_command

    from .infer import load_model, save_model, time_inference
    from .train import train

    torch.set_num_threads(1)
    if args.steps is not None and args.steps < 0:
        raise ValueError(f"--steps: expected >= 0, got {args.steps}")
    if args.minutes is not None and not args.minutes > 0:
        raise ValueError(f"--minutes: expected > 0, got {args.minutes}")
    settings = _settings(args)
    out = Path(args.out)
    if not args.resume and (out / "checkpoint.pt").exists():
        (out / "checkpoint.pt").unlink()
    command = "polygeo " + record_command(sys.argv[1:]) if sys.argv else ""
    try:
        res = train(settings, out, minutes=args.minutes, steps=args.steps, resume=args.resume,
                    quiet=args.quiet, command=command)
    except CheckpointError as exc:
        raise ValueError(f"{exc} (drop --resume to start afresh)") from None
    model = load_model(res.model_path)
    record = dict(model.record)
    if args.eval_frames:
        record["held_out"] = held_out_record(model, args.eval_frames)
        record["stress"] = held_out_record(model, args.eval_frames, stress=True)
    record["check"] = check_record(model)
    record["inference_cpu_ms_per_frame"] = time_inference(model, AnnyBody.load())
    record["file_bytes"] = res.model_path.stat().st_size
    record["parameters"] = int(sum(p.numel() for p in model.parameters()))
    save_model(res.model_path, model, record)
    atomic_write_json(out / "model.json", {"settings": record["training"]["settings"], **record})
    print(f"trained {res.steps} steps in {res.cpu_minutes:.1f} CPU min / {res.wall_minutes:.1f} "
          f"wall min -> {res.model_path}")
    if "held_out" in record:
        m = record["held_out"]["mean"]
        ms = record["inference_cpu_ms_per_frame"]
        print(f"held out: eps_e {m['eps_e']:.3f} %  eps_a {m['eps_a']:.3f} %  eps_c "
              f"{m['eps_c']:.4f} %  ({ms['model']:.2f} CPU ms/frame, "
              f"{ms['with_skeleton']:.2f} with the skeleton, {ms['with_body_mesh']:.2f} with "
              "the body mesh)")
    return 0


def register_drape(sub: argparse._SubParsersAction) -> None:
    """Add ``drape`` to the ``polygeo`` sub-parsers."""
    p = sub.add_parser(
        "drape",
        help="drape a garment on a moving body with a trained GAPS model",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=(
            "Drape a garment on the free Anny body moving through a motion with a trained\n"
            "draping model (GAPS by default; the shipped T-shirt and dress models, or --model).\n"
            "Units: metres, seconds. Writes OUT/meshes/000000.ply ... (garment, m),\n"
            "OUT/body/000000.ply ... (posed body), OUT/garment.npz (the rest garment on the\n"
            "body shape), OUT/metrics.json (per frame eps_e, eps_a: mean % change of edge\n"
            "lengths / triangle areas against the rest garment; eps_c: % of garment vertices\n"
            "inside the body; ms per frame of the model, CPU), OUT/strip.png and OUT/drape.gif.\n"
            "With --reference, also the physics reference drape of the same frames and\n"
            "E_dist (cm, mean vertex distance) and E_norm (degrees, mean normal angle)."
        ),
        epilog='example: polygeo drape --method gaps --garment tshirt --motion walk --frames 120 '
               '--shape "age=0.66,gender=0.8" -o OUT',
    )
    p.add_argument("--method", default="gaps", choices=_METHODS,
                   help="model kind; gaps uses the shipped model of the garment unless --model "
                   "(snug and ncs need --model) (default gaps)")
    p.add_argument("--model", default=None, metavar="FILE",
                   help="a model.pt written by polygeo train-drape (for --garment-file: one "
                   "trained for that garment; default: the shipped model of --garment)")
    p.add_argument("--garment", default="tshirt", metavar="NAME",
                   help=f"garment template, one of {', '.join(GARMENTS)}; shipped models: tshirt, "
                   "dress (default tshirt)")
    p.add_argument("--garment-file", default=None, metavar="FILE",
                   help="garment mesh (OBJ/PLY, metres, rest pose of the default body); needs "
                   "--model trained for it")
    add_scene_arguments(p, frames=120, seed_help="integer seed of the random motion (default 0)")
    p.add_argument("--reference", action="store_true",
                   help="also run the physics reference solver on the same frames (slow: about "
                   "1-3 CPU s per frame) and add e_dist (cm) and e_norm (deg) to the metrics")
    p.add_argument("-o", "--out", required=True, metavar="OUT", help="output folder")
    p.add_argument("--no-pictures", action="store_true", help="skip the PNG strip and the GIF")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_drape)


def run_drape(args: argparse.Namespace) -> int:
    """Run ``polygeo drape``; bad input raises ``ValueError`` (exit status 2)."""
    import torch

    from .drape_io import drape_job

    torch.set_num_threads(1)
    if args.frames < 1:
        raise ValueError(f"--frames: expected >= 1, got {args.frames}")
    t0 = time.perf_counter()
    summary = drape_job(args)
    m = summary["mean"]
    extra = "".join(f"  {k} {m[k]:.3f}" for k in ("e_dist", "e_norm") if k in m)
    print(f"{summary['frames']} frames -> {args.out}: eps_e {m['eps_e']:.2f} %  eps_a "
          f"{m['eps_a']:.2f} %  eps_c {m['eps_c']:.3f} %  {m['ms_per_frame']:.2f} CPU ms/frame"
          f"{extra}  ({time.perf_counter() - t0:.1f} s wall)")
    return 0
