"""Membrane, bending, gravity and inertia energies (SI units, J).

Part of :mod:`draping.physics`; import from there.
"""

from __future__ import annotations

from typing import Any

import torch

from polygeo import mesh
from polygeo.checks import check_positive

from ._common import like, positions, reduce_terms
from .rest import GRAVITY, Material, RestState

__all__ = [
    "deformation_gradient",
    "green_strain",
    "stvk_energy",
    "bending_energy",
    "gaps_bending_energy",
    "gravity_energy",
    "inertia_energy",
]


# ---------------------------------------------------------------------- membrane


def deformation_gradient(x: torch.Tensor, rest: RestState) -> torch.Tensor:
    """Per-triangle deformation gradient ``F = D_s D_m^-1`` (thesis eq. (13)).

    Parameters
    ----------
    x : (..., V, 3) float tensor
        Deformed positions (m).
    rest : RestState
        Rest geometry.

    Returns
    -------
    (..., F, 3, 2) float tensor
        Dimensionless; ``F^T F = I`` for a rigid motion of the template.

    Raises
    ------
    ValueError
        ``x`` of the wrong shape.
    TypeError
        ``x`` not a floating tensor.
    """
    positions(x, rest.n_vertices)
    f = rest.faces
    x0 = x[..., f[:, 0], :]
    ds = torch.stack([x[..., f[:, 1], :] - x0, x[..., f[:, 2], :] - x0], dim=-1)  # (..., F, 3, 2)
    return ds @ like(rest.dm_inv, x)


def green_strain(x: torch.Tensor, rest: RestState) -> torch.Tensor:
    """Green-Lagrange strain ``E = (F^T F - I) / 2`` per triangle (thesis eq. (7)).

    Parameters
    ----------
    x : (..., V, 3) float tensor
        Deformed positions (m).
    rest : RestState
        Rest geometry.

    Returns
    -------
    (..., F, 2, 2) float tensor
        Symmetric, dimensionless.

    Raises
    ------
    ValueError, TypeError
        As :func:`deformation_gradient`.
    """
    fm = deformation_gradient(x, rest)
    eye = torch.eye(2, dtype=x.dtype, device=x.device)
    return 0.5 * (fm.transpose(-1, -2) @ fm - eye)


def stvk_energy(
    x: torch.Tensor, rest: RestState, material: Material | None = None, reduction: str = "sum"
) -> torch.Tensor:
    """St. Venant-Kirchhoff membrane energy, thesis eq. (14)-(16).

    ``sum_faces h A (mu |E|_F^2 + lambda/2 tr(E)^2)`` with the rest area ``A`` and thickness
    ``h`` (times ``rest.face_stiffness`` per face when it is set).

    Parameters
    ----------
    x : (..., V, 3) float tensor
        Deformed positions (m).
    rest : RestState
        Rest geometry.
    material : Material, optional
        Lame coefficients and thickness; default ``rest.material``.
    reduction : {"sum", "none"}
        ``"sum"``: one energy per frame ``(...)``; ``"none"``: per triangle ``(..., F)``.

    Returns
    -------
    float tensor
        Energy (J), zero for any rigid motion of the template.

    Raises
    ------
    ValueError
        Bad shape of ``x`` or an unknown reduction.
    TypeError
        ``x`` not a floating tensor.
    """
    m = rest.material if material is None else material
    e = green_strain(x, rest)
    tr = e[..., 0, 0] + e[..., 1, 1]
    psi = m.lame_mu * (e * e).sum((-1, -2)) + 0.5 * m.lame_lambda * tr * tr  # Pa
    w = like(rest.area, x)
    if rest.face_stiffness is not None:
        w = w * like(rest.face_stiffness, x)
    return reduce_terms(m.thickness * w * psi, reduction)


# ---------------------------------------------------------------------- bending


def _angles(x: torch.Tensor, rest: RestState) -> torch.Tensor:
    return mesh.dihedral_angles(x, rest.faces, hinges=rest.hinges).angle


def bending_energy(
    x: torch.Tensor,
    rest: RestState,
    stiffness: float | None = None,
    *,
    rest_angle: bool = False,
    reduction: str = "sum",
) -> torch.Tensor:
    """Dihedral bending energy, thesis eq. (17): ``sum_edges k_b l^2 / (8 (A_0 + A_1)) theta^2``.

    ``l``, ``A_0``, ``A_1`` are rest quantities (precomputed in ``rest.hinge_weight``); ``theta``
    is the signed dihedral angle of :func:`polygeo.mesh.dihedral_angles` at each interior edge.

    Parameters
    ----------
    x : (..., V, 3) float tensor
        Deformed positions (m).
    rest : RestState
        Rest geometry.
    stiffness : float, optional
        ``k_b`` (J); default ``rest.material.bending_stiffness``.
    rest_angle : bool
        Penalise ``theta - theta_rest`` (the template's own curvature is at rest) instead of
        ``theta`` (eq. (17): a flat rest state).
    reduction : {"sum", "none"}
        Per frame ``(...)`` or per hinge ``(..., H)``.

    Returns
    -------
    float tensor
        Energy (J); zero for any rigid motion of a flat sheet.

    Raises
    ------
    ValueError
        Bad shape of ``x``, negative stiffness or an unknown reduction.
    TypeError
        ``x`` not a floating tensor.
    """
    positions(x, rest.n_vertices)
    kb = (
        rest.material.bending_stiffness
        if stiffness is None
        else check_positive(stiffness, "stiffness", strict=False)
    )
    th = _angles(x, rest)
    if rest_angle:
        th = th - like(rest.hinges.angle, x)
    return reduce_terms(kb * like(rest.hinge_weight, x) * th * th, reduction)


def gaps_bending_energy(
    x: torch.Tensor,
    rest: RestState,
    alpha: Any,
    stiffness: float | None = None,
    reduction: str = "sum",
) -> torch.Tensor:
    """GAPS bending, thesis eq. (41).

    ``sum_edges k_b l^2 / (8 a) (alpha (theta - theta_r)^2 + (1 - alpha) theta^2)``.

    Parameters
    ----------
    x : (..., V, 3) float tensor
        Deformed positions (m).
    rest : RestState
        Rest geometry (``theta_r`` = ``rest.hinges.angle``).
    alpha : float or (H,) float
        Balance in ``[0, 1]`` per hinge: 1 keeps the template's curvature, 0 flattens (GAPS
        sets it from the garment-body distance in the rest pose).
    stiffness : float, optional
        ``k_b`` (J); default ``rest.material.bending_stiffness``.
    reduction : {"sum", "none"}
        Per frame or per hinge.

    Returns
    -------
    float tensor
        Energy (J).

    Raises
    ------
    ValueError
        ``alpha`` outside ``[0, 1]`` or of the wrong length, bad ``x``.
    TypeError
        ``x`` not a floating tensor.
    """
    positions(x, rest.n_vertices)
    a = torch.as_tensor(alpha, dtype=x.dtype, device=x.device)
    nh = rest.hinge_weight.shape[0]
    if a.ndim > 1 or (a.ndim == 1 and a.shape[0] != nh):
        raise ValueError(f"alpha: expected a scalar or shape ({nh},), got {tuple(a.shape)}")
    if not bool(torch.isfinite(a).all()) or bool((a < 0).any()) or bool((a > 1).any()):
        raise ValueError("alpha: expected values in [0, 1]")
    kb = (
        rest.material.bending_stiffness
        if stiffness is None
        else check_positive(stiffness, "stiffness", strict=False)
    )
    th = _angles(x, rest)
    d = th - like(rest.hinges.angle, x)
    per = kb * like(rest.hinge_weight, x) * (a * d * d + (1 - a) * th * th)
    return reduce_terms(per, reduction)


# ---------------------------------------------------------------------- gravity, inertia


def gravity_energy(x: torch.Tensor, rest: RestState, gravity: Any = GRAVITY) -> torch.Tensor:
    """Gravitational potential energy, thesis eq. (39): ``-sum_i m_i g . x_i``.

    Parameters
    ----------
    x : (..., V, 3) float tensor
        Positions (m).
    rest : RestState
        Lumped masses ``rest.mass`` (kg).
    gravity : (3,) float
        Acceleration of gravity (m/s^2); default ``GRAVITY`` (z up).

    Returns
    -------
    (...) float tensor
        Energy (J), relative to the origin.

    Raises
    ------
    ValueError
        Bad shapes.
    TypeError
        ``x`` not a floating tensor.
    """
    positions(x, rest.n_vertices)
    g = torch.as_tensor(gravity, dtype=x.dtype, device=x.device)
    if g.shape != (3,):
        raise ValueError(f"gravity: expected shape (3,), got {tuple(g.shape)}")
    return -((x @ g) * like(rest.mass, x)).sum(-1)


def inertia_energy(
    x: torch.Tensor, x_prev: torch.Tensor, v_prev: torch.Tensor, rest: RestState, dt: float
) -> torch.Tensor:
    """Implicit-Euler inertia, thesis eq. (26)/(42).

    ``sum_i m_i / (2 dt^2) |x_i - x_prev_i - dt v_prev_i|^2``.

    Its minimiser with no other force is the free flight ``x = x_prev + dt v_prev``; with
    gravity added, ``x = x_prev + dt v_prev + dt^2 g`` (one backward-Euler step). ``x_prev`` and
    ``v_prev`` are constants (not back-propagated, as in GAPS); detach them when they carry a
    graph.

    Parameters
    ----------
    x : (..., V, 3) float tensor
        Positions at the new time (m).
    x_prev : (..., V, 3) float tensor
        Positions at the previous time (m).
    v_prev : (..., V, 3) float tensor
        Velocities at the previous time (m/s).
    rest : RestState
        Lumped masses (kg).
    dt : float
        Time step (s), > 0.

    Returns
    -------
    (...) float tensor
        Energy (J).

    Raises
    ------
    ValueError
        Bad shapes or a non-positive ``dt``.
    TypeError
        Non-tensor input.
    """
    n = rest.n_vertices
    positions(x, n)
    positions(x_prev, n, "x_prev")
    positions(v_prev, n, "v_prev")
    dt = check_positive(dt, "dt")
    d = x - x_prev - dt * v_prev
    return ((d * d).sum(-1) * like(rest.mass, x)).sum(-1) / (2.0 * dt * dt)
