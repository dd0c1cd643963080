"""Small FNOpt step problems shared by the FNOpt test modules (not a test module itself).

Imported as ``from fnopt_cases import random_problem``: pytest puts this folder on
``sys.path`` for the test modules in it (they form no package).
"""

from __future__ import annotations

import torch

from draping.fnopt import cloth
from draping.fnopt.cloth import Material, Sheet
from draping.fnopt.step_problem import StepProblem, make_problem

F64 = torch.float64


def random_problem(n: int = 9, dtype: torch.dtype = F64, seed: int = 0,
                   layout: str = "corners") -> StepProblem:
    """One step of an ``n x (n + 2)`` sheet near rest with random velocities, batch 1.

    Positions are the vertical rest sheet moved by 1 mm Gaussian noise, velocities 0.1 m/s
    Gaussian, the ``layout``'s handles displaced by 1 mm, damping 0.3; built in float64 from
    ``seed`` and cast to ``dtype``, so the same seed gives the same problem in either dtype.
    """
    gen = torch.Generator().manual_seed(seed)
    sheet = Sheet(n, n + 2)
    x = cloth.rest_positions(sheet, "vertical", F64)[None]
    x = x + 1e-3 * torch.randn(x.shape, generator=gen, dtype=F64)
    v = 0.1 * torch.randn(x.shape, generator=gen, dtype=F64)
    idx = cloth.handle_indices(layout, n, n + 2)
    tgt = x[:, idx[:, 0], idx[:, 1]] + 1e-3
    mat = Material(damping=0.3).tensors(1, F64)
    return make_problem(x.to(dtype), v.to(dtype), idx, tgt.to(dtype), sheet.hx, sheet.hy,
                        {k: t.to(dtype) for k, t in mat.items()})
