"""FNOpt: a resolution-agnostic, meta-learned cloth optimiser built on a Fourier neural operator.

``cloth`` (grid sheet, energies, backward Euler), ``handles`` (trajectories), ``solvers``
(step problem, GD/Adam/L-BFGS, converged reference, rollouts), ``model`` (FNO, Algorithm 2),
``train`` (data-pool meta-training), ``simulate`` (rollouts, metrics, files), ``cli``
(``polygeo train-fnopt``, ``polygeo simulate``).
"""
