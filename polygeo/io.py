"""Reading and writing point clouds and meshes.

Readers return float64 NumPy arrays in the file's own vertex order: meshes are loaded with
``trimesh`` *without* its processing (``process=False``), so no vertex is merged, dropped
or reordered and per-vertex attributes stay aligned with the points. Writers never leave a
half-written file: they write to a temporary file beside the target and ``os.replace`` it.

Supported inputs: ``.ply`` (ASCII or binary; every extra vertex property becomes an
attribute), ``.obj``, ``.off``, ``.xyz`` / ``.txt`` (whitespace-separated ``x y z`` or
``x y z nx ny nz`` rows, ``#`` comments), ``.npy`` (an ``(N, 3)`` or ``(N, 6)`` array) and
``.npz`` (key ``points`` or ``vertices``, optional ``normals``, ``faces``; other ``(N, ...)``
arrays become attributes).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .runs import atomic_write

__all__ = ["PointData", "read_points", "read_mesh", "write_ply", "write_npz", "SUFFIXES"]

#: File suffixes :func:`read_points` understands.
SUFFIXES = (".ply", ".obj", ".off", ".xyz", ".txt", ".npy", ".npz")


@dataclass(frozen=True)
class PointData:
    """Points read from a file.

    Attributes
    ----------
    points : (N, 3) float64
        Coordinates, in the file's unit and vertex order.
    normals : (N, 3) float64 or None
        Per-point normals when the file stores them (``nx, ny, nz`` in PLY, columns 4-6 of
        XYZ/NPY, key ``normals`` in NPZ; OBJ/OFF files carry none that are per-vertex here).
    faces : (F, 3) int64 or None
        Triangles (polygons are fan-triangulated by trimesh), None for a bare cloud.
    attributes : dict of str to (N,) or (N, C) arrays
        Other per-vertex properties (PLY properties, NPZ arrays).
    """

    points: np.ndarray
    normals: np.ndarray | None = None
    faces: np.ndarray | None = None
    attributes: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.points.shape[0])


def _check_file(path: Any) -> Path:
    p = Path(os.fspath(path))
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such file")
    if not p.is_file():
        raise ValueError(f"{p}: expected a regular file, got a directory or special file")
    if p.stat().st_size == 0:
        raise ValueError(f"{p}: the file is empty")
    suffix = p.suffix.lower()
    if suffix not in SUFFIXES:
        raise ValueError(f"{p}: unknown extension {p.suffix!r}; expected one of {list(SUFFIXES)}")
    return p


def _split_xyz_normals(arr: np.ndarray, p: Path) -> tuple[np.ndarray, np.ndarray | None]:
    if arr.ndim != 2 or arr.shape[1] not in (3, 6):
        raise ValueError(f"{p}: expected an (N, 3) or (N, 6) array, got shape {arr.shape}")
    if arr.shape[0] == 0:
        raise ValueError(f"{p}: the file holds no points")
    if arr.dtype.kind not in "iuf":
        raise ValueError(f"{p}: expected numeric values, got dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    return np.ascontiguousarray(arr[:, :3]), (
        np.ascontiguousarray(arr[:, 3:6]) if arr.shape[1] == 6 else None
    )


def _read_ply(p: Path) -> PointData:
    import trimesh

    try:
        obj = trimesh.load(str(p), file_type="ply", process=False)
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise ValueError(f"{p}: could not parse as PLY ({type(exc).__name__}: {exc})") from exc
    raw = getattr(obj, "metadata", {}).get("_ply_raw", {}).get("vertex", {})
    data = raw.get("data")
    if data is None or len(data) == 0:
        raise ValueError(f"{p}: the PLY file has no vertices")
    names = list(data.dtype.names or ())
    for c in "xyz":
        if c not in names:
            raise ValueError(f"{p}: the PLY vertex element has no property {c!r}")
    pts = np.stack([np.asarray(data[c], dtype=np.float64) for c in "xyz"], axis=1)
    normals = None
    used = {"x", "y", "z"}
    if all(c in names for c in ("nx", "ny", "nz")):
        normals = np.stack([np.asarray(data[c], dtype=np.float64) for c in ("nx", "ny", "nz")], 1)
        used |= {"nx", "ny", "nz"}
    attrs = {n: np.asarray(data[n]).copy() for n in names if n not in used}
    attrs = _group_vector_attributes(attrs)
    faces = None
    if isinstance(obj, trimesh.Trimesh) and len(obj.faces):
        faces = np.asarray(obj.faces, dtype=np.int64)
    return PointData(pts, normals, faces, attrs)


def _group_vector_attributes(attrs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Re-assemble ``name_x, name_y, name_z`` properties (as :func:`write_ply` writes them)."""
    out: dict[str, np.ndarray] = {}
    done: set[str] = set()
    for n in attrs:
        if n in done:
            continue
        if n.endswith("_x"):
            base = n[:-2]
            parts = [f"{base}_{c}" for c in "xyz"]
            if all(q in attrs for q in parts):
                out[base] = np.stack([attrs[q] for q in parts], axis=1)
                done.update(parts)
                continue
        out[n] = attrs[n]
        done.add(n)
    return out


def _read_trimesh(p: Path, kind: str) -> PointData:
    import trimesh

    try:
        obj = trimesh.load(str(p), file_type=kind, process=False, maintain_order=True)
    except Exception as exc:
        msg = f"{p}: could not parse as {kind.upper()} ({type(exc).__name__}: {exc})"
        raise ValueError(msg) from exc
    if isinstance(obj, trimesh.Scene):
        geoms = list(obj.geometry.values())
        if not geoms:
            raise ValueError(f"{p}: the file has no geometry")
        if len(geoms) > 1:
            obj = trimesh.util.concatenate(geoms)
        else:
            obj = geoms[0]
    verts = np.asarray(getattr(obj, "vertices", np.zeros((0, 3))), dtype=np.float64)
    if verts.shape[0] == 0:
        raise ValueError(f"{p}: the file has no vertices")
    faces = None
    if isinstance(obj, trimesh.Trimesh) and len(obj.faces):
        faces = np.asarray(obj.faces, dtype=np.int64)
    return PointData(np.ascontiguousarray(verts), None, faces, {})


def _read_npz(p: Path) -> PointData:
    try:
        with np.load(p, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as exc:
        raise ValueError(f"{p}: could not read as NPZ ({type(exc).__name__}: {exc})") from exc
    key = "points" if "points" in data else "vertices" if "vertices" in data else None
    if key is None:
        raise ValueError(f"{p}: expected a 'points' or 'vertices' array, found {sorted(data)}")
    pts, _ = _split_xyz_normals(data.pop(key), p)
    normals = None
    if "normals" in data:
        normals = np.asarray(data.pop("normals"), dtype=np.float64)
        if normals.shape != pts.shape:
            raise ValueError(f"{p}: 'normals' has shape {normals.shape}, expected {pts.shape}")
    faces = None
    if "faces" in data:
        faces = np.asarray(data.pop("faces"))
        if faces.ndim != 2 or faces.shape[1] != 3 or faces.dtype.kind not in "iu":
            raise ValueError(f"{p}: 'faces' must be an (F, 3) integer array, got {faces.shape}")
        faces = faces.astype(np.int64)
    n = pts.shape[0]
    attrs = {k: v for k, v in data.items() if v.ndim >= 1 and v.shape[0] == n}
    return PointData(pts, normals, faces, attrs)


def read_points(path: str | os.PathLike) -> PointData:
    """Read a point cloud or mesh file.

    Parameters
    ----------
    path : str or os.PathLike
        A ``.ply``, ``.obj``, ``.off``, ``.xyz``/``.txt``, ``.npy`` or ``.npz`` file.

    Returns
    -------
    PointData
        Points ``(N, 3)`` float64, optional normals, faces and per-vertex attributes, in the
        file's vertex order.

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    ValueError
        Unknown extension, empty file, unparsable content or wrong array shapes (the message
        names the file).
    """
    p = _check_file(path)
    suffix = p.suffix.lower()
    if suffix == ".ply":
        out = _read_ply(p)
    elif suffix in (".obj", ".off"):
        out = _read_trimesh(p, suffix[1:])
    elif suffix in (".xyz", ".txt"):
        try:
            arr = np.loadtxt(p, comments="#", ndmin=2, dtype=np.float64)
        except ValueError as exc:
            msg = f"{p}: could not parse as whitespace-separated numbers ({exc})"
            raise ValueError(msg) from exc
        pts, nrm = _split_xyz_normals(arr, p)
        out = PointData(pts, nrm, None, {})
    elif suffix == ".npy":
        try:
            arr = np.load(p, allow_pickle=False)
        except Exception as exc:
            raise ValueError(f"{p}: could not read as NPY ({type(exc).__name__}: {exc})") from exc
        pts, nrm = _split_xyz_normals(np.asarray(arr), p)
        out = PointData(pts, nrm, None, {})
    else:
        out = _read_npz(p)
    if out.faces is not None and out.faces.size:
        if out.faces.min() < 0 or out.faces.max() >= out.points.shape[0]:
            raise ValueError(f"{p}: faces refer to vertices outside [0, {out.points.shape[0] - 1}]")
    return out


def read_mesh(path: str | os.PathLike) -> PointData:
    """Read a triangle mesh (a file with faces).

    Parameters
    ----------
    path : str or os.PathLike
        A ``.ply``, ``.obj``, ``.off`` or ``.npz`` file with faces.

    Returns
    -------
    PointData
        With ``faces`` not None.

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    ValueError
        As :func:`read_points`, or the file holds no faces.
    """
    data = read_points(path)
    if data.faces is None or data.faces.shape[0] == 0:
        raise ValueError(f"{os.fspath(path)}: expected a mesh with faces, found a bare point cloud")
    return data


def _np(x: Any, name: str) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    a = np.asarray(x)
    if a.dtype == object or a.dtype.kind not in "biuf":
        raise TypeError(f"{name}: expected a numeric array, got dtype {a.dtype}")
    return a


_PLY_TYPES = {"f4": "float", "f8": "double", "i4": "int", "u1": "uchar", "i8": "int"}


def write_ply(
    path: str | os.PathLike,
    points: Any,
    faces: Any = None,
    attributes: dict[str, Any] | None = None,
    *,
    normals: Any = None,
    precision: str = "float",
) -> Path:
    """Write a binary little-endian PLY with per-vertex properties, atomically.

    Parameters
    ----------
    path : str or os.PathLike
        Output file; its folder is created. An existing file is replaced only once the new
        one is complete.
    points : (N, 3) float
        Vertex coordinates.
    faces : (F, 3) int, optional
        Triangles (written as a ``vertex_indices`` list).
    attributes : dict of str to (N,) or (N, 3) arrays, optional
        Extra per-vertex properties. ``(N,)`` floating arrays become one ``float`` property,
        integer or boolean ones an ``int`` property; ``(N, 3)`` arrays become three
        properties ``name_x, name_y, name_z`` (read back as one ``(N, 3)`` attribute).
    normals : (N, 3) float, optional
        Written as ``nx, ny, nz``.
    precision : {"float", "double"}
        Storage of coordinates, normals and floating attributes (``float`` = float32).

    Returns
    -------
    pathlib.Path
        The written path.

    Raises
    ------
    ValueError
        Bad shapes, a bad property name, or an unknown precision.
    TypeError
        Non-numeric arrays.
    """
    if precision not in ("float", "double"):
        raise ValueError(f"precision: expected 'float' or 'double', got {precision!r}")
    fdt = "<f4" if precision == "float" else "<f8"
    pts = _np(points, "points")
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points: expected shape (N, 3), got {pts.shape}")
    n = pts.shape[0]
    fields: list[tuple[str, str, np.ndarray]] = [
        (c, fdt, pts[:, i]) for i, c in enumerate("xyz")
    ]
    if normals is not None:
        nrm = _np(normals, "normals")
        if nrm.shape != (n, 3):
            raise ValueError(f"normals: expected shape ({n}, 3), got {nrm.shape}")
        fields += [(c, fdt, nrm[:, i]) for i, c in enumerate(("nx", "ny", "nz"))]
    for name, value in (attributes or {}).items():
        if not name.isidentifier() or name in ("x", "y", "z", "nx", "ny", "nz"):
            raise ValueError(f"attributes: bad or reserved property name {name!r}")
        a = _np(value, f"attributes[{name!r}]")
        dt = fdt if a.dtype.kind == "f" else "<i4"
        if a.shape == (n,):
            fields.append((name, dt, a))
        elif a.shape == (n, 3):
            fields += [(f"{name}_{c}", dt, a[:, i]) for i, c in enumerate("xyz")]
        else:
            raise ValueError(
                f"attributes[{name!r}]: expected shape ({n},) or ({n}, 3), got {a.shape}"
            )
    rec = np.zeros(n, dtype=[(nm, dt) for nm, dt, _ in fields])
    for nm, _, col in fields:
        rec[nm] = col
    face_block = b""
    n_faces = 0
    if faces is not None:
        f = _np(faces, "faces")
        if f.ndim != 2 or f.shape[1] != 3 or f.dtype.kind not in "iu":
            raise ValueError(f"faces: expected an (F, 3) integer array, got {f.shape} {f.dtype}")
        if f.size and (f.min() < 0 or f.max() >= n):
            raise ValueError(f"faces: expected indices in [0, {n - 1}], got [{f.min()}, {f.max()}]")
        n_faces = f.shape[0]
        frec = np.zeros(n_faces, dtype=[("n", "u1"), ("v", "<i4", (3,))])
        frec["n"] = 3
        frec["v"] = f
        face_block = frec.tobytes()
    header = ["ply", "format binary_little_endian 1.0", "comment written by polygeo"]
    header.append(f"element vertex {n}")
    header += [f"property {_PLY_TYPES[np.dtype(dt).str[1:]]} {nm}" for nm, dt, _ in fields]
    if faces is not None:
        header += [f"element face {n_faces}", "property list uchar int vertex_indices"]
    header.append("end_header")
    blob = ("\n".join(header) + "\n").encode("ascii") + rec.tobytes() + face_block
    out = Path(os.fspath(path))
    atomic_write(out, lambda fh: fh.write(blob))
    return out


def write_npz(path: str | os.PathLike, **arrays: Any) -> Path:
    """Write arrays to an uncompressed ``.npz`` file, atomically.

    Parameters
    ----------
    path : str or os.PathLike
        Output file (the ``.npz`` suffix is not added implicitly); its folder is created.
    **arrays : array_like or torch.Tensor
        Named arrays (tensors are detached and converted).

    Returns
    -------
    pathlib.Path
        The written path.

    Raises
    ------
    ValueError
        No arrays given.
    TypeError
        A value that is not numeric.
    """
    if not arrays:
        raise ValueError("write_npz: expected at least one array")
    data = {k: _np(v, k) for k, v in arrays.items()}
    out = Path(os.fspath(path))
    atomic_write(out, lambda fh: np.savez(fh, **data))
    return out
