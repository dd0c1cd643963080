"""``polygeo jets``: per-point normals and curvatures of a point cloud or mesh file."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

_DESCRIPTION = """\
Estimate per-point differential quantities (normals, principal curvatures and directions,
mean and Gaussian curvature) by fitting n-jets (Cazals & Pouget 2005) to the neighbourhood of
every point, and write them to an NPZ file (and optionally a PLY file).

Input formats: .ply (ASCII or binary; nx/ny/nz are used to orient the normals), .obj, .off,
.stl (meshes: the face winding orients the normals), text clouds .xyz/.txt/.csv/.asc/.pts
(comma or space separated, optional header line of names), .npy ((N, C) array), .npz (key
'points' or 'vertices', optional 'normals', 'faces'). Columns of a text or NPY cloud: given
by --columns, else by a header line of names (x y z nx ny nz ...), else x y z first and
columns 4-6 are normals only if there are exactly six and all are unit vectors (so
'x y z r g b' keeps its colours apart).

Output NPZ keys (exactly): points (N,3), normals (N,3), k1 (N,), k2 (N,) with k1 >= k2,
d1 (N,3), d2 (N,3), mean_curvature (N,), gaussian_curvature (N,), status (N,).

Sign convention: curvature is positive where the surface bends towards the normal. With
outward normals a sphere of radius r has k1 = k2 = H = -1/r and K = 1/r^2. Normals are
oriented by the input normals if present, else by the mesh faces (made consistent, outward
for closed surfaces), else by propagation over the neighbour graph (outward at the extreme
points of each connected piece).

Status codes: 0 ok; 1 nonfinite input (the point is NaN/inf: its values are NaN); 2 too few
points (fewer distinct neighbours than jet coefficients); 3 order reduced (degenerate
neighbourhood, e.g. a single scan line: fitted at a lower order); 4 degenerate (normal from
PCA only, curvature 0); 5 ill conditioned; 6 not a graph; 7 non manifold (the
neighbourhood reaches an edge shared by more than two faces, e.g. a fin). Values of non-zero
statuses other than 1 are finite fallbacks: treat them as unreliable.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "jets",
        help="per-point normals and curvatures of a point cloud or mesh (n-jet fitting)",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "input",
        help="point cloud or mesh file (.ply .obj .off .xyz .txt .npy .npz .las .laz), or a "
        "quoted pattern such as 'scans/*.laz' (then -o is a folder)",
    )
    p.add_argument(
        "--columns",
        default=None,
        help="names of the columns of a text or .npy cloud, e.g. 'x y z nx ny nz' or "
        "'x,y,z,r,g,b' (must include x, y, z; nx ny nz are normals; others are ignored; default: "
        "a header line of names, else the rule above)",
    )
    p.add_argument(
        "-o",
        "--output",
        required=True,
        help="output .npz file, or .las/.laz for a LAS/LAZ input (written atomically)",
    )
    p.add_argument(
        "--k",
        default="20",
        help="nearest neighbours per point besides the point itself, as in CGAL (default 20; "
        "at least the number of jet coefficients minus one: 2, 5, 9, 14 for orders 1-4), or "
        "'auto' to choose per point from 12..384 by a bias-variance rule",
    )
    p.add_argument(
        "--radius",
        type=float,
        default=None,
        help="use all neighbours within this distance (input units) instead of the k nearest "
        "(default: none, --k)",
    )
    p.add_argument(
        "--order",
        default="2",
        help="jet order 1-4 (default 2), or 'auto' to pick per point the lowest order that "
        "higher ones do not improve significantly (F-test on the fit residuals)",
    )
    p.add_argument(
        "--rings",
        type=int,
        default=None,
        help="meshes only: use the RINGS-ring of each vertex as its neighbourhood (default: "
        "none, --k)",
    )
    p.add_argument(
        "--weights",
        choices=["uniform", "gaussian"],
        default="uniform",
        help="least-squares weights: uniform (CGAL) or Gaussian in the distance (default "
        "uniform)",
    )
    p.add_argument(
        "--interpolate",
        action="store_true",
        help="make each jet pass through its point (for exact samples, e.g. vertices of an "
        "analytic or subdivision surface: smaller order-2 curvature bias; worse on noisy data)",
    )
    p.add_argument(
        "--orient",
        choices=["auto", "input", "mesh", "propagate", "none", "up"],
        default="auto",
        help="where the normals' signs come from (default auto: input normals, else mesh, "
        "else propagation; up: towards +z, per point, the default of tiled runs)",
    )
    p.add_argument("--ply", default=None,
                   help="also write a binary PLY with the same attributes (default: none)")
    p.add_argument("--quiet", action="store_true", help="no progress bar and no summary")
    from polygeo._cli.jets_large import add_arguments

    add_arguments(p)  # LAS/LAZ, tiles, Dask, batches
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from polygeo._cli import jets_large

    if jets_large.wants(args):  # LAS/LAZ, tiles, Dask, batches
        return jets_large.run(args)
    from polygeo.cli import int_or_auto
    from polygeo.estimate import differential_quantities
    from polygeo.io import read_points, write_npz, write_ply
    from polygeo.status import describe

    out = Path(args.output)
    if out.suffix.lower() != ".npz":
        raise ValueError(f"-o/--output: expected a .npz path, got {str(out)!r}")
    k = int_or_auto(args.k, "k")
    order = int_or_auto(args.order, "order")
    t0 = time.perf_counter()
    data = read_points(args.input, columns=args.columns)
    t_read = time.perf_counter() - t0
    n_finite = int(np.isfinite(data.points).all(axis=1).sum())
    if isinstance(k, int) and args.radius is None and args.rings is None and k >= n_finite:
        raise ValueError(f"--k: {k} neighbours requested but {args.input} has {n_finite} "
                         f"finite points (at most {n_finite - 1} neighbours each)")
    t1 = time.perf_counter()
    dq = differential_quantities(
        data.points,
        faces=data.faces,
        normals=data.normals,
        k=k,
        radius=args.radius,
        rings=args.rings,
        order=order,
        weights=None if args.weights == "uniform" else "gaussian",
        orient=args.orient,
        interpolate=bool(args.interpolate),
        progress=False if args.quiet else None,
    )
    t_fit = time.perf_counter() - t1
    fields = {
        "points": data.points,
        "normals": dq.normals,
        "k1": dq.k1,
        "k2": dq.k2,
        "d1": dq.d1,
        "d2": dq.d2,
        "mean_curvature": dq.mean_curvature,
        "gaussian_curvature": dq.gaussian_curvature,
        "status": dq.status.astype(np.int64),
    }
    write_npz(out, **fields)
    if args.ply:
        attrs = {k_: v for k_, v in fields.items() if k_ not in ("points", "normals")}
        write_ply(args.ply, data.points, data.faces, attrs, normals=dq.normals)
    if not args.quiet:
        n = len(dq)
        kind = "mesh" if data.faces is not None else "point cloud"
        lines = [f"polygeo jets: {args.input} ({kind}, {n} points)"]
        lines.append(
            f"  k={args.k} order={args.order} radius={args.radius} orient={args.orient}"
        )
        st = dq.status
        for code in np.unique(st):
            lines.append(f"  status {int(code)} ({describe(int(code))}): {int((st == code).sum())}")
        ok = st == 0
        for name in ("k1", "k2", "mean_curvature", "gaussian_curvature"):
            v = getattr(dq, name)[ok]
            if v.size:
                q = np.percentile(v, [0, 5, 50, 95, 100])
                lines.append(
                    f"  {name:<18} min {q[0]: .4g}  p5 {q[1]: .4g}  median {q[2]: .4g}  "
                    f"p95 {q[3]: .4g}  max {q[4]: .4g}"
                )
        rate = n / t_fit if t_fit > 0 else float("inf")
        lines.append(f"  time: read {t_read:.2f} s, estimate {t_fit:.2f} s ({rate:,.0f} points/s)")
        lines.append(f"  wrote {out}" + (f" and {args.ply}" if args.ply else ""))
        print("\n".join(lines), file=sys.stdout)
    return 0
