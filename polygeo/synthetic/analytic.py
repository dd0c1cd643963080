"""Analytic surfaces with exact differential quantities, for tests and benchmarks.

Every generator returns an :class:`AnalyticSample` of float64 NumPy arrays: the clean points,
their exact unit normals, principal curvatures ``k1 >= k2``, unit principal directions, mean and
Gaussian curvature, and (mesh variants) triangle faces. Quantities follow the sign convention of
:mod:`polygeo.diffgeo`: curvature is positive where the surface bends towards its normal, so with
the **outward** normals used here a sphere of radius ``r`` has ``k1 = k2 = H = -1/r`` and
``K = 1/r^2``; graphs ``z = f(x, y)`` use the ``+z`` side normal. ``(d1, d2, n)`` is
right-handed (``d2 = n x d1``); at umbilics (sphere, plane) ``d1`` is an arbitrary but
deterministic tangent.

The closed forms here are written independently of :mod:`polygeo.diffgeo` (graphs use the
classical formulas for ``H`` and ``K`` of a height field) so that tests can compare the two.

Sampling: random samples are uniform with respect to surface area (rejection sampling where the
parametrisation is not equi-areal) and reproducible from ``seed``; ``grid=True`` gives a
deterministic structured sampling of about ``n`` points instead. ``noise`` adds isotropic
Gaussian noise of standard deviation ``noise`` times the bounding-box diagonal of the clean
points, returned separately as ``noisy_points`` (the exact quantities refer to ``points``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..checks import check_int, check_positive
from ._common import grid_faces

__all__ = [
    "AnalyticSample",
    "sphere",
    "cylinder",
    "torus",
    "monge_patch",
    "plane",
    "sphere_mesh",
    "cylinder_mesh",
    "torus_mesh",
    "monge_patch_mesh",
    "plane_mesh",
    "wavy_sheet_mesh",
]


@dataclass(frozen=True)
class AnalyticSample:
    """Samples of an analytic surface with exact differential quantities (float64 NumPy).

    Attributes
    ----------
    points : numpy.ndarray
        ``(N, 3)`` clean points on the surface.
    normals : numpy.ndarray
        ``(N, 3)`` unit normals (outward for closed surfaces, ``+z`` side for graphs).
    k1, k2 : numpy.ndarray
        ``(N,)`` principal curvatures, ``k1 >= k2`` (1 / length units).
    d1, d2 : numpy.ndarray
        ``(N, 3)`` unit principal directions, ``d2 = normals x d1``.
    mean_curvature, gaussian_curvature : numpy.ndarray
        ``(N,)`` ``H = (k1 + k2)/2`` and ``K = k1 k2``.
    faces : numpy.ndarray or None
        ``(F, 3)`` int64 triangles, consistently oriented with ``normals`` (mesh variants).
    noisy_points : numpy.ndarray
        ``(N, 3)`` ``points`` plus the requested noise (a copy of ``points`` when noise = 0).
    noise_sigma : float
        Standard deviation of that noise (length units).
    uv : numpy.ndarray
        ``(N, 2)`` parameters of each point in the surface's parametrisation.
    name : str
        Surface name.
    """

    points: np.ndarray
    normals: np.ndarray
    k1: np.ndarray
    k2: np.ndarray
    d1: np.ndarray
    d2: np.ndarray
    mean_curvature: np.ndarray
    gaussian_curvature: np.ndarray
    faces: np.ndarray | None
    noisy_points: np.ndarray
    noise_sigma: float
    uv: np.ndarray
    name: str

    def __len__(self) -> int:
        return int(self.points.shape[0])


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _any_tangent(n: np.ndarray) -> np.ndarray:
    """Deterministic unit tangent orthogonal to each unit normal."""
    a = np.zeros_like(n)
    use_x = np.abs(n[:, 2]) > 0.9
    a[use_x, 0] = 1.0
    a[~use_x, 2] = 1.0
    return _unit(np.cross(a, n))


def _finish(name, pts, nrm, k1, k2, d1, uv, faces, noise, seed) -> AnalyticSample:
    noise = check_positive(noise, "noise", strict=False)
    d1 = _unit(d1)
    d2 = np.cross(nrm, d1)
    if len(pts):
        diag = float(np.linalg.norm(pts.max(0) - pts.min(0)))
    else:
        diag = 0.0
    sigma = noise * diag
    if sigma > 0:
        rng = np.random.default_rng([int(seed), 7919])
        noisy = pts + rng.normal(scale=sigma, size=pts.shape)
    else:
        noisy = pts.copy()
    return AnalyticSample(
        points=np.ascontiguousarray(pts, dtype=np.float64),
        normals=np.ascontiguousarray(nrm, dtype=np.float64),
        k1=np.asarray(k1, dtype=np.float64),
        k2=np.asarray(k2, dtype=np.float64),
        d1=np.ascontiguousarray(d1, dtype=np.float64),
        d2=np.ascontiguousarray(d2, dtype=np.float64),
        mean_curvature=0.5 * (np.asarray(k1) + np.asarray(k2)),
        gaussian_curvature=np.asarray(k1) * np.asarray(k2),
        faces=None if faces is None else np.ascontiguousarray(faces, dtype=np.int64),
        noisy_points=noisy,
        noise_sigma=float(sigma),
        uv=np.ascontiguousarray(uv, dtype=np.float64),
        name=name,
    )


def _check_n(n) -> int:
    return check_int(n, "n", low=0)


def _seed(seed) -> int:
    return check_int(seed, "seed", low=0)




def _rejection(rng, n, sample, density, dmax) -> np.ndarray:
    """Draw n samples from `sample(m)` accepted with probability density / dmax."""
    out = []
    got = 0
    while got < n:
        m = max(2 * (n - got), 64)
        s = sample(m)
        keep = rng.random(m) * dmax <= density(s)
        out.append(s[keep])
        got += int(keep.sum())
    return np.concatenate(out, 0)[:n]


# --------------------------------------------------------------------------------------------
# sphere, cylinder, torus, plane
# --------------------------------------------------------------------------------------------


def _sphere_from_normals(nrm, radius, faces, noise, seed) -> AnalyticSample:
    pts = radius * nrm
    k = np.full(len(nrm), -1.0 / radius)
    theta = np.arccos(np.clip(nrm[:, 2], -1, 1))
    phi = np.arctan2(nrm[:, 1], nrm[:, 0])
    return _finish("sphere", pts, nrm, k, k.copy(), _any_tangent(nrm),
                   np.stack([theta, phi], 1), faces, noise, seed)


def sphere(n: int = 2000, radius: float = 1.0, seed: int = 0, *, grid: bool = False,
           noise: float = 0.0) -> AnalyticSample:
    """Points on a sphere centred at the origin, outward normals.

    Parameters
    ----------
    n : int
        Number of points.
    radius : float
        Radius (> 0).
    seed : int
        Random seed (uniform-area random sampling).
    grid : bool
        Deterministic Fibonacci-spiral sampling instead of random.
    noise : float
        Noise standard deviation as a fraction of the bounding-box diagonal.

    Returns
    -------
    AnalyticSample
        ``k1 = k2 = H = -1/radius``, ``K = 1/radius^2``; ``uv`` = (polar, azimuth) angles.

    Raises
    ------
    ValueError, TypeError
        On a negative ``n``, non-positive ``radius`` or negative ``noise``.
    """
    n = _check_n(n)
    radius = check_positive(radius, "radius")
    seed = _seed(seed)
    if grid:
        i = np.arange(n) + 0.5
        zc = 1 - 2 * i / max(n, 1)
        ang = np.pi * (3 - np.sqrt(5.0)) * i
        rr = np.sqrt(np.clip(1 - zc * zc, 0, None))
        nrm = np.stack([rr * np.cos(ang), rr * np.sin(ang), zc], 1)
    else:
        rng = np.random.default_rng(seed)
        nrm = rng.normal(size=(n, 3))
        nrm = _unit(nrm)
    return _sphere_from_normals(nrm.reshape(-1, 3), radius, None, noise, seed)


def _cylinder_from_params(th, zz, radius, faces, noise, seed) -> AnalyticSample:
    nrm = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], 1)
    pts = np.stack([radius * np.cos(th), radius * np.sin(th), zz], 1)
    d1 = np.tile(np.array([0.0, 0.0, 1.0]), (len(th), 1))
    k1 = np.zeros(len(th))
    k2 = np.full(len(th), -1.0 / radius)
    return _finish("cylinder", pts, nrm, k1, k2, d1, np.stack([th, zz], 1), faces, noise, seed)


def cylinder(n: int = 2000, radius: float = 1.0, height: float = 2.0, seed: int = 0, *,
             grid: bool = False, noise: float = 0.0) -> AnalyticSample:
    """Points on an open cylinder of axis ``z``, ``|z| <= height/2``, outward normals.

    Parameters
    ----------
    n : int
        Number of points (about ``n`` with ``grid``).
    radius, height : float
        Radius and height (> 0).
    seed : int
        Random seed.
    grid : bool
        Structured (angle x height) sampling instead of random.
    noise : float
        Noise fraction of the bounding-box diagonal.

    Returns
    -------
    AnalyticSample
        ``k1 = 0`` along the axis (``d1 = +z``), ``k2 = -1/radius`` around it; ``uv`` =
        (angle, z).

    Raises
    ------
    ValueError, TypeError
        On bad sizes.
    """
    n = _check_n(n)
    radius = check_positive(radius, "radius")
    height = check_positive(height, "height")
    seed = _seed(seed)
    if grid:
        nt = max(3, int(round(np.sqrt(n * 2 * np.pi * radius / height))))
        nz = max(2, int(round(n / nt))) if n else 0
        th, zz = np.meshgrid(np.arange(nt) * 2 * np.pi / nt, np.linspace(-height / 2,
                             height / 2, nz), indexing="ij")
        th, zz = th.ravel(), zz.ravel()
    else:
        rng = np.random.default_rng(seed)
        th = rng.uniform(0, 2 * np.pi, n)
        zz = rng.uniform(-height / 2, height / 2, n)
    return _cylinder_from_params(th, zz, radius, None, noise, seed)


def _torus_from_params(u, v, R, r, faces, noise, seed) -> AnalyticSample:
    cu, su, cv, sv = np.cos(u), np.sin(u), np.cos(v), np.sin(v)
    pts = np.stack([(R + r * cv) * cu, (R + r * cv) * su, r * sv], 1)
    nrm = np.stack([cv * cu, cv * su, sv], 1)
    d1 = np.stack([-su, cu, np.zeros_like(u)], 1)
    k1 = -cv / (R + r * cv)
    k2 = np.full(len(u), -1.0 / r)
    return _finish("torus", pts, nrm, k1, k2, d1, np.stack([u, v], 1), faces, noise, seed)


def torus(n: int = 2000, R: float = 1.0, r: float = 0.3, seed: int = 0, *, grid: bool = False,
          noise: float = 0.0) -> AnalyticSample:
    """Points on a torus around the ``z`` axis (tube radius ``r`` < ring radius ``R``).

    Parameters
    ----------
    n : int
        Number of points (about ``n`` with ``grid``).
    R, r : float
        Ring and tube radii, ``0 < r < R``.
    seed : int
        Random seed (uniform-area sampling).
    grid : bool
        Structured sampling in the two angles.
    noise : float
        Noise fraction of the bounding-box diagonal.

    Returns
    -------
    AnalyticSample
        Outward normals; ``k1 = -cos v / (R + r cos v)`` along the parallels (``d1``),
        ``k2 = -1/r`` along the meridians; ``uv`` = (ring angle u, tube angle v).

    Raises
    ------
    ValueError, TypeError
        On bad sizes or ``r >= R``.
    """
    n = _check_n(n)
    R = check_positive(R, "R")
    r = check_positive(r, "r")
    if r >= R:
        raise ValueError(f"r: expected a tube radius smaller than R={R}, got {r}")
    seed = _seed(seed)
    if grid:
        nu = max(3, int(round(np.sqrt(n * R / r))))
        nv = max(3, int(round(n / nu))) if n else 0
        u, v = np.meshgrid(np.arange(nu) * 2 * np.pi / nu, np.arange(nv) * 2 * np.pi / max(nv, 1),
                           indexing="ij")
        u, v = u.ravel(), v.ravel()
    else:
        rng = np.random.default_rng(seed)
        v = _rejection(rng, n, lambda m: rng.uniform(0, 2 * np.pi, m),
                       lambda s: R + r * np.cos(s), R + r)
        u = rng.uniform(0, 2 * np.pi, n)
    return _torus_from_params(u, v, R, r, None, noise, seed)


# --------------------------------------------------------------------------------------------
# height graphs (Monge patch, plane, wavy sheet)
# --------------------------------------------------------------------------------------------


def _graph_quantities(x, y, f, fx, fy, fxx, fxy, fyy):
    """Exact quantities of z = f(x, y) by the classical height-field formulas."""
    w2 = 1 + fx * fx + fy * fy
    w = np.sqrt(w2)
    pts = np.stack([x, y, f], 1)
    nrm = np.stack([-fx, -fy, np.ones_like(x)], 1) / w[:, None]
    K = (fxx * fyy - fxy * fxy) / (w2 * w2)
    H = ((1 + fy * fy) * fxx - 2 * fx * fy * fxy + (1 + fx * fx) * fyy) / (2 * w2 * w)
    disc = np.sqrt(np.clip(H * H - K, 0, None))
    k1, k2 = H + disc, H - disc
    # Shape operator S = I^{-1} II in (x, y) coordinates; eigenvector of k1.
    E, F, G = 1 + fx * fx, fx * fy, 1 + fy * fy
    L, M, N = fxx / w, fxy / w, fyy / w
    det = E * G - F * F
    s11 = (G * L - F * M) / det
    s12 = (G * M - F * N) / det
    s21 = (E * M - F * L) / det
    s22 = (E * N - F * M) / det
    va = np.stack([s12, k1 - s11], 1)
    vb = np.stack([k1 - s22, s21], 1)
    na = np.linalg.norm(va, axis=1)
    nb = np.linalg.norm(vb, axis=1)
    vec = np.where((na >= nb)[:, None], va, vb)
    tiny = np.maximum(na, nb) <= 1e-12 * (1 + np.abs(H))
    vec[tiny] = [1.0, 0.0]
    d1 = vec[:, :1] * np.stack([np.ones_like(x), np.zeros_like(x), fx], 1) + vec[:, 1:] * \
        np.stack([np.zeros_like(x), np.ones_like(x), fy], 1)
    return pts, nrm, k1, k2, d1


def _as_tuple(vals, name: str, size: int) -> tuple[float, ...]:
    t = tuple(float(v) for v in np.asarray(vals, dtype=np.float64).ravel())
    if len(t) != size or not all(np.isfinite(t)):
        raise ValueError(f"{name}: expected {size} finite numbers, got {vals!r}")
    return t


def _monge_funcs(k1, k2, b, c):
    b0, b1, b2, b3 = b
    c0, c1, c2, c3, c4 = c

    def ev(x, y):
        f = (0.5 * (k1 * x**2 + k2 * y**2)
             + (b0 * x**3 + 3 * b1 * x**2 * y + 3 * b2 * x * y**2 + b3 * y**3) / 6
             + (c0 * x**4 + 4 * c1 * x**3 * y + 6 * c2 * x**2 * y**2 + 4 * c3 * x * y**3
                + c4 * y**4) / 24)
        fx = (k1 * x + (3 * b0 * x**2 + 6 * b1 * x * y + 3 * b2 * y**2) / 6
              + (4 * c0 * x**3 + 12 * c1 * x**2 * y + 12 * c2 * x * y**2 + 4 * c3 * y**3) / 24)
        fy = (k2 * y + (3 * b1 * x**2 + 6 * b2 * x * y + 3 * b3 * y**2) / 6
              + (4 * c1 * x**3 + 12 * c2 * x**2 * y + 12 * c3 * x * y**2 + 4 * c4 * y**3) / 24)
        fxx = k1 + (6 * b0 * x + 6 * b1 * y) / 6 + (12 * c0 * x**2 + 24 * c1 * x * y
                                                    + 12 * c2 * y**2) / 24
        fxy = (6 * b1 * x + 6 * b2 * y) / 6 + (12 * c1 * x**2 + 24 * c2 * x * y
                                               + 12 * c3 * y**2) / 24
        fyy = k2 + (6 * b2 * x + 6 * b3 * y) / 6 + (12 * c2 * x**2 + 24 * c3 * x * y
                                                    + 12 * c4 * y**2) / 24
        return f, fx, fy, fxx, fxy, fyy

    return ev


def _graph_sample(name, ev, n, extent, seed, grid, noise, faces_grid=False):
    n = _check_n(n)
    extent = check_positive(extent, "extent")
    seed = _seed(seed)
    faces = None
    if grid or faces_grid:
        m = max(2, int(round(np.sqrt(n))))
        g = np.linspace(-extent, extent, m)
        X, Y = np.meshgrid(g, g, indexing="ij")
        x, y = X.ravel(), Y.ravel()
        if faces_grid:
            faces = grid_faces(m, m, False, False)
    else:
        rng = np.random.default_rng(seed)
        probe = rng.uniform(-extent, extent, (4096, 2))
        _, fx, fy, *_ = ev(probe[:, 0], probe[:, 1])
        dmax = float(np.sqrt(1 + fx * fx + fy * fy).max()) * 1.05

        def density(s):
            _, gx, gy, *_ = ev(s[:, 0], s[:, 1])
            return np.sqrt(1 + gx * gx + gy * gy)

        xy = _rejection(rng, n, lambda k: rng.uniform(-extent, extent, (k, 2)), density, dmax)
        x, y = xy[:, 0], xy[:, 1]
    pts, nrm, k1, k2, d1 = _graph_quantities(x, y, *ev(x, y))
    return _finish(name, pts, nrm, k1, k2, d1, np.stack([x, y], 1), faces, noise, seed)


def monge_patch(n: int = 2000, k1: float = 1.0, k2: float = 0.5,
                b: Sequence[float] = (0.0, 0.0, 0.0, 0.0),
                c: Sequence[float] = (0.0, 0.0, 0.0, 0.0, 0.0), extent: float = 0.5,
                seed: int = 0, *, grid: bool = False, noise: float = 0.0) -> AnalyticSample:
    """Points on the Monge patch ``z = 1/2(k1 x^2 + k2 y^2) + cubic + quartic`` (CGAL form).

    ``z = 1/2 (k1 x^2 + k2 y^2) + 1/6 (b0 x^3 + 3 b1 x^2 y + 3 b2 x y^2 + b3 y^3)
    + 1/24 (c0 x^4 + 4 c1 x^3 y + 6 c2 x^2 y^2 + 4 c3 x y^3 + c4 y^4)`` over
    ``[-extent, extent]^2``.

    Parameters
    ----------
    n : int
        Number of points (``round(sqrt(n))^2`` with ``grid``).
    k1, k2 : float
        Principal curvatures at the origin.
    b : sequence of 4 floats
        Third-order Monge coefficients ``b0..b3``.
    c : sequence of 5 floats
        Fourth-order Monge coefficients ``c0..c4``.
    extent : float
        Half side of the square domain.
    seed : int
        Random seed (uniform-area sampling).
    grid : bool
        Regular grid instead of random sampling.
    noise : float
        Noise fraction of the bounding-box diagonal.

    Returns
    -------
    AnalyticSample
        Exact quantities at every point (``+z`` side normal); ``uv`` = (x, y).

    Raises
    ------
    ValueError, TypeError
        On bad sizes or coefficient counts.
    """
    b = _as_tuple(b, "b", 4)
    c = _as_tuple(c, "c", 5)
    k1, k2 = _as_tuple((k1, k2), "k1, k2", 2)
    return _graph_sample("monge_patch", _monge_funcs(k1, k2, b, c), n, extent, seed, grid, noise)


def plane(n: int = 2000, extent: float = 1.0, seed: int = 0, *, grid: bool = False,
          noise: float = 0.0) -> AnalyticSample:
    """Points on the plane ``z = 0`` over ``[-extent, extent]^2`` (normal ``+z``, zero curvature).

    Parameters
    ----------
    n : int
        Number of points.
    extent : float
        Half side of the square.
    seed : int
        Random seed.
    grid : bool
        Regular grid instead of random sampling.
    noise : float
        Noise fraction of the bounding-box diagonal.

    Returns
    -------
    AnalyticSample
        ``d1 = +x``, ``d2 = +y``.

    Raises
    ------
    ValueError, TypeError
        On bad sizes.
    """
    return _graph_sample("plane", _monge_funcs(0.0, 0.0, (0,) * 4, (0,) * 5), n, extent, seed,
                         grid, noise)


def _wavy_funcs(amp=0.1, a=3.0, bb=2.0):
    def ev(x, y):
        sx, cx, sy, cy = np.sin(a * x), np.cos(a * x), np.sin(bb * y), np.cos(bb * y)
        f = amp * sx * cy
        fx = amp * a * cx * cy
        fy = -amp * bb * sx * sy
        fxx = -amp * a * a * sx * cy
        fxy = -amp * a * bb * cx * sy
        fyy = -amp * bb * bb * sx * cy
        return f, fx, fy, fxx, fxy, fyy

    return ev


# --------------------------------------------------------------------------------------------
# meshes
# --------------------------------------------------------------------------------------------


def sphere_mesh(subdivisions: int = 3, radius: float = 1.0, *, noise: float = 0.0,
                seed: int = 0) -> AnalyticSample:
    """Icosphere (``trimesh.creation.icosphere``) with exact quantities at the vertices.

    Parameters
    ----------
    subdivisions : int
        Subdivision level (0..7; 3 gives 642 vertices).
    radius : float
        Radius.
    noise : float
        Noise fraction of the bounding-box diagonal.
    seed : int
        Noise seed.

    Returns
    -------
    AnalyticSample
        With outward-oriented ``faces``.

    Raises
    ------
    ValueError, TypeError
        On bad sizes.
    """
    import trimesh

    subdivisions = check_int(subdivisions, "subdivisions", low=0, high=7)
    radius = check_positive(radius, "radius")
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    nrm = _unit(np.asarray(m.vertices, dtype=np.float64))
    return _sphere_from_normals(nrm, radius, np.asarray(m.faces), noise, _seed(seed))


def cylinder_mesh(resolution: int = 32, radius: float = 1.0, height: float = 2.0, *,
                  noise: float = 0.0, seed: int = 0) -> AnalyticSample:
    """Open cylinder as a structured grid: ``resolution`` vertices around, welded seam.

    Parameters
    ----------
    resolution : int
        Vertices around the axis (>= 3); rings along the axis are spaced alike.
    radius, height : float
        Radius and height.
    noise : float
        Noise fraction of the bounding-box diagonal.
    seed : int
        Noise seed.

    Returns
    -------
    AnalyticSample
        With outward-oriented ``faces``.

    Raises
    ------
    ValueError, TypeError
        On bad sizes.
    """
    nt = check_int(resolution, "resolution", low=3)
    radius = check_positive(radius, "radius")
    height = check_positive(height, "height")
    nz = max(2, int(round(height / (2 * np.pi * radius / nt))) + 1)
    th, zz = np.meshgrid(np.arange(nt) * 2 * np.pi / nt, np.linspace(-height / 2, height / 2, nz),
                         indexing="ij")
    faces = grid_faces(nt, nz, True, False)
    return _cylinder_from_params(th.ravel(), zz.ravel(), radius, faces, noise, _seed(seed))


def torus_mesh(resolution: int = 48, R: float = 1.0, r: float = 0.3, *, noise: float = 0.0,
               seed: int = 0) -> AnalyticSample:
    """Torus as a structured periodic grid (``resolution`` vertices around the ring).

    Parameters
    ----------
    resolution : int
        Vertices around the ring (>= 3); the tube gets a proportional count (>= 3).
    R, r : float
        Ring and tube radii, ``0 < r < R``.
    noise : float
        Noise fraction of the bounding-box diagonal.
    seed : int
        Noise seed.

    Returns
    -------
    AnalyticSample
        With outward-oriented ``faces``.

    Raises
    ------
    ValueError, TypeError
        On bad sizes.
    """
    nu = check_int(resolution, "resolution", low=3)
    R = check_positive(R, "R")
    r = check_positive(r, "r")
    if r >= R:
        raise ValueError(f"r: expected a tube radius smaller than R={R}, got {r}")
    nv = max(3, int(round(nu * r / R)))
    u, v = np.meshgrid(np.arange(nu) * 2 * np.pi / nu, np.arange(nv) * 2 * np.pi / nv,
                       indexing="ij")
    faces = grid_faces(nu, nv, True, True)
    return _torus_from_params(u.ravel(), v.ravel(), R, r, faces, noise, _seed(seed))


def monge_patch_mesh(resolution: int = 32, k1: float = 1.0, k2: float = 0.5,
                     b: Sequence[float] = (0.0, 0.0, 0.0, 0.0),
                     c: Sequence[float] = (0.0, 0.0, 0.0, 0.0, 0.0), extent: float = 0.5, *,
                     noise: float = 0.0, seed: int = 0) -> AnalyticSample:
    """Monge patch (see :func:`monge_patch`) as a ``resolution x resolution`` grid mesh.

    Parameters
    ----------
    resolution : int
        Vertices per side (>= 2).
    k1, k2, b, c, extent
        As in :func:`monge_patch`.
    noise : float
        Noise fraction of the bounding-box diagonal.
    seed : int
        Noise seed.

    Returns
    -------
    AnalyticSample
        With ``+z``-oriented ``faces``.

    Raises
    ------
    ValueError, TypeError
        On bad sizes.
    """
    res = check_int(resolution, "resolution", low=2)
    b = _as_tuple(b, "b", 4)
    c = _as_tuple(c, "c", 5)
    k1, k2 = _as_tuple((k1, k2), "k1, k2", 2)
    return _graph_sample("monge_patch", _monge_funcs(k1, k2, b, c), res * res, extent, seed,
                         True, noise, faces_grid=True)


def plane_mesh(resolution: int = 32, extent: float = 1.0, *, noise: float = 0.0,
               seed: int = 0) -> AnalyticSample:
    """The plane ``z = 0`` as a ``resolution x resolution`` grid mesh.

    Parameters
    ----------
    resolution : int
        Vertices per side (>= 2).
    extent : float
        Half side of the square.
    noise : float
        Noise fraction of the bounding-box diagonal.
    seed : int
        Noise seed.

    Returns
    -------
    AnalyticSample
        With ``+z``-oriented ``faces``.

    Raises
    ------
    ValueError, TypeError
        On bad sizes.
    """
    res = check_int(resolution, "resolution", low=2)
    return _graph_sample("plane", _monge_funcs(0.0, 0.0, (0,) * 4, (0,) * 5), res * res, extent,
                         seed, True, noise, faces_grid=True)


def wavy_sheet_mesh(nu: int = 64, nv: int = 64, extent: float = 1.0, *, noise: float = 0.0,
                    seed: int = 0) -> AnalyticSample:
    """The sheet ``z = 0.1 sin(3x) cos(2y)`` over ``[-extent, extent]^2`` as an nu x nv grid.

    Parameters
    ----------
    nu, nv : int
        Vertices along x and y (>= 2).
    extent : float
        Half side of the square.
    noise : float
        Noise fraction of the bounding-box diagonal.
    seed : int
        Noise seed.

    Returns
    -------
    AnalyticSample
        With ``+z``-oriented ``faces``.

    Raises
    ------
    ValueError, TypeError
        On bad sizes.
    """
    nu = check_int(nu, "nu", low=2)
    nv = check_int(nv, "nv", low=2)
    extent = check_positive(extent, "extent")
    X, Y = np.meshgrid(np.linspace(-extent, extent, nu), np.linspace(-extent, extent, nv),
                       indexing="ij")
    x, y = X.ravel(), Y.ravel()
    pts, nrm, k1, k2, d1 = _graph_quantities(x, y, *_wavy_funcs()(x, y))
    return _finish("wavy_sheet", pts, nrm, k1, k2, d1, np.stack([x, y], 1),
                   grid_faces(nu, nv, False, False), noise, _seed(seed))


# =============================================================================================
# PolyFit training and test data (engineer P): the four synthetic patch families of the
# thesis (§5.5.1) and procedural garment-like meshes. Everything below is NumPy, seeded.
# =============================================================================================
