"""polygeo.lazy: a package's names import on first use, exactly the eager names."""

from __future__ import annotations

import importlib
import subprocess
import sys
import textwrap

import pytest

from polygeo.lazy import attach, type_checking_exports


def _package(tmp_path, init: str, subs: dict[str, str]) -> str:
    name = f"lazypkg_{abs(hash(str(tmp_path))) % 10**8}"
    d = tmp_path / name
    d.mkdir()
    (d / "__init__.py").write_text(textwrap.dedent(init))
    for k, v in subs.items():
        (d / f"{k}.py").write_text(textwrap.dedent(v))
    sys.path.insert(0, str(tmp_path))
    return name


INIT = """
    from typing import TYPE_CHECKING

    from polygeo.lazy import attach

    if TYPE_CHECKING:
        from .heavy import answer, Thing as Alias
        from .other import other

    __getattr__, __dir__ = attach(__name__, __file__)
"""


def test_names_import_on_first_use(tmp_path):
    name = _package(tmp_path, INIT, {
        "heavy": "LOADED = True\nanswer = 42\nclass Thing:\n    pass\n",
        "other": "def other():\n    return 'o'\n",
        "plain": "x = 1\n",
    })
    try:
        pkg = importlib.import_module(name)
        assert f"{name}.heavy" not in sys.modules
        assert pkg.answer == 42
        assert f"{name}.heavy" in sys.modules and f"{name}.other" not in sys.modules
        assert pkg.Alias.__name__ == "Thing"
        assert pkg.other() == "o"
        assert pkg.plain.x == 1  # a sub-module is an attribute too
        assert {"answer", "Alias", "other"} <= set(dir(pkg))
        with pytest.raises(AttributeError, match="nothing"):
            pkg.nothing  # noqa: B018
    finally:
        sys.path.remove(str(tmp_path))


def test_exports_are_read_from_the_type_checking_block(tmp_path):
    f = tmp_path / "__init__.py"
    f.write_text(textwrap.dedent(INIT))
    assert type_checking_exports(f) == {
        "answer": ("heavy", "answer"), "Alias": ("heavy", "Thing"), "other": ("other", "other")}
    f.write_text("from .heavy import answer\n")  # eager import: nothing to attach
    with pytest.raises(ValueError, match="TYPE_CHECKING"):
        attach("x", f)
    f.write_text("import typing\nif typing.TYPE_CHECKING:\n    from .a import n\n"
                 "    from .b import n\n")
    with pytest.raises(ValueError, match="both"):
        type_checking_exports(f)


@pytest.mark.parametrize("package", ["polygeo.render", "draping.gaps"])
def test_lazy_packages_export_their_all(package):
    # every name of __all__ resolves, and the package imports none of its heavy modules
    code = (f"import sys, {package} as p\n"
            "light = 'torch' not in sys.modules\n"
            "missing = [n for n in p.__all__ if getattr(p, n, None) is None]\n"
            "print('LIGHT', light, 'MISSING', missing)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert "LIGHT True MISSING []" in out, out
