"""Tests of polygeo.status: the codes are stable (they are written into result files)."""

import numpy as np

from polygeo.status import Status, describe


def test_codes_are_stable_and_distinct():
    # the integers are part of the file formats (status columns of NPZ/PLY/CSV results)
    want = {
        "OK": 0,
        "NONFINITE_INPUT": 1,
        "TOO_FEW_POINTS": 2,
        "ORDER_REDUCED": 3,
        "DEGENERATE": 4,
        "ILL_CONDITIONED": 5,
        "NOT_A_GRAPH": 6,
        "NON_MANIFOLD": 7,
    }
    assert {s.name: int(s) for s in Status} == want


def test_describe_known_codes_any_integer_type():
    assert describe(0) == "ok"
    assert describe(Status.TOO_FEW_POINTS) == "too few points"
    assert describe(np.int64(6)) == "not a graph"
    assert describe(np.array(3)) == "order reduced"


def test_describe_unknown_code_is_answered():
    assert describe(99) == "unknown status 99"
    assert describe(-1) == "unknown status -1"


def test_status_compares_with_integer_arrays():
    status = np.array([0, 2, 2, 4])
    assert (status == Status.TOO_FEW_POINTS).sum() == 2
    assert (status != Status.OK).sum() == 3
