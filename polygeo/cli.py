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

from ._compile_notice import COMPILE_NOTICE, compile_notice

__all__ = ["main", "build_parser", "int_or_auto", "compile_notice", "COMPILE_NOTICE"]


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


def _command_name(argv: list[str]) -> str | None:
    """The sub-command named in ``argv`` (its first word that is not an option), or None."""
    for word in argv:
        if word == "--":
            return None
        if not word.startswith("-"):
            return word
    return None


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """Build the top-level parser.

    Parameters
    ----------
    only : str, optional
        Load only this sub-command's plug-in (the others are listed by name, unloaded), so
        that ``polygeo jets --help`` or an argument error does not import every layer.
        None loads every registered plug-in.
    """
    parser = argparse.ArgumentParser(
        prog="polygeo",
        description=(
            "Deformable surfaces as local polynomial jets: jets, PolyFit, PolySfT, draping."
        ),
    )
    from . import __version__

    parser.add_argument("--version", action="version", version=f"polygeo {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    eps = sorted(entry_points(group="polygeo.commands"), key=lambda e: e.name)
    names = {ep.name for ep in eps}
    for ep in eps:
        if only is not None and only in names and ep.name != only:
            sub.add_parser(ep.name, help=f"(see polygeo {ep.name} --help)")
            continue
        try:
            register = ep.load()
        except ImportError as exc:  # a broken or partial install: say so, keep the others usable
            print(f"polygeo: warning: command {ep.name!r} unavailable ({exc})", file=sys.stderr)
            continue
        register(sub)
    return parser


def _top_level_help() -> None:
    """``polygeo`` / ``polygeo --help`` without importing any plug-in: names and modules."""
    eps = sorted(entry_points(group="polygeo.commands"), key=lambda e: e.name)
    lines = [
        "usage: polygeo [-h] [--version] COMMAND ...",
        "",
        "Deformable surfaces as local polynomial jets: jets, PolyFit, PolySfT, draping.",
        "",
        "commands (polygeo COMMAND --help for each one's options, defaults and units):",
    ]
    lines += [f"  {ep.name:<18} {_HELP.get(ep.name, 'plug-in ' + ep.value.split(':')[0])}"
              for ep in eps]
    lines += ["", "options:", "  -h, --help         show this help message and exit",
              "  --version          show program's version number and exit"]
    print("\n".join(lines))


#: One-line help of the known sub-commands, shown by ``polygeo --help`` without loading them.
_HELP = {
    "jets": "per-point normals and curvatures of a point cloud or mesh (n-jet fitting)",
    "polyfit": "partition a mesh or point cloud into patches and fit an oriented n-jet to each",
    "sft": "shape from template (PolySfT) on an image sequence",
    "demo": "run the main jobs on embedded defaults and print their accuracy",
    "bench": "run a benchmark (speed against accuracy; JSON + PNG)",
    "train-stn": "retrain the shipped STN weights",
    "drape-reference": "physics reference drape of a garment on a posed body (cloth solver)",
    "drape": "drape a garment with a trained model (GAPS, SNUG-like, NCS-like)",
    "train-drape": "train a self-supervised draping model for one garment",
    "simulate": "grid-cloth rollout with FNOpt or a classical optimiser",
    "train-fnopt": "retrain the FNOpt learned cloth optimiser",
}


def main(argv: list[str] | None = None) -> int:
    """Run the command line; return the exit status."""
    argv = sys.argv[1:] if argv is None else list(argv)
    command = _command_name(argv)
    if command is None and (not argv or argv[0] in ("-h", "--help")):
        _top_level_help()
        return 0 if argv else 2
    parser = build_parser(only=command)
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        parser.print_help()
        return 2
    if not getattr(args, "quiet", False):
        compile_notice()
    try:
        return int(args.func(args) or 0)
    except (ValueError, TypeError, FileNotFoundError) as exc:
        print(f"polygeo {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
