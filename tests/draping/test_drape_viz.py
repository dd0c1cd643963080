"""draping.viz.render_drapes: a depth buffer, so the nearest surface is the one drawn."""

from __future__ import annotations

import numpy as np
import pytest

from draping import viz


def _square(x: float):
    """A unit square in the plane ``x = const`` facing +x (two triangles)."""
    v = np.array([[x, -0.5, -0.5], [x, 0.5, -0.5], [x, 0.5, 0.5], [x, -0.5, 0.5]])
    return v, np.array([[0, 1, 2], [0, 2, 3]])


@pytest.mark.parametrize("azim, nearest", [(0.0, "garment"), (180.0, "body")])
def test_nearest_surface_wins_whatever_the_face_order(azim, nearest):
    body, bf = _square(0.0)
    garment, gf = _square(0.01)  # 1 cm in front of the body, seen from +x
    colours = {"body": (1.0, 0.0, 0.0), "garment": (0.0, 0.0, 1.0)}
    (im,) = viz.render_drapes([(body, bf, garment)], gf, elev=0.0, azim=azim, size=64,
                              body_color=colours["body"], garment_color=colours["garment"])
    rgb = np.asarray(im, dtype=float)[32, 32] / 255.0
    want = np.array(colours[nearest])
    # shaded by the light direction: the dominant channel is the nearest surface's colour
    assert np.argmax(rgb) == np.argmax(want)
    assert rgb[np.argmax(want)] > 0.3 and rgb.min() < 0.05


def test_one_frame_box_and_errors():
    body, bf = _square(0.0)
    garment, gf = _square(0.01)
    ims = viz.render_drapes([(body, bf, garment), (body + 5.0, bf, garment + 5.0)], gf,
                            titles=["a", "b"], size=40, azim=0.0, elev=0.0)
    assert [im.size for im in ims] == [(40, 40), (40, 40)]
    # the box spans both frames: each frame fills less than half the picture
    for im in ims:
        drawn = (np.asarray(im, dtype=float).sum(-1) < 3 * 250).mean()
        assert 0.0 < drawn < 0.5
    with pytest.raises(ValueError, match="meshes"):
        viz.render_drapes([], gf)
    with pytest.raises(ValueError, match="size"):
        viz.render_drapes([(body, bf, garment)], gf, size=4)
