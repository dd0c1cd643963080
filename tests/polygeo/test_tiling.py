"""Tiled jets (polygeo.tiling) against one in-memory call: same neighbours, same numbers."""

import numpy as np
import pytest

import polygeo
from polygeo import tiling
from polygeo.status import Status
from polygeo.tiling import FIELDS, TileSettings, jets_tiled, parse_memory

K = 8


def _terrain(n, seed):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, 10.0, (n, 2))
    xy[:4] = [[0, 0], [0, 10], [10, 0], [10, 10]]  # bounding box exactly [0, 10]^2
    z = 0.4 * np.sin(0.8 * xy[:, 0]) * np.cos(0.6 * xy[:, 1]) + rng.normal(0, 0.01, n)
    return np.column_stack([xy, z])


def _cloud(case, seed=0):
    P = _terrain(3000, seed)
    rng = np.random.default_rng(seed + 1)
    edges = np.array([2.5, 5.0, 7.5])  # tile edges of the 4 x 4 grid used below
    if case == "borders":
        P[4:150, 0] = rng.choice(edges, 146)
        P[150:300, 1] = rng.choice(edges, 150)
        P[300:320, :2] = rng.choice(edges, (20, 2))  # on tile corners
    elif case == "empty":
        hole = (P[:, 0] > 2.5) & (P[:, 0] < 5) & (P[:, 1] > 2.5) & (P[:, 1] < 5)
        P = P[~hole]
    elif case == "sparse":
        inside = (P[:, 0] > 5) & (P[:, 0] < 7.5) & (P[:, 1] > 5) & (P[:, 1] < 7.5)
        drop = np.flatnonzero(inside)[3:]  # 3 points left: fewer than k
        P = np.delete(P, drop, axis=0)
    elif case == "duplicates":
        P[4:60, 0] = rng.choice(edges, 56)
        P = np.concatenate([P, P[4:60], P[100:130]])  # exact copies, on and off the borders
    elif case == "nan":
        P[10] = np.nan
        P[11, 2] = np.inf
    return P


def _in_memory(P, settings):
    up = tiling.up_reference(P)
    return polygeo.differential_quantities(P, normals=up, orient="input", progress=False,
                                           **settings.estimator_kwargs())


def _assert_same(res, ref):
    for name in FIELDS:
        a, b = np.asarray(getattr(ref, name)), np.asarray(res[name])
        assert a.shape == b.shape, name
        if name == "status":
            np.testing.assert_array_equal(a.astype(np.int64), b.astype(np.int64))
        else:
            np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-9, equal_nan=True,
                                       err_msg=name)


@pytest.mark.parametrize("case", ["borders", "empty", "sparse", "duplicates", "nan"])
def test_tiled_equals_in_memory(tmp_path, case):
    P = _cloud(case)
    st = TileSettings(k=K)
    res = jets_tiled(P, tmp_path / "run", st, tile_points=400, tiles=(4, 4), quiet=True)
    assert res.n_tiles == 16
    _assert_same(res, _in_memory(P, st))
    if case == "nan":
        assert res["status"][10] == Status.NONFINITE_INPUT and np.isnan(res["k1"][11])
    if case == "borders":  # the halos really crossed the borders
        log = polygeo.runs.read_jsonl(tmp_path / "run" / "tiles.jsonl")
        assert all(r["loaded"] > r["n"] for r in log if r.get("n"))


def _walls(seed=0):
    """Vertical walls (normals horizontal to rounding) at several angles, across tile borders."""
    rng = np.random.default_rng(seed)
    walls = []
    for deg in (0, 90, 180, 270, 45, 135):
        a = np.deg2rad(deg)
        centre = np.array([5 + 2.5 * np.cos(a), 5 + 2.5 * np.sin(a)])  # 0 deg: x = 7.5, a border
        along = np.array([-np.sin(a), np.cos(a)])
        t, z = rng.uniform(0.0, 3.0, 500), rng.uniform(0.0, 1.0, 500)
        walls.append(np.column_stack([centre + t[:, None] * along, z]))
    return np.concatenate(walls)


def test_up_orients_horizontal_normals_the_same_in_tiles_and_in_memory(tmp_path):
    P = _walls()
    st = TileSettings(k=K)
    ref = _in_memory(P, st)
    n = np.asarray(ref.normals)
    assert np.all(np.abs(n[:, 2]) < 1e-6)  # the walls' normals are horizontal
    # +z cannot decide (n_z is 0 or rounding noise): ties go to +x, then +y, the same for every
    # point of a wall, whatever else the call holds (plain +z left walls with mixed signs)
    assert np.all(n[:, 0] + np.sqrt(2.0) * n[:, 1] > 0.1)
    res = jets_tiled(P, tmp_path / "run", st, tile_points=300, tiles=(4, 4), quiet=True)
    _assert_same(res, ref)


def test_tiled_radius_equals_in_memory(tmp_path):
    P = _cloud("borders")
    st = TileSettings(k=40, radius=0.45)
    res = jets_tiled(P, tmp_path / "run", st, tile_points=400, tiles=(4, 4), quiet=True)
    _assert_same(res, _in_memory(P, st))


def test_halo_grows_until_neighbours_inside(tmp_path):
    # a dense strip and a sparse rest: the first guess of the halo is too small for the
    # sparse points next to a border, so it must grow
    rng = np.random.default_rng(3)
    dense = np.column_stack([rng.uniform(0, 10, 2500), rng.uniform(0, 0.5, 2500),
                             rng.normal(0, 0.01, 2500)])
    sparse = np.column_stack([rng.uniform(0, 10, 60), rng.uniform(0.5, 10, 60),
                              rng.normal(0, 0.01, 60)])
    P = np.concatenate([dense, sparse])
    st = TileSettings(k=K)
    res = jets_tiled(P, tmp_path / "run", st, tile_points=1500, tiles=(3, 3), quiet=True)
    _assert_same(res, _in_memory(P, st))
    log = polygeo.runs.read_jsonl(tmp_path / "run" / "tiles.jsonl")
    plan = tiling.plan_tiles(P, tile_points=1500, tiles=(3, 3))
    assert max(r["halo"] for r in log if "tile" in r) > tiling._initial_halo(plan, st)


@pytest.mark.parametrize("case", ["borders", "duplicates"])
def test_tiled_auto_k_equals_in_memory_whatever_the_chunks(tmp_path, case):
    # k="auto" pools each point's size choice with its neighbours': the pooled choices must
    # be the neighbours' own whatever chunk (in memory) or tile holds them
    P = _cloud(case)
    st = TileSettings(k="auto", k_candidates=(8, 16, 32, 64))
    up = np.zeros_like(P)
    up[:, 2] = 1.0
    kw = dict(normals=up, orient="input", progress=False, **st.estimator_kwargs())
    one = polygeo.differential_quantities(P, **kw)
    assert np.unique(one.n_neighbors[one.status == Status.OK]).size > 1  # sizes vary
    for batch in (97, 1000):  # many chunks, with borders between them
        chunked = polygeo.differential_quantities(P, batch_size=batch, **kw)
        for name in [*FIELDS, "n_neighbors"]:
            np.testing.assert_array_equal(np.asarray(getattr(chunked, name)),
                                          np.asarray(getattr(one, name)), err_msg=name)
    # the halo covers two pooling hops (errors pooled over neighbours whose bias rates pool
    # their own): a budget of 3 x 600 points per tile
    res = jets_tiled(P, tmp_path / "run", st, tile_points=600, tiles=(4, 4), quiet=True)
    _assert_same(res, one)


def test_plan_streams_in_chunks(tmp_path):
    # the plan read 101 rows at a time, its order bucketed into a file, equals the plan of
    # one pass and the independent definition: finite rows sorted by tile, ascending inside
    P = _cloud("nan")
    one = tiling.plan_tiles(P, tile_points=400, chunk=10**9)
    small = tiling.plan_tiles(P, tile_points=400, chunk=101, order_file=tmp_path / "o.npy")
    assert one.shape == small.shape and one.n_nonfinite == small.n_nonfinite == 2
    np.testing.assert_array_equal(small.offsets, one.offsets)
    np.testing.assert_array_equal(np.asarray(small.order), one.order)
    fin = np.flatnonzero(np.isfinite(P).all(1))
    nx, ny = one.shape
    ix = np.clip(np.floor((P[fin, 0] - one.lo[0]) / ((one.hi[0] - one.lo[0]) / nx)), 0, nx - 1)
    iy = np.clip(np.floor((P[fin, 1] - one.lo[1]) / ((one.hi[1] - one.lo[1]) / ny)), 0, ny - 1)
    key = (ix * ny + iy).astype(np.int64)
    np.testing.assert_array_equal(one.order, fin[np.argsort(key, kind="stable")])
    np.testing.assert_array_equal(np.diff(one.offsets), np.bincount(key, minlength=nx * ny))


def test_tiled_scattered_input_order(tmp_path):
    # a shuffled cloud: every tile's rows are spread over the whole input order
    P = _cloud("borders")[np.random.default_rng(7).permutation(3000)]
    st = TileSettings(k=K)
    res = jets_tiled(P, tmp_path / "run", st, tile_points=400, tiles=(4, 4), quiet=True)
    _assert_same(res, _in_memory(P, st))
    assert not list((tmp_path / "run").glob("tile_*.npy"))  # tile-order files removed


def test_resume_after_interruption_gives_same_result(tmp_path, monkeypatch):
    P = _cloud("borders")
    st = TileSettings(k=K)
    full = jets_tiled(P, tmp_path / "a", st, tile_points=400, tiles=(4, 4), quiet=True)
    real = tiling.tile_task
    calls = []

    def dying(*a, **kw):
        calls.append(1)
        if len(calls) == 6:
            raise KeyboardInterrupt  # the process is stopped during the sixth tile
        return real(*a, **kw)

    monkeypatch.setattr(tiling, "tile_task", dying)
    with pytest.raises(KeyboardInterrupt):
        jets_tiled(P, tmp_path / "b", st, tile_points=400, tiles=(4, 4), quiet=True)
    monkeypatch.setattr(tiling, "tile_task", real)
    again = jets_tiled(P, tmp_path / "b", st, tile_points=400, tiles=(4, 4), quiet=True)
    assert again.n_resumed == 5
    for name in FIELDS:
        np.testing.assert_array_equal(np.asarray(again[name]), np.asarray(full[name]))
    # other settings start afresh
    other = jets_tiled(P, tmp_path / "b", TileSettings(k=K + 2), tile_points=400,
                       tiles=(4, 4), quiet=True)
    assert other.n_resumed == 0


def test_memory_limit_picks_tiles_and_too_small_fails(tmp_path):
    P = _terrain(3000, 5)
    st = TileSettings(k=K)
    bpp = tiling.bytes_per_point(st)
    limit = int(tiling._FIXED_BYTES + 3 * 500 * bpp)  # room for ~500 own points per tile
    res = jets_tiled(P, tmp_path / "ok", st, memory_limit=limit, quiet=True)
    assert res.n_tiles >= 4
    _assert_same(res, _in_memory(P, st))
    with pytest.raises(ValueError, match="memory_limit"):
        jets_tiled(P, tmp_path / "small", st, memory_limit="100MB", quiet=True)


def test_parse_memory():
    assert parse_memory("4GB") == 4_000_000_000
    assert parse_memory("512MiB") == 512 * 2**20
    assert parse_memory(2e9) == 2_000_000_000
    for bad in ("4XB", "GB", "-1GB", 0):
        with pytest.raises(ValueError, match="memory_limit"):
            parse_memory(bad)
    with pytest.raises(TypeError, match="memory_limit"):
        parse_memory(True)


def test_bad_settings(tmp_path):
    P = _terrain(200, 1)
    with pytest.raises(ValueError, match="orient"):
        jets_tiled(P, tmp_path / "r", TileSettings(orient="propagate"), tile_points=100)
    with pytest.raises(ValueError, match="radius"):
        jets_tiled(P, tmp_path / "r", TileSettings(radius=-1.0), tile_points=100)


@pytest.mark.slow
def test_unreachable_scheduler(tmp_path):
    pytest.importorskip("distributed")
    with pytest.raises(ConnectionError, match="scheduler"):
        tiling.jets_dask(_terrain(300, 1), tmp_path / "r", dask="tcp://127.0.0.1:9",
                         tile_points=100)
    assert not (tmp_path / "r").exists()


@pytest.mark.slow
def test_local_cluster_equals_single_process(tmp_path):
    pytest.importorskip("distributed")
    P = _cloud("borders")
    st = TileSettings(k=K)
    one = jets_tiled(P, tmp_path / "one", st, tile_points=400, tiles=(4, 4), quiet=True)
    np.save(tmp_path / "P.npy", P)
    mm = np.load(tmp_path / "P.npy", mmap_mode="r")  # workers open the file themselves
    two = tiling.jets_dask(mm, tmp_path / "two", st, dask="local:2", tile_points=400,
                           tiles=(4, 4), quiet=True)
    for name in FIELDS:
        np.testing.assert_array_equal(np.asarray(two[name]), np.asarray(one[name]))
