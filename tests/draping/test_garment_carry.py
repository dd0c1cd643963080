"""Carrying a garment template to another body shape: smooth displacement, no folds."""

import numpy as np
import pytest
import torch

from draping.body import AnnyBody
from draping.collision import MeshQuery
from draping.gaps import random_shapes
from draping.garment_fit import fold_faces, relax_folds, smooth_displacement
from draping.garments import check_garment, fit_garment_to_shape, garment
from polygeo.mesh import dihedral_angles, edges


def _grid(n=12, size=1.0):
    """A flat ``n x n`` vertex sheet in the plane z = 0 (two triangles per cell)."""
    x, y = np.meshgrid(np.linspace(0, size, n), np.linspace(0, size, n), indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return v, f


def _min_angle(v, f):
    t = v[f]
    out = np.full(len(f), 180.0)
    for c in range(3):
        a, b = t[:, (c + 1) % 3] - t[:, c], t[:, (c + 2) % 3] - t[:, c]
        cos = np.einsum("ij,ij->i", a, b) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
        out = np.minimum(out, np.degrees(np.arccos(np.clip(cos, -1, 1))))
    return out


def _plane_query(z0):
    """Signed distance to the half space below ``z = z0`` (the "body")."""

    def query(p):
        p = np.asarray(p, float)
        d = p[:, 2] - z0
        closest = p.copy()
        closest[:, 2] = z0
        return d, closest, np.tile([0.0, 0.0, 1.0], (len(p), 1))

    return query


# ------------------------------------------------------------------ smooth_displacement


def test_constant_displacement_is_kept():
    v, f = _grid()
    u = np.tile([0.3, -0.1, 2.0], (len(v), 1))
    out = smooth_displacement(u, f, v, np.full(len(v), 0.5))
    np.testing.assert_allclose(out, u, atol=1e-12)


def test_minimiser_of_the_stated_energy():
    # Independent check: the gradient of sum c |u - u0|^2 + sum_edges |u_i - u_j|^2, written
    # edge by edge, vanishes at the returned field.
    rng = np.random.default_rng(0)
    v, f = _grid(8)
    u0 = rng.normal(size=(len(v), 3))
    dist = rng.uniform(0.0, 0.5, len(v))
    u = smooth_displacement(u0, f, v, dist)
    e = edges(f)
    ell = np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1).mean()
    c = (ell / np.maximum(dist, ell)) ** 2
    grad = 2 * c[:, None] * (u - u0)
    for i, j in e:
        grad[i] += 2 * (u[i] - u[j])
        grad[j] += 2 * (u[j] - u[i])
    np.testing.assert_allclose(grad, 0.0, atol=1e-10)


def test_jump_far_from_the_body_is_smoothed_and_near_it_kept():
    v, f = _grid(20)
    u0 = np.zeros_like(v)
    u0[v[:, 0] > 0.5, 2] = 1.0  # the nearest body part switches in the middle of the sheet
    e = edges(f)
    ell = np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1).mean()

    def max_step(u):
        return np.abs(u[e[:, 0], 2] - u[e[:, 1], 2]).max()

    far = smooth_displacement(u0, f, v, np.full(len(v), 8 * ell))
    near = smooth_displacement(u0, f, v, np.full(len(v), 0.5 * ell))
    assert max_step(u0) == 1.0
    assert max_step(far) < 0.15  # spread over about eight edges
    assert max_step(near) > 0.3  # on the skin the body's own displacement is kept closely
    # Far from the jump the field stays what it was.
    edge_x = np.abs(v[:, 0] - 0.5) > 0.45
    np.testing.assert_allclose(near[edge_x], u0[edge_x], atol=0.05)


def test_smoothing_is_scale_free():
    rng = np.random.default_rng(1)
    v, f = _grid(10)
    u0 = rng.normal(size=(len(v), 3))
    dist = rng.uniform(0.0, 0.4, len(v))
    a = smooth_displacement(u0, f, v, dist)
    b = smooth_displacement(1000 * u0, f, 1000 * v, 1000 * dist)
    np.testing.assert_allclose(b, 1000 * a, rtol=1e-9, atol=1e-9)


# ------------------------------------------------------------------ folds


def test_fold_faces_flags_a_fold_and_a_sliver_but_not_the_reference():
    v, f = _grid(6)
    assert not fold_faces(v, f, v).any()
    folded = v.copy()
    folded[v[:, 0] > 0.5, 2] = 0.0
    folded[v[:, 0] > 0.5, 0] = 1.0 - folded[v[:, 0] > 0.5, 0]  # the right half folded back
    bad = fold_faces(folded, f, v)
    assert bad.any()
    squashed = v.copy()
    squashed[:, 1] *= 0.01  # every triangle a sliver
    assert fold_faces(squashed, f, v).all()
    # A reference that has the sliver already is not flagged for it.
    assert not fold_faces(squashed, f, squashed).any()


def test_relax_folds_unfolds_a_pinched_sheet_and_keeps_it_off_the_body():
    v, f = _grid(15)
    pinched = v.copy()
    mid = np.argmin(np.linalg.norm(v[:, :2] - 0.5, axis=1))
    pinched[mid, :2] += [0.2, 0.15]  # one vertex dragged over its neighbours: folds
    pinched[:, 2] = 0.05
    assert fold_faces(pinched, f, v).any()
    query = _plane_query(0.0)
    room = np.full(len(v), 0.05)
    out = relax_folds(pinched, f, query, room, v)
    assert not fold_faces(out, f, v).any()
    assert query(out)[0].min() >= 0.025 - 1e-12  # half the room where it relaxed
    moved = np.linalg.norm(out - pinched, axis=1) > 0
    far = np.linalg.norm(v[:, :2] - v[mid, :2], axis=1) > 0.6
    assert not moved[far].any()  # only around the fold


# ------------------------------------------------------------------ on the body


@pytest.fixture(scope="module")
def body():
    return AnnyBody.load(dtype=torch.float64)


# Shape draws on which the old carry folded each garment (max hinge 164-179 deg, slivers of
# 0.1-3.6 deg): a child about 1 m tall (1003) and bm_gaps' held-back shape 2000.
@pytest.mark.parametrize("name, seed", [("skirt", 2000), ("dress", 1003), ("tshirt", 1003)])
def test_carried_garment_has_no_folds_or_slivers(body, name, seed):
    g = garment(name)
    s = random_shapes(1, seed)[0].double()
    fitted = fit_garment_to_shape(g, body, s)
    dh0 = np.degrees(np.abs(np.asarray(dihedral_angles(g.vertices, g.faces).angle)))
    dh = np.degrees(np.abs(np.asarray(dihedral_angles(fitted.vertices, fitted.faces).angle)))
    assert dh.max() < max(100.0, dh0.max() + 30.0)
    assert _min_angle(fitted.vertices, fitted.faces).min() > 4.0
    v, _ = body.rest(s)
    q = MeshQuery(v.reshape(-1, 3), body.faces)
    assert q.query(fitted.vertices).distance.min() > 0
    assert check_garment(fitted.vertices, fitted.faces) == []
