"""Committed records (benchmark results, shipped weights' JSON) name no machine's paths."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RECORDS = sorted(
    [*(ROOT / "benchmarks" / "results").glob("*.json"), *(ROOT / "polygeo" / "data").glob("*.json"),
     *(ROOT / "draping" / "data").glob("*.json")]
)
# absolute paths of a user's or a build machine's file system (a record names repository files
# relative to its root, cached files under ~ and other files as .../<folder>/<name>:
# polygeo.runs.record_path)
MACHINE = re.compile(r'(?<![\w.~/-])(/(?:home|root|work|tmp|Users|mnt|private|var/folders)/'
                     r'[^\s,"()]*)')


@pytest.mark.parametrize("path", RECORDS, ids=lambda p: str(p.relative_to(ROOT)))
def test_record_names_no_machine_path(path):
    hits = MACHINE.findall(path.read_text(encoding="utf-8"))
    assert not hits, f"{path.name}: machine paths {hits[:3]}"
