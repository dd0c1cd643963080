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
    with pytest.raises(ValueError, match=r"w.npy: cannot read as NPY: expected an \(N, 3\)"):
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


def _sheet(nx=4, ny=3):
    a, b = np.meshgrid(np.linspace(0.0, 1.0, nx), np.linspace(0.0, 0.5, ny))
    v = np.stack([a.ravel(), b.ravel(), 0.1 * a.ravel() ** 2], 1)
    f = []
    for j in range(ny - 1):
        for i in range(nx - 1):
            k = j * nx + i
            f += [[k, k + 1, k + nx], [k + 1, k + nx + 1, k + nx]]
    uv = np.stack([a.ravel(), 2 * b.ravel()], 1)
    return v, np.array(f), uv


def test_textured_obj_round_trip_per_vertex(tmp_path, rng):
    v, f, uv = _sheet()
    tex = rng.integers(0, 256, (6, 8, 3)).astype(np.uint8)
    out = io.write_textured_obj(tmp_path / "m" / "sheet.obj", v, f, uvs=uv, texture=tex)
    assert (tmp_path / "m" / "sheet.mtl").is_file() and (tmp_path / "m" / "texture.png").is_file()
    m = io.read_textured_obj(out)
    np.testing.assert_allclose(m.vertices, v, rtol=1e-8)
    np.testing.assert_array_equal(m.faces, f)
    assert m.uvs.shape == (len(v), 2)
    np.testing.assert_allclose(m.uvs, uv, atol=1e-9)
    np.testing.assert_array_equal(np.rint(m.texture * 255).astype(np.uint8), tex)  # lossless
    assert m.texture.dtype == np.float32 and m.colors is None
    assert io.read_textured_obj(out, load_texture=False).texture is None


def test_textured_obj_seams_keep_one_vertex_and_corner_uvs(tmp_path):
    v, f, uv = _sheet()
    corner = uv[f].copy()
    corner[0, 1] = [0.9, 0.9]  # vertex f[0, 1] (in 3 faces) gets a second uv in face 0: a seam
    out = io.write_textured_obj(tmp_path / "s.obj", v, f, uvs=corner,
                                texture=np.zeros((2, 2, 3)))
    m = io.read_textured_obj(out)
    assert m.vertices.shape == v.shape and m.uvs.shape == (len(f), 3, 2)
    np.testing.assert_allclose(m.uvs, corner, atol=1e-9)


def test_vertex_colour_obj_and_polygons(tmp_path):
    v, f, _ = _sheet()
    col = np.linspace(0, 1, 3 * len(v)).reshape(-1, 3)
    m = io.read_textured_obj(io.write_textured_obj(tmp_path / "c.obj", v, f, colors=col))
    np.testing.assert_allclose(m.colors, col, atol=1e-6)
    assert m.uvs is None and m.texture is None
    # a quad with v//vn corners and negative (relative) indices is fan-triangulated
    (tmp_path / "q.obj").write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvn 0 0 1\n"
                                    "f -4//1 -3//1 -2//1 -1//1\n")
    q = io.read_textured_obj(tmp_path / "q.obj")
    np.testing.assert_array_equal(q.faces, [[0, 1, 2], [0, 2, 3]])


def test_textured_obj_written_by_trimesh(tmp_path, rng):
    """An OBJ from another writer (trimesh's exporter: its own vertex order, ``v/vt/vn``
    faces, an ``mtllib`` with a ``map_Kd`` image) reads back to the same textured surface."""
    from PIL import Image

    v, f, uv = _sheet(5, 4)
    img = Image.fromarray(rng.integers(0, 256, (8, 8, 3)).astype(np.uint8))
    visual = trimesh.visual.TextureVisuals(uv=uv, image=img)
    tm = trimesh.Trimesh(v, f, visual=visual, process=False)
    tm.export(tmp_path / "tm.obj")
    m = io.read_textured_obj(tmp_path / "tm.obj")
    assert m.texture is not None and m.texture.shape == (8, 8, 3)
    np.testing.assert_allclose(m.texture, np.asarray(img) / 255.0, atol=1e-6)
    # same triangles (as coordinate triples) and the same uv at every corner
    ours = {tuple(np.round(m.vertices[t].ravel(), 6)): m.uvs[i] if m.uvs.ndim == 3
            else m.uvs[t] for i, t in enumerate(m.faces)}
    assert len(ours) == len(f)
    for t in f:
        key = tuple(np.round(v[t].ravel(), 6))
        np.testing.assert_allclose(ours[key], uv[t], atol=1e-6)


@pytest.mark.parametrize("text, match", [
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", r"face indices must lie in \[1, 3\]"),
    ("v 0 0 0\nv 1 abc 0\n", r"x.obj:2: cannot parse"),
    ("v 0 0 0\n", r"expected a non-empty"),
    ("mtllib none.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", r"none.mtl: material library"),
    ("mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", r"faces lack 'vt' indices"),
    ("mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/5\n", r"refers to vt 5 of 1"),
])
def test_read_textured_obj_errors(tmp_path, text, match):
    (tmp_path / "m.mtl").write_text("newmtl a\nmap_Kd t.png\n")
    import cv2

    cv2.imwrite(str(tmp_path / "t.png"), np.zeros((2, 2, 3), np.uint8))
    (tmp_path / "x.obj").write_text(text)
    with pytest.raises(ValueError, match=match):
        io.read_textured_obj(tmp_path / "x.obj")
    with pytest.raises(FileNotFoundError):
        io.read_textured_obj(tmp_path / "none.obj")


@pytest.mark.parametrize("kwargs, exc, match", [
    (dict(vertices=np.ones((3, 2))), ValueError, "vertices"),
    (dict(faces=np.array([[0, 1, 7]])), ValueError, "faces: expected indices"),
    (dict(texture=np.zeros((2, 2, 3)), uvs=None), ValueError, "uvs: a texture needs"),
    (dict(texture=np.zeros((2, 2, 3)), uvs=np.zeros((2, 2))), ValueError, "uvs: expected"),
    (dict(texture=np.zeros((2, 2))), ValueError, "texture: expected an"),
    (dict(colors=np.zeros((2, 3))), ValueError, "colors: expected shape"),
    (dict(texture=np.full((2, 2, 3), "a")), TypeError, "texture"),
])
def test_write_textured_obj_validators(tmp_path, kwargs, exc, match):
    args = {"vertices": np.eye(3), "faces": np.array([[0, 1, 2]]), "uvs": np.zeros((3, 2)),
            **kwargs}
    with pytest.raises(exc, match=match):
        io.write_textured_obj(tmp_path / "w.obj", **args)
    assert not (tmp_path / "w.obj").exists()
