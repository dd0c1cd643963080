"""draping.gaps weight averaging (``TrainSettings.average_from``): the exported network is the
plain mean of the weights after the steps past ``average_from`` (computed here apart from
:class:`draping.gaps.WeightAverage`), training is unchanged, the average survives a checkpoint,
and the default exports the last weights as before."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from draping.body import AnnyBody
from draping.gaps import GapsSettings, Trainer, TrainSettings, WeightAverage, load_model
from draping.gaps.train import train

SMALL = dict(width=16, depth=1, rank=8)


@pytest.fixture(scope="module")
def body():
    return AnnyBody.load()


def _settings(**kw) -> TrainSettings:
    return TrainSettings(GapsSettings(garment="tshirt", **SMALL), batch=2, shapes=2,
                         motion_frames=12, speeds=(1.0,), random_motions=1, seed=7, **kw)


def _params(module) -> dict:
    return {k: p.detach().clone() for k, p in module.named_parameters()}


def test_weight_average_is_the_plain_mean():
    torch.manual_seed(0)
    net = torch.nn.Linear(3, 2)
    net.register_buffer("fixed", torch.arange(4.0))
    avg = WeightAverage(5)
    snaps = []
    for _ in range(3):
        with torch.no_grad():
            for p in net.parameters():
                p.add_(torch.randn(p.shape))
        snaps.append(_params(net))
        avg.update(net)
    out = avg.averaged(net)
    assert avg.count == 3
    for k, p in out.named_parameters():
        mean = torch.stack([s[k] for s in snaps]).double().mean(0)
        torch.testing.assert_close(p.detach(), mean.float())
        assert not torch.equal(p.detach(), snaps[-1][k])
    assert torch.equal(out.fixed, net.fixed)  # buffers are the module's own
    torch.testing.assert_close(net.weight.detach(), snaps[-1]["weight"])  # net untouched
    again = WeightAverage(5)
    again.load(avg.state())
    assert again.count == 3
    torch.testing.assert_close(again.averaged(net).weight, out.weight)


def test_weight_average_bad_input():
    net = torch.nn.Linear(2, 2)
    for bad in (-1, 1.5, True, "3"):
        with pytest.raises((TypeError, ValueError), match="start"):
            WeightAverage(bad)
    avg = WeightAverage(0)
    with pytest.raises(ValueError, match="count 0"):
        avg.averaged(net)
    with torch.no_grad():
        net.weight[0, 0] = float("nan")
    with pytest.raises(ValueError, match="not finite"):
        avg.update(net)
    assert avg.count == 0
    with pytest.raises(ValueError, match="parameters differ"):
        avg.update(torch.nn.Linear(2, 2))
        avg.update(torch.nn.Conv1d(2, 2, 1, bias=False))
    with pytest.raises(ValueError, match="no weight average"):
        WeightAverage(0).load(None)
    with pytest.raises(ValueError, match="starts at step 0"):
        WeightAverage(3).load(avg.state())


def test_average_from_setting_key_and_checks():
    s = _settings()
    assert s.average_from is None
    t = s.replace(average_from=4)
    assert t.key_dict() == s.key_dict()  # training unchanged: the same run
    assert TrainSettings.from_dict(dataclasses.asdict(t)) == t
    legacy = dataclasses.asdict(s)
    legacy.pop("average_from")
    assert TrainSettings.from_dict(legacy) == s
    with pytest.raises(ValueError, match="average_from"):
        s.replace(average_from=-1)
    with pytest.raises(TypeError, match="average_from"):
        s.replace(average_from=2.0)


def test_trainer_averages_past_the_step_and_trains_the_same(body):
    torch.set_num_threads(1)
    plain = Trainer(_settings(), body)
    avg = Trainer(_settings(average_from=2), body)
    snaps = []
    for _ in range(5):
        plain.train_step()
        avg.train_step()
        snaps.append(_params(plain.model))
    for k, p in avg.model.named_parameters():  # the trajectory is the plain run's
        assert torch.equal(p.detach(), snaps[-1][k])
    assert avg.average.count == 3
    out = avg.average.averaged(avg.model)
    for k, p in out.named_parameters():  # weights after steps 3, 4, 5
        mean = torch.stack([s[k] for s in snaps[2:]]).double().mean(0)
        torch.testing.assert_close(p.detach(), mean.float())
    # resumed from a checkpoint past the start: the same average as without the stop
    state5 = {"model": plain.model.state_dict(), "optim": plain.opt.state_dict()}
    with pytest.raises(ValueError, match="no weight average"):
        Trainer(_settings(average_from=2), body).load_state(state5, 5)
    early = Trainer(_settings(average_from=5), body)
    early.load_state(state5, 5)  # at the start: nothing to restore
    assert early.average.count == 0


def test_resume_keeps_the_average(body, tmp_path):
    torch.set_num_threads(1)
    s = _settings(average_from=1, steps=4, checkpoint_every=2)
    whole = train(s, tmp_path / "whole", quiet=True)
    train(s, tmp_path / "cut", steps=3, quiet=True)
    cut = train(s, tmp_path / "cut", quiet=True)
    assert whole.steps == cut.steps == 4
    a, b = load_model(whole.model_path), load_model(cut.model_path)
    for (k, p), q in zip(a.named_parameters(), b.parameters()):
        assert torch.equal(p, q), k
    last = load_model(tmp_path / "whole" / "model_last.pt")
    assert a.record["training"]["average"] == {"from_step": 1, "snapshots": 3}
    assert any(not torch.equal(p, q) for p, q in zip(a.parameters(), last.parameters()))
    # the default exports the last weights and writes no model_last.pt
    plain = train(s.replace(average_from=None), tmp_path / "plain", quiet=True)
    assert not (tmp_path / "plain" / "model_last.pt").exists()
    p_model = load_model(plain.model_path)
    assert "average" not in p_model.record["training"]
    for p, q in zip(p_model.parameters(), last.parameters()):
        assert torch.equal(p, q)


def test_average_cli_option(tmp_path):
    from draping.gaps.cli import _settings as cli_settings
    from polygeo.cli import build_parser

    base = ["train-drape", "--garment", "dress", "-o", str(tmp_path / "r")]
    parser = build_parser()
    assert cli_settings(parser.parse_args([*base, "--average-from", "8000"])).average_from == 8000
    assert cli_settings(parser.parse_args(base)).average_from is None
