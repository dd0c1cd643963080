"""The run folder of a drape: frames, metrics and pictures, from plain arrays.

Every method that drapes a sequence (the physics reference of ``polygeo drape-reference``,
GAPS, OneFit, GarNet) writes the same folder, so that their outputs compare file by file:

* ``meshes/000000.ply ...``: the garment of each frame (float64 PLY, metres);
* ``body/000000.ply ...``: the posed body of each frame (float32 PLY, metres);
* ``metrics.json``: one row per frame (``eps_e``, ``eps_a``, ``eps_c`` in %, seconds per frame,
  whatever else the method measures) with their mean and max over the sequence, plus the
  settings of the run;
* ``strip.png`` (a few frames side by side) and ``drape.gif`` (the sequence), garment and
  body rendered off screen (:mod:`draping.viz`).

The functions take NumPy arrays or torch tensors and no scene object: :func:`write_frame`
per frame, :func:`frame_metrics` for a frame's metric row, :func:`write_metrics` once at the
end (or after every frame), :func:`write_pictures` once at the end.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from polygeo.checks import check_faces, check_finite, check_int, check_shape

__all__ = [
    "MESHES",
    "BODY",
    "METRICS",
    "STRIP",
    "GIF",
    "frame_path",
    "write_frame",
    "read_frame",
    "frame_metrics",
    "sequence_summary",
    "write_metrics",
    "write_pictures",
]

#: Sub-folder of the garment frames.
MESHES = "meshes"
#: Sub-folder of the posed body frames.
BODY = "body"
#: File name of the per-frame metrics and their summary.
METRICS = "metrics.json"
#: File name of the picture strip.
STRIP = "strip.png"
#: File name of the animated GIF.
GIF = "drape.gif"


def frame_path(out_dir: str | os.PathLike, t: int, part: str = MESHES) -> Path:
    """Path of frame ``t``'s PLY: ``out_dir/meshes/000012.ply`` (or ``body/`` for the body).

    Raises
    ------
    TypeError, ValueError
        ``t`` not an integer >= 0, ``part`` not ``"meshes"`` or ``"body"``.
    """
    t = check_int(t, "t", low=0)
    if part not in (MESHES, BODY):
        raise ValueError(f"part: expected {MESHES!r} or {BODY!r}, got {part!r}")
    return Path(out_dir) / part / f"{t:06d}.ply"


def _vertices(x: Any, name: str) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    a = np.asarray(x, dtype=np.float64)
    check_shape(a, name, ("V", 3))
    check_finite(torch.from_numpy(a), name)
    return a


def write_frame(out_dir: str | os.PathLike, t: int, garment_vertices: Any, garment_faces: Any,
                body_vertices: Any, body_faces: Any) -> tuple[Path, Path]:
    """Write frame ``t``: the garment (float64 PLY) and the posed body (float32 PLY).

    Parameters
    ----------
    out_dir : str or PathLike
        Run folder (created).
    t : int
        Frame index (>= 0).
    garment_vertices : (G, 3) float array or tensor
        Garment of the frame (m).
    garment_faces : (F_g, 3) int
    body_vertices : (V, 3) float array or tensor
        Posed body of the frame (m).
    body_faces : (F_b, 3) int

    Returns
    -------
    (Path, Path)
        The garment and body files.

    Raises
    ------
    TypeError, ValueError
        A bad frame index, wrong shapes, NaN or infinite vertices, or faces out of range.
    """
    from polygeo.io import write_ply

    gv = _vertices(garment_vertices, "garment_vertices")
    bv = _vertices(body_vertices, "body_vertices")
    gf = check_faces(garment_faces, len(gv), "garment_faces").numpy()
    bf = check_faces(body_faces, len(bv), "body_faces").numpy()
    pg, pb = frame_path(out_dir, t, MESHES), frame_path(out_dir, t, BODY)
    write_ply(pg, gv, gf, precision="double")
    write_ply(pb, bv, bf)
    return pg, pb


def read_frame(out_dir: str | os.PathLike, t: int, part: str = MESHES
               ) -> tuple[np.ndarray, np.ndarray]:
    """Read frame ``t`` back: ``(vertices (V, 3) float64, faces (F, 3) int64)``.

    Raises
    ------
    FileNotFoundError
        The frame was not written.
    """
    from polygeo.io import read_mesh

    m = read_mesh(frame_path(out_dir, t, part))
    return (np.asarray(m.points, dtype=np.float64), np.asarray(m.faces, dtype=np.int64))


def frame_metrics(garment_vertices: Any, rest_vertices: Any, garment_faces: Any,
                  body_vertices: Any = None, body_faces: Any = None, *,
                  distance: Any = None) -> dict:
    """The metric row of one frame (JSON-able floats).

    Parameters
    ----------
    garment_vertices : (G, 3) float
        Draped garment (m).
    rest_vertices : (G, 3) float
        Rest garment (the template the strains are measured against, m).
    garment_faces : (F, 3) int
    body_vertices, body_faces : (V, 3) float, (F_b, 3) int, optional
        Posed body: the signed distances are queried against it
        (:class:`draping.collision.MeshQuery`) unless ``distance`` is given.
    distance : (G,) float, optional
        Signed distances of the garment vertices to the body (m, negative inside).

    Returns
    -------
    dict
        ``eps_e``, ``eps_a`` (mean % change of edge lengths and triangle areas,
        :mod:`draping.metrics`); with a body or distances also ``eps_c`` (% vertices inside)
        and ``min_distance_mm`` (smallest signed distance, mm).

    Raises
    ------
    TypeError, ValueError
        Wrong shapes, NaN, faces out of range, a body without its faces.
    """
    from .metrics import area_error, collision_error, edge_error

    x = torch.from_numpy(_vertices(garment_vertices, "garment_vertices"))
    r = torch.from_numpy(_vertices(rest_vertices, "rest_vertices"))
    if r.shape != x.shape:
        raise ValueError(f"rest_vertices: expected shape {tuple(x.shape)} (as garment_vertices),"
                         f" got {tuple(r.shape)}")
    f = check_faces(garment_faces, len(x), "garment_faces")
    row = {"eps_e": float(edge_error(x, r, f)), "eps_a": float(area_error(x, r, f))}
    if distance is None and body_vertices is not None:
        from .collision import MeshQuery

        if body_faces is None:
            raise ValueError("body_faces: expected the body's (F, 3) triangles with "
                             "body_vertices, got None")
        bv = _vertices(body_vertices, "body_vertices")
        bf = check_faces(body_faces, len(bv), "body_faces").numpy()
        distance = MeshQuery(bv, bf).query(x.numpy()).distance
    if distance is not None:
        d = torch.as_tensor(np.asarray(distance, dtype=np.float64)).reshape(-1)
        if d.shape[0] != x.shape[0]:
            raise ValueError(f"distance: expected {x.shape[0]} values (one per garment vertex),"
                             f" got {d.shape[0]}")
        row["eps_c"] = float(collision_error(d))
        row["min_distance_mm"] = 1000.0 * float(d.min())
    return row


def _number(v: Any) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)


def sequence_summary(rows: Sequence[dict]) -> dict:
    """Mean and max over frames of every numeric entry the rows share (``frame`` excluded).

    Parameters
    ----------
    rows : sequence of dict
        One metric row per frame (e.g. :func:`frame_metrics` plus seconds per frame).

    Returns
    -------
    dict
        ``{"frames": T, "mean": {name: float}, "max": {name: float}}``.

    Raises
    ------
    ValueError
        No rows, or a non-finite value in a shared numeric entry.
    """
    rows = list(rows)
    if not rows:
        raise ValueError("rows: expected at least one frame, got none")
    keys = [k for k, v in rows[0].items()
            if k != "frame" and _number(v) and all(k in r and _number(r[k]) for r in rows)]
    mean, worst = {}, {}
    for k in keys:
        a = np.array([float(r[k]) for r in rows])
        if not np.isfinite(a).all():
            bad = [int(i) for i in np.flatnonzero(~np.isfinite(a))[:5]]
            raise ValueError(f"rows: {k} is NaN or infinite at row(s) {bad}")
        mean[k], worst[k] = float(a.mean()), float(a.max())
    return {"frames": len(rows), "mean": mean, "max": worst}


def write_metrics(out_dir: str | os.PathLike, rows: Sequence[dict], settings: Any = None,
                  **fields: Any) -> dict:
    """Write ``out_dir/metrics.json`` (atomically) and return what it holds.

    Parameters
    ----------
    out_dir : str or PathLike
    rows : sequence of dict
        One JSON-able metric row per frame (``frame``, ``eps_e``, ``eps_a``, ``eps_c``,
        ``seconds``, ``cpu_seconds``, ...).
    settings : JSON-able, optional
        What produced the run (method, garment, motion, solver settings, ...).
    **fields
        More JSON-able top-level entries (e.g. ``garment_vertices``, ``dt`` in s).

    Returns
    -------
    dict
        ``fields`` + :func:`sequence_summary` + ``settings`` + ``per_frame`` (the rows).

    Raises
    ------
    ValueError
        As :func:`sequence_summary`.
    """
    from polygeo.runs import atomic_write_json

    rows = [dict(r) for r in rows]
    record = {**fields, **sequence_summary(rows), "settings": settings, "per_frame": rows}
    atomic_write_json(Path(out_dir) / METRICS, record)
    return record


def write_pictures(out_dir: str | os.PathLike, garment_faces: Any, n_frames: int, *,
                   body_vertices: Any = None, body_faces: Any = None, strip: int = 6,
                   gif: int = 40, fps: float = 30.0, elev: float = 10.0,
                   azim: float = -70.0) -> tuple[Path, Path]:
    """Render ``strip.png`` and ``drape.gif`` from the garment frames written in ``out_dir``.

    Parameters
    ----------
    out_dir : str or PathLike
        A run folder with ``meshes/000000.ply ...`` (and ``body/...`` unless ``body_vertices``
        is given).
    garment_faces : (F, 3) int
    n_frames : int
        Frames written (``0 .. n_frames - 1``).
    body_vertices : (T, P, 3) float, optional
        Body per frame to draw (a decimated proxy is faster); default: the ``body/`` PLYs.
    body_faces : (F_p, 3) int, optional
        Faces of ``body_vertices`` (required with them).
    strip, gif : int
        Frames in the strip and (at most) in the GIF, evenly spaced.
    fps : float
        GIF frame rate (capped at 30).
    elev, azim : float
        View angles (degrees).

    Returns
    -------
    (Path, Path)
        ``strip.png`` and ``drape.gif``.

    Raises
    ------
    ValueError, FileNotFoundError
        Bad counts, body vertices without faces, missing frames.
    """
    from . import viz

    n = check_int(n_frames, "n_frames", low=1)
    strip, gif = check_int(strip, "strip", low=1), check_int(gif, "gif", low=1)
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps: expected a finite value > 0, got {fps}")
    gf = check_faces(garment_faces, None, "garment_faces").numpy()
    if body_vertices is not None:
        if body_faces is None:
            raise ValueError("body_faces: expected (F, 3) triangles with body_vertices, got None")
        bv_all = body_vertices
        if isinstance(bv_all, torch.Tensor):
            bv_all = bv_all.detach().cpu().numpy()
        bv_all = np.asarray(bv_all, dtype=np.float64)
        check_shape(bv_all, "body_vertices", ("T", "P", 3))
        if bv_all.shape[0] < n:
            raise ValueError(f"body_vertices: expected at least {n} frames, got {bv_all.shape[0]}")
        bf = check_faces(body_faces, bv_all.shape[1], "body_faces").numpy()

    def body(t):
        if body_vertices is not None:
            return bv_all[t], bf
        return read_frame(out_dir, t, BODY)

    def render(ts):
        meshes = []
        for t in ts:
            x, _ = read_frame(out_dir, t, MESHES)
            b, f = body(t)
            meshes.append((b, f, x))
        return viz.render_drapes(meshes, gf, titles=[f"frame {t}" for t in ts],
                                 elev=elev, azim=azim)

    def spaced(k):
        return sorted(set(np.linspace(0, n - 1, min(k, n)).round().astype(int).tolist()))

    out = Path(out_dir)
    ps = viz.write_strip(render(spaced(strip)), out / STRIP)
    pg = viz.write_gif(render(spaced(gif)), out / GIF, fps=min(30.0, float(fps)))
    return ps, pg
