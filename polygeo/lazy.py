"""Lazy package exports (PEP 562): importing a package costs nothing until a name is used.

A package whose public names live in heavy sub-modules (torch, numba kernels) lists them once,
as ordinary relative imports inside an ``if TYPE_CHECKING:`` block of its ``__init__.py`` (so
that type checkers and IDEs see them), and hands that file to :func:`attach`::

    from typing import TYPE_CHECKING

    from polygeo.lazy import attach

    if TYPE_CHECKING:
        from .soft import render, render_silhouette
        from .settings import RasterSettings

    __getattr__, __dir__ = attach(__name__, __file__)

``package.render`` then imports ``package.soft`` on first access and keeps the value in the
package's namespace. Sub-modules (``package.soft``) are importable as attributes as well. This
is what keeps ``polygeo <command> --help`` free of torch: a command-line plug-in living inside
such a package can be imported without importing the package's heavy modules.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["attach", "type_checking_exports"]


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def type_checking_exports(init_file: str | Path) -> dict[str, tuple[str, str]]:
    """Names imported relatively inside the ``if TYPE_CHECKING:`` blocks of a file.

    Parameters
    ----------
    init_file : str or Path
        A package's ``__init__.py``.

    Returns
    -------
    dict
        ``{exported name: (sub-module name, name in it)}``, e.g. ``{"render": ("soft",
        "render")}`` for ``from .soft import render``, ``{"R": ("soft", "render")}`` for
        ``from .soft import render as R``.

    Raises
    ------
    ValueError
        If the file has no such block or the block imports nothing relatively (a lazy package
        with no names is a mistake), or if one name is imported from two sub-modules.
    """
    tree = ast.parse(Path(init_file).read_text(encoding="utf-8"))
    out: dict[str, tuple[str, str]] = {}
    for node in tree.body:
        if not (isinstance(node, ast.If) and _is_type_checking(node.test)):
            continue
        for imp in node.body:
            if isinstance(imp, ast.ImportFrom) and imp.level == 1 and imp.module:
                for alias in imp.names:
                    name = alias.asname or alias.name
                    if name in out and out[name][0] != imp.module:
                        raise ValueError(
                            f"init_file {init_file}: {name!r} is imported from both "
                            f".{out[name][0]} and .{imp.module}"
                        )
                    out[name] = (imp.module, alias.name)
    if not out:
        raise ValueError(
            f"init_file {init_file}: expected relative imports ('from .module import name') "
            "inside an 'if TYPE_CHECKING:' block, found none"
        )
    return out


def attach(
    package: str, init_file: str | Path
) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """Module-level ``__getattr__`` and ``__dir__`` that import a package's names on first use.

    Parameters
    ----------
    package : str
        The package's ``__name__``.
    init_file : str or Path
        Its ``__file__``; the exported names are read from its ``if TYPE_CHECKING:`` block
        (:func:`type_checking_exports`).

    Returns
    -------
    (__getattr__, __dir__)
        Assign both at module level of the package.

    Raises
    ------
    ValueError
        As :func:`type_checking_exports`. The returned ``__getattr__`` raises ``AttributeError``
        for a name that is neither exported nor a sub-module.
    """
    exports = type_checking_exports(init_file)

    def __getattr__(name: str) -> Any:
        module = sys.modules[package]
        where = exports.get(name)
        if where is not None:
            value = getattr(importlib.import_module(f"{package}.{where[0]}"), where[1])
        elif not name.startswith("__") and importlib.util.find_spec(f"{package}.{name}"):
            value = importlib.import_module(f"{package}.{name}")
        else:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        setattr(module, name, value)
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(exports))

    return __getattr__, __dir__
