"""Pose sequences without licensed data: procedural motions, and an AMASS-style reader.

``generate(name, body, frames, fps=30, seed=0)`` returns a :class:`Motion` for any body whose
bones it can name (the Anny rig, SMPL / SMPL-X joint names): ``walk`` (a walk-like gait
forward), ``arms`` (arm raises and swings), ``squat``, ``turn`` (a quarter turn on the spot
with small steps), ``jacks`` (jumping jacks) and ``random`` (seeded smooth random motion of
the main joints within their limits).

How: each motion drives a few degrees of freedom (DOF) -- a bone, an axis and an angle curve
of time. Axes are built from the body's rest skeleton and its frame (left, up, forward), so a
DOF means the same on Anny (z up, facing -y, A-pose) and on SMPL (y up, facing +z, T-pose):
hip flexion, knee flexion, shoulder swing and abduction, elbow flexion, spine flexion, yaw.
A bone's rotation vector is the sum of its DOFs' ``angle * axis`` (radians). Every angle
stays inside :data:`LIMITS`; curves are sums of sinusoids and C2 smooth steps, and every
motion starts at the rest pose and eases in over the first 0.5 s (bounded accelerations).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from draping import names as _names
from draping.smpl import smpl_joint_names
from polygeo.checks import check_finite, check_int, check_positive

__all__ = [
    "LIMITS",
    "MOTIONS",
    "Motion",
    "generate",
    "motion_dofs",
    "read_amass",
]

MOTIONS = _names.MOTIONS

#: Joint limits (radians) of each DOF, ``name: (low, high)``; ``_L``/``_R`` share them.
LIMITS = {
    "hip_flex": (-0.6, 2.0),
    "hip_abd": (-0.3, 0.8),
    "knee_flex": (0.0, 2.4),
    "ankle_flex": (-0.8, 0.6),
    "spine_flex": (-0.15, 0.35),  # per spine segment
    "spine_yaw": (-0.2, 0.2),
    "spine_side": (-0.12, 0.12),
    "neck_flex": (-0.4, 0.5),
    "neck_yaw": (-0.7, 0.7),
    "shoulder_swing": (-0.9, 2.6),
    "shoulder_abd": (-0.9, 2.9),  # from the arm's hanging position
    "elbow_flex": (0.0, 2.4),
    "root_yaw": (-math.pi, math.pi),
}

# Roles -> bone names of the supported rigs.
_RIGS = {
    "anny": dict(
        root="root", spine=("spine05", "spine04", "spine03", "spine02", "spine01"),
        neck="neck01", hip_L="upperleg01.L", hip_R="upperleg01.R", knee_L="lowerleg01.L",
        knee_R="lowerleg01.R", ankle_L="foot.L", ankle_R="foot.R",
        shoulder_L="upperarm01.L", shoulder_R="upperarm01.R", elbow_L="lowerarm01.L",
        elbow_R="lowerarm01.R", wrist_L="wrist.L", wrist_R="wrist.R"),
    "smpl": dict(
        root="pelvis", spine=("spine1", "spine2", "spine3"), neck="neck",
        hip_L="left_hip", hip_R="right_hip", knee_L="left_knee", knee_R="right_knee",
        ankle_L="left_ankle", ankle_R="right_ankle", shoulder_L="left_shoulder",
        shoulder_R="right_shoulder", elbow_L="left_elbow", elbow_R="right_elbow",
        wrist_L="left_wrist", wrist_R="right_wrist"),
}


@dataclass(frozen=True)
class Motion:
    """A pose sequence for a body model.

    Attributes
    ----------
    rotations : (T, J, 3) float tensor
        Per-bone axis-angle rotations (radians), ``draping.body`` parameterisation.
    translation : (T, 3) float tensor
        Root translation, metres.
    fps : float
        Frames per second.
    name : str
    bone_names : tuple of str
        The ``J`` bones the rotations refer to.
    shape : (S,) float tensor or None
        Body shape parameters recorded with the motion (AMASS ``betas``), if any.
    """

    rotations: torch.Tensor
    translation: torch.Tensor
    fps: float = 30.0
    name: str = ""
    bone_names: tuple[str, ...] = ()
    shape: torch.Tensor | None = None

    def __len__(self) -> int:
        return self.rotations.shape[0]

    @property
    def velocity(self) -> torch.Tensor:
        """``(T, 3)`` root velocity (m/s): central differences, one-sided at the ends."""
        x = self.translation
        if len(x) < 2:
            return torch.zeros_like(x)
        v = torch.empty_like(x)
        v[1:-1] = (x[2:] - x[:-2]) * (self.fps / 2)
        v[0] = (x[1] - x[0]) * self.fps
        v[-1] = (x[-1] - x[-2]) * self.fps
        return v

    @property
    def duration(self) -> float:
        """Seconds spanned by the frames."""
        return (len(self) - 1) / self.fps


# ----------------------------------------------------------------------------------------
# skeleton frame and DOF axes
# ----------------------------------------------------------------------------------------


def _rig_of(bone_names) -> dict:
    names = set(bone_names)
    for rig in _RIGS.values():
        need = [v for v in rig.values() if isinstance(v, str)] + list(rig["spine"])
        if all(n in names for n in need):
            return rig
    raise ValueError(
        "body: procedural motions need the Anny rig or SMPL joint names "
        f"(e.g. {_RIGS['smpl']['hip_L']!r}); got bones {list(bone_names)[:6]}..."
    )


def _unit(v):
    return v / np.linalg.norm(v)


def _body_frame(joints, idx):
    """Left, up and forward unit vectors of a rest skeleton (from hips, spine and feet)."""
    left = _unit(joints[idx["hip_L"]] - joints[idx["hip_R"]])
    up0 = joints[idx["neck"]] - joints[idx["root"]]
    up = _unit(up0 - (up0 @ left) * left)
    fwd = np.cross(left, up)  # right-handed: left x up = forward for z-up/-y and y-up/+z
    return left, up, fwd


def _axes(joints, idx):
    """Rotation axis of every DOF (rest world axes) for each side."""
    left, up, fwd = _body_frame(joints, idx)
    ax = {"spine_flex": left, "spine_yaw": up, "spine_side": fwd, "neck_flex": left,
          "neck_yaw": up, "root_yaw": up}
    for s, sign in (("L", 1.0), ("R", -1.0)):
        arm = _unit(joints[idx[f"elbow_{s}"]] - joints[idx[f"shoulder_{s}"]])
        fore = _unit(joints[idx[f"wrist_{s}"]] - joints[idx[f"elbow_{s}"]])
        ax[f"hip_flex_{s}"] = -left
        ax[f"knee_flex_{s}"] = left
        ax[f"ankle_flex_{s}"] = -left
        ax[f"hip_abd_{s}"] = sign * fwd
        ax[f"shoulder_abd_{s}"] = sign * fwd
        ax[f"shoulder_swing_{s}"] = _unit(np.cross(arm, fwd))
        ax[f"elbow_flex_{s}"] = _unit(np.cross(fore, fwd))
    return ax, (left, up, fwd)


def _hang(joints, idx, up):
    """Abduction (radians, negative) that brings the arms from rest to ~72 deg below horizontal."""
    arm = _unit(joints[idx["elbow_L"]] - joints[idx["shoulder_L"]])
    below = math.asin(float(np.clip(-(arm @ up), -1, 1)))
    return min(0.0, below - math.radians(72.0))


# ----------------------------------------------------------------------------------------
# angle curves
# ----------------------------------------------------------------------------------------


def _smooth(x):
    """C2 smooth step: 0 for x <= 0, 1 for x >= 1."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6 * x - 15) + 10)


def _curves(name, t, total, hang, legs, rng):
    """DOF angle curves (radians) and root offsets (forward, left, up; metres) of a motion."""
    ease = _smooth(t / 0.5)
    z = np.zeros_like(t)
    c: dict[str, np.ndarray] = {}
    fwd_off, up_off, yaw = z.copy(), z.copy(), z.copy()
    for s in "LR":
        c[f"shoulder_abd_{s}"] = hang * ease
    if name == "walk":
        ph = 2 * np.pi * t / 1.1
        for s, sh in (("L", 0.0), ("R", np.pi)):
            c[f"hip_flex_{s}"] = ease * (0.12 + 0.42 * np.sin(ph + sh))
            c[f"knee_flex_{s}"] = ease * (0.1 + 0.6 * (0.5 + 0.5 * np.sin(ph + sh + 1.3)) ** 2)
            c[f"ankle_flex_{s}"] = ease * 0.15 * np.sin(ph + sh - 0.5)
            c[f"shoulder_swing_{s}"] = ease * 0.3 * np.sin(ph + sh + np.pi)
            c[f"elbow_flex_{s}"] = ease * (0.25 + 0.12 * (1 + np.sin(ph + sh + np.pi)))
        c["spine_yaw"] = ease * 0.04 * np.sin(ph)
        speed = 1.1  # m/s, eased in: distance = speed * integral of ease (trapezoids)
        fwd_off = speed * np.concatenate([[0.0], np.cumsum(0.5 * (ease[1:] + ease[:-1])
                                                           * np.diff(t))])
        up_off = ease * 0.012 * np.cos(2 * ph)
    elif name == "arms":
        ph = 2 * np.pi * t / 2.4
        raise_ = 0.5 - 0.5 * np.cos(ph)
        for s, sh in (("L", 0.0), ("R", np.pi / 2)):
            c[f"shoulder_abd_{s}"] = hang * ease + ease * (2.0 - hang) * raise_ * 0.6
            c[f"shoulder_swing_{s}"] = ease * 0.7 * np.sin(0.5 * ph + sh)
            c[f"elbow_flex_{s}"] = ease * (0.2 + 0.9 * (0.5 - 0.5 * np.cos(ph + sh)))
        c["spine_yaw"] = ease * 0.08 * np.sin(0.5 * ph)
    elif name == "squat":
        d = ease * (0.5 - 0.5 * np.cos(2 * np.pi * t / 2.5))
        a = 1.15 * d  # hip flexion
        b = 1.7 * d  # knee flexion
        for s in "LR":
            c[f"hip_flex_{s}"] = a
            c[f"knee_flex_{s}"] = b
            c[f"ankle_flex_{s}"] = b - a  # keeps the shin over a flat foot
            c[f"shoulder_swing_{s}"] = 1.2 * d
            c[f"elbow_flex_{s}"] = 0.3 * d
        c["spine_flex"] = 0.08 * d
        lt, ls = legs
        up_off = -(lt * (1 - np.cos(a)) + ls * (1 - np.cos(b - a)))
        fwd_off = -(lt * np.sin(a) - ls * np.sin(b - a))
    elif name == "turn":
        span = max(total, 1.0)
        yaw = (np.pi / 2) * _smooth(t / span)
        ph = 2 * np.pi * t / 0.8
        for s, sh in (("L", 0.0), ("R", np.pi)):
            step = ease * (0.5 + 0.5 * np.sin(ph + sh)) ** 2
            c[f"hip_flex_{s}"] = 0.3 * step
            c[f"knee_flex_{s}"] = 0.55 * step
            c[f"elbow_flex_{s}"] = ease * 0.3
        up_off = ease * 0.01 * np.cos(2 * ph)
    elif name == "jacks":
        ph = 2 * np.pi * t / 1.2
        p = ease * (0.5 - 0.5 * np.cos(ph))
        for s in "LR":
            c[f"shoulder_abd_{s}"] = hang * ease + (2.25 - hang) * p
            c[f"elbow_flex_{s}"] = 0.25 * p
            c[f"hip_abd_{s}"] = 0.32 * p
            c[f"knee_flex_{s}"] = ease * 0.12 * (0.5 - 0.5 * np.cos(2 * ph))
        up_off = ease * 0.05 * (0.5 - 0.5 * np.cos(2 * ph))
    elif name == "random":
        for dof, (lo, hi) in _RANDOM_DOFS.items():
            for s in ("L", "R") if dof not in _CENTRAL else ("",):
                key = f"{dof}_{s}" if s else dof
                f = rng.uniform(0.15, 0.6, 3)
                phase = rng.uniform(0, 2 * np.pi, 3)
                amp = rng.dirichlet(np.ones(3))
                wave = (amp[:, None] * np.sin(2 * np.pi * f[:, None] * t + phase[:, None])).sum(0)
                mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
                base = hang if dof == "shoulder_abd" else 0.0
                c[key] = base * ease + ease * (mid + half * wave)
        yaw = ease * 0.5 * np.sin(2 * np.pi * rng.uniform(0.05, 0.15) * t + rng.uniform(0, 6))
    else:
        raise ValueError(f"name: expected one of {MOTIONS}, got {name!r}")
    return c, (fwd_off, up_off), yaw


# random motion: DOF ranges (inside LIMITS, kept modest so that limbs stay apart)
_RANDOM_DOFS = {
    "hip_flex": (-0.2, 0.7), "knee_flex": (0.05, 0.9), "hip_abd": (0.0, 0.3),
    "shoulder_swing": (-0.4, 1.0), "shoulder_abd": (0.1, 1.4), "elbow_flex": (0.1, 1.4),
    "spine_flex": (-0.05, 0.15), "spine_yaw": (-0.1, 0.1), "neck_yaw": (-0.5, 0.5),
}
_CENTRAL = {"spine_flex", "spine_yaw", "neck_yaw"}


def motion_dofs(name: str, body, frames: int, fps: float = 30.0, seed: int = 0):
    """The DOF angle curves of a procedural motion (for inspection and the limit tests).

    Returns
    -------
    dict
        ``dof name -> (T,) float64 array`` of angles (radians); ``_L``/``_R`` suffixes name
        the side; limits in :data:`LIMITS` under the name without the suffix.
    """
    return _generate(name, body, frames, fps, seed)[2]


def generate(name: str, body, frames: int = 60, fps: float = 30.0, seed: int = 0) -> Motion:
    """A procedural motion for a body model.

    Parameters
    ----------
    name : {"walk", "arms", "squat", "turn", "jacks", "random"}
    body : BodyModel
        A body with the Anny rig or SMPL joint names (``draping.body.AnnyBody``,
        ``draping.smpl.SMPLBody``); its default-shape rest skeleton sets the axes.
    frames : int
        Number of frames ``T >= 1``.
    fps : float
        Frames per second (30 by default).
    seed : int
        Seed of ``random`` (other motions are deterministic).

    Returns
    -------
    Motion
        Rotations ``(T, J, 3)`` and root translation ``(T, 3)`` in the body's dtype.

    Raises
    ------
    ValueError
        On an unknown name, ``frames < 1``, a non-positive fps or an unsupported rig.
    """
    rot, trans, _ = _generate(name, body, frames, fps, seed)
    dt = body.rest_vertices.dtype
    return Motion(torch.as_tensor(rot, dtype=dt), torch.as_tensor(trans, dtype=dt),
                  float(fps), name, tuple(body.bone_names))


def _generate(name, body, frames, fps, seed):
    if name not in MOTIONS:
        raise ValueError(f"name: expected one of {MOTIONS}, got {name!r}")
    frames = check_int(frames, "frames", low=1)
    fps = check_positive(fps, "fps")
    rig = _rig_of(body.bone_names)
    names = list(body.bone_names)
    idx = {role: names.index(b) for role, b in rig.items() if isinstance(b, str)}
    spine = [names.index(b) for b in rig["spine"]]
    joints = body.rest_joints.detach().double().cpu().numpy()
    axes, (left, up, fwd) = _axes(joints, idx)
    hang = _hang(joints, idx, up)
    legs = (float(np.linalg.norm(joints[idx["knee_L"]] - joints[idx["hip_L"]])),
            float(np.linalg.norm(joints[idx["ankle_L"]] - joints[idx["knee_L"]])))
    t = np.arange(frames) / fps
    rng = np.random.default_rng(seed)
    curves, (fwd_off, up_off), yaw = _curves(name, t, (frames - 1) / fps, hang, legs, rng)
    rot = np.zeros((frames, len(names), 3))
    for dof, angle in curves.items():
        base, _, side = dof.rpartition("_")
        if side in ("L", "R"):
            bone = idx[{"hip_flex": "hip", "hip_abd": "hip", "knee_flex": "knee",
                        "ankle_flex": "ankle", "shoulder_swing": "shoulder",
                        "shoulder_abd": "shoulder", "elbow_flex": "elbow"}[base] + "_" + side]
            rot[:, bone] += angle[:, None] * axes[dof]
        elif dof.startswith("spine"):
            for b in spine:  # spread over the segments
                rot[:, b] += angle[:, None] * axes[dof]
        else:  # neck
            rot[:, idx["neck"]] += angle[:, None] * axes[dof]
    rot[:, idx["root"]] += yaw[:, None] * axes["root_yaw"]
    # root path: forward offsets follow the heading (yaw)
    heading = np.cos(yaw)[:, None] * fwd + np.sin(yaw)[:, None] * np.cross(up, fwd)
    trans = fwd_off[:, None] * heading + up_off[:, None] * up
    check_finite(torch.as_tensor(rot), "rotations")
    return rot, trans, curves


# ----------------------------------------------------------------------------------------
# AMASS
# ----------------------------------------------------------------------------------------


def read_amass(path, n_joints: int = 24, dtype: torch.dtype = torch.float32) -> Motion:
    """Read an AMASS-style ``.npz`` (``poses``, ``trans``, ``betas``, frame rate) for SMPL bodies.

    AMASS stores SMPL+H poses ``(T, 156)`` (52 joints) or SMPL-X poses ``(T, 165)`` (55
    joints); the first 22 joints (pelvis to wrists) are shared. For a 24-joint SMPL body the
    two hand joints are set to zero; for 52 / 55 joints the file's joints are kept and padded
    with zeros. AMASS's root orientation and translation put the (y-up) SMPL body in a z-up
    world, so posed bodies come out z-up.

    Parameters
    ----------
    path : str or Path
        The ``.npz`` file (the user's own download; nothing is fetched).
    n_joints : int
        Joints of the target body (24 SMPL, 52 SMPL+H, 55 SMPL-X).
    dtype : torch.dtype

    Returns
    -------
    Motion
        ``rotations (T, n_joints, 3)``, ``translation (T, 3)``, ``fps`` from
        ``mocap_framerate`` / ``mocap_frame_rate`` (30 if absent), ``shape`` = ``betas``.

    Raises
    ------
    ValueError
        On a missing key, inconsistent frame counts, NaN, or too few pose columns.
    """
    path = Path(path)
    n_joints = check_int(n_joints, "n_joints", low=1)
    with np.load(path, allow_pickle=False) as z:
        d = {k: z[k] for k in z.files}
    for key in ("poses", "trans"):
        if key not in d:
            raise ValueError(f"path: {path.name} has no {key!r} array (keys: {sorted(d)})")
    poses = np.asarray(d["poses"], dtype=np.float64)
    trans = np.asarray(d["trans"], dtype=np.float64)
    if poses.ndim != 2 or poses.shape[1] % 3 or poses.shape[1] < 66:
        raise ValueError(f"poses: expected (T, 3 * J) with J >= 22, got {poses.shape}")
    if trans.shape != (poses.shape[0], 3):
        raise ValueError(f"trans: expected ({poses.shape[0]}, 3), got {trans.shape}")
    if not (np.isfinite(poses).all() and np.isfinite(trans).all()):
        raise ValueError(f"poses/trans: {path.name} holds NaN or infinite values")
    rot = poses.reshape(len(poses), -1, 3)
    keep = 22 if n_joints == 24 else min(n_joints, rot.shape[1])
    out = np.zeros((len(poses), n_joints, 3))
    out[:, :keep] = rot[:, :keep]
    fps = 30.0
    for key in ("mocap_framerate", "mocap_frame_rate"):
        if key in d:
            fps = float(d[key])
    betas = torch.as_tensor(d["betas"], dtype=dtype) if "betas" in d else None
    names = smpl_joint_names(n_joints)
    return Motion(torch.as_tensor(out, dtype=dtype), torch.as_tensor(trans, dtype=dtype),
                  fps, path.stem, names, betas)

