"""The remeshing and fitting stages of garment templates (:func:`draping.garments.make_garment`).

- **Remeshing** (:func:`remesh`): even triangles at a requested vertex count by approximate
  centroidal Voronoi clustering (``pyacvd``), cleaned to one consistently wound manifold piece
  (:func:`make_manifold`: degenerate and non-manifold faces and ears dropped, the largest
  piece kept, small clustering holes filled).
- **Fitting** (:func:`fit_to_body`): Laplacian smoothing (rims along themselves, Taubin)
  alternating with projection to a clearance off the body (:func:`project_out`, less room in
  the body's hollows: :func:`room`), with untangling rounds where the garment crosses itself;
  for garments with legs, the folds and slivers left at the leg hems smoothed out locally
  (:func:`smooth_defects`).

Meshes are NumPy ``(V, 3)`` float64 vertices (any length unit: every length is relative to
the ``clearance`` given) and ``(F, 3)`` int64 faces. ``query(points) -> (signed_distance,
closest, normal)`` answers for the rest body. Edges, boundary edges (directed along their
face's winding), adjacency, orientation and vertex normals come from :mod:`polygeo.mesh`.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import scipy.sparse as sp

from draping.garment_checks import crossing_pairs, face_edges
from polygeo.mesh import (
    boundary_edges,
    dihedral_angles,
    edges,
    orient_faces,
    vertex_adjacency,
    vertex_normals,
)

__all__ = [
    "boundary_loops",
    "largest_component",
    "remesh",
    "make_manifold",
    "fill_small_holes",
    "orient",
    "mean_operators",
    "room",
    "project_out",
    "fit_to_body",
    "smooth_displacement",
    "fold_faces",
    "relax_folds",
    "MAX_HINGE_DEG",
    "MIN_CORNER_DEG",
    "defect_faces",
    "smooth_defects",
    "wind_outward",
]


def largest_component(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The connected piece with most faces, unreferenced vertices removed."""
    from scipy.sparse.csgraph import connected_components

    if len(f) == 0:
        raise ValueError("garment: the selected body region is empty")
    _, lab = connected_components(vertex_adjacency(f, len(v)), directed=False)
    flab = lab[f[:, 0]]
    keep = f[flab == np.bincount(flab).argmax()]
    used = np.unique(keep)
    remap = np.full(len(v), -1)
    remap[used] = np.arange(len(used))
    return v[used], remap[keep]



def boundary_loops(f: np.ndarray) -> list[np.ndarray]:
    """Boundary loops as ordered vertex lists."""
    be = boundary_edges(f)
    nxt = dict(zip(be[:, 0].tolist(), be[:, 1].tolist()))
    loops, seen = [], set()
    for s in be[:, 0].tolist():
        if s in seen:
            continue
        loop, u = [], s
        while u not in seen and u in nxt:
            seen.add(u)
            loop.append(u)
            u = nxt[u]
        loops.append(np.array(loop))
    return loops



# ------------------------------------------------------------------------------ remeshing



def remesh(
    v: np.ndarray, f: np.ndarray, n_vertices: int, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """Even triangles by approximate centroidal Voronoi clustering (pyacvd), then cleaned."""
    import pyacvd
    import pyvista as pv

    level = max(0, int(math.ceil(math.log(max(8.0 * n_vertices / len(f), 1.0), 4))))
    mesh = pv.PolyData(v, np.hstack([np.full((len(f), 1), 3), f]).ravel())
    state = np.random.get_state()  # noqa: NPY002 - pyacvd draws its seeds from NumPy's global
    try:  # state: seed it here and give the caller's state back afterwards
        with warnings.catch_warnings():  # pyacvd uses a deprecated pyvista accessor
            warnings.filterwarnings("ignore", module="pyacvd")
            clus = pyacvd.Clustering(mesh)
            if level:
                clus.subdivide(level)
            np.random.seed(seed)  # noqa: NPY002
            clus.cluster(n_vertices)
            out = clus.create_mesh()
    finally:
        np.random.set_state(state)  # noqa: NPY002
    rv = np.asarray(out.points, dtype=np.float64)
    rf = np.asarray(out.faces).reshape(-1, 4)[:, 1:].astype(np.int64)
    return make_manifold(rv, rf)


def make_manifold(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop degenerate faces and faces on edges shared by more than two, keep one piece."""
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])]
    for _ in range(10):
        key = np.sort(face_edges(f), 1)
        _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        over = cnt[inv.ravel()].reshape(3, -1).max(0) > 2  # faces on a non-manifold edge
        if not over.any():
            break
        f = f[~over]
    for _ in range(10):
        # Ears (triangles with two rim edges) would flatten to zero area once the rim is
        # smoothed along itself: cut them off.
        key = np.sort(face_edges(f), 1)
        _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        ears = (cnt[inv.ravel()].reshape(3, -1) == 1).sum(0) >= 2
        if not ears.any():
            break
        f = f[~ears]
    v, f = largest_component(v, f)
    v, f = orient(v, f)
    return fill_small_holes(v, f)


def fill_small_holes(v: np.ndarray, f: np.ndarray, max_rim: int = 6, max_ratio: float = 0.25):
    """Close the small holes that clustering leaves (not the garment's openings).

    A hole is a rim of at most ``max_rim`` vertices whose perimeter is under ``max_ratio``
    of the longest rim's (the openings are far longer). Each is closed by a fan around a new
    vertex at its centroid, wound like its faces.
    """
    loops = boundary_loops(f)
    if not loops:
        return v, f
    perimeter = [float(np.linalg.norm(v[lp] - v[np.roll(lp, -1)], axis=1).sum()) for lp in loops]
    longest = max(perimeter)
    new_v, new_f = [v], [f]
    n = len(v)
    for loop, per in zip(loops, perimeter):
        if len(loop) > max_rim or per >= max_ratio * longest:
            continue
        c = n
        n += 1
        new_v.append(v[loop].mean(0, keepdims=True))
        # A rim edge a->b runs along its face's winding; the filling face runs b->a.
        new_f.append(np.stack([np.roll(loop, -1), loop, np.full(len(loop), c)], 1))
    return np.vstack(new_v), np.vstack(new_f)


def orient(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Consistent winding (BFS over faces), normals pointing away from the centroid side."""
    f = np.asarray(orient_faces(f).faces, dtype=np.int64)
    return v, f


# -------------------------------------------------------------------------------- fitting


def mean_operators(f: np.ndarray, n: int) -> tuple[sp.csr_matrix, np.ndarray]:
    """Neighbour-mean operator in which rim vertices average their two rim neighbours only.

    Returns the ``(n, n)`` operator and the rim mask ``(n,)``.
    """
    be = boundary_edges(f)
    rim = np.zeros(n, bool)
    rim[be.ravel()] = True
    along = sp.csr_matrix(
        (np.ones(2 * len(be)), (np.r_[be[:, 0], be[:, 1]], np.r_[be[:, 1], be[:, 0]])), (n, n)
    )
    along.data[:] = 1.0
    adj = vertex_adjacency(f, n)
    rows = sp.diags((~rim).astype(float)) @ adj + sp.diags(rim.astype(float)) @ along
    deg = np.asarray(rows.sum(1)).ravel()
    return sp.csr_matrix(sp.diags(1.0 / np.maximum(deg, 1.0)) @ rows), rim


def room(v: np.ndarray, query, clearance) -> np.ndarray:
    """Per-vertex clearance: ``clearance`` where there is room, less in the body's hollows.

    ``clearance`` is one distance or one per vertex ``(V,)`` (a snug waistband).

    A probe ``clearance`` off the skin at the closest body point is nearer than that to
    another part of the body where the gap across (armpit, crotch) is under twice the
    clearance; the gap is then about ``distance + clearance`` and a vertex keeps to 40 % of
    it, so that the garment's two sides of the hollow stay apart.
    """
    c = np.broadcast_to(np.asarray(clearance, dtype=np.float64), (len(v),))
    _, closest, normal = query(v)
    probe = np.abs(query(closest + c[:, None] * normal)[0])
    gap = probe + c
    return np.clip(0.4 * gap, 0.1 * c, c)


def project_out(v: np.ndarray, query, room: np.ndarray) -> np.ndarray:
    """Move vertices nearer to the body than ``room`` (V,) out to that distance.

    Along the direction from the closest body point (the distance's gradient), not the
    closest triangle's normal, so that vertices over a ridge of the body spread over an arc
    instead of collapsing onto one point.
    """
    d, closest, normal = query(v)
    low = d < room
    if not low.any():
        return v
    away = v[low] - closest[low]
    length = np.linalg.norm(away, axis=1, keepdims=True)
    sign = np.where(d[low] < 0, -1.0, 1.0)[:, None]
    direction = np.where(
        length > 1e-9 * room[low, None], sign * away / np.maximum(length, 1e-300), normal[low]
    )
    v = v.copy()
    v[low] = closest[low] + room[low, None] * direction
    return v


def fit_to_body(v: np.ndarray, f: np.ndarray, query, clearance,
                iterations: int) -> np.ndarray:
    """Laplacian smoothing alternating with projection to the clearance off the body.

    ``clearance`` is one distance or one per vertex ``(V,)``.

    Where the garment then crosses itself (two sides of a hollow), the vertices around the
    crossing get half the room and the rounds go on, at most eight times.
    """
    mean, rim = mean_operators(f, len(v))
    space = room(v, query, clearance)
    adj = vertex_adjacency(f, len(v))
    for _ in range(8):
        for _ in range(iterations):
            v = v + 0.5 * (mean @ v - v)  # shrinks: bridges the body's hollows
            v[rim] -= 0.53 * (mean @ v - v)[rim]  # Taubin on the rims: they keep their size
            v = project_out(v, query, space)
        pairs = crossing_pairs(v, f)
        if len(pairs) == 0:
            break
        near = np.zeros(len(v), bool)
        near[f[pairs.ravel()].ravel()] = True
        for _ in range(2):  # and their neighbours, twice removed
            near |= (adj @ near.astype(float)) > 0
        floor = 0.05 * np.broadcast_to(np.asarray(clearance, dtype=np.float64), (len(v),))
        space[near] = np.maximum(0.5 * space[near], floor[near])
    return v


# ------------------------------------------------------------ carrying to another body


def smooth_displacement(u: np.ndarray, f: np.ndarray, v: np.ndarray,
                        distance: np.ndarray) -> np.ndarray:
    """Screened smoothing of a displacement field over the garment's edges.

    A displacement carried from the body to the garment (each garment vertex takes the
    displacement of the body vertices nearest to it) is smooth where the garment lies on the
    skin but jumps where the nearest body vertices switch from one body part to another
    across a gap (between the legs, under the arms): carried as it is, it folds the garment
    there. It is replaced by the minimiser of

        sum_i c_i |u_i - u0_i|^2 + sum_(i,j) edge |u_i - u_j|^2,
        c_i = (l / max(distance_i, l))^2,

    with ``l`` the mean edge length: a vertex on the skin (``distance <= l``) keeps its own
    displacement up to about one edge of smoothing, one hanging ``k`` edge lengths off the
    body has a smoothing length of about ``k`` edges (the distance over which its nearest
    body vertex is ambiguous). Scale-free: only ratios of lengths enter.

    Parameters
    ----------
    u : (V, 3) float64
        Carried displacement (any length unit).
    f : (F, 3) int64
        Garment faces.
    v : (V, 3) float64
        Garment vertices (for the mean edge length; same unit).
    distance : (V,) float64
        Distance of each garment vertex to the body vertices its displacement came from.

    Returns
    -------
    (V, 3) float64
        Smoothed displacement.
    """
    import scipy.sparse.linalg as spl

    n = len(v)
    e = edges(f)
    ell = float(np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1).mean())
    adj = vertex_adjacency(f, n).astype(np.float64)
    adj.data[:] = 1.0
    lap = sp.diags(np.asarray(adj.sum(1)).ravel()) - adj  # graph Laplacian (V, V)
    c = (ell / np.maximum(np.asarray(distance, dtype=np.float64), ell)) ** 2
    return spl.spsolve(sp.csc_matrix(sp.diags(c) + lap), c[:, None] * u)


def _min_angles(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Smallest corner angle of each face (degrees)."""
    t = v[f]
    out = np.full(len(f), 180.0)
    for c in range(3):
        a, b = t[:, (c + 1) % 3] - t[:, c], t[:, (c + 2) % 3] - t[:, c]
        ang = np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("ij,ij->i", a, b))
        out = np.minimum(out, np.degrees(ang))
    return out


def fold_faces(v: np.ndarray, f: np.ndarray, reference: np.ndarray, max_fold: float = 90.0,
               min_angle: float = 5.0) -> np.ndarray:
    """Faces folded or squashed by a deformation of ``reference`` into ``v``.

    A face is flagged when one of its hinges bends more than ``max_fold`` degrees and 30
    degrees more than in ``reference``, or when its smallest corner angle is under
    ``min_angle`` degrees and under half of its reference value (defects the reference
    already has are not flagged).

    Returns
    -------
    (F,) bool
    """
    h = dihedral_angles(reference, f)
    a0 = np.degrees(np.abs(np.asarray(h.angle)))
    a = np.degrees(np.abs(np.asarray(dihedral_angles(v, f, hinges=h).angle)))
    bad = np.zeros(len(f), bool)
    hf = np.asarray(h.faces)
    bad[hf[(a > max_fold) & (a > a0 + 30.0)].ravel()] = True
    m0, m = _min_angles(reference, f), _min_angles(v, f)
    return bad | ((m < min_angle) & (m < 0.5 * m0))


def _relax_flagged(v: np.ndarray, f: np.ndarray, query, flagged, space: np.ndarray, *,
                   keep_rest_out: bool, rounds: int, iterations: int) -> np.ndarray:
    """Local smoothing of flagged faces (the loop of relax_folds and smooth_defects).

    Each round, the vertices of the faces ``flagged(v)`` (F,) bool marks, and a neighbourhood
    that grows by one ring per round (from two), get ``iterations`` Laplacian steps (rims along
    themselves), each followed by the projection of that region out to ``space`` (V,) off the
    body; with ``keep_rest_out`` the other vertices are kept out of the body, otherwise they do
    not move. Stops when no face is flagged or after ``rounds`` rounds.
    """
    mean, _ = mean_operators(f, len(v))
    adj = vertex_adjacency(f, len(v))
    region = np.zeros(len(v), bool)
    for r in range(rounds):
        bad = flagged(v)
        if not bad.any():
            break
        near = np.zeros(len(v), bool)
        near[f[bad].ravel()] = True
        for _ in range(2 + r):
            near |= (adj @ near.astype(float)) > 0
        region |= near
        for _ in range(iterations):
            v = v.copy()
            v[region] += 0.5 * (mean @ v - v)[region]
            if keep_rest_out:
                v = project_out(v, query, np.where(region, space, 0.0))
            else:
                v = np.where(region[:, None], project_out(v, query, space), v)
    return v


def relax_folds(v: np.ndarray, f: np.ndarray, query, room: np.ndarray, reference: np.ndarray,
                rounds: int = 10, iterations: int = 10) -> np.ndarray:
    """Smooth out folds and slivers (:func:`fold_faces`) left by a fit, locally.

    Each round, the vertices of flagged faces and a neighbourhood that grows by one ring per
    round (from two) get ``iterations`` Laplacian steps (rims along themselves), each followed
    by a projection to half the ``room`` (V,) off the body: in a sharp hollow (a small body's
    armpit) the full clearance is itself what creases the garment. Vertices outside the
    region do not move (unless inside the body). Stops when no face is flagged or after
    ``rounds`` rounds; returns the ``(V, 3)`` vertices.
    """
    return _relax_flagged(v, f, query, lambda x: fold_faces(x, f, reference), 0.5 * room,
                          keep_rest_out=True, rounds=rounds, iterations=iterations)


#: Template quality a generated garment with legs is held to (:func:`smooth_defects`):
#: the largest dihedral angle between neighbouring triangles (degrees; a sharper hinge is a
#: fold) and the smallest corner angle (degrees; a thinner triangle is a sliver).
MAX_HINGE_DEG = 60.0
MIN_CORNER_DEG = 10.0


def defect_faces(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """``(F,)`` bool: faces on a fold or a sliver (:data:`MAX_HINGE_DEG`, `MIN_CORNER_DEG`)."""
    h = dihedral_angles(v, f)
    bad = np.zeros(len(f), bool)
    sharp = np.degrees(np.abs(np.asarray(h.angle))) > MAX_HINGE_DEG
    bad[np.asarray(h.faces)[sharp].ravel()] = True
    return bad | (_min_angles(v, f) < MIN_CORNER_DEG)


def smooth_defects(v: np.ndarray, f: np.ndarray, query, space: np.ndarray,
                    rounds: int = 10, iterations: int = 10) -> np.ndarray:
    """Smooth out the folds and slivers a legged template's fit leaves, locally.

    The remeshed pants' leg hems (the body is thin and densely meshed at the ankle) came out
    with a rim vertex folded back over its neighbours: a 163 degree hinge and a 0.6 degree
    sliver on the shipped pants before this step. Each round, the vertices of
    :func:`defect_faces` and a neighbourhood growing by one ring per round (from two) get
    ``iterations`` Laplacian steps (rims along themselves), each followed by the projection
    out to ``space`` (V,) off the body; the rest do not move. Stops when no face is flagged
    or after ``rounds`` rounds.
    """
    return _relax_flagged(v, f, query, lambda x: defect_faces(x, f), space,
                          keep_rest_out=False, rounds=rounds, iterations=iterations)


def wind_outward(v: np.ndarray, f: np.ndarray, query) -> np.ndarray:
    """Wind ``f`` so that normals point away from the body."""
    _, closest, _ = query(v)
    n = vertex_normals(v, f).normals
    if np.einsum("ij,ij->i", n, v - closest).mean() < 0:
        f = f[:, ::-1].copy()
    return f
