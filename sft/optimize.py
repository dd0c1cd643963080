"""The PolySfT optimiser: adaptive sliding window, checkpoints and resume.

Adaptive sliding window (thesis section 5.5.2): the frames ``s .. s + W - 1`` are optimised
together until the loss has not improved on its running minimum for ``patience`` iterations or
``frame_period`` iterations have run; frame ``s`` is then final (its mesh is written at once),
the window moves forward by one frame and the frame that enters it starts from the parameters of
the frame before it (extrapolated from the two before it by default). When a patch of the frame
just finished has grown too steep to bend further, that frame's surface is re-partitioned into
new patches (``SfTSettings.refit_tilt``). At the end of the sequence the window shrinks. Every
frame is thus optimised in up to ``W`` windows; the wall time and the iterations of window ``s``
are charged to frame ``s``.

One Adam optimiser per window, with the learning rates of the thesis per parameter group
(``Delta uv`` 1e-3, ``Delta alpha`` 1e-2; rigid 1e-3 instead of the thesis' 1e-4, see
:class:`SfTSettings`; the per-vertex baseline's offsets use ``lr_vertex``). The parameters are
in the model's normalised units (the template radius is 1), see :mod:`sft.model`. A fresh
Adam state ramps its learning rates up over its first ``warmup`` steps, and a window hands on
its lowest-loss iterate (``keep_best``), not its last.

Checkpoints are written after every ``checkpoint_every`` windows (atomically): the index of the
next window, the parameters of the frames still in the window (with their Adam moments), the
model's state (active jet order) and the surface of the last re-partition. Windows are
deterministic, so resuming from a checkpoint gives the same meshes as an uninterrupted run.
Only the current window's frames are held in memory; meshes, per-frame records
(``frames.jsonl``) and loss curves (``losses.jsonl``) are written as the run goes and read back
once at the end for ``metrics.json``, so memory does not grow with the number of frames
(before, the records were kept in memory and in the checkpoint: about 1.5 KB per frame).
"""

from __future__ import annotations

import hashlib
import json
import os
import time
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from polygeo.checks import check_choice, check_int, check_positive
from polygeo.io import write_ply
from polygeo.render import RasterSettings

from .data import Sequence, load_sequence
from .losses import ImageTerms, Inextensibility, temporal_acceleration, temporal_consistency
from .metrics import frame_errors, summarize
from .model import (
    MAX_TILT,
    ORDER_AUTO,
    PATCHES_AUTO,
    DeformationModel,
    JetModel,
    JetTemplate,
    _check_patches,
    _check_tilt,
    build_model,
)

__all__ = ["SfTSettings", "SfTResult", "run_sft", "reconstruct_window", "CHECKPOINT_NAME"]

#: File name of the checkpoint inside the output folder.
CHECKPOINT_NAME = "checkpoint.pt"
_CKPT_VERSION = 2
#: Per-frame records, one JSON line per frame, written as the run goes.
FRAMES_NAME = "frames.jsonl"


@dataclass
class SfTSettings:
    """All settings of a PolySfT (or baseline) run (the thesis' defaults, except where noted).

    Attributes
    ----------
    method : {"polysft", "vertex"}
        Jet patches (PolySfT) or per-vertex offsets (the baseline).
    order : int or "auto"
        Jet order of PolySfT (default 6, the highest; the thesis' experiments use 4). An
        order-4 polynomial over the whole sheet cannot follow a wave or a crease narrower
        than the sheet; order 6 costs the same time per iteration (the renderer dominates).
        On the 8-frame synthetic sequences (patience 30, period 150) the ratio of e_3D to
        the fixed template's went from 0.270 to 0.145 (swave), 0.198 to 0.189 (fold) and
        0.300 to 0.312 (roll) from order 4 to 6. ``"auto"`` starts at 2 and raises the
        order by one (up to ``max_order``, never lowering it; the order carries over to the
        next window) whenever progress is slow: every ``patience`` iterations, when the
        running minimum of the loss fell by less than ``auto_gain`` (relative) over them,
        and at a plateau. It suits scenes that low orders explain (8-frame bend: ratio 0.134
        at orders 2 -> 6 against 0.237 at order 6, period 150) and loses on fine ones
        (swave 0.265 against 0.145, fold 0.219 against 0.189), hence not the default.
    max_order : int
        Highest order for ``"auto"``.
    auto_gain : float
        Relative decrease of the loss's running minimum over ``patience`` iterations below
        which ``"auto"`` raises the order.
    patches : int or "auto"
        Number of jet patches. Default ``"auto"``: the fewest (1, 2, ..., 8, 12, 18, ...)
        whose every triangle lies within ``max_tilt`` of the axis of each patch it touches
        (:meth:`sft.model.JetTemplate.fit`): one patch, the thesis' model, for a sheet that
        is not already bent past about 140 degrees; several for a tube, a cap or a crumpled
        cloth, which are no height graph over one plane. On the 8-frame ``curl`` sequence (a
        270-degree tube; period 200) one patch folds over its plane and diverges (ratio of
        e_3D to the fixed template's 2.76, e_n 22.0 degrees) while "auto" picks 2 (0.100,
        2.94; 4 patches: 0.062; with eq. (48) instead of ``k_acc``, 8: 0.098, 16: 0.153, and 3
        patches, one folded over: 1.56). With several, each patch has its own rigid motion
        (``patch_rigid``) and the boundary term ties them. On the sheets (one patch under
        "auto") 4 patches lowered the ratio from 0.120 to 0.072 (bend), 0.106 to 0.071
        (cloth), 0.148 to 0.073 (fold) and 0.135 to 0.094 (roll, which rolls 208 degrees
        after the template: the choice is made on the template), at 8-42 % more time per
        frame, but raised it from 0.137 to 0.582 on the travelling S-wave (the patches drift
        in depth while their renders still match the frames), hence one patch wherever one
        is a height graph.
    max_tilt : float
        Degrees in ``(0, 90)`` for ``patches="auto"`` (default 70: one patch tracks sheets
        whose graph tilts to about 80 degrees during the ``bend`` sequence, so 70 at the
        template leaves room for the deformation).
    refit_tilt : float
        Degrees; 0 never re-partitions. After each frame, when a patch's jet is steeper than
        this over its plane (:meth:`sft.model.JetModel.tilt`, the steepest ``atan |grad z|``
        at its samples) and has steepened by more than ``refit_tilt - refit_max_tilt`` since
        it was fitted, that frame's reconstruction becomes the template of a new model
        (``patches="auto"`` on it, bounded by ``refit_max_tilt`` on the jets' slopes, at most
        ``refit_max_patches``), and the frames still in the window and the two before are
        projected onto the new model (:meth:`sft.model.JetModel.params_for`): the
        extrapolated start and the constant-velocity prior carry the motion on. A height
        graph over one plane cannot follow a sheet that rolls past a quarter turn: on the
        8-frame ``roll`` the one patch's slope stalls at 70-75 degrees while the truth goes
        to 90 and the curl beyond; re-partitioned, each patch turns with its own rigid
        motion. Inextensibility keeps the first template's edge lengths. On the 8-frame
        synthetic sequences (``benchmarks/bm_sft.py`` and the same runs by hand) the ratio of
        e_3D to the fixed template's and e_n went from 0.135 / 5.80 degrees to 0.085 / 4.45
        on ``roll`` (re-partitioned after frames 2, 4 and 6: 2, then 8 patches; hidden
        vertices 21.7 to 16.8 degrees), 0.120 / 2.34 to 0.088 / 2.03 on ``bend`` (5 patches
        after frame 2) and 0.137 / 4.82 to 0.096 / 4.01 on ``swave`` (8 patches after frame
        4, one again after frame 7); fold, cloth and curl never re-partition. A trigger at 55
        degrees: roll 0.096 / 4.92, swave 0.106 / 4.00; at 45 (patches within 30) the S-wave
        was re-partitioned after every frame (0.189 / 7.39); at most 4 patches: roll 0.111 /
        5.32. Eight patches make an iteration about 25 % dearer (3-frame window, 2,700
        vertices: 37 -> 46 ms).
    refit_max_tilt : float
        Degrees in ``(0, 90)``: the steepest jet slope a patch of a new partition may have.
    refit_max_patches : int
        Most patches of a new partition (the model's share of an iteration grows with the
        count: 4 ms for one patch, 10 ms for 8, forward and backward of a 3-frame window of
        2,700 vertices, against about 30 ms for the renders).
    window : int
        Sliding-window size ``W``.
    patience : int
        Iterations without improvement of the running minimum that end a window. Default
        30 (thesis: 100; see ``frame_period``).
    frame_period : int
        Most iterations per window. Default 200 instead of the thesis' 500 (about 10 s per
        frame on a V100): one iteration of a 3-frame window costs about 45 ms of one CPU
        core at 128 px with 2700 vertices, so 200 iterations keep a frame at about 9 CPU
        seconds, within the 10 s per frame budget. On the 8-frame synthetic sequences the
        windows rarely plateau before the period ends, and 150 -> 200 iterations took the
        normal error from 5.15 to 4.16 degrees (swave) and 5.02 to 4.70 (fold).
        ``patience=100, frame_period=500`` is the thesis' budget.
    min_improvement : float
        An iteration improves when its loss is below ``(1 - min_improvement)`` times the
        running minimum.
    lr_uv, lr_alpha, lr_rigid, lr_vertex : float
        Adam learning rates (normalised units): ``Delta uv``, ``Delta alpha``, rigid motion
        (rotation vector in radians and translation), per-vertex offsets (baseline).
        ``lr_rigid`` = 1e-3 instead of the thesis' 1e-4: Adam moves a parameter by about
        its learning rate per step, and in our units (template radius 1, 15 cm for a
        24 x 18 cm sheet) 1e-4 is 15 um and 0.006 degrees per step, so a frame-to-frame
        motion of a few millimetres and half a degree takes hundreds of iterations, and the
        jets absorb the rest as deformation. On the 8-frame synthetic fold sequence
        (patience 30, period 150) the ratio to the fixed template fell from 0.45 to 0.20
        (1e-3; 0.21 at 3e-3), on roll from 0.47 to 0.30. ``lr_rigid=1e-4`` restores the
        thesis.
    k_rgb, k_sil, k_mi, k_tc : float
        Weights of the colour, silhouette, inextensibility (eq. (47)) and temporal
        consistency (eq. (48)) terms. ``k_tc`` = 0 by default (the thesis: 0.05, see
        ``k_acc``). ``k_mi`` = 10 instead of the thesis' 0.1: eq. (47) is evaluated with
        lengths in units of the template radius and the image terms are means over pixels,
        and in these units 0.1 lets the sheet stretch to explain a depth drift. On our
        synthetic bend sequence (12 frames, patience 30, period 150) the ratio of e_3D to
        the fixed template's e_3D was 0.25 / 0.15 / 0.09 / 0.26 for k_mi = 0.1 / 1 / 10 /
        100 (PolySfT), and 0.32 / - / 0.23 / 0.43 for the per-vertex baseline.
    k_acc : float
        Weight of the constant-velocity prior (:func:`sft.losses.temporal_acceleration`:
        squared second differences of every parameter over the window; needs ``window`` >=
        3). With ``init="extrapolate"`` it replaces eq. (48), which pulls every frame
        towards the previous one, i.e. towards stopping: a part of the surface that the
        images stop constraining then freezes while the real one moves on. On the 8-frame
        ``roll`` sequence (its curl turns out of sight behind the flat part; up to 32 % of
        the vertices hidden) the ratio of e_3D to the fixed template's went from 0.260 to
        0.135 and e_n from 10.4 to 5.8 degrees (hidden vertices 38.7 to 21.7 degrees; 4
        patches: 0.094 and 5.1 degrees), and the other sequences stayed within their
        targets: bend 0.147 / 2.19 -> 0.120 / 2.34, swave 0.122 / 4.01 -> 0.137 / 4.82,
        fold 0.154 / 4.73 -> 0.148 / 4.28, cloth 0.122 / 2.64 -> 0.106 / 2.51, curl 0.098 /
        2.92 -> 0.100 / 2.94 (``benchmarks/bm_sft.py``; ``k_tc=0.05, k_acc=0,
        init="previous"`` restores the thesis). Heavier weights cost the S-wave (k_acc 0.5:
        0.29), whose shape oscillates from frame to frame.
    k_b, k_bn : float
        Boundary consistency (eq. (51), several patches): positions and normals.
    patch_rigid : bool
        With several patches, a rigid motion per patch relative to the global one, tied to
        the neighbouring patches by the boundary term (:class:`sft.model.JetModel`).
    lr_patch : float
        Adam learning rate of the per-patch rigid motions.
    rgb_kind : {"l1", "l2"}
    sil_kind : {"l2", "l1", "iou"}
    pyramid : int
        Coarser image levels (2x2, 4x4, ... block means) averaged into the colour and
        silhouette terms (:class:`sft.losses.ImageTerms`); 0 = full resolution only (phi-SfT).
    sigma : float
        Soft rasterizer sharpness in pixels² (:class:`polygeo.render.RasterSettings`).
    gamma : float
        Soft rasterizer depth temperature.
    dtype : {"float32", "float64"}
        Optimisation dtype.
    init : {"previous", "extrapolate"}
        How a frame entering the window starts: from the previous frame's parameters
        (thesis), or extrapolated at constant velocity from the two previous frames (the
        default; it goes with ``k_acc``: alone, with eq. (48), it did not help).
    carry_adam : bool
        Keep each frame's Adam moments across windows (a frame entering the window inherits
        those of the previous frame). False restarts Adam in every window, which kicks every
        parameter by about its learning rate in the first steps.
    keep_best : bool
        A window returns the iterate with the lowest loss, not the last one. Adam's loss is
        not monotone: an occasional spike (a triangle turning edge-on, a patch boundary
        opening) followed by ``patience`` iterations without a new minimum would otherwise
        end the window at the spike and hand its damaged shape to the next frame. Costs a
        copy of the window's parameters per new minimum; on the five 8-frame sequences
        the default run's figures were unchanged to within 0.003 of ratio.
    warmup : int
        Adam steps over which a frame's learning rates ramp up linearly from 0 when its Adam
        state is fresh (the first window; every window with ``carry_adam=False``). A fresh
        Adam moves every parameter by about its learning rate in its first steps, whatever
        its gradient: for the 28 coefficients of an order-6 jet that is up to 2 cm at the
        sheet's corners in one step. 0: no ramp. With carried moments only the first window
        is affected, yet its damage propagates: on the 8-frame synthetic sequences (default
        settings otherwise) 20 steps took the ratio of e_3D to the fixed template's from
        0.212 to 0.147 on bend (e_n 3.95 to 2.19 degrees), 0.264 to 0.260 on roll and 0.157
        to 0.154 on fold, and cost 0.114 to 0.122 on swave and 0.119 to 0.122 on cloth
        (mean ratio 0.173 to 0.161, mean e_n 5.24 to 4.80 degrees).
    freeze : tuple of str
        Parameters kept at their initial value (e.g. ``("d_alpha", "d_uv")`` optimises the
        rigid motion alone).
    checkpoint_every : int
        Windows between checkpoints (0: none).
    overlays : int
        Number of frames (spread over the sequence) that get a render/frame/error PNG.
    seed : int
        Seed (patch partition; the optimisation itself is deterministic).
    """

    method: str = "polysft"
    order: int | str = 6
    max_order: int = 6
    auto_gain: float = 0.03
    patches: int | str = PATCHES_AUTO
    max_tilt: float = MAX_TILT
    refit_tilt: float = 50.0
    refit_max_tilt: float = 35.0
    refit_max_patches: int = 8
    window: int = 3
    patience: int = 30
    frame_period: int = 200
    min_improvement: float = 1e-4
    lr_uv: float = 1e-3
    lr_alpha: float = 1e-2
    lr_rigid: float = 1e-3
    lr_vertex: float = 1e-3
    k_rgb: float = 1.0
    k_sil: float = 1.0
    k_mi: float = 10.0
    k_tc: float = 0.0
    k_acc: float = 0.05
    k_b: float = 1.0
    k_bn: float = 0.1
    patch_rigid: bool = True
    lr_patch: float = 1e-3
    rgb_kind: str = "l1"
    sil_kind: str = "l2"
    pyramid: int = 0
    sigma: float = 0.1
    gamma: float = 1e-4
    dtype: str = "float32"
    init: str = "extrapolate"
    carry_adam: bool = True
    keep_best: bool = True
    warmup: int = 20
    freeze: tuple[str, ...] = ()
    checkpoint_every: int = 1
    overlays: int = 4
    seed: int = 0

    def __post_init__(self) -> None:
        check_choice(self.method, "method", ("polysft", "vertex"))
        if self.order != ORDER_AUTO:
            self.order = check_int(self.order, "order", low=1, high=6)
        self.max_order = check_int(self.max_order, "max_order", low=2, high=6)
        self.patches, self.max_tilt = _check_patches(self.patches, self.max_tilt)
        self.refit_max_tilt = _check_tilt(self.refit_max_tilt, "refit_max_tilt")
        self.refit_tilt = check_positive(self.refit_tilt, "refit_tilt", strict=False)
        if self.refit_tilt >= 180.0:
            raise ValueError(f"refit_tilt: expected degrees in [0, 180), got {self.refit_tilt}")
        self.window = check_int(self.window, "window", low=1)
        self.refit_max_patches = check_int(self.refit_max_patches, "refit_max_patches", low=1)
        self.patience = check_int(self.patience, "patience", low=1)
        self.frame_period = check_int(self.frame_period, "frame_period", low=1)
        self.checkpoint_every = check_int(self.checkpoint_every, "checkpoint_every", low=0)
        self.overlays = check_int(self.overlays, "overlays", low=0)
        self.warmup = check_int(self.warmup, "warmup", low=0)
        self.pyramid = check_int(self.pyramid, "pyramid", low=0, high=8)
        self.seed = check_int(self.seed, "seed")
        for name in ("lr_uv", "lr_alpha", "lr_rigid", "lr_vertex", "lr_patch", "sigma",
                     "gamma"):
            setattr(self, name, check_positive(getattr(self, name), name))
        for name in ("k_rgb", "k_sil", "k_mi", "k_tc", "k_acc", "k_b", "k_bn", "min_improvement",
                     "auto_gain"):
            setattr(self, name, check_positive(getattr(self, name), name, strict=False))
        check_choice(self.rgb_kind, "rgb_kind", ("l1", "l2"))
        check_choice(self.sil_kind, "sil_kind", ("l2", "l1", "iou"))
        check_choice(self.dtype, "dtype", ("float32", "float64"))
        check_choice(self.init, "init", ("previous", "extrapolate"))
        known = {"d_alpha", "d_uv", "d_x", "rot", "trans", "p_rot", "p_trans"}
        self.freeze = tuple(self.freeze)
        for name in self.freeze:
            check_choice(name, "freeze", sorted(known))

    @property
    def torch_dtype(self) -> torch.dtype:
        """The optimisation dtype as a torch dtype."""
        return torch.float32 if self.dtype == "float32" else torch.float64


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
    per frame (+0.10 MB per 100 frames on bm_sft's 500-frame run, +0.02 with it: flat to
    the measurement's resolution) although no object outlives its window. Costs 1-2 ms
    per frame on the 128 px sequences (12 ms on a deliberately fragmented 400 MB heap),
    against seconds per frame.
    """
    if _LIBC is not None:
        _LIBC.malloc_trim(0)


def _fingerprint(seq: Sequence) -> str:
    h = hashlib.sha1()
    h.update(np.ascontiguousarray(seq.template.verts).tobytes())
    h.update(np.ascontiguousarray(seq.template.faces).tobytes())
    h.update(np.ascontiguousarray(seq.K).tobytes())
    h.update(str(seq.n_frames).encode())
    return h.hexdigest()


def _atomic_save(obj: Any, path: Path) -> None:
    tmp = path.with_name(path.name + ".part")
    torch.save(obj, tmp)
    os.replace(tmp, path)


class _Window:
    """Frames of the current window with their cached targets."""

    def __init__(self, seq: Sequence, terms: ImageTerms) -> None:
        self.seq, self.terms = seq, terms
        self.cache: dict[int, tuple[torch.Tensor, torch.Tensor | None]] = {}

    def targets(self, idx: list[int]):
        for j in idx:
            if j not in self.cache:
                self.cache[j] = self.terms.target(self.seq.frame(j), self.seq.mask(j))
        for j in list(self.cache):
            if j not in idx:
                del self.cache[j]
        t = torch.stack([self.cache[j][0] for j in idx])
        m = None
        if self.seq.has_masks:
            m = torch.stack([self.cache[j][1] for j in idx])
        return t, m


def _overlay_frames(n: int, k: int) -> set[int]:
    if k <= 0:
        return set()
    return {int(round(x)) for x in np.linspace(0, n - 1, min(k, n))}


def run_sft(
    sequence: Sequence | str | os.PathLike,
    out_dir: str | os.PathLike,
    settings: SfTSettings | None = None,
    *,
    resume: bool = True,
    progress: bool = True,
    max_frames: int | None = None,
    max_windows: int | None = None,
    charts: bool = True,
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
        Defaults to ``SfTSettings()``.
    resume : bool
        Continue from ``out_dir/checkpoint.pt`` when it exists and matches the sequence and
        settings; otherwise start over.
    progress : bool
        Show a tqdm progress bar.
    max_frames : int, optional
        Process only the first ``max_frames`` frames.
    max_windows : int, optional
        Stop after this many windows of this call (simulates an interruption; used by tests).
    charts : bool
        Write the PNG charts at the end.

    Returns
    -------
    SfTResult

    Raises
    ------
    ValueError
        If a checkpoint exists for other settings or another sequence and ``resume`` is True,
        or on invalid settings.
    """
    settings = settings or SfTSettings()
    seq = sequence if isinstance(sequence, Sequence) else load_sequence(sequence)
    out = Path(out_dir)
    (out / "meshes").mkdir(parents=True, exist_ok=True)
    T = seq.n_frames if max_frames is None else min(seq.n_frames, check_int(max_frames,
                                                                            "max_frames", low=1))
    t = seq.template
    model, terms, inext = _objective_parts(seq, settings)
    window = _Window(seq, terms)
    fp = _fingerprint(seq)
    ckpt_path = out / CHECKPOINT_NAME
    sdict = asdict(settings)

    start, pending, last, last2, refit_ref = 0, {}, None, None, None
    if resume and ckpt_path.is_file():
        ck = torch.load(ckpt_path, weights_only=False)
        if (ck.get("version") != _CKPT_VERSION or ck.get("fingerprint") != fp
                or ck.get("settings") != sdict or ck.get("T") != T):
            raise ValueError(
                f"{ckpt_path}: the checkpoint belongs to another sequence or other settings "
                "(or an older polygeo); remove it or choose another output folder"
            )
        start, pending = ck["next"], ck["pending"]
        last, last2 = ck["last"], ck["last2"]
        refit_ref = ck.get("refit")
        if refit_ref is not None:
            model = _refit_model(model, settings, refit_ref, t.faces)
        model.load_state(ck["model_state"])
    # per-frame records and loss curves go to files as the run goes (memory stays flat);
    # on resume, lines of frames after the checkpoint are dropped
    losses_path, frames_path = out / "losses.jsonl", out / FRAMES_NAME
    for path in (losses_path, frames_path):
        _truncate_jsonl(path, start)

    overlay_set = _overlay_frames(T, settings.overlays)
    template_v = torch.as_tensor(t.verts, dtype=torch.float64)
    W = settings.window
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=T, initial=start, desc=f"sft {settings.method}", unit="frame")
    n_windows = 0
    for s in range(start, T):
        if max_windows is not None and n_windows >= max_windows:
            break
        t0, c0 = time.perf_counter(), time.process_time()
        idx = list(range(s, min(s + W, T)))
        done = {s - 1: last, s - 2: last2}  # the two frames finalised last

        def params_of(k: int, done=done):
            return pending[k] if k in pending else done.get(k)

        for j in idx:
            if j not in pending:
                pending[j] = _initial(model, settings, params_of(j - 1), params_of(j - 2))
        targets, masks = window.targets(idx)
        iters, curve, loss_val = _optimize_window(model, terms, inext, settings, pending, idx,
                                                  targets, masks)
        with torch.no_grad():
            p = {k: pending[s][k][None] for k in model.init_params()}
            X = model.vertices(p)[0].to(torch.float64)
        write_ply(out / "meshes" / f"{s:06d}.ply", X.numpy(), t.faces)
        row: dict[str, Any] = {"frame": s, "iterations": iters, "loss": loss_val,
                               "order": getattr(model, "order", None)}
        gt = seq.gt(s)
        if gt is not None:
            row.update(frame_errors(X, gt, template_v, t.faces).as_dict())
        if s in overlay_set:
            _overlay(out / f"overlay_{s:06d}.png", terms, X, targets[0], gt, t.faces)
        if isinstance(model, JetModel):
            slopes = model.tilt(pending[s])
            row["slope"] = float(slopes.max())
            if _needs_refit(model, settings, slopes):
                model, last = _refit(model, settings, X, t.faces, pending, s, last)
                refit_ref = X.clone()
                row["refit_patches"] = model.template.n_patches
        last2, last = last, pending.pop(s)
        _trim_heap()  # inside the frame's timer: its cost is charged to the frame
        row["seconds"] = time.perf_counter() - t0
        row["cpu_seconds"] = time.process_time() - c0
        row["rss_mb"] = _rss_mb()
        with open(frames_path, "a") as fh:
            fh.write(json.dumps(row) + "\n")
        with open(losses_path, "a") as fh:
            fh.write(json.dumps({"frame": s, "iterations": iters, "loss": curve}) + "\n")
        n_windows += 1
        if settings.checkpoint_every and (n_windows % settings.checkpoint_every == 0
                                          or s == T - 1):
            _atomic_save({"version": _CKPT_VERSION, "fingerprint": fp, "settings": sdict, "T": T,
                          "next": s + 1, "pending": pending, "last": last,
                          "last2": last2, "refit": refit_ref,
                          "model_state": model.state()}, ckpt_path)
        if bar is not None:
            bar.update(1)
            if "e_3d" in row:
                bar.set_postfix(e3d=f"{row['e_3d']:.4f}", it=iters)
    if bar is not None:
        bar.close()
    rows = _read_jsonl(frames_path)
    complete = len(rows) == T
    summary = summarize(rows)
    record = {"sequence": str(seq.root), "frames": T, "complete": complete,
              "settings": sdict, "model": _model_info(model, rows), "mean": summary,
              "per_frame": rows}
    tmp = out / "metrics.json.part"
    tmp.write_text(json.dumps(record, indent=1) + "\n")
    os.replace(tmp, out / "metrics.json")
    if charts and complete:
        from .plots import write_charts

        write_charts(out, rows, losses_path)
    return SfTResult(out_dir=out, rows=rows, summary=summary, complete=complete)


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


def _build_model(st: SfTSettings, template) -> DeformationModel:
    """The deformation model of ``st`` for a sequence's template."""
    return build_model(st.method, template.verts, template.faces, order=st.order,
                       max_order=st.max_order, patches=st.patches, max_tilt=st.max_tilt,
                       k_b=st.k_b, k_bn=st.k_bn,
                       patch_rigid=st.patch_rigid, seed=st.seed, dtype=st.torch_dtype)


def _needs_refit(model: JetModel, st: SfTSettings, slopes: np.ndarray) -> bool:
    """Whether a patch has used up its room to bend (``SfTSettings.refit_tilt``).

    ``slopes`` ``(K,)``: the steepest jet slope of each patch in the frame just finished.
    A patch is full when it is steeper than ``refit_tilt`` and has steepened by more than
    ``refit_tilt - refit_max_tilt`` since it was fitted.
    """
    if not st.refit_tilt > 0:
        return False
    room = max(st.refit_tilt - st.refit_max_tilt, 0.0)
    limit = np.maximum(st.refit_tilt, model.template_slopes + room)
    return bool((slopes > limit).any())


def _refit_model(model: JetModel, st: SfTSettings, verts, faces) -> JetModel:
    """A model of the same settings whose template is ``verts`` (``patches="auto"``)."""
    with warnings.catch_warnings():  # a reconstruction may be rough: the cap is the answer
        warnings.simplefilter("ignore", RuntimeWarning)
        tmpl = JetTemplate.fit(verts, faces, model.max_order, PATCHES_AUTO,
                               max_tilt=st.refit_max_tilt, max_patches=st.refit_max_patches,
                               tilt="jet", seed=st.seed)
    return JetModel(tmpl, order=model.order, k_b=st.k_b, k_bn=st.k_bn,
                    patch_rigid=st.patch_rigid, dtype=st.torch_dtype)


def _refit(model: JetModel, st: SfTSettings, X: torch.Tensor, faces, pending: dict, s: int,
           last: dict | None) -> tuple[JetModel, dict | None]:
    """Re-partition the surface of frame ``s`` (``X``) and re-express the window in it.

    The new model's template is ``X`` itself (its own patches and frames, see
    :func:`_refit_model`); the parameters of the window's frames (``pending``, changed in
    place, Adam moments dropped) and of the frame before ``s`` (``last``) are projected onto
    it (:meth:`sft.model.JetModel.params_for`), so that the extrapolated start and the
    constant-velocity prior carry the motion on. Returns the new model and ``last``
    projected.
    """
    new = _refit_model(model, st, X, faces)

    def project(params: dict) -> dict:
        return new.params_for(model.vertices(model.batch_of_one(params))[0].double())

    with torch.no_grad():
        for j in list(pending):
            pending[j] = new.params_for(X) if j == s else project(pending[j])
        return new, (None if last is None else project(last))


def _objective_parts(seq: Sequence, st: SfTSettings):
    """``(model, image terms, inextensibility)`` of a run with settings ``st`` on ``seq``."""
    t = seq.template
    model = _build_model(st, t)
    terms = ImageTerms(seq, RasterSettings(sigma=st.sigma, gamma=st.gamma), k_rgb=st.k_rgb,
                       k_sil=st.k_sil, rgb_kind=st.rgb_kind, sil_kind=st.sil_kind,
                       pyramid=st.pyramid, dtype=st.torch_dtype)
    inext = Inextensibility(t.verts, t.faces, model.scale, st.k_mi)
    return model, terms, inext


def _read_jsonl(path: Path) -> list[dict]:
    """The records of a JSON-lines file (empty when it does not exist)."""
    if not path.exists():
        return []
    return [json.loads(ln) for ln in path.read_text().splitlines() if ln.strip()]


def _truncate_jsonl(path: Path, start: int) -> None:
    """Keep the lines of frames before ``start`` (remove the file when ``start`` is 0)."""
    if not path.exists():
        return
    if start == 0:
        path.unlink()
        return
    kept = [r for r in _read_jsonl(path) if r["frame"] < start]
    path.write_text("".join(json.dumps(r) + "\n" for r in kept))


def _initial(model: DeformationModel, st: SfTSettings, prev: dict | None,
             prev2: dict | None) -> dict[str, torch.Tensor]:
    """Parameters of a frame entering the window (see ``SfTSettings.init``)."""
    if prev is None:
        return model.init_params()
    out = {k: (v.clone() if isinstance(v, torch.Tensor) else v) for k, v in prev.items()}
    if st.init == "extrapolate" and prev2 is not None:
        for k in model.init_params():  # the parameters; the Adam moments are copied
            out[k] = 2 * prev[k] - prev2[k]
    return out


def _window_loss(model: DeformationModel, terms: ImageTerms, inext: Inextensibility,
                 st: SfTSettings, params: dict, targets: torch.Tensor,
                 masks: torch.Tensor | None) -> torch.Tensor:
    """The window's objective (scalar tensor).

    Image terms and inextensibility summed over the window's frames, the model's regulariser,
    the temporal consistency between consecutive frames and the constant-velocity prior.
    """
    verts, reg = model.forward(params)
    img = terms(verts, targets, masks)
    per_frame = img["rgb"] + inext(verts)
    if "sil" in img:
        per_frame = per_frame + img["sil"]
    loss = per_frame.sum() + reg
    if st.k_tc > 0 and verts.shape[0] > 1:
        loss = loss + temporal_consistency(params, model.temporal, st.k_tc)
    if st.k_acc > 0 and verts.shape[0] > 2:
        loss = loss + temporal_acceleration(params, model.groups, st.k_acc)
    return loss


def _optimize_window(model: DeformationModel, terms: ImageTerms, inext: Inextensibility,
                     st: SfTSettings, pending: dict, idx: list[int], targets: torch.Tensor,
                     masks: torch.Tensor | None, callback=None) -> tuple[int, list[float], float]:
    """Optimise the frames ``idx`` in place in ``pending``; return (iterations, curve, loss).

    With ``st.keep_best`` the parameters left in ``pending`` are the iterate of the lowest
    loss of ``curve``, and ``loss`` is that value; without, they are those after the last
    step and ``loss`` is ``curve[-1]`` (the loss before that step).
    ``callback(iteration, params)`` is called after every step when given.
    """
    names = list(model.init_params())
    params = {n: torch.stack([pending[j][n] for j in idx]) for n in names}
    free = [n for n in names if n not in st.freeze]
    if not free:
        raise ValueError(f"freeze: every parameter of the model is frozen ({names})")
    for n in free:
        params[n].requires_grad_(True)
    opt = _FrameAdam(params, free, {n: getattr(st, model.groups[n]) for n in free},
                     [pending[j] if st.carry_adam else {} for j in idx], st.warmup)
    best, since, curve = float("inf"), 0, []
    best_val, best_params = float("inf"), None  # the best iterate is what the window returns
    auto = st.method == "polysft" and st.order == ORDER_AUTO
    block_best = float("inf")  # running minimum at the start of the current block
    it = 0
    for it in range(1, st.frame_period + 1):  # noqa: B007 - `it` is reported after the loop
        for n in free:
            params[n].grad = None
        loss = _window_loss(model, terms, inext, st, params, targets, masks)
        val = float(loss.detach())
        if st.keep_best and val < best_val:  # the parameters this loss was evaluated at
            best_val = val
            best_params = {n: params[n].detach().clone() for n in free}
        loss.backward()
        opt.step()
        curve.append(val)
        if callback is not None:
            callback(it, params)
        if val < best * (1.0 - st.min_improvement):
            best, since = val, 0
        else:
            since += 1
        if auto and it % st.patience == 0:
            # slow progress over the last block: the active order is the bottleneck
            if (model.order < model.max_order and np.isfinite(block_best)
                    and best > block_best * (1.0 - st.auto_gain)):
                model.set_order(model.order + 1)
                since = 0
            block_best = best
        if since >= st.patience:
            if auto and model.order < model.max_order:
                model.set_order(model.order + 1)
                since = 0
                continue
            break
    if best_params is not None:  # the Adam moments stay those of the last step
        with torch.no_grad():
            for n in free:
                params[n].copy_(best_params[n])
    for k, j in enumerate(idx):
        pending[j] = {n: params[n][k].detach().clone() for n in names}
        pending[j].update(opt.state_of(k))
    final = best_val if best_params is not None else (curve[-1] if curve else float("nan"))
    return it, curve, final


class _FrameAdam:
    """Adam (the torch.optim.Adam update) with per-frame moments and step counts.

    The moments of a frame travel with it from window to window (``SfTSettings.carry_adam``)
    and a frame entering the window inherits those of the frame before it, so a new window
    does not restart every parameter with the lr-sized first steps of a fresh Adam. With
    ``warmup`` N > 0 the learning rate of a frame at its step t is ``lr * min(1, t / N)``
    (``torch.optim.lr_scheduler.LambdaLR`` with that factor): only fresh states ramp.
    """

    B1, B2, EPS = 0.9, 0.999, 1e-8

    def __init__(self, params: dict, names: list[str], lrs: dict, states: list[dict],
                 warmup: int = 0):
        self.params, self.names, self.lrs = params, names, lrs
        self.warmup = int(warmup)
        F = len(states)
        self.m = {n: torch.stack([s.get("_m:" + n, torch.zeros_like(params[n][k]))
                                  for k, s in enumerate(states)]) for n in names}
        self.v = {n: torch.stack([s.get("_v:" + n, torch.zeros_like(params[n][k]))
                                  for k, s in enumerate(states)]) for n in names}
        self.t = torch.tensor([float(s.get("_t", 0)) for s in states], dtype=torch.float64)
        self.t = self.t.reshape(F)

    @torch.no_grad()
    def step(self) -> None:
        self.t += 1.0
        bc1 = 1.0 - self.B1 ** self.t
        bc2 = 1.0 - self.B2 ** self.t
        if self.warmup > 0:  # linear ramp over a fresh state's first steps
            bc1 = bc1 / torch.clamp(self.t / self.warmup, max=1.0)
        for n in self.names:
            p, g = self.params[n], self.params[n].grad
            if g is None:
                continue
            shape = (-1,) + (1,) * (p.ndim - 1)
            m, v = self.m[n], self.v[n]
            m.mul_(self.B1).add_(g, alpha=1.0 - self.B1)
            v.mul_(self.B2).addcmul_(g, g, value=1.0 - self.B2)
            denom = (v.sqrt() / bc2.sqrt().to(p.dtype).view(shape)).add_(self.EPS)
            p.sub_((self.lrs[n] / bc1).to(p.dtype).view(shape) * m / denom)

    def state_of(self, k: int) -> dict:
        """Moments and step count of frame ``k`` of the window (checkpointed with it)."""
        out: dict[str, Any] = {"_t": int(self.t[k])}
        for n in self.names:
            out["_m:" + n] = self.m[n][k].clone()
            out["_v:" + n] = self.v[n][k].clone()
        return out


def reconstruct_window(
    sequence: Sequence | str | os.PathLike,
    frames: list[int],
    settings: SfTSettings | None = None,
    *,
    callback=None,
) -> tuple[np.ndarray, int]:
    """Optimise one window of frames, all starting from the template (no sliding).

    Parameters
    ----------
    sequence : Sequence or path
    frames : list of int
        Frame indices of the window, in order.
    settings : SfTSettings, optional
        ``window`` is ignored; ``patience`` and ``frame_period`` apply.
    callback : callable, optional
        ``callback(iteration, vertices)`` after every step, with ``(F, V, 3)`` float64
        vertices (computed only when given).

    Returns
    -------
    vertices : np.ndarray
        ``(F, V, 3)`` float64 reconstruction (scene units).
    iterations : int
    """
    st = settings or SfTSettings()
    seq = sequence if isinstance(sequence, Sequence) else load_sequence(sequence)
    model, terms, inext = _objective_parts(seq, st)
    targets, masks = _Window(seq, terms).targets(list(frames))
    pending = {j: model.init_params() for j in frames}
    cb = None
    if callback is not None:
        def cb(it, params):
            with torch.no_grad():
                callback(it, model.vertices(params).to(torch.float64).numpy())
    iters, _, _ = _optimize_window(model, terms, inext, st, pending, list(frames), targets,
                                   masks, cb)
    with torch.no_grad():
        p = {n: torch.stack([pending[j][n] for j in frames]) for n in model.init_params()}
        X = model.vertices(p).to(torch.float64).numpy()
    return X, iters


def _overlay(path: Path, terms: ImageTerms, X: torch.Tensor, target: torch.Tensor,
             gt: np.ndarray | None, faces: np.ndarray) -> None:
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
