"""Stiff, snug waistbands: per-face membrane stiffness and the skirt that stays on the hips."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from draping import _minimize
from draping import physics as P
from draping import reference as R
from draping.garments import Garment, face_stiffness


def _two_triangles():
    v = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]])
    f = np.array([[0, 1, 2], [1, 3, 2]])
    return v, f


def test_face_stiffness_scales_each_face_membrane_energy():
    v, f = _two_triangles()
    plain = P.rest_state(v, f)
    stiff = P.rest_state(v, f, face_stiffness=[3.0, 0.5])
    x = torch.tensor(v * np.array([1.1, 0.95, 1.0]) + np.array([0, 0, 0.0]))
    per_face = P.stvk_energy(x, plain, reduction="none")
    want = 3.0 * per_face[0] + 0.5 * per_face[1]
    assert float(P.stvk_energy(x, stiff)) == pytest.approx(float(want), rel=1e-12)
    # masses do not change
    torch.testing.assert_close(stiff.mass, plain.mass)
    # the solver's fused objective agrees with the torch energy
    st = R.SolverSettings(bending=False)
    pb = R._problem(stiff, st, None, None, None, None, None)
    e, _, _ = _minimize.evaluate(R._objective(pb, x.numpy()), x.numpy())
    assert e == pytest.approx(float(R.frame_energy(x, stiff, st)), rel=1e-12)


@pytest.mark.parametrize("bad", [[1.0], [1.0, -2.0], [1.0, float("nan")]])
def test_face_stiffness_rejects_bad_values(bad):
    v, f = _two_triangles()
    with pytest.raises(ValueError, match="face_stiffness"):
        P.rest_state(v, f, face_stiffness=bad)


def test_garment_face_stiffness_from_info():
    v, f = _two_triangles()
    assert face_stiffness(Garment("g", v, f, {})) is None
    g = Garment("g", v, f, {"waistband": {"faces": [1], "stiffness": 40.0}})
    np.testing.assert_array_equal(face_stiffness(g), [1.0, 40.0])
    with pytest.raises(ValueError, match="waistband"):
        face_stiffness(Garment("g", v, f, {"waistband": {"faces": [2], "stiffness": 40.0}}))
    with pytest.raises(ValueError, match="waistband"):
        face_stiffness(Garment("g", v, f, {"waistband": {"faces": [0], "stiffness": -1.0}}))


def _hull_perimeter(points2: np.ndarray) -> float:
    from scipy.spatial import ConvexHull

    return float(ConvexHull(points2).area)  # in 2-D, ``area`` is the perimeter


@pytest.mark.slow
def test_shipped_skirt_stays_on_the_hips_while_walking():
    """The waist ring may not slide below the height where the body is wider than it.

    A closed ring around the body is at least as long as the convex hull of the body's
    cross-section; so a ring of rest length ``P0`` can only pass a section of hull perimeter
    ``P`` by stretching by ``P / P0 - 1``. The bound is the first height below the waist
    where that exceeds the 3 % edge-strain target of the reference drapes: the ring's drop
    against the skinned (pelvis-following) garment must stay above it.
    """
    from draping.drape import DrapeJob, drape_frames, prepare
    from draping.garment_fit import boundary_loops

    scene = prepare(DrapeJob(garment="skirt", motion="walk", frames=4))
    g = scene.garment
    assert face_stiffness(g) is not None  # the shipped skirt has its stiff waistband
    ring = max(boundary_loops(g.faces), key=lambda lp: g.vertices[lp, 2].mean())
    p = g.vertices[ring]
    p0 = float(np.linalg.norm(p - np.roll(p, 1, 0), axis=1).sum())
    z_waist = float(p[:, 2].mean())
    # the torso and legs of the rest body (the hands hang beside the hips)
    from draping.body import AnnyBody

    anny = AnnyBody.load(dtype=torch.float64)
    w, idx = anny.skin_weights.numpy(), anny.skin_indices.numpy()
    dominant = idx[np.arange(len(idx)), w.argmax(1)]
    arm_words = ("arm", "hand", "wrist", "finger", "thumb", "metacarpal", "shoulder", "clavicle")
    arm = np.array([any(k in anny.bone_names[d].lower() for k in arm_words) for d in dominant])
    body = scene.body_vertices[0].numpy()[~arm]
    z_stop = None
    for z in np.arange(z_waist, z_waist - 0.5, -0.005):
        sl = body[np.abs(body[:, 2] - z) < 0.005]
        if len(sl) >= 3 and _hull_perimeter(sl[:, :2]) >= 1.03 * p0:
            z_stop = z
            break
    assert z_stop is not None
    bound = z_waist - z_stop  # m
    for fr in drape_frames(scene):
        drop = float(scene.skinned[fr.frame].numpy()[ring, 2].mean() - fr.x.numpy()[ring, 2].mean())
        assert drop < bound, (fr.frame, drop, bound)
        assert fr.row["eps_c"] <= 0.5


@pytest.mark.parametrize("name", ["skirt", "pants"])
def test_shipped_waistbands_are_stiff_rings_at_the_top(name):
    from draping.garment_fit import boundary_loops
    from draping.garments import WAISTBAND_HEIGHT, garment

    g = garment(name)
    k = face_stiffness(g)
    assert k is not None and k.max() > 1.0
    band = k > 1.0
    ring = max(boundary_loops(g.faces), key=lambda lp: g.vertices[lp, 2].mean())
    z_low = g.vertices[ring, 2].min() - WAISTBAND_HEIGHT * g.info["hip_to_neck"]
    assert (g.vertices[g.faces[band], 2].min(1) >= z_low).all()
    # the band goes all the way round: every waist-ring vertex is on a stiff face
    on_band = np.zeros(len(g.vertices), bool)
    on_band[g.faces[band].ravel()] = True
    assert on_band[ring].all()
