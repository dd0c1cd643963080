"""Tests of polygeo.render.settings: the SoftRas sigma conversion and RasterSettings."""

import math

import numpy as np
import pytest

from polygeo.render import RasterSettings, sigma_from_softras


def test_sigma_from_softras_scales_with_pixel_size():
    # one pixel is 2 / S normalised units: a squared distance scales by (S / 2)^2
    assert sigma_from_softras(1e-4, 128) == pytest.approx(1e-4 * 64**2)
    assert sigma_from_softras(1e-4, 256) == pytest.approx(4 * sigma_from_softras(1e-4, 128))
    assert sigma_from_softras(2.0, 2) == pytest.approx(2.0)


@pytest.mark.parametrize(
    "args, exc, match",
    [
        ((0.0, 128), ValueError, "sigma_ndc"),
        ((-1e-4, 128), ValueError, "sigma_ndc"),
        ((float("nan"), 128), ValueError, "sigma_ndc"),
        ((1e-4, 0), ValueError, "image_size"),
        ((1e-4, 12.5), TypeError, "image_size"),
    ],
)
def test_sigma_from_softras_validation(args, exc, match):
    with pytest.raises(exc, match=match):
        sigma_from_softras(*args)


def test_blur_margin_is_where_coverage_reaches_the_threshold():
    s = RasterSettings(sigma=0.3, blur_threshold=1e-3)
    d = s.blur_margin
    # coverage outside an edge at distance d: sigmoid(-d^2 / sigma)
    assert 1.0 / (1.0 + math.exp(d * d / s.sigma)) == pytest.approx(s.blur_threshold)
    assert RasterSettings(blur_threshold=0.0).blur_margin == math.inf


def test_background_for_broadcasts_and_normalises():
    s = RasterSettings(background=[0.5])
    np.testing.assert_array_equal(s.background_for(3), [0.5, 0.5, 0.5])
    s = RasterSettings(background=np.array([0.1, 0.2, 0.3]))
    assert s.background == (0.1, 0.2, 0.3)  # stored as a tuple of floats
    np.testing.assert_array_equal(s.background_for(3), [0.1, 0.2, 0.3])
    with pytest.raises(ValueError, match="background: expected 1 or 2 values"):
        s.background_for(2)


def test_values_are_normalised_to_python_types():
    s = RasterSettings(sigma=np.float32(0.5), tile_size=np.int64(16), min_area=0)
    assert type(s.sigma) is float and type(s.tile_size) is int and s.min_area == 0.0


@pytest.mark.parametrize(
    "kwargs, exc, match",
    [
        (dict(sigma=0.0), ValueError, "sigma"),
        (dict(sigma=-1.0), ValueError, "sigma"),
        (dict(gamma=0.0), ValueError, "gamma"),
        (dict(blur_threshold=0.5), ValueError, "blur_threshold"),
        (dict(blur_threshold=-0.1), ValueError, "blur_threshold"),
        (dict(tile_size=0), ValueError, "tile_size"),
        (dict(tile_size=257), ValueError, "tile_size"),
        (dict(tile_size=8.0), TypeError, "tile_size"),
        (dict(background=()), ValueError, "background"),
        (dict(background=(0.0, float("nan"), 0.0)), ValueError, "background"),
        (dict(background_depth=float("inf")), ValueError, "background_depth"),
        (dict(znear=0.0), ValueError, "znear"),
        (dict(znear=1.0, zfar=1.0), ValueError, "zfar"),
        (dict(zfar=-5.0), ValueError, "zfar"),
        (dict(min_area=-1e-9), ValueError, "min_area"),
        (dict(hard=1), TypeError, "hard"),
        (dict(cull_backfaces="yes"), TypeError, "cull_backfaces"),
    ],
)
def test_raster_settings_validation(kwargs, exc, match):
    with pytest.raises(exc, match=match):
        RasterSettings(**kwargs)
