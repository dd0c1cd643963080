"""Tests of polygeo.render.texture: bilinear sampling, the v flip and the checkerboard."""

import numpy as np
import pytest
import torch

from polygeo.render import checkerboard, flip_v, sample_texture


def _texture(rng, h=5, w=7, c=3):
    return rng.uniform(0, 1, (h, w, c))


def test_texel_centres_return_texels(rng):
    tex = _texture(rng)
    H, W, _ = tex.shape
    i, j = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    uv = np.stack([(j + 0.5) / W, (i + 0.5) / H], -1)  # u along columns, v down the rows
    out = sample_texture(tex, uv)
    assert isinstance(out, np.ndarray) and out.shape == (H, W, 3)
    np.testing.assert_allclose(out, tex, rtol=0, atol=1e-12)


def test_bilinear_between_texels_and_clamp_to_edge(rng):
    tex = _texture(rng)
    H, W, _ = tex.shape
    # halfway between texel (1, 2) and (1, 3), a quarter of the way to row 2
    u, v = 3.0 / W, (1.5 + 0.25) / H
    want = 0.75 * 0.5 * (tex[1, 2] + tex[1, 3]) + 0.25 * 0.5 * (tex[2, 2] + tex[2, 3])
    np.testing.assert_allclose(sample_texture(tex, [u, v]), want, atol=1e-12)
    # outside [0, 1]^2: the edge texel (clamp to edge)
    np.testing.assert_allclose(sample_texture(tex, [-3.0, -3.0]), tex[0, 0], atol=1e-12)
    np.testing.assert_allclose(sample_texture(tex, [4.0, 9.0]), tex[-1, -1], atol=1e-12)


def test_torch_in_torch_out_and_gradcheck(rng):
    tex = torch.from_numpy(_texture(rng, 4, 4, 2)).requires_grad_(True)
    # generic points (not on texel centre lines, where the bilinear map has kinks)
    uv = torch.from_numpy(rng.uniform(0.13, 0.87, (6, 2))).requires_grad_(True)
    out = sample_texture(tex, uv)
    assert isinstance(out, torch.Tensor) and out.shape == (6, 2) and out.dtype == torch.float64
    assert torch.autograd.gradcheck(sample_texture, (tex, uv), eps=1e-7, atol=1e-6)


@pytest.mark.parametrize(
    "texture, uv, exc, match",
    [
        (np.ones((4, 4)), np.zeros((1, 2)), ValueError, "texture"),
        (np.ones((0, 4, 3)), np.zeros((1, 2)), ValueError, "texture"),
        (np.ones((4, 4, 3)), np.zeros((1, 3)), ValueError, "uv"),
        (np.ones((4, 4, 3)), np.array([["a", "b"]]), TypeError, "uv"),
        (np.array([[["x"]]]), np.zeros((1, 2)), TypeError, "texture"),
    ],
)
def test_sample_texture_validation(texture, uv, exc, match):
    with pytest.raises(exc, match=match):
        sample_texture(texture, uv)


def test_flip_v_values_involution_and_types(rng):
    uv = rng.uniform(0, 1, (10, 2))
    f = flip_v(uv)
    np.testing.assert_allclose(f, np.stack([uv[:, 0], 1.0 - uv[:, 1]], -1))
    np.testing.assert_allclose(flip_v(f), uv, atol=1e-15)
    t = flip_v(torch.from_numpy(uv))
    assert isinstance(t, torch.Tensor)
    with pytest.raises(ValueError, match="uv"):
        flip_v(np.zeros((3, 3)))


def test_checkerboard_squares():
    a, b = (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)
    tex = checkerboard(8, 2, (a, b))
    assert tex.shape == (8, 8, 3) and tex.dtype == np.float64
    # 2 x 2 squares of 4 x 4 texels, colour a in the top-left one
    np.testing.assert_array_equal(tex[:4, :4], np.broadcast_to(a, (4, 4, 3)))
    np.testing.assert_array_equal(tex[4:, 4:], np.broadcast_to(a, (4, 4, 3)))
    np.testing.assert_array_equal(tex[:4, 4:], np.broadcast_to(b, (4, 4, 3)))
    np.testing.assert_array_equal(tex[4:, :4], np.broadcast_to(b, (4, 4, 3)))


def test_checkerboard_smooth_shading():
    flat = checkerboard(16, 4, ((1.0,), (0.5,)))
    tex = checkerboard(16, 4, ((1.0,), (0.5,)), smooth=True)
    r = (np.arange(16) + 0.5) / 16
    shade = 0.75 + 0.25 * np.sin(2 * np.pi * r)[:, None] * np.cos(3 * np.pi * r)[None, :]
    np.testing.assert_allclose(tex[..., 0], flat[..., 0] * shade, atol=1e-15)
    assert 0.5 <= shade.min() and shade.max() <= 1.0


@pytest.mark.parametrize(
    "kwargs, exc, match",
    [
        (dict(size=0), ValueError, "size"),
        (dict(size=2.5), TypeError, "size"),
        (dict(checks=0), ValueError, "checks"),
        (dict(colors=((1, 0, 0), (0, 1, 0), (0, 0, 1))), ValueError, "colors"),
        (dict(colors=(1.0, 0.0)), ValueError, "colors"),
    ],
)
def test_checkerboard_validation(kwargs, exc, match):
    with pytest.raises(exc, match=match):
        checkerboard(**kwargs)
