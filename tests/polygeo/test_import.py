"""``import polygeo`` writes nothing and sets no environment variable."""

import json
import os
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import polygeo

_IMPORT = """
import json, os, sys
sys.path.insert(0, {site!r})
before = dict(os.environ)
import polygeo
polygeo.__version__, dir(polygeo)
after = dict(os.environ)
changed = sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k))
print(json.dumps({{"file": polygeo.__file__, "changed": changed,
                  "heavy": [m for m in ("numba", "torch") if m in sys.modules]}}))
"""

_KERNEL = """
import json, os, sys
sys.path.insert(0, {site!r})
before = dict(os.environ)
import numpy as np
import polygeo
from polygeo._numba_util import finite_rows
a = np.ones((6, 3))
a[2, 1] = np.nan
r = finite_rows(a)
import numba
print(json.dumps({{"ok": r.tolist() == [True, True, False, True, True, True],
                  "env_same": dict(os.environ) == before,
                  "layer": numba.config.THREADING_LAYER}}))
"""


def _copy_package(tmp_path: Path) -> Path:
    site = tmp_path / "site"
    shutil.copytree(Path(polygeo.__file__).parent, site / "polygeo",
                    ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    return site


def _snapshot(root: Path) -> dict:
    return {str(p.relative_to(root)): (p.stat().st_mtime_ns, p.stat().st_size)
            for p in sorted(root.rglob("*"))}


def _chmod_tree(root: Path, writable: bool) -> None:
    for p in [root, *root.rglob("*")]:
        mode = p.stat().st_mode
        mode = mode | stat.S_IWUSR if writable else mode & ~(stat.S_IWUSR | stat.S_IWGRP
                                                              | stat.S_IWOTH)
        p.chmod(mode)


def _run(code: str, cwd: Path, **env_extra) -> subprocess.Popen:
    env = {k: v for k, v in os.environ.items()
           if k not in ("NUMBA_THREADING_LAYER", "NUMBA_CACHE_DIR")}
    env.update(PYTHONDONTWRITEBYTECODE="1", NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1",
               **env_extra)
    return subprocess.Popen([sys.executable, "-c", code], cwd=cwd, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def _result(proc: subprocess.Popen) -> dict:
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    return json.loads(out.strip().splitlines()[-1])


def test_import_from_read_only_copy_writes_nothing_and_keeps_environ(tmp_path):
    site = _copy_package(tmp_path)
    before = _snapshot(site)
    _chmod_tree(site, writable=False)
    try:
        res = _result(_run(_IMPORT.format(site=str(site)), tmp_path))
        assert res["file"] == str(site / "polygeo" / "__init__.py")
        assert res["changed"] == []
        assert res["heavy"] == []  # the sub-modules load on first access
        assert _snapshot(site) == before  # nothing created, deleted or rewritten
    finally:
        _chmod_tree(site, writable=True)


def test_two_processes_import_and_compile_at_once(tmp_path):
    # a fresh writable copy: both processes compile and write numba's cache concurrently
    site = _copy_package(tmp_path)
    cache = tmp_path / "xdg"
    procs = [_run(_KERNEL.format(site=str(site)), tmp_path, XDG_CACHE_HOME=str(cache))
             for _ in range(2)]
    for p in procs:
        res = _result(p)
        assert res["ok"] and res["env_same"]
        assert res["layer"] == "workqueue"  # chosen in numba.config, not in os.environ
