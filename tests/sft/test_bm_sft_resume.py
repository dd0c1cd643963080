"""bm_sft --resume keeps exactly the finished runs whose frames, label, kind and settings match."""

from __future__ import annotations

import json


def test_resume_keeps_matching_runs_only(script):
    bm = script("benchmarks/bm_sft.py")
    jobs = [
        ("polysft base", "polysft", {"order": 2, "window": 3}, "bend"),
        ("polysft base", "polysft", {"order": 2, "window": 3}, "fold"),
        ("vertex base", "vertex", {"lr": 0.01}, "bend"),
    ]
    done = json.loads(json.dumps({"frames": 8, "results": [
        {"config": "polysft base", "kind": "bend", "settings": {"order": 2, "window": 3},
         "e_3d": 1.0},
        {"config": "vertex base", "kind": "bend", "settings": {"lr": 0.02}, "e_3d": 2.0},
    ]}))
    kept, left = bm.resume_jobs(done, jobs, 8)
    assert [r["e_3d"] for r in kept] == [1.0]
    # the other kind and the changed settings run again
    assert left == jobs[1:]
    # another number of frames: nothing is reused
    kept, left = bm.resume_jobs(done, jobs, 6)
    assert kept == [] and left == jobs
