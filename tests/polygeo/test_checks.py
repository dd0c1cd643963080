"""Tests of polygeo.checks: every validator accepts good input and refuses bad input with a
message that names the argument."""

import numpy as np
import pytest
import torch

from polygeo import checks
from polygeo.checks import (
    as_tensor,
    check_choice,
    check_faces,
    check_finite,
    check_int,
    check_mask,
    check_positive,
    check_shape,
    is_numpy_like,
    to_like,
)


def test_all_names_exist():
    for name in checks.__all__:
        assert callable(getattr(checks, name))


# ---------------------------------------------------------------------------- as_tensor


def test_as_tensor_numpy_float_keeps_dtype_and_memory():
    a = np.arange(6, dtype=np.float32).reshape(2, 3)
    t = as_tensor(a, "x")
    assert t.dtype == torch.float32
    a[0, 0] = 7.0
    assert float(t[0, 0]) == 7.0  # shares memory: no copy of a writeable float array


def test_as_tensor_ints_become_float64_unless_not_floating():
    assert as_tensor([1, 2, 3], "x").dtype == torch.float64
    assert as_tensor(np.array([1, 2], np.int32), "x", floating=False).dtype == torch.int32
    assert as_tensor(np.float16(1.5), "x").dtype == torch.float32


def test_as_tensor_dtype_and_device():
    t = as_tensor(torch.ones(2, dtype=torch.float32), "x", dtype=torch.float64, device="cpu")
    assert t.dtype == torch.float64 and t.device.type == "cpu"


@pytest.mark.parametrize(
    "bad, err",
    [
        (np.array(["a", "b"]), TypeError),
        (np.array([1.0 + 2.0j]), TypeError),
        (np.array([object(), 1], dtype=object), TypeError),
        (torch.tensor([1.0 + 1.0j]), TypeError),
        (torch.tensor([True, False]), TypeError),
    ],
)
def test_as_tensor_refuses_non_real(bad, err):
    with pytest.raises(err, match="points"):
        as_tensor(bad, "points")


def test_as_tensor_read_only_numpy_is_copied():
    a = np.ones(3)
    a.flags.writeable = False
    t = as_tensor(a, "x")
    t[0] = 5.0  # would fail or corrupt the input if the memory were shared
    assert a[0] == 1.0


# ---------------------------------------------------------------------------- check_shape


def test_check_shape_accepts_patterns():
    check_shape(torch.zeros(4, 3), "x", ("N", 3))
    check_shape(np.zeros((2, 5, 3)), "x", ("...", "N", 3))
    check_shape(torch.zeros(3, 3), "x", ("N", "N"))
    check_shape(torch.zeros(2, 7), "x", (None, 7))


@pytest.mark.parametrize(
    "shape, pattern",
    [
        ((4, 2), ("N", 3)),  # wrong fixed size
        ((4,), ("N", 3)),  # wrong number of dimensions
        ((3, 4), ("N", "N")),  # named dimension used twice with two sizes
        ((2,), ("...", "N", 3)),  # too few dimensions for the tail
    ],
)
def test_check_shape_refuses(shape, pattern):
    with pytest.raises(ValueError, match=r"vertices: expected shape .* got \(") as info:
        check_shape(torch.zeros(shape), "vertices", pattern)
    assert str(tuple(shape)) in str(info.value)


# ---------------------------------------------------------------------------- check_finite


def test_check_finite():
    check_finite(torch.zeros(3), "x")
    bad = torch.tensor([0.0, float("nan"), float("inf")])
    with pytest.raises(ValueError, match="weights: expected finite values, got 2 NaN/inf"):
        check_finite(bad, "weights")


# ---------------------------------------------------------------------------- check_positive


def test_check_positive_returns_float():
    assert check_positive(2, "sigma") == 2.0
    assert check_positive(0.0, "sigma", strict=False) == 0.0


@pytest.mark.parametrize("value", [0.0, -1.0, float("nan"), float("inf")])
def test_check_positive_refuses_values(value):
    with pytest.raises(ValueError, match="sigma: expected a finite value > 0"):
        check_positive(value, "sigma")


def test_check_positive_non_strict_refuses_negative():
    with pytest.raises(ValueError, match="gamma: expected a finite value >= 0"):
        check_positive(-1e-9, "gamma", strict=False)


def test_check_positive_refuses_types():
    with pytest.raises(TypeError, match="sigma: expected a real number"):
        check_positive("big", "sigma")


# ---------------------------------------------------------------------------- check_int


def test_check_int_accepts_integers():
    assert check_int(np.int64(3), "k", low=1) == 3
    assert check_int(torch.tensor(4), "k") == 4
    assert check_int(5, "k", low=5, high=5) == 5


@pytest.mark.parametrize("value", [2.0, True, "3", torch.tensor(1.0), None])
def test_check_int_refuses_types(value):
    with pytest.raises(TypeError, match="order: expected an integer"):
        check_int(value, "order")


@pytest.mark.parametrize("value, low, high", [(0, 1, None), (9, None, 8), (-1, 0, 4)])
def test_check_int_refuses_out_of_range(value, low, high):
    with pytest.raises(ValueError, match=rf"order: expected an integer in .* got {value}"):
        check_int(value, "order", low=low, high=high)


# ---------------------------------------------------------------------------- check_choice


def test_check_choice():
    assert check_choice("mean", "reduction", ("mean", "sum")) == "mean"
    msg = r"reduction: expected one of \['mean', 'sum'\], got 'max'"
    with pytest.raises(ValueError, match=msg):
        check_choice("max", "reduction", ("mean", "sum"))


# ---------------------------------------------------------------------------- check_faces


@pytest.mark.parametrize(
    "faces",
    [
        np.array([[0, 1, 2], [0, 2, 3]], np.int32),
        [[0, 1, 2], [0, 2, 3]],
        torch.tensor([[0, 1, 2], [0, 2, 3]], dtype=torch.int16),
    ],
)
def test_check_faces_returns_int64_tensor(faces):
    f = check_faces(faces, n_vertices=4)
    assert isinstance(f, torch.Tensor) and f.dtype == torch.int64
    assert f.tolist() == [[0, 1, 2], [0, 2, 3]]


def test_check_faces_empty_and_unbounded():
    assert check_faces(np.zeros((0, 3), np.int64), n_vertices=0).shape == (0, 3)
    assert check_faces([[5, 6, 7]]).tolist() == [[5, 6, 7]]  # no n_vertices: any index >= 0


@pytest.mark.parametrize(
    "faces", [np.zeros((2, 3)), torch.zeros(2, 3, dtype=torch.bool), np.array(["0", "1", "2"])]
)
def test_check_faces_refuses_dtype(faces):
    with pytest.raises(TypeError, match="tris: expected"):
        check_faces(faces, 4, name="tris")


@pytest.mark.parametrize("shape", [(3,), (2, 4), (1, 2, 3)])
def test_check_faces_refuses_shape(shape):
    with pytest.raises(ValueError, match=r"tris: expected shape \(F, 3\)"):
        check_faces(np.zeros(shape, np.int64), 4, name="tris")


def test_check_faces_refuses_out_of_range():
    with pytest.raises(ValueError, match=r"faces: expected vertex indices in \[0, 3\].*\[0, 4\]"):
        check_faces([[0, 1, 4]], n_vertices=4)
    with pytest.raises(ValueError, match=r"faces: expected non-negative vertex indices.*\[-1, 2\]"):
        check_faces([[0, -1, 2]])


def test_check_faces_refuses_bad_n_vertices():
    with pytest.raises(ValueError, match="n_vertices"):
        check_faces([[0, 1, 2]], n_vertices=-1)
    with pytest.raises(TypeError, match="n_vertices"):
        check_faces([[0, 1, 2]], n_vertices=3.0)


# ---------------------------------------------------------------------------- to_like


def test_is_numpy_like_and_to_like():
    assert is_numpy_like(np.zeros(2)) and is_numpy_like([1.0]) and is_numpy_like(1.0)
    assert not is_numpy_like(torch.zeros(2))
    t = torch.ones(2, requires_grad=True) * 2
    out = to_like(t, True)
    assert isinstance(out, np.ndarray) and out.tolist() == [2.0, 2.0]
    assert to_like(t, False) is t


# ---------------------------------------------------------------------------- check_mask


def test_check_mask_returns_bool_tensor():
    m = check_mask(np.array([[True, False, True]]), "mask", ("B", 3))
    assert isinstance(m, torch.Tensor) and m.dtype == torch.bool
    assert m.tolist() == [[True, False, True]]


@pytest.mark.parametrize("bad", [np.array([[1, 0, 1]]), np.array([[1.0, 0.0, 1.0]])])
def test_check_mask_refuses_non_bool(bad):
    with pytest.raises(TypeError, match="mask: expected a bool array"):
        check_mask(bad, "mask", ("B", 3))


def test_check_mask_refuses_shape():
    with pytest.raises(ValueError, match="valid"):
        check_mask(np.ones((2, 4), bool), "valid", ("B", 3))
