"""Minimisers of one frame's cloth energy for :mod:`draping.reference` (NumPy, float64, SI).

The objective is the energy of :func:`draping.reference.frame_energy` evaluated with the fused
kernels of :mod:`draping.physics.fused` (membrane, bending) plus closed forms for gravity,
inertia and the collision penalty on fixed tangent planes. Three minimisers share it:

- ``newton``: truncated Newton. The membrane Hessian with the positive part of the stress
  (``Objective.project_membrane``; the exact one, indefinite where the cloth is compressed,
  without it), the
  Gauss-Newton bending Hessian (:mod:`draping.physics.fused`), collision Hessians
  ``6 k_c p n n^T``, friction and the mass term are assembled into a sparse matrix of 3x3
  blocks on a pattern built once; the Newton system is solved by conjugate gradients
  preconditioned with the factorised Laplacian below, to a relative residual
  ``min(0.5, 3 sqrt(|g| / |M g|))`` (:func:`forcing_term`) or an iteration cap, stopped at negative
  curvature (Steihaug: the iterate so far, or the preconditioned gradient); backtracking line
  search. Optionally (``subspace``) each step is then corrected by the exact energy's
  curvature over the Newton direction and the previous step (:func:`subspace_step`).
- ``pqn``: L-BFGS whose initial inverse Hessian is that factorised Laplacian (Liu et al. 2017).
- ``lbfgs``: plain L-BFGS with the usual scaled identity.

Every accepted step lowers the energy (Armijo condition).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .physics import RestState, fused

__all__: list[str] = []


class Structure(NamedTuple):
    """Per-garment constants of the objective, computed once (:func:`structure`)."""

    faces: np.ndarray  # (F, 3) int64
    dm_inv: np.ndarray  # (F, 2, 2)
    area: np.ndarray  # (F,) m^2, times the face's stiffness multiplier (membrane weight)
    quads: np.ndarray  # (H, 4) int64
    weight: np.ndarray  # (H,)
    mass: np.ndarray  # (V,) kg
    edges: np.ndarray  # (E, 2)
    edge_length: np.ndarray  # (E,) m
    block_rows: np.ndarray  # (NB,) vertex row of each 3x3 block, CSR order
    block_cols: np.ndarray  # (NB,)
    indptr: np.ndarray  # (V + 1,)
    tri_map: np.ndarray  # (F, 3, 3) block index of corner pairs
    hinge_map: np.ndarray  # (H, 4, 4)
    diag_map: np.ndarray  # (V,)


def structure(rest: RestState) -> Structure:
    """Arrays and the sparse block pattern of a garment (numpy float64)."""
    f = rest.faces.numpy().astype(np.int64)
    quads = fused.hinge_quads(f, rest.hinges.edges, rest.hinges.faces)
    n = rest.n_vertices
    pairs_t = np.stack(np.broadcast_arrays(f[:, :, None], f[:, None, :]), -1)  # (F,3,3,2)
    pairs_h = np.stack(np.broadcast_arrays(quads[:, :, None], quads[:, None, :]), -1)
    keys = np.concatenate(
        [
            (pairs_t[..., 0] * n + pairs_t[..., 1]).ravel(),
            (pairs_h[..., 0] * n + pairs_h[..., 1]).ravel(),
            np.arange(n) * (n + 1),
        ]
    )
    uniq = np.unique(keys)
    rows, cols = uniq // n, uniq % n
    indptr = np.searchsorted(rows, np.arange(n + 1))
    tri_map = np.searchsorted(uniq, pairs_t[..., 0] * n + pairs_t[..., 1])
    hinge_map = np.searchsorted(uniq, pairs_h[..., 0] * n + pairs_h[..., 1])
    diag_map = np.searchsorted(uniq, np.arange(n) * (n + 1))
    return Structure(
        f,
        rest.dm_inv.detach().double().numpy(),
        _stiffness_area(rest),
        quads,
        rest.hinge_weight.detach().double().numpy(),
        rest.mass.detach().double().numpy(),
        rest.edges.numpy(),
        rest.edge_length.detach().double().numpy(),
        rows,
        cols,
        indptr,
        tri_map,
        hinge_map,
        diag_map,
    )


def _stiffness_area(rest: RestState) -> np.ndarray:
    """Rest areas (m^2) times ``rest.face_stiffness``: the membrane weight of each face."""
    area = rest.area.detach().double().numpy()
    if rest.face_stiffness is None:
        return area
    return area * rest.face_stiffness.detach().double().numpy()


class Objective(NamedTuple):
    """One frame's energy: constants, optional previous state and tangent planes (SI)."""

    st: Structure
    rest: RestState
    gravity: np.ndarray  # (3,) m/s^2
    bending: bool
    k_c: float  # J/m^3
    eps: float  # m
    x_hat: np.ndarray | None  # (V, 3) x_prev + dt v_prev, dynamic frames only
    dt: float | None
    anchor: np.ndarray | None  # (V, 3)
    normal: np.ndarray | None  # (V, 3)
    free: np.ndarray  # (V,) bool
    friction_ref: np.ndarray | None = None  # (V, 3) where a vertex sticking to the body goes
    friction_weight: np.ndarray | None = None  # (V,) mu * lagged normal force (N)
    friction_eps: float = 1e-4  # m: slip below which friction is static (smoothed)
    project_membrane: bool = False  # PSD (positive stress part) instead of exact membrane Hessian


def evaluate(
    ob: Objective, x: np.ndarray, want_grad: bool = True, want_hess: bool = False
) -> tuple[float, np.ndarray | None, sp.bsr_matrix | None]:
    """Energy (J), gradient (V, 3) with pinned rows zeroed, and the PSD Hessian (BSR)."""
    st, m = ob.st, ob.rest.material
    blocks = np.zeros((st.block_rows.shape[0], 3, 3)) if want_hess else None
    e, g, _ = fused.membrane(
        x,
        st.faces,
        st.dm_inv,
        st.area,
        m.thickness,
        m.lame_mu,
        m.lame_lambda,
        want_hess,
        blocks,
        st.tri_map,
        project=ob.project_membrane,
        want_grad=want_grad,
    )
    if ob.bending:
        eb, gb, _ = fused.bending(
            x,
            st.quads,
            st.weight,
            m.bending_stiffness,
            want_hess,
            blocks,
            st.hinge_map,
            want_grad=want_grad,
        )
        e += eb
        g += gb
    e -= float((st.mass * (x @ ob.gravity)).sum())
    g -= st.mass[:, None] * ob.gravity
    diag = np.zeros((x.shape[0], 3, 3)) if want_hess else None
    if ob.anchor is not None:
        d = ((x - ob.anchor) * ob.normal).sum(1)
        pen = np.maximum(ob.eps - d, 0.0)
        e += ob.k_c * float((pen**3).sum())
        g -= (3.0 * ob.k_c * pen**2)[:, None] * ob.normal
        if want_hess:
            diag += (6.0 * ob.k_c * pen)[:, None, None] * (
                ob.normal[:, :, None] * ob.normal[:, None, :]
            )
    if ob.friction_weight is not None:
        e_f, g_f, h_f = _friction(ob, x, want_hess)
        e += e_f
        g += g_f
        if want_hess:
            diag += h_f
    if ob.x_hat is not None:
        w = st.mass / (ob.dt * ob.dt)
        dx = x - ob.x_hat
        e += 0.5 * float((w * (dx * dx).sum(1)).sum())
        g += w[:, None] * dx
        if want_hess:
            diag += w[:, None, None] * np.eye(3)
    g[~ob.free] = 0.0
    if not want_hess:
        return e, g, None
    blocks[st.diag_map] += diag
    return e, g, _assemble(ob, blocks)


def _friction(ob: Objective, x: np.ndarray, want_hess: bool):
    """Lagged, smoothed Coulomb friction against the body (IPC's ``f0``; Li et al. 2020).

    ``u = (I - n n^T)(x - ref)`` is the tangential slip against the body over the step,
    ``E = sum_i w_i f0(|u_i|)`` with ``w_i = mu lambda_i`` (lagged normal force) and ``f0(s) = s``
    beyond ``eps``, ``-s^3 / (3 eps^2) + s^2 / eps + eps / 3`` below (static friction). The
    Hessian is the positive semi-definite ``w f1(s) / s (I - n n^T)``.
    """
    n, w, eps = ob.normal, ob.friction_weight, ob.friction_eps
    dx = x - ob.friction_ref
    u = dx - (dx * n).sum(1)[:, None] * n
    s = np.linalg.norm(u, axis=1)
    small = s < eps
    f0 = np.where(small, -(s**3) / (3 * eps**2) + s**2 / eps + eps / 3, s)
    ratio = np.where(small, 2.0 / eps - s / eps**2, 1.0 / np.maximum(s, 1e-300))  # f1(s) / s
    e = float((w * f0).sum())
    g = (w * ratio)[:, None] * u
    h = None
    if want_hess:
        h = (w * ratio)[:, None, None] * (np.eye(3) - n[:, :, None] * n[:, None, :])
    return e, g, h


def _assemble(ob: Objective, data: np.ndarray) -> sp.bsr_matrix:
    st = ob.st
    pinned = ~ob.free
    if pinned.any():
        kill = pinned[st.block_rows] | pinned[st.block_cols]
        data[kill] = 0.0
        data[st.diag_map[pinned]] = np.eye(3)
    n = ob.free.shape[0]
    return sp.bsr_matrix((data, st.block_cols, st.indptr), shape=(3 * n, 3 * n))


def contact_diagonal(ob: Objective, x: np.ndarray, scale: float = 1.0) -> np.ndarray | None:
    """Per-vertex isotropic stand-in ``(V,)`` (N/m) of the contact Hessians at ``x``.

    ``scale`` times the collision stiffness along the normal ``6 k_c (eps - d)`` plus the
    friction's tangential stiffness; None without body contact.
    """
    if ob.anchor is None:
        return None
    d = ((x - ob.anchor) * ob.normal).sum(1)
    c = 6.0 * ob.k_c * np.maximum(ob.eps - d, 0.0)
    if ob.friction_weight is not None:
        dx = x - ob.friction_ref
        u = dx - (dx * ob.normal).sum(1)[:, None] * ob.normal
        s = np.linalg.norm(u, axis=1)
        eps = ob.friction_eps
        c = c + ob.friction_weight * np.where(s < eps, 2.0 / eps - s / eps**2,
                                              1.0 / np.maximum(s, 1e-300))
    return scale * c


def laplacian_factor(ob: Objective, dt: float, extra: np.ndarray | None = None
                     ) -> Callable[[np.ndarray], np.ndarray]:
    """Factorised ``M / dt^2 + K`` (V x V, shared by x, y, z) as a solve ``(V, 3) -> (V, 3)``.

    ``K`` is the graph Laplacian with edge weights ``(2 mu + lambda) h (A_0 + A_1) / (3 l^2)``
    (the membrane's stiffness along each edge at rest, blind to the garment's orientation),
    plus ``diag(extra)`` (e.g. :func:`contact_diagonal`). Pinned vertices get identity rows.
    """
    st, m = ob.st, ob.rest.material
    n = st.mass.shape[0]
    e = st.edges
    he = np.sort(st.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    pos = np.searchsorted(e[:, 0] * n + e[:, 1], he[:, 0] * n + he[:, 1])
    a_e = np.bincount(pos, weights=np.repeat(st.area, 3), minlength=e.shape[0])
    w = (2 * m.lame_mu + m.lame_lambda) * m.thickness * a_e / (3.0 * st.edge_length**2)
    ij = np.concatenate([e[:, 0], e[:, 1]])
    ji = np.concatenate([e[:, 1], e[:, 0]])
    lap = sp.coo_matrix((np.concatenate([-w, -w]), (ij, ji)), shape=(n, n)).tocsr()
    a = lap - sp.diags(np.asarray(lap.sum(1)).ravel()) + sp.diags(st.mass / dt**2)
    if extra is not None:
        a = a + sp.diags(extra)
    if not ob.free.all():
        keep = sp.diags(ob.free.astype(np.float64))
        a = keep @ a @ keep + sp.diags((~ob.free).astype(np.float64))
    # symmetric positive definite: no pivoting, symmetric ordering. On the 5,000-vertex T-shirt
    # this factorises in 12 ms and solves (V, 3) in 0.5 ms, against 128 ms and 3.2 ms with
    # SuperLU's default partial pivoting (same ordering, same fill; one thread).
    lu = spla.splu(a.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                   options={"SymmetricMode": True})
    return lambda r: lu.solve(np.ascontiguousarray(r.reshape(n, 3)))


class Outcome(NamedTuple):
    x: np.ndarray
    energy: float
    grad_norm: float
    iterations: int
    trace: list


def _line_search(
    ob: Objective, x: np.ndarray, e: float, g: np.ndarray, d: np.ndarray
) -> tuple[float, np.ndarray, float] | None:
    slope = float((d * g).sum())
    if slope >= 0:
        return None
    step = 1.0
    while step > 1e-12:
        x_new = x + step * d
        e_new, _, _ = evaluate(ob, x_new, want_grad=False)
        if e_new <= e + 1e-4 * step * slope:
            return step, x_new, e_new
        step *= 0.5
    return None


def _pcg(
    h: sp.bsr_matrix,
    b: np.ndarray,
    precond: Callable[[np.ndarray], np.ndarray],
    rtol: float,
    maxiter: int,
) -> np.ndarray:
    """Preconditioned CG on ``h d = b``, stopped at ``|r| <= rtol |b|`` or negative curvature.

    At negative curvature (Steihaug) the iterate so far is returned, or the preconditioned
    ``b`` at the first step.
    """
    x = np.zeros_like(b)
    r = b.copy()
    z = precond(r)
    p = z.copy()
    rz = float(r @ z)
    bn = float(np.linalg.norm(b))
    for it in range(maxiter):
        hp = h @ p
        curv = float(p @ hp)
        if curv <= 0:
            return z if it == 0 else x
        a = rz / curv
        x += a * p
        r -= a * hp
        if float(np.linalg.norm(r)) <= rtol * bn:
            break
        z = precond(r)
        rz_new = float(r @ z)
        p = z + (rz_new / rz) * p
        rz = rz_new
    return x


#: Accepted Newton steps in a row without any energy decrease after which :func:`newton`
#: gives up (the frame is then reported as not converged).
STALL_STEPS = 3


def forcing_term(gn: float, weight: float, cap: float = 0.5, scale: float = 3.0) -> float:
    """Relative residual the inner CG solve of a Newton step must reach.

    ``min(cap, scale * sqrt(|g| / |M g|))``: loose (``cap``) while the residual force is above
    about 3 % of the garment's weight, then tightening with its square root (superlinear
    convergence towards tight tolerances). Where a wrinkle forms Newton converges only
    linearly and tighter inner solves buy almost no Newton steps (replayed T-shirt walk frame
    11: 61 steps with the former ``scale = 1``, 46 with CG to 1e-3), only conjugate-gradient
    iterations; on six replayed walk frames (8, 11, 13, 19, 24, 47; paired, one thread, load
    about 5) ``scale = 3`` took 7.7 against 9.5 CPU s (292 against 294 Newton steps). An
    Eisenstat-Walker forcing term (choice 2) was as fast there but let Newton crawl at tight
    tolerances (2,025-vertex sheet onto a sphere at ``tol = 1e-4``, third frame: 336 steps
    against 194 with this rule).

    Parameters
    ----------
    gn : float
        Gradient norm (N).
    weight : float
        ``|M g|`` (N), the scale of the stopping rule.
    cap, scale : float
        Largest forcing term; factor on ``sqrt(|g| / |M g|)``.

    Returns
    -------
    float
        The forcing term, in ``(0, cap]`` for ``gn > 0``.
    """
    return float(min(cap, scale * np.sqrt(gn / weight)))


def hessian_vector(ob: Objective, x: np.ndarray, g: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Product ``H v`` (V, 3) of the exact Hessian of the energy at ``x`` (N/m times ``v``'s m).

    A forward difference of gradients, ``(grad E(x + h v) - g) / h``, with ``h`` moving no
    vertex by more than 1e-7 m (the energies are smooth at that scale; the collision
    penalty and the smoothed friction are C1 with kinks only where a vertex crosses the
    clearance or the static-friction radius). One gradient evaluation; no Hessian is
    assembled. ``g`` is the gradient at ``x``; rows of pinned vertices are zero.
    """
    vmax = float(np.abs(v).max())
    if vmax == 0.0:
        return np.zeros_like(v)
    h = 1e-7 / vmax
    _, g2, _ = evaluate(ob, x + h * v)
    return (g2 - g) / h


def trust_region_2d(hr: np.ndarray, br: np.ndarray, gr: np.ndarray, radius: float
                    ) -> tuple[np.ndarray, bool]:
    """Minimise ``gr . c + c . hr c / 2`` subject to ``c . br c <= radius^2`` (k <= a few).

    ``hr`` symmetric (possibly indefinite), ``br`` symmetric positive definite (the metric),
    ``radius > 0``. The classic characterisation (More and Sorensen 1983): the minimiser is
    ``-(hr + mu br)^-1 gr`` with ``mu >= max(0, -lambda_min)`` and ``mu = 0`` unless the
    constraint is active, found here by bisection on ``mu`` after whitening ``br``; the
    "hard case" (``gr`` orthogonal to the lowest eigenvector) adds that eigenvector.

    Returns
    -------
    c : (k,) ndarray
        The minimiser.
    active : bool
        Whether it lies on the boundary ``c . br c = radius^2``.

    Raises
    ------
    numpy.linalg.LinAlgError
        ``br`` not positive definite.
    """
    low = np.linalg.cholesky(br)
    li = np.linalg.inv(low)
    a = li @ hr @ li.T
    lam, q = np.linalg.eigh(0.5 * (a + a.T))
    b = q.T @ (li @ gr)
    if lam[0] > 0:
        z = -b / lam
        if np.linalg.norm(z) <= radius:
            return li.T @ (q @ z), False
    lo = max(0.0, -lam[0]) + 1e-15 * max(1.0, float(np.abs(lam).max()))

    def size(mu: float) -> float:
        return float(np.linalg.norm(b / (lam + mu)))

    if size(lo) < radius:  # hard case: fill up along the lowest eigenvector
        z = -b / (lam + lo)
        z[0] = 0.0
        z[0] = math.copysign(math.sqrt(max(radius**2 - float(z @ z), 0.0)), -b[0])
        return li.T @ (q @ z), True
    hi = lo + 1.0
    while size(hi) > radius:
        hi = lo + 2.0 * (hi - lo)
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if size(mid) > radius:
            lo = mid
        else:
            hi = mid
    return li.T @ (q @ (-b / (lam + hi))), True


def subspace_step(
    ob: Objective,
    x: np.ndarray,
    g: np.ndarray,
    h: sp.bsr_matrix,
    d: np.ndarray,
    s_prev: np.ndarray | None,
    y_prev: np.ndarray | None,
    kappa: float,
) -> tuple[np.ndarray, bool]:
    """Curvature-corrected step in the span of the Newton direction and the previous step.

    ``d`` solves (inexactly) the Newton system of the projected Hessian ``h``, which
    overestimates the curvature along a buckling wrinkle 4-8 times (and hides its saddle), so
    Newton creeps along it. Here the exact energy's quadratic model is minimised over
    ``span(d, s_prev)``: the exact curvature along ``d`` from :func:`hessian_vector`, along
    the previous step ``s_prev`` from the change of gradient over it ``y_prev`` (a secant),
    within a trust region ``|p|_h <= kappa |d|_h`` measured with the projected Hessian (the
    exact model is unbounded below on a saddle). Without a previous step the subspace is
    ``d`` alone (a 1-D Newton step on the step length).

    Returns
    -------
    p : (V, 3) ndarray
        The step (``d`` itself if the subspace step is not a descent direction).
    active : bool
        Whether the trust region bounded it.
    """
    cols = [d] if s_prev is None else [d, s_prev]
    hcols = [hessian_vector(ob, x, g, d)] + ([] if s_prev is None else [y_prev])
    k = len(cols)
    n = x.shape[0]
    hb = [(h @ c.ravel()).reshape(n, 3) for c in cols]
    hr = np.array([[float((cols[i] * hcols[j]).sum()) for j in range(k)] for i in range(k)])
    br = np.array([[float((cols[i] * hb[j]).sum()) for j in range(k)] for i in range(k)])
    gr = np.array([float((g * c).sum()) for c in cols])
    br = 0.5 * (br + br.T) + 1e-12 * np.trace(br) * np.eye(k)
    if not np.all(np.isfinite(hr)) or br[0, 0] <= 0:
        return d, False
    try:
        coef, active = trust_region_2d(0.5 * (hr + hr.T), br, gr, kappa * math.sqrt(br[0, 0]))
    except np.linalg.LinAlgError:  # previous step parallel to d
        return d, False
    p = sum(c * col for c, col in zip(coef, cols))
    if float((p * g).sum()) >= 0:
        return d, False
    return p, active


#: Forcing term cap of the inner solves once :func:`newton` takes subspace steps and the
#: residual force is below the garment's weight: the subspace step is only as good as the
#: Newton direction it starts from (replayed T-shirt walk frames 11, 25, 40, 55: 4.2-4.5 CPU s
#: with caps 0.1-0.3, more Newton steps with 0.5).
SUBSPACE_FORCING = 0.2
#: Trust region of the subspace step: its radius starts at this many times the Newton step's
#: length (in the projected Hessian's norm), doubles after a full step on the boundary and
#: halves after a backtracked one, within [1, 64] times (replayed frames: 2-16 alike).
SUBSPACE_RADIUS = 4.0


def newton(
    ob: Objective,
    x: np.ndarray,
    tol_abs: float,
    max_iter: int,
    precond: Callable[[np.ndarray], np.ndarray],
    weight: float,
    cg_max_iter: int = 200,
    subspace: bool = False,
) -> Outcome:
    """Truncated Newton with PCG inner solves (module docstring); stops at ``|g| <= tol_abs``.

    Each inner solve stops at its forcing term (:func:`forcing_term`, ``weight`` = ``|M g|``,
    N) or after ``cg_max_iter`` CG iterations. With ``subspace`` each step is
    :func:`subspace_step` (the exact energy minimised over the Newton direction and the
    previous step), with inner solves to at most :data:`SUBSPACE_FORCING` once ``|g| <
    weight``. The
    minimiser also stops, short of the tolerance, after :data:`STALL_STEPS` accepted steps in a
    row that do not lower the energy at all (a line search passing on rounding alone): on
    garments with folded-over sliver triangles the gradient of the bending energy is singular
    where a sliver collapses, and the iteration then ran to ``max_iter`` without moving
    (measured: the skirt fitted to the held-out shape of ``benchmarks/bm_gaps.py``'s ``turn``
    case, 2,000 iterations and 16-45 CPU s per frame, ``|g|`` stuck at 188 times the
    tolerance's scale).
    """
    trace = []
    e, g, h = evaluate(ob, x, want_hess=True)
    it = 0
    n = x.shape[0]
    fm = ob.free[:, None].astype(np.float64)
    stalled = 0
    s_prev = y_prev = None
    kappa = SUBSPACE_RADIUS
    while it < max_iter:
        gn = float(np.linalg.norm(g))
        if gn <= tol_abs:
            break
        forcing = forcing_term(gn, weight)
        if subspace and gn < weight:
            forcing = min(forcing, SUBSPACE_FORCING)
        d = _pcg(h, -g.ravel(), lambda r: (precond(r) * fm).ravel(), forcing, cg_max_iter)
        d = d.reshape(n, 3) * fm
        p, active = (subspace_step(ob, x, g, h, d, s_prev, y_prev, kappa) if subspace
                     else (d, False))
        ls = _line_search(ob, x, e, g, p)
        if ls is None and p is not d:
            ls = _line_search(ob, x, e, g, d)
        if ls is None:  # CG direction failed: fall back to the preconditioned gradient
            ls = _line_search(ob, x, e, g, -precond(g) * fm)
            if ls is None:
                break
        step, x_new, e_new = ls
        if step < 1.0:
            kappa = max(1.0, 0.5 * kappa)
        elif active:
            kappa = min(64.0, 2.0 * kappa)
        stalled = stalled + 1 if e_new >= e else 0
        s_prev, g_prev = x_new - x, g
        x = x_new
        e, g, h = evaluate(ob, x, want_hess=True)
        y_prev = g - g_prev
        trace.append(e)
        it += 1
        if stalled >= STALL_STEPS:
            break
    return Outcome(x, e, float(np.linalg.norm(g)), it, trace)


def quasi_newton(
    ob: Objective,
    x: np.ndarray,
    tol_abs: float,
    max_iter: int,
    history: int,
    precond: Callable[[np.ndarray], np.ndarray] | None,
) -> Outcome:
    """L-BFGS, preconditioned (``pqn``) or with a scaled identity (``lbfgs``)."""
    trace = []
    fm = ob.free[:, None].astype(np.float64)
    e, g, _ = evaluate(ob, x)
    s_hist: list = []
    y_hist: list = []
    it = 0
    while it < max_iter and float(np.linalg.norm(g)) > tol_abs:
        q = g.copy()
        alphas = []
        for s, y in zip(reversed(s_hist), reversed(y_hist), strict=True):
            rho = 1.0 / float((y * s).sum())
            a = rho * float((s * q).sum())
            alphas.append((a, rho))
            q -= a * y
        if precond is not None:
            r = precond(q) * fm
        elif y_hist:
            r = q * (float((s_hist[-1] * y_hist[-1]).sum()) / float((y_hist[-1] ** 2).sum()))
        else:
            r = q * (1e-3 / max(float(np.abs(g).max()), 1e-300))  # first step: 1 mm at most
        for (s, y), (a, rho) in zip(
            zip(s_hist, y_hist, strict=True), reversed(alphas), strict=True
        ):
            r += (a - rho * float((y * r).sum())) * s
        ls = _line_search(ob, x, e, g, -r * fm)
        if ls is None:
            if not s_hist:
                break
            s_hist, y_hist = [], []
            continue
        _, x_new, _ = ls
        e_new, g_new, _ = evaluate(ob, x_new)
        s, y = x_new - x, g_new - g
        if float((s * y).sum()) > 1e-12 * float(np.linalg.norm(s) * np.linalg.norm(y)):
            s_hist.append(s)
            y_hist.append(y)
            if len(s_hist) > history:
                s_hist.pop(0)
                y_hist.pop(0)
        x, e, g = x_new, e_new, g_new
        trace.append(e)
        it += 1
    return Outcome(x, e, float(np.linalg.norm(g)), it, trace)
