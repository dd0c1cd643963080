"""`polygeo --help`, a sub-command's --help and argument errors import no heavy module."""

import subprocess
import sys

import pytest

CODE = """
import sys
from polygeo.cli import main
try:
    rc = main({argv!r})
except SystemExit as exc:
    rc = exc.code
heavy = sorted(m for m in ("torch", "numba", "scipy", "sft", "draping", "trimesh")
               if m in sys.modules)
print("HEAVY", heavy, "RC", rc)
"""


@pytest.mark.parametrize("argv, rc", [(["--help"], 0), (["jets", "--help"], 0),
                                      (["polyfit", "--bogus"], 2), (["bench", "--help"], 0)])
def test_help_and_argument_errors_stay_light(argv, rc):
    out = subprocess.run([sys.executable, "-c", CODE.format(argv=argv)], capture_output=True,
                         text=True, check=True).stdout
    assert f"HEAVY [] RC {rc}" in out, out


PLUGIN = CODE.replace('("torch", "numba", "scipy", "sft", "draping", "trimesh")',
                      '("torch", "numba", "scipy", "trimesh", "pyvista", "cv2")')


@pytest.mark.parametrize("argv, rc", [
    (["sft", "--help"], 0), (["sft", "--bogus"], 2), (["train-stn", "--help"], 0),
    (["drape", "--help"], 0), (["drape", "--bogus"], 2), (["train-drape", "--help"], 0),
    (["drape-reference", "--help"], 0), (["demo", "--help"], 0),
    (["train-fnopt", "--help"], 0), (["simulate", "--help"], 0), (["simulate", "--bogus"], 2),
])
def test_plugin_help_and_argument_errors_import_no_torch(argv, rc):
    # the plug-ins (sft, draping) may import their own light modules, never torch or numba:
    # `--help` and a mistyped option answer in a fraction of a second
    out = subprocess.run([sys.executable, "-c", PLUGIN.format(argv=argv)], capture_output=True,
                         text=True, check=True).stdout
    assert f"HEAVY [] RC {rc}" in out, out


def test_top_level_help_lists_every_command(capsys):
    from importlib.metadata import entry_points

    from polygeo.cli import main

    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    for ep in entry_points(group="polygeo.commands"):
        assert f"  {ep.name} " in out
