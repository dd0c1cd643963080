"""Per-edge and per-face geometry of triangle meshes.

Edge lengths and the edge-length (inextensibility) energy, face areas and normals, vertex
normals, dihedral angles and cotangent weights.

Torch-differentiable with respect to the vertices, a leading batch of vertex sets
``(..., N, 3)`` sharing one connectivity, never NaN: degenerate faces come back with a ``valid``
mask and zero normals (and zero gradients). Public names are re-exported by
:mod:`polygeo.mesh`, their documented home.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import torch

from ..checks import as_tensor, check_choice, check_finite, check_positive, check_shape, to_like
from ._common import (
    as_output,
    checked_vertices,
    corners,
    faces_array,
    faces_tensor,
    safe_norm,
    tiny_eps,
)
from .topology import edge_faces

__all__ = [
    "FaceNormals",
    "VertexNormals",
    "Dihedral",
    "CotanWeights",
    "edge_lengths",
    "edge_length_energy",
    "face_areas",
    "face_normals",
    "vertex_normals",
    "dihedral_angles",
    "cotangent_weights",
]


class FaceNormals(NamedTuple):
    """Unit face normals (right-hand rule on the winding) and a validity mask.

    Attributes
    ----------
    normals : (..., F, 3) float
        Unit normals; zero vectors for degenerate (zero-area) faces.
    valid : (..., F) bool
        False for degenerate faces.
    """

    normals: Any
    valid: Any


class VertexNormals(NamedTuple):
    """Unit vertex normals and a validity mask.

    Attributes
    ----------
    normals : (..., N, 3) float
        Unit normals; zero vectors where undefined.
    valid : (..., N) bool
        False for unreferenced vertices and where the weighted sum of face normals vanishes.
    """

    normals: Any
    valid: Any


class Dihedral(NamedTuple):
    """Signed dihedral (bending) angles at interior manifold edges.

    Attributes
    ----------
    edges : (E, 2) int64
        The edge ``(a, b)`` in the winding order of ``faces[:, 0]``.
    faces : (E, 2) int64
        The two faces sharing the edge.
    angle : (..., E) float
        Angle in radians between the two face normals, in ``(-pi, pi]``: 0 for a flat
        hinge, positive where the surface is convex with respect to its normals (bends away
        from the normal side, as an outward-oriented sphere does), negative where concave.
    valid : (..., E) bool
        False when either face is degenerate (angle 0 then).
    """

    edges: Any
    faces: Any
    angle: Any
    valid: Any


class CotanWeights(NamedTuple):
    """Cotangent weights of the unique undirected edges.

    Attributes
    ----------
    edges : (E, 2) int64
        Unique undirected edges ``(i, j)``, ``i < j`` (as :func:`edges`).
    weight : (..., E) float
        ``(cot alpha + cot beta) / 2`` summed over the faces opposite to each edge (one term
        at a boundary edge). Degenerate faces contribute 0.
    """

    edges: Any
    weight: Any


def edge_lengths(vertices: Any, edge_index: Any) -> Any:
    """Lengths of edges, differentiable.

    Parameters
    ----------
    vertices : (..., N, 3) float
        Vertex coordinates.
    edge_index : (E, 2) int
        Vertex pairs (e.g. from :func:`edges`).

    Returns
    -------
    (..., E) float
        Euclidean lengths in the unit of ``vertices``. The gradient of a zero-length edge is
        zero (not NaN).

    Raises
    ------
    ValueError
        Bad shapes or out-of-range indices.
    TypeError
        Non-numeric input.
    """
    v, numpy_in = checked_vertices(vertices)
    t = as_tensor(edge_index, "edge_index", floating=False)
    if t.is_floating_point():
        raise TypeError(f"edge_index: expected an integer array, got dtype {t.dtype}")
    check_shape(t, "edge_index", ("E", 2))
    e = t.to(torch.int64)
    n = v.shape[-2]
    if e.numel() and (int(e.min()) < 0 or int(e.max()) >= n):
        raise ValueError(f"edge_index: expected indices in [0, {n - 1}], got {int(e.max())}")
    d = v[..., e[:, 1], :] - v[..., e[:, 0], :]
    length, _ = safe_norm(d, tiny_eps(v))
    return to_like(length, numpy_in)


def edge_length_energy(vertices: Any, edge_index: Any, rest_lengths: Any,
                       scale: float = 1.0) -> Any:
    """Inextensibility energy: squared changes of edge lengths, summed, differentiable.

    ``E = sum_e (l_e / scale - r_e / scale)^2`` with ``l_e`` the edge lengths of
    ``vertices`` and ``r_e`` their rest lengths. ``scale`` (a length of the surface, e.g. its
    radius) makes the energy independent of the unit of the input; for a uniform stretch
    ``l = (1 + eps) r`` it is ``eps^2 sum_e (r_e / scale)^2``.

    Parameters
    ----------
    vertices : (..., N, 3) float
        Vertex coordinates (any length unit), a leading batch sharing the edges.
    edge_index : (E, 2) int
        Vertex pairs (e.g. from :func:`edges`).
    rest_lengths : (E,) float
        Rest length of each edge, >= 0, same unit as ``vertices``; compared in the dtype of
        ``vertices`` after division by ``scale`` in its own dtype (keep it float64).
    scale : float
        Normalising length (> 0), same unit as ``vertices``.

    Returns
    -------
    (...,) float
        The energy, dimensionless (lengths in units of ``scale``); NumPy when ``vertices``
        is NumPy. The gradient of a zero-length edge is zero (not NaN).

    Raises
    ------
    ValueError
        Bad shapes, out-of-range indices, a ``rest_lengths`` that is not ``(E,)``, finite and
        >= 0, or a ``scale`` that is not finite and > 0.
    TypeError
        Non-numeric input.
    """
    v, numpy_in = checked_vertices(vertices)
    scale = check_positive(scale, "scale")
    lengths = edge_lengths(v, edge_index) / scale  # (..., E)
    r = as_tensor(rest_lengths, "rest_lengths")
    check_shape(r, "rest_lengths", (lengths.shape[-1],))
    check_finite(r, "rest_lengths")
    if r.numel() and float(r.min()) < 0:
        raise ValueError(f"rest_lengths: expected values >= 0, got {float(r.min())}")
    energy = (lengths - (r / scale).to(lengths.device, lengths.dtype)).pow(2).sum(-1)
    return to_like(energy, numpy_in)


def _face_cross(v: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
    p0, p1, p2 = corners(v, f)
    return torch.linalg.cross(p1 - p0, p2 - p0, dim=-1)


def face_areas(vertices: Any, faces: Any) -> Any:
    """Triangle areas, differentiable.

    Parameters
    ----------
    vertices : (..., N, 3) float
        Vertex coordinates.
    faces : (F, 3) int
        Triangles.

    Returns
    -------
    (..., F) float
        Areas in squared units of ``vertices``; 0 for degenerate faces (zero gradient).

    Raises
    ------
    ValueError
        Bad shapes or out-of-range indices.
    TypeError
        Non-numeric input.
    """
    v, numpy_in = checked_vertices(vertices)
    f = faces_tensor(faces, v.shape[-2])
    n2, _ = safe_norm(_face_cross(v, f), tiny_eps(v))
    return to_like(0.5 * n2, numpy_in)


def face_normals(vertices: Any, faces: Any) -> FaceNormals:
    """Unit face normals by the right-hand rule, with a validity mask.

    Parameters
    ----------
    vertices : (..., N, 3) float
        Vertex coordinates.
    faces : (F, 3) int
        Triangles.

    Returns
    -------
    FaceNormals
        ``normals (..., F, 3)`` (zero for degenerate faces, never NaN) and ``valid (..., F)``.

    Raises
    ------
    ValueError
        Bad shapes or out-of-range indices.
    TypeError
        Non-numeric input.
    """
    v, numpy_in = checked_vertices(vertices)
    f = faces_tensor(faces, v.shape[-2])
    c = _face_cross(v, f)
    n, ok = _face_unit(c, v)
    return FaceNormals(to_like(n, numpy_in), to_like(ok, numpy_in))


def _face_unit(c: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    # relative threshold: a face is degenerate when |cross| is tiny against its edge scale
    norm, ok = safe_norm(c, tiny_eps(v))
    ok = ok & torch.isfinite(norm)
    safe = torch.where(ok, norm, torch.ones_like(norm))
    n = torch.where(ok[..., None], c / safe[..., None], torch.zeros_like(c))
    return n, ok


def vertex_normals(vertices: Any, faces: Any, weighting: str = "area") -> VertexNormals:
    """Unit vertex normals as weighted sums of incident face normals.

    Parameters
    ----------
    vertices : (..., N, 3) float
        Vertex coordinates.
    faces : (F, 3) int
        Triangles (their winding sets the side of the normals).
    weighting : {"area", "angle", "uniform"}
        Face weights: the face area, the corner angle at the vertex (Thuermer-Wuethrich) or 1.

    Returns
    -------
    VertexNormals
        ``normals (..., N, 3)`` and ``valid (..., N)`` (False for unreferenced vertices or
        cancelling normals; the normal is zero there).

    Raises
    ------
    ValueError
        Bad shapes, indices or weighting.
    TypeError
        Non-numeric input.
    """
    check_choice(weighting, "weighting", ("area", "angle", "uniform"))
    v, numpy_in = checked_vertices(vertices)
    f = faces_tensor(faces, v.shape[-2])
    c = _face_cross(v, f)
    fn, fok = _face_unit(c, v)
    batch = v.shape[:-2]
    acc = torch.zeros((*batch, v.shape[-2], 3), dtype=v.dtype)
    for corner in range(3):
        if weighting == "area":
            area = 0.5 * safe_norm(c, tiny_eps(v))[0]
            w = torch.where(fok, area, torch.zeros_like(area))
        elif weighting == "uniform":
            w = fok.to(v.dtype)
        else:
            ang = _corner_angle(v, f, corner)
            w = torch.where(fok, ang, torch.zeros_like(ang))
        contrib = fn * w[..., None]
        idx = f[:, corner]
        acc = acc.index_add(-2, idx, contrib)
    n, ok = _face_unit(acc, v)
    return VertexNormals(to_like(n, numpy_in), to_like(ok, numpy_in))


def _corner_angle(v: torch.Tensor, f: torch.Tensor, corner: int) -> torch.Tensor:
    p = v[..., f[:, corner], :]
    a = v[..., f[:, (corner + 1) % 3], :] - p
    b = v[..., f[:, (corner + 2) % 3], :] - p
    cr, _ = safe_norm(torch.linalg.cross(a, b, dim=-1), tiny_eps(v))
    return torch.atan2(cr, (a * b).sum(-1))


def dihedral_angles(vertices: Any, faces: Any, *, hinges: Dihedral | None = None) -> Dihedral:
    """Signed dihedral (bending) angles at interior manifold edges.

    Parameters
    ----------
    vertices : (..., N, 3) float
        Vertex coordinates.
    faces : (F, 3) int
        Consistently wound triangles (see :func:`orient_faces`).
    hinges : Dihedral, optional
        A previous result for the same ``faces``: its ``edges`` and ``faces`` are reused and
        the hinge topology is not searched again (solvers evaluate the angles many times on
        one connectivity). Its ``angle`` and ``valid`` are ignored.

    Returns
    -------
    Dihedral
        Edges, face pairs, angles ``theta = atan2((n0 x n1) . e, n0 . n1)`` with ``e`` the
        unit edge direction as traversed by the first face, and a validity mask. Boundary
        edges and fins (more than two faces) are not included.

    Raises
    ------
    ValueError
        Bad shapes or out-of-range indices.
    TypeError
        Non-numeric input.
    """
    v, numpy_in = checked_vertices(vertices)
    fnp, fnumpy = faces_array(faces, v.shape[-2])
    f = torch.from_numpy(fnp)
    if hinges is None:
        _, eid, count = edge_faces(fnp)
        he = fnp[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
        sel = (eid >= 0) & (count[np.maximum(eid, 0)] == 2)
        order = np.argsort(eid[sel], kind="stable")
        hs = np.flatnonzero(sel)[order]
        h0, h1 = hs[0::2], hs[1::2]
        fa, fb = h0 // 3, h1 // 3
        e = he[h0]
    else:
        e, fa, fb = _hinge_topology(hinges, fnp.shape[0], v.shape[-2])
    c = _face_cross(v, f)
    fn, fok = _face_unit(c, v)
    n0, n1 = fn[..., torch.from_numpy(fa), :], fn[..., torch.from_numpy(fb), :]
    ev = v[..., torch.from_numpy(e[:, 1]), :] - v[..., torch.from_numpy(e[:, 0]), :]
    el, eok = safe_norm(ev, tiny_eps(v))
    eu = ev / torch.where(eok, el, torch.ones_like(el))[..., None]
    s = (torch.linalg.cross(n0, n1, dim=-1) * eu).sum(-1)
    co = (n0 * n1).sum(-1)
    ok = fok[..., torch.from_numpy(fa)] & fok[..., torch.from_numpy(fb)] & eok
    # atan2(0, 0) has a NaN-free gradient in torch only away from the origin: guard it
    co_s = torch.where(ok, co, torch.ones_like(co))
    s_s = torch.where(ok, s, torch.zeros_like(s))
    ang = torch.where(ok, torch.atan2(s_s, co_s), torch.zeros_like(co))
    return Dihedral(
        as_output(e.astype(np.int64), fnumpy),
        as_output(np.stack([fa, fb], 1).astype(np.int64), fnumpy),
        to_like(ang, numpy_in),
        to_like(ok, numpy_in),
    )


def _hinge_topology(
    hinges: Dihedral, n_faces: int, n_vertices: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validated ``(edges, face_a, face_b)`` of a previous :func:`dihedral_angles` result."""
    if not isinstance(hinges, Dihedral):
        raise TypeError(f"hinges: expected a Dihedral, got {type(hinges).__name__}")
    e = np.asarray(torch.as_tensor(hinges.edges).cpu().numpy(), dtype=np.int64)
    hf = np.asarray(torch.as_tensor(hinges.faces).cpu().numpy(), dtype=np.int64)
    if e.ndim != 2 or e.shape[1] != 2 or hf.shape != e.shape:
        raise ValueError(
            f"hinges: expected edges and faces of shape (E, 2), got {e.shape} and {hf.shape}"
        )
    if e.size and (e.min() < 0 or e.max() >= n_vertices or hf.min() < 0 or hf.max() >= n_faces):
        raise ValueError("hinges: indices out of range for these vertices and faces")
    return e, hf[:, 0], hf[:, 1]


def cotangent_weights(vertices: Any, faces: Any) -> CotanWeights:
    """Cotangent weights ``(cot alpha_ij + cot beta_ij) / 2`` of the undirected edges.

    Parameters
    ----------
    vertices : (..., N, 3) float
        Vertex coordinates.
    faces : (F, 3) int
        Triangles.

    Returns
    -------
    CotanWeights
        Edges ``(E, 2)`` (as :func:`edges`) and weights ``(..., E)``; the cotangent
        Laplacian is ``L_ij = -w_ij``, ``L_ii = sum_j w_ij``. Degenerate faces contribute 0.

    Raises
    ------
    ValueError
        Bad shapes or out-of-range indices.
    TypeError
        Non-numeric input.
    """
    v, numpy_in = checked_vertices(vertices)
    fnp, fnumpy = faces_array(faces, v.shape[-2])
    f = torch.from_numpy(fnp)
    e, eid, count = edge_faces(fnp)
    batch = v.shape[:-2]
    w = torch.zeros((*batch, e.shape[0]), dtype=v.dtype)
    eid_t = torch.from_numpy(eid.reshape(-1, 3))
    for corner in range(3):
        # half-edge from corner c to c+1 is opposite to corner c+2
        opp = (corner + 2) % 3
        p = v[..., f[:, opp], :]
        a = v[..., f[:, corner], :] - p
        b = v[..., f[:, (corner + 1) % 3], :] - p
        cr, ok = safe_norm(torch.linalg.cross(a, b, dim=-1), tiny_eps(v))
        dot = (a * b).sum(-1)
        cot = torch.where(ok, dot / torch.where(ok, cr, torch.ones_like(cr)), torch.zeros_like(cr))
        ids = eid_t[:, corner]
        good = ids >= 0
        w = w.index_add(-1, ids[good], 0.5 * cot[..., good])
    return CotanWeights(as_output(e, fnumpy), to_like(w, numpy_in))
