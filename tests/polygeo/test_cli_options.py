import numpy as np
import pytest

from polygeo.cli import int_or_auto, main


@pytest.mark.parametrize(
    "value, kw, expected",
    [("auto", {}, "auto"), (" auto ", {}, "auto"), ("12", {}, 12), ("-3", {}, -3), (" 7", {}, 7),
     (4, {}, 4), ("6", {"low": 1, "high": 6}, 6), ("1", {"low": 1}, 1)],
)
def test_int_or_auto_accepts(value, kw, expected):
    assert int_or_auto(value, "order", **kw) == expected


@pytest.mark.parametrize(
    "value, kw, msg",
    [
        ("many", {}, r"--k: expected an integer or 'auto', got 'many'"),
        ("2.5", {}, "expected an integer or 'auto'"),
        ("", {}, "expected an integer or 'auto'"),
        ("Auto", {}, "expected an integer or 'auto'"),
        (True, {}, "expected an integer or 'auto'"),
        ("7", {"low": 1, "high": 6}, r"expected an integer in \[1, 6\] or 'auto', got '7'"),
        ("0", {"low": 1}, r"expected an integer in \[1, inf\]"),
        (-1, {"high": -2}, r"expected an integer in \[-inf, -2\]"),
    ],
)
def test_int_or_auto_refuses(value, kw, msg):
    name = "k" if "--k" in msg else "max_tilt"
    with pytest.raises(ValueError, match=msg):
        int_or_auto(value, name, **kw)


def test_int_or_auto_names_the_flag_with_dashes():
    with pytest.raises(ValueError, match="--max-tilt: "):
        int_or_auto("x", "max_tilt")


def test_polyfit_bad_order_is_a_clean_error(tmp_path, capsys):
    src = tmp_path / "p.npy"
    np.save(src, np.random.default_rng(0).normal(size=(50, 3)))
    assert main(["polyfit", str(src), "-o", str(tmp_path / "o.npz"), "--order", "9"]) == 2
    assert "--order: expected an integer in [1, 6] or 'auto', got '9'" in capsys.readouterr().err
