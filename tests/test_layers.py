"""The layer rules of DESIGN.md section 2, checked on the sources.

* import-linter runs the contracts of ``[tool.importlinter]`` in pyproject.toml: polygeo is
  the core below sft and draping, and sft and draping never import each other.
* An AST scan checks what import-linter cannot express: no file in sft/, draping/ or
  benchmarks/ uses a private polygeo name (a ``polygeo._x`` module or a ``_x`` function,
  constant or class of a polygeo module), and inside polygeo no module uses another module's
  private names (package-private modules such as ``polygeo._jets_numba`` may be imported
  inside polygeo; their public names are the package's internal API).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CORE = "polygeo"

#: Known uses being removed by the restructuring of issue 15 (file, private name): the
#: estimate stages, which benchmarks/bm_jets.py times one by one. Delete an entry when its
#: use is gone; nothing may be added here.
PENDING: set[tuple[str, str]] = set()


def _private(segment: str) -> bool:
    return segment.startswith("_") and not segment.startswith("__")


def _module_name(path: Path, root: Path) -> tuple[str, bool]:
    """Dotted module name of ``path`` under ``root`` and whether it is a package."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    is_pkg = parts[-1] == "__init__"
    if is_pkg:
        parts = parts[:-1]
    return ".".join(parts), is_pkg


def _absolute(node: ast.ImportFrom, current: str, is_pkg: bool) -> str:
    if node.level == 0:
        return node.module or ""
    base = current.split(".")
    if not is_pkg:
        base = base[:-1]
    if node.level > 1:
        base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _is_module(dotted: str, root: Path) -> bool:
    p = root.joinpath(*dotted.split("."))
    return p.with_suffix(".py").is_file() or (p / "__init__.py").is_file()


def _dotted(node: ast.expr) -> list[str] | None:
    """``a.b.c`` as ``["a", "b", "c"]``; None for anything but names and attributes."""
    out = []
    while isinstance(node, ast.Attribute):
        out.append(node.attr)
        node = node.value
    if not isinstance(node, ast.Name):
        return None
    out.append(node.id)
    return out[::-1]


def _uses(path: Path, root: Path) -> list[tuple[int, str]]:
    """Every polygeo name ``path`` imports or reaches by attribute: ``(line, dotted name)``."""
    current, is_pkg = _module_name(path, root)
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    bound: dict[str, str] = {}  # local name -> dotted polygeo name
    uses: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == CORE:
                    uses.append((node.lineno, a.name))
                    if a.asname:
                        bound[a.asname] = a.name
                    else:
                        bound[CORE] = CORE
        elif isinstance(node, ast.ImportFrom):
            src = _absolute(node, current, is_pkg)
            if src.split(".")[0] != CORE:
                continue
            for a in node.names:
                full = f"{src}.{a.name}"
                uses.append((node.lineno, full))
                bound[a.asname or a.name] = full
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Load):
            chain = _dotted(node)
            if chain and chain[0] in bound:
                uses.append((node.lineno, ".".join([bound[chain[0]], *chain[1:]])))
    return uses


def private_uses(path: Path, root: Path = ROOT, pending: frozenset = frozenset()) -> list[str]:
    """Private polygeo names used by ``path``, as ``"file:line name"`` strings.

    Outside polygeo every private segment counts. Inside polygeo a private segment counts
    unless it names a module (package-private modules are polygeo's internal API) or the
    name belongs to the file's own module. ``(file, name)`` pairs in ``pending`` are skipped.
    """
    current, _ = _module_name(path, root)
    inside = current.split(".")[0] == CORE
    bad = []
    for line, name in _uses(path, root):
        segs = name.split(".")
        for i, seg in enumerate(segs):
            if not _private(seg):
                continue
            prefix = ".".join(segs[: i + 1])
            if inside and (_is_module(prefix, root) or ".".join(segs[:i]) == current):
                continue
            if (path.relative_to(root).as_posix(), name) in pending:
                break
            bad.append(f"{path.relative_to(root)}:{line} {name}")
            break
    return sorted(set(bad))


def _files(*folders: str) -> list[Path]:
    return sorted(p for f in folders for p in (ROOT / f).rglob("*.py") if ".venv" not in p.parts)


def test_import_linter_contracts(tmp_path, monkeypatch):
    importlinter_cli = pytest.importorskip("importlinter.cli")
    monkeypatch.chdir(tmp_path)  # anything the tool writes lands in tmp_path
    rc = importlinter_cli.lint_imports(
        config_filename=str(ROOT / "pyproject.toml"), no_cache=True, no_logo=True
    )
    assert rc == 0, "an import-linter contract of pyproject.toml is broken (see the output)"


def test_higher_layers_use_only_public_polygeo_names():
    files = _files("sft", "draping", "benchmarks")
    bad = [b for p in files for b in private_uses(p, ROOT, PENDING)]
    assert not bad, "private polygeo names used outside polygeo:\n" + "\n".join(bad)


def test_polygeo_modules_use_only_each_others_public_names():
    bad = [b for p in _files(CORE) for b in private_uses(p, ROOT, PENDING)]
    assert not bad, "private names of another polygeo module:\n" + "\n".join(bad)


@pytest.mark.parametrize(
    "where, source",
    [
        ("sft/bad.py", "from polygeo._jets_numba import fit_item\n"),
        ("sft/bad.py", "from polygeo.synthetic import _grid_faces\n"),
        ("sft/bad.py", "import polygeo.render._shared\n"),
        ("sft/bad.py", "import polygeo.synthetic as syn\nsyn._family_params(0, 1, (), 1)\n"),
        ("draping/bad.py", "from polygeo import _numba_cache\n"),
        ("benchmarks/bad.py", "import polygeo\npolygeo.stn._canonicalize(1, 2, 3)\n"),
        ("polygeo/bad.py", "from .jets import _valid_mask\n"),
        ("polygeo/render/bad.py", "from . import soft\nsoft._np64(None, ())\n"),
    ],
)
def test_scan_flags_private_uses(tmp_path, where, source):
    # a scan that finds nothing must be able to find something
    for pkg in ("polygeo", "polygeo/render", "sft", "draping"):
        (tmp_path / pkg).mkdir(parents=True, exist_ok=True)
        (tmp_path / pkg / "__init__.py").write_text("")
    (tmp_path / "polygeo" / "_jets_numba.py").write_text("")
    (tmp_path / "benchmarks").mkdir(exist_ok=True)
    path = tmp_path / where
    path.write_text(source)
    assert private_uses(path, tmp_path), source


@pytest.mark.parametrize(
    "where, source",
    [
        ("polygeo/jets.py", "from ._jets_numba import fit_item\n"),  # package-private module
        ("polygeo/jets.py", "def _f():\n    pass\n\n_f()\n"),  # own private name
        ("sft/ok.py", "from polygeo.checks import as_tensor\nimport torch\ntorch._C\n"),
        ("sft/ok.py", "from polygeo import jets\njets.__name__\n"),
    ],
)
def test_scan_allows_public_uses(tmp_path, where, source):
    for pkg in ("polygeo", "sft"):
        (tmp_path / pkg).mkdir(exist_ok=True)
        (tmp_path / pkg / "__init__.py").write_text("")
    (tmp_path / "polygeo" / "_jets_numba.py").write_text("")
    path = tmp_path / where
    path.write_text(source)
    assert not private_uses(path, tmp_path), source
