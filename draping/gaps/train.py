"""Self-supervised training of a GAPS model (and of the SNUG-like / NCS-like baselines).

Part of :mod:`draping.gaps`; import from there.

A step (see :class:`draping.gaps.TrainSettings`): one training body shape, ``batch`` windows
of ``window`` frames from the training motions, each started from the GRU state of the
motion read up to it (``burn_in``), eq. (46) on every frame, the gradient norm clipped.
Seeded per step (``numpy`` and ``torch`` generators keyed by ``(seed, step)``), so a run
resumed from its checkpoint continues exactly as the uninterrupted run would.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from draping.body import AnnyBody
from draping.collision import MeshQuery

from .average import WeightAverage
from .data import ShapeCase, random_shapes, shape_case, training_sequences
from .infer import build_model, motion_features, save_model
from .losses import TERMS, body_contacts, loss_terms
from .model import GapsModel
from .pinch import PinchQuery, face_parts
from .settings import TrainSettings

__all__ = ["TrainResult", "Trainer", "train", "STAGES"]

#: Hard-example replay (``TrainSettings.replay``): fresh steps remembered, the quantile above
#: which a step is hard, the fewest remembered steps before any is, hard steps kept.
REPLAY_HISTORY, REPLAY_QUANTILE, REPLAY_MIN, REPLAY_POOL = 200, 0.9, 20, 64

#: Timed stages of a step (CPU seconds summed in the log): body posing, network forward and
#: skinning, body distance queries, energies, backward and optimiser update.
STAGES = ("pose", "forward", "query", "energies", "backward")


class TrainResult(NamedTuple):
    """What :func:`train` did: the run folder, the exported model, steps and minutes."""

    out_dir: Path
    model_path: Path
    steps: int
    cpu_minutes: float
    wall_minutes: float
    last: dict


class Trainer:
    """The pieces of a training run (model, optimiser, shape pool, motions), one step at a time.

    Parameters
    ----------
    settings : TrainSettings
    body : AnnyBody, optional
        Default: the shipped body (float32).
    """

    def __init__(self, settings: TrainSettings, body: AnnyBody | None = None):
        torch.manual_seed(settings.seed)
        self.settings = settings
        self.body = AnnyBody.load() if body is None else body
        self.model, self.template = build_model(settings.model, self.body)
        if settings.init is not None:
            self._init_from(settings.init)
        self.opt = torch.optim.Adam(self.model.parameters(), lr=settings.lr)
        self.shapes = random_shapes(settings.shapes, settings.seed)
        self._cases: dict[int, ShapeCase] = {}
        self.sequences = training_sequences(settings, self.body)
        self.query = MeshQuery(self.body.rest()[0][0].double(), self.body.faces)
        self.pinch = None
        if settings.pinch_push or (settings.pinch_inext != 1.0
                                   and settings.model.inext_mode != "none"):
            arm = np.isin(face_parts(self.body), ("armL", "armR"))
            self.pinch = PinchQuery(self.body.rest()[0][0].double(), self.body.faces, arm)
        self.dt = 1.0 / 30.0
        self.step = 0
        self.grad_ref = float("nan")  # running mean of clipped gradient norms (grad_clip)
        self.timing = dict.fromkeys(STAGES, 0.0)
        self.history: list[float] = []  # collision losses of the latest fresh steps (replay)
        self.hard: list[tuple] = []  # (shape index, windows) of the latest hard steps
        self.average = (None if settings.average_from is None
                        else WeightAverage(settings.average_from))

    def _init_from(self, path: str) -> None:
        """Start from a saved model of the same garment and architecture (fine-tuning).

        A model whose skinning smoothing differs (e.g. one saved before ``skin_smoothing``)
        gives its network; the skinning weights stay those of this run's settings.
        """
        from .infer import load_model

        start = load_model(path)
        want = self.settings.model
        same_net = dataclasses.replace(start.settings, skin_smoothing=want.skin_smoothing)
        if same_net != want:
            raise ValueError(f"init: {path} was trained with {start.settings}, expected {want}")
        state = start.state_dict()
        if start.settings != want:  # other skinning weights: keep this run's
            for k in ("weights", "indices"):
                state[k] = getattr(self.model, k)
        self.model.load_state_dict(state)

    def case(self, i: int) -> ShapeCase:
        """The garment of training shape ``i`` (made once, then cached)."""
        if i not in self._cases:
            self._cases[i] = shape_case(self.template, self.body, self.shapes[i])
        return self._cases[i]

    def epoch(self, step: int | None = None) -> int:
        """Epoch of the schedules at a step."""
        return (self.step if step is None else step) // self.settings.epoch_steps

    def lr(self, step: int | None = None) -> float:
        """The paper's schedule: ``lr`` for ``lr_epochs`` epochs, then ``lr_late``."""
        s = self.settings
        return s.lr if self.epoch(step) < s.lr_epochs else s.lr_late

    def batch(self, step: int):
        """Shape index and ``(sequence, start)`` windows of a step (seeded by the step)."""
        s = self.settings
        rng = np.random.default_rng([s.seed, step, 11])
        i = int(rng.integers(len(self.shapes)))
        wins = []
        for _ in range(s.batch):
            k = int(rng.integers(len(self.sequences)))
            n = self.sequences[k].rotations.shape[0]
            wins.append((k, int(rng.integers(0, n - s.window + 1))))
        return i, wins

    def pick(self, step: int) -> tuple[int, list, bool]:
        """Shape index and windows of a step, and whether they are fresh.

        Fresh: :meth:`batch`. Otherwise (with probability ``replay`` once there is a hard
        step; seeded by the step) those of a remembered hard step (:meth:`note`).
        """
        s = self.settings
        if s.replay > 0 and self.hard:
            rng = np.random.default_rng([s.seed, step, 13])
            if rng.random() < s.replay:
                i, wins = self.hard[int(rng.integers(len(self.hard)))]
                return i, list(wins), False
        return (*self.batch(step), True)

    def note(self, i: int, wins: list, collision: float) -> bool:
        """Remember a fresh step's collision loss; keep it as hard if in the top decile.

        Returns whether it was kept.
        """
        self.history = (self.history + [float(collision)])[-REPLAY_HISTORY:]
        if len(self.history) < REPLAY_MIN or not collision > 0:
            return False
        if collision < float(np.quantile(self.history, REPLAY_QUANTILE)):
            return False
        self.hard = (self.hard + [(int(i), [tuple(map(int, w)) for w in wins])])[-REPLAY_POOL:]
        return True

    def context(self, wins: list, shape: torch.Tensor, h0: torch.Tensor) -> torch.Tensor:
        """GRU states ``(depth, B, width)`` at the windows' first frames (``burn_in``).

        Each window's motion is read, without gradient, from ``burn_in`` frames before the
        window (or its first frame, where the state is zero as at inference; elsewhere
        ``h0``).
        """
        n = self.settings.burn_in
        if n <= 0:
            return h0
        out = []
        with torch.no_grad():
            for j, (k, st) in enumerate(wins):
                lo = max(0, st - n)
                h = h0[:, j:j + 1] if lo > 0 else torch.zeros_like(h0[:, j:j + 1])
                if st > lo:
                    seq = self.sequences[k]
                    f = motion_features(self.body, seq.rotations[lo:st][None],
                                        seq.velocity[lo:st][None], shape[None])
                    h = self.model.state(f, h)
                out.append(h)
        return torch.cat(out, dim=1)

    def losses(self, step: int, timing: dict | None = None,
               pick: tuple | None = None) -> tuple[torch.Tensor, dict]:
        """The loss of a step (differentiable) and its terms per frame (floats).

        ``pick``: the step's ``(shape index, windows)`` (default :meth:`batch`).
        """
        s, m = self.settings, self.model
        tm = self.timing if timing is None else timing
        c0 = time.process_time()
        i, wins = self.batch(step) if pick is None else pick
        case = self.case(i)
        sl = [slice(st, st + s.window) for _, st in wins]
        rot = torch.stack([self.sequences[k].rotations[w] for (k, _), w in zip(wins, sl)])
        trans = torch.stack([self.sequences[k].translation[w] for (k, _), w in zip(wins, sl)])
        vel = torch.stack([self.sequences[k].velocity[w] for (k, _), w in zip(wins, sl)])
        b, n_l = rot.shape[:2]
        posed = self.body.pose(case.shape, rot.reshape(b * n_l, -1, 3), trans.reshape(-1, 3))
        c1 = time.process_time()
        gen = torch.Generator().manual_seed(int(s.seed) * 1_000_003 + int(step))
        h0 = s.hidden_std * torch.randn(m.settings.depth, b, m.settings.width, generator=gen)
        h0 = self.context(wins, case.shape, h0)
        feats = motion_features(self.body, rot, vel, case.shape.expand(b, 6))
        disp, _ = m(feats, h0)
        rest_v = case.rest.vertices.to(disp.dtype)
        x = m.skin((rest_v + disp).reshape(b * n_l, -1, 3), posed.transforms)
        c2 = time.process_time()
        contacts = body_contacts(x, posed.vertices, self.query, s.query_radius, self.pinch,
                                 s.collision_eps, push=s.pinch_push)
        c3 = time.process_time()
        terms = loss_terms(x.reshape(b, n_l, -1, 3), case, m.settings, s, contacts,
                           self.epoch(step), self.dt)
        total = sum(t.sum(1) for t in terms.values()).mean()
        c4 = time.process_time()
        for k, a, z in (("pose", c0, c1), ("forward", c1, c2), ("query", c2, c3),
                        ("energies", c3, c4)):
            tm[k] += z - a
        per = {k: float(v.detach().mean()) for k, v in terms.items()}
        return total, per

    def train_step(self) -> dict:
        """One optimiser step; returns the logged record."""
        for g in self.opt.param_groups:
            g["lr"] = self.lr()
        i, wins, fresh = self.pick(self.step)
        total, per = self.losses(self.step, pick=(i, wins))
        if fresh and self.settings.replay > 0 and np.isfinite(per["collision"]):
            self.note(i, wins, per["collision"])
        c0 = time.process_time()
        self.opt.zero_grad(set_to_none=True)
        ok = bool(torch.isfinite(total))
        norm = float("nan")
        if ok:
            total.backward()
            norm = self.clip()
            ok = np.isfinite(norm)
            if ok:
                self.opt.step()
        self.timing["backward"] += time.process_time() - c0
        rec = {"step": self.step, "loss": float(total.detach()), "finite": bool(ok),
               "lr": self.lr(), "epoch": self.epoch(),
               "grad_norm": norm if np.isfinite(norm) else None, **per}
        self.step += 1
        if self.average is not None and self.step > self.average.start:
            self.average.update(self.model)
        return rec

    def clip(self) -> float:
        """Clip the gradient norm at ``grad_clip`` times the running mean of clipped norms.

        Returns the norm before clipping (NaN or inf: the step is skipped, the mean kept).
        """
        c = self.settings.grad_clip
        ref = self.grad_ref
        limit = float("inf") if c <= 0 or not np.isfinite(ref) else c * ref
        norm = float(torch.nn.utils.clip_grad_norm_(self.model.parameters(), limit))
        if np.isfinite(norm):
            kept = min(norm, limit)
            self.grad_ref = kept if not np.isfinite(ref) else 0.98 * ref + 0.02 * kept
        return norm

    def state(self) -> dict:
        """Tensors of a checkpoint."""
        out = {"model": self.model.state_dict(), "optim": self.opt.state_dict(),
               "grad_ref": torch.tensor(self.grad_ref, dtype=torch.float64)}
        if self.settings.replay > 0:
            out["replay_history"] = torch.tensor(self.history, dtype=torch.float64)
            w = self.settings.batch
            out["replay_hard"] = torch.tensor(
                [[i] + [v for win in wins for v in win] for i, wins in self.hard],
                dtype=torch.int64).reshape(-1, 1 + 2 * w)
        if self.average is not None and self.step > self.average.start:
            out["average"] = self.average.state()
        return out

    def load_state(self, tensors: dict, step: int) -> None:
        """Restore a checkpoint's tensors.

        Raises
        ------
        ValueError
            With ``average_from`` set and ``step`` past it, if the checkpoint holds no weight
            average from that step (a run trained past it without averaging cannot resume
            with it).
        """
        self.model.load_state_dict(tensors["model"])
        self.opt.load_state_dict(tensors["optim"])
        if "grad_ref" in tensors:
            self.grad_ref = float(tensors["grad_ref"])
        if "replay_history" in tensors:
            self.history = [float(v) for v in tensors["replay_history"]]
            self.hard = [(int(r[0]), [(int(r[k]), int(r[k + 1])) for k in range(1, len(r), 2)])
                         for r in tensors["replay_hard"].tolist()]
        self.step = int(step)
        if self.average is not None and self.step > self.average.start:
            self.average.load(tensors.get("average"))  # ValueError if it holds none
        elif self.average is not None:
            self.average = WeightAverage(self.average.start)


def _fingerprint(settings: TrainSettings) -> str:
    from polygeo.runs import fingerprint

    return fingerprint(settings.key_dict())  # more steps continue the same run


def _curves(log: list, path: Path) -> None:
    from draping import viz

    steps = [r["step"] for r in log]
    curves = {k: [abs(r[k]) + 1e-12 for r in log] for k in ("loss",) + TERMS
              if k != "gravity"}
    viz.plot_curves(curves, path, xlabel="step", ylabel="energy per frame (J; |loss|)",
                    title="GAPS training", logy=True, x=dict.fromkeys(curves, steps))


def train(settings: TrainSettings, out_dir: str | Path, *, minutes: float | None = None,
          steps: int | None = None, resume: bool = True, quiet: bool = False,
          body: AnnyBody | None = None, log_every: int = 10, command: str = "") -> TrainResult:
    """Train a model, checkpointed and resumable; export ``model.pt`` and ``curves.png``.

    Parameters
    ----------
    settings : TrainSettings
    out_dir : str or Path
        Run folder: ``checkpoint.pt`` (every ``checkpoint_every`` steps), ``log.jsonl``
        (loss terms, learning rate, stage CPU seconds), ``model.pt`` (the exported model,
        :func:`draping.gaps.load_model`: the weight average with ``average_from``, then the
        last weights in ``model_last.pt``), ``curves.png``.
    minutes : float, optional
        Wall-clock budget (minutes): stop (checkpointed and exported) when spent.
    steps : int, optional
        Total steps (default ``settings.steps``); a resumed run goes on to this count.
    resume : bool
        Continue from the folder's checkpoint if its settings match (a
        :class:`polygeo.runs.SettingsChangedError` if they do not).
    quiet : bool
        No progress bar.
    body : AnnyBody, optional
    log_every : int
        Steps between log records.
    command : str
        The command line, recorded in the model's record.

    Returns
    -------
    TrainResult
    """
    from polygeo.runs import (
        JsonlLog,
        progress,
        read_jsonl,
        resume_state,
        save_checkpoint,
        truncate_jsonl,
    )

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    total_steps = settings.steps if steps is None else int(steps)
    fp = _fingerprint(settings)
    ck = resume_state(out, fp) if resume else None
    tr = Trainer(settings, body)
    cpu0, wall0 = 0.0, 0.0
    if ck is not None:
        tr.load_state(ck.tensors, ck.meta["step"])
        cpu0, wall0 = float(ck.meta["cpu_seconds"]), float(ck.meta["wall_seconds"])
        tr.timing.update(ck.meta.get("timing", {}))
        # records of steps after the checkpoint (a run stopped between two) are done again
        truncate_jsonl(out / "log.jsonl", lambda r: r.get("step", -1) < tr.step)
    elif (out / "log.jsonl").exists():
        (out / "log.jsonl").unlink()
    c_start, w_start = time.process_time(), time.perf_counter()

    def spent():
        return (cpu0 + time.process_time() - c_start, wall0 + time.perf_counter() - w_start)

    def checkpoint():
        cpu, wall = spent()
        save_checkpoint(out / "checkpoint.pt", tr.state(),
                        {"fingerprint": fp, "step": tr.step, "cpu_seconds": cpu,
                         "wall_seconds": wall, "timing": tr.timing,
                         "settings": dataclasses.asdict(settings)})

    bar = progress(total=total_steps, initial=tr.step, desc="train-drape", quiet=quiet,
                   unit="step")
    with JsonlLog(out / "log.jsonl") as log:
        while tr.step < total_steps:
            if minutes is not None and (time.perf_counter() - w_start) / 60.0 >= minutes:
                break
            rec = tr.train_step()
            bar.update(1)
            if rec["step"] % log_every == 0 or tr.step == total_steps:
                cpu, wall = spent()
                log.append({**rec, "cpu_seconds": cpu, "wall_seconds": wall,
                            "timing": dict(tr.timing)})
                bar.set_postfix(loss=f"{rec['loss']:.4g}", col=f"{rec['collision']:.2g}")
            if tr.step % settings.checkpoint_every == 0:
                checkpoint()
    bar.close()
    checkpoint()
    cpu, wall = spent()
    records = read_jsonl(out / "log.jsonl")
    if records:
        _curves(records, out / "curves.png")
    record = {
        "training": {"settings": dataclasses.asdict(settings), "steps": tr.step,
                     "cpu_minutes": cpu / 60.0, "wall_minutes": wall / 60.0,
                     "stage_cpu_seconds": dict(tr.timing), "command": command,
                     "threads": torch.get_num_threads()},
    }
    model = tr.model
    if tr.average is not None and tr.average.count > 0:
        record["training"]["average"] = {"from_step": tr.average.start,
                                         "snapshots": tr.average.count}
        save_model(out / "model_last.pt", tr.model, {**record, "weights": "last"})
        model = tr.average.averaged(tr.model)
    path = save_model(out / "model.pt", model, record)
    return TrainResult(out, path, tr.step, cpu / 60.0, wall / 60.0,
                       records[-1] if records else {})


def untrained_model(settings: TrainSettings, body: AnnyBody | None = None) -> GapsModel:
    """The model a run starts from (zero displacements: pure skinning)."""
    return build_model(settings.model, AnnyBody.load() if body is None else body)[0]
