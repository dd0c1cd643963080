import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial.transform import Rotation

from polygeo import covariance as cv
from polygeo import neighbors as nb


@pytest.fixture
def ring_mesh():
    m = trimesh.creation.icosphere(subdivisions=2)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    r = nb.mesh_k_ring(f, len(v), 1)
    return v, r.index, r.mask


def test_covariance_matches_numpy_cov(ring_mesh):
    v, idx, mask = ring_mesh
    c = cv.vertex_covariance(v, idx, mask)
    for i in (0, 5, 100):
        pts = v[idx[i][mask[i]]]
        np.testing.assert_allclose(c[i], np.cov(pts.T, bias=True), atol=1e-15)


def test_singular_values_match_svd(ring_mesh):
    v, idx, mask = ring_mesh
    c = cv.vertex_covariance(v, idx, mask)
    s = cv.singular_values(c)
    np.testing.assert_allclose(s, np.linalg.svd(c, compute_uv=False), atol=1e-15)
    assert (np.diff(s, axis=1) <= 0).all()


def test_residual_zero_under_rigid_motion_positive_under_stretch(ring_mesh):
    v, idx, mask = ring_mesh
    s = cv.singular_values(cv.vertex_covariance(v, idx, mask))
    rot = Rotation.random(random_state=1).as_matrix()
    moved = v @ rot.T + np.array([3.0, -1.0, 2.0])
    res = cv.inextensibility_residual(cv.vertex_covariance(moved, idx, mask), s, reduction="none")
    scale = np.abs(s).max() ** 3
    assert np.abs(res).max() < 1e-10 * scale
    stretched = v * 1.1
    c_st = cv.vertex_covariance(stretched, idx, mask)
    assert cv.inextensibility_residual(c_st, s) > 1e-3 * scale * len(v)
    # a uniform stretch by a scales C by a^2: extension = a^2 makes it admissible again
    np.testing.assert_allclose(
        cv.inextensibility_residual(c_st, s, extension=1.21, reduction="none"),
        0,
        atol=1e-10 * scale,
    )


def test_residual_equals_product_of_eigenvalue_gaps(rng):
    a = rng.normal(size=(7, 3, 3))
    c = a @ a.transpose(0, 2, 1)
    sig = rng.random((7, 3))
    k = 1.3
    lam = np.linalg.eigvalsh(c)
    want = np.abs(np.prod(lam[:, None, :] - k * sig[:, :, None], axis=-1)).sum(1) * 2.0
    got = cv.inextensibility_residual(c, sig, k, weight=2.0, reduction="none")
    np.testing.assert_allclose(got, want, rtol=1e-10)
    assert cv.inextensibility_residual(c, sig, k, weight=2.0) == pytest.approx(want.sum())


def test_batched_points_and_per_vertex_extension(ring_mesh, rng):
    v, idx, mask = ring_mesh
    vb = np.stack([v, 1.05 * v])
    c = cv.vertex_covariance(vb, idx, mask)
    for i in range(2):
        np.testing.assert_allclose(c[i], cv.vertex_covariance(vb[i], idx, mask))
    s = cv.singular_values(c[0])
    k = rng.uniform(1, 1.2, size=(2, len(v)))
    res = cv.inextensibility_residual(c, s, k, reduction="none")
    for i in range(2):
        np.testing.assert_allclose(
            res[i], cv.inextensibility_residual(c[i], s, k[i], reduction="none")
        )


def test_empty_neighbourhood_gives_zero():
    v = np.arange(9, dtype=float).reshape(3, 3)
    idx = np.array([[0, 1], [-1, -1], [2, -1]])
    c = cv.vertex_covariance(v, idx)
    assert np.isfinite(c).all() and (c[1] == 0).all() and (c[2] == 0).all()


def test_gradcheck_points_to_residual(gen):
    x = torch.rand(8, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    idx = torch.tensor([[(i + j) % 8 for j in range(4)] for i in range(8)])
    s = cv.singular_values(cv.vertex_covariance(x.detach() * 0.9, idx))

    def f(p):
        return cv.inextensibility_residual(cv.vertex_covariance(p, idx), s, 1.0, reduction="none")

    torch.autograd.gradcheck(f, (x,))
    torch.autograd.gradcheck(lambda p: cv.singular_values(cv.vertex_covariance(p, idx)), (x,))


def test_closed_form_backward_equals_autograd_of_the_formula(ring_mesh, gen):
    # The covariance's hand-written backward against autograd through eq. (31) written out,
    # on a batch with padded (masked) neighbourhoods, first and second derivatives.
    v, idx, mask = ring_mesh
    idx = torch.as_tensor(np.where(mask, idx, -1))
    x = torch.as_tensor(v)[None].repeat(2, 1, 1) + 0.05 * torch.rand(2, len(v), 3, generator=gen,
                                                                      dtype=torch.float64)
    g = torch.rand(2, len(v), 3, 3, generator=gen, dtype=torch.float64)
    a = x.clone().requires_grad_(True)
    (cv.vertex_covariance(a, idx) * g).sum().backward()
    b = x.clone().requires_grad_(True)
    m = (idx >= 0).to(b.dtype)[..., None]
    nbrs = b[..., idx.clamp_min(0), :]
    mean = (nbrs * m).sum(-2) / m.sum(-2)
    d = (nbrs - mean[..., None, :]) * m
    ((d.transpose(-1, -2) @ d / m.sum(-2)[..., None]) * g).sum().backward()
    torch.testing.assert_close(a.grad, b.grad, rtol=1e-10, atol=1e-12)
    # Hessian-vector product of a non-linear function of the covariances: against the formula's
    def hvp(cov_fn):
        c = x.clone().requires_grad_(True)
        (grad,) = torch.autograd.grad((cov_fn(c) * g).square().sum(), c, create_graph=True)
        (h,) = torch.autograd.grad((grad * g[..., 0]).sum(), c)
        return h

    def formula(p):
        nbrs = p[..., idx.clamp_min(0), :]
        d = (nbrs - ((nbrs * m).sum(-2) / m.sum(-2))[..., None, :]) * m
        return d.transpose(-1, -2) @ d / m.sum(-2)[..., None]

    torch.testing.assert_close(hvp(lambda p: cv.vertex_covariance(p, idx)), hvp(formula),
                               rtol=1e-10, atol=1e-12)


def test_gradgradcheck_covariance(ring_mesh, gen):
    v, idx, _ = ring_mesh
    x = torch.as_tensor(v)[:12].clone() + 0.05 * torch.rand(12, 3, generator=gen,
                                                             dtype=torch.float64)
    idx = torch.as_tensor(idx)[:12].clamp(max=11)
    x.requires_grad_(True)
    torch.autograd.gradgradcheck(lambda p: cv.vertex_covariance(p, idx), (x,))


def test_torch_in_torch_out(ring_mesh):
    v, idx, mask = ring_mesh
    c = cv.vertex_covariance(torch.from_numpy(v).float(), torch.from_numpy(idx))
    assert isinstance(c, torch.Tensor) and c.dtype == torch.float32


@pytest.mark.parametrize(
    "call, exc",
    [
        (lambda: cv.vertex_covariance(np.zeros((3, 2)), np.zeros((3, 2), int)), ValueError),
        (lambda: cv.vertex_covariance(np.zeros((3, 3)), np.zeros((2, 2), int)), ValueError),
        (lambda: cv.vertex_covariance(np.zeros((3, 3)), np.full((3, 2), 3)), ValueError),
        (lambda: cv.vertex_covariance(np.zeros((3, 3)), np.zeros((3, 2))), TypeError),
        (lambda: cv.vertex_covariance(np.full((3, 3), np.nan), np.zeros((3, 2), int)), ValueError),
        (
            lambda: cv.vertex_covariance(np.zeros((3, 3)), np.zeros((3, 2), int), np.ones((3, 2))),
            TypeError,
        ),
        (lambda: cv.singular_values(np.zeros((3, 2, 2))), ValueError),
        (lambda: cv.inextensibility_residual(np.zeros((4, 3, 3)), np.zeros((5, 3))), ValueError),
        (
            lambda: cv.inextensibility_residual(np.zeros((4, 3, 3)), np.zeros((4, 3)), -1.0),
            ValueError,
        ),
        (
            lambda: cv.inextensibility_residual(np.zeros((4, 3, 3)), np.zeros((4, 3)), np.ones(3)),
            ValueError,
        ),
        (
            lambda: cv.inextensibility_residual(
                np.zeros((4, 3, 3)), np.zeros((4, 3)), reduction="mean"
            ),
            ValueError,
        ),
    ],
)
def test_validators(call, exc):
    with pytest.raises(exc):
        call()


@pytest.mark.parametrize("extension", [-1.0, np.ones(3), np.nan])
def test_extension_validation_names_the_argument(extension):
    with pytest.raises(ValueError, match="extension"):
        cv.inextensibility_residual(np.zeros((4, 3, 3)), np.zeros((4, 3)), extension=extension)
