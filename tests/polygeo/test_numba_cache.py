"""polygeo._numba_cache: numba's disk cache keyed on every kernel source of the package."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from polygeo._numba_cache import sources_hash

_A = "import numba as nb\n\n\n@nb.njit(cache=True, inline='always')\ndef g(x):\n    return x + {}\n"
_B = ("import numba as nb\n\nfrom .a import g\n\n\n@nb.njit(cache=True)\ndef f(x):\n"
      "    return g(x)\n")
_RUN = """
import json, sys
sys.path.insert(0, {site!r})
if {ours}:
    from polygeo._numba_cache import install
    install({pkg!r})
import {name}.b as b
print(json.dumps([b.f(1), sum(b.f.stats.cache_hits.values())]))
"""


def _package(site: Path, name: str) -> Path:
    pkg = site / name
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text(_A.format(1))
    (pkg / "b.py").write_text(_B)
    return pkg


def _call(site: Path, pkg: Path, ours: bool) -> list:
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR",)}
    env.update(NUMBA_NUM_THREADS="1", XDG_CACHE_HOME=str(site.parent / "xdg"))
    code = _RUN.format(site=str(site), ours=ours, pkg=str(pkg), name=pkg.name)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.slow  # seven interpreters importing numba and compiling
def test_change_of_an_inlined_kernel_in_another_module_recompiles(tmp_path):
    site = tmp_path / "site"
    ours, plain = _package(site, "kpkg"), _package(site, "kplain")
    for pkg, keyed in ((ours, True), (plain, False)):
        assert _call(site, pkg, keyed) == [2, 0]  # compiled and cached
        assert _call(site, pkg, keyed) == [2, 1]  # loaded from the cache
        (pkg / "a.py").write_text(_A.format(2))  # b.py, which defines f, is unchanged
    # keyed on all kernel sources: recompiled with the new g
    assert _call(site, ours, True) == [3, 0]
    assert _call(site, ours, True) == [3, 1]
    # numba's own key (the defining file) loads the stale kernel: what the locators fix
    assert _call(site, plain, False) == [2, 1]


def test_sources_hash_follows_kernel_files_only(tmp_path):
    root = tmp_path / "pkg"
    (root / "sub").mkdir(parents=True)
    (root / "kernels.py").write_text(_A.format(1))
    (root / "plain.py").write_text("X = 1\n")
    (root / "sub" / "more.py").write_text("from ..kernels import g  # calls a numba kernel\n")
    h0 = sources_hash.__wrapped__(root)
    assert sources_hash.__wrapped__(root) == h0
    (root / "plain.py").write_text("X = 2\n")
    assert sources_hash.__wrapped__(root) == h0  # a file without kernels changed
    (root / "sub" / "more.py").write_text("from ..kernels import g  # numba, edited\n")
    h1 = sources_hash.__wrapped__(root)
    assert h1 != h0
    (root / "kernels.py").write_text(_A.format(2))
    assert sources_hash.__wrapped__(root) not in (h0, h1)
