"""Every option of the core and PolySfT commands says what it means and what its default is.

The parsers are read as argparse builds them (not a stored copy of the help): each action's
help, as the sub-command's formatter expands it (``ArgumentDefaultsHelpFormatter`` adds the
default itself), must have text, and an option that is neither required nor an on/off flag
must state its default.
"""

import argparse
import re

import pytest

from polygeo.cli import build_parser, main

#: Commands whose help this test holds to the rule: every registered one.
COMMANDS = ("jets", "polyfit", "sft", "train-stn", "demo", "bench", "drape-reference", "drape",
            "train-drape", "simulate", "train-fnopt")

_FLAGS = (argparse._StoreTrueAction, argparse._StoreFalseAction, argparse._StoreConstAction,
          argparse._HelpAction, argparse._VersionAction)


def _subparsers():
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices


def _expanded_help(sp: argparse.ArgumentParser, action: argparse.Action) -> str:
    fmt = sp._get_formatter()
    text = fmt._get_help_string(action) or ""
    return fmt._expand_help(action) if "%(" in text else text


def _problems(sp: argparse.ArgumentParser) -> list[str]:
    out = []
    for a in sp._actions:
        if isinstance(a, (argparse._HelpAction, argparse._VersionAction)):
            continue
        name = "/".join(a.option_strings) or a.dest
        text = _expanded_help(sp, a).strip()
        if not text:
            out.append(f"{name}: no help text")
            continue
        stated = re.search(r"\bdefault\b", text, re.IGNORECASE)
        if a.option_strings and not a.required and not isinstance(a, _FLAGS) and not stated:
            out.append(f"{name}: no default stated ({a.default!r}): {text!r}")
    return out


@pytest.mark.parametrize("command", COMMANDS)
def test_every_option_has_a_meaning_and_a_default(command):
    choices = _subparsers()
    assert command in choices
    assert _problems(choices[command]) == []


def test_the_rule_catches_a_bare_option():
    p = argparse.ArgumentParser()
    p.add_argument("--a", type=int, default=3, help="a count")  # default not stated
    p.add_argument("--b", default=None)  # no help at all
    p.add_argument("--c", default=1.0, help="a factor (default 1)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    found = _problems(p)
    assert len(found) == 2 and found[0].startswith("--a: no default") and "--b" in found[1]
    q = argparse.ArgumentParser(formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    q.add_argument("--a", type=int, default=3, help="a count")  # the formatter states it
    assert _problems(q) == []


def test_units_and_meanings_the_issue_asked_for(capsys):
    choices = _subparsers()
    polyfit = {a.dest: a.help for a in choices["polyfit"]._actions}
    assert "count of patches" in polyfit["patches"] and "units" in polyfit["patches"]
    sft = {a.dest: _expanded_help(choices["sft"], a) for a in choices["sft"]._actions}
    assert "pixels^2" in sft["sigma"] and "degrees" in sft["max_tilt"]
    assert "radians" in sft["lr_rigid"] and "default: 0.001" in sft["lr_rigid"]
    # polygeo bench lists its benchmarks, with and without --help
    assert main(["bench"]) == 0
    listed = capsys.readouterr().out
    for name in ("jets", "polyfit", "render", "sft"):
        assert f"  {name} " in listed
    assert "run_env" not in listed  # the shared record helper is not a benchmark


def test_top_level_help_describes_every_registered_command(capsys):
    from importlib.metadata import entry_points

    assert main(["--help"]) == 0
    listed = capsys.readouterr().out
    names = {ep.name for ep in entry_points(group="polygeo.commands")}
    assert {"jets", "sft", "drape", "simulate"} <= names
    assert names == set(COMMANDS)  # every command is also held to the option rule above
    for name in names:
        line = next(ln for ln in listed.splitlines() if ln.strip().startswith(name + " "))
        assert "plug-in" not in line, line  # a one-line description, not the module's name
