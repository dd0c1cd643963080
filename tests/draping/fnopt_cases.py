"""Small FNOpt step problems shared by the FNOpt test modules (not a test module itself).

Imported as ``from fnopt_cases import random_problem``: pytest puts this folder on
``sys.path`` for the test modules in it (they form no package).
"""

from __future__ import annotations

from dataclasses import fields

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


class QuadraticProblem(StepProblem):
    """``L(a) = 1/2 a^T A a - b^T a`` on the free vertices of a step problem (float64).

    ``A``: the inertia ``m dt^2`` plus grid-edge springs ``k`` that couple the three coordinates
    through a 3x3 SPD matrix ``coupling`` (the identity: isotropic springs); ``b``: a load.
    Set by :func:`quadratic_problem`.
    """

    def loss(self, a: torch.Tensor) -> torch.Tensor:
        a = self.compose(a)
        m = self.mass[..., None] * self.dt * self.dt
        du = a[:, 1:] - a[:, :-1]
        dv = a[:, :, 1:] - a[:, :, :-1]
        springs = ((du @ self.coupling) * du).sum((1, 2, 3)) + \
            ((dv @ self.coupling) * dv).sum((1, 2, 3))
        return 0.5 * (m * a * a).sum((1, 2, 3)) + 0.5 * self.k * springs - \
            (self.b * a).sum((1, 2, 3))


def quadratic_problem(res=(12, 10), stiffness: float = 400.0, load: float = 10.0, seed: int = 0,
                      anisotropic: bool = True) -> QuadraticProblem:
    """A :class:`QuadraticProblem` on an ``H x W`` rest sheet with corner-centre handles.

    ``k = stiffness m dt^2``, ``b`` Gaussian times ``load m dt^2`` (``m`` the mean vertex mass);
    ``anisotropic``: the coupling is ``R diag(1, 0.02, 6) R^T`` with a random rotation ``R``
    (drawn from ``seed`` before ``b``), so the isotropic DCT preconditioner is not exact;
    otherwise the identity.
    """
    sheet = Sheet(*res)
    x = cloth.rest_positions(sheet, dtype=F64)[None]
    idx = cloth.handle_indices("corner-centre", *res)
    p = make_problem(x, torch.zeros_like(x), idx, x[:, idx[:, 0], idx[:, 1]], sheet.hx,
                     sheet.hy, Material().tensors(1, F64))
    q = QuadraticProblem(**{f.name: getattr(p, f.name) for f in fields(p)})
    g = torch.Generator().manual_seed(seed)
    q.coupling = torch.eye(3, dtype=F64)
    if anisotropic:
        rot = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=F64))[0]
        q.coupling = rot @ torch.diag(torch.tensor([1.0, 0.02, 6.0], dtype=F64)) @ rot.T
    q.k = float(p.mass.mean()) * p.dt ** 2 * stiffness
    q.b = torch.randn(x.shape, generator=g, dtype=F64) * float(p.mass.mean()) * p.dt ** 2 * load
    return q


#: Training settings of a tiny pool (8x8 sheets, 4 entries) for the training-loop tests.
TINY_TRAIN = dict(width=4, modes=2, layers=1, projection=8, res=8, pool=4, batch=2, steps=0,
                  inner_min=2, inner_max=3, max_frames=40, eval_every=3, checkpoint_every=3,
                  seed=3)


def tiny_fno(normal: bool = True, zero: bool = False):
    """A seeded 4-wide, 1-layer FNO (``normal``: with the normal directions, split 2); ``zero``:
    every parameter 0, so its proposal is exactly 0. The global RNG is left as it was."""
    from draping.fnopt import model

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        net = model.FNO(model.FNOConfig(4, 2, 1, 8, normal, 2 if normal else 0))
    if zero:
        with torch.no_grad():
            for q in net.parameters():
                q.zero_()
    return net


def tiny_pool(seed: int = 0):
    """A :data:`TINY_TRAIN` pool whose sheets are 0.3 s into their motion (handles moving)."""
    from draping.fnopt.train import Pool, TrainSettings

    pool = Pool(TrainSettings(**TINY_TRAIN), torch.Generator().manual_seed(seed))
    pool.t[:] = 0.3
    return pool
