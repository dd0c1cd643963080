"""sft.cli: one option per settings field, each documented with its default."""

import argparse

import pytest

from sft.cli import _HIDDEN, OPTION_HELP, _settings_from, register
from sft.settings import SfTSettings, field_defaults, flat_fields


def _parser():
    ap = argparse.ArgumentParser(prog="polygeo")
    register(ap.add_subparsers(dest="command"))
    return ap


def test_every_setting_is_an_option_with_its_meaning_and_default(capsys):
    exposed = [n for n in flat_fields() if n not in _HIDDEN]
    assert sorted(OPTION_HELP) == sorted(exposed)
    with pytest.raises(SystemExit):
        _parser().parse_args(["sft", "--help"])
    text = " ".join(capsys.readouterr().out.split())  # undo argparse's line wrapping
    defaults = field_defaults()
    for name in exposed:
        assert "--" + name.replace("_", "-") in text, name
        shown = defaults[name]
        shown = ",".join(map(str, shown)) if isinstance(shown, list) else shown
        assert f"(default: {shown if shown != '' else 'none'})" in text, name


def test_options_become_nested_settings():
    args = _parser().parse_args([
        "sft", "seq", "-o", "out", "--order", "auto", "--patches", "3", "--rgb-weight", "0.5",
        "--freeze", "d_uv,rot", "--keep-best", "false", "--background", "0.1,0.2,0.3",
        "--sigma", "0.2", "--quiet", "--max-iterations", "7"])
    st = _settings_from(args)
    want = SfTSettings.from_flat(order="auto", patches=3, rgb_weight=0.5, freeze=("d_uv", "rot"),
                                 keep_best=False, background=(0.1, 0.2, 0.3), sigma=0.2,
                                 quiet=True, max_iterations=7)
    assert st == want
    assert _settings_from(_parser().parse_args(["sft", "seq", "-o", "out"])) == SfTSettings()
    with pytest.raises(SystemExit):  # argparse refuses a malformed bool
        _parser().parse_args(["sft", "seq", "-o", "out", "--keep-best", "maybe"])
