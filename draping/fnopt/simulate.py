"""Rollouts with any inner optimiser, their metrics against the converged reference, files.

Metrics per frame: ``e_CD`` (``polygeo.proximity.chamfer_distance`` with 10 000 area-uniform
samples per surface, both meshes normalised by the reference's unit sphere, times 1e3),
``e_3D`` (:func:`draping.metrics.relative_vertex_error`), ``L_cloth`` (J) and wall-clock and CPU
milliseconds per frame of the optimiser.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from polygeo.checks import check_int

from ..metrics import relative_vertex_error
from . import cloth
from .classical import CLASSICAL, REFERENCE_TOL, solve_pcg, solve_reference
from .coarse import check_grid_option
from .handles import DT, check_motion
from .rollouts import Rollout, rollout
from .settings import COARSE_EVERY, FNOPT_COARSE, FNOPT_COARSE_EVERY, FNOPT_COARSE_FROM, OPTIMIZERS

__all__ = ["SimSettings", "OPTIMIZERS", "DEFAULT_LR", "PCG_NORMAL_SPLIT", "step_function", "run",
           "e_cd", "frame_metrics", "reference_rollout", "write_outputs"]

#: Default step sizes (mass metric); ``benchmarks/bm_fnopt.py`` reports their errors. GD:
#: ``None``, per sheet the stable step of :func:`~draping.fnopt.preconditioners.curvature_bound`
#: (the previous fixed 2e-3 diverged from 24x24 on, within 1-3 frames: the mass-metric curvature
#: grows as ``1 / h^2``, its largest eigenvalue 1.6e4 at 64x64 with the default material).
DEFAULT_LR = {"gd": None, "adam": 0.1, "lbfgs": 1.0}

#: ``optimizer="pcg"``: :func:`~draping.fnopt.classical.solve_pcg` with the out-of-plane
#: directions cut at this many DCT modes (``normal=True, split=PCG_NORMAL_SPLIT``), the shipped
#: weights' ``normal_split``: FNOpt's classical directions without the FNO, the ``pcg-n`` rows of
#: ``benchmarks/bm_fnopt.py`` and session 14's equal-cost control.
PCG_NORMAL_SPLIT = 4

@dataclass
class SimSettings:
    """A rollout: grid ``res`` (H, W), sheet width ``size`` (m), handles, motion, optimiser.

    ``fno_coarse`` (FNOpt only; 0, the default: off): run the FNO on the grid whose longer side
    has this many vertices (``solve_fnopt(coarse_res=...)``, :mod:`draping.fnopt.coarse`).
    ``recycle`` (FNOpt only; 0, the default: off): carry the span of each solve's last
    ``recycle`` updates to the next frame's solve (``solve_fnopt(recycle=...)``).
    ``fno_every`` (FNOpt only; 1, the default: every iteration): the FNO's proposal on every
    ``fno_every``-th iteration only, the classical step between (``solve_fnopt(fno_every=...)``).
    ``optimizer="pcg"``: FNOpt's step without the FNO, ``iters`` iterations of PCG with the
    normal directions (:data:`PCG_NORMAL_SPLIT`); ``lr`` is not used (exact subspace steps).
    ``coarse`` (``pcg`` or ``fnopt``): the two-level coarse correction on the grid whose longer
    side has this many vertices (``solve_pcg(coarse=...)``, ``solve_fnopt(two_level=...)``,
    :mod:`draping.fnopt.twolevel`; 0: off), rebuilt every ``coarse_every`` frames, joining the
    inner iterations ``k >= coarse_from`` (``fnopt`` only; ``solve_fnopt(two_level_from=...)``).
    ``None`` (the defaults) resolves per optimiser: ``fnopt`` :data:`FNOPT_COARSE` every
    :data:`FNOPT_COARSE_EVERY` frames from iteration :data:`FNOPT_COARSE_FROM` (FNOpt's default
    step; the shipped weights were trained without it), every other optimiser off (``pcg`` with
    a ``coarse``: every :data:`COARSE_EVERY` frames, from iteration 0).
    """

    res: tuple = (64, 64)
    size: float = 1.0
    handles: str = "corners"
    motion: str = "xy"
    speed: float = 1.0
    frames: int = 120
    optimizer: str = "fnopt"
    iters: int = 10
    lr: float | None = None
    material: cloth.Material = field(default_factory=cloth.Material)
    repulsion: float = 0.0
    orientation: str = "vertical"
    fno_coarse: int = 0
    recycle: int = 0
    fno_every: int = 1
    coarse: int | None = None
    coarse_every: int | None = None
    coarse_from: int | None = None

    def __post_init__(self) -> None:
        if self.optimizer not in OPTIMIZERS:
            raise ValueError(f"optimizer: expected one of {list(OPTIMIZERS)}, "
                             f"got {self.optimizer!r}")
        check_motion(self.motion)
        cloth.layout_points(self.handles)
        if isinstance(self.iters, bool) or not isinstance(self.iters, int) or self.iters < 1:
            raise ValueError(f"iters: expected an int >= 1, got {self.iters!r}")
        if isinstance(self.frames, bool) or not isinstance(self.frames, int) or \
                self.frames < 1:
            raise ValueError(f"frames: expected an int >= 1, got {self.frames!r}")
        self.res = tuple(int(r) for r in self.res)
        check_grid_option(self.fno_coarse, "fno_coarse")
        from .model import check_fno_every, check_recycle

        check_recycle(self.recycle)
        check_fno_every(self.fno_every)
        self._resolve_coarse()

    def _resolve_coarse(self) -> None:
        """Check the two-level fields; ``None``: the optimiser's default."""
        fnopt = self.optimizer == "fnopt"
        if self.coarse is None:
            self.coarse = FNOPT_COARSE if fnopt else 0
        check_grid_option(self.coarse, "coarse")
        if self.coarse and self.optimizer not in ("pcg", "fnopt"):
            raise ValueError(f"coarse: {self.coarse} needs optimizer 'pcg' or 'fnopt', got "
                             f"{self.optimizer!r}")
        if self.coarse_every is None:
            self.coarse_every = FNOPT_COARSE_EVERY if fnopt else COARSE_EVERY
        check_int(self.coarse_every, "coarse_every", low=1)
        if self.coarse_from is None:
            self.coarse_from = FNOPT_COARSE_FROM if fnopt and self.coarse else 0
        check_int(self.coarse_from, "coarse_from", low=0)
        if self.coarse_from and not (fnopt and self.coarse):
            raise ValueError(f"coarse_from: {self.coarse_from} needs optimizer 'fnopt' with a "
                             f"coarse grid (got {self.optimizer!r}, coarse {self.coarse})")

    def two_level_options(self) -> dict:
        """``solve_fnopt``'s two-level keywords for these settings (``{}`` when ``coarse`` is 0)."""
        if not self.coarse:
            return {}
        return {"two_level": self.coarse, "two_level_every": self.coarse_every,
                "two_level_from": self.coarse_from}

    def sheet(self) -> cloth.Sheet:
        """The grid sheet."""
        return cloth.Sheet(self.res[0], self.res[1], self.size)

    def key(self) -> dict:
        """What the reference rollout depends on."""
        d = asdict(self)
        for k in ("optimizer", "iters", "lr", "fno_coarse", "recycle", "fno_every", "coarse",
                  "coarse_every", "coarse_from"):
            d.pop(k)
        return d


def step_function(settings: SimSettings, model=None):
    """``step(problem, a_prev) -> a`` for the settings' optimiser (``model``: an FNO).

    GD, Adam and L-BFGS take the fused closed-form gradient (``fused_grad``: autograd's values
    up to rounding, 2.7x cheaper L-BFGS iterations at 64x64; autograd where it does not apply,
    e.g. with repulsion), as FNOpt's inference and ``benchmarks/bm_fnopt.py``'s classical rows
    do, so that ``polygeo simulate`` and the benchmark time the same solver. ``pcg``:
    ``solve_pcg(normal=True, split=PCG_NORMAL_SPLIT)`` (with ``coarse``: the two-level
    correction too, its coarse space kept across the rollout's frames; FNOpt's ``coarse`` the
    same, as ``solve_fnopt(two_level=...)``). Every solver but the
    reference runs under ``torch.inference_mode`` where the step problem needs no autograd
    (:func:`~draping.fnopt.step_problem.autograd_free_call`).
    """
    name, n = settings.optimizer, settings.iters
    if name == "reference":
        return lambda p, a0: solve_reference(p, a0)
    if name == "fnopt":
        from .model import load_pretrained, solve_fnopt

        net = model if model is not None else load_pretrained()
        k, r, e, memory = settings.fno_coarse, settings.recycle, settings.fno_every, {}
        two = settings.two_level_options()
        return lambda p, a0: solve_fnopt(net, p, n, coarse_res=k, recycle=r, memory=memory,
                                         fno_every=e, **two)
    if name == "pcg":
        k, memory = settings.coarse, {}
        if k:
            return lambda p, a0: solve_pcg(p, n, normal=True, split=PCG_NORMAL_SPLIT, coarse=k,
                                           coarse_every=settings.coarse_every,
                                           memory=memory)
        return lambda p, a0: solve_pcg(p, n, normal=True, split=PCG_NORMAL_SPLIT)
    lr = settings.lr if settings.lr is not None else DEFAULT_LR[name]
    if name == "lbfgs":
        return lambda p, a0: CLASSICAL[name](p, n, step=lr, fused_grad=True)
    return lambda p, a0: CLASSICAL[name](p, n, lr=lr, fused_grad=True)


def run(settings: SimSettings, model=None, progress=None) -> Rollout:
    """Roll the settings out (the reference warm-starts from the previous acceleration)."""
    ref = settings.optimizer == "reference"
    return rollout(settings.sheet(), settings.material, settings.handles, settings.motion,
                   settings.frames, step_function(settings, model), settings.speed, DT,
                   settings.orientation, settings.repulsion, warm_start=ref,
                   dtype=torch.float64 if ref else torch.float32, progress=progress)


def reference_rollout(settings: SimSettings, cache_dir: str | Path | None = None,
                      progress=None, tol: float = REFERENCE_TOL) -> Rollout:
    """The converged reference of ``settings`` (cached as NPZ in ``cache_dir``).

    Every step is solved by :func:`solve_reference` to the RMS residual ``tol`` (m/s^2),
    warm-started from the previous frame's acceleration, with float64 states.
    """
    from polygeo import runs

    path = None
    if cache_dir is not None:
        fp = runs.fingerprint({**settings.key(), "tol": tol, "state": "float64",
                               "material": asdict(settings.material)})
        path = Path(cache_dir) / f"reference_{fp}.npz"
        if path.is_file():
            z = np.load(path)
            return Rollout(torch.from_numpy(z["positions"]), z["loss"].tolist(),
                           z["ms"].tolist(), torch.from_numpy(z["handles"]))
    s = settings
    ro = rollout(s.sheet(), s.material, s.handles, s.motion, s.frames,
                 lambda p, a0: solve_reference(p, a0, tol=tol), s.speed, DT, s.orientation,
                 s.repulsion, warm_start=True, dtype=torch.float64, progress=progress)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        buf = {"positions": ro.positions.numpy(), "loss": np.asarray(ro.loss),
               "ms": np.asarray(ro.ms), "handles": ro.handles.numpy()}
        runs.atomic_write(path, lambda fh: np.savez(fh, **buf))
    return ro


def e_cd(x: torch.Tensor, x_ref: torch.Tensor, faces: np.ndarray, faces_ref: np.ndarray,
         seed: int = 0) -> float:
    """Chamfer distance x 1e3 (10k samples; unit sphere of the reference) of two meshes."""
    from polygeo.proximity import chamfer_distance

    return 1e3 * float(chamfer_distance(
        np.asarray(x_ref, dtype=np.float64).reshape(-1, 3), faces_ref,
        np.asarray(x, dtype=np.float64).reshape(-1, 3), faces, n_samples=10000, seed=seed))


def frame_metrics(ro: Rollout, ref: Rollout, every: int = 1) -> dict:
    """Per-frame e_CD, e_3D (frames 1, 1 + every, ...) of a rollout against its reference."""
    h, w = ro.positions.shape[1:3]
    hr, wr = ref.positions.shape[1:3]
    f = cloth.grid_faces(h, w).numpy()
    fr = cloth.grid_faces(hr, wr).numpy()
    frames = list(range(1, ro.positions.shape[0], every))
    same = (h, w) == (hr, wr)
    cd = [e_cd(ro.positions[k], ref.positions[k], f, fr) for k in frames]
    e3 = [float(relative_vertex_error(ro.positions[k].reshape(-1, 3),
                                      ref.positions[k].reshape(-1, 3)))
          if same else float("nan") for k in frames]
    return {"frames": frames, "e_cd": cd, "e_3d": e3}


def summary(values) -> float:
    """Mean of the finite values (nan if none)."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else float("nan")


def write_outputs(out_dir: str | Path, settings: SimSettings, ro: Rollout,
                  ref: Rollout | None, gif_every: int = 2, quiet: bool = True,
                  weights: str | Path | None = None) -> dict:
    """PLY per frame, ``metrics.json``, ``errors.png`` and ``rollout.gif`` in ``out_dir``.

    ``weights``: the FNOpt weights file the rollout used, recorded in ``metrics.json`` (as
    :func:`polygeo.runs.record_path` names it; ``None``: the shipped weights, or no FNO).
    """
    from polygeo import io as pio
    from polygeo import runs

    from .. import viz

    out = Path(out_dir)
    h, w = ro.positions.shape[1:3]
    faces = cloth.grid_faces(h, w).numpy()
    for k in range(ro.positions.shape[0]):
        pio.write_ply(out / "meshes" / f"{k:06d}.ply",
                      ro.positions[k].reshape(-1, 3).numpy().astype(np.float32), faces)
    t0 = time.perf_counter()
    m = frame_metrics(ro, ref) if ref is not None else None
    per_frame = []
    for k in range(1, ro.positions.shape[0]):
        rec = {"frame": k, "L_cloth": ro.loss[k - 1], "ms": ro.ms[k - 1]}
        if ro.cpu_ms is not None:
            rec["cpu_ms"] = ro.cpu_ms[k - 1]
        if m is not None:
            rec["e_cd"] = m["e_cd"][k - 1]
            rec["e_3d"] = m["e_3d"][k - 1]
        per_frame.append(rec)
    res = {"settings": {**asdict(settings), "material": asdict(settings.material)},
           "weights": None if weights is None else runs.record_path(weights),
           "reference_tol_m_s2": REFERENCE_TOL,
           "mean": {"L_cloth": summary(ro.loss), "ms": summary(ro.ms),
                    "cpu_ms": summary(ro.cpu_ms) if ro.cpu_ms is not None else float("nan")},
           "frames": per_frame, "metric_seconds": time.perf_counter() - t0}
    if m is not None:
        res["mean"]["e_cd"] = summary(m["e_cd"])
        res["mean"]["e_3d"] = summary(m["e_3d"])
        viz.plot_curves({"e_CD x 1e3": m["e_cd"], "e_3D x 1e2": [100 * e for e in m["e_3d"]]},
                        out / "errors.png", x={"e_CD x 1e3": m["frames"],
                                               "e_3D x 1e2": m["frames"]},
                        xlabel="frame", title=f"{settings.optimizer} vs reference")
    else:
        viz.plot_curves({"L_cloth (J)": ro.loss}, out / "errors.png", xlabel="frame")
    runs.atomic_write_json(out / "metrics.json", res)
    sel = list(range(0, ro.positions.shape[0], max(gif_every, 1)))
    pts = [ro.handles[k].numpy() for k in sel]
    imgs = viz.render_frames([ro.positions[k].reshape(-1, 3).numpy() for k in sel], faces,
                             points=pts)
    viz.write_gif(imgs, out / "rollout.gif", fps=60 / max(gif_every, 1))
    return res


def settings_json(s: SimSettings) -> str:
    """The settings as JSON."""
    return json.dumps({**asdict(s), "material": asdict(s.material)})
