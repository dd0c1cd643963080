"""Settings of the soft rasterizer.

Units used throughout :mod:`polygeo.render`:

* image-plane distances are in **pixels** (OpenCV convention: the image origin is the
  top-left corner of the top-left pixel, pixel ``(i, j)`` has its centre at
  ``(x, y) = (j + 0.5, i + 0.5)``);
* ``sigma`` is a squared distance, in **pixels²**;
* depths are camera-space ``z`` in the scene's length unit (metres, say);
* ``gamma`` and ``background_depth`` are in *normalised depth* units,
  ``z_n = (zfar - z) / (zfar - znear)`` (1 at the near plane, 0 at the far plane).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ..checks import check_int, check_positive

__all__ = ["RasterSettings", "sigma_from_softras"]


def sigma_from_softras(sigma_ndc: float, image_size: int) -> float:
    """Convert a SoftRas ``sigma`` (normalised units) to pixels².

    SoftRas measures image-plane distances in normalised device coordinates where the
    image spans ``[-1, 1]``, so one pixel is ``2 / S`` units wide for an image of ``S``
    pixels. A squared distance therefore scales by ``(S / 2)²``.

    Parameters
    ----------
    sigma_ndc : float
        SoftRas ``sigma`` (its default is ``1e-4``), > 0.
    image_size : int
        Image side ``S`` in pixels (the larger side for non-square images), >= 1.

    Returns
    -------
    float
        ``sigma`` in pixels², e.g. ``1e-4`` -> 0.41 px² at 128 px and 1.64 px² at 256 px.

    Raises
    ------
    ValueError
        If ``sigma_ndc`` is not a finite positive number or ``image_size`` < 1.
    TypeError
        If ``image_size`` is not an integer.
    """
    s = check_positive(sigma_ndc, "sigma_ndc")
    n = check_int(image_size, "image_size", low=1)
    return s * (n / 2.0) ** 2


@dataclass
class RasterSettings:
    """How :func:`polygeo.render.render` turns triangles into pixels.

    Attributes
    ----------
    sigma : float
        Sharpness of the SoftRas coverage ``D = sigmoid(delta * d² / sigma)``, in
        **pixels²** (``d`` is the distance in pixels from the pixel centre to the projected
        triangle's boundary, ``delta`` = +1 inside, -1 outside). Default 0.1 px², a
        pixel-sized blur: ``D`` is 0.076 half a pixel outside an edge and falls below
        ``blur_threshold`` = 1e-4 at 0.96 px; the silhouette thresholded at 0.5 then has an
        IoU >= 0.99 with a hard rasterization of an open sheet (a closed mesh, whose
        silhouette has front and back faces on top of each other, gets about 0.98; use a
        smaller ``sigma`` for evaluation renders, or ``hard=True``). Larger values widen the
        basin of attraction of silhouette fitting. SoftRas' default ``1e-4`` (normalised
        units) equals 0.41 px² at 128² and 1.64 px² at 256² (see
        :func:`sigma_from_softras`).
    gamma : float
        Temperature of the softmax over normalised depth used to blend face colours
        (SoftRas' ``gamma``), in normalised-depth units; smaller is closer to a z-buffer.
    blur_threshold : float
        Coverage below which a face is ignored at a pixel (treated as ``D = 0``, and left
        out of the colour softmax). It sets the blur margin
        ``sqrt(sigma * ln(1 / blur_threshold - 1))`` pixels by which each face's bounding
        box is grown for binning. 0 disables the cut-off (every face reaches every pixel:
        exact but slow; used by gradient checks). Must be in ``[0, 0.5)``.
    tile_size : int
        Side in pixels of the square screen tiles faces are binned into (the unit of
        parallel work; results do not depend on it).
    background : sequence of float
        Background colour, one value per colour channel (broadcast when it has one value).
    background_depth : float
        Normalised depth of the background term of the colour softmax (SoftRas ``eps``).
    znear, zfar : float
        Near and far planes (camera-space depth, scene units). Faces with **any** vertex
        closer than ``znear`` are culled (not clipped). ``zfar`` only normalises depth for
        the colour softmax; farther faces are still drawn (with negative normalised depth).
    hard : bool
        Hard mode for evaluation renders: binary coverage and the colour of the nearest
        face only (z-buffer). Differentiable w.r.t. colours and texture, and w.r.t. vertex
        positions through the interpolation only (no silhouette gradient).
    cull_backfaces : bool
        Cull back faces: those whose normal (right-hand rule on the vertex order
        ``(v0, v1, v2)``) points away from the camera, i.e. whose projected signed area
        ``cross(p1 - p0, p2 - p0)`` in the y-down image axes is positive. Off by default
        (sheets are two-sided).
    min_area : float
        Faces whose projected area is below this (pixels²) are degenerate and skipped.
    """

    sigma: float = 0.1
    gamma: float = 1e-4
    blur_threshold: float = 1e-4
    tile_size: int = 8
    background: Sequence[float] = field(default=(0.0, 0.0, 0.0))
    background_depth: float = 1e-3
    znear: float = 1e-2
    zfar: float = 100.0
    hard: bool = False
    cull_backfaces: bool = False
    min_area: float = 1e-8

    def __post_init__(self) -> None:
        self.sigma = check_positive(self.sigma, "sigma")
        self.gamma = check_positive(self.gamma, "gamma")
        thr = check_positive(self.blur_threshold, "blur_threshold", strict=False)
        if thr >= 0.5:
            raise ValueError(f"blur_threshold: expected a value in [0, 0.5), got {thr!r}")
        self.blur_threshold = thr
        self.tile_size = check_int(self.tile_size, "tile_size", low=1, high=256)
        bg = np.asarray(self.background, dtype=np.float64).reshape(-1)
        if bg.size == 0 or not np.all(np.isfinite(bg)):
            raise ValueError(
                f"background: expected one or more finite values, got {self.background!r}"
            )
        self.background = tuple(float(v) for v in bg)
        bd = float(self.background_depth)
        if not math.isfinite(bd):
            raise ValueError(f"background_depth: expected a finite value, got {bd!r}")
        self.background_depth = bd
        self.znear = check_positive(self.znear, "znear")
        self.zfar = check_positive(self.zfar, "zfar")
        if self.zfar <= self.znear:
            raise ValueError(f"zfar: expected a value > znear = {self.znear!r}, got {self.zfar!r}")
        self.min_area = check_positive(self.min_area, "min_area", strict=False)
        if not isinstance(self.hard, (bool, np.bool_)):
            raise TypeError(f"hard: expected a bool, got {type(self.hard).__name__}")
        if not isinstance(self.cull_backfaces, (bool, np.bool_)):
            raise TypeError(
                f"cull_backfaces: expected a bool, got {type(self.cull_backfaces).__name__}"
            )

    @property
    def blur_margin(self) -> float:
        """Distance in pixels beyond a face's edges where its coverage drops below the threshold.

        ``inf`` when ``blur_threshold`` is 0 (no cut-off).
        """
        if self.blur_threshold == 0.0:
            return math.inf
        return math.sqrt(self.sigma * math.log(1.0 / self.blur_threshold - 1.0))

    def background_for(self, channels: int) -> np.ndarray:
        """Return the background colour as a float64 array of ``channels`` values.

        Raises
        ------
        ValueError
            If the background has neither one value nor ``channels`` values.
        """
        bg = np.asarray(self.background, dtype=np.float64)
        if bg.size == 1:
            return np.full(channels, bg[0])
        if bg.size != channels:
            raise ValueError(
                f"background: expected 1 or {channels} values (one per colour channel), "
                f"got {bg.size}"
            )
        return bg.copy()
