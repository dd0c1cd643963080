"""Physics reference drapes: the energies of :mod:`draping.physics` minimised per frame.

A dynamic frame is one step of backward Euler written as a minimisation (seed thesis eq.
(21)-(26)): ``x_{t+1} = argmin_x  1/(2 dt^2) |x - x_t - dt v_t|_M^2 + P(x)`` with ``P`` the
membrane (StVK), bending, gravity and body-collision energies, then ``v_{t+1} = (x_{t+1} - x_t) /
dt``. A static drape minimises ``P`` alone. Every solve stops on one rule, stated in
:class:`SolverSettings`: the residual force ``|grad E|`` (over the free vertices, 2-norm) falls
below ``tol`` times the weight of the garment ``|M g|`` (2-norm), or ``max_iter`` is reached.

Body contact follows SNUG and GAPS: a body query gives, for the garment vertices, the signed
distance ``d`` and outward normal ``n`` of the body; the collision energy is applied to the
distance to the body's tangent plane ``n . (x - p)`` with ``p = x - d n`` (linear in ``x``),
re-queried every ``requery_every`` iterations (the minimisation restarts its memory there).
Dynamic frames add lagged Coulomb friction against the body (``SolverSettings.friction``,
:func:`draping.physics.friction_energy`): the slip of each vertex in contact is measured
against where the body under it moved (``body_motion``), its normal force is the collision
penalty's at the last query. A dynamic frame starts from ``x0`` (default the free fall;
:func:`project_outside` moves a start out of the body).

Solvers (``SolverSettings.method``, implemented in ``draping._minimize`` on the fused kernels
of :mod:`draping.physics.fused`):

- ``"newton"`` (default): truncated Newton; positive semi-definite element Hessians
  (``SolverSettings.hessian``) assembled into a sparse block matrix, each Newton
  system solved by conjugate gradients preconditioned with a sparse factorisation of
  ``M / dt^2 + K`` (``K`` a stiffness-weighted graph Laplacian shared by x, y and z, plus the
  contact stiffness on its diagonal, factorised at each body query), capped at
  ``cg_max_iter`` iterations, stopped at negative curvature; backtracking line search;
  after the last body query, steps corrected by the exact curvature over the Newton
  direction and the previous step (``SolverSettings.subspace``);
- ``"pqn"``: L-BFGS whose initial inverse Hessian is that factorisation (Liu, Bouaziz, Kavan
  2017, "Quasi-Newton methods for real-time simulation of hyperelastic materials");
- ``"lbfgs"``: plain L-BFGS.

Every accepted step lowers the energy (Armijo line search) until the body is re-queried.
``"newton"`` is the default because it was the fastest at equal tolerance in
``benchmarks/bm_drape.py --sections solver`` (a 1 m sheet falling onto a 0.3 m sphere, three
frames of 1/30 s, one thread on a shared 2-core machine under a load of about 12): seconds per
frame at ``tol = 1e-2`` for 2025 / 5041 / 10000 vertices, newton 0.30 / 0.69 / 2.3, pqn
1.2 / 5.2 / 13.4, lbfgs 1.1 / 3.2 (10k not run); at ``tol = 1e-3`` (2025 vertices) newton
4.1, pqn 2.7, lbfgs 1.6. The quasi-Newton minimisers stop at lower energies for a given
``tol`` (mean distance to a 1e-4 solve at 2025 vertices: pqn 0.06 mm, newton 0.85 mm at
``tol = 1e-2``), so at 2025 vertices pqn is the most accurate per second beyond the default
tolerance; from 5041 vertices newton is both faster and closer (0.04 mm at ``1e-3`` in 4.6 s
against pqn's 0.55 mm at ``1e-2`` in 5.2 s). Frames where the sheet buckles on impact need
tens of Newton iterations. Since the preconditioner is factorised without pivoting, CPU
seconds per frame of the 2025-vertex sheet (``--quick``, load about 33): newton 0.086 / 0.137
at ``tol = 1e-2`` / ``1e-3``, pqn 0.118 / 0.181, lbfgs 0.159 / 0.264.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import torch

from polygeo.checks import (
    as_tensor,
    check_choice,
    check_finite,
    check_int,
    check_positive,
    check_shape,
)

from . import _minimize, physics
from .collision import QueryFn, plane_query, sphere_query

__all__ = [
    "QueryFn",
    "SolverSettings",
    "DrapeResult",
    "sphere_query",
    "plane_query",
    "frame_energy",
    "drape_static",
    "drape_step",
    "drape_sequence",
    "free_fall",
    "project_outside",
]


@dataclass(frozen=True)
class SolverSettings:
    """Settings of the reference solver (SI units).

    Parameters
    ----------
    method : {"newton", "pqn", "lbfgs"}
        Minimiser (module docstring).
    tol : float
        Stopping rule: ``|grad E|_2 <= tol |M g|_2`` over the free vertices (dimensionless).
        The default ``1e-2`` (residual force a hundredth of the garment's weight) left the
        newton drapes of the sheet-over-sphere benchmark (``benchmarks/bm_drape.py``)
        0.85 / 0.91 mm (mean; 3.7 / 3.5 mm max) from solves at ``1e-4`` for 2025 / 5041
        vertices, 7 to 14 times faster than ``1e-3`` (0.15 / 0.04 mm). On the 5,000-vertex
        T-shirt of the walk (``bm_drape.py --sections walk``: each of the 59 dynamic frames
        solved again from the same state at each tolerance; one thread, load about 6; inner
        solves then by an Eisenstat-Walker forcing term, as fast there as today's), CPU s
        per frame mean (max) and distance to a ``1e-4`` solve, mean over vertices / max over
        vertices on the median frame: ``3e-3`` 1.03 (2.14) s, 0.004 / 0.14 mm; ``1e-2`` 0.77
        (1.38) s, 0.010 / 0.35 mm; ``2e-2`` 0.64 (1.11) s, 0.017 / 0.52 mm; ``5e-2`` 0.53 (1.03)
        s, 0.032 / 1.1 mm (``1e-4``: 2.04 s). Loosening buys little (the body re-queries of the
        first iterations cost about 15 Newton steps at any tolerance) and moves the vertices
        where a wrinkle forms by millimetres (frames with a vertex more than 1 mm off: 12 of 59
        at ``1e-2``, 22 at ``2e-2``, 31 at ``5e-2``), so ``1e-2`` stays. Those figures are
        plain Newton's; with the subspace steps (``subspace``, the default since) the same
        replay (``--walk-tols 1e-2,2e-2``, load 3.6-7) gave at ``1e-2`` 0.66 s mean, 0.63
        median, 1.14 max (2 of 59 frames over 1 s), 0.0018 / 0.046 mm (2 frames with a vertex
        over 1 mm off, 2.7 mm at worst); at ``2e-2`` 0.59 / 0.59 / 0.88 s (none over 1 s),
        0.0042 / 0.095 mm (5 frames over 1 mm, 3.8 mm at worst); plain Newton at ``1e-2`` in
        the same run 0.69 / 0.64 / 1.54 s (5 over 1 s), 0.0098 / 0.39 mm (14 frames over 1 mm,
        3.8 mm at worst); ``1e-4`` itself took 0.98 s mean against 2.04 before.
    max_iter : int
        Iteration cap per frame.
    history : int
        Quasi-Newton memory (pairs).
    collision_stiffness : float
        ``k_c`` of the cubic collision penalty (J/m^3). The default 1e4 suits light contact
        (the sheet-over-sphere benchmark). A 1.2 m sheet of 2025 vertices dropped on the Anny
        body (15 frames) kept 0.3-3.5 % of its vertices inside the body (down to 17.7 mm) with
        1e4, up to 1.3 % (7.4 mm) with 1e5 and at most 0.44 % (1.4 mm) with 1e6, which took
        about 5 times longer per frame (that sheet had no friction and no clearance start).
        With friction, the projected start and the contact-aware preconditioner, 1e4 keeps the
        5,000-vertex T-shirt and dress of the walk at eps_c <= 0.04 % (README), and replaying
        T-shirt frames 6, 12 and 20 took 2.3-2.7 CPU s with 1e4, 3.9 with 1e5 and 7.4 with 1e6
        (no vertex inside in any): 1e4 stays the default.
    collision_eps : float
        Collision clearance ``epsilon`` (m).
    requery_every : int
        Iterations between body queries (the tangent planes are refreshed). The default 3 was
        measured on one dynamic frame of the shipped 5,000-vertex T-shirt on the walk (frame 3,
        one thread, shared machine): 1.36 CPU s / 18 iterations against 2.76 s / 34 (every 10)
        and 5.08 s / 47 (every 30), the same energy (0.24837 J) and no vertex inside the body.
    max_requery : int
        Body queries per frame after the first; then the planes stay fixed until the
        tolerance is met.
    friction : float
        Coulomb friction coefficient ``mu`` between garment and body in dynamic frames
        (dimensionless; 0: frictionless). Lagged (IPC, Li et al. 2020): the normal force of each
        vertex is the collision penalty's at the last body query, and the slip is measured
        against where the vertex would be had it moved with the body (``body_motion`` of
        :func:`drape_step`); smoothed below ``friction_eps`` of slip (static friction).
        Without it a T-shirt slides off the shoulders of a walking body (measured: the
        5,000-vertex T-shirt on the walk was down at the hips by frame 21 with 0).
    friction_eps : float
        Slip (m) below which friction is static.
    bending : bool
        Include the dihedral bending energy (eq. (17), flat rest).
    gravity : tuple of float
        Acceleration of gravity (m/s^2).
    static_dt : float
        Pseudo time step (s) of the preconditioner's mass term in static drapes (keeps it
        definite; does not change the minimised energy).
    hessian : {"projected", "exact"}
        Membrane Hessian of ``"newton"``: ``"projected"`` (default; positive part of the
        stress: positive semi-definite) or ``"exact"`` (indefinite where the cloth is
        compressed; conjugate gradients stop at negative curvature). Measured on the
        5,000-vertex garments of the walk (one thread, load 3-6): the exact one took the
        T-shirt's 60 frames in 1,940 Newton iterations against 2,049, the dress's in 2,254
        against 2,060; on the four slowest T-shirt / dress frames, with ``cg_max_iter`` 20,
        3.9 / 4.8 CPU s against 5.9 / 3.4 for the projected one: no clear winner, so the
        default stays the Hessian the shipped reference drapes were made with.
    cg_max_iter : int
        Cap of conjugate-gradient iterations per Newton step (``"newton"``). Where the cloth
        buckles, long inner solves buy little: on the four slowest walk frames of the T-shirt
        (3, 8, 11, 55) and of the dress (13, 19, 25, 27), 7.3 / 4.5 CPU s with 200 (the
        default), 5.9 / 3.4 with 20 (drapes 0.001-0.002 mm apart on average; one thread, load
        about 4), 7.7 / - with 40, slower again with 10. But a small cap starves tight
        tolerances: with 20, a dynamic frame of a sheet on a sphere at ``tol = 1e-4`` did not
        converge in 300 iterations (and doubling the cap whenever ``|g|`` stalled undid the
        gain at ``1e-2``), so 20 is an opt-in for the default tolerance only.
    subspace : bool
        ``"newton"`` only: after the last body query (the tangent planes fixed), each step
        minimises the exact energy's quadratic model over the Newton direction and the
        previous step, in a trust region (``draping._minimize.subspace_step``), with inner
        solves to a forcing term of at most 0.2 once ``|g| < |M g|``. Where a wrinkle
        buckles, the projected Hessian overestimates the curvature along the Newton step 4-8
        times and hides a saddle: plain Newton creeps along it (0.1 mm per step) and can meet
        the ``1e-2`` rule while still on the saddle, millimetres from the minimum. Paired
        replays of walk frames from the same states (one thread, load about 7; distance to a
        ``1e-4`` solve with the same tangent planes, mean / max over vertices): T-shirt frames
        11, 26, 55: 4.06 against 5.34 CPU s, 141 against 188 Newton steps, 0.0008 / 0.029 mm
        against 0.011 / 3.49 mm; dress frames 13, 22, 26, 38: 5.47 against 5.12 CPU s, 201
        against 214 steps, 0.011 / 4.8 mm against 0.037 / 7.1 mm (eight slow dress frames:
        7.11 against 7.12 CPU s, 346 against 396 steps). False: plain truncated Newton.
    """

    method: str = "newton"
    tol: float = 1e-2
    max_iter: int = 2000
    history: int = 8
    collision_stiffness: float = 1e4
    collision_eps: float = 2e-3
    requery_every: int = 3
    max_requery: int = 5
    friction: float = 0.3
    friction_eps: float = 1e-4
    bending: bool = True
    gravity: tuple[float, float, float] = physics.GRAVITY
    static_dt: float = 0.05
    hessian: str = "projected"
    cg_max_iter: int = 200
    subspace: bool = True

    def __post_init__(self) -> None:
        check_choice(self.method, "method", ("newton", "pqn", "lbfgs"))
        check_choice(self.hessian, "hessian", ("exact", "projected"))
        for name in ("tol", "static_dt"):
            check_positive(getattr(self, name), name)
        check_positive(self.friction_eps, "friction_eps")
        for name in ("collision_stiffness", "collision_eps", "friction"):
            check_positive(getattr(self, name), name, strict=False)
        for name in ("max_iter", "history", "requery_every", "cg_max_iter"):
            check_int(getattr(self, name), name, low=1)
        check_int(self.max_requery, "max_requery", low=0)
        if not isinstance(self.subspace, bool):
            raise TypeError(f"subspace: expected a bool, got {type(self.subspace).__name__}")
        g = np.asarray(self.gravity, dtype=np.float64)
        if g.shape != (3,) or not np.isfinite(g).all():
            raise ValueError(f"gravity: expected 3 finite values, got {self.gravity}")


class DrapeResult(NamedTuple):
    """One solved frame.

    Attributes
    ----------
    x : (V, 3) float64 tensor
        Positions (m).
    v : (V, 3) float64 tensor
        Velocities (m/s); zeros for a static drape.
    energy : float
        Final energy (J), with the last tangent planes.
    residual : float
        Final ``|grad E| / |M g|``.
    iterations : int
        Iterations used.
    converged : bool
        Whether the stopping rule was met before ``max_iter``.
    seconds : float
        Wall time of the solve (s).
    trace : list of float
        Energy after each accepted iteration (J); entries after a re-query use the new planes.
    """

    x: torch.Tensor
    v: torch.Tensor
    energy: float
    residual: float
    iterations: int
    converged: bool
    seconds: float
    trace: list[float]


# ---------------------------------------------------------------------- energy


def frame_energy(
    x: torch.Tensor,
    rest: physics.RestState,
    settings: SolverSettings | None = None,
    *,
    x_prev: torch.Tensor | None = None,
    v_prev: torch.Tensor | None = None,
    dt: float | None = None,
    anchor: torch.Tensor | None = None,
    normal: torch.Tensor | None = None,
    friction_reference: torch.Tensor | None = None,
    friction_weight: torch.Tensor | None = None,
) -> torch.Tensor:
    """The energy the reference solver minimises, in torch (J).

    Membrane (StVK) + bending (eq. (17), if ``settings.bending``) + gravity + collision on the
    tangent planes ``(anchor, normal)`` (if given) + inertia (if ``x_prev`` is given).

    Parameters
    ----------
    x : (..., V, 3) float tensor
        Positions (m).
    rest : physics.RestState
        Garment rest geometry and material.
    settings : SolverSettings, optional
        Which terms and their constants.
    x_prev, v_prev : (V, 3) float tensor, optional
        Previous positions (m) and velocities (m/s) of a dynamic frame.
    dt : float, optional
        Time step (s), with ``x_prev``.
    anchor, normal : (V, 3) float tensor, optional
        Closest body points (m) and outward normals.
    friction_reference, friction_weight : (V, 3), (V,) float tensor, optional
        Sticking positions (m) and ``mu`` times the lagged normal forces (N) of the friction
        term (:func:`draping.physics.friction_energy`, with ``normal``).

    Returns
    -------
    (...) float tensor
        Energy (J).

    Raises
    ------
    ValueError
        Bad shapes, ``x_prev`` without ``v_prev`` and ``dt``, ``anchor`` without ``normal``.
    """
    settings = SolverSettings() if settings is None else settings
    e = physics.stvk_energy(x, rest) + physics.gravity_energy(x, rest, settings.gravity)
    if settings.bending:
        e = e + physics.bending_energy(x, rest)
    if (anchor is None) != (normal is None):
        raise ValueError("anchor, normal: expected both or neither")
    if anchor is not None:
        d = physics.plane_distance(x, anchor, normal)
        e = e + physics.collision_energy(d, settings.collision_stiffness, settings.collision_eps)
    if friction_weight is not None:
        if normal is None or friction_reference is None:
            raise ValueError("friction_weight: expected normal and friction_reference with it")
        e = e + physics.friction_energy(x, friction_reference, normal, friction_weight,
                                        settings.friction_eps)
    if x_prev is not None:
        if v_prev is None or dt is None:
            raise ValueError("x_prev: expected v_prev and dt with it")
        e = e + physics.inertia_energy(x, x_prev, v_prev, rest, dt)
    return e


def _planes(
    x: torch.Tensor, query: QueryFn | None
) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """Tangent planes ``(anchor, normal)`` of the body under each vertex (module docstring)."""
    if query is None:
        return None, None
    ans = query(x.detach())
    closest = getattr(ans, "closest", None)
    if closest is not None:  # a draping.collision.SignedDistance
        d, n = ans.distance, ans.normal
    else:
        d, n = ans
    d = torch.as_tensor(d, dtype=x.dtype).reshape(-1)
    n = torch.as_tensor(n, dtype=x.dtype).reshape(-1, 3)
    if d.shape[0] != x.shape[0] or n.shape[0] != x.shape[0]:
        raise ValueError(
            f"query: expected distances (V,) and normals (V, 3) for V = {x.shape[0]}, got "
            f"{tuple(d.shape)} and {tuple(n.shape)}"
        )
    if bool(torch.isnan(d).any()) or bool((d == -torch.inf).any()):
        raise ValueError("query: returned NaN or -inf distances")
    far = torch.isinf(d)  # beyond the query's max_distance: no contact possible
    ok_n = torch.isfinite(n).all(-1)
    if not bool((ok_n | far).all()):
        raise ValueError("query: returned non-finite normals")
    up = torch.tensor([0.0, 0.0, 1.0], dtype=x.dtype)
    n = torch.where(far[:, None], up, n)
    d = torch.where(far, torch.full_like(d, 1e3), d)
    if closest is not None:
        anchor = torch.as_tensor(closest, dtype=x.dtype).reshape(-1, 3)
        anchor = torch.where(
            far[:, None] | ~torch.isfinite(anchor), x.detach() - d[:, None] * n, anchor
        )
    else:
        anchor = x.detach() - d[:, None] * n
    return anchor, n


# ---------------------------------------------------------------------- solve


class _Problem(NamedTuple):
    rest: physics.RestState
    settings: SolverSettings
    query: QueryFn | None
    free: torch.Tensor  # (V,) bool
    weight: float  # |M g| (N)
    x_prev: torch.Tensor | None
    v_prev: torch.Tensor | None
    dt: float | None
    body_motion: torch.Tensor | None = None


def _objective(pb: _Problem, x: np.ndarray) -> _minimize.Objective:
    st = pb.settings
    anchor, normal = _planes(torch.from_numpy(x), pb.query)
    x_hat = None
    if pb.x_prev is not None:
        x_hat = (pb.x_prev + pb.dt * pb.v_prev).numpy()
    f_ref = f_w = None
    if pb.x_prev is not None and anchor is not None and st.friction > 0:
        a, n = anchor.numpy(), normal.numpy()
        pen = np.maximum(st.collision_eps - ((x - a) * n).sum(1), 0.0)
        f_w = st.friction * 3.0 * st.collision_stiffness * pen**2  # mu * lagged normal force
        f_ref = pb.x_prev.numpy()
        if pb.body_motion is not None:
            f_ref = f_ref + pb.body_motion.numpy()
    return _minimize.Objective(
        _structure(pb.rest),
        pb.rest,
        np.asarray(st.gravity, dtype=np.float64),
        st.bending,
        float(st.collision_stiffness),
        float(st.collision_eps),
        x_hat,
        pb.dt,
        None if anchor is None else anchor.numpy(),
        None if normal is None else normal.numpy(),
        pb.free.numpy(),
        f_ref,
        f_w,
        float(st.friction_eps),
        st.hessian == "projected",
    )


_STRUCTURES: dict[int, tuple[physics.RestState, _minimize.Structure]] = {}


def _structure(rest: physics.RestState) -> _minimize.Structure:
    """The garment's sparse pattern, cached per RestState object (a few entries)."""
    hit = _STRUCTURES.get(id(rest))
    if hit is not None and hit[0] is rest:
        return hit[1]
    if len(_STRUCTURES) > 8:
        _STRUCTURES.clear()
    st = _minimize.structure(rest)
    _STRUCTURES[id(rest)] = (rest, st)
    return st


#: Weight of the contact stiffness (collision along the normal, friction along the tangent
#: plane) added to the diagonal of the preconditioner ``M / dt^2 + K`` at each body query,
#: as an isotropic stand-in for the 3x3 contact blocks (the factorisation is shared by x, y, z).
#: Replaying frames 6, 12 and 20 of the 5,000-vertex T-shirt on the walk (one thread, load
#: 19-23): 3.54-3.85 CPU s without it, 2.61 with weight 1, 2.32-2.35 with 1/3; same energies
#: to 1e-5 J and eps_e to 0.002 %.
_CONTACT_SCALE = 1.0 / 3.0


def _solve(x0: torch.Tensor, pb: _Problem) -> tuple[torch.Tensor, float, float, int, list]:
    """Minimise one frame, re-querying the body every ``requery_every`` iterations.

    After ``max_requery`` re-queries the tangent planes stay fixed and the minimiser runs to
    the tolerance: on a mesh body the closest feature of a vertex can alternate between
    faces from one query to the next, which would otherwise cycle until ``max_iter``.
    """
    st = pb.settings
    x = x0.numpy().copy()
    ob = _objective(pb, x)
    tol_abs = st.tol * pb.weight
    precond = None
    if st.method in ("newton", "pqn"):
        precond = _minimize.laplacian_factor(ob, pb.dt or st.static_dt,
                                             _minimize.contact_diagonal(ob, x, _CONTACT_SCALE))
    done, trace, rounds = 0, [], 0
    while True:
        last = pb.query is None or rounds >= st.max_requery
        chunk = st.max_iter - done if last else min(st.requery_every, st.max_iter - done)
        if st.method == "newton":
            out = _minimize.newton(ob, x, tol_abs, chunk, precond, pb.weight, st.cg_max_iter,
                                   subspace=st.subspace and last)
        else:
            out = _minimize.quasi_newton(ob, x, tol_abs, chunk, st.history, precond)
        x, done = out.x, done + out.iterations
        trace += out.trace
        if last:
            e, gn = out.energy, out.grad_norm
            break
        ob = _objective(pb, x)
        rounds += 1
        if precond is not None:  # the contacts changed: refactorise (12 ms for 5k vertices)
            precond = _minimize.laplacian_factor(
                ob, pb.dt or st.static_dt, _minimize.contact_diagonal(ob, x, _CONTACT_SCALE))
        e, g, _ = _minimize.evaluate(ob, x)
        gn = float(np.linalg.norm(g))
        if gn <= tol_abs or done >= st.max_iter or out.iterations == 0:
            break
    return torch.from_numpy(x), e, gn / pb.weight, done, trace


# ---------------------------------------------------------------------- public drivers


def free_fall(x: Any, v: Any, dt: float, gravity: Sequence[float] = physics.GRAVITY
              ) -> torch.Tensor:
    """Free-fall prediction ``x + dt v + dt^2 g`` (m): the minimiser of inertia + gravity.

    Parameters
    ----------
    x, v : (V, 3) float
        Positions (m) and velocities (m/s).
    dt : float
        Time step (s), > 0.
    gravity : (3,) float
        m/s^2.

    Returns
    -------
    (V, 3) float64 tensor

    Raises
    ------
    ValueError
        Bad shapes, non-finite values, ``dt <= 0``.
    """
    xt = as_tensor(x, "x").detach().to(torch.float64)
    check_shape(xt, "x", ("V", 3))
    vt = _check_positions(v, xt.shape[0], "v")
    dt = check_positive(dt, "dt")
    return xt + dt * vt + dt * dt * torch.as_tensor(gravity, dtype=torch.float64)


def project_outside(x: Any, query: QueryFn, clearance: float = 0.0) -> torch.Tensor:
    """Move the vertices closer to the body than ``clearance`` out along the body normal.

    A vertex at signed distance ``d < clearance`` (inside the body when ``d < 0``) moves by
    ``(clearance - d) n`` onto the tangent plane of its closest body point, offset by
    ``clearance``; the others stay. A cheap initial guess for :func:`drape_step` (the free
    fall or the skinned garment can start inside a moving body).

    Parameters
    ----------
    x : (V, 3) float
        Positions (m).
    query : QueryFn
        The body.
    clearance : float
        Target distance (m), >= 0 (e.g. the collision clearance ``collision_eps``).

    Returns
    -------
    (V, 3) float64 tensor

    Raises
    ------
    ValueError
        Bad shapes, non-finite positions, a negative clearance or a bad query answer.
    """
    xt = as_tensor(x, "x").detach().to(torch.float64)
    check_shape(xt, "x", ("V", 3))
    check_finite(xt, "x")
    c = check_positive(clearance, "clearance", strict=False)
    anchor, normal = _planes(xt, query)
    d = ((xt - anchor) * normal).sum(-1)
    return xt + (c - d).clamp_min(0.0)[:, None] * normal



def _check_positions(x: Any, n: int, name: str) -> torch.Tensor:
    t = as_tensor(x, name)
    check_shape(t, name, (n, 3))
    check_finite(t, name)
    return t.detach().to(torch.float64)


def _free_mask(pinned: Any, n: int) -> torch.Tensor:
    free = torch.ones(n, dtype=torch.bool)
    if pinned is None:
        return free
    p = torch.as_tensor(np.asarray(pinned))
    if p.dtype == torch.bool:
        if p.shape != (n,):
            raise ValueError(f"pinned: expected a ({n},) bool mask, got shape {tuple(p.shape)}")
        return ~p
    if p.is_floating_point() or p.ndim != 1:
        raise TypeError(f"pinned: expected vertex indices or a bool mask, got {p.dtype}")
    if p.numel() and (int(p.min()) < 0 or int(p.max()) >= n):
        raise ValueError(f"pinned: expected indices in [0, {n - 1}]")
    free[p.long()] = False
    return free


def _check_rest(rest: Any) -> int:
    if not isinstance(rest, physics.RestState):
        raise TypeError(f"rest: expected a physics.RestState, got {type(rest).__name__}")
    return rest.n_vertices


def _problem(rest, settings, query, pinned, x_prev, v_prev, dt, body_motion=None) -> _Problem:
    _check_rest(rest)
    settings = SolverSettings() if settings is None else settings
    if not isinstance(settings, SolverSettings):
        raise TypeError(f"settings: expected SolverSettings, got {type(settings).__name__}")
    free = _free_mask(pinned, rest.n_vertices)
    mass = rest.mass.detach().double()
    weight = float(torch.linalg.norm(mass[free])) * float(np.linalg.norm(settings.gravity))
    if weight == 0:
        weight = float(torch.linalg.norm(mass[free])) * 9.81 or 1.0
    return _Problem(rest, settings, query, free, weight, x_prev, v_prev, dt, body_motion)


def drape_static(
    rest: physics.RestState,
    x0: Any,
    query: QueryFn | None = None,
    settings: SolverSettings | None = None,
    pinned: Any = None,
) -> DrapeResult:
    """Static drape: minimise membrane + bending + gravity + collision from ``x0``.

    The contact is frictionless: a garment must be held by the body's shape (a sleeve, a
    waistband) or by pinned vertices, otherwise its energy is unbounded below (a sheet slides
    off a sphere) and the solve ends at ``max_iter`` with ``converged`` False.

    Parameters
    ----------
    rest : physics.RestState
        Garment rest geometry and material.
    x0 : (V, 3) float
        Initial positions (m), e.g. the garment skinned to the posed body.
    query : QueryFn, optional
        The body (signed distance and normal); None for no body.
    settings : SolverSettings, optional
        Solver and energy constants.
    pinned : (V,) bool or (P,) int, optional
        Vertices held at their ``x0`` positions.

    Returns
    -------
    DrapeResult
        With zero velocities.

    Raises
    ------
    ValueError
        Bad shapes, non-finite positions, bad pinned indices or a bad query answer.
    TypeError
        Bad argument types.
    """
    x0 = _check_positions(x0, _check_rest(rest), "x0")
    pb = _problem(rest, settings, query, pinned, None, None, None)
    t0 = time.perf_counter()
    x, e, res, it, trace = _solve(x0, pb)
    sec = time.perf_counter() - t0
    return DrapeResult(x, torch.zeros_like(x), e, res, it, res <= pb.settings.tol, sec, trace)


def drape_step(
    rest: physics.RestState,
    x_prev: Any,
    v_prev: Any,
    dt: float,
    query: QueryFn | None = None,
    settings: SolverSettings | None = None,
    pinned: Any = None,
    x_pinned: Any = None,
    x0: Any = None,
    body_motion: Any = None,
) -> DrapeResult:
    """One backward-Euler frame (thesis eq. (25)-(26)) from ``(x_prev, v_prev)``.

    Parameters
    ----------
    rest : physics.RestState
        Garment rest geometry and material.
    x_prev, v_prev : (V, 3) float
        Positions (m) and velocities (m/s) at the previous frame.
    dt : float
        Time step (s), > 0 (1/30 for 30 fps motions).
    query : QueryFn, optional
        The body at the new frame; None for no body.
    settings : SolverSettings, optional
        Solver and energy constants.
    pinned : (V,) bool or (P,) int, optional
        Vertices prescribed at ``x_pinned`` (default: ``x_prev``, i.e. held still).
    x_pinned : (V, 3) float, optional
        Prescribed positions of the pinned vertices at the new frame (m).
    x0 : (V, 3) float, optional
        Initial guess of the minimisation (m); default the free fall ``x_prev + dt v_prev +
        dt^2 g``, which on a moving body can start vertices inside it (a garment resting on
        the shoulders of a walking body): pass e.g. :func:`project_outside` of it. The
        minimum does not depend on it where the energy is convex; it does where the body
        contact is (a vertex started deep inside a limb is pushed out the nearest way).
    body_motion : (V, 3) float, optional
        Displacement over the step of the body under each garment vertex (m), e.g. the
        skinned garment's; friction (``settings.friction``) resists slip relative to it.
        Default zero (a body at rest).

    Returns
    -------
    DrapeResult
        ``x`` at the new frame and ``v = (x - x_prev) / dt``.

    Raises
    ------
    ValueError
        Bad shapes, non-finite values, ``dt <= 0``.
    TypeError
        Bad argument types.
    """
    n = _check_rest(rest)
    xp = _check_positions(x_prev, n, "x_prev")
    vp = _check_positions(v_prev, n, "v_prev")
    dt = check_positive(dt, "dt")
    bm = None if body_motion is None else _check_positions(body_motion, n, "body_motion")
    pb = _problem(rest, settings, query, pinned, xp, vp, float(dt), bm)
    # start from x0, by default the free fall (the minimiser of inertia + gravity), pinned
    # vertices at their targets
    if x0 is None:
        x0 = free_fall(xp, vp, dt, pb.settings.gravity)
    else:
        x0 = _check_positions(x0, n, "x0")
    if x_pinned is not None:
        x0 = torch.where(pb.free[:, None], x0, _check_positions(x_pinned, n, "x_pinned"))
    else:
        x0 = torch.where(pb.free[:, None], x0, xp)
    t0 = time.perf_counter()
    x, e, res, it, trace = _solve(x0, pb)
    sec = time.perf_counter() - t0
    return DrapeResult(x, (x - xp) / dt, e, res, it, res <= pb.settings.tol, sec, trace)


def drape_sequence(
    rest: physics.RestState,
    x0: Any,
    queries: Sequence[QueryFn | None],
    dt: float,
    settings: SolverSettings | None = None,
    v0: Any = None,
    pinned: Any = None,
    pinned_positions: Sequence[Any] | None = None,
    project: bool = True,
) -> list[DrapeResult]:
    """A dynamic drape: one :func:`drape_step` per body frame.

    Parameters
    ----------
    rest : physics.RestState
        Garment rest geometry and material.
    x0 : (V, 3) float
        Positions at time 0 (m) (e.g. a static drape on the first pose).
    queries : sequence of QueryFn or None
        The body at frames 1..T.
    dt : float
        Time step (s).
    settings : SolverSettings, optional
        Solver and energy constants.
    v0 : (V, 3) float, optional
        Initial velocities (m/s); zeros by default.
    pinned : (V,) bool or (P,) int, optional
        Prescribed vertices.
    pinned_positions : sequence of (V, 3) float, optional
        Their positions at frames 1..T (default: held at ``x0``).
    project : bool
        Start each step from the free fall moved out of the body (:func:`project_outside`
        with the collision clearance) instead of the free fall itself.

    Returns
    -------
    list of DrapeResult
        Frames 1..T.

    Raises
    ------
    ValueError, TypeError
        As :func:`drape_step`.
    """
    n = _check_rest(rest)
    x = _check_positions(x0, n, "x0")
    v = torch.zeros_like(x) if v0 is None else _check_positions(v0, n, "v0")
    if pinned_positions is not None and len(pinned_positions) != len(queries):
        raise ValueError(
            f"pinned_positions: expected {len(queries)} frames, got {len(pinned_positions)}"
        )
    out = []
    for t, q in enumerate(queries):
        xp = None if pinned_positions is None else pinned_positions[t]
        guess = None
        if project and q is not None:
            eps = (SolverSettings() if settings is None else settings).collision_eps
            g = (SolverSettings() if settings is None else settings).gravity
            guess = project_outside(free_fall(x, v, dt, g), q, eps)
        r = drape_step(rest, x, v, dt, q, settings, pinned, xp, guess)
        out.append(r)
        x, v = r.x, r.v
    return out
