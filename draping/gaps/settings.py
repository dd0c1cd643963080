"""Settings of the GAPS model and of its self-supervised training (dataclasses, JSON-able).

Part of :mod:`draping.gaps`; import from there.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

from polygeo.checks import check_choice, check_int, check_positive

__all__ = [
    "METHODS",
    "INEXTENSIBILITY",
    "POSE_BONES",
    "TRAIN_MOTIONS",
    "HELD_OUT_MOTIONS",
    "GapsSettings",
    "TrainSettings",
]

#: Methods of :class:`GapsSettings`: GAPS, and the SNUG-like and NCS-like baselines.
METHODS = ("gaps", "snug", "ncs")

#: ``GapsSettings.inextensibility``: ``"schedule"`` (eq. (44) with the collision-aware
#: ``k_ext`` of eq. (45)), ``"one"`` (eq. (44) with ``k_ext = 1``), ``"none"`` (no L_inext);
#: ``"auto"`` is ``"schedule"`` for GAPS and ``"none"`` for the baselines.
INEXTENSIBILITY = ("auto", "schedule", "one", "none")

#: Bones whose rotations the model reads (the ones the procedural motions drive, feet
#: excepted): the five spine segments, the neck, hips, knees, shoulders and elbows of Anny.
POSE_BONES = (
    "spine05", "spine04", "spine03", "spine02", "spine01", "neck01",
    "upperleg01.L", "upperleg01.R", "lowerleg01.L", "lowerleg01.R",
    "upperarm01.L", "upperarm01.R", "lowerarm01.L", "lowerarm01.R",
)

#: Procedural motions trained on (``random`` with seeds below 1000). ``jacks`` is left out: its
#: arms overhead make skinning alone stretch the armpits of a T-shirt to ~640 J per frame
#: (walk: ~7 J), and those few windows dominated the loss; it is reported as a stress case.
TRAIN_MOTIONS = ("walk", "arms", "squat", "random")
#: Held back from training: the ``turn`` motion (and ``jacks``), ``random`` with seeds >= 1000,
#: and body shapes drawn with seeds >= 1000 (see :func:`draping.gaps.held_out_cases`).
HELD_OUT_MOTIONS = ("turn", "jacks")


@dataclass(frozen=True)
class GapsSettings:
    """The model of one garment (GAPS eq. (37)) and the method it is trained as.

    Attributes
    ----------
    garment : str
        A garment of :data:`draping.garments.GARMENTS` (the shipped 5,000-vertex template).
    garment_file : str or None
        An OBJ/PLY garment in the rest pose of the default body shape (metres); replaces
        ``garment``.
    method : {"gaps", "snug", "ncs"}
        ``gaps``: RBF body-participation skinning (thesis eq. (34)-(36)), GAPS bending
        (eq. (41)) and covariance inextensibility; ``snug``: nearest-body-vertex skinning,
        dihedral bending against a flat rest state (eq. (17)), no inextensibility; ``ncs``:
        as ``snug`` with Laplacian-smoothed skinning weights.
    inextensibility : str
        One of :data:`INEXTENSIBILITY` (the ablations of Tables 4.2-4.3).
    width, depth : int
        GRU hidden size and number of layers (the paper: 256 x 4). Default 32 x 1: the
        parsimony sweep of ``benchmarks/bm_gaps.py`` (the fewest parameters with E_dist within
        10 % of the best; 32x1, 64x1, 64x2 and 128x2 are within 0.3 % of each other at 800
        and 2,000 steps). Training cost hardly depends on it (the output basis and the
        energies dominate).
    rank : int
        Size of the linear output basis: the GRU output goes through ``width -> rank`` and a
        learnt basis ``rank -> 3 V`` (``rank = 0``: one ``width -> 3 V`` layer). Keeps the file
        small and the per-frame cost at ``rank * 3 V`` multiply-adds.
    top_bones : int
        Skinning weights kept per garment vertex (the largest, renormalised).
    skin_smoothing : int
        GAPS only: Laplacian smoothing steps (``smoothing=`` of
        :func:`draping.skinning.skinning_weights`, :func:`draping.skinning.smooth_weights`, step
        0.5, as NCS's) applied over the garment's edges to the RBF participation weights; 0
        gives the thesis' weights. The RBF participation of each garment vertex is computed
        from the body alone, vertex by vertex, so nothing makes neighbouring garment vertices
        agree; under skinning every difference between neighbours' weights is stretch that
        the network's low-rank output must undo. Measured on the T-shirt (skinning alone,
        training motions and shapes): eps_e 4.22 % (0) vs 3.73 % (20), NCS-like's 3.93 %.
        Models saved before this setting existed load with 0.
    """

    garment: str = "tshirt"
    garment_file: str | None = None
    method: str = "gaps"
    inextensibility: str = "auto"
    width: int = 32
    depth: int = 1
    rank: int = 64
    top_bones: int = 6
    skin_smoothing: int = 20

    def __post_init__(self) -> None:
        check_choice(self.method, "method", METHODS)
        check_choice(self.inextensibility, "inextensibility", INEXTENSIBILITY)
        check_int(self.width, "width", low=1, high=4096)
        check_int(self.depth, "depth", low=1, high=16)
        check_int(self.rank, "rank", low=0, high=4096)
        check_int(self.top_bones, "top_bones", low=1, high=32)
        check_int(self.skin_smoothing, "skin_smoothing", low=0, high=10_000)
        if self.garment_file is None:
            from draping.garments import GARMENTS

            check_choice(self.garment, "garment", GARMENTS)

    @property
    def skinning(self) -> str:
        """Skinning of the method: ``rbf`` (gaps), ``nearest`` (snug), ``laplacian`` (ncs)."""
        return {"gaps": "rbf", "snug": "nearest", "ncs": "laplacian"}[self.method]

    def key_dict(self) -> dict:
        """The settings as a dict without the fields that do not change this model.

        ``skin_smoothing`` is left out unless the method is GAPS and it is non-zero, so the
        keys of baselines and of models trained before it existed do not change.
        """
        d = dataclasses.asdict(self)
        if self.method != "gaps" or self.skin_smoothing == 0:
            d.pop("skin_smoothing")
        return d

    @property
    def inext_mode(self) -> str:
        """``"schedule"``, ``"one"`` or ``"none"`` (``"auto"`` resolved by the method)."""
        if self.inextensibility == "auto":
            return "schedule" if self.method == "gaps" else "none"
        return self.inextensibility


@dataclass(frozen=True)
class TrainSettings:
    """Self-supervised training of a :class:`GapsSettings` model (the run's fingerprint).

    A step draws one body shape from a pool of ``shapes`` random phenotype vectors (seeded;
    each with the garment carried over to it by :func:`draping.garments.fit_garment_to_shape`,
    whose rest geometry is the strain reference), ``batch`` windows of ``window`` consecutive
    frames from the training motions, runs the GRU over each window from the state it has
    there at inference (``burn_in``; a random hidden state with ``burn_in = 0``), skins, and
    minimises eq. (46) summed over the frames (inertia, eq. (42), on the frames that have two
    predecessors in the window), the gradient clipped (``grad_clip``).

    Attributes
    ----------
    model : GapsSettings
    steps : int
        Optimiser steps.
    batch : int
        Windows per step.
    window : int
        Frames per window (>= 3 so that inertia applies).
    lr, lr_late : float
        Adam learning rate for the first ``lr_epochs`` epochs, then after (the paper: 1e-3
        for 10 epochs, then 1e-4).
    lr_epochs : int
    epoch_steps : int
        Steps per "epoch" of the schedules (learning rate and ``k_ext``, eq. (45)).
    shapes : int
        Training body shapes (drawn with ``seed``; held-out shapes use seeds >= 1000).
    motion_frames : int
        Frames of each training motion sequence (30 fps).
    speeds : tuple of float
        Playback speeds of the deterministic training motions (augmentation).
    random_motions : int
        Seeded ``random`` motions in the training set (seeds ``0 .. random_motions - 1``).
    grad_clip : float
        The gradient norm of a step is clipped at ``grad_clip`` times a running mean of the
        (clipped) norms of the previous steps (0: no clipping). A few windows (extreme poses
        on some shapes) have strain energies 100-500 times the median; unclipped, their
        gradients swamp Adam's second-moment estimate, which then damps the following
        hundreds of steps (the median loss of the first recipe did not fall after step 200).
    hidden_std : float
        Standard deviation of the random initial hidden state (training only).
    burn_in : int
        Frames of the window's motion that the GRU reads, without gradient, before the
        window (0: none, the paper's random state at the window). From the motion's first
        frame (when ``burn_in`` reaches it) the state starts at zero, as at inference; from a
        later frame, at the random state. Without it, a model trained on 3-frame windows
        from random states drifts on long sequences: the shipped T-shirt of the first recipe
        had held-out eps_c 3.64 % on a 60-frame random motion, 0.33 % when re-started every
        3 frames.
    collision_stiffness : float
        ``k_c`` of eq. (40) (J/m^3).
    collision_eps : float
        Clearance ``epsilon`` of eq. (40) (m), relative to the full Anny body.
    k_ext_rings : int
        GAPS ``k_ext`` schedule (eq. (45)) spread to the cloth within this many 1-rings of a
        contact (``rings=`` of :func:`draping.physics.k_ext_schedule`); 0: eq. (45) as
        written, only the colliding vertices may stretch.
    inext_weight : float
        ``k_i`` of eq. (44).
    pinch_inext : float
        Factor in [0, 1] on L_inext (eq. (44)) at the cloth pinched between an arm and the rest
        of the body (within ``collision_eps`` of both, their surfaces facing) and within
        ``k_ext_rings`` 1-rings of it (:mod:`draping.gaps.pinch`); 0 lets that cloth stretch out
        of the pinch as NCS-like's (no L_inext) does. 1: no pinch test, the old behaviour.
    pinch_push : bool
        At that pinched cloth, measure the collision penetration (eq. (40)) along the
        normalised sum of the two facing parts' normals (:func:`draping.gaps.push_normal`: out
        of the wedge) instead of the closest part's normal (into the other part). False: the
        old behaviour.
    query_radius : float
        Body distance queries stop at this distance (m): farther vertices cannot collide.
    seed : int
    checkpoint_every : int
        Steps between checkpoints.
    replay : float
        Hard-example replay: the probability that a step trains again on the shape and
        windows of a recent hard step instead of fresh ones. A fresh step is hard when its
        collision loss is in the top decile of the last 200 fresh steps (once 20 are known);
        the 64 latest hard steps are kept. 0: every step fresh (the paper).
    init : str or None
        A model file (:func:`draping.gaps.save_model`) of the same garment and architecture to
        start from (fine-tuning) instead of the zero output basis. Its ``skin_smoothing`` may
        differ: the network is taken, the skinning weights are this run's.
    """

    model: GapsSettings = field(default_factory=GapsSettings)
    steps: int = 3000
    batch: int = 4
    window: int = 3
    lr: float = 1e-3
    lr_late: float = 1e-4
    lr_epochs: int = 10
    epoch_steps: int = 60
    shapes: int = 128
    motion_frames: int = 90
    speeds: tuple = (0.75, 1.0, 1.3)
    random_motions: int = 12
    grad_clip: float = 3.0
    hidden_std: float = 0.5
    burn_in: int = 90
    collision_stiffness: float = 1e4
    collision_eps: float = 2e-3
    k_ext_rings: int = 0
    inext_weight: float = 2e8
    pinch_inext: float = 1.0
    pinch_push: bool = False
    query_radius: float = 0.02
    seed: int = 0
    checkpoint_every: int = 100
    replay: float = 0.0
    init: str | None = None
    average_from: int | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.model, GapsSettings):
            raise TypeError(f"model: expected GapsSettings, got {type(self.model).__name__}")
        check_int(self.steps, "steps", low=0)
        check_int(self.batch, "batch", low=1)
        check_int(self.window, "window", low=3)
        check_int(self.lr_epochs, "lr_epochs", low=0)
        check_int(self.epoch_steps, "epoch_steps", low=1)
        check_int(self.shapes, "shapes", low=1)
        check_int(self.motion_frames, "motion_frames", low=self.window)
        check_int(self.random_motions, "random_motions", low=0)
        check_int(self.burn_in, "burn_in", low=0)
        check_int(self.seed, "seed")
        check_int(self.checkpoint_every, "checkpoint_every", low=1)
        check_int(self.k_ext_rings, "k_ext_rings", low=0, high=1000)
        if self.average_from is not None:
            check_int(self.average_from, "average_from", low=0)
        for name in ("lr", "lr_late", "collision_stiffness", "inext_weight", "query_radius"):
            check_positive(getattr(self, name), name)
        for name in ("hidden_std", "collision_eps", "grad_clip"):
            check_positive(getattr(self, name), name, strict=False)
        if not (0.0 <= check_positive(self.pinch_inext, "pinch_inext", strict=False) <= 1.0):
            raise ValueError(f"pinch_inext: expected a factor in [0, 1], got {self.pinch_inext!r}")
        if self.pinch_inext != 1.0 and self.collision_eps <= 0:
            raise ValueError("pinch_inext: needs collision_eps > 0 (the pinch test's clearance)")
        if not isinstance(self.pinch_push, bool):
            raise TypeError(f"pinch_push: expected a bool, got {type(self.pinch_push).__name__}")
        if self.pinch_push and self.collision_eps <= 0:
            raise ValueError("pinch_push: needs collision_eps > 0 (the pinch test's clearance)")
        if check_positive(self.replay, "replay", strict=False) >= 1.0:
            raise ValueError(f"replay: expected a probability in [0, 1), got {self.replay!r}")
        if not self.speeds or not all(math.isfinite(s) and s > 0 for s in self.speeds):
            raise ValueError(f"speeds: expected positive playback speeds, got {self.speeds}")

    def key_dict(self) -> dict:
        """The run's identity: the settings that change the training trajectory.

        ``steps``, ``checkpoint_every`` and ``average_from`` are left out: a run continued for
        more steps, or exporting a weight average, is the same run. The model's part is
        :meth:`GapsSettings.key_dict`. ``k_ext_rings`` and ``replay`` are left out when 0 and
        ``pinch_inext`` when 1 and ``pinch_push`` when False, so the keys of runs from before
        they existed do not change.
        """
        d = dataclasses.asdict(self)
        for k in ("steps", "checkpoint_every", "average_from"):
            d.pop(k)
        for k in ("k_ext_rings", "replay"):
            if d[k] == 0:
                d.pop(k)
        if d["pinch_inext"] == 1.0:
            d.pop("pinch_inext")
        if not d["pinch_push"]:
            d.pop("pinch_push")
        d["model"] = self.model.key_dict()
        return d

    def replace(self, **changes) -> TrainSettings:
        """A copy with some fields changed (``model`` fields by their own names too)."""
        model_fields = {f.name for f in dataclasses.fields(GapsSettings)}
        mchanges = {k: changes.pop(k) for k in list(changes) if k in model_fields}
        model = dataclasses.replace(self.model, **mchanges) if mchanges else self.model
        return dataclasses.replace(self, model=model, **changes)

    @classmethod
    def from_dict(cls, d: dict) -> TrainSettings:
        """Inverse of ``dataclasses.asdict``."""
        d = dict(d)
        model = GapsSettings(**d.pop("model"))
        if "speeds" in d:
            d["speeds"] = tuple(d["speeds"])
        return cls(model=model, **d)
