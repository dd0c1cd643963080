"""draping.gaps: losses equal the shared energies, a step lowers the loss, inference, bad input."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from draping import physics
from draping.body import AnnyBody
from draping.gaps import (
    GapsSettings,
    Trainer,
    TrainSettings,
    body_contacts,
    check_phenotypes,
    drape_motion,
    drape_sequence,
    load_model,
    loss_terms,
    motion_features,
    pose_features,
    save_model,
    top_weights,
)
from draping.gaps.infer import pose_bone_indices, up_vector
from draping.motion import Motion, generate
from polygeo.frames import axis_angle_to_matrix

SMALL = dict(width=16, depth=1, rank=8)


@pytest.fixture(scope="module")
def body():
    return AnnyBody.load()


@pytest.fixture(scope="module")
def trainer(body):
    torch.set_num_threads(1)
    s = TrainSettings(GapsSettings(garment="tshirt", **SMALL), batch=2, shapes=2,
                      motion_frames=12, speeds=(1.0,), random_motions=1, seed=3)
    return Trainer(s, body)


def test_loss_terms_equal_the_shared_energies(trainer):
    """Each term is the draping.physics energy of the posed garment (computed here apart)."""
    tr = trainer
    s = tr.settings
    i, wins = tr.batch(5)
    case = tr.case(i)
    k, st = wins[0]
    seq = tr.sequences[k]
    rot, trans = seq.rotations[st:st + 3], seq.translation[st:st + 3]
    posed = tr.body.pose(case.shape, rot, trans)
    x = tr.model.skin(case.rest.vertices.expand(3, -1, -1), posed.transforms)
    x = x + 1e-3 * torch.randn(x.shape, generator=torch.Generator().manual_seed(0))
    contacts = body_contacts(x, posed.vertices, tr.query, s.query_radius)
    terms = loss_terms(x[None], case, s.model, s, contacts, epoch=40, dt=tr.dt)
    rest = case.rest
    torch.testing.assert_close(terms["strain"][0], physics.stvk_energy(x, rest))
    torch.testing.assert_close(terms["bending"][0],
                               physics.gaps_bending_energy(x, rest, case.alpha))
    torch.testing.assert_close(terms["gravity"][0], physics.gravity_energy(x, rest))
    # collision: the plane distance to the closest body point, eq. (40)
    near = contacts.near
    d = torch.where(near, physics.plane_distance(x, contacts.anchor, contacts.normal),
                    torch.full(near.shape, 10.0 * s.query_radius))
    torch.testing.assert_close(terms["collision"][0], physics.collision_energy(
        d, s.collision_stiffness, s.collision_eps))
    # inertia on the third frame, with the velocity of the first two (eq. (42))
    iner = physics.inertia_energy(x[2], x[1], (x[1] - x[0]) / tr.dt, rest, tr.dt)
    torch.testing.assert_close(terms["inertia"][0, 2], iner)
    assert float(terms["inertia"][0, :2].abs().sum()) == 0.0
    kx = physics.k_ext_schedule(d, 40, s.collision_eps)
    torch.testing.assert_close(terms["inext"][0], physics.inextensibility_energy(
        x, rest, kx, s.inext_weight))



def test_k_ext_rings_setting_reaches_the_loss_and_keeps_old_keys(trainer):
    """``TrainSettings.k_ext_rings`` spreads eq. (45)'s allowance in L_inext (the shared
    schedule with the garment's 1-rings); 0 keeps the keys of runs from before it existed."""
    tr = trainer
    s = tr.settings.replace(k_ext_rings=2)
    assert "k_ext_rings" not in tr.settings.key_dict()
    assert s.key_dict()["k_ext_rings"] == 2
    assert TrainSettings.from_dict(dataclasses.asdict(s)) == s
    legacy = dataclasses.asdict(tr.settings)
    legacy.pop("k_ext_rings")
    assert TrainSettings.from_dict(legacy) == tr.settings
    with pytest.raises(ValueError, match="k_ext_rings"):
        tr.settings.replace(k_ext_rings=-1)
    case = tr.case(0)
    rest = case.rest
    posed = tr.body.pose(case.shape, torch.zeros(3, tr.body.num_bones, 3))
    x = tr.model.skin(rest.vertices.expand(3, -1, -1), posed.transforms)
    x = x + 1e-3 * torch.randn(x.shape, generator=torch.Generator().manual_seed(4))
    contacts = body_contacts(x, posed.vertices, tr.query, s.query_radius)
    push = torch.zeros(contacts.near.shape, dtype=torch.bool)
    push[:, torch.nonzero(contacts.near[0]).flatten()[::40]] = True  # a few vertices inside
    x = torch.where(push[..., None], contacts.anchor - 3e-3 * contacts.normal, x)
    contacts = body_contacts(x, posed.vertices, tr.query, s.query_radius)
    d = torch.where(contacts.near, physics.plane_distance(x, contacts.anchor, contacts.normal),
                    torch.full(contacts.near.shape, 10.0 * s.query_radius))
    assert bool((d < 0).any())  # some contact, so the rings matter
    spread = loss_terms(x[None], case, s.model, s, contacts, epoch=40, dt=tr.dt)["inext"][0]
    plain = loss_terms(x[None], case, s.model, tr.settings, contacts, epoch=40, dt=tr.dt)
    kx = physics.k_ext_schedule(d, 40, s.collision_eps, rest, 2)
    assert bool((kx > physics.k_ext_schedule(d, 40, s.collision_eps)).any())
    torch.testing.assert_close(spread, physics.inextensibility_energy(x, rest, kx,
                                                                      s.inext_weight))
    assert not torch.equal(spread, plain["inext"][0])


def test_hard_example_replay(body):
    """``replay``: fresh steps whose collision loss is in the top decile of the recent ones are
    kept and trained on again with probability ``replay``; the pool survives a checkpoint;
    ``replay = 0`` keeps the fresh batches and the run keys."""
    from draping.gaps.train import REPLAY_MIN

    base = TrainSettings(GapsSettings(garment="tshirt", **SMALL), batch=2, shapes=2,
                         motion_frames=12, speeds=(1.0,), random_motions=1, seed=5)
    assert "replay" not in base.key_dict()
    s = base.replace(replay=0.5)
    assert s.key_dict()["replay"] == 0.5
    for bad in (-0.1, 1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="replay"):
            base.replace(replay=bad)
    with pytest.raises(TypeError, match="replay"):
        base.replace(replay="x")
    tr = Trainer(s, body)
    assert all(tr.pick(k) == (*tr.batch(k), True) for k in range(20))  # nothing hard yet
    kept = [tr.note(k % 2, tr.batch(k)[1], float(k)) for k in range(REPLAY_MIN + 20)]
    assert not any(kept[:REPLAY_MIN - 1])  # too few known
    assert all(kept[REPLAY_MIN:])  # rising losses: each new one is the largest
    assert not tr.note(0, tr.batch(0)[1], 0.5)  # a low one is not kept
    assert not tr.note(0, tr.batch(0)[1], 0.0)
    hard = [(i, list(w)) for i, w in tr.hard]
    picks = [tr.pick(k) for k in range(400)]
    replayed = [(i, w) for i, w, fresh in picks if not fresh]
    assert 150 < len(replayed) < 250
    assert all((i, w) in hard for i, w in replayed)
    assert all(p == (*tr.batch(k), True) for k, p in enumerate(picks) if p[2])
    # checkpoint round trip
    tr2 = Trainer(s, body)
    tr2.load_state(tr.state(), 7)
    assert tr2.history == tr.history and [(i, list(w)) for i, w in tr2.hard] == hard
    # a training step notes its fresh collision loss
    tr3 = Trainer(s, body)
    rec = tr3.train_step()
    assert tr3.history == [pytest.approx(rec["collision"])]

def test_baseline_terms(trainer):
    """SNUG-like: flat-rest dihedral bending (eq. 17) and no L_inext; k_ext = 1 ablation."""
    tr = trainer
    s = tr.settings
    case = tr.case(0)
    x = case.rest.vertices[None, None].expand(1, 3, -1, -1).clone()
    x = x + 1e-3 * torch.randn(x.shape, generator=torch.Generator().manual_seed(1))
    posed = tr.body.pose(case.shape, torch.zeros(3, tr.body.num_bones, 3))
    contacts = body_contacts(x[0], posed.vertices, tr.query, s.query_radius)
    snug = GapsSettings(method="snug", **SMALL)
    t = loss_terms(x, case, snug, s, contacts, 0, tr.dt)
    torch.testing.assert_close(t["bending"][0], physics.bending_energy(x[0], case.rest))
    assert float(t["inext"].abs().sum()) == 0.0
    one = GapsSettings(inextensibility="one", **SMALL)
    t1 = loss_terms(x, case, one, s, contacts, 50, tr.dt)
    torch.testing.assert_close(t1["inext"][0], physics.inextensibility_energy(
        x[0], case.rest, 1.0, s.inext_weight))


def test_one_training_step_lowers_the_loss(body):
    """From a deformed start (random output basis: strained garments), one Adam step of the
    trainer lowers the loss of the same batch (same windows, shape and hidden state)."""
    torch.set_num_threads(1)
    s = TrainSettings(GapsSettings(garment="tshirt", **SMALL), batch=2, shapes=1,
                      motion_frames=12, speeds=(1.0,), random_motions=0, seed=1, lr=1e-4)
    tr = Trainer(s, body)
    torch.manual_seed(0)
    torch.nn.init.normal_(tr.model.basis.weight, std=0.05)
    before, _ = tr.losses(0)
    tr.train_step()
    after, _ = tr.losses(0)
    assert float(after.detach()) < float(before.detach()) - 1e-4 * abs(float(before.detach()))


def test_untrained_model_is_skinning_and_hidden_state_zero(body, trainer):
    """Zero basis: the garment is the skinned template; inference starts from h = 0."""
    model = trainer.model
    m = generate("walk", body, 5)
    x = drape_sequence(model, body, m)
    posed = body.pose(None, m.rotations, m.translation)
    w = torch.zeros(model.n_vertices, body.num_bones)
    w.scatter_(1, model.indices, model.weights)
    blend = torch.einsum("gj,tjab->tgab", w, posed.transforms[..., :3, :])
    ref = torch.einsum("tgab,gb->tga", blend[..., :3], model.template) + blend[..., 3]
    torch.testing.assert_close(x, ref, atol=1e-5, rtol=1e-5)
    # a trained-looking model: random basis; None hidden state equals an explicit zero state
    torch.manual_seed(0)
    torch.nn.init.normal_(model.basis.weight, std=0.1)
    try:
        feats = torch.randn(1, 4, model.gru.input_size)
        a, _ = model(feats)
        b, _ = model(feats, model.zero_state(1))
        c, _ = model(feats, torch.ones_like(model.zero_state(1)))
        torch.testing.assert_close(a, b)
        assert not torch.allclose(a, c)
    finally:
        torch.nn.init.zeros_(model.basis.weight)


def test_pose_features_ignore_heading(body):
    """Turning the whole motion about the vertical (root yaw) leaves the inputs unchanged."""
    m = generate("random", body, 6, seed=4)
    bones, up = pose_bone_indices(body), up_vector()
    shape = torch.full((6,), 0.5)
    f0 = pose_features(m.rotations, m.velocity, shape, bones, up)
    yaw = torch.tensor([0.0, 0.0, 1.1])
    r = m.rotations.clone()
    rz = axis_angle_to_matrix(yaw)
    root = rz @ axis_angle_to_matrix(r[:, 0])
    # back to axis-angle via the rotation's log (scipy-free: quaternion from matrix)
    from scipy.spatial.transform import Rotation

    r[:, 0] = torch.as_tensor(Rotation.from_matrix(root.double().numpy()).as_rotvec(),
                              dtype=r.dtype)
    f1 = pose_features(r, m.velocity @ rz.T, shape, bones, up)
    torch.testing.assert_close(f0, f1, atol=1e-5, rtol=1e-5)


def test_motion_features_feed_inference(body, trainer):
    """One helper builds the inputs (the body's POSE_BONES and the world up, bit for bit) and
    inference drapes with exactly them (training's states: the burn-in test below)."""
    m = generate("random", body, 5, seed=2)
    shape = torch.full((6,), 0.4)
    f = motion_features(body, m.rotations[None], m.velocity[None], shape[None])
    ref = pose_features(m.rotations[None], m.velocity[None], shape[None],
                        pose_bone_indices(body), up_vector())
    assert torch.equal(f, ref)
    with pytest.raises(ValueError, match="body"):
        motion_features(SimpleNamespace(bone_names=("root",)), m.rotations, m.velocity, shape)
    model = trainer.model
    torch.manual_seed(1)
    torch.nn.init.normal_(model.basis.weight, std=0.1)
    try:
        d = drape_motion(model, body, m, shape)
        with torch.no_grad():
            disp, _ = model(f)
            rest = torch.as_tensor(d.case.garment.vertices, dtype=torch.float32)
            posed = body.pose(d.case.shape, m.rotations, m.translation)
            x = model.skin(rest + disp[0], posed.transforms)
        assert torch.equal(d.x, x)
    finally:
        torch.nn.init.zeros_(model.basis.weight)


def test_top_weights_renormalised():
    w = torch.tensor([[0.5, 0.3, 0.2, 0.0], [0.1, 0.1, 0.1, 0.7]])
    wk, ik = top_weights(w, 2)
    torch.testing.assert_close(wk.sum(1), torch.ones(2))
    assert ik.tolist() == [[0, 1], [3, 0]] or ik[1, 0] == 3
    torch.testing.assert_close(wk[0], torch.tensor([0.625, 0.375]))


def test_save_load_roundtrip(tmp_path, body, trainer):
    model = trainer.model
    p = save_model(tmp_path / "m.pt", model, {"note": "x"})
    m2 = load_model(p)
    assert m2.record == {"note": "x"}
    assert m2.settings == model.settings
    mo = generate("arms", body, 3)
    torch.testing.assert_close(drape_sequence(m2, body, mo), drape_sequence(model, body, mo),
                               atol=1e-4, rtol=1e-4)


def test_bad_inputs(body, trainer, tmp_path):
    model = trainer.model
    m = generate("walk", body, 3)
    rot = m.rotations.clone()
    rot[1, 3, 0] = float("nan")
    with pytest.raises(ValueError, match="rotations"):
        drape_sequence(model, body, Motion(rot, m.translation))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        drape_sequence(model, body, m, shape=torch.tensor([0.5, 0.5, 1.2, 0.5, 0.5, 0.5]))
    with pytest.raises(ValueError, match="shape"):
        check_phenotypes(torch.zeros(5))
    with pytest.raises(ValueError, match="rotations"):
        drape_sequence(model, body, Motion(m.rotations[:, :10], m.translation))
    with pytest.raises(FileNotFoundError):
        load_model(tmp_path / "none.pt")
    with pytest.raises(ValueError, match="method"):
        GapsSettings(method="pbns")
    with pytest.raises(ValueError, match="window"):
        TrainSettings(window=2)


def test_model_refuses_another_garment(body, trainer):
    from draping.gaps import check_garment_for
    from draping.garments import garment

    with pytest.raises(ValueError, match="trained for garment"):
        check_garment_for(trainer.model, garment("dress"))


def test_garment_file_inside_the_body_is_refused(body, tmp_path):
    from draping.gaps import template_garment
    from draping.garments import garment
    from polygeo.io import write_ply

    g = garment("tank")
    c = g.vertices.mean(0)
    v = c + 0.7 * (g.vertices - c)  # shrunk into the torso
    p = tmp_path / "tight.ply"
    write_ply(p, v, g.faces)
    with pytest.raises(ValueError, match="inside"):
        template_garment(GapsSettings(garment_file=str(p)), body)


def test_rbf_beats_nearest_on_a_dress(body):
    """Untrained models (zero displacement: skinning alone) on a held-back shape and motion:
    RBF body participation has fewer body collisions and less stretch than nearest-vertex
    skinning on the dress."""
    from draping.gaps import Case, build_model, drape_case, frame_metrics

    case = Case("walk", 0, 1.15, (0.3, 0.6, 0.5, 0.6, 0.5, 0.5), 45)
    out = {}
    for method in ("gaps", "snug"):
        model, _ = build_model(GapsSettings(garment="dress", method=method), body)
        m = frame_metrics(drape_case(model, body, case), body)
        out[method] = {k: float(np.mean(m[k])) for k in ("eps_e", "eps_c")}
    assert out["gaps"]["eps_e"] < out["snug"]["eps_e"]
    assert out["gaps"]["eps_c"] < out["snug"]["eps_c"]


def test_held_out_cases_are_not_training_data():
    """Held-out shapes are not in a training pool; held-out motions are not trained on."""
    from draping.gaps import TRAIN_MOTIONS, check_case, held_out_cases, random_shapes, stress_cases

    pool = random_shapes(256, 0)
    for c in held_out_cases(10) + stress_cases(10) + [check_case()]:
        s = torch.tensor(c.shape)
        assert float((pool - s).abs().max(1).values.min()) > 1e-3 or c.shape == (0.5,) * 6
        assert c.motion != "random" or c.seed >= 1000
    assert "turn" not in TRAIN_MOTIONS and "jacks" not in TRAIN_MOTIONS


def test_validation_cases_are_neither_training_data_nor_held_out():
    """Validation: training-type motions with seeds a run does not train on (random 500-502),
    shapes outside the default training pool, and nothing shared with the held-out cases."""
    from draping.gaps import (
        TRAIN_MOTIONS,
        TrainSettings,
        held_out_cases,
        random_shapes,
        validation_cases,
    )

    val = validation_cases(12)
    assert len(val) == 6 and all(c.frames == 12 for c in val)
    pool = random_shapes(TrainSettings().shapes, TrainSettings().seed)
    held = held_out_cases(12)
    for c in val:
        assert c.motion in TRAIN_MOTIONS
        assert c.motion != "random" or TrainSettings().random_motions <= c.seed < 1000
        s = torch.tensor(c.shape)
        assert float((pool - s).abs().max(1).values.min()) > 1e-3
        assert all(float((torch.tensor(h.shape) - s).abs().max()) > 1e-3 for h in held)
    assert len({c.shape for c in val}) == len(val)
    with pytest.raises(ValueError, match="frames"):
        validation_cases(2)


def test_time_inference_reports_three_costs(body, trainer):
    from draping.gaps import time_inference

    t = time_inference(trainer.model, body, frames=4, repeats=1)
    assert set(t) == {"model", "with_skeleton", "with_body_mesh"}
    assert all(v > 0 for v in t.values())


def test_burn_in_gives_the_inference_state(trainer):
    """The state a training window starts from is the state inference reaches at that frame:
    the GRU read from a zero state at the motion's first frame (``burn_in`` covers it), or
    from the random state ``burn_in`` frames earlier; ``burn_in = 0`` keeps the random state."""
    tr = trainer
    m = tr.model
    k, seq = 0, tr.sequences[0]
    shape = tr.case(0).shape
    feats = motion_features(tr.body, seq.rotations[None], seq.velocity[None], shape[None])
    gen = torch.Generator().manual_seed(4)
    h0 = torch.randn(m.settings.depth, 3, m.settings.width, generator=gen)
    wins = [(k, 0), (k, 5), (k, 9)]
    with torch.no_grad():
        full = tr.context(wins, shape, h0)
        torch.testing.assert_close(full[:, 0], torch.zeros_like(full[:, 0]))
        for j, (_, st) in enumerate(wins[1:], start=1):
            _, h = m.gru(feats[:, :st], torch.zeros(m.settings.depth, 1, m.settings.width))
            torch.testing.assert_close(full[:, j:j + 1], h)
        # the window's displacements are the ones inference gives at those frames
        d_inf, _ = m(feats[:, :12])
        d_win, _ = m(feats[:, 9:12], full[:, 2:3])
        torch.testing.assert_close(d_win, d_inf[:, 9:12], atol=1e-6, rtol=1e-5)
        short = dataclasses.replace(tr.settings, burn_in=3)
        tr.settings, keep = short, tr.settings
        try:
            part = tr.context(wins, shape, h0)
            none = dataclasses.replace(short, burn_in=0)
            tr.settings = none
            torch.testing.assert_close(tr.context(wins, shape, h0), h0)
        finally:
            tr.settings = keep
        _, h = m.gru(feats[:, 6:9], h0[:, 2:3].contiguous())
        torch.testing.assert_close(part[:, 2:3], h)
        _, h = m.gru(feats[:, 2:5], h0[:, 1:2].contiguous())
        torch.testing.assert_close(part[:, 1:2], h)


def test_burn_in_is_validated():
    with pytest.raises(ValueError, match="burn_in"):
        TrainSettings(burn_in=-1)


def test_gradient_clipping_bounds_a_spike(body):
    """A step whose gradient is far above the running mean is clipped to grad_clip times that
    mean (the returned norm is the unclipped one); grad_clip = 0 leaves it; NaN skips."""
    torch.set_num_threads(1)
    s = TrainSettings(GapsSettings(garment="tshirt", **SMALL), batch=1, shapes=1,
                      motion_frames=6, speeds=(1.0,), random_motions=0, seed=2, grad_clip=3.0)
    tr = Trainer(s, body)
    params = [p for p in tr.model.parameters()]

    def fake(scale):
        for i, p in enumerate(params):
            g = torch.Generator().manual_seed(i)
            p.grad = scale * torch.randn(p.shape, generator=g)
        return float(torch.sqrt(sum((p.grad ** 2).sum() for p in params)))

    n1 = fake(1.0)
    assert tr.clip() == pytest.approx(n1, rel=1e-5) and tr.grad_ref == pytest.approx(n1)
    n2 = fake(100.0)
    assert tr.clip() == pytest.approx(n2, rel=1e-5)
    after = float(torch.sqrt(sum((p.grad ** 2).sum() for p in params)))
    assert after == pytest.approx(3.0 * n1, rel=1e-4)
    assert tr.grad_ref == pytest.approx(0.98 * n1 + 0.02 * 3.0 * n1, rel=1e-6)
    fake(float("nan"))
    ref = tr.grad_ref
    assert not np.isfinite(tr.clip()) and tr.grad_ref == ref
    tr.settings = dataclasses.replace(s, grad_clip=0.0)
    n3 = fake(100.0)
    tr.clip()
    after = float(torch.sqrt(sum((p.grad ** 2).sum() for p in params)))
    assert after == pytest.approx(n3, rel=1e-5)
    with pytest.raises(ValueError, match="grad_clip"):
        TrainSettings(grad_clip=-1.0)


def test_garment_weights_are_bit_identical_to_rbf_then_smooth_weights(body):
    """GAPS's skinning goes through ``skinning_weights(..., smoothing=)``: the same numbers,
    bit for bit, as the RBF weights followed by ``smooth_weights`` (what shipped models were
    trained on); NCS is nearest + 20 steps, SNUG nearest."""
    from draping.gaps import garment_weights, template_garment
    from draping.skinning import (
        dense_body_weights,
        laplacian_weights,
        nearest_weights,
        rbf_weights,
        smooth_weights,
    )

    g = template_garment(GapsSettings(garment="tshirt"), body)
    rv = body.rest()[0][0].double().numpy()
    wb = dense_body_weights((body.skin_indices.numpy(), body.skin_weights.double().numpy()),
                            body.num_vertices, body.num_bones)
    rbf = rbf_weights(g.vertices, rv, wb)
    for n in (0, 5, 20):
        got = garment_weights(GapsSettings(garment="tshirt", skin_smoothing=n), g, body).numpy()
        want = smooth_weights(rbf, g.faces, iterations=n) if n else rbf
        assert np.array_equal(got, want)
    got = garment_weights(GapsSettings(garment="tshirt", method="ncs"), g, body).numpy()
    assert np.array_equal(got, laplacian_weights(g.vertices, g.faces, rv, wb))
    got = garment_weights(GapsSettings(garment="tshirt", method="snug"), g, body).numpy()
    assert np.array_equal(got, nearest_weights(g.vertices, rv, wb))


def test_smoothed_rbf_stretches_less_than_the_thesis_rbf_on_a_tshirt(body):
    """Skinning alone on a held-back shape and motion: the RBF weights smoothed over the
    garment (``skin_smoothing``, the default) stretch the T-shirt less than the thesis' RBF
    weights, and vary less between neighbouring vertices."""
    from draping.gaps import Case, build_model, drape_case, frame_metrics, garment_weights

    case = Case("turn", 0, 1.0, (0.3, 0.6, 0.5, 0.6, 0.5, 0.5), 20)
    eps, rough = {}, {}
    for n in (0, 20):
        st = GapsSettings(garment="tshirt", skin_smoothing=n)
        model, g = build_model(st, body)
        eps[n] = float(np.mean(frame_metrics(drape_case(model, body, case), body)["eps_e"]))
        w = garment_weights(st, g, body).numpy()
        f = np.asarray(g.faces)
        rough[n] = float(np.abs(w[f[:, 0]] - w[f[:, 1]]).sum(1).mean())
    assert GapsSettings().skin_smoothing == 20
    assert eps[20] < eps[0]
    assert rough[20] < 0.95 * rough[0]


def test_skin_smoothing_key_and_legacy_files(tmp_path, trainer):
    from polygeo.runs import load_checkpoint, save_checkpoint

    assert "skin_smoothing" in GapsSettings().key_dict()
    assert "skin_smoothing" not in GapsSettings(skin_smoothing=0).key_dict()
    # The baselines do not use it: their keys (cached runs, resumes) do not depend on it.
    assert (GapsSettings(method="ncs", skin_smoothing=3).key_dict()
            == GapsSettings(method="ncs").key_dict())
    ts = TrainSettings(GapsSettings(skin_smoothing=0))
    assert ts.key_dict() == ts.replace(steps=5, checkpoint_every=7).key_dict()
    assert "skin_smoothing" not in ts.key_dict()["model"]
    with pytest.raises(ValueError, match="skin_smoothing"):
        GapsSettings(skin_smoothing=-1)
    # A file written before the setting existed was trained on the thesis' weights.
    p = save_model(tmp_path / "m.pt", trainer.model)
    ck = load_checkpoint(p)
    meta = dict(ck.meta)
    meta["settings"] = {k: v for k, v in meta["settings"].items() if k != "skin_smoothing"}
    save_checkpoint(tmp_path / "old.pt", ck.tensors, meta)
    assert load_model(tmp_path / "old.pt").settings.skin_smoothing == 0


def test_init_from_a_model_with_other_skin_smoothing(tmp_path, body):
    """Fine-tuning a model trained on other skinning weights: its network, this run's weights."""
    kw = dict(batch=2, shapes=2, motion_frames=12, speeds=(1.0,), random_motions=1, seed=3)
    old = Trainer(TrainSettings(GapsSettings(garment="tshirt", skin_smoothing=0, **SMALL), **kw),
                  body)
    with torch.no_grad():
        old.model.basis.weight.normal_()
    p = save_model(tmp_path / "old.pt", old.model)
    new = Trainer(TrainSettings(GapsSettings(garment="tshirt", **SMALL), init=str(p), **kw), body)
    fresh = Trainer(TrainSettings(GapsSettings(garment="tshirt", **SMALL), **kw), body)
    torch.testing.assert_close(new.model.basis.weight, old.model.basis.weight.half().float())
    torch.testing.assert_close(new.model.weights, fresh.model.weights)
    assert not torch.allclose(new.model.weights, old.model.weights)
    with pytest.raises(ValueError, match="init"):
        Trainer(TrainSettings(GapsSettings(garment="tshirt", width=8, depth=1, rank=8),
                              init=str(p), **kw), body)
