"""The run folder of ``polygeo drape``: the same files as ``polygeo drape-reference``.

Part of :mod:`draping.gaps`; written through :mod:`draping.outputs`.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from draping.body import AnnyBody
from draping.garments import save_garment

from .data import shape_case, template_garment
from .infer import (
    check_garment_for,
    drape_motion,
    load_model,
    model_garment,
    shipped_garments,
    shipped_model_path,
)
from .settings import GapsSettings

__all__ = ["drape_job", "resolve_model", "reference_errors"]


def resolve_model(method: str, garment: str, garment_file: str | None, model_file: str | None,
                  body: AnnyBody | None = None):
    """The model of a ``polygeo drape`` call, checked against the garment asked for.

    Raises
    ------
    ValueError
        No model for the garment (none shipped, or a method other than gaps without
        ``--model``), or a model trained for another garment or method.
    """
    if model_file is None:
        if method != "gaps" or garment_file is not None:
            raise ValueError(f"--model: required for method {method!r}"
                             + (" with --garment-file" if garment_file else "")
                             + " (train one with polygeo train-drape)")
        path = shipped_model_path(garment)
        if not path.is_file():
            raise ValueError(f"--garment: no shipped GAPS model for {garment!r} (shipped: "
                             f"{', '.join(shipped_garments())}); train one with polygeo "
                             "train-drape and pass --model")
        model = load_model(path)
    else:
        model = load_model(model_file)
    if model.settings.method != method:
        raise ValueError(f"--method: the model was trained as {model.settings.method!r}, got "
                         f"{method!r}")
    body = AnnyBody.load() if body is None else body
    if garment_file is not None:
        g = template_garment(GapsSettings(garment_file=garment_file), body)
    else:
        if model.settings.garment_file is not None or model.garment_name != garment:
            raise ValueError(f"--garment: the model was trained for garment "
                             f"{model.garment_name!r}, got {garment!r}")
        g = model_garment(model)
    check_garment_for(model, g)
    return model, body


def reference_errors(case, body_faces, motion, x: torch.Tensor, dt: float, quiet: bool):
    """Reference drape of the same frames and the per-frame ``e_dist`` (cm), ``e_norm`` (deg)."""
    from draping.collision import MeshQuery
    from draping.drape import DEFAULT_SOLVER, DrapeJob, prepare
    from draping.metrics import distance_error, normal_error
    from draping.reference import drape_static, drape_step
    from polygeo.runs import progress

    body64 = AnnyBody.load(dtype=torch.float64)
    job = DrapeJob(frames=len(motion.rotations))
    scene = prepare(job, body64, case.garment)
    posed = body64.pose(case.shape.double(), motion.rotations.double(),
                        motion.translation.double())
    faces = np.asarray(case.garment.faces)
    q = MeshQuery(posed.vertices[0], body_faces)
    rows, xr, vr = [], None, None
    for t in progress(range(x.shape[0]), desc="reference", quiet=quiet, unit="frame"):
        q.update(posed.vertices[t])
        if t == 0:
            from draping.drape import skin_garment

            sk = skin_garment(case.garment.vertices, scene.weights, posed.transforms[:1])[0]
            res = drape_static(scene.rest, sk, q, DEFAULT_SOLVER)
        else:
            res = drape_step(scene.rest, xr, vr, dt, q, DEFAULT_SOLVER)
        xr, vr = res.x, res.v
        xt = x[t].double()
        rows.append({"e_dist": float(distance_error(xt, xr)),
                     "e_norm": float(normal_error(xt, xr, faces))})
    return rows


def drape_job(args: argparse.Namespace) -> dict:
    """Drape what the ``polygeo drape`` arguments ask for and write the run folder.

    Returns
    -------
    dict
        What ``metrics.json`` holds.
    """
    from draping import outputs
    from draping.drape import parse_shape, read_motion
    from draping.motion import Motion, generate

    body = AnnyBody.load()
    pheno = dict(parse_shape(args.shape)) if args.shape else {}
    shape = body.shape_from(**pheno) if pheno else None
    if args.motion_file is not None:
        motion = read_motion(args.motion_file, body, args.frames)
    else:
        motion = generate(args.motion, body, args.frames, 30.0, args.seed)
    model, body = resolve_model(args.method, args.garment, args.garment_file, args.model, body)
    motion = Motion(motion.rotations.float(), motion.translation.float(), motion.fps)
    case = shape_case(model_garment(model), body, shape)
    d = drape_motion(model, body, motion, shape, case)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    save_garment(out / "garment.npz", case.garment)
    n = d.x.shape[0]
    ms = 1000.0 * d.seconds["model"] / n
    ms_pose = 1000.0 * d.seconds["with_posing"] / n
    rows = []
    for t in range(n):
        outputs.write_frame(out, t, d.x[t].double(), case.garment.faces, d.body_vertices[t],
                            body.faces)
        row = {"frame": t, **outputs.frame_metrics(d.x[t].double(), case.garment.vertices,
                                                   case.garment.faces, d.body_vertices[t].double(),
                                                   body.faces)}
        row.update(ms_per_frame=ms, ms_per_frame_with_posing=ms_pose)
        rows.append(row)
    if args.reference:
        t0 = time.process_time()
        ref = reference_errors(case, body.faces.numpy(), motion, d.x, 1.0 / float(motion.fps),
                               args.quiet)
        for r, e in zip(rows, ref):
            r.update(e)
        ref_cpu = time.process_time() - t0
    settings = {"method": args.method, "model": str(args.model or shipped_model_path(args.garment)),
                "garment": args.garment_file or args.garment,
                "motion": args.motion_file or args.motion, "frames": n, "shape": pheno,
                "seed": args.seed, "reference": bool(args.reference)}
    extra = {"reference_cpu_seconds": ref_cpu} if args.reference else {}
    summary = outputs.write_metrics(out, rows, settings,
                                    garment_vertices=len(case.garment.vertices),
                                    dt=1.0 / float(motion.fps), **extra)
    if not args.no_pictures:
        outputs.write_pictures(out, case.garment.faces, n,
                               body_vertices=body.proxy_vertices(d.body_vertices),
                               body_faces=body.proxy_faces, fps=float(motion.fps))
    return summary
