"""The step problem, classical inner optimisers, preconditioners and rollouts, by one name.

Re-exports, so that ``draping.fnopt.solvers.X`` keeps working; each name has its home in
:mod:`~draping.fnopt.step_problem` (:class:`StepProblem`, :func:`make_problem`,
:func:`subspace_solve`), :mod:`~draping.fnopt.preconditioners` (the DCT preconditioners and
the normal directions), :mod:`~draping.fnopt.classical` (GD, Adam, L-BFGS, PGD, PCG, the
converged reference, ``CLASSICAL``, ``REFERENCE_TOL``) or :mod:`~draping.fnopt.rollouts`
(:class:`Rollout`, :func:`rollout`).
"""

from __future__ import annotations

from .classical import (
    CLASSICAL,
    REFERENCE_TOL,
    solve_adam,
    solve_gd,
    solve_lbfgs,
    solve_lbfgs_wolfe,
    solve_pcg,
    solve_pgd,
    solve_reference,
)
from .handles import DT  # noqa: F401  (was importable from here; tests use solvers.DT)
from .preconditioners import (
    laplace_preconditioner,
    low_modes,
    normal_directions,
    normal_preconditioner,
)
from .rollouts import Rollout, rollout
from .step_problem import StepProblem, make_problem, subspace_solve

__all__ = ["StepProblem", "make_problem", "laplace_preconditioner", "normal_preconditioner",
           "low_modes", "normal_directions", "solve_pgd", "solve_pcg",
           "subspace_solve", "solve_gd", "solve_adam", "solve_lbfgs", "solve_lbfgs_wolfe",
           "solve_reference",
           "Rollout", "rollout", "CLASSICAL", "REFERENCE_TOL"]
