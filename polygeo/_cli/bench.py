"""``polygeo bench NAME``: run ``benchmarks/bm_NAME.py`` from a source checkout."""

from __future__ import annotations

import argparse
import runpy
import sys
from pathlib import Path


def _benchmarks_dir() -> Path:
    return Path(__file__).resolve().parents[2] / "benchmarks"


def _available() -> list[str]:
    return sorted(p.stem[3:] for p in _benchmarks_dir().glob("bm_*.py"))


def register(sub: argparse._SubParsersAction) -> None:
    names = _available()
    listed = ", ".join(names) if names else "none found (source checkout only)"
    p = sub.add_parser(
        "bench",
        help="run a benchmark script (source checkout only)",
        description="Run benchmarks/bm_NAME.py; extra arguments are passed to the script "
        "(polygeo bench NAME --help shows them). Each benchmark writes a JSON record and a PNG "
        f"chart into benchmarks/results/. Benchmarks: {listed}.",
    )
    p.add_argument("name", nargs="?", default=None,
                   help=f"benchmark name ({listed}); without it, list them")
    p.add_argument("args", nargs=argparse.REMAINDER, help="arguments passed to the script")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    if args.name is None:
        names = _available()
        print("benchmarks (polygeo bench NAME [ARGS]):" if names else "no benchmarks found "
              "(they live in a source checkout's benchmarks/ folder)")
        for name in names:
            print(f"  {name:<12} benchmarks/bm_{name}.py")
        return 0
    script = _benchmarks_dir() / f"bm_{args.name}.py"
    if not script.is_file():
        available = sorted(p.stem[3:] for p in _benchmarks_dir().glob("bm_*.py"))
        raise FileNotFoundError(f"no benchmark {args.name!r}; available: {available}")
    sys.argv = [str(script), *args.args]
    runpy.run_path(str(script), run_name="__main__")
    return 0
