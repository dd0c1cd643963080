"""Benchmark of the draping body: posing time and the collision query against body resolution.

``bench_pose``: seconds to pose the Anny body (13,348 vertices, 104 bones) for batches of 1
and 30 frames (float32, one thread).

``bench_collision``: signed distance + closest point + normal (``draping.collision``) of 10k
points lying 1 mm inside or outside the surface (along vertex normals), against the body at
three resolutions: the 2.5k-vertex collision proxy, the full 13k-vertex body and a 4x
subdivision of it (53k vertices). Reported: BVH build and per-frame refit time, query wall
time and CPU time of this process (the machine is shared: wall time includes waiting for a
core), sign agreement with a brute-force generalized winding number on a subset, and for the
proxy the distance error against the full body. When ``warp`` is importable its mesh queries
(closest point + normal sign, winding-number sign) are timed on the same points as a peer.

Usage: python benchmarks/bm_drape_body.py [--quick] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch
import trimesh

from draping.body import AnnyBody, default_asset_path
from draping.collision import MeshQuery, winding_numbers


def _timed(fn, repeat=5):
    walls, cpus = [], []
    out = None
    for _ in range(repeat):
        w, c = time.perf_counter(), time.process_time()
        out = fn()
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
    return out, min(walls), min(cpus)


def _points(v, f, n, seed):
    vn = trimesh.Trimesh(v, f, process=False).vertex_normals
    rng = np.random.default_rng(seed)
    idx = rng.choice(len(v), n)
    side = np.where(rng.random(n) < 0.5, 1.0, -1.0)
    return v[idx] + 1e-3 * side[:, None] * vn[idx], side


def bench_pose(body, repeat=5):
    rows = []
    for B in (1, 30):
        rot = 0.3 * torch.randn(B, body.num_bones, 3, generator=torch.Generator().manual_seed(0))
        body.pose(None, rot)
        _, wall, cpu = _timed(lambda rot=rot: body.pose(None, rot), repeat)
        rows.append(dict(frames=B, wall_ms=wall * 1e3, cpu_ms=cpu * 1e3,
                         wall_ms_per_frame=wall * 1e3 / B))
        print(f"pose B={B}: {wall * 1e3:.1f} ms wall, {cpu * 1e3:.1f} ms cpu")
    return rows


def _warp_peer(v, f, pts, repeat):
    try:
        import warp as wp
    except ImportError:
        return None
    wp.config.quiet = True
    wp.init()

    @wp.kernel
    def by_normal(mesh: wp.uint64, p: wp.array(dtype=wp.vec3), d: wp.array(dtype=float)):
        i = wp.tid()
        r = wp.mesh_query_point_sign_normal(mesh, p[i], 1.0e3)
        if r.result:
            d[i] = r.sign * wp.length(p[i] - wp.mesh_eval_position(mesh, r.face, r.u, r.v))

    @wp.kernel
    def by_winding(mesh: wp.uint64, p: wp.array(dtype=wp.vec3), d: wp.array(dtype=float)):
        i = wp.tid()
        r = wp.mesh_query_point_sign_winding_number(mesh, p[i], 1.0e3, 2.0, 0.5)
        if r.result:
            d[i] = r.sign * wp.length(p[i] - wp.mesh_eval_position(mesh, r.face, r.u, r.v))

    mesh = wp.Mesh(points=wp.array(v.astype(np.float32), dtype=wp.vec3),
                   indices=wp.array(f.astype(np.int32).ravel(), dtype=int),
                   support_winding_number=True)
    p = wp.array(pts.astype(np.float32), dtype=wp.vec3)
    d = wp.zeros(len(pts), dtype=float)
    out = {}
    for name, k in (("warp_normal_sign", by_normal), ("warp_winding_sign", by_winding)):
        wp.launch(k, dim=len(pts), inputs=[mesh.id, p], outputs=[d])
        wp.synchronize()

        def run(k=k):
            wp.launch(k, dim=len(pts), inputs=[mesh.id, p], outputs=[d])
            wp.synchronize()
            return d.numpy()

        res, wall, cpu = _timed(run, repeat)
        out[name] = dict(wall_ms=wall * 1e3, cpu_ms=cpu * 1e3, distance=res)
    return out


def bench_collision(body, n_points=10000, n_check=500, repeat=5, peers=True):
    v = body.rest_vertices.double().numpy()
    f = body.faces.numpy()
    proxy_v = body.proxy_vertices(body.rest_vertices.double()).numpy()
    sub_v, sub_f = trimesh.remesh.subdivide(v, f)
    meshes = [("proxy", proxy_v, body.proxy_faces.numpy()), ("full", v, f),
              ("subdivided", sub_v, sub_f)]
    pts, side = _points(v, f, n_points, seed=0)
    check = np.random.default_rng(1).choice(n_points, n_check, replace=False)
    truth_inside = winding_numbers(pts[check], v, f).numpy() > 0.5
    dists = {}
    rows = []
    for name, mv, mf in meshes:
        MeshQuery(mv, mf)  # compile
        q, build_wall, build_cpu = _timed(lambda mv=mv, mf=mf: MeshQuery(mv, mf), 3)
        _, refit_wall, refit_cpu = _timed(lambda q=q, mv=mv: q.update(mv), 3)
        res, wall, cpu = _timed(lambda q=q: q.query(pts), repeat)
        row = dict(mesh=name, vertices=len(mv), faces=len(mf), points=n_points,
                   build_ms=build_wall * 1e3, refit_ms=refit_wall * 1e3,
                   refit_cpu_ms=refit_cpu * 1e3,
                   query_wall_ms=wall * 1e3, query_cpu_ms=cpu * 1e3,
                   sign_vs_winding=float(((res.distance[check] < 0) == truth_inside).mean()),
                   sign_vs_construction=float((np.sign(res.distance) == side).mean()))
        dists[name] = res.distance
        rows.append(row)
        print(json.dumps(row))
    full_d = dists["full"]
    for row in rows:
        if row["mesh"] != "full":
            err = np.abs(dists[row["mesh"]] - full_d) * 1e3
            row["distance_error_vs_full_mm"] = dict(mean=float(err.mean()), max=float(err.max()))
    if peers:
        peer = _warp_peer(v, f, pts, repeat)
        if peer is not None:
            for name, r in peer.items():
                d = r.pop("distance")
                r.update(mesh="full", vertices=len(v), faces=len(f), points=n_points,
                         method=name,
                         sign_vs_winding=float(((d[check] < 0) == truth_inside).mean()),
                         max_abs_distance_diff_vs_ours_mm=float(
                             np.abs(np.abs(d) - np.abs(full_d)).max() * 1e3))
                rows.append(r)
                print(json.dumps(r))
    return rows


def _chart(record, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    ours = [r for r in record["collision"] if "method" not in r]
    ax = axes[0]
    ax.plot([r["faces"] for r in ours], [r["query_cpu_ms"] for r in ours], "o-",
            label="draping.collision (CPU time)")
    ax.plot([r["faces"] for r in ours], [r["query_wall_ms"] for r in ours], "o--",
            label="draping.collision (wall, shared machine)")
    for r in record["collision"]:
        if "method" in r:
            ax.plot([r["faces"]], [r["cpu_ms"]], "s", label=f"{r['method']} (CPU time)")
    ax.axhline(50, color="gray", lw=0.8, ls=":")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("body triangles")
    ax.set_ylabel(f"ms for {ours[0]['points']} points")
    ax.set_title("signed distance + closest point + normal")
    ax.legend(fontsize=7)
    ax = axes[1]
    ax.bar([r["mesh"] for r in ours], [100 * (1 - r["sign_vs_winding"]) for r in ours])
    for i, r in enumerate(ours):
        err = r.get("distance_error_vs_full_mm")
        if err:
            ax.annotate(f"|d - d_full| mean {err['mean']:.2f} mm", (i, 0), fontsize=7,
                        rotation=90, va="bottom", ha="center")
    ax.set_ylabel("% signs differing from the winding number")
    ax.set_title("accuracy (points 1 mm from the full body)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer points and repeats")
    ap.add_argument("--no-peers", action="store_true", help="skip warp even if installed")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    body = AnnyBody.load()
    load_s = time.perf_counter() - t
    n, rep = (2000, 2) if args.quick else (10000, 5)
    record = dict(
        benchmark="drape_body", python=platform.python_version(), torch=torch.__version__,
        machine=platform.machine(), cpus=os.cpu_count(), threads=1,
        note="shared, busy machine: CPU time of this process is the comparable figure",
        asset_load_s=load_s, asset_bytes=os.path.getsize(default_asset_path()),
        pose=bench_pose(body, rep),
        collision=bench_collision(body, n_points=n, repeat=rep, peers=not args.no_peers),
    )
    (out / "bm_drape_body.json").write_text(json.dumps(record, indent=2))
    _chart(record, out / "bm_drape_body.png")
    print(f"wrote {out / 'bm_drape_body.json'} and {out / 'bm_drape_body.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
