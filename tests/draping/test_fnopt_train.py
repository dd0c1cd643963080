"""``draping.fnopt.train.train``: seeded without touching the global RNG, resumable exactly."""

import json

import torch

from draping.fnopt import cloth, solvers
from draping.fnopt.model import FNO, FNOConfig
from draping.fnopt.train import TrainSettings, train
from polygeo.runs import read_jsonl

torch.set_num_threads(1)

TINY = dict(width=4, modes=2, layers=1, projection=8, res=8, pool=4, batch=2, steps=6,
            inner_min=2, inner_max=3, max_frames=40, eval_every=3, checkpoint_every=3, seed=3)


def _val():
    """One hand-made validation step (an 8x8 sheet hanging from its corners)."""
    sheet = cloth.Sheet(8, 8, 0.5)
    x = cloth.rest_positions(sheet)[None]
    idx = cloth.handle_indices("corners", 8, 8)
    mk = [solvers.make_problem(x.to(dt), torch.zeros_like(x).to(dt), idx,
                               x[:, idx[:, 0], idx[:, 1]].to(dt), sheet.hx, sheet.hy,
                               cloth.Material().tensors(1, dt)) for dt in (torch.float32,
                                                                          torch.float64)]
    a = solvers.solve_reference(mk[0], None)
    return [{"problem": mk[0], "p64": mk[1], "l_star": float(mk[1].loss(a.double())[0]),
             "l_zero": float(mk[1].loss(torch.zeros_like(a).double())[0])}]


def _weights(path):
    return torch.load(path / "model.pt", weights_only=True)


def test_training_is_seeded_without_touching_the_global_rng(tmp_path):
    torch.manual_seed(1234)
    before = torch.get_rng_state()
    s = TrainSettings(**{**TINY, "steps": 0})
    train(s, tmp_path, quiet=True, log=lambda *a: None, val=_val())
    assert torch.equal(torch.get_rng_state(), before)
    torch.manual_seed(s.seed)                           # the initial weights: seed's own
    want = FNO(FNOConfig(s.width, s.modes, s.layers, s.projection)).state_dict()
    got = _weights(tmp_path)
    assert all(torch.equal(got[k], want[k]) for k in want)


def test_an_interrupted_run_resumes_to_the_same_weights(tmp_path):
    s = TrainSettings(**TINY)
    val = _val()
    train(s, tmp_path / "whole", quiet=True, log=lambda *a: None, val=val)
    out = tmp_path / "parts"
    first = train(s, out, quiet=True, log=lambda *a: None, val=val, max_minutes=0.0)
    assert not first["finished"] and first["step"] < s.steps
    # a record logged after the checkpoint by a process stopped before the next one
    with open(out / "log.jsonl", "a") as fh:
        fh.write(json.dumps({"step": first["step"] + 1, "loss_ema": 0.0}) + "\n")
    torch.manual_seed(99)                               # whatever the caller's RNG holds
    rest = train(s, out, quiet=True, log=lambda *a: None, val=val)
    assert rest["finished"] and rest["step"] == s.steps
    a, b = _weights(tmp_path / "whole"), _weights(out)
    assert all(torch.equal(a[k], b[k]) for k in a)
    steps = [r["step"] for r in read_jsonl(out / "log.jsonl")]
    assert steps == [r["step"] for r in read_jsonl(tmp_path / "whole" / "log.jsonl")]
