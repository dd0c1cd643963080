import math

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from draping.body import AnnyBody
from draping.motion import LIMITS, MOTIONS, Motion, generate, motion_dofs
from polygeo.frames import axis_angle_to_matrix
from polygeo.mesh import vertex_normals

FPS = 30.0


@pytest.fixture(scope="module")
def body():
    return AnnyBody.load(dtype=torch.float64)


@pytest.fixture(scope="module")
def motions(body):
    return {name: generate(name, body, frames=120, seed=0) for name in MOTIONS}


def _limit(dof):
    return LIMITS[dof[:-2] if dof.endswith(("_L", "_R")) else dof]


@pytest.mark.parametrize("name", MOTIONS)
def test_shapes_finite_start_at_rest_and_limits(body, motions, name):
    m = motions[name]
    assert isinstance(m, Motion) and m.fps == FPS and len(m) == 120
    assert m.rotations.shape == (120, body.num_bones, 3) and m.translation.shape == (120, 3)
    assert torch.isfinite(m.rotations).all() and torch.isfinite(m.translation).all()
    assert m.rotations[0].abs().max() < 1e-12 and m.translation[0].abs().max() < 1e-12
    dofs = motion_dofs(name, body, 120)
    assert len(dofs) >= 3
    for dof, angle in dofs.items():
        lo, hi = _limit(dof)
        assert angle.min() >= lo - 1e-12 and angle.max() <= hi + 1e-12, dof


@pytest.mark.parametrize("name", MOTIONS)
def test_smooth_bounded_accelerations(motions, name):
    m = motions[name]
    R = axis_angle_to_matrix(m.rotations)
    # second differences of the local rotation matrices (Frobenius, rad/s^2) and of the root
    acc = ((R[2:] - 2 * R[1:-1] + R[:-2]).flatten(2).norm(dim=-1) * FPS**2).max()
    assert float(acc) < 200.0  # a 0.25 rad jump in one frame alone gives > 300
    tacc = ((m.translation[2:] - 2 * m.translation[1:-1] + m.translation[:-2]).norm(dim=-1)
            * FPS**2).max()
    assert float(tacc) < 10.0  # m/s^2
    # and the DOF angle curves themselves
    for angle in motion_dofs(name, _BODY[0], 120).values():
        assert np.abs(np.diff(angle, 2)).max() * FPS**2 < 100.0  # a 0.12 rad jump: 108


_BODY = [AnnyBody.load(dtype=torch.float64)]


def test_seeded_reproducible(body):
    a = generate("random", body, frames=40, seed=3)
    b = generate("random", body, frames=40, seed=3)
    c = generate("random", body, frames=40, seed=4)
    assert torch.equal(a.rotations, b.rotations) and torch.equal(a.translation, b.translation)
    assert not torch.allclose(a.rotations, c.rotations)
    assert torch.equal(generate("walk", body, 40, seed=1).rotations,
                       generate("walk", body, 40, seed=2).rotations)


def test_walk_moves_forward_and_turn_turns(body, motions):
    walk = motions["walk"]
    v = walk.velocity[45:]
    # the body faces -y: the walk advances along -y at ~1.1 m/s
    assert torch.allclose(v[:, 1].mean(), torch.tensor(-1.1, dtype=v.dtype), atol=0.05)
    assert v[:, 0].abs().max() < 1e-9
    turn = motions["turn"]
    yaw = turn.rotations[-1, 0]
    assert abs(float(yaw.norm()) - math.pi / 2) < 1e-6
    assert turn.duration == pytest.approx(119 / FPS)


def _groups(body):
    dom = [body.bone_names[i] for i in body.skin_indices[:, 0].tolist()]
    arm = np.array([n.startswith(("lowerarm", "wrist", "finger", "metacarpal")) for n in dom])
    torso = np.array([n.startswith(("root", "pelvis", "spine", "clavicle", "neck", "upperleg"))
                      for n in dom])
    shin_l = np.array([n.startswith(("lowerleg", "foot")) and n.endswith(".L") for n in dom])
    shin_r = np.array([n.startswith(("lowerleg", "foot")) and n.endswith(".R") for n in dom])
    return (arm, torso), (shin_l, shin_r)


def _penetration(V, normals, a, b, radius=0.03):
    """Deepest vertex of group a behind the surface of group b (local test near b, metres)."""
    Vb = V[b]
    d, i = cKDTree(Vb).query(V[a])
    depth = -((V[a] - Vb[i]) * normals[b][i]).sum(1)
    near = d < radius
    return float(depth[near].max()) if near.any() else 0.0


def _max_penetration(body, vertices):
    pairs = _groups(body)
    worst = 0.0
    for V in vertices:
        n = vertex_normals(V, body.faces).normals.numpy()
        V = V.numpy()
        for a, b in pairs:
            worst = max(worst, _penetration(V, n, a, b), _penetration(V, n, b, a))
    return worst


@pytest.mark.parametrize("name", MOTIONS)
def test_limbs_do_not_pass_through_the_body(body, motions, name):
    m = motions[name]
    out = body.pose(None, m.rotations[::8], m.translation[::8])
    assert _max_penetration(body, out.vertices) < 0.005  # metres


def test_penetration_check_detects_an_arm_through_the_torso(body):
    # the check above can fail: swing the left forearm into the belly
    rot = torch.zeros(body.num_bones, 3, dtype=torch.float64)
    rot[body.bone_names.index("upperarm01.L"), 1] = 0.9  # lower the arm to the side
    rot[body.bone_names.index("lowerarm01.L")] = torch.tensor([0.0, 0.0, -1.9],
                                                               dtype=torch.float64)
    out = body.pose(None, rot)
    assert _max_penetration(body, out.vertices) > 0.02


def test_bad_arguments(body):
    with pytest.raises(ValueError, match="name"):
        generate("moonwalk", body)
    with pytest.raises(ValueError, match="frames"):
        generate("walk", body, frames=0)
    with pytest.raises(ValueError, match="fps"):
        generate("walk", body, fps=-1.0)

    class NoRig:
        bone_names = ("a", "b")

    with pytest.raises(ValueError, match="rig"):
        generate("walk", NoRig())
