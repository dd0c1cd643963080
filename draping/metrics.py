"""Cloth metrics shared by every draping method: stretch, collision and errors to a reference.

Per frame (a leading batch of frames ``(..., V, 3)``, one garment connectivity) and per
sequence (:func:`summarize`):

- ``eps_e``, ``eps_a`` (GAPS, thesis section 4.4): mean absolute change (%) of the edge lengths
  and of the triangle areas against the template;
- ``eps_c`` (GAPS): % of garment vertices inside the body, from signed distances (negative
  inside) given by the caller's body query;
- ``e_dist`` (GarNet eq. (7)): mean vertex-to-vertex distance to a reference drape, in cm;
- ``e_norm`` (GarNet section 4.1): mean angle between corresponding face normals, in degrees;
- ``e_3D`` (FNOpt, thesis section 6.3): ``||X - X_ref||_F / ||X_ref - mean(X_ref)||_F``, a
  relative vertex error (dimensionless) that depends neither on the unit nor on the origin.

Lengths come from :mod:`polygeo.mesh`. Torch in, torch out; NumPy in, NumPy out.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from polygeo import mesh
from polygeo.checks import as_tensor, check_faces, check_finite, check_shape, is_numpy_like

__all__ = [
    "edge_error",
    "area_error",
    "collision_error",
    "distance_error",
    "normal_error",
    "relative_vertex_error",
    "drape_metrics",
    "summarize",
]


def _positions(x: Any, name: str) -> tuple[torch.Tensor, bool]:
    t = as_tensor(x, name)
    check_shape(t, name, ("...", "V", 3))
    check_finite(t, name)
    return t.detach(), is_numpy_like(x)


def _pair(x: Any, template: Any) -> tuple[torch.Tensor, torch.Tensor, bool]:
    xt, numpy_in = _positions(x, "x")
    tt, _ = _positions(template, "template")
    if tt.shape[-2] != xt.shape[-2]:
        raise ValueError(f"template: expected {xt.shape[-2]} vertices like x, got {tt.shape[-2]}")
    return xt, tt.to(xt.dtype), numpy_in


def _out(t: torch.Tensor, numpy_in: bool) -> Any:
    return t.numpy() if numpy_in else t


def edge_error(x: Any, template: Any, faces: Any) -> Any:
    """``eps_e``: mean over edges of ``|l / l_0 - 1|``, in percent.

    Parameters
    ----------
    x : (..., V, 3) float
        Draped garment(s) (any length unit).
    template : (V, 3) float
        Rest garment (same unit).
    faces : (F, 3) int
        Triangles.

    Returns
    -------
    (...) float
        Percent per frame; zero-length template edges are skipped.

    Raises
    ------
    ValueError
        Bad shapes, non-finite positions, bad faces.
    TypeError
        Non-floating positions.
    """
    xt, tt, numpy_in = _pair(x, template)
    e = mesh.edges(check_faces(faces, xt.shape[-2]))
    l0 = mesh.edge_lengths(tt, e)
    ok = l0 > 0
    ratio = mesh.edge_lengths(xt, e)[..., ok] / l0[ok]
    return _out(100.0 * (ratio - 1.0).abs().mean(-1), numpy_in)


def area_error(x: Any, template: Any, faces: Any) -> Any:
    """``eps_a``: mean over triangles of ``|A / A_0 - 1|``, in percent.

    Parameters
    ----------
    x : (..., V, 3) float
        Draped garment(s).
    template : (V, 3) float
        Rest garment.
    faces : (F, 3) int
        Triangles.

    Returns
    -------
    (...) float
        Percent per frame; degenerate template faces are skipped.

    Raises
    ------
    ValueError, TypeError
        As :func:`edge_error`.
    """
    xt, tt, numpy_in = _pair(x, template)
    f = check_faces(faces, xt.shape[-2])
    a0 = mesh.face_areas(tt, f)
    ok = a0 > 0
    ratio = mesh.face_areas(xt, f)[..., ok] / a0[ok]
    return _out(100.0 * (ratio - 1.0).abs().mean(-1), numpy_in)


def collision_error(distance: Any, threshold: float = 0.0) -> Any:
    """``eps_c``: percentage of vertices whose signed distance to the body is below ``threshold``.

    Parameters
    ----------
    distance : (..., V) float
        Signed distances of the garment vertices to the body (negative inside).
    threshold : float
        Distance counted as inside (same unit; 0: strictly inside).

    Returns
    -------
    (...) float
        Percent per frame.

    Raises
    ------
    ValueError
        Empty or non-finite distances.
    TypeError
        Non-floating distances.
    """
    numpy_in = is_numpy_like(distance)
    d = as_tensor(distance, "distance").detach()
    if d.ndim < 1 or d.shape[-1] == 0:
        raise ValueError(f"distance: expected shape (..., V) with V > 0, got {tuple(d.shape)}")
    check_finite(d, "distance")
    return _out(100.0 * (d < threshold).to(d.dtype).mean(-1), numpy_in)


def distance_error(x: Any, reference: Any, to_cm: float = 100.0) -> Any:
    """``E_dist`` (GarNet eq. (7)): mean vertex-to-vertex distance to a reference, in cm.

    Parameters
    ----------
    x : (..., V, 3) float
        Draped garment(s).
    reference : (..., V, 3) float
        Reference drape(s) with the same vertices (broadcast over frames).
    to_cm : float
        Factor from the input length unit to centimetres (100 for metres).

    Returns
    -------
    (...) float
        Centimetres per frame.

    Raises
    ------
    ValueError
        Shapes that do not match, non-finite values.
    TypeError
        Non-floating positions.
    """
    xt, numpy_in = _positions(x, "x")
    rt, _ = _positions(reference, "reference")
    if rt.shape[-2] != xt.shape[-2]:
        raise ValueError(f"reference: expected {xt.shape[-2]} vertices, got {rt.shape[-2]}")
    return _out(to_cm * torch.linalg.norm(xt - rt.to(xt.dtype), dim=-1).mean(-1), numpy_in)


def normal_error(x: Any, reference: Any, faces: Any) -> Any:
    """``E_norm`` (GarNet section 4.1): mean angle between corresponding face normals, degrees.

    Parameters
    ----------
    x : (..., V, 3) float
        Draped garment(s).
    reference : (..., V, 3) float
        Reference drape(s).
    faces : (F, 3) int
        Triangles.

    Returns
    -------
    (...) float
        Degrees per frame, over the faces valid (non-degenerate) in both.

    Raises
    ------
    ValueError, TypeError
        As :func:`distance_error`.
    """
    xt, numpy_in = _positions(x, "x")
    rt, _ = _positions(reference, "reference")
    if rt.shape[-2] != xt.shape[-2]:
        raise ValueError(f"reference: expected {xt.shape[-2]} vertices, got {rt.shape[-2]}")
    f = check_faces(faces, xt.shape[-2])
    na = mesh.face_normals(xt, f)
    nb = mesh.face_normals(rt.to(xt.dtype), f)
    cos = (na.normals * nb.normals).sum(-1).clamp(-1.0, 1.0)
    ok = (na.valid & nb.valid).to(xt.dtype)
    ang = torch.rad2deg(torch.arccos(cos)) * ok
    return _out(ang.sum(-1) / ok.sum(-1).clamp_min(1.0), numpy_in)


def relative_vertex_error(x: Any, reference: Any) -> Any:
    """``e_3D``: ``||X - X_ref||_F / ||X_ref - mean(X_ref)||_F`` per frame (dimensionless).

    The Frobenius norm of the vertex differences over that of the reference's vertices about
    their centroid: invariant to the length unit and to a common translation of both.

    Parameters
    ----------
    x : (..., V, 3) float
        Positions (any length unit).
    reference : (..., V, 3) float
        Reference positions with the same vertices, same unit (broadcast over frames).

    Returns
    -------
    (...) float
        Relative error per frame, in float64 (0 for identical meshes).

    Raises
    ------
    ValueError
        Shapes that do not match, non-finite values, or a reference whose vertices all coincide
        (its spread is zero, so no relative error exists).
    TypeError
        Non-floating positions.
    """
    xt, numpy_in = _positions(x, "x")
    rt, _ = _positions(reference, "reference")
    if rt.shape[-2] != xt.shape[-2]:
        raise ValueError(f"reference: expected {xt.shape[-2]} vertices, got {rt.shape[-2]}")
    xt, rt = xt.double(), rt.double()
    spread = torch.linalg.norm((rt - rt.mean(-2, keepdim=True)).flatten(-2), dim=-1)
    if bool((spread <= 0).any()):
        raise ValueError("reference: expected vertices with a non-zero spread about their "
                         "centroid, got all vertices at one point")
    num = torch.linalg.norm((xt - rt).flatten(-2), dim=-1)
    return _out(num / spread, numpy_in)


def drape_metrics(
    x: Any,
    template: Any,
    faces: Any,
    distance: Any = None,
    reference: Any = None,
    to_cm: float = 100.0,
) -> dict[str, Any]:
    """All metrics of a drape, per frame.

    Parameters
    ----------
    x : (T, V, 3) or (V, 3) float
        Draped garment(s) (m by default).
    template : (V, 3) float
        Rest garment.
    faces : (F, 3) int
        Triangles.
    distance : (T, V) or (V,) float, optional
        Signed distances to the body (``eps_c`` is left out without them).
    reference : same shape as ``x``, optional
        Reference drape (``e_dist``, ``e_norm`` are left out without it).
    to_cm : float
        Input length unit to centimetres.

    Returns
    -------
    dict
        ``eps_e``, ``eps_a`` (%), and when available ``eps_c`` (%), ``e_dist`` (cm),
        ``e_norm`` (degrees): each of shape ``x.shape[:-2]``.

    Raises
    ------
    ValueError, TypeError
        As the individual metrics.
    """
    out = {"eps_e": edge_error(x, template, faces), "eps_a": area_error(x, template, faces)}
    if distance is not None:
        out["eps_c"] = collision_error(distance)
    if reference is not None:
        out["e_dist"] = distance_error(x, reference, to_cm)
        out["e_norm"] = normal_error(x, reference, faces)
    return out


def summarize(per_frame: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per-sequence summary of per-frame metrics: mean, max and the per-frame list.

    Parameters
    ----------
    per_frame : dict of (T,) float
        E.g. from :func:`drape_metrics` on a sequence.

    Returns
    -------
    dict
        ``{name: {"mean": float, "max": float, "per_frame": list of float}}`` (JSON-able).

    Raises
    ------
    ValueError
        An empty series.
    """
    out = {}
    for name, vals in per_frame.items():
        a = np.atleast_1d(
            np.asarray(vals.numpy() if isinstance(vals, torch.Tensor) else vals, dtype=np.float64)
        )
        if a.size == 0:
            raise ValueError(f"per_frame[{name!r}]: expected at least one frame, got none")
        out[name] = {
            "mean": float(a.mean()),
            "max": float(a.max()),
            "per_frame": [float(v) for v in a.ravel()],
        }
    return out
