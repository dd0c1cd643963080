"""polygeo: deformable surfaces as local polynomial jets.

Sub-modules (imported on first access, so that ``import polygeo`` stays cheap):

``jets``        monomial basis of n-jets, batched weighted least-squares fitting, evaluation
``frames``      PCA frames, quaternions, orientations (s, R, T)
``diffgeo``     fundamental forms, shape operator, curvatures, Monge form
``neighbors``   k-NN / radius neighbourhoods, mesh k-rings
``covariance``  per-vertex covariance descriptors and the GAPS inextensibility residual
``mesh``        edge lengths, areas, normals, adjacency of triangle meshes
``io``          reading and writing point clouds and meshes
``io_las``      LAS/LAZ files, memory-mapped coordinates of large NPY/PLY/LAS files
``tiling``      jets of clouds larger than memory: tiles with exact halos, resume, Dask
``runs``        atomic writes, safe checkpoints, resume by settings fingerprint, logs, progress
``partition``   ACVD-like partition of a surface into patches
``patches``     PatchSet: oriented n-jet patches (PolyFit)
``proximity``   closest points on triangles, point-to-mesh distances, Chamfer distances
``subdivision`` regular barycentric subdivision of triangulations
``canonical``   PCA canonical frames of patches, jet height residual, test-time refinement
``stn``         rigid spatial transformer refining patch orientations (network, weights)
``stn_train``   training of the STN (resumable, checkpointed)
``stn_settings`` settings of the STN training (torch-free, for the command line)
``render``      differentiable soft rasterizer for CPU
``synthetic``   analytic surfaces and synthetic patch families
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_SUBMODULES = (
    "jets",
    "frames",
    "diffgeo",
    "neighbors",
    "covariance",
    "mesh",
    "io",
    "io_las",
    "runs",
    "tiling",
    "partition",
    "patches",
    "proximity",
    "subdivision",
    "canonical",
    "stn",
    "stn_train",
    "stn_settings",
    "render",
    "synthetic",
)
# Public functions re-exported at the top level: name -> defining sub-module.
_FUNCTIONS = {
    "differential_quantities": "estimate",
    "DifferentialQuantities": "estimate",
}

__all__ = ["__version__", *_SUBMODULES, *_FUNCTIONS]


def __getattr__(name: str) -> Any:
    if name in _SUBMODULES:
        module = importlib.import_module(f".{name}", __name__)
        globals()[name] = module
        return module
    if name in _FUNCTIONS:
        value = getattr(importlib.import_module(f".{_FUNCTIONS[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'polygeo' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
