"""Reading and writing point clouds and meshes.

Readers return float64 NumPy arrays in the file's own vertex order: no vertex is merged,
dropped or reordered (except STL, a triangle soup whose shared corners are merged), so
per-vertex attributes stay aligned with the points. Writers never leave a half-written
file: they write to a temporary file beside the target and ``os.replace`` it.

PLY is read and written with ``plyfile`` (a small, public, well-kept library that handles
every PLY variant: ASCII and binary of either endianness, any scalar and list property type,
extra elements, ``comment``/``obj_info`` lines); OBJ, OFF and text clouds are parsed in
:mod:`polygeo._io_formats`; STL is read with ``trimesh``'s public loader. Supported inputs:
``.ply .obj .off .stl``, text clouds ``.xyz .txt .csv .asc .pts`` (comma, semicolon, tab or
space separated, optional header of column names), ``.npy`` (an ``(N, C >= 3)`` array) and
``.npz`` (key ``points`` or ``vertices``, optional ``normals``, ``faces``; other ``(N, ...)``
arrays become attributes). A file that cannot be read raises one ``ValueError`` line naming
the file and the problem.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from . import _io_formats as _fmt
from .runs import atomic_write

__all__ = [
    "PointData",
    "TexturedMesh",
    "read_points",
    "read_mesh",
    "read_textured_obj",
    "write_ply",
    "write_npz",
    "write_textured_obj",
    "SUFFIXES",
]

#: File suffixes :func:`read_points` understands.
SUFFIXES = (".ply", ".obj", ".off", ".stl", ".xyz", ".txt", ".csv", ".asc", ".pts", ".npy", ".npz")


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


def _read_npy(p: Path, columns: list[str] | None) -> dict[str, Any]:
    arr = np.load(p, allow_pickle=False)
    if arr.dtype.kind not in "iuf":
        raise ValueError(f"expected numeric values, got dtype {arr.dtype}")
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise ValueError(f"expected an (N, 3) or (N, C >= 3) array, got shape {arr.shape}")
    return _fmt.split_columns(arr.astype(np.float64), columns, explicit=columns)


def _read_npz(p: Path) -> dict[str, Any]:
    with np.load(p, allow_pickle=False) as z:
        data = {k: z[k] for k in z.files}
    key = "points" if "points" in data else "vertices" if "vertices" in data else None
    if key is None:
        raise ValueError(f"expected a 'points' or 'vertices' array, found {sorted(data)}")
    pts = np.asarray(data.pop(key))
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.dtype.kind not in "iuf":
        raise ValueError(f"{key!r}: expected a numeric (N, 3) array, got {pts.shape} {pts.dtype}")
    pts = pts.astype(np.float64)
    normals = None
    if "normals" in data:
        normals = np.asarray(data.pop("normals"), dtype=np.float64)
        if normals.shape != pts.shape:
            raise ValueError(f"'normals' has shape {normals.shape}, expected {pts.shape}")
    faces = None
    if "faces" in data:
        faces = np.asarray(data.pop("faces"))
        if faces.ndim != 2 or faces.shape[1] != 3 or faces.dtype.kind not in "iu":
            raise ValueError(f"'faces' must be an (F, 3) integer array, got {faces.shape}")
        faces = faces.astype(np.int64)
    n = pts.shape[0]
    attrs = {k: v for k, v in data.items() if v.ndim >= 1 and v.shape[0] == n}
    return {"points": pts, "normals": normals, "faces": faces, "attributes": attrs}


def _parse_columns(columns: Any) -> list[str] | None:
    if columns is None:
        return None
    names = columns.replace(",", " ").split() if isinstance(columns, str) else list(columns)
    if len(names) < 3 or not all(isinstance(n, str) and n for n in names):
        raise ValueError(f"columns: expected at least 3 column names (x y z ...), got {columns!r}")
    return [n.lower() for n in names]


def read_points(path: str | os.PathLike, *, columns: str | list[str] | None = None) -> PointData:
    """Read a point cloud or mesh file.

    Formats: PLY (ASCII or binary of either endianness, any property types, extra elements;
    through ``plyfile``; ``nx ny nz`` are normals, ``red green blue`` the attribute
    ``colors``, other vertex properties attributes), OBJ (polygons, ``v/vt/vn`` corners;
    normals when each vertex has one), OFF (``OFF``/``COFF``/``NOFF``), STL (ASCII or binary;
    shared corners merged), text clouds (``.xyz .txt .csv .asc .pts``), NPY and NPZ.

    Columns of a text cloud or an ``(N, C)`` NPY array are read by an explicit rule: the
    ``columns`` argument; else a header line of names (``x y z nx ny nz ...``); else ``x y z``
    first, and columns 4-6 are normals only when there are exactly six and all are unit
    vectors (``x y z r g b`` keeps its colours as attributes ``col3 col4 col5``).

    Parameters
    ----------
    path : str or os.PathLike
        The file; its extension selects the format (one of :data:`SUFFIXES`).
    columns : str or list of str, optional
        Names of the columns of a text or NPY file, e.g. ``"x y z nx ny nz"`` or
        ``"x,y,z,r,g,b"``; must include ``x``, ``y`` and ``z``.

    Returns
    -------
    PointData
        Points ``(N, 3)`` float64, optional normals, faces and per-vertex attributes, in the
        file's vertex order (STL: order of first appearance).

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    ValueError
        Unknown extension, empty file, unparsable content or wrong array shapes: one line
        that names the file and the problem.
    """
    p = _check_file(path)
    cols = _parse_columns(columns)
    suffix = p.suffix.lower()
    readers = {".ply": _fmt.read_ply, ".obj": _fmt.read_obj, ".off": _fmt.read_off,
               ".stl": _fmt.read_stl, ".npz": _read_npz}
    try:
        if suffix in readers:
            rec = readers[suffix](p)
        elif suffix == ".npy":
            rec = _read_npy(p, cols)
        else:
            rec = _fmt.read_text(p, cols)
    except Exception as exc:  # every parser failure becomes one line naming the file
        kind = suffix[1:].upper()
        detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ValueError(f"{p}: cannot read as {kind}: {detail}") from exc
    out = PointData(rec["points"], rec["normals"], rec["faces"], rec["attributes"])
    if out.faces is not None and out.faces.size:
        if out.faces.min() < 0 or out.faces.max() >= out.points.shape[0]:
            raise ValueError(f"{p}: faces refer to vertices outside [0, {out.points.shape[0] - 1}]")
    if out.faces is not None and out.faces.shape[0] == 0:
        out = PointData(out.points, out.normals, None, out.attributes)
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
    from plyfile import PlyData, PlyElement

    elements = [PlyElement.describe(rec, "vertex")]
    if faces is not None:
        f = _np(faces, "faces")
        if f.ndim != 2 or f.shape[1] != 3 or f.dtype.kind not in "iu":
            raise ValueError(f"faces: expected an (F, 3) integer array, got {f.shape} {f.dtype}")
        if f.size and (f.min() < 0 or f.max() >= n):
            raise ValueError(f"faces: expected indices in [0, {n - 1}], got [{f.min()}, {f.max()}]")
        frec = np.zeros(f.shape[0], dtype=[("vertex_indices", "<i4", (3,))])
        frec["vertex_indices"] = f
        elements.append(PlyElement.describe(frec, "face", len_types={"vertex_indices": "u1"},
                                            val_types={"vertex_indices": "i4"}))
    ply = PlyData(elements, text=False, byte_order="<", comments=["written by polygeo"])
    out = Path(os.fspath(path))
    atomic_write(out, ply.write)
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


# ---------------------------------------------------------------------- textured OBJ


@dataclass(frozen=True)
class TexturedMesh:
    """A triangle mesh with its appearance, as a Wavefront OBJ holds it.

    Attributes
    ----------
    vertices : (V, 3) float64
        Coordinates, in the file's unit and vertex order.
    faces : (F, 3) int64
        Triangles, 0-based (polygons are fan-triangulated).
    uvs : (V, 2) or (F, 3, 2) float64 or None
        Texture coordinates (OBJ convention: ``v = 0`` at the *bottom* row of the image):
        one per vertex when every vertex has one ``vt`` wherever it is used, else one per
        face corner (a vertex on a UV seam has a different ``vt`` in the faces on either
        side; the geometry stays one vertex). None when a face has no ``vt``.
    texture : (Ht, Wt, 3) float32 or None
        RGB in ``[0, 1]``, row 0 at the top of the image: the ``map_Kd`` image of the
        material library (``mtllib``), None without one.
    colors : (V, 3) float32 or None
        Vertex colours in ``[0, 1]`` (``v x y z r g b`` lines), None unless every vertex has
        one.
    """

    vertices: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray | None = None
    texture: np.ndarray | None = None
    colors: np.ndarray | None = None


def _obj_texture_path(mtl: Path) -> Path | None:
    """The ``map_Kd`` image named by a material library (its first one), or None."""
    if not mtl.is_file():
        raise ValueError(f"{mtl}: material library referenced by the OBJ does not exist")
    for line in mtl.read_text().splitlines():
        parts = line.strip().split(maxsplit=1)
        if len(parts) == 2 and parts[0] == "map_Kd":
            words = parts[1].split()
            name = words[-1] if words[0].startswith("-") else parts[1].strip()  # -s, -o, ...
            tex = mtl.parent / name
            if not tex.is_file():
                raise ValueError(f"{mtl}: texture {name!r} (map_Kd) does not exist")
            return tex
    return None


def _read_texture(path: Path) -> np.ndarray:
    """An 8 or 16 bit image as ``(H, W, 3)`` float32 RGB in ``[0, 1]``."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{path}: cannot decode the texture image")
    if img.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"{path}: expected an 8 or 16 bit texture, got dtype {img.dtype}")
    img = img.astype(np.float32) / (65535.0 if img.dtype == np.uint16 else 255.0)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    return np.ascontiguousarray(img[..., 2::-1] if img.shape[2] >= 3 else img)


def _parse_obj(p: Path) -> dict[str, Any]:
    """The records of an OBJ file: v, colours, vt, faces and their vt indices, mtllib."""
    out: dict[str, Any] = {"v": [], "rgb": [], "vt": [], "f": [], "fvt": [], "mtllib": None}
    for lineno, line in enumerate(p.read_text().splitlines(), 1):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        try:
            if parts[0] == "v":
                out["v"].append([float(x) for x in parts[1:4]])
                if len(parts) >= 7:
                    out["rgb"].append([float(x) for x in parts[4:7]])
            elif parts[0] == "vt":
                out["vt"].append([float(x) for x in parts[1:3]])
            elif parts[0] == "f":
                idx = [c.split("/") for c in parts[1:]]
                if len(idx) < 3:
                    raise ValueError("a face needs at least 3 vertices")
                nv, nt = len(out["v"]), len(out["vt"])
                vi = [int(c[0]) for c in idx]
                ti = [int(c[1]) if len(c) > 1 and c[1] else 0 for c in idx]
                vi = [i - 1 if i > 0 else nv + i for i in vi]  # negative: relative
                ti = [i - 1 if i > 0 else (nt + i if i < 0 else -1) for i in ti]
                for k in range(1, len(vi) - 1):  # fan triangulation of polygons
                    out["f"].append([vi[0], vi[k], vi[k + 1]])
                    out["fvt"].append([ti[0], ti[k], ti[k + 1]])
            elif parts[0] == "mtllib":
                out["mtllib"] = line.strip().split(maxsplit=1)[1]
        except (ValueError, IndexError) as exc:
            raise ValueError(f"{p}:{lineno}: cannot parse {line.strip()!r} ({exc})") from exc
    return out


def _obj_uvs(p: Path, f: np.ndarray, fvt: np.ndarray, vt: np.ndarray, n: int) -> np.ndarray:
    """Per-vertex ``(V, 2)`` uvs when they are consistent, else per face corner ``(F, 3, 2)``."""
    if fvt.size and fvt.max() >= len(vt):
        raise ValueError(f"{p}: a face refers to vt {fvt.max() + 1} of {len(vt)}")
    corner = vt[fvt]  # (F, 3, 2)
    per_vertex = np.full((n, 2), np.nan)
    per_vertex[f.reshape(-1)] = corner.reshape(-1, 2)
    if np.isnan(per_vertex).any() or not np.allclose(per_vertex[f], corner, atol=1e-9):
        return corner  # a seam, or a vertex in no face: per face corner
    return per_vertex


def read_textured_obj(path: str | os.PathLike, *, load_texture: bool = True) -> TexturedMesh:
    """Read a Wavefront OBJ with its texture coordinates, texture image and vertex colours.

    Faces may be ``v``, ``v/vt``, ``v/vt/vn`` or ``v//vn`` (normals are ignored), with
    negative (relative) indices; polygons are fan-triangulated. The texture is the first
    ``map_Kd`` of the ``mtllib`` material library (8 or 16 bit image).

    Parameters
    ----------
    path : str or os.PathLike
        The ``.obj`` file.
    load_texture : bool
        Decode the texture image (else ``texture`` is None; the library is still checked).

    Returns
    -------
    TexturedMesh

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    ValueError
        A line that cannot be parsed (the message names the line), no vertices or faces,
        face or ``vt`` indices out of range, a material library or texture that does not
        exist, or a texture while some face has no ``vt``.
    """
    p = Path(os.fspath(path))
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no such file")
    rec = _parse_obj(p)
    v = np.asarray(rec["v"], dtype=np.float64).reshape(-1, 3)
    f = np.asarray(rec["f"], dtype=np.int64).reshape(-1, 3)
    if len(v) == 0 or len(f) == 0:
        raise ValueError(f"{p}: expected a non-empty (V, 3) vertex array and (F, 3) face "
                         f"array, got {len(v)} vertices and {len(f)} faces")
    if f.min() < 0 or f.max() >= len(v):
        raise ValueError(f"{p}: face indices must lie in [1, {len(v)}], got "
                         f"[{f.min() + 1}, {f.max() + 1}]")
    colors = None
    if rec["rgb"] and len(rec["rgb"]) == len(v):
        colors = np.clip(np.asarray(rec["rgb"], dtype=np.float32), 0.0, 1.0)
    tex_path = _obj_texture_path(p.parent / rec["mtllib"]) if rec["mtllib"] else None
    fvt = np.asarray(rec["fvt"], dtype=np.int64).reshape(-1, 3)
    uvs = None
    if rec["vt"] and not (fvt < 0).any():
        uvs = _obj_uvs(p, f, fvt, np.asarray(rec["vt"], dtype=np.float64), len(v))
    elif tex_path is not None:
        raise ValueError(f"{p}: the material has a texture but faces lack 'vt' indices")
    texture = _read_texture(tex_path) if tex_path is not None and load_texture else None
    return TexturedMesh(vertices=v, faces=f, uvs=uvs, texture=texture, colors=colors)


def _to_uint8_image(img: Any) -> np.ndarray:
    a = _np(img, "texture")
    if a.ndim != 3 or a.shape[2] != 3 or min(a.shape[:2]) < 1:
        raise ValueError(f"texture: expected an (Ht, Wt, 3) image, got shape {a.shape}")
    if a.dtype == np.uint8:
        return a
    if a.dtype.kind != "f":
        raise TypeError(f"texture: expected uint8 or float in [0, 1], got dtype {a.dtype}")
    if not np.isfinite(a).all():
        raise ValueError("texture: non-finite pixel values")
    return np.clip(np.rint(a * 255.0), 0, 255).astype(np.uint8)


def write_textured_obj(
    path: str | os.PathLike,
    vertices: Any,
    faces: Any,
    *,
    uvs: Any = None,
    texture: Any = None,
    colors: Any = None,
    texture_name: str = "texture.png",
) -> Path:
    """Write a mesh as a Wavefront OBJ, with its material library and texture, atomically.

    With a texture, ``<stem>.mtl`` (one material whose ``map_Kd`` is ``texture_name``) and
    the PNG ``texture_name`` are written beside the OBJ; :func:`read_textured_obj` reads the
    three back (coordinates to 9 significant digits).

    Parameters
    ----------
    path : str or os.PathLike
        The ``.obj`` file; its folder is created.
    vertices : (V, 3) float
        Coordinates.
    faces : (F, 3) int
        Triangles, 0-based.
    uvs : (V, 2) or (F, 3, 2) float, optional
        Texture coordinates (OBJ convention, ``v`` up): per vertex, or per face corner for a
        mesh with UV seams (written as one ``vt`` per corner).
    texture : (Ht, Wt, 3) uint8 or float in [0, 1], optional
        RGB image, row 0 at the top; needs ``uvs``.
    colors : (V, 3) float in [0, 1], optional
        Vertex colours (``v x y z r g b``), written when there is no texture.
    texture_name : str
        File name of the texture image (PNG), relative to the OBJ's folder.

    Returns
    -------
    pathlib.Path
        The written OBJ path.

    Raises
    ------
    ValueError
        Bad shapes, face indices out of range, a texture without ``uvs``, or non-finite
        values.
    TypeError
        Non-numeric arrays.
    """
    out = Path(os.fspath(path))
    v = _np(vertices, "vertices").astype(np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or not np.isfinite(v).all():
        raise ValueError(f"vertices: expected a finite (V, 3) array, got shape {v.shape}")
    f = _np(faces, "faces")
    if f.ndim != 2 or f.shape[1] != 3 or f.dtype.kind not in "iu":
        raise ValueError(f"faces: expected an (F, 3) integer array, got {f.shape} {f.dtype}")
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError(f"faces: expected indices in [0, {len(v) - 1}], got "
                         f"[{f.min()}, {f.max()}]")
    lines = ["# written by polygeo"]
    if texture is not None:
        if uvs is None:
            raise ValueError("uvs: a texture needs texture coordinates, got None")
        uv = _np(uvs, "uvs").astype(np.float64)
        if uv.shape not in ((len(v), 2), (len(f), 3, 2)) or not np.isfinite(uv).all():
            raise ValueError(f"uvs: expected finite ({len(v)}, 2) or ({len(f)}, 3, 2), got "
                             f"shape {uv.shape}")
        img = _to_uint8_image(texture)
        mtl = out.with_suffix(".mtl")
        lines.append(f"mtllib {mtl.name}")
    rgb = None if colors is None or texture is not None else _np(colors, "colors")
    if rgb is not None and rgb.shape != (len(v), 3):
        raise ValueError(f"colors: expected shape ({len(v)}, 3), got {rgb.shape}")
    for i, p in enumerate(v):
        xyz = f"v {p[0]:.9g} {p[1]:.9g} {p[2]:.9g}"
        lines.append(xyz if rgb is None else
                     f"{xyz} {rgb[i, 0]:.6g} {rgb[i, 1]:.6g} {rgb[i, 2]:.6g}")
    if texture is not None:
        lines += [f"vt {a:.9g} {b:.9g}" for a, b in uv.reshape(-1, 2)]
        lines.append("usemtl material")
        if uv.ndim == 2:  # per vertex: vt index = vertex index
            lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in f]
        else:  # per face corner: vt 3i + k is corner k of face i
            lines += [f"f {a + 1}/{3 * i + 1} {b + 1}/{3 * i + 2} {c + 1}/{3 * i + 3}"
                      for i, (a, b, c) in enumerate(f)]
    else:
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f]
    if texture is not None:
        import cv2

        ok, png = cv2.imencode(".png", cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        if not ok:  # pragma: no cover - cv2 failure
            raise ValueError(f"texture: could not encode {texture_name} as PNG")
        atomic_write(out.parent / texture_name, lambda fh: fh.write(png.tobytes()))
        text = ("newmtl material\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nillum 1\n"
                f"map_Kd {texture_name}\n")
        atomic_write(mtl, lambda fh: fh.write(text.encode()))
    blob = ("\n".join(lines) + "\n").encode()
    atomic_write(out, lambda fh: fh.write(blob))
    return out
