"""Garment-like test meshes in metres: a sheet draped over a table edge, a skirt, a body.

Public names are re-exported by :mod:`polygeo.synthetic`, their documented home.
"""

from __future__ import annotations

import numpy as np

from ..checks import check_int, check_positive
from ._common import grid_faces

__all__ = [
    "draped_sheet_mesh",
    "skirt_mesh",
    "body_mesh",
]


def draped_sheet_mesh(
    n: int = 100, *, size: float = 1.0, n_folds: int = 4, fold_depth: float = 0.05, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """A square sheet draped over a table edge, with folds growing along the hanging part.

    The sheet (side ``size`` metres) lies flat on ``z = 0`` for ``x < 0``, bends over a
    rounded edge of radius ``0.1 * size`` and hangs down, with sinusoidal folds across it
    whose depth grows linearly from the edge to ``fold_depth``; the phases are seeded.

    Parameters
    ----------
    n : int
        Vertices per side (>= 2); ``V = n**2``.
    size : float
        Side length in metres.
    n_folds : int
        Number of folds across the sheet.
    fold_depth : float
        Largest fold amplitude in metres.
    seed : int
        Seed of the fold phases and of a small random modulation.

    Returns
    -------
    vertices : np.ndarray, shape (V, 3), float64
    faces : np.ndarray, shape (F, 3), int64
        Consistently wound triangles, ``F = 2 (n-1)^2``.

    Raises
    ------
    ValueError
        On ``n < 2`` or non-positive sizes.
    """
    n = check_int(n, "n", low=2)
    size = check_positive(size, "size")
    fold_depth = check_positive(fold_depth, "fold_depth", strict=False)
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, n)
    a, b = np.meshgrid(s, s, indexing="ij")  # a: along the drape, b: across
    rad = 0.1 * size
    arc = 0.5 * np.pi * rad
    flat = 0.4 * size
    t = a * size  # arclength along the drape
    x = np.where(t < flat, t - flat, 0.0)
    z = np.zeros_like(t)
    on_arc = (t >= flat) & (t < flat + arc)
    phi = (t - flat) / rad
    x = np.where(on_arc, rad * np.sin(phi), x)
    z = np.where(on_arc, rad * (np.cos(phi) - 1.0), z)
    hang = t >= flat + arc
    x = np.where(hang, rad, x)
    z = np.where(hang, -rad - (t - flat - arc), z)
    grow = np.clip((t - flat) / (size - flat), 0.0, 1.0)
    phase = rng.uniform(0, 2 * np.pi)
    freq = n_folds * (1.0 + 0.1 * rng.uniform(-1, 1))
    fold = fold_depth * grow**1.5 * np.sin(2 * np.pi * freq * b + phase)
    y = b * size + 0.3 * fold_depth * grow * np.sin(np.pi * freq * b)
    # folds displace along the outward direction of the draped curve (x for the hanging part)
    nx = np.where(on_arc, np.sin(phi), np.where(hang, 1.0, 0.0))
    nz = np.where(on_arc, np.cos(phi), np.where(hang, 0.0, 1.0))
    verts = np.stack([x + fold * nx, y - 0.5 * size, z + fold * nz], axis=-1).reshape(-1, 3)
    return verts, grid_faces(n, n, False, False).astype(np.int64)


def skirt_mesh(
    n_around: int = 160,
    n_down: int = 80,
    *,
    waist: float = 0.16,
    hem: float = 0.36,
    length: float = 0.6,
    n_folds: int = 9,
    fold_depth: float = 0.03,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """An open flared tube (a skirt) with vertical folds that deepen towards the hem.

    Parameters
    ----------
    n_around, n_down : int
        Vertices around (>= 3) and along (>= 2) the skirt.
    waist, hem : float
        Radii at the top and the bottom in metres.
    length : float
        Height in metres (the skirt hangs from ``z = 0`` down to ``z = -length``).
    n_folds : int
        Number of folds around.
    fold_depth : float
        Fold amplitude at the hem in metres.
    seed : int
        Seed of the fold phases and of a small irregularity.

    Returns
    -------
    vertices : np.ndarray, shape (n_around * n_down, 3), float64
    faces : np.ndarray, shape (F, 3), int64
        A tube open at both ends (two boundary loops).

    Raises
    ------
    ValueError
        On too few vertices or non-positive sizes.
    """
    nu = check_int(n_around, "n_around", low=3)
    nv = check_int(n_down, "n_down", low=2)
    for val, nm in ((waist, "waist"), (hem, "hem"), (length, "length")):
        check_positive(val, nm)
    rng = np.random.default_rng(seed)
    th = np.linspace(0.0, 2 * np.pi, nu, endpoint=False)
    t = np.linspace(0.0, 1.0, nv)
    T, H = np.meshgrid(th, t, indexing="ij")
    phase = rng.uniform(0, 2 * np.pi)
    jitter = rng.uniform(-0.3, 0.3, 3)
    folds = np.sin(n_folds * T + phase + jitter[0] * np.sin(T)) * (1 + jitter[1] * np.cos(2 * T))
    r = waist + (hem - waist) * H**0.8 + fold_depth * H**1.3 * folds
    z = -length * H + 0.02 * length * H * np.sin(2 * T + jitter[2])
    verts = np.stack([r * np.cos(T), r * np.sin(T), z], axis=-1).reshape(-1, 3)
    return verts, grid_faces(nu, nv, True, False).astype(np.int64)


def body_mesh(subdivisions: int = 5, *, height: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """A smooth closed body-like surface (hips, waist, chest, shoulders, neck, head).

    A unit icosphere ``(x, y, h)`` is mapped to ``(x W(h), y D(h), h height / 2)`` with smooth
    (monotone cubic) width and depth profiles of a torso with a head: wider left-right than
    front-back, a narrow neck. Genus 0, closed, outward-wound, smooth.

    Parameters
    ----------
    subdivisions : int
        Icosphere subdivisions (0..7); ``V = 10 * 4**subdivisions + 2``.
    height : float
        Height in metres (default 1: torso and head).

    Returns
    -------
    vertices : np.ndarray, shape (V, 3), float64
    faces : np.ndarray, shape (F, 3), int64

    Raises
    ------
    ValueError
        On subdivisions outside ``[0, 7]`` or a non-positive height.
    """
    import trimesh
    from scipy.interpolate import PchipInterpolator

    sub = check_int(subdivisions, "subdivisions", low=0, high=7)
    height = check_positive(height, "height")
    ico = trimesh.creation.icosphere(subdivisions=sub)
    v = np.asarray(ico.vertices, dtype=np.float64)
    h = v[:, 2]
    # profiles in metres for a 1 m figure: bottom, hips, waist, chest, shoulders, neck, head, top
    knots = np.array([-1.0, -0.75, -0.3, 0.1, 0.42, 0.6, 0.8, 1.0])
    wide = np.array([0.16, 0.19, 0.14, 0.18, 0.21, 0.06, 0.09, 0.07])
    deep = np.array([0.12, 0.13, 0.10, 0.13, 0.11, 0.06, 0.10, 0.08])
    s = height / 1.0
    w = PchipInterpolator(knots, wide)(h) * s
    d = PchipInterpolator(knots, deep)(h) * s
    verts = np.stack([v[:, 0] * w, v[:, 1] * d, 0.5 * height * h], axis=-1)
    return verts, np.asarray(ico.faces, dtype=np.int64)
