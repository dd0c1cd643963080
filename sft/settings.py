"""Settings of a PolySfT run: small dataclasses, one per concern, with JSON round trips.

:class:`SfTSettings` holds

- ``model``: :class:`ModelSettings`, the deformation model (method, jet order, patches,
  re-partitioning);
- ``optimiser``: :class:`OptimiserSettings`, the sliding window and Adam;
- ``losses``: :class:`LossSettings`, the weights and kinds of the loss terms;
- ``raster``: a :class:`polygeo.render.RasterSettings`, the soft rasterizer itself;
- ``output``: :class:`OutputSettings`, what a run writes and shows (no effect on results).

Defaults are the thesis' except where a field says why not; the measured effect of each
departure is in the README's PolySfT section and in ``benchmarks/bm_sft.py``'s results.
Every field name is unique across the groups, so a flat ``{name: value}`` mapping (the
CLI's options, the benchmark's configurations) addresses one field without its group
(:meth:`SfTSettings.from_flat`, :meth:`SfTSettings.replace`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Any

from polygeo.checks import check_choice, check_int, check_positive
from polygeo.render import RasterSettings

if TYPE_CHECKING:
    import torch

__all__ = [
    "SfTSettings",
    "ModelSettings",
    "OptimiserSettings",
    "LossSettings",
    "OutputSettings",
    "PARAMETERS",
]

#: Names of the per-frame parameters of the models (what ``freeze`` may name).
PARAMETERS = ("d_alpha", "d_uv", "d_x", "rot", "trans", "p_rot", "p_trans")

#: Value of ``order`` that lets the optimiser raise the jet order on plateaus.
ORDER_AUTO = "auto"

#: Value of ``patches`` that picks the fewest patches each of which is a height graph.
PATCHES_AUTO = "auto"

#: Default largest tilt (degrees) of a triangle from its patch's axis for ``patches="auto"``.
#: One patch tracks sheets whose graph tilts to about 80 degrees (the ``bend`` sequence), so
#: 70 at the template leaves room for the deformation that follows.
MAX_TILT = 70.0


def _check_patches(patches, max_tilt: float) -> tuple[int | str, float]:
    """Validate a patch count (an integer >= 1 or ``"auto"``) and ``max_tilt`` (degrees).

    Returns them (the count as int); raises ``ValueError``/``TypeError`` naming the argument.
    """
    if isinstance(patches, str):
        if patches != PATCHES_AUTO:
            raise ValueError(f"patches: expected an integer >= 1 or 'auto', got {patches!r}")
    else:
        patches = check_int(patches, "patches", low=1)
    return patches, _check_tilt(max_tilt, "max_tilt")


def _check_tilt(value, name: str) -> float:
    """Validate an angle in degrees in ``(0, 90)``; raises ``ValueError`` naming ``name``."""
    value = check_positive(value, name)
    if value >= 90.0:
        raise ValueError(f"{name}: expected degrees in (0, 90), got {value}")
    return value


def _check_bool(value: Any, name: str) -> bool:
    if not isinstance(value, bool):
        raise TypeError(f"{name}: expected a bool, got {type(value).__name__} {value!r}")
    return value


@dataclass
class ModelSettings:
    """The deformation model.

    Attributes
    ----------
    method : {"polysft", "vertex"}
        Jet patches (PolySfT) or per-vertex offsets (the classical baseline).
    order : int or "auto"
        Jet order in ``[1, 6]``. Default 6 (the thesis' experiments use 4): a polynomial of
        order 4 over the whole sheet cannot follow a wave or a crease narrower than the sheet,
        and order 6 costs the same time per iteration (the renderer dominates). ``"auto"``
        starts at 2 and raises the order by one (never lowering it) whenever the running
        minimum of the loss fell by less than ``auto_gain`` over ``patience`` iterations and
        at a plateau; it suits scenes that low orders explain and loses on fine ones.
    max_order : int
        Highest order ``"auto"`` may reach.
    auto_gain : float
        Relative decrease of the loss over ``patience`` iterations below which ``"auto"``
        raises the order.
    patches : int or "auto"
        Number of jet patches. ``"auto"`` (default): the fewest (1, 2, ..., 8, 12, 18, ...)
        whose every triangle lies within ``max_tilt`` of its patch's axis
        (:meth:`sft.template.JetTemplate.fit`): one patch, the thesis' model, for a sheet;
        several for a tube, a cap or a crumpled cloth, which are no height graph over one
        plane. More patches than needed let them drift in depth on a travelling wave.
    max_tilt : float
        Degrees in ``(0, 90)`` for ``patches="auto"``. 70 leaves a sheet's one patch room to
        bend further during the sequence.
    patch_rigid : bool
        With several patches, a rigid motion per patch relative to the global one, tied to the
        neighbouring patches by the boundary term (:class:`sft.model.JetModel`).
    refit_tilt : float
        Degrees in ``[0, 180)``; 0 never re-partitions. After each frame, when a patch's jet
        is steeper than this (:meth:`sft.model.JetModel.tilt`) and has steepened by more than
        ``refit_tilt - refit_max_tilt`` since it was fitted, that frame's reconstruction
        becomes the template of a new model (``patches="auto"`` bounded by
        ``refit_max_tilt`` on the jets' slopes, at most ``refit_max_patches``) and the window
        is projected onto it: a height graph over one plane cannot follow a sheet that rolls
        past a quarter turn. Inextensibility keeps the first template's edge lengths.
    refit_max_tilt : float
        Degrees in ``(0, 90)``: the steepest jet slope a patch of a new partition may have.
    refit_max_patches : int
        Most patches of a new partition (each patch makes an iteration dearer).
    seed : int
        Seed of the patch partition (the optimisation itself is deterministic).
    """

    method: str = "polysft"
    order: int | str = 6
    max_order: int = 6
    auto_gain: float = 0.03
    patches: int | str = PATCHES_AUTO
    max_tilt: float = MAX_TILT
    patch_rigid: bool = True
    refit_tilt: float = 50.0
    refit_max_tilt: float = 35.0
    refit_max_patches: int = 8
    seed: int = 0

    def __post_init__(self) -> None:
        check_choice(self.method, "method", ("polysft", "vertex"))
        if self.order != ORDER_AUTO:
            self.order = check_int(self.order, "order", low=1, high=6)
        self.max_order = check_int(self.max_order, "max_order", low=2, high=6)
        self.auto_gain = check_positive(self.auto_gain, "auto_gain", strict=False)
        self.patches, self.max_tilt = _check_patches(self.patches, self.max_tilt)
        self.patch_rigid = _check_bool(self.patch_rigid, "patch_rigid")
        self.refit_tilt = check_positive(self.refit_tilt, "refit_tilt", strict=False)
        if self.refit_tilt >= 180.0:
            raise ValueError(f"refit_tilt: expected degrees in [0, 180), got {self.refit_tilt}")
        self.refit_max_tilt = _check_tilt(self.refit_max_tilt, "refit_max_tilt")
        self.refit_max_patches = check_int(self.refit_max_patches, "refit_max_patches", low=1)
        self.seed = check_int(self.seed, "seed")


@dataclass
class OptimiserSettings:
    """The adaptive sliding window and its Adam optimiser (:mod:`sft.optimize`).

    Attributes
    ----------
    window : int
        Sliding-window size ``W`` (frames optimised together).
    patience : int
        Iterations without improvement of the loss's running minimum that end a window.
        Default 30 (thesis: 100): the windows rarely plateau before ``max_iterations``.
    max_iterations : int
        Most iterations per window (the thesis' "frame period"). Default 200 (thesis: 500)
        keeps a frame within about 10 CPU seconds at 128 px; ``patience=100,
        max_iterations=500`` is the thesis' budget.
    min_improvement : float
        An iteration improves when its loss is below ``(1 - min_improvement)`` times the
        running minimum.
    lr_uv, lr_alpha, lr_rigid, lr_vertex, lr_patch : float
        Adam learning rates in the model's normalised units (template radius 1): ``Delta uv``,
        ``Delta alpha``, the rigid motion (rotation vector in radians and translation), the
        baseline's per-vertex offsets, the per-patch rigid motions. ``lr_rigid`` = 1e-3
        instead of the thesis' 1e-4: Adam moves a parameter by about its learning rate per
        step, and 1e-4 of a 15 cm radius is 15 um per step, so the jets would absorb a
        frame's rigid motion as deformation.
    init : {"extrapolate", "previous"}
        How a frame entering the window starts: extrapolated at constant velocity from the
        two frames before it (default; it goes with ``acceleration_weight``), or from the
        previous frame's parameters (the thesis).
    carry_adam : bool
        Keep each frame's Adam moments across windows (a frame entering the window inherits
        those of the frame before it); False restarts Adam in every window, which kicks every
        parameter by about its learning rate in the first steps.
    keep_best : bool
        A window hands on its lowest-loss iterate, not its last: Adam's loss is not monotone,
        and a spike followed by ``patience`` iterations without a new minimum would otherwise
        hand a damaged shape to the next frame.
    warmup : int
        Adam steps over which a fresh state's learning rates ramp up linearly from 0 (0: no
        ramp). A fresh Adam moves every parameter by about its learning rate in its first
        steps whatever its gradient, which for the coefficients of an order-6 jet is
        centimetres at the sheet's corners.
    freeze : tuple of str
        Parameters kept at their initial value (names in :data:`PARAMETERS`; e.g.
        ``("d_alpha", "d_uv")`` optimises the rigid motion alone).
    dtype : {"float32", "float64"}
        Dtype of the parameters and renders.
    """

    window: int = 3
    patience: int = 30
    max_iterations: int = 200
    min_improvement: float = 1e-4
    lr_uv: float = 1e-3
    lr_alpha: float = 1e-2
    lr_rigid: float = 1e-3
    lr_vertex: float = 1e-3
    lr_patch: float = 1e-3
    init: str = "extrapolate"
    carry_adam: bool = True
    keep_best: bool = True
    warmup: int = 20
    freeze: tuple[str, ...] = ()
    dtype: str = "float32"

    def __post_init__(self) -> None:
        self.window = check_int(self.window, "window", low=1)
        self.patience = check_int(self.patience, "patience", low=1)
        self.max_iterations = check_int(self.max_iterations, "max_iterations", low=1)
        self.min_improvement = check_positive(self.min_improvement, "min_improvement",
                                              strict=False)
        for name in ("lr_uv", "lr_alpha", "lr_rigid", "lr_vertex", "lr_patch"):
            setattr(self, name, check_positive(getattr(self, name), name))
        check_choice(self.init, "init", ("previous", "extrapolate"))
        self.carry_adam = _check_bool(self.carry_adam, "carry_adam")
        self.keep_best = _check_bool(self.keep_best, "keep_best")
        self.warmup = check_int(self.warmup, "warmup", low=0)
        if isinstance(self.freeze, str):
            raise TypeError(f"freeze: expected a sequence of names, got the string "
                            f"{self.freeze!r}")
        self.freeze = tuple(self.freeze)
        for name in self.freeze:
            check_choice(name, "freeze", sorted(PARAMETERS))
        check_choice(self.dtype, "dtype", ("float32", "float64"))

    @property
    def torch_dtype(self) -> torch.dtype:
        """``dtype`` as a torch dtype."""
        import torch  # here: the settings (and `polygeo sft --help`) need no torch

        return torch.float32 if self.dtype == "float32" else torch.float64


@dataclass
class LossSettings:
    """Weights and kinds of the loss terms (:mod:`sft.losses`); weights are >= 0.

    Attributes
    ----------
    rgb_weight : float
        Colour term (mean over pixels).
    silhouette_weight : float
        Silhouette term (mean over pixels; dropped when the sequence has no masks).
    inextensibility_weight : float
        Edge-length inextensibility (thesis eq. (47),
        :func:`polygeo.mesh.edge_length_energy` in units of the template radius). Default 10
        instead of the thesis' 0.1: with lengths in these units and image terms that are
        means over pixels, 0.1 lets the sheet stretch to explain a drift in depth.
    consistency_weight : float
        Temporal consistency (thesis eq. (48), the pull of each frame towards the one before
        it). Default 0 (thesis: 0.05): it pulls a frame towards stopping, so a part of the
        surface the images stop constraining freezes while the real one moves on.
    acceleration_weight : float
        Constant-velocity prior (squared second differences of every parameter over the
        window; needs ``window >= 3``); with ``init="extrapolate"`` it replaces eq. (48).
        ``consistency_weight=0.05, acceleration_weight=0, init="previous"`` is the thesis.
    boundary_weight, boundary_normal_weight : float
        Boundary consistency between patches (eq. (51)): positions and normals.
    rgb_kind : {"l1", "l2"}
        Norm of the colour term.
    silhouette_kind : {"l2", "l1", "iou"}
        Form of the silhouette term.
    pyramid : int
        Coarser image levels (2x2, 4x4, ... block means) averaged into the image terms
        (:class:`sft.losses.ImageTerms`); 0 = full resolution only (phi-SfT).
    """

    rgb_weight: float = 1.0
    silhouette_weight: float = 1.0
    inextensibility_weight: float = 10.0
    consistency_weight: float = 0.0
    acceleration_weight: float = 0.05
    boundary_weight: float = 1.0
    boundary_normal_weight: float = 0.1
    rgb_kind: str = "l1"
    silhouette_kind: str = "l2"
    pyramid: int = 0

    def __post_init__(self) -> None:
        for f in fields(self):
            if f.name.endswith("_weight"):
                setattr(self, f.name, check_positive(getattr(self, f.name), f.name,
                                                     strict=False))
        check_choice(self.rgb_kind, "rgb_kind", ("l1", "l2"))
        check_choice(self.silhouette_kind, "silhouette_kind", ("l2", "l1", "iou"))
        self.pyramid = check_int(self.pyramid, "pyramid", low=0, high=8)


@dataclass
class OutputSettings:
    """What a run writes and shows; none of it changes the reconstruction.

    Attributes
    ----------
    checkpoint_every : int
        Windows between checkpoints (0: none; the last frame always writes one when > 0).
    overlays : int
        Frames (spread over the sequence) that get a frame / render / error PNG.
    charts : bool
        Write the PNG charts (errors and loss curves) at the end of a complete run.
    quiet : bool
        No progress bar.
    """

    checkpoint_every: int = 1
    overlays: int = 4
    charts: bool = True
    quiet: bool = False

    def __post_init__(self) -> None:
        self.checkpoint_every = check_int(self.checkpoint_every, "checkpoint_every", low=0)
        self.overlays = check_int(self.overlays, "overlays", low=0)
        self.charts = _check_bool(self.charts, "charts")
        self.quiet = _check_bool(self.quiet, "quiet")


#: The groups of :class:`SfTSettings` and their types.
_GROUPS: dict[str, type] = {"model": ModelSettings, "optimiser": OptimiserSettings,
                            "losses": LossSettings, "raster": RasterSettings,
                            "output": OutputSettings}


def _group(cls: type, value: Any, name: str) -> Any:
    """``value`` as a ``cls``: an instance as it is, a mapping validated key by key."""
    if isinstance(value, cls):
        return value
    if not isinstance(value, dict):
        raise TypeError(f"{name}: expected {cls.__name__} or a dict, got "
                        f"{type(value).__name__}")
    known = [f.name for f in fields(cls)]
    unknown = sorted(set(value) - set(known))
    if unknown:
        raise ValueError(f"{name}: unknown setting(s) {unknown}; expected some of {known}")
    try:
        return cls(**value)
    except (TypeError, ValueError) as exc:  # name the group: "raster.sigma: ..."
        raise type(exc)(f"{name}.{exc}") from exc


@dataclass
class SfTSettings:
    """All settings of a PolySfT (or baseline) run, grouped.

    Attributes
    ----------
    model : ModelSettings
    optimiser : OptimiserSettings
    losses : LossSettings
    raster : polygeo.render.RasterSettings
        The soft rasterizer of the optimisation (``hard`` must be False: a hard render has no
        silhouette gradient). Its defaults (``sigma`` 0.1 px², ``gamma`` 1e-4) are used.
    output : OutputSettings

    Each group may also be given as a dict of its fields. ``to_dict`` / ``from_dict`` round
    trip through JSON; ``from_flat`` and ``replace`` take field names without their group.

    Examples
    --------
    >>> st = SfTSettings.from_flat(window=2, rgb_weight=0.5, sigma=0.2)
    >>> st.optimiser.window, st.losses.rgb_weight, st.raster.sigma
    (2, 0.5, 0.2)
    >>> SfTSettings.from_dict(st.to_dict()) == st
    True
    """

    model: ModelSettings = field(default_factory=ModelSettings)
    optimiser: OptimiserSettings = field(default_factory=OptimiserSettings)
    losses: LossSettings = field(default_factory=LossSettings)
    raster: RasterSettings = field(default_factory=RasterSettings)
    output: OutputSettings = field(default_factory=OutputSettings)

    def __post_init__(self) -> None:
        for name, cls in _GROUPS.items():
            setattr(self, name, _group(cls, getattr(self, name), name))
        if self.raster.hard:
            raise ValueError("raster.hard: expected False (the optimiser needs soft renders), "
                             "got True")

    @property
    def torch_dtype(self) -> torch.dtype:
        """The optimisation dtype as a torch dtype."""
        return self.optimiser.torch_dtype

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """``{group: {field: value}}`` of plain JSON values (tuples become lists)."""

        def plain(v: Any) -> Any:
            return list(v) if isinstance(v, tuple) else v

        return {name: {f.name: plain(getattr(getattr(self, name), f.name))
                       for f in fields(cls)} for name, cls in _GROUPS.items()}

    def result_dict(self) -> dict[str, dict[str, Any]]:
        """:meth:`to_dict` without ``output``: what decides the reconstruction (resume key)."""
        d = self.to_dict()
        del d["output"]
        return d

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SfTSettings:
        """Settings from :meth:`to_dict`'s form; missing groups and fields take defaults.

        Raises
        ------
        TypeError
            If ``data`` or a group is not a dict, or a value has the wrong type.
        ValueError
            For an unknown group or field, or an invalid value (the message names it as
            ``group.field``).
        """
        if not isinstance(data, dict):
            raise TypeError(f"settings: expected a dict, got {type(data).__name__}")
        unknown = sorted(set(data) - set(_GROUPS))
        if unknown:
            raise ValueError(f"settings: unknown group(s) {unknown}; expected some of "
                             f"{list(_GROUPS)}")
        return cls(**{name: _group(_GROUPS[name], data[name], name) for name in data})

    @classmethod
    def from_flat(cls, **options: Any) -> SfTSettings:
        """Settings from field names without their group (``window=2, sigma=0.2``).

        Raises
        ------
        ValueError
            For a name that is no field of any group, or an invalid value.
        """
        return cls().replace(**options)

    def replace(self, **options: Any) -> SfTSettings:
        """A copy with the named fields (without their group) changed; ``self`` is unchanged.

        Raises
        ------
        ValueError
            For a name that is no field of any group, or an invalid value.
        """
        where = flat_fields()
        unknown = sorted(set(options) - set(where))
        if unknown:
            raise ValueError(f"settings: unknown option(s) {unknown}; expected some of "
                             f"{sorted(where)}")
        data = self.to_dict()
        for name, value in options.items():
            data[where[name]][name] = value
        return SfTSettings.from_dict(data)


def flat_fields() -> dict[str, str]:
    """``{field name: group}`` of every field of every group (names are unique)."""
    out: dict[str, str] = {}
    for group, cls in _GROUPS.items():
        for f in fields(cls):
            if f.name in out:  # pragma: no cover - guarded by a test
                raise RuntimeError(f"settings: field {f.name!r} in {out[f.name]} and {group}")
            out[f.name] = group
    return out


def field_defaults() -> dict[str, Any]:
    """``{field name: default}`` of every field of every group (flat)."""
    d = SfTSettings().to_dict()
    return {name: d[group][name] for name, group in flat_fields().items()}


def field_types() -> dict[str, str]:
    """``{field name: annotation string}`` of every field of every group (flat)."""
    return {f.name: str(f.type) for cls in _GROUPS.values() for f in dataclasses.fields(cls)}
