"""polygeo._numba_cache: numba's disk cache is dropped when the kernel sources change."""

from polygeo._numba_cache import STAMP_NAME, drop_stale


def _package(tmp_path):
    root = tmp_path / "pkg"
    (root / "sub" / "__pycache__").mkdir(parents=True)
    (root / "__pycache__").mkdir()
    (root / "kernels.py").write_text("import numba as nb\n\n@nb.njit(cache=True)\ndef f(x):\n"
                                     "    return x\n")
    (root / "plain.py").write_text("X = 1\n")
    (root / "sub" / "more.py").write_text("from ..kernels import f  # calls a numba kernel\n")
    return root


def _caches(root):
    for d in (root / "__pycache__", root / "sub" / "__pycache__"):
        (d / "kernels.f-3.py311.nbi").write_bytes(b"i")
        (d / "kernels.f-3.py311.1.nbc").write_bytes(b"c")
        (d / "kernels.cpython-311.pyc").write_bytes(b"p")


def test_cache_dropped_only_when_kernel_sources_change(tmp_path, monkeypatch):
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    root = _package(tmp_path)
    _caches(root)
    # no stamp yet: whatever is cached may predate it
    assert drop_stale(root) == 4
    assert (root / "__pycache__" / STAMP_NAME).is_file()
    assert sorted(p.name for p in (root / "__pycache__").iterdir()) == [
        "kernels.cpython-311.pyc", STAMP_NAME]
    _caches(root)
    assert drop_stale(root) == 0  # unchanged sources: the cache stays
    (root / "plain.py").write_text("X = 2\n")
    assert drop_stale(root) == 0  # a file without kernels changed: the cache stays
    (root / "sub" / "more.py").write_text("from ..kernels import f  # numba, edited\n")
    assert drop_stale(root) == 4  # a numba file changed: every cache file goes
    assert not list(root.rglob("*.nbi")) and not list(root.rglob("*.nbc"))
    assert len(list(root.rglob("*.pyc"))) == 2


def test_numba_cache_dir_left_to_its_owner(tmp_path, monkeypatch):
    root = _package(tmp_path)
    _caches(root)
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "elsewhere"))
    assert drop_stale(root) == 0
    assert len(list(root.rglob("*.nbc"))) == 2
