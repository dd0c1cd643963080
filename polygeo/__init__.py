"""polygeo: deformable surfaces as local polynomial jets.

Sub-modules (imported on first access, so that ``import polygeo`` stays cheap):

``jets``        monomial basis of n-jets, batched weighted least-squares fitting, evaluation
``frames``      PCA frames, quaternions, orientations (s, R, T)
``diffgeo``     fundamental forms, shape operator, curvatures, Monge form
``neighbors``   k-NN / radius neighbourhoods, mesh k-rings
``covariance``  per-vertex covariance descriptors and the GAPS inextensibility residual
``mesh``        edge lengths, areas, normals, adjacency of triangle meshes
``io``          reading and writing point clouds and meshes
``runs``        atomic writes, safe checkpoints, resume by settings fingerprint, logs, progress
``partition``   ACVD-like partition of a surface into patches
``patches``     PatchSet: oriented n-jet patches (PolyFit)
``proximity``   closest points on triangles, point-to-mesh distances, Chamfer distances
``subdivision`` regular barycentric subdivision of triangulations
``canonical``   PCA canonical frames of patches, jet height residual, test-time refinement
``stn``         rigid spatial transformer refining patch orientations (network, weights)
``stn_train``   training of the STN (resumable, checkpointed)
``render``      differentiable soft rasterizer for CPU
``synthetic``   analytic surfaces and synthetic patch families
"""

from __future__ import annotations

import importlib
import os
import sys
from typing import Any

__version__ = "0.1.0"

# The compiled kernels (numba, ``parallel=True``) default to numba's own "workqueue" thread
# pool. With the OpenMP layer, idle worker threads spin-wait: on a machine whose cores are busy
# with other work, a 128 x 128 soft render measured 115 ms (median) instead of 9-11 ms. Users
# who set NUMBA_THREADING_LAYER themselves keep their choice. The workqueue layer must not be
# entered from several Python threads at once; use processes for that kind of parallelism.
if "NUMBA_THREADING_LAYER" not in os.environ:
    os.environ["NUMBA_THREADING_LAYER"] = "workqueue"
    if "numba" in sys.modules:  # numba already imported: its config was read, set it directly
        sys.modules["numba"].config.THREADING_LAYER = "workqueue"

# numba's disk cache does not notice a change in a kernel inlined from another module, nor an
# upgrade that leaves old cache files behind: drop it when the kernels' sources changed.
from ._numba_cache import drop_stale as _drop_stale  # noqa: E402

_drop_stale(os.path.dirname(__file__))

_SUBMODULES = (
    "jets",
    "frames",
    "diffgeo",
    "neighbors",
    "covariance",
    "mesh",
    "io",
    "runs",
    "partition",
    "patches",
    "proximity",
    "subdivision",
    "canonical",
    "stn",
    "stn_train",
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
