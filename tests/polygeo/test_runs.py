"""polygeo.runs: atomic writes, safe checkpoints, fingerprints, resume, JSONL log, progress."""

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from polygeo import runs
from polygeo.runs import (
    CheckpointError,
    JsonlLog,
    SettingsChangedError,
    atomic_write,
    atomic_write_json,
    atomic_write_text,
    fingerprint,
    load_checkpoint,
    read_jsonl,
    resume_state,
    save_checkpoint,
    truncate_jsonl,
)


class _Payload:
    """Unpickling this object writes a marker file (what a malicious checkpoint could do)."""

    def __init__(self, marker: str):
        self.marker = marker

    def __reduce__(self):
        return (Path.write_text, (Path(self.marker), "pwned"))


# --------------------------------------------------------------------------------------------
# atomic writes
# --------------------------------------------------------------------------------------------


def test_atomic_write_replaces_and_leaves_no_temporary(tmp_path):
    p = tmp_path / "sub" / "a.txt"
    atomic_write_text(p, "one")
    atomic_write_text(p, "two")
    assert p.read_text() == "two"
    assert sorted(x.name for x in p.parent.iterdir()) == ["a.txt"]


def test_atomic_write_keeps_old_file_when_the_writer_raises(tmp_path):
    p = tmp_path / "a.bin"
    p.write_bytes(b"old content")

    def bad(fh):
        fh.write(b"half of the new")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        atomic_write(p, bad)
    assert p.read_bytes() == b"old content"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["a.bin"]
    # no file at all under the final name when there was none before
    with pytest.raises(RuntimeError):
        atomic_write(tmp_path / "new.bin", bad)
    assert sorted(x.name for x in tmp_path.iterdir()) == ["a.bin"]


def test_atomic_write_json_refuses_unjsonable_without_writing(tmp_path):
    p = tmp_path / "h.json"
    atomic_write_json(p, {"a": [1, 2.5]})
    assert json.loads(p.read_text()) == {"a": [1, 2.5]}
    with pytest.raises(TypeError):
        atomic_write_json(p, {"a": object()})
    assert json.loads(p.read_text()) == {"a": [1, 2.5]}


def test_atomic_write_uses_umask_permissions(tmp_path):
    old = os.umask(0o022)
    try:
        p = atomic_write_text(tmp_path / "m.txt", "x")
    finally:
        os.umask(old)
    assert (p.stat().st_mode & 0o777) == 0o644


# --------------------------------------------------------------------------------------------
# checkpoints
# --------------------------------------------------------------------------------------------


def test_checkpoint_round_trip_with_optimizer_state(tmp_path):
    torch.manual_seed(0)
    net = torch.nn.Linear(3, 2)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    net(torch.randn(4, 3)).sum().backward()
    opt.step()
    arr = np.arange(6, dtype=np.float32).reshape(2, 3)
    tensors = {"model": net.state_dict(), "optimizer": opt.state_dict(),
               "nested": {"arr": arr, "t": torch.tensor([1.0, 2.0])}}
    meta = {"step": 7, "history": [0.5, 0.25], "name": "run"}
    p = save_checkpoint(tmp_path / "ck.pt", tensors, meta)
    t, m = load_checkpoint(p)
    assert m == meta
    assert isinstance(t["nested"]["arr"], np.ndarray)
    np.testing.assert_array_equal(t["nested"]["arr"], arr)
    for k, v in net.state_dict().items():
        assert torch.equal(t["model"][k], v)
    opt2 = torch.optim.Adam(torch.nn.Linear(3, 2).parameters(), lr=5.0)
    opt2.load_state_dict(t["optimizer"])  # integer keys, tuples (betas) survive
    assert opt2.param_groups[0]["lr"] == 1e-3
    assert opt2.param_groups[0]["betas"] == (0.9, 0.999)
    for a, b in zip(opt.state.values(), opt2.state.values()):
        assert torch.equal(a["exp_avg"], b["exp_avg"])


def test_checkpoint_with_pickled_object_is_refused_and_runs_nothing(tmp_path):
    marker = tmp_path / "marker"
    p = tmp_path / "evil.pt"
    blob = {"header": json.dumps({"format": runs.CHECKPOINT_FORMAT, "version": 1}),
            "meta": "{}", "tensors": {"w": torch.zeros(2), "x": _Payload(str(marker))}}
    torch.save(blob, p)
    with pytest.raises(CheckpointError, match="pickled objects"):
        load_checkpoint(p)
    assert not marker.exists()
    # a bare pickle of the object alone, too
    torch.save(_Payload(str(marker)), tmp_path / "bare.pt")
    with pytest.raises(CheckpointError):
        load_checkpoint(tmp_path / "bare.pt")
    assert not marker.exists()
    # the file really is harmful when loaded the unsafe way (so the test above can fail)
    torch.load(p, weights_only=False)
    assert marker.read_text() == "pwned"


def test_save_checkpoint_refuses_objects_and_bad_meta(tmp_path):
    p = tmp_path / "ck.pt"
    with pytest.raises(TypeError, match=r"tensors\['x'\]"):
        save_checkpoint(p, {"x": _Payload("never")})
    with pytest.raises(TypeError, match="meta"):
        save_checkpoint(p, {"w": torch.zeros(1)}, {"bad": object()})
    with pytest.raises(TypeError, match="tensors"):
        save_checkpoint(p, [torch.zeros(1)])
    with pytest.raises(TypeError, match="object array"):
        save_checkpoint(p, {"a": np.array([None])})
    assert not p.exists()


def test_truncated_wrong_version_and_old_checkpoints_refused(tmp_path):
    p = save_checkpoint(tmp_path / "ck.pt", {"w": torch.arange(1000.0)}, {"step": 1})
    data = p.read_bytes()
    (tmp_path / "cut.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="truncated"):
        load_checkpoint(tmp_path / "cut.pt")
    (tmp_path / "empty.pt").write_bytes(b"")
    with pytest.raises(CheckpointError, match="truncated"):
        load_checkpoint(tmp_path / "empty.pt")
    v2 = {"header": json.dumps({"format": runs.CHECKPOINT_FORMAT, "version": 2}),
          "meta": "{}", "tensors": {}}
    torch.save(v2, tmp_path / "v2.pt")
    with pytest.raises(CheckpointError, match="version 2"):
        load_checkpoint(tmp_path / "v2.pt")
    torch.save({"state_dict": {"w": torch.zeros(1)}, "step": 3}, tmp_path / "old.pt")
    with pytest.raises(CheckpointError, match="older polygeo"):
        load_checkpoint(tmp_path / "old.pt")
    with pytest.raises(FileNotFoundError):
        load_checkpoint(tmp_path / "absent.pt")
    assert issubclass(CheckpointError, ValueError)


# --------------------------------------------------------------------------------------------
# fingerprints and resume
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass
class _Inner:
    sigma: float = 1e-4
    name: str = "a"


@dataclasses.dataclass
class _Settings:
    steps: int = 100
    lr: float = 0.1 + 0.2  # a float whose repr has many digits
    widths: tuple = (32, 64)
    flag: bool = True
    inner: _Inner = dataclasses.field(default_factory=_Inner)
    extra: dict = dataclasses.field(default_factory=lambda: {"b": 1, "a": None})


@pytest.mark.slow
def test_fingerprint_stable_across_processes():
    fp = fingerprint(_Settings())
    code = (
        f"import sys; sys.path.insert(0, {str(Path(__file__).parent)!r})\n"
        "from test_runs import _Settings\n"
        "from polygeo.runs import fingerprint\n"
        "print(fingerprint(_Settings()))\n"
    )
    for seed in ("1", "2"):
        env = {**os.environ, "PYTHONHASHSEED": seed}
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                             text=True, check=True).stdout.strip()
        assert out == fp
    assert len(fp) == 16 and int(fp, 16) >= 0
    # mapping order does not matter, a dataclass hashes as its fields
    assert fingerprint({"x": 1, "y": 2}) == fingerprint({"y": 2, "x": 1})
    assert fingerprint(_Inner()) == fingerprint({"sigma": 1e-4, "name": "a"})


def test_fingerprint_sensitive_to_every_field():
    base = _Settings()
    fps = {fingerprint(base)}
    changes = {"steps": 101, "lr": 0.3, "widths": (32, 65), "flag": False,
               "inner": _Inner(sigma=1.0000000000000002e-4), "extra": {"b": 1, "a": 0}}
    assert set(changes) == {f.name for f in dataclasses.fields(_Settings)}
    for k, v in changes.items():
        fps.add(fingerprint(dataclasses.replace(base, **{k: v})))
    assert len(fps) == 1 + len(changes)
    assert fingerprint(dataclasses.replace(base, inner=_Inner(name="b"))) not in fps
    assert fingerprint({"a": 1}) != fingerprint({"a": 1.0})


def test_fingerprint_refuses_unhashable_values():
    with pytest.raises(TypeError, match=r"settings\['f'\]"):
        fingerprint({"f": lambda: 0})
    with pytest.raises(TypeError, match="str keys"):
        fingerprint({1: 2})
    assert fingerprint({"x": float("nan")}) == fingerprint({"x": float("nan")})
    assert fingerprint({"x": float("inf")}) != fingerprint({"x": float("-inf")})


def test_resume_state_only_with_same_settings(tmp_path):
    fp = fingerprint(_Settings())
    assert resume_state(tmp_path, fp) is None
    save_checkpoint(tmp_path / runs.CHECKPOINT_NAME, {"w": torch.ones(2)},
                    {"fingerprint": fp, "step": 5})
    t, m = resume_state(tmp_path, fp)
    assert m["step"] == 5 and torch.equal(t["w"], torch.ones(2))
    other = fingerprint(dataclasses.replace(_Settings(), steps=7))
    with pytest.raises(SettingsChangedError, match="settings changed"):
        resume_state(tmp_path, other)


# --------------------------------------------------------------------------------------------
# JSONL log and progress
# --------------------------------------------------------------------------------------------


def test_jsonl_log_appends_and_ignores_a_torn_last_line(tmp_path):
    p = tmp_path / "log.jsonl"
    with JsonlLog(p) as log:
        log.append({"step": 1, "loss": 0.5})
        log.append({"step": 2, "loss": 0.25})
        assert log.read() == [{"step": 1, "loss": 0.5}, {"step": 2, "loss": 0.25}]
    with open(p, "ab") as fh:
        fh.write(b'{"step": 3, "lo')  # killed mid-write
    assert read_jsonl(p) == [{"step": 1, "loss": 0.5}, {"step": 2, "loss": 0.25}]
    with JsonlLog(p) as log:  # reopening cuts the torn line; the next record is whole
        log.append({"step": 3})
    assert [r["step"] for r in read_jsonl(p)] == [1, 2, 3]
    with pytest.raises(ValueError, match="closed"):
        log.append({"step": 4})
    with pytest.raises(TypeError):
        JsonlLog(tmp_path / "b.jsonl").append({"x": object()})
    p.write_text('{"a": 1}\nnot json\n{"a": 2}\n')
    with pytest.raises(ValueError, match="line 2"):
        read_jsonl(p)
    assert read_jsonl(tmp_path / "absent.jsonl") == []


def test_truncate_jsonl_drops_what_keep_rejects(tmp_path):
    p = tmp_path / "log.jsonl"
    with JsonlLog(p) as log:
        for step in range(5):
            log.append({"step": step})
    with open(p, "ab") as fh:
        fh.write(b'{"step": 5, "lo')  # killed mid-write after the checkpoint at step 3
    assert truncate_jsonl(p, lambda r: r["step"] < 3) == 2
    assert read_jsonl(p) == [{"step": 0}, {"step": 1}, {"step": 2}]
    assert p.read_bytes().endswith(b"\n")  # the torn line is gone with the dropped ones
    before = p.stat().st_mtime_ns
    assert truncate_jsonl(p, lambda r: True) == 0
    assert p.stat().st_mtime_ns == before  # nothing dropped, nothing torn: not rewritten
    assert truncate_jsonl(p, lambda r: False) == 3 and read_jsonl(p) == []
    assert truncate_jsonl(tmp_path / "absent.jsonl", lambda r: False) == 0
    assert not (tmp_path / "absent.jsonl").exists()
    with pytest.raises(TypeError, match="keep must be callable"):
        truncate_jsonl(p, 3)


def test_progress_quiet_and_counts(capsys):
    bar = runs.progress(range(5), desc="x", quiet=True)
    assert list(bar) == [0, 1, 2, 3, 4]
    bar.set_postfix(loss=1.0)
    bar.close()
    assert capsys.readouterr().err == ""
    bar = runs.progress(range(3), desc="shown", quiet=False)
    assert list(bar) == [0, 1, 2]
    bar.close()
    assert "shown" in capsys.readouterr().err
    bar = runs.progress(range(3), desc="auto", quiet=None)  # captured stderr: not a TTY
    assert list(bar) == [0, 1, 2]
    bar.close()
    assert "auto" not in capsys.readouterr().err


def test_record_path_names_files_without_the_machines_paths(tmp_path, monkeypatch):
    from polygeo.runs import record_path

    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    repo = tmp_path / "repo"
    assert record_path(repo / "draping" / "data" / "m.pt", repo) == "draping/data/m.pt"
    assert record_path(tmp_path / "home" / ".cache" / "m.pt", repo) == "~/.cache/m.pt"
    assert record_path("/scratch/run7/seed1/model.pt", repo) == ".../seed1/model.pt"
    assert record_path("/scratch/run7/../run8/model.pt") == ".../run8/model.pt"  # normalised
    # relative paths and words that are not paths are left alone; a repo path's prefix is not
    # taken for the repo
    assert record_path("RUN/model.pt", repo) == "RUN/model.pt"
    assert record_path("--steps") == "--steps"
    assert record_path(str(repo) + "-old/m.pt", repo) == ".../repo-old/m.pt"


def test_record_command_maps_paths_inside_options_and_lists(tmp_path, monkeypatch):
    from polygeo.runs import record_command

    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    words = ["--candidates", "shipped,/scratch/s1/model.pt", f"--out={tmp_path}/repo/res",
             "--shape", "age=0.66,gender=0.8", "-o", "/scratch/run/OUT", "--steps", "800"]
    got = record_command(words, tmp_path / "repo")
    assert got == ("--candidates shipped,.../s1/model.pt --out=res --shape age=0.66,gender=0.8"
                   " -o .../run/OUT --steps 800")
    assert record_command([]) == ""
