"""Generic pictures of cloth: rendered mesh frames, PNG strips, animated GIFs, curve charts.

Small on purpose: every draping method reuses it (matplotlib with Agg, PIL).
"""

from __future__ import annotations

import io
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

__all__ = ["render_frames", "render_drapes", "write_gif", "write_strip", "plot_curves"]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def render_frames(vertices: Sequence, faces, *, points: Sequence | None = None,
                  colors: Sequence | None = None, size: float = 3.0, elev: float = 20.0,
                  azim: float = -60.0, titles: Sequence[str] | None = None) -> list:
    """Render meshes ``vertices[k]`` ``(V, 3)`` sharing ``faces`` ``(F, 3)`` to RGB images.

    One fixed bounding box over all frames (so that motion shows); ``points[k]`` ``(P, 3)``
    are drawn as dots (handles); ``colors[k]`` ``(V,)`` colour the faces by the mean of
    their vertices' values (e.g. an error). Returns a list of ``PIL.Image``.
    """
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection
    from PIL import Image

    plt = _plt()
    verts = [np.asarray(v, dtype=np.float64) for v in vertices]
    f = np.asarray(faces, dtype=np.int64)
    allv = np.concatenate(verts)
    lo, hi = allv.min(0), allv.max(0)
    c, r = 0.5 * (lo + hi), 0.5 * float((hi - lo).max()) + 1e-9
    vmax = max(float(np.max(colors)) if colors is not None else 1.0, 1e-12)
    images = []
    for k, v in enumerate(verts):
        fig = plt.figure(figsize=(size, size), dpi=80)
        ax = fig.add_subplot(projection="3d")
        tri = v[f]
        if colors is not None:
            val = np.asarray(colors[k])[f].mean(1) / vmax
            fc = plt.get_cmap("viridis")(val)
        else:
            n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
            shade = 0.35 + 0.65 * np.abs(n @ np.array([0.3, -0.5, 0.8]) / 1.0)
            fc = np.clip(shade[:, None] * np.array([0.55, 0.7, 0.95]), 0, 1)
        ax.add_collection3d(Poly3DCollection(tri, facecolors=fc, edgecolor="none"))
        if points is not None:
            p = np.asarray(points[k])
            ax.scatter(p[:, 0], p[:, 1], p[:, 2], c="red", s=12, depthshade=False)
        ax.set_xlim(c[0] - r, c[0] + r)
        ax.set_ylim(c[1] - r, c[1] + r)
        ax.set_zlim(c[2] - r, c[2] + r)
        ax.view_init(elev=elev, azim=azim)
        ax.set_axis_off()
        if titles is not None:
            ax.set_title(titles[k], fontsize=8)
        buf = io.BytesIO()
        fig.savefig(buf, format="png")
        plt.close(fig)
        buf.seek(0)
        images.append(Image.open(buf).convert("RGB"))
    return images


def render_drapes(meshes: Sequence, garment_faces, *, titles: Sequence[str] | None = None,
                  elev: float = 10.0, azim: float = -70.0, size: float = 3.0) -> list:
    """Render garments on bodies: ``meshes[k] = (body_vertices, body_faces, garment_vertices)``.

    The body is drawn dark and the garment light, one fixed bounding box over all frames.
    Returns a list of ``PIL.Image``.
    """
    gf = np.asarray(garment_faces, dtype=np.int64)
    verts, faces, colors = [], [], []
    for b, bf, x in meshes:
        b, x = np.asarray(b, dtype=np.float64), np.asarray(x, dtype=np.float64)
        verts.append(np.concatenate([b, x]))
        faces.append(np.concatenate([np.asarray(bf, dtype=np.int64), gf + len(b)]))
        colors.append(np.concatenate([np.full(len(b), 0.25), np.full(len(x), 0.9)]))
    if any(f.shape != faces[0].shape or not np.array_equal(f, faces[0]) for f in faces):
        raise ValueError("meshes: expected the same body faces in every frame")
    return render_frames(verts, faces[0], colors=colors, titles=titles, elev=elev, azim=azim,
                         size=size)


def write_gif(images: Sequence, path: str | os.PathLike, fps: float = 20.0) -> Path:
    """Write ``images`` (PIL) as a looping animated GIF."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    if not images:
        raise ValueError("images: expected at least one frame")
    images[0].save(p, save_all=True, append_images=list(images[1:]),
                   duration=int(round(1000 / fps)), loop=0)
    return p


def write_strip(images: Sequence, path: str | os.PathLike) -> Path:
    """Write ``images`` (PIL) side by side as one PNG."""
    from PIL import Image

    if not images:
        raise ValueError("images: expected at least one frame")
    w = sum(im.width for im in images)
    h = max(im.height for im in images)
    out = Image.new("RGB", (w, h), "white")
    x = 0
    for im in images:
        out.paste(im, (x, 0))
        x += im.width
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    out.save(p)
    return p


def plot_curves(curves: dict, path: str | os.PathLike, *, xlabel: str = "", ylabel: str = "",
                title: str = "", logy: bool = False, x: dict | None = None,
                markers: bool = False) -> Path:
    """Line chart of ``curves`` ``{label: values}`` (``x[label]`` optional abscissae)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    for name, y in curves.items():
        xs = x[name] if x is not None and name in x else np.arange(len(y))
        ax.plot(xs, y, label=str(name), marker="o" if markers else None, ms=3)
    if logy:
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(p)
    plt.close(fig)
    return p
