import json

import numpy as np
import pytest

import polygeo.synthetic as syn
from polygeo.cli import main
from polygeo.io import read_mesh, write_ply
from polygeo.patches import PatchSet
from polygeo.runs import load_checkpoint


@pytest.fixture
def sheet_ply(tmp_path):
    v, f = syn.draped_sheet_mesh(30, size=1.0, seed=2)
    path = tmp_path / "sheet.ply"
    write_ply(path, v, f)
    return path, v, f


@pytest.mark.slow
def test_polyfit_command_writes_patches_mesh_and_summary(tmp_path, sheet_ply, capsys):
    path, v, f = sheet_ply
    out = tmp_path / "patches.npz"
    mesh_out = tmp_path / "resampled.ply"
    js = tmp_path / "summary.json"
    rc = main([
        "polyfit", str(path), "-o", str(out), "--patches", "12", "--order", "3",
        "--resample", "1", "--mesh-out", str(mesh_out), "--chamfer-samples", "2000",
        "--chamfer-dense", "20000",
        "--json", str(js),
    ])
    assert rc == 0
    text = capsys.readouterr().out
    for key in ("patches", "height RMSE", "normal error", "boundary gap", "foldover share",
                "Chamfer x 1e3", "surface", "sampling floor", "dense points"):
        assert key in text
    ps = PatchSet.load(out)
    assert ps.n_patches >= 8 and ps.order == 3
    np.testing.assert_allclose(ps.vertices.numpy(), v, rtol=0, atol=1e-6)  # PLY float32
    res = read_mesh(mesh_out)
    assert len(res.faces) == 4 * len(f)
    summary = json.loads(js.read_text())
    assert summary["patches"] == ps.n_patches
    assert summary["chamfer"] is not None and summary["chamfer"] < 1e-3
    # the dense protocol lowers the point protocol's floor; the surface distance has none
    assert summary["chamfer_dense_floor"] < 0.8 * summary["chamfer_floor"]
    assert summary["chamfer_surface"] < summary["chamfer_dense"] < summary["chamfer"]
    # the resampled mesh is what the set evaluates to
    rv, _ = ps.resample(1)
    np.testing.assert_allclose(res.points, rv, atol=1e-6)


@pytest.mark.slow
def test_polyfit_auto_order_optimize_and_target(tmp_path, sheet_ply, capsys):
    path, _, _ = sheet_ply
    out = tmp_path / "p.npz"
    assert main(["polyfit", str(path), "-o", str(out), "--order", "auto", "--tol", "1e-3",
                 "--orient", "optimize", "--patches", "10", "--chamfer-samples", "0"]) == 0
    ps = PatchSet.load(out)
    assert ps.orient == "optimize"
    assert (ps.residual * ps.scale <= 1e-3 + 1e-12).all() or int(ps.orders.max()) == 6
    assert main(["polyfit", str(path), "-o", str(out), "--target-rmse", "1e-3",
                 "--chamfer-samples", "0"]) == 0
    assert "K search" in capsys.readouterr().out


def test_polyfit_point_cloud(tmp_path, capsys):
    s = syn.sphere(1500, seed=0)
    path = tmp_path / "cloud.npy"
    np.save(path, np.concatenate([s.points, s.normals], 1))
    assert main(["polyfit", str(path), "-o", str(tmp_path / "c.npz"), "--patches", "10"]) == 0
    text = capsys.readouterr().out
    assert "point cloud" in text and "Chamfer" not in text


def test_polyfit_bad_input(tmp_path, sheet_ply, capsys):
    path, _, _ = sheet_ply
    out = str(tmp_path / "x.npz")
    assert main(["polyfit", str(tmp_path / "missing.ply"), "-o", out]) == 2
    assert main(["polyfit", str(path), "-o", out, "--order", "seven"]) == 2
    assert main(["polyfit", str(path), "-o", out, "--order", "9"]) == 2
    assert main(["polyfit", str(path), "-o", out, "--patches", "100000"]) == 2
    err = capsys.readouterr().err
    assert "order" in err and "n_patches" in err
    with pytest.raises(SystemExit):
        main(["polyfit", str(path), "-o", out, "--orient", "svd"])


def test_train_stn_command(tmp_path, capsys):
    w = tmp_path / "w.pt"
    rc = main([
        "train-stn", "--out", str(w), "--checkpoint-dir", str(tmp_path / "ck"), "--steps", "2",
        "--batch-size", "4", "--points", "16", "--mesh-share", "0", "--eval-every", "1",
        "--train-patches", "8", "--val-patches", "4", "--quiet", "--threads", "1",
    ])
    assert rc == 0
    assert w.is_file() and (tmp_path / "ck" / "stn_checkpoint.pt").is_file()
    meta = load_checkpoint(w).meta["meta"]
    assert meta["validation"]["step"] in (1, 2) and meta["steps_run"] == 2
    assert meta["train_cpu_seconds"] > 0 and meta["train_seconds"] > 0
    assert json.loads(w.with_suffix(".json").read_text()) == meta
    assert "held-out height RMS" in capsys.readouterr().out
