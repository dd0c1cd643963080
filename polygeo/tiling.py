"""Jets of clouds larger than memory: spatial tiles with halos, resumable, optionally on Dask.

A job beside :mod:`polygeo.estimate` (it calls :func:`polygeo.differential_quantities` on each
tile). The cloud is cut into a grid of tiles in the ``(x, y)`` plane (LiDAR scans are wide and
flat; the tiles are columns, so any cloud works). Each tile is processed with a *halo*: the
points of the neighbouring tiles close enough to belong to the neighbourhood of one of its
own points. The halo is exact, not a guess:

- ``radius``: the halo is the radius (every neighbour is within it);
- ``k`` nearest: the k nearest neighbours of each own point are found among the loaded points;
  where the k-th distance reaches the edge of the loaded box (a closer point could lie
  outside) the halo grows to that distance and the tile is loaded again, until every own
  point's k neighbours are provably inside;
- ``k="auto"``: the same with the largest candidate size, for the own points, their
  ``AUTO_K_SMOOTH`` nearest neighbours (whose errors are pooled with theirs) and those
  neighbours' own ``AUTO_K_SMOOTH`` nearest (whose bias rates those pool).

So each point sees the same neighbours as in one in-memory call and gets the same numbers (to
float rounding: the neighbours' summation order may differ). Orientation must then be local
too: normals are oriented towards a reference direction (``orient="up"``: ``+z``, the usual
choice for aerial scans), towards input normals (``"input"``), or left as fitted
(``"none"``); the global propagation of the in-memory default is not available here.

Each finished tile's rows are written, in tile order, into ``tile_<field>.npy`` files of a
run folder with a JSONL log of finished tiles (:class:`polygeo.runs.JsonlLog`): an interrupted
run started again with the same settings continues at the next unfinished tile. A last pass
writes ``<field>.npy`` in the input's point order (so scattered input orders cost one
streamed pass, not a rewrite of every result page per tile). Everything that spans the whole
cloud is streamed (the plan in chunked passes, its order bucketed into a file; rows read from
memory maps in blocks whose pages are released): peak memory is bounded by the tile size,
chosen from ``memory_limit`` and a measured bytes-per-point model (:func:`bytes_per_point`).
"""

from __future__ import annotations

import math
import os
import re
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ._tiles import (
    NpyRows,
    TilePlan,
    create_tile_files,
    drop_pages,
    plan_tiles,
    read_rows,
    reorder,
    store_tile,
    tile_keys,
)
from .checks import check_choice, check_int, check_positive
from .runs import JsonlLog, atomic_write_json, fingerprint, progress, read_jsonl

__all__ = [
    "TileSettings",
    "TilePlan",
    "TiledResult",
    "FIELDS",
    "parse_memory",
    "bytes_per_point",
    "plan_tiles",
    "jets_tiled",
    "jets_dask",
    "tile_task",
    "dask_client",
    "up_reference",
]

#: Output fields: name -> (columns or None, dtype).
FIELDS: dict[str, tuple[int | None, str]] = {
    "normals": (3, "f8"),
    "k1": (None, "f8"),
    "k2": (None, "f8"),
    "mean_curvature": (None, "f8"),
    "gaussian_curvature": (None, "f8"),
    "d1": (3, "f8"),
    "d2": (3, "f8"),
    "status": (None, "i1"),
}

# Measured peak resident memory per processed point of one estimator call (bytes), order 2,
# uniform weights, this machine: BASE + PER_NEIGHBOR * (k + 1). See bytes_per_point.
_BPP_BASE = 600.0
_BPP_PER_NEIGHBOR = 30.0
# Python, NumPy, torch and numba loaded: resident memory not counted in the per-point model.
_FIXED_BYTES = 600 * 2**20


@dataclass(frozen=True)
class TileSettings:
    """What each tile computes (passed to :func:`polygeo.differential_quantities`).

    Attributes
    ----------
    k : int or "auto"
        Nearest neighbours besides the point (see ``differential_quantities``).
    radius : float or None
        Neighbourhood radius (length unit of the input) instead of k nearest.
    order : int or "auto"
        Jet order.
    weights : None or "gaussian"
        Least-squares weights.
    interpolate : bool
        Jets through their point.
    orient : {"up", "none"}
        Normals towards ``+z``, or as fitted.
    k_candidates : tuple of int
        Sizes tried by ``k="auto"``.

    With ``k="auto"`` and ``order="auto"`` the tiles run without the held-out check of the
    normals (``normal_check=False``): it decides once per cloud, and a verdict per tile could
    differ from tile to tile. A tiled run equals an in-memory call with ``normal_check=False``.
    """

    k: int | str = 20
    radius: float | None = None
    order: int | str = 2
    weights: str | None = None
    interpolate: bool = False
    orient: str = "up"
    k_candidates: tuple[int, ...] = (12, 24, 48, 96, 192, 384)

    def estimator_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of ``differential_quantities`` (orientation excepted)."""
        kw = dict(k=self.k, radius=self.radius, order=self.order, weights=self.weights,
                  interpolate=self.interpolate)
        if self.k == "auto":
            kw["k_candidates"] = tuple(self.k_candidates)
        if self.k == "auto" and self.order == "auto":
            kw["normal_check"] = False  # one verdict per cloud, never per tile
        return kw

    def neighbours(self) -> int:
        """Largest neighbour count a point's result depends on (``k`` or the largest size)."""
        return int(max(self.k_candidates)) if self.k == "auto" else int(self.k)


def _validate(settings: TileSettings) -> None:
    if settings.k != "auto":
        check_int(settings.k, "k", low=1)
    if settings.radius is not None:
        check_positive(settings.radius, "radius")
    check_choice(settings.orient, "orient", ("up", "none"))


#: Tilt of the ``orient="up"`` reference: ``+z`` decides, and a normal exactly horizontal
#: (``n_z == 0``, e.g. a wall of a synthetic or CAD-derived cloud) is decided by ``+x`` and
#: then ``+y`` instead of by propagation over whichever points one call holds, so that a tiled
#: run and an in-memory run orient it the same way. Irrational ratio: no axis-aligned normal is
#: orthogonal to the tilted reference.
_UP_TILT = (1e-9, 1e-9 * math.sqrt(2.0))


def up_reference(points: Any) -> np.ndarray:
    """Per-point reference direction of ``orient="up"`` (``+z``, ties to ``+x``, then ``+y``).

    Parameters
    ----------
    points : (N, 3) array_like
        The cloud (only its length and dtype are used).

    Returns
    -------
    (N, 3) float64 ndarray
        ``(1e-9, 1e-9 * sqrt(2), 1)`` on every row: a normal is flipped towards ``+z``; one with
        ``|n_z|`` below ~1e-9 is flipped towards ``+x`` (then ``+y``), the same whatever other
        points the call holds. Used by tiled runs and by ``polygeo jets --orient up``.
    """
    n = len(points)
    ref = np.empty((n, 3), dtype=np.float64)
    ref[:, 0], ref[:, 1], ref[:, 2] = _UP_TILT[0], _UP_TILT[1], 1.0
    return ref


def parse_memory(value: Any) -> int:
    """Bytes of a memory size such as ``"4GB"``, ``"512MiB"``, ``"2e9"`` or ``4_000_000_000``.

    Units: B, kB/KB, MB, GB, TB (powers of 1000) and KiB, MiB, GiB, TiB (powers of 1024).

    Raises
    ------
    ValueError
        Unparsable text or a non-positive size.
    TypeError
        Neither a number nor a string.
    """
    if isinstance(value, bool) or not isinstance(value, int | float | str):
        raise TypeError(f"memory_limit: expected a number of bytes or a string like '4GB', "
                        f"got {type(value).__name__}")
    if isinstance(value, str):
        m = re.fullmatch(r"\s*([0-9.eE+]+)\s*([kKMGT]?i?B?)\s*", value)
        units = {"": 1, "B": 1, "KB": 1e3, "KIB": 2**10, "MB": 1e6, "MIB": 2**20, "GB": 1e9,
                 "GIB": 2**30, "TB": 1e12, "TIB": 2**40, "K": 1e3, "M": 1e6, "G": 1e9,
                 "T": 1e12}
        unit = m.group(2).upper() if m else None
        if not m or unit not in units:
            raise ValueError(f"memory_limit: expected a size like '4GB' or '512MiB', "
                             f"got {value!r}")
        try:
            value = float(m.group(1)) * units[unit]
        except ValueError as exc:
            raise ValueError(f"memory_limit: expected a size like '4GB', got {value!r}") from exc
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"memory_limit: expected a positive size, got {value!r}")
    return int(value)


def bytes_per_point(settings: TileSettings) -> float:
    """Modelled peak memory of one estimator call per loaded point (bytes).

    ``600 + 30 * (k + 1)`` (``k``: the largest neighbour count). Measured growth of peak
    RSS of one ``differential_quantities`` call on random 2.5D terrains (order 2, one
    thread): 594 bytes/point at k = 20 and 999 at k = 60 for 4e5 points (720 and 1670
    for 2e5), i.e. about 380 + 10 (k + 1); the model about doubles that for the tile's own
    copies (loaded coordinates, the halo check's k-NN lists, the results). Higher orders
    cost more: the model is scaled by the number of jet coefficients over 6.
    """
    k = settings.neighbours()
    if settings.radius is not None and settings.k == "auto":
        k = max(k, 64)
    order = 4 if settings.order == "auto" else int(settings.order)
    scale = max(1.0, (order + 1) * (order + 2) / 12.0)
    return (_BPP_BASE + _BPP_PER_NEIGHBOR * (k + 1)) * scale


def _load_region(points: Any, plan: TilePlan, t: int, h: float) -> tuple[np.ndarray, ...]:
    """Own and halo points of tile ``t`` for halo width ``h``: (index, xyz, own mask, box)."""
    x0, x1, y0, y1 = plan.tile_box(t)
    wx, wy = plan._widths()
    nx, ny = plan.shape
    ix, iy = divmod(int(t), int(ny))
    rx, ry = int(math.ceil(h / wx)), int(math.ceil(h / wy))
    parts = []
    for jx in range(max(0, ix - rx), min(nx, ix + rx + 1)):
        for jy in range(max(0, iy - ry), min(ny, iy + ry + 1)):
            parts.append(plan.members(jx * ny + jy))
    idx = np.sort(np.concatenate(parts)) if parts else np.zeros(0, dtype=np.int64)
    drop_pages(plan.order)
    xyz = read_rows(points, idx)
    box = (x0 - h, x1 + h, y0 - h, y1 + h)
    keep = ((xyz[:, 0] >= box[0]) & (xyz[:, 0] <= box[1]) & (xyz[:, 1] >= box[2])
            & (xyz[:, 1] <= box[3]))
    idx, xyz = idx[keep], xyz[keep]
    kx = tile_keys(xyz[:, :2], plan.lo, plan.hi, plan.shape)
    return idx, xyz, kx == t, box


def _margins(xyz: np.ndarray, box, plan: TilePlan) -> np.ndarray:
    """Distance in (x, y) from each point to the nearest edge of ``box`` with points beyond."""
    m = np.full(len(xyz), np.inf)
    if box[0] > plan.lo[0]:
        m = np.minimum(m, xyz[:, 0] - box[0])
    if box[1] < plan.hi[0]:
        m = np.minimum(m, box[1] - xyz[:, 0])
    if box[2] > plan.lo[1]:
        m = np.minimum(m, xyz[:, 1] - box[2])
    if box[3] < plan.hi[1]:
        m = np.minimum(m, box[3] - xyz[:, 1])
    return m


def _covers(box, plan: TilePlan) -> bool:
    return (box[0] <= plan.lo[0] and box[1] >= plan.hi[0] and box[2] <= plan.lo[1]
            and box[3] >= plan.hi[1])


def _halo_shortfall(xyz: np.ndarray, own: np.ndarray, box, plan: TilePlan,
                    settings: TileSettings) -> float:
    """0 when every own point's neighbourhood is inside ``box``, else how much wider it must be."""
    from .neighbors import knn

    if settings.radius is not None and settings.k != "auto":
        return 0.0  # the halo is the radius (k only caps the count inside it)
    if not own.any() or _covers(box, plan):
        return 0.0  # nothing to do, or every point of the cloud is loaded
    n_fin = len(xyz)
    kq = settings.neighbours() + 1
    queries = np.flatnonzero(own)
    if settings.k == "auto":
        from .estimate import AUTO_K_SMOOTH

        # two hops: a point's choice pools its neighbours' errors, whose bias rates pool
        # their own neighbours'
        for _ in range(2):
            first = knn(xyz, min(AUTO_K_SMOOTH + 1, n_fin), queries=xyz[queries]).index
            queries = np.unique(np.concatenate([queries, first[first >= 0].ravel()]))
    dist = knn(xyz, kq, queries=xyz[queries]).distance[:, -1]
    margin = _margins(xyz[queries], box, plan)
    short = dist - margin
    bad = ~(short < 0)
    if not bad.any():
        return 0.0
    s = short[bad]
    return float(np.max(np.where(np.isfinite(s), s, np.inf)))


def tile_task(points: Any, plan: TilePlan, t: int, settings: TileSettings,
              h0: float) -> dict[str, np.ndarray]:
    """Quantities of the points tile ``t`` owns (the unit of work, in-process or on Dask).

    Returns a dict with ``index`` (global indices, ascending), the :data:`FIELDS` rows and
    ``halo`` (the final halo width, length unit) and ``loaded`` (points loaded).

    Raises
    ------
    MemoryError
        The tile with the halo its neighbourhoods need holds more than ``plan.budget`` points.
    """
    from .estimate import differential_quantities

    h = float(h0)
    diag = math.hypot(plan.hi[0] - plan.lo[0], plan.hi[1] - plan.lo[1])
    while True:
        idx, xyz, own, box = _load_region(points, plan, t, h)
        if len(idx) > plan.budget:
            raise MemoryError(
                f"memory_limit: tile {t} needs {len(idx)} points with its halo (width {h:.4g}) "
                f"but the limit allows {plan.budget}; raise the memory limit or lower k")
        short = _halo_shortfall(xyz, own, box, plan, settings)
        if short == 0.0:
            break
        h_all = max(plan.hi[0] - plan.lo[0], plan.hi[1] - plan.lo[1]) * (1 + 1e-9) + 1e-300
        h = 2 * h if not math.isfinite(short) else h + short * 1.01 + 1e-12 * diag
        h = min(h, h_all)
    out = {"index": idx[own], "halo": np.float64(h), "loaded": np.int64(len(idx))}
    if not own.any():
        for name, (cols, typ) in FIELDS.items():
            out[name] = np.zeros((0, cols) if cols else (0,), dtype=typ)
        return out
    ref = up_reference(xyz) if settings.orient == "up" else None
    dq = differential_quantities(
        xyz, normals=ref, orient="input" if ref is not None else "none", progress=False,
        **settings.estimator_kwargs(),
    )
    for name, (_cols, typ) in FIELDS.items():
        out[name] = np.asarray(getattr(dq, name))[own].astype(typ)
    return out


@dataclass(frozen=True)
class TiledResult:
    """Memory-mapped results of a tiled run (input point order).

    Attributes
    ----------
    folder : Path
        The run folder (``<name>.npy`` per field, ``plan.json``, ``tiles.jsonl``).
    fields : dict of str to numpy.memmap
        :data:`FIELDS`, read-only maps.
    n_tiles, n_resumed : int
        Tiles in the plan, and tiles found finished by an earlier run.
    """

    folder: Path
    fields: dict[str, np.ndarray]
    n_tiles: int
    n_resumed: int

    def __getitem__(self, name: str) -> np.ndarray:
        return self.fields[name]


def _setup_run(points, folder: Path, settings: TileSettings, memory_limit, tile_points,
               source_id: str, tiles=None):
    _validate(settings)
    n = int(points.shape[0])
    bpp = bytes_per_point(settings)
    if tile_points is None:
        limit = parse_memory(memory_limit if memory_limit is not None else "4GB")
        budget = int((limit - _FIXED_BYTES) // bpp)
        need = 4 * (settings.neighbours() + 1)
        if budget < need:
            raise ValueError(
                f"memory_limit: {limit} bytes leave room for {max(budget, 0)} points per tile "
                f"(model: {_FIXED_BYTES / 2**20:.0f} MiB fixed + {bpp:.0f} bytes per point), "
                f"fewer than one tile's halo needs ({need} points for k={settings.k}); "
                f"expected at least {int(_FIXED_BYTES + need * bpp)} bytes")
        tile_points = max(1, budget // 3)
    else:
        tile_points = check_int(tile_points, "tile_points", low=1)
        budget = max(3 * tile_points, 4 * (settings.neighbours() + 1))
    key = fingerprint({"settings": asdict(settings), "source": source_id, "n": n,
                       "tile_points": int(tile_points), "budget": int(budget),
                       "tiles": None if tiles is None else list(tiles)})
    folder.mkdir(parents=True, exist_ok=True)
    meta_path = folder / "plan.json"
    resumed = False
    if meta_path.exists():
        import json

        meta = json.loads(meta_path.read_text())
        resumed = meta.get("fingerprint") == key and (folder / "plan.npz").exists()
    if resumed:
        z = np.load(folder / "plan.npz")
        plan = TilePlan(tuple(meta["lo"]), tuple(meta["hi"]), tuple(meta["shape"]),
                        z["offsets"], np.load(folder / "order.npy", mmap_mode="r"),
                        n, int(meta["n_nonfinite"]), int(budget))
        done = {int(r["tile"]) for r in read_jsonl(folder / "tiles.jsonl") if "tile" in r}
        return plan, done, {f: None for f in FIELDS}
    for stale in ("tiles.jsonl", "plan.json", *(f"{f}.npy" for f in FIELDS)):
        (folder / stale).unlink(missing_ok=True)
    # the order (8 bytes per point) bucketed straight into a file, read from there
    plan = plan_tiles(points, tile_points=tile_points, budget=budget, tiles=tiles,
                      order_file=folder / "order.npy")
    np.savez(folder / "plan.npz", offsets=plan.offsets)
    create_tile_files(folder, FIELDS, int(plan.offsets[-1]))
    maps = {f: None for f in FIELDS}
    atomic_write_json(meta_path, {"fingerprint": key, "lo": plan.lo, "hi": plan.hi,
                                  "shape": plan.shape, "n_nonfinite": plan.n_nonfinite,
                                  "n_points": n, "settings": asdict(settings),
                                  "tile_points": int(tile_points), "budget": int(budget)})
    return plan, set(), maps


def _initial_halo(plan: TilePlan, settings: TileSettings) -> float:
    if settings.radius is not None and settings.k != "auto":
        return float(settings.radius) * (1 + 1e-9)
    wx, wy = plan._widths()
    area = max(wx * wy * plan.n_tiles, 1e-300)
    density = max(plan.n_points - plan.n_nonfinite, 1) / area
    # the radius of a disc holding the neighbours at the mean density, doubled
    return 2.0 * math.sqrt((settings.neighbours() + 1) / (math.pi * density))


def _store(folder: Path, plan: TilePlan, t: int, res) -> None:
    """Write tile ``t``'s rows into the tile-order result files."""
    start, stop = int(plan.offsets[t]), int(plan.offsets[t + 1])
    if res["index"].size != stop - start:
        raise RuntimeError(f"tile {t}: {res['index'].size} points computed, the plan "
                           f"gives it {stop - start}")
    store_tile(folder, FIELDS, start, res)


class _HaloHint:
    """Starting halo of the next tile: the largest final halo of the last 8 tiles.

    Neighbouring tiles need about the same halo, so starting there saves most reloads; the
    halo is still checked and grown per tile, so the hint changes no result.
    """

    def __init__(self, h0: float, records: list[dict]):
        self.h0 = float(h0)
        self.recent = [float(r["halo"]) for r in records if "halo" in r][-8:]

    def add(self, h: float) -> None:
        self.recent = [*self.recent[-7:], float(h)]

    def __float__(self) -> float:
        return max([self.h0, *self.recent])


def _timing(stage: str, t0: float, c0: float) -> dict:
    return {"stage": stage, "seconds": time.perf_counter() - t0,
            "cpu_seconds": time.process_time() - c0}


def _finish(folder, maps, plan, n_resumed) -> TiledResult:
    """Input-order result files from the tile-order ones (once), as read-only maps."""
    if all((folder / f"tile_{f}.npy").exists() for f in FIELDS):
        t0, c0 = time.perf_counter(), time.process_time()
        reorder(folder, FIELDS, plan)
        with JsonlLog(folder / "tiles.jsonl") as log:
            log.append(_timing("reorder", t0, c0))
    for f in FIELDS:  # left by a run stopped while deleting them
        (folder / f"tile_{f}.npy").unlink(missing_ok=True)
    fields = {f: np.load(folder / f"{f}.npy", mmap_mode="r") for f in FIELDS}
    return TiledResult(folder, fields, plan.n_tiles, n_resumed)


def _source_id(points: Any, source: Any) -> str:
    if source is not None:
        p = Path(os.fspath(source)).resolve()
        st = p.stat()
        return f"{p}:{st.st_size}:{st.st_mtime_ns}"
    sample = np.asarray(points[: min(len(points), 4096)], dtype=np.float64)
    return f"array:{points.shape}:{fingerprint(sample.round(12).tolist())}"


def jets_tiled(
    points: Any,
    folder: str | os.PathLike,
    settings: TileSettings | None = None,
    *,
    memory_limit: Any = "4GB",
    tile_points: int | None = None,
    source: str | os.PathLike | None = None,
    tiles: tuple[int, int] | None = None,
    quiet: bool | None = False,
) -> TiledResult:
    """Per-point jets of a large cloud, tile by tile, resumable (single process).

    Parameters
    ----------
    points : (N, 3) array-like
        Coordinates (length unit L): a NumPy array, a memory map or
        :func:`polygeo.io_las.open_points`. Non-finite rows get status ``NONFINITE_INPUT``
        and NaN values, as in memory.
    folder : str or os.PathLike
        Run folder: results ``<field>.npy`` (memory maps, input order), ``plan.json``,
        ``tiles.jsonl`` (finished tiles). Started again with the same settings and input it
        resumes; other settings start afresh.
    settings : TileSettings, optional
        Neighbourhood, order, orientation (default ``TileSettings()``: k = 20, order 2, up).
    memory_limit : str or int
        Peak memory to stay under (``"4GB"``, bytes); picks the tile size through
        :func:`bytes_per_point`. Ignored when ``tile_points`` is given.
    tile_points : int, optional
        Own points per tile (overrides the memory model; the halo budget is three times it).
    source : str or os.PathLike, optional
        The input file, to recognise it on resume (default: a hash of the first rows).
    tiles : (int, int), optional
        A fixed grid of tiles along x and y (default: from the tile size).
    quiet : bool or None
        Progress bar over tiles (see :func:`polygeo.runs.progress`).

    Returns
    -------
    TiledResult
        Read-only memory maps of :data:`FIELDS`.

    Raises
    ------
    ValueError
        Bad settings, or a memory limit too small for one tile with its halo.
    MemoryError
        A tile whose halo (dense spot, large k) exceeds the budget.
    """
    settings = settings or TileSettings()
    folder = Path(os.fspath(folder))
    t0, c0 = time.perf_counter(), time.process_time()
    plan, done, maps = _setup_run(points, folder, settings, memory_limit, tile_points,
                                  _source_id(points, source), tiles)
    hint = _HaloHint(_initial_halo(plan, settings), read_jsonl(folder / "tiles.jsonl"))
    todo = [t for t in range(plan.n_tiles) if t not in done]
    fresh = not (folder / "tiles.jsonl").exists()
    with JsonlLog(folder / "tiles.jsonl") as log:
        if fresh:
            log.append(_timing("plan", t0, c0))
        bar = progress(total=plan.n_tiles, desc="tiles", quiet=quiet, initial=len(done))
        try:
            for t in todo:
                t0, c0 = time.perf_counter(), time.process_time()
                res = tile_task(points, plan, t, settings, float(hint))
                _store(folder, plan, t, res)
                hint.add(res["halo"])
                log.append({"tile": t, "n": int(res["index"].size),
                            "halo": float(res["halo"]), "loaded": int(res["loaded"]),
                            "seconds": time.perf_counter() - t0,
                            "cpu_seconds": time.process_time() - c0})
                bar.update(1)
        finally:
            bar.close()
    return _finish(folder, maps, plan, len(done))


def dask_client(dask: Any):
    """A ``distributed.Client`` from ``"local:N"``, an address or a Client.

    Returns
    -------
    (Client, bool)
        The client and whether the caller owns it (must close it and its cluster).

    Raises
    ------
    ConnectionError
        No scheduler answers at the address (within 5 s).
    TypeError
        Neither a string nor a Client.
    """
    try:
        from distributed import Client, LocalCluster
    except ImportError as exc:  # pragma: no cover - optional extra
        raise ImportError("--dask needs dask.distributed: pip install 'polygeo[dask]'") from exc
    if isinstance(dask, Client):
        return dask, False
    if not isinstance(dask, str):
        raise TypeError(f"dask: expected 'local:N', 'tcp://host:port' or a Client, "
                        f"got {type(dask).__name__}")
    m = re.fullmatch(r"local(?::(\d+))?", dask)
    if m:
        nw = int(m.group(1) or 2)
        cluster = LocalCluster(n_workers=nw, threads_per_worker=1, processes=True,
                               dashboard_address=None)
        return Client(cluster), True
    try:
        return Client(dask, timeout="5s"), True
    except (OSError, TimeoutError) as exc:
        raise ConnectionError(f"dask: could not reach the scheduler at {dask!r} "
                              f"({type(exc).__name__}: {exc})") from exc


def _remote_tile(source_path, points, plan, t, settings, h0):
    if points is None:
        from .io_las import open_points

        points = open_points(source_path)
    return tile_task(points, plan, t, settings, h0)


def jets_dask(
    points: Any,
    folder: str | os.PathLike,
    settings: TileSettings | None = None,
    *,
    dask: Any = "local:2",
    memory_limit: Any = "4GB",
    tile_points: int | None = None,
    source: str | os.PathLike | None = None,
    tiles: tuple[int, int] | None = None,
    quiet: bool | None = False,
) -> TiledResult:
    """:func:`jets_tiled` with the tiles run as Dask tasks; same files, same numbers.

    The client plans the tiles and writes each finished tile into the run folder (so the
    workers need no shared output folder); workers read their tile's points from the file
    behind ``points`` when it is a memory map (the decompressed LAZ cache of
    :func:`polygeo.io_las.open_points`), else from ``source`` (paths they can open: a shared
    file system), else they receive the array.
    At most two tiles per worker are in flight, so client memory stays bounded.

    Parameters
    ----------
    dask : str or distributed.Client
        ``"local:N"`` (a LocalCluster of N single-thread worker processes),
        ``"tcp://host:port"`` (an existing scheduler) or a Client.
    points, folder, settings, memory_limit, tile_points, source, tiles, quiet
        As :func:`jets_tiled` (``memory_limit`` is per worker).

    Returns
    -------
    TiledResult

    Raises
    ------
    ConnectionError
        The scheduler cannot be reached (no output is written under the final name).
    """
    from distributed import as_completed

    settings = settings or TileSettings()
    folder = Path(os.fspath(folder))
    client, own_client = dask_client(dask)
    try:
        plan, done, maps = _setup_run(points, folder, settings, memory_limit, tile_points,
                                      _source_id(points, source), tiles)
        hint = _HaloHint(_initial_halo(plan, settings), read_jsonl(folder / "tiles.jsonl"))
        todo = [t for t in range(plan.n_tiles) if t not in done]
        n_workers = max(1, len(client.scheduler_info().get("workers", {})))
        # workers open a file themselves: the memory-mapped .npy behind ``points`` (e.g. the
        # decompressed LAZ cache) or ``source``; only without either is the array sent
        src = getattr(points, "filename", None) if isinstance(points, np.memmap) else None
        if src is None and source is not None:
            src = str(Path(os.fspath(source)).resolve())
        # with a shared file system, the plan's order goes as its file, not 8 bytes a point
        shared = replace(plan, order=NpyRows(folder.resolve() / "order.npy"))
        plan_f = client.scatter(shared if src is not None else plan, broadcast=True)
        pts_f = None if src is not None else client.scatter(np.asarray(points),
                                                            broadcast=True)
        with JsonlLog(folder / "tiles.jsonl") as log:
            bar = progress(total=plan.n_tiles, desc="tiles", quiet=quiet, initial=len(done))
            try:
                it = iter(todo)
                pending = as_completed()
                for t in it:
                    pending.add(client.submit(_remote_tile, src, pts_f, plan_f, t, settings,
                                              float(hint),
                                              key=f"polygeo-tile-{folder.name}-{t}"))
                    if pending.count() >= 2 * n_workers:
                        break
                for fut in pending:
                    res = fut.result()
                    t = int(fut.key.rsplit("-", 1)[1])
                    _store(folder, plan, t, res)
                    hint.add(res["halo"])
                    log.append({"tile": t, "n": int(res["index"].size),
                                "halo": float(res["halo"]), "loaded": int(res["loaded"])})
                    bar.update(1)
                    fut.release()
                    nxt = next(it, None)
                    if nxt is not None:
                        pending.add(client.submit(_remote_tile, src, pts_f, plan_f, nxt,
                                                  settings, float(hint),
                                                  key=f"polygeo-tile-{folder.name}-{nxt}"))
            finally:
                bar.close()
        return _finish(folder, maps, plan, len(done))
    finally:
        if own_client:
            cluster = getattr(client, "cluster", None)
            client.close()
            if cluster is not None:
                cluster.close()
