"""Cloth energies shared by every draping method (GAPS, OneFit, GarNet, FNOpt, the reference).

SI units throughout: positions in metres (m), masses in kilograms (kg), time in seconds (s),
energies in joules (J), stresses and moduli in pascals (Pa = J/m^3). Every energy takes vertex
positions ``x`` of shape ``(..., V, 3)`` (a leading batch of frames sharing one garment) and
returns one energy per frame, shape ``(...)``; all are differentiable in torch (float64 passes
``gradcheck``). Seed thesis (004) section 3.2-3.4 and section 4.3.2:

- membrane: St. Venant-Kirchhoff, eq. (15)-(16), ``h A psi(E)`` per triangle with
  ``E = (F^T F - I) / 2`` and ``F = D_s D_m^-1`` (eq. (13));
- bending: dihedral angles, eq. (17), and the GAPS blend of eq. (41);
- gravity eq. (39), inertia eq. (42) (the implicit-Euler term of eq. (26));
- body collision eq. (27)/(40): cubic penalty on a signed distance supplied by the caller;
- body friction: lagged, smoothed Coulomb friction (IPC, Li et al. 2020) for dynamic frames;
- self repulsion eq. (28) over truncated neighbour pairs (memory ``O(V k)``);
- GAPS covariance inextensibility eq. (44) with the collision-aware ``k_ext`` of eq. (45)
  (optionally spread to the cloth around a contact), built on :mod:`polygeo.covariance`.

The rest geometry of a garment (inverse rest edge matrices, areas, lumped masses, hinges,
1-ring neighbourhoods) is computed once by :func:`rest_state`.
"""

from .contact import (
    collision_energy,
    friction_energy,
    inextensibility_energy,
    k_ext_schedule,
    plane_distance,
    repulsion_energy,
    repulsion_pairs,
    spread_over_rings,
)
from .elastic import (
    bending_energy,
    deformation_gradient,
    gaps_bending_energy,
    gravity_energy,
    green_strain,
    inertia_energy,
    stvk_energy,
)
from .rest import GRAVITY, Material, RestState, rest_state

__all__ = [
    "GRAVITY",
    "Material",
    "RestState",
    "rest_state",
    "deformation_gradient",
    "green_strain",
    "stvk_energy",
    "bending_energy",
    "gaps_bending_energy",
    "gravity_energy",
    "inertia_energy",
    "collision_energy",
    "plane_distance",
    "friction_energy",
    "repulsion_pairs",
    "repulsion_energy",
    "inextensibility_energy",
    "k_ext_schedule",
    "spread_over_rings",
]
