"""Format parsers behind :func:`polygeo.io.read_points` (package-private).

Each parser takes a path and returns a dict with ``points`` (N, 3) float64, ``normals``
(N, 3) float64 or None, ``faces`` (F, 3) int64 or None and ``attributes`` (dict of per-vertex
arrays), in the file's own vertex order. Polygons are fan-triangulated. A parser raises
``ValueError`` with a message that does not yet name the file (the caller prefixes it).

PLY goes through ``plyfile`` (public, pure-Python, every PLY variant: ASCII and binary of
either endianness, any scalar and list type, extra elements, ``comment`` and ``obj_info``
lines); OBJ, OFF, STL and text clouds are parsed here, so that no vertex is merged, dropped
or reordered (STL alone is a triangle soup: its repeated corners are merged, first seen
first).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

#: PLY vertex properties read as normals and as colours.
_NORMAL_NAMES = ("nx", "ny", "nz")
_COLOUR_NAMES = (("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green",
                                                                 "diffuse_blue"))
_FACE_LISTS = ("vertex_indices", "vertex_index")


def _result(points, normals=None, faces=None, attributes=None) -> dict[str, Any]:
    return {"points": points, "normals": normals, "faces": faces,
            "attributes": attributes or {}}


def _fan(polys: list[np.ndarray] | np.ndarray) -> np.ndarray:
    """Fan-triangulate polygons given as index sequences; ``(F, 3)`` int64."""
    tris: list[list[int]] = []
    for poly in polys:
        q = [int(i) for i in poly]
        if len(q) < 3:
            raise ValueError(f"a face needs at least 3 vertices, got {len(q)}")
        tris += [[q[0], q[k], q[k + 1]] for k in range(1, len(q) - 1)]
    return np.asarray(tris, dtype=np.int64).reshape(-1, 3)


def _faces_from_lists(lists: Any) -> np.ndarray:
    """Faces from a PLY list property: a 2-D array when every face has the same length."""
    arr = np.asarray(lists) if len(lists) else np.zeros((0, 3), np.int64)
    if arr.dtype != object and arr.ndim == 2:
        if arr.shape[1] == 3:
            return arr.astype(np.int64)
        return _fan(arr)
    return _fan(list(lists))


def read_ply(p: Path) -> dict[str, Any]:
    """PLY through ``plyfile``: any format, scalar type, list type and extra element."""
    from plyfile import PlyData

    with open(p, "rb") as fh:
        ply = PlyData.read(fh)
    names = [e.name for e in ply.elements]
    if "vertex" not in names:
        raise ValueError(f"the PLY file has no 'vertex' element (elements: {names})")
    vertex = ply["vertex"].data
    if len(vertex) == 0:
        raise ValueError("the PLY file has no vertices")
    props = list(vertex.dtype.names or ())
    missing = [c for c in "xyz" if c not in props]
    if missing:
        raise ValueError(f"the PLY vertex element has no property {missing[0]!r} "
                         f"(properties: {props})")
    pts = np.stack([np.asarray(vertex[c], dtype=np.float64) for c in "xyz"], axis=1)
    used = {"x", "y", "z"}
    normals = None
    if all(c in props for c in _NORMAL_NAMES):
        normals = np.stack([np.asarray(vertex[c], dtype=np.float64) for c in _NORMAL_NAMES], 1)
        used |= set(_NORMAL_NAMES)
    attrs: dict[str, np.ndarray] = {}
    for trio in _COLOUR_NAMES:
        if all(c in props for c in trio) and "colors" not in attrs:
            attrs["colors"] = np.stack([np.asarray(vertex[c]) for c in trio], axis=1)
            used |= set(trio)
    for n in props:
        col = vertex[n]
        if n in used or col.dtype == object:  # list properties per vertex: not an attribute
            continue
        attrs[n] = np.asarray(col).astype(col.dtype.newbyteorder("="))
    faces = None
    if "face" in names:
        fdata = ply["face"].data
        fprops = list(fdata.dtype.names or ())
        key = next((k for k in _FACE_LISTS if k in fprops), None)
        if key is None and len(fdata):
            raise ValueError(f"the PLY face element has no vertex list (properties: {fprops})")
        if key is not None and len(fdata):
            faces = _faces_from_lists(fdata[key])
    return _result(pts, normals, faces, group_vector_attributes(attrs))


def group_vector_attributes(attrs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Re-assemble ``name_x, name_y, name_z`` properties (as ``write_ply`` writes them)."""
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


def _obj_index(token: str, count: int) -> int:
    i = int(token)
    if i == 0 or abs(i) > count and i < 0:
        raise ValueError(f"index {i} out of range")
    return i - 1 if i > 0 else count + i


def read_obj(p: Path) -> dict[str, Any]:
    """Wavefront OBJ: ``v``, ``vn`` and polygon ``f`` records; others are ignored.

    Corners may be ``v``, ``v/vt``, ``v/vt/vn`` or ``v//vn``, with negative indices.

    Normals are returned per vertex when every vertex used by a face has one ``vn``
    wherever it is used (else None: a vertex with several normals is a crease).
    """
    v: list[list[float]] = []
    vn: list[list[float]] = []
    polys: list[list[int]] = []
    pnorm: list[list[int]] = []
    with open(p, encoding="utf-8", errors="replace") as fh:
        text = fh.read()
    for lineno, line in enumerate(text.splitlines(), 1):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        try:
            if parts[0] == "v":
                v.append([float(x) for x in parts[1:4]])
                if len(v[-1]) != 3:
                    raise ValueError("a vertex needs 3 coordinates")
            elif parts[0] == "vn":
                vn.append([float(x) for x in parts[1:4]])
            elif parts[0] == "f":
                corners = [c.split("/") for c in parts[1:]]
                polys.append([_obj_index(c[0], len(v)) for c in corners])
                pnorm.append([_obj_index(c[2], len(vn)) if len(c) > 2 and c[2] else -1
                              for c in corners])
        except (ValueError, IndexError) as exc:
            raise ValueError(f"line {lineno}: cannot parse {line.strip()[:60]!r} ({exc})") from exc
    if not v:
        raise ValueError("the OBJ file has no vertices")
    pts = np.asarray(v, dtype=np.float64)
    faces = _fan(polys) if polys else None
    normals = None
    if faces is not None and vn and all(i >= 0 for q in pnorm for i in q):
        fn = _fan(pnorm)
        nv = np.asarray(vn, dtype=np.float64)
        per = np.full((len(pts), 3), np.nan)
        per[faces.reshape(-1)] = nv[fn.reshape(-1)]
        if not np.isnan(per).any() and np.allclose(per[faces], nv[fn], atol=1e-6):
            normals = per
    return _result(pts, normals, faces)


def read_off(p: Path) -> dict[str, Any]:
    """Object File Format: ``OFF``, ``COFF``, ``NOFF`` or ``CNOFF``.

    One vertex and one polygon per line (per-face colours after the indices are ignored).
    """
    with open(p, encoding="utf-8", errors="replace") as fh:
        lines = [ln.split("#", 1)[0].split() for ln in fh]
    lines = [ln for ln in lines if ln]
    if not lines or not re.fullmatch(r"C?N?OFF", lines[0][0]):
        got = lines[0][0][:20] if lines else ""
        raise ValueError(f"expected an 'OFF' header, got {got!r}")
    head = lines[0][0]
    counts, body = (lines[0][1:], lines[1:]) if len(lines[0]) > 1 else (lines[1], lines[2:])
    try:
        nv, nf = int(counts[0]), int(counts[1])
    except (IndexError, ValueError) as exc:
        raise ValueError("the OFF header lacks vertex and face counts") from exc
    if len(body) < nv + nf:
        raise ValueError(f"expected {nv} vertex and {nf} face lines, got {len(body)} lines")
    try:
        block = np.asarray([ln[:6] if "N" in head else ln[:3] for ln in body[:nv]],
                           dtype=np.float64)
        polys = [[int(x) for x in ln[1:1 + int(ln[0])]] for ln in body[nv:nv + nf]]
    except ValueError as exc:
        raise ValueError(f"malformed vertex or face line ({exc})") from exc
    normals = block[:, 3:6].copy() if "N" in head else None
    return _result(block[:, :3].copy(), normals, _fan(polys) if polys else None)


def read_stl(p: Path) -> dict[str, Any]:
    """STL, ASCII or binary, through trimesh's public loader.

    A triangle soup: its shared corners are merged (first seen first), so that the mesh is
    connected.
    """
    import trimesh

    mesh = trimesh.load(str(p), file_type="stl", process=False)
    tri = np.asarray(mesh.triangles, dtype=np.float64).reshape(-1, 3)
    if tri.shape[0] == 0:
        raise ValueError("the STL file has no triangles")
    _, first, inverse = np.unique(tri, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)  # unique rows in order of first appearance
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    points = tri[first[order]]
    faces = rank[inverse.reshape(-1)].reshape(-1, 3).astype(np.int64)
    return _result(points, None, faces)


_TEXT_NAMES = {
    "x": "x", "y": "y", "z": "z", "//x": "x",
    "nx": "nx", "ny": "ny", "nz": "nz", "normal_x": "nx", "normal_y": "ny", "normal_z": "nz",
}


def _split(line: str) -> list[str]:
    return [w for w in re.split(r"[,;\s]+", line.strip()) if w]


def _is_number(word: str) -> bool:
    try:
        float(word)
    except ValueError:
        return False
    return True


def read_text(p: Path, columns: list[str] | None = None) -> dict[str, Any]:
    """A text cloud (``.xyz``, ``.txt``, ``.csv``, ``.asc``, ``.pts``): one point per row.

    Values are comma, semicolon, tab or space separated; ``#``/``//`` lines are comments.

    Column rule, first that applies: ``columns`` given by the caller; else a header line of
    names (the last non-numeric line before the data, ``#`` allowed) naming ``x y z`` and
    optionally ``nx ny nz``; else ``x y z`` first, and columns 4-6 are normals only when
    there are exactly six and every row of them is a unit vector. Every other column is an
    attribute (named from the header, else ``col3``, ``col4``...).
    """
    header: list[str] | None = None
    rows: list[list[str]] = []
    with open(p, encoding="utf-8", errors="replace") as fh:
        for line in fh:
            s = line.strip()
            if not s:
                continue
            words = _split(s.lstrip("#/").strip()) if s[0] in "#/" else _split(s)
            if s[0] in "#/" or not all(_is_number(w) for w in words):
                if rows:
                    raise ValueError(f"row {len(rows) + 1}: expected numbers, got {s[:60]!r}")
                if words and not any(_is_number(w) for w in words):
                    header = [w.lower() for w in words]
                continue
            rows.append(words)
    if not rows:
        raise ValueError("the file holds no points")
    width = len(rows[0])
    bad = next((i for i, r in enumerate(rows) if len(r) != width), None)
    if bad is not None:
        raise ValueError(f"row {bad + 1} has {len(rows[bad])} columns, row 1 has {width}")
    arr = np.asarray(rows, dtype=np.float64)
    return split_columns(arr, columns if columns is not None else header, explicit=columns)


def split_columns(arr: np.ndarray, names: list[str] | None, *,
                  explicit: Any = None) -> dict[str, Any]:
    """Points, normals and attributes of an ``(N, C)`` table by the column rule above."""
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise ValueError(f"expected at least 3 columns (x y z), got shape {arr.shape}")
    width = arr.shape[1]
    if names is not None and len(names) != width:
        if explicit is not None:
            raise ValueError(f"columns: {len(names)} names for {width} columns")
        names = None  # a header that does not match the data is a comment, not names
    if names is not None:
        canon = [_TEXT_NAMES.get(n, n) for n in names]
        if not all(c in canon for c in "xyz"):
            if explicit is not None:
                raise ValueError(f"columns: expected names x, y and z, got {names}")
            names = None
    if names is None:
        canon = ["x", "y", "z"] + [f"col{i}" for i in range(3, width)]
        if width == 6:
            n = arr[:, 3:6]
            length = np.linalg.norm(n, axis=1)
            fin = np.isfinite(length)
            if fin.any() and np.all(np.abs(length[fin] - 1.0) < 1e-3):
                canon[3:6] = list(_NORMAL_NAMES)
    index = {c: i for i, c in enumerate(canon)}
    pts = np.ascontiguousarray(arr[:, [index[c] for c in "xyz"]])
    normals = None
    if all(c in index for c in _NORMAL_NAMES):
        normals = np.ascontiguousarray(arr[:, [index[c] for c in _NORMAL_NAMES]])
    used = {"x", "y", "z"} | (set(_NORMAL_NAMES) if normals is not None else set())
    attrs = {c: arr[:, i].copy() for i, c in enumerate(canon) if c not in used}
    return _result(pts, normals, None, attrs)
