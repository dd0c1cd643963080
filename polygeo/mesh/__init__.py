"""Triangle-mesh primitives, the one home of per-edge and per-face geometry.

Edges, lengths, areas, normals, dihedral angles, cotangent weights, boundaries, components,
welding, clean-up and consistent face winding.

``polygeo.mesh`` is the public home of these names (import them from here); the code lives in
three modules by concept:

- :mod:`polygeo.mesh.topology`: connectivity on integer ``faces (F, 3)`` (edges, edge-face
  incidence, boundary and non-manifold edges, vertex adjacency, connected components, welding
  and removal of unreferenced vertices); NumPy arrays out (tensors when given tensors).
- :mod:`polygeo.mesh.orientation`: consistent face winding (:func:`orient_faces`).
- :mod:`polygeo.mesh.geometry`: per-edge and per-face quantities (:func:`edge_lengths`,
  :func:`edge_length_energy`, :func:`face_areas`, :func:`face_normals`,
  :func:`vertex_normals`, :func:`dihedral_angles`, :func:`cotangent_weights`); these are
  torch-differentiable with respect to the vertices, accept a leading batch of vertex sets
  ``(..., N, 3)`` sharing one connectivity, and never return NaN: degenerate faces come back
  with a ``valid`` mask and zero normals (and zero gradients).
"""

from __future__ import annotations

from .geometry import (
    CotanWeights,
    Dihedral,
    FaceNormals,
    VertexNormals,
    cotangent_weights,
    dihedral_angles,
    edge_length_energy,
    edge_lengths,
    face_areas,
    face_normals,
    vertex_normals,
)
from .orientation import (
    OrientedFaces,
    orient_faces,
)
from .topology import (
    Compacted,
    Welded,
    boundary_edges,
    connected_components,
    edge_faces,
    edges,
    non_manifold_edges,
    remove_unreferenced_vertices,
    vertex_adjacency,
    weld_vertices,
)

__all__ = [
    "FaceNormals",
    "VertexNormals",
    "Dihedral",
    "CotanWeights",
    "Welded",
    "Compacted",
    "OrientedFaces",
    "edges",
    "edge_faces",
    "edge_lengths",
    "edge_length_energy",
    "face_areas",
    "face_normals",
    "vertex_normals",
    "dihedral_angles",
    "cotangent_weights",
    "boundary_edges",
    "non_manifold_edges",
    "connected_components",
    "vertex_adjacency",
    "weld_vertices",
    "remove_unreferenced_vertices",
    "orient_faces",
]
