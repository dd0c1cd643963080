"""Material constants and the rest geometry of a garment (SI units).

Part of :mod:`draping.physics`; import from there.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from polygeo import covariance, mesh, neighbors
from polygeo.checks import as_tensor, check_faces, check_finite, check_shape

__all__ = ["GRAVITY", "Material", "RestState", "rest_state"]

#: Gravitational acceleration (m/s^2), z up (the Anny body's convention).
GRAVITY = (0.0, 0.0, -9.81)


@dataclass(frozen=True)
class Material:
    """Cloth material (SI units); the defaults are the SNUG/GAPS fabric.

    Parameters
    ----------
    density : float
        Volumetric density (kg/m^3); 426 by default.
    thickness : float
        Sheet thickness ``h`` (m); 4.7e-4 by default. The areal density is ``density *
        thickness`` (0.200 kg/m^2 by default).
    young : float
        Young's modulus ``E_Y`` (Pa); 0.7e5 by default. SNUG (and GAPS, which takes its material
        from SNUG) use it as a volumetric modulus multiplied by the thickness, i.e. a membrane
        stiffness ``E_Y h`` of 32.9 N/m.
    poisson : float
        Poisson's ratio ``nu`` in ``[0, 0.5)``; 0.485 by default.
    bending_multiplier : float
        Factor on the plate bending stiffness ``E_Y h^3 / (12 (1 - nu^2))``; SNUG uses 50, which
        gives the default bending stiffness ``k_b = 3.96e-5`` J (N m).
    lame : {"plane_stress", "eq16"}
        Lame coefficients. ``"plane_stress"`` (default, as SNUG and ARCSim): ``mu = E/(2(1+nu))``,
        ``lambda = E nu / (1 - nu^2)``, the moduli of a thin sheet whose transverse stress
        vanishes. ``"eq16"``: the three-dimensional ``lambda = E nu / ((1+nu)(1-2nu))`` of
        thesis eq. (16), which for ``nu = 0.485`` is 17 times stiffer in area change.

    Raises
    ------
    ValueError
        Non-positive density, thickness or modulus, ``nu`` outside ``[0, 0.5)``, a negative
        multiplier or an unknown ``lame``.
    """

    density: float = 426.0
    thickness: float = 4.7e-4
    young: float = 0.7e5
    poisson: float = 0.485
    bending_multiplier: float = 50.0
    lame: str = "plane_stress"

    def __post_init__(self) -> None:
        for name in ("density", "thickness", "young"):
            val = getattr(self, name)
            if not (np.isfinite(val) and val > 0):
                raise ValueError(f"Material.{name}: expected a finite value > 0, got {val}")
        if not (0.0 <= self.poisson < 0.5):
            raise ValueError(f"Material.poisson: expected a value in [0, 0.5), got {self.poisson}")
        if not (np.isfinite(self.bending_multiplier) and self.bending_multiplier >= 0):
            raise ValueError(
                f"Material.bending_multiplier: expected a finite value >= 0, "
                f"got {self.bending_multiplier}"
            )
        if self.lame not in ("plane_stress", "eq16"):
            raise ValueError(f"Material.lame: expected 'plane_stress' or 'eq16', got {self.lame!r}")

    @property
    def area_density(self) -> float:
        """Mass per unit area (kg/m^2)."""
        return self.density * self.thickness

    @property
    def lame_mu(self) -> float:
        """Shear modulus ``mu = E / (2 (1 + nu))`` (Pa)."""
        return self.young / (2.0 * (1.0 + self.poisson))

    @property
    def lame_lambda(self) -> float:
        """First Lame coefficient (Pa), plane stress or thesis eq. (16) (see ``lame``)."""
        nu = self.poisson
        if self.lame == "plane_stress":
            return self.young * nu / (1.0 - nu * nu)
        return self.young * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))

    @property
    def bending_stiffness(self) -> float:
        """Bending stiffness ``k_b`` of eq. (17) (J = N m)."""
        plate = self.young * self.thickness**3 / (12.0 * (1.0 - self.poisson**2))
        return self.bending_multiplier * plate


@dataclass(frozen=True)
class RestState:
    """Rest geometry of a garment, computed once by :func:`rest_state`.

    Attributes
    ----------
    vertices : (V, 3) float
        Rest (template) positions (m).
    faces : (F, 3) int64
        Consistently wound triangles.
    dm_inv : (F, 2, 2) float
        Inverse of the rest edge matrix ``D_m`` in a local 2-D frame of each triangle (1/m).
    area : (F,) float
        Rest triangle areas (m^2).
    mass : (V,) float
        Lumped vertex masses: a third of the adjacent rest areas times the areal density (kg).
    edges : (E, 2) int64
        Unique undirected edges; ``edge_length (E,)`` their rest lengths (m).
    edge_length : (E,) float
    hinges : polygeo.mesh.Dihedral
        Interior manifold edges with their two faces (the topology reused by the bending
        energies) and the rest dihedral angles ``hinges.angle (H,)`` (rad).
    hinge_weight : (H,) float
        ``l^2 / (8 (A_0 + A_1))`` of eq. (17) on the rest mesh (dimensionless).
    ring_index : (V, K) int64
        1-ring neighbourhoods (the vertex first), ``-1`` padding; ``ring_mask (V, K)`` bool.
    ring_mask : (V, K) bool
    ring_sigma : (V, 3) float
        Singular values of the rest 1-ring covariances (m^2), for eq. (44).
    material : Material
        The material the masses were computed with.
    face_stiffness : (F,) float or None
        Multiplier of the membrane stiffness per triangle (dimensionless; None: 1 everywhere),
        e.g. a stiff waistband on a stretchy skirt (:data:`draping.garments.SPECS`).
    """

    vertices: torch.Tensor
    faces: torch.Tensor
    dm_inv: torch.Tensor
    area: torch.Tensor
    mass: torch.Tensor
    edges: torch.Tensor
    edge_length: torch.Tensor
    hinges: mesh.Dihedral
    hinge_weight: torch.Tensor
    ring_index: torch.Tensor
    ring_mask: torch.Tensor
    ring_sigma: torch.Tensor
    material: Material
    face_stiffness: torch.Tensor | None = None

    @property
    def n_vertices(self) -> int:
        """Number of vertices ``V``."""
        return int(self.vertices.shape[0])


# ---------------------------------------------------------------------- validation


# ---------------------------------------------------------------------- rest state


def _local_dm(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rest edge matrices in an orthonormal frame of each triangle, and the areas."""
    e1 = v[f[:, 1]] - v[f[:, 0]]  # (F, 3)
    e2 = v[f[:, 2]] - v[f[:, 0]]
    l1 = np.linalg.norm(e1, axis=1)
    cr = np.cross(e1, e2)
    area = 0.5 * np.linalg.norm(cr, axis=1)
    if np.any(l1 <= 0) or np.any(area <= 1e-12 * np.maximum(l1, 1e-300) ** 2):
        bad = int(np.flatnonzero((l1 <= 0) | (area <= 1e-12 * l1**2))[0])
        raise ValueError(f"faces: face {bad} is degenerate (zero area) in the rest vertices")
    t = e1 / l1[:, None]
    b = np.cross(cr / (2 * area)[:, None], t)
    dm = np.zeros((f.shape[0], 2, 2))
    dm[:, 0, 0] = l1
    dm[:, 0, 1] = (e2 * t).sum(1)
    dm[:, 1, 1] = (e2 * b).sum(1)
    return dm, area


def rest_state(vertices: Any, faces: Any, material: Material | None = None,
               face_stiffness: Any = None) -> RestState:
    """Precompute the rest geometry of a garment template.

    Parameters
    ----------
    vertices : (V, 3) float array or tensor
        Rest positions (m); the template defines the unstrained metric (``E = 0``).
    faces : (F, 3) int array or tensor
        Consistently wound, non-degenerate triangles.
    material : Material, optional
        The cloth (default :class:`Material`), used for the lumped masses.
    face_stiffness : (F,) float, optional
        Multiplier (> 0, dimensionless) of the membrane stiffness of each triangle; None for
        a uniform cloth. Masses do not change.

    Returns
    -------
    RestState
        Tensors in the dtype of ``vertices`` (float64 for NumPy input).

    Raises
    ------
    ValueError
        Bad shapes, out-of-range indices, non-finite vertices, a degenerate face or a
        ``face_stiffness`` of the wrong length or not finite and positive.
    TypeError
        Non-numeric vertices, non-integer faces or a bad material.
    """
    material = Material() if material is None else material
    if not isinstance(material, Material):
        raise TypeError(f"material: expected a Material, got {type(material).__name__}")
    vt = as_tensor(vertices, "vertices")
    check_shape(vt, "vertices", ("V", 3))
    check_finite(vt, "vertices")
    dtype = vt.dtype
    v = vt.detach().cpu().to(torch.float64).numpy()
    n = v.shape[0]
    f = check_faces(faces, n).cpu().numpy()
    e_idx = mesh.edges(f)
    dm, area = _local_dm(v, f)
    fs = None
    if face_stiffness is not None:
        fs = np.asarray(face_stiffness, dtype=np.float64)
        if fs.shape != (f.shape[0],) or not (np.isfinite(fs).all() and (fs > 0).all()):
            raise ValueError(f"face_stiffness: expected {f.shape[0]} finite values > 0, got "
                             f"shape {fs.shape}")
    mass = np.zeros(n)
    np.add.at(mass, f.reshape(-1), np.repeat(area / 3.0, 3))
    mass *= material.area_density
    vt64 = torch.from_numpy(v)
    hinges = mesh.dihedral_angles(vt64, f)
    hf = np.asarray(hinges.faces)
    he = np.asarray(hinges.edges)
    lh = np.linalg.norm(v[he[:, 1]] - v[he[:, 0]], axis=1)
    weight = lh**2 / (8.0 * (area[hf[:, 0]] + area[hf[:, 1]])) if len(he) else np.zeros(0)
    ring = neighbors.mesh_k_ring(f, n, 1)
    ridx = torch.from_numpy(np.asarray(ring.index))
    rmask = torch.from_numpy(np.asarray(ring.mask))
    sigma = covariance.singular_values(covariance.vertex_covariance(vt64, ridx, rmask))

    def t(a: Any) -> torch.Tensor:
        return torch.as_tensor(np.asarray(a), dtype=dtype)

    return RestState(
        vertices=vt.detach().clone(),
        faces=torch.from_numpy(f),
        dm_inv=t(np.linalg.inv(dm)),
        area=t(area),
        mass=t(mass),
        edges=torch.from_numpy(np.asarray(e_idx, dtype=np.int64)),
        edge_length=t(np.linalg.norm(v[e_idx[:, 1]] - v[e_idx[:, 0]], axis=1)),
        hinges=mesh.Dihedral(he, hf, t(hinges.angle.detach().numpy()), hinges.valid),
        hinge_weight=t(weight),
        ring_index=ridx,
        ring_mask=rmask,
        ring_sigma=sigma.to(dtype),
        material=material,
        face_stiffness=None if fs is None else t(fs),
    )
