"""A fin hung on a closed sphere: the vertices whose neighbourhood reaches it are flagged."""

import numpy as np
import pytest
import trimesh

from polygeo.cli import main
from polygeo.estimate import differential_quantities
from polygeo.io import write_ply
from polygeo.mesh import non_manifold_edges
from polygeo.neighbors import knn, reaches_non_manifold
from polygeo.status import Status, describe


def _sphere_with_fin():
    s = trimesh.creation.icosphere(subdivisions=3)  # 642 vertices, closed
    v, f = np.asarray(s.vertices), np.asarray(s.faces)
    a, b = f[0, 0], f[0, 1]
    mid = 0.5 * (v[a] + v[b])
    apex = mid * 1.15  # a triangle standing out of the surface on edge (a, b)
    v = np.vstack([v, apex])
    f = np.vstack([f, [a, b, len(v) - 1]])
    return v, f, (a, b, len(v) - 1)


def test_fin_is_non_manifold_and_flagged():
    v, f, (a, b, apex) = _sphere_with_fin()
    np.testing.assert_array_equal(non_manifold_edges(f), [sorted((a, b))])
    dq = differential_quantities(v, f, k=20)
    st = dq.status
    assert st[apex] == Status.NON_MANIFOLD and st[a] == st[b] == Status.NON_MANIFOLD
    # exactly the vertices whose 21 nearest (the point included) hold a fin-face vertex...
    fin_faces = np.flatnonzero(np.isin(f, [a, b]).sum(1) == 2)
    touched = np.unique(f[fin_faces])
    near = np.isin(knn(v, 21).index, touched).any(axis=1)
    np.testing.assert_array_equal(st == Status.NON_MANIFOLD, near)
    # ...while the rest of the sphere keeps its reliable status and curvature
    far = ~near
    assert far.sum() > 500 and (st[far] == 0).all()
    np.testing.assert_allclose(dq.mean_curvature[far], -1.0, atol=0.05)
    assert describe(7) == "non manifold"


def test_manifold_mesh_unflagged_and_ring_neighbourhoods():
    s = trimesh.creation.icosphere(subdivisions=2)
    assert not reaches_non_manifold(s.vertices, s.faces).any()
    v, f, (a, b, apex) = _sphere_with_fin()
    ring = reaches_non_manifold(v, f, rings=1)
    assert ring[apex] and ring[a] and 3 <= ring.sum() < 30
    with pytest.raises(ValueError):
        reaches_non_manifold(v, f[:, :2])


def test_cli_reports_the_fin(tmp_path, capsys):
    v, f, (_, _, apex) = _sphere_with_fin()
    write_ply(tmp_path / "fin.ply", v, f, precision="double")
    out = tmp_path / "o.npz"
    assert main(["jets", str(tmp_path / "fin.ply"), "-o", str(out)]) == 0
    assert "status 7 (non manifold)" in capsys.readouterr().out
    with np.load(out) as z:
        assert z["status"][apex] == 7
