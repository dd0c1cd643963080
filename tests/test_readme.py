"""Every Python snippet of README.md runs as written (in a temporary working folder)."""

import os
import re
import tempfile
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def _snippets():
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert len(blocks) >= 4
    return blocks


@pytest.mark.parametrize(
    "index",
    [pytest.param(i, marks=pytest.mark.slow) if "run_sft" in b else i
     for i, b in enumerate(_snippets())],
)
def test_readme_snippet_runs(index, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code = _snippets()[index]
    exec(compile(code, f"README.md python block {index}", "exec"), {"__name__": "__readme__"})


def test_readme_points_inside_the_repository():
    text = README.read_text()
    assert "shared folder" not in text
    for target in re.findall(r"\]\(([^)#]+)\)", text):
        if not target.startswith("http"):
            assert (README.parent / target).exists(), target
    assert os.path.isfile(README.parent / "docs" / "ARCHITECTURE.md")


def test_docs_point_inside_the_repository():
    """README and docs/: relative links resolve inside the repository, and no absolute path of
    the machine the tests run on (the checkout's parent folder, the temporary folder) appears."""
    root = README.parent.resolve()
    machine = [Path(p) for p in (root.parent, tempfile.gettempdir()) if len(Path(p).parts) > 1]
    for doc in [README, *sorted((root / "docs").rglob("*.md"))]:
        text = doc.read_text()
        for folder in machine:
            assert str(folder) + os.sep not in text, (doc.name, str(folder))
        for target in re.findall(r"\]\(([^)#]+)", text):
            if not target.startswith("http"):
                path = (doc.parent / target).resolve()
                assert path.exists() and (path == root or root in path.parents), (doc.name, target)
