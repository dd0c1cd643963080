"""FNOpt: a resolution-agnostic, meta-learned cloth optimiser built on a Fourier neural operator.

``cloth`` (grid sheet, energies, backward Euler), ``handles`` (trajectories),
``step_problem`` (one time step as an optimisation problem), ``preconditioners`` (DCT
preconditioners), ``classical`` (GD/Adam/L-BFGS/PCG, converged reference), ``rollouts``
(``solvers`` re-exports these four), ``model`` (FNO, Algorithm 2),
``train`` (data-pool meta-training), ``simulate`` (rollouts, metrics, files), ``cli``
(``polygeo train-fnopt``, ``polygeo simulate``).
"""
