import numpy as np
import pytest
import torch
import trimesh

from polygeo import io


@pytest.fixture
def cloud(rng):
    return rng.normal(size=(50, 3)), rng.normal(size=(50, 3))


def test_ply_round_trip_with_attributes(tmp_path, cloud, rng):
    p, n = cloud
    f = np.array([[0, 1, 2], [2, 3, 4]])
    attrs = {"k1": rng.random(50), "d1": rng.random((50, 3)), "status": np.arange(50) % 4}
    out = io.write_ply(tmp_path / "sub" / "a.ply", p, f, attrs, normals=n, precision="double")
    d = io.read_points(out)
    np.testing.assert_array_equal(d.points, p)
    np.testing.assert_array_equal(d.normals, n)
    np.testing.assert_array_equal(d.faces, f)
    np.testing.assert_array_equal(d.attributes["k1"], attrs["k1"])
    np.testing.assert_array_equal(d.attributes["d1"], attrs["d1"])
    np.testing.assert_array_equal(d.attributes["status"], attrs["status"])
    assert d.attributes["status"].dtype.kind == "i"


def test_ply_float_precision_and_torch_input(tmp_path, cloud):
    p, _ = cloud
    io.write_ply(tmp_path / "b.ply", torch.from_numpy(p))
    d = io.read_points(tmp_path / "b.ply")
    assert d.faces is None and d.normals is None and d.points.dtype == np.float64
    np.testing.assert_allclose(d.points, p, rtol=1e-7, atol=1e-7)


def test_ply_keeps_vertex_order_and_duplicates(tmp_path):
    # duplicated and unreferenced vertices must survive (no trimesh processing)
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0], [5, 5, 5.0]])
    f = np.array([[0, 1, 2], [3, 2, 1]])
    io.write_ply(tmp_path / "m.ply", v, f, precision="double")
    d = io.read_mesh(tmp_path / "m.ply")
    np.testing.assert_array_equal(d.points, v)
    np.testing.assert_array_equal(d.faces, f)


@pytest.mark.parametrize("suffix", ["obj", "off"])
def test_obj_off_read_in_order(tmp_path, suffix):
    m = trimesh.creation.icosphere(subdivisions=1)
    path = tmp_path / f"s.{suffix}"
    m.export(path)
    d = io.read_mesh(path)
    np.testing.assert_allclose(d.points, m.vertices, atol=1e-7)
    np.testing.assert_array_equal(d.faces, m.faces)


def test_xyz_npy_npz(tmp_path, cloud):
    p, n = cloud
    np.savetxt(tmp_path / "a.xyz", np.hstack([p, n]), header="x y z nx ny nz")
    d = io.read_points(tmp_path / "a.xyz")
    np.testing.assert_allclose(d.points, p)
    np.testing.assert_allclose(d.normals, n)
    np.savetxt(tmp_path / "b.txt", p)
    assert io.read_points(tmp_path / "b.txt").normals is None
    np.save(tmp_path / "c.npy", p.astype(np.float32))
    d = io.read_points(tmp_path / "c.npy")
    assert d.points.dtype == np.float64 and d.points.shape == (50, 3)
    io.write_npz(
        tmp_path / "d.npz", points=p, normals=n, k1=np.ones(50), faces=np.array([[0, 1, 2]])
    )
    d = io.read_points(tmp_path / "d.npz")
    np.testing.assert_array_equal(d.points, p)
    np.testing.assert_array_equal(d.faces, [[0, 1, 2]])
    assert set(d.attributes) == {"k1"}


def test_write_npz_atomic_replace(tmp_path):
    path = tmp_path / "x.npz"
    io.write_npz(path, a=np.zeros(3))
    io.write_npz(path, a=torch.ones(3))
    with np.load(path) as z:
        np.testing.assert_array_equal(z["a"], np.ones(3))
    assert [q.name for q in tmp_path.iterdir()] == ["x.npz"]  # no temp files left


def test_failed_write_leaves_old_file(tmp_path):
    path = tmp_path / "y.ply"
    io.write_ply(path, np.zeros((3, 3)))
    before = path.read_bytes()
    with pytest.raises(ValueError):
        io.write_ply(path, np.zeros((3, 3)), attributes={"bad": np.zeros(4)})
    assert path.read_bytes() == before


def test_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.ply"):
        io.read_points(tmp_path / "nope.ply")
    (tmp_path / "e.ply").write_bytes(b"")
    with pytest.raises(ValueError, match="e.ply: the file is empty"):
        io.read_points(tmp_path / "e.ply")
    (tmp_path / "u.stl2").write_text("x")
    with pytest.raises(ValueError, match="unknown extension"):
        io.read_points(tmp_path / "u.stl2")
    np.save(tmp_path / "w.npy", np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"w.npy: expected an \(N, 3\)"):
        io.read_points(tmp_path / "w.npy")
    (tmp_path / "g.xyz").write_text("1 2 three\n")
    with pytest.raises(ValueError, match="g.xyz"):
        io.read_points(tmp_path / "g.xyz")
    (tmp_path / "h.ply").write_text("not a ply")
    with pytest.raises(ValueError, match="h.ply"):
        io.read_points(tmp_path / "h.ply")
    io.write_npz(tmp_path / "i.npz", other=np.zeros(3))
    with pytest.raises(ValueError, match="'points' or 'vertices'"):
        io.read_points(tmp_path / "i.npz")
    io.write_ply(tmp_path / "c.ply", np.zeros((3, 3)))
    with pytest.raises(ValueError, match="bare point cloud"):
        io.read_mesh(tmp_path / "c.ply")
    with pytest.raises(ValueError):
        io.read_points(tmp_path)


@pytest.mark.parametrize(
    "kwargs, exc",
    [
        (dict(points=np.zeros((3, 2))), ValueError),
        (dict(points=np.zeros((3, 3)), faces=np.array([[0, 1, 3]])), ValueError),
        (dict(points=np.zeros((3, 3)), faces=np.zeros((1, 3))), ValueError),
        (dict(points=np.zeros((3, 3)), normals=np.zeros((2, 3))), ValueError),
        (dict(points=np.zeros((3, 3)), attributes={"x": np.zeros(3)}), ValueError),
        (dict(points=np.zeros((3, 3)), attributes={"a b": np.zeros(3)}), ValueError),
        (dict(points=np.zeros((3, 3)), precision="half"), ValueError),
        (dict(points=np.array([["a"] * 3] * 3)), TypeError),
    ],
)
def test_write_ply_validators(tmp_path, kwargs, exc):
    with pytest.raises(exc):
        io.write_ply(tmp_path / "v.ply", **kwargs)


def test_write_npz_needs_arrays(tmp_path):
    with pytest.raises(ValueError):
        io.write_npz(tmp_path / "z.npz")
