"""Consistent face winding of triangle meshes (:func:`orient_faces`).

Public names are re-exported by :mod:`polygeo.mesh`, their documented home.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import connected_components as _cc

from ..checks import check_shape
from ._common import as_output, checked_vertices, faces_array
from .topology import edge_faces

__all__ = [
    "OrientedFaces",
    "orient_faces",
]


class OrientedFaces(NamedTuple):
    """Result of :func:`orient_faces`.

    Attributes
    ----------
    faces : (F, 3) int64
        Faces with consistent winding inside each orientable component.
    flipped : (F,) bool
        Which input faces were reversed.
    component : (F,) int64
        Edge-connected component of each face (through manifold edges).
    n_components : int
        Number of face components.
    orientable : (C,) bool
        Whether each component admits a consistent orientation (a Moebius strip does not;
        its faces are then oriented as far as a spanning forest allows).
    """

    faces: Any
    flipped: Any
    component: Any
    n_components: int
    orientable: Any


def orient_faces(faces: Any, vertices: Any = None) -> OrientedFaces:
    """Make the winding of adjacent faces consistent, per edge-connected component.

    Two faces sharing a manifold edge are consistent when they traverse it in opposite
    directions. Orientation is solved globally as connected components of a doubled face
    graph (each face in two states), which is linear time and needs no traversal order.
    Non-manifold edges (fins, more than two faces) do not propagate orientation.

    Which of the two consistent windings a component gets: when ``vertices`` is given and the
    component is closed (no boundary edge), the one with positive signed volume (outward
    normals); otherwise the one that flips the fewest input faces.

    Parameters
    ----------
    faces : (F, 3) int array or tensor
        Triangles.
    vertices : (N, 3) float, optional
        Coordinates, used only to choose outward winding of closed components.

    Returns
    -------
    OrientedFaces
        Re-wound faces, flip flags, face components, their count and orientability.

    Raises
    ------
    ValueError
        Bad shapes or out-of-range indices.
    TypeError
        Non-integer faces.
    """
    f, numpy_in = faces_array(faces)
    nf = f.shape[0]
    if nf == 0:
        z = np.zeros(0, dtype=np.int64)
        return OrientedFaces(
            as_output(f, numpy_in), as_output(z.astype(bool), numpy_in), as_output(z, numpy_in), 0,
            as_output(z.astype(bool), numpy_in),
        )
    x = None
    if vertices is not None:
        vt, _ = checked_vertices(vertices)
        check_shape(vt, "vertices", ("N", 3))
        x = vt.detach().cpu().to(torch.float64).numpy()
        if f.max() >= x.shape[0]:
            raise ValueError(
                f"faces: expected vertex indices in [0, {x.shape[0] - 1}], got max {f.max()}"
            )
    he = f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    _, eid, count = edge_faces(f)
    face_of = np.repeat(np.arange(nf), 3)
    sel = (eid >= 0) & (count[np.maximum(eid, 0)] == 2)
    e_sel = eid[sel]
    order = np.argsort(e_sel, kind="stable")
    hs = np.flatnonzero(sel)[order]
    h0, h1 = hs[0::2], hs[1::2]
    fa, fb = face_of[h0], face_of[h1]
    same_dir = he[h0, 0] == he[h1, 0]  # traversed the same way: windings disagree
    not_self = fa != fb
    fa, fb, same_dir = fa[not_self], fb[not_self], same_dir[not_self]
    # node 2f = face f as given, 2f+1 = face f reversed
    # consistent pair: (a as given ~ b as given); inconsistent: (a as given ~ b reversed)
    a, a2 = 2 * fa, 2 * fa + 1
    b = np.where(same_dir, 2 * fb + 1, 2 * fb)
    b2 = np.where(same_dir, 2 * fb, 2 * fb + 1)
    rows = np.concatenate([a, a2])
    cols = np.concatenate([b, b2])
    g = sp.coo_matrix((np.ones(rows.size), (rows, cols)), shape=(2 * nf, 2 * nf))
    _, lab = _cc(g, directed=False)
    lp, lm = lab[0::2], lab[1::2]
    orientable_face = lp != lm
    flipped = lp > lm
    # face components: undirected adjacency through manifold edges
    gf = sp.coo_matrix((np.ones(fa.size), (fa, fb)), shape=(nf, nf))
    ncomp, comp = _cc(gf, directed=False)
    orientable = np.ones(ncomp, dtype=bool)
    np.logical_and.at(orientable, comp, orientable_face)
    # non-orientable components: orient along a BFS spanning tree instead
    for c in np.flatnonzero(~orientable):
        flipped[comp == c] = _spanning_flip(np.flatnonzero(comp == c), fa, fb, same_dir)
    out = f.copy()
    out[flipped] = out[flipped][:, ::-1]
    # choose the global winding of each component
    closed = np.ones(ncomp, dtype=bool)
    bnd = (eid >= 0) & (count[np.maximum(eid, 0)] == 1)
    closed[np.unique(comp[face_of[bnd]])] = False
    closed[np.unique(comp[face_of[(eid >= 0) & (count[np.maximum(eid, 0)] > 2)]])] = False
    invert = np.zeros(ncomp, dtype=bool)
    if x is not None:
        p0, p1, p2 = x[out[:, 0]], x[out[:, 1]], x[out[:, 2]]
        vol = np.einsum("ij,ij->i", p0, np.cross(p1, p2)) / 6.0
        vol = np.where(np.isfinite(vol), vol, 0.0)
        cvol = np.bincount(comp, weights=vol, minlength=ncomp)
        use_vol = closed & orientable & (cvol != 0)
        invert[use_vol] = cvol[use_vol] < 0
    else:
        use_vol = np.zeros(ncomp, dtype=bool)
    nflip = np.bincount(comp, weights=flipped.astype(float), minlength=ncomp)
    size = np.bincount(comp, minlength=ncomp)
    by_count = ~use_vol & (nflip > size / 2)
    invert |= by_count
    inv_f = invert[comp]
    out[inv_f] = out[inv_f][:, ::-1]
    flipped = flipped ^ inv_f
    return OrientedFaces(
        as_output(out, numpy_in),
        as_output(flipped, numpy_in),
        as_output(comp.astype(np.int64), numpy_in),
        int(ncomp),
        as_output(orientable, numpy_in),
    )


def _spanning_flip(
    members: np.ndarray, fa: np.ndarray, fb: np.ndarray, same_dir: np.ndarray
) -> np.ndarray:
    """Flip flags along a breadth-first spanning tree (non-orientable component)."""
    from scipy.sparse.csgraph import breadth_first_order

    nf = int(max(fa.max(initial=0), fb.max(initial=0), members.max())) + 1
    w = np.where(same_dir, 2.0, 1.0)  # 2: flip relative to parent, 1: keep
    g = sp.coo_matrix((np.concatenate([w, w]), (np.concatenate([fa, fb]),
                                                np.concatenate([fb, fa]))), shape=(nf, nf))
    g = g.tocsr()
    order, pred = breadth_first_order(g, members[0], directed=False)
    flip = np.zeros(nf, dtype=bool)
    for node in order[1:]:
        p = pred[node]
        flip[node] = flip[p] ^ (g[p, node] == 2.0)
    return flip[members]
