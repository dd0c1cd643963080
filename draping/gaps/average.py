"""Uniform weight averaging over the last steps of a training run (SWA-like).

Part of :mod:`draping.gaps`; import from there. Used by :class:`draping.gaps.Trainer` when
``TrainSettings.average_from`` is set: after every optimiser step past that step the
network's parameters are added to a running mean, and the run exports the mean.
"""

from __future__ import annotations

import copy

import torch

from polygeo.checks import check_int

__all__ = ["WeightAverage"]


class WeightAverage:
    """Running uniform mean of a module's parameters (float64), one snapshot per call.

    Only ``module.named_parameters()`` are averaged; buffers (the garment template, the
    skinning weights and indices) are the module's own.

    Parameters
    ----------
    start : int
        The step after which snapshots are taken (recorded; :meth:`load` checks it).
    """

    def __init__(self, start: int):
        self.start = check_int(start, "start", low=0)
        self.count = 0
        self.mean: dict[str, torch.Tensor] = {}

    def update(self, module: torch.nn.Module) -> None:
        """Add the module's current parameters to the mean.

        Raises
        ------
        ValueError
            If a parameter is not finite (a NaN would poison the whole mean silently) or the
            parameter names differ from the earlier snapshots'.
        """
        params = dict(module.named_parameters())
        if self.mean and set(params) != set(self.mean):
            raise ValueError("module: its parameters differ from the averaged ones")
        vals = {k: p.detach().to(torch.float64) for k, p in params.items()}
        for k, v in vals.items():  # all checked before any is added
            if not bool(torch.isfinite(v).all()):
                raise ValueError(f"module: parameter {k!r} is not finite; not averaged")
        n = self.count + 1
        for k, v in vals.items():
            if k not in self.mean:
                self.mean[k] = v.clone()
            else:
                self.mean[k] += (v - self.mean[k]) / n
        self.count = n

    def averaged(self, module: torch.nn.Module) -> torch.nn.Module:
        """A deep copy of ``module`` with the mean parameters (in each parameter's dtype).

        Raises
        ------
        ValueError
            If no snapshot was taken.
        """
        if self.count == 0:
            raise ValueError("no snapshot averaged yet (count 0)")
        out = copy.deepcopy(module)
        with torch.no_grad():
            for k, p in out.named_parameters():
                p.copy_(self.mean[k].to(p.dtype))
        return out

    def state(self) -> dict:
        """Checkpoint tensors: ``{"mean": {name: float64 tensor}, "count": ..., "start": ...}``."""
        return {"mean": {k: v.clone() for k, v in self.mean.items()},
                "count": torch.tensor(self.count, dtype=torch.int64),
                "start": torch.tensor(self.start, dtype=torch.int64)}

    def load(self, state: dict | None) -> None:
        """Restore :meth:`state` (a checkpoint's ``"average"`` entry).

        Raises
        ------
        ValueError
            If ``state`` is None (the checkpoint holds no average) or its average started at
            another step.
        """
        if state is None:
            raise ValueError(f"state: no weight average (from step {self.start}) saved")
        start = int(state["start"])
        if start != self.start:
            raise ValueError(f"state: the saved average starts at step {start}, "
                             f"expected {self.start}")
        self.count = int(state["count"])
        self.mean = {k: v.to(torch.float64).clone() for k, v in state["mean"].items()}
