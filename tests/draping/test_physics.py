"""Cloth energies of draping.physics against hand-computed values and analytic truths."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from draping import physics as P


def grid_sheet(n: int = 5, size: float = 1.0):
    """Flat square sheet in the xy plane, (n*n, 3) vertices, consistently wound."""
    u, v = np.meshgrid(np.linspace(0, size, n), np.linspace(0, size, n), indexing="ij")
    verts = np.stack([u.ravel(), v.ravel(), np.zeros(n * n)], 1)
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            b = a + n
            faces += [[a, b, a + 1], [a + 1, b, b + 1]]
    return verts, np.array(faces, dtype=np.int64)


def random_rotation(seed: int) -> torch.Tensor:
    q, _ = torch.linalg.qr(
        torch.randn(3, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    )
    return q * torch.sign(torch.linalg.det(q))


TRI_V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
TRI_F = np.array([[0, 1, 2]])


# ---------------------------------------------------------------------- material


def test_material_defaults_hand_values():
    m = P.Material()
    assert m.area_density == pytest.approx(426 * 4.7e-4)
    assert m.lame_mu == pytest.approx(0.7e5 / (2 * 1.485))
    assert m.lame_lambda == pytest.approx(0.7e5 * 0.485 / (1 - 0.485**2))
    m16 = P.Material(lame="eq16")
    assert m16.lame_lambda == pytest.approx(0.7e5 * 0.485 / (1.485 * 0.03))
    # SNUG's bending coefficient: 50 * E h^3 / (12 (1 - nu^2)) = 3.96e-5
    assert m.bending_stiffness == pytest.approx(3.96e-5, rel=1e-3)


@pytest.mark.parametrize(
    "kw",
    [
        {"density": 0},
        {"thickness": -1},
        {"young": float("nan")},
        {"poisson": 0.5},
        {"poisson": -0.1},
        {"bending_multiplier": -1},
        {"lame": "3d"},
    ],
)
def test_material_rejects_bad_values(kw):
    with pytest.raises(ValueError, match=next(iter(kw))):
        P.Material(**kw)


# ---------------------------------------------------------------------- rest state


def test_rest_state_masses_and_areas():
    v, f = grid_sheet(4, 0.3)
    r = P.rest_state(v, f)
    assert float(r.area.sum()) == pytest.approx(0.09)
    assert float(r.mass.sum()) == pytest.approx(0.09 * 426 * 4.7e-4)
    # a corner vertex with one triangle (area 0.005) gets a third of its mass
    assert float(r.mass[0]) == pytest.approx(0.005 / 3 * 426 * 4.7e-4)
    assert torch.allclose(r.hinges.angle, torch.zeros_like(r.hinges.angle))


def test_rest_state_rejects_bad_input():
    v, f = grid_sheet(3)
    with pytest.raises(ValueError, match="vertices"):
        P.rest_state(v[:, :2], f)
    with pytest.raises(ValueError, match="faces"):
        P.rest_state(v, f + 100)
    with pytest.raises(ValueError, match="degenerate"):
        P.rest_state(np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]), TRI_F)
    with pytest.raises(ValueError, match="vertices"):
        P.rest_state(np.full_like(v, np.nan), f)
    with pytest.raises(TypeError, match="material"):
        P.rest_state(v, f, material="cotton")


# ---------------------------------------------------------------------- membrane


def test_stvk_one_triangle_uniaxial_stretch():
    m = P.Material()
    r = P.rest_state(TRI_V, TRI_F, m)
    s = 1.2
    x = torch.tensor(TRI_V * np.array([s, 1, 1]))
    e11 = (s * s - 1) / 2
    psi = m.lame_mu * e11**2 + 0.5 * m.lame_lambda * e11**2
    assert float(P.stvk_energy(x, r)) == pytest.approx(m.thickness * 0.5 * psi, rel=1e-12)
    e = P.green_strain(x, r)[0]
    assert torch.allclose(e, torch.tensor([[e11, 0.0], [0.0, 0.0]], dtype=e.dtype), atol=1e-14)


def test_stvk_one_triangle_shear_rotated_template():
    """Pure shear of a template lying in an arbitrary plane (the local 2-D frame is free)."""
    m = P.Material()
    rot = random_rotation(1)
    rest_v = torch.tensor(TRI_V) @ rot.T
    r = P.rest_state(rest_v, TRI_F, m)
    g = 0.3
    x = torch.tensor([[0.0, 0, 0], [1, 0, 0], [g, 1, 0]], dtype=torch.float64)
    # F = [[1, g], [0, 1], [0, 0]], E = [[0, g/2], [g/2, g^2/2]]
    frob2 = g**2 / 2 + g**4 / 4
    tr = g**2 / 2
    want = m.thickness * 0.5 * (m.lame_mu * frob2 + 0.5 * m.lame_lambda * tr**2)
    assert float(P.stvk_energy(x, r)) == pytest.approx(want, rel=1e-12)


def test_zero_strain_and_bending_for_rigid_motions():
    v, f = grid_sheet(6, 0.5)
    r = P.rest_state(v, f)
    x0 = torch.tensor(v)
    # references: a 5 % stretch and a gentle fold of the same sheet
    stretched = x0 * torch.tensor([1.05, 1.0, 1.0], dtype=torch.float64)
    folded = x0.clone()
    folded[:, 2] = 0.1 * x0[:, 0] ** 2
    e_stretch = float(P.stvk_energy(stretched, r))
    e_inext = float(P.inextensibility_energy(stretched, r))
    e_fold = float(P.bending_energy(folded, r))
    assert min(e_stretch, e_inext, e_fold) > 0
    for seed in range(3):
        x = x0 @ random_rotation(seed).T + torch.tensor([0.3, -1.0, 2.0], dtype=torch.float64)
        assert float(P.stvk_energy(x, r)) < 1e-12 * e_stretch
        assert float(P.bending_energy(x, r)) < 1e-12 * e_fold
        assert float(P.inextensibility_energy(x, r)) < 1e-10 * e_inext


# ---------------------------------------------------------------------- bending


def hinge(phi: float):
    """Two unit-leg triangles on the edge (0,0,0)-(0,1,0); the second folded by ``phi``."""
    v = np.array([[0.0, 0, 0], [0, 1, 0], [1, 0.5, 0], [-math.cos(phi), 0.5, math.sin(phi)]])
    f = np.array([[0, 2, 1], [0, 1, 3]])
    return v, f


@pytest.mark.parametrize("phi", [0.3, 1.0, 2.5])
def test_bending_folded_pair_analytic(phi):
    v0, f = hinge(0.0)
    r = P.rest_state(v0, f)
    v, _ = hinge(phi)
    kb = r.material.bending_stiffness
    # l = 1, A_0 = A_1 = 1/2: k_b * 1 / (8 * 1) * phi^2
    e = P.bending_energy(torch.tensor(v), r)
    assert float(e) == pytest.approx(kb / 8 * phi**2, rel=1e-10)
    assert float(P.bending_energy(torch.tensor(v), r, stiffness=2.0)) == pytest.approx(
        2.0 / 8 * phi**2, rel=1e-10
    )


def test_bending_rest_angle_and_gaps_blend():
    v0, f = hinge(0.8)
    r = P.rest_state(v0, f)  # curved template: theta_r = +-0.8
    assert abs(float(r.hinges.angle[0])) == pytest.approx(0.8)
    x_rest = torch.tensor(v0)
    x, _ = hinge(1.1)
    x = torch.tensor(x)
    assert float(P.bending_energy(x_rest, r, rest_angle=True)) < 1e-24
    assert float(P.gaps_bending_energy(x_rest, r, alpha=1.0)) < 1e-24
    plain = P.bending_energy(x, r)
    rel = P.bending_energy(x, r, rest_angle=True)
    w = r.material.bending_stiffness * float(r.hinge_weight[0])
    assert float(plain) == pytest.approx(w * 1.1**2, rel=1e-10)
    assert float(rel) == pytest.approx(w * 0.3**2, rel=1e-10)
    assert float(P.gaps_bending_energy(x, r, alpha=0.0)) == pytest.approx(float(plain))
    mix = P.gaps_bending_energy(x, r, alpha=torch.tensor([0.25], dtype=torch.float64))
    assert float(mix) == pytest.approx(0.25 * float(rel) + 0.75 * float(plain), rel=1e-12)
    with pytest.raises(ValueError, match="alpha"):
        P.gaps_bending_energy(x, r, alpha=1.5)
    with pytest.raises(ValueError, match="alpha"):
        P.gaps_bending_energy(x, r, alpha=torch.zeros(3))


# ---------------------------------------------------------------------- gravity, inertia


def test_gravity_hand_value():
    v, f = grid_sheet(4, 2.0)
    r = P.rest_state(v, f)
    x = torch.tensor(v) + torch.tensor([0.0, 0.0, 1.5], dtype=torch.float64)
    mtot = 4.0 * 426 * 4.7e-4
    assert float(P.gravity_energy(x, r)) == pytest.approx(mtot * 9.81 * 1.5)
    e = P.gravity_energy(x, r, gravity=(0.0, -2.0, 0.0))
    assert float(e) == pytest.approx(mtot * 2.0 * float(x[:, 1].mean()))
    with pytest.raises(ValueError, match="gravity"):
        P.gravity_energy(x, r, gravity=(0.0, 9.81))


def test_inertia_hand_value():
    r = P.rest_state(TRI_V, TRI_F)
    m = r.mass
    x_prev = torch.tensor(TRI_V)
    v_prev = torch.tensor([[1.0, 0, 0]] * 3, dtype=torch.float64)
    dt = 0.1
    x = x_prev + torch.tensor([0.0, 0.0, 0.2], dtype=torch.float64)
    # |x - x_prev - dt v|^2 = 0.1^2 + 0.2^2 per vertex
    want = float(m.sum()) * 0.05 / (2 * dt * dt)
    assert float(P.inertia_energy(x, x_prev, v_prev, r, dt)) == pytest.approx(want)
    with pytest.raises(ValueError, match="dt"):
        P.inertia_energy(x, x_prev, v_prev, r, 0.0)


def test_free_fall_step_is_a_critical_point():
    """x = x_prev + dt v + dt^2 g makes the total energy stationary: the sheet accelerates at g."""
    v, f = grid_sheet(5, 0.4)
    r = P.rest_state(v, f)
    dt = 1 / 30
    x_prev = torch.tensor(v) @ random_rotation(3).T
    v_prev = torch.tensor([0.2, 0.0, -0.5], dtype=torch.float64).expand(25, 3)
    g = torch.tensor(P.GRAVITY, dtype=torch.float64)
    x = (x_prev + dt * v_prev + dt * dt * g).requires_grad_()
    total = (
        P.stvk_energy(x, r)
        + P.bending_energy(x, r)
        + P.gravity_energy(x, r)
        + P.inertia_energy(x, x_prev, v_prev, r, dt)
    )
    (grad,) = torch.autograd.grad(total, x)
    weight = float(r.mass.max()) * 9.81
    assert float(grad.abs().max()) < 1e-9 * weight
    # and a displaced x is not stationary
    y = (x.detach() + 1e-3).requires_grad_()
    tot2 = P.gravity_energy(y, r) + P.inertia_energy(y, x_prev, v_prev, r, dt)
    (g2,) = torch.autograd.grad(tot2, y)
    assert float(g2.abs().max()) > 1e-3 * weight


# ---------------------------------------------------------------------- collisions


def test_collision_hand_value():
    d = torch.tensor([[0.005, 0.001, -0.001]], dtype=torch.float64)
    e = P.collision_energy(d, stiffness=10.0, eps=2e-3)
    assert float(e[0]) == pytest.approx(10.0 * (1e-9 + 27e-9))
    per = P.collision_energy(d, 10.0, reduction="none")
    assert per.shape == (1, 3) and float(per[0, 0]) == 0.0
    with pytest.raises(ValueError, match="stiffness"):
        P.collision_energy(d, -1.0)
    with pytest.raises(TypeError, match="distance"):
        P.collision_energy([0.1, 0.2])
    with pytest.raises(ValueError, match="reduction"):
        P.collision_energy(d, reduction="mean")


def test_plane_distance():
    x = torch.tensor([[0.0, 0.0, 1.0], [1.0, 2.0, -0.5]])
    p = torch.zeros(2, 3)
    n = torch.tensor([[0.0, 0.0, 1.0]]).expand(2, 3)
    assert torch.allclose(P.plane_distance(x, p, n), torch.tensor([1.0, -0.5]))
    with pytest.raises(ValueError, match="anchor"):
        P.plane_distance(x, torch.zeros(3, 3), n)


def test_repulsion_two_layers_hand_value():
    v, f = grid_sheet(4, 0.3)  # spacing 0.1
    top = v + np.array([0.0, 0.0, 0.02])
    verts = np.concatenate([v, top])
    faces = np.concatenate([f, f + 16])
    r = P.rest_state(verts, faces)
    delta = 0.03
    pairs = P.repulsion_pairs(verts, r, delta, k=4)
    assert pairs.shape == (32, 4)
    # each vertex sees exactly its twin across the gap (in-sheet neighbours are >= 0.1 away)
    cnt = (pairs >= 0).sum(1)
    assert torch.all(cnt == 1)
    assert torch.all(pairs[:16, 0] == torch.arange(16, 32))
    e = P.repulsion_energy(torch.tensor(verts), pairs, delta, weight=0.5)
    assert float(e) == pytest.approx(0.5 * 32 * -math.log((0.02 / 0.03) ** 2))
    # pulled apart beyond delta: no energy
    far = torch.tensor(np.concatenate([v, v + np.array([0.0, 0.0, 0.05])]))
    assert float(P.repulsion_energy(far, pairs, delta)) == 0.0


def test_repulsion_excludes_adjacent_vertices():
    v, f = grid_sheet(4, 0.3)
    r = P.rest_state(v, f)
    pairs = P.repulsion_pairs(v, r, delta=0.12, k=8)  # the 1-ring lies at 0.1
    assert int((pairs >= 0).sum()) == 0
    pairs = P.repulsion_pairs(v, r, delta=0.15, k=8)  # the non-adjacent diagonal at 0.141
    assert int((pairs >= 0).sum()) > 0
    with pytest.raises(ValueError, match="delta"):
        P.repulsion_pairs(v, r, delta=0.0)
    with pytest.raises(ValueError, match="k"):
        P.repulsion_pairs(v, r, delta=0.1, k=0)


# ---------------------------------------------------------------------- GAPS inextensibility


def test_inextensibility_stretch_positive_and_k_ext_compensates():
    v, f = grid_sheet(5, 0.4)
    r = P.rest_state(v, f)
    x = torch.tensor(v) * 1.1
    e1 = P.inextensibility_energy(x, r, k_ext=1.0, weight=1.0)
    assert float(e1) > 0
    # a uniform in-plane scale s multiplies each 1-ring covariance by s^2: k_ext = 1.21 at rest
    e2 = P.inextensibility_energy(x, r, k_ext=1.21, weight=1.0)
    assert float(e2) < 1e-12 * float(e1)


def test_k_ext_schedule_hand_values():
    d = torch.tensor([0.01, 0.0015, -0.01])
    k = P.k_ext_schedule(d, epoch=50)
    # d_c = [0, 0.0005, 0.012] -> min(10 d_c, 0.03) = [0, 0.005, 0.03]
    assert torch.allclose(k, torch.tensor([1.0, 1.25, 2.5]))
    assert torch.allclose(P.k_ext_schedule(d, epoch=500), torch.tensor([1.0, 1.5, 4.0]))
    with pytest.raises(ValueError, match="epoch"):
        P.k_ext_schedule(d, epoch=-1)



def test_k_ext_rings_reach_the_cloth_around_a_contact():
    """With ``rings`` the 1-ring neighbours of a contact share its allowance (eq. (45)'s value
    at the contact), vertices farther away keep 1; colliding vertices keep eq. (45) exactly,
    also next to a deeper contact; ``rings=0`` is eq. (45) as written."""
    v, f = grid_sheet(7, 0.6)  # 7 x 7 vertices, row-major; vertex 24 is the centre
    r = P.rest_state(v, f)
    n = len(v)
    d = torch.full((n,), 0.01, dtype=torch.float64)
    d[24] = -0.01  # deep: d_c = 0.012 -> min(10 d_c, 0.03) = 0.03
    d[25] = 0.0015  # shallow contact next to it: d_c = 0.0005
    plain = P.k_ext_schedule(d, 50)
    k1 = P.k_ext_schedule(d, 50, rest=r, rings=1)
    k2 = P.k_ext_schedule(d, 50, rest=r, rings=2)
    contact = d < 2e-3
    torch.testing.assert_close(k1[contact], plain[contact])
    torch.testing.assert_close(k2[contact], plain[contact])
    torch.testing.assert_close(P.k_ext_schedule(d, 50, rest=r, rings=0), plain)
    ring1 = set(int(j) for j in r.ring_index[24][r.ring_mask[24]]) - {24, 25}
    far = [i for i in range(n) if i not in ring1 | {24, 25}]
    assert ring1 and far
    for j in ring1:  # a non-contact neighbour of the deep contact: its allowance
        assert float(plain[j]) == 1.0
        assert float(k1[j]) == pytest.approx(float(plain[24]))
    # one ring further: reached with rings=2, not with rings=1
    ring2 = set()
    for j in ring1:
        ring2 |= set(int(i) for i in r.ring_index[j][r.ring_mask[j]])
    ring2 -= ring1 | {24, 25}
    ring2 -= set(int(i) for i in r.ring_index[25][r.ring_mask[25]])  # the shallow one's ring
    assert ring2
    for j in ring2:
        assert float(k1[j]) == 1.0
        assert float(k2[j]) == pytest.approx(float(plain[24]))
    untouched = [i for i in far if i not in ring2 and float(k2[i]) == 1.0]
    assert len(untouched) > n // 3  # the rest of the sheet stays inextensible
    # batched distances, float32
    kb = P.k_ext_schedule(torch.stack([d, d]).float(), 50, rest=r, rings=1)
    torch.testing.assert_close(kb[1], k1.float())


def test_spread_over_rings_is_a_graph_max_dilation_and_validates():
    v, f = grid_sheet(5, 0.4)
    r = P.rest_state(v, f)
    x = torch.zeros(len(v))
    x[0] = 2.0  # a corner
    one = P.spread_over_rings(x, r, 1)
    # independent: the corner's neighbours from the faces
    nb = {0} | {int(j) for tri in f if 0 in tri for j in tri}
    assert set(torch.nonzero(one).flatten().tolist()) == nb
    torch.testing.assert_close(P.spread_over_rings(x, r, 0), x)
    with pytest.raises(ValueError, match="rest"):
        P.k_ext_schedule(torch.zeros(len(v)), 5, rings=1)
    with pytest.raises(ValueError, match="rings"):
        P.k_ext_schedule(torch.zeros(len(v)), 5, rest=r, rings=-1)
    with pytest.raises(ValueError, match="values"):
        P.spread_over_rings(torch.zeros(len(v) + 1), r, 1)


# ---------------------------------------------------------------------- batches, gradients


def test_batched_equals_per_frame():
    v, f = grid_sheet(4, 0.3)
    r = P.rest_state(v, f)
    gen = torch.Generator().manual_seed(4)
    xb = torch.tensor(v) + 0.02 * torch.randn(3, 16, 3, generator=gen, dtype=torch.float64)
    for fn in (P.stvk_energy, P.bending_energy, P.gravity_energy, P.inextensibility_energy):
        batch = fn(xb, r)
        assert batch.shape == (3,)
        single = torch.stack([fn(xb[i], r) for i in range(3)])
        assert torch.allclose(batch, single, rtol=1e-12, atol=0)


def test_gradcheck_every_energy():
    v, f = grid_sheet(3, 0.2)
    r = P.rest_state(v, f)
    gen = torch.Generator().manual_seed(5)
    x = torch.tensor(v) + 0.01 * torch.randn(9, 3, generator=gen, dtype=torch.float64)
    x.requires_grad_()
    x_prev = torch.tensor(v)
    v_prev = torch.zeros(9, 3, dtype=torch.float64)
    normal = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64).expand(9, 3)
    anchor = torch.zeros(9, 3, dtype=torch.float64)
    pairs = P.repulsion_pairs(x.detach(), r, delta=0.2, k=6)
    alpha = torch.linspace(0, 1, r.hinge_weight.shape[0], dtype=torch.float64)
    fns = [
        lambda y: P.stvk_energy(y, r),
        lambda y: P.bending_energy(y, r),
        lambda y: P.bending_energy(y, r, rest_angle=True),
        lambda y: P.gaps_bending_energy(y, r, alpha),
        lambda y: P.gravity_energy(y, r),
        lambda y: P.inertia_energy(y, x_prev, v_prev, r, 0.05),
        lambda y: P.collision_energy(P.plane_distance(y, anchor, normal), 1e6, eps=0.02),
        lambda y: P.repulsion_energy(y, pairs, delta=0.2),
        lambda y: P.inextensibility_energy(y, r, k_ext=1.1, weight=1e6),
    ]
    for fn in fns:
        assert torch.autograd.gradcheck(fn, (x,))


def test_energies_reject_bad_positions():
    v, f = grid_sheet(3)
    r = P.rest_state(v, f)
    with pytest.raises(ValueError, match="x"):
        P.stvk_energy(torch.zeros(8, 3, dtype=torch.float64), r)
    with pytest.raises(TypeError, match="x"):
        P.bending_energy(torch.zeros(9, 3, dtype=torch.int64), r)
    with pytest.raises(TypeError, match="x"):
        P.gravity_energy(np.zeros((9, 3)), r)
    with pytest.raises(ValueError, match="reduction"):
        P.stvk_energy(torch.tensor(v), r, reduction="mean")
