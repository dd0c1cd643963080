import numpy as np
import pytest
import torch

from draping.body import BodyModel
from draping.motion import generate, read_amass
from draping.smpl import SMPLBody, smpl_joint_names

PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21]


def _synthetic_smpl(path, seed=0, posedirs=True, V=120, S=12):
    """A tiny file with the official SMPL .npz layout (random but well-formed numbers)."""
    rng = np.random.default_rng(seed)
    J = 24
    # a skeleton roughly like SMPL's (y up) and vertices scattered around its joints
    joints = np.zeros((J, 3))
    for j in range(1, J):
        joints[j] = joints[PARENTS[j]] + rng.normal(scale=0.1, size=3)
    near = rng.integers(0, J, V)
    v = joints[near] + rng.normal(scale=0.03, size=(V, 3))
    w = np.zeros((V, J))
    w[np.arange(V), near] = rng.uniform(0.5, 1.0, V)
    w[np.arange(V), np.array(PARENTS)[near].clip(0)] += rng.uniform(0.0, 0.5, V)
    w /= w.sum(1, keepdims=True)
    jr = rng.uniform(size=(J, V)) * (near[None] == np.arange(J)[:, None])
    jr[jr.sum(1) == 0, 0] = 1.0
    jr /= jr.sum(1, keepdims=True)
    kt = np.stack([np.array(PARENTS) % (2**32), np.arange(J)]).astype(np.int64)
    d = dict(v_template=v, f=rng.integers(0, V, (200, 3)), shapedirs=rng.normal(
        scale=0.01, size=(V, 3, S)), J_regressor=jr, weights=w, kintree_table=kt)
    if posedirs:
        d["posedirs"] = rng.normal(scale=0.01, size=(V, 3, 9 * (J - 1)))
    np.savez(path, **d)
    return d


def _rodrigues(r):
    th = np.linalg.norm(r)
    if th < 1e-12:
        return np.eye(3)
    k = r / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


def _reference_smpl(d, betas, pose, trans):
    """Textbook SMPL forward pass (numpy, one body) as the independent reference."""
    S = len(betas)
    v = d["v_template"] + d["shapedirs"][:, :, :S] @ betas
    J = d["J_regressor"] @ v
    R = np.stack([_rodrigues(p) for p in pose])
    if "posedirs" in d:
        v = v + d["posedirs"] @ (R[1:] - np.eye(3)).reshape(-1)
    G = np.zeros((24, 4, 4))
    for j in range(24):
        M = np.eye(4)
        M[:3, :3] = R[j]
        M[:3, 3] = J[j] - (J[PARENTS[j]] if j else 0)
        G[j] = M if j == 0 else G[PARENTS[j]] @ M
    A = G.copy()
    A[:, :3, 3] -= np.einsum("jab,jb->ja", G[:, :3, :3], J)
    T = np.einsum("vj,jab->vab", d["weights"], A)
    return np.einsum("vab,vb->va", T[:, :3, :3], v) + T[:, :3, 3] + trans


@pytest.mark.parametrize("posedirs", [True, False])
def test_smpl_matches_reference(tmp_path, posedirs):
    d = _synthetic_smpl(tmp_path / "smpl.npz", posedirs=posedirs)
    body = SMPLBody.load(tmp_path / "smpl.npz", num_betas=10, dtype=torch.float64)
    assert isinstance(body, BodyModel)
    assert body.bone_names == smpl_joint_names(24) and body.parents[0] == -1
    g = np.random.default_rng(1)
    betas = g.normal(size=(2, 10))
    pose = 0.4 * g.normal(size=(2, 24, 3))
    trans = g.normal(size=(2, 3))
    out = body.pose(torch.as_tensor(betas), torch.as_tensor(pose), torch.as_tensor(trans))
    for b in range(2):
        ref = _reference_smpl(d, betas[b], pose[b], trans[b])
        assert np.allclose(out.vertices[b].numpy(), ref, atol=1e-10)
    # zero pose: the shaped template
    rest_v, _ = body.rest(torch.as_tensor(betas[:1]))
    assert torch.allclose(body.pose(torch.as_tensor(betas[:1])).vertices, rest_v)


def test_smpl_bad_files(tmp_path):
    np.savez(tmp_path / "x.npz", v_template=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="missing"):
        SMPLBody.load(tmp_path / "x.npz")
    d = _synthetic_smpl(tmp_path / "s.npz")
    d["weights"] = d["weights"][:, :5]
    np.savez(tmp_path / "bad.npz", **d)
    with pytest.raises(ValueError, match="weights"):
        SMPLBody.load(tmp_path / "bad.npz")
    with pytest.raises(ValueError, match="num_betas"):
        SMPLBody.load(tmp_path / "s.npz", num_betas=99)
    np.savez(tmp_path / "obj.npz", **{**d, "J_regressor": np.array([{"a": 1}], dtype=object)})
    with pytest.raises(ValueError, match="pickled"):
        SMPLBody.load(tmp_path / "obj.npz")


def test_amass_reader_and_posing(tmp_path):
    _synthetic_smpl(tmp_path / "smpl.npz")
    body = SMPLBody.load(tmp_path / "smpl.npz", dtype=torch.float64)
    rng = np.random.default_rng(2)
    T = 7
    poses = 0.2 * rng.normal(size=(T, 156))
    trans = np.cumsum(rng.normal(scale=0.01, size=(T, 3)), 0)
    np.savez(tmp_path / "seq.npz", poses=poses, trans=trans, betas=rng.normal(size=16),
             mocap_framerate=np.array(60.0))
    m = read_amass(tmp_path / "seq.npz", n_joints=24, dtype=torch.float64)
    assert m.fps == 60.0 and len(m) == T and m.rotations.shape == (T, 24, 3)
    assert torch.allclose(m.rotations[:, :22].reshape(T, -1), torch.as_tensor(poses[:, :66]))
    assert (m.rotations[:, 22:] == 0).all()
    assert m.shape.shape == (16,) and m.bone_names == body.bone_names
    assert torch.allclose(m.velocity[1:-1], torch.as_tensor((trans[2:] - trans[:-2]) * 30.0))
    out = body.pose(m.shape[:10], m.rotations, m.translation)
    assert out.vertices.shape == (T, 120, 3) and torch.isfinite(out.vertices).all()
    m55 = read_amass(tmp_path / "seq.npz", n_joints=55)
    assert m55.rotations.shape == (T, 55, 3) and (m55.rotations[:, 52:] == 0).all()
    np.savez(tmp_path / "bad.npz", poses=poses, trans=trans[:-1])
    with pytest.raises(ValueError, match="trans"):
        read_amass(tmp_path / "bad.npz")
    np.savez(tmp_path / "nan.npz", poses=poses * np.nan, trans=trans)
    with pytest.raises(ValueError, match="NaN"):
        read_amass(tmp_path / "nan.npz")
    np.savez(tmp_path / "nokey.npz", trans=trans)
    with pytest.raises(ValueError, match="poses"):
        read_amass(tmp_path / "nokey.npz")


def test_procedural_motion_runs_on_an_smpl_rig(tmp_path):
    _synthetic_smpl(tmp_path / "smpl.npz")
    body = SMPLBody.load(tmp_path / "smpl.npz", dtype=torch.float64)
    m = generate("walk", body, frames=20)
    assert m.rotations.shape == (20, 24, 3)
    out = body.pose(None, m.rotations, m.translation)
    assert torch.isfinite(out.vertices).all()
