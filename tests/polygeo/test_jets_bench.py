"""bm_jets' record keeping: a partial run keeps the earlier sections with their own provenance."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module")
def bm(script):
    return script("benchmarks/bm_jets.py")


def test_partial_run_keeps_old_sections_with_their_own_provenance(bm):
    mine = {"date_utc": "NEW", "command": "python benchmarks/bm_jets.py --sections parsimony"}
    old_acc = {"date_utc": "OLD", "command": "python benchmarks/bm_jets.py --sections accuracy"}
    record = {"parsimony": {"runs": [2]}, "section_runs": {"parsimony": mine}}
    old = {"parsimony": {"runs": [1]}, "accuracy": [{"a": 1}], "auto_vs_best": {"x": 1},
           "speed_reference": {"s": 1}, "section_runs": {"accuracy": old_acc}}
    out = bm.merge_sections(record, old)
    assert out is record
    assert record["parsimony"] == {"runs": [2]}  # this run's section is not replaced
    assert record["section_runs"]["parsimony"] == mine
    assert record["accuracy"] == [{"a": 1}] and record["auto_vs_best"] == {"x": 1}
    assert record["section_runs"]["accuracy"] == old_acc
    # written before provenance was kept: marked, not given this run's date
    assert record["speed_reference"] == {"s": 1}
    assert record["section_runs"]["speed"] == {"date_utc": "unrecorded"}
    assert "robustness" not in record["section_runs"] and "scans" not in record["section_runs"]
