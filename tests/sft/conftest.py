"""Small synthetic SfT sequences rendered with VTK (datasets/generate_sft.py), once per session."""

import importlib.util
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
            try:
                gen.generate(cfg, out, progress=False)
            except Exception as exc:  # no off-screen OpenGL: VTK cannot render here
                pytest.skip(f"VTK off-screen rendering unavailable ({exc})")
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
