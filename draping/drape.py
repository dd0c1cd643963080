"""Reference drapes of a garment on a moving body: the pipeline behind ``polygeo drape-reference``.

One place that strings the draping foundation together, reusable by every method that needs
ground-truth drapes (GAPS, OneFit and GarNet compare with it; GarNet trains on it):

1. **Body and motion.** The shipped Anny body (:class:`draping.body.AnnyBody`) at a shape
   (phenotypes in ``[0, 1]``), posed by a procedural motion (:func:`draping.motion.generate`)
   or by a motion file (``rotations (T, J, 3)`` in radians and ``translation (T, 3)`` in metres
   for the body's ``J`` bones, optional ``fps``).
2. **Garment.** A named template (:func:`draping.garments.garment`, carried over to a shape
   other than the default by :func:`draping.garments.fit_garment_to_shape`) or a user's
   OBJ/PLY (:func:`draping.garments.load_garment`, checked against the rest body).
3. **Skinning.** Garment blend weights from the body's (RBF body participation by default,
   :func:`draping.skinning.skinning_weights`); the skinned garment of each frame is the
   initial guess of static solves and the picture of what skinning alone gives.
4. **Solve.** Frame 0 (the motions start at the rest pose) is a static drape
   (:func:`draping.reference.drape_static`); every later frame is one backward-Euler step
   (:func:`draping.reference.drape_step`) at ``dt = 1 / fps`` (or, with ``static``, a static
   drape from that frame's skinned garment), against a signed-distance query of the full posed
   body (:class:`draping.collision.MeshQuery`, refitted per frame).
5. **Metrics** per frame (:mod:`draping.metrics`): ``eps_e``, ``eps_a`` (%, against the rest
   garment), ``eps_c`` (% of garment vertices inside the posed body), the energy (J), the
   solver's iterations and residual, and seconds per frame (wall clock, and CPU time of the
   process: on a shared machine the wall clock also counts the others' load).

:func:`run_drape` writes the frames (PLY), ``metrics.json``, pictures and a checkpoint after
every frame, so that an interrupted run resumes at the next frame with identical results.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from polygeo.checks import check_choice, check_int

from . import reference
from .body import ANNY_PHENOTYPES, AnnyBody
from .garments import GARMENTS, Garment
from .motion import MOTIONS, Motion

__all__ = [
    "DrapeJob",
    "DrapeScene",
    "FrameResult",
    "DEFAULT_SOLVER",
    "parse_shape",
    "read_motion",
    "skin_garment",
    "prepare",
    "drape_frames",
    "run_drape",
]

#: Solver settings of the pipeline: the reference defaults
#: (:class:`draping.reference.SolverSettings`).
DEFAULT_SOLVER = reference.SolverSettings()


@dataclass(frozen=True)
class DrapeJob:
    """What to drape (the settings of a run; their fingerprint keys its checkpoint).

    Attributes
    ----------
    garment : str
        One of :data:`draping.garments.GARMENTS` (ignored when ``garment_file`` is set).
    garment_file : str or None
        An OBJ/PLY garment in the rest pose of the default body shape (metres).
    motion : str
        One of :data:`draping.motion.MOTIONS` (ignored when ``motion_file`` is set).
    motion_file : str or None
        A motion ``.npz`` (:func:`read_motion`).
    frames : int
        Frames to drape (the first ``frames`` of a motion file).
    shape : tuple of (str, float)
        Phenotypes by name, values in ``[0, 1]`` (others 0.5, Anny's default adult).
    seed : int
        Seed of the ``random`` motion and of generated garment templates.
    res : int or None
        Garment vertex count (None: the shipped 5,000-vertex template).
    static : bool
        A static drape of every frame's pose instead of a dynamic sequence.
    skinning : str
        Garment skinning: ``"rbf"`` (default), ``"laplacian"`` or ``"nearest"``.
    fps : float
        Frames per second of generated motions (the time step is ``1 / fps`` s).
    """

    garment: str = "tshirt"
    garment_file: str | None = None
    motion: str = "walk"
    motion_file: str | None = None
    frames: int = 30
    shape: tuple[tuple[str, float], ...] = ()
    seed: int = 0
    res: int | None = None
    static: bool = False
    skinning: str = "rbf"
    fps: float = 30.0

    def __post_init__(self) -> None:
        if self.garment_file is None:
            check_choice(self.garment, "garment", GARMENTS)
        if self.motion_file is None:
            check_choice(self.motion, "motion", MOTIONS)
        check_int(self.frames, "frames", low=1)
        check_int(self.seed, "seed")
        if self.res is not None:
            check_int(self.res, "res", low=1000, high=100_000)
        check_choice(self.skinning, "skinning", ("rbf", "laplacian", "nearest"))
        if not (np.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"fps: expected a finite value > 0, got {self.fps}")
        for name, value in self.shape:
            _check_phenotype(name, value)


def _check_phenotype(name: str, value: float) -> None:
    if name not in ANNY_PHENOTYPES:
        raise ValueError(f"shape: unknown phenotype {name!r}, expected one of "
                         f"{', '.join(ANNY_PHENOTYPES)}")
    if not (np.isfinite(value) and 0.0 <= value <= 1.0):
        raise ValueError(f"shape: {name} expected a value in [0, 1], got {value}")


def parse_shape(text: str | None) -> tuple[tuple[str, float], ...]:
    """Phenotypes from ``"age=0.66,gender=0.2"`` (names of the six Anny phenotypes, [0, 1]).

    Raises
    ------
    ValueError
        A malformed item, an unknown name, a repeated name or a value outside ``[0, 1]``.
    """
    out: dict[str, float] = {}
    for item in (text or "").split(","):
        item = item.strip()
        if not item:
            continue
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep:
            raise ValueError(f"shape: expected NAME=VALUE items, got {item!r}")
        try:
            v = float(value)
        except ValueError:
            raise ValueError(f"shape: {name} expected a number in [0, 1], got {value!r}") from None
        _check_phenotype(name, v)
        if name in out:
            raise ValueError(f"shape: {name} given twice")
        out[name] = v
    return tuple(sorted(out.items()))


def read_motion(path: str | Path, body: AnnyBody, frames: int | None = None) -> Motion:
    """Read a motion ``.npz`` for the body: ``rotations (T, J, 3)``, ``translation (T, 3)``.

    ``rotations`` are axis-angle per bone (radians, :mod:`draping.body`'s parameterisation, the
    body's ``J`` bones in order), ``translation`` the root's (metres); an optional scalar
    ``fps`` (default 30). AMASS files (``poses``) are for SMPL bodies
    (:func:`draping.motion.read_amass`), not for the Anny rig.

    Raises
    ------
    FileNotFoundError
        No such file.
    ValueError
        Missing arrays, wrong shapes, NaN or infinite values, or a non-positive fps.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"motion file not found: {p}")
    try:
        with np.load(p, allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise ValueError(f"{p}: not a readable .npz motion ({exc})") from None
    if "rotations" not in d:
        hint = " (an AMASS file: those drive SMPL bodies)" if "poses" in d else ""
        raise ValueError(f"{p}: expected arrays 'rotations' (T, {body.num_bones}, 3) and "
                         f"'translation' (T, 3), got {sorted(d)}{hint}")
    rot = np.asarray(d["rotations"], dtype=np.float64)
    n = rot.shape[0] if rot.ndim else 0
    trans = np.asarray(d.get("translation", np.zeros((n, 3))), dtype=np.float64)
    if rot.ndim != 3 or rot.shape[1:] != (body.num_bones, 3) or n < 1:
        raise ValueError(f"{p}: rotations expected shape (T, {body.num_bones}, 3), "
                         f"got {rot.shape}")
    if trans.shape != (n, 3):
        raise ValueError(f"{p}: translation expected shape ({n}, 3), got {trans.shape}")
    bad = ~np.isfinite(rot).all(axis=(1, 2)) | ~np.isfinite(trans).all(axis=1)
    if bad.any():
        raise ValueError(f"{p}: NaN or infinite poses at frame(s) "
                         f"{np.flatnonzero(bad)[:5].tolist()}")
    fps = float(d["fps"]) if "fps" in d else 30.0
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"{p}: fps expected a finite value > 0, got {fps}")
    if frames is not None:
        rot, trans = rot[:frames], trans[:frames]
    dt = body.dtype
    return Motion(torch.as_tensor(rot, dtype=dt), torch.as_tensor(trans, dtype=dt), fps,
                  p.stem, tuple(body.bone_names))


def skin_garment(vertices: Any, weights: Any, transforms: torch.Tensor) -> torch.Tensor:
    """Linear blend skinning of rest garment vertices with dense blend weights.

    Parameters
    ----------
    vertices : (G, 3) float
        Rest garment (m).
    weights : (G, J) float
        Blend weights (rows sum to one).
    transforms : (T, J, 4, 4) float tensor
        Bone transforms (rest space to posed space) of ``T`` frames.

    Returns
    -------
    (T, G, 3) float64 tensor
        Skinned garment per frame (m).
    """
    v = torch.as_tensor(np.asarray(vertices), dtype=torch.float64)
    w = torch.as_tensor(np.asarray(weights), dtype=torch.float64)
    tr = transforms.to(torch.float64)
    blend = torch.einsum("gj,tjab->tgab", w, tr[..., :3, :])  # (T, G, 3, 4)
    return torch.einsum("tgab,gb->tga", blend[..., :3], v) + blend[..., 3]


class DrapeScene(NamedTuple):
    """Everything a drape needs, prepared once.

    Attributes
    ----------
    job : DrapeJob
    garment : Garment
        Rest garment on the job's body shape (m).
    rest : physics.RestState
        Its rest geometry and material.
    weights : (G, J) float64 ndarray
        Garment blend weights.
    body_faces : (F, 3) int64 ndarray
    body_vertices : (T, V, 3) float64 tensor
        Posed body per frame (m).
    skinned : (T, G, 3) float64 tensor
        Skinned garment per frame (m).
    proxy_faces : (P_f, 3) int64 ndarray
        Decimated body (pictures).
    proxy_vertices : (T, P, 3) float64 tensor
    dt : float
        Time step (s).
    """

    job: DrapeJob
    garment: Garment
    rest: Any
    weights: np.ndarray
    body_faces: np.ndarray
    body_vertices: torch.Tensor
    skinned: torch.Tensor
    proxy_faces: np.ndarray
    proxy_vertices: torch.Tensor
    dt: float


def _garment_for(job: DrapeJob, body: AnnyBody, shape: torch.Tensor | None) -> Garment:
    from . import garments as gm

    if job.garment_file is None:
        return gm.garment(job.garment, None if job.res is None else body, shape,
                          n_vertices=job.res, seed=job.seed)
    rv, _ = body.rest(None)
    rest0 = rv[0].double().numpy()
    faces = body.faces.numpy()
    g = gm.load_garment(job.garment_file, query=_query3(rest0, faces))
    if shape is not None:
        g = gm.fit_garment_to_shape(g, body, shape)
    return g


def _query3(vertices: np.ndarray, faces: np.ndarray):
    from .collision import MeshQuery

    mesh = MeshQuery(vertices, faces)

    def query(points):
        r = mesh.query(np.asarray(points, dtype=np.float64))
        return r.distance, r.closest, r.normal

    return query


def prepare(job: DrapeJob, body: AnnyBody | None = None, garment: Garment | None = None
            ) -> DrapeScene:
    """Body, motion, garment, skinning weights and skinned frames of a job.

    Parameters
    ----------
    job : DrapeJob
    body : AnnyBody, optional
        The body (default: the shipped asset, float64).
    garment : Garment, optional
        A garment already made for the job's shape (skips making / fitting it).

    Raises
    ------
    ValueError, FileNotFoundError
        Bad garment or motion files, or what the foundation modules raise.
    """
    from . import motion as mo
    from . import physics
    from .garments import face_stiffness
    from .skinning import dense_body_weights, skinning_weights

    body = AnnyBody.load(dtype=torch.float64) if body is None else body
    shape = body.shape_from(**dict(job.shape)) if job.shape else None
    if job.motion_file is not None:
        mot = read_motion(job.motion_file, body, job.frames)
    else:
        mot = mo.generate(job.motion, body, job.frames, job.fps, job.seed)
    g = _garment_for(job, body, shape) if garment is None else garment
    posed = body.pose(shape, mot.rotations, mot.translation)
    rv = posed.rest_vertices[0].double().numpy()
    wb = dense_body_weights((body.skin_indices.numpy(), body.skin_weights.double().numpy()),
                            body.num_vertices, body.num_bones)
    w = np.asarray(skinning_weights(job.skinning, g.vertices, rv, wb, garment_faces=g.faces))
    verts = posed.vertices.double()
    return DrapeScene(
        job=job, garment=g, rest=physics.rest_state(g.vertices, g.faces,
                                                    face_stiffness=face_stiffness(g)),
        weights=w,
        body_faces=body.faces.numpy(), body_vertices=verts,
        skinned=skin_garment(g.vertices, w, posed.transforms),
        proxy_faces=body.proxy_faces.numpy(), proxy_vertices=body.proxy_vertices(verts),
        dt=1.0 / float(mot.fps),
    )


class FrameResult(NamedTuple):
    """One draped frame: positions, velocities and its metric row (JSON-able)."""

    frame: int
    x: torch.Tensor
    v: torch.Tensor
    row: dict


def _row(scene: DrapeScene, t: int, res: reference.DrapeResult, distance: torch.Tensor,
         seconds: float, cpu_seconds: float) -> dict:
    from .outputs import frame_metrics

    g = scene.garment
    m = frame_metrics(res.x, g.vertices, g.faces, distance=distance)
    return {
        "frame": t,
        "eps_e": m["eps_e"],
        "eps_a": m["eps_a"],
        "eps_c": m["eps_c"],
        "energy": float(res.energy),
        "residual": float(res.residual),
        "iterations": int(res.iterations),
        "converged": bool(res.converged),
        "min_distance_mm": m["min_distance_mm"],
        "seconds": float(seconds),
        "cpu_seconds": float(cpu_seconds),
    }


INITS = ("project", "freefall", "skin")


def initial_guess(scene: DrapeScene, t: int, x: torch.Tensor, v: torch.Tensor, query,
                  solver: reference.SolverSettings, init: str = "project") -> torch.Tensor:
    """Initial guess of dynamic frame ``t`` from the state ``(x, v)`` of frame ``t - 1``.

    ``"project"``: the free fall moved out of the posed body
    (:func:`draping.reference.project_outside` to the collision clearance); ``"freefall"``:
    the free fall itself; ``"skin"``: the previous drape moved by the skinned garment's
    displacement from frame ``t - 1`` to ``t``, moved out of the body.
    """
    init = check_choice(init, "init", INITS)
    if init == "skin":
        guess = x + (scene.skinned[t] - scene.skinned[t - 1])
    else:
        guess = reference.free_fall(x, v, scene.dt, solver.gravity)
    if init == "freefall":
        return guess
    return reference.project_outside(guess, query, solver.collision_eps)


def drape_frames(scene: DrapeScene, solver: reference.SolverSettings | None = None, *,
                 start: int = 0, x: Any = None, v: Any = None, init: str = "project"):
    """Drape the scene's frames ``start .. T-1``, yielding a :class:`FrameResult` per frame.

    Parameters
    ----------
    scene : DrapeScene
    solver : SolverSettings, optional
        Default :data:`DEFAULT_SOLVER`.
    start : int
        First frame to solve; ``x``, ``v`` (m, m/s) are the state after frame ``start - 1``
        (needed for ``start > 0`` in dynamic drapes).
    init : str
        Initial guess of dynamic frames (:func:`initial_guess`).

    Yields
    ------
    FrameResult
    """
    from .collision import MeshQuery

    solver = DEFAULT_SOLVER if solver is None else solver
    n_frames = scene.body_vertices.shape[0]
    start = check_int(start, "start", low=0, high=n_frames)
    if start > 0 and not scene.job.static and (x is None or v is None):
        raise ValueError("x, v: the state of the previous frame is needed to resume at "
                         f"frame {start}")
    query = MeshQuery(scene.body_vertices[start], scene.body_faces)
    for t in range(start, n_frames):
        t0, c0 = time.perf_counter(), time.process_time()
        query.update(scene.body_vertices[t])
        if t == 0 or scene.job.static:
            res = reference.drape_static(scene.rest, scene.skinned[t], query, solver)
        else:
            x0 = initial_guess(scene, t, x, v, query, solver, init)
            res = reference.drape_step(scene.rest, x, v, scene.dt, query, solver, x0=x0,
                                       body_motion=scene.skinned[t] - scene.skinned[t - 1])
        distance = query.query(res.x).distance
        seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
        x, v = res.x, res.v
        yield FrameResult(t, x, v, _row(scene, t, res, distance, seconds, cpu))


# ------------------------------------------------------------------------------ run folder

CHECKPOINT = "checkpoint.pt"


@dataclass
class DrapeRun:
    """What :func:`run_drape` wrote: the folder, per-frame rows and the summary."""

    out_dir: Path
    rows: list = field(default_factory=list)
    summary: dict = field(default_factory=dict)
    resumed_at: int = 0


def _settings_record(job: DrapeJob, solver: reference.SolverSettings) -> dict:
    return {"job": dataclasses.asdict(job), "solver": dataclasses.asdict(solver), "version": 1}


def run_drape(job: DrapeJob, out_dir: str | Path, solver: reference.SolverSettings | None = None,
              *, resume: bool = True, quiet: bool = False, pictures: bool = True,
              body: AnnyBody | None = None,
              on_frame: Callable[[FrameResult], None] | None = None) -> DrapeRun:
    """Drape a job and write its run folder.

    Writes the run folder of :mod:`draping.outputs` (``meshes/000000.ply ...`` garment,
    float64; ``body/000000.ply ...`` posed body; ``metrics.json`` per-frame rows with their
    mean and max; ``strip.png`` and ``drape.gif`` with ``pictures``) plus ``garment.npz`` (the
    rest garment) and ``checkpoint.pt`` after every frame: a run interrupted after frame ``t``
    resumes at ``t + 1`` with the same results.

    Parameters
    ----------
    job : DrapeJob
    out_dir : str or Path
    solver : SolverSettings, optional
    resume : bool
        Continue from the folder's checkpoint (its settings must match; otherwise
        :class:`polygeo.runs.SettingsChangedError`).
    quiet : bool
        No progress bar.
    pictures : bool
        Render the strip and the GIF.
    body : AnnyBody, optional
    on_frame : callable, optional
        Called with each new :class:`FrameResult` after it is saved.

    Returns
    -------
    DrapeRun
    """
    from polygeo.runs import fingerprint, progress, resume_state, save_checkpoint

    from .garments import read_garment_npz, save_garment
    from .outputs import write_frame, write_metrics, write_pictures

    solver = DEFAULT_SOLVER if solver is None else solver
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fp = fingerprint(_settings_record(job, solver))
    ck = resume_state(out, fp, name=CHECKPOINT) if resume else None
    g = read_garment_npz(out / "garment.npz") if ck is not None else None
    scene = prepare(job, body, g)
    if ck is None:
        save_garment(out / "garment.npz", scene.garment)
    start, rows = 0, []
    x = v = None
    if ck is not None:
        start, rows = int(ck.meta["next_frame"]), list(ck.meta["rows"])
        x, v = ck.tensors["x"], ck.tensors["v"]
    n = scene.body_vertices.shape[0]
    bar = progress(total=n, desc="drape", quiet=quiet, initial=start, unit="frame")
    for fr in drape_frames(scene, solver, start=start, x=x, v=v):
        write_frame(out, fr.frame, fr.x, scene.garment.faces, scene.body_vertices[fr.frame],
                    scene.body_faces)
        rows.append(fr.row)
        save_checkpoint(out / CHECKPOINT, {"x": fr.x, "v": fr.v},
                        {"fingerprint": fp, "next_frame": fr.frame + 1, "rows": rows})
        bar.update(1)
        bar.set_postfix(eps_c=f"{fr.row['eps_c']:.2f}%", s=f"{fr.row['seconds']:.1f}")
        if on_frame is not None:
            on_frame(fr)
    bar.close()
    summary = write_metrics(
        out, rows, _settings_record(job, solver), garment_vertices=int(len(scene.garment.vertices)),
        dt=scene.dt, static=job.static, all_converged=bool(all(r["converged"] for r in rows)))
    if pictures:
        write_pictures(out, scene.garment.faces, n, body_vertices=scene.proxy_vertices,
                       body_faces=scene.proxy_faces, fps=1.0 / scene.dt)
    return DrapeRun(out, rows, summary, start)
