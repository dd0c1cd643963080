"""``polygeo demo``: the main jobs on embedded defaults, with their accuracy tables.

The core part fits jets to an analytic torus (exact normals and curvatures known) at several
jet orders and noise levels and prints the accuracy and throughput of each setting. Higher
layers add their own parts through the ``polygeo.demo`` entry-point group (PolySfT on the
embedded sample sequence); ``--only jets`` skips them.
"""

from __future__ import annotations

import argparse
import sys
import time
from importlib.metadata import entry_points

import numpy as np


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="run the main jobs on embedded defaults and print their accuracy",
        description="Run the library's main jobs on embedded defaults: jet fitting on an analytic "
        "torus (accuracy against the exact normals and curvatures), then every registered demo "
        "part (PolySfT on the embedded sample sequence).",
    )
    p.add_argument("--points", type=int, default=20000, help="torus sample size (default 20000)")
    p.add_argument("--k", type=int, default=30, help="neighbours per point (default 30)")
    p.add_argument(
        "--only",
        choices=["all", "jets", "parts"],
        default="all",
        help="'jets' runs the core table only, 'parts' only the plug-in parts "
        "(default: all)",
    )
    p.add_argument(
        "--out", default="polygeo-demo",
        help="folder for the plug-in parts' outputs, kept after the run (default: "
        "./polygeo-demo)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_run)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    # Unsigned angle between unoriented directions, in degrees.
    c = np.abs(np.sum(a * b, axis=-1)) / (
        np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1)
    )
    return np.degrees(np.arccos(np.clip(c, 0.0, 1.0)))


def jets_table(n_points: int, k: int) -> list[dict]:
    """Fit jets to a torus at orders 1..4 and noise 0 / 0.1 % / 1 %; return one row per setting."""
    from polygeo import differential_quantities, synthetic

    # warm-up: the first call in a fresh environment compiles the kernels (tens of seconds,
    # announced by polygeo.cli.compile_notice); keep that out of the points/s column
    # (same size as the table: small inputs take the serial kernels, large ones the parallel)
    warm = synthetic.torus(n_points, R=1.0, r=0.4, seed=1)
    for order in (1, 2, 3, 4):
        differential_quantities(warm.points, k=k, order=order, normals=warm.normals)
    rows = []
    for noise in (0.0, 0.001, 0.01):
        sample = synthetic.torus(n_points, R=1.0, r=0.4, seed=0, noise=noise)
        pts = sample.points if noise == 0 else sample.noisy_points
        for order in (1, 2, 3, 4):
            t0 = time.perf_counter()
            dq = differential_quantities(pts, k=k, order=order, normals=sample.normals)
            dt = time.perf_counter() - t0
            ok = dq.status == 0
            ang = _angle_deg(dq.normals[ok], sample.normals[ok])
            row = {
                "noise": noise,
                "order": order,
                "normal_median_deg": float(np.median(ang)),
                "normal_p95_deg": float(np.percentile(ang, 95)),
                "points_per_s": n_points / dt,
                "ok_share": float(ok.mean()),
            }
            if order >= 2:
                h_ref = sample.mean_curvature[ok]
                k_ref = sample.gaussian_curvature[ok]
                row["H_rel_median"] = float(
                    np.median(np.abs(dq.mean_curvature[ok] - h_ref) / np.abs(h_ref))
                )
                k_err = np.abs(dq.gaussian_curvature[ok] - k_ref) / np.maximum(np.abs(k_ref), 1e-3)
                row["K_rel_median"] = float(np.median(k_err))
            rows.append(row)
    return rows


def _print_table(rows: list[dict], n_points: int, k: int) -> None:
    print(f"Jets on a torus (R = 1, r = 0.4), {n_points} random points, k = {k}:")
    print("  noise  order  normal med / p95 (deg)   H rel. err   K rel. err   points/s")
    for r in rows:
        h = f"{r['H_rel_median']:.2e}" if "H_rel_median" in r else "    -   "
        kk = f"{r['K_rel_median']:.2e}" if "K_rel_median" in r else "    -   "
        print(
            f"  {100 * r['noise']:4.1f}%  {r['order']:5d}  {r['normal_median_deg']:9.4f} / "
            f"{r['normal_p95_deg']:8.4f}     {h}     {kk}   {r['points_per_s']:9.0f}"
        )
    print(
        "  (noise: Gaussian, sigma in % of the bounding-box diagonal; curvature errors are "
        "medians of |est - true| / |true|)"
    )


def _run(args: argparse.Namespace) -> int:
    from pathlib import Path

    status = 0
    if args.out:
        args.out = str(Path(args.out).resolve())
    if args.only in ("all", "jets"):
        rows = jets_table(args.points, args.k)
        _print_table(rows, args.points, args.k)
    if args.only in ("all", "parts"):
        for ep in sorted(entry_points(group="polygeo.demo"), key=lambda e: e.name):
            print()
            try:
                part = ep.load()
            except ImportError as exc:
                print(f"polygeo demo: part {ep.name!r} unavailable ({exc})", file=sys.stderr)
                status = 1
                continue
            status = max(status, int(part(args) or 0))
        if args.out:
            print(f"\npolygeo demo: outputs kept in {args.out}")
    return status
