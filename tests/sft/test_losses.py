"""sft.losses: image terms against independent (VTK) renders, inextensibility, temporal term."""

import warnings

import numpy as np
import pytest
import torch

from polygeo.render import RasterSettings
from sft.data import load_sequence, write_sequence
from sft.losses import (
    ImageTerms,
    Inextensibility,
    prefilter_texture,
    temporal_acceleration,
    temporal_consistency,
)


def test_inextensibility_closed_forms():
    rng = np.random.default_rng(0)
    a, b = np.meshgrid(np.linspace(0, 1, 5), np.linspace(0, 1, 4))
    v = np.stack([a.ravel(), b.ravel(), 0.1 * a.ravel() ** 2], 1)
    f = []
    for j in range(3):
        for i in range(4):
            k = j * 5 + i
            f += [[k, k + 1, k + 5], [k + 1, k + 6, k + 5]]
    f = np.array(f)
    term = Inextensibility(v, f, scale=2.0, weight=0.1)
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    moved = torch.tensor(np.stack([v, v @ q.T + 1.0]))
    np.testing.assert_allclose(term(moved).numpy(), [0.0, 0.0], atol=1e-24)
    eps = 0.03  # uniform stretch: weight * sum (eps e_i / s)^2
    expect = 0.1 * np.sum((eps * term.rest.numpy() / 2.0) ** 2)  # rest: scene units
    assert float(term(torch.tensor((1 + eps) * v)[None])[0]) == pytest.approx(expect, rel=1e-12)


def test_temporal_consistency_formula():
    g = torch.Generator().manual_seed(0)
    p = {"a": torch.randn(3, 4, 2, generator=g), "b": torch.randn(3, 5, generator=g),
         "c": torch.randn(3, 3, generator=g)}
    got = temporal_consistency(p, ["a", "b"], 0.05)
    want = 0.05 / 2 * sum(((p[n][t + 1] - p[n][t]) ** 2).sum() for n in "ab" for t in range(2))
    assert float(got) == pytest.approx(float(want), rel=1e-6)
    same = {"a": torch.ones(3, 2)}
    assert float(temporal_consistency(same, ["a"], 1.0)) == 0.0
    assert float(temporal_consistency({"a": torch.ones(1, 2)}, ["a"], 1.0)) == 0.0


def test_temporal_acceleration_zero_at_constant_velocity():
    """Second differences: 0 on a straight, uniform trajectory whatever its speed; 2a on
    p_t = a t^2 + b t + c; against an explicit sum on random parameters; 0 below 3 frames."""
    t = torch.arange(4, dtype=torch.float64)[:, None, None]
    g = torch.Generator().manual_seed(1)
    v, c, a = torch.randn(3, 1, 5, 3, generator=g, dtype=torch.float64)
    assert float(temporal_acceleration({"a": c + 7.0 * v * t}, ["a"], 1.0)) < 1e-24
    quad = {"a": a * t**2 + v * t + c}
    # two second differences, each 2a: k / (W - 2) * 2 * ||2a||^2
    want = 0.3 / 2 * 2 * float((2 * a).pow(2).sum())
    assert float(temporal_acceleration(quad, ["a"], 0.3)) == pytest.approx(want, rel=1e-12)
    p = {"a": torch.randn(5, 4, 2, generator=g), "b": torch.randn(5, 3, generator=g)}
    got = temporal_acceleration(p, ["a", "b"], 0.05)
    want = 0.05 / 3 * sum(((p[n][k + 1] - 2 * p[n][k] + p[n][k - 1]) ** 2).sum()
                          for n in "ab" for k in range(1, 4))
    assert float(got) == pytest.approx(float(want), rel=1e-6)
    assert float(temporal_acceleration({"a": torch.randn(2, 3, generator=g)}, ["a"], 1.0)) == 0


def test_temporal_terms_gradcheck():
    g = torch.Generator().manual_seed(2)
    x = torch.randn(4, 3, 2, generator=g, dtype=torch.float64, requires_grad=True)
    torch.autograd.gradcheck(lambda z: temporal_acceleration({"a": z}, ["a"], 0.7), (x,))
    torch.autograd.gradcheck(lambda z: temporal_consistency({"a": z}, ["a"], 0.7), (x,))


def test_image_terms_minimal_at_ground_truth(make_sequence):
    """The colour and silhouette terms against VTK renders are lowest at the true shape."""
    seq = load_sequence(make_sequence("bend", 3))
    terms = ImageTerms(seq, RasterSettings(sigma=0.1), dtype=torch.float64)
    i = 2
    target, mask = terms.target(seq.frame(i), seq.mask(i))
    gt = torch.tensor(seq.gt(i))

    def losses(X):
        out = terms(X[None], target[None], mask[None])
        return float(out["rgb"][0]), float(out["sil"][0])

    at_truth = losses(gt)
    z = gt[:, 2:3]
    f = float(seq.K[0, 0])
    for shift in (-1.0, 1.0):  # one pixel left / right, up / down
        for axis in (0, 1):
            d = torch.zeros(3, dtype=torch.float64)
            d[axis] = shift / f
            moved = losses(gt + z * d)
            assert moved[0] > at_truth[0] and moved[1] > at_truth[1]
    bigger = losses(gt.mean(0) + 1.02 * (gt - gt.mean(0)))
    assert bigger[0] > at_truth[0] and bigger[1] > at_truth[1]
    # interior coverage after the remap is exactly 1 (no SoftRas dip on internal edges)
    _, alpha = terms.render(gt[None])
    inner = torch.nn.functional.max_pool2d(1 - mask[None, None], 5, 1, 2)[0, 0] == 0
    assert float(alpha[0][inner].min()) == pytest.approx(1.0)


def test_uv_seam_renders_like_duplicated_seam_vertices(tmp_path):
    """Face-corner uvs (a template with UV seams) render exactly like the same mesh with its
    seam vertices duplicated and per-vertex uvs."""
    from test_data import H, K, W, seam_template

    from sft.data import write_sequence

    seam, dupl, vmap = seam_template()
    assert len(dupl.verts) > len(seam.verts)
    renders = []
    for name, t in (("seam", seam), ("dupl", dupl)):
        seq = load_sequence(write_sequence(tmp_path / name, t, K, W, H, [np.zeros((H, W, 3))],
                                           [np.ones((H, W), bool)]))
        terms = ImageTerms(seq, RasterSettings(sigma=0.05), dtype=torch.float64)
        rgb, alpha = terms.render(torch.tensor(seq.template.verts)[None])
        renders.append((rgb, alpha))
    (r0, a0), (r1, a1) = renders
    assert float(a0.max()) > 0.9 and float(r0.std()) > 0.05  # the sheet is in view, textured
    torch.testing.assert_close(r0, r1, atol=1e-12, rtol=0)
    torch.testing.assert_close(a0, a1, atol=1e-12, rtol=0)


def test_prefilter_texture_density():
    tex = np.random.default_rng(0).random((512, 512, 3)).astype(np.float32)
    uvs = np.array([[0, 0], [1, 0], [0, 1]], float)
    K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    verts = np.array([[0, 0, 1.0], [0.5, 0, 1.0], [0, 0.5, 1.0]])  # 50 px on a side
    out = prefilter_texture(tex, uvs, verts, np.array([[0, 1, 2]]), K, texels_per_pixel=2.0)
    assert out.shape == (100, 100, 3)  # 512 texels over 50 px -> 2 texels per pixel
    small = prefilter_texture(tex[:64, :64], uvs, verts, np.array([[0, 1, 2]]), K)
    assert small.shape == (64, 64, 3)  # already coarser than 2 texels/pixel: unchanged


def test_missing_masks_are_reported_not_invented(tmp_path, make_sequence):
    seq = load_sequence(make_sequence("small", 2))
    p = write_sequence(tmp_path / "nomask", seq.template, seq.K, seq.width, seq.height,
                       [seq.frame(0), seq.frame(1)])
    s2 = load_sequence(p)
    with pytest.warns(UserWarning, match="no masks/ folder: the silhouette loss is disabled"):
        terms = ImageTerms(s2, RasterSettings())
    target, mask = terms.target(s2.frame(0), s2.mask(0))
    assert mask is None
    np.testing.assert_array_equal(target.numpy(), s2.frame(0))  # the frame, untouched
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = terms(torch.tensor(s2.template.verts, dtype=torch.float32)[None], target[None],
                    None)
    assert set(out) == {"rgb"}


def test_image_pyramid_levels_are_block_means(make_sequence):
    """pyramid=2 averages the terms over full resolution, 2x2 and 4x4 block means (computed
    here independently with NumPy reshapes), and is still lowest at the true shape."""
    seq = load_sequence(make_sequence("bend", 3))
    raster = RasterSettings(sigma=0.1)
    flat = ImageTerms(seq, raster, dtype=torch.float64)
    pyr = ImageTerms(seq, raster, pyramid=2, dtype=torch.float64)
    target, mask = flat.target(seq.frame(2), seq.mask(2))
    gt = torch.tensor(seq.gt(2))
    X = gt + 0.002 * torch.sin(40.0 * gt)  # a few pixels off the truth
    rgb, alpha = (x.numpy()[0] for x in flat.render(X[None]))
    t, m = target.numpy(), mask.numpy()
    H, W = m.shape

    def blocks(a, k):
        return a.reshape(H // k, k, W // k, k, *a.shape[2:]).mean(axis=(1, 3))

    want_rgb = np.mean([np.abs(blocks(rgb, k) - blocks(t, k)).mean() for k in (1, 2, 4)])
    want_sil = np.mean([((blocks(alpha, k) - blocks(m, k)) ** 2).mean() for k in (1, 2, 4)])
    got = pyr(X[None], target[None], mask[None])
    assert float(got["rgb"][0]) == pytest.approx(want_rgb, rel=1e-9)
    assert float(got["sil"][0]) == pytest.approx(want_sil, rel=1e-9)
    at_truth = pyr(gt[None], target[None], mask[None])
    assert float(at_truth["rgb"][0]) < float(got["rgb"][0])
    assert float(at_truth["sil"][0]) < float(got["sil"][0])
