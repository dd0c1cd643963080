"""Differential geometry of parametric patches and jets.

Fundamental forms, shape operator, principal curvatures and directions, mean and Gaussian
curvature, and the Monge form.

Sign convention (fixed project-wide)
------------------------------------
The unit normal of a patch ``x(u, v)`` is ``n = x_u x x_v / |x_u x x_v|`` and the second
fundamental form is ``II_ij = <x_ij, n>``. A curvature is therefore **positive where the
surface bends towards its normal**: the Monge patch ``z = (k1 x^2 + k2 y^2) / 2`` with
``n = +z`` has principal curvatures ``k1, k2``. All curvatures (``k1, k2, H``) flip sign with
the normal; ``K`` does not. A sphere of radius ``r`` with outward normals has
``k1 = k2 = H = -1/r`` and ``K = 1/r^2``. Principal curvatures are ordered ``k1 >= k2`` and
``(d1, d2, n)`` is a right-handed orthonormal frame (``d2 = n x d1``).

Everything here is batched over leading dimensions, torch, differentiable, and NaN-free: a
singular metric (``x_u`` parallel to ``x_v``) gives ``valid = False`` with zeros.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ._jets_common import exponents_np
from .checks import as_tensor, check_shape
from .jets import as_coeffs, derivatives

__all__ = [
    "SurfaceGeometry",
    "from_derivatives",
    "from_jet",
    "MongeForm",
    "monge_form",
    "to_world",
]

_EPS_METRIC = 1e-24  # relative threshold on det(I) / (E G) for a singular metric
_EPS_UMBILIC = 1e-30  # absolute threshold on the squared anisotropy (a - c)^2/4 + b^2


@dataclass(frozen=True)
class SurfaceGeometry:
    """Differential quantities of a parametric patch at a batch of parameters.

    All tensors share the leading dimensions ``...``.

    Attributes
    ----------
    jacobian : torch.Tensor
        ``(..., 3, 2)`` the columns ``x_u, x_v``.
    metric : torch.Tensor
        ``(..., 2, 2)`` first fundamental form ``I = J^T J``.
    second_form : torch.Tensor
        ``(..., 2, 2)`` second fundamental form ``II_ij = <x_ij, n>``.
    normal : torch.Tensor
        ``(..., 3)`` unit normal ``x_u x x_v / |x_u x x_v|`` (zeros where not valid).
    shape_operator : torch.Tensor
        ``(..., 2, 2)`` ``I^{-1} II`` in the ``(u, v)`` basis.
    k1, k2 : torch.Tensor
        ``(...)`` principal curvatures, ``k1 >= k2`` (1 / length units).
    d1, d2 : torch.Tensor
        ``(..., 3)`` unit principal directions in 3D, ``d2 = n x d1``.
    mean_curvature : torch.Tensor
        ``(...)`` ``H = (k1 + k2) / 2``.
    gaussian_curvature : torch.Tensor
        ``(...)`` ``K = k1 k2 = det II / det I``.
    valid : torch.Tensor
        ``(...)`` bool, False where the metric is singular (then curvatures, normal and
        directions are zero).
    """

    jacobian: torch.Tensor
    metric: torch.Tensor
    second_form: torch.Tensor
    normal: torch.Tensor
    shape_operator: torch.Tensor
    k1: torch.Tensor
    k2: torch.Tensor
    d1: torch.Tensor
    d2: torch.Tensor
    mean_curvature: torch.Tensor
    gaussian_curvature: torch.Tensor
    valid: torch.Tensor

    def squeeze(self, dim: int = -1) -> SurfaceGeometry:
        """Drop a size-1 batch dimension (e.g. the ``P = 1`` of :func:`from_jet` at the origin).

        Parameters
        ----------
        dim : int
            Batch dimension index counted among the leading dimensions (negative from the last
            leading dimension).

        Returns
        -------
        SurfaceGeometry
        """
        nlead = self.k1.dim()
        d = dim % nlead

        def sq(t):
            return t.squeeze(d)

        return SurfaceGeometry(**{k: sq(getattr(self, k)) for k in self.__dataclass_fields__})


def _comps(v: torch.Tensor):
    """Contiguous components (x, y, z) of a (..., 3) tensor."""
    return v.movedim(-1, 0).contiguous().unbind(0)


def _cdot(a, b):
    """Dot product of vectors given as 3-tuples of components."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _ccross(a, b):
    """Cross product of vectors given as 3-tuples of components."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _safe_sqrt(x: torch.Tensor) -> torch.Tensor:
    """Square root with a finite gradient at 0 (the gradient there is taken as 0)."""
    pos = x > 0
    return torch.where(pos, torch.sqrt(torch.where(pos, x, torch.ones_like(x))),
                       torch.zeros_like(x))


def _cat_vectors(xu, xv, xuu, xuv, xvv):
    ts = []
    for name, v in (("xu", xu), ("xv", xv), ("xuu", xuu), ("xuv", xuv), ("xvv", xvv)):
        t = as_tensor(v, name)
        check_shape(t, name, ("...", 3))
        ts.append(t)
    shape = torch.broadcast_shapes(*(t.shape for t in ts))
    dtype = ts[0].dtype
    for t in ts[1:]:
        dtype = torch.promote_types(dtype, t.dtype)
    return [t.to(dtype).expand(shape) for t in ts]


def from_derivatives(xu, xv, xuu, xuv, xvv) -> SurfaceGeometry:
    """Differential quantities of any parametric patch from its first and second derivatives.

    Parameters
    ----------
    xu, xv : array_like or torch.Tensor
        ``(..., 3)`` first partial derivatives of ``x(u, v)``.
    xuu, xuv, xvv : array_like or torch.Tensor
        ``(..., 3)`` second partial derivatives (broadcast together).

    Returns
    -------
    SurfaceGeometry
        Torch tensors in the promoted floating dtype.

    Raises
    ------
    ValueError
        If a last dimension is not 3 or the shapes do not broadcast.
    TypeError
        On non-numeric input.

    Notes
    -----
    The shape operator is diagonalised in the orthonormal tangent basis
    ``t1 = x_u / |x_u|, t2 = n x t1``, where it is the symmetric matrix
    ``W = C^{-T} II C^{-1}`` (``C`` the upper-triangular coordinates of ``x_u, x_v`` in that
    basis), by the closed form of a symmetric 2x2 eigenproblem: ``k = m ± r`` with
    ``m = (a + c)/2``, ``r = sqrt(((a - c)/2)^2 + b^2)`` and ``d1`` at the angle
    ``atan2(2b, a - c) / 2`` from ``t1``. At an umbilic (``r = 0``) every tangent direction is
    principal and ``d1 = t1``, ``d2 = t2`` is returned. Differentiable away from umbilics
    (gradients stay finite at them).
    """
    xu, xv, xuu, xuv, xvv = _cat_vectors(xu, xv, xuu, xuv, xvv)
    # Component-wise arithmetic on (...) fields: far fewer tiny reductions than (..., 3) ops.
    u3, v3 = _comps(xu), _comps(xv)
    E, F, G = _cdot(u3, u3), _cdot(u3, v3), _cdot(v3, v3)
    nrm = _ccross(u3, v3)
    det = _cdot(nrm, nrm)  # = E G - F^2, computed without cancellation
    valid = (det > _EPS_METRIC * E * G) & (E > 0) & (G > 0) & torch.isfinite(det)
    one = torch.ones_like(det)
    zero = torch.zeros_like(det)
    dets = torch.where(valid, det, one)
    inv_sd = dets.rsqrt()
    n3 = tuple(torch.where(valid, c * inv_sd, zero) for c in nrm)
    L, Mm, N = _cdot(_comps(xuu), n3), _cdot(_comps(xuv), n3), _cdot(_comps(xvv), n3)
    lead = det.shape
    jac = torch.stack([xu, xv], dim=-1)
    metric = torch.stack([E, F, F, G], -1).reshape(lead + (2, 2))
    second = torch.stack([L, Mm, Mm, N], -1).reshape(lead + (2, 2))
    # Shape operator I^{-1} II.
    idet = torch.where(valid, 1.0 / dets, zero)
    s11 = (G * L - F * Mm) * idet
    s12 = (G * Mm - F * N) * idet
    s21 = (E * Mm - F * L) * idet
    s22 = (E * N - F * Mm) * idet
    shape_op = torch.stack([s11, s12, s21, s22], -1).reshape(lead + (2, 2))
    # Orthonormal tangent basis t1 = xu/|xu|, t2 = n x t1 and the symmetric operator W in it.
    su = torch.where(valid, E, one).sqrt()
    t1 = tuple(c / su for c in u3)
    t2 = _ccross(n3, t1)
    c11 = su
    c12 = _cdot(v3, t1)
    c22 = torch.where(valid, _cdot(v3, t2), one)  # = sqrt(det) / |xu| > 0
    # C^{-1} = [[1/c11, -c12/(c11 c22)], [0, 1/c22]]
    i11, i12, i22 = 1.0 / c11, -c12 / (c11 * c22), 1.0 / c22
    a = i11 * i11 * L
    b = i11 * (i12 * L + i22 * Mm)
    c = i12 * i12 * L + 2 * i12 * i22 * Mm + i22 * i22 * N
    m = 0.5 * (a + c)
    hd = 0.5 * (a - c)
    r2 = hd * hd + b * b
    r = _safe_sqrt(r2)
    aniso = r2 > _EPS_UMBILIC * (m * m).clamp_min(1e-300)
    theta = 0.5 * torch.atan2(torch.where(aniso, b, zero), torch.where(aniso, hd, one))
    ct, st = torch.cos(theta), torch.sin(theta)
    d1 = tuple(ct * x + st * y for x, y in zip(t1, t2))
    d2 = _ccross(n3, d1)

    def vz(t):
        return torch.where(valid, t, zero)

    def vz3(t3):
        return torch.stack([vz(x) for x in t3], -1)

    return SurfaceGeometry(
        jacobian=jac,
        metric=metric,
        second_form=second,
        normal=torch.stack(n3, -1),
        shape_operator=shape_op,
        k1=vz(m + r),
        k2=vz(m - r),
        d1=vz3(d1),
        d2=vz3(d2),
        mean_curvature=vz(m),
        gaussian_curvature=vz(a * c - b * b),
        valid=valid,
    )


def _jet_patch_derivatives(coeffs: torch.Tensor, uv: torch.Tensor):
    """x_u, x_v, x_uu, x_uv, x_vv of the height graph (u, v, z(u, v)) at uv (B, P, 2)."""
    d = derivatives(coeffs, uv, max_order=2)
    zero = torch.zeros_like(d[(1, 0)])
    one = torch.ones_like(zero)
    xu = torch.stack([one, zero, d[(1, 0)]], -1)
    xv = torch.stack([zero, one, d[(0, 1)]], -1)
    xuu = torch.stack([zero, zero, d[(2, 0)]], -1)
    xuv = torch.stack([zero, zero, d[(1, 1)]], -1)
    xvv = torch.stack([zero, zero, d[(0, 2)]], -1)
    return xu, xv, xuu, xuv, xvv


def _origin_patch_derivatives(c: torch.Tensor, order: int):
    """Derivatives of the height graph at (0, 0): read off the coefficients, (B, 1, 3) each."""
    B = c.shape[0]
    zero = c.new_zeros(B)
    one = c.new_ones(B)

    def coef(i):
        return c[:, i] if i < c.shape[1] else zero

    zu, zv = coef(1), coef(2)
    zuu, zuv, zvv = 2 * coef(3), coef(4), 2 * coef(5)
    out = (
        torch.stack([one, zero, zu], -1),
        torch.stack([zero, one, zv], -1),
        torch.stack([zero, zero, zuu], -1),
        torch.stack([zero, zero, zuv], -1),
        torch.stack([zero, zero, zvv], -1),
    )
    return tuple(t[:, None, :] for t in out)


def from_jet(coeffs, uv=None) -> SurfaceGeometry:
    """Differential quantities of jets' height graphs ``(u, v, z(u, v))`` in the jets' frames.

    Parameters
    ----------
    coeffs : array_like or torch.Tensor
        ``(B, M)`` jet coefficients (:mod:`polygeo.jets` storage order).
    uv : array_like or torch.Tensor, optional
        ``(B, P, 2)`` parameters; default: the origin only (``P = 1``), where the derivatives
        are read directly from the coefficients.

    Returns
    -------
    SurfaceGeometry
        Leading dimensions ``(B, P)``; vectors in the jet's local frame, normal on the
        ``+z`` side. Use :meth:`SurfaceGeometry.squeeze` to drop ``P = 1``.

    Raises
    ------
    ValueError
        If ``M`` is not triangular or shapes disagree.
    TypeError
        On non-numeric input.
    """
    c, order = as_coeffs(coeffs)
    if uv is None:
        return from_derivatives(*_origin_patch_derivatives(c, order))
    t = as_tensor(uv, "uv")
    check_shape(t, "uv", (c.shape[0], "P", 2))
    dtype = torch.promote_types(c.dtype, t.dtype)
    return from_derivatives(*_jet_patch_derivatives(c.to(dtype), t.to(dtype)))


def to_world(geom: SurfaceGeometry, rotation, scale=None) -> SurfaceGeometry:
    """Express a local :class:`SurfaceGeometry` in world coordinates.

    The local frame maps to world as ``x_world = scale R x_local + t`` (the translation does not
    affect differential quantities).

    Parameters
    ----------
    geom : SurfaceGeometry
        Quantities with leading dimensions ``(B, ...)``.
    rotation : array_like or torch.Tensor
        ``(B, 3, 3)`` local-to-world rotations (columns: local axes in world).
    scale : array_like or torch.Tensor, optional
        ``(B,)`` positive scales (default 1).

    Returns
    -------
    SurfaceGeometry
        Jacobian ``s R J``, metric ``s^2 I``, second form ``s II``, normal and directions
        rotated, shape operator and ``k1, k2, H`` divided by ``s``, ``K`` by ``s^2``.

    Raises
    ------
    ValueError
        On bad shapes or non-positive scales.
    """
    R = as_tensor(rotation, "rotation").to(geom.k1.dtype)
    B = geom.k1.shape[0]
    check_shape(R, "rotation", (B, 3, 3))
    extra = geom.k1.dim() - 1
    Rb = R.reshape((B,) + (1,) * extra + (3, 3))
    if scale is None:
        s = torch.ones(B, dtype=geom.k1.dtype)
    else:
        s = as_tensor(scale, "scale").to(geom.k1.dtype)
        check_shape(s, "scale", (B,))
        if not bool((torch.isfinite(s) & (s > 0)).all()):
            raise ValueError("scale: expected finite values > 0")
    sb = s.reshape((B,) + (1,) * extra)

    def rot(v):
        return (Rb @ v[..., None])[..., 0]

    return SurfaceGeometry(
        jacobian=sb[..., None, None] * (Rb @ geom.jacobian),
        metric=sb[..., None, None] ** 2 * geom.metric,
        second_form=sb[..., None, None] * geom.second_form,
        normal=rot(geom.normal),
        shape_operator=geom.shape_operator / sb[..., None, None],
        k1=geom.k1 / sb,
        k2=geom.k2 / sb,
        d1=rot(geom.d1),
        d2=rot(geom.d2),
        mean_curvature=geom.mean_curvature / sb,
        gaussian_curvature=geom.gaussian_curvature / sb**2,
        valid=geom.valid,
    )


# --------------------------------------------------------------------------------------------
# Monge form
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MongeForm:
    """Monge form of a surface at a point (CGAL ``Monge_via_jet_fitting`` conventions).

    In the Monge frame ``(d1, d2, n)`` centred at ``origin`` the surface is the graph

    ``w = 1/2 (k1 x^2 + k2 y^2) + 1/6 (b0 x^3 + 3 b1 x^2 y + 3 b2 x y^2 + b3 y^3)
    + 1/24 (c0 x^4 + 4 c1 x^3 y + 6 c2 x^2 y^2 + 4 c3 x y^3 + c4 y^4) + ...``

    Attributes
    ----------
    origin : torch.Tensor
        ``(B, 3)`` the surface point.
    d1, d2, normal : torch.Tensor
        ``(B, 3)`` right-handed orthonormal Monge frame (``d1`` of ``k1``, ``d2 = n x d1``).
    k1, k2 : torch.Tensor
        ``(B,)`` principal curvatures, ``k1 >= k2`` (sign convention of this module).
    b : torch.Tensor
        ``(B, 4)`` third-order coefficients ``b0..b3`` (zeros unless ``has_cubic``).
    c : torch.Tensor
        ``(B, 5)`` fourth-order coefficients ``c0..c4`` (zeros unless ``has_quartic``).
    valid : torch.Tensor
        ``(B,)`` bool, False for non-finite input coefficients (then ``k``, ``b``, ``c``, the
        frame vectors are zeros; ``origin`` may hold the non-finite height).
    order : int
        Order of the jet the form was computed from.
    """

    origin: torch.Tensor
    d1: torch.Tensor
    d2: torch.Tensor
    normal: torch.Tensor
    k1: torch.Tensor
    k2: torch.Tensor
    b: torch.Tensor
    c: torch.Tensor
    valid: torch.Tensor
    order: int

    @property
    def has_cubic(self) -> bool:
        """True when ``b`` was computed (jet order >= 3)."""
        return self.order >= 3

    @property
    def has_quartic(self) -> bool:
        """True when ``c`` was computed (jet order >= 4)."""
        return self.order >= 4


class _TruncPoly:
    """Bivariate polynomials in (x, y) truncated at a total degree, batched: (B, T)."""

    def __init__(self, degree: int):
        self.degree = degree
        e = exponents_np(degree)
        self.T = len(e)
        index = {(int(p), int(q)): i for i, (p, q) in enumerate(e)}
        rows_i, rows_j, rows_k = [], [], []
        for i, (p1, q1) in enumerate(e):
            for j, (p2, q2) in enumerate(e):
                if p1 + p2 + q1 + q2 <= degree:
                    rows_i.append(i)
                    rows_j.append(j)
                    rows_k.append(index[(int(p1 + p2), int(q1 + q2))])
        self.i = torch.tensor(rows_i)
        self.j = torch.tensor(rows_j)
        self.k = torch.tensor(rows_k)
        self.index = index
        self.deg = torch.from_numpy(e.sum(1))

    def mul(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        prod = a[:, self.i] * b[:, self.j]
        out = a.new_zeros(a.shape[0], self.T)
        return out.index_add(1, self.k, prod)


def monge_form(coeffs, frame_rotation=None, frame_origin=None, at=None) -> MongeForm:
    """Monge form of jets at a point, optionally expressed in world coordinates.

    Parameters
    ----------
    coeffs : array_like or torch.Tensor
        ``(B, M)`` jet coefficients of height graphs ``w = z(u, v)`` fitted in local frames.
    frame_rotation : array_like or torch.Tensor, optional
        ``(B, 3, 3)`` local-to-world rotations of those frames (columns = local axes in world,
        e.g. :func:`polygeo.frames.pca_frames` ``rotation``). Default: identity.
    frame_origin : array_like or torch.Tensor, optional
        ``(B, 3)`` world position of the local origins (``x_world = R x_local + origin``).
        Default: zero.
    at : array_like or torch.Tensor, optional
        ``(B, 2)`` parameters ``(u, v)`` of the point; default the origin ``(0, 0)``.

    Returns
    -------
    MongeForm
        Torch tensors (float64 unless the input is float32). The normal is the jet's ``+w``
        side normal ``(-z_u, -z_v, 1)/|.|`` rotated to world.

    Raises
    ------
    ValueError
        On bad shapes.
    TypeError
        On non-numeric input.

    Notes
    -----
    The third- and fourth-order coefficients are the derivatives of the implicit height
    function ``h(x, y)`` of the jet's surface over its tangent plane in the Monge frame, found
    order by order from the jet's Taylor expansion at the point with truncated bivariate
    polynomial arithmetic (exact for the jet, no refitting). As in CGAL, ``b`` is computed for
    jets of order >= 3 and ``c`` for order >= 4; lower orders give zeros.
    """
    c, order = as_coeffs(coeffs)
    B = c.shape[0]
    dtype = c.dtype
    if at is None:
        uv0 = c.new_zeros(B, 1, 2)
    else:
        a = as_tensor(at, "at")
        check_shape(a, "at", (B, 2))
        dtype = torch.promote_types(dtype, a.dtype)
        uv0 = a.to(dtype)[:, None, :]
    c = c.to(dtype)
    geom = from_jet(c, uv0).squeeze(1)
    dmax = min(order, 4)
    der = derivatives(c, uv0, max_order=max(dmax, 2))
    der = {k: v[:, 0] for k, v in der.items()}  # (B,)
    origin_local = torch.stack([uv0[:, 0, 0], uv0[:, 0, 1], der[(0, 0)]], -1)
    n, d1, d2 = geom.normal, geom.d1, geom.d2
    b = c.new_zeros(B, 4)
    cc = c.new_zeros(B, 5)
    if dmax >= 3:
        h = _monge_higher(der, d1, d2, n, dmax)
        P = _TruncPoly(dmax)
        b = torch.stack([h[:, P.index[(3 - j, j)]] for j in range(4)], -1)
        # h stores Taylor coefficients; b_j and c_j are the partial derivatives.
        b = b * torch.tensor([6.0, 2.0, 2.0, 6.0], dtype=dtype)
        if dmax >= 4:
            cc = torch.stack([h[:, P.index[(4 - j, j)]] for j in range(5)], -1)
            cc = cc * torch.tensor([24.0, 6.0, 4.0, 6.0, 24.0], dtype=dtype)
    valid = torch.isfinite(c).all(-1) & geom.valid
    b = torch.where(valid[:, None], b, torch.zeros_like(b))
    cc = torch.where(valid[:, None], cc, torch.zeros_like(cc))
    k1, k2 = geom.k1, geom.k2
    origin = origin_local
    if frame_rotation is not None:
        R = as_tensor(frame_rotation, "frame_rotation").to(dtype)
        check_shape(R, "frame_rotation", (B, 3, 3))

        def rot(v):
            return (R @ v[..., None])[..., 0]

        n, d1, d2, origin = rot(n), rot(d1), rot(d2), rot(origin)
    if frame_origin is not None:
        o = as_tensor(frame_origin, "frame_origin").to(dtype)
        check_shape(o, "frame_origin", (B, 3))
        origin = origin + o
    return MongeForm(origin, d1, d2, n, k1, k2, b, cc, valid, order)


def _monge_higher(der: dict, d1, d2, n, degree: int) -> torch.Tensor:
    """Taylor coefficients (B, T) of the Monge height h(x, y) up to ``degree`` (>= 3).

    The surface near the point is ``G(x, y, h) = f(u0 + du, v0 + dv) - (w0 + dw) = 0`` with
    ``(du, dv, dw) = x d1 + y d2 + h n`` in the jet's frame; ``h`` has no terms below degree 2.
    At each degree ``k`` the unknown degree-``k`` part of ``h`` enters ``G``'s degree-``k``
    part only through ``(f_u n_u + f_v n_v - n_w) h_k``, so it is solved for directly.
    """
    P = _TruncPoly(degree)
    B = d1.shape[0]
    idx = P.index
    X = d1.new_zeros(B, P.T)
    Y = d1.new_zeros(B, P.T)
    X[:, idx[(1, 0)]] = 1.0
    Y[:, idx[(0, 1)]] = 1.0
    h = d1.new_zeros(B, P.T)
    fu, fv = der[(1, 0)], der[(0, 1)]
    lin = fu * n[:, 0] + fv * n[:, 1] - n[:, 2]  # = -sqrt(1 + |grad f|^2) != 0
    zero = d1.new_zeros(B)
    for k in range(2, degree + 1):
        du = d1[:, 0:1] * X + d2[:, 0:1] * Y + n[:, 0:1] * h
        dv = d1[:, 1:2] * X + d2[:, 1:2] * Y + n[:, 1:2] * h
        dw = d1[:, 2:3] * X + d2[:, 2:3] * Y + n[:, 2:3] * h
        # powers of du and dv
        pu = [torch.zeros_like(du)]
        pu[0][:, idx[(0, 0)]] = 1.0
        pv = [pu[0].clone()]
        for _ in range(degree):
            pu.append(P.mul(pu[-1], du))
            pv.append(P.mul(pv[-1], dv))
        G = -dw
        for tot in range(1, degree + 1):
            for j in range(tot + 1):
                i = tot - j
                coef = der.get((i, j), zero) / (_fact(i) * _fact(j))
                G = G + coef[:, None] * P.mul(pu[i], pv[j])
        sel = (P.deg == k)
        upd = torch.where(sel[None, :], -G / lin[:, None], torch.zeros_like(G))
        h = h + upd
    return h


def _fact(k: int) -> float:
    out = 1.0
    for i in range(2, k + 1):
        out *= i
    return out

