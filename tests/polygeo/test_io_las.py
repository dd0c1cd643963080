"""LAS/LAZ reading and writing, memory-mapped point sources (polygeo.io_las)."""

import numpy as np
import pytest

from polygeo import io
from polygeo.cli import main
from polygeo.io_las import LAS_FIELDS, open_points, read_las, write_las

laspy = pytest.importorskip("laspy")


def _fixture(path, n=2000, seed=0):
    """A LAS/LAZ file written by laspy itself (not by our writer), with an extra dimension."""
    rng = np.random.default_rng(seed)
    h = laspy.LasHeader(point_format=3, version="1.2")
    h.scales = [0.001, 0.001, 0.001]
    h.offsets = [1000.0, 2000.0, 0.0]
    h.add_extra_dim(laspy.ExtraBytesParams(name="reflectance", type=np.float32))
    las = laspy.LasData(h)
    xy = rng.uniform(0, 20, (n, 2))
    las.x, las.y = 1000 + xy[:, 0], 2000 + xy[:, 1]
    las.z = 0.3 * np.sin(xy[:, 0]) + rng.normal(0, 0.005, n)
    las.intensity = rng.integers(0, 65535, n).astype(np.uint16)
    las.classification = rng.integers(0, 20, n).astype(np.uint8)
    las.return_number = rng.integers(1, 4, n).astype(np.uint8)
    las.gps_time = rng.uniform(0, 1e5, n)
    las.red = rng.integers(0, 65535, n).astype(np.uint16)
    las.reflectance = rng.normal(size=n).astype(np.float32)
    las.write(str(path))
    return las


def _fields(n, seed=1):
    rng = np.random.default_rng(seed)
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return {"normals": nrm, "k1": rng.normal(size=n), "k2": rng.normal(size=n),
            "mean_curvature": rng.normal(size=n), "gaussian_curvature": rng.normal(size=n),
            "d1": rng.normal(size=(n, 3)), "d2": rng.normal(size=(n, 3)),
            "status": rng.integers(0, 7, n)}


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_round_trip_keeps_every_dimension(tmp_path, suffix):
    src = tmp_path / f"scan{suffix}"
    _fixture(src)
    fields = _fields(2000)
    out = tmp_path / f"out{suffix}"
    write_las(out, src, fields, chunk_size=700)  # several chunks
    a, b = laspy.read(str(src)), laspy.read(str(out))
    assert b.header.are_points_compressed == (suffix == ".laz")
    np.testing.assert_array_equal(b.header.scales, a.header.scales)
    np.testing.assert_array_equal(b.header.offsets, a.header.offsets)
    for dim in a.point_format.dimension_names:
        np.testing.assert_array_equal(np.asarray(b[dim]), np.asarray(a[dim]), err_msg=dim)
    for name, (src_name, col, _typ) in LAS_FIELDS.items():
        want = fields[src_name] if col is None else fields[src_name][:, col]
        np.testing.assert_allclose(np.asarray(b[name], dtype=np.float64), want, rtol=1e-6,
                                   atol=1e-7, err_msg=name)
    back = read_las(src)
    np.testing.assert_allclose(back.points, np.column_stack([a.x, a.y, a.z]), rtol=0, atol=0)
    assert {"intensity", "classification", "gps_time", "red", "reflectance"} <= set(
        back.attributes)
    np.testing.assert_array_equal(back.attributes["reflectance"], np.asarray(a.reflectance))


def test_truncated_laz_clear_error_and_no_output(tmp_path, capsys):
    src = tmp_path / "scan.laz"
    _fixture(src, n=5000)
    data = src.read_bytes()
    bad = tmp_path / "cut.laz"
    bad.write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(ValueError, match="cut.laz"):
        read_las(bad)
    out = tmp_path / "res" / "out.laz"
    with pytest.raises(ValueError, match="cut.laz"):
        write_las(out, bad, _fields(5000))
    assert not out.exists() and not any((tmp_path / "res").glob("*"))
    for extra in ([], ["--tile-points", "500"]):
        assert main(["jets", str(bad), "-o", str(out), "--quiet", "--k", "8", *extra]) != 0
        assert "truncated" in capsys.readouterr().err
        assert not out.exists()


def test_write_las_bad_input(tmp_path):
    src = tmp_path / "scan.las"
    _fixture(src, n=100)
    with pytest.raises(ValueError, match="path"):
        write_las(tmp_path / "out.txt", src, _fields(100))
    with pytest.raises(ValueError, match="rows"):
        write_las(tmp_path / "out.las", src, _fields(99))
    with pytest.raises(ValueError, match="unknown"):
        write_las(tmp_path / "out.las", src, {"curvedness": np.zeros(100)})
    with pytest.raises(FileNotFoundError):
        write_las(tmp_path / "out.las", tmp_path / "missing.las", _fields(100))
    not_las = tmp_path / "x.las"
    not_las.write_bytes(b"hello world" * 100)
    with pytest.raises(ValueError, match="x.las"):
        read_las(not_las)


def test_open_points_memory_maps(tmp_path):
    rng = np.random.default_rng(0)
    P = rng.normal(size=(500, 3))
    np.save(tmp_path / "a.npy", P)
    m = open_points(tmp_path / "a.npy")
    assert isinstance(m, np.memmap)
    np.testing.assert_array_equal(m[[3, 7]], P[[3, 7]])
    np.save(tmp_path / "b.npy", np.column_stack([P, P]).astype(np.float32))
    np.testing.assert_array_equal(open_points(tmp_path / "b.npy")[:], P.astype(np.float32))
    io.write_ply(tmp_path / "c.ply", P, attributes={"q": np.arange(500.0)}, precision="double")
    src = open_points(tmp_path / "c.ply")
    assert not isinstance(src, np.ndarray)
    np.testing.assert_array_equal(src[np.array([0, 499])], P[[0, 499]])
    las = _fixture(tmp_path / "d.las", n=300)
    for name in ("d.las", "d.laz"):
        if name == "d.laz":
            las.write(str(tmp_path / name))
        pts = open_points(tmp_path / name, cache_dir=tmp_path / "cache")
        np.testing.assert_allclose(pts[:], np.column_stack([las.x, las.y, las.z]), rtol=0,
                                   atol=1e-9)
    with pytest.raises(ValueError, match="shape"):
        np.save(tmp_path / "e.npy", np.zeros((4, 2)))
        open_points(tmp_path / "e.npy")


def test_cli_laz_in_memory_tiled_and_batch(tmp_path):
    scans = tmp_path / "scans"
    scans.mkdir()
    _fixture(scans / "a.laz", n=1500, seed=1)
    _fixture(scans / "b.laz", n=1200, seed=2)
    mem = tmp_path / "a_mem.laz"
    assert main(["jets", str(scans / "a.laz"), "-o", str(mem), "--k", "8", "--quiet"]) == 0
    til = tmp_path / "a_tiled.laz"
    assert main(["jets", str(scans / "a.laz"), "-o", str(til), "--k", "8", "--quiet",
                 "--tile-points", "300"]) == 0
    a, b = laspy.read(str(mem)), laspy.read(str(til))
    for name in LAS_FIELDS:
        np.testing.assert_allclose(np.asarray(b[name], float), np.asarray(a[name], float),
                                   rtol=1e-6, atol=1e-6, err_msg=name)
    assert (np.asarray(a["normal_z"]) > 0).mean() > 0.99  # oriented up
    assert not (tmp_path / "a_tiled.laz.parts").exists()
    out = tmp_path / "out"
    assert main(["jets", str(scans / "*.laz"), "-o", str(out), "--k", "8", "--quiet",
                 "--tile-points", "400"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["a_jets.laz", "b_jets.laz"]
    c = laspy.read(str(out / "a_jets.laz"))
    np.testing.assert_array_equal(np.asarray(c["k1"]), np.asarray(b["k1"]))
