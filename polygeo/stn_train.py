"""Training :class:`polygeo.stn.PatchSTN` on the height residual of n-jet fits (thesis §5.5.1).

The run is a driver (:func:`train_stn`) over named stages:

1. settings (:class:`TrainConfig`) checked, the network, Adam and a cosine schedule built from
   the seed (:func:`_new_run`);
2. resume: the run folder's checkpoint is continued only if it was written with the same
   settings (keyed by :func:`polygeo.runs.fingerprint` of the :class:`TrainConfig`); a
   checkpoint of other settings, of an older polygeo or carrying pickled objects is refused
   (:func:`_restore_run`);
3. data: training and held-out patches drawn once and cached with the network's per-point
   features (:func:`training_batch`, :func:`mesh_patch_pool`, :func:`_training_data`);
4. steps (:func:`_train_step`), validations with model selection and early stopping
   (:func:`_validate`), checkpoints written atomically (:func:`_save_run`,
   :func:`polygeo.runs.save_checkpoint`), a progress bar (:func:`polygeo.runs.progress`).

Checkpoints hold plain tensors and JSON (:mod:`polygeo.runs`): resuming a run folder received
from someone else runs no code.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from . import runs
from .canonical import canonicalize, height_residual
from .checks import check_int
from .frames import quaternion_to_matrix, random_rotation
from .stn import PatchSTN
from .stn_settings import TrainConfig

__all__ = [
    "TrainConfig",
    "train_stn",
    "training_batch",
    "mesh_patch_pool",
    "CHECKPOINT_FILE",
]

#: File name of the training checkpoint inside ``checkpoint_dir``.
CHECKPOINT_FILE = "stn_checkpoint.pt"


def _pad_patch(pts: np.ndarray, n_points: int, rng: np.random.Generator) -> tuple:
    """Subsample (or pad with a mask) one patch to ``n_points`` points."""
    out = np.zeros((n_points, 3))
    m = np.zeros(n_points, bool)
    if len(pts) >= n_points:
        sel = rng.choice(len(pts), n_points, replace=False)
        out[:] = pts[sel]
        m[:] = True
    else:
        out[: len(pts)] = pts
        m[: len(pts)] = True
    return out, m


def mesh_patch_pool(seeds: tuple[int, ...] = (0,), *, min_points: int = 20) -> list[np.ndarray]:
    """Patches of procedural garment-like meshes, partitioned with the default K.

    For each seed: a draped sheet, a skirt and a body-like closed surface (the latter only
    for seeds 0 and 100, where its shape does not depend on the seed), each partitioned by
    :func:`polygeo.partition.partition_mesh` with the thesis' default patch count.

    Parameters
    ----------
    seeds : tuple of int
        Mesh seeds (fold phases and depths, sheet and skirt sizes).
    min_points : int
        Patches with fewer vertices are dropped.

    Returns
    -------
    list of np.ndarray
        One ``(n_k, 3)`` float64 array of vertex positions per patch (metres).
    """
    from . import synthetic
    from .partition import partition_mesh

    pool: list[np.ndarray] = []
    for sd in seeds:
        rng = np.random.default_rng([sd, 7])
        meshes = [
            synthetic.draped_sheet_mesh(
                110,
                size=float(rng.uniform(0.8, 1.3)),
                n_folds=int(rng.integers(3, 7)),
                fold_depth=float(rng.uniform(0.02, 0.08)),
                seed=sd,
            ),
            synthetic.skirt_mesh(
                180,
                90,
                hem=float(rng.uniform(0.28, 0.42)),
                n_folds=int(rng.integers(6, 12)),
                fold_depth=float(rng.uniform(0.015, 0.05)),
                seed=sd,
            ),
        ]
        if sd in (0, 100):
            meshes.append(synthetic.body_mesh(5))
        for v, f in meshes:
            part = partition_mesh(v, f, seed=sd)
            order = np.argsort(part.labels, kind="stable")
            bounds = np.cumsum(np.bincount(part.labels, minlength=part.n_patches))[:-1]
            for idx in np.split(order, bounds):
                if len(idx) >= min_points:
                    pool.append(v[idx])
    return pool


def _grid_family_points(
    n: int, n_points: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Family sums on jittered grids, padded: :func:`polygeo.synthetic.family_grid_patches`."""
    from . import synthetic

    return synthetic.family_grid_patches(n, n_points, seed=rng)


def training_batch(
    n: int,
    n_points: int,
    rng: np.random.Generator,
    *,
    pool: list[np.ndarray] | None = None,
    mesh_share: float = 0.0,
    grid_share: float = 0.0,
    noise: float = 0.02,
) -> tuple[torch.Tensor, torch.Tensor]:
    """A batch of canonical training patches (synthetic families and mesh patches).

    Parameters
    ----------
    n : int
        Patches.
    n_points : int
        Points per patch (mesh patches are subsampled or padded with the mask).
    rng : numpy.random.Generator
        Randomness.
    pool : list of np.ndarray, optional
        Mesh patches (:func:`mesh_patch_pool`); required when ``mesh_share > 0``.
    mesh_share : float
        Share of mesh patches in the batch.
    grid_share : float
        Share of the synthetic patches sampled on jittered grids (the rest irregularly).
    noise : float
        Largest noise standard deviation of synthetic patches (canonical units).

    Returns
    -------
    local : torch.Tensor
        ``(n, n_points, 3)`` float64 canonical points (:func:`polygeo.canonical.canonicalize`).
    mask : torch.Tensor
        ``(n, n_points)`` bool.
    """
    from . import synthetic

    n_mesh = int(round(n * mesh_share)) if pool else 0
    n_syn = n - n_mesh
    n_grid = int(round(n_syn * grid_share))
    n_irr = n_syn - n_grid
    pts = np.zeros((n, n_points, 3))
    msk = np.zeros((n, n_points), bool)
    if n_irr:
        fp = synthetic.family_patches(n_irr, n_points, noise=0.0, seed=rng)
        pts[:n_irr] = fp.points
        msk[:n_irr] = True
    if n_grid:
        pts[n_irr:n_syn], msk[n_irr:n_syn] = _grid_family_points(n_grid, n_points, rng)
    if n_syn:
        sig = rng.uniform(0.0, noise, (n_syn, 1, 1))
        pts[:n_syn] += sig * rng.normal(size=(n_syn, n_points, 3)) * msk[:n_syn, :, None]
    if n_mesh:
        pick = rng.integers(0, len(pool), n_mesh)
        gen = torch.Generator().manual_seed(int(rng.integers(2**62)))
        rot = random_rotation(n_mesh, gen).to(torch.float64).numpy()
        for i, k in enumerate(pick):
            p, m = _pad_patch(pool[k], n_points, rng)
            pts[n_syn + i] = p @ rot[i].T
            msk[n_syn + i] = m
    c = canonicalize(torch.from_numpy(pts), torch.from_numpy(msk))
    return c.local, c.mask



def _cached_set(
    net: PatchSTN, n: int, cfg: TrainConfig, rng: np.random.Generator, pool, chunk: int = 1024
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``n`` canonical patches, their masks and the network's per-point features (float32)."""
    locs, masks, feats = [], [], []
    for i in range(0, n, chunk):
        b = min(chunk, n - i)
        loc, m = training_batch(
            b,
            cfg.n_points,
            rng,
            pool=pool,
            mesh_share=cfg.mesh_share,
            grid_share=cfg.grid_share,
            noise=cfg.noise,
        )
        locs.append(loc)
        masks.append(m)
        feats.append(net.point_features(loc.float(), m).float())
    return torch.cat(locs), torch.cat(masks), torch.cat(feats)


# --------------------------------------------------------------------------------------------
# The stages of a run
# --------------------------------------------------------------------------------------------


@dataclass
class _Run:
    """What a checkpoint holds: the network, its optimiser and schedule, the history."""

    net: PatchSTN
    opt: torch.optim.Optimizer
    sched: torch.optim.lr_scheduler.LRScheduler
    history: dict
    best_state: dict | None = None
    since_best: int = 0
    step: int = 0


class _Data(NamedTuple):
    """Cached training and held-out patches, their masks and per-point features."""

    x_loc: torch.Tensor
    x_mask: torch.Tensor
    x_feat: torch.Tensor
    v_loc: torch.Tensor
    v_mask: torch.Tensor
    v_feat: torch.Tensor
    v_pca: float


class _Clock:
    """Wall and CPU seconds of this process, added to a history at each checkpoint."""

    def __init__(self) -> None:
        self.t0, self.c0 = time.perf_counter(), time.process_time()

    def add_to(self, history: dict) -> None:
        t, c = time.perf_counter(), time.process_time()
        history["seconds"] += t - self.t0
        history["cpu_seconds"] += c - self.c0
        self.t0, self.c0 = t, c


def _check_config(cfg: TrainConfig) -> None:
    check_int(cfg.steps, "steps", low=0)
    check_int(cfg.batch_size, "batch_size", low=1)
    check_int(cfg.n_train, "n_train", low=1)
    check_int(cfg.n_val, "n_val", low=1)
    check_int(cfg.patience, "patience", low=0)
    check_int(cfg.eval_every, "eval_every", low=1)
    check_int(cfg.checkpoint_every, "checkpoint_every", low=1)


def _new_run(cfg: TrainConfig) -> _Run:
    """Network (seeded), Adam and the cosine schedule to ``lr / 20``; an empty history."""
    torch.manual_seed(cfg.seed)
    net = PatchSTN(
        tuple(cfg.widths),
        tuple(cfg.head),
        features=cfg.features,
        output=cfg.output,
        canonical_signs=cfg.canonical_signs,
        context=cfg.context,
    )
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    n_steps = max(cfg.steps, 1)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda i: 0.05 + 0.475 * (1 + math.cos(math.pi * min(i, n_steps) / n_steps))
    )
    cfg_dict = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(cfg).items()}
    history = {"config": cfg_dict, "val": [], "loss": [], "best": None, "stopped_at": None,
               "seconds": 0.0, "cpu_seconds": 0.0}
    return _Run(net, opt, sched, history)


def _save_run(run: _Run, path: Path, fp: str) -> None:
    """Checkpoint (atomically) and ``history.json`` beside it."""
    tensors = {
        "state_dict": run.net.state_dict(),
        "optimizer": run.opt.state_dict(),
        "scheduler": run.sched.state_dict(),
        "best_state": run.best_state or {},
    }
    meta = {
        "fingerprint": fp,
        "step": run.step,
        "config": run.net.config(),
        "history": run.history,
        "since_best": run.since_best,
        "has_best": run.best_state is not None,
    }
    runs.save_checkpoint(path, tensors, meta)
    runs.atomic_write_json(path.parent / "history.json", run.history)


def _restore_run(run: _Run, path: Path, fp: str) -> None:
    """Continue ``run`` from the checkpoint at ``path`` if it has the same settings."""
    try:
        ck = runs.resume_state(path.parent, fp, name=path.name)
    except runs.SettingsChangedError as exc:
        raise runs.SettingsChangedError(
            f"checkpoint_dir: {str(path)!r} was written with another configuration (the "
            "TrainConfig changed); use another folder or resume=False"
        ) from exc
    except runs.CheckpointError as exc:
        raise runs.CheckpointError(
            f"checkpoint_dir: {exc}; use another folder or resume=False"
        ) from exc
    if ck is None:
        return
    t, m = ck
    run.net.load_state_dict(t["state_dict"])
    run.opt.load_state_dict(t["optimizer"])
    run.sched.load_state_dict(t["scheduler"])
    run.best_state = t["best_state"] if m["has_best"] else None
    run.history = m["history"]
    run.since_best = int(m["since_best"])
    run.step = int(m["step"])


def _training_data(cfg: TrainConfig, net: PatchSTN) -> _Data:
    """Training and held-out sets, drawn once from the seed (other seeds and meshes held out)."""
    pool = mesh_patch_pool(tuple(cfg.mesh_seeds)) if cfg.mesh_share > 0 else None
    val_pool = mesh_patch_pool(tuple(cfg.val_mesh_seeds)) if cfg.mesh_share > 0 else None
    with torch.no_grad():
        x = _cached_set(net, cfg.n_train, cfg, np.random.default_rng([cfg.seed, 2]), pool)
        v = _cached_set(net, cfg.n_val, cfg, np.random.default_rng([cfg.seed, 10**9]), val_pool)
        v_pca = float(height_residual(v[0], v[1], None, cfg.order)[0].mean())
    return _Data(*x, *v, v_pca)


def _train_step(run: _Run, data: _Data, cfg: TrainConfig, step: int) -> float:
    """One Adam step on a batch drawn from ``(seed, step)``; returns the loss."""
    rng = np.random.default_rng([cfg.seed, step])
    idx = torch.from_numpy(rng.choice(cfg.n_train, min(cfg.batch_size, cfg.n_train),
                                      replace=False))
    local, mask = data.x_loc[idx], data.x_mask[idx]
    q = run.net(local.float(), mask, data.x_feat[idx])
    r, _ = height_residual(local, mask, quaternion_to_matrix(q.double()), cfg.order)
    loss = r.mean()
    run.opt.zero_grad()
    loss.backward()
    run.opt.step()
    run.sched.step()
    value = float(loss.detach())
    run.history["loss"].append(value)
    return value


def _validate(
    run: _Run, data: _Data, cfg: TrainConfig, log: Callable[[str], None] | None
) -> None:
    """Held-out residual at ``run.step``; keeps the best weights and counts the patience."""
    net, history = run.net, run.history
    net.eval()
    with torch.no_grad():
        q = net(data.v_loc.float(), data.v_mask, data.v_feat)
        rot = quaternion_to_matrix(q.double())
        r = float(height_residual(data.v_loc, data.v_mask, rot, cfg.order)[0].mean())
    net.train()
    v_pca = data.v_pca
    rec = {"step": run.step, "pca": v_pca, "stn": r, "ratio": r / v_pca}
    history["val"].append(rec)
    if history["best"] is None or r < history["best"]["stn"]:
        history["best"] = rec
        run.best_state = {k: v.detach().clone() for k, v in net.state_dict().items()}
        run.since_best = 0
    else:
        run.since_best += 1
    if log is not None:
        best = history["best"]
        log(
            f"step {run.step}: held-out height RMS pca {v_pca:.5f} stn {r:.5f} "
            f"(ratio {r / v_pca:.3f}; best {best['ratio']:.3f} at step {best['step']})"
        )


def train_stn(
    config: TrainConfig | None = None,
    *,
    checkpoint_dir: str | os.PathLike | None = None,
    resume: bool = True,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
) -> tuple[PatchSTN, dict]:
    """Train :class:`polygeo.stn.PatchSTN` on the height residual of n-jet fits.

    A training set of ``n_train`` patches is drawn once (sums of the four synthetic families,
    randomly rotated, irregularly or grid sampled, noisy; plus patches of garment-like
    meshes), canonicalised by PCA, with the network's per-point features cached. Every step
    draws a batch from it, predicts the refinement rotation, rotates, fits an n-jet and
    minimises the mean RMS height residual with Adam (the gradient of the least-squares
    solve by the envelope theorem, :func:`polygeo.canonical.height_residual`). Every
    ``eval_every`` steps the mean residual on ``n_val`` held-out patches (other seeds, other
    meshes) is measured; the best validated weights are kept and training stops early after
    ``patience`` validations without improvement.

    Parameters
    ----------
    config : TrainConfig, optional
        Settings (default :class:`TrainConfig`).
    checkpoint_dir : str or os.PathLike, optional
        Folder of :data:`CHECKPOINT_FILE` (written every ``checkpoint_every`` steps,
        atomically, by :func:`polygeo.runs.save_checkpoint`) and ``history.json``; with
        ``resume=True`` an existing checkpoint of the same settings is continued.
    resume : bool
        Continue from an existing checkpoint of the same configuration.
    progress : bool
        Show a tqdm bar.
    log : callable, optional
        Receives one line per validation.

    Returns
    -------
    model : PatchSTN
        The best validated network (eval mode).
    history : dict
        ``{"config", "val": [{"step", "pca", "stn", "ratio"}...], "loss": [...], "best",
        "stopped_at", "seconds", "cpu_seconds"}``; residuals are mean RMS heights in
        canonical units on the held-out set; ``seconds`` (wall) and ``cpu_seconds`` (this
        process, all threads) include drawing the cached data.

    Raises
    ------
    polygeo.runs.SettingsChangedError
        (a ``ValueError``) if the checkpoint was written with another configuration.
    polygeo.runs.CheckpointError
        (a ``ValueError``) if the checkpoint cannot be read safely: written by an older
        polygeo, truncated, or carrying pickled objects.
    ValueError
        On bad settings.
    """
    cfg = TrainConfig() if config is None else config
    _check_config(cfg)
    clock = _Clock()
    if cfg.threads:
        torch.set_num_threads(int(cfg.threads))
    # 1. network, optimiser, schedule; 2. resume from a checkpoint of the same settings
    run = _new_run(cfg)
    fp = runs.fingerprint(cfg)
    ckpt = None if checkpoint_dir is None else Path(checkpoint_dir) / CHECKPOINT_FILE
    if ckpt is not None and resume:
        _restore_run(run, ckpt, fp)
    # 3. cached training and held-out data
    data = _training_data(cfg, run.net)
    # 4. steps, validations, early stopping, checkpoints
    stopped = run.history["stopped_at"] is not None
    run.net.train()
    bar = runs.progress(range(run.step, cfg.steps), initial=run.step, total=cfg.steps,
                        desc="train-stn", quiet=not progress or stopped)
    for step in bar:
        if stopped:
            break
        loss = _train_step(run, data, cfg, step)
        bar.set_postfix(loss=f"{loss:.4f}")
        run.step = done = step + 1
        if done % cfg.eval_every == 0 or done == cfg.steps:
            _validate(run, data, cfg, log)
            if cfg.patience and run.since_best >= cfg.patience:
                run.history["stopped_at"] = done
                stopped = True
        if ckpt is not None and (stopped or done % cfg.checkpoint_every == 0
                                 or done == cfg.steps):
            clock.add_to(run.history)
            _save_run(run, ckpt, fp)
    bar.close()
    if not run.history["val"]:
        _validate(run, data, cfg, log)
    clock.add_to(run.history)
    if run.best_state is not None:
        run.net.load_state_dict(run.best_state)
    run.net.eval()
    return run.net, run.history
