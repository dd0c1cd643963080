import math

import numpy as np
import pytest
import torch

from polygeo.render import Camera


def _rot(axis, angle):
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def _random_camera(rng, batch=None):
    def one():
        f = rng.uniform(50, 200)
        K = np.array(
            [
                [f, rng.uniform(-1, 1), rng.uniform(20, 60)],
                [0, f * rng.uniform(0.8, 1.2), rng.uniform(20, 60)],
                [0, 0, 1],
            ]
        )
        return K, _rot(rng.normal(size=3), rng.uniform(0, 3)), rng.normal(size=3)

    if batch is None:
        K, R, t = one()
        return Camera(K=K, R=R, t=t, width=80, height=60)
    Ks, Rs, ts = zip(*[one() for _ in range(batch)])
    return Camera(K=np.stack(Ks), R=np.stack(Rs), t=np.stack(ts), width=80, height=60)


def test_project_matches_pinhole_formula(rng):
    cam = _random_camera(rng)
    X = rng.normal(size=(50, 3)) + np.array([0, 0, 8.0])
    uv, depth = cam.project(X)
    K, R, t = cam.K.numpy(), cam.R.numpy(), cam.t.numpy()
    for x, u, d in zip(X, uv, depth):
        xc = R @ x + t
        assert d == pytest.approx(xc[2], rel=1e-12)
        fx, s, cx, fy, cy = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]
        want = [fx * xc[0] / xc[2] + s * xc[1] / xc[2] + cx, fy * xc[1] / xc[2] + cy]
        np.testing.assert_allclose(u, want, rtol=1e-12, atol=1e-9)
    assert isinstance(uv, np.ndarray) and uv.shape == (50, 2) and depth.shape == (50,)


def test_opencv_axes_and_pixel_centres():
    # identity pose: x right -> larger column, y down -> larger row; the principal point
    # (cx, cy) = (W/2, H/2) is the corner shared by the four central pixels.
    cam = Camera(K=[[100.0, 0, 4.0], [0, 100.0, 3.0], [0, 0, 1]], width=8, height=6)
    uv, _ = cam.project(torch.tensor([[0.0, 0.0, 1.0], [0.01, 0.0, 1.0], [0.0, 0.01, 1.0]]))
    np.testing.assert_allclose(uv[0].numpy(), [4.0, 3.0])
    assert uv[1, 0] > uv[0, 0] and uv[1, 1] == uv[0, 1]
    assert uv[2, 1] > uv[0, 1] and uv[2, 0] == uv[0, 0]


def test_world_camera_roundtrip(rng):
    cam = _random_camera(rng)
    X = torch.from_numpy(rng.normal(size=(4, 7, 3)))
    back = cam.camera_to_world(cam.world_to_camera(X))
    torch.testing.assert_close(back, X, rtol=1e-12, atol=1e-12)


def test_look_at_geometry():
    eye = np.array([1.0, -2.0, -5.0])
    target = np.array([0.2, 0.3, 0.1])
    cam = Camera.look_at(eye, target, focal=120.0, width=64, height=48, up=(0.0, -1.0, 0.0))
    uv, z = cam.project(np.stack([target, target + np.array([0, -0.5, 0])]))
    np.testing.assert_allclose(uv[0], [32.0, 24.0], atol=1e-9)
    assert z[0] == pytest.approx(np.linalg.norm(target - eye))
    assert uv[1, 1] < uv[0, 1]  # world "up" appears higher in the image
    np.testing.assert_allclose(cam.world_to_camera(eye), [0, 0, 0], atol=1e-12)
    R = cam.R.numpy()
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_batched_camera_equals_per_item(rng):
    cams = _random_camera(rng, batch=3)
    assert cams.batch_size == 3 and len(cams) == 3
    X = torch.from_numpy(rng.normal(size=(3, 5, 3)) + np.array([0, 0, 6.0]))
    uv, z = cams.project(X)
    Xs = torch.from_numpy(rng.normal(size=(5, 3)) + np.array([0, 0, 6.0]))
    uv_shared, _ = cams.project(Xs)
    for b in range(3):
        u1, z1 = cams[b].project(X[b])
        torch.testing.assert_close(uv[b], u1)
        torch.testing.assert_close(z[b], z1)
        torch.testing.assert_close(uv_shared[b], cams[b].project(Xs)[0])


def test_project_gradcheck_pose():
    K = torch.tensor([[90.0, 0.5, 30.0], [0.0, 80.0, 20.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    X = torch.tensor([[0.1, -0.2, 4.0], [0.5, 0.3, 5.0]], dtype=torch.float64)

    def f(R, t):
        return Camera(K=K, R=R, t=t, width=60, height=40).project(X)[0]

    R = torch.from_numpy(_rot([1, 2, 3], 0.3)).requires_grad_(True)
    t = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(f, (R, t))


def test_points_behind_camera_project_finite():
    cam = Camera(K=np.diag([100.0, 100.0, 1.0]), width=10, height=10)
    uv, z = cam.project(np.array([[0.1, 0.1, 0.0], [0.1, 0.1, -1.0]]))
    assert np.isfinite(uv).all() and z[1] == -1.0


@pytest.mark.parametrize(
    "kwargs, exc",
    [
        (dict(K=np.eye(2)), ValueError),
        (dict(K=np.diag([1.0, 1.0, 0.0])), ValueError),
        (dict(K=[[1.0, 0, 0], [0, 1.0, 0], [0, 0, 2.0]]), ValueError),
        (dict(K=[[1.0, 0, 0], [0, 0.0, 0], [0, 0, 1.0]]), ValueError),
        (dict(K=np.diag([np.nan, 1.0, 1.0])), ValueError),
        (dict(t=[0.0, np.inf, 0.0]), ValueError),
        (dict(R=np.eye(4)), ValueError),
        (dict(t=np.zeros(2)), ValueError),
        (dict(width=0), ValueError),
        (dict(height=-3), ValueError),
        (dict(width=10.5), TypeError),
        (dict(K=np.stack([np.eye(3)] * 2), R=np.stack([np.eye(3)] * 3)), ValueError),
        (dict(K=[["a", "b", "c"]] * 3), TypeError),
    ],
)
def test_camera_validation(kwargs, exc):
    args = dict(K=np.diag([100.0, 100.0, 1.0]), R=np.eye(3), t=np.zeros(3), width=10, height=10)
    args.update(kwargs)
    with pytest.raises(exc):
        Camera(**args)


def test_look_at_validation():
    with pytest.raises(ValueError, match="target"):
        Camera.look_at([0, 0, 0], [0, 0, 0], focal=10, width=4, height=4)
    with pytest.raises(ValueError, match="up"):
        Camera.look_at([0, 0, 0], [0, 1, 0], focal=10, width=4, height=4, up=(0, 2, 0))


def test_points_validation():
    cam = Camera(K=np.diag([100.0, 100.0, 1.0]), width=10, height=10)
    with pytest.raises(ValueError, match="points"):
        cam.project(np.zeros((4, 2)))
    with pytest.raises(TypeError):
        cam[0]
