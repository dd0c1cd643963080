import math

import numpy as np
import pytest
import torch

from polygeo import frames


def _rand_quat(gen, n):
    q = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    return q / q.norm(dim=-1, keepdim=True)


def _is_rotation(R, tol=1e-12):
    eye = torch.eye(3, dtype=R.dtype).expand_as(R)
    return bool(((R.transpose(-1, -2) @ R - eye).abs().max() < tol)
                and ((torch.linalg.det(R) - 1).abs().max() < tol))


# ---------------------------------------------------------------- quaternions


def test_quaternion_roundtrip_and_double_cover(gen):
    q = _rand_quat(gen, 200)
    R = frames.quaternion_to_matrix(q)
    assert _is_rotation(R)
    torch.testing.assert_close(frames.quaternion_to_matrix(-q), R)
    back = frames.matrix_to_quaternion(R)
    assert (back[:, 0] >= 0).all()
    canon = torch.where(q[:, :1] < 0, -q, q)
    torch.testing.assert_close(back, canon, rtol=0, atol=1e-12)
    torch.testing.assert_close(back.norm(dim=-1), torch.ones(200, dtype=torch.float64))


def test_matrix_to_quaternion_near_pi_and_identity():
    # rotations by ~pi about each axis (trace ~ -1, where the naive formula breaks down)
    aa = torch.tensor([[math.pi, 0, 0], [0, math.pi - 1e-9, 0], [0, 0, -math.pi],
                       [1e-12, 0, 0], [0, 0, 0]], dtype=torch.float64)
    R = frames.axis_angle_to_matrix(aa)
    q = frames.matrix_to_quaternion(R)
    torch.testing.assert_close(frames.quaternion_to_matrix(q), R, rtol=0, atol=1e-12)
    assert (q[:, 0] >= 0).all()
    # w == 0: first non-zero vector component positive
    assert q[2, 3] > 0 and q[0, 1] > 0


def test_quaternion_multiply_matches_matrix_product(gen):
    a, b = _rand_quat(gen, 50), _rand_quat(gen, 50)
    Rab = frames.quaternion_to_matrix(frames.quaternion_multiply(a, b))
    torch.testing.assert_close(Rab, frames.quaternion_to_matrix(a) @ frames.quaternion_to_matrix(b))
    ident = frames.quaternion_multiply(a, frames.quaternion_conjugate(a))
    torch.testing.assert_close(ident, torch.tensor([1.0, 0, 0, 0]).double().expand(50, 4))


def test_quaternion_apply_matches_matrix(gen):
    q = _rand_quat(gen, 30)
    v = torch.randn(30, 3, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(frames.quaternion_apply(q, v),
                               (frames.quaternion_to_matrix(q) @ v[..., None])[..., 0])


def test_axis_angle_matches_quaternion(gen):
    axis = torch.randn(40, 3, generator=gen, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    ang = torch.rand(40, generator=gen, dtype=torch.float64) * 3
    ang[:3] = torch.tensor([0.0, 1e-7, 1e-3], dtype=torch.float64)
    q = torch.cat([torch.cos(ang / 2)[:, None], torch.sin(ang / 2)[:, None] * axis], -1)
    torch.testing.assert_close(frames.axis_angle_to_matrix(axis * ang[:, None]),
                               frames.quaternion_to_matrix(q), rtol=0, atol=1e-13)


def test_random_rotation_is_reproducible_and_uniform():
    R1 = frames.random_rotation(2000, torch.Generator().manual_seed(3))
    R2 = frames.random_rotation(2000, torch.Generator().manual_seed(3))
    assert torch.equal(R1, R2) and _is_rotation(R1)
    # Haar measure: E[R] = 0 and E[trace R] = 0, std of a matrix entry = 1/sqrt(3)
    assert R1.mean(0).abs().max() < 0.06
    assert abs(float(R1.diagonal(dim1=-2, dim2=-1).sum(-1).mean())) < 0.1
    assert abs(float(R1[:, 0, 0].std()) - 1 / math.sqrt(3)) < 0.03


def test_gradcheck_quaternion_conversions(gen):
    q = _rand_quat(gen, 4).requires_grad_(True)
    assert torch.autograd.gradcheck(frames.quaternion_to_matrix, (q,))
    aa = (torch.randn(4, 3, generator=gen, dtype=torch.float64)).requires_grad_(True)
    assert torch.autograd.gradcheck(frames.axis_angle_to_matrix, (aa,))
    small = (1e-6 * torch.randn(2, 3, generator=gen, dtype=torch.float64)).requires_grad_(True)
    assert torch.autograd.gradcheck(frames.axis_angle_to_matrix, (small,))

    # matrix_to_quaternion on a rotation parametrised by axis-angle, covering all four branches
    aa2 = torch.tensor([[0.3, -0.2, 0.1], [3.0, 0.1, 0.0], [0.0, 3.0, 0.1], [0.1, 0.0, 3.0]],
                       dtype=torch.float64, requires_grad=True)

    def f(a):
        return frames.matrix_to_quaternion(frames.axis_angle_to_matrix(a))

    assert torch.autograd.gradcheck(f, (aa2,))


def test_quaternion_validators():
    with pytest.raises(ValueError, match="q"):
        frames.quaternion_to_matrix(torch.zeros(2, 4))
    with pytest.raises(ValueError, match="q"):
        frames.quaternion_to_matrix(torch.ones(2, 3))
    with pytest.raises(ValueError, match="R"):
        frames.matrix_to_quaternion(torch.eye(4))
    with pytest.raises(ValueError, match="n"):
        frames.random_rotation(-1)
    with pytest.raises(ValueError, match="axis_angle"):
        frames.axis_angle_to_matrix(torch.zeros(2, 4))
    with pytest.raises(ValueError, match="v"):
        frames.quaternion_apply(torch.ones(4), torch.ones(2))


# ---------------------------------------------------------------- orientation


def _orientation(gen, B):
    return frames.Orientation(
        torch.rand(B, generator=gen, dtype=torch.float64) + 0.5,
        frames.random_rotation(B, gen),
        torch.randn(B, 3, generator=gen, dtype=torch.float64),
    )


def test_orientation_identities(gen):
    o, p = _orientation(gen, 5), _orientation(gen, 5)
    x = torch.randn(5, 7, 3, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(o.inverse_apply(o.apply(x)), x)
    torch.testing.assert_close(o.invert().apply(x), o.inverse_apply(x))
    torch.testing.assert_close(o.compose(p).apply(x), o.apply(p.apply(x)))
    torch.testing.assert_close(o.compose(o.invert()).apply(x), x)
    ident = frames.Orientation.identity(5)
    torch.testing.assert_close(ident.apply(x), x)
    torch.testing.assert_close(o.compose(ident).apply(x), o.apply(x))
    # vectors: rotation only, and differences of points transform like vectors times s
    torch.testing.assert_close(o.apply(x)[:, 1:] - o.apply(x)[:, :1],
                               o.s[:, None, None] * o.apply_vectors(x[:, 1:] - x[:, :1]))
    # batch indexing and dtype
    one = o[2]
    assert len(one) == 1 and len(o[1:4]) == 3
    torch.testing.assert_close(one.apply(x[2:3]), o.apply(x)[2:3])
    assert o.to(torch.float32).R.dtype == torch.float32


def test_orientation_create_validates():
    with pytest.raises(ValueError, match="s"):
        frames.Orientation.create(torch.tensor([1.0, -1.0]), torch.eye(3).expand(2, 3, 3),
                                  torch.zeros(2, 3))
    with pytest.raises(ValueError, match="R"):
        frames.Orientation.create(torch.ones(2), torch.eye(3).expand(3, 3, 3), torch.zeros(2, 3))
    with pytest.raises(ValueError, match="x"):
        frames.Orientation.identity(2).apply(torch.zeros(3, 4, 3))
    o = frames.Orientation.create(np.ones(2), np.eye(3)[None].repeat(2, 0), np.zeros((2, 3)))
    assert o.R.dtype == torch.float64


# ---------------------------------------------------------------- PCA frames


@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_pca_frame_of_tilted_plane_recovers_normal(gen, backend):
    B, K = 20, 40
    R = frames.random_rotation(B, gen)
    uv = torch.randn(B, K, 2, generator=gen, dtype=torch.float64) * torch.tensor([2.0, 1.0])
    local = torch.cat([uv, torch.zeros(B, K, 1, dtype=torch.float64)], -1)
    offset = 1e6 * torch.randn(B, 1, 3, generator=gen, dtype=torch.float64)
    pts = local @ R.transpose(-1, -2) + offset
    f = frames.pca_frames(pts, backend=backend)
    n_true = R[..., 2]
    cosang = (f.rotation[..., 2] * n_true).sum(-1).abs()
    assert (1 - cosang).max() < 1e-12
    assert _is_rotation(f.rotation)
    assert f.eigenvalues[:, 2].abs().max() < 1e-12 * f.eigenvalues[:, 0].max() + 1e-6
    assert (f.eigenvalues[:, 0] >= f.eigenvalues[:, 1]).all()
    # sign convention: largest component of e1 and e3 positive
    for axis in (0, 2):
        e = f.rotation[..., axis]
        assert (e.gather(-1, e.abs().argmax(-1, keepdim=True)) > 0).all()
    torch.testing.assert_close(f.centroid, pts.mean(1))


@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_pca_frame_reference_normal_and_center(gen, backend):
    pts = torch.randn(3, 10, 3, generator=gen, dtype=torch.float64) * torch.tensor([1, 1, 0.01])
    ref = torch.tensor([[0, 0, -1.0], [0, 0, 1.0], [0, 0, -1.0]], dtype=torch.float64)
    f = frames.pca_frames(pts, reference_normal=ref, backend=backend)
    assert ((f.rotation[..., 2] * ref).sum(-1) > 0).all()
    assert _is_rotation(f.rotation)
    c = torch.zeros(3, 3, dtype=torch.float64)
    g = frames.pca_frames(pts, center=c, backend=backend)
    torch.testing.assert_close(g.centroid, c)


@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_pca_frame_mask_weights_and_degenerate(gen, backend):
    pts = torch.randn(4, 12, 3, generator=gen, dtype=torch.float64)
    mask = torch.ones(4, 12, dtype=torch.bool)
    mask[0, 6:] = False
    pts_nan = pts.clone()
    pts_nan[1, 3] = float("nan")
    mask[1, 3] = False
    a = frames.pca_frames(pts_nan, mask=mask, backend=backend)
    for b, k in ((0, slice(0, 6)), (1, [i for i in range(12) if i != 3])):
        one = frames.pca_frames(pts[b : b + 1, k], backend=backend)
        torch.testing.assert_close(a.rotation[b], one.rotation[0])
        torch.testing.assert_close(a.eigenvalues[b], one.eigenvalues[0])
    # integer weights == duplicated points
    w = torch.randint(1, 4, (12,), generator=gen)
    wf = frames.pca_frames(pts[2:3], weights=w[None].double(), backend=backend)
    dup = frames.pca_frames(pts[2:3, torch.repeat_interleave(torch.arange(12), w)])
    torch.testing.assert_close(wf.rotation, dup.rotation)
    # degenerate: all points equal, and nothing valid -> identity frame, zero eigenvalues
    same = torch.ones(2, 5, 3, dtype=torch.float64)
    d = frames.pca_frames(same, mask=torch.tensor([[True] * 5, [False] * 5]), backend=backend)
    torch.testing.assert_close(d.rotation, torch.eye(3, dtype=torch.float64).expand(2, 3, 3))
    assert (d.eigenvalues == 0).all() and d.count.tolist() == [5, 0]
    # collinear: e1 along the line
    line = torch.linspace(-1, 1, 7, dtype=torch.float64)[:, None] * torch.tensor([1.0, 2, 2]) / 3
    c = frames.pca_frames(line[None], backend=backend)
    torch.testing.assert_close(c.rotation[0, :, 0], torch.tensor([1.0, 2, 2]).double() / 3)
    assert _is_rotation(c.rotation)


def test_pca_frames_numpy_and_batched(rng):
    pts = rng.normal(size=(5, 9, 3))
    f = frames.pca_frames(pts)
    assert isinstance(f.rotation, np.ndarray)
    for b in range(5):
        one = frames.pca_frames(pts[b : b + 1])
        np.testing.assert_allclose(f.rotation[b], one.rotation[0], atol=1e-12)


def test_pca_backends_agree(gen):
    B, K = 200, 15
    pts = torch.randn(B, K, 3, generator=gen, dtype=torch.float64) * torch.tensor([3.0, 1.0, 0.2])
    pts = pts @ frames.random_rotation(B, gen).transpose(-1, -2) + 100.0
    mask = torch.rand(B, K, generator=gen) > 0.3
    w = torch.rand(B, K, generator=gen, dtype=torch.float64)
    ref = torch.randn(B, 3, generator=gen, dtype=torch.float64)
    ctr = pts[:, 0]
    pts[0] = 1.0  # degenerate item
    for kw in ({}, {"mask": mask}, {"weights": w, "reference_normal": ref}, {"center": ctr}):
        a = frames.pca_frames(pts, backend="torch", **kw)
        b = frames.pca_frames(pts, backend="numba", **kw)
        torch.testing.assert_close(a.rotation, b.rotation, rtol=0, atol=1e-9)
        torch.testing.assert_close(a.eigenvalues, b.eigenvalues, rtol=1e-9, atol=1e-12)
        torch.testing.assert_close(a.centroid, b.centroid)
        assert torch.equal(a.count, b.count)
    f32 = frames.pca_frames(pts.float(), backend="numba")
    assert f32.rotation.dtype == torch.float32
    # auto picks the differentiable path when needed
    g = frames.pca_frames(pts[:3].clone().requires_grad_(True))
    assert g.rotation.requires_grad


def test_gradcheck_pca_frames(gen):
    pts = (torch.randn(2, 8, 3, generator=gen, dtype=torch.float64)
           * torch.tensor([2.0, 1.0, 0.3])).requires_grad_(True)

    def f(p):
        fr = frames.pca_frames(p, backend="torch")
        return fr.rotation, fr.eigenvalues, fr.centroid

    assert torch.autograd.gradcheck(f, (pts,))


def test_pca_frames_validators():
    with pytest.raises(ValueError, match="points"):
        frames.pca_frames(torch.zeros(2, 5, 2))
    with pytest.raises(TypeError, match="mask"):
        frames.pca_frames(torch.zeros(2, 5, 3), mask=torch.ones(2, 5))
    with pytest.raises(ValueError, match="weights"):
        frames.pca_frames(torch.zeros(2, 5, 3), weights=-torch.ones(2, 5))
    with pytest.raises(ValueError, match="center"):
        frames.pca_frames(torch.zeros(2, 5, 3), center=torch.zeros(3))
    with pytest.raises(ValueError, match="backend"):
        frames.pca_frames(torch.zeros(2, 5, 3), backend="gpu")


# ---------------------------------------------------------------- axis-angle, rigid alignment


def test_matrix_to_axis_angle_inverts_rodrigues(gen):
    axis = torch.randn(300, 3, generator=gen, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    # angles over (0, pi), with the small-angle branch and the identity
    ang = torch.cat([torch.rand(296, generator=gen, dtype=torch.float64) * (math.pi - 1e-6),
                     torch.tensor([1e-9, 1e-14, 0.0, math.pi - 1e-6], dtype=torch.float64)])
    aa = axis * ang[:, None]
    back = frames.matrix_to_axis_angle(frames.axis_angle_to_matrix(aa))
    torch.testing.assert_close(back, aa, rtol=0, atol=1e-9)
    # an angle above pi comes back as the same rotation the other way round
    big = torch.tensor([[0.0, 0.0, 1.5 * math.pi]], dtype=torch.float64)
    torch.testing.assert_close(frames.matrix_to_axis_angle(frames.axis_angle_to_matrix(big)),
                               torch.tensor([[0.0, 0.0, -0.5 * math.pi]], dtype=torch.float64))
    with pytest.raises(ValueError, match="R"):
        frames.matrix_to_axis_angle(torch.eye(4))


def test_rigid_align_recovers_a_rigid_motion(gen):
    R = frames.random_rotation(6, gen, dtype=torch.float64)
    t = torch.randn(6, 3, generator=gen, dtype=torch.float64)
    p = torch.randn(6, 40, 3, generator=gen, dtype=torch.float64)
    q = p @ R.transpose(-1, -2) + t[:, None]
    R2, t2 = frames.rigid_align(p, q)
    torch.testing.assert_close(R2, R, rtol=0, atol=1e-12)
    torch.testing.assert_close(t2, t, rtol=0, atol=1e-12)
    # with noise the residual is no larger than that of the true motion (it is the optimum),
    # and a reflected target still gets a rotation
    qn = q + 0.05 * torch.randn(q.shape, generator=gen, dtype=torch.float64)
    R3, t3 = frames.rigid_align(p, qn)
    res = ((p @ R3.transpose(-1, -2) + t3[:, None] - qn) ** 2).sum((-1, -2))
    res_true = ((q - qn) ** 2).sum((-1, -2))
    assert bool((res <= res_true + 1e-12).all())
    R4, _ = frames.rigid_align(p[0], p[0] * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64))
    assert _is_rotation(R4)
    # weights: points of zero weight do not matter
    w = torch.ones(40, dtype=torch.float64)
    w[:10] = 0
    bad = q[0].clone()
    bad[:10] += 5.0
    R5, t5 = frames.rigid_align(p[0], bad, w)
    torch.testing.assert_close(R5, R[0], rtol=0, atol=1e-12)
    # degenerate but answerable: one point (translation), collinear points (a rotation)
    R6, t6 = frames.rigid_align(p[0, :1], q[0, :1])
    torch.testing.assert_close(p[0, :1] @ R6.T + t6, q[0, :1], rtol=0, atol=1e-12)
    line = torch.linspace(0, 1, 5, dtype=torch.float64)[:, None] * torch.tensor([1.0, 2, 3])
    R7, t7 = frames.rigid_align(line, line @ R[0].T)
    assert _is_rotation(R7)
    torch.testing.assert_close(line @ R7.T + t7, line @ R[0].T, rtol=0, atol=1e-12)


def test_rigid_align_validation():
    p = torch.zeros(5, 3)
    with pytest.raises(ValueError, match="target"):
        frames.rigid_align(p, torch.zeros(4, 3))
    with pytest.raises(ValueError, match="weights"):
        frames.rigid_align(p, p, torch.zeros(5))
    with pytest.raises(ValueError, match="weights"):
        frames.rigid_align(p, p, -torch.ones(5))
    with pytest.raises(ValueError, match="source"):
        frames.rigid_align(torch.zeros(5, 2), torch.zeros(5, 2))
