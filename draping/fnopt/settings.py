"""Settings and names of FNOpt that the command line needs, importable without torch.

The one home of :class:`TrainSettings` (``polygeo train-fnopt``), the handle layouts
``LAYOUTS``, the handle motions ``MOTIONS`` and the optimiser names ``OPTIMIZERS`` of
``polygeo simulate``; :mod:`draping.fnopt.train`, :mod:`~draping.fnopt.cloth`,
:mod:`~draping.fnopt.handles` and :mod:`~draping.fnopt.simulate` re-export them. Kept free of
torch so that ``polygeo train-fnopt --help`` and ``polygeo simulate --help`` answer at once.
"""

from __future__ import annotations

from dataclasses import dataclass

from polygeo.checks import check_int, check_positive

__all__ = ["TrainSettings", "HANDLE_DISTRIBUTIONS", "LAYOUTS", "MOTIONS", "OPTIMIZERS"]

#: Handle layouts as fractional grid coordinates ``(row, col)`` in ``[0, 1]`` (row 0: top edge).
LAYOUTS: dict[str, tuple[tuple[float, float], ...]] = {
    "corners": ((0.0, 0.0), (0.0, 1.0)),
    "diagonal": ((0.0, 0.0), (1.0, 1.0)),
    "mid-edges": ((0.5, 0.0), (0.5, 1.0)),
    "corner-centre": ((0.0, 0.0), (0.5, 0.5)),
    "single": ((0.0, 0.5),),
    "single-centre": ((0.5, 0.5),),
}

#: Motion names accepted by :func:`draping.fnopt.handles.handle_targets`.
MOTIONS = ("x", "y", "z", "xy", "xyz", "x-rev", "y-rev", "z-rev", "xy-rev", "xyz-rev",
           "rot-a", "rot-b", "rot-a-rev", "rot-b-rev", "still")

#: Optimisers of ``polygeo simulate``.
OPTIMIZERS = ("fnopt", "gd", "adam", "lbfgs", "pcg", "reference")

#: ``polygeo simulate --coarse K`` (``pcg`` or ``fnopt``): by default the two-level coarse space
#: is rebuilt every this many frames (``SimSettings.coarse_every``, ``solve_pcg(coarse_every=...)``,
#: ``solve_fnopt(two_level_every=...)``; its build costs about 20 PCG iterations at 64x64).
COARSE_EVERY = 8

#: ``polygeo simulate --optimizer fnopt``'s default two-level coarse direction (``--coarse 0``:
#: off): the coarse grid's longer side (``SimSettings.coarse``), its rebuild period in frames
#: (``coarse_every``) and the first inner iteration it joins (``coarse_from``; iteration 0 is the
#: FNO's and the classical directions' alone). Chosen in session 19 on cases drawn for the
#: choice only (``docs/measurements/fnopt.md``, rules L9 / L9b).
FNOPT_COARSE = 16
FNOPT_COARSE_EVERY = 4
FNOPT_COARSE_FROM = 1

#: Handle distributions of the training pool (see :func:`draping.fnopt.train.random_handles`).
HANDLE_DISTRIBUTIONS = ("random", "corners-interior", "folding")


@dataclass(frozen=True)
class TrainSettings:
    """Settings of ``polygeo train-fnopt`` (the fingerprint of a resumable run).

    The defaults are the settings of the shipped ``draping/data/fnopt_model.pt``: width 16, 8 modes,
    the pick of the parsimony sweep at this budget without the normal direction
    (``benchmarks/fnopt_sweep.py --steps 7000``: 16x4 / 16x8 / 32x4 / 32x8 / 64x4 reached
    validation sub-optimality 0.031 / 0.028 / 0.042 / 0.028 / 0.032; the fewest parameters within
    10 % of the best); with it (``fnopt_sweep_normal4.json``) the sweep's rule picks 32x4, which
    ties the shipped weights on the validation rollouts (one seed), so 16x8 stays; 7000 steps,
    handle sets drawn by :func:`random_handles`
    (``handles="random"``; ``"corners-interior"`` was the distribution of the first weights;
    ``"folding"`` draws half the sheets with a two-pin folding layout, an option),
    the subspace step (``step_rule``, the only rule: :func:`draping.fnopt.model.subspace_update`
    differentiated through) with the out-of-plane direction cut into its lowest 4 x 4 DCT modes
    and the rest (``normal=True, normal_split=4``): over three seeds each, better than without
    it on validation rollouts at 48x48 (geometric-mean e_CD x 1e3 2.07 / 2.13 / 1.91 against
    4.82 / 4.40 / 4.92; worst case a tie, 37-39 against 31-40); the shipped weights are its
    seed 0, the median (trained by the code before commit 7e8bb74, whose rounding change in the
    normal direction makes a run today differ from them). ``iter_weight``: a pool entry at its
    ``k``-th inner iteration weighs ``1 + iter_weight k / 10`` in the training loss (0, the
    shipped weights: every iteration equally; > 0 favours the late iterations, those that decide
    the ``N = 10`` iterate).

    ``rollout_*`` and ``init``: an optional fine-tuning phase after the ``steps`` pool steps
    (:mod:`draping.fnopt.tbptt`): ``rollout_steps`` steps (0, the shipped weights: none), each
    through ``rollout_frames`` consecutive frames of the model's own rollout of
    ``rollout_batch`` pool sheets with ``rollout_iters`` inner iterations per frame, the graph
    kept across the frame boundaries; each frame's loss is its sub-optimality against
    ``rollout_extra`` more classical iterations; Adam at ``rollout_lr`` (cosine to a tenth).
    ``init``: start from these weights instead of a seeded initialisation (``"shipped"``: the
    package's; ``""``: none); with ``steps=0`` only the fine-tuning runs. Three seeds of
    ``--init shipped --steps 0 --rollout-steps 800`` were not better than the shipped weights
    (docs/measurements/fnopt.md, session 11), so the default stays 0.

    ``proposal_iters`` ``K`` (0, the shipped weights: off): every pool step trains the FNO for
    the first-iteration role instead (:mod:`draping.fnopt.train_proposal`: its proposal on
    iteration 0, then ``K`` classical iterations, loss ``log(L(a_K) - L_ref)`` straight through
    them, ``L_ref`` after ``proposal_extra`` more); validation by the role's solve. Session 15:
    ``K = 19`` from the shipped weights did not beat PCG at equal cost nor the shipped weights in
    the same role (docs/measurements/fnopt.md), so the default stays 0.

    ``two_level`` ``K`` (0, the shipped weights: off): the pool step's subspace also holds the
    two-level coarse correction ``-P A_c^-1 P^T g`` (:mod:`draping.fnopt.twolevel`; the
    Galerkin space of each pool sheet's step on the grid whose longer side has ``K`` vertices,
    built at ``a = 0`` of its current frame and kept while it stays on that frame), as
    ``solve_fnopt(two_level=K)`` does at inference; the validation solve uses it too. The FNO
    then only has to learn what the coarse space and the classical directions leave. Not with
    ``proposal_iters`` or ``rollout_steps``. Session 17: ``K = 16`` from the shipped weights
    (13,002 steps) did not beat the two-level PCG at equal cost (hard trio 9.00 against 0.66,
    docs/measurements/fnopt.md), so the default stays 0.
    """

    width: int = 16
    modes: int = 8
    layers: int = 4
    projection: int = 64
    res: int = 32
    pool: int = 64
    batch: int = 8
    steps: int = 7000
    lr: float = 1e-3
    lr_final: float = 1e-4
    inner_min: int = 5
    inner_max: int = 15
    max_frames: int = 240
    size_min: float = 0.3
    size_max: float = 1.5
    reset_prob: float = 0.02
    handles: str = "random"
    step_rule: str = "subspace"
    normal: bool = True
    normal_split: int = 4
    iter_weight: float = 0.0
    rollout_steps: int = 0
    rollout_frames: int = 3
    rollout_iters: int = 10
    rollout_batch: int = 4
    rollout_extra: int = 20
    rollout_lr: float = 1e-4
    init: str = ""
    proposal_iters: int = 0
    proposal_extra: int = 10
    two_level: int = 0
    seed: int = 0
    eval_every: int = 1000
    checkpoint_every: int = 500

    def __post_init__(self) -> None:
        check_positive(self.iter_weight, "iter_weight", strict=False)
        check_positive(self.rollout_lr, "rollout_lr")
        for name in ("steps", "rollout_steps", "rollout_extra", "proposal_iters"):
            check_int(getattr(self, name), name, low=0)
        for name in ("rollout_frames", "rollout_iters", "rollout_batch", "proposal_extra"):
            check_int(getattr(self, name), name, low=1)
        check_int(self.two_level, "two_level", low=0)
        if self.two_level == 1 or (self.two_level and (self.proposal_iters or
                                                       self.rollout_steps)):
            raise ValueError(f"two_level: expected 0 or an int >= 2, and not with proposal_iters "
                             f"or rollout_steps, got {self.two_level} (proposal_iters "
                             f"{self.proposal_iters}, rollout_steps {self.rollout_steps})")
        if self.step_rule != "subspace":
            raise ValueError(f"step_rule: expected 'subspace', got {self.step_rule!r}")
        if self.handles not in HANDLE_DISTRIBUTIONS:
            raise ValueError(f"handles: expected one of {list(HANDLE_DISTRIBUTIONS)}, got "
                             f"{self.handles!r}")
