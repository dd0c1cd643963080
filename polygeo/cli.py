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

__all__ = ["main", "build_parser", "int_or_auto"]


def int_or_auto(
    value: str | int, name: str, *, low: int | None = None, high: int | None = None
) -> int | str:
    """Parse a command-line value that is an integer or the word ``"auto"``.

    The one parser of such options for every sub-command (``polygeo jets --k``, ``polygeo
    polyfit --order``, ``polygeo sft --order/--patches``). It is called on the parsed string
    (not as an argparse ``type``) so that a bad value raises ``ValueError``, which
    :func:`main` reports as ``polygeo COMMAND: error: ...`` with exit status 2, like every
    other invalid option value.

    Parameters
    ----------
    value : str or int
        The option's value (surrounding spaces ignored); an ``int`` is checked as is.
    name : str
        The option's name without dashes (``"order"``, ``"max_tilt"``), for the message
        (underscores are shown as dashes: ``--max-tilt``).
    low, high : int, optional
        Inclusive bounds of the integer (None: unbounded).

    Returns
    -------
    int or str
        The integer, or ``"auto"``.

    Raises
    ------
    ValueError
        If ``value`` is neither ``"auto"`` nor an integer within ``[low, high]``.

    Examples
    --------
    >>> int_or_auto("12", "k"), int_or_auto("auto", "k")
    (12, 'auto')
    """
    flag = "--" + name.replace("_", "-")
    lo = "-inf" if low is None else low
    hi = "inf" if high is None else high
    want = "an integer" if low is None and high is None else f"an integer in [{lo}, {hi}]"
    if isinstance(value, str) and value.strip() == "auto":
        return "auto"
    if isinstance(value, bool):
        number = None
    elif isinstance(value, int):
        number = value
    else:
        try:
            number = int(str(value).strip())
        except ValueError:
            number = None
    if number is None or (low is not None and number < low) or (high is not None and number > high):
        raise ValueError(f"{flag}: expected {want} or 'auto', got {value!r}")
    return number


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
