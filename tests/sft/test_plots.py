"""Tests of sft.plots: the charts are written as readable PNG images (files in tmp_path)."""

import json

import numpy as np
import pytest

from sft.plots import overlay_png, write_charts

plt_image = pytest.importorskip("matplotlib.image")


def _png(path):
    assert path.is_file() and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    img = plt_image.imread(path)
    assert img.ndim == 3 and img.shape[2] in (3, 4)
    assert float(np.ptp(img[..., :3])) > 0  # something was drawn
    return img


def _rows(n=4):
    rows = []
    for f in range(n):
        row = {"frame": f}
        for key in ("e_3d", "e_n", "rmse"):
            row[key] = 0.1 * (f + 1)
            row[key + "_template"] = 0.2 * (f + 1)
        rows.append(row)
    return rows


def test_write_charts_errors_and_losses(tmp_path):
    losses = tmp_path / "losses.jsonl"
    curves = [{"frame": f, "iterations": 10 + f, "loss": list(np.geomspace(1, 1e-3, 10 + f))}
              for f in range(4)]
    losses.write_text("\n".join(json.dumps(c) for c in curves) + "\n\n")
    paths = write_charts(tmp_path, _rows(), losses)
    assert [p.name for p in paths] == ["errors.png", "losses.png"]
    for p in paths:
        _png(p)


def test_write_charts_without_ground_truth_or_losses(tmp_path):
    rows = [{"frame": 0, "loss": 1.0}]
    assert write_charts(tmp_path, rows, tmp_path / "missing.jsonl") == []
    assert list(tmp_path.iterdir()) == []
    assert write_charts(tmp_path, [], tmp_path / "missing.jsonl") == []


def test_overlay_png_with_and_without_error_map(tmp_path, rng):
    H, W = 24, 32
    target = rng.uniform(0, 1, (H, W, 3))
    rgb = np.clip(target + rng.normal(0, 0.1, (H, W, 3)), 0, 1)
    alpha = np.ones((H, W))
    p3 = overlay_png(tmp_path / "three.png", target, rgb, alpha, None)
    err = (rng.uniform(0, 1, (H, W)), (rng.uniform(0, 1, (H, W)) > 0.3).astype(float), 0.01)
    p4 = overlay_png(tmp_path / "four.png", target, rgb, alpha, err)
    a, b = _png(p3), _png(p4)
    assert b.shape[1] > a.shape[1]  # one more panel side by side
    assert b.shape[0] == a.shape[0]
