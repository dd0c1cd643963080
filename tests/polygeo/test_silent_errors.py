"""Cases that used to return numbers marked reliable without a word (issue 17, item 5)."""

import numpy as np
import pytest
import pyvista as pv

import polygeo.synthetic as sy
from polygeo.cli import main
from polygeo.io import write_ply
from polygeo.partition import patch_count_for_vertices
from polygeo.patches import PatchSet

R, r = 1.0, 0.5  # pyvista's ParametricTorus: ring and cross-section radii


def _torus(res=50):
    m = pv.ParametricTorus(u_res=res, v_res=res).triangulate().clean()
    return np.asarray(m.points, dtype=np.float64), m.faces.reshape(-1, 4)[:, 1:].astype(np.int64)


def _off_torus(p, scale):
    """Distance of points to the analytic torus scaled by ``scale``, over ``scale``."""
    q = np.asarray(p) / scale
    return np.abs(np.hypot(np.hypot(q[:, 0], q[:, 1]) - R, q[:, 2]) - r)


def test_patch_count_is_scale_free_and_validated():
    assert patch_count_for_vertices(9801, 15) == 108
    assert patch_count_for_vertices(10, 15) == 1 and patch_count_for_vertices(10**7, 15) == 400
    for bad in (dict(n_vertices=0, n_coeffs=15), dict(n_vertices=10, n_coeffs=0),
                dict(n_vertices=10, n_coeffs=3, high=0)):
        with pytest.raises(ValueError):
            patch_count_for_vertices(**bad)


def test_polyfit_torus_same_relative_error_at_every_scale():
    v, f = _torus()
    errs, counts = [], []
    for scale in (1e-3, 1.0, 1e3):
        ps = PatchSet.fit(v * scale, f)
        rv, _ = ps.resample(2)  # between the vertices, where spikes and fins show
        e = _off_torus(rv, scale)
        errs.append((np.median(e), e.max()))
        counts.append(ps.n_patches)
    assert counts[0] == counts[1] == counts[2]
    np.testing.assert_allclose(errs[0], errs[1], rtol=1e-3)
    np.testing.assert_allclose(errs[2], errs[1], rtol=1e-3)
    assert errs[1][1] < 0.02 * r  # the default leaves the torus by < 2 % of its tube radius


def test_polyfit_warns_when_the_surface_leaves_the_input(tmp_path, capsys):
    v, f = _torus()
    write_ply(tmp_path / "t.ply", v, f, precision="double")
    args = ["polyfit", str(tmp_path / "t.ply"), "-o", str(tmp_path / "p.npz"),
            "--chamfer-samples", "0"]
    assert main(args) == 0
    cap = capsys.readouterr()
    assert "deviation        resampled level 2" in cap.out and "warning" not in cap.err
    assert main([*args, "--patches", "40"]) == 0  # too many patches for 2,401 vertices
    cap = capsys.readouterr()
    assert "leaves the input" in cap.err


@pytest.mark.parametrize("n, k", [(15, 100), (642, 5000), (50, 50)])
def test_jets_k_beyond_the_cloud_is_refused(tmp_path, capsys, n, k):
    src = tmp_path / "c.npy"
    np.save(src, sy.sphere(n).points)
    assert main(["jets", str(src), "-o", str(tmp_path / "o.npz"), "--k", str(k)]) == 2
    err = capsys.readouterr().err
    assert f"--k: {k} neighbours requested" in err and f"has {n} finite points" in err


def test_jets_xyz_rgb_columns_are_not_normals(tmp_path):
    s = sy.sphere(300)
    rgb = np.random.default_rng(0).integers(0, 256, (300, 3))
    np.savetxt(tmp_path / "c.xyz", np.hstack([s.points, rgb]), fmt="%.9g")
    out = tmp_path / "o.npz"
    assert main(["jets", str(tmp_path / "c.xyz"), "-o", str(out), "--quiet"]) == 0
    with np.load(out) as z:
        # outward normals from propagation: H of the unit sphere is -1, never +1
        ok = z["status"] == 0
        assert ok.mean() > 0.9
        np.testing.assert_allclose(np.median(z["mean_curvature"][ok]), -1.0, atol=0.1)
        assert (np.einsum("ij,ij->i", z["normals"], s.points) > 0).mean() > 0.99
