"""The reader matrix: files written by other writers (tests/data/make_fixtures.py).

Every fixture holds trimesh's icosphere (unit sphere; 42 vertices and 80 triangles, or the
12-vertex icosahedron for STL) or, for ``hand_polygons.obj``, a cube. The reads are checked
against that geometry (radius, area, closedness, outward normals), not a stored output.
"""

from pathlib import Path

import numpy as np
import pytest
import trimesh

from polygeo import io
from polygeo.cli import main

DATA = Path(__file__).resolve().parents[1] / "data"

MESHES = [
    "vtk_ascii.ply", "vtk_binary.ply", "trimesh_ascii.ply", "meshio_binary.ply",
    "plyfile_be_double.ply", "plyfile_ascii_rgb.ply", "trimesh_tex.obj", "meshio.obj",
    "trimesh.off", "meshio.off", "vtk_ascii.stl", "vtk_binary.stl", "meshio_ascii.stl",
    "mesh.npz",
]
CLOUDS = [
    "plyfile_le_cloud.ply", "header_names.csv", "comments_space.txt", "xyzrgb.xyz",
    "xyz_normals.xyz", "semicolon.csv", "points.npy",
]
WITH_NORMALS = {"vtk_ascii.ply", "vtk_binary.ply", "plyfile_be_double.ply", "trimesh_tex.obj",
                "header_names.csv", "xyz_normals.xyz", "mesh.npz"}


def _area(v, f):
    return 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]),
                                axis=1).sum()


def _closed(f):
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return bool((counts == 2).all())


@pytest.mark.parametrize("name", MESHES)
def test_meshes_from_other_writers(name):
    d = io.read_mesh(DATA / name)
    n = 12 if name.endswith(".stl") else 42
    assert d.points.shape == (n, 3) and d.points.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(d.points, axis=1), 1.0, atol=1e-6)
    assert d.faces.shape == (2 * n - 4, 3) and _closed(d.faces)
    # the polyhedron's area (trimesh's own icosphere), whatever the writer
    ref = trimesh.creation.icosphere(subdivisions=0 if n == 12 else 1).area
    assert abs(_area(d.points, d.faces) - ref) / ref < 1e-5
    if name in WITH_NORMALS:
        np.testing.assert_allclose(d.normals, d.points, atol=1e-5)  # outward unit normals
    else:
        assert d.normals is None


@pytest.mark.parametrize("name", CLOUDS)
def test_clouds_from_other_writers(name):
    d = io.read_points(DATA / name)
    assert d.points.shape == (42, 3) and d.faces is None
    np.testing.assert_allclose(np.linalg.norm(d.points, axis=1), 1.0, atol=1e-6)
    if name in WITH_NORMALS:
        np.testing.assert_allclose(d.normals, d.points, atol=1e-6)
    else:
        assert d.normals is None


def test_ply_properties_colours_and_extra_elements():
    d = io.read_points(DATA / "plyfile_be_double.ply")  # big-endian, ushort/uint face lists
    assert d.attributes["colors"].shape == (42, 3) and d.attributes["colors"].dtype == np.uint8
    np.testing.assert_allclose(d.attributes["quality"], np.linspace(0, 1, 42), atol=1e-6)
    np.testing.assert_array_equal(d.attributes["scan_id"], np.arange(42) % 3)
    assert d.attributes["scan_id"].dtype.byteorder in "=|<"  # native order for numpy users
    a = io.read_points(DATA / "plyfile_ascii_rgb.ply")  # vertex_index list, alpha
    assert set(a.attributes) == {"colors", "alpha"}
    c = io.read_points(DATA / "plyfile_le_cloud.ply")
    np.testing.assert_array_equal(c.attributes["intensity"], np.arange(42))


def test_text_columns_by_rule():
    rgb = io.read_points(DATA / "xyzrgb.xyz")  # x y z r g b: colours, never normals
    assert rgb.normals is None and set(rgb.attributes) == {"col3", "col4", "col5"}
    assert rgb.attributes["col3"].max() > 1
    hdr = io.read_points(DATA / "header_names.csv")  # X,Y,Z,Nx,Ny,Nz header
    assert hdr.normals is not None and not hdr.attributes
    semi = io.read_points(DATA / "semicolon.csv")
    assert set(semi.attributes) == {"col3"}
    forced = io.read_points(DATA / "xyzrgb.xyz", columns="x y z red green blue")
    assert forced.normals is None and set(forced.attributes) == {"red", "green", "blue"}
    as_normals = io.read_points(DATA / "xyz_normals.xyz", columns=["x", "y", "z", "a", "b", "c"])
    assert as_normals.normals is None and set(as_normals.attributes) == {"a", "b", "c"}
    with pytest.raises(ValueError, match="columns"):
        io.read_points(DATA / "xyzrgb.xyz", columns="x y")
    with pytest.raises(ValueError, match="xyzrgb.xyz"):
        io.read_points(DATA / "xyzrgb.xyz", columns="x y z r g")


def test_obj_polygons_and_missing_material():
    d = io.read_mesh(DATA / "hand_polygons.obj")  # quads, a pentagon, mtllib that is absent
    assert d.points.shape == (9, 3)
    assert d.faces.shape == (5 * 2 + 3 + 1, 3) and _closed(d.faces)


def test_write_ply_is_read_by_plyfile(tmp_path):
    from plyfile import PlyData

    v = np.random.default_rng(0).normal(size=(5, 3))
    io.write_ply(tmp_path / "w.ply", v, np.array([[0, 1, 2]]), {"q": np.arange(5.0)})
    ply = PlyData.read(str(tmp_path / "w.ply"))
    np.testing.assert_allclose(ply["vertex"]["x"], v[:, 0], rtol=1e-6)
    np.testing.assert_array_equal(np.stack(ply["face"]["vertex_indices"]), [[0, 1, 2]])


@pytest.mark.parametrize(
    "name, text, words",
    [
        ("trunc.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 5\n"
         b"property float x\nproperty float y\nproperty float z\nend_header\n\x00\x00",
         "cannot read as PLY"),
        ("noxyz.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float a\n"
         b"end_header\n1\n", "no property 'x'"),
        ("bad.obj", b"v 0 0 0\nv 1 0 0\nf 1 2 7\n", "bad.obj"),
        ("bad.off", b"OFF\n3 1 0\n0 0 0\n1 0 0\n", "bad.off"),
        ("bad.stl", b"solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 0\n", "bad.stl"),
        ("bad.csv", b"x,y,z\n1,2,3\n4,5\n", "row 2 has 2 columns"),
        ("bad.npy", b"\x93NUMPY garbage", "bad.npy"),
        ("bin.xyz", bytes(range(256)) * 4, "bin.xyz"),
    ],
)
def test_unreadable_files_one_clear_line(tmp_path, capsys, name, text, words):
    path = tmp_path / name
    path.write_bytes(text)
    with pytest.raises(ValueError, match=words) as info:
        io.read_points(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)
    assert main(["jets", str(path), "-o", str(tmp_path / "o.npz"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and name in err and "Traceback" not in err
