"""sft.metrics against closed forms."""

import numpy as np
import pytest
import torch

from sft.metrics import e_3d, e_n, frame_errors, rmse, summarize


def plane(n=6):
    a, b = np.meshgrid(np.linspace(-1, 1, n), np.linspace(-1, 1, n))
    v = np.stack([a.ravel(), b.ravel(), np.full(a.size, 3.0)], 1)
    f = []
    for j in range(n - 1):
        for i in range(n - 1):
            k = j * n + i
            f += [[k, k + 1, k + n], [k + 1, k + n + 1, k + n]]
    return v, np.array(f)


def test_e3d_and_rmse_closed_forms():
    v, _ = plane()
    assert float(e_3d(1.01 * v, v)) == pytest.approx(0.01, rel=1e-12)
    d = np.array([0.3, -0.4, 0.0])
    assert float(rmse(v + d, v)) == pytest.approx(0.5, rel=1e-12)
    assert float(e_3d(v + d, v)) == pytest.approx(
        0.5 * np.sqrt(len(v)) / np.linalg.norm(v), rel=1e-12)
    # batched == per item, torch in
    X = torch.tensor(np.stack([v, 1.02 * v]))
    np.testing.assert_allclose(e_3d(X, torch.tensor(np.stack([v, v]))), [0.0, 0.02], atol=1e-15)


def test_normal_angle_closed_forms():
    v, f = plane()
    assert float(e_n(v, v, f)) == pytest.approx(0.0, abs=1e-6)
    th = np.radians(7.0)
    R = np.array([[1, 0, 0], [0, np.cos(th), -np.sin(th)], [0, np.sin(th), np.cos(th)]])
    assert float(e_n(v @ R.T, v, f)) == pytest.approx(7.0, rel=1e-9)
    assert float(e_n(v, v, f[:, ::-1])) == pytest.approx(0.0, abs=1e-6)  # both flipped
    flip = np.diag([1.0, -1.0, -1.0])  # half turn about x: every normal reverses
    assert float(e_n(v @ flip, v, f)) == pytest.approx(180.0, rel=1e-6)


def test_normal_angle_mask_selects_vertices():
    # a plane tilted by 7 degrees about the line y = 0 for y > 0 only (a crease): vertices of
    # the flat half away from the crease keep their normals exactly, those of the tilted half
    # (away from it) are off by 7 degrees; the crease row has the mean normal in between
    v, f = plane(9)
    th = np.radians(7.0)
    X = v.copy()
    up = v[:, 1] > 0
    X[up, 1] = v[up, 1] * np.cos(th)
    X[up, 2] = 3.0 + v[up, 1] * np.sin(th)
    flat = v[:, 1] < -0.3
    tilted = v[:, 1] > 0.3
    assert float(e_n(X, v, f, mask=flat)) == pytest.approx(0.0, abs=1e-6)
    assert float(e_n(X, v, f, mask=tilted)) == pytest.approx(7.0, rel=1e-9)
    whole = float(e_n(X, v, f))
    assert 0.0 < whole < 7.0
    assert float(e_n(X, v, f, mask=np.zeros(len(v), bool))) == 0.0  # nothing left: 0
    with pytest.raises(ValueError, match="mask"):
        e_n(X, v, f, mask=np.ones(3, bool))


def test_frame_errors_and_summary():
    v, f = plane()
    fe = frame_errors(1.01 * v, v, 1.02 * v, f)
    assert fe.e_3d == pytest.approx(0.01) and fe.e_3d_template == pytest.approx(0.02)
    d = fe.as_dict()
    assert set(d) == {"e_3d", "e_n", "rmse", "e_3d_template", "e_n_template", "rmse_template"}
    s = summarize([{"frame": 0, "a": 1.0, "b": "x"}, {"frame": 1, "a": 3.0, "b": "y"}])
    assert s == {"frames": 2, "a": 2.0}
    assert summarize([]) == {"frames": 0}


def test_metric_validation():
    v, f = plane()
    with pytest.raises(ValueError, match="X, X_gt: expected the same"):
        e_3d(v[:-1], v)
    with pytest.raises(ValueError, match="X: expected shape"):
        rmse(v[:, :2], v)
    with pytest.raises(ValueError, match="X_gt: the ground truth is all zeros"):
        e_3d(v, np.zeros_like(v))
