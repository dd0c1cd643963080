import json
import math

import numpy as np
import pytest
import torch

from draping import viz
from draping.fnopt import cloth, model, solvers
from draping.fnopt.cloth import Material, Sheet
from draping.fnopt.handles import DT
from draping.fnopt.simulate import SimSettings

torch.set_num_threads(1)


def _pretrained():
    if not model.WEIGHTS.is_file():
        pytest.skip("no shipped FNOpt weights")
    return model.load_pretrained()


def _mid_rollout_problem(n, layout="corners", motion="xy", frames=8):
    mat = Material()
    sheet = Sheet(n, n)
    ro = solvers.rollout(sheet, mat, layout, motion, frames,
                         lambda p, a0: solvers.solve_pgd(p, 10), speed=1.5)
    idx = cloth.handle_indices(layout, n, n)
    x = ro.positions[-2][None]
    v = (ro.positions[-2] - ro.positions[-3])[None] / DT
    tgt = ro.positions[-1][None][:, idx[:, 0], idx[:, 1]]
    return solvers.make_problem(x, v, idx, tgt, sheet.hx, sheet.hy, mat.tensors(1))


def test_spectral_conv_is_resolution_consistent():
    torch.manual_seed(0)
    conv = model.SpectralConv2d(2, 3, 4)
    out = {}
    for n in (32, 64):
        u = torch.linspace(0, 1, n + 1)[:-1]          # periodic samples of one function
        f = torch.stack([torch.sin(2 * math.pi * u)[:, None] * torch.cos(4 * math.pi * u)[None],
                         torch.cos(2 * math.pi * u)[:, None].expand(n, n)])[None]
        out[n] = conv(f)
    # band-limited input: the 64 grid's even samples are the 32 grid's samples
    assert torch.allclose(out[64][..., ::2, ::2], out[32], atol=1e-5)


@pytest.mark.parametrize("shape", [(1, 32, 32), (3, 64, 48), (2, 33, 20), (1, 7, 5),
                                   (1, 100, 100), (1, 12, 14), (2, 6, 6)])
def test_pruned_spectral_transform_is_the_full_one(shape):
    # the inference path (truncated DFT matrices) against the training
    # path (full rfft2 / irfft2, two einsums), float64; (7, 5), (12, 14), (6, 6): modes clipped
    # by the grid (14 and 6 columns: the kept ones include the Nyquist column)
    b, h, w = shape
    torch.manual_seed(1)
    conv = model.SpectralConv2d(3, 4, 8).double()
    x = torch.randn(b, 3, h, w, dtype=torch.float64)
    full = conv(x)                                   # gradients enabled: the full transforms
    with torch.no_grad():
        infer = conv(x)
    assert torch.equal(infer, conv.forward_dft(x).detach())
    full = full.detach()
    assert torch.allclose(infer, full, rtol=0, atol=1e-12 * float(full.abs().max()))
    # float32: rounding only
    c32 = model.SpectralConv2d(3, 4, 8)
    c32.load_state_dict({k: v.float() for k, v in conv.state_dict().items()})
    with torch.no_grad():
        got = c32(x.float())
    assert float((got.double() - full).norm() / full.norm()) < 1e-5


def test_inference_forward_is_the_training_forward():
    # the no-grad FNO (cached kept weights, 1x1 convolutions accumulated by baddbmm, GELUs in
    # place) against the autograd path (full FFTs, Conv2d), float64: to rounding
    torch.manual_seed(2)
    net = model.FNO(model.FNOConfig(width=6, modes=4, layers=3, projection=8)).double()
    with torch.no_grad():
        for q in net.parameters():
            q.normal_(0.0, 0.3)
    x = torch.randn(2, model.N_INPUTS, 20, 17, dtype=torch.float64)
    full = net(x).detach()
    with torch.no_grad():
        infer = net(x)
    assert float(full.abs().max()) > 1e-3
    assert torch.allclose(infer, full, rtol=0, atol=1e-12 * float(full.abs().max()))


def test_kept_spectral_weights_follow_weight_changes():
    # the inference cache of the kept complex weights is rebuilt after an in-place change
    # (an optimiser step) and after load_state_dict; never a stale operator
    torch.manual_seed(3)
    conv = model.SpectralConv2d(3, 2, 4).double()
    x = torch.randn(1, 3, 16, 16, dtype=torch.float64)
    with torch.no_grad():
        first = conv(x)
        conv.w.mul_(-2.0)
        second = conv(x)
    assert torch.allclose(second, -2.0 * first, rtol=1e-12, atol=1e-14)
    other = model.SpectralConv2d(3, 2, 4).double()
    conv.load_state_dict(other.state_dict())
    with torch.no_grad():
        third = conv(x)
    assert torch.allclose(third, other(x).detach(), rtol=0, atol=1e-12)
    assert not torch.allclose(third, second)


def test_constant_features_are_the_per_iteration_ones():
    p = _mid_rollout_problem(12, "diagonal", frames=3)
    z = torch.randn(1, 12, 12, 3)
    sc = p.residual_rms(z)
    const = model.constant_features(p, z.dtype)
    assert const.shape == (1, 6, 12, 12)
    assert torch.equal(model.features(p, z, 2 * z, 3 * z, sc, const),
                       model.features(p, z, 2 * z, 3 * z, sc))
    # the handle mask channel marks exactly the two diagonal corners
    assert float(const[0, 0].sum()) == 2.0 and float(const[0, 0, 0, 0]) == 1.0


def test_fno_runs_on_any_grid_and_keeps_handles_fixed():
    net = model.FNO(model.FNOConfig(width=8, modes=4, layers=2, projection=8))
    for h, w in ((32, 32), (20, 48), (7, 5)):
        sheet = Sheet(h, w)
        x = cloth.rest_positions(sheet)[None]
        p = solvers.make_problem(x, torch.zeros_like(x), "corner-centre",
                                 x[:, [0, h // 2], [0, w // 2]], sheet.hx, sheet.hy,
                                 Material().tensors(1))
        a = model.solve_fnopt(net, p, 3)
        assert a.shape == x.shape and bool(torch.isfinite(a).all())
        idx = cloth.handle_indices("corner-centre", h, w)
        assert torch.allclose(a[:, idx[:, 0], idx[:, 1]], p.a_fixed[:, idx[:, 0], idx[:, 1]])


@pytest.mark.parametrize("n", [32, 64, 100])
def test_trained_optimizer_lowers_the_loss_within_10_iterations(n):
    net = _pretrained()
    p = _mid_rollout_problem(n)
    l0 = float(p.loss(torch.zeros_like(p.x_prev))[0])
    losses = []
    for it in (1, 3, 10):
        losses.append(float(p.loss(model.solve_fnopt(net, p, it))[0]))
    assert losses[-1] < losses[0] < l0
    # and it gets most of the way to the converged minimum
    l_star = float(p.loss(solvers.solve_reference(p))[0])
    assert (losses[-1] - l_star) < 0.5 * (l0 - l_star)


def test_trained_optimizer_lowers_the_loss_on_an_unseen_random_layout_at_64():
    """Three random pinned vertices (none of the five named layouts), a rotation, at 64^2."""
    net = _pretrained()
    n = 64
    g = torch.Generator().manual_seed(19)
    idx = torch.unique(torch.randint(0, n, (3, 2), generator=g), dim=0)
    assert idx.shape[0] == 3
    named = {tuple(map(tuple, cloth.handle_indices(k, n, n).tolist())) for k in cloth.LAYOUTS}
    assert tuple(map(tuple, idx.tolist())) not in named
    p = _mid_rollout_problem(n, layout=idx, motion="rot-b", frames=6)
    zero = torch.zeros_like(p.x_prev)
    l0 = float(p.loss(zero)[0])
    l_star = float(p.loss(solvers.solve_reference(p))[0])
    l10 = float(p.loss(model.solve_fnopt(net, p, 10))[0])
    assert l10 < l0
    # most of the way to the converged minimum, and better than 10 preconditioned descents
    l_pgd = float(p.loss(solvers.solve_pgd(p, 10))[0])
    assert (l10 - l_star) < 0.5 * (l0 - l_star)
    assert l10 < l_pgd


@pytest.mark.slow
def test_500_frame_rollout_at_100_is_finite_and_bounded():
    """``polygeo simulate``'s default FNOpt step (with the two-level coarse direction)."""
    from draping.fnopt.simulate import SimSettings, step_function

    net = _pretrained()
    sheet = Sheet(100, 100)
    step = step_function(SimSettings(res=(100, 100)), net)
    ro = solvers.rollout(sheet, Material(), "corners", "xyz", 500, step, speed=1.5)
    x = ro.positions
    assert bool(torch.isfinite(x).all())
    # bounded: the sheet stays within its size of the handles, edges within 1.5x rest
    hmid = ro.handles.mean(1)                               # (F+1, 3)
    assert float((x - hmid[:, None, None]).norm(dim=-1).max()) < 1.6
    e = (x[:, :, 1:] - x[:, :, :-1]).norm(dim=-1) / sheet.hx
    assert float(e.max()) < 1.5
    assert all(math.isfinite(v) for v in ro.loss)


def test_simulate_cli_writes_meshes_metrics_and_pictures(tmp_path):
    from polygeo.cli import main

    out = tmp_path / "sim"
    rc = main(["simulate", "--res", "8x6", "--frames", "3", "--optimizer", "lbfgs",
               "--iters", "5", "--handles", "diagonal", "--motion", "rot-b", "--speed", "2",
               "-o", str(out), "--quiet", "--gif-every", "1"])
    assert rc in (0, None)
    m = json.loads((out / "metrics.json").read_text())
    assert len(m["frames"]) == 3
    for rec in m["frames"]:
        assert {"e_cd", "e_3d", "L_cloth", "ms", "cpu_ms"} <= set(rec)
        assert rec["e_cd"] >= 0 and np.isfinite(rec["L_cloth"])
    assert len(list((out / "meshes").glob("*.ply"))) == 4
    assert (out / "errors.png").stat().st_size > 0
    from PIL import Image

    assert Image.open(out / "rollout.gif").n_frames == 4


def test_reference_rollout_has_zero_error_against_itself(tmp_path):
    from draping.fnopt import simulate

    s = SimSettings(res=(8, 8), frames=3, optimizer="reference")
    ro = simulate.run(s)
    m = simulate.frame_metrics(ro, ro)
    assert max(m["e_3d"]) == 0.0
    # e_CD of a mesh with itself is the sampling floor, far below the target 5
    assert max(m["e_cd"]) < 0.5


def test_bad_settings_errors():
    with pytest.raises(ValueError, match="optimizer"):
        SimSettings(optimizer="newton")
    with pytest.raises(ValueError, match="layout"):
        SimSettings(handles="three")
    with pytest.raises(ValueError, match="motion"):
        SimSettings(motion="spin")
    with pytest.raises(ValueError, match="iters"):
        SimSettings(iters=0)
    with pytest.raises(ValueError, match="FNOConfig.width"):
        model.FNOConfig(width=0)
    with pytest.raises(FileNotFoundError):
        model.load_pretrained("/nonexistent/fnopt.pt")


def test_viz_gif_and_strip(tmp_path):
    f = cloth.grid_faces(4, 4).numpy()
    v = cloth.rest_positions(Sheet(4, 4)).reshape(-1, 3).numpy()
    imgs = viz.render_frames([v, v + 0.1], f, points=[v[:1], v[:1]])
    viz.write_gif(imgs, tmp_path / "a.gif")
    viz.write_strip(imgs, tmp_path / "a.png")
    from PIL import Image

    assert Image.open(tmp_path / "a.gif").n_frames == 2
    assert Image.open(tmp_path / "a.png").width == 2 * imgs[0].width
    with pytest.raises(ValueError):
        viz.write_gif([], tmp_path / "b.gif")


def test_random_handle_distribution_covers_corners_edges_and_interior():
    from draping.fnopt.train import TrainSettings, random_handles

    n = 32
    g = torch.Generator().manual_seed(0)
    named = {tuple(map(tuple, cloth.handle_indices(k, n, n).tolist())): k for k in cloth.LAYOUTS}
    seen, kinds, counts = set(), set(), set()
    for _ in range(3000):
        idx = random_handles(g, n)
        assert idx.ndim == 2 and idx.shape[1] == 2 and int(idx.min()) >= 0
        assert int(idx.max()) <= n - 1
        assert len({tuple(p) for p in idx.tolist()}) == idx.shape[0]      # unique
        counts.add(idx.shape[0])
        seen.add(named.get(tuple(map(tuple, idx.tolist())), "other"))
        for r, c in idx.tolist():
            on_r, on_c = r in (0, n - 1), c in (0, n - 1)
            kinds.add("corner" if on_r and on_c else "edge" if on_r or on_c else "interior")
    assert {"corners", "diagonal", "other"} <= seen          # named layouts are ordinary draws
    assert kinds == {"corner", "edge", "interior"}
    assert {1, 2, 3, 4} <= counts and max(counts) > 4        # runs along a row or column
    with pytest.raises(ValueError, match="handles"):
        random_handles(g, n, "everywhere")
    with pytest.raises(ValueError, match="handles"):
        TrainSettings(handles="everywhere")


def test_solve_fnopt_step_rules():
    net = model.FNO(model.FNOConfig(width=8, modes=4, layers=2, projection=8))
    p = _mid_rollout_problem(16, frames=4)
    l0 = float(p.loss(torch.zeros_like(p.x_prev))[0])
    for step in model.STEPS:
        assert float(p.loss(model.solve_fnopt(net, p, 5, step=step))[0]) < l0
    # the subspace step contains preconditioned descent: an untrained FNO cannot make it worse
    l_sub = float(p.loss(model.solve_fnopt(net, p, 10))[0])
    assert l_sub <= float(p.loss(solvers.solve_pgd(p, 10))[0]) * (1 + 1e-6)
    with pytest.raises(ValueError, match="step"):
        model.solve_fnopt(net, p, 3, step="newton")


def test_folding_handle_distribution_draws_far_apart_pairs_half_the_time():
    from draping.fnopt.train import TrainSettings, folding_pair, random_handles

    n, m = 32, 31
    g = torch.Generator().manual_seed(0)
    kinds = set()
    for _ in range(600):
        idx = folding_pair(g, n)
        assert idx.shape == (2, 2) and int(idx.min()) >= 0 and int(idx.max()) <= m
        assert int((idx[0] - idx[1]).abs().max()) >= m / 2          # Chebyshev distance
        pins = {tuple(p) for p in idx.tolist()}
        if pins in ({(0, 0), (m, m)}, {(0, m), (m, 0)}):
            kinds.add("opposite corners")
        elif {c for _, c in pins} == {0, m} or {r for r, _ in pins} == {0, m}:
            kinds.add("opposite edges")
        else:
            kinds.add("far points")
    assert kinds == {"opposite corners", "opposite edges", "far points"}

    def far_pairs(kind: str) -> float:
        gen = torch.Generator().manual_seed(1)
        draws = [random_handles(gen, n, kind) for _ in range(2000)]
        return sum(d.shape[0] == 2 and int((d[0] - d[1]).abs().max()) >= m / 2
                   for d in draws) / len(draws)

    p_random, p_folding = far_pairs("random"), far_pairs("folding")
    assert p_random < 0.35                                   # 0.15 corners + chance pairs
    assert abs(p_folding - (0.5 + 0.5 * p_random)) < 0.05    # half the draws are folding pairs
    assert TrainSettings().handles == "random"               # the shipped weights' pool
    assert TrainSettings(handles="folding").handles == "folding"
    with pytest.raises(ValueError, match="res"):
        folding_pair(g, 1)
