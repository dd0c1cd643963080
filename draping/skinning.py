"""Blend weights of a garment from the body it is worn on.

A garment follows the body through linear blend skinning: each garment vertex needs a
weight per body bone. Three ways of transferring the body's own weights to a garment are
offered, one per draping method that uses them:

``nearest``
    Each garment vertex takes the weights of its nearest body vertex (SNUG). Exact for a
    garment on the skin; on a loose garment neighbouring garment vertices can snap to body
    vertices of different limbs (a dress between the legs).
``laplacian``
    The nearest-vertex weights, then iterative Laplacian smoothing over the garment's own
    edges (NCS): ``W <- (1 - alpha) W + alpha * mean of the neighbours' W``
    (:func:`smooth_weights`). :func:`skinning_weights` applies the same smoothing after any
    method (``smoothing=`` steps): GAPS smooths its RBF weights this way.
``rbf``
    GAPS's body participation (thesis eq. (34)-(36)). With ``m_i`` the distance from garment
    vertex ``g_i`` to its nearest body vertex and ``d_ij`` its distance to body vertex ``b_j``,
    body vertex ``j`` participates with ``phi_ij = exp(-(d_ij - m_i)^2 / (width * m_i^2))`` and
    the garment weights are the participation-weighted sum of the body weights, normalised
    so that each row sums to one. A vertex on the skin (``m_i -> 0``) takes its nearest body
    vertex's weights; a vertex far from the body blends the weights of a body region whose
    size grows with ``m_i``.

The participation is truncated where ``phi < tol`` (a ball of radius
``m_i (1 + sqrt(width * ln(1/tol)))`` around ``g_i``) and gathered in chunks of garment
vertices, so memory stays ``O(chunk * neighbours + N_garment * J)``, never
``N_garment x N_body``. All distances are in the unit of the inputs; nothing depends on it.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import scipy.sparse as sp
import torch
from scipy.spatial import cKDTree

from polygeo.checks import (
    as_tensor,
    check_choice,
    check_faces,
    check_finite,
    check_int,
    check_positive,
    check_shape,
    is_numpy_like,
)

__all__ = [
    "SKINNING_METHODS",
    "dense_body_weights",
    "nearest_weights",
    "laplacian_weights",
    "smooth_weights",
    "rbf_weights",
    "skinning_weights",
]

#: Names accepted by :func:`skinning_weights`.
SKINNING_METHODS = ("nearest", "laplacian", "rbf")


def _points(x: Any, name: str) -> np.ndarray:
    t = as_tensor(x, name, dtype=torch.float64)
    check_shape(t, name, ("N", 3))
    check_finite(t, name)
    return t.detach().cpu().numpy()


def dense_body_weights(weights: Any, n_vertices: int, n_bones: int | None = None) -> np.ndarray:
    """Body blend weights as a dense ``(V, J)`` float64 array.

    Parameters
    ----------
    weights : (V, J) array or tensor, or a pair ``(index, weight)`` of (V, S) arrays
        Dense weights, or sparse ones: ``index[v, s]`` is a bone (``-1`` for padding) and
        ``weight[v, s]`` its weight.
    n_vertices : int
        Number of body vertices ``V``.
    n_bones : int, optional
        Number of bones ``J`` for sparse weights (default: largest index + 1).

    Returns
    -------
    (V, J) float64 ndarray
        Non-negative weights, rows summing to one.

    Raises
    ------
    ValueError
        Wrong shapes, negative weights, a bone index out of range, or a row summing to zero.
    """
    if isinstance(weights, tuple):
        if len(weights) != 2:
            raise ValueError(f"weights: expected (index, weight), got a tuple of {len(weights)}")
        idx = np.asarray(weights[0].cpu() if torch.is_tensor(weights[0]) else weights[0])
        w = _matrix(weights[1], "weights[1]")
        if idx.shape != w.shape or idx.shape[0] != n_vertices:
            raise ValueError(
                f"weights: expected index and weight of shape ({n_vertices}, S), "
                f"got {idx.shape} and {w.shape}"
            )
        if not np.issubdtype(idx.dtype, np.integer):
            raise TypeError(f"weights[0]: expected integer bone indices, got {idx.dtype}")
        j = int(idx.max()) + 1 if n_bones is None else check_int(n_bones, "n_bones", low=1)
        if idx.min() < -1 or idx.max() >= j:
            raise ValueError(f"weights[0]: bone indices must lie in [-1, {j}), got "
                             f"[{idx.min()}, {idx.max()}]")
        keep = idx >= 0
        rows = np.broadcast_to(np.arange(idx.shape[0])[:, None], idx.shape)[keep]
        dense = np.zeros((idx.shape[0], j))
        np.add.at(dense, (rows, idx[keep]), w[keep])
    else:
        dense = _matrix(weights, "weights")
        if dense.shape[0] != n_vertices:
            raise ValueError(f"weights: expected {n_vertices} rows, got {dense.shape[0]}")
    if (dense < 0).any():
        raise ValueError("weights: expected non-negative blend weights")
    total = dense.sum(1, keepdims=True)
    if (total <= 0).any():
        raise ValueError(f"weights: {int((total <= 0).sum())} body vertices have no weight")
    return dense / total


def _matrix(x: Any, name: str) -> np.ndarray:
    t = as_tensor(x, name, dtype=torch.float64)
    check_shape(t, name, ("V", "J"))
    check_finite(t, name)
    return t.detach().cpu().numpy()


def _out(w: np.ndarray, like: Any) -> Any:
    return w if is_numpy_like(like) else torch.from_numpy(w)


def nearest_weights(garment_vertices: Any, body_vertices: Any, body_weights: Any) -> Any:
    """Weights of each garment vertex's nearest body vertex (SNUG's skinning).

    Parameters
    ----------
    garment_vertices : (G, 3) float array or tensor
        Garment vertices, in the body's rest pose and unit.
    body_vertices : (V, 3) float array or tensor
        Body vertices in the same pose and unit.
    body_weights : (V, J) array, or ``(index, weight)`` of (V, S) arrays
        The body's blend weights (see :func:`dense_body_weights`).

    Returns
    -------
    (G, J) float64 array or tensor
        Rows summing to one; the array type of ``garment_vertices``.

    Raises
    ------
    ValueError, TypeError
        Bad shapes, non-finite coordinates or bad weights (the argument is named).
    """
    g = _points(garment_vertices, "garment_vertices")
    b = _points(body_vertices, "body_vertices")
    w = dense_body_weights(body_weights, b.shape[0])
    _, nearest = cKDTree(b).query(g, k=1)
    return _out(w[nearest], garment_vertices)


def laplacian_weights(
    garment_vertices: Any,
    garment_faces: Any,
    body_vertices: Any,
    body_weights: Any,
    *,
    iterations: int = 20,
    alpha: float = 0.5,
) -> Any:
    """Nearest-vertex weights smoothed over the garment's edges (NCS's skinning).

    Parameters
    ----------
    garment_vertices : (G, 3) float array or tensor
        Garment vertices in the body's rest pose.
    garment_faces : (F, 3) int array or tensor
        Garment triangles.
    body_vertices : (V, 3) float array or tensor
        Body vertices in the same pose and unit.
    body_weights : (V, J) array, or ``(index, weight)`` of (V, S) arrays
        The body's blend weights.
    iterations : int
        Smoothing steps, ``>= 0`` (0 gives :func:`nearest_weights`).
    alpha : float
        Step in ``(0, 1]``: each step moves a vertex's weights this far towards the mean of
        its neighbours' weights.

    Returns
    -------
    (G, J) float64 array or tensor
        Rows summing to one; the array type of ``garment_vertices``.

    Raises
    ------
    ValueError, TypeError
        Bad shapes, indices, ``iterations < 0`` or ``alpha`` outside ``(0, 1]``.
    """
    g = _points(garment_vertices, "garment_vertices")
    faces = check_faces(garment_faces, g.shape[0], name="garment_faces")
    w = nearest_weights(g, body_vertices, body_weights)
    return _out(smooth_weights(w, faces, iterations=iterations, alpha=alpha), garment_vertices)


def smooth_weights(weights: Any, faces: Any, *, iterations: int = 20, alpha: float = 0.5) -> Any:
    """Iterative Laplacian smoothing of per-vertex blend weights over a mesh's edges.

    ``W <- (1 - alpha) W + alpha * mean of the neighbours' W``, ``iterations`` times, then
    each row renormalised. Used by :func:`laplacian_weights` (on nearest-vertex weights) and
    by GAPS on its RBF weights (:class:`draping.gaps.GapsSettings` ``skin_smoothing``).

    Parameters
    ----------
    weights : (G, J) float array or tensor
        Non-negative weights of the mesh's vertices, rows summing to one.
    faces : (F, 3) int array or tensor
        The mesh's triangles (indices into the rows of ``weights``).
    iterations : int
        Smoothing steps, ``>= 0`` (0 returns the weights unchanged).
    alpha : float
        Step in ``(0, 1]``.

    Returns
    -------
    (G, J) float64 array or tensor
        Rows summing to one; the array type of ``weights``. Vertices in no face keep their
        weights.

    Raises
    ------
    ValueError, TypeError
        Bad shapes, negative or non-finite weights, bad faces, ``iterations < 0`` or
        ``alpha`` outside ``(0, 1]``.
    """
    w = _matrix(weights, "weights")
    if (w < 0).any():
        raise ValueError("weights: expected non-negative blend weights")
    f = check_faces(faces, w.shape[0], name="faces")
    iterations = check_int(iterations, "iterations", low=0)
    alpha = check_positive(alpha, "alpha")
    if alpha > 1:
        raise ValueError(f"alpha: expected a value in (0, 1], got {alpha}")
    f = np.asarray(f.cpu() if torch.is_tensor(f) else f, dtype=np.int64)
    n = w.shape[0]
    a = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    c = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    adj = sp.csr_matrix((np.ones(2 * a.size), (np.r_[a, c], np.r_[c, a])), shape=(n, n))
    adj.data[:] = 1.0  # duplicated edges count once
    deg = np.asarray(adj.sum(1)).ravel()
    has = deg > 0  # isolated vertices keep their weights
    mean = sp.diags(np.where(has, 1.0 / np.maximum(deg, 1), 0.0)) @ adj
    for _ in range(iterations):
        smoothed = mean @ w
        w = np.where(has[:, None], (1 - alpha) * w + alpha * smoothed, w)
    total = w.sum(1, keepdims=True)
    if (total <= 0).any():
        raise ValueError(f"weights: {int((total <= 0).sum())} rows have no weight")
    return _out(w / total, weights)


def rbf_weights(
    garment_vertices: Any,
    body_vertices: Any,
    body_weights: Any,
    *,
    width: float = 0.5,
    tol: float = 1e-4,
    chunk: int = 1024,
) -> Any:
    """GAPS's body-participation weights (thesis eq. (34)-(36)).

    Parameters
    ----------
    garment_vertices : (G, 3) float array or tensor
        Garment vertices in the body's rest pose.
    body_vertices : (V, 3) float array or tensor
        Body vertices in the same pose and unit.
    body_weights : (V, J) array, or ``(index, weight)`` of (V, S) arrays
        The body's blend weights.
    width : float
        ``k`` of eq. (34), ``> 0``: the kernel's squared width relative to ``m_i^2``
        (0.5 in the thesis; larger blends more of the body into loose parts).
    tol : float
        Participation below ``tol`` (relative to the nearest vertex's, which is 1) is
        dropped, in ``(0, 1)``; it bounds the neighbourhood of each garment vertex.
    chunk : int
        Garment vertices gathered at once (bounds memory).

    Returns
    -------
    (G, J) float64 array or tensor
        Rows summing to one; the array type of ``garment_vertices``. A garment vertex lying
        on a body vertex takes that vertex's weights exactly.

    Raises
    ------
    ValueError, TypeError
        Bad shapes or values (the argument is named).
    """
    g = _points(garment_vertices, "garment_vertices")
    b = _points(body_vertices, "body_vertices")
    w_body = dense_body_weights(body_weights, b.shape[0])
    width = check_positive(width, "width")
    tol = check_positive(tol, "tol")
    if tol >= 1:
        raise ValueError(f"tol: expected a value in (0, 1), got {tol}")
    chunk = check_int(chunk, "chunk", low=1)
    tree = cKDTree(b)
    m, nearest = tree.query(g, k=1)
    reach = m * (1.0 + math.sqrt(width * math.log(1.0 / tol)))
    out = np.empty((g.shape[0], w_body.shape[1]))
    for s in range(0, g.shape[0], chunk):
        sl = slice(s, min(s + chunk, g.shape[0]))
        balls = tree.query_ball_point(g[sl], reach[sl])
        sizes = np.fromiter((len(x) for x in balls), dtype=np.int64, count=len(balls))
        cols = np.concatenate([np.asarray(x, dtype=np.int64) for x in balls])
        rows = np.repeat(np.arange(len(balls)), sizes)
        mi = m[sl][rows]
        d = np.linalg.norm(g[sl][rows] - b[cols], axis=1)
        on_skin = mi <= 0.0
        with np.errstate(divide="ignore", invalid="ignore"):
            phi = np.exp(-((d - mi) ** 2) / (width * mi**2))
        phi[on_skin] = 0.0
        phi[phi < tol] = 0.0
        part = sp.csr_matrix((phi, (rows, cols)), shape=(len(balls), b.shape[0]))
        block = part @ w_body
        # A vertex on the skin (m = 0) takes its nearest body vertex's weights exactly.
        skin = m[sl] <= 0.0
        block[skin] = w_body[nearest[sl][skin]]
        out[sl] = block
    out /= out.sum(1, keepdims=True)
    return _out(out, garment_vertices)


def skinning_weights(
    method: str,
    garment_vertices: Any,
    body_vertices: Any,
    body_weights: Any,
    *,
    garment_faces: Any = None,
    smoothing: int | None = None,
    smoothing_alpha: float = 0.5,
    **options: Any,
) -> Any:
    """Garment blend weights by name: ``"nearest"``, ``"laplacian"`` or ``"rbf"``.

    The method's weights, then ``smoothing`` Laplacian steps over the garment's edges
    (:func:`smooth_weights`, the one home of the smoothing). ``"laplacian"`` is
    ``"nearest"`` with 20 steps by default; GAPS smooths its ``"rbf"`` weights the same way.

    Parameters
    ----------
    method : str
        One of :data:`SKINNING_METHODS`.
    garment_vertices, body_vertices, body_weights
        As in :func:`nearest_weights`.
    garment_faces : (F, 3) int array or tensor, optional
        Garment triangles; needed when any smoothing is done.
    smoothing : int, optional
        Laplacian smoothing steps, ``>= 0`` (default: 20 for ``"laplacian"``, 0 otherwise).
    smoothing_alpha : float
        Step of each smoothing step, in ``(0, 1]`` (see :func:`smooth_weights`).
    **options
        Keyword options of ``"rbf"`` (``width``, ``tol``, ``chunk``); the other methods
        take none.

    Returns
    -------
    (G, J) float64 array or tensor
        Rows summing to one; the array type of ``garment_vertices``.

    Raises
    ------
    ValueError
        An unknown method, an option the method does not take, missing faces when
        smoothing, ``smoothing < 0``, or what the method raises.
    """
    check_choice(method, "method", SKINNING_METHODS)
    if method == "laplacian" and {"iterations", "alpha"} & set(options):
        raise ValueError("options: 'laplacian' takes smoothing= and smoothing_alpha= "
                         f"(steps and step size), got {sorted(options)}")
    if method != "rbf" and options:
        raise ValueError(f"options: {method!r} takes none, got {sorted(options)}")
    if smoothing is None:
        smoothing = 20 if method == "laplacian" else 0
    smoothing = check_int(smoothing, "smoothing", low=0)
    smoothing_alpha = check_positive(smoothing_alpha, "smoothing_alpha")
    if smoothing_alpha > 1:
        raise ValueError(f"smoothing_alpha: expected a value in (0, 1], got {smoothing_alpha}")
    if smoothing > 0 and garment_faces is None:
        raise ValueError(f"garment_faces: required to smooth the weights (method {method!r}, "
                         f"smoothing={smoothing})")
    if method == "rbf":
        w = rbf_weights(garment_vertices, body_vertices, body_weights, **options)
    else:
        w = nearest_weights(garment_vertices, body_vertices, body_weights)
    w = np.asarray(w)
    if smoothing > 0:
        w = smooth_weights(w, garment_faces, iterations=smoothing, alpha=smoothing_alpha)
    return _out(w, garment_vertices)
