"""Small synthetic SfT sequences rendered with VTK (datasets/generate_sft.py), once per session.

Where VTK cannot render off screen (pyvista/VTK not importable, or no OpenGL context) the
tests that need a sequence are skipped locally, but fail in CI (``CI`` set to ``true`` or
``1``): CI must not go green with them silently skipped. Any other error of the generator is
a test failure everywhere.
"""

import functools
import importlib.util
import os
import sys
from pathlib import Path

import pytest
import torch

_GEN = Path(__file__).resolve().parents[2] / "datasets" / "generate_sft.py"


def _generator():
    spec = importlib.util.spec_from_file_location("generate_sft", _GEN)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["generate_sft"] = mod
    spec.loader.exec_module(mod)
    return mod


def in_ci() -> bool:
    """Whether the tests run in CI (``CI=true`` or ``CI=1``, as CI services set it)."""
    return os.environ.get("CI", "").strip().lower() in ("1", "true", "yes")


@functools.cache
def vtk_unavailable() -> str | None:
    """Why VTK cannot render off screen here, or None when it can (probed once).

    Only two cases count: pyvista/VTK cannot be imported (ImportError, e.g. a missing
    libGL), or the off-screen render window cannot be created or draws nothing
    (RuntimeError, or an empty probe image).
    """
    try:
        import pyvista as pv
        import vtk
    except ImportError as exc:
        return f"pyvista/VTK cannot be imported ({exc})"
    vtk.vtkLogger.SetStderrVerbosity(vtk.vtkLogger.VERBOSITY_OFF)
    try:
        p = pv.Plotter(off_screen=True, window_size=(16, 16))
        p.background_color = (0.0, 0.0, 0.0)
        p.add_mesh(pv.Sphere(radius=0.2), color="white", lighting=False)
        p.camera_position = [(0, 0, 3), (0, 0, 0), (0, 1, 0)]
        img = p.screenshot(return_img=True)
        p.close()
    except RuntimeError as exc:
        return f"VTK off-screen rendering unavailable ({exc})"
    if img is None or not img.any():
        return "VTK off-screen rendering unavailable (the probe render is empty)"
    return None


def require_vtk() -> None:
    """Skip (locally) or fail (in CI) when VTK cannot render off screen."""
    reason = vtk_unavailable()
    if reason is None:
        return
    if in_ci():
        pytest.fail(f"{reason}; CI must run the SfT sequence tests (CI={os.environ['CI']!r})")
    pytest.skip(reason)


@pytest.fixture(scope="session")
def make_sequence(tmp_path_factory):
    """make_sequence(kind, frames, size=80, grid=(16, 12)) -> path of a generated sequence."""
    gen = _generator()
    cache = {}

    def make(kind, frames, size=80, grid=(16, 12), texture_size=128):
        key = (kind, frames, size, grid, texture_size)
        if key not in cache:
            out = tmp_path_factory.mktemp(f"seq_{kind}") / "seq"
            cfg = gen.Config(kind=kind, frames=frames, size=size, grid=grid,
                             texture_size=texture_size, supersample=4, seed=0)
            require_vtk()
            gen.generate(cfg, out, progress=False)  # any error here is a failure
            cache[key] = out
        return cache[key]

    return make


@pytest.fixture(scope="session")
def generator_module():
    return _generator()


@pytest.fixture(autouse=True)
def _single_thread():
    """One thread for torch and numba: on a shared 2-core machine the small tensors of these
    tests run several times faster without intra-op parallelism (no waiting at barriers)."""
    import numba

    old_t, old_n = torch.get_num_threads(), numba.get_num_threads()
    torch.set_num_threads(1)
    numba.set_num_threads(1)
    yield
    torch.set_num_threads(old_t)
    numba.set_num_threads(old_n)
