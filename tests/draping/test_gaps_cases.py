"""draping.gaps.random_cases and gaps_contacts' random-seed screen (session 15): each seed's
random motion on the shape drawn with that seed, seeds neither trained on nor held out."""

from __future__ import annotations

import json

import numpy as np
import pytest

from draping.gaps import held_out_cases, random_cases, random_shapes


def test_random_cases_are_each_seeds_motion_on_its_own_shape():
    cases = random_cases([642, 509, 811], frames=7)
    assert [c.seed for c in cases] == [642, 509, 811]
    for c in cases:
        assert (c.motion, c.speed, c.frames) == ("random", 1.0, 7)
        np.testing.assert_array_equal(np.asarray(c.shape), random_shapes(1, c.seed)[0])
    assert cases[0].shape != cases[1].shape
    held = {(c.motion, c.seed) for c in held_out_cases(7)}
    assert not held & {(c.motion, c.seed) for c in random_cases(range(500, 1000), 3)}


def test_random_cases_bad_input():
    for bad in ([499], [1000], [509, 509], []):
        with pytest.raises(ValueError, match="seeds"):
            random_cases(bad)
    with pytest.raises(TypeError, match="seeds"):
        random_cases([509.0])
    with pytest.raises(ValueError, match="frames"):
        random_cases([509], frames=2)


def test_parse_seeds(script):
    gc = script("benchmarks/gaps_contacts.py")
    assert gc.parse_seeds("506-510") == [506, 507, 508, 509, 510]
    assert gc.parse_seeds("509, 642,811") == [509, 642, 811]
    assert gc.parse_seeds("538-542", "540") == [538, 539, 541, 542]
    for bad in ("510-506", "5x", "506-"):
        with pytest.raises(ValueError, match="seeds"):
            gc.parse_seeds(bad)


def test_screen_writes_its_seeds(tmp_path, script):
    gc = script("benchmarks/gaps_contacts.py")
    assert gc.main(["--models", "dress", "--cases", "random", "--seeds", "508-510",
                    "--skip", "509", "--frames", "3", "--out", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "gaps_contacts_dress_random.json").read_text())
    assert res["seeds"] == [508, 510]
    rows = res["models"]["dress"]["cases"]
    assert [r["case"] for r in rows] == ["random:508:1", "random:510:1"]
    assert all(len(r["per_frame"]) == 3 for r in rows)


def test_validation_random_cases_are_disjoint_from_every_other_set():
    from draping.gaps import VALIDATION_RANDOM_SEEDS, TrainSettings, validation_random_cases

    cases = validation_random_cases(frames=5)
    assert [c.seed for c in cases] == list(range(906, 966)) == list(VALIDATION_RANDOM_SEEDS)
    assert cases == random_cases(range(906, 966), frames=5)
    seeds = set(VALIDATION_RANDOM_SEEDS)
    assert not seeds & set(range(500, 906))  # validation_cases, wide set, session-15 screen
    assert not seeds & set(range(TrainSettings().random_motions))
    assert not seeds & {c.seed for c in held_out_cases(5) if c.motion == "random"}
    with pytest.raises(ValueError, match="frames"):
        validation_random_cases(frames=2)
