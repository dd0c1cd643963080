from pathlib import Path

import numpy as np
import pytest
import torch

import polygeo.stn as polygeo_stn
import polygeo.synthetic as syn
from polygeo.canonical import canonicalize, height_residual, optimize_rotations
from polygeo.frames import axis_angle_to_matrix, quaternion_to_matrix
from polygeo.runs import CheckpointError, SettingsChangedError, fingerprint, load_checkpoint
from polygeo.stn import (
    PatchSTN,
    load_pretrained,
    pretrained_path,
    save_weights,
    stn_rotations,
)
from polygeo.stn_train import CHECKPOINT_FILE, TrainConfig, train_stn
from polygeo.synthetic._common import grid_faces as _grid_faces
from polygeo.synthetic.families import _family_height_grad, _family_params

# Seeds 10**6 + i are never used by `polygeo train-stn` (batches use (seed, step) with
# seed 0 and validation (0, 10**9)): these patches are held out.
HELD_OUT = 10**6


def _grid_family(n, m=12, amplitude=0.5, seed=HELD_OUT):
    """Family sums on an m x m grid of [-1, 1]^2 (shared faces), randomly rotated."""
    rng = np.random.default_rng(seed)
    t = np.linspace(-1, 1, m)
    U, V = np.meshgrid(t, t, indexing="ij")
    uv = np.broadcast_to(np.stack([U.ravel(), V.ravel()], 1), (n, m * m, 2)).copy()
    z, _ = _family_height_grad(uv, _family_params(rng, n, syn.PATCH_FAMILIES, amplitude))
    local = np.concatenate([uv, z[..., None]], -1)
    gen = torch.Generator().manual_seed(seed)
    from polygeo.frames import random_rotation

    R = random_rotation(n, gen).to(torch.float64).numpy()
    pts = np.einsum("bij,bpj->bpi", R, local) + rng.normal(size=(n, 1, 3))
    return torch.from_numpy(pts), _grid_faces(m, m, False, False)


def _foldover(local, faces):
    q = local[:, faces, :2]
    e1, e2 = q[:, :, 1] - q[:, :, 0], q[:, :, 2] - q[:, :, 0]
    a = e1[..., 0] * e2[..., 1] - e1[..., 1] * e2[..., 0]
    dom = torch.sign(a.sum(1, keepdim=True))
    return (a * dom < 0).to(torch.float64).mean(1)


def test_untrained_network_is_the_identity():
    net = PatchSTN((8, 16), (8,))
    x = torch.randn(5, 20, 3)
    q = net(x)
    torch.testing.assert_close(q, torch.tensor([[1.0, 0, 0, 0]]).expand(5, 4))


@pytest.mark.parametrize(
    "kw",
    [{}, {"context": True}, {"features": "xyz", "output": "quaternion", "canonical_signs": False}],
)
def test_network_batched_equals_single_and_ignores_padding(kw):
    torch.manual_seed(0)
    net = PatchSTN((8, 16), (8,), **kw)
    with torch.no_grad():
        net.out.weight.normal_(0, 0.5)
    x = torch.randn(4, 30, 3)
    m = torch.ones(4, 30, dtype=torch.bool)
    m[1, 20:] = False
    q = net(x, m)
    torch.testing.assert_close(q.norm(dim=-1), torch.ones(4))
    for i in range(4):
        keep = m[i]
        torch.testing.assert_close(net(x[i : i + 1, keep]), q[i : i + 1])
    x2 = x.clone()
    x2[1, 20:] = 1e3  # padded garbage does not matter
    torch.testing.assert_close(net(x2, m), q)


def test_canonicalize_frame_and_invariance():
    fp = syn.family_patches(6, 50, seed=1)
    p = torch.from_numpy(fp.points)
    c = canonicalize(p)
    r = c.local.norm(dim=-1)
    torch.testing.assert_close(r.amax(1), torch.ones(6, dtype=torch.float64))
    back = c.orientation.apply(c.local)
    torch.testing.assert_close(back, p)
    # rigid motion and scaling of the input leave the residual unchanged
    R = quaternion_to_matrix(torch.tensor([0.3, -0.5, 0.2, 0.7], dtype=torch.float64))
    c2 = canonicalize(3.0 * p @ R.T + torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
    r1, _ = height_residual(c.local, c.mask, None, 3)
    r2, _ = height_residual(c2.local, c2.mask, None, 3)
    torch.testing.assert_close(r1, r2)


def test_height_residual_gradcheck_wrt_rotation():
    fp = syn.family_patches(2, 24, seed=3)
    c = canonicalize(torch.from_numpy(fp.points))
    w = (0.1 * torch.randn(2, 3, dtype=torch.float64)).requires_grad_()

    def f(w):
        return height_residual(c.local, c.mask, axis_angle_to_matrix(w), 2)[0]

    assert torch.autograd.gradcheck(f, (w,))


def test_optimize_lowers_residual_and_removes_pca_foldovers():
    pts, faces = _grid_family(120, m=10)
    c = canonicalize(pts)
    f0 = _foldover(c.local, faces)
    folded = f0 > 0
    assert folded.sum() > 25  # PCA folds over on many of these curved patches
    res = optimize_rotations(c.local, c.mask, 4, steps=30)
    assert (res.residual <= res.initial_residual + 1e-12).all()
    ratio = res.residual.mean() / res.initial_residual.mean()
    assert ratio < 0.8, f"optimize / pca residual {ratio:.3f}"
    rf = res.residual[folded].mean() / res.initial_residual[folded].mean()
    assert rf < 0.8, f"on PCA-folded patches: {rf:.3f}"
    f1 = _foldover(c.local @ res.rotation, faces)
    assert f1[folded].mean() < 0.25 * f0[folded].mean()
    # starting from a given rotation, zero steps return it
    Q = axis_angle_to_matrix(torch.full((120, 3), 0.1, dtype=torch.float64))
    same = optimize_rotations(c.local, c.mask, 4, init=Q, steps=0)
    torch.testing.assert_close(same.rotation, Q)


def test_shipped_stn_beats_pca_on_held_out_patches():
    path = pretrained_path()
    assert path.is_file(), "polygeo/data/stn_weights.pt is missing: run polygeo train-stn"
    assert path.stat().st_size < 1_000_000
    net = load_pretrained()
    assert load_pretrained() is net  # cached
    pts, faces = _grid_family(400, seed=HELD_OUT + 1)
    c = canonicalize(pts)
    r0, _ = height_residual(c.local, c.mask, None, 4)
    Q = stn_rotations(c.local, c.mask)
    r1, _ = height_residual(c.local, c.mask, Q, 4)
    ratio = float(r1.mean() / r0.mean())
    assert ratio < 0.82, f"stn / pca residual {ratio:.3f}"
    folded = _foldover(c.local, faces) > 0
    rf = float(r1[folded].mean() / r0[folded].mean())
    assert rf < 0.76, f"on PCA-folded patches: {rf:.3f}"
    # irregular, noisy samples of the families (the training distribution, other seeds)
    fp = syn.family_patches(400, 128, noise=0.01, seed=HELD_OUT + 2)
    c = canonicalize(torch.from_numpy(fp.points))
    r0, _ = height_residual(c.local, c.mask, None, 4)
    r1, _ = height_residual(c.local, c.mask, stn_rotations(c.local, c.mask), 4)
    assert float(r1.mean() / r0.mean()) < 0.85


def test_training_is_reproducible_and_resumes(tmp_path):
    cfg = TrainConfig(
        steps=4, batch_size=6, n_points=24, mesh_share=0.0, widths=(8, 16), head=(8,),
        n_val=8, n_train=32, eval_every=2, checkpoint_every=2, threads=1, lr=1e-2,
        patience=0,
    )
    full, hist = train_stn(cfg, checkpoint_dir=tmp_path / "a", progress=False)
    assert (tmp_path / "a" / "stn_checkpoint.pt").is_file()
    assert [r["step"] for r in hist["val"]] == [2, 4]

    class Stop(Exception):
        pass

    def stop_at_4(line):
        if line.startswith("step 4"):
            raise Stop

    with pytest.raises(Stop):
        train_stn(cfg, checkpoint_dir=tmp_path / "b", progress=False, log=stop_at_4)
    resumed, hist_b = train_stn(cfg, checkpoint_dir=tmp_path / "b", progress=False)
    for k, v in full.state_dict().items():
        torch.testing.assert_close(resumed.state_dict()[k], v, rtol=0, atol=0)
    assert len(hist_b["loss"]) == 4
    # a checkpoint of another configuration is refused
    other = TrainConfig(**{**cfg.__dict__, "lr": 5e-3})
    with pytest.raises(ValueError, match="configuration"):
        train_stn(other, checkpoint_dir=tmp_path / "a", progress=False)
    # weights round-trip
    p = save_weights(full, tmp_path / "w.pt", meta={"x": 1})
    back = load_pretrained(p)
    x = torch.randn(3, 10, 3)
    torch.testing.assert_close(back(x), full(x))


def test_bad_input(tmp_path):
    with pytest.raises(ValueError, match="points"):
        canonicalize(torch.zeros(2, 5, 2))
    with pytest.raises(TypeError, match="mask"):
        canonicalize(torch.zeros(2, 5, 3), torch.ones(2, 5))
    with pytest.raises(ValueError, match="mask"):
        canonicalize(torch.zeros(2, 5, 3), torch.ones(2, 4, dtype=torch.bool))
    bad = torch.zeros(1, 4, 3)
    bad[0, 1, 0] = float("nan")
    with pytest.raises(ValueError, match="points"):
        canonicalize(bad)
    x = torch.randn(2, 10, 3, dtype=torch.float64)
    m = torch.ones(2, 10, dtype=torch.bool)
    with pytest.raises(ValueError, match="steps"):
        optimize_rotations(x, m, 2, steps=-1)
    with pytest.raises(ValueError, match="lr"):
        optimize_rotations(x, m, 2, lr=0.0)
    with pytest.raises(FileNotFoundError):
        load_pretrained(tmp_path / "none.pt")
    torch.save({"a": 1}, tmp_path / "junk.pt")
    with pytest.raises(ValueError, match="STN"):
        load_pretrained(tmp_path / "junk.pt")


def _perturbed_net(seed=0, **kw):
    torch.manual_seed(seed)
    net = PatchSTN((8, 16), (8,), **kw)
    with torch.no_grad():
        net.out.weight.normal_(0, 0.5)
        net.out.bias.normal_(0, 0.3)
    return net


@pytest.mark.parametrize("output", ["tilt", "quaternion"])
def test_network_is_equivariant_to_axis_sign_flips(output):
    # flipping canonical axes (x -> x D) changes nothing for the height residual, so the
    # refined rotation must follow: Q(x D) = D Q(x) D
    fp = syn.family_patches(5, 40, seed=4)
    x = canonicalize(torch.from_numpy(fp.points)).local.float()
    net = _perturbed_net(output=output)
    Q = quaternion_to_matrix(net(x).double())
    for signs in ([-1, 1, 1], [1, -1, -1], [-1, -1, -1]):
        D = torch.diag(torch.tensor(signs, dtype=torch.float64))
        Qf = quaternion_to_matrix(net(x * D.diagonal().float()).double())
        torch.testing.assert_close(Qf, D @ Q @ D, atol=1e-5, rtol=0)
        r1, _ = height_residual(x.double(), torch.ones(5, 40, dtype=torch.bool), Q, 3)
        r2, _ = height_residual(x.double() @ D, torch.ones(5, 40, dtype=torch.bool),
                                D @ Q @ D, 3)
        torch.testing.assert_close(r1, r2)
    if output == "tilt":  # no spin about the normal: the rotation vector's z is zero
        q = net(x)
        torch.testing.assert_close(q[:, 3], torch.zeros(5))
        torch.testing.assert_close(q.norm(dim=-1), torch.ones(5))


def test_knn_normals_on_plane_and_sphere_ignore_padding():
    rng = np.random.default_rng(0)
    uv = rng.uniform(-1, 1, (2, 60, 2))
    plane = np.concatenate([uv, np.zeros((2, 60, 1))], -1)
    R = quaternion_to_matrix(torch.tensor([0.9, 0.1, -0.3, 0.2], dtype=torch.float64))
    x = torch.from_numpy(plane) @ R.T
    m = torch.ones(2, 60, dtype=torch.bool)
    m[1, 40:] = False
    x[1, 40:] = 5.0  # padded garbage
    n = polygeo_stn.knn_normals(x, m, k=8)
    expect = R[:, 2] * torch.sign(R[2, 2])
    torch.testing.assert_close(n[m], expect.expand(int(m.sum()), 3), atol=1e-9, rtol=0)
    assert (n[~m] == 0).all()
    s = syn.sphere(400, seed=1)  # unit sphere: normals radial (up to sign)
    p = torch.from_numpy(s.points)[None]
    n = polygeo_stn.knn_normals(p, None, k=10)[0]
    cos = (n * p[0]).sum(-1).abs()
    assert float(cos.min()) > 0.97
    assert (n[:, 2] >= 0).all()


def test_early_stopping_returns_best_and_stops(tmp_path):
    cfg = TrainConfig(
        steps=20, batch_size=4, n_points=16, mesh_share=0.0, widths=(8,), head=(4,),
        n_val=4, n_train=8, eval_every=2, checkpoint_every=2, threads=1, lr=0.0, patience=2,
    )
    net, hist = train_stn(cfg, checkpoint_dir=tmp_path, progress=False)
    # lr = 0: the first validation stays the best, two more without improvement stop it
    assert hist["stopped_at"] == 6 and len(hist["loss"]) == 6
    assert hist["best"]["step"] == 2
    assert hist["cpu_seconds"] > 0


class _Payload:
    """Unpickling this object writes a marker file (what a malicious file could do)."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (Path.write_text, (Path(self.marker), "pwned"))


def _tiny_config(**kw):
    return TrainConfig(**{
        "steps": 2, "batch_size": 4, "n_points": 16, "mesh_share": 0.0, "widths": (8,),
        "head": (4,), "n_val": 4, "n_train": 8, "eval_every": 1, "checkpoint_every": 1,
        "threads": 1, "patience": 0, **kw,
    })


def test_old_and_pickled_training_checkpoints_are_refused(tmp_path):
    cfg = _tiny_config()
    net = PatchSTN((8,), (4,))
    # a checkpoint of the layout written before polygeo.runs (a pickle of plain data)
    old = tmp_path / "old"
    old.mkdir()
    torch.save({"state_dict": net.state_dict(), "step": 1, "history": {"config": {}}},
               old / CHECKPOINT_FILE)
    with pytest.raises(CheckpointError, match="older polygeo.*resume=False"):
        train_stn(cfg, checkpoint_dir=old, progress=False)
    # one carrying a pickled object: refused, and nothing runs
    evil = tmp_path / "evil"
    evil.mkdir()
    marker = tmp_path / "marker"
    torch.save({"state_dict": net.state_dict(), "x": _Payload(str(marker))},
               evil / CHECKPOINT_FILE)
    with pytest.raises(CheckpointError, match="pickled"):
        train_stn(cfg, checkpoint_dir=evil, progress=False)
    assert not marker.exists()
    # resume=False starts afresh over either
    _, hist = train_stn(cfg, checkpoint_dir=old, resume=False, progress=False)
    assert len(hist["loss"]) == 2
    _, meta = load_checkpoint(old / CHECKPOINT_FILE)
    assert meta["step"] == 2 and meta["fingerprint"] == fingerprint(cfg)


def test_weights_files_new_legacy_and_pickled(tmp_path):
    net = _perturbed_net(3)
    x = torch.randn(3, 12, 3)
    p = save_weights(net, tmp_path / "w.pt", meta={"note": "x"})
    assert load_checkpoint(p).meta == {"config": net.config(), "meta": {"note": "x"}}
    torch.testing.assert_close(load_pretrained(p)(x), net(x), rtol=0, atol=0)
    # the first layout (the shipped file's): a plain dict, read with weights_only=True
    sd = {k: v.detach().clone() for k, v in net.state_dict().items()}
    torch.save({"config": net.config(), "state_dict": sd, "meta": {}}, tmp_path / "legacy.pt")
    torch.testing.assert_close(load_pretrained(tmp_path / "legacy.pt")(x), net(x), rtol=0,
                               atol=0)
    marker = tmp_path / "marker"
    torch.save({"config": net.config(), "state_dict": sd, "meta": _Payload(str(marker))},
               tmp_path / "evil.pt")
    with pytest.raises(ValueError, match="STN weights"):
        load_pretrained(tmp_path / "evil.pt")
    assert not marker.exists()
    # a training checkpoint holds weights too
    cfg = _tiny_config(widths=(8, 16), head=(8,))
    trained, _ = train_stn(cfg, checkpoint_dir=tmp_path / "run", progress=False)
    last = load_pretrained(tmp_path / "run" / CHECKPOINT_FILE)
    assert last.config() == trained.config()


def test_resume_after_settings_change_is_refused_with_a_message(tmp_path):
    cfg = _tiny_config()
    train_stn(cfg, checkpoint_dir=tmp_path, progress=False)
    with pytest.raises(SettingsChangedError, match="another configuration"):
        train_stn(_tiny_config(seed=1), checkpoint_dir=tmp_path, progress=False)
    # a finished run resumes to the same result without further steps
    net_a, hist_a = train_stn(cfg, checkpoint_dir=tmp_path, progress=False)
    assert len(hist_a["loss"]) == 2
