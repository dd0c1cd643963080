"""Generate synthetic SfT sequences with ground truth (textured sheet seen by a pinhole camera).

The frames are rendered with VTK (through pyvista, off screen), a renderer independent of
``polygeo.render``, so that evaluating PolySfT does not grade our soft rasterizer with itself.
VTK is given the exact OpenCV projection of ``K`` (an explicit projection matrix), renders the
texture unlit, with ``--supersample`` x ``--supersample`` samples per pixel averaged into each
output pixel (anti-aliasing); the mask is a second, flat-white pass thresholded at 50 % coverage.

Deformations of the sheet (``--kind``), all functions of the time ``t`` in [0, 1]:

``bend``    isometric: a cylindrical bend whose axis turns (20 -> 55 deg) and shifts over time
``roll``    isometric: one end rolls into a cylinder of shrinking radius
``swave``   isometric: an S-shaped wave travelling across the sheet
``fold``    isometric: a rounded fold along the diagonal closing to about 75 deg
``curl``    isometric, not a sheet: a C-shaped open tube (270 deg, radius 5 cm) opening to
            190 deg and rippling; its template is no height graph over any plane
``cloth``   nearly isometric: moving Gaussian bumps and a travelling ripple (strain <= 1.2 %)
``small``   isometric: a gentle bend (test sequence, small deformation)
``rigid``   no deformation, rigid motion only (test sequence)

Every kind also moves the sheet rigidly a little (a few degrees and about a centimetre). The
template is the frame-0 shape, in camera coordinates, in metres. See ``datasets/README.md``.

Usage::

    python datasets/generate_sft.py --kind bend --out data/bend [--frames 30] [--size 128]
    python datasets/generate_sft.py --all --out data/           # one folder per kind
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

KINDS = ("bend", "roll", "swave", "fold", "cloth", "curl", "small", "rigid")


# --------------------------------------------------------------------------------------------
# Sheet, texture
# --------------------------------------------------------------------------------------------


def sheet_grid(nx: int, ny: int, width: float, height: float):
    """Regular triangulated sheet: material coords (V, 2) in metres, faces (F, 3), uvs (V, 2)."""
    a = np.linspace(-width / 2, width / 2, nx)
    b = np.linspace(-height / 2, height / 2, ny)
    A, B = np.meshgrid(a, b)  # row-major: index = j * nx + i
    ab = np.stack([A.ravel(), B.ravel()], axis=1)
    i, j = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1))
    v00 = (j * nx + i).ravel()
    v10, v01, v11 = v00 + 1, v00 + nx, v00 + nx + 1
    # alternate the diagonal so that the mesh has no preferred direction
    flip = ((i + j) % 2 == 1).ravel()
    f1 = np.where(flip[:, None], np.stack([v00, v10, v11], 1), np.stack([v00, v10, v01], 1))
    f2 = np.where(flip[:, None], np.stack([v00, v11, v01], 1), np.stack([v10, v11, v01], 1))
    faces = np.concatenate([f1, f2]).astype(np.int64)
    uvs = np.stack([(ab[:, 0] / width) + 0.5, (ab[:, 1] / height) + 0.5], axis=1)
    return ab, faces, uvs


def make_texture(size: int, seed: int) -> np.ndarray:
    """A colourful multi-scale texture (size, size, 3) uint8: smooth noise, blobs and strokes."""
    import cv2

    rng = np.random.default_rng(seed)
    img = np.zeros((size, size, 3))
    for scale, weight in ((size / 4, 1.0), (size / 12, 0.7), (size / 40, 0.35)):
        noise = rng.standard_normal((size, size, 3))
        k = int(2 * round(1.5 * scale) + 1)
        sm = cv2.GaussianBlur(noise, (k, k), scale / 2.0, borderType=cv2.BORDER_REFLECT)
        img += weight * sm / (sm.std() + 1e-12)
    img = 1.0 / (1.0 + np.exp(-1.2 * img))
    out = (img * 255).astype(np.uint8)
    for _ in range(int(size / 10)):  # disks and strokes give corners and edges to track
        c = tuple(int(x) for x in rng.integers(0, 256, 3))
        p = tuple(int(x) for x in rng.integers(0, size, 2))
        if rng.random() < 0.5:
            r = int(rng.integers(size // 60 + 1, size // 15 + 2))
            cv2.circle(out, p, r, c, -1, lineType=cv2.LINE_AA)
        else:
            q = tuple(int(x) for x in rng.integers(0, size, 2))
            cv2.line(out, p, q, c, max(1, size // 100), lineType=cv2.LINE_AA)
    return cv2.GaussianBlur(out, (3, 3), 0.6)


# --------------------------------------------------------------------------------------------
# Deformations (object frame: the flat sheet lies in z = 0)
# --------------------------------------------------------------------------------------------


def developable(ab: np.ndarray, theta: float, psi, s_range: float) -> np.ndarray:
    """Isometric generalised cylinder: rulings along direction ``theta`` of the material plane.

    The cross-section curve has turning angle ``psi(s)`` at arc length ``s`` (perpendicular to
    the rulings); it is integrated with 20001 trapezoid steps, so the map is isometric up to
    ~1e-9 relative error.
    """
    d = np.array([np.cos(theta), np.sin(theta)])
    n = np.array([-np.sin(theta), np.cos(theta)])
    s = ab @ n
    r = ab @ d
    grid = np.linspace(-s_range, s_range, 20001)
    ps = psi(grid)
    c, si = np.cos(ps), np.sin(ps)
    ds = grid[1] - grid[0]
    x = np.concatenate([[0.0], np.cumsum(0.5 * (c[1:] + c[:-1]) * ds)])
    z = np.concatenate([[0.0], np.cumsum(0.5 * (si[1:] + si[:-1]) * ds)])
    x0, z0 = np.interp(0.0, grid, x), np.interp(0.0, grid, z)
    xs, zs = np.interp(s, grid, x) - x0, np.interp(s, grid, z) - z0
    out = np.zeros((len(ab), 3))
    out[:, :2] = r[:, None] * d[None] + xs[:, None] * n[None]
    out[:, 2] = zs
    return out


def smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def deform(kind: str, ab: np.ndarray, t: float, size: tuple[float, float]) -> np.ndarray:
    """Deformed sheet (V, 3) in the object frame at time t in [0, 1]."""
    w, h = size
    sr = 0.6 * np.hypot(w, h) + 0.01
    if kind == "bend":
        theta = np.radians(20.0 + 35.0 * t)
        kappa = 4.0 + 6.0 * np.sin(np.pi * t) ** 2  # 1/m: radius 25 cm -> 10 cm
        s0 = 0.02 * np.sin(2 * np.pi * t)
        return developable(ab, theta, lambda s: kappa * (s - s0), sr)
    if kind == "small":
        kappa = 1.0 + 2.0 * t  # radius 1 m -> 33 cm
        return developable(ab, np.radians(10.0), lambda s: kappa * s, sr)
    if kind == "roll":
        kappa = 1e-6 + 28.0 * t  # radius -> 3.6 cm
        s0 = -0.01
        return developable(ab, np.pi / 2, lambda s: kappa * np.maximum(s - s0, 0.0), sr)
    if kind == "swave":
        lam, amp = 0.24, 0.5
        return developable(ab, np.pi / 2, lambda s: amp * np.sin(2 * np.pi * (s / lam - t)), sr)
    if kind == "fold":
        theta = np.arctan2(h, w)  # the diagonal
        phi, width = np.radians(75.0) * t, 0.035
        return developable(ab, theta, lambda s: phi * smoothstep((s + width / 2) / width), sr)
    if kind == "curl":
        # turning angle 270 deg -> 189 deg over the width, centred on the sheet; the tube
        # opens towards the camera (negative curvature in the object frame)
        kappa = 1.5 * np.pi / w * (1.0 - 0.3 * t)
        ripple = 0.3 * np.sin(np.pi * t)
        return developable(ab, np.pi / 2,
                           lambda s: -kappa * s + ripple * np.sin(2 * np.pi * s / w), sr)
    if kind == "cloth":
        out = np.zeros((len(ab), 3))
        out[:, :2] = ab
        z = np.zeros(len(ab))
        centres = [(-0.05 + 0.08 * t, 0.03), (0.06, -0.04 + 0.06 * t), (0.0, 0.0)]
        amps = [0.005 * np.sin(np.pi * t + 0.3), -0.0045, 0.004 * np.cos(np.pi * t)]
        for (cx, cy), a in zip(centres, amps):
            z += a * np.exp(-((ab[:, 0] - cx) ** 2 + (ab[:, 1] - cy) ** 2) / (2 * 0.045**2))
        z += 0.0015 * np.sin(2 * np.pi * (ab[:, 0] / 0.15 + ab[:, 1] / 0.25 - t))
        out[:, 2] = z
        return out
    if kind == "rigid":
        out = np.zeros((len(ab), 3))
        out[:, :2] = ab
        return out
    raise ValueError(f"kind: expected one of {list(KINDS)}, got {kind!r}")


def rot(axis: str, deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def pose(kind: str, t: float, distance: float) -> tuple[np.ndarray, np.ndarray]:
    """Object-to-camera rotation (3, 3) and translation (3,) at time t (metres)."""
    amp = 2.0 if kind == "rigid" else 1.0
    R = rot("x", -30.0 + 4.0 * amp * np.sin(np.pi * t)) @ rot("y", 8.0 + 4.0 * amp * t)
    R = R @ rot("z", 5.0 + 3.0 * amp * t)
    T = np.array([0.008 * amp * np.sin(2 * np.pi * t), 0.006 * amp * t, distance + 0.01 * amp * t])
    return R, T


# --------------------------------------------------------------------------------------------
# Rendering with VTK (independent of polygeo.render)
# --------------------------------------------------------------------------------------------


class VTKRenderer:
    """Off-screen VTK renderer with an exact OpenCV pinhole projection (unlit texture)."""

    def __init__(self, K, width, height, faces, uvs, texture, supersample=4, background=0.0):
        import pyvista as pv
        import vtk

        self.pv, self.vtk = pv, vtk
        # the X-server probe before the EGL fallback logs a harmless warning: silence it
        vtk.vtkLogger.SetStderrVerbosity(vtk.vtkLogger.VERBOSITY_OFF)
        self.S = int(supersample)
        self.W, self.H = int(width), int(height)
        Ks = np.asarray(K, float).copy()
        Ks[:2] *= self.S  # pixel-corner convention: scaling K scales the image exactly
        self.Ks = Ks
        self.faces = np.hstack([np.full((len(faces), 1), 3), faces]).astype(np.int64).ravel()
        self.uvs = np.asarray(uvs, float)
        self.texture = pv.Texture(np.ascontiguousarray(texture))
        self.texture.interpolate = True
        self.background = background

    def _plotter(self, mesh, textured):
        pv, vtk = self.pv, self.vtk
        W, H = self.W * self.S, self.H * self.S
        p = pv.Plotter(off_screen=True, window_size=(W, H))
        p.background_color = (self.background,) * 3
        if textured:
            p.add_mesh(mesh, texture=self.texture, lighting=False)
        else:
            p.add_mesh(mesh, color="white", lighting=False)
        pts = mesh.points
        n, f = 0.5 * float(pts[:, 2].min()), 2.0 * float(pts[:, 2].max())
        fx, fy, cx, cy = self.Ks[0, 0], self.Ks[1, 1], self.Ks[0, 2], self.Ks[1, 2]
        P = np.array(
            [
                [2 * fx / W, -2 * self.Ks[0, 1] / W, 1 - 2 * cx / W, 0],
                [0, 2 * fy / H, 2 * cy / H - 1, 0],
                [0, 0, (f + n) / (n - f), 2 * f * n / (n - f)],
                [0, 0, -1, 0],
            ]
        )
        cam = p.renderer.GetActiveCamera()
        cam.SetPosition(0, 0, 0)
        cam.SetFocalPoint(0, 0, 1)
        cam.SetViewUp(0, -1, 0)
        m = vtk.vtkMatrix4x4()
        for i in range(4):
            for j in range(4):
                m.SetElement(i, j, P[i, j])
        cam.SetExplicitProjectionTransformMatrix(m)
        cam.SetUseExplicitProjectionTransformMatrix(True)
        cam.SetClippingRange(n, f)
        p.camera_set = True  # stop pyvista from resetting the camera on the first render
        return p

    def render(self, verts):
        """RGB (H, W, 3) float in [0, 1] and coverage alpha (H, W) in [0, 1]."""
        mesh = self.pv.PolyData(np.asarray(verts, float), self.faces)
        mesh.active_texture_coordinates = self.uvs
        out = []
        for textured in (True, False):
            p = self._plotter(mesh, textured)
            img = p.screenshot(return_img=True).astype(np.float64) / 255.0
            p.close()
            img = img.reshape(self.H, self.S, self.W, self.S, 3).mean(axis=(1, 3))
            out.append(img)
        return out[0], out[1].mean(axis=2)


# --------------------------------------------------------------------------------------------
# Sequences
# --------------------------------------------------------------------------------------------


@dataclass
class Config:
    kind: str = "bend"
    frames: int = 30
    size: int = 128
    grid: tuple[int, int] = (60, 45)
    sheet: tuple[float, float] = (0.24, 0.18)
    distance: float = 0.40
    focal: float = 1.3  # focal length in units of the image width
    texture_size: int = 512
    supersample: int = 4
    seed: int = 0
    t_end: float = 1.0  # frames sample t in [0, t_end] (a shorter, slower clip when < 1)


def sequence_geometry(cfg: Config):
    """Yield (t, camera-frame vertices (V, 3)) for each frame, and return mesh data first."""
    ab, faces, uvs = sheet_grid(cfg.grid[0], cfg.grid[1], *cfg.sheet)
    verts = []
    for i in range(cfg.frames):
        t = cfg.t_end * i / max(cfg.frames - 1, 1)
        X = deform(cfg.kind, ab, t, cfg.sheet)
        R, T = pose(cfg.kind, t, cfg.distance)
        verts.append(X @ R.T + T)
    return ab, faces, uvs, verts


def generate(cfg: Config, out: Path, overwrite: bool = False, progress: bool = True) -> Path:
    """Generate one sequence folder (see sft.data for the format)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from sft.data import SequenceWriter, Template

    ab, faces, uvs, verts = sequence_geometry(cfg)
    tex = make_texture(cfg.texture_size, cfg.seed)
    f = cfg.focal * cfg.size
    K = np.array([[f, 0.0, cfg.size / 2], [0.0, f, cfg.size / 2], [0.0, 0.0, 1.0]])
    template = Template(verts=verts[0], faces=faces, uvs=uvs, texture=tex.astype(np.float32) / 255)
    renderer = VTKRenderer(K, cfg.size, cfg.size, faces, uvs, tex, cfg.supersample)
    it = range(cfg.frames)
    if progress:
        from tqdm import tqdm

        it = tqdm(it, desc=f"render {cfg.kind}", unit="frame")
    with SequenceWriter(out, template, K, cfg.size, cfg.size, overwrite=overwrite) as w:
        for i in it:
            rgb, alpha = renderer.render(verts[i])
            w.add_frame(rgb, mask=alpha >= 0.5, gt=verts[i])
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--kind", choices=KINDS, default="bend")
    ap.add_argument("--all", action="store_true", help="generate every kind into OUT/<kind>")
    ap.add_argument("--out", required=True, help="output folder")
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--size", type=int, default=128, help="image width = height in pixels")
    ap.add_argument("--grid", type=int, nargs=2, default=(60, 45), metavar=("NX", "NY"))
    ap.add_argument("--texture-size", type=int, default=512)
    ap.add_argument("--supersample", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--t-end", type=float, default=1.0,
                    help="the frames cover t in [0, T_END] of the motion (default 1)")
    ap.add_argument("--overwrite", action="store_true")
    ap.add_argument("--quiet", action="store_true")
    a = ap.parse_args(argv)
    kinds = KINDS if a.all else (a.kind,)
    for k in kinds:
        cfg = Config(
            kind=k,
            frames=a.frames,
            size=a.size,
            grid=tuple(a.grid),
            texture_size=a.texture_size,
            supersample=a.supersample,
            seed=a.seed,
            t_end=a.t_end,
        )
        out = Path(a.out) / k if a.all else Path(a.out)
        generate(cfg, out, overwrite=a.overwrite, progress=not a.quiet)
        print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
