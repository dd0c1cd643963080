"""The ``polygeo`` command line.

Sub-commands are plug-ins registered under the entry-point group ``polygeo.commands``
(see ``pyproject.toml``): each entry point is a function ``register(subparsers)`` that adds
an ``argparse`` sub-parser whose ``func`` default runs the command and returns an exit
status. This keeps the layering of DESIGN.md: the core never imports ``sft`` or
``draping``, yet ``polygeo sft`` and ``polygeo demo`` can use them.
"""

from __future__ import annotations

import argparse
import sys
from importlib.metadata import entry_points

__all__ = ["main", "build_parser"]


def build_parser() -> argparse.ArgumentParser:
    """Build the top-level parser with every registered sub-command."""
    parser = argparse.ArgumentParser(
        prog="polygeo",
        description="Deformable surfaces as local polynomial jets: jets, PolyFit, PolySfT.",
    )
    from . import __version__

    parser.add_argument("--version", action="version", version=f"polygeo {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    eps = sorted(entry_points(group="polygeo.commands"), key=lambda e: e.name)
    for ep in eps:
        try:
            register = ep.load()
        except ImportError as exc:  # a broken or partial install: say so, keep the others usable
            print(f"polygeo: warning: command {ep.name!r} unavailable ({exc})", file=sys.stderr)
            continue
        register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line; return the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except (ValueError, TypeError, FileNotFoundError) as exc:
        print(f"polygeo {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
