"""Garment draping and cloth optimisation on polygeo's geometry (GAPS, OneFit, GarNet, FNOpt).

Layout (DESIGN.md section 2): the foundation below is shared by every method; a method never
imports another method.

- :mod:`draping.physics` - every cloth energy (StVK membrane, dihedral bending and the GAPS
  variant, gravity, inertia, body collision, self repulsion, GAPS covariance inextensibility)
  and the rest geometry of a garment, SI units.
- :mod:`draping.reference` - the physics reference solver (static and implicit-Euler drapes).
- :mod:`draping.metrics` - edge, area and collision errors, distances and normal angles.
- ``draping.drape`` - the reference-drape pipeline (body + motion + garment -> skinning ->
  per-frame solves -> metrics, resumable run folders) behind ``polygeo drape-reference``.
- ``draping.outputs`` - the run folder every drape method writes (frame PLYs, ``metrics.json``,
  strip and GIF) from plain arrays.
- ``draping.body``, ``draping.motion``, ``draping.garments`` (+ ``garment_fit``,
  ``garment_checks``), ``draping.skinning``,
  ``draping.viz`` - the posable body, motions, garment templates, skinning and pictures.
- ``draping.names`` - the garment, motion and phenotype names (torch-free, for the CLIs).
- methods: ``draping.gaps``, ``draping.onefit``, ``draping.garnet``, ``draping.fnopt``.

Submodules are imported explicitly (``from draping import physics``); importing ``draping``
itself loads nothing heavy.
"""

__all__: list[str] = []
