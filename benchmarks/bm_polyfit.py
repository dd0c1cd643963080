"""PolyFit benchmark: accuracy against fitting time for PCA, STN and test-time-optimised frames.

Sections (all measured in one run, baselines included):

* ``families``: held-out patches of the four synthetic families of thesis §5.5.1 (irregular,
  noisy, randomly rotated), jet orders 2-6: mean height RMSE (canonical units), normal
  error against the exact normals (degrees) and time per patch, for ``pca``, ``stn`` and
  ``optimize``; ratios to PCA (the baseline). ``stn`` rows are the network alone and also
  give the guarded figure (its rotation kept only where the residual is below PCA's, as
  :meth:`polygeo.patches.PatchSet.fit` applies it).
* ``meshes``: analytic meshes (sphere, torus, cylinder, wavy sheet), a body-like closed
  mesh and garment-like meshes (draped sheet, skirt) never seen in training: K in
  {1, 25, 100, 400} and orders 2-6 with PCA frames (height RMSE, normal error, boundary gap,
  foldover share, fit time, Chamfer x 1e3), and at the default K the three orientations.
  Chamfer protocol (:func:`polygeo.proximity.chamfer_distance`): the fitted surface is
  resampled once (level 1) and compared with the input, both normalised by the input's
  unit-sphere similarity, with 10k input samples and squared distances (thesis Table 5.1,
  AtlasNet). Three figures: ``chamfer_x1e3`` the point protocol (10k samples on each
  side); ``chamfer_dense_x1e3`` the same with the reconstruction densely sampled (100k
  points, as AtlasNet takes all the points its charts produce); ``chamfer_surface_x1e3``
  point-to-surface distances (the continuous Chamfer distance). The point protocols have a
  sampling floor, measured per mesh as the input against an independent sampling of itself
  with the same counts (``chamfer_floor_x1e3``, ``chamfer_dense_floor_x1e3``): the
  baseline. The <= 0.2 target is judged on the surface Chamfer distance, which measures the
  reconstruction; the point figures are reported with their floors.
* ``speed``: a 100k-vertex mesh, K = 400, order 4, PCA: partition and fit times.
* ``stn_inference``: per-patch STN inference time.
* ``parsimony``: parameters used against height error (``order="auto"`` tolerances, fixed
  orders; ``target_rmse`` patch-count search).

Kernels (jets of every order, partition, resampling, Chamfer) are compiled or loaded from
numba's cache on a small mesh before any timing; the time it took is recorded apart
(``warmup_s``).

Writes ``bm_polyfit.json`` and ``bm_polyfit.png`` into ``benchmarks/results/`` (``--out``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import matplotlib
import numpy as np
import torch

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from tqdm.auto import tqdm  # noqa: E402

import polygeo.synthetic as syn  # noqa: E402
from polygeo import jets  # noqa: E402
from polygeo.canonical import canonicalize, height_residual, optimize_rotations  # noqa: E402
from polygeo.partition import default_n_patches, mesh_area, partition_mesh  # noqa: E402
from polygeo.patches import PatchSet  # noqa: E402
from polygeo.proximity import chamfer_distance  # noqa: E402
from polygeo.stn import load_pretrained, stn_rotations  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from run_env import environment, finish  # noqa: E402

ORIENTS = ("pca", "stn", "optimize")
HELD_OUT_SEED = 10**6 + 7


def _now() -> float:
    return time.perf_counter()


# ------------------------------------------------------------------------------ families


def _family_normals_error(local, mask, Q, R_pca, fit, normals_true) -> float:
    """Mean unsigned angle (deg) between fitted normals (world) and exact normals."""
    y = local @ Q
    uv = y[..., :2]
    d = jets.derivatives(fit.coeffs.to(torch.float64), uv, max_order=1)
    n_loc = torch.stack([-d[(1, 0)], -d[(0, 1)], torch.ones_like(d[(1, 0)])], -1)
    n_loc = n_loc / n_loc.norm(dim=-1, keepdim=True)
    n_world = n_loc @ (R_pca @ Q).transpose(1, 2)
    c = (n_world * normals_true).sum(-1).abs().clamp(max=1.0)
    ang = torch.rad2deg(torch.arccos(c))
    return float(ang[mask].mean())


def bench_families(n: int, orders, bar) -> list[dict]:
    fp = syn.family_patches(n, 128, noise=0.01, seed=HELD_OUT_SEED)
    pts = torch.from_numpy(fp.points)
    nrm = torch.from_numpy(fp.normals)
    net = load_pretrained()
    out = []
    for order in orders:  # warm-up: compile the numba kernels of every order
        c = canonicalize(pts[:4])
        jets.fit(c.local[..., :2], c.local[..., 2], order, mask=c.mask)
        stn_rotations(c.local, c.mask, net)
    for order in orders:
        base = None
        for orient in ORIENTS:
            t0 = _now()
            c = canonicalize(pts)
            if orient == "pca":
                Q = torch.eye(3, dtype=torch.float64).expand(n, 3, 3)
            elif orient == "stn":
                Q = stn_rotations(c.local, c.mask, net)
            else:
                Q = optimize_rotations(c.local, c.mask, order).rotation
            y = c.local @ Q
            fit = jets.fit(y[..., :2], y[..., 2], order, mask=c.mask)
            sec = _now() - t0
            r, _ = height_residual(c.local, c.mask, Q, order)
            rec = {
                "section": "families",
                "orient": orient,
                "order": order,
                "patches": n,
                "height_rmse": float(r.mean()),
                "normal_deg": _family_normals_error(
                    c.local, c.mask, Q, c.orientation.R, fit, nrm
                ),
                "seconds": sec,
                "ms_per_patch": 1e3 * sec / n,
            }
            if orient == "pca":
                base, r_pca = rec, r
            rec["rmse_ratio_to_pca"] = rec["height_rmse"] / base["height_rmse"]
            rec["normal_ratio_to_pca"] = rec["normal_deg"] / base["normal_deg"]
            if orient == "stn":  # as PatchSet.fit applies it: kept where it beats PCA
                rec["height_rmse_guarded"] = float(torch.minimum(r, r_pca).mean())
                rec["rmse_ratio_to_pca_guarded"] = rec["height_rmse_guarded"] / base["height_rmse"]
            out.append(rec)
            bar.update(1)
    return out


def _grid_family(n: int, m: int, seed: int):
    """Family sums sampled on an m x m grid of [-1, 1]^2 (shared faces), randomly rotated."""
    from polygeo.frames import random_rotation

    grid = syn.plane_mesh(m)  # m x m vertices on [-1, 1]^2 and their triangles
    fam = syn.family_patches(n, uv=grid.points[:, :2], max_angle=0.0, seed=seed)
    local = fam.points  # not rotated (max_angle=0): (u, v, height)
    R = random_rotation(n, torch.Generator().manual_seed(seed)).to(torch.float64).numpy()
    return torch.from_numpy(np.einsum("bij,bpj->bpi", R, local)), grid.faces


def _foldover(local, faces) -> torch.Tensor:
    q = local[:, faces, :2]
    e1, e2 = q[:, :, 1] - q[:, :, 0], q[:, :, 2] - q[:, :, 0]
    a = e1[..., 0] * e2[..., 1] - e1[..., 1] * e2[..., 0]
    dom = torch.sign(a.sum(1, keepdim=True))
    return (a * dom < 0).to(torch.float64).mean(1)


def bench_tilted(n: int, bar) -> list[dict]:
    """Family patches on a grid where the PCA frame folds the patch over its uv plane."""
    pts, faces = _grid_family(n, 12, HELD_OUT_SEED + 2)
    c = canonicalize(pts)
    fold0 = _foldover(c.local, faces)
    sel = fold0 > 0
    net = load_pretrained()
    out = []
    r_pca = None
    for orient in ORIENTS:
        if orient == "pca":
            Q = torch.eye(3, dtype=torch.float64).expand(n, 3, 3)
        elif orient == "stn":
            Q = stn_rotations(c.local, c.mask, net)
        else:
            Q = optimize_rotations(c.local, c.mask, 4).rotation
        r, _ = height_residual(c.local, c.mask, Q, 4)
        fold = _foldover(c.local @ Q, faces)
        if orient == "pca":
            r_pca = r
        out.append({
            "section": "tilted",
            "orient": orient,
            "patches": n,
            "pca_folded_patches": int(sel.sum()),
            "height_rmse_folded": float(r[sel].mean()),
            "rmse_ratio_to_pca_folded": float(r[sel].mean() / r_pca[sel].mean()),
            "foldover_share_folded": float(fold[sel].mean()),
            "patches_still_folded": int((fold[sel] > 0).sum()),
        })
        bar.update(1)
    return out


# ------------------------------------------------------------------------------ meshes


def _meshes(quick: bool) -> dict:
    ms = {}
    s = syn.sphere_mesh(4 if quick else 5)
    ms["sphere"] = (s.points, s.faces, False)
    t = syn.torus_mesh(64 if quick else 96)
    ms["torus"] = (t.points, t.faces, False)
    c = syn.cylinder_mesh(64 if quick else 96)
    ms["cylinder"] = (c.points, c.faces, False)
    w = syn.wavy_sheet_mesh(64, 64) if quick else syn.wavy_sheet_mesh(96, 96)
    ms["wavy_sheet"] = (w.points, w.faces, False)
    v, f = syn.body_mesh(4 if quick else 5)
    ms["body"] = (v, f, True)
    v, f = syn.draped_sheet_mesh(90 if quick else 110, seed=100)
    ms["draped_sheet"] = (v, f, True)
    v, f = syn.skirt_mesh(140 if quick else 180, 70 if quick else 90, seed=100)
    ms["skirt"] = (v, f, True)
    return ms


N_CHAMFER = 10000
N_CHAMFER_DENSE = 100000


def _numpy(*arrays):
    """NumPy copies of tensors or arrays (the resampled surface follows the input's type)."""
    return tuple(np.asarray(a.detach() if torch.is_tensor(a) else a) for a in arrays)


def _chamfer_floors(v, f) -> dict:
    """The point protocols' sampling floors for a mesh (itself, independently sampled)."""
    return {
        "points": chamfer_distance(v, f, v, f, n_samples=N_CHAMFER, seed=1),
        "dense": chamfer_distance(v, f, v, f, n_samples=N_CHAMFER, n_samples_b=N_CHAMFER_DENSE,
                                  seed=1),
    }


def _mesh_record(name, v, f, ps, fit_sec, part_sec, floors, *, chamfer=True, seed=0):
    s = ps.metrics().summary()
    rec = {
        "section": "meshes",
        "mesh": name,
        "vertices": int(len(v)),
        "patches": ps.n_patches,
        "order": ps.order,
        "orient": ps.orient,
        "n_coefficients": ps.n_coefficients,
        "fit_seconds": fit_sec,
        "partition_seconds": part_sec,
        "height_rmse_all": s["height_rmse_all"],
        "height_rmse_canonical_mean": float(ps.residual.mean()),
        "normal_deg": s.get("normal_error_mean"),
        "boundary_gap_mean": s["boundary_gap_mean"],
        "boundary_gap_max": s["boundary_gap_max"],
        "boundary_normal_angle_mean": s["boundary_normal_angle_mean"],
        "foldover_mean": s.get("foldover_mean"),
        "chamfer_floor_x1e3": floors["points"] * 1e3,
        "chamfer_dense_floor_x1e3": floors["dense"] * 1e3,
    }
    if chamfer:
        rv, rf = _numpy(*ps.resample(1))
        kw = dict(n_samples=N_CHAMFER, seed=seed)
        rec["chamfer_x1e3"] = 1e3 * chamfer_distance(v, f, rv, rf, **kw)
        rec["chamfer_dense_x1e3"] = 1e3 * chamfer_distance(v, f, rv, rf,
                                                           n_samples_b=N_CHAMFER_DENSE, **kw)
        rec["chamfer_surface_x1e3"] = 1e3 * chamfer_distance(v, f, rv, rf, mode="surface", **kw)
    return rec


def bench_meshes(quick: bool, ks, orders, bar) -> list[dict]:
    out = []
    for name, (v, f, garment) in _meshes(quick).items():
        floor = _chamfer_floors(v, f)
        area = mesh_area(v, f)
        k_default = default_n_patches(area) if garment else 100
        parts = {}
        for k in sorted(set(ks) | {k_default}):
            if k > len(v) // 15:
                continue
            t0 = _now()
            parts[k] = partition_mesh(v, f, k, min_vertices=15)
            part_sec = _now() - t0
            for order in orders:
                t0 = _now()
                ps = PatchSet.fit(v, f, partition=parts[k], order=order)
                sec = _now() - t0
                want_chamfer = order == 4 or k == k_default
                rec = _mesh_record(name, v, f, ps, sec, part_sec, floor, chamfer=want_chamfer)
                rec["requested_k"] = k
                rec["default_k"] = k == k_default
                rec["garment"] = garment
                out.append(rec)
                bar.update(1)
        # orientations at the default K, order 4
        k = k_default
        if k in parts:
            base = None
            for orient in ORIENTS:
                t0 = _now()
                ps = PatchSet.fit(v, f, partition=parts[k], order=4, orient=orient)
                sec = _now() - t0
                rec = _mesh_record(name, v, f, ps, sec, 0.0, floor)
                rec.update(requested_k=k, default_k=True, garment=garment, section="orient")
                if orient == "pca":
                    base = rec
                rec["rmse_ratio_to_pca"] = (
                    rec["height_rmse_canonical_mean"] / base["height_rmse_canonical_mean"]
                )
                rec["rmse_all_ratio_to_pca"] = rec["height_rmse_all"] / base["height_rmse_all"]
                out.append(rec)
                bar.update(1)
    return out


# ------------------------------------------------------------------------------ speed


def bench_speed(quick: bool, bar) -> dict:
    nu, nv = (400, 250) if not quick else (200, 125)
    v, f = syn.skirt_mesh(nu, nv)
    reps = 3
    tp, tf = [], []
    for _ in range(reps):
        t0 = _now()
        part = partition_mesh(v, f, 400)
        tp.append(_now() - t0)
        t0 = _now()
        ps = PatchSet.fit(v, f, partition=part, order=4)
        tf.append(_now() - t0)
        bar.update(1)
    t0 = _now()
    PatchSet.fit(v, f, partition=part, order=4, orient="stn")
    t_stn = _now() - t0
    t0 = _now()
    PatchSet.fit(v, f, partition=part, order=4, orient="optimize")
    t_opt = _now() - t0
    bar.update(1)
    return {
        "section": "speed",
        "vertices": int(len(v)),
        "patches": ps.n_patches,
        "order": 4,
        "partition_seconds_median": float(np.median(tp)),
        "fit_pca_seconds_median": float(np.median(tf)),
        "partition_plus_fit_seconds": float(np.median(tp) + np.median(tf)),
        "fit_stn_seconds": t_stn,
        "fit_optimize_seconds": t_opt,
        "stn_overhead_ratio": t_stn / float(np.median(tf)),
        "optimize_overhead_ratio": t_opt / float(np.median(tf)),
        "height_rmse_all": ps.metrics(boundary=False).summary()["height_rmse_all"],
    }


def bench_stn_inference(bar) -> list[dict]:
    net = load_pretrained()
    fp = syn.family_patches(400, 128, seed=HELD_OUT_SEED + 1)
    c = canonicalize(torch.from_numpy(fp.points))
    out = []
    for b in (1, 64, 400):
        x, m = c.local[:b], c.mask[:b]
        stn_rotations(x, m, net)  # warm-up
        reps = max(3, 400 // b)
        t0 = _now()
        for _ in range(reps):
            stn_rotations(x, m, net)
        sec = (_now() - t0) / reps
        t0 = _now()
        for _ in range(reps):
            canonicalize(torch.from_numpy(fp.points[:b]))
        sec_pca = (_now() - t0) / reps
        out.append({
            "section": "stn_inference",
            "batch": b,
            "points_per_patch": 128,
            "ms_per_patch": 1e3 * sec / b,
            "pca_ms_per_patch": 1e3 * sec_pca / b,
            "parameters": int(sum(p.numel() for p in net.parameters())),
        })
        bar.update(1)
    return out


# ------------------------------------------------------------------------------ parsimony


def bench_parsimony(quick: bool, bar) -> list[dict]:
    out = []
    v, f = syn.skirt_mesh(140 if quick else 180, 70 if quick else 90, seed=100)
    part = partition_mesh(v, f, min_vertices=15)
    for order in (1, 2, 3, 4, 5, 6):
        ps = PatchSet.fit(v, f, partition=part, order=order)
        out.append({
            "section": "parsimony", "mode": f"order {order}", "n_coefficients": ps.n_coefficients,
            "height_rmse_all": ps.metrics(boundary=False).summary()["height_rmse_all"],
        })
        bar.update(1)
    for tol in (1e-3, 3e-4, 1e-4, 3e-5, 1e-5):
        ps = PatchSet.fit(v, f, partition=part, order="auto", tol=tol)
        met = ps.metrics(boundary=False)
        out.append({
            "section": "parsimony", "mode": f"auto tol {tol:g}", "tol": tol,
            "n_coefficients": ps.n_coefficients,
            "height_rmse_all": met.summary()["height_rmse_all"],
            "patches_within_tol": float(np.mean(met.height_rmse <= tol)),
            "order_histogram": np.bincount(met.order, minlength=7).tolist(),
        })
        bar.update(1)
    ps = PatchSet.fit(v, f, partition=part, order="auto")
    out.append({
        "section": "parsimony", "mode": "auto BIC", "n_coefficients": ps.n_coefficients,
        "height_rmse_all": ps.metrics(boundary=False).summary()["height_rmse_all"],
        "order_histogram": np.bincount(ps.orders.numpy(), minlength=7).tolist(),
    })
    for target in (1e-4, 1e-5):
        t0 = _now()
        ps = PatchSet.fit(v, f, order=4, target_rmse=target)
        out.append({
            "section": "parsimony", "mode": f"target_rmse {target:g}", "target": target,
            "seconds": _now() - t0, "patches": ps.n_patches,
            "n_coefficients": ps.n_coefficients, "search": ps.info["search"],
            "height_rmse_all": ps.info["search"][-1]["height_rmse"],
            "target_met": ps.info["target_met"],
        })
        bar.update(1)
    return out


# ------------------------------------------------------------------------------ report


def _targets(fam, meshes, speed) -> dict:
    t = {}
    f4 = {r["orient"]: r for r in fam if r["order"] == 4}
    t["families_order4_best_ratio"] = min(f4["stn"]["rmse_ratio_to_pca"],
                                          f4["optimize"]["rmse_ratio_to_pca"])
    t["families_order4_stn_ratio"] = f4["stn"]["rmse_ratio_to_pca"]
    t["families_order4_optimize_ratio"] = f4["optimize"]["rmse_ratio_to_pca"]
    t["families_order4_stn_guarded_ratio"] = f4["stn"]["rmse_ratio_to_pca_guarded"]
    g = [r for r in meshes if r["section"] == "orient" and r["garment"]]
    for o in ("stn", "optimize"):
        rs = [r["rmse_ratio_to_pca"] for r in g if r["orient"] == o]
        t[f"garment_order4_{o}_ratio_mean"] = float(np.mean(rs)) if rs else None
    t["families_order4_stn_20pct_lower_met"] = bool(t["families_order4_stn_ratio"] <= 0.8)
    t["rmse_20pct_lower_met"] = bool(
        t["families_order4_best_ratio"] <= 0.8
        and min(t["garment_order4_stn_ratio_mean"], t["garment_order4_optimize_ratio_mean"])
        <= 0.8
    )
    ch = [r for r in meshes if r["section"] == "meshes" and r["garment"] and r["default_k"]
          and r["order"] == 4]
    t["garment_chamfer_x1e3_default_k"] = {r["mesh"]: r["chamfer_x1e3"] for r in ch}
    t["garment_chamfer_surface_x1e3_default_k"] = {r["mesh"]: r["chamfer_surface_x1e3"]
                                                   for r in ch}
    t["garment_chamfer_floor_x1e3"] = {r["mesh"]: r["chamfer_floor_x1e3"] for r in ch}
    t["garment_chamfer_dense_x1e3_default_k"] = {r["mesh"]: r["chamfer_dense_x1e3"] for r in ch}
    t["garment_chamfer_dense_floor_x1e3"] = {r["mesh"]: r["chamfer_dense_floor_x1e3"]
                                             for r in ch}
    t["garment_chamfer_points_excess_over_floor_x1e3"] = {
        r["mesh"]: r["chamfer_x1e3"] - r["chamfer_floor_x1e3"] for r in ch}
    t["chamfer_target_measure"] = "surface (point-to-triangle) Chamfer x1e3"
    t["chamfer_le_0.2_met"] = bool(all(r["chamfer_surface_x1e3"] <= 0.2 for r in ch))
    t["chamfer_points_le_0.2"] = bool(all(r["chamfer_x1e3"] <= 0.2 for r in ch))
    t["chamfer_dense_le_0.2"] = bool(all(r["chamfer_dense_x1e3"] <= 0.2 for r in ch))
    t["speed_fit_lt_1s_met"] = bool(speed["fit_pca_seconds_median"] < 1.0)
    t["speed_partition_plus_fit_lt_3s_met"] = bool(speed["partition_plus_fit_seconds"] < 3.0)
    return t


def _plot(rec: dict, path: Path) -> None:
    fig, ax = plt.subplots(2, 3, figsize=(17, 10))
    colors = {"pca": "tab:blue", "stn": "tab:orange", "optimize": "tab:green"}
    # (a) families: rmse vs time per patch, per orient, labelled by order
    a = ax[0, 0]
    for o in ORIENTS:
        rs = [r for r in rec["families"] if r["orient"] == o]
        a.plot([r["ms_per_patch"] for r in rs], [r["height_rmse"] for r in rs], "o-",
               color=colors[o], label=o)
        for r in rs:
            a.annotate(str(r["order"]), (r["ms_per_patch"], r["height_rmse"]), fontsize=7)
    a.set(xscale="log", yscale="log", xlabel="ms per patch", ylabel="height RMSE (canonical)",
          title="synthetic families (held out), orders 2-6")
    a.legend()
    # (b) orientation on meshes (default K, order 4): ratio to PCA
    b = ax[0, 1]
    ori = [r for r in rec["meshes"] if r["section"] == "orient"]
    names = sorted({r["mesh"] for r in ori})
    x = np.arange(len(names))
    for i, o in enumerate(ORIENTS):
        vals = [next(r["rmse_ratio_to_pca"] for r in ori if r["mesh"] == n and r["orient"] == o)
                for n in names]
        b.bar(x + (i - 1) * 0.27, vals, 0.27, color=colors[o], label=o)
    b.axhline(0.8, color="k", ls="--", lw=0.8)
    b.set_xticks(x, names, rotation=30)
    b.set(ylabel="height RMSE / PCA", title="meshes: default K, order 4")
    b.legend()
    # (c) height RMSE vs order for each mesh at K=100 (or default)
    c = ax[0, 2]
    for n in names:
        rs = [r for r in rec["meshes"] if r["section"] == "meshes" and r["mesh"] == n
              and r["requested_k"] == 100]
        if rs:
            c.plot([r["order"] for r in rs], [r["height_rmse_all"] for r in rs], "o-", label=n)
    c.set(yscale="log", xlabel="jet order", ylabel="height RMSE (input units)",
          title="K = 100, PCA")
    c.legend(fontsize=7)
    # (d) chamfer vs K (order 4)
    d = ax[1, 0]
    for n in names:
        rs = sorted((r for r in rec["meshes"] if r["section"] == "meshes" and r["mesh"] == n
                     and r["order"] == 4 and "chamfer_x1e3" in r), key=lambda r: r["patches"])
        if rs:
            line, = d.plot([r["patches"] for r in rs], [r["chamfer_surface_x1e3"] for r in rs],
                           "o-", label=n)
            d.plot([r["patches"] for r in rs], [r["chamfer_x1e3"] for r in rs], "x:",
                   color=line.get_color())
            d.plot([r["patches"] for r in rs], [r["chamfer_dense_x1e3"] for r in rs], "+--",
                   color=line.get_color(), lw=0.7)
    d.axhline(0.2, color="k", ls="--", lw=0.8)
    d.set(xscale="log", yscale="log", xlabel="patches K", ylabel="Chamfer x 1e3",
          title="order 4: surface (o-), points 10k (x:), dense 100k (+--)")
    d.legend(fontsize=7)
    # (e) fit time vs vertices x patches
    e = ax[1, 1]
    rs = [r for r in rec["meshes"] if r["section"] == "meshes" and r["order"] == 4]
    e.scatter([r["vertices"] for r in rs], [r["fit_seconds"] for r in rs],
              c=np.log([r["patches"] for r in rs]), cmap="viridis")
    sp = rec["speed"]
    e.scatter([sp["vertices"]], [sp["fit_pca_seconds_median"]], marker="*", s=200, c="r",
              label=f"{sp['vertices']} v, K={sp['patches']}: "
                    f"{sp['fit_pca_seconds_median']:.2f} s")
    e.set(xscale="log", yscale="log", xlabel="vertices", ylabel="fit seconds (PCA, order 4)",
          title="fit time (colour: log K)")
    e.legend(fontsize=8)
    # (f) parsimony
    f = ax[1, 2]
    pr = [r for r in rec["parsimony"] if "n_coefficients" in r and "search" not in r]
    fixed = [r for r in pr if r["mode"].startswith("order")]
    auto = [r for r in pr if r["mode"].startswith("auto")]
    f.plot([r["n_coefficients"] for r in fixed], [r["height_rmse_all"] for r in fixed], "o-",
           label="fixed order 1-6")
    f.plot([r["n_coefficients"] for r in auto], [r["height_rmse_all"] for r in auto], "s",
           label="order auto (tol / BIC)")
    f.set(xscale="log", yscale="log", xlabel="parameters", ylabel="height RMSE (m)",
          title="skirt: parameters vs error")
    f.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _stn_training_meta() -> dict | None:
    """Training settings, time and held-out figures stored beside the shipped weights."""
    from polygeo.stn import pretrained_path

    p = pretrained_path().with_suffix(".json")
    return json.loads(p.read_text()) if p.is_file() else None


def warm_up(orders) -> float:
    """Run every timed code path once on a small sphere (compilation / cache load); seconds."""
    t0 = _now()
    s = syn.sphere_mesh(2)
    part = partition_mesh(s.points, s.faces, 4, min_vertices=15)
    for order in orders:
        for orient in ORIENTS if order == 4 else ("pca",):
            ps = PatchSet.fit(s.points, s.faces, partition=part, order=order, orient=orient)
    ps.metrics().summary()
    rv, rf = _numpy(*ps.resample(1))
    for kw in ({}, {"n_samples_b": 2000}, {"mode": "surface"}):
        chamfer_distance(s.points, s.faces, rv, rf, n_samples=1000, **kw)
    return _now() - t0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="smaller grid (about a minute)")
    p.add_argument("--out", default=str(Path(__file__).resolve().parent / "results"))
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    quick = args.quick
    orders = (2, 3, 4, 5, 6)
    ks = (1, 25, 100, 400)
    n_fam = 128 if quick else 512
    total = 3 * len(orders) + 3 + 7 * (4 * 5 + 3) + 4 + 3 + 13
    env = environment()
    warmup_s = warm_up(orders)
    print(f"warm-up (kernel compilation or cache load): {warmup_s:.1f} s")
    t_start = _now()
    with tqdm(total=total, desc="bm_polyfit") as bar:
        fam = bench_families(n_fam, orders, bar)
        tilted = bench_tilted(n_fam, bar)
        meshes = bench_meshes(quick, ks, orders, bar)
        speed = bench_speed(quick, bar)
        inf = bench_stn_inference(bar)
        pars = bench_parsimony(quick, bar)
    rec = {
        "benchmark": "polyfit",
        **finish(env),
        "quick": quick,
        "threads": torch.get_num_threads(),
        "warmup_s": warmup_s,
        "seconds": _now() - t_start,
        "families": fam,
        "tilted": tilted,
        "meshes": meshes,
        "speed": speed,
        "stn_inference": inf,
        "parsimony": pars,
        "chamfer_protocol": {
            "normalisation": "input's samples centred at their mean and scaled into the unit "
            "ball; the same similarity applied to the reconstruction",
            "reconstruction": "PatchSet.resample(1) (input triangulation subdivided once, "
            "evaluated through the patches)",
            "distance": "mean squared nearest distance, both directions summed; reported x1e3",
            "points": f"{N_CHAMFER} area-uniform samples on each surface (thesis Table 5.1)",
            "dense": f"{N_CHAMFER} input samples, {N_CHAMFER_DENSE} reconstruction samples "
            "(all the points the charts produce, densely, as AtlasNet evaluates)",
            "surface": f"{N_CHAMFER} samples on each surface, exact distance to the other "
            "surface's triangles (continuous Chamfer distance, no sampling floor)",
            "floor": "the same protocol between the input and an independent sampling of "
            "itself (seed 1): what a perfect reconstruction scores",
            "target": "Chamfer x1e3 <= 0.2 on garment-like meshes at the default K, judged on "
            "the surface distance",
        },
        "stn_training": _stn_training_meta(),
    }
    rec["targets"] = _targets(fam, meshes, speed)
    tt = {r["orient"]: r for r in tilted}
    rec["targets"]["tilted_stn_ratio"] = tt["stn"]["rmse_ratio_to_pca_folded"]
    rec["targets"]["tilted_optimize_ratio"] = tt["optimize"]["rmse_ratio_to_pca_folded"]
    (out / "bm_polyfit.json").write_text(json.dumps(rec, indent=1))
    _plot(rec, out / "bm_polyfit.png")
    t = rec["targets"]
    print(f"families order 4: stn/pca {t['families_order4_stn_ratio']:.3f} (guarded as in "
          f"PatchSet.fit: {t['families_order4_stn_guarded_ratio']:.3f}), "
          f"optimize/pca {t['families_order4_optimize_ratio']:.3f}")
    print(f"PCA-folded patches ({tt['pca']['pca_folded_patches']}/{tt['pca']['patches']}): "
          f"stn/pca {tt['stn']['rmse_ratio_to_pca_folded']:.3f}, optimize/pca "
          f"{tt['optimize']['rmse_ratio_to_pca_folded']:.3f}; still folded: pca "
          f"{tt['pca']['patches_still_folded']}, stn {tt['stn']['patches_still_folded']}, "
          f"optimize {tt['optimize']['patches_still_folded']}")
    print(f"garment meshes order 4 (mean): stn/pca {t['garment_order4_stn_ratio_mean']:.3f}, "
          f"optimize/pca {t['garment_order4_optimize_ratio_mean']:.3f}")
    def _fmt(d):
        return ", ".join(f"{k} {v:.4g}" for k, v in d.items())

    print(f"garment Chamfer x1e3 (surface, target <= 0.2): "
          f"{_fmt(t['garment_chamfer_surface_x1e3_default_k'])}")
    print(f"garment Chamfer x1e3 (points 10k/10k): {_fmt(t['garment_chamfer_x1e3_default_k'])}"
          f"; floor {_fmt(t['garment_chamfer_floor_x1e3'])}")
    print(f"garment Chamfer x1e3 (dense 10k/100k): "
          f"{_fmt(t['garment_chamfer_dense_x1e3_default_k'])}; floor "
          f"{_fmt(t['garment_chamfer_dense_floor_x1e3'])}")
    print(f"speed: {speed['vertices']} vertices, K={speed['patches']}: partition "
          f"{speed['partition_seconds_median']:.3f} s, fit {speed['fit_pca_seconds_median']:.3f} s")
    print(f"STN inference: {inf[-1]['ms_per_patch']:.4f} ms per patch (batch {inf[-1]['batch']})")
    print(f"wrote {out / 'bm_polyfit.json'} and {out / 'bm_polyfit.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
