import numpy as np
import pytest
import torch

from draping.skinning import (
    dense_body_weights,
    laplacian_weights,
    nearest_weights,
    rbf_weights,
    skinning_weights,
    smooth_weights,
)


def _limb(n_theta=24, n_z=41, radius=0.1, n_bones=5):
    """A capped-free cylinder of body vertices, one bone per height band (one-hot weights)."""
    th, z = np.meshgrid(np.linspace(0, 2 * np.pi, n_theta, endpoint=False), np.linspace(0, 1, n_z))
    verts = np.stack([radius * np.cos(th), radius * np.sin(th), z], -1).reshape(-1, 3)
    band = np.minimum((verts[:, 2] * n_bones).astype(int), n_bones - 1)
    weights = np.eye(n_bones)[band]
    return verts, weights


def _sleeve(offset, radius=0.1, n_theta=16, n_z=21):
    """A garment cylinder ``offset`` outside the limb, with its triangles."""
    th, z = np.meshgrid(np.linspace(0, 2 * np.pi, n_theta, endpoint=False), np.linspace(0, 1, n_z))
    r = radius + offset
    verts = np.stack([r * np.cos(th), r * np.sin(th), z], -1).reshape(-1, 3)
    faces = []
    for i in range(n_z - 1):
        for j in range(n_theta):
            a, b = i * n_theta + j, i * n_theta + (j + 1) % n_theta
            c, d = a + n_theta, b + n_theta
            faces += [(a, b, d), (a, d, c)]
    return verts, np.array(faces)


@pytest.mark.parametrize("method", ["nearest", "laplacian", "rbf"])
def test_rows_sum_to_one_and_are_non_negative(method):
    body, w = _limb()
    garment, faces = _sleeve(0.05)
    out = skinning_weights(method, garment, body, w, garment_faces=faces)
    assert out.shape == (garment.shape[0], w.shape[1])
    assert np.all(out >= 0)
    np.testing.assert_allclose(out.sum(1), 1.0, atol=1e-12)


def test_points_on_the_skin_take_the_body_weights():
    rng = np.random.default_rng(0)
    body = rng.normal(size=(300, 3))
    w = rng.dirichlet(np.ones(7), size=300)
    pick = rng.choice(300, 50, replace=False)
    for fn in (nearest_weights, rbf_weights):
        np.testing.assert_allclose(fn(body[pick], body, w), w[pick], atol=1e-12)
    # A hair off the skin: the RBF kernel is narrow there, so the nearest vertex dominates.
    near = body[pick] + 1e-6 * rng.normal(size=(50, 3))
    np.testing.assert_allclose(rbf_weights(near, body, w), w[pick], atol=1e-6)


def test_rbf_blends_more_bones_far_from_the_body():
    body, w = _limb()
    counts = []
    for offset in (0.005, 0.05, 0.3):
        garment, _ = _sleeve(offset)
        out = rbf_weights(garment, body, w)
        counts.append(np.mean((out > 1e-3).sum(1)))
    assert counts[0] < counts[1] < counts[2]
    # Nearest-vertex skinning never blends: always one bone on this one-hot body.
    garment, _ = _sleeve(0.3)
    assert np.all((nearest_weights(garment, body, w) > 0).sum(1) == 1)


def test_rbf_truncation_matches_the_full_participation_matrix():
    rng = np.random.default_rng(1)
    body = rng.normal(size=(400, 3))
    w = rng.dirichlet(np.ones(4), size=400)
    garment = 1.5 * rng.normal(size=(60, 3))
    d = np.linalg.norm(garment[:, None] - body[None], axis=-1)  # (G, V) brute force
    m = d.min(1, keepdims=True)
    phi = np.exp(-((d - m) ** 2) / (0.5 * m**2))
    full = phi @ w
    full /= full.sum(1, keepdims=True)
    got = rbf_weights(garment, body, w, tol=1e-12, chunk=7)
    np.testing.assert_allclose(got, full, atol=1e-9)
    # The default truncation changes the weights by about the dropped participation only.
    np.testing.assert_allclose(rbf_weights(garment, body, w), full, atol=5e-3)


def test_laplacian_smooths_a_weight_jump():
    body, w = _limb(n_bones=2)
    garment, faces = _sleeve(0.2)
    raw = laplacian_weights(garment, faces, body, w, iterations=0)
    np.testing.assert_allclose(raw, nearest_weights(garment, body, w))
    smooth = laplacian_weights(garment, faces, body, w, iterations=30)
    # Along the sleeve the first bone's weight falls from 1 to 0: smoothing spreads the step.
    z = garment[:, 2]
    mid = np.abs(z - 0.5) < 0.08
    assert np.all(np.isin(raw[mid, 0], (0.0, 1.0)))
    assert np.any((smooth[mid, 0] > 0.05) & (smooth[mid, 0] < 0.95))
    assert np.diff(smooth[np.argsort(z), 0]).max() < 0.2 + np.diff(raw[np.argsort(z), 0]).max()


def test_sparse_body_weights_equal_dense():
    rng = np.random.default_rng(2)
    body = rng.normal(size=(100, 3))
    idx = np.stack([rng.choice(12, 3, replace=False) for _ in range(100)])
    val = rng.dirichlet(np.ones(3), size=100)
    idx[:5, 2] = -1  # padding
    val[:5, 2] = 0.0
    dense = dense_body_weights((idx, val), 100, n_bones=12)
    assert dense.shape == (100, 12)
    garment = rng.normal(size=(30, 3))
    sparse_out = rbf_weights(garment, body, (idx, val))
    np.testing.assert_allclose(sparse_out, rbf_weights(garment, body, dense))


def test_torch_in_torch_out():
    body, w = _limb()
    garment, _ = _sleeve(0.05)
    out = rbf_weights(torch.from_numpy(garment), body, w)
    assert isinstance(out, torch.Tensor)
    np.testing.assert_allclose(out.numpy(), rbf_weights(garment, body, w))


def test_bad_input_is_named():
    body, w = _limb()
    garment, faces = _sleeve(0.05)
    with pytest.raises(ValueError, match="method"):
        skinning_weights("linear", garment, body, w)
    with pytest.raises(ValueError, match="garment_faces"):
        skinning_weights("laplacian", garment, body, w)
    with pytest.raises(ValueError, match="garment_vertices"):
        rbf_weights(garment[:, :2], body, w)
    bad = garment.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="garment_vertices"):
        nearest_weights(bad, body, w)
    with pytest.raises(ValueError, match="weights"):
        rbf_weights(garment, body, w[:-1])
    with pytest.raises(ValueError, match="weights"):
        rbf_weights(garment, body, -w)
    with pytest.raises(ValueError, match="width"):
        rbf_weights(garment, body, w, width=0)
    with pytest.raises(ValueError, match="alpha"):
        laplacian_weights(garment, faces, body, w, alpha=1.5)
    with pytest.raises(ValueError, match="garment_faces"):
        laplacian_weights(garment, faces + garment.shape[0], body, w)


def _square():
    """Two triangles on four vertices: 0 and 2 have three neighbours, 1 and 3 two."""
    return np.array([[0, 1, 2], [0, 2, 3]])


def test_smooth_weights_one_step_is_the_neighbour_mean():
    faces = _square()
    w = np.eye(4)
    out = smooth_weights(w, faces, iterations=1, alpha=0.5)
    np.testing.assert_allclose(out[0], [0.5, 1 / 6, 1 / 6, 1 / 6])
    np.testing.assert_allclose(out[1], [0.25, 0.5, 0.25, 0.0])
    np.testing.assert_allclose(out.sum(1), 1.0)
    np.testing.assert_allclose(smooth_weights(w, faces, iterations=0), w)
    same = np.tile([[0.2, 0.3, 0.5, 0.0]], (4, 1))  # equal rows are a fixed point
    np.testing.assert_allclose(smooth_weights(same, faces, iterations=7), same)
    t = smooth_weights(torch.from_numpy(w), torch.from_numpy(faces), iterations=1)
    assert isinstance(t, torch.Tensor)
    np.testing.assert_allclose(t.numpy(), out)


def test_laplacian_weights_are_smoothed_nearest_weights():
    body, w = _limb(n_bones=2)
    garment, faces = _sleeve(0.2)
    np.testing.assert_allclose(laplacian_weights(garment, faces, body, w, iterations=9),
                               smooth_weights(nearest_weights(garment, body, w), faces,
                                              iterations=9))


def test_smooth_weights_bad_input_is_named():
    faces = _square()
    w = np.eye(4)
    with pytest.raises(ValueError, match="iterations"):
        smooth_weights(w, faces, iterations=-1)
    for alpha in (0.0, 1.5):
        with pytest.raises(ValueError, match="alpha"):
            smooth_weights(w, faces, alpha=alpha)
    with pytest.raises(ValueError, match="weights"):
        smooth_weights(-w, faces)
    with pytest.raises(ValueError, match="faces"):
        smooth_weights(w, faces + 3)
    with pytest.raises(ValueError, match="weights"):
        smooth_weights(w[:, :, None], faces)


@pytest.mark.parametrize("method", ["nearest", "laplacian", "rbf"])
def test_smoothing_option_is_smooth_weights_after_the_method(method):
    body, w = _limb(n_bones=3)
    garment, faces = _sleeve(0.15)
    base = (rbf_weights(garment, body, w) if method == "rbf"
            else nearest_weights(garment, body, w))
    for steps in (0, 1, 7):
        got = skinning_weights(method, garment, body, w, garment_faces=faces, smoothing=steps,
                               smoothing_alpha=0.3)
        want = smooth_weights(base, faces, iterations=steps, alpha=0.3) if steps else base
        assert np.array_equal(got, want)  # bit-identical: one home for the smoothing
    # Defaults: 'laplacian' is nearest plus 20 steps (laplacian_weights), the others unsmoothed.
    got = skinning_weights(method, garment, body, w, garment_faces=faces)
    want = laplacian_weights(garment, faces, body, w) if method == "laplacian" else base
    assert np.array_equal(got, want)
    t = skinning_weights(method, torch.from_numpy(garment), body, w, garment_faces=faces,
                         smoothing=3)
    assert isinstance(t, torch.Tensor)


def test_smoothing_option_bad_input_is_named():
    body, w = _limb()
    garment, faces = _sleeve(0.05)
    with pytest.raises(ValueError, match="smoothing"):
        skinning_weights("rbf", garment, body, w, garment_faces=faces, smoothing=-1)
    with pytest.raises(ValueError, match="smoothing_alpha"):
        skinning_weights("nearest", garment, body, w, garment_faces=faces, smoothing_alpha=2.0)
    with pytest.raises(ValueError, match="garment_faces"):
        skinning_weights("rbf", garment, body, w, smoothing=2)
    with pytest.raises(ValueError, match="smoothing"):
        skinning_weights("laplacian", garment, body, w, garment_faces=faces, iterations=3)
    with pytest.raises(ValueError, match="options"):
        skinning_weights("nearest", garment, body, w, width=0.5)
