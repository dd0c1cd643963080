"""Random patch families of STN training (thesis §5.5.1).

Jets, trigonometric, Gaussian and Bessel height fields, rigidly rotated, on irregular or
jittered-grid samples.

Public names are re-exported by :mod:`polygeo.synthetic`, their documented home.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..checks import check_int, check_positive, check_shape

__all__ = [
    "PATCH_FAMILIES",
    "FamilyPatches",
    "family_patches",
    "family_grid_patches",
]


#: The patch families of thesis §5.5.1, in the order their parameters are drawn.
PATCH_FAMILIES = ("jet", "trig", "gauss", "bessel")


@dataclass(frozen=True)
class FamilyPatches:
    """Random patches of the §5.5.1 families (see :func:`family_patches`).

    Attributes
    ----------
    points : np.ndarray, shape (B, P, 3), float64
        Sample positions after the random rotation and the noise.
    normals : np.ndarray, shape (B, P, 3), float64
        Exact unit normals of the noise-free surface at the samples (rotated with the points;
        pointing to the side of the rotated +z axis).
    uv : np.ndarray, shape (B, P, 2), float64
        Parameters of the samples in the generating frame, in ``[-1, 1]^2``.
    height : np.ndarray, shape (B, P), float64
        Noise-free height ``z(u, v)`` in the generating frame.
    rotation : np.ndarray, shape (B, 3, 3), float64
        Rotation applied: ``points = (u, v, z) @ rotation.T + noise``.
    """

    points: np.ndarray
    normals: np.ndarray
    uv: np.ndarray
    height: np.ndarray
    rotation: np.ndarray


def _family_params(
    rng: np.random.Generator, n: int, families: tuple[str, ...], amplitude: float
) -> dict:
    """Draw the parameters of the families (ranges of thesis §5.5.1)."""
    a = amplitude
    par: dict = {}
    if "jet" in families:
        par["jet"] = rng.uniform(-a, a, size=(n, 15))
    if "trig" in families:
        par["trig"] = (rng.uniform(-a, a, n), rng.uniform(np.pi, 2 * np.pi, n))
    if "gauss" in families:
        par["gauss"] = (
            rng.uniform(-a, a, n),
            rng.uniform(-1.0, 1.0, (n, 2)),
            rng.uniform(0.5, 1.0, n),
        )
    if "bessel" in families:
        par["bessel"] = (rng.uniform(-a, a, n), rng.uniform(-1.0, 1.0, (n, 2)), np.full(n, 5.0))
    return par


def _family_height_grad(uv: np.ndarray, par: dict) -> tuple[np.ndarray, np.ndarray]:
    """Sum of the families' heights and its gradient at ``uv`` (B, P, 2)."""
    from scipy.special import j0, j1

    u, v = uv[..., 0], uv[..., 1]
    z = np.zeros(u.shape)
    g = np.zeros(uv.shape)
    if "jet" in par:
        c = par["jet"]
        k = 0
        for i in range(5):
            for j in range(i + 1):
                p, q = i - j, j
                z += c[:, k, None] * u**p * v**q
                if p > 0:
                    g[..., 0] += c[:, k, None] * p * u ** (p - 1) * v**q
                if q > 0:
                    g[..., 1] += c[:, k, None] * q * u**p * v ** (q - 1)
                k += 1
    if "trig" in par:
        al, th = par["trig"]
        r = np.sqrt(u**2 + v**2)
        z += al[:, None] * np.cos(th[:, None] * r)
        dr = -al[:, None] * th[:, None] * np.sin(th[:, None] * r)
        safe = np.where(r > 0, r, 1.0)
        g += (dr / safe)[..., None] * np.where(r[..., None] > 0, uv, 0.0)
    if "gauss" in par:
        al, c0, sg = par["gauss"]
        d = uv - c0[:, None, :]
        e = al[:, None] * np.exp(-(d**2).sum(-1) / (2 * sg[:, None] ** 2))
        z += e
        g += -(e / sg[:, None] ** 2)[..., None] * d
    if "bessel" in par:
        al, c0, kk = par["bessel"]
        d = uv - c0[:, None, :]
        r = np.sqrt((d**2).sum(-1))
        z += al[:, None] * j0(kk[:, None] * r)
        dr = -al[:, None] * kk[:, None] * j1(kk[:, None] * r)
        safe = np.where(r > 0, r, 1.0)
        g += (dr / safe)[..., None] * np.where(r[..., None] > 0, d, 0.0)
    return z, g


def _random_rotations_np(rng: np.random.Generator, n: int, max_angle: float) -> np.ndarray:
    """Rotations about uniformly random axes by angles uniform in [0, max_angle] (radians)."""
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    ang = rng.uniform(0.0, max_angle, n)
    kx = np.zeros((n, 3, 3))
    kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    kx = kx - kx.transpose(0, 2, 1)
    s, c = np.sin(ang)[:, None, None], np.cos(ang)[:, None, None]
    return np.eye(3) + s * kx + (1 - c) * kx @ kx


def _irregular_uv(rng: np.random.Generator, n: int, p: int, irregular: float) -> np.ndarray:
    """Samples in [-1, 1]^2: uniform, with a share ``irregular`` drawn around a random centre."""
    uv = rng.uniform(-1.0, 1.0, (n, p, 2))
    if irregular > 0:
        share = rng.uniform(0.0, irregular, n)
        centre = rng.uniform(-0.7, 0.7, (n, 1, 2))
        spread = rng.uniform(0.15, 0.5, (n, 1, 1))
        clustered = np.clip(centre + spread * rng.normal(size=(n, p, 2)), -1.0, 1.0)
        pick = rng.uniform(size=(n, p, 1)) < share[:, None, None]
        uv = np.where(pick, clustered, uv)
    return uv


def _given_uv(uv, n: int) -> np.ndarray:
    """The caller's sample parameters as a float64 (n, P, 2) array (a copy)."""
    a = np.asarray(uv.detach().cpu() if hasattr(uv, "detach") else uv)
    if a.dtype.kind not in "biuf":
        raise TypeError(f"uv: expected a real array, got dtype {a.dtype}")
    a = a.astype(np.float64)
    if a.ndim == 2:
        a = np.broadcast_to(a, (n, *a.shape))
    check_shape(a, "uv", (n, "P", 2))
    if not np.isfinite(a).all():
        raise ValueError(f"uv: expected finite values, got {int((~np.isfinite(a)).sum())} NaN/inf")
    return a.copy()


def family_patches(
    n_patches: int,
    n_points: int = 128,
    *,
    families: tuple[str, ...] = PATCH_FAMILIES,
    amplitude: float = 0.5,
    noise: float = 0.0,
    max_angle: float = np.pi,
    irregular: float = 0.5,
    seed: int | np.random.Generator = 0,
    uv: np.ndarray | None = None,
) -> FamilyPatches:
    """Random height-field patches, sums of the four families of thesis §5.5.1.

    The height over ``(u, v)`` in ``[-1, 1]^2`` is the sum of the chosen families:

    * ``"jet"``: a 4-jet, 15 coefficients uniform in ``[-amplitude, amplitude]``;
    * ``"trig"``: ``a cos(theta sqrt(u^2 + v^2))``, ``theta`` in ``[pi, 2 pi]``;
    * ``"gauss"``: ``a exp(-|uv - c|^2 / (2 sigma^2))``, ``sigma`` in ``[0.5, 1]``,
      centre ``c`` uniform in ``[-1, 1]^2``;
    * ``"bessel"``: ``a J0(k |uv - c|)`` with ``k = 5``;

    each amplitude ``a`` uniform in ``[-amplitude, amplitude]``. Samples are irregular
    (uniform plus a cluster), the patch is rotated by a random rotation of angle up to
    ``max_angle`` and Gaussian noise of standard deviation ``noise`` (same units as
    ``u, v``) is added to the positions.

    Parameters
    ----------
    n_patches : int
        Number of patches B (>= 1).
    n_points : int
        Samples per patch P (>= 1).
    families : tuple of str
        Non-empty subset of :data:`PATCH_FAMILIES`.
    amplitude : float
        Bound of the amplitudes and jet coefficients (thesis: 0.5).
    noise : float
        Standard deviation of the positional noise (>= 0).
    max_angle : float
        Largest rotation angle in radians (``pi``: uniformly random axis and angle).
    irregular : float
        Largest share of clustered samples, in ``[0, 1]``.
    seed : int or numpy.random.Generator
        Randomness.
    uv : array_like, shape (P, 2) or (B, P, 2), optional
        Sample parameters to use instead of the irregular draw (for instance a grid, to
        share one triangulation between the patches); ``n_points`` and ``irregular`` are
        then ignored and the draws of the parameters and rotations are unchanged.

    Returns
    -------
    FamilyPatches
        Points, exact normals, generating parameters and heights, rotations.

    Raises
    ------
    ValueError
        On an empty or unknown family, non-positive counts, negative noise/amplitude or
        ``uv`` of the wrong shape or not finite.
    TypeError
        If a count is not an integer.
    """
    n = check_int(n_patches, "n_patches", low=1)
    p = check_int(n_points, "n_points", low=1)
    fams = tuple(families)
    if not fams or any(f not in PATCH_FAMILIES for f in fams):
        raise ValueError(f"families: expected a non-empty subset of {PATCH_FAMILIES}, got {fams}")
    amplitude = check_positive(amplitude, "amplitude", strict=False)
    noise = check_positive(noise, "noise", strict=False)
    max_angle = check_positive(max_angle, "max_angle", strict=False)
    irregular = float(irregular)
    if not 0.0 <= irregular <= 1.0:
        raise ValueError(f"irregular: expected a value in [0, 1], got {irregular}")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    par = _family_params(rng, n, fams, amplitude)
    uv = _irregular_uv(rng, n, p, irregular) if uv is None else _given_uv(uv, n)
    z, g = _family_height_grad(uv, par)
    local = np.concatenate([uv, z[..., None]], axis=-1)
    nrm = np.concatenate([-g, np.ones(z.shape + (1,))], axis=-1)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    rot = _random_rotations_np(rng, n, max_angle)
    pts = np.einsum("bij,bpj->bpi", rot, local)
    nrm = np.einsum("bij,bpj->bpi", rot, nrm)
    if noise > 0:
        pts = pts + noise * rng.normal(size=pts.shape)
    return FamilyPatches(points=pts, normals=nrm, uv=uv, height=z, rotation=rot)


def family_grid_patches(
    n_patches: int, n_points: int, *, seed: int | np.random.Generator = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Family patches (see :func:`family_patches`) sampled on jittered grids, padded.

    Each patch draws a grid size ``m`` in ``[m_max - 4, m_max]``, ``m_max =
    max(4, floor(sqrt(n_points)))``, samples its height (the sum of the four families with
    amplitude 0.5) on the ``m x m`` grid of ``[-1, 1]^2`` jittered by up to a quarter of the
    spacing, and is rotated by a uniformly random rotation. The first ``min(m^2, n_points)``
    slots hold the points, the rest is zero padding (the training data of the STN).

    Parameters
    ----------
    n_patches : int
        Number of patches ``B`` (>= 1).
    n_points : int
        Slots per patch ``P`` (>= 1).
    seed : int or numpy.random.Generator
        Randomness; the draws are, in order: family parameters, grid sizes, jitter per
        patch, rotations.

    Returns
    -------
    points : numpy.ndarray, shape (B, P, 3), float64
        Samples (same units as ``u, v``), zero in the padding.
    mask : numpy.ndarray, shape (B, P), bool
        True for the samples, False for the padding.

    Raises
    ------
    ValueError, TypeError
        If a count is not a positive integer.
    """
    n = check_int(n_patches, "n_patches", low=1)
    n_points = check_int(n_points, "n_points", low=1)
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    m_hi = max(4, math.isqrt(n_points))
    par = _family_params(rng, n, PATCH_FAMILIES, 0.5)
    ms = rng.integers(max(2, m_hi - 4), m_hi + 1, n)
    uv = np.zeros((n, n_points, 2))
    msk = np.zeros((n, n_points), bool)
    for i, m in enumerate(ms):
        t = np.linspace(-1.0, 1.0, int(m))
        g = np.stack(np.meshgrid(t, t, indexing="ij"), -1).reshape(-1, 2)
        g = g + rng.uniform(-0.25, 0.25, g.shape) * (2.0 / (m - 1))
        k = min(len(g), n_points)
        uv[i, :k] = g[:k]
        msk[i, :k] = True
    z, _ = _family_height_grad(uv, par)
    local = np.concatenate([uv, z[..., None]], -1)
    rot = _random_rotations_np(rng, n, np.pi)
    pts = np.einsum("bij,bpj->bpi", rot, local)
    return np.where(msk[..., None], pts, 0.0), msk
