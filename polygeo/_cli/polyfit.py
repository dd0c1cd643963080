"""``polygeo polyfit MESH -o patches.npz``: fit oriented n-jet patches (PolyFit) to a surface."""

from __future__ import annotations

import argparse
import sys
import time


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "polyfit",
        help="partition a mesh or point cloud into patches and fit an oriented n-jet to each",
        description="PolyFit (thesis 5.2): ACVD partition, PCA/STN/optimised frames, batched "
        "n-jet fits. Prints per-set quality (height RMSE, normal error, boundary gap, foldover "
        "share, Chamfer x 1e3 against the input normalised to the unit sphere) and writes the "
        "patch set as NPZ.",
    )
    p.add_argument("mesh", help="input mesh or point cloud (.ply .obj .off .stl .npz .xyz "
                   ".txt .csv .npy), in any length unit")
    p.add_argument("-o", "--output", required=True,
                   help="output patch set (.npz; required, replaced atomically)")
    p.add_argument("--patches", type=int, default=None, metavar="K",
                   help="number of patches K (a count of patches, not an area, so it does not "
                   "depend on the input's units; default scale-free: about 6 vertices per jet "
                   "coefficient, at most 400)")
    p.add_argument("--order", default="4", metavar="N|auto",
                   help="jet order 1..6 or 'auto' (default 4)")
    p.add_argument("--tol", type=float, default=None, metavar="HEIGHT",
                   help="height tolerance for --order auto (input units; default: BIC)")
    p.add_argument("--target-rmse", type=float, default=None, metavar="RMSE",
                   help="choose K so that the overall height RMSE is at most this (input "
                   "units; default: none, K from --patches)")
    p.add_argument("--orient", choices=("pca", "stn", "optimize"), default="pca",
                   help="patch canonicalisation (default pca)")
    p.add_argument("--resample", type=int, default=None, metavar="R",
                   help="subdivision level of the resampled surface (used for the Chamfer "
                   "distance, the deviation check and --mesh-out; default 2: level 0 samples "
                   "only the input vertices and misses a surface that leaves the input "
                   "between them)")
    p.add_argument("--mesh-out", default=None, metavar="PLY",
                   help="write the resampled surface as PLY (default: not written)")
    p.add_argument("--chamfer-samples", type=int, default=10000, metavar="N",
                   help="input samples for the Chamfer distances (0 disables; default 10000, "
                   "Table 5.1)")
    p.add_argument("--chamfer-dense", type=int, default=100000, metavar="N",
                   help="samples of the resampled surface for the dense (AtlasNet-style) point "
                   "protocol (default 100000)")
    p.add_argument("--seed", type=int, default=0,
                   help="partition and sampling seed (default 0)")
    p.add_argument("--json", default=None, metavar="PATH",
                   help="also write the summary as JSON (default: not written)")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    import json

    from polygeo.cli import int_or_auto
    from polygeo.io import read_points, write_ply
    from polygeo.patches import PatchSet
    from polygeo.proximity import chamfer_report

    order = int_or_auto(args.order, "order", low=1, high=6)
    data = read_points(args.mesh)
    t0 = time.perf_counter()
    ps = PatchSet.fit(
        data.points,
        data.faces,
        n_patches=args.patches,
        order=order,
        orient=args.orient,
        normals=data.normals,
        target_rmse=args.target_rmse,
        tol=args.tol,
        seed=args.seed,
    )
    t_fit = time.perf_counter() - t0
    out = ps.save(args.output)
    m = ps.metrics()
    s = m.summary()
    level = (2 if data.faces is not None else 0) if args.resample is None else args.resample
    rv, rf = ps.resample(level)  # NumPy: the points were read as NumPy
    deviation = None
    if data.faces is not None:
        deviation = _deviation(rv, data.points, data.faces)
    chamfer = None
    if args.chamfer_samples and data.faces is not None:
        chamfer = chamfer_report(data.points, data.faces, rv, rf,
                                 n_samples=args.chamfer_samples, n_dense=args.chamfer_dense,
                                 seed=args.seed)
    if args.mesh_out:
        write_ply(args.mesh_out, rv, rf)
    lines = [
        f"input            {args.mesh}: {len(data.points)} vertices"
        + (f", {len(data.faces)} faces" if data.faces is not None else " (point cloud)"),
        f"patches          {ps.n_patches} (orient {ps.orient}, orders "
        f"{int(m.order.min())}..{int(m.order.max())}, {ps.n_coefficients} parameters)",
        f"fit time         {t_fit:.3f} s (partition included)",
        f"height RMSE      mean {s['height_rmse_mean']:.3e}  max {s['height_rmse_max']:.3e}  "
        f"all points {s['height_rmse_all']:.3e}",
    ]
    if "normal_error_mean" in s:
        lines.append(f"normal error     {s['normal_error_mean']:.3f} deg")
    lines.append(
        f"boundary gap     mean {s['boundary_gap_mean']:.3e}  max {s['boundary_gap_max']:.3e}  "
        f"normal angle {s['boundary_normal_angle_mean']:.3f} deg"
    )
    if "foldover_mean" in s:
        lines.append(
            f"foldover share   {s['foldover_mean']:.4f} ({s['foldover_patches']} patches)"
        )
    if chamfer is not None:
        c = chamfer.as_dict()
        lines += [
            f"Chamfer x 1e3    resample level {level}, input normalised to the unit sphere, "
            f"{chamfer.n_samples} input samples:",
            f"  surface        {c['surface']:.3e}  (point-to-surface: measures the "
            "reconstruction)",
            f"  points         {c['points']:.4f}  (Table 5.1 point protocol, "
            f"{chamfer.n_samples} samples each; sampling floor {c['points_floor']:.4f})",
            f"  dense points   {c['dense']:.4f}  ({chamfer.n_dense} reconstruction samples; "
            f"sampling floor {c['dense_floor']:.4f})",
        ]
    warn = None
    if deviation is not None:
        lines.append(
            f"deviation        resampled level {level} vs input, / bounding-box diagonal: "
            f"p99 {deviation['p99']:.2e}  max {deviation['max']:.2e}  "
            f"beyond 1 %: {100 * deviation['share_1pc']:.2f} % of points"
        )
        if deviation["max"] > 0.01:
            warn = (f"polygeo polyfit: warning: the fitted surface leaves the input by up to "
                    f"{100 * deviation['max']:.1f} % of its size between vertices "
                    f"({100 * deviation['share_1pc']:.2f} % of the level-{level} points beyond "
                    "1 %): spikes or fins; try fewer patches (--patches) or a lower --order")
    if "search" in ps.info:
        for rec in ps.info["search"]:
            lines.append(f"  K search       requested {rec['requested']}: {rec['patches']} "
                         f"patches, height RMSE {rec['height_rmse']:.3e}")
    lines.append(f"wrote            {out}" + (f", {args.mesh_out}" if args.mesh_out else ""))
    print("\n".join(lines))
    if warn:
        print(warn, file=sys.stderr)
    if args.json:
        ch = {} if chamfer is None else chamfer._asdict()
        rec = dict(s, chamfer=ch.get("points"), chamfer_floor=ch.get("points_floor"),
                   chamfer_dense=ch.get("dense"), chamfer_dense_floor=ch.get("dense_floor"),
                   chamfer_surface=ch.get("surface"), chamfer_samples=ch.get("n_samples"),
                   chamfer_dense_samples=ch.get("n_dense"), fit_seconds=t_fit,
                   n_coefficients=ps.n_coefficients, orient=ps.orient, resample_level=level,
                   deviation=deviation)
        with open(args.json, "w") as fh:
            json.dump(rec, fh, indent=1)
    sys.stdout.flush()
    return 0


def _deviation(rv, v, f) -> dict:
    """Distances of the resampled points to the input surface, over its bounding-box diagonal."""
    import numpy as np

    from polygeo.proximity import squared_distance_to_mesh

    diag = float(np.linalg.norm(v.max(0) - v.min(0))) or 1.0
    d = np.sqrt(squared_distance_to_mesh(np.asarray(rv), v, f)) / diag
    return {"p99": float(np.percentile(d, 99)), "max": float(d.max()),
            "share_1pc": float((d > 0.01).mean())}
