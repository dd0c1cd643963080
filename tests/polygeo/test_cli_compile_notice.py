"""The first run says that it compiles kernels; a warm run says nothing; --quiet silences it."""

import argparse
import subprocess
import sys
import textwrap

import polygeo.cli as cli

KERNELS = """
from numba import njit


@njit(cache=True)
def cached_a(x):
    return x + 1


@njit(cache=True)
def cached_b(x):
    return 2 * x


@njit  # no disk cache: compiled on every run, never announced
def uncached(x):
    return x - 1
"""

RUN = """
import sys
sys.path.insert(0, {folder!r})
from polygeo.cli import compile_notice, COMPILE_NOTICE
assert compile_notice() is True and compile_notice() is False
import kernels_for_notice as k
print("uncached", k.uncached(3), file=sys.stderr, flush=True)
print("cached", k.cached_a(1), k.cached_b(2), file=sys.stderr, flush=True)
"""


def _run(tmp_path):
    env = {"NUMBA_CACHE_DIR": str(tmp_path / "cache"), "PATH": "/usr/bin:/bin",
           "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}
    code = textwrap.dedent(RUN.format(folder=str(tmp_path)))
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=env, check=True)
    return res.stderr


def test_notice_once_on_a_cold_cache_and_never_on_a_warm_one(tmp_path):
    (tmp_path / "kernels_for_notice.py").write_text(KERNELS)
    cold = _run(tmp_path)
    lines = cold.splitlines()
    assert lines.count(cli.COMPILE_NOTICE) == 1, cold
    # said when the first cached kernel starts compiling, not for the uncached one
    assert lines.index("uncached 2") < lines.index(cli.COMPILE_NOTICE) < lines.index(
        "cached 2 4")
    warm = _run(tmp_path)  # the same cache folder: every cached kernel is loaded
    assert cli.COMPILE_NOTICE not in warm and "cached 2 4" in warm


def _fake_parser(calls):
    def build(only=None):
        p = argparse.ArgumentParser(prog="polygeo")
        sub = p.add_subparsers(dest="command")
        q = sub.add_parser("work")
        q.add_argument("--quiet", action="store_true")
        q.set_defaults(func=lambda args: 0)
        return p

    return build


def test_main_asks_for_the_notice_unless_quiet(monkeypatch):
    calls = []
    monkeypatch.setattr(cli, "build_parser", _fake_parser(calls))
    monkeypatch.setattr(cli, "compile_notice", lambda stream=None: calls.append(1))
    assert cli.main(["work"]) == 0 and calls == [1]
    assert cli.main(["work", "--quiet"]) == 0 and calls == [1]


def test_the_command_line_is_not_a_kernel_source():
    # polygeo._numba_cache keys every cached kernel on the files that mention numba: were the
    # command line one of them, each edit of it would recompile every kernel (15-40 s)
    from pathlib import Path

    text = Path(cli.__file__).read_bytes()
    assert b"numba" not in text and b"njit" not in text
