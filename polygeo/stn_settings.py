"""Settings of the STN training (:func:`polygeo.stn_train.train_stn`), importable without torch.

Kept apart from :mod:`polygeo.stn_train` so that ``polygeo train-stn --help`` states every
default without importing torch; :mod:`polygeo.stn_train` re-exports :class:`TrainConfig`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["TrainConfig"]


@dataclass
class TrainConfig:
    """Settings of :func:`train_stn`.

    The defaults are those of the shipped weights (``polygeo/data/stn_weights.json`` records
    the CPU and wall time of that run). Training runs on one thread: on a shared two-core
    machine a second intra-op thread mostly spin-waits (measured: about six times the CPU
    seconds per step of a single thread).

    Attributes
    ----------
    steps : int
        Largest number of optimisation steps.
    batch_size : int
        Patches per step (thesis: 512).
    n_points : int
        Points per training patch.
    lr : float
        Adam learning rate (thesis: 1e-3), cosine-decayed to ``lr / 20`` over ``steps``.
    order : int
        Jet order of the residual (thesis: 4).
    mesh_share : float
        Share of the training patches cut from garment-like meshes (the rest are sums of the
        four synthetic families of §5.5.1).
    grid_share : float
        Share of the synthetic patches sampled on a jittered grid rather than irregularly
        (the grid patches of the tests and benchmark, many of which PCA folds over).
    noise : float
        Largest standard deviation of the positional noise of synthetic patches (canonical
        units, the patch spans [-1, 1]).
    widths, head : tuple of int
        Network size (:class:`polygeo.stn.PatchSTN`).
    features, output : str
        Input and rotation parametrisation of :class:`polygeo.stn.PatchSTN`.
    canonical_signs, context : bool
        Third-moment sign canonicalisation and global context of :class:`polygeo.stn.PatchSTN`.
    seed : int
        Seed of the network initialisation, the cached training set and every batch (batch
        ``i`` is drawn from ``(seed, i)``, so that a resumed run sees the same data).
    n_train : int
        Cached training patches, drawn once (the batches draw from them).
    n_val : int
        Held-out validation patches (other seeds, other meshes), for model selection and early
        stopping.
    eval_every : int
        Validation period in steps.
    checkpoint_every : int
        Checkpoint period in steps.
    patience : int
        Stop after this many validations without a better held-out residual (0: never);
        the best validated weights are returned.
    threads : int
        Torch intra-op threads during training (0: leave as is).
    mesh_seeds, val_mesh_seeds : tuple of int
        Seeds of the garment-like meshes of :func:`mesh_patch_pool` for training and for
        validation.
    """

    steps: int = 2000
    batch_size: int = 256
    n_points: int = 128
    lr: float = 2e-3
    order: int = 4
    mesh_share: float = 0.3
    grid_share: float = 0.2
    noise: float = 0.02
    widths: tuple[int, ...] = (32, 64, 128)
    head: tuple[int, ...] = (64, 32)
    features: str = "normals"
    output: str = "tilt"
    canonical_signs: bool = True
    context: bool = False
    seed: int = 0
    n_train: int = 16384
    n_val: int = 1024
    eval_every: int = 100
    checkpoint_every: int = 100
    patience: int = 5
    threads: int = 1
    mesh_seeds: tuple[int, ...] = field(default=(0, 1, 2, 3))
    val_mesh_seeds: tuple[int, ...] = field(default=(50,))
