"""``bm_gaps_wide``: its shared-query scores equal the metrics called directly; bad input."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

# Seeds whose shipped drapes touch the body within 15 frames (dress from frame 6 on 720, 13 on
# 642; T-shirt from frame 12 on 642), so the contact counts compared are not all zero.
SEEDS, FRAMES = "642,720", 15


@pytest.fixture(scope="module")
def wide(script):
    return script("benchmarks/bm_gaps_wide.py")


@pytest.fixture(scope="module")
def record(wide, tmp_path_factory):
    out = tmp_path_factory.mktemp("wide") / "w.json"
    wide.run(["--seeds", SEEDS, "--skip", "", "--frames", str(FRAMES), "--out", str(out),
              "--quiet", "tshirt", "dress"])
    return out


def test_scores_equal_frame_metrics_and_contacts(wide, record):
    """Per case and model: the JSON's eps and inside counts are those of ``frame_metrics`` and
    ``contacts`` on ``drape_case`` (each model re-posed, its own garment fit and queries)."""
    from draping.body import AnnyBody
    from draping.gaps import drape_case, face_parts, frame_metrics, load_model, random_cases

    gc = sys.modules["gaps_contacts"]
    res = json.loads(record.read_text())
    body = AnnyBody.load()
    parts = face_parts(body)
    cases = random_cases([642, 720], FRAMES)
    assert res["seeds"] == [642, 720]
    total = 0
    for g in ("tshirt", "dress"):
        m = load_model(g)
        rows = res["garments"][g]["models"]["gaps"]["cases"]
        for c, row in zip(cases, rows):
            d = drape_case(m, body, c)
            fm = frame_metrics(d, body)
            ct = gc.contacts(d, body, parts, 0.01)
            for k in ("eps_e", "eps_a", "eps_c"):
                assert row[k] == pytest.approx(float(np.mean(fm[k])), rel=1e-12, abs=1e-15)
            assert row["inside"] == ct["inside_vertex_frames"]
            assert row["pinched"] == ct["pinched"]
            assert row["parts"] == {p: v["inside"] for p, v in ct["parts"].items()}
            total += row["inside"]
        mean = res["garments"][g]["models"]["gaps"]["mean"]
        assert mean["eps_e"] == pytest.approx(np.mean([r["eps_e"] for r in rows]))
    assert total > 0


def test_merge_keeps_scored_models_and_compares(wide, record, tmp_path):
    """``--merge`` adds a model beside the scored ones; the paired counts add up."""
    out = tmp_path / "m.json"
    out.write_text(record.read_text())
    res = wide.run(["--seeds", SEEDS, "--skip", "", "--frames", str(FRAMES), "--out",
                    str(out), "--quiet", "--merge", "other=dress:dress"])
    before = json.loads(record.read_text())
    assert res["garments"]["tshirt"] == before["garments"]["tshirt"]
    dress = res["garments"]["dress"]
    assert dress["models"]["gaps"] == before["garments"]["dress"]["models"]["gaps"]
    c = dress["comparisons"]["other"]
    # the same model scored twice: every case ties, and neither is "better"
    assert (c["fewer_contacts"], c["more_contacts"], c["equal_contacts"]) == (0, 0, 2)
    assert c["lower_eps_e"] == 0 and c["better"] is False
    assert len(res["runs"]) == 2 and out.with_suffix(".png").is_file()


def test_add_combines_records_without_scoring(wide, record, tmp_path):
    """``--add`` takes another process's record as it is; other seeds or frames: an error."""
    out = tmp_path / "a.json"
    res = wide.run(["--seeds", SEEDS, "--skip", "", "--frames", str(FRAMES), "--out",
                    str(out), "--quiet", "--add", str(record)])
    before = json.loads(record.read_text())
    assert res["garments"] == before["garments"] and res["runs"] == before["runs"]
    # records that share runs (one --merge'd from the other): each run is kept once
    twice = wide.run(["--seeds", SEEDS, "--skip", "", "--frames", str(FRAMES), "--out",
                      str(out), "--quiet", "--add", str(record), str(record)])
    assert twice["runs"] == before["runs"]
    with pytest.raises(ValueError, match="other seeds or frames"):
        wide.run(["--seeds", SEEDS, "--skip", "", "--frames", "5", "--out",
                  str(tmp_path / "b.json"), "--quiet", "--add", str(record)])


def test_compare_rule(wide):
    """Better only if both mean eps_c and mean eps_e are lower."""
    def rec(e, c, ins):
        cases = [{"seed": i, "eps_e": e[i], "eps_c": c[i], "inside": ins[i]} for i in range(2)]
        return {"cases": cases, "mean": {"eps_e": float(np.mean(e)), "eps_c": float(np.mean(c))}}

    a = rec([3.0, 3.0], [0.01, 0.0], [5, 0])
    assert wide.compare(a, rec([4.0, 4.0], [0.02, 0.0], [9, 0]))["better"] is True
    r = wide.compare(a, rec([4.0, 2.0], [0.0, 0.0], [0, 0]))
    assert r["better"] is False and r["more_contacts"] == 1 and r["lower_eps_e"] == 1
    with pytest.raises(ValueError, match="different seeds"):
        wide.compare(a, {**a, "cases": a["cases"][::-1]})


def test_bad_input(wide, tmp_path):
    with pytest.raises(ValueError, match="unknown garment 'hat'"):
        wide.parse_spec("gaps=hat:model.pt")
    with pytest.raises(ValueError, match="LABEL=GARMENT:MODEL"):
        wide.parse_spec("gaps=dress")
    with pytest.raises(FileNotFoundError, match="no GAPS model"):
        wide.load_specs([wide.Spec("x", "dress", str(tmp_path / "missing.pt"))])
    with pytest.raises(ValueError, match="trained for 'dress', not 'tshirt'"):
        wide.load_specs([wide.Spec("x", "tshirt", "dress")])
    with pytest.raises(ValueError, match="repeated"):
        wide.load_specs([wide.Spec("x", "dress", "dress")] * 2)
    with pytest.raises(ValueError, match="seeds"):
        wide.run(["--seeds", "506", "--skip", "506", "--out", str(tmp_path / "e.json")])
    with pytest.raises(ValueError, match="seeds"):
        wide.run(["--seeds", "1200", "--out", str(tmp_path / "e.json")])
