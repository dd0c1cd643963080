"""``polygeo train-stn``: train the rigid spatial transformer of PolyFit (reproducible)."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    from polygeo.stn_settings import TrainConfig

    d = TrainConfig()
    p = sub.add_parser(
        "train-stn",
        help="train the PolyFit STN on synthetic patch families and garment-like meshes",
        description="Trains polygeo.stn.PatchSTN by minimising the n-jet height residual after "
        "rotation (thesis 5.5.1), on sums of 4-jet, trigonometric, Gaussian and Bessel patches "
        "(irregular and grid samples) plus patches of procedural garment-like meshes, drawn "
        "once and cached. Keeps the best weights on a held-out set and stops early. "
        "Deterministic for a seed; writes checkpoints and resumes from them. The defaults are "
        "those of the shipped weights; copy the result (.pt and .json) to "
        "polygeo/data/stn_weights.* to ship it.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("--out", default="stn_weights.pt",
                   help="weights file to write (.pt, with a .json of its config, command, time "
                   "and figures beside it)")
    p.add_argument("--checkpoint-dir", default="stn_checkpoints",
                   help="checkpoint folder (resumed if it holds a checkpoint of the same setup)")
    p.add_argument("--no-resume", action="store_true", help="ignore an existing checkpoint")
    p.add_argument("--steps", type=int, default=d.steps, help="largest number of Adam steps")
    p.add_argument("--batch-size", type=int, default=d.batch_size, help="patches per step")
    p.add_argument("--points", type=int, default=d.n_points, help="points per patch")
    p.add_argument("--train-patches", type=int, default=d.n_train,
                   help="cached training patches (drawn once)")
    p.add_argument("--val-patches", type=int, default=d.n_val, help="held-out validation patches")
    p.add_argument("--lr", type=float, default=d.lr, help="Adam learning rate (per step, on the "
                   "network's weights)")
    p.add_argument("--order", type=int, default=d.order,
                   help="jet order of the height residual minimised after rotation")
    p.add_argument("--mesh-share", type=float, default=d.mesh_share,
                   help="fraction in [0, 1] of the training patches cut from garment-like meshes")
    p.add_argument("--patience", type=int, default=d.patience,
                   help="validations without improvement before stopping (0: never)")
    p.add_argument("--seed", type=int, default=d.seed, help="seed of data and initialisation")
    p.add_argument("--threads", type=int, default=d.threads, help="torch CPU threads")
    p.add_argument("--eval-every", type=int, default=d.eval_every,
                   help="Adam steps between validations on the held-out patches")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from polygeo.runs import atomic_write_json
    from polygeo.stn import save_weights
    from polygeo.stn_train import TrainConfig, train_stn

    cfg = TrainConfig(
        steps=args.steps,
        batch_size=args.batch_size,
        n_points=args.points,
        n_train=args.train_patches,
        n_val=args.val_patches,
        lr=args.lr,
        order=args.order,
        mesh_share=args.mesh_share,
        patience=args.patience,
        seed=args.seed,
        threads=args.threads,
        eval_every=args.eval_every,
        checkpoint_every=args.eval_every,
    )
    model, hist = train_stn(
        cfg,
        checkpoint_dir=args.checkpoint_dir,
        resume=not args.no_resume,
        progress=not args.quiet,
        log=print,
    )
    best = hist["best"]
    meta = {
        "config": hist["config"],
        "validation": best,
        "stopped_at": hist["stopped_at"],
        "steps_run": len(hist["loss"]),
        "train_seconds": hist["seconds"],
        "train_cpu_seconds": hist["cpu_seconds"],
    }
    out = save_weights(model, args.out, meta=meta)
    print(
        f"held-out height RMS (best, step {best['step']}): pca {best['pca']:.5f}, "
        f"stn {best['stn']:.5f} (ratio {best['ratio']:.3f}); {len(hist['loss'])} steps, "
        f"{hist['seconds']:.0f} s wall, {hist['cpu_seconds']:.0f} s CPU; wrote {out}"
    )
    atomic_write_json(Path(out).with_suffix(".json"), meta)
    return 0
