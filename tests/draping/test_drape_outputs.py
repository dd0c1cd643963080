"""draping.outputs: the run folder every drape method writes (frames, metrics, pictures)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from PIL import Image

from draping import outputs


def _octahedron(scale=1.0):
    v = scale * np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1.0]])
    f = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
                  [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    return v, f


def _sheet(n=4, z=0.0):
    u, w = np.meshgrid(np.linspace(-0.5, 0.5, n), np.linspace(-0.5, 0.5, n), indexing="ij")
    v = np.stack([u.ravel(), w.ravel(), np.full(n * n, z)], 1)
    f = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
            f += [[a, b, c], [a, c, d]]
    return v, np.array(f)


def test_frame_round_trip_numpy_and_torch(tmp_path):
    rng = np.random.default_rng(0)
    gv, gf = _sheet()
    gv = gv + 1e-3 * rng.standard_normal(gv.shape)
    bv, bf = _octahedron(0.3)
    pg, pb = outputs.write_frame(tmp_path, 7, torch.from_numpy(gv), gf, bv, torch.from_numpy(bf))
    assert pg == tmp_path / "meshes" / "000007.ply" and pb == tmp_path / "body" / "000007.ply"
    x, f = outputs.read_frame(tmp_path, 7)
    np.testing.assert_array_equal(x, gv)  # float64 garment: exact
    np.testing.assert_array_equal(f, gf)
    b, f2 = outputs.read_frame(tmp_path, 7, "body")
    np.testing.assert_allclose(b, bv, atol=1e-7)  # float32 body
    np.testing.assert_array_equal(f2, bf)


@pytest.mark.parametrize("kwargs, match", [
    ({"t": -1}, "t: expected an integer"),
    ({"garment_vertices": np.zeros((16, 2))}, "garment_vertices"),
    ({"garment_vertices": np.full((16, 3), np.nan)}, "garment_vertices"),
    ({"body_faces": np.array([[0, 1, 99]])}, "body_faces"),
])
def test_write_frame_bad_input(tmp_path, kwargs, match):
    gv, gf = _sheet()
    bv, bf = _octahedron()
    args = {"t": 0, "garment_vertices": gv, "garment_faces": gf, "body_vertices": bv,
            "body_faces": bf, **kwargs}
    with pytest.raises((ValueError, TypeError), match=match):
        outputs.write_frame(tmp_path, **args)


def test_frame_metrics_against_hand_values():
    gv, gf = _sheet(2)  # one unit square, two triangles, edges 1, 1, 1, 1 and sqrt 2
    x = gv * np.array([2.0, 1.0, 1.0])  # stretch x by 2
    m = outputs.frame_metrics(x, gv, gf)
    # edges: two along x double (+100 %), two along y unchanged, diagonal sqrt(5)/sqrt(2)
    diag = 100.0 * (np.sqrt(5.0) / np.sqrt(2.0) - 1.0)
    edges = [100.0, 100.0, 0.0, 0.0, diag]
    assert m["eps_e"] == pytest.approx(np.mean(edges))
    assert m["eps_a"] == pytest.approx(100.0)
    assert "eps_c" not in m
    # a body: the octahedron of radius 0.6 around the origin holds the sheet's centre only
    bv, bf = _octahedron(0.6)
    sv, sf = _sheet(3)
    m = outputs.frame_metrics(sv, sv, sf, bv, bf)
    # inside the octahedron |x| + |y| + |z| < 0.6: the centre and the four edge midpoints
    inside = (np.abs(sv).sum(1) < 0.6).sum()
    assert m["eps_c"] == pytest.approx(100.0 * inside / len(sv))
    assert m["min_distance_mm"] == pytest.approx(-1000.0 * 0.6 / np.sqrt(3.0))
    assert m["eps_e"] == 0.0 and m["eps_a"] == 0.0
    d = np.linspace(-0.1, 0.1, len(sv))
    m = outputs.frame_metrics(sv, sv, sf, distance=d)
    assert m["eps_c"] == pytest.approx(100.0 * (d < 0).sum() / len(sv))
    with pytest.raises(ValueError, match="distance"):
        outputs.frame_metrics(sv, sv, sf, distance=d[:-1])
    with pytest.raises(ValueError, match="body_faces"):
        outputs.frame_metrics(sv, sv, sf, bv)
    with pytest.raises(ValueError, match="rest_vertices"):
        outputs.frame_metrics(sv, sv[:-1], sf)


def test_sequence_summary_and_metrics_file(tmp_path):
    rows = [{"frame": t, "eps_e": float(t), "eps_c": 0.5 * t, "seconds": 1.0 + t,
             "converged": True, "note": "x"} for t in range(4)]
    s = outputs.sequence_summary(rows)
    assert s["frames"] == 4
    assert s["mean"] == {"eps_e": 1.5, "eps_c": 0.75, "seconds": 2.5}
    assert s["max"] == {"eps_e": 3.0, "eps_c": 1.5, "seconds": 4.0}
    rec = outputs.write_metrics(tmp_path, rows, {"method": "test"}, garment_vertices=16)
    on_disk = json.loads((tmp_path / "metrics.json").read_text())
    assert on_disk == rec
    assert on_disk["per_frame"] == rows and on_disk["settings"] == {"method": "test"}
    assert on_disk["garment_vertices"] == 16 and on_disk["mean"]["eps_e"] == 1.5
    with pytest.raises(ValueError, match="at least one frame"):
        outputs.sequence_summary([])
    with pytest.raises(ValueError, match="eps_e is NaN"):
        outputs.sequence_summary([{"eps_e": float("nan")}])


def test_pictures_from_body_files_and_from_a_proxy(tmp_path):
    gv, gf = _sheet(5, z=0.4)
    bv, bf = _octahedron(0.3)
    n = 3
    for t in range(n):
        outputs.write_frame(tmp_path, t, gv + [0.05 * t, 0, 0], gf, bv, bf)
    ps, pg = outputs.write_pictures(tmp_path, gf, n, strip=2, gif=3)
    assert ps == tmp_path / "strip.png" and pg == tmp_path / "drape.gif"
    with Image.open(ps) as im:
        w1 = im.width
    with Image.open(pg) as im:
        assert im.n_frames == 3
    proxy = np.stack([bv] * n)
    outputs.write_pictures(tmp_path, gf, n, body_vertices=proxy, body_faces=bf, strip=3)
    with Image.open(ps) as im:
        assert im.width == pytest.approx(1.5 * w1)
    with pytest.raises(ValueError, match="body_faces"):
        outputs.write_pictures(tmp_path, gf, n, body_vertices=proxy)
    with pytest.raises(ValueError, match="at least 3 frames"):
        outputs.write_pictures(tmp_path, gf, n, body_vertices=proxy[:2], body_faces=bf)
    with pytest.raises(FileNotFoundError):
        outputs.write_pictures(tmp_path, gf, n + 1)
