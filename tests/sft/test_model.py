"""sft.model: jet-patch template, PolySfT deformation and the per-vertex baseline."""

import numpy as np
import pytest
import torch

from polygeo import jets
from polygeo.frames import axis_angle_to_matrix
from sft.model import JetModel, JetTemplate, VertexModel, build_model


def sheet(nx=9, ny=7, bend=0.0):
    """A 24 x 18 cm sheet 40 cm in front of the camera, optionally bent (cylinder)."""
    a, b = np.meshgrid(np.linspace(-0.12, 0.12, nx), np.linspace(-0.09, 0.09, ny))
    a, b = a.ravel(), b.ravel()
    if bend:
        r = 1.0 / bend
        x, z = r * np.sin(a / r), r * (1 - np.cos(a / r))
    else:
        x, z = a, np.zeros_like(a)
    verts = np.stack([x, b, 0.4 + z], 1)
    faces = []
    for j in range(ny - 1):
        for i in range(nx - 1):
            v = j * nx + i
            faces += [[v, v + 1, v + nx], [v + 1, v + nx + 1, v + nx]]
    return verts, np.array(faces)


def stack(params, n):
    return {k: v[None].repeat(n, *[1] * v.ndim) for k, v in params.items()}


@pytest.mark.parametrize("order, patches", [(2, 1), (4, 1), (3, 4)])
def test_zero_parameters_reproduce_template(order, patches):
    v, f = sheet(bend=5.0)
    m = build_model("polysft", v, f, order=order, patches=patches, dtype=torch.float64)
    X = m.vertices(stack(m.init_params(), 2))
    np.testing.assert_allclose(X[1].numpy(), v, atol=1e-12)
    # positions coincide exactly; the jets of two patches have slightly different normals
    assert float(m.regularizer(stack(m.init_params(), 1))) < 1e-6


def test_jet_fit_exact_on_polynomial_sheet():
    # the template is a quadratic height field: an order-2 jet represents it exactly
    a, b = np.meshgrid(np.linspace(-1, 1, 11), np.linspace(-1, 1, 9))
    z = 0.1 * a**2 - 0.05 * a * b + 0.02
    v = np.stack([a.ravel(), b.ravel(), z.ravel()], 1)
    _, f = sheet(11, 9)
    t = JetTemplate.fit(v, f, order=2)
    assert t.fit_rms < 1e-12
    assert t.n_patches == 1 and t.n_samples == len(v)
    r = float(t.uv.norm(dim=1).max())
    assert 0.9 < r <= 1.0 + 1e-12  # normalised: the patch lies in the unit ball


def test_rigid_parameters_move_rigidly():
    v, f = sheet(bend=4.0)
    for m in (build_model("polysft", v, f, dtype=torch.float64),
              build_model("vertex", v, f, dtype=torch.float64)):
        p = stack(m.init_params(), 1)
        p["rot"] = torch.tensor([[0.05, -0.1, 0.02]], dtype=torch.float64)
        p["trans"] = torch.tensor([[0.01, 0.02, -0.03]], dtype=torch.float64)
        X = m.vertices(p)[0].numpy()
        # pairwise distances are preserved and the motion is the documented one
        d0 = np.linalg.norm(v[:, None] - v[None], axis=-1)
        d1 = np.linalg.norm(X[:, None] - X[None], axis=-1)
        np.testing.assert_allclose(d1, d0, atol=1e-12)
        fr = m._frame
        Rc = axis_angle_to_matrix(p["rot"][0]).numpy()
        s, R, T = float(fr.s[0]), fr.R[0].numpy(), fr.T[0].numpy()
        expect = s * ((((v - T) @ R / s) @ Rc.T + p["trans"][0].numpy()) @ R.T) + T
        np.testing.assert_allclose(X, expect, atol=1e-12)


def test_alpha_offsets_change_heights_along_the_normal():
    v, f = sheet()
    m = build_model("polysft", v, f, order=2, dtype=torch.float64)
    p = stack(m.init_params(), 1)
    p["d_alpha"][0, 0, 0] = 0.1  # constant term: a shift along the patch normal
    X = m.vertices(p)[0].numpy()
    n = m.template.orientation.R[0, :, 2].numpy()
    shift = X - v
    np.testing.assert_allclose(shift, np.outer(np.full(len(v), 0.1 * m.scale), n), atol=1e-12)


def test_auto_order_masks_high_degree_offsets():
    v, f = sheet()
    m = build_model("polysft", v, f, order="auto", max_order=4, dtype=torch.float64)
    assert m.order == 2 and m.max_order == 4
    p = stack(m.init_params(), 1)
    p["d_alpha"][0, 0, -1] = 1.0  # a v^4 coefficient: inactive at order 2
    np.testing.assert_allclose(m.vertices(p)[0].numpy(), v, atol=1e-12)
    m.set_order(4)
    assert np.abs(m.vertices(p)[0].numpy() - v).max() > 1e-3
    m.load_state({"order": 3})
    assert m.state() == {"order": 3}


def test_batched_equals_per_frame():
    v, f = sheet(bend=3.0)
    g = torch.Generator().manual_seed(0)
    for m in (build_model("polysft", v, f, order=3, patches=3, dtype=torch.float64),
              build_model("vertex", v, f, dtype=torch.float64)):
        p = {k: 0.01 * torch.randn((3, *t.shape), generator=g, dtype=torch.float64)
             for k, t in m.init_params().items()}
        X = m.vertices(p)
        for i in range(3):
            Xi = m.vertices({k: t[i : i + 1] for k, t in p.items()})[0]
            torch.testing.assert_close(X[i], Xi, rtol=0, atol=1e-14)


def test_gradcheck_vertices_and_boundary_term():
    v, f = sheet(5, 4, bend=3.0)
    m = build_model("polysft", v, f, order=2, patches=2, dtype=torch.float64)
    g = torch.Generator().manual_seed(1)
    base = {k: 0.02 * torch.randn((1, *t.shape), generator=g, dtype=torch.float64)
            for k, t in m.init_params().items()}
    names = list(base)

    def fn(*xs):
        p = dict(zip(names, xs))
        return m.vertices(p), m.regularizer(p)

    inputs = tuple(base[n].requires_grad_(True) for n in names)
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6)
    mv = build_model("vertex", v, f, dtype=torch.float64)
    pv = {k: 0.02 * torch.randn((1, *t.shape), generator=g, dtype=torch.float64)
          .requires_grad_(True) for k, t in mv.init_params().items()}
    nv = list(pv)
    assert torch.autograd.gradcheck(lambda *xs: mv.vertices(dict(zip(nv, xs))),
                                    tuple(pv[n] for n in nv), eps=1e-6, atol=1e-6)


def test_boundary_term_penalises_torn_patches():
    v, f = sheet(bend=3.0)
    m = build_model("polysft", v, f, order=2, patches=3, dtype=torch.float64)
    assert len(m.template.pairs) > 0
    p = stack(m.init_params(), 1)
    p["d_alpha"][0, 0, 0] = 0.05  # lift patch 0 only: tears it from its neighbours
    assert float(m.regularizer(p)) > 1e-4
    # a rigid motion keeps them together: the term keeps its (tiny) template value
    p = stack(m.init_params(), 1)
    base = float(m.regularizer(p))
    p["rot"][0] = torch.tensor([0.1, 0.0, 0.0])
    p["trans"][0] = torch.tensor([0.0, 0.2, 0.0])
    assert float(m.regularizer(p)) == pytest.approx(base, rel=1e-6, abs=1e-18)


def test_model_validation():
    v, f = sheet()
    with pytest.raises(ValueError, match="method: expected 'polysft' or 'vertex'"):
        build_model("mesh", v, f)
    with pytest.raises(ValueError, match="order: expected an integer in"):
        build_model("polysft", v, f, order="high")
    with pytest.raises(ValueError, match="order: expected an integer in"):
        build_model("polysft", v, f, order=7)
    with pytest.raises(ValueError, match="verts: expected shape"):
        build_model("polysft", v[:, :2], f)
    bad = v.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="verts: expected finite values"):
        build_model("vertex", bad, f)
    vs, fs = sheet(4, 3)
    with pytest.raises(ValueError, match="verts: the template has 12 vertices, fewer than the 28"):
        JetTemplate.fit(vs, fs, order=6)
    m = JetModel(JetTemplate.fit(v, f, order=3))
    with pytest.raises(ValueError, match="order: expected an integer in \\[1, 3\\]"):
        m.set_order(4)
    assert isinstance(build_model("vertex", v, f), VertexModel)


def test_patch_rigid_parameters_only_with_several_patches():
    v, f = sheet(bend=3.0)
    one = build_model("polysft", v, f, order=2, patches=1, dtype=torch.float64)
    assert "p_rot" not in one.init_params() and "p_rot" not in one.groups
    many = build_model("polysft", v, f, order=2, patches=3, dtype=torch.float64)
    p = many.init_params()
    assert p["p_rot"].shape == (3, 3) and p["p_trans"].shape == (3, 3)
    assert many.groups["p_rot"] == many.groups["p_trans"] == "lr_patch"
    off = build_model("polysft", v, f, order=2, patches=3, patch_rigid=False,
                      dtype=torch.float64)
    assert "p_rot" not in off.init_params()


def test_equal_patch_motions_are_the_global_rigid_motion():
    # every patch rotated by the same R about the global origin (p_trans_k = R b_k - b_k)
    # moves the sheet rigidly: same vertices as the global (rot, trans) and no tearing
    v, f = sheet(bend=3.0)
    m = build_model("polysft", v, f, order=3, patches=4, dtype=torch.float64)
    r = torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)
    R = axis_angle_to_matrix(r)
    p = stack(m.init_params(), 1)
    base_reg = float(m.regularizer(p))
    p["p_rot"][0] = r
    p["p_trans"][0] = m._b @ R.T - m._b
    q = stack(m.init_params(), 1)
    q["rot"][0] = r
    torch.testing.assert_close(m.vertices(p), m.vertices(q), rtol=0, atol=1e-13)
    assert float(m.regularizer(p)) == pytest.approx(base_reg, rel=1e-6, abs=1e-18)
    # one patch moved alone tears it from its neighbours
    p = stack(m.init_params(), 1)
    p["p_rot"][0, 0] = torch.tensor([0.0, 0.3, 0.0])
    assert float(m.regularizer(p)) > base_reg + 1e-4


def _hinge(verts, angle, width=0.02):
    """Fold the flat sheet ``sheet()`` isometrically about the line x = 0 by ``angle``."""
    a, b = verts[:, 0], verts[:, 1]
    s = np.linspace(-0.13, 0.13, 4001)
    t = np.clip((s + width / 2) / width, 0.0, 1.0)
    psi = angle * t * t * (3 - 2 * t)
    x = np.concatenate([[0.0], np.cumsum(0.5 * (np.cos(psi[1:]) + np.cos(psi[:-1])) * np.diff(s))])
    z = np.concatenate([[0.0], np.cumsum(0.5 * (np.sin(psi[1:]) + np.sin(psi[:-1])) * np.diff(s))])
    x -= np.interp(0.0, s, x)
    z -= np.interp(0.0, s, z)
    return np.stack([np.interp(a, s, x), b, 0.4 + np.interp(a, s, z)], 1)


@pytest.mark.slow
def test_patch_rigid_motions_fit_a_sharp_fold():
    # a 160-degree fold fitted in 3D (no images): the two halves become the two patches,
    # their rigid motions take the halves apart and the jets bend the crease; the boundary
    # term keeps the halves joined
    v, f = sheet(13, 7)
    target = torch.as_tensor(_hinge(v, np.radians(160.0)))
    m = build_model("polysft", v, f, order=3, patches=2, dtype=torch.float64)
    labels = m.template.sample_patch[m.template.primary]
    assert len({int(x) for x in labels[v[:, 0] < -0.05]}) == 1  # the halves are the patches
    p = {k: t.clone().requires_grad_(True) for k, t in stack(m.init_params(), 1).items()}
    opt = torch.optim.Adam(p.values(), lr=2e-2)
    for _ in range(600):
        opt.zero_grad()
        X, reg = m.forward(p)
        loss = (X[0] - target).pow(2).sum(-1).mean() / m.scale**2 + reg
        loss.backward()
        opt.step()
    with torch.no_grad():
        X, reg = m.forward(p)
        err = (X[0] - target).norm(dim=-1)
    assert float(err.mean()) < 0.005  # 5 mm on a 24 cm sheet, fold at 2 cm width, order 3
    halves = (p["p_rot"][0, 0] - p["p_rot"][0, 1]).detach().norm()
    assert float(halves) > np.radians(40.0)  # the patch motions took a large part of it
    assert float(reg) < 1e-3


def _tilts(template, verts, faces):
    """Largest angle (deg) between a triangle and the axis of a patch holding one of its
    corners, computed here from the patch frames (independently of PatchMetrics)."""
    R = template.orientation.R.numpy()
    labels = np.empty(len(verts), dtype=np.int64)
    labels[template.sample_vertex.numpy()[template.primary.numpy()]] = \
        template.sample_patch.numpy()[template.primary.numpy()]
    p = verts[faces]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    out = 0.0
    for c in range(3):
        axis = R[labels[faces[:, c]], :, 2]
        out = max(out, np.degrees(np.arccos(np.clip((n * axis).sum(1), -1, 1))).max())
    return out


def test_auto_patches_one_for_a_sheet_several_for_a_tube():
    v, f = sheet(41, 15, bend=4.0)  # a gently bent sheet (radius 25 cm, 55 degrees)
    t = JetTemplate.fit(v, f, 4, "auto")
    assert t.n_patches == 1
    assert t.max_tilt == pytest.approx(_tilts(t, v, f), abs=1e-9) and t.max_tilt < 30
    # the same sheet rolled into a C-shaped tube (270 degrees): no height graph over one
    # plane (a single patch folds over), so "auto" splits it until every patch is steep
    # by at most max_tilt
    v, f = sheet(41, 15, bend=1.5 * np.pi / 0.24)
    one = JetTemplate.fit(v, f, 4, 1)
    assert one.max_tilt > 90
    for max_tilt in (70.0, 45.0):
        t = JetTemplate.fit(v, f, 4, "auto", max_tilt=max_tilt)
        assert t.n_patches > 1
        assert t.max_tilt == pytest.approx(_tilts(t, v, f), abs=1e-9)
        assert t.max_tilt <= max_tilt
        # the fewest of the counts tried (1, 2, ..., 8, 12, 18, ...): the count before fails
        prev = t.n_patches - 1 if t.n_patches <= 8 else {12: 8, 18: 12, 27: 18}[t.n_patches]
        assert JetTemplate.fit(v, f, 4, prev).max_tilt > max_tilt
        m = JetModel(t, dtype=torch.float64)
        X = m.vertices(stack(m.init_params(), 1))[0].numpy()
        np.testing.assert_allclose(X, v, atol=1e-12)


def test_auto_patches_warns_when_the_cap_leaves_steep_patches():
    v, f = sheet(41, 15, bend=1.5 * np.pi / 0.24)
    with pytest.warns(RuntimeWarning, match="patches='auto': 2 patches \\(the most tried\\)"):
        t = JetTemplate.fit(v, f, 4, "auto", max_tilt=20.0, max_patches=2)
    assert t.n_patches == 2 and t.max_tilt > 20
    with pytest.raises(ValueError, match="patches: expected an integer >= 1 or 'auto'"):
        JetTemplate.fit(v, f, 4, "some")
    with pytest.raises(ValueError, match="max_tilt: expected degrees in \\(0, 90\\)"):
        JetTemplate.fit(v, f, 4, "auto", max_tilt=120.0)
    with pytest.raises(ValueError, match="max_patches: expected an integer in"):
        JetTemplate.fit(v, f, 4, "auto", max_patches=0)


@pytest.mark.slow
@pytest.mark.parametrize("patches", [1, 3])
def test_params_for_projects_surfaces_onto_the_model(patches):
    v, f = sheet(25, 19, bend=3.0)
    m = build_model("polysft", v, f, order=4, patches=patches, dtype=torch.float64)
    # the template itself: zero parameters
    p0 = m.params_for(v)
    for k, x in p0.items():
        np.testing.assert_allclose(x.numpy(), 0.0, atol=1e-10, err_msg=k)
    # a rigid motion of the template: recovered exactly (as the global rigid motion)
    R = axis_angle_to_matrix(torch.tensor([0.3, -0.5, 0.2], dtype=torch.float64)).numpy()
    moved = (v - v.mean(0)) @ R.T + v.mean(0) + np.array([0.01, -0.02, 0.05])
    p = m.params_for(moved)
    X = m.vertices(stack(p, 1))[0].numpy()
    np.testing.assert_allclose(X, moved, atol=1e-10)
    assert float(p["d_alpha"].abs().max()) < 1e-9 and float(p["d_uv"].abs().max()) < 1e-9
    # another bend (not a polynomial of order 4): the projection is close, and no worse than
    # what fitting the parameters to the vertices by gradient descent reaches
    target = torch.as_tensor(sheet(25, 19, bend=7.0)[0] @ R.T)
    p = m.params_for(target)
    err = float((m.vertices(stack(p, 1))[0] - target).norm(dim=-1).max())
    q = {k: x.clone().requires_grad_(True) for k, x in stack(m.init_params(), 1).items()}
    opt = torch.optim.Adam(q.values(), lr=1e-2)
    for _ in range(1500):
        opt.zero_grad()
        loss = (m.vertices(q)[0] - target).pow(2).sum(-1).mean() / m.scale**2
        loss.backward()
        opt.step()
    with torch.no_grad():
        err_gd = float((m.vertices(q)[0] - target).norm(dim=-1).max())
    assert err < 2e-4  # 0.2 mm on a 24 cm sheet
    assert err <= 1.5 * err_gd + 1e-5
    with pytest.raises(ValueError, match="verts"):
        m.params_for(v[:-1])
    with pytest.raises(ValueError, match="verts"):
        m.params_for(np.full_like(v, np.nan))


def test_tilt_is_the_steepest_jet_slope():
    # a sheet bent into a cylinder arc of half-angle 0.12 m / 0.25 m = 27.5 degrees: the slope
    # of a one-patch jet over the chord plane reaches the arc's half-angle at its ends
    v, f = sheet(41, 15, bend=4.0)
    m = JetModel(JetTemplate.fit(v, f, 6, 1), dtype=torch.float64)
    p = m.init_params()
    tilt = m.tilt(p)
    assert tilt.shape == (1,)
    assert tilt[0] == pytest.approx(np.degrees(0.12 * 4.0), abs=0.5)
    # a rigid motion does not change it; offsets that steepen the jet do
    p["rot"] = torch.tensor([0.4, 0.1, -0.3], dtype=torch.float64)
    np.testing.assert_allclose(m.tilt(p), tilt, atol=1e-9)
    # several patches: each its own, all below the single patch's
    m4 = JetModel(JetTemplate.fit(v, f, 6, 4), dtype=torch.float64)
    t4 = m4.tilt(m4.init_params())
    assert t4.shape == (4,) and t4.max() < tilt[0] - 5
    # the same surface after a further bend (projected): steeper
    target = sheet(41, 15, bend=6.0)[0]
    assert m.tilt(m.params_for(target))[0] == pytest.approx(np.degrees(0.12 * 6.0), abs=1.0)


def test_auto_patches_on_jet_slopes():
    # "auto" bounded on the jets' slopes: every patch's jet within max_tilt (checked with an
    # independent finite difference of the fitted height field), the count before fails;
    # single rough triangles (noise on a few vertices) do not raise the count
    v, f = sheet(41, 15, bend=1.5 * np.pi / 0.24)
    t = JetTemplate.fit(v, f, 4, "auto", max_tilt=45.0, tilt="jet")
    assert t.n_patches > 1 and t.max_tilt <= 45.0
    m = JetModel(t, dtype=torch.float64)
    assert m.tilt(m.init_params()).max() == pytest.approx(t.max_tilt, abs=1e-9)
    h = 1e-6
    for k, sl in enumerate(t.slices):
        uv = t.uv[sl]
        c = t.coeffs[k]

        def z(q, c=c):
            return (jets.monomials(q, t.order) * c).sum(-1)

        gu = (z(uv + torch.tensor([h, 0.0], dtype=torch.float64))
              - z(uv - torch.tensor([h, 0.0], dtype=torch.float64))) / (2 * h)
        gv = (z(uv + torch.tensor([0.0, h], dtype=torch.float64))
              - z(uv - torch.tensor([0.0, h], dtype=torch.float64))) / (2 * h)
        assert np.degrees(np.arctan(float(torch.hypot(gu, gv).max()))) <= 45.0 + 1e-4
    prev = t.n_patches - 1 if t.n_patches <= 8 else {12: 8, 18: 12, 27: 18}[t.n_patches]
    assert JetTemplate.fit(v, f, 4, prev, tilt="jet").max_tilt > 45.0
    flat, f2 = sheet(25, 19)
    rough = flat.copy()
    rough[[100, 250, 300], 2] += 0.015  # three 15 mm spikes: single triangles at ~56 degrees
    assert JetTemplate.fit(rough, f2, 4, "auto", max_tilt=45.0, tilt="jet").n_patches == 1
    with pytest.warns(RuntimeWarning, match="still leave a triangle"):
        assert JetTemplate.fit(rough, f2, 4, "auto", max_tilt=45.0).n_patches > 1
    with pytest.raises(ValueError, match="tilt: expected one of"):
        JetTemplate.fit(v, f, 4, "auto", tilt="normals")
