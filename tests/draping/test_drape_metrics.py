"""Cloth metrics of draping.metrics on hand-made cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from draping import metrics as M

SQUARE_V = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
SQUARE_F = np.array([[0, 1, 2], [0, 2, 3]])


def test_edge_and_area_errors_hand_values():
    # stretch x by 10 %: edges along x +10 %, along y 0 %, diagonal sqrt(1.21 + 1)/sqrt(2) - 1
    x = SQUARE_V * np.array([1.1, 1.0, 1.0])
    diag = math.sqrt(2.21 / 2) - 1
    want_e = 100 * (0.1 + 0.1 + 0 + 0 + diag) / 5
    assert M.edge_error(x, SQUARE_V, SQUARE_F) == pytest.approx(want_e)
    assert M.area_error(x, SQUARE_V, SQUARE_F) == pytest.approx(10.0)
    # a rigid motion changes nothing
    rot = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    moved = SQUARE_V @ rot.T + 3.0
    assert M.edge_error(moved, SQUARE_V, SQUARE_F) == pytest.approx(0.0, abs=1e-12)
    assert M.area_error(moved, SQUARE_V, SQUARE_F) == pytest.approx(0.0, abs=1e-12)


def test_batched_frames_and_types():
    x = np.stack([SQUARE_V, SQUARE_V * 1.2])
    e = M.edge_error(x, SQUARE_V, SQUARE_F)
    assert isinstance(e, np.ndarray) and e.shape == (2,)
    assert e[1] == pytest.approx(20.0)
    a = M.area_error(torch.tensor(x), torch.tensor(SQUARE_V), SQUARE_F)
    assert isinstance(a, torch.Tensor)
    assert float(a[1]) == pytest.approx(44.0)


def test_collision_error_hand_values():
    d = np.array([[0.01, -0.001, 0.0, 0.002], [-1.0, -1.0, -1.0, 1.0]])
    np.testing.assert_allclose(M.collision_error(d), [25.0, 75.0])
    np.testing.assert_allclose(M.collision_error(d, threshold=0.005), [75.0, 75.0])
    with pytest.raises(ValueError, match="distance"):
        M.collision_error(np.array([np.nan, 1.0]))
    with pytest.raises(ValueError, match="distance"):
        M.collision_error(np.zeros(0))
    with pytest.raises(TypeError, match="distance"):
        M.collision_error("near")


def test_distance_and_normal_errors_hand_values():
    ref = SQUARE_V
    x = SQUARE_V + np.array([0.0, 0.0, 0.02])  # 2 cm up
    assert M.distance_error(x, ref) == pytest.approx(2.0)
    assert M.distance_error(x * 10, ref * 10, to_cm=10.0) == pytest.approx(2.0)
    assert M.normal_error(x, ref, SQUARE_F) == pytest.approx(0.0, abs=1e-6)
    # fold the second triangle by 30 degrees about the diagonal (0, 2): one face of two turns
    folded = SQUARE_V.copy()
    axis = np.array([1.0, 1, 0]) / math.sqrt(2)
    p = folded[3]
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    folded[3] = p * c + np.cross(axis, p) * s + axis * (axis @ p) * (1 - c)
    assert M.normal_error(folded, ref, SQUARE_F) == pytest.approx(15.0)
    assert M.edge_error(folded, ref, SQUARE_F) == pytest.approx(0.0, abs=1e-12)


def test_drape_metrics_and_summary():
    x = np.stack([SQUARE_V, SQUARE_V * np.array([1.1, 1.0, 1.0])])
    d = np.array([[1.0, 1, 1, -1], [1.0, 1, 1, 1]])
    m = M.drape_metrics(x, SQUARE_V, SQUARE_F, distance=d, reference=x)
    assert set(m) == {"eps_e", "eps_a", "eps_c", "e_dist", "e_norm"}
    s = M.summarize(m)
    assert s["eps_c"]["mean"] == pytest.approx(12.5)
    assert s["eps_c"]["max"] == pytest.approx(25.0)
    assert s["eps_a"]["per_frame"] == pytest.approx([0.0, 10.0])
    assert s["e_dist"]["max"] == 0.0
    assert set(M.drape_metrics(x, SQUARE_V, SQUARE_F)) == {"eps_e", "eps_a"}
    with pytest.raises(ValueError, match="per_frame"):
        M.summarize({"eps_e": []})


def test_metrics_reject_bad_input():
    with pytest.raises(ValueError, match="template"):
        M.edge_error(SQUARE_V, SQUARE_V[:3], SQUARE_F)
    with pytest.raises(ValueError, match="x"):
        M.area_error(SQUARE_V[:, :2], SQUARE_V, SQUARE_F)
    with pytest.raises(TypeError, match="x"):
        M.edge_error("square", SQUARE_V, SQUARE_F)
    with pytest.raises(ValueError, match="x"):
        M.distance_error(np.full((4, 3), np.inf), SQUARE_V)
    with pytest.raises(ValueError, match="reference"):
        M.normal_error(SQUARE_V, SQUARE_V[:2], SQUARE_F)


def test_relative_vertex_error_hand_values_and_invariances():
    rng = np.random.default_rng(3)
    ref = rng.normal(size=(50, 3))
    c = ref.mean(0)
    # scaling about the centroid by 1.01: ||0.01 (ref - c)|| / ||ref - c|| = 0.01
    assert float(M.relative_vertex_error(c + 1.01 * (ref - c), ref)) == pytest.approx(0.01,
                                                                                     rel=1e-12)
    d = rng.normal(size=(50, 3))
    want = np.linalg.norm(d) / np.linalg.norm(ref - c)      # independent formula
    got = M.relative_vertex_error(ref + d, ref)
    assert isinstance(got, np.ndarray) and float(got) == pytest.approx(want, rel=1e-12)
    # same value after a common translation and a change of unit (m -> mm)
    t = np.array([5.0, -2.0, 7.0])
    assert float(M.relative_vertex_error(1e3 * (ref + d + t), 1e3 * (ref + t))) == \
        pytest.approx(want, rel=1e-9)
    # batched frames, torch in -> torch out, broadcast reference
    x = torch.tensor(np.stack([ref, ref + d]))
    out = M.relative_vertex_error(x, torch.tensor(ref))
    assert isinstance(out, torch.Tensor) and out.shape == (2,)
    np.testing.assert_allclose(out.numpy(), [0.0, want], rtol=1e-12, atol=1e-15)


def test_relative_vertex_error_rejects_bad_input():
    v = np.random.default_rng(0).normal(size=(6, 3))
    with pytest.raises(ValueError, match="reference"):
        M.relative_vertex_error(v, v[:5])
    with pytest.raises(ValueError, match="reference"):
        M.relative_vertex_error(v, np.ones((6, 3)))          # no spread
    with pytest.raises(ValueError, match="x"):
        M.relative_vertex_error(np.full((6, 3), np.nan), v)
    with pytest.raises(TypeError, match="x"):
        M.relative_vertex_error("grid", v)
