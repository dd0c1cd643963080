"""``polygeo drape-reference``: help, bad input (one line, exit status 2), and the pipeline."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from draping import drape
from draping.body import AnnyBody
from polygeo.cli import build_parser, main

OPTIONS = ("--garment", "--garment-file", "--motion", "--motion-file", "--frames", "--shape",
           "--seed", "--res", "--static", "-o")


def _help() -> str:
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    return sub.choices["drape-reference"].format_help()


def test_help_lists_every_option_with_units():
    text = _help()
    for opt in OPTIONS:
        assert opt in text, opt
    for word in ("metres", "radians", "[0, 1]", "fps", "seconds", "eps_c"):
        assert word in text, word
    for name in ("tshirt", "dress", "walk", "jacks", "random", "gender", "proportions"):
        assert name in text, name


def test_help_states_every_default():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    for action in sub.choices["drape-reference"]._actions:
        if action.dest == "help":
            continue
        assert action.help and "default" in action.help, action.option_strings
    text = " ".join(_help().split()).split("options:", 1)[1]
    assert "--motion-file FILE" in text
    motion_file = text.split("--motion-file FILE", 1)[1].split("--frames", 1)[0]
    assert "default" in motion_file and "fps" in motion_file


def _fails(capsys, argv) -> str:
    status = main(["drape-reference", *argv])
    err = capsys.readouterr().err
    assert status == 2
    assert "Traceback" not in err
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("polygeo drape-reference: error:")
    return lines[0]


def test_unknown_garment_name(capsys, tmp_path):
    line = _fails(capsys, ["--garment", "poncho", "-o", str(tmp_path)])
    assert "garment" in line and "poncho" in line and "tshirt" in line


def test_unknown_motion_name(capsys, tmp_path):
    line = _fails(capsys, ["--motion", "moonwalk", "-o", str(tmp_path)])
    assert "motion" in line and "moonwalk" in line


@pytest.mark.parametrize("shape, words", [
    ("age=1.5", ("age", "[0, 1]", "1.5")),
    ("height=-0.1", ("height", "[0, 1]")),
    ("size=0.3", ("size", "gender")),
    ("age", ("NAME=VALUE",)),
    ("age=old", ("age", "old")),
    ("age=0.2,age=0.3", ("twice",)),
])
def test_bad_shape(capsys, tmp_path, shape, words):
    line = _fails(capsys, ["--shape", shape, "-o", str(tmp_path)])
    for w in words:
        assert w in line, (w, line)


def test_parse_shape():
    assert drape.parse_shape("age=0.66, gender=0.2") == (("age", 0.66), ("gender", 0.2))
    assert drape.parse_shape("") == ()


def test_bad_frames_and_res(capsys, tmp_path):
    assert "frames" in _fails(capsys, ["--frames", "0", "-o", str(tmp_path)])
    assert "res" in _fails(capsys, ["--res", "10", "-o", str(tmp_path)])


def test_nan_poses_in_motion_file(capsys, tmp_path):
    body = AnnyBody.load()
    rot = np.zeros((5, body.num_bones, 3))
    rot[3, 7, 1] = np.nan
    f = tmp_path / "m.npz"
    np.savez(f, rotations=rot, translation=np.zeros((5, 3)))
    line = _fails(capsys, ["--motion-file", str(f), "-o", str(tmp_path / "o")])
    assert "NaN" in line and "[3]" in line


def test_motion_file_wrong_layout(capsys, tmp_path):
    f = tmp_path / "amass.npz"
    np.savez(f, poses=np.zeros((5, 156)), trans=np.zeros((5, 3)))
    line = _fails(capsys, ["--motion-file", str(f), "-o", str(tmp_path / "o")])
    assert "rotations" in line and "AMASS" in line
    assert "not found" in _fails(capsys, ["--motion-file", str(tmp_path / "nope.npz"),
                                          "-o", str(tmp_path / "o")])


def test_read_motion_round_trip(tmp_path):
    body = AnnyBody.load()
    rng = np.random.default_rng(0)
    rot = 0.1 * rng.standard_normal((4, body.num_bones, 3))
    tr = rng.standard_normal((4, 3))
    np.savez(tmp_path / "m.npz", rotations=rot, translation=tr, fps=25.0)
    m = drape.read_motion(tmp_path / "m.npz", body, frames=3)
    assert len(m) == 3 and m.fps == 25.0
    np.testing.assert_allclose(m.rotations.numpy(), rot[:3], rtol=1e-6)


def _write_obj(path, v, f):
    lines = [f"v {a} {b} {c}" for a, b, c in v] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f]
    path.write_text("\n".join(lines) + "\n")


def test_non_manifold_garment_file(capsys, tmp_path):
    # three triangles on one edge, far from the body
    v = np.array([[0, 0, 3.0], [1, 0, 3], [0.5, 1, 3], [0.5, -1, 3], [0.5, 0, 4]])
    f = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    _write_obj(tmp_path / "g.obj", v, f)
    line = _fails(capsys, ["--garment-file", str(tmp_path / "g.obj"), "-o", str(tmp_path / "o")])
    assert "g.obj" in line and "manifold" in line


def test_garment_inside_the_body(capsys, tmp_path):
    body = AnnyBody.load()
    rv, rj = body.rest()
    centre = rj[0, body.bone_names.index("spine03")].double().numpy()
    # a small octahedron around a spine joint: inside the torso
    v = centre + 0.02 * np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1],
                                  [0, 0, -1.0]])
    f = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5],
                  [0, 3, 5]])
    _write_obj(tmp_path / "in.obj", v, f)
    line = _fails(capsys, ["--garment-file", str(tmp_path / "in.obj"),
                           "-o", str(tmp_path / "o")])
    assert "inside" in line


def test_skin_garment_matches_body_skinning():
    """Dense-weight skinning of body vertices reproduces the body's own posing."""
    from draping.motion import generate
    from draping.skinning import dense_body_weights

    body = AnnyBody.load(dtype=torch.float64)
    mot = generate("arms", body, 3)
    posed = body.pose(None, mot.rotations, mot.translation)
    w = dense_body_weights((body.skin_indices.numpy(), body.skin_weights.numpy()),
                           body.num_vertices, body.num_bones)
    idx = np.arange(0, body.num_vertices, 97)
    out = drape.skin_garment(posed.rest_vertices[0, idx].numpy(), w[idx], posed.transforms)
    torch.testing.assert_close(out, posed.vertices[:, idx], atol=1e-9, rtol=0)


# ------------------------------------------------------------------ the pipeline (slow)


@pytest.fixture(scope="module")
def small_scene_parts(tmp_path_factory):
    """A coarse T-shirt (1000 vertices) and the body, made once."""
    from draping.garments import garment

    body = AnnyBody.load(dtype=torch.float64)
    g = garment("tshirt", body, None, n_vertices=1000, seed=0)
    return body, g


@pytest.mark.slow
def test_tight_tshirt_leaves_no_penetration(small_scene_parts):
    """A T-shirt whose rest size is 8 % smaller than its template hugs the body: no vertex ends
    inside it."""
    from draping import physics
    from draping.collision import MeshQuery
    from draping.metrics import collision_error
    from draping.reference import drape_static

    body, g = small_scene_parts
    rv = body.rest_vertices.double()
    c = g.vertices.mean(0)
    tight = physics.rest_state(c + 0.92 * (g.vertices - c), g.faces)
    q = MeshQuery(rv, body.faces)
    res = drape_static(tight, torch.from_numpy(g.vertices), q)
    d = q.query(res.x).distance
    # tension pulls it onto the skin: it ends closer than it started ...
    assert float(q.query(torch.from_numpy(g.vertices)).distance.mean()) > float(d.mean())
    # ... yet no vertex inside the body
    assert float(collision_error(d)) == 0.0
    assert float(d.min()) > -1e-3


@pytest.mark.slow
def test_pipeline_and_resume_give_identical_outputs(tmp_path, small_scene_parts):
    from draping.garments import save_garment
    from polygeo.io import read_mesh

    body, g = small_scene_parts
    path = tmp_path / "coarse.ply"
    from polygeo.io import write_ply

    write_ply(path, g.vertices, g.faces, precision="double")
    save_garment(tmp_path / "coarse.npz", g)
    job = drape.DrapeJob(garment_file=str(path), motion="walk", frames=3)
    full = drape.run_drape(job, tmp_path / "full", quiet=True, pictures=True, body=body)
    s = json.loads((tmp_path / "full" / "metrics.json").read_text())
    assert len(s["per_frame"]) == 3 and s["frames"] == 3
    for key in ("eps_e", "eps_a", "eps_c", "energy", "seconds"):
        assert key in s["mean"] and key in s["per_frame"][0]
    assert s["max"]["eps_c"] <= 0.5 and s["max"]["eps_e"] <= 3.0
    for t in range(3):
        assert (tmp_path / "full" / "meshes" / f"{t:06d}.ply").is_file()
        assert (tmp_path / "full" / "body" / f"{t:06d}.ply").is_file()
    assert (tmp_path / "full" / "strip.png").stat().st_size > 0
    assert (tmp_path / "full" / "drape.gif").stat().st_size > 0

    class Stop(Exception):
        pass

    def stop_after_1(fr):
        if fr.frame == 1:
            raise Stop

    with pytest.raises(Stop):
        drape.run_drape(job, tmp_path / "cut", quiet=True, pictures=False, body=body,
                        on_frame=stop_after_1)
    assert not (tmp_path / "cut" / "meshes" / "000002.ply").exists()
    again = drape.run_drape(job, tmp_path / "cut", quiet=True, pictures=False, body=body)
    assert again.resumed_at == 2
    for t in range(3):
        a = read_mesh(tmp_path / "full" / "meshes" / f"{t:06d}.ply").points
        b = read_mesh(tmp_path / "cut" / "meshes" / f"{t:06d}.ply").points
        np.testing.assert_array_equal(a, b)
    for ra, rb in zip(full.rows, again.rows):
        assert ra["energy"] == rb["energy"] and ra["eps_c"] == rb["eps_c"]
    # other settings in the same folder: refused with a clear message
    other = drape.DrapeJob(garment_file=str(path), motion="walk", frames=4)
    with pytest.raises(ValueError, match="other settings"):
        drape.run_drape(other, tmp_path / "cut", quiet=True, pictures=False, body=body)


def test_plugins_are_registered():
    from importlib.metadata import entry_points

    commands = {e.name: e.value for e in entry_points(group="polygeo.commands")}
    parts = {e.name: e.value for e in entry_points(group="polygeo.demo")}
    assert commands.get("drape-reference") == "draping.cli:register"
    assert parts.get("drape") == "draping.cli:demo"


@pytest.mark.slow
def test_demo_part_prints_its_metric_table(capsys, tmp_path):
    import argparse

    from draping.cli import DEMO_FRAMES, demo

    assert demo(argparse.Namespace(out=str(tmp_path), quiet=True)) == 0
    out = capsys.readouterr().out
    assert "eps_c(%)" in out and "mean" in out
    s = json.loads((tmp_path / "drape" / "metrics.json").read_text())
    assert s["frames"] == DEMO_FRAMES
