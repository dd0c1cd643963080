"""The GAPS benchmark's evaluation set is held back from training; its parsimony rule."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def ev(script):
    return script("datasets/make_gaps_eval.py")


@pytest.fixture(scope="module")
def bm(script):
    return script("benchmarks/bm_gaps.py")


def test_eval_cases_are_held_back_from_training(ev):
    from draping.gaps import TRAIN_MOTIONS, TrainSettings, held_out_cases, random_shapes

    ts = TrainSettings()
    cases = ev.eval_cases()
    assert len(cases) == 3 * 2 * 2
    pool = random_shapes(ts.shapes, ts.seed).numpy()
    trainer_held_out = {c.shape for c in held_out_cases(3)}
    for c in cases:
        if c.motion == "random":
            assert c.seed >= max(ts.random_motions, 1000)
        else:
            assert c.motion not in TRAIN_MOTIONS
        s = np.asarray(c.shape)
        assert np.all((s >= 0) & (s <= 1))
        assert np.abs(pool - s).max(1).min() > 1e-3  # not a training shape
        assert c.shape not in trainer_held_out
    assert len({c.shape for c in cases}) == 2
    # the record's "held_back" text (this paragraph of the module docstring) says so too
    text = ev.__doc__.split("\n\n")[2]
    sampled = text.split("samples")[1].split("at speeds")[0]
    assert all(m in sampled for m in TRAIN_MOTIONS if m != "random")
    assert "jacks" not in sampled and "never\n``jacks``" in text


@pytest.mark.parametrize("frames", [0, 61])
def test_eval_cases_reject_frame_counts(ev, frames):
    with pytest.raises(ValueError, match="frames"):
        ev.eval_cases(frames=frames)


def test_case_motion_is_a_prefix_of_one_motion(ev, tmp_path):
    import dataclasses

    c = ev.eval_cases(["tshirt"], frames=4, quick=True)[0]
    short = ev.case_motion(tmp_path, c)
    long = ev.case_motion(tmp_path, dataclasses.replace(c, frames=9))
    assert short.rotations.shape[0] == 4 and long.rotations.shape[0] == 9
    assert np.array_equal(short.rotations.numpy(), long.rotations[:4].numpy())
    assert np.array_equal(short.translation.numpy(), long.translation[:4].numpy())
    assert float(long.rotations.abs().max()) > 0  # the body moves


def test_parsimony_picks_the_smallest_network_within_ten_percent(bm):
    rows = [{"label": "big", "params": 1000, "e_dist_cm_mean": 1.00},
            {"label": "mid", "params": 500, "e_dist_cm_mean": 1.08},
            {"label": "small", "params": 100, "e_dist_cm_mean": 1.25}]
    pick, best = bm.parsimonious(rows)
    assert (pick["label"], best) == ("mid", 1.00)
    rows[2]["e_dist_cm_mean"] = 1.09
    assert bm.parsimonious(rows)[0]["label"] == "small"
    with pytest.raises(ValueError, match="rows"):
        bm.parsimonious([])


def test_reference_key_follows_the_template_content(ev, monkeypatch):
    import draping.garments as garments

    c = ev.eval_cases(["tshirt"], frames=4, quick=True)[0]
    key = ev._key(c)
    folder = ev.reference_dir(Path("/cache"), c)
    assert ev._key(c) == key
    real = garments.garment

    def moved(name, *a, **k):
        g = real(name, *a, **k)
        v = np.array(g.vertices, dtype=np.float64)
        v[0, 0] += 1e-6  # a regenerated template: one vertex moved by a micrometre
        return garments.Garment(g.name, v, g.faces, g.info)

    monkeypatch.setattr(garments, "garment", moved)
    assert ev._key(c) != key
    assert ev.reference_dir(Path("/cache"), c) != folder  # a stale drape is not re-used


def _moved_fit(monkeypatch):
    """Make the trainer's carry-over to a body shape move one vertex by a micrometre."""
    import draping.gaps.data as data
    import draping.garments as garments

    real = garments.fit_garment_to_shape

    def moved(*a, **k):
        g = real(*a, **k)
        v = np.array(g.vertices, dtype=np.float64)
        v[0, 0] += 1e-6
        return garments.Garment(g.name, v, g.faces, g.info)

    monkeypatch.setattr(data, "fit_garment_to_shape", moved)


def test_reference_key_follows_the_carried_rest_garment(ev, monkeypatch):
    c = ev.eval_cases(["skirt"], frames=4, quick=True)[0]
    key, folder = ev._key(c), ev.reference_dir(Path("/cache"), c)
    _moved_fit(monkeypatch)
    assert ev._key(c) != key
    assert ev.reference_dir(Path("/cache"), c) != folder  # drapes of the old fit not re-used


def test_model_key_follows_the_training_data(bm, ev, monkeypatch):
    st = bm.train_settings("skirt", width=32, depth=1)
    ev.data_digest.cache_clear()
    path = bm.model_path(st, 100, Path("/cache"))
    assert bm.model_path(st, 100, Path("/cache")) == path
    _moved_fit(monkeypatch)
    ev.data_digest.cache_clear()
    try:
        assert bm.model_path(st, 100, Path("/cache")) != path  # a changed fit retrains
    finally:
        ev.data_digest.cache_clear()
    other = bm.train_settings("skirt", width=64, depth=1)
    assert bm.model_path(other, 100, Path("/cache")) != path


def test_case_pairs_keep_only_the_named_cases(bm, ev):
    cases = ev.eval_cases(["tshirt", "dress"], frames=4)
    kept = bm.keep_pairs(cases, ["turn/2000", "random/2001"])
    assert sorted((c.garment, c.motion, c.shape_seed) for c in kept) == [
        ("dress", "random", 2001), ("dress", "turn", 2000),
        ("tshirt", "random", 2001), ("tshirt", "turn", 2000)]
    assert bm.keep_pairs(cases, None) == cases
    for bad in (["turn"], ["turn/x"], ["walk/2000"]):
        with pytest.raises(ValueError, match="cases"):
            bm.keep_pairs(cases, bad)


def test_recorded_paths_carry_no_machine_paths(bm):
    # a shipped model is recorded relative to the repository, a cached one under ~, and both
    # read back to the same files
    shipped = bm.ROOT / "draping" / "data" / "gaps_tshirt.pt"
    assert bm._portable(shipped) == "draping/data/gaps_tshirt.pt"
    assert bm._recorded(bm._portable(shipped)) == shipped
    cached = Path.home() / ".cache" / "polygeo" / "m.pt"
    assert bm._portable(cached) == "~/.cache/polygeo/m.pt"
    assert bm._recorded(bm._portable(cached)) == cached


def test_sweep_of_given_models_picks_per_garment_and_charts(bm, monkeypatch, tmp_path):
    import types

    import draping.gaps as gaps

    sizes = {"a": ("tshirt", 32, 1, 100, 1.05), "b": ("tshirt", 128, 2, 300, 1.00),
             "c": ("dress", 32, 1, 100, 1.30), "d": ("dress", 128, 2, 300, 1.00),
             "e": ("skirt", 32, 1, 100, 1.00)}

    def load(path):
        g, w, d, _, _ = sizes[path]
        return types.SimpleNamespace(settings=types.SimpleNamespace(garment=g, width=w, depth=d))

    def record(path, ev_, label):
        _, _, _, params, e = sizes[str(path)]
        return {"label": label, "params": params, "e_dist_cm_mean": e, "steps": 10,
                "eps_e_mean": 1.0, "eps_a_mean": 1.0, "eps_c_mean": 0.0, "eps_c_max": 0.0,
                "e_norm_deg_mean": 1.0, "ms_per_frame": 0.2, "ms_per_frame_with_posing": 1.0,
                "train_cpu_minutes": 1.0}

    monkeypatch.setattr(gaps, "load_model", load)
    monkeypatch.setattr(bm, "model_record", record)
    res = bm.sweep_given(list(sizes), None, ["tshirt", "dress"])
    assert set(res["garments"]) == {"tshirt", "dress"}  # the skirt was not asked for
    assert res["garments"]["tshirt"]["parsimonious"] == "32x1"  # 5 % off the best
    assert res["garments"]["dress"]["parsimonious"] == "128x2"  # 30 % off: not within 10 %
    assert abs(res["garments"]["dress"]["within"]["32x1"] - 0.30) < 1e-12
    bm.chart_sweep(res, tmp_path / "sweep.png")
    assert (tmp_path / "sweep.png").stat().st_size > 1000


def test_default_size_is_the_recorded_parsimony_pick(bm):
    """GapsSettings' default width x depth is what the sweep at the shipped budget picked
    (recomputed from the recorded E_dist of each size, on every swept garment)."""
    import json

    from draping.gaps import GapsSettings

    rec = json.loads((ROOT / "benchmarks" / "results" / "bm_gaps_sweep_shipped.json")
                     .read_text())["sweep"]
    default = f"{GapsSettings().width}x{GapsSettings().depth}"
    assert set(rec["garments"]) == {"tshirt", "dress"}
    for g, r in rec["garments"].items():
        assert len(r["models"]) >= 2, g
        pick, best = bm.parsimonious(r["models"])
        assert pick["label"] == r["parsimonious"] == default, g


def test_strip_skips_garments_without_a_case_in_the_run(bm, tmp_path):
    """``--sections given charts --garments dress`` on a record that also holds T-shirt rows:
    the strip picks a garment of this run's cases, and draws nothing when there is none
    (it used to index the T-shirt's empty case list)."""

    class NoCases:
        def garment_cases(self, g):
            return []

    res = {"tshirt": {"models": []}, "dress": {"models": []}}
    assert bm.strip(None, NoCases(), res, tmp_path, tmp_path / "s.png") is None
    assert not (tmp_path / "s.png").exists()


def test_contacts_body_parts_and_inside_counts(script):
    """``gaps_contacts``: bones map to their side's limb or the torso; on a garment with two
    vertices pushed into the body (one deep, one on the skin's inner side of a thigh) the
    counts, the part and the depth are those of the construction."""
    gc = script("benchmarks/gaps_contacts.py")
    assert gc.body_part("upperleg01.L") == "legL" and gc.body_part("pelvis.R") == "legR"
    assert gc.body_part("upperarm02.R") == "armR" and gc.body_part("clavicle.L") == "armL"
    assert gc.body_part("spine04") == "torso" and gc.body_part("head") == "torso"
    import torch

    from draping.body import AnnyBody
    from draping.collision import MeshQuery
    from draping.gaps.infer import Drape

    body = AnnyBody.load()
    parts = gc.face_parts(body)
    assert set(parts) == set(gc.PARTS)
    rest = body.rest()[0][0].double()
    q = MeshQuery(rest, body.faces)
    vi = int(np.nonzero(np.array(body.bone_names)[body.skin_indices[:, 0].numpy()]
                        == "upperleg01.L")[0][0])
    far = rest[vi] + torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64)  # well away
    n = q.query(rest[vi][None]).normal[0]
    x = torch.stack([rest[vi] - 0.004 * n, far, far + 0.01]).float()[None].repeat(2, 1, 1)
    x[1, 0] = far + 0.02  # outside in frame 1
    d = Drape(x, rest.float()[None].repeat(2, 1, 1), None, {})
    r = gc.contacts(d, body, parts, pinch=0.01)
    assert r["inside_vertex_frames"] == 1 and r["frames_with_contact"] == 1
    assert r["parts"]["legL"]["inside"] == 1
    assert abs(r["depth_mm_max"] - 4.0) < 0.5
    assert r["per_frame"] == [1, 0]


def test_contacts_pinch_counts_equal_a_fresh_query_per_frame(script):
    """``gaps_contacts.contacts`` builds each "body less one part" query once and refits it per
    frame; its pinch counts per part equal those of a query built afresh at every frame and
    part (the construction it replaces), on a body that moves between frames, with inside
    points on every part."""
    import torch

    from draping.body import AnnyBody
    from draping.collision import MeshQuery
    from draping.gaps.infer import Drape

    gc = script("benchmarks/gaps_contacts.py")
    body = AnnyBody.load()
    parts = gc.face_parts(body)
    faces = body.faces.numpy()
    rest = body.rest()[0][0].double()
    g = torch.Generator().manual_seed(0)
    bv = torch.stack([rest, rest * 1.02 + torch.tensor([0.05, -0.02, 0.03], dtype=torch.float64),
                      rest + 0.01 * torch.randn(rest.shape, generator=g, dtype=torch.float64)])
    xs = []
    for t in range(3):
        q = MeshQuery(bv[t], body.faces)
        idx = torch.randperm(rest.shape[0], generator=g)[:400]
        n = q.query(bv[t][idx]).normal
        xs.append(bv[t][idx] - 0.003 * n)  # 3 mm inside, mostly
    d = Drape(torch.stack(xs).float(), bv.float(), None, {})
    r = gc.contacts(d, body, parts, pinch=0.01)
    want = {p: 0 for p in gc.PARTS}
    inside = {p: 0 for p in gc.PARTS}
    x = d.x.double()
    for t in range(3):
        res = MeshQuery(bv[t], body.faces).query(x[t])
        dist, face = np.asarray(res.distance), np.asarray(res.face)
        ins = np.nonzero(dist < 0)[0]
        for p in gc.PARTS:
            sel = ins[parts[face[ins]] == p]
            if sel.size:
                other = MeshQuery(bv[t], torch.as_tensor(faces[parts != p]))
                do = np.abs(np.asarray(other.query(x[t][sel], max_distance=0.02).distance))
                want[p] += int((do < 0.01).sum())
                inside[p] += int(sel.size)
    assert {p: v["pinched"] for p, v in r["parts"].items()} == want
    assert {p: v["inside"] for p, v in r["parts"].items()} == inside
    assert sum(want.values()) > 0 and all(v > 0 for v in inside.values())


def test_span_optimum_rebuilds_the_model_output_and_lowers_the_loss(script):
    """``gaps_contacts.span_optimum``: the garment rebuilt from the network's own output-basis
    coefficients at a frame is the model's drape there (to float32 rounding); minimising the
    training loss over those coefficients does not raise it; the inside count before is the
    body query's; a model without an output basis is refused. ``loss_optimum`` (free
    vertices) counts the same inside vertices before and does not raise the loss either."""
    import dataclasses

    import torch

    from draping.body import AnnyBody
    from draping.collision import MeshQuery
    from draping.gaps import Case, drape_case, load_model

    gc = script("benchmarks/gaps_contacts.py")
    torch.set_num_threads(1)
    body = AnnyBody.load()
    model = load_model("tshirt")
    case = Case("walk", 0, 1.0, (0.3, 0.6, 0.4, 0.7, 0.5, 0.2), 5)
    d = drape_case(model, body, case)
    r = gc.span_optimum(model, d, body, case, 4, rounds=2)
    assert r["frame"] == 4 and r["reconstruction_mm"] < 0.01
    assert r["loss_span_J"] <= r["loss_model_J"] + 1e-6
    q = MeshQuery(d.body_vertices[4].double(), body.faces)
    assert r["inside_model"] == int((np.asarray(q.query(d.x[4].double()).distance) < 0).sum())
    assert all(p.requires_grad for p in model.parameters())  # restored
    o = gc.loss_optimum(model, d, body, 4, rounds=1)  # free vertices
    assert o["inside_model"] == r["inside_model"]
    assert o["loss_optimum_J"] <= o["loss_model_J"] + 1e-6
    model.settings = dataclasses.replace(model.settings, rank=0)
    with pytest.raises(ValueError, match="rank"):
        gc.span_optimum(model, d, body, case, 4)


def test_contacts_judge_a_model_by_its_own_training_loss(script):
    """``gaps_contacts.train_settings_of``: the loss re-solved at a frame uses the settings the
    model's record holds (the shipped dress: k_c = 1e5, not the default 1e4); a model without
    a record gets the defaults with its own model settings."""
    from draping.gaps import TrainSettings, load_model

    gc = script("benchmarks/gaps_contacts.py")
    dress = load_model("dress")
    rec = dress.record["training"]["settings"]
    ts = gc.train_settings_of(dress)
    assert ts.collision_stiffness == rec["collision_stiffness"] != \
        TrainSettings().collision_stiffness
    assert ts.model == dress.settings
    dress.record = {}
    assert gc.train_settings_of(dress) == TrainSettings(model=dress.settings)


def test_shipped_section_replaces_only_the_shipped_row(tmp_path, monkeypatch, script):
    """``--sections shipped``: merged into a record, the re-scored shipped row replaces the
    old one (keeping its label and budget mark) and every other row, the given ones
    included, stays; a re-score against other references, or a record without a shipped
    row, is refused."""
    import json

    rec = script("benchmarks/bm_gaps_record.py")
    ref = {"eps_e_mean": 1.5, "eps_a_mean": 2.0, "eps_c_mean": 0.0}
    old = {"methods": {"dress": {
        "models": [{"label": "gaps", "eps_c_mean": 0.01},
                   {"label": "ncs", "eps_c_mean": 0.0},
                   {"label": "gaps (shipped, own budget)", "eps_c_mean": 0.5,
                    "not_equal_budget": True}],
        "given": [{"label": "gaps (8000 steps, given)", "eps_c_mean": 0.2}],
        "reference": {**ref, "cpu_s_per_frame_median": 3.0}}}}
    path = tmp_path / "bm_gaps.json"
    path.write_text(json.dumps(old))
    monkeypatch.setattr("tempfile.gettempdir", lambda: str(tmp_path))
    new = {"row": {"label": "gaps (shipped)", "eps_c_mean": 0.25},
           "reference": {**ref, "cpu_s_per_frame_median": 9.0}}  # timings may differ
    res = rec.merge_results(path, {"shipped": {"dress": new}}, {"command": "x"})
    rows = res["methods"]["dress"]["models"]
    assert rows[:2] == old["methods"]["dress"]["models"][:2]
    assert rows[2] == {"label": "gaps (shipped, own budget)", "eps_c_mean": 0.25,
                       "not_equal_budget": True}
    assert res["methods"]["dress"]["given"] == old["methods"]["dress"]["given"]
    assert json.loads(path.read_text()) == res
    moved = {"row": new["row"], "reference": {**ref, "eps_e_mean": 1.6}}
    with pytest.raises(ValueError, match="reference eps_e_mean"):
        rec.replace_shipped_row(res, "dress", moved)
    with pytest.raises(ValueError, match="no shipped GAPS row"):
        rec.replace_shipped_row({"methods": {"skirt": {"models": []}}}, "skirt", new)
