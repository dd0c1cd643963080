"""Cloth pinched between two body parts in GAPS training: the L_inext factor
(``TrainSettings.pinch_inext``) and the collision push out of the pinch (``pinch_push``)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from draping import physics
from draping.collision import MeshQuery
from draping.gaps import (
    GapsSettings,
    PinchQuery,
    TrainSettings,
    body_contacts,
    loss_terms,
    pinch_factor,
    push_normal,
)
from draping.gaps.losses import Contacts
from polygeo import covariance


def box(lo, hi):
    """Closed, outward-wound box ``(8, 3)`` vertices, ``(12, 3)`` faces."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    v = np.array([[x, y, z] for x in (x0, x1) for y in (y0, y1) for z in (z0, z1)], float)
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return v, f


def two_boxes(lo_a, hi_a, lo_b, hi_b):
    """Body of two boxes, the first an arm: vertices, faces, arm flags per face."""
    va, fa = box(lo_a, hi_a)
    vb, fb = box(lo_b, hi_b)
    v = np.concatenate([va, vb])
    f = np.concatenate([fa, fb + len(va)])
    return torch.from_numpy(v), torch.from_numpy(f), np.arange(len(f)) < len(fa)


def flags(v, f, arm, points, eps):
    """Pinch flags of ``points`` against the two-part body, via the whole body's query."""
    whole = MeshQuery(v, f)
    r = whole.query(torch.as_tensor(points, dtype=torch.float64), max_distance=0.02)
    ok = np.isfinite(np.asarray(r.distance))
    normal = np.where(ok[:, None], np.asarray(r.normal), 0.0)
    return PinchQuery(v, f, arm).pinched(v, np.asarray(points, float), r.distance, r.face,
                                         normal, eps)


def test_cloth_between_facing_parts_is_pinched():
    """An arm box 10 mm above a torso box: a point 4 mm above the torso (6 mm under the arm)
    is within a 7 mm clearance of both facing surfaces; above the arm, or with a clearance
    smaller than the far side, it is not; inside the arm, 12 mm from the torso, only a
    clearance over 12 mm makes it one."""
    v, f, arm = two_boxes((0, 0, 0.010), (0.1, 0.1, 0.030), (0, 0, -0.020), (0.1, 0.1, 0.0))
    pts = [[0.05, 0.05, 0.004], [0.05, 0.05, 0.035], [0.05, 0.05, 0.012]]
    assert flags(v, f, arm, pts, 0.007).tolist() == [True, False, False]
    assert flags(v, f, arm, pts, 0.005).tolist() == [False, False, False]  # arm 6 mm away
    assert flags(v, f, arm, pts, 0.013).tolist() == [True, False, True]


def test_where_two_parts_meet_is_no_pinch():
    """An arm box beside a torso box (a shoulder-like seam): a point 3 mm above the arm, 2 mm
    past the seam, is within 7 mm of both, but their surfaces face the same way."""
    v, f, arm = two_boxes((0.1, 0, -0.02), (0.2, 0.1, 0.0), (0, 0, -0.02), (0.1, 0.1, 0.0))
    pts = [[0.102, 0.05, 0.003], [0.098, 0.05, 0.003]]
    assert flags(v, f, arm, pts, 0.007).tolist() == [False, False]


def test_pinch_query_refuses_bad_input():
    v, f, arm = two_boxes((0, 0, 0.010), (0.1, 0.1, 0.030), (0, 0, -0.020), (0.1, 0.1, 0.0))
    with pytest.raises(ValueError, match="arm"):
        PinchQuery(v, f, arm[:-1])
    with pytest.raises(ValueError, match="arm"):
        PinchQuery(v, f, np.ones(len(f), bool))
    with pytest.raises(ValueError, match="arm"):
        PinchQuery(v, f, arm.astype(int))
    with pytest.raises(ValueError, match="eps"):
        flags(v, f, arm, [[0.05, 0.05, 0.004]], 0.0)


def sheet(n=5):
    u, w = np.meshgrid(np.linspace(0, 0.4, n), np.linspace(0, 0.4, n), indexing="ij")
    verts = np.stack([u.ravel(), w.ravel(), np.zeros(n * n)], 1)
    faces = [[i * n + j, (i + 1) * n + j, i * n + j + 1]
             for i in range(n - 1) for j in range(n - 1)]
    faces += [[i * n + j + 1, (i + 1) * n + j, (i + 1) * n + j + 1]
              for i in range(n - 1) for j in range(n - 1)]
    return verts, np.array(faces, dtype=np.int64)


def test_pinch_factor_per_vertex_on_the_rings():
    """``factor`` at a flagged vertex and, with one ring, at its face neighbours; 1 elsewhere."""
    v, f = sheet()
    rest = physics.rest_state(v, f)
    p = torch.zeros(2, len(v), dtype=torch.bool)
    p[0, 12] = True  # the middle vertex, frame 0 only
    w0 = pinch_factor(p, rest, 0, 0.25)
    assert w0[0, 12] == 0.25 and int((w0 != 1).sum()) == 1
    w1 = pinch_factor(p, rest, 1, 0.0)
    nb = {12} | {int(j) for tri in f if 12 in tri for j in tri}
    assert set(torch.nonzero(w1[0] == 0).flatten().tolist()) == nb
    assert bool((w1[1] == 1).all()) and bool((w1[0][[i for i in range(len(v))
                                                    if i not in nb]] == 1).all())
    with pytest.raises(ValueError, match="factor"):
        pinch_factor(p, rest, 1, 1.5)
    with pytest.raises(ValueError, match="pinched"):
        pinch_factor(p.float(), rest, 1, 0.5)
    with pytest.raises(ValueError, match="rings"):
        pinch_factor(p, rest, -1, 0.5)


def test_inextensibility_vertex_weight():
    """The weighted energy is the per-vertex residual (polygeo.covariance) times the weights."""
    v, f = sheet()
    rest = physics.rest_state(v, f)
    g = torch.Generator().manual_seed(0)
    x = torch.as_tensor(v, dtype=torch.float64) * 1.1 + 0.01 * torch.randn(len(v), 3, generator=g,
                                                                          dtype=torch.float64)
    w = torch.rand(len(v), generator=g, dtype=torch.float64)
    cov = covariance.vertex_covariance(x, rest.ring_index, rest.ring_mask)
    per = covariance.inextensibility_residual(cov, rest.ring_sigma.to(x.dtype), 1.3, weight=2e8,
                                              reduction="none")
    torch.testing.assert_close(physics.inextensibility_energy(x, rest, 1.3, 2e8, w),
                               (per * w).sum())
    torch.testing.assert_close(physics.inextensibility_energy(x, rest, 1.3, 2e8),
                               physics.inextensibility_energy(x, rest, 1.3, 2e8,
                                                              torch.ones(len(v))))
    for bad in (-w, w[:-1], torch.full_like(w, float("nan"))):
        with pytest.raises(ValueError, match="vertex_weight"):
            physics.inextensibility_energy(x, rest, 1.3, 2e8, bad)


def test_settings_default_off_and_validated():
    s = TrainSettings()
    assert s.pinch_inext == 1.0 and "pinch_inext" not in s.key_dict()
    t = s.replace(pinch_inext=0.0)
    assert t.key_dict()["pinch_inext"] == 0.0
    assert TrainSettings.from_dict(dataclasses.asdict(t)) == t
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="pinch_inext"):
            s.replace(pinch_inext=bad)
    with pytest.raises(ValueError, match="pinch_inext"):
        s.replace(pinch_inext=0.0, collision_eps=0.0)


def test_pinch_cli_option(tmp_path):
    from draping.gaps.cli import _settings
    from polygeo.cli import build_parser

    base = ["train-drape", "--garment", "dress", "-o", str(tmp_path / "r")]
    parser = build_parser()
    assert _settings(parser.parse_args([*base, "--pinch-inext", "0"])).pinch_inext == 0.0
    assert _settings(parser.parse_args(base)).pinch_inext == 1.0


def test_loss_terms_apply_the_factor_at_pinched_cloth():
    """With ``contacts.pinched``, L_inext is the shared energy weighted by :func:`pinch_factor`;
    ``pinch_inext = 1`` (the default) leaves it as before."""
    from draping.gaps.data import ShapeCase

    v, f = sheet()
    rest = physics.rest_state(v, f)
    case = ShapeCase(shape=torch.zeros(6), garment=None, rest=rest,
                     alpha=torch.zeros(rest.hinge_weight.shape[0]))
    s = TrainSettings(GapsSettings(garment="dress", inextensibility="one"), k_ext_rings=1,
                      pinch_inext=0.0)
    g = torch.Generator().manual_seed(1)
    x = (torch.as_tensor(v, dtype=torch.float32) * 1.05).expand(3, -1, -1) + \
        0.01 * torch.randn(3, len(v), 3, generator=g)
    far = torch.zeros(3, len(v), dtype=torch.bool)
    pinched = far.clone()
    pinched[:, 6] = True
    ct = Contacts(x.clone(), torch.zeros_like(x), far, pinched)
    got = loss_terms(x[None], case, s.model, s, ct, epoch=3, dt=1 / 30)["inext"][0]
    w = pinch_factor(pinched, rest, 1, 0.0)
    torch.testing.assert_close(got, physics.inextensibility_energy(x, rest, 1.0, s.inext_weight, w))
    plain = loss_terms(x[None], case, s.model, s.replace(pinch_inext=1.0), ct, epoch=3,
                       dt=1 / 30)["inext"][0]
    torch.testing.assert_close(plain, physics.inextensibility_energy(x, rest, 1.0, s.inext_weight))
    assert bool((got < plain).all())


def test_body_contacts_flag_pinches_only_when_asked():
    v, f, arm = two_boxes((0, 0, 0.010), (0.1, 0.1, 0.030), (0, 0, -0.020), (0.1, 0.1, 0.0))
    x = torch.tensor([[[0.05, 0.05, 0.004], [0.05, 0.05, 0.035]]])
    q = MeshQuery(v, f)
    assert body_contacts(x, v[None], q, 0.02).pinched is None
    ct = body_contacts(x, v[None], q, 0.02, PinchQuery(v, f, arm), 0.007)
    assert ct.pinched.tolist() == [[True, False]]


def wedge():
    """A torso box (top at z = 0, normal +z) and an arm box tilted 45 deg about y whose lower
    face, normal (s, 0, -s) with s = sqrt(1/2), rises from the edge x = 0.03, z = 2 mm: a
    wedge between the two, opening towards +x. Vertices, faces, arm flags per face."""
    va, fa = box((0.0, 0.0, 0.0), (0.1, 0.1, 0.02))
    s = np.sqrt(0.5)
    va = va @ np.array([[s, 0, -s], [0, 1, 0], [s, 0, s]]).T + np.array([0.03, 0.0, 0.002])
    vb, fb = box((0, 0, -0.02), (0.1, 0.1, 0.0))
    v = torch.from_numpy(np.concatenate([va, vb]))
    f = torch.from_numpy(np.concatenate([fa, fb + len(va)]))
    return v, f, np.arange(len(f)) < len(fa)


def test_push_is_along_the_wedge_bisector():
    """In the wedge (torso normal +z, arm normal (s, 0, -s)) the pushed normal is the bisector
    (cos 22.5, 0, sin 22.5) deg, and the penetration along it is sin 22.5 deg of the distance to
    the closest part (its closest point is the anchor): a point 2.83 mm from the arm (closer
    than the torso, 3 mm), one 2.5 mm above the torso (4.6 mm from the arm), one 1 mm inside the
    torso (6.4 mm from the arm). A point 4 mm above the torso, 34 mm from the arm, is not
    pinched: normal and distance as without the push."""
    v, f, arm = wedge()
    pts = [[0.035, 0.05, 0.003], [0.037, 0.05, 0.0025], [0.036, 0.05, -0.001],
           [0.08, 0.05, 0.004]]
    x = torch.tensor([pts], dtype=torch.float64)
    q, pq = MeshQuery(v, f), PinchQuery(v, f, arm)
    plain = body_contacts(x, v[None], q, 0.02, pq, 0.007)
    pushed = body_contacts(x, v[None], q, 0.02, pq, 0.007, push=True)
    assert plain.pinched.tolist() == pushed.pinched.tolist() == [[True, True, True, False]]
    c, s = np.cos(np.pi / 8), np.sin(np.pi / 8)
    want = torch.tensor([[c, 0, s]] * 3 + [[0, 0, 1]], dtype=torch.float64)
    torch.testing.assert_close(pushed.normal[0], want, atol=1e-9, rtol=0)
    h = np.sqrt(0.5)
    torch.testing.assert_close(plain.normal[0], torch.tensor([[h, 0, -h], [0, 0, 1], [0, 0, 1],
                                                             [0, 0, 1]], dtype=torch.float64),
                               atol=1e-9, rtol=0)
    d_plain = torch.tensor([0.002 * np.sqrt(2), 0.0025, -0.001, 0.004], dtype=torch.float64)
    torch.testing.assert_close(plain.distance(x, far=1.0)[0], d_plain, atol=1e-12, rtol=0)
    d_push = d_plain * torch.tensor([s, s, s, 1.0], dtype=torch.float64)
    torch.testing.assert_close(pushed.distance(x, far=1.0)[0], d_push, atol=1e-12, rtol=0)


def test_push_leaves_seams_and_parallel_pinches_alone():
    """A shoulder-like seam is not pinched, so its normal stays; between parallel, opposite
    surfaces (arm box 10 mm over the torso box) the two normals cancel: no way out, the closest
    part's normal is kept."""
    v, f, arm = two_boxes((0.1, 0, -0.02), (0.2, 0.1, 0.0), (0, 0, -0.02), (0.1, 0.1, 0.0))
    x = torch.tensor([[[0.102, 0.05, 0.003], [0.098, 0.05, 0.003]]], dtype=torch.float64)
    q, pq = MeshQuery(v, f), PinchQuery(v, f, arm)
    ct = body_contacts(x, v[None], q, 0.02, pq, 0.007, push=True)
    assert ct.pinched.tolist() == [[False, False]]
    torch.testing.assert_close(ct.normal, body_contacts(x, v[None], q, 0.02).normal)
    v, f, arm = two_boxes((0, 0, 0.010), (0.1, 0.1, 0.030), (0, 0, -0.020), (0.1, 0.1, 0.0))
    x = torch.tensor([[[0.05, 0.05, 0.004]]], dtype=torch.float64)
    ct = body_contacts(x, v[None], MeshQuery(v, f), 0.02, PinchQuery(v, f, arm), 0.007,
                       push=True)
    assert ct.pinched.tolist() == [[True]]
    torch.testing.assert_close(ct.normal[0, 0], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))


def test_push_refuses_bad_input():
    n = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    o = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    p = np.array([True, False])
    np.testing.assert_allclose(push_normal(n, o, p), [[np.sqrt(0.5), 0, np.sqrt(0.5)], [1, 0, 0]])
    with pytest.raises(ValueError, match="pinched"):
        push_normal(n, o, p.astype(int))
    with pytest.raises(ValueError, match="pinched"):
        push_normal(n, o, p[:1])
    with pytest.raises(ValueError, match="normal"):
        push_normal(n, o[:1], p)
    with pytest.raises(ValueError, match="normal"):
        push_normal(n, np.full_like(o, np.nan), p)
    v, f, _ = wedge()
    with pytest.raises(ValueError, match="push"):
        body_contacts(torch.zeros(1, 2, 3), v[None], MeshQuery(v, f), 0.02, push=True)
    s = TrainSettings()
    assert s.pinch_push is False and "pinch_push" not in s.key_dict()
    t = s.replace(pinch_push=True)
    assert t.key_dict()["pinch_push"] is True
    assert TrainSettings.from_dict(dataclasses.asdict(t)) == t
    with pytest.raises(TypeError, match="pinch_push"):
        s.replace(pinch_push=1)
    with pytest.raises(ValueError, match="pinch_push"):
        s.replace(pinch_push=True, collision_eps=0.0)


def test_push_cli_option(tmp_path):
    from draping.gaps.cli import _settings
    from polygeo.cli import build_parser

    base = ["train-drape", "--garment", "dress", "-o", str(tmp_path / "r")]
    parser = build_parser()
    assert _settings(parser.parse_args([*base, "--pinch-push"])).pinch_push is True
    assert _settings(parser.parse_args(base)).pinch_push is False
