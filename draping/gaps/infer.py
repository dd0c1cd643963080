"""Building, saving, loading and running a GAPS model; held-out evaluation.

Part of :mod:`draping.gaps`; import from there.
"""

from __future__ import annotations

import dataclasses
import hashlib
import time
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from draping.body import AnnyBody
from draping.collision import MeshQuery
from draping.garments import Garment
from draping.metrics import area_error, collision_error, edge_error
from draping.motion import Motion
from draping.physics import GRAVITY
from polygeo.checks import as_tensor, check_finite, check_shape

from .data import (
    Case,
    ShapeCase,
    check_phenotypes,
    garment_weights,
    held_out_cases,
    sequence_of,
    shape_case,
    template_garment,
)
from .model import GapsModel, feature_size, pose_features, top_weights
from .settings import POSE_BONES, GapsSettings

__all__ = [
    "DATA_DIR",
    "build_model",
    "save_model",
    "load_model",
    "garment_key",
    "check_garment_for",
    "Drape",
    "drape_sequence",
    "drape_motion",
    "time_inference",
    "drape_case",
    "evaluate",
    "shipped_model_path",
    "shipped_garments",
    "model_garment",
    "frame_metrics",
    "pose_bone_indices",
    "up_vector",
    "motion_features",
]

DATA_DIR = Path(__file__).resolve().parent.parent / "data"
_FORMAT = "draping.gaps.model"


def shipped_model_path(garment: str) -> Path:
    """``draping/data/gaps_<garment>.pt`` (may not exist for every garment)."""
    return DATA_DIR / f"gaps_{garment}.pt"


def shipped_garments() -> list[str]:
    """The garments whose GAPS model ships (those :func:`shipped_model_path` finds), sorted."""
    return sorted(p.stem[len("gaps_"):] for p in DATA_DIR.glob("gaps_*.pt"))


def garment_key(vertices: Any, faces: Any) -> str:
    """A short hash of a garment's faces and (millimetre-rounded) rest vertices."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(np.asarray(faces, dtype=np.int64)).tobytes())
    v = np.round(np.asarray(vertices, dtype=np.float64) * 1000.0).astype(np.int64)
    h.update(np.ascontiguousarray(v).tobytes())
    return h.hexdigest()[:16]


def pose_bone_indices(body: AnnyBody) -> torch.Tensor:
    """``(P,)`` indices of :data:`POSE_BONES` in the body's bones (``ValueError`` if missing)."""
    names = list(body.bone_names)
    missing = [b for b in POSE_BONES if b not in names]
    if missing:
        raise ValueError(f"body: expected the Anny rig, missing bones {missing}")
    return torch.tensor([names.index(b) for b in POSE_BONES], dtype=torch.int64)


def up_vector() -> torch.Tensor:
    """``(3,)`` unit up direction (against :data:`draping.physics.GRAVITY`)."""
    g = torch.tensor(GRAVITY, dtype=torch.float32)
    return -g / g.norm()


def motion_features(body: AnnyBody, rotations: torch.Tensor, velocity: torch.Tensor,
                    shape: torch.Tensor) -> torch.Tensor:
    """The regressor's inputs for a motion of ``body`` (what training and inference feed).

    :func:`draping.gaps.pose_features` with the body's :data:`POSE_BONES` and the world up
    direction (:func:`up_vector`).

    Parameters
    ----------
    body : AnnyBody
    rotations : (..., T, J, 3) float tensor
        Axis-angle rotations of the body's bones (radians).
    velocity : (..., T, 3) float tensor
        Root velocity (m/s).
    shape : (..., 6) float tensor
        Phenotypes in ``[0, 1]``.

    Returns
    -------
    (..., T, feature_size()) float tensor

    Raises
    ------
    ValueError
        A body without the bones of :data:`POSE_BONES`.
    """
    return pose_features(rotations, velocity, shape, pose_bone_indices(body), up_vector())


def build_model(settings: GapsSettings, body: AnnyBody) -> tuple[GapsModel, Garment]:
    """An untrained model of the settings' garment and method, and the template garment."""
    g = template_garment(settings, body)
    w = garment_weights(settings, g, body)
    wk, ik = top_weights(w, settings.top_bones)
    v = torch.as_tensor(g.vertices, dtype=torch.float32)
    f = torch.as_tensor(g.faces, dtype=torch.int64)
    e = np.concatenate([g.faces[:, [0, 1]], g.faces[:, [1, 2]], g.faces[:, [2, 0]]])
    unit = float(np.linalg.norm(g.vertices[e[:, 0]] - g.vertices[e[:, 1]], axis=1).mean())
    model = GapsModel(settings, v, f, wk, ik, unit, feature_size())
    model.garment_name = g.name
    model.garment_info = dict(g.info)
    return model, g


def save_model(path: str | Path, model: GapsModel, record: dict | None = None) -> Path:
    """Write a model with :func:`polygeo.runs.save_checkpoint`.

    Network weights in float16, the garment in float32; its settings and ``record`` (JSON-able)
    as metadata.
    """
    from polygeo.runs import save_checkpoint

    state = {}
    for k, t in model.state_dict().items():
        keep = k in ("template", "weights") or not t.is_floating_point()
        state[k] = t if keep else t.half()
    meta = {
        "format": _FORMAT,
        "settings": dataclasses.asdict(model.settings),
        "unit": model.unit,
        "n_features": feature_size(),
        "garment": getattr(model, "garment_name", model.settings.garment),
        "garment_info": getattr(model, "garment_info", {}),
        "garment_key": garment_key(model.template.numpy(), model.faces.numpy()),
        "record": record or {},
    }
    return save_checkpoint(Path(path), {"state": state}, meta)


def load_model(path_or_name: str | Path) -> GapsModel:
    """A model from a file written by :func:`save_model`, or a shipped one by garment name.

    Parameters
    ----------
    path_or_name : str or Path
        A ``.pt`` path, or ``"tshirt"`` / ``"dress"`` for ``draping/data/gaps_<name>.pt``.

    Returns
    -------
    GapsModel
        In evaluation mode, float32; ``model.record`` holds the file's JSON record.

    Raises
    ------
    FileNotFoundError
        No such file or shipped model.
    ValueError
        A file that is not a GAPS model.
    """
    from polygeo.runs import load_checkpoint

    p = Path(path_or_name)
    if not p.suffix and not p.exists():
        p = shipped_model_path(str(path_or_name))
    if not p.is_file():
        raise FileNotFoundError(f"model: no GAPS model at {str(p)!r}")
    ck = load_checkpoint(p)
    if ck.meta.get("format") != _FORMAT:
        raise ValueError(f"model: {p} is not a GAPS model (format {ck.meta.get('format')!r})")
    # Files from before ``skin_smoothing`` existed were trained on the thesis' RBF weights.
    s = GapsSettings(**{"skin_smoothing": 0, **ck.meta["settings"]})
    st = {k: (t.float() if t.is_floating_point() else t) for k, t in ck.tensors["state"].items()}
    model = GapsModel(s, st["template"], st["faces"], st["weights"], st["indices"],
                      float(ck.meta["unit"]), int(ck.meta["n_features"]))
    model.load_state_dict(st)
    model.eval()
    model.garment_name = ck.meta.get("garment", s.garment)
    model.garment_info = dict(ck.meta.get("garment_info", {}))
    model.record = dict(ck.meta.get("record", {}))
    model.key = ck.meta.get("garment_key")
    return model


def model_garment(model: GapsModel) -> Garment:
    """The template garment a model was trained for."""
    return Garment(getattr(model, "garment_name", model.settings.garment),
                   model.template.double().numpy(), model.faces.numpy(),
                   dict(getattr(model, "garment_info", {})))


def check_garment_for(model: GapsModel, g: Garment) -> None:
    """Raise ``ValueError`` unless ``g`` is the garment the model was trained for."""
    if len(g.vertices) != model.n_vertices or g.faces.shape != tuple(model.faces.shape) or (
            garment_key(g.vertices, g.faces)
            != garment_key(model.template.numpy(), model.faces.numpy())):
        raise ValueError(
            f"garment: the model was trained for garment {getattr(model, 'garment_name', '?')!r}"
            f" ({model.n_vertices} vertices, {model.faces.shape[0]} faces), got {g.name!r} "
            f"({len(g.vertices)} vertices, {len(g.faces)} faces); train one for it with "
            "polygeo train-drape --garment-file")


class Drape(NamedTuple):
    """A draped sequence.

    Attributes
    ----------
    x : (T, V, 3) float32 tensor
        Garment per frame (m).
    body_vertices : (T, Vb, 3) float32 tensor
        Posed body per frame (m).
    case : ShapeCase
        The shape's rest garment (the metrics' reference) and rest geometry.
    seconds : dict
        CPU seconds of the model alone (``model``: GRU, output basis, skinning) and with the
        body posing (``with_posing``), for the whole sequence.
    """

    x: torch.Tensor
    body_vertices: torch.Tensor
    case: ShapeCase
    seconds: dict


def drape_sequence(model: GapsModel, body: AnnyBody, motion: Motion, shape: Any = None,
                   case: ShapeCase | None = None) -> torch.Tensor:
    """Drape a motion with a model (hidden state zero at the first frame).

    Parameters
    ----------
    model : GapsModel
    body : AnnyBody
    motion : Motion
        Rotations ``(T, J, 3)`` (rad), translation ``(T, 3)`` (m), fps.
    shape : (6,) float, optional
        Phenotypes in ``[0, 1]`` (None: the default shape).
    case : ShapeCase, optional
        Precomputed garment of the shape (:func:`draping.gaps.shape_case`).

    Returns
    -------
    (T, V, 3) float32 tensor
        Garment positions (m).

    Raises
    ------
    ValueError
        NaN or infinite poses, a rotation array of the wrong shape, phenotypes outside
        ``[0, 1]``.
    """
    return drape_motion(model, body, motion, shape, case).x


def drape_motion(model: GapsModel, body: AnnyBody, motion: Motion, shape: Any = None,
                 case: ShapeCase | None = None) -> Drape:
    """As :func:`drape_sequence`, with the posed bodies, the shape's garment and timings."""
    rot = as_tensor(motion.rotations, "rotations", dtype=torch.float32)
    check_shape(rot, "rotations", ("T", body.num_bones, 3))
    check_finite(rot, "rotations")
    trans = as_tensor(motion.translation, "translation", dtype=torch.float32)
    check_shape(trans, "translation", (rot.shape[0], 3))
    check_finite(trans, "translation")
    if case is None:
        case = shape_case(model_garment(model), body, None if shape is None
                          else check_phenotypes(shape))
    vel = Motion(rot, trans, float(motion.fps)).velocity
    c0 = time.process_time()
    with torch.no_grad():
        posed = body.pose(case.shape, rot, trans)
        c1 = time.process_time()
        feats = motion_features(body, rot[None], vel[None], case.shape[None])
        disp, _ = model(feats)  # hidden state zero
        unposed = torch.as_tensor(case.garment.vertices, dtype=torch.float32) + disp[0]
        x = model.skin(unposed, posed.transforms.float())
    c2 = time.process_time()
    return Drape(x, posed.vertices.float(), case,
                 {"model": c2 - c1, "with_posing": c2 - c0})


def time_inference(model: GapsModel, body: AnnyBody, frames: int = 120, repeats: int = 3
                   ) -> dict:
    """CPU milliseconds per frame of draping a walk of ``frames`` frames (best of ``repeats``).

    Returns
    -------
    dict
        ``model``: GRU, output basis and garment skinning with the bone transforms given;
        ``with_skeleton``: plus the forward kinematics of the pose (what a garment needs from
        the body); ``with_body_mesh``: plus posing the full 13,348-vertex body mesh
        (:meth:`draping.body.AnnyBody.pose`). The garment of the body shape
        (:func:`draping.gaps.shape_case`, once per sequence) is not counted.
    """
    from draping.body import forward_kinematics
    from draping.motion import generate
    from polygeo.frames import axis_angle_to_matrix

    m = generate("walk", body, frames)
    vel = m.velocity
    case = shape_case(model_garment(model), body, None)
    rest_v = torch.as_tensor(case.garment.vertices, dtype=torch.float32)
    _, joints = body.rest(case.shape)
    best = {"model": float("inf"), "with_skeleton": float("inf"),
            "with_body_mesh": float("inf")}
    with torch.no_grad():
        for _ in range(repeats):
            c0 = time.process_time()
            posed = body.pose(case.shape, m.rotations, m.translation)
            c1 = time.process_time()
            tr, _ = forward_kinematics(axis_angle_to_matrix(m.rotations),
                                       joints.expand(frames, -1, -1), body.parents,
                                       m.translation, body.levels)
            c2 = time.process_time()
            feats = motion_features(body, m.rotations[None], vel[None], case.shape[None])
            disp, _ = model(feats)
            model.skin(rest_v + disp[0], tr)
            c3 = time.process_time()
            best["model"] = min(best["model"], c3 - c2)
            best["with_skeleton"] = min(best["with_skeleton"], c3 - c1)
            best["with_body_mesh"] = min(best["with_body_mesh"], c3 - c2 + c1 - c0)
    del posed
    return {k: 1000.0 * v / frames for k, v in best.items()}


def drape_case(model: GapsModel, body: AnnyBody, case: Case) -> Drape:
    """Drape an evaluation :class:`Case`."""
    seq = sequence_of(body, case.motion, case.frames, case.seed, case.speed)
    m = Motion(seq.rotations, seq.translation, 30.0)
    return drape_motion(model, body, m, torch.tensor(case.shape, dtype=torch.float32), None)


def frame_metrics(d: Drape, body: AnnyBody, distance: Any = None) -> dict:
    """Per-frame metrics of a drape.

    ``eps_e``, ``eps_a``, ``eps_c`` (%) against the shape's rest garment and the full posed
    body, and the minimum body distance (mm).

    Parameters
    ----------
    d : Drape
    body : AnnyBody
    distance : (T, V) float tensor, optional
        Signed distances (m) of the drape's vertices to its posed body per frame, when the
        caller has queried them already (a benchmark scoring several models on one posed
        body); None: queried here (:class:`draping.collision.MeshQuery`, float64).

    Raises
    ------
    ValueError
        ``distance`` not of shape ``(T, V)``.
    """
    g = d.case.garment
    tmpl = torch.as_tensor(g.vertices, dtype=torch.float64)
    x = d.x.double()
    if distance is None:
        q = MeshQuery(d.body_vertices[0].double(), body.faces)
        dist = []
        for t in range(x.shape[0]):
            q.update(d.body_vertices[t].double())
            dist.append(q.query(x[t]).distance)
        dist = torch.stack(dist)
    else:
        dist = as_tensor(distance, "distance", dtype=torch.float64)
        check_shape(dist, "distance", tuple(x.shape[:2]))
    return {
        "eps_e": edge_error(x, tmpl, g.faces).tolist(),
        "eps_a": area_error(x, tmpl, g.faces).tolist(),
        "eps_c": collision_error(dist).tolist(),
        "min_distance_mm": (1000.0 * dist.min(1).values).tolist(),
    }


def evaluate(model: GapsModel, cases: list[Case] | None = None, body: AnnyBody | None = None
             ) -> dict:
    """Metrics of a model on evaluation cases (default: :func:`held_out_cases`).

    Returns
    -------
    dict
        ``cases``: per case its label, mean ``eps_e``, ``eps_a``, ``eps_c`` (%), worst
        ``eps_c`` and ms per frame; ``mean``: the means over all frames of all cases;
        ``ms_per_frame``: CPU ms per frame of the model alone and with body posing.
    """
    body = AnnyBody.load() if body is None else body
    cases = held_out_cases() if cases is None else cases
    rows, allm = [], {"eps_e": [], "eps_a": [], "eps_c": []}
    sec = {"model": 0.0, "with_posing": 0.0}
    n = 0
    for c in cases:
        d = drape_case(model, body, c)
        m = frame_metrics(d, body)
        for k in allm:
            allm[k].extend(m[k])
        for k in sec:
            sec[k] += d.seconds[k]
        n += d.x.shape[0]
        rows.append({
            "motion": c.motion, "seed": c.seed, "speed": c.speed,
            "shape": [round(v, 4) for v in c.shape], "frames": c.frames,
            **{k: float(np.mean(m[k])) for k in allm},
            "eps_c_max": float(np.max(m["eps_c"])),
            "ms_per_frame": 1000.0 * d.seconds["model"] / d.x.shape[0],
        })
    return {
        "cases": rows,
        "mean": {k: float(np.mean(v)) for k, v in allm.items()},
        "ms_per_frame": {k: 1000.0 * v / max(n, 1) for k, v in sec.items()},
    }
