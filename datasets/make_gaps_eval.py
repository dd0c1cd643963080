"""Held-back evaluation set of the GAPS benchmark and its physics reference drapes.

Run ``python datasets/make_gaps_eval.py [--garments tshirt dress skirt] [--frames 30]
[--quick] [--cache DIR] [--workers N]``: drapes every case with the reference solver
(:func:`draping.drape.prepare` + :func:`draping.drape.drape_frames`, the ground truth of
``polygeo drape-reference``) into a cache outside the repository, resumable frame by frame.
``benchmarks/bm_gaps.py`` imports this file and re-uses the cache.

What is held back from GAPS training (:func:`draping.gaps.training_sequences` samples walk,
arms and squat at speeds 0.75 / 1 / 1.3 and ``random`` with seeds below 1000, never
``jacks``; body shapes are drawn with the run's seed, below 1000;
``draping.gaps.held_out_cases`` uses seeds 1000-1003):

* motions: ``turn`` (a motion type never trained on) and ``random`` with seed 2000;
* body shapes: :func:`draping.gaps.random_shapes` with seeds 2000 and 2001 (draws that no
  training pool and none of the trainer's own held-out cases use);
* garments: the T-shirt, the dress and the skirt (5,000-vertex templates carried over to each
  shape by :func:`draping.garments.fit_garment_to_shape`, as the trainer does).

A motion is generated once with :data:`MOTION_FRAMES` frames at 30 fps and a case uses its
first ``frames`` (the procedural motions depend on their length), so that a longer
evaluation extends a cached reference instead of redoing it. The cache key of a reference is
the fingerprint of garment, the template's content (:func:`template_digest`), the content of
the rest garment carried over to the case's shape (:func:`rest_digest`: a changed
``fit_garment_to_shape`` gets new references), motion, seed, shape, motion length and solver
settings.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

GARMENTS = ("tshirt", "dress", "skirt")
#: Held-back motions: (name, seed).
MOTIONS = (("turn", 0), ("random", 2000))
#: Seeds of the held-back body shapes (:func:`draping.gaps.random_shapes`).
SHAPE_SEEDS = (2000, 2001)
#: Frames each motion is generated with (30 fps); cases use a prefix.
MOTION_FRAMES = 60
VERSION = 1


@dataclass(frozen=True)
class EvalCase:
    """One held-back sequence: a garment on a shape moving through a motion."""

    garment: str
    motion: str
    seed: int
    shape_seed: int
    shape: tuple
    frames: int

    @property
    def label(self) -> str:
        return f"{self.garment}/{self.motion}{self.seed}/shape{self.shape_seed}"


def default_cache() -> Path:
    """``$POLYGEO_CACHE/bm_gaps`` or ``~/.cache/polygeo/bm_gaps`` (outside the repository)."""
    root = os.environ.get("POLYGEO_CACHE")
    return (Path(root) if root else Path.home() / ".cache" / "polygeo") / "bm_gaps"


def shape_of(seed: int) -> tuple:
    """The phenotype vector (6 floats in ``[0, 1]``) drawn with ``seed``."""
    from draping.gaps import random_shapes

    return tuple(float(v) for v in random_shapes(1, seed)[0])


def eval_cases(garments=GARMENTS, frames: int = 30, quick: bool = False, motions=None,
               shape_seeds=None) -> list[EvalCase]:
    """The cases: per garment 2 motions x 2 shapes (quick: the turn on the first shape).

    ``motions`` (names in :data:`MOTIONS`) and ``shape_seeds`` (in :data:`SHAPE_SEEDS`) keep
    a subset of them.
    """
    ms = [m for m in (MOTIONS[:1] if quick else MOTIONS) if motions is None or m[0] in motions]
    seeds = [k for k in (SHAPE_SEEDS[:1] if quick else SHAPE_SEEDS)
             if shape_seeds is None or k in shape_seeds]
    if not ms or not seeds:
        raise ValueError(f"motions, shape_seeds: no case left of {MOTIONS} x {SHAPE_SEEDS}")
    if not 1 <= frames <= MOTION_FRAMES:
        raise ValueError(f"frames: expected 1..{MOTION_FRAMES}, got {frames}")
    return [EvalCase(g, m, s, k, shape_of(k), frames)
            for g in garments for m, s in ms for k in seeds]


def motion_file(cache: Path, motion: str, seed: int, body=None) -> Path:
    """The motion's ``.npz`` (``rotations``, ``translation``, ``fps``), made once."""
    from draping.body import AnnyBody
    from draping.gaps import sequence_of
    from polygeo.runs import atomic_write

    p = Path(cache) / "motions" / f"{motion}_{seed}_{MOTION_FRAMES}.npz"
    if not p.is_file():
        body = AnnyBody.load() if body is None else body
        s = sequence_of(body, motion, MOTION_FRAMES, seed, 1.0)
        p.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(p, lambda f: np.savez(f, rotations=s.rotations.double().numpy(),
                                           translation=s.translation.double().numpy(),
                                           fps=np.float64(30.0)))
    return p


def case_motion(cache: Path, case: EvalCase, body=None):
    """The case's :class:`draping.motion.Motion` (its ``frames``, float32, 30 fps)."""
    import torch

    from draping.motion import Motion

    with np.load(motion_file(cache, case.motion, case.seed, body)) as z:
        rot, trans = z["rotations"][: case.frames], z["translation"][: case.frames]
    return Motion(torch.as_tensor(rot, dtype=torch.float32),
                  torch.as_tensor(trans, dtype=torch.float32), 30.0)


def garment_digest(g) -> str:
    """SHA-256 of a garment's content (float64 vertices and int64 faces)."""
    import hashlib

    h = hashlib.sha256()
    h.update(np.ascontiguousarray(np.asarray(g.vertices, dtype=np.float64)).tobytes())
    h.update(np.ascontiguousarray(np.asarray(g.faces, dtype=np.int64)).tobytes())
    return h.hexdigest()


def template_digest(name: str) -> str:
    """SHA-256 of a shipped garment template's content (float64 vertices and faces).

    Part of a reference's cache key: a regenerated template (new cut, new sampling, moved
    vertices) gets new references instead of re-using drapes of the old one.
    """
    from draping.garments import garment

    return garment_digest(garment(name))


def rest_digest(name: str, shape: tuple) -> str:
    """SHA-256 of the rest garment the GAPS trainer makes for a shape (freshly carried over).

    Part of a reference's cache key: a changed carry-over (:func:`draping.gaps.shape_case`,
    :func:`draping.garments.fit_garment_to_shape`) gets new references. About 0.2-1 CPU s.
    """
    from draping.body import AnnyBody
    from draping.gaps import shape_case
    from draping.garments import garment

    return garment_digest(shape_case(garment(name), AnnyBody.load(), shape).garment)


@functools.cache
def data_digest(garment_name: str, shapes: int, seed: int, probes: int = 2) -> str:
    """SHA-256 of what a run trains on: the template and its first ``probes`` shape fits.

    The rest garments of the first training shapes (:func:`draping.gaps.random_shapes` with
    the run's ``shapes`` and ``seed``), carried over as the trainer does: a changed template
    or a changed :func:`draping.garments.fit_garment_to_shape` changes it (cached per
    process: call ``data_digest.cache_clear()`` after changing either in a live process).
    """
    import hashlib

    from draping.body import AnnyBody
    from draping.gaps import random_shapes, shape_case
    from draping.garments import garment

    g = garment(garment_name)
    h = hashlib.sha256(garment_digest(g).encode())
    body = AnnyBody.load()
    for s in random_shapes(shapes, seed)[:probes]:
        h.update(garment_digest(shape_case(g, body, s).garment).encode())
    return h.hexdigest()


def _key(case: EvalCase) -> str:
    from draping.drape import DEFAULT_SOLVER
    from polygeo.runs import fingerprint

    return fingerprint({"garment": case.garment, "template": template_digest(case.garment),
                        "rest": rest_digest(case.garment, tuple(case.shape)),
                        "motion": case.motion, "seed": case.seed,
                        "shape": list(case.shape), "motion_frames": MOTION_FRAMES,
                        "solver": dataclasses.asdict(DEFAULT_SOLVER), "version": VERSION})


def reference_dir(cache: Path, case: EvalCase) -> Path:
    """Folder of a case's reference drape in the cache."""
    return (Path(cache) / "refs"
            / f"{case.garment}_{case.motion}{case.seed}_s{case.shape_seed}_{_key(case)[:10]}")


def _rest_garment(folder: Path, case: EvalCase):
    """The shape's rest garment, made as the GAPS trainer makes it (cached as NPZ)."""
    from draping.body import AnnyBody
    from draping.gaps import shape_case
    from draping.garments import garment, read_garment_npz, save_garment

    p = folder / "garment.npz"
    if p.is_file():
        return read_garment_npz(p)
    g = shape_case(garment(case.garment), AnnyBody.load(), case.shape).garment
    save_garment(p, g)
    return g


def reference_drape(case: EvalCase, cache: Path | None = None, quiet: bool = True) -> dict:
    """The reference drape of a case's first ``frames`` frames (solved and cached as needed).

    Returns
    -------
    dict
        ``x``: (T, V, 3) float64 positions (m); ``rows``: the solver's per-frame metric rows
        (``eps_e``, ``eps_a``, ``eps_c``, seconds, CPU seconds, iterations, converged);
        ``faces``; ``rest``: the rest garment's vertices (m).
    """
    import torch

    from draping.body import ANNY_PHENOTYPES, AnnyBody
    from draping.drape import DEFAULT_SOLVER, DrapeJob, drape_frames, prepare
    from polygeo.runs import load_checkpoint, progress, save_checkpoint

    cache = default_cache() if cache is None else Path(cache)
    folder = reference_dir(cache, case)
    folder.mkdir(parents=True, exist_ok=True)
    ckp = folder / "reference.pt"
    key = _key(case)
    xs, rows, v = [], [], None
    if ckp.is_file():
        ck = load_checkpoint(ckp)
        if ck.meta.get("fingerprint") == key:
            xs = list(ck.tensors["x"].unbind(0))
            v, rows = ck.tensors["v"], list(ck.meta["rows"])
    g = _rest_garment(folder, case)
    if len(xs) < case.frames:
        body = AnnyBody.load(dtype=torch.float64)
        job = DrapeJob(garment=case.garment, motion_file=str(motion_file(cache, case.motion,
                                                                         case.seed)),
                       frames=MOTION_FRAMES, shape=tuple(zip(ANNY_PHENOTYPES, case.shape)))
        scene = prepare(job, body, g)
        bar = progress(total=case.frames, initial=len(xs), desc=case.label, quiet=quiet,
                       unit="frame")
        start = len(xs)
        for fr in drape_frames(scene, DEFAULT_SOLVER, start=start,
                               x=xs[-1] if xs else None, v=v):
            xs.append(fr.x.double())
            v = fr.v.double()
            rows.append(fr.row)
            save_checkpoint(ckp, {"x": torch.stack(xs), "v": v},
                            {"fingerprint": key, "rows": rows, "case": dataclasses.asdict(case),
                             "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())})
            bar.update(1)
            if len(xs) >= case.frames:
                break
        bar.close()
    return {"x": torch.stack(xs[: case.frames]).numpy(), "rows": rows[: case.frames],
            "faces": np.asarray(g.faces), "rest": np.asarray(g.vertices)}


def _one(args) -> str:
    case, cache, quiet = args
    import torch

    torch.set_num_threads(1)
    t0, c0 = time.perf_counter(), time.process_time()
    reference_drape(case, cache, quiet)
    return (f"{case.label}: {case.frames} frames, {time.process_time() - c0:.0f} CPU s, "
            f"{time.perf_counter() - t0:.0f} s wall")


def run_all(cases: list[EvalCase], cache: Path, workers: int = 1, quiet: bool = True) -> None:
    """Solve the references of ``cases`` (``workers`` processes, one thread each)."""
    jobs = [(c, cache, quiet) for c in cases]
    if workers <= 1:
        for j in jobs:
            print(_one(j), flush=True)
        return
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(workers, mp_context=mp.get_context("fork")) as ex:
        for msg in ex.map(_one, jobs):
            print(msg, flush=True)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--garments", nargs="+", default=list(GARMENTS), choices=GARMENTS)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--quick", action="store_true", help="one case per garment")
    ap.add_argument("--cache", type=Path, default=None)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--quiet", action="store_true")
    a = ap.parse_args(argv)
    for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        os.environ.setdefault(k, "1")
    cache = default_cache() if a.cache is None else a.cache
    run_all(eval_cases(a.garments, a.frames, a.quick), cache, a.workers, a.quiet)


if __name__ == "__main__":
    sys.exit(main())
