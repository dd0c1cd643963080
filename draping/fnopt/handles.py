"""Handle trajectories in the style of the ARCSim square-cloth set (60 fps).

Translations along x, y, z, xy, xyz and rotations about two axes (and their opposites) of the
handles' rest positions. A motion is eased in and out over ``T = 2 s / speed`` (the handles
move, then hold still so that the cloth settles); ``speed`` compresses time, so the base motion
has the dataset's base speed and ``speed=2`` moves twice as fast over the same path.
"""

from __future__ import annotations

import math

import torch

from .settings import MOTIONS

__all__ = ["MOTIONS", "FPS", "DT", "BASE_DURATION", "AMPLITUDE", "ANGLE",
           "check_motion", "ease", "handle_targets", "trajectory"]

#: Frames per second of the dataset.
FPS = 60
#: Time step, s.
DT = 1.0 / FPS
#: Duration of the base motion, s (at ``speed=1``).
BASE_DURATION = 2.0
#: Translation amplitude, m (the cloth is 1 m wide by default).
AMPLITUDE = 0.5
#: Rotation amplitude, rad.
ANGLE = 0.5 * math.pi

_DIRS = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0),
         "xy": (1.0, 1.0, 0.0), "xyz": (1.0, 1.0, 1.0)}
#: Rotation axes: ``rot-a`` about the vertical z axis, ``rot-b`` about the horizontal y axis
#: (the normal of the hanging sheet), each through the handles' centroid.
_AXES = {"rot-a": (0.0, 0.0, 1.0), "rot-b": (0.0, 1.0, 0.0)}



def check_motion(motion: str) -> str:
    """Return ``motion`` or raise ``ValueError`` naming the accepted ones."""
    if motion not in MOTIONS:
        raise ValueError(f"motion: expected one of {list(MOTIONS)}, got {motion!r}")
    return motion


def ease(t: torch.Tensor | float, duration: float) -> torch.Tensor:
    """Smooth 0 -> 1 ramp ``(1 - cos(pi t / T)) / 2`` over ``[0, T]``, held at 1 after."""
    t = torch.as_tensor(t, dtype=torch.float64)
    s = torch.clamp(t / duration, 0.0, 1.0)
    return 0.5 * (1.0 - torch.cos(math.pi * s))


def _rotate(p: torch.Tensor, axis, angle: torch.Tensor) -> torch.Tensor:
    k = torch.tensor(axis, dtype=p.dtype)
    c, s = torch.cos(angle), torch.sin(angle)
    return p * c + torch.cross(k.expand_as(p), p, dim=-1) * s + k * (p @ k)[..., None] * (1 - c)


def handle_targets(rest: torch.Tensor, motion: str, t, speed: float = 1.0,
                   amplitude: float = AMPLITUDE, angle: float = ANGLE,
                   direction=None) -> torch.Tensor:
    """Handle positions ``(K, 3)`` (m, float64) at time ``t`` (s).

    Parameters
    ----------
    rest : torch.Tensor
        Rest positions of the handles ``(K, 3)`` in metres.
    motion : str
        One of :data:`MOTIONS`.
    t : float
        Time in seconds.
    speed : float
        Factor on the base speed (> 0).
    amplitude, angle : float
        Translation (m) and rotation (rad) amplitudes.
    direction : sequence of 3 floats, optional
        Overrides the translation direction (used for random training motions).

    Raises
    ------
    ValueError
        On an unknown motion or a non-positive speed.
    """
    check_motion(motion)
    if not (math.isfinite(speed) and speed > 0):
        raise ValueError(f"speed: expected a finite factor > 0, got {speed!r}")
    rest = torch.as_tensor(rest, dtype=torch.float64)
    s = ease(t, BASE_DURATION / speed)
    if motion == "still":
        return rest.clone()
    sign = -1.0 if motion.endswith("-rev") else 1.0
    base = motion[:-4] if motion.endswith("-rev") else motion
    if base in _AXES:
        c = rest.mean(0, keepdim=True)
        return c + _rotate(rest - c, _AXES[base], sign * angle * s)
    d = torch.tensor(direction if direction is not None else _DIRS[base], dtype=torch.float64)
    d = d / d.norm().clamp(min=1e-12)
    return rest + sign * amplitude * s * d


def trajectory(rest: torch.Tensor, motion: str, frames: int, speed: float = 1.0,
               dt: float = DT, **kw) -> torch.Tensor:
    """Handle positions ``(frames + 1, K, 3)`` at ``t = 0, dt, ..., frames dt``."""
    return torch.stack([handle_targets(rest, motion, f * dt, speed, **kw)
                        for f in range(frames + 1)])
