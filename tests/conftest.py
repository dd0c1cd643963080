import importlib.util
import os
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]

# Keep the two CPU cores of CI from being oversubscribed by intra-op threads in tests.
torch.set_num_threads(min(2, os.cpu_count() or 1))


@pytest.fixture
def rng():
    return np.random.default_rng(0)


@pytest.fixture
def gen():
    return torch.Generator().manual_seed(0)


def _import_script(relpath: str):
    """The repository script ``relpath`` (e.g. ``"benchmarks/bm_gaps.py"``) as a module.

    Registered in ``sys.modules`` under its file's stem (dataclasses and pickling look a
    module up by name) and executed once per session; the script's folder is on ``sys.path``
    while it runs, so that it can import its siblings (``bm_fnopt_common``, ...).
    """
    path = ROOT / relpath
    mod = sys.modules.get(path.stem)
    if mod is not None and getattr(mod, "__file__", None) == str(path):
        return mod
    spec = importlib.util.spec_from_file_location(path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[path.stem] = mod
    sys.path.insert(0, str(path.parent))
    try:
        spec.loader.exec_module(mod)
    except BaseException:
        del sys.modules[path.stem]
        raise
    finally:
        sys.path.remove(str(path.parent))
    return mod


@pytest.fixture(scope="session")
def script():
    """``script("benchmarks/bm_x.py")``: a repository script imported by path, once."""
    return _import_script
