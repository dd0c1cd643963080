"""What GAPS trains and is evaluated on: garments per body shape, motions, held-out cases.

Part of :mod:`draping.gaps`; import from there.

How the rest garment follows the body shape: the template (made for the default Anny shape)
is carried over to each shape by :func:`draping.garments.fit_garment_to_shape` (the same
carry-over ``polygeo drape-reference --shape`` uses), and that garment is both ``T(beta)`` of
eq. (37) and the strain / inextensibility reference of the shape (a garment of the same cut
made for that body). The skinning weights are computed once, on the template and the default
body, and shared by every shape (one vertex correspondence).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from draping import physics
from draping.body import ANNY_PHENOTYPES, AnnyBody
from draping.collision import MeshQuery
from draping.garments import Garment, fit_garment_to_shape, garment, load_garment
from draping.motion import MOTIONS, Motion, generate
from draping.skinning import dense_body_weights, skinning_weights
from polygeo.checks import as_tensor, check_choice, check_finite, check_int, check_shape

from .settings import TRAIN_MOTIONS, GapsSettings, TrainSettings

__all__ = [
    "ShapeCase",
    "Sequence",
    "Case",
    "template_garment",
    "garment_weights",
    "shape_case",
    "check_phenotypes",
    "random_shapes",
    "training_sequences",
    "sequence_of",
    "held_out_cases",
    "random_cases",
    "validation_cases",
    "stress_cases",
    "check_case",
]


class ShapeCase(NamedTuple):
    """A body shape with its garment, ready for the losses.

    Attributes
    ----------
    shape : (6,) float tensor
        Phenotypes in ``[0, 1]``.
    garment : Garment
        ``T(beta)``: the template carried over to the shape (m).
    rest : physics.RestState
        Its rest geometry (float32).
    alpha : (H,) float tensor
        GAPS bending balance per hinge (eq. (41)): the hinge's rest distance to the body over
        the largest such distance (0 on the skin, 1 where the garment hangs farthest).
    """

    shape: torch.Tensor
    garment: Garment
    rest: physics.RestState
    alpha: torch.Tensor


class Sequence(NamedTuple):
    """A pose sequence at 30 fps.

    Rotations ``(T, J, 3)`` rad, translation ``(T, 3)`` m, root velocity ``(T, 3)`` m/s, a label.
    """

    rotations: torch.Tensor
    translation: torch.Tensor
    velocity: torch.Tensor
    name: str


class Case(NamedTuple):
    """An evaluation case: a motion (name, seed, playback speed), a shape, a frame count."""

    motion: str
    seed: int
    speed: float
    shape: tuple
    frames: int


def template_garment(settings: GapsSettings, body: AnnyBody) -> Garment:
    """The garment on the default body shape (shipped template or a checked file).

    Raises
    ------
    ValueError
        A garment file that is not a usable garment (the message lists why), e.g. vertices
        inside the rest body.
    """
    if settings.garment_file is None:
        return garment(settings.garment)
    rv = body.rest()[0][0].double().numpy()
    q = MeshQuery(rv, body.faces)

    def query(points):
        r = q.query(np.asarray(points, dtype=np.float64))
        return r.distance, r.closest, r.normal

    g = load_garment(settings.garment_file, query=query)
    d = q.query(g.vertices).distance
    info = dict(g.info)
    info.setdefault("clearance", float(np.median(d)))
    return Garment(g.name, g.vertices, g.faces, info)


def garment_weights(settings: GapsSettings, g: Garment, body: AnnyBody) -> torch.Tensor:
    """Dense ``(V, J)`` float64 skinning weights of the method (rbf / nearest / laplacian).

    GAPS: the RBF participation weights, then ``settings.skin_smoothing`` Laplacian steps
    over the garment's edges.
    """
    rv = body.rest()[0][0].double().numpy()
    wb = dense_body_weights((body.skin_indices.numpy(), body.skin_weights.double().numpy()),
                            body.num_vertices, body.num_bones)
    steps = settings.skin_smoothing if settings.method == "gaps" else None
    w = skinning_weights(settings.skinning, g.vertices, rv, wb, garment_faces=g.faces,
                         smoothing=steps)
    return torch.as_tensor(np.asarray(w), dtype=torch.float64)


def _alpha(g: Garment, rest: physics.RestState, body_vertices: np.ndarray,
           body_faces: np.ndarray) -> torch.Tensor:
    d = MeshQuery(body_vertices, body_faces).query(g.vertices).distance
    d = np.clip(np.asarray(d, dtype=np.float64), 0.0, None)
    e = np.asarray(rest.hinges.edges)
    dh = 0.5 * (d[e[:, 0]] + d[e[:, 1]])
    top = dh.max() if len(dh) else 0.0
    a = dh / top if top > 0 else np.zeros_like(dh)
    return torch.as_tensor(np.clip(a, 0.0, 1.0), dtype=torch.float32)


def shape_case(template: Garment, body: AnnyBody, shape) -> ShapeCase:
    """The garment of a body shape and its rest geometry.

    Parameters
    ----------
    template : Garment
        The garment on the default shape.
    body : AnnyBody
    shape : (6,) float or None
        Phenotypes in ``[0, 1]`` (None: the default shape, the template itself).

    Raises
    ------
    ValueError
        Phenotypes outside ``[0, 1]`` or of the wrong shape.
    """
    s = body.default_shape if shape is None else check_phenotypes(shape)
    g = template if shape is None else fit_garment_to_shape(template, body, s)
    rest = physics.rest_state(torch.as_tensor(g.vertices, dtype=torch.float32), g.faces)
    rv = body.rest(s)[0][0].double().numpy()
    return ShapeCase(s.float(), g, rest, _alpha(g, rest, rv, body.faces.numpy()))


def check_phenotypes(shape) -> torch.Tensor:
    """Validated ``(6,)`` float32 phenotypes in ``[0, 1]``.

    Raises
    ------
    ValueError
        Wrong shape, NaN, or a value outside ``[0, 1]`` (the phenotype is named).
    """
    s = as_tensor(shape, "shape", dtype=torch.float32)
    check_shape(s, "shape", (6,))
    check_finite(s, "shape")
    bad = [(n, float(v)) for n, v in zip(ANNY_PHENOTYPES, s) if not 0.0 <= float(v) <= 1.0]
    if bad:
        raise ValueError(f"shape: phenotypes must lie in [0, 1], got {bad}")
    return s


def random_shapes(n: int, seed: int) -> torch.Tensor:
    """``(n, 6)`` phenotype vectors uniform in ``[0, 1]^6`` (training: seed < 1000)."""
    n = check_int(n, "n", low=0)
    rng = np.random.default_rng([int(seed), 77])
    return torch.as_tensor(rng.uniform(0.0, 1.0, (n, 6)), dtype=torch.float32)


def sequence_of(body: AnnyBody, motion: str, frames: int, seed: int = 0, speed: float = 1.0,
                fps: float = 30.0) -> Sequence:
    """A procedural motion played at ``speed`` times its natural pace, sampled at ``fps``."""
    check_choice(motion, "motion", MOTIONS)
    m = generate(motion, body, frames, fps / float(speed), seed)
    m = Motion(m.rotations, m.translation, fps, m.name, m.bone_names)
    return Sequence(m.rotations, m.translation, m.velocity, f"{motion}:{seed}:{speed:g}")


def training_sequences(settings: TrainSettings, body: AnnyBody) -> list[Sequence]:
    """The training motions.

    Walk, arms, squat at each playback speed, and ``random_motions`` seeded random motions
    (seeds < 1000); ``turn`` and ``jacks`` are held back (:data:`TRAIN_MOTIONS`).
    """
    out = []
    for name in (m for m in TRAIN_MOTIONS if m != "random"):
        for sp in settings.speeds:
            out.append(sequence_of(body, name, settings.motion_frames, 0, sp))
    for seed in range(settings.random_motions):
        out.append(sequence_of(body, "random", settings.motion_frames, seed, 1.0))
    return out


def stress_cases(frames: int = 60) -> list[Case]:
    """Held-back cases beyond the training range.

    Jumping jacks (arms overhead), on a held-out shape and on the default shape.
    """
    frames = check_int(frames, "frames", low=3)
    s = tuple(float(v) for v in random_shapes(1, 1004)[0])
    return [Case("jacks", 0, 1.0, s, frames), Case("jacks", 0, 1.0, (0.5,) * 6, frames)]


def check_case(frames: int = 20) -> Case:
    """The fixed short sequence whose metrics a shipped model records.

    The walk on a held-out shape, 20 frames (the shipped-model test redoes it).
    """
    return Case("walk", 0, 1.0, tuple(float(v) for v in random_shapes(1, 1005)[0]), frames)


def validation_cases(frames: int = 60) -> list[Case]:
    """Cases for choosing settings: training-type motions on shapes no training pool draws.

    ``random`` with seeds 500-502 (a run trains on seeds ``0 .. random_motions - 1``), the walk,
    squat and arms at their trained speed; shapes drawn with seeds 500-505 (a run's pool uses
    its own seed, 0 by default). Disjoint from :func:`held_out_cases` (seeds >= 1000), so
    that choices made on these never look at the held-out figures.
    """
    frames = check_int(frames, "frames", low=3)
    shapes = [tuple(float(v) for v in random_shapes(1, 500 + i)[0]) for i in range(6)]
    motions = [("random", 500), ("random", 501), ("random", 502), ("walk", 0), ("squat", 0),
               ("arms", 0)]
    return [Case(m, seed, 1.0, s, frames) for (m, seed), s in zip(motions, shapes)]


def random_cases(seeds, frames: int = 60) -> list[Case]:
    """``random`` motions with the given seeds, each on the shape drawn with its own seed.

    For screens wider than :func:`validation_cases` (session 15: 197 seeds of 506-705):
    training-type motions and shapes that no run trains on and that are not held out.

    Parameters
    ----------
    seeds : iterable of int
        Seeds in [500, 999] (a run trains on ``random`` seeds below ``random_motions`` and
        draws its shapes with its own seed; seeds >= 1000 are held out), no repeats.
    frames : int
        Frames per case (>= 3).

    Raises
    ------
    ValueError
        If a seed is outside [500, 999] or repeated, or ``seeds`` is empty.
    TypeError
        If a seed is not an integer.
    """
    frames = check_int(frames, "frames", low=3)
    seeds = [check_int(s, "seeds", low=500, high=999) for s in seeds]
    if not seeds or len(set(seeds)) != len(seeds):
        raise ValueError(f"seeds: expected distinct seeds, got {seeds}")
    return [Case("random", s, 1.0, tuple(float(v) for v in random_shapes(1, s)[0]), frames)
            for s in seeds]


#: Seeds of :func:`validation_random_cases` (declared in session 16, before any model was scored
#: on them): disjoint from the training motions (seeds ``0 .. random_motions - 1``),
#: :func:`validation_cases` (500-505), the wide held-out set (506-705) and the session-15 screen
#: (706-905) of ``docs/measurements/gaps.md``, and :func:`held_out_cases` (>= 1000).
VALIDATION_RANDOM_SEEDS = tuple(range(906, 966))


def validation_random_cases(frames: int = 60) -> list[Case]:
    """Sixty random motions for choosing settings, each on its own seed's shape.

    :func:`random_cases` of :data:`VALIDATION_RANDOM_SEEDS` (906-965).

    The six :func:`validation_cases` gate at the size of one vertex-frame's noise; these judge
    a model on the motion type (``random``) where the dress's eps_e is highest.

    Raises
    ------
    ValueError
        If ``frames`` < 3.
    """
    return random_cases(VALIDATION_RANDOM_SEEDS, frames)


def held_out_cases(frames: int = 60) -> list[Case]:
    """Evaluation cases held back from training.

    Motions: ``turn`` (a motion type never trained on), ``random`` with seeds 1000 and 1001,
    and the walk at an untrained playback speed (1.15); shapes: uniform draws with seeds >=
    1000 (never in a training pool, which uses the run's seed < 1000).
    """
    frames = check_int(frames, "frames", low=3)
    shapes = [tuple(float(v) for v in random_shapes(1, 1000 + i)[0]) for i in range(4)]
    return [
        Case("turn", 0, 1.0, shapes[0], frames),
        Case("random", 1000, 1.0, shapes[1], frames),
        Case("random", 1001, 1.0, shapes[2], frames),
        Case("walk", 0, 1.15, shapes[3], frames),
    ]
