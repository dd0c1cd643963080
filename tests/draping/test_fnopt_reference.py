"""The converged reference (ground truth of FNOpt's metrics) and the strong-Wolfe L-BFGS."""

import pytest
import torch

from draping.fnopt import cloth, handles, solvers
from draping.fnopt.cloth import Material, Sheet
from draping.fnopt.simulate import SimSettings, reference_rollout

torch.set_num_threads(1)


def _residual64(p: solvers.StepProblem, a: torch.Tensor) -> torch.Tensor:
    """RMS residual of ``a`` recomputed independently in float64 (autograd of the loss)."""
    x, v = p.x_prev.double(), p.v_prev.double()
    mat = {k: t.double() for k, t in p.material.items()}
    a = (a.double() * p.free.double()).requires_grad_(True)
    aa = a + p.a_fixed.double()
    loss = cloth.cloth_loss(aa, x, v, p.hx.double(), p.hy.double(), mat, p.dt,
                            p.mass.double()).sum()
    (g,) = torch.autograd.grad(loss, a)
    r = g * p.free.double() / (p.mass.double()[..., None] * p.dt * p.dt)
    n = float(p.free.expand(r.shape[:-1] + (1,)).sum()) * 3
    return (r.square().sum() / n).sqrt()


@pytest.mark.parametrize("layout", ["corners", "diagonal", "mid-edges", "corner-centre",
                                    "single"])
def test_reference_residual_below_tolerance_on_every_layout(layout):
    sheet = Sheet(10, 10)
    seen = []

    def step(p, a0):
        a = solvers.solve_reference(p, a0)
        seen.append(float(_residual64(p, a)))
        return a

    solvers.rollout(sheet, Material(), layout, "xy", 8, step, speed=2.0, warm_start=True,
                    dtype=torch.float64)
    assert len(seen) == 8
    assert max(seen) <= solvers.REFERENCE_TOL


def test_reference_rollout_converged_in_the_tolerance(tmp_path):
    """Solving 10x tighter moves the reference rollout by far less than a grid spacing."""
    s = SimSettings(res=(10, 10), handles="mid-edges", frames=20, speed=1.5)
    ref = reference_rollout(s, tmp_path, tol=solvers.REFERENCE_TOL)
    tight = reference_rollout(s, tmp_path, tol=solvers.REFERENCE_TOL / 10)
    loose = reference_rollout(s, tmp_path, tol=5e-2)
    assert ref.positions.dtype == torch.float64
    d_tight = float((ref.positions - tight.positions).norm(dim=-1).max())
    d_loose = float((loose.positions - tight.positions).norm(dim=-1).max())
    assert d_tight < 1e-4 * s.size            # 0.1 mm on a 1 m sheet
    assert d_tight < d_loose                  # the tolerance is what moves it
    # cached by settings and tolerance
    assert len(list(tmp_path.glob("reference_*.npz"))) == 3
    again = reference_rollout(s, tmp_path, tol=solvers.REFERENCE_TOL)
    assert torch.equal(again.positions, ref.positions)


def _problem(res=10, layout="single", dtype=torch.float64):
    sheet = Sheet(res, res)
    idx = cloth.handle_indices(layout, res, res)
    x = cloth.rest_positions(sheet, dtype=dtype)[None]
    v = torch.zeros_like(x)
    v[..., 1] = 0.5                                   # moving out of plane
    target = x[:, idx[:, 0], idx[:, 1]] + torch.tensor([0.01, 0.0, 0.005], dtype=x.dtype)
    return solvers.make_problem(x, v, idx, target, sheet.hx, sheet.hy,
                                Material().tensors(1, dtype))


def test_reference_warns_when_not_converged():
    p = _problem()
    info = {}
    with pytest.warns(RuntimeWarning, match="not converged"):
        solvers.solve_reference(p, max_iter=2, info=info)
    assert float(info["residual"][0]) > solvers.REFERENCE_TOL


def test_lbfgs_wolfe_descends_and_converges():
    p = _problem()
    a_ref = solvers.solve_reference(p, tol=1e-8)
    l0, l_ref = float(p.loss(torch.zeros_like(p.x_prev))[0]), float(p.loss(a_ref)[0])
    info = {}
    losses = [float(p.loss(solvers.solve_lbfgs_wolfe(p, n, info=info))[0]) for n in (2, 10)]
    assert l0 > losses[0] >= losses[1] >= l_ref - 1e-9
    a = solvers.solve_lbfgs_wolfe(p, 300, history=20, info=info)
    assert float(info["residual"][0]) < 1e-3
    assert info["evaluations"] <= 600
    assert torch.allclose(a, a_ref, atol=1e-2)
    # the handles keep their prescribed accelerations
    idx = cloth.handle_indices("single", 10, 10)
    assert torch.equal(a[:, idx[:, 0], idx[:, 1]], p.a_fixed[:, idx[:, 0], idx[:, 1]])
    assert handles.DT == p.dt


def test_batched_hessian_products_match_single_ones_and_finite_differences():
    p = _problem(res=8, layout="corners")
    a = 0.3 * torch.randn(p.x_prev.shape, dtype=torch.float64,
                          generator=torch.Generator().manual_seed(0))
    _, g, hvp = p.grad_hvp(a)
    ds = [torch.randn(a.shape, dtype=a.dtype, generator=torch.Generator().manual_seed(k))
          for k in (1, 2, 3)]
    many = hvp.many(ds)
    for k, d in enumerate(ds):
        one = hvp(d)
        assert torch.allclose(many[k], one, rtol=1e-10, atol=1e-14)
        eps = 1e-6                                 # central differences of the gradient
        gp = p.loss_grad(a + eps * d * p.free)[1]
        gm = p.loss_grad(a - eps * d * p.free)[1]
        assert torch.allclose(one, (gp - gm) / (2 * eps), rtol=1e-5, atol=1e-9)
    # the subspace step is the same with batched and single products
    dirs = [-g, ds[0] * p.free, ds[1] * p.free]
    s_batched = p.subspace_step(g, dirs, hvp)
    p.batched_hvp = False
    assert torch.allclose(p.subspace_step(g, dirs, hvp), s_batched, rtol=1e-9, atol=1e-12)


def test_lbfgs_wolfe_in_float64_on_a_float32_problem():
    p = _problem(dtype=torch.float32)
    info = {}
    a = solvers.solve_lbfgs_wolfe(p, 300, history=20, info=info, float64=True)
    assert a.dtype == torch.float32
    assert info["evaluations"] > 0 and p.evals >= info["evaluations"]
    assert float(info["residual"][0]) < 1e-3
    a_ref = solvers.solve_reference(_problem(), tol=1e-8)
    assert torch.allclose(a.double(), a_ref, atol=1e-2)
