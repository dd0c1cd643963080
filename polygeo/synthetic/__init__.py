"""Analytic surfaces with exact differential quantities, and synthetic test shapes.

``polygeo.synthetic`` is the public home of these names; the code lives by concept in

- :mod:`polygeo.synthetic.analytic`: spheres, cylinders, tori, Monge patches, planes and wavy
  sheets with exact normals and curvatures (:class:`AnalyticSample`), as point samples or
  meshes (conventions and sign of curvature in that module's docstring);
- :mod:`polygeo.synthetic.families`: the random patch families of STN training;
- :mod:`polygeo.synthetic.cloth`: garment-like test meshes (draped sheet, skirt, body).
"""

from __future__ import annotations

from .analytic import (
    AnalyticSample,
    cylinder,
    cylinder_mesh,
    monge_patch,
    monge_patch_mesh,
    plane,
    plane_mesh,
    sphere,
    sphere_mesh,
    torus,
    torus_mesh,
    wavy_sheet_mesh,
)
from .cloth import (
    body_mesh,
    draped_sheet_mesh,
    skirt_mesh,
)
from .families import (
    PATCH_FAMILIES,
    FamilyPatches,
    family_grid_patches,
    family_patches,
)

__all__ = [
    "AnalyticSample",
    "sphere",
    "cylinder",
    "torus",
    "monge_patch",
    "plane",
    "sphere_mesh",
    "cylinder_mesh",
    "torus_mesh",
    "monge_patch_mesh",
    "plane_mesh",
    "wavy_sheet_mesh",
    "PATCH_FAMILIES",
    "FamilyPatches",
    "family_patches",
    "family_grid_patches",
    "draped_sheet_mesh",
    "skirt_mesh",
    "body_mesh",
]
