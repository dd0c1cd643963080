"""The FNO on a coarse grid (draping.fnopt.coarse, solve_fnopt(coarse_res=, stiffness_res=))."""

import pytest
import torch

from draping.fnopt import cloth, coarse, model, solvers
from draping.fnopt.cloth import Material, Sheet

torch.set_num_threads(1)


def _problem(h, w, layout="corner-centre", size=1.0, seed=0):
    g = torch.Generator().manual_seed(seed)
    sheet = Sheet(h, w, size)
    x = cloth.rest_positions(sheet)[None]
    x = x + 1e-3 * torch.randn(x.shape, generator=g)
    v = 0.1 * torch.randn(x.shape, generator=g)
    idx = cloth.handle_indices(layout, h, w)
    return solvers.make_problem(x, v, idx, x[:, idx[:, 0], idx[:, 1]], sheet.hx, sheet.hy,
                                Material().tensors(1))


def _small_net(seed=0):
    torch.manual_seed(seed)
    net = model.FNO(model.FNOConfig(width=8, modes=4, layers=2, projection=8, normal=True,
                                    normal_split=2))
    with torch.no_grad():                       # a proposal large enough to matter
        net.proj2.weight.mul_(100.0)
    return net.eval()


@pytest.mark.parametrize("shape,longer,expected", [((64, 64), 32, (32, 32)),
                                                   ((100, 100), 32, (32, 32)),
                                                   ((100, 50), 32, (32, 16)),
                                                   ((40, 64), 32, (20, 32)),
                                                   ((32, 32), 32, (32, 32)),
                                                   ((20, 24), 32, (20, 24))])
def test_coarse_shape_keeps_the_aspect_and_never_refines(shape, longer, expected):
    assert coarse.coarse_shape(*shape, longer) == expected


def test_interpolation_keeps_constants_and_linear_sequences():
    for n_from, n_to in ((64, 32), (32, 64), (100, 32), (17, 5), (9, 9)):
        m = coarse.interpolation_matrix(n_from, n_to, torch.float64)
        assert torch.allclose(m.sum(1), torch.ones(n_to, dtype=torch.float64), atol=1e-14)
        t_from = torch.linspace(0.0, 1.0, n_from, dtype=torch.float64)
        t_to = torch.linspace(0.0, 1.0, n_to, dtype=torch.float64)
        assert torch.allclose(m @ (3.0 * t_from - 2.0), 3.0 * t_to - 2.0, atol=1e-13)
    assert torch.equal(coarse.interpolation_matrix(9, 9), torch.eye(9))


def test_restriction_and_prolongation_are_exact_on_bilinear_fields():
    def bilinear(h, w):
        yy, xx = torch.meshgrid(torch.linspace(0, 1, h, dtype=torch.float64),
                                torch.linspace(0, 1, w, dtype=torch.float64), indexing="ij")
        return torch.stack([1.0 + 0 * xx, 2 * xx - yy + 0.5, 3 * xx * yy - xx], -1)[None]

    free = torch.ones(1, 64, 48, 1, dtype=torch.float64)
    shape = coarse.coarse_shape(64, 48, 32)
    grid = coarse.fno_grid(free, shape, torch.zeros(1), torch.float64)
    fine, crs = bilinear(64, 48), bilinear(*shape)
    assert torch.allclose(coarse.restrict(fine, grid), crs, atol=1e-13)
    assert torch.allclose(coarse.prolong(crs, grid), fine, atol=1e-13)


def test_coarse_handles_are_the_nearest_coarse_vertices():
    p = _problem(64, 64, "mid-edges")
    free_c = coarse.coarse_free(p.free, (32, 32))
    pins = torch.nonzero(free_c[0, ..., 0] == 0).tolist()
    idx = cloth.handle_indices("mid-edges", 64, 64).tolist()
    assert len(pins) == len(idx) == 2
    assert pins == [[round(i * 31 / 63), round(j * 31 / 63)] for i, j in idx]


def test_coarse_grid_equal_to_the_fine_grid_is_the_default_solve_bit_for_bit():
    net = _small_net()
    for h, w in ((32, 32), (24, 20)):
        p = _problem(h, w)
        a0 = model.solve_fnopt(net, p, 4)
        assert torch.equal(model.solve_fnopt(net, p, 4, coarse_res=32), a0)
        assert torch.equal(model.solve_fnopt(net, p, 4, stiffness_res=max(h, w)), a0)


def test_coarse_proposal_is_the_coarse_fno_prolonged_and_zero_at_handles():
    net = _small_net()
    p = _problem(64, 64, "corner-centre")
    const, grid = model.fno_inputs(p, torch.float32, coarse_res=32)
    assert grid is not None and const.shape == (1, 6, 32, 32)
    g = torch.Generator().manual_seed(1)
    z, zp, da = (torch.randn(1, 64, 64, 3, generator=g) * p.free for _ in range(3))
    with torch.no_grad():
        f = model.fno_correction(net, p, z, zp, da, const, grid)
        # independently: the FNO on the restricted fields, normalised by their coarse RMS
        zc, zpc, dac = (coarse.restrict(q, grid) for q in (z, zp, da))
        sc = coarse.free_rms(zc, grid.free)
        y = net(model.features(p, zc, zpc, dac, sc, const)).permute(0, 2, 3, 1)
        want = coarse.prolong(y * sc * grid.free, grid) * p.free
    assert torch.allclose(f, want, atol=1e-6 * float(want.abs().max()))
    idx = cloth.handle_indices("corner-centre", 64, 64)
    assert float(f[0, idx[:, 0], idx[:, 1]].abs().max()) == 0.0
    assert float(f.abs().max()) > 0.0
    # the stiffness channels are the coarse spacing's: those of the same sheet at 32 x 32
    p32 = _problem(32, 32, "corner-centre")
    want = model.constant_features(p32, torch.float32)[0, 1:4, 0, 0]
    assert torch.allclose(const[0, 1:4, 0, 0], want, atol=1e-5)


def test_coarse_solve_keeps_handles_and_lowers_the_loss():
    net = _small_net()
    p = _problem(48, 40, "diagonal")
    for kw in ({"coarse_res": 24}, {"stiffness_res": 24}):
        a = model.solve_fnopt(net, p, 5, **kw)
        idx = cloth.handle_indices("diagonal", 48, 40)
        assert torch.equal(a[:, idx[:, 0], idx[:, 1]], p.a_fixed[:, idx[:, 0], idx[:, 1]])
        assert float(p.loss(a * p.free)) < float(p.loss(torch.zeros_like(a)))
    # the coarse run differs from the fine one (the option does something)
    on_coarse = model.solve_fnopt(net, p, 5, coarse_res=24)
    assert not torch.equal(on_coarse, model.solve_fnopt(net, p, 5))


@pytest.mark.parametrize("kw,err", [({"coarse_res": 1}, ValueError),
                                    ({"coarse_res": -3}, ValueError),
                                    ({"stiffness_res": 1}, ValueError),
                                    ({"coarse_res": 2.5}, TypeError),
                                    ({"coarse_res": True}, TypeError),
                                    ({"coarse_res": 16, "stiffness_res": 16}, ValueError),
                                    ({"coarse_res": 16, "step": "line"}, ValueError)])
def test_bad_coarse_options_raise(kw, err):
    with pytest.raises(err, match="coarse_res|stiffness_res"):
        model.solve_fnopt(_small_net(), _problem(24, 24), 2, **kw)


def test_bad_coarse_shape_raises():
    with pytest.raises(ValueError, match="longer"):
        coarse.coarse_shape(10, 10, 1)
