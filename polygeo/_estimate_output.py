"""Last stages of :func:`polygeo.estimate.differential_quantities`: orientation and outputs.

:func:`orientation_signs` decides one sign per point (input normals, the mesh's faces, or
propagation over the k-NN graph); :func:`oriented_outputs` applies it to the estimates of the
compiled path (NumPy) or of the torch path (differentiable), and :func:`extras` adds the
optional fundamental forms and Monge coefficients.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from . import jets
from ._estimate_numba import Quantities
from .neighbors import reaches_non_manifold
from .status import Status

_CURVATURES = ("k1", "k2", "mean_curvature", "gaussian_curvature")
_VECTORS = ("normals", "d1", "d2")


def orientation_signs(P, nrm, status, *, graph, reference, faces, orient, workers) -> np.ndarray:
    """Sign (+1/-1) per point making the estimated normals consistent.

    ``reference`` (N, 3) input normals or None; ``faces`` (F, 3) or None; ``graph`` (N, k)
    k-NN graph (-1 padding). See :mod:`polygeo.estimate` for the rules.
    """
    from . import orient as ori
    from .mesh import weld_vertices

    n = P.shape[0]
    sign = np.ones(n)
    if orient == "none" or n == 0:
        return sign
    usable = np.isfinite(nrm).all(1) & (status != Status.NONFINITE_INPUT)
    ref_dir = None
    if orient in ("auto", "input") and reference is not None:
        ref_dir = np.where(np.isfinite(reference), reference, 0.0)
    elif orient in ("auto", "mesh") and faces is not None:
        Pw = np.where(np.isfinite(P), P, np.nan)
        w = weld_vertices(Pw, faces)
        wn, wvalid = ori.mesh_reference_normals(w.vertices, w.faces)
        ref_dir = np.where(wvalid[:, None], wn, 0.0)[w.mapping]
    nz = np.where(usable[:, None], nrm, 0.0)
    decided = np.zeros(n, dtype=bool)
    if ref_dir is not None:
        dot = np.einsum("ij,ij->i", nz, ref_dir)
        decided = usable & (dot != 0)
        sign = np.where(decided & (dot < 0), -1.0, 1.0)
        if decided.all() or not (usable & ~decided).any():
            return sign
    # propagate through reliable estimates only: a flagged normal (scan line, too few
    # points) may be far off and would flip everything behind it
    good = usable & (status == Status.OK)
    if not good.any():
        good = usable
    nz_good = np.where(good[:, None], nz, 0.0)
    prop = ori.propagate_orientation(P, nz_good, neighbors=graph, workers=workers)
    s_prop = np.where(good, prop.sign, 1.0)
    comp = np.where(good, prop.component, -1)
    if ref_dir is not None and decided.any():
        # per component: agree with the majority of decided points
        ok = decided & (comp >= 0)
        vote = np.zeros(max(int(comp.max()) + 1, 1))
        dot = np.abs(np.einsum("ij,ij->i", nz, ref_dir))
        np.add.at(vote, comp[ok], (sign[ok] * s_prop[ok]) * dot[ok])
        comp_sign = np.where(vote < 0, -1.0, 1.0)
        rest = good & ~decided & (comp >= 0)
        sign[rest] = s_prop[rest] * comp_sign[comp[rest]]
    else:
        sign = s_prop.copy()
    # flagged points: agree with the oriented normals of their reliable graph neighbours
    rest = usable & ~good & ~decided
    if rest.any():
        nb = graph[rest]
        valid = (nb >= 0) & good[np.maximum(nb, 0)]
        oriented = nz[np.maximum(nb, 0)] * (sign[np.maximum(nb, 0)] * valid)[..., None]
        ref_rest = oriented.sum(1)
        d = np.einsum("ij,ij->i", nz[rest], ref_rest)
        sign[rest] = np.where(d < 0, -1.0, 1.0)
    return np.where(usable, sign, 1.0)


def quantities_dict(out: Quantities) -> dict[str, np.ndarray]:
    """Normals, directions and curvatures of ``out`` by output name (views)."""
    res = {"normals": out.normals, "d1": out.d1, "d2": out.d2}
    for c, name in enumerate(_CURVATURES):
        res[name] = out.curvatures[:, c]
    return res


def apply_sign(res: dict, s) -> dict:
    """Estimates with the normals flipped where ``s < 0`` (k1, k2 and d1, d2 swap roles)."""
    lib = torch if isinstance(s, torch.Tensor) else np
    neg = s < 0
    out = dict(res)
    out["normals"] = res["normals"] * _as(s, res["normals"])[:, None]
    out["k1"] = lib.where(neg, -res["k2"], res["k1"])
    out["k2"] = lib.where(neg, -res["k1"], res["k2"])
    out["d1"] = lib.where(neg[:, None], res["d2"], res["d1"])
    out["d2"] = lib.where(neg[:, None], res["d1"], res["d2"])
    out["mean_curvature"] = res["mean_curvature"] * _as(s, res["mean_curvature"])
    return out


def _as(s, like):
    return s.to(like.dtype) if isinstance(s, torch.Tensor) else s


def coeff_signs(s: torch.Tensor, order: int) -> torch.Tensor:
    """Factors turning jet coefficients in (e1, e2, e3) into ones in (e1, -e2, -e3).

    With ``v' = -v`` and ``z' = -z``: ``a'_pq = -(-1)^q a_pq`` where the sign is flipped.
    """
    q = jets.exponents(order)[:, 1].to(torch.float64)  # (M,)
    s = s.to(torch.float64)[:, None]
    return torch.where(s < 0, -((-1.0) ** q)[None, :], torch.ones_like(q)[None, :])


def flip_frame(frame, s):
    """Frames with ``e2`` and ``e3`` flipped where ``s < 0`` (right-handed stays so)."""
    if isinstance(frame, torch.Tensor):
        m = torch.stack([torch.ones_like(s), s, s], -1).to(frame.dtype)
        return frame * m[:, None, :]
    f = frame.copy()
    f[:, :, 1] *= s[:, None]
    f[:, :, 2] *= s[:, None]
    return f


def assemble_torch(parts, n: int, n_coeffs: int) -> tuple[dict, Any, Any, Any]:
    """Estimates of the torch path's chunks ``(q, fit, geometry, frames)`` in point order."""
    shapes = {"normals": (3,), "d1": (3,), "d2": (3,)}
    res = {
        k_: torch.full((n, *shapes.get(k_, ())), float("nan"), dtype=torch.float64)
        for k_ in (*_VECTORS, *_CURVATURES)
    }
    frame = torch.full((n, 3, 3), float("nan"), dtype=torch.float64)
    coeffs = torch.zeros((n, n_coeffs), dtype=torch.float64)
    resid = torch.full((n,), float("nan"), dtype=torch.float64)
    for q, fit, geom, R in parts:
        qt = torch.from_numpy(q)
        for k_ in res:
            name = "normal" if k_ == "normals" else k_
            res[k_] = res[k_].index_copy(0, qt, getattr(geom, name).to(torch.float64))
        frame = frame.index_copy(0, qt, R.to(torch.float64))
        c = fit.coeffs.to(torch.float64)
        cpad = torch.zeros((c.shape[0], n_coeffs), dtype=torch.float64)
        cpad[:, : c.shape[1]] = c
        coeffs = coeffs.index_copy(0, qt, cpad)
        resid = resid.index_copy(0, qt, fit.residual.to(torch.float64))
    return res, frame, coeffs, resid


def oriented_outputs(out: Quantities, parts, *, settings, orient_args: dict,
                     dtype: torch.dtype) -> dict[str, torch.Tensor]:
    """Orientation stage, then every per-point field as a tensor of ``dtype``.

    ``parts``: the torch path's chunks (None on the compiled path); ``orient_args``: the
    keyword arguments of :func:`orientation_signs` besides the normals and status.
    """
    max_order = max(settings.orders)
    if parts is not None:
        res, frame, coeffs, resid = assemble_torch(parts, out.status.shape[0],
                                                   out.coeffs.shape[1])
        nrm = res["normals"].detach().numpy()
    else:
        res, frame, coeffs, resid = quantities_dict(out), out.frame, out.coeffs, out.residual
        nrm = res["normals"]
    sign = orientation_signs(nrm=nrm, status=out.status, **orient_args)
    if parts is not None:
        s_t = torch.from_numpy(sign)
        res = apply_sign(res, s_t)
        frame = flip_frame(frame, s_t)
        coeffs = coeffs * coeff_signs(torch.from_numpy(sign), max_order)
        fields = {k_: v.to(dtype) for k_, v in res.items()}
    else:
        if (sign < 0).any():
            res = apply_sign(res, sign)
            frame = flip_frame(frame, sign)
            coeffs = coeffs * coeff_signs(torch.from_numpy(sign), max_order).numpy()
        fields = {k_: torch.from_numpy(np.ascontiguousarray(v)).to(dtype)
                  for k_, v in res.items()}
        frame, coeffs, resid = (torch.from_numpy(a) for a in (frame, coeffs, resid))
    fields.update(frame=frame.to(dtype), coeffs=coeffs.to(dtype), residual=resid.to(dtype),
                  status=torch.from_numpy(out.status),
                  order=torch.from_numpy(out.fitted_order),
                  n_neighbors=torch.from_numpy(out.n_neighbors))
    return fields


def extras(fields: dict, P: np.ndarray, *, forms: bool, monge: bool,
           dtype: torch.dtype) -> dict[str, Any]:
    """The optional fields: fundamental forms and Monge coefficients (None when not asked)."""
    from .diffgeo import from_jet, monge_form

    out: dict[str, Any] = {"metric": None, "second_form": None, "monge": None}
    coeffs = fields["coeffs"].double()
    if forms:
        g = from_jet(coeffs).squeeze(1)
        out["metric"], out["second_form"] = g.metric.to(dtype), g.second_form.to(dtype)
    if monge:
        frame = fields["frame"].double()
        ok = torch.isfinite(frame).all(-1).all(-1)
        origin_p = torch.from_numpy(np.where(np.isfinite(P), P, 0.0))
        R = torch.where(ok[:, None, None], frame, torch.eye(3, dtype=frame.dtype))
        mf = monge_form(coeffs, R, origin_p)
        # the coefficients/frame are already oriented (the jet's +z side is the final normal)
        nan = torch.tensor(float("nan"), dtype=coeffs.dtype)
        out["monge"] = {
            name: torch.where(ok[:, None], getattr(mf, name), nan).to(dtype)
            for name in ("origin", "b", "c")
        }
    return out


def non_manifold_status(P: np.ndarray, faces: np.ndarray, out: Quantities, *,
                        radius: float | None, rings: int | None) -> np.ndarray:
    """``(N,)`` status with ``NON_MANIFOLD`` where an OK neighbourhood reaches a fin edge."""
    reach = reaches_non_manifold(P, faces, out.n_neighbors, radius=radius, rings=rings)
    return np.where(reach & (out.status == int(Status.OK)), int(Status.NON_MANIFOLD),
                    out.status)
