"""Generic pictures of cloth: rendered mesh frames, PNG strips, animated GIFs, curve charts.

Small on purpose: every draping method reuses it (matplotlib with Agg, PIL, and a small numba
depth-buffer rasteriser for garments on bodies, so that the body never shows through a garment
drawn over it, as it does with matplotlib's per-face painter's order).
"""

from __future__ import annotations

import io
import os
from collections.abc import Sequence
from pathlib import Path

import numba as nb
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


@nb.njit(cache=True)
def _raster(px, py, depth, faces, colors, width, height):  # pragma: no cover - compiled
    """Z-buffer rasterisation of flat-coloured triangles (pixel centres, nearest wins)."""
    img = np.ones((height, width, 3))
    zbuf = np.full((height, width), -np.inf)
    for k in range(faces.shape[0]):
        a, b, c = faces[k, 0], faces[k, 1], faces[k, 2]
        x0, y0, x1, y1, x2, y2 = px[a], py[a], px[b], py[b], px[c], py[c]
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if area == 0.0:
            continue
        i0 = max(int(np.floor(min(x0, x1, x2))), 0)
        i1 = min(int(np.ceil(max(x0, x1, x2))), width - 1)
        j0 = max(int(np.floor(min(y0, y1, y2))), 0)
        j1 = min(int(np.ceil(max(y0, y1, y2))), height - 1)
        for j in range(j0, j1 + 1):
            yc = j + 0.5
            for i in range(i0, i1 + 1):
                xc = i + 0.5
                w0 = ((x1 - xc) * (y2 - yc) - (x2 - xc) * (y1 - yc)) / area
                w1 = ((x2 - xc) * (y0 - yc) - (x0 - xc) * (y2 - yc)) / area
                w2 = 1.0 - w0 - w1
                if w0 < 0.0 or w1 < 0.0 or w2 < 0.0:
                    continue
                z = w0 * depth[a] + w1 * depth[b] + w2 * depth[c]
                if z > zbuf[j, i]:
                    zbuf[j, i] = z
                    img[j, i, 0] = colors[k, 0]
                    img[j, i, 1] = colors[k, 1]
                    img[j, i, 2] = colors[k, 2]
    return img


def _view(elev: float, azim: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit vectors towards the eye, screen right and screen up of a view (degrees).

    Matplotlib's convention: azimuth about +z, elevation above the xy plane.
    """
    e, a = np.deg2rad(elev), np.deg2rad(azim)
    eye = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    right = np.array([-np.sin(a), np.cos(a), 0.0])
    return eye, right, np.cross(eye, right)


def render_drapes(meshes: Sequence, garment_faces, *, titles: Sequence[str] | None = None,
                  elev: float = 10.0, azim: float = -70.0, size: int = 240,
                  body_color=(0.55, 0.45, 0.42), garment_color=(0.45, 0.62, 0.92)) -> list:
    """Render garments on bodies with a depth buffer (no body showing through the garment).

    Parameters
    ----------
    meshes : sequence of (body_vertices (V, 3), body_faces (F_b, 3), garment_vertices (G, 3))
        One frame each (m); garment faces are shared.
    garment_faces : (F_g, 3) int
    titles : sequence of str, optional
        One caption per frame.
    elev, azim : float
        View (degrees, as matplotlib's 3D axes).
    size : int
        Image width and height (pixels); rendered at twice the size and downsampled.
    body_color, garment_color : (3,) float in [0, 1]
        Base colours, shaded by the angle to a light at the eye.

    Returns
    -------
    list of PIL.Image
        RGB images, one bounding box over all frames (the motion shows).

    Raises
    ------
    ValueError
        No frames or a bad size.
    """
    from PIL import Image, ImageDraw

    if len(meshes) == 0:
        raise ValueError("meshes: expected at least one frame")
    size = int(size)
    if size < 16:
        raise ValueError(f"size: expected at least 16 pixels, got {size}")
    gf = np.asarray(garment_faces, dtype=np.int64)
    frames = []
    for b, bf, x in meshes:
        b, x = np.asarray(b, dtype=np.float64), np.asarray(x, dtype=np.float64)
        f = np.concatenate([np.asarray(bf, dtype=np.int64), gf + len(b)])
        base = np.concatenate([np.tile(body_color, (len(bf), 1)),
                               np.tile(garment_color, (len(gf), 1))])
        frames.append((np.concatenate([b, x]), f, base))
    allv = np.concatenate([v for v, _, _ in frames])
    lo, hi = allv.min(0), allv.max(0)
    c, r = 0.5 * (lo + hi), 0.5 * float((hi - lo).max()) * 1.05 + 1e-12
    eye, right, up = _view(elev, azim)
    big = 2 * size
    images = []
    for k, (v, f, base) in enumerate(frames):
        p = v - c
        px = (p @ right / r + 1.0) * 0.5 * big
        py = (1.0 - p @ up / r) * 0.5 * big
        tri = v[f]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-300
        light = eye + 0.4 * up
        shade = 0.35 + 0.65 * np.abs(n @ (light / np.linalg.norm(light)))
        img = _raster(px, py, p @ eye, f, np.clip(base * shade[:, None], 0, 1), big, big)
        im = Image.fromarray((255 * img).astype(np.uint8), "RGB").resize(
            (size, size), Image.LANCZOS)
        if titles is not None:
            ImageDraw.Draw(im).text((4, 2), str(titles[k]), fill=(0, 0, 0))
        images.append(im)
    return images


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
                markers: bool = False, logx: bool = False,
                hline: float | None = None) -> Path:
    """Line chart of ``curves`` ``{label: values}`` (``x[label]`` optional abscissae).

    ``logx`` / ``logy`` put an axis on a log scale; ``hline`` draws a dashed horizontal
    reference line (a target or a floor) at that ordinate.
    """
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    for name, y in curves.items():
        xs = x[name] if x is not None and name in x else np.arange(len(y))
        ax.plot(xs, y, label=str(name), marker="o" if markers else None, ms=3)
    if logx:
        ax.set_xscale("log")
    if logy:
        ax.set_yscale("log")
    if hline is not None:
        ax.axhline(hline, color="gray", ls="--", lw=0.8)
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
