"""LAS/LAZ files and memory-mapped point sources for clouds larger than memory.

This module sits beside :mod:`polygeo.io` on the ground floor: :mod:`polygeo.io` reads whole
files into memory (PLY, OBJ, OFF, XYZ, NPY, NPZ); this one adds the formats and access paths
that large surveys need, so that the common readers stay small:

- :func:`read_las` / :func:`write_las`: LAS 1.0-1.4 and LAZ (``laspy`` with the ``lazrs``
  backend, no compiler). Every dimension of the input (standard and extra bytes) is kept;
  the writer streams the input again in chunks and appends the estimated quantities as extra
  dimensions (:data:`LAS_FIELDS`), so that memory stays bounded by the chunk size.
- :func:`open_points`: an ``(N, 3)`` float64 *view* of a file's coordinates read on demand:
  ``.npy`` and uncompressed ``.las`` and binary ``.ply`` files are memory-mapped (nothing read
  until indexed); ``.laz`` is decompressed once, chunk by chunk, into an ``.npy`` cache file.

Coordinates are in the file's unit (LAS: scaled and offset integers, returned as float64).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from .io import PointData
from .runs import atomic_write

__all__ = [
    "LAS_SUFFIXES",
    "LAS_FIELDS",
    "PointSource",
    "read_las",
    "write_las",
    "open_points",
    "las_point_count",
]

#: File suffixes handled here.
LAS_SUFFIXES = (".las", ".laz")

#: Extra dimensions written by :func:`write_las`: name -> (source field, column or None, type).
#: Float quantities are stored as float32 (LAS extra bytes; ~7 significant digits), the
#: status as uint8 (:class:`polygeo.status.Status` codes).
LAS_FIELDS: dict[str, tuple[str, int | None, str]] = {
    "normal_x": ("normals", 0, "f4"),
    "normal_y": ("normals", 1, "f4"),
    "normal_z": ("normals", 2, "f4"),
    "k1": ("k1", None, "f4"),
    "k2": ("k2", None, "f4"),
    "mean_curvature": ("mean_curvature", None, "f4"),
    "gaussian_curvature": ("gaussian_curvature", None, "f4"),
    "d1_x": ("d1", 0, "f4"),
    "d1_y": ("d1", 1, "f4"),
    "d1_z": ("d1", 2, "f4"),
    "d2_x": ("d2", 0, "f4"),
    "d2_y": ("d2", 1, "f4"),
    "d2_z": ("d2", 2, "f4"),
    "jet_status": ("status", None, "u1"),
}

_CHUNK = 2_000_000


def _laspy():
    try:
        import laspy
    except ImportError as exc:  # pragma: no cover - a dependency
        raise ImportError("LAS/LAZ files need laspy and lazrs: pip install laspy lazrs") from exc
    return laspy


def _check_path(path: Any, name: str = "path") -> Path:
    if not isinstance(path, str | os.PathLike):
        raise TypeError(f"{name}: expected a str or os.PathLike, got {type(path).__name__}")
    p = Path(os.fspath(path))
    if not p.exists():
        raise FileNotFoundError(f"{name}: no such file {str(p)!r}")
    return p


def _open_reader(p: Path):
    laspy = _laspy()
    try:
        return laspy.open(str(p), mode="r")
    except Exception as exc:  # laspy raises LaspyException, ValueError, OSError...
        raise ValueError(f"{p}: could not read as LAS/LAZ ({type(exc).__name__}: {exc})") from exc


def las_point_count(path: str | os.PathLike) -> int:
    """Number of points declared by a LAS/LAZ header (nothing else is read).

    Raises
    ------
    FileNotFoundError
        No such file.
    ValueError
        Not a LAS/LAZ file.
    """
    p = _check_path(path)
    with _open_reader(p) as reader:
        return int(reader.header.point_count)


def _chunks(p: Path, size: int = _CHUNK) -> Iterator[Any]:
    """Point records of a LAS/LAZ file, ``size`` at a time, checking the declared count."""
    with _open_reader(p) as reader:
        expected = int(reader.header.point_count)
        got = 0
        try:
            for chunk in reader.chunk_iterator(size):
                got += len(chunk)
                yield chunk
        except Exception as exc:
            msg = f"{p}: truncated or corrupt LAS/LAZ data after {got} of {expected} points"
            raise ValueError(f"{msg} ({type(exc).__name__}: {exc})") from exc
        if got != expected:
            raise ValueError(f"{p}: truncated LAS/LAZ file: {got} of {expected} points readable")


def read_las(path: str | os.PathLike) -> PointData:
    """Read a whole LAS/LAZ file into memory.

    Parameters
    ----------
    path : str or os.PathLike
        A ``.las`` or ``.laz`` file.

    Returns
    -------
    PointData
        ``points (N, 3)`` float64 (scaled coordinates, the file's unit), ``normals`` when the
        file has ``normal_x/y/z`` (or ``NormalX/Y/Z``) dimensions, and every other dimension
        as an ``(N,)`` attribute under its laspy name (``intensity``, ``classification``,
        ``gps_time``, extra bytes, ...).

    Raises
    ------
    FileNotFoundError
        No such file.
    ValueError
        Not a LAS/LAZ file, or a truncated one (fewer points than the header declares).
    """
    p = _check_path(path)
    parts = list(_chunks(p))
    if not parts or sum(len(c) for c in parts) == 0:
        raise ValueError(f"{p}: the LAS/LAZ file has no points")
    names = list(parts[0].point_format.dimension_names)
    pts = np.concatenate(
        [np.stack([np.asarray(c.x), np.asarray(c.y), np.asarray(c.z)], 1) for c in parts]
    ).astype(np.float64, copy=False)
    attrs = {}
    for n in names:
        if n in ("X", "Y", "Z"):
            continue
        attrs[n] = np.concatenate([np.asarray(c[n]) for c in parts])
    normals = None
    for trio in (("normal_x", "normal_y", "normal_z"), ("NormalX", "NormalY", "NormalZ")):
        if all(t in attrs for t in trio):
            normals = np.stack([attrs.pop(t).astype(np.float64) for t in trio], 1)
            break
    return PointData(pts, normals, None, attrs)


def _out_header(src_header: Any, fields: dict[str, Any]):
    import copy

    laspy = _laspy()
    header = copy.deepcopy(src_header)
    have = set(header.point_format.dimension_names)
    extra = []
    for name, (src, _col, typ) in LAS_FIELDS.items():
        if src in fields and name not in have:
            extra.append(laspy.ExtraBytesParams(name=name, type=np.dtype(typ)))
    if extra:
        header.add_extra_dims(extra)
    return header


def write_las(
    path: str | os.PathLike,
    source: str | os.PathLike,
    fields: dict[str, Any],
    *,
    chunk_size: int = _CHUNK,
) -> Path:
    """Copy a LAS/LAZ file with per-point quantities added as extra dimensions, atomically.

    The source is streamed ``chunk_size`` points at a time, so ``fields`` may be memory maps
    of any size: memory stays bounded by the chunk.

    Parameters
    ----------
    path : str or os.PathLike
        Output ``.las`` or ``.laz`` (compressed when the suffix is ``.laz``). Written to a
        temporary file beside it and renamed when complete: an error leaves no file under
        this name.
    source : str or os.PathLike
        The LAS/LAZ file whose points the fields belong to (same order); all its dimensions,
        its header (scales, offsets, CRS VLRs) and point format are kept.
    fields : dict of str to array
        Any of ``normals (N, 3)``, ``k1``, ``k2``, ``mean_curvature``,
        ``gaussian_curvature`` ``(N,)``, ``d1``, ``d2 (N, 3)``, ``status (N,)``; written
        under the names of :data:`LAS_FIELDS` (an input dimension of the same name is
        overwritten).

    Returns
    -------
    pathlib.Path
        ``path``.

    Raises
    ------
    ValueError
        Bad suffix, a field whose length is not the source's point count, unknown field
        names, or an unreadable/truncated source.
    """
    laspy = _laspy()
    out = Path(os.fspath(path))
    if out.suffix.lower() not in LAS_SUFFIXES:
        raise ValueError(f"path: expected a .las or .laz file name, got {str(out)!r}")
    src = _check_path(source, "source")
    known = {v[0] for v in LAS_FIELDS.values()}
    unknown = sorted(set(fields) - known)
    if unknown:
        raise ValueError(f"fields: unknown names {unknown}; expected some of {sorted(known)}")
    n = las_point_count(src)
    for name, arr in fields.items():
        if len(arr) != n:
            raise ValueError(f"fields[{name!r}]: expected {n} rows (the source's points), "
                             f"got {len(arr)}")
    with _open_reader(src) as reader:
        header = _out_header(reader.header, fields)

    def _write(fh) -> None:
        with laspy.open(fh, mode="w", header=header, closefd=False,
                        do_compress=out.suffix.lower() == ".laz") as writer:
            start = 0
            for chunk in _chunks(src, chunk_size):
                m = len(chunk)
                rec = laspy.ScaleAwarePointRecord.zeros(m, header=header)
                for dim in chunk.point_format.dimension_names:
                    rec[dim] = chunk[dim]
                for name, (fld, col, typ) in LAS_FIELDS.items():
                    if fld not in fields:
                        continue
                    vals = np.asarray(fields[fld][start:start + m])
                    vals = vals if col is None else vals[:, col]
                    if typ == "u1":
                        vals = np.clip(vals, 0, 255)
                    rec[name] = vals.astype(typ)
                writer.write_points(rec)
                start += m

    return atomic_write(out, _write)


class PointSource:
    """``(N, 3)`` float64 coordinates read on demand from memory-mapped columns.

    Indexing (``src[i]``, ``src[a:b]``, ``src[index_array]``) returns an in-memory
    ``(m, 3)`` float64 array: ``column * scale + offset`` per axis. Only the rows asked for
    are read from disk.

    Parameters
    ----------
    columns : tuple of three 1-D array-likes (memory maps)
        x, y, z raw values.
    scale, offset : (3,) float
        Per axis: coordinate = raw * scale + offset.
    path : Path, optional
        The file, for messages.
    """

    def __init__(self, columns, scale=(1.0, 1.0, 1.0), offset=(0.0, 0.0, 0.0), path=None):
        self.columns = tuple(columns)
        self.scale = np.asarray(scale, dtype=np.float64)
        self.offset = np.asarray(offset, dtype=np.float64)
        self.path = path
        self.shape = (int(len(self.columns[0])), 3)
        self.dtype = np.dtype(np.float64)

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, index: Any) -> np.ndarray:
        cols = [np.asarray(c[index], dtype=np.float64) for c in self.columns]
        out = np.stack(cols, axis=-1)
        if np.any(self.scale != 1.0) or np.any(self.offset != 0.0):
            out = out * self.scale + self.offset
        return out


def _ply_memmap(p: Path) -> PointSource | None:
    """Memory-map the vertex element of a binary PLY file (None when not possible)."""
    types = {"char": "i1", "uchar": "u1", "short": "i2", "ushort": "u2", "int": "i4",
             "uint": "u4", "float": "f4", "double": "f8", "int8": "i1", "uint8": "u1",
             "int16": "i2", "uint16": "u2", "int32": "i4", "uint32": "u4", "float32": "f4",
             "float64": "f8"}
    with open(p, "rb") as fh:
        if fh.readline().strip() != b"ply":
            raise ValueError(f"{p}: not a PLY file (no 'ply' magic)")
        fmt, elements = None, []
        while True:
            line = fh.readline()
            if not line:
                raise ValueError(f"{p}: PLY header without end_header")
            words = line.decode("ascii", "replace").split()
            if not words:
                continue
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                elements.append((words[1], int(words[2]), []))
            elif words[0] == "property" and elements:
                typ = None if words[1] == "list" else types.get(words[1])
                elements[-1][2].append((words[-1], typ))
            elif words[0] == "end_header":
                break
        offset = fh.tell()
    if fmt not in ("binary_little_endian", "binary_big_endian") or not elements:
        return None
    name, count, props = elements[0]
    if name != "vertex" or any(t is None for _n, t in props):
        return None  # lists or another element first: the plain reader handles it
    end = "<" if fmt == "binary_little_endian" else ">"
    dtype = np.dtype([(n, end + t) for n, t in props])
    names = dtype.names or ()
    if not all(c in names for c in "xyz"):
        raise ValueError(f"{p}: the PLY vertex element has no x, y, z properties")
    if os.path.getsize(p) < offset + count * dtype.itemsize:
        raise ValueError(f"{p}: truncated PLY file ({count} vertices declared)")
    mm = np.memmap(p, dtype=dtype, mode="r", offset=offset, shape=(count,))
    return PointSource((mm["x"], mm["y"], mm["z"]), path=p)


def _las_memmap(p: Path) -> PointSource:
    with _open_reader(p) as reader:
        h = reader.header
        count = int(h.point_count)
        size = int(h.point_format.size)
        offset = int(h.offset_to_point_data)
        scale, off = np.asarray(h.scales, float), np.asarray(h.offsets, float)
    if os.path.getsize(p) < offset + count * size:
        raise ValueError(f"{p}: truncated LAS file ({count} points declared)")
    rec = np.dtype({"names": ["X", "Y", "Z"], "formats": ["<i4"] * 3, "offsets": [0, 4, 8],
                    "itemsize": size})
    mm = np.memmap(p, dtype=rec, mode="r", offset=offset, shape=(count,))
    return PointSource((mm["X"], mm["Y"], mm["Z"]), scale, off, path=p)


def _laz_cache(p: Path, cache_dir: Path) -> np.ndarray:
    """Decompress the coordinates of a LAZ file into ``cache_dir`` once (float64 ``.npy``)."""
    st = p.stat()
    cache = cache_dir / f"{p.stem}.{st.st_size}.{int(st.st_mtime_ns)}.xyz.npy"
    if not cache.exists():
        n = las_point_count(p)
        cache_dir.mkdir(parents=True, exist_ok=True)
        tmp = cache.with_name(cache.name + f".{os.getpid()}.tmp")
        try:
            # appended to the file (not through a memory map: its pages would stay resident)
            header = {"descr": np.lib.format.dtype_to_descr(np.dtype(np.float64)),
                      "fortran_order": False, "shape": (n, 3)}
            start = 0
            with open(tmp, "wb") as fh:
                np.lib.format.write_array_header_1_0(fh, header)
                for chunk in _chunks(p):
                    xyz = np.empty((len(chunk), 3))
                    xyz[:, 0], xyz[:, 1], xyz[:, 2] = chunk.x, chunk.y, chunk.z
                    fh.write(xyz.tobytes())
                    start += len(xyz)
            if start != n:
                raise ValueError(f"{p}: {start} points decompressed, {n} declared")
            os.replace(tmp, cache)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
    return np.load(cache, mmap_mode="r")


def open_points(path: str | os.PathLike, *, cache_dir: str | os.PathLike | None = None):
    """Open a file's coordinates as an ``(N, 3)`` array-like read on demand.

    Parameters
    ----------
    path : str or os.PathLike
        ``.npy`` (``(N, 3)`` or ``(N, >=3)``: first three columns), ``.las`` (memory-mapped
        point records), ``.laz`` (decompressed once into ``cache_dir``), binary ``.ply``
        (memory-mapped vertex element). Other files are read whole with
        :func:`polygeo.io.read_points`.
    cache_dir : str or os.PathLike, optional
        Folder for the decompressed LAZ coordinates (default: beside the input, in
        ``.polygeo_cache``).

    Returns
    -------
    numpy.memmap or PointSource or numpy.ndarray
        Indexing returns float64 ``(m, 3)`` arrays.

    Raises
    ------
    FileNotFoundError
        No such file.
    ValueError
        Unreadable, truncated or wrongly shaped content (the message names the file).
    """
    p = _check_path(path)
    suffix = p.suffix.lower()
    if suffix == ".npy":
        try:
            arr = np.load(p, mmap_mode="r", allow_pickle=False)
        except Exception as exc:
            raise ValueError(f"{p}: could not read as NPY ({type(exc).__name__}: {exc})") from exc
        if arr.ndim != 2 or arr.shape[1] < 3:
            raise ValueError(f"{p}: expected an (N, 3) array, got shape {arr.shape}")
        if arr.dtype == np.float64 and arr.shape[1] == 3:
            return arr
        return PointSource((arr[:, 0], arr[:, 1], arr[:, 2]), path=p)
    if suffix == ".las":
        return _las_memmap(p)
    if suffix == ".laz":
        return _laz_cache(p, Path(cache_dir) if cache_dir else p.parent / ".polygeo_cache")
    if suffix == ".ply":
        src = _ply_memmap(p)
        if src is not None:
            return src
    from .io import read_points

    return read_points(p).points
