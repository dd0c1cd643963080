"""``polygeo drape-reference`` and the draping part of ``polygeo demo`` (entry-point plug-ins).

Heavy modules (torch, the body, the solver) are imported inside the commands so that
``polygeo --help`` stays fast.
"""

from __future__ import annotations

import argparse
import sys
import tempfile

from .names import GARMENTS, MOTIONS, PHENOTYPES

__all__ = ["register", "run", "demo", "add_scene_arguments", "DEMO_FRAMES", "DEMO_VERTICES"]


#: Frames of the ``polygeo demo`` drape (a T-shirt on a walking body).
DEMO_FRAMES = 3
#: Garment vertices of the demo (a coarse template, made in ~10-20 s, keeps it near a minute).
DEMO_VERTICES = 1000


def add_scene_arguments(p: argparse.ArgumentParser, *, frames: int, seed_help: str) -> None:
    """Add the body and motion options every drape command shares.

    ``--motion``, ``--motion-file``, ``--frames`` (default ``frames``), ``--shape`` and
    ``--seed`` (described by ``seed_help``), with the same names, units and meanings in
    ``polygeo drape-reference`` and ``polygeo drape``.
    """
    p.add_argument("--motion", default="walk", metavar="NAME",
                   help=f"procedural motion, one of {', '.join(MOTIONS)} (random: a seeded "
                   "random smooth motion); 30 frames per second (default walk)")
    p.add_argument("--motion-file", default=None, metavar="FILE",
                   help="motion .npz with 'rotations' (T, 104, 3) axis-angle per Anny bone in "
                   "radians, 'translation' (T, 3) in metres and optional 'fps' (frames per "
                   "second, default 30); replaces --motion (default: none, use --motion)")
    p.add_argument("--frames", type=int, default=frames, metavar="T",
                   help=f"number of frames, >= 1 (default {frames}, i.e. {frames / 30:g} s at "
                   "30 fps)")
    p.add_argument("--shape", default="", metavar="NAME=V,...",
                   help=f"body phenotypes, values in [0, 1], names among {', '.join(PHENOTYPES)}"
                   " (others 0.5, the default adult), e.g. \"age=0.66,gender=0.2\"")
    p.add_argument("--seed", type=int, default=0, help=seed_help)


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``drape-reference`` sub-command (entry point of ``polygeo.commands``)."""
    p = sub.add_parser(
        "drape-reference",
        help="physics reference drape of a garment on a moving body (Anny)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=(
            "Drape a garment on the free Anny body moving through a motion by minimising the\n"
            "cloth energies (StVK membrane, bending, gravity, body collision) per frame:\n"
            "frame 0 is a static drape of the rest pose, later frames are backward-Euler steps\n"
            "of 1/fps s (or static drapes with --static). Units: metres, seconds, joules.\n\n"
            "Writes OUT/meshes/000000.ply ... (garment, m), OUT/body/000000.ply ... (posed\n"
            "body, m), OUT/garment.npz (rest garment), OUT/metrics.json (per frame, mean and\n"
            "max: eps_e and eps_a = mean % change of edge lengths and triangle areas against\n"
            "the rest garment, eps_c = % of garment vertices inside the body, energy in J,\n"
            "solver iterations, seconds per frame: wall clock and CPU), OUT/strip.png and\n"
            "OUT/drape.gif, and OUT/checkpoint.pt after every frame: rerunning the same\n"
            "command resumes an interrupted run at the next frame with identical results."
        ),
        epilog="example: polygeo drape-reference --garment tshirt --motion walk --frames 60 "
               '--shape "age=0.66,gender=0.2" -o OUT',
    )
    p.add_argument("--garment", default="tshirt", metavar="NAME",
                   help=f"garment template, one of {', '.join(GARMENTS)} (default tshirt)")
    p.add_argument("--garment-file", default=None, metavar="FILE",
                   help="garment mesh (OBJ/PLY/OFF/STL) in the rest pose of the default body, "
                   "metres; checked (manifold, consistent winding, no degenerate triangles, "
                   "outside the body); replaces --garment (default: none, use --garment)")
    add_scene_arguments(p, frames=30, seed_help="integer seed of the random motion and of "
                        "generated garments (with --res; default 0)")
    p.add_argument("--res", type=int, default=None, metavar="N",
                   help="garment vertex count, 1000..100000 (default: the shipped 5000-vertex "
                   "template; another count generates one, ~10-20 s)")
    p.add_argument("--static", action="store_true",
                   help="static drape of every frame's pose (no dynamics) instead of a "
                   "dynamic sequence (default off: frame 0 static, later frames backward Euler)")
    p.add_argument("--tol", type=float, default=None,
                   help="solver tolerance: residual force / garment weight, dimensionless "
                   "(default 1e-2)")
    p.add_argument("-o", "--out", required=True, metavar="OUT",
                   help="output folder, created if missing (required; no default)")
    p.add_argument("--no-resume", action="store_true",
                   help="start afresh, ignoring a checkpoint in OUT (default off: resume "
                   "from OUT/checkpoint.pt when its settings match)")
    p.add_argument("--no-pictures", action="store_true",
                   help="skip the PNG strip and the GIF (default off: both are written)")
    p.add_argument("--quiet", action="store_true",
                   help="no progress bar (default off: a tqdm bar over frames)")
    p.set_defaults(func=run)


def _job(args: argparse.Namespace):
    from .drape import DrapeJob, parse_shape

    return DrapeJob(
        garment=args.garment, garment_file=args.garment_file, motion=args.motion,
        motion_file=args.motion_file, frames=args.frames, shape=parse_shape(args.shape),
        seed=args.seed, res=args.res, static=args.static,
    )


def _table(summary: dict, title: str) -> None:
    print(title)
    print("  frame  eps_e(%)  eps_a(%)  eps_c(%)  energy(J)  iters  s/frame  cpu s")
    for r in summary["per_frame"]:
        print(f"  {r['frame']:5d}  {r['eps_e']:8.3f}  {r['eps_a']:8.3f}  {r['eps_c']:8.3f}  "
              f"{r['energy']:9.4f}  {r['iterations']:5d}  {r['seconds']:7.2f}  "
              f"{r.get('cpu_seconds', float('nan')):5.2f}")
    m, x = summary["mean"], summary["max"]
    print(f"  mean   {m['eps_e']:8.3f}  {m['eps_a']:8.3f}  {m['eps_c']:8.3f}  {m['energy']:9.4f}  "
          f"{m['iterations']:5.0f}  {m['seconds']:7.2f}  {m.get('cpu_seconds', float('nan')):5.2f}")
    print(f"  max    {x['eps_e']:8.3f}  {x['eps_a']:8.3f}  {x['eps_c']:8.3f}  {x['energy']:9.4f}  "
          f"{x['iterations']:5.0f}  {x['seconds']:7.2f}  {x.get('cpu_seconds', float('nan')):5.2f}")
    print(f"  ({summary['garment_vertices']} garment vertices, dt = {summary['dt']:.4f} s; "
          "eps_e / eps_a: mean % change of edge lengths / areas, eps_c: % vertices inside "
          "the body)")


def run(args: argparse.Namespace) -> int:
    """Run ``polygeo drape-reference``; bad input raises ``ValueError`` (exit status 2)."""
    import dataclasses

    import torch

    from polygeo.runs import CheckpointError

    from .drape import DEFAULT_SOLVER, run_drape

    torch.set_num_threads(1)
    job = _job(args)
    solver = DEFAULT_SOLVER
    if args.tol is not None:
        if not args.tol > 0:
            raise ValueError(f"--tol: expected a value > 0, got {args.tol}")
        solver = dataclasses.replace(solver, tol=float(args.tol))
    try:
        res = run_drape(job, args.out, solver, resume=not args.no_resume, quiet=args.quiet,
                        pictures=not args.no_pictures)
    except CheckpointError as exc:
        raise ValueError(f"{exc} (or pass --no-resume)") from None
    what = job.garment_file or job.garment
    how = "static" if job.static else "dynamic"
    resumed = f", resumed at frame {res.resumed_at}" if res.resumed_at else ""
    _table(res.summary, f"{what} on {job.motion_file or job.motion}, {how}, "
           f"{len(res.rows)} frames{resumed} -> {res.out_dir}")
    return 0


def demo(args: argparse.Namespace) -> int:
    """Drape the shipped T-shirt on a walking body for a few frames; print the metric table."""
    import torch

    from .drape import DrapeJob, run_drape

    torch.set_num_threads(1)
    out = getattr(args, "out", None)
    tmp = None
    if out is None:
        tmp = tempfile.TemporaryDirectory(prefix="polygeo-drape-demo-")
        out = tmp.name
    job = DrapeJob(garment="tshirt", motion="walk", frames=DEMO_FRAMES, res=DEMO_VERTICES)
    res = run_drape(job, f"{out}/drape", resume=False, quiet=bool(getattr(args, "quiet", False)),
                    pictures=False)
    _table(res.summary, f"Reference drape: T-shirt ({DEMO_VERTICES} vertices) on a walking "
           f"Anny body, {DEMO_FRAMES} frames (outputs in {out}/drape):")
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":  # pragma: no cover
    ap = argparse.ArgumentParser(prog="python -m draping.cli")
    sp = ap.add_subparsers(dest="command")
    register(sp)
    a = ap.parse_args()
    sys.exit(a.func(a) if getattr(a, "func", None) else 2)
