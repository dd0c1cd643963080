"""datasets/generate_sft.py: isometry of the deformations and the VTK camera convention."""

import cv2
import numpy as np
import pytest

from polygeo.mesh import edge_lengths, edges
from sft.data import load_sequence


def _max_strain(g, kind, n, t):
    ab, faces, _ = g.sheet_grid(n, (3 * n) // 4 + 1, 0.24, 0.18)
    e = edges(faces)
    l0 = edge_lengths(np.concatenate([ab, np.zeros((len(ab), 1))], 1), e)
    return np.abs(edge_lengths(g.deform(kind, ab, t, (0.24, 0.18)), e) / l0 - 1).max()


@pytest.mark.parametrize("kind", ["bend", "roll", "swave", "fold", "curl", "small", "rigid"])
def test_isometric_kinds_preserve_lengths(generator_module, kind):
    """Edges are chords of the bent sheet, shorter by (kappa l)^2 / 24: the strain is small
    and converges at second order under refinement (the surface itself is isometric)."""
    for t in (0.5, 1.0):
        coarse = _max_strain(generator_module, kind, 49, t)
        fine = _max_strain(generator_module, kind, 97, t)
        assert coarse < 1e-2, (kind, t, coarse)
        assert fine < coarse / 3.5 or fine < 1e-9, (kind, t, coarse, fine)


def test_cloth_is_nearly_isometric(generator_module):
    g = generator_module
    ab, faces, _ = g.sheet_grid(25, 19, 0.24, 0.18)
    e = edges(faces)
    l0 = edge_lengths(np.concatenate([ab, np.zeros((len(ab), 1))], 1), e)
    X = g.deform("cloth", ab, 0.5, (0.24, 0.18))
    strain = np.abs(edge_lengths(X, e) / l0 - 1)
    assert 1e-4 < strain.max() < 0.015  # nearly isometric: about 1 % at most


def test_vtk_renders_follow_the_opencv_camera(make_sequence):
    """The VTK mask equals an independent polygon fill of the projected triangles."""
    seq = load_sequence(make_sequence("bend", 3))
    S = 8  # fill at 8x resolution, then average: coverage per pixel
    for i in (0, 2):
        X = seq.gt(i)
        p = X @ seq.K.T
        px = p[:, :2] / p[:, 2:3]
        hi = np.zeros((seq.height * S, seq.width * S), np.uint8)
        pts = np.round(px * S * 16 - 0.5 * 16).astype(np.int32)  # 4 fractional bits
        for f in seq.template.faces:
            cv2.fillPoly(hi, [pts[f]], 1, lineType=cv2.LINE_8, shift=4)
        cov = hi.reshape(seq.height, S, seq.width, S).mean(axis=(1, 3))
        ref = cov >= 0.5
        got = seq.mask(i) > 0
        iou = (ref & got).sum() / (ref | got).sum()
        assert iou > 0.98, iou
        assert np.abs(ref.astype(int) - got.astype(int)).sum() <= 0.02 * ref.sum()


def test_template_is_frame_zero(make_sequence):
    seq = load_sequence(make_sequence("bend", 3))
    np.testing.assert_allclose(seq.gt(0), seq.template.verts, atol=1e-6)
    assert seq.n_frames == 3 and seq.has_masks and seq.template.textured
