"""The PolySfT sequence driver: adaptive sliding window, re-partitioning, checkpoints, resume.

Adaptive sliding window (thesis section 5.5.2): the frames ``s .. s + W - 1`` are optimised
together (:mod:`sft.window`) until the loss has not improved on its running minimum for
``patience`` iterations or ``max_iterations`` have run; frame ``s`` is then final (its mesh is
written at once), the window moves forward by one frame and the frame that enters it starts
from the parameters of the frame before it (extrapolated from the two before it by default).
When a patch of the frame just finished has grown too steep to bend further, that frame's
surface is re-partitioned into new patches (``ModelSettings.refit_tilt``). At the end of the
sequence the window shrinks. Every frame is thus optimised in up to ``W`` windows; the wall
time and the iterations of window ``s`` are charged to frame ``s``.

Checkpoints are written after every ``checkpoint_every`` windows (atomically): the index of
the next window, the parameters of the frames still in the window (with their Adam moments),
the model's state (active jet order) and the surface of the last re-partition, as plain
tensors and JSON, read back without executing code. A checkpoint is keyed by a fingerprint of
the sequence, the frame count and the settings that decide the result (not ``output``).
Windows are deterministic, so resuming gives the same meshes as an uninterrupted run. Only
the current window's frames are held in memory; meshes, per-frame records (``frames.jsonl``)
and loss curves (``losses.jsonl``) are written as the run goes and read back once at the end
for ``metrics.json``, so memory does not grow with the number of frames.
"""

from __future__ import annotations

import hashlib
import os
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from polygeo import runs
from polygeo.checks import check_int
from polygeo.io import write_ply

from .data import Sequence, load_sequence
from .losses import ImageTerms, Inextensibility
from .metrics import frame_errors, summarize
from .model import PATCHES_AUTO, DeformationModel, JetModel, JetTemplate
from .settings import SfTSettings
from .window import _initial, _objective_parts, _optimize_window, _Window, reconstruct_window

__all__ = ["SfTSettings", "SfTResult", "run_sft", "reconstruct_window", "CHECKPOINT_NAME"]

#: File name of the checkpoint inside the output folder.
CHECKPOINT_NAME = runs.CHECKPOINT_NAME
#: Per-frame records, one JSON line per frame, written as the run goes.
FRAMES_NAME = "frames.jsonl"
#: Loss curves, one JSON line per window.
LOSSES_NAME = "losses.jsonl"


@dataclass(frozen=True)
class SfTResult:
    """Outcome of :func:`run_sft`.

    Attributes
    ----------
    out_dir : Path
        The output folder.
    rows : list of dict
        Per-frame records: ``frame``, ``iterations``, ``seconds`` (wall), ``cpu_seconds``,
        ``loss``, ``order`` (active jet order), ``rss_mb``, for PolySfT ``slope`` (the
        steepest jet slope of the frame in degrees, :meth:`sft.model.JetModel.tilt`) and, on
        a frame after which the surface was re-partitioned, ``refit_patches`` (the new
        count), and with ground truth the fields of :class:`sft.metrics.FrameErrors`.
    summary : dict
        Means over frames (:func:`sft.metrics.summarize`).
    complete : bool
        False when the run stopped early (``max_windows``).
    """

    out_dir: Path
    rows: list[dict[str, Any]]
    summary: dict[str, float]
    complete: bool


# ------------------------------------------------------------------------------ memory


def _rss_mb() -> float:
    try:
        with open("/proc/self/statm") as fh:
            pages = int(fh.read().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError):  # pragma: no cover - non-Linux
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _load_libc():
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        libc.malloc_trim  # noqa: B018 - glibc only
        return libc
    except (OSError, AttributeError):  # pragma: no cover - not glibc
        return None


_LIBC = _load_libc()


def _trim_heap() -> None:
    """Return the heap's free memory to the OS (glibc ``malloc_trim``; no-op elsewhere).

    Each window allocates and frees tensors of slightly different sizes; glibc keeps the
    freed pages, so without this the resident size of a long run creeps up by about 1 KB
    per frame although no object outlives its window. Costs 1-2 ms per frame.
    """
    if _LIBC is not None:
        _LIBC.malloc_trim(0)


# ------------------------------------------------------------------------------ state


@dataclass
class _State:
    """What carries from window to window, and what a checkpoint holds.

    ``pending``: parameters (and Adam state) of the frames in the window, by frame;
    ``last``, ``last2``: those of the two frames finalised last; ``refit``: the surface
    ``(V, 3)`` of the last re-partition (the template of ``model``), None before one.
    """

    model: DeformationModel
    next: int = 0
    pending: dict[int, dict[str, Any]] = field(default_factory=dict)
    last: dict[str, Any] | None = None
    last2: dict[str, Any] | None = None
    refit: torch.Tensor | None = None


@dataclass
class _Run:
    """What every window of a run shares (read-only during the run)."""

    seq: Sequence
    st: SfTSettings
    out: Path
    T: int
    terms: ImageTerms
    inext: Inextensibility
    window: _Window
    template_v: torch.Tensor
    overlays: set[int]


def _sequence_fingerprint(seq: Sequence) -> str:
    h = hashlib.sha1()
    h.update(np.ascontiguousarray(seq.template.verts).tobytes())
    h.update(np.ascontiguousarray(seq.template.faces).tobytes())
    h.update(np.ascontiguousarray(seq.K).tobytes())
    h.update(str(seq.n_frames).encode())
    return h.hexdigest()


def _run_key(seq: Sequence, st: SfTSettings, T: int) -> str:
    """Fingerprint of what decides a run's meshes: sequence, frame count, settings."""
    return runs.fingerprint({"sequence": _sequence_fingerprint(seq), "frames": T,
                             "settings": st.result_dict()})


# ------------------------------------------------------------------------------ checkpoints


def _save_checkpoint(path: Path, state: _State, key: str) -> None:
    """The state as plain tensors (:func:`polygeo.runs.save_checkpoint`), keyed by ``key``."""
    tensors = {"pending": state.pending, "last": state.last, "last2": state.last2,
               "refit": state.refit}
    meta = {"fingerprint": key, "next": state.next, "model_state": state.model.state()}
    runs.save_checkpoint(path, tensors, meta)


def _resume(out: Path, key: str, st: SfTSettings, state: _State, faces) -> None:
    """Load the checkpoint of ``out`` into ``state`` (rebuilding a re-partitioned model).

    Raises :class:`polygeo.runs.CheckpointError` (a ``ValueError``) when the checkpoint
    belongs to other settings, an older polygeo, or holds anything but plain data; nothing
    of it runs (:func:`polygeo.runs.load_checkpoint`).
    """
    ck = runs.resume_state(out, key, name=CHECKPOINT_NAME)
    if ck is None:
        return
    state.next, state.pending = int(ck.meta["next"]), ck.tensors["pending"]
    state.last, state.last2 = ck.tensors["last"], ck.tensors["last2"]
    state.refit = ck.tensors["refit"]
    if state.refit is not None:
        state.model = _refit_model(state.model, st, state.refit, faces)
    state.model.load_state(ck.meta["model_state"])


# ------------------------------------------------------------------------------ records


def _truncate_jsonl(path: Path, start: int) -> None:
    """Keep the lines of frames before ``start`` (remove the file when ``start`` is 0)."""
    if not path.exists():
        return
    if start == 0:
        path.unlink()
        return
    runs.truncate_jsonl(path, lambda r: r["frame"] < start)


def _model_info(model: DeformationModel, rows: list[dict]) -> dict:
    """What ``metrics.json`` records of the model at the end of a run.

    Its patches and their steepest tilt (triangles for the template's partition, jet slopes
    after a re-partition), and ``refits``: ``[frame, patches]`` of every re-partition.
    """
    if not isinstance(model, JetModel):
        return {"name": model.name}
    t = model.template
    return {"name": model.name, "patches": t.n_patches, "order": t.order,
            "max_tilt_deg": None if np.isnan(t.max_tilt) else round(t.max_tilt, 2),
            "fit_rms": t.fit_rms,
            "refits": [[r["frame"], r["refit_patches"]] for r in rows if "refit_patches" in r]}


# ------------------------------------------------------------------------------ re-partition


def _needs_refit(model: JetModel, st: SfTSettings, slopes: np.ndarray) -> bool:
    """Whether a patch has used up its room to bend (``ModelSettings.refit_tilt``).

    ``slopes`` ``(K,)``: the steepest jet slope of each patch in the frame just finished.
    A patch is full when it is steeper than ``refit_tilt`` and has steepened by more than
    ``refit_tilt - refit_max_tilt`` since it was fitted.
    """
    m = st.model
    if not m.refit_tilt > 0:
        return False
    room = max(m.refit_tilt - m.refit_max_tilt, 0.0)
    limit = np.maximum(m.refit_tilt, model.template_slopes + room)
    return bool((slopes > limit).any())


def _refit_model(model: JetModel, st: SfTSettings, verts, faces) -> JetModel:
    """A model of the same settings whose template is ``verts`` (``patches="auto"``)."""
    m, w = st.model, st.losses
    with warnings.catch_warnings():  # a reconstruction may be rough: the cap is the answer
        warnings.simplefilter("ignore", RuntimeWarning)
        tmpl = JetTemplate.fit(verts, faces, model.max_order, PATCHES_AUTO,
                               max_tilt=m.refit_max_tilt, max_patches=m.refit_max_patches,
                               tilt="jet", seed=m.seed)
    return JetModel(tmpl, order=model.order, boundary_weight=w.boundary_weight,
                    boundary_normal_weight=w.boundary_normal_weight,
                    patch_rigid=m.patch_rigid, dtype=st.torch_dtype)


def _refit(state: _State, st: SfTSettings, X: torch.Tensor, faces, s: int) -> None:
    """Re-partition the surface of frame ``s`` (``X``) and re-express the window in it.

    The new model's template is ``X`` itself (its own patches and frames, see
    :func:`_refit_model`); the parameters of the window's frames (``state.pending``, Adam
    moments dropped) and of the frame before ``s`` (``state.last``) are projected onto it
    (:meth:`sft.model.JetModel.params_for`), so that the extrapolated start and the
    constant-velocity prior carry the motion on.
    """
    model = state.model
    new = _refit_model(model, st, X, faces)

    def project(params: dict) -> dict:
        return new.params_for(model.vertices(model.batch_of_one(params))[0].double())

    with torch.no_grad():
        for j in list(state.pending):
            state.pending[j] = new.params_for(X) if j == s else project(state.pending[j])
        state.last = None if state.last is None else project(state.last)
    state.model, state.refit = new, X.clone()


# ------------------------------------------------------------------------------ outputs


def _overlay_frames(n: int, k: int) -> set[int]:
    if k <= 0:
        return set()
    return {int(round(x)) for x in np.linspace(0, n - 1, min(k, n))}


def _overlay(path: Path, terms: ImageTerms, X: torch.Tensor, target: torch.Tensor,
             gt: np.ndarray | None) -> None:
    """PNG: frame | render | colour error | per-vertex 3D error (when ground truth exists)."""
    from .plots import overlay_png

    with torch.no_grad():
        rgb, alpha = terms.render(X[None].to(terms.dtype), hard=True)
    err_img = None
    if gt is not None:
        err = (X - torch.as_tensor(gt)).norm(dim=-1)
        err_img = _error_render(terms, X, err)
    overlay_png(path, target.numpy(), rgb[0].numpy(), alpha[0].numpy(), err_img)


def _error_render(terms: ImageTerms, X: torch.Tensor, err: torch.Tensor):
    """Render per-vertex errors (scene units) as vertex colours; return (image, vmax)."""
    from polygeo.render import render

    vmax = float(err.max()) if float(err.max()) > 0 else 1.0
    c = (err / vmax).to(terms.dtype)[:, None].repeat(1, 3)
    out = render(X[None].to(terms.dtype), terms.faces, terms.camera, terms._hard, colors=c[None],
                 coords="camera")
    return out.rgb[0, ..., 0].numpy(), out.alpha[0].numpy(), vmax


# ------------------------------------------------------------------------------ stages


def _prepare(seq: Sequence, st: SfTSettings, out: Path, T: int) -> tuple[_Run, _State]:
    """The run's shared parts and its initial state (the template, frame 0 next)."""
    (out / "meshes").mkdir(parents=True, exist_ok=True)
    model, terms, inext = _objective_parts(seq, st)
    run = _Run(seq=seq, st=st, out=out, T=T, terms=terms, inext=inext,
               window=_Window(seq, terms),
               template_v=torch.as_tensor(seq.template.verts, dtype=torch.float64),
               overlays=_overlay_frames(T, st.output.overlays))
    return run, _State(model)


def _enter_window(run: _Run, state: _State, s: int) -> list[int]:
    """The frames of window ``s``; frames new to it get their initial parameters."""
    idx = list(range(s, min(s + run.st.optimiser.window, run.T)))
    done = {s - 1: state.last, s - 2: state.last2}  # the two frames finalised last

    def params_of(k: int):
        return state.pending[k] if k in state.pending else done.get(k)

    for j in idx:
        if j not in state.pending:
            state.pending[j] = _initial(state.model, run.st, params_of(j - 1), params_of(j - 2))
    return idx


def _finalise_frame(run: _Run, state: _State, s: int, target: torch.Tensor) -> dict[str, Any]:
    """Write frame ``s``'s mesh (and overlay), measure it, re-partition if due; its record."""
    model = state.model
    with torch.no_grad():
        p = {k: state.pending[s][k][None] for k in model.init_params()}
        X = model.vertices(p)[0].to(torch.float64)
    faces = run.seq.template.faces
    write_ply(run.out / "meshes" / f"{s:06d}.ply", X.numpy(), faces)
    row: dict[str, Any] = {"order": getattr(model, "order", None)}
    gt = run.seq.gt(s)
    if gt is not None:
        row.update(frame_errors(X, gt, run.template_v, faces).as_dict())
    if s in run.overlays:
        _overlay(run.out / f"overlay_{s:06d}.png", run.terms, X, target, gt)
    if isinstance(model, JetModel):
        slopes = model.tilt(state.pending[s])
        row["slope"] = float(slopes.max())
        if _needs_refit(model, run.st, slopes):
            _refit(state, run.st, X, faces, s)
            row["refit_patches"] = state.model.template.n_patches
    return row


def _advance(run: _Run, state: _State, s: int) -> tuple[dict[str, Any], list[float]]:
    """Optimise window ``s``, finalise frame ``s`` and slide: its record and loss curve."""
    t0, c0 = time.perf_counter(), time.process_time()
    idx = _enter_window(run, state, s)
    targets, masks = run.window.targets(idx)
    iters, curve, loss = _optimize_window(state.model, run.terms, run.inext, run.st,
                                          state.pending, idx, targets, masks)
    row = {"frame": s, "iterations": iters, "loss": loss,
           **_finalise_frame(run, state, s, targets[0])}
    state.last2, state.last = state.last, state.pending.pop(s)
    state.next = s + 1
    _trim_heap()  # inside the frame's timer: its cost is charged to the frame
    row["seconds"] = time.perf_counter() - t0
    row["cpu_seconds"] = time.process_time() - c0
    row["rss_mb"] = _rss_mb()
    return row, curve


def _slide(run: _Run, state: _State, key: str, max_windows: int | None) -> None:
    """Slide the window from ``state.next`` to the end (or ``max_windows`` windows)."""
    out, every = run.out, run.st.output.checkpoint_every
    bar = runs.progress(total=run.T, initial=state.next, desc=f"sft {run.st.model.method}",
                        unit="frame", quiet=run.st.output.quiet)
    n_windows = 0
    with runs.JsonlLog(out / FRAMES_NAME) as frames, runs.JsonlLog(out / LOSSES_NAME) as losses:
        for s in range(state.next, run.T):
            if max_windows is not None and n_windows >= max_windows:
                break
            row, curve = _advance(run, state, s)
            frames.append(row)
            losses.append({"frame": s, "iterations": row["iterations"], "loss": curve})
            n_windows += 1
            if every and (n_windows % every == 0 or s == run.T - 1):
                _save_checkpoint(out / CHECKPOINT_NAME, state, key)
            bar.update(1)
            if "e_3d" in row:
                bar.set_postfix(e3d=f"{row['e_3d']:.4f}", it=row["iterations"])
    bar.close()


def _finish(run: _Run, model: DeformationModel) -> SfTResult:
    """Read the records back, write ``metrics.json`` (atomically) and the charts."""
    out = run.out
    rows = runs.read_jsonl(out / FRAMES_NAME)
    complete = len(rows) == run.T
    summary = summarize(rows)
    record = {"sequence": str(run.seq.root), "frames": run.T, "complete": complete,
              "settings": run.st.to_dict(), "model": _model_info(model, rows),
              "mean": summary, "per_frame": rows}
    runs.atomic_write_json(out / "metrics.json", record, indent=1)
    if run.st.output.charts and complete:
        from .plots import write_charts

        write_charts(out, rows, out / LOSSES_NAME)
    return SfTResult(out_dir=out, rows=rows, summary=summary, complete=complete)


def run_sft(
    sequence: Sequence | str | os.PathLike,
    out_dir: str | os.PathLike,
    settings: SfTSettings | None = None,
    *,
    resume: bool = True,
    max_frames: int | None = None,
    max_windows: int | None = None,
) -> SfTResult:
    """Reconstruct every frame of a sequence; write meshes, metrics, charts and checkpoints.

    Parameters
    ----------
    sequence : Sequence or path
        A loaded sequence or its folder (see :mod:`sft.data`).
    out_dir : path
        Output folder: ``meshes/000000.ply ...`` (template vertex order, scene units),
        ``metrics.json``, ``frames.jsonl`` (one record per frame), ``losses.jsonl`` (one line
        per window), ``checkpoint.pt`` and PNG charts. Created if needed.
    settings : SfTSettings, optional
        Defaults to ``SfTSettings()``; ``settings.output`` says what is written and shown.
    resume : bool
        Continue from ``out_dir/checkpoint.pt`` when it exists; otherwise start over.
    max_frames : int, optional
        Process only the first ``max_frames`` frames.
    max_windows : int, optional
        Stop after this many windows of this call (simulates an interruption; used by tests).

    Returns
    -------
    SfTResult

    Raises
    ------
    TypeError
        If ``settings`` is not an :class:`SfTSettings`.
    polygeo.runs.CheckpointError
        (a ``ValueError``) if ``resume`` is True and the checkpoint belongs to another
        sequence, frame count or settings, was written by an older polygeo (version-2
        checkpoints are refused, not read), or holds anything but tensors and plain data (it
        is refused before any of it runs).
    """
    st = SfTSettings() if settings is None else settings
    if not isinstance(st, SfTSettings):
        raise TypeError(f"settings: expected SfTSettings, got {type(st).__name__}")
    seq = sequence if isinstance(sequence, Sequence) else load_sequence(sequence)
    out = Path(out_dir)
    T = seq.n_frames
    if max_frames is not None:
        T = min(T, check_int(max_frames, "max_frames", low=1))
    run, state = _prepare(seq, st, out, T)
    key = _run_key(seq, st, T)
    if resume:
        _resume(out, key, st, state, seq.template.faces)
    # records go to files as the run goes (memory stays flat); on resume, lines of frames
    # after the checkpoint are dropped
    for name in (LOSSES_NAME, FRAMES_NAME):
        _truncate_jsonl(out / name, state.next)
    _slide(run, state, key, max_windows)
    return _finish(run, state.model)
