"""The reference solver's curvature-corrected subspace step (``draping._minimize``)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from draping import _minimize
from draping import physics as P
from draping import reference as R


def grid_sheet(n: int, size: float, z: float):
    u, v = np.meshgrid(np.linspace(-size / 2, size / 2, n), np.linspace(-size / 2, size / 2, n),
                       indexing="ij")
    verts = np.stack([u.ravel(), v.ravel(), np.full(n * n, z)], 1)
    a = np.array([i * n + j for i in range(n - 1) for j in range(n - 1)])
    faces = np.concatenate([np.stack([a, a + n, a + 1], 1), np.stack([a + 1, a + n, a + n + 1], 1)])
    return verts, faces


def _frame(seed: int = 3):
    """A dynamic frame of a sheet pressed into a ball, compressed (indefinite exact Hessian)."""
    v, f = grid_sheet(5, 0.4, z=0.31)
    r = P.rest_state(v, f)
    rng = np.random.default_rng(seed)
    x_prev = torch.tensor(v)
    v_prev = torch.tensor(0.1 * rng.standard_normal(v.shape))
    # shrunk by 10 % in the plane (compressed cloth) and pushed 15 mm into the ball
    x = v * np.array([0.9, 0.9, 1.0]) + 0.003 * rng.standard_normal(v.shape)
    x = torch.tensor(x - np.array([0.0, 0.0, 0.015]))
    motion = torch.tensor(0.002 * rng.standard_normal(v.shape))
    st = R.SolverSettings()
    pb = R._problem(r, st, R.sphere_query([0, 0, 0], 0.3), None, x_prev, v_prev, 1 / 30, motion)
    ob = R._objective(pb, x.numpy())

    def energy(y):
        return R.frame_energy(
            y, r, st, x_prev=x_prev, v_prev=v_prev, dt=1 / 30,
            anchor=torch.from_numpy(ob.anchor), normal=torch.from_numpy(ob.normal),
            friction_reference=x_prev + motion,
            friction_weight=torch.from_numpy(ob.friction_weight),
        )

    return ob, x.numpy(), energy


def _autograd_hvp(energy, x: np.ndarray, v: np.ndarray) -> np.ndarray:
    _, hv = torch.autograd.functional.hvp(energy, torch.tensor(x), torch.tensor(v))
    return hv.numpy()


def test_hessian_vector_matches_autograd_of_the_torch_energy():
    ob, x, energy = _frame()
    ob = ob._replace(friction_eps=1e-9)  # no static-friction kink within the difference step
    _, g, _ = _minimize.evaluate(ob, x)
    hx = torch.autograd.functional.hessian(energy, torch.tensor(x)).reshape(75, 75).numpy()
    assert np.linalg.eigvalsh(hx).min() < 0  # the compressed sheet's energy is indefinite
    rng = np.random.default_rng(0)
    for _ in range(3):
        v = rng.standard_normal(x.shape)
        got = _minimize.hessian_vector(ob, x, g, v)
        want = _autograd_hvp(energy, x, v)
        np.testing.assert_allclose(got, want, atol=1e-5 * np.abs(want).max())
    assert not _minimize.hessian_vector(ob, x, g, np.zeros_like(x)).any()


def _model(hr, gr, c):
    return gr @ c + 0.5 * c @ hr @ c


def _brute_force(hr, br, gr, radius, n=20000):
    """Best of the model on the boundary ellipse and, if inside, its unconstrained minimum."""
    low = np.linalg.cholesky(br)
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = radius * np.linalg.solve(low.T, np.stack([np.cos(t), np.sin(t)]))  # c . br c = r^2
    vals = np.array([_model(hr, gr, c) for c in ring.T])
    best = vals.min()
    if np.linalg.eigvalsh(hr).min() > 0:
        c = -np.linalg.solve(hr, gr)
        if c @ br @ c <= radius**2:
            best = min(best, _model(hr, gr, c))
    return best


@pytest.mark.parametrize("seed", range(6))
def test_trust_region_2d_against_brute_force(seed):
    rng = np.random.default_rng(seed)
    a = rng.standard_normal((2, 2))
    br = a @ a.T + 0.3 * np.eye(2)
    hr = rng.standard_normal((2, 2))
    hr = hr + hr.T + (2.0 if seed % 2 == 0 else -1.0) * np.eye(2)  # definite or not
    gr = rng.standard_normal(2)
    for radius in (0.05, 0.5, 5.0):
        c, active = _minimize.trust_region_2d(hr, br, gr, radius)
        size = float(np.sqrt(c @ br @ c))
        assert size <= radius * (1 + 1e-9)
        assert _model(hr, gr, c) <= _brute_force(hr, br, gr, radius) + 1e-9 * (1 + abs(
            _model(hr, gr, c)))
        assert active == (size > radius * (1 - 1e-6))


def test_trust_region_2d_hard_case_and_interior():
    hr, br = np.diag([-2.0, 1.0]), np.eye(2)
    c, active = _minimize.trust_region_2d(hr, br, np.array([0.0, 0.5]), 2.0)
    assert active and c @ c == pytest.approx(4.0)  # gradient orthogonal to the saddle's axis
    assert _model(hr, np.array([0.0, 0.5]), c) == pytest.approx(
        _brute_force(hr, br, np.array([0.0, 0.5]), 2.0), abs=1e-6)
    c, active = _minimize.trust_region_2d(np.diag([2.0, 1.0]), br, np.array([1.0, 1.0]), 10.0)
    assert not active and np.allclose(c, [-0.5, -1.0])  # the Newton step, inside


def test_subspace_step_minimises_the_exact_model_over_the_two_directions():
    ob, x, energy = _frame(4)
    ob = ob._replace(friction_eps=1e-9)
    e, g, h = _minimize.evaluate(ob, x, want_hess=True)
    n = x.shape[0]
    pre = _minimize.laplacian_factor(ob, 1 / 30)
    d = _minimize._pcg(h, -g.ravel(), lambda r: pre(r).ravel(), 0.3, 200).reshape(n, 3)
    s = 1e-3 * np.random.default_rng(5).standard_normal(x.shape)
    y = _autograd_hvp(energy, x, s)  # the exact curvature along the previous step
    for kappa in (1.0, 4.0, 64.0):
        p, active = _minimize.subspace_step(ob, x, g, h, d, s, y, kappa)
        assert float((p * g).sum()) < 0  # a descent direction
        # p = a d + b s, and (a, b) is the brute-force minimiser of the autograd model
        cols = np.stack([d.ravel(), s.ravel()], 1)
        coef, *_ = np.linalg.lstsq(cols, p.ravel(), rcond=None)
        np.testing.assert_allclose(cols @ coef, p.ravel(), atol=1e-12)
        hx = [_autograd_hvp(energy, x, c.reshape(n, 3)).ravel() for c in cols.T]
        hr = np.array([[cols[:, i] @ hx[j] for j in range(2)] for i in range(2)])
        hr = 0.5 * (hr + hr.T)
        br = np.array([[cols[:, i] @ (h @ cols[:, j]) for j in range(2)] for i in range(2)])
        gr = cols.T @ g.ravel()
        radius = kappa * np.sqrt(br[0, 0])
        assert np.sqrt(coef @ br @ coef) <= radius * (1 + 1e-6)
        best = _brute_force(hr, br, gr, radius)
        assert _model(hr, gr, coef) <= best + 1e-4 * abs(best)


def test_subspace_newton_descends_and_meets_the_same_rule():
    """A sheet thrown onto a ball (it buckles on impact), planes fixed: both minimisers lower
    the energy at every step and stop at the rule; the subspace steps end at the same drape."""
    v, f = grid_sheet(13, 0.6, z=0.305)
    r = P.rest_state(v, f)
    v0 = np.tile([0.0, 0.0, -1.5], (len(v), 1))
    q = R.sphere_query([0, 0, 0], 0.3)
    out = {}
    for sub in (False, True):
        st = R.SolverSettings(tol=1e-5, max_iter=1000, max_requery=0, subspace=sub)
        x0 = R.project_outside(R.free_fall(v, v0, 1 / 30), q, st.collision_eps)
        res = R.drape_step(r, v, v0, 1 / 30, q, st, x0=x0)
        assert res.converged
        assert np.all(np.diff(res.trace) <= 1e-12 * abs(res.trace[0]))
        out[sub] = res
    assert out[True].iterations < out[False].iterations  # the point of it (65 against 35)
    assert out[True].energy == pytest.approx(out[False].energy, rel=1e-6)
    assert float((out[True].x - out[False].x).norm(dim=1).max()) < 1e-4  # m


def test_subspace_setting_is_validated():
    assert R.SolverSettings().subspace is True
    with pytest.raises(TypeError, match="subspace"):
        R.SolverSettings(subspace="yes")
