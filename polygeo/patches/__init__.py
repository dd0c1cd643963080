r"""PolyFit: a surface as K oriented n-jet patches (thesis §5.2).

Every patch ``i`` is an orientation ``O_i = (s_i, R_i, T_i)`` and the coefficients ``a_i`` of
an n-jet height ``z_i(u, v)`` over a canonical uv plane:

.. math::

    p = s_i R_i \, (u, v, z_i(u, v))^T + T_i .

:meth:`PatchSet.fit` partitions the input (:mod:`polygeo.partition`), frames every patch
(PCA, optionally refined by the rigid STN or by test-time optimisation, :mod:`polygeo.stn`)
and fits all jets in one batched least-squares call (:func:`polygeo.jets.fit`, patches
padded with a mask). A :class:`PatchSet` then evaluates positions, normals, Jacobians,
metric tensors and curvatures at any ``(patch, uv)`` (differentiably, through
:func:`evaluate_patches` / :func:`patch_geometry`), resamples the whole surface as a mesh at
any resolution (watertight across patch boundaries where the input mesh was), reports
per-patch quality (:meth:`PatchSet.metrics`) and round-trips through NPZ.

The package is a thin front end over pure functions, one module per stage:

``fitting``     padding, reference normals, frame refinement, order cap, capped / auto fits
``evaluation``  positions, differential geometry and projection on patches
``resampling``  the surface as a mesh (subdivided input triangulation, or per-patch lattices)
``metrics``     :class:`PatchMetrics` and the per-patch error measures
``storage``     the NPZ format
``patchset``    :class:`PatchSet`

Chamfer distances and closest points live in :mod:`polygeo.proximity`, the barycentric
subdivision in :mod:`polygeo.subdivision`; they are re-exported here for existing callers.

Units and conventions
---------------------
* ``uv`` and heights are canonical (dimensionless): the patch's points lie in the unit ball
  around its centroid before the jet fit, so ``s_i`` is the patch radius in input units.
  Height RMSE, boundary gaps and the Chamfer distance are reported in input units (or as
  documented); normal errors in degrees.
* Jet coefficients are stored at the largest order of the set, ``(K, M)``; a patch of a
  lower order (``order="auto"`` or a reduced fit) has zeros in its higher slots (the monomial
  order of :mod:`polygeo.jets` is graded, so a lower-order jet is a prefix).
* Normals follow the input's orientation where it is known (mesh winding or given normals):
  each patch's frame is flipped so that its normal agrees with the mean input normal.
"""

from __future__ import annotations

from ..proximity import (
    ChamferReport,
    chamfer_distance,
    chamfer_report,
    closest_point_on_triangles,
    squared_distance_to_mesh,
)
from ..subdivision import subdivide_barycentric
from .evaluation import PatchGeometry, evaluate_patches, patch_geometry
from .fitting import ORIENT_CHOICES
from .metrics import PatchMetrics
from .patchset import PatchSet

__all__ = [
    "PatchSet",
    "PatchMetrics",
    "PatchGeometry",
    "evaluate_patches",
    "patch_geometry",
    "ORIENT_CHOICES",
    # re-exported from polygeo.proximity and polygeo.subdivision (their homes)
    "subdivide_barycentric",
    "chamfer_distance",
    "chamfer_report",
    "ChamferReport",
]


def _closest_on_triangles(p, a, b, c):
    """Squared distances to triangles (kept for callers of the former private helper)."""
    return closest_point_on_triangles(p, a, b, c).sq_distance


def _point_to_mesh_sq(p, v, f, k=8):
    """Squared distances to a mesh (kept for callers of the former private helper)."""
    return squared_distance_to_mesh(p, v, f, k=k)
