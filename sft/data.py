"""The SfT sequence format: loader (validated up front) and writer.

A sequence is a folder::

    template.obj (+ template.mtl + texture image)   or   template.ply (with vertex colours)
    camera.json            {"K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], "width": W, "height": H}
    frames/000000.png ...  RGB frames (8 or 16 bit PNG, or JPEG)
    masks/000000.png ...   optional; foreground = non-zero (PNG: lossless)
    gt/000000.ply ...      optional; ground-truth vertices in the template's vertex order

File names are frame indices ``0 .. N - 1`` with any zero-padding (``000000.png``, ``0000.png``
and ``0.png`` alike); hidden files (``.DS_Store``) are ignored. ``K`` may also be written as
one flat row-major list of 9 numbers.

Conventions
-----------
- Template and ground truth are in camera coordinates (OpenCV: x right, y down, z forward),
  in scene units (metres for the generated sequences); the template has the shape of frame 0.
- ``K`` is in pixels with the image origin at the top-left pixel corner.
- Texture coordinates follow the OBJ convention: ``(u, v)`` in ``[0, 1]``, ``v = 0`` at the
  *bottom* row of the texture image. A vertex may have different ``vt`` in different faces
  (UV seams): the template then carries one ``uv`` per face corner and its vertices stay as
  they are (ground truth and outputs keep their order).
- Ground-truth PLY files may hold faces or only vertices; only the vertices are read.

Everything that can be checked without decoding the frames is checked by
:func:`load_sequence` (file names, counts, image sizes from the headers, camera, template,
ground-truth vertex counts), so that a long optimisation never fails half way. Frames, masks
and ground truth are read lazily, one at a time, so memory does not grow with the sequence.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
import warnings
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from polygeo.io import read_textured_obj, write_ply, write_textured_obj

__all__ = [
    "Template",
    "Sequence",
    "SequenceWriter",
    "load_sequence",
    "load_template",
    "load_camera",
    "write_sequence",
    "read_vertices",
]

# file names are a frame index with any zero-padding (000000.png, 0000.png and 0.png alike);
# frames may also be JPEG, masks stay lossless (a JPEG mask has no clean "non-zero")
_FRAME_RE = re.compile(r"^(\d+)\.(?:png|jpe?g)$", re.IGNORECASE)
_MASK_RE = re.compile(r"^(\d+)\.png$", re.IGNORECASE)
_GT_RE = re.compile(r"^(\d+)\.ply$", re.IGNORECASE)


# --------------------------------------------------------------------------------------------
# Template
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Template:
    """A textured or coloured triangle mesh, in camera coordinates.

    Attributes
    ----------
    verts : np.ndarray
        ``(V, 3)`` float64, scene units (metres), camera coordinates.
    faces : np.ndarray
        ``(F, 3)`` int64 vertex indices, counter-clockwise seen from the front.
    uvs : np.ndarray or None
        Texture coordinates in ``[0, 1]`` (OBJ convention, v up), float64: ``(V, 2)`` per
        vertex, or ``(F, 3, 2)`` per face corner for a template with UV seams (a vertex on a
        seam has a different ``uv`` in the faces on either side; the geometry stays one
        vertex, so ground truth and outputs keep the template's vertex order).
    texture : np.ndarray or None
        ``(Ht, Wt, 3)`` float32 RGB in ``[0, 1]``, row 0 at the top of the image.
    colors : np.ndarray or None
        ``(V, 3)`` float32 RGB vertex colours in ``[0, 1]`` (used when there is no texture).
    """

    verts: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray | None = None
    texture: np.ndarray | None = None
    colors: np.ndarray | None = None

    @property
    def n_verts(self) -> int:
        """Number of vertices ``V``."""
        return int(self.verts.shape[0])

    @property
    def textured(self) -> bool:
        """Whether the appearance is a UV-mapped texture (else vertex colours)."""
        return self.texture is not None


def _check_template(t: Template, where: str) -> None:
    v, f = t.verts, t.faces
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
        raise ValueError(f"{where}: expected a non-empty (V, 3) vertex array, got shape {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
        raise ValueError(f"{where}: expected a non-empty (F, 3) face array, got shape {f.shape}")
    if not np.isfinite(v).all():
        raise ValueError(f"{where}: {int((~np.isfinite(v)).sum())} non-finite vertex coordinates")
    if f.min() < 0 or f.max() >= v.shape[0]:
        raise ValueError(
            f"{where}: face indices must lie in [0, {v.shape[0] - 1}], got [{f.min()}, {f.max()}]"
        )
    if t.texture is None and t.colors is None:
        raise ValueError(f"{where}: the template has neither a texture nor vertex colours")
    if t.texture is not None:
        if t.uvs is None or t.uvs.shape not in ((v.shape[0], 2), (f.shape[0], 3, 2)):
            got = None if t.uvs is None else t.uvs.shape
            raise ValueError(
                f"{where}: a texture needs uvs per vertex (V, 2) = ({v.shape[0]}, 2) or per "
                f"face corner (F, 3, 2) = ({f.shape[0]}, 3, 2), got {got}"
            )
        if not np.isfinite(t.uvs).all():
            raise ValueError(f"{where}: non-finite texture coordinates")
        if t.texture.ndim != 3 or t.texture.shape[2] != 3 or min(t.texture.shape[:2]) < 1:
            raise ValueError(f"{where}: expected an (Ht, Wt, 3) texture, got {t.texture.shape}")
    if t.colors is not None and t.colors.shape != (v.shape[0], 3):
        raise ValueError(f"{where}: expected ({v.shape[0]}, 3) colours, got {t.colors.shape}")


def _read_image(path: Path, what: str) -> np.ndarray:
    """Read an image as float32 in [0, 1]: (H, W, 3) RGB, or (H, W) for what == 'mask'."""
    flag = cv2.IMREAD_UNCHANGED
    img = cv2.imread(str(path), flag)
    if img is None:
        raise ValueError(f"{path}: cannot decode the {what} image")
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    if img.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"{path}: expected an 8 or 16 bit {what} image, got dtype {img.dtype}")
    img = img.astype(np.float32) / scale
    if what == "mask":
        return img if img.ndim == 2 else img[..., :3].max(axis=2)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    return np.ascontiguousarray(img[..., 2::-1] if img.shape[2] >= 3 else img)


def _image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image from its header only."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            return int(im.size[0]), int(im.size[1])
    except Exception as exc:
        raise ValueError(f"{path}: not a readable image ({exc})") from exc


def _load_obj(path: Path) -> Template:
    m = read_textured_obj(path)
    uvs = m.uvs if m.texture is not None else None
    return Template(verts=m.vertices, faces=m.faces, uvs=uvs, texture=m.texture,
                    colors=m.colors)


def _load_ply_template(path: Path) -> Template:
    from polygeo.io import read_mesh

    data = read_mesh(path)
    col = None
    a = data.attributes
    if "colors" in a and np.ndim(a["colors"]) == 2:  # polygeo.io groups red/green/blue
        raw = np.asarray(a["colors"])[:, :3]
    elif all(c in a for c in ("red", "green", "blue")):
        raw = np.stack([np.asarray(a[c]) for c in ("red", "green", "blue")], 1)
    else:
        raw = None
    if raw is not None:
        col = raw.astype(np.float32) / (255.0 if np.issubdtype(raw.dtype, np.integer) else 1.0)
    return Template(verts=data.points, faces=data.faces, colors=col)


def read_vertices(path: str | os.PathLike) -> np.ndarray:
    """Vertex coordinates ``(V, 3)`` float64 of a PLY/OBJ/OFF file, in file order.

    Raises
    ------
    FileNotFoundError, ValueError
        As :func:`polygeo.io.read_points`.
    """
    from polygeo.io import read_points

    return read_points(path).points


def load_template(path: str | os.PathLike) -> Template:
    """Read a template mesh (``.obj`` with its material and texture, or ``.ply`` with colours).

    Parameters
    ----------
    path : str or path-like
        The template file.

    Returns
    -------
    Template
        Validated template.

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    ValueError
        If the file cannot be parsed, is empty, has out-of-range faces, faces without ``vt``
        under a texture, or has neither a texture nor vertex colours (the message names the
        file).
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: template file does not exist")
    suffix = p.suffix.lower()
    if suffix == ".obj":
        t = _load_obj(p)
    elif suffix == ".ply":
        t = _load_ply_template(p)
    else:
        raise ValueError(f"{p}: expected a .obj or .ply template, got {suffix!r}")
    _check_template(t, str(p))
    return t


# --------------------------------------------------------------------------------------------
# Camera
# --------------------------------------------------------------------------------------------


def _check_camera(K: np.ndarray, width: int, height: int, where: str) -> None:
    if K.shape != (3, 3):
        raise ValueError(f"{where}: expected K of shape (3, 3), got {K.shape}")
    if not np.isfinite(K).all():
        raise ValueError(f"{where}: K has non-finite entries")
    if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0.0:
        raise ValueError(
            f"{where}: expected K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}"
        )
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(
            f"{where}: K is not invertible with positive focal lengths: "
            f"fx = {K[0, 0]}, fy = {K[1, 1]}"
        )
    for name, val in (("width", width), ("height", height)):
        if isinstance(val, bool) or not isinstance(val, (int, np.integer)) or val < 1:
            raise ValueError(f"{where}: expected a positive integer {name}, got {val!r}")


def load_camera(path: str | os.PathLike) -> tuple[np.ndarray, int, int]:
    """Read ``camera.json``.

    Parameters
    ----------
    path : str or path-like
        The JSON file: ``{"K": 3x3 list, "width": int, "height": int}`` (``K`` may also be
        a flat row-major list of 9 numbers).

    Returns
    -------
    K : np.ndarray
        ``(3, 3)`` float64 intrinsics in pixels (OpenCV convention).
    width, height : int
        Image size in pixels.

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    ValueError
        If the JSON is malformed, a key is missing, or ``K`` is not an invertible upper
        triangular intrinsic matrix with positive focal lengths.

    Warns
    -----
    RuntimeWarning
        For keys other than ``K``, ``width``, ``height`` (lens distortion, say): ignored.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: camera file does not exist")
    try:
        data = json.loads(p.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{p}: not valid JSON ({exc})") from exc
    if not isinstance(data, dict):
        raise ValueError(f"{p}: expected a JSON object with keys K, width, height")
    missing = [k for k in ("K", "width", "height") if k not in data]
    if missing:
        raise ValueError(f"{p}: missing key(s) {missing}")
    try:
        K = np.asarray(data["K"], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{p}: K is not a numeric 3x3 matrix ({exc})") from exc
    if K.shape == (9,):  # written row-major as one flat list
        K = K.reshape(3, 3)
    _check_camera(K, data["width"], data["height"], str(p))
    extra = sorted(set(data) - {"K", "width", "height"})
    if extra:
        warnings.warn(f"{p}: key(s) {extra} ignored: the format is an ideal pinhole (no lens "
                      "distortion; undistort the frames first)", RuntimeWarning, stacklevel=2)
    return K, int(data["width"]), int(data["height"])


# --------------------------------------------------------------------------------------------
# Sequence
# --------------------------------------------------------------------------------------------


def _check_in_view(verts: np.ndarray, K: np.ndarray, width: int, height: int,
                   where: str) -> None:
    """Refuse a template that is not in front of the camera or not in its image."""
    z = verts[:, 2]
    behind = int((z <= 0).sum())
    if behind:
        raise ValueError(
            f"{where}: {behind} of {len(z)} vertices lie at or behind the camera (z <= 0); "
            "the template must be in camera coordinates (OpenCV: z forward)")
    from polygeo.render.camera import Camera

    cam = Camera(K=K, R=np.eye(3), t=np.zeros(3), width=width, height=height)
    uv = cam.project(np.asarray(verts, dtype=np.float64))[0]  # pixels
    inside = (uv[:, 0] >= 0) & (uv[:, 0] <= width) & (uv[:, 1] >= 0) & (uv[:, 1] <= height)
    if not inside.any():
        raise ValueError(
            f"{where}: no vertex projects into the {width}x{height} image of camera.json "
            f"(pixel range of the template: x {uv[:, 0].min():.0f} .. {uv[:, 0].max():.0f}, "
            f"y {uv[:, 1].min():.0f} .. {uv[:, 1].max():.0f})")


def _check_image_sizes(paths: list[Path], what: str, width: int, height: int) -> None:
    """Raise ``ValueError`` naming the first image whose size is not ``width x height``."""
    for path in paths:
        size = _image_size(path)
        if size != (width, height):
            raise ValueError(
                f"{path}: {what} size {size[0]}x{size[1]} differs from camera.json "
                f"{width}x{height}"
            )


def _numbered(folder: Path, pattern: re.Pattern, what: str, ext: str) -> list[Path]:
    """The files of ``folder`` named by a frame index, in index order.

    Hidden files (``.DS_Store``, editor swap files) are ignored; any other file that does not
    match ``pattern``, an index given twice (``1.png`` and ``000001.png``) or a gap in
    ``0 .. N - 1`` is an error naming the folder.
    """
    files = [f for f in folder.iterdir() if not f.name.startswith(".")]
    bad = sorted(f.name for f in files if not pattern.match(f.name))
    if bad:
        raise ValueError(
            f"{folder}: unexpected {what} file(s) {bad[:5]}; "
            f"expected names 000000.{ext}, 000001.{ext}, ..."
        )
    by_index: dict[int, Path] = {}
    for f in files:
        i = int(pattern.match(f.name).group(1))
        if i in by_index:
            a, b = sorted((by_index[i].name, f.name))
            raise ValueError(f"{folder}: {what} {i} is given twice ({a} and {b})")
        by_index[i] = f
    missing = sorted(set(range(len(files))) - set(by_index))
    if missing:
        raise ValueError(
            f"{folder}: missing {what} {missing[:5]} (expected 0 .. {len(files) - 1})")
    return [by_index[i] for i in range(len(files))]


@dataclass(frozen=True)
class Sequence:
    """A validated SfT sequence; frames, masks and ground truth are read lazily.

    Attributes
    ----------
    root : Path
        The sequence folder.
    template : Template
        The template (camera coordinates, shape of frame 0).
    K : np.ndarray
        ``(3, 3)`` float64 intrinsics in pixels.
    width, height : int
        Image size in pixels.
    frame_paths, mask_paths, gt_paths : tuple of Path
        One per frame; ``mask_paths`` / ``gt_paths`` are empty when absent.
    """

    root: Path
    template: Template
    K: np.ndarray
    width: int
    height: int
    frame_paths: tuple[Path, ...]
    mask_paths: tuple[Path, ...] = ()
    gt_paths: tuple[Path, ...] = ()

    def __len__(self) -> int:
        return len(self.frame_paths)

    @property
    def n_frames(self) -> int:
        """Number of frames."""
        return len(self.frame_paths)

    @property
    def has_masks(self) -> bool:
        """Whether foreground masks are given."""
        return bool(self.mask_paths)

    @property
    def has_gt(self) -> bool:
        """Whether ground-truth meshes are given."""
        return bool(self.gt_paths)

    def frame(self, i: int) -> np.ndarray:
        """Frame ``i`` as ``(H, W, 3)`` float32 RGB in ``[0, 1]``."""
        return _read_image(self.frame_paths[i], "frame")

    def mask(self, i: int) -> np.ndarray | None:
        """Mask ``i`` as ``(H, W)`` float32 in ``{0, 1}`` (foreground = 1), or None."""
        if not self.mask_paths:
            return None
        return (_read_image(self.mask_paths[i], "mask") > 0).astype(np.float32)

    def gt(self, i: int) -> np.ndarray | None:
        """Ground-truth vertices of frame ``i``, ``(V, 3)`` float64, or None."""
        if not self.gt_paths:
            return None
        v = read_vertices(self.gt_paths[i])
        if v.shape[0] != self.template.n_verts:
            raise ValueError(
                f"{self.gt_paths[i]}: {v.shape[0]} vertices, template has {self.template.n_verts}"
            )
        return v


def load_sequence(path: str | os.PathLike) -> Sequence:
    """Open and validate an SfT sequence folder (see the module docstring for the format).

    Parameters
    ----------
    path : str or path-like
        The sequence folder.

    Returns
    -------
    Sequence
        The validated sequence (frames are read on demand).

    Raises
    ------
    FileNotFoundError
        If the folder, the template, ``camera.json`` or ``frames/`` is missing.
    ValueError
        For missing or extra frames, masks or ground truth, image sizes that differ from
        ``camera.json``, a non-invertible ``K``, an empty or broken template, a template
        with a vertex at or behind the camera or none in the image, or a ground-truth mesh
        whose vertex count differs from the template's or that holds NaN / inf. The
        message names the offending file.
    """
    root = Path(path)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: sequence folder does not exist")
    cands = [root / "template.obj", root / "template.ply"]
    present = [c for c in cands if c.is_file()]
    if not present:
        raise FileNotFoundError(f"{root}: no template.obj or template.ply")
    if len(present) > 1:
        raise ValueError(f"{root}: both template.obj and template.ply exist; keep one")
    template = load_template(present[0])
    K, width, height = load_camera(root / "camera.json")
    _check_in_view(template.verts, K, width, height, str(present[0]))
    fdir = root / "frames"
    if not fdir.is_dir():
        raise FileNotFoundError(f"{fdir}: frames folder does not exist")
    frames = _numbered(fdir, _FRAME_RE, "frame", "png")
    if not frames:
        raise ValueError(f"{fdir}: no frames")
    _check_image_sizes(frames, "image", width, height)
    masks: list[Path] = []
    mdir = root / "masks"
    if mdir.is_dir():
        masks = _numbered(mdir, _MASK_RE, "mask", "png")
        if len(masks) != len(frames):
            raise ValueError(f"{mdir}: {len(masks)} masks for {len(frames)} frames")
        _check_image_sizes(masks, "mask", width, height)
    gts: list[Path] = []
    gdir = root / "gt"
    if gdir.is_dir():
        gts = _numbered(gdir, _GT_RE, "ground-truth", "ply")
        if len(gts) != len(frames):
            raise ValueError(f"{gdir}: {len(gts)} ground-truth meshes for {len(frames)} frames")
        for g in gts:  # read each once (one at a time: memory stays flat)
            gv = read_vertices(g)
            if len(gv) != template.n_verts:
                raise ValueError(f"{g}: {len(gv)} vertices, the template has {template.n_verts}")
            if not np.isfinite(gv).all():
                raise ValueError(f"{g}: {int((~np.isfinite(gv)).sum())} non-finite vertex "
                                 "coordinates")
    return Sequence(
        root=root,
        template=template,
        K=K,
        width=width,
        height=height,
        frame_paths=tuple(frames),
        mask_paths=tuple(masks),
        gt_paths=tuple(gts),
    )


# --------------------------------------------------------------------------------------------
# Writer
# --------------------------------------------------------------------------------------------


def _to_uint8(img: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(img)
    if a.dtype == np.uint8:
        return a
    if a.dtype.kind != "f":
        raise TypeError(f"{name}: expected uint8 or float in [0, 1], got dtype {a.dtype}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name}: non-finite pixel values")
    return np.clip(np.rint(a * 255.0), 0, 255).astype(np.uint8)


def _write_obj(root: Path, t: Template) -> None:
    """``template.obj`` (with ``template.mtl`` and ``texture.png`` when textured)."""
    write_textured_obj(root / "template.obj", t.verts, t.faces, uvs=t.uvs, texture=t.texture,
                       colors=None if t.textured else t.colors)


class SequenceWriter:
    """Write a sequence frame by frame into a new folder, made visible atomically on close.

    Parameters
    ----------
    path : str or path-like
        Destination folder. It must not exist (or be empty) unless ``overwrite`` is True.
    template : Template
        The template (camera coordinates; shape of frame 0).
    K : array_like
        ``(3, 3)`` intrinsics in pixels.
    width, height : int
        Image size in pixels.
    overwrite : bool
        Replace an existing folder.

    Raises
    ------
    FileExistsError
        If ``path`` exists, is not empty, and ``overwrite`` is False.
    ValueError
        For an invalid template or camera.

    Examples
    --------
    >>> with SequenceWriter(out, template, K, 128, 128) as w:  # doctest: +SKIP
    ...     w.add_frame(rgb, mask=mask, gt=verts)
    """

    def __init__(
        self,
        path: str | os.PathLike,
        template: Template,
        K: np.ndarray,
        width: int,
        height: int,
        *,
        overwrite: bool = False,
    ) -> None:
        self.path = Path(path)
        if self.path.exists() and any(self.path.iterdir()) and not overwrite:
            raise FileExistsError(f"{self.path}: exists and is not empty (pass overwrite=True)")
        _check_template(template, "template")
        Kn = np.asarray(K, dtype=np.float64)
        _check_camera(Kn, width, height, "camera")
        self.template, self.K, self.width, self.height = template, Kn, int(width), int(height)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", dir=self.path.parent))
        self._n = 0
        self._has_mask: bool | None = None
        self._has_gt: bool | None = None
        _write_obj(self._tmp, template)
        cam = {"K": Kn.tolist(), "width": self.width, "height": self.height}
        (self._tmp / "camera.json").write_text(json.dumps(cam, indent=1) + "\n")
        (self._tmp / "frames").mkdir()

    def add_frame(
        self, rgb: np.ndarray, mask: np.ndarray | None = None, gt: np.ndarray | None = None
    ) -> None:
        """Append one frame.

        Parameters
        ----------
        rgb : np.ndarray
            ``(H, W, 3)`` uint8, or float in ``[0, 1]``.
        mask : np.ndarray, optional
            ``(H, W)`` foreground mask (bool, or numbers > 0 for foreground). Either every
            frame has one or none does.
        gt : np.ndarray, optional
            ``(V, 3)`` ground-truth vertices (same rule as ``mask``).

        Raises
        ------
        ValueError
            For a size mismatch, or a mask / ground truth given for some frames only.
        """
        name = f"{self._n:06d}"
        img = _to_uint8(rgb, "rgb")
        if img.shape != (self.height, self.width, 3):
            want = (self.height, self.width, 3)
            raise ValueError(f"rgb: expected shape {want}, got {img.shape}")
        for flag, val, what in ((self._has_mask, mask, "mask"), (self._has_gt, gt, "gt")):
            if flag is not None and flag != (val is not None):
                raise ValueError(f"{what}: given for some frames only (frame {self._n})")
        self._has_mask, self._has_gt = mask is not None, gt is not None
        cv2.imwrite(str(self._tmp / "frames" / f"{name}.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        if mask is not None:
            m = np.asarray(mask)
            if m.shape != (self.height, self.width):
                want = (self.height, self.width)
                raise ValueError(f"mask: expected shape {want}, got {m.shape}")
            (self._tmp / "masks").mkdir(exist_ok=True)
            m8 = np.where(m > 0, 255, 0).astype(np.uint8)
            cv2.imwrite(str(self._tmp / "masks" / f"{name}.png"), m8)
        if gt is not None:
            g = np.asarray(gt, dtype=np.float64)
            if g.shape != self.template.verts.shape:
                raise ValueError(f"gt: expected shape {self.template.verts.shape}, got {g.shape}")
            (self._tmp / "gt").mkdir(exist_ok=True)
            write_ply(self._tmp / "gt" / f"{name}.ply", g)  # vertices only
        self._n += 1

    def close(self) -> Path:
        """Move the finished sequence into place; return its path."""
        if self._n == 0:
            self.abort()
            raise ValueError("no frames were added")
        os.chmod(self._tmp, 0o755)  # mkdtemp makes it private
        if self.path.exists():
            shutil.rmtree(self.path)
        os.replace(self._tmp, self.path)
        return self.path

    def abort(self) -> None:
        """Discard the partial sequence."""
        shutil.rmtree(self._tmp, ignore_errors=True)

    def __enter__(self) -> SequenceWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def write_sequence(
    path: str | os.PathLike,
    template: Template,
    K: np.ndarray,
    width: int,
    height: int,
    frames: Iterable[np.ndarray],
    masks: Iterable[np.ndarray] | None = None,
    gt: Iterable[np.ndarray] | None = None,
    *,
    overwrite: bool = False,
) -> Path:
    """Write a whole sequence (see :class:`SequenceWriter`); return its path.

    Raises
    ------
    FileExistsError, ValueError
        As :class:`SequenceWriter`; also if ``masks`` or ``gt`` have a different length.
    """
    frames = list(frames)
    ms = list(masks) if masks is not None else [None] * len(frames)
    gs = list(gt) if gt is not None else [None] * len(frames)
    if len(ms) != len(frames) or len(gs) != len(frames):
        raise ValueError(f"frames, masks, gt: lengths differ ({len(frames)}, {len(ms)}, {len(gs)})")
    with SequenceWriter(path, template, K, width, height, overwrite=overwrite) as w:
        for f, m, g in zip(frames, ms, gs):
            w.add_frame(f, mask=m, gt=g)
    return Path(path)
