"""The FNO and the learned optimiser of Algorithm 2.

Spectral convolutions are written here with ``torch.fft`` (a few lines) rather than taken from
``neuraloperator``: that library pulls about 200 MB of dependencies (wandb, tensorly, h5py,
opentelemetry) and its import breaks when a broken Open3D is present; the layer below is the
same operator (truncated Fourier multiplication on the lowest ``modes`` frequencies plus a
pointwise linear path, GELU), and our grids are small enough that nothing else is needed.

Resolution independence: ``torch.fft.rfft2``/``irfft2`` with the default normalisation keep a
mode's amplitude independent of the grid size, and every input is a field in physical units
made scale-free (the residual and the previous update divided by the residual's RMS; material
numbers as dimensionless stiffness ratios), so one set of weights runs at any ``H x W``.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from torch import nn

from polygeo.checks import check_int

from . import coarse
from .cloth import positions_from_accel
from .solvers import (
    StepProblem,
    laplace_preconditioner,
    normal_directions,
    normal_preconditioner,
    subspace_solve,
)
from .step_problem import autograd_free_call
from .twolevel import coarse_correction, kept_space

__all__ = ["FNOConfig", "SpectralConv2d", "FNO", "features", "constant_features",
           "fno_correction", "fno_direction", "fno_inputs",
           "fnopt_iteration", "subspace_update", "solve_fnopt", "STEPS", "RECYCLE_MAX",
           "check_recycle", "check_fno_every", "recycled_basis", "carried_basis",
           "N_INPUTS", "load_pretrained", "n_parameters", "optimizer_step",
           "stiffness_numbers", "WEIGHTS"]

#: Input channels: preconditioned gradient (3), the previous one (3), previous update (3), mask (1),
#: three stiffness numbers (3), two grid coordinates (2).
N_INPUTS = 15


@dataclass(frozen=True)
class FNOConfig:
    """FNO hyper-parameters (thesis: 4 layers, 8 x 8 modes, width 64, projection 64).

    ``normal``: the step the weights were trained with searches the out-of-plane direction of
    :func:`draping.fnopt.solvers.normal_preconditioner` too (:func:`subspace_update`); part of
    the config because the weights are trained for one step rule (default ``False``: the
    weights recorded without the field). ``normal_split``: that direction cut into its lowest
    ``normal_split x normal_split`` DCT modes and the rest (0: one direction).
    """

    width: int = 32
    modes: int = 8
    layers: int = 4
    projection: int = 64
    normal: bool = False
    normal_split: int = 0

    def __post_init__(self) -> None:
        for k, v in asdict(self).items():
            if k == "normal_split":
                if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                    raise ValueError(f"FNOConfig.normal_split: expected an int >= 0, got {v!r}")
            elif k == "normal":
                if not isinstance(v, bool):
                    raise TypeError(f"FNOConfig.normal: expected a bool, got {v!r}")
            elif isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"FNOConfig.{k}: expected an int >= 1, got {v!r}")


class SpectralConv2d(nn.Module):
    """Truncated Fourier multiplication with learned complex ``C_in x C_out`` matrices.

    The lowest ``modes x modes`` frequencies (both signs along rows, non-negative along
    columns) are multiplied; the others are dropped.
    """

    def __init__(self, c_in: int, c_out: int, modes: int):
        super().__init__()
        self.modes = modes
        scale = 1.0 / (c_in * c_out)
        self.w = nn.Parameter(scale * torch.randn(2, c_in, c_out, modes, modes, 2))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` ``(B, C, H, W)`` -> ``(B, C_out, H, W)``.

        With gradients enabled (training) the full 2-D transforms of the trained weights' own
        run, bit for bit (``polygeo train-fnopt`` reproduces the shipped weights exactly);
        without (inference), :meth:`forward_dft`, the same operator up to float rounding.
        """
        if not torch.is_grad_enabled():
            return self.forward_dft(x)
        b, _, h, w = x.shape
        f = torch.fft.rfft2(x)
        m1, m2 = min(self.modes, h // 2), min(self.modes, w // 2 + 1)
        out = torch.zeros(b, self.w.shape[2], h, w // 2 + 1, dtype=f.dtype, device=x.device)
        wc = torch.view_as_complex(self.w)
        out[:, :, :m1, :m2] = torch.einsum("bixy,ioxy->boxy", f[:, :, :m1, :m2],
                                           wc[0, :, :, :m1, :m2])
        out[:, :, h - m1:, :m2] = torch.einsum("bixy,ioxy->boxy", f[:, :, h - m1:, :m2],
                                               wc[1, :, :, :m1, :m2])
        return torch.fft.irfft2(out, s=(h, w))

    def forward_dft(self, x: torch.Tensor, acc: torch.Tensor | None = None) -> torch.Tensor:
        """:meth:`forward` with the truncated transforms as matrix products (inference).

        Only ``2 m1 x m2`` of the ``H x (W / 2 + 1)`` Fourier coefficients are kept, so the
        transforms are dense products with cached ``(W, 2 m2)``, ``(2 m1, H)``, ``(H, 2 m1)``
        and ``(2 m2, W)`` matrices (:func:`_dft_matrices`, built in float64 per grid size)
        instead of full FFTs: equal to :meth:`forward` up to float rounding (3e-7
        relative in float32), per layer 0.47 -> 0.30 ms at 100x100, 0.19 -> 0.15 ms at 64x64
        (one thread; equal at 32x32). The column transforms' real and imaginary parts are
        interleaved, so the complex coefficients are views of the real products, not copies
        (per layer 13-15 % less time at 32-100). ``acc`` ``(B, C_out, H, W)`` (contiguous): the
        result is added into it in place by the last product and ``acc`` returned (the FNO's
        pointwise path; one buffer and one sum fewer).
        """
        b, c, h, w = x.shape
        m1, m2 = min(self.modes, h // 2), min(self.modes, w // 2 + 1)
        fw, fh, gh, bw = _dft_matrices(h, w, m1, m2, x.dtype)
        r = torch.view_as_complex(torch.matmul(x, fw).view(b, c, h, m2, 2))   # (B, C, H, m2)
        f = torch.matmul(fh, r)                                         # (B, C, 2 m1, m2)
        z = torch.matmul(gh, (f[:, :, None] * self._kept_weights(m1, m2, f.dtype)).sum(1))
        zr = torch.view_as_real(z).view(b, -1, h, 2 * m2)               # (B, C_out, H, 2 m2)
        if acc is None:
            return torch.matmul(zr, bw)
        acc.view(-1, w).addmm_(zr.view(-1, 2 * m2), bw)
        return acc

    def _kept_weights(self, m1: int, m2: int, dtype: torch.dtype) -> torch.Tensor:
        """The complex weights of the kept rows ``(C_in, C_out, 2 m1, m2)`` (inference).

        Cached per ``(m1, m2, dtype)`` and the parameter's identity and version counter, so an
        in-place change of the weights (an optimiser step, ``load_state_dict``) rebuilds it.
        """
        key = (m1, m2, dtype, self.w.data_ptr(), self.w._version)
        cache = getattr(self, "_kept", None)
        if cache is None or cache[0] != key:
            with torch.inference_mode(False):     # a normal tensor, also when built in one
                wc = torch.view_as_complex(self.w.detach()).to(dtype)
                cache = (key, torch.cat([wc[0, :, :, :m1, :m2], wc[1, :, :, :m1, :m2]], 2))
            self._kept = cache
        return cache[1]


_DFT_CACHE: dict = {}


def _dft_matrices(h: int, w: int, m1: int, m2: int, dtype: torch.dtype):
    """The truncated real/complex DFT matrices of :meth:`SpectralConv2d.forward_dft` (cached).

    ``fw`` ``(W, 2 m2)``: the cosines and minus sines of ``rfft`` along the columns (real and
    imaginary part of each kept column interleaved: column ``2 j`` and ``2 j + 1``); ``fh``
    ``(2 m1, H)``: the forward transform on the kept rows (``0 .. m1-1`` and ``H-m1 .. H-1``);
    ``gh`` ``(H, 2 m1)``: its inverse with ``1/H``; ``bw`` ``(2 m2, W)``: ``irfft`` of the
    kept columns, rows interleaved as ``fw``'s columns (``1/W``, the non-DC, non-Nyquist
    columns counted twice for their conjugates, the imaginary parts of DC and Nyquist
    ignored, as ``irfft`` does).
    """
    key = (h, w, m1, m2, dtype)
    if key not in _DFT_CACHE:
        with torch.inference_mode(False):         # normal tensors, also when built in one
            _DFT_CACHE[key] = _dft_built(h, w, m1, m2, dtype)
    return _DFT_CACHE[key]


def _dft_built(h: int, w: int, m1: int, m2: int, dtype: torch.dtype) -> tuple:
    """:func:`_dft_matrices`' four matrices ``(fw, fh, gh, bw)``, built (not cached)."""
    f64 = torch.float64
    th = 2 * math.pi * torch.outer(torch.arange(w, dtype=f64), torch.arange(m2, dtype=f64)) / w
    rows = torch.cat([torch.arange(m1), torch.arange(h - m1, h)]).to(f64)
    ph = 2 * math.pi * torch.outer(rows, torch.arange(h, dtype=f64)) / h       # (2 m1, H)
    c = torch.full((m2,), 2.0, dtype=f64)
    c[0] = 1.0
    if w % 2 == 0 and m2 - 1 == w // 2:
        c[-1] = 1.0
    cdt = torch.complex128 if dtype == f64 else torch.complex64
    return (torch.stack([torch.cos(th), -torch.sin(th)], 2).reshape(w, 2 * m2).to(dtype),
            torch.complex(torch.cos(ph), -torch.sin(ph)).to(cdt),
            (torch.complex(torch.cos(ph), torch.sin(ph)).T / h).to(cdt),
            (torch.stack([c[:, None] * torch.cos(th.T), -c[:, None] * torch.sin(th.T)], 1)
             .reshape(2 * m2, w) / w).to(dtype))


class FNO(nn.Module):
    """The Fourier neural operator.

    Lifting (1x1), ``layers`` Fourier layers (spectral + 1x1, GELU), projection (1x1, GELU,
    1x1) to 3 channels. Input ``(B, N_INPUTS, H, W)``, output ``(B, 3, H, W)``.
    """

    def __init__(self, config: FNOConfig = FNOConfig()):
        super().__init__()
        self.config = config
        c = config.width
        self.lift = nn.Conv2d(N_INPUTS, c, 1)
        self.spectral = nn.ModuleList(SpectralConv2d(c, c, config.modes)
                                      for _ in range(config.layers))
        self.pointwise = nn.ModuleList(nn.Conv2d(c, c, 1) for _ in range(config.layers))
        self.proj1 = nn.Conv2d(c, config.projection, 1)
        self.proj2 = nn.Conv2d(config.projection, 3, 1)
        nn.init.zeros_(self.proj2.bias)
        with torch.no_grad():
            self.proj2.weight.mul_(0.01)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Map features ``(B, N_INPUTS, H, W)`` to updates ``(B, 3, H, W)``.

        Without gradients (inference) the 1x1 convolutions are batched matrix products
        (:func:`_pointwise`: ``Conv2d``'s 1x1 path copied its input first), the spectral
        layers' inverse transform accumulates into the pointwise path's output
        (:meth:`SpectralConv2d.forward_dft`'s ``acc``) and the GELUs work in place: the same
        operator up to float rounding, with no fresh ``(B, width, H, W)`` buffers, whose first
        touch (page faults of freshly mapped memory) had cost 35 % / 44 % of the forward at
        64x64 / 100x100.
        """
        if torch.is_grad_enabled():
            y = self.lift(x)
            for k, (sp, pw) in enumerate(zip(self.spectral, self.pointwise)):
                y = sp(y) + pw(y)
                if k < len(self.spectral) - 1:
                    y = nn.functional.gelu(y)
            return self.proj2(nn.functional.gelu(self.proj1(y)))
        y = _pointwise(self.lift, x)
        for k, (sp, pw) in enumerate(zip(self.spectral, self.pointwise)):
            y = sp.forward_dft(y, acc=_pointwise(pw, y))
            if k < len(self.spectral) - 1:
                y = _gelu(y, True)
        return _pointwise(self.proj2, _gelu(_pointwise(self.proj1, y), True))


def _pointwise(conv: nn.Conv2d, y: torch.Tensor) -> torch.Tensor:
    """A 1x1 ``conv`` of ``y`` ``(B, C, H, W)`` as one batched product with the bias (inference).

    ``baddbmm(bias, W, y)``: ``Conv2d``'s value up to float rounding, one operation on the
    ``(B, C, H W)`` view of ``y``.
    """
    b, c, h, w = y.shape
    wt = conv.weight[:, :, 0, 0]
    return torch.baddbmm(conv.bias[None, :, None], wt.expand(b, -1, -1),
                         y.reshape(b, c, h * w)).view(b, wt.shape[0], h, w)


def _gelu(y: torch.Tensor, inplace: bool) -> torch.Tensor:
    """The exact (erf) GELU, in place on ``y`` when ``inplace`` (no autograd)."""
    return torch.ops.aten.gelu_(y) if inplace else nn.functional.gelu(y)


def stiffness_numbers(p: StepProblem, spacing=None) -> torch.Tensor:
    """Dimensionless stiffness numbers ``(B, 3)``, log10, centred.

    ``dt^2 k / (rho h^2)`` for stretch and shear, ``dt^2 k_b / (rho h^4)`` for bending (``h``:
    the mean spacing; ``spacing``: ``(hx, hy)`` ``(B,)`` in m to use instead of ``p``'s).
    """
    hx, hy = (p.hx, p.hy) if spacing is None else spacing
    h = 0.5 * (hx + hy)
    rho = p.material["density"]
    dt2 = p.dt * p.dt
    s = dt2 * p.material["stretch"] / (rho * h * h)
    sh = dt2 * p.material["shear"] / (rho * h * h)
    b = dt2 * 1e-3 * p.material["bend"] / (rho * h ** 4)
    return torch.stack([(torch.log10(s) - 3.0) / 1.0, (torch.log10(sh) - 1.5) / 1.0,
                        (torch.log10(b) - 1.0) / 1.5], 1)


def constant_features(p: StepProblem, dtype: torch.dtype, spacing=None,
                      free: torch.Tensor | None = None) -> torch.Tensor:
    """The FNO's input channels that one step problem keeps ``(B, 6, H, W)``.

    The handle mask, the three :func:`stiffness_numbers` and the two grid coordinates in
    ``[-1, 1]``: built once per solve by :func:`solve_fnopt` and passed to :func:`features`.
    ``spacing``: ``(hx, hy)`` ``(B,)`` (m) for the stiffness numbers instead of ``p``'s;
    ``free``: a free mask ``(B or 1, H, W, 1)`` of another grid than ``p``'s (the FNO's coarse
    grid, :mod:`draping.fnopt.coarse`), whose shape the channels then take.
    """
    b = p.x_prev.shape[0]
    free = p.free if free is None else free
    h, w = free.shape[1:3]
    mask = (1.0 - free[..., 0]).to(dtype).expand(b, h, w)[:, None]
    stiff = stiffness_numbers(p, spacing).to(dtype)[:, :, None, None].expand(b, 3, h, w)
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, h, dtype=dtype),
                            torch.linspace(-1, 1, w, dtype=dtype), indexing="ij")
    coords = torch.stack([yy, xx])[None].expand(b, 2, h, w)
    return torch.cat([mask, stiff, coords], 1)


def features(p: StepProblem, z: torch.Tensor, z_prev: torch.Tensor, da_prev: torch.Tensor,
             scale: torch.Tensor, const: torch.Tensor | None = None) -> torch.Tensor:
    """The FNO's input ``(B, N_INPUTS, H, W)``; fields ``(B, H, W, 3)`` divided by ``scale``.

    ``const``: :func:`constant_features` of ``p`` (built here when not given).
    """
    s = scale[:, None, None, None]
    const = constant_features(p, z.dtype) if const is None else const
    fields = torch.cat([z / s, z_prev / s, da_prev / s], -1).permute(0, 3, 1, 2)
    return torch.cat([fields, const], 1)


def fno_correction(model: FNO, p: StepProblem, z, z_prev, da_prev, const=None,
                   grid: coarse.FNOGrid | None = None) -> torch.Tensor:
    """The FNO's proposal ``(B, H, W, 3)`` (m/s^2): ``RMS(z) F(...)``, zero at handles.

    ``z = P g`` is the gradient in the metric of
    :func:`draping.fnopt.solvers.laplace_preconditioner`; the FNO sees ``z``, the previous
    ``z`` and the previous update, divided by ``z``'s RMS (scale-free inputs and output).
    ``const``: :func:`constant_features` of ``p``, when the caller keeps them. ``grid``: run
    the FNO on a coarse grid instead (:mod:`draping.fnopt.coarse`): the three fields
    restricted to it, normalised by the restricted ``z``'s RMS over the coarse free vertices,
    ``grid.const`` as the constant channels; the proposal, zero at the coarse handles, is
    prolonged back (then zero at ``p``'s handles too).
    """
    if grid is not None:
        z, z_prev, da_prev = (coarse.restrict(f, grid) for f in (z, z_prev, da_prev))
        free, const = grid.free, grid.const
        scale = coarse.free_rms(z, free).clamp(min=1e-12)
    else:
        free = p.free3                # the mask expanded to the coordinate axis: the same
        scale = p.residual_rms(z).clamp(min=1e-12)     # product, broadcast over the batch only
    y = model(features(p, z, z_prev, da_prev, scale, const)).permute(0, 2, 3, 1)
    y = y * scale[:, None, None, None] * free
    return y if grid is None else coarse.prolong(y, grid) * p.free3


def fno_direction(model: FNO, p: StepProblem, z, z_prev, da_prev) -> torch.Tensor:
    """The line-step direction ``d = -z + RMS(z) F(...)`` ``(B, H, W, 3)``, zero at handles."""
    return fno_correction(model, p, z, z_prev, da_prev) - z * p.free3


def fnopt_iteration(model: FNO, p: StepProblem, pre, a, z_prev, da_prev,
                    create_graph: bool = False):
    """One inner iteration with the line step: ``(a + Delta a, z, Delta a, g)``.

    ``Delta a = t d`` with ``d`` from :func:`fno_direction` and ``t`` the minimiser of the
    quadratic model of ``L_cloth`` along ``d`` (one Hessian-vector product): the step rule of
    the first shipped weights (``step="line"``).
    """
    val, g, hvp = p.grad_hvp(a)
    z = pre(g) * p.free
    d = fno_direction(model, p, z, z_prev, da_prev)
    if create_graph:
        t = p.exact_step(g, d, lambda v: hvp(v, create_graph=True))
    else:
        t = p.exact_step(g, d.detach(), hvp)
    da = t * d
    return a + da, z, da, g


#: Step rules of :func:`solve_fnopt`.
STEPS = ("line", "subspace")


def subspace_update(model: FNO, p: StepProblem, g, hvp, z, z_prev, da_prev,
                    create_graph: bool = False, zn=None, const=None, grid=None, extra=None,
                    proposal: bool = True):
    """FNOpt's update: the classical PCG step's subspace plus the FNO's proposal.

    The span of the preconditioned steepest descent ``-z``, the previous update (PCG's memory)
    and the FNO's proposal ``f`` (:func:`fno_correction`) is searched by exact minimisation of
    the quadratic model of ``L_cloth`` (three Hessian-vector products in one batched pass,
    :func:`draping.fnopt.solvers.subspace_solve`). The first two directions alone are
    :func:`draping.fnopt.solvers.solve_pcg`'s step, so in the model the update is never worse
    than the classical one from the same state; a useless proposal gets a coefficient ~0, a
    zero one reproduces PCG iterate by iterate. ``create_graph``: keep the graph through ``f``
    (training).

    The memory is the previous update, proposal included. Carrying only its PCG part instead
    (the proposal kept out of the conjugate-gradient recurrence) was tried with a model
    trained that way: worse on the diagonal and mid-edges layouts at 64x64 (e_CD x 1e3 10.6 and
    14.1 against 6.0 and 9.5, 60 frames).

    ``zn`` (weights with ``config.normal``): a list of further classical directions, the
    out-of-plane preconditioned gradient's (:func:`draping.fnopt.solvers.normal_directions`);
    they join the classical step (then ``solve_pcg(..., normal=True)``'s). ``const``:
    :func:`constant_features` of ``p`` (a solve builds them once). ``grid``: the FNO's coarse
    grid (:func:`fno_correction`). ``extra`` (inference only): ``(W, HW)``, further directions
    and their Hessian products, given (not computed here: :func:`solve_fnopt` passes a recycled
    basis with products from the start of its solve); they join the learned step only, so
    the classical step ``da_pcg`` is unchanged. ``proposal=False`` (inference only): no FNO
    call and no proposal direction (the span of the classical directions and ``extra``; without
    ``extra`` the update is the classical one).

    Returns
    -------
    tuple
        ``(da, da_pcg, m, m_pcg)``: the update and the classical update ``(B, H, W, 3)``
        (m/s^2), and their model decreases ``(B,)`` (J, float64, <= 0).
    """
    if create_graph and (extra or not proposal):
        raise ValueError("extra / proposal=False: supported without create_graph only (inference)")
    base = [-z * p.free3, da_prev] + (list(zn) if zn is not None else [])
    if not proposal:
        dirs, hd = base, p.hessian_products(base, hvp)
    elif create_graph:
        f = fno_correction(model, p, z, z_prev, da_prev, const, grid=grid)
        dirs, hd = base + [f], p.hessian_products(base, hvp) + [hvp(f, create_graph=True)]
    else:
        f = fno_correction(model, p, z, z_prev, da_prev, const, grid=grid).detach()
        dirs = base + [f]
        hd = p.hessian_products(dirs, hvp)
    if extra:
        dirs, hd = dirs + list(extra[0]), hd + list(extra[1])
    k = len(base)
    (c, m), (c2, m2) = subspace_solve(g, dirs, hd, sub=k, fused=p.fused and not create_graph)
    d = torch.stack(dirs, 1)
    if not create_graph:              # both updates in one product (c2 is 0 beyond k)
        both = torch.bmm(torch.stack([c, c2], 1).to(g.dtype), d.view(d.shape[0], len(dirs), -1))
        return both[:, 0].view(g.shape), both[:, 1].view(g.shape), m, m2
    da = torch.einsum("bi,bihwc->bhwc", c.to(g.dtype), d)
    da_pcg = torch.einsum("bi,bihwc->bhwc", c2[:, :k].detach().to(g.dtype), d[:, :k].detach())
    return da, da_pcg, m, m2


def _evaluate(p: StepProblem, a: torch.Tensor, grad: bool):
    """``(L, g, hvp)`` at ``a`` when ``grad``, else ``(L, None, None)`` (no gradient pass)."""
    if grad:
        return p.grad_hvp(a)
    with torch.no_grad():
        return p.loss(a).detach(), None, None


def fno_inputs(p: StepProblem, dtype: torch.dtype, coarse_res: int = 0,
               stiffness_res: int = 0):
    """The FNO's constant channels and grid for one solve: ``(const, grid)``.

    ``coarse_res`` > 0: the FNO runs on the grid whose longer side has ``coarse_res`` vertices
    (:func:`draping.fnopt.coarse.coarse_shape`), with the stiffness numbers of that grid's
    spacing; ``grid`` is its :class:`~draping.fnopt.coarse.FNOGrid` (``None`` where that grid is
    ``p``'s own, so the solve is the default one). ``stiffness_res`` > 0: the FNO stays on
    ``p``'s grid but its stiffness numbers take the spacing of that ``stiffness_res`` grid.
    0 (both defaults): ``p``'s grid and spacing.

    Raises
    ------
    ValueError
        If an option is not 0 or an int >= 2, or both are set.
    TypeError
        If an option is not an int.
    """
    for name, v in (("coarse_res", coarse_res), ("stiffness_res", stiffness_res)):
        coarse.check_grid_option(v, name)
    if coarse_res and stiffness_res:
        raise ValueError("coarse_res and stiffness_res: expected at most one of them set, got "
                         f"{coarse_res} and {stiffness_res}")
    fine = tuple(p.x_prev.shape[1:3])
    shape = coarse.coarse_shape(*fine, coarse_res or stiffness_res or max(fine))
    if shape == fine:
        return constant_features(p, dtype), None
    spacing = coarse.coarse_spacing(p.hx, p.hy, fine, shape)
    if stiffness_res:
        return constant_features(p, dtype, spacing), None
    free_c = coarse.coarse_free(p.free, shape)
    const = constant_features(p, dtype, spacing, free_c)
    return const, coarse.fno_grid(p.free, shape, const, dtype)


#: Largest recycled basis of :func:`solve_fnopt` (``recycle``).
RECYCLE_MAX = 16

#: How far (m) a problem's ``x_prev`` may lie from the state the carried basis was made for
#: (rounding of the handles' exact placement) for it to count as that problem's next frame.
RECYCLE_TOL = 1e-5


def check_fno_every(fno_every) -> None:
    """Check ``solve_fnopt``'s ``fno_every``: an int >= 1.

    Raises
    ------
    TypeError
        If ``fno_every`` is not an int (``bool`` included).
    ValueError
        If it is below 1.
    """
    check_int(fno_every, "fno_every", low=1)


def check_recycle(recycle) -> None:
    """Check ``solve_fnopt``'s ``recycle``: an int in ``[0, RECYCLE_MAX]``.

    Raises
    ------
    TypeError
        If ``recycle`` is not an int (``bool`` included).
    ValueError
        If it is out of range.
    """
    check_int(recycle, "recycle", low=0, high=RECYCLE_MAX)


def recycled_basis(updates: list, free3: torch.Tensor) -> list:
    """An orthonormal basis of the span of ``updates`` (each ``(B, H, W, 3)``), zero at handles.

    Euclidean per sheet, in float64, returned in the updates' dtype: the Gram matrix's
    eigenvectors whose eigenvalues are above 1e-12 of the largest on every sheet (a repeated or
    zero update adds none), then a QR of those combinations (orthonormal to rounding). ``free3``:
    the free mask ``(B or 1, H, W, 3)``. Empty ``updates``: ``[]``.
    """
    if not updates:
        return []
    shape = updates[0].shape
    u = torch.stack([d * free3 for d in updates], -1).reshape(shape[0], -1, len(updates))
    u = u.double()
    lam, vec = torch.linalg.eigh(u.transpose(1, 2) @ u)
    keep = (lam > 1e-12 * lam[:, -1:].clamp(min=1e-300)).all(0)
    if not bool(keep.any()):
        return []
    q = torch.linalg.qr(u @ (vec[:, :, keep] / lam[:, None, keep].sqrt()))[0]
    q = q.to(updates[0].dtype).reshape(*shape, -1) * free3[..., None]
    return [q[..., i] for i in range(q.shape[-1])]


def carried_basis(p: StepProblem, memory: dict) -> list:
    """The recycled basis ``memory`` carries to ``p``, or ``[]``.

    ``memory["basis"]`` (from :func:`solve_fnopt`) is used only if ``p`` continues the step it
    was made on: ``p.x_prev`` within :data:`RECYCLE_TOL` (m, max over vertices) of
    ``memory["x_next"]``, the positions that step's solution leads to. A new rollout, another
    sheet or a repeated frame starts without one.
    """
    basis, x_next = memory.get("basis"), memory.get("x_next")
    if not basis or x_next is None or x_next.shape != p.x_prev.shape:
        return []
    if float((p.x_prev - x_next.to(p.x_prev.dtype)).abs().max()) > RECYCLE_TOL:
        return []
    return [w.to(p.x_prev.dtype) for w in basis]


def solve_fnopt(model: FNO, p: StepProblem, iters: int, a0=None, step: str = "subspace",
                guard: bool = True, info: dict | None = None, coarse_res: int = 0,
                stiffness_res: int = 0, recycle: int = 0,
                memory: dict | None = None, fno_every: int = 1, two_level: int = 0,
                two_level_every: int = 1, two_level_from: int = 0) -> torch.Tensor:
    """Algorithm 2: ``iters`` learned updates from ``a = 0``; returns the accelerations.

    ``step``: ``"subspace"`` (default, :func:`subspace_update`) or ``"line"`` (the exact
    line step along the FNO's direction, :func:`fnopt_iteration`). ``guard`` (subspace step):
    an update whose actual decrease of ``L_cloth`` is smaller than the classical PCG step's
    model decrease (up to float rounding) is replaced by that PCG step, per sheet, so the
    learned part cannot spoil a step where the quadratic model misleads it (a replaced
    update costs one more gradient; the last iteration's check one more energy).
    ``info`` receives ``replaced`` (updates replaced, summed over the batch).
    ``coarse_res``, ``stiffness_res`` (subspace step; 0, the default: off): the FNO's grid and
    spacing (:func:`fno_inputs`); the subspace step and its classical directions stay on
    ``p``'s grid.

    ``recycle`` (subspace step; 0, the default: off) with ``memory`` (a dict kept by the caller
    across the frames of a rollout): the soft modes a step leaves undone are nearly those of the
    next step, so the span of this solve's last ``recycle`` updates is kept
    (:func:`recycled_basis`, stored in ``memory`` with the positions the solution leads to) and
    the next frame's solve (:func:`carried_basis`) adds it to every iteration's learned step
    (:func:`subspace_update`'s ``extra``), with the basis' Hessian products taken once, at
    ``a = 0``: the quadratic model picks their coefficients, the classical step and the guard
    are unchanged (the learned update, basis included, is kept only if it lowers ``L_cloth``
    at least as much as the classical step's model predicts).

    ``fno_every`` (subspace step; 1, the default: every iteration): the FNO's proposal only at
    iterations ``k`` with ``k % fno_every == 0`` (the first included); the others take the
    classical step (with a recycled basis, its span too), one FNO forward and one Hessian
    product cheaper, and skip the guard where their update is the classical one.

    ``two_level`` (subspace step; 0, the default: off), ``two_level_every`` (with ``memory``):
    the two-level coarse correction of :mod:`draping.fnopt.twolevel` on the grid whose longer
    side has ``two_level`` vertices joins the classical directions (``solve_pcg``'s ``coarse``
    and ``coarse_every``; the shipped weights were not trained with it). ``two_level_from``
    (0, the default: every iteration): the coarse direction joins iterations ``k >=
    two_level_from`` only (the coarse space is still built or kept at iteration 0); at 64x64,
    N = 10, K = 16 rebuilt every 4 frames, ``1`` kept both one-handle layouts on the
    reference's fold where ``0`` did not (docs/measurements/fnopt.md, session 19).

    Where the step problem needs no autograd (:meth:`StepProblem.autograd_free`: the default
    fused closed forms) the solve runs under ``torch.inference_mode``: the same arithmetic bit
    for bit, without autograd's per-operation bookkeeping; the result (and ``memory``'s
    entries) are returned as normal tensors.

    Raises
    ------
    ValueError
        On an unknown ``step``, bad ``coarse_res`` / ``stiffness_res`` (:func:`fno_inputs`), or
        either of them set with ``step="line"``; ``recycle`` out of range
        (:func:`check_recycle`), set with ``step="line"`` or without ``memory``;
        ``fno_every`` < 1 or not 1 with ``step="line"``; ``two_level`` negative or 1, set
        with ``step="line"``, or ``two_level_every > 1`` without ``memory``;
        ``two_level_from`` negative, or not 0 without ``two_level``.
    TypeError
        If ``recycle``, ``fno_every``, ``two_level``, ``two_level_every`` or
        ``two_level_from`` is not an int.
    """
    if step not in STEPS:
        raise ValueError(f"step: expected one of {list(STEPS)}, got {step!r}")
    if step == "line" and (coarse_res or stiffness_res):
        raise ValueError("coarse_res / stiffness_res: supported by step='subspace' only, got "
                         f"{coarse_res} / {stiffness_res} with step='line'")
    check_recycle(recycle)
    check_fno_every(fno_every)
    if fno_every != 1 and step == "line":
        raise ValueError(f"fno_every: {fno_every} needs step='subspace' (got 'line')")
    if recycle and (step == "line" or memory is None):
        raise ValueError(f"recycle: {recycle} needs step='subspace' (got {step!r}) and a "
                         f"memory dict (got {type(memory).__name__})")
    coarse.check_grid_option(two_level, "two_level")
    check_int(two_level_every, "two_level_every", low=1)
    if two_level and (step == "line" or (two_level_every > 1 and memory is None)):
        raise ValueError(f"two_level: {two_level} needs step='subspace' (got {step!r}), and "
                         f"two_level_every > 1 a memory dict (got {type(memory).__name__})")
    check_int(two_level_from, "two_level_from", low=0)
    if two_level_from and not two_level:
        raise ValueError(f"two_level_from: {two_level_from} needs two_level > 0 (got 0)")
    args = (model, p, iters, a0, step, guard, info, coarse_res, stiffness_res, recycle, memory,
            fno_every, two_level, two_level_every, two_level_from)
    out = autograd_free_call(p, _solve, *args)   # no autograd bookkeeping where none is needed
    if recycle and p.autograd_free():            # normal tensors for the caller (in-place use)
        memory["basis"] = [w.clone() for w in memory["basis"]]
        memory["x_next"] = memory["x_next"].clone()
    return out


def _solve(model: FNO, p: StepProblem, iters: int, a0, step: str, guard: bool, info,
           coarse_res: int, stiffness_res: int, recycle: int, memory, fno_every: int,
           two_level: int = 0, two_level_every: int = 1, two_level_from: int = 0):
    """:func:`solve_fnopt` after its checks (the same arguments, in its order)."""
    pre = laplace_preconditioner(p)
    pn = normal_preconditioner(p) if model.config.normal and step == "subspace" else None
    a = torch.zeros_like(p.x_prev) if a0 is None else (a0 * p.free).clone()
    const, grid = fno_inputs(p, a.dtype, coarse_res, stiffness_res)
    z_prev = torch.zeros_like(a)
    da = torch.zeros_like(a)
    if step == "line":
        for _ in range(iters):
            with torch.no_grad():
                a, z_prev, da, _ = fnopt_iteration(model, p, pre, a, z_prev, da)
        return p.compose(a)
    slack = 1e-6 if a.dtype != torch.float64 else 1e-12
    replaced = 0
    val, g, hvp = p.grad_hvp(a)
    w = carried_basis(p, memory) if recycle else []
    extra = (w, p.hessian_products(w, hvp)) if w else None
    updates, space = [], None
    for k in range(iters):
        more = k < iters - 1              # a next iteration needs the gradient at a + dn
        z = pre(g) * p.free3
        zn = normal_directions(p, g, pn, model.config.normal_split) if pn is not None else None
        if two_level:
            space = space if k else kept_space(p, hvp, two_level, two_level_every, memory)
            if k >= two_level_from:
                zn = (zn or []) + [-coarse_correction(space, g)]
        learned = k % fno_every == 0
        with torch.no_grad():
            dn, dn_pcg, _, m_pcg = subspace_update(model, p, g, hvp, z, z_prev, da, zn=zn,
                                                   const=const, grid=grid, extra=extra,
                                                   proposal=learned)
        check = guard and (learned or extra is not None)   # else dn is the classical step
        nxt = _evaluate(p, a + dn, more) if (more or check) else None
        if check:
            bad = (nxt[0] - val).double() > m_pcg + slack * val.abs().double()
            if bool(bad.any()):
                replaced += int(bad.sum())
                dn = torch.where(bad[:, None, None, None], dn_pcg, dn)
                nxt = _evaluate(p, a + dn, True) if more else nxt
        a, da, z_prev = a + dn, dn, z
        if recycle:
            updates = (updates + [dn])[-recycle:]
        if more:
            val, g, hvp = nxt
    if info is not None:
        info["replaced"] = replaced
    out = p.compose(a)
    if recycle:
        memory["basis"] = recycled_basis(updates, p.free3)
        memory["x_next"] = positions_from_accel(out, p.x_prev, p.v_prev, p.dt).detach()
    return out


def n_parameters(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(int(math.prod(q.shape)) for q in model.parameters())


#: The shipped weights (trained by ``polygeo train-fnopt``) and their JSON record.
WEIGHTS = Path(__file__).resolve().parent.parent / "data" / "fnopt_model.pt"
RECORD = WEIGHTS.with_suffix(".json")


def optimizer_step(model: nn.Module, opt: torch.optim.Optimizer, loss: torch.Tensor,
                   lr: float, clip: float = 1.0) -> None:
    """One training update of ``model``: ``opt`` at rate ``lr`` on ``loss``'s gradient.

    The gradient's global norm is clipped at ``clip`` first (every FNOpt training loop's
    rule). ``loss``: a scalar tensor in the graph of ``model``'s parameters.
    """
    for grp in opt.param_groups:
        grp["lr"] = lr
    opt.zero_grad()
    loss.backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), clip)
    opt.step()


def load_pretrained(path: str | Path | None = None) -> FNO:
    """The trained FNO optimiser (default: the shipped ``draping/data/fnopt_model.pt``).

    The config comes from the JSON record beside the weights; the weights are read with
    ``torch.load(weights_only=True)``.

    Raises
    ------
    FileNotFoundError
        If the weights or their JSON record are missing.
    """
    p = Path(path) if path is not None else WEIGHTS
    rec = p.with_suffix(".json")
    if not p.is_file() or not rec.is_file():
        raise FileNotFoundError(f"FNOpt weights: expected {p} and {rec} (train them with "
                                "`polygeo train-fnopt`)")
    cfg = FNOConfig(**json.loads(rec.read_text())["config"])
    model = FNO(cfg)
    model.load_state_dict(torch.load(p, map_location="cpu", weights_only=True))
    model.eval()
    return model
