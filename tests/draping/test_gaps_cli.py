"""``polygeo train-drape`` and ``polygeo drape``: help, bad input (one line, exit 2), a short
training run that resumes, and a drape with the model it wrote."""

from __future__ import annotations

import json

import numpy as np
import pytest

from polygeo.cli import build_parser, main


def _help(name: str) -> str:
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    return sub.choices[name].format_help()


def test_help_documents_options_and_units():
    t = _help("train-drape")
    for opt in ("--method", "--garment", "--garment-file", "--minutes", "--steps", "--seed",
                "--resume", "-o", "--width", "--depth", "--rank", "--inextensibility",
                "--skin-smoothing", "--collision-stiffness", "--collision-eps", "--k-ext-rings",
                "--replay"):
        assert opt in t, opt
    for word in ("minutes", "snug", "ncs", "held", "eps_c", "CPU"):
        assert word in t, word
    d = _help("drape")
    for opt in ("--method", "--model", "--garment", "--garment-file", "--motion",
                "--motion-file", "--frames", "--shape", "--seed", "--reference", "-o"):
        assert opt in d, opt
    for word in ("metres", "radians", "[0, 1]", "cm", "degrees", "ms per frame"):
        assert word in d, word


def _fails(capsys, argv) -> str:
    status = main(argv)
    err = capsys.readouterr().err
    assert status == 2
    assert "Traceback" not in err
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, err
    return lines[0]


def test_bad_drape_arguments(capsys, tmp_path):
    o = ["-o", str(tmp_path / "o")]
    assert "[0, 1]" in _fails(capsys, ["drape", "--shape", "age=1.5", *o])
    assert "--frames" in _fails(capsys, ["drape", "--frames", "0", *o])
    assert "--model" in _fails(capsys, ["drape", "--method", "snug", *o])
    line = _fails(capsys, ["drape", "--garment", "pants", *o])
    assert "pants" in line and "shipped: " in line and "dress" in line and "tshirt" in line


def test_nan_motion_file(capsys, tmp_path, monkeypatch):
    rot = np.zeros((4, 104, 3))
    rot[2, 5, 1] = np.nan
    p = tmp_path / "m.npz"
    np.savez(p, rotations=rot, translation=np.zeros((4, 3)))
    line = _fails(capsys, ["drape", "--motion-file", str(p), "--model", "tshirt",
                           "-o", str(tmp_path / "o")])
    assert "NaN" in line or "nan" in line.lower()


@pytest.mark.slow
def test_train_resume_and_drape(tmp_path, capsys):
    run = tmp_path / "run"
    args = ["train-drape", "--garment", "tshirt", "--width", "8", "--depth", "1", "--rank",
            "4", "--batch", "1", "--eval-frames", "3", "--quiet", "-o", str(run)]
    assert main([*args, "--steps", "2"]) == 0
    rec = json.loads((run / "model.json").read_text())
    assert rec["training"]["steps"] == 2
    assert set(rec["held_out"]["mean"]) == {"eps_e", "eps_a", "eps_c"}
    # a record logged after the last checkpoint by a process stopped before the next one
    last = json.loads((run / "log.jsonl").read_text().splitlines()[-1])
    with open(run / "log.jsonl", "a") as fh:
        fh.write(json.dumps({**last, "step": 2}) + "\n")
    assert main([*args, "--steps", "3", "--resume"]) == 0
    log = [json.loads(s) for s in (run / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log] == [0, 1, 2]
    capsys.readouterr()
    out = tmp_path / "drape"
    assert main(["drape", "--model", str(run / "model.pt"), "--garment", "tshirt", "--frames",
                 "3", "--shape", "age=0.66,gender=0.8", "--no-pictures", "--quiet",
                 "-o", str(out)]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert len(m["per_frame"]) == 3
    for k in ("eps_e", "eps_a", "eps_c", "ms_per_frame"):
        assert k in m["mean"]
    assert (out / "meshes" / "000002.ply").is_file() and (out / "body" / "000000.ply").is_file()
    # the model refuses another garment
    line = _fails(capsys, ["drape", "--model", str(run / "model.pt"), "--garment", "dress",
                           "-o", str(out)])
    assert "trained for garment" in line


def test_option_choices_are_the_library_names():
    from draping.gaps import INEXTENSIBILITY, METHODS
    from draping.garments import GARMENTS

    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    for name in ("train-drape", "drape"):
        acts = {a.dest: a for a in sub.choices[name]._actions}
        assert tuple(acts["method"].choices) == METHODS
    acts = {a.dest: a for a in sub.choices["train-drape"]._actions}
    assert tuple(acts["inextensibility"].choices) == INEXTENSIBILITY
    # the library modules re-export the torch-free names the parsers use (one home each)
    from draping import names
    from draping.body import ANNY_PHENOTYPES
    from draping.motion import MOTIONS

    assert GARMENTS is names.GARMENTS and MOTIONS is names.MOTIONS
    assert ANNY_PHENOTYPES is names.PHENOTYPES
    for cmd in ("drape", "drape-reference"):  # the shared body/motion options, same defaults
        acts = {a.dest: a for a in sub.choices[cmd]._actions}
        assert {"motion", "motion_file", "frames", "shape", "seed"} <= set(acts)
        assert acts["motion"].default == "walk" and acts["seed"].default == 0


def test_collision_stiffness_option(capsys, tmp_path):
    """``--collision-stiffness`` sets k_c of eq. (40) (the shipped dress uses 1e5) and
    ``--collision-eps`` its clearance (m); left out, the library defaults; a negative value is
    refused with one line naming it."""
    from draping.gaps import TrainSettings
    from draping.gaps.cli import _settings

    parser = build_parser()
    base = ["train-drape", "--garment", "dress", "-o", str(tmp_path / "r")]
    args = parser.parse_args([*base, "--collision-stiffness", "1e5"])
    assert _settings(args).collision_stiffness == 1e5
    assert _settings(parser.parse_args(base)).collision_stiffness == \
        TrainSettings().collision_stiffness
    assert "collision_stiffness" in _fails(capsys, [*base, "--collision-stiffness", "-1"])
    args = parser.parse_args([*base, "--collision-eps", "0.004"])
    assert _settings(args).collision_eps == 0.004
    assert _settings(parser.parse_args(base)).collision_eps == TrainSettings().collision_eps
    assert "collision_eps" in _fails(capsys, [*base, "--collision-eps", "-0.001"])
    assert _settings(parser.parse_args([*base, "--k-ext-rings", "3"])).k_ext_rings == 3
    assert _settings(parser.parse_args(base)).k_ext_rings == 0
    assert "k_ext_rings" in _fails(capsys, [*base, "--k-ext-rings", "-1"])
    assert _settings(parser.parse_args([*base, "--replay", "0.25"])).replay == 0.25
    assert _settings(parser.parse_args(base)).replay == 0.0
    assert "replay" in _fails(capsys, [*base, "--replay", "1.5"])
    assert not (tmp_path / "r" / "checkpoint.pt").exists()
