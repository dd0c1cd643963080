import numpy as np
import pytest

from polygeo import io
from polygeo import synthetic as sy
from polygeo.cli import main

KEYS = {
    "points",
    "normals",
    "k1",
    "k2",
    "d1",
    "d2",
    "mean_curvature",
    "gaussian_curvature",
    "status",
}


def test_cli_point_cloud_npz_and_ply(tmp_path, capsys):
    s = sy.sphere(1500, seed=1)
    src = tmp_path / "cloud.npy"
    np.save(src, s.points)
    out = tmp_path / "res" / "out.npz"
    ply = tmp_path / "res" / "out.ply"
    rc = main(["jets", str(src), "-o", str(out), "--k", "20", "--order", "2", "--ply", str(ply)])
    assert rc == 0
    with np.load(out) as z:
        assert set(z.files) == KEYS
        np.testing.assert_array_equal(z["points"], s.points)
        assert (z["status"] == 0).all() and z["status"].dtype == np.int64
        assert (z["k1"] >= z["k2"]).all()
        assert np.median(z["mean_curvature"]) == pytest.approx(-1.0, rel=0.02)
        assert (np.einsum("ij,ij->i", z["normals"], s.normals) > 0.99).all()
        h = z["mean_curvature"]
    back = io.read_points(ply)
    assert set(back.attributes) == {
        "k1",
        "k2",
        "d1",
        "d2",
        "mean_curvature",
        "gaussian_curvature",
        "status",
    }
    np.testing.assert_allclose(back.attributes["mean_curvature"], h, rtol=1e-6)
    text = capsys.readouterr().out
    assert "status 0 (ok): 1500" in text and "mean_curvature" in text and "points/s" in text


@pytest.mark.slow
def test_cli_mesh_with_flipped_faces_and_auto(tmp_path, capsys):
    m = sy.torus_mesh(40)
    f = m.faces.copy()
    f[::2] = f[::2, ::-1]
    src = tmp_path / "torus.ply"
    io.write_ply(src, m.points, f, precision="double")
    out = tmp_path / "t.npz"
    assert main(["jets", str(src), "-o", str(out), "--k", "12", "--order", "auto", "--quiet"]) == 0
    assert capsys.readouterr().out == ""
    with np.load(out) as z:
        assert (np.einsum("ij,ij->i", z["normals"], m.normals) > 0.9).all()


def test_cli_nan_point_reported(tmp_path, capsys):
    pts = np.vstack([sy.sphere(500).points, [[np.nan, 0, 0]]])
    src = tmp_path / "c.xyz"
    np.savetxt(src, pts)
    out = tmp_path / "c.npz"
    assert main(["jets", str(src), "-o", str(out)]) == 0
    assert "status 1 (nonfinite input): 1" in capsys.readouterr().out
    with np.load(out) as z:
        assert z["status"][-1] == 1 and (z["status"][:-1] == 0).all()


@pytest.mark.parametrize(
    "args, msg",
    [
        (["--k", "many"], "--k: expected an integer"),
        (["--order", "9"], "order"),
        (["--k", "3"], "k must be at least"),
    ],
)
def test_cli_bad_options(tmp_path, capsys, args, msg):
    src = tmp_path / "c.npy"
    np.save(src, sy.sphere(100).points)
    assert main(["jets", str(src), "-o", str(tmp_path / "o.npz"), *args]) == 2
    assert msg in capsys.readouterr().err


def test_cli_missing_file_and_bad_output(tmp_path, capsys):
    assert main(["jets", str(tmp_path / "none.ply"), "-o", str(tmp_path / "o.npz")]) == 2
    assert "none.ply" in capsys.readouterr().err
    src = tmp_path / "c.npy"
    np.save(src, sy.sphere(100).points)
    assert main(["jets", str(src), "-o", str(tmp_path / "o.txt")]) == 2
    assert ".npz" in capsys.readouterr().err


def test_cli_help_explains_conventions(capsys):
    with pytest.raises(SystemExit):
        main(["jets", "--help"])
    text = capsys.readouterr().out
    for word in ("k1 >= k2", "-1/r", "Status codes", "--radius", "--order", "--ply", "--quiet"):
        assert word in text


def test_cli_interpolate_flag(tmp_path):
    # exact sphere vertices: the interpolating jets have the smaller bias of H
    s = sy.sphere(3000, radius=2.0, seed=5)
    src = tmp_path / "sphere.npy"
    np.save(src, s.points)
    errs = []
    for extra in ([], ["--interpolate"]):
        out = tmp_path / f"o{len(extra)}.npz"
        assert main(["jets", str(src), "-o", str(out), "--quiet", *extra]) == 0
        with np.load(out) as z:
            errs.append(np.median(np.abs(z["mean_curvature"] - s.mean_curvature)))
    assert errs[1] < 0.85 * errs[0]
