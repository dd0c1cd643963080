"""``polygeo bench NAME``: run ``benchmarks/bm_NAME.py`` from a source checkout."""

from __future__ import annotations

import argparse
import runpy
import sys
from pathlib import Path


def _benchmarks_dir() -> Path:
    return Path(__file__).resolve().parents[2] / "benchmarks"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bench",
        help="run a benchmark script (source checkout only)",
        description="Run benchmarks/bm_NAME.py; extra arguments are passed to the script. "
        "Each benchmark writes a JSON record and a PNG chart into its results folder.",
    )
    p.add_argument("name", help="benchmark name, e.g. 'jets' for benchmarks/bm_jets.py")
    p.add_argument("args", nargs=argparse.REMAINDER, help="arguments passed to the script")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    script = _benchmarks_dir() / f"bm_{args.name}.py"
    if not script.is_file():
        available = sorted(p.stem[3:] for p in _benchmarks_dir().glob("bm_*.py"))
        raise FileNotFoundError(f"no benchmark {args.name!r}; available: {available}")
    sys.argv = [str(script), *args.args]
    runpy.run_path(str(script), run_name="__main__")
    return 0
