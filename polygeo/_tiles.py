"""The out-of-core parts of :mod:`polygeo.tiling`: the tile plan, reading rows, storing results.

Everything here touches the whole cloud and so streams it: the plan is built in passes over
chunks of the points (a bounding box, a fine histogram, counts per tile, then the point
indices bucketed by tile straight into a ``.npy`` file), rows are read from memory maps in
blocks whose pages are released after each block, tile results are appended in tile order to
plain files, and a last pass writes them in the input's point order. So peak resident memory
is bounded by the chunk and tile sizes, not by the number of points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .checks import check_int
from .status import Status

#: Rows read from a memory map between two releases of its pages.
BLOCK_ROWS = 1 << 22


@dataclass(frozen=True)
class TilePlan:
    """A grid of tiles over the finite points' ``(x, y)`` bounding box.

    Attributes
    ----------
    lo, hi : (2,) float
        Bounding box of the finite points in x, y (length unit).
    shape : (2,) int
        Tiles along x and y.
    offsets : (T + 1,) int64
        Tile ``t`` owns ``order[offsets[t]:offsets[t + 1]]`` (``t = ix * ny + iy``).
    order : (N_finite,) int64 array
        Indices of the finite points sorted by tile, ascending inside a tile (in memory or
        a memory map).
    n_points, n_nonfinite : int
        Points in the cloud, of which not finite (no tile: status NONFINITE_INPUT).
    budget : int
        Largest number of points (own + halo) one tile may load.
    """

    lo: tuple[float, float]
    hi: tuple[float, float]
    shape: tuple[int, int]
    offsets: np.ndarray
    order: np.ndarray
    n_points: int
    n_nonfinite: int
    budget: int

    @property
    def n_tiles(self) -> int:
        """Number of tiles (empty ones included)."""
        return int(self.shape[0] * self.shape[1])

    def tile_box(self, t: int) -> tuple[float, float, float, float]:
        """``(x0, x1, y0, y1)`` of tile ``t``."""
        ix, iy = divmod(int(t), int(self.shape[1]))
        wx, wy = self._widths()
        return (self.lo[0] + ix * wx, self.lo[0] + (ix + 1) * wx,
                self.lo[1] + iy * wy, self.lo[1] + (iy + 1) * wy)

    def _widths(self) -> tuple[float, float]:
        wx = (self.hi[0] - self.lo[0]) / self.shape[0] or 1.0
        wy = (self.hi[1] - self.lo[1]) / self.shape[1] or 1.0
        return wx, wy

    def members(self, t: int) -> np.ndarray:
        """Global indices of the points tile ``t`` owns (ascending)."""
        return np.array(self.order[self.offsets[t]:self.offsets[t + 1]])


class NpyRows:
    """An ``.npy`` file read on demand through a memory map; pickled as its path.

    Stands for a large plan array sent to Dask workers that share the file system.
    """

    def __init__(self, path: str | Path):
        self.path = str(path)
        self._arr: np.ndarray | None = None

    def _array(self) -> np.ndarray:
        if self._arr is None:
            self._arr = np.load(self.path, mmap_mode="r")
        return self._arr

    @property
    def _mmap(self):
        return getattr(self._array(), "_mmap", None)

    @property
    def shape(self) -> tuple[int, ...]:
        return self._array().shape

    def __getitem__(self, index: Any) -> np.ndarray:
        return self._array()[index]

    def __getstate__(self) -> dict:
        return {"path": self.path}

    def __setstate__(self, state: dict) -> None:
        self.path, self._arr = state["path"], None


def drop_pages(arr: Any) -> None:
    """Let the kernel drop a memory map's pages from this process's resident set.

    Harmless on arrays in memory; the data stay in the file (and the page cache).
    """
    arrays = getattr(arr, "columns", None) or (arr,)
    for a in arrays:
        mm = getattr(a, "_mmap", None)
        if mm is not None and hasattr(mm, "madvise"):
            try:
                import mmap

                mm.madvise(mmap.MADV_DONTNEED)
            except (OSError, ValueError, AttributeError):  # pragma: no cover - platform
                pass


def read_rows(points: Any, idx: np.ndarray, block: int = BLOCK_ROWS) -> np.ndarray:
    """``points[idx]`` as float64 ``(m, 3)`` for ascending ``idx``, block by block.

    The memory map's pages are released after each block of ``block`` rows, so reading
    scattered rows never maps the whole file into memory.
    """
    out = np.empty((idx.size, 3))
    if idx.size == 0:
        return out
    cuts = np.flatnonzero(np.diff(idx // block)) + 1
    for a, b in zip(np.r_[0, cuts], np.r_[cuts, idx.size]):
        out[a:b] = np.asarray(points[idx[a:b]], dtype=np.float64).reshape(-1, 3)
        drop_pages(points)
    return out


def _chunks(points: Any, chunk: int):
    """``(start, xyz float64, finite mask)`` over ``chunk`` rows at a time."""
    n = int(points.shape[0])
    for s in range(0, n, chunk):
        xyz = np.asarray(points[s:s + chunk], dtype=np.float64).reshape(-1, 3)
        drop_pages(points)
        yield s, xyz, np.isfinite(xyz).all(1)


def tile_keys(xy: np.ndarray, lo, hi, shape) -> np.ndarray:
    """Tile index of each (finite) row of ``xy`` (points on the upper edge go to the last)."""
    keys = []
    for a in range(2):
        w = (hi[a] - lo[a]) / shape[a] or 1.0
        i = np.floor((xy[:, a] - lo[a]) / w).astype(np.int64)
        keys.append(np.clip(i, 0, shape[a] - 1))
    return keys[0] * shape[1] + keys[1]


def _grid(counts: np.ndarray, n_fin: int, ext: np.ndarray, tile_points: int) -> tuple[int, int]:
    """The coarsest square-ish grid whose tiles hold <= ``tile_points`` (fine histogram)."""
    fine = counts.shape[0]
    aspect = float(ext[0] / ext[1]) if ext[1] > 0 else 1.0
    t = max(1.0, n_fin / tile_points)
    while True:
        nx = int(min(fine, max(1, round(math.sqrt(t * aspect)))))
        ny = int(min(fine, max(1, math.ceil(t / nx))))
        edges_x = np.linspace(0, fine, nx + 1).round().astype(int)
        edges_y = np.linspace(0, fine, ny + 1).round().astype(int)
        block = np.add.reduceat(np.add.reduceat(counts, edges_x[:-1], 0), edges_y[:-1], 1)
        if block.max(initial=0) <= tile_points or (nx >= fine and ny >= fine) or \
                nx * ny >= 4096:
            return nx, ny
        t *= 1.5


def plan_tiles(points: Any, *, tile_points: int, budget: int | None = None,
               tiles: tuple[int, int] | None = None, chunk: int = 4_000_000,
               order_file: str | Path | None = None) -> TilePlan:
    """Cut a cloud into a grid of tiles of at most about ``tile_points`` own points.

    The grid is square-celled in the finite points' ``(x, y)`` box and refined until no
    tile owns more than ``tile_points`` points (or a tile is smaller than 1/4096 of the box:
    dense spots then give bigger tiles). Points are read ``chunk`` rows at a time, in four
    passes (box, fine histogram, counts per tile, bucketing), so memory stays bounded by the
    chunk (plus the order, 8 bytes per point, unless ``order_file`` is given).

    Parameters
    ----------
    points : (N, 3) array-like
        Coordinates (a NumPy array, memory map or :class:`polygeo.io_las.PointSource`).
    tile_points : int
        Target largest number of own points per tile.
    budget : int, optional
        Largest number of points one tile may load with its halo (default
        ``2 * tile_points``).
    tiles : (int, int), optional
        A fixed grid (tiles along x, y) instead of the one ``tile_points`` gives.
    order_file : str or Path, optional
        A ``.npy`` file to write the bucketed order into (returned as a read-only memory
        map) instead of memory.

    Returns
    -------
    TilePlan
    """
    n = int(points.shape[0])
    tile_points = check_int(tile_points, "tile_points", low=1)
    lo = np.array([np.inf, np.inf])
    hi = -lo
    n_bad = 0
    for _s, xyz, fin in _chunks(points, chunk):
        n_bad += int((~fin).sum())
        if fin.any():
            lo = np.minimum(lo, xyz[fin, :2].min(0))
            hi = np.maximum(hi, xyz[fin, :2].max(0))
    if not np.isfinite(lo).all():
        lo, hi = np.zeros(2), np.ones(2)
    n_fin = n - n_bad
    if tiles is None:
        fine = 256
        counts = np.zeros((fine, fine), dtype=np.int64)
        for _s, xyz, fin in _chunks(points, chunk):
            key = tile_keys(xyz[fin, :2], lo, hi, (fine, fine))
            counts += np.bincount(key, minlength=fine * fine).reshape(fine, fine)
        nx, ny = _grid(counts, n_fin, np.maximum(hi - lo, 1e-300), tile_points)
    else:
        nx, ny = (check_int(v, "tiles", low=1) for v in tiles)
    shape = (nx, ny)
    T = nx * ny
    per_tile = np.zeros(T, dtype=np.int64)
    for _s, xyz, fin in _chunks(points, chunk):
        per_tile += np.bincount(tile_keys(xyz[fin, :2], lo, hi, shape), minlength=T)
    offsets = np.zeros(T + 1, dtype=np.int64)
    offsets[1:] = np.cumsum(per_tile)
    if order_file is None:
        order = np.empty(n_fin, dtype=np.int64)
    else:
        order = np.lib.format.open_memmap(order_file, mode="w+", dtype=np.int64,
                                          shape=(n_fin,))
    # bucketing: chunk by chunk (ascending rows), each tile's rows appended at its cursor
    cursor = offsets[:-1].copy()
    for s, xyz, fin in _chunks(points, chunk):
        rows = np.flatnonzero(fin) + s
        keys = tile_keys(xyz[fin, :2], lo, hi, shape)
        o = np.argsort(keys, kind="stable")
        sk = keys[o]
        cnt = np.bincount(keys, minlength=T)
        first = np.cumsum(cnt) - cnt
        order[cursor[sk] + np.arange(sk.size) - first[sk]] = rows[o]
        cursor += cnt
        if order_file is not None:
            order.flush()
            drop_pages(order)
    if order_file is not None:
        del order
        order = np.load(order_file, mmap_mode="r")
    return TilePlan((float(lo[0]), float(lo[1])), (float(hi[0]), float(hi[1])), shape,
                    offsets, order, n, n_bad, int(budget or 2 * tile_points))


# ----------------------------------------------------------------------------- result files


def _field_shape(cols: int | None, n: int) -> tuple[int, ...]:
    return (n, cols) if cols else (n,)


def create_npy(path: Path, dtype: Any, shape: tuple[int, ...]) -> None:
    """An ``.npy`` file of ``shape`` (sparse: its data not written, so read as zeros)."""
    dt = np.dtype(dtype)
    with open(path, "wb") as fh:
        np.lib.format.write_array_header_1_0(
            fh, {"descr": np.lib.format.dtype_to_descr(dt), "fortran_order": False,
                 "shape": tuple(int(v) for v in shape)})
        fh.truncate(fh.tell() + dt.itemsize * int(np.prod(shape, dtype=np.int64)))


def create_tile_files(folder: Path, fields: dict, n_rows: int) -> None:
    """Empty ``tile_<name>.npy`` files (tile order, ``n_rows`` rows) for every field."""
    for f, (cols, typ) in fields.items():
        create_npy(folder / f"tile_{f}.npy", typ, _field_shape(cols, n_rows))


def _data_offset(path: Path) -> int:
    with open(path, "rb") as fh:
        version = np.lib.format.read_magic(fh)
        if version == (1, 0):
            np.lib.format.read_array_header_1_0(fh)
        else:
            np.lib.format.read_array_header_2_0(fh)
        return fh.tell()


def store_tile(folder: Path, fields: dict, start: int, res: dict) -> None:
    """Write one tile's rows at row ``start`` of the tile-order files (plain file writes).

    Written through the file, not a memory map, so no page stays in the resident set.
    """
    for f, (_cols, typ) in fields.items():
        data = np.ascontiguousarray(res[f], dtype=typ)
        if not data.shape[0]:
            continue
        path = folder / f"tile_{f}.npy"
        row = data.nbytes // data.shape[0]
        off = _data_offset(path)
        with open(path, "r+b") as fh:
            fh.seek(off + start * row)
            fh.write(data.tobytes())


def _nonfinite_value(name: str, typ: str):
    return int(Status.NONFINITE_INPUT) if name == "status" else np.nan


def reorder(folder: Path, fields: dict, plan: TilePlan, chunk: int = 1 << 23) -> None:
    """Write ``<name>.npy`` in input order from the tile-order files, then delete those.

    A position file (input row -> tile-order row, -1 for non-finite points) is built from
    the plan's order; each chunk of input rows is then gathered from the tile-order files in
    ascending position, block by block, and appended to the output files.
    """
    n, n_fin = plan.n_points, int(plan.offsets[-1])
    pos_path = folder / "position.npy"
    if n == 0:
        for f, (cols, typ) in fields.items():
            create_npy(folder / f"{f}.npy", typ, _field_shape(cols, 0))
        return
    pos = np.lib.format.open_memmap(pos_path, mode="w+", dtype=np.int64, shape=(n,))
    for s in range(0, n, chunk):
        pos[s:s + chunk] = -1
        pos.flush()
        drop_pages(pos)
    for s in range(0, n_fin, chunk):
        rows = np.asarray(plan.order[s:s + chunk])
        pos[rows] = np.arange(s, s + rows.size)
        pos.flush()
        drop_pages(pos)
        drop_pages(plan.order)
    del pos
    pos = np.load(pos_path, mmap_mode="r")
    src = {f: np.load(folder / f"tile_{f}.npy", mmap_mode="r") if n_fin else None
           for f in fields}
    tmp = {f: folder / f"{f}.npy.tmp" for f in fields}
    handles = {}
    try:
        for f, (cols, typ) in fields.items():
            fh = open(tmp[f], "wb")
            handles[f] = fh
            np.lib.format.write_array_header_1_0(
                fh, {"descr": np.lib.format.dtype_to_descr(np.dtype(typ)),
                     "fortran_order": False, "shape": _field_shape(cols, n)})
        for s in range(0, n, chunk):
            p = np.array(pos[s:s + chunk])
            drop_pages(pos)
            good = p >= 0
            o = np.argsort(p, kind="stable")
            o = o[good[o]]  # finite rows in ascending tile-order position
            ps = p[o]
            cuts = np.flatnonzero(np.diff(ps // BLOCK_ROWS)) + 1
            for f, (cols, typ) in fields.items():
                vals = np.empty(_field_shape(cols, p.size), dtype=typ)
                vals[~good] = _nonfinite_value(f, typ)
                for a, b in zip(np.r_[0, cuts], np.r_[cuts, ps.size]) if ps.size else ():
                    vals[o[a:b]] = src[f][ps[a:b]]
                    drop_pages(src[f])
                handles[f].write(vals.tobytes())
        for f, fh in handles.items():
            fh.close()
            tmp[f].replace(folder / f"{f}.npy")
    finally:
        for fh in handles.values():
            fh.close()
        for t in tmp.values():
            t.unlink(missing_ok=True)
    del src, pos
    for f in fields:
        (folder / f"tile_{f}.npy").unlink(missing_ok=True)
    pos_path.unlink(missing_ok=True)
