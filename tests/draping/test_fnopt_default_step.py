"""FNOpt's default step: the two-level coarse direction from the second inner iteration.

``SimSettings`` / ``polygeo simulate --optimizer fnopt`` resolve ``coarse``, ``coarse_every`` and
``coarse_from`` to ``FNOPT_COARSE`` / ``FNOPT_COARSE_EVERY`` / ``FNOPT_COARSE_FROM`` for FNOpt and
to off for every other optimiser. Truths: the settings' step equals ``solve_fnopt`` called with
those values, frame after frame with one memory, bit for bit; ``--coarse 0`` is the one-level
solve; the benchmark's ``fnopt-2l`` row is the same step; bad values raise naming the field.
"""

from __future__ import annotations

import pytest
import torch
from fnopt_cases import random_problem, tiny_fno

from draping.fnopt import model
from draping.fnopt.settings import (
    COARSE_EVERY,
    FNOPT_COARSE,
    FNOPT_COARSE_EVERY,
    FNOPT_COARSE_FROM,
)
from draping.fnopt.simulate import SimSettings, step_function


def test_defaults_resolve_per_optimizer():
    s = SimSettings()
    assert (s.coarse, s.coarse_every, s.coarse_from) == \
        (FNOPT_COARSE, FNOPT_COARSE_EVERY, FNOPT_COARSE_FROM)
    assert FNOPT_COARSE >= 2 and FNOPT_COARSE_EVERY >= 1 and FNOPT_COARSE_FROM >= 1
    for name in ("gd", "adam", "lbfgs", "pcg", "reference"):
        s = SimSettings(optimizer=name)
        assert (s.coarse, s.coarse_every, s.coarse_from) == (0, COARSE_EVERY, 0), name
    off = SimSettings(coarse=0)
    assert (off.coarse, off.coarse_from) == (0, 0)
    # the reference rollout's cache key does not depend on the inner solver's options
    assert off.key() == SimSettings().key() == SimSettings(optimizer="pcg", coarse=8).key()


def test_default_step_is_the_two_level_solve_from_iteration_one():
    """Over three frames (one memory, so the coarse space is kept for ``FNOPT_COARSE_EVERY``
    frames) the default settings' step is ``solve_fnopt(two_level=FNOPT_COARSE,
    two_level_every=FNOPT_COARSE_EVERY, two_level_from=FNOPT_COARSE_FROM)`` bit for bit on a
    grid finer than the coarse one; it differs from the one-level solve and from the coarse
    direction on every iteration; ``coarse=0`` is the one-level solve."""
    net = tiny_fno(normal=True)
    n = FNOPT_COARSE + 6
    probs = [random_problem(n, torch.float32, seed, layout="diagonal") for seed in (4, 5, 6)]
    step, mem = step_function(SimSettings(res=(n, n), iters=3), net), {}
    for p in probs:
        want = model.solve_fnopt(net, p, 3, memory=mem, two_level=FNOPT_COARSE,
                                 two_level_every=FNOPT_COARSE_EVERY,
                                 two_level_from=FNOPT_COARSE_FROM)
        assert torch.equal(step(p, None), want)
    p = probs[0]
    got = step_function(SimSettings(res=(n, n), iters=3), net)(p, None)
    assert not torch.equal(got, model.solve_fnopt(net, p, 3))
    assert not torch.equal(got, model.solve_fnopt(net, p, 3, two_level=FNOPT_COARSE))
    off = step_function(SimSettings(res=(n, n), iters=3, coarse=0), net)
    assert torch.equal(off(p, None), model.solve_fnopt(net, p, 3))
    every = step_function(SimSettings(res=(n, n), iters=3, coarse_from=0), net)
    assert torch.equal(every(p, None), model.solve_fnopt(net, p, 3, two_level=FNOPT_COARSE))


def test_bad_coarse_fields_raise():
    with pytest.raises(ValueError, match="coarse_from"):
        SimSettings(coarse_from=-1)
    with pytest.raises(TypeError, match="coarse_from"):
        SimSettings(coarse_from=1.5)
    with pytest.raises(ValueError, match="coarse_from"):
        SimSettings(coarse=0, coarse_from=1)
    with pytest.raises(ValueError, match="coarse_from"):
        SimSettings(optimizer="pcg", coarse=8, coarse_from=1)
    with pytest.raises(ValueError, match="coarse"):
        SimSettings(optimizer="gd", coarse=FNOPT_COARSE)
    with pytest.raises(ValueError, match="coarse_every"):
        SimSettings(coarse_every=0)


def test_cli_flags_reach_the_settings():
    """``--coarse`` / ``--coarse-every`` / ``--coarse-from`` default to None (the optimiser's
    default) and are passed through."""
    import argparse

    from draping.fnopt.cli import register_simulate

    ap = argparse.ArgumentParser()
    register_simulate(ap.add_subparsers())
    a = ap.parse_args(["simulate", "-o", "X"])
    assert (a.coarse, a.coarse_every, a.coarse_from) == (None, None, None)
    a = ap.parse_args(["simulate", "-o", "X", "--coarse", "0"])
    s = SimSettings(coarse=a.coarse, coarse_every=a.coarse_every, coarse_from=a.coarse_from)
    assert (s.coarse, s.coarse_from) == (0, 0)
    a = ap.parse_args(["simulate", "-o", "X", "--coarse", "8", "--coarse-every", "2",
                       "--coarse-from", "3"])
    assert (a.coarse, a.coarse_every, a.coarse_from) == (8, 2, 3)


def test_benchmark_default_row_is_the_default_step(script):
    common = script("benchmarks/bm_fnopt_common.py")

    net = tiny_fno(normal=True)
    n = FNOPT_COARSE + 2
    probs = [random_problem(n, torch.float32, seed, layout="corners") for seed in (7, 8)]
    row = common._step(common.FNOPT_DEFAULT_ROW, 3, net)
    step = step_function(SimSettings(res=(n, n), iters=3), net)
    for p in probs:
        assert torch.equal(row(p, None), step(p, None))
