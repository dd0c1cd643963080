"""Benchmark of the draping foundation: reference-solver speed against accuracy.

Run ``python benchmarks/bm_drape.py [--sections solver,skinning,collision,newton,walk] [--quick]
[--out DIR]``. Writes
``bm_drape.json`` and one PNG chart per section (``bm_drape_<section>.png``) into
``benchmarks/results``. Each section is one function; ``--sections`` picks them.

Section ``solver`` (issue 18, Benchmark): a square sheet (1 m, the default SNUG/GAPS fabric)
starts flat 1 cm above a sphere (radius 0.3 m) and falls onto it for ``frames`` implicit-Euler
frames of 1/30 s (:func:`draping.reference.drape_sequence`), for sheets of about 2k, 5k and 10k
vertices, with each minimiser (``newton``, ``pqn``, ``lbfgs``) and stopping tolerances
(residual force over weight, ``SolverSettings.tol``). Recorded per run: seconds per frame,
iterations per frame, whether every frame met the tolerance, the final energy and the
distance (mean and max over vertices, mm) of the last frame to a tight reference solve
(``newton`` with the exact membrane Hessian, tol 1e-4; 1e-3 for 10k vertices). The cloth
buckles as it wraps the sphere, so the energy has many local minima: two solvers may stop in
different wrinkle patterns, which the distance shows.

Section ``walk``: the stopping tolerance on the reference's real job, the 5,000-vertex T-shirt
on the walk (60 frames): the sequence is draped once with the default solver, then every
dynamic frame is solved again from the same previous state at tolerances ``WALK_TOLS`` and at
``WALK_TIGHT``; recorded per frame and tolerance: CPU seconds, iterations, eps metrics and the
distance to the tight solve (mean and max over vertices, mm); the chart puts CPU seconds
against distance and shows the spread of CPU seconds per frame.

Section ``skinning``: CPU seconds and peak traced memory (``tracemalloc``) of the nearest,
Laplacian and RBF garment weights (:mod:`draping.skinning`) of T-shirts of about 2k, 5k and 10k
vertices against the full 13k-vertex body (memory must stay ``O(N_garment k)``, far from the
``N_garment x N_body`` a dense participation matrix takes). Section ``collision``: the signed
distance query of ``bm_drape_body.py`` against body resolution.

Solver timings are wall-clock with one thread, on whatever machine runs this (a shared, busy CPU
makes them noisy).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("MPLBACKEND", "Agg")

RESULTS = Path(__file__).resolve().parent / "results"


def grid_sheet(n: int, size: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Flat ``n x n`` square sheet centred on the z axis at height 0 (metres)."""
    u, v = np.meshgrid(
        np.linspace(-size / 2, size / 2, n), np.linspace(-size / 2, size / 2, n), indexing="ij"
    )
    verts = np.stack([u.ravel(), v.ravel(), np.zeros(n * n)], 1)
    a = np.array([i * n + j for i in range(n - 1) for j in range(n - 1)])
    faces = np.concatenate([np.stack([a, a + n, a + 1], 1), np.stack([a + 1, a + n, a + n + 1], 1)])
    return verts, faces


def _drape(n: int, method: str, tol: float, frames: int, max_iter: int,
           hessian: str = "projected"):
    import torch

    from draping import physics, reference

    v, f = grid_sheet(n)
    rest = physics.rest_state(v, f)
    query = reference.sphere_query([0.0, 0.0, 0.0], 0.3)
    x0 = torch.tensor(v) + torch.tensor([0.0, 0.0, 0.31], dtype=torch.float64)
    st = reference.SolverSettings(method=method, tol=tol, max_iter=max_iter, hessian=hessian)
    t0, c0 = time.perf_counter(), time.process_time()
    res = reference.drape_sequence(rest, x0, [query] * frames, 1 / 30, st)
    wall = time.perf_counter() - t0
    return res, (wall, time.process_time() - c0)


def section_solver(quick: bool, save) -> dict:
    """Seconds per frame against tolerance and accuracy, per minimiser and sheet size."""
    import torch

    torch.set_num_threads(1)
    sizes = [45] if quick else [45, 71, 100]
    frames = 2 if quick else 3
    data = {"frames": frames, "dt": 1 / 30, "runs": []}
    runs = data["runs"]
    for n in sizes:
        ref_tol = 1e-4 if n <= 71 else 1e-3  # a 1e-4 solve of 10k vertices takes ~15 min here
        # the tight solve with the exact membrane Hessian: with the projected one (the default)
        # Newton converges only linearly where the sheet buckles (5,041 vertices, third frame:
        # not converged in 400 iterations at 1e-4; 69 with the exact one)
        ref, ref_times = _drape(n, "newton", ref_tol, frames, 400, hessian="exact")
        x_ref = ref[-1].x.numpy()
        runs.append(_record(n, "newton", ref_tol, ref, ref_times, x_ref, reference_run=True))
        save(data)
        for method in ("newton", "pqn", "lbfgs"):
            for tol in (1e-2, 1e-3):
                if (
                    (method == "newton" and tol <= ref_tol)
                    or (method != "newton" and n > 45 and tol < 1e-2)
                    or (method == "lbfgs" and n > 71)
                ):
                    continue  # the reference itself, or too slow here; smaller runs rank them
                res, times = _drape(n, method, tol, frames, 300 if method == "newton" else 1500)
                runs.append(_record(n, method, tol, res, times, x_ref))
                print(runs[-1], flush=True)
                save(data)
    return data


def _record(n, method, tol, res, times, x_ref, reference_run=False) -> dict:
    wall, cpu = times
    x = res[-1].x.numpy()
    dist = np.linalg.norm(x - x_ref, axis=1) * 1e3
    return {
        "vertices": n * n,
        "method": method,
        "tol": tol,
        "reference": reference_run,
        "seconds_per_frame": wall / len(res),
        "cpu_seconds_per_frame": cpu / len(res),
        "iterations_per_frame": float(np.mean([r.iterations for r in res])),
        "all_converged": bool(all(r.converged for r in res)),
        "final_residual": res[-1].residual,
        "final_energy_J": res[-1].energy,
        "dist_to_reference_mm_mean": float(dist.mean()),
        "dist_to_reference_mm_max": float(dist.max()),
    }


def chart_solver(data: dict, path: Path) -> None:
    import matplotlib.pyplot as plt

    runs = [r for r in data["runs"] if not r["reference"]]
    sizes = sorted({r["vertices"] for r in runs})
    fig, axes = plt.subplots(1, len(sizes), figsize=(4.5 * len(sizes), 4), squeeze=False)
    marks = {"newton": "o", "pqn": "s", "lbfgs": "^"}
    for ax, nv in zip(axes[0], sizes, strict=True):
        for method, mk in marks.items():
            rr = [r for r in runs if r["vertices"] == nv and r["method"] == method]
            if not rr:
                continue
            ax.loglog(
                [r.get("cpu_seconds_per_frame", r["seconds_per_frame"]) for r in rr],
                [max(r["dist_to_reference_mm_mean"], 1e-4) for r in rr],
                mk + "-",
                label=method,
            )
            for r in rr:
                ax.annotate(
                    f"tol {r['tol']:g}",
                    (r.get("cpu_seconds_per_frame", r["seconds_per_frame"]),
                     max(r["dist_to_reference_mm_mean"], 1e-4)),
                    fontsize=7,
                )
        ax.set_title(f"{nv} vertices, sheet onto sphere")
        ax.set_xlabel("CPU seconds per frame (1 thread)")
        ax.set_ylabel("mean distance to tight solve (mm)")
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ------------------------------------------------------------------ tolerance on the walk

#: Tolerances of the walk section and the tight solve the others are measured against.
WALK_TOLS = (3e-3, 1e-2, 2e-2, 5e-2)
WALK_TIGHT = 1e-4


def section_walk(quick: bool, save, garment: str = "tshirt",
                 tols: tuple = WALK_TOLS) -> dict:
    """Stopping tolerance against cost and accuracy on the reference's real job.

    The 5,000-vertex T-shirt on the walk (``polygeo drape-reference --garment tshirt --motion
    walk``): the sequence is draped once with the default solver; then every dynamic frame is
    solved again from the same previous state at each tolerance and at ``WALK_TIGHT``, and each
    solve's distance to the tight one (mean and max over vertices, mm), CPU seconds,
    iterations and eps metrics are recorded (a per-frame replay: the solver's error over one
    step, without the drift of a whole sequence that starts from different states). Rows
    with ``subspace`` False are plain truncated Newton at the default tolerance
    (``SolverSettings.subspace`` off), for comparison.
    """
    import dataclasses

    import torch

    from draping import drape, reference
    from draping.collision import MeshQuery
    from draping.outputs import frame_metrics

    torch.set_num_threads(1)
    frames = 8 if quick else 60
    job = drape.DrapeJob(garment=garment, motion="walk", frames=frames)
    scene = drape.prepare(job)
    base = drape.DEFAULT_SOLVER
    states = [(fr.x, fr.v) for fr in drape.drape_frames(scene, base)]
    data = {"garment": garment, "frames": frames, "vertices": int(scene.rest.n_vertices),
            "default_tol": base.tol, "tight_tol": WALK_TIGHT, "tols": list(tols),
            "rows": []}
    query = MeshQuery(scene.body_vertices[0], scene.body_faces)
    g = scene.garment
    for t in range(1, frames):
        query.update(scene.body_vertices[t])
        xp, vp = states[t - 1]
        x0 = drape.initial_guess(scene, t, xp, vp, query, base)
        motion = scene.skinned[t] - scene.skinned[t - 1]
        out = {}
        # the default solver at each tolerance, and plain Newton (no subspace steps) at the
        # default tolerance
        for key in (WALK_TIGHT, *tols, "plain"):
            tol = base.tol if key == "plain" else key
            st = dataclasses.replace(base, tol=tol, subspace=key != "plain" and base.subspace)
            c0 = time.process_time()
            res = reference.drape_step(scene.rest, xp, vp, scene.dt, query, st, x0=x0,
                                       body_motion=motion)
            cpu = time.process_time() - c0
            m = frame_metrics(res.x, g.vertices, g.faces, distance=query.query(res.x).distance)
            out[key] = (res, cpu, m)
        x_tight = out[WALK_TIGHT][0].x.numpy()
        for key, (res, cpu, m) in out.items():
            d = np.linalg.norm(res.x.numpy() - x_tight, axis=1) * 1e3
            data["rows"].append({
                "frame": t, "tol": base.tol if key == "plain" else key,
                "subspace": key != "plain" and base.subspace,
                "cpu_seconds": cpu, "iterations": res.iterations,
                "converged": bool(res.converged), "eps_e": m["eps_e"], "eps_c": m["eps_c"],
                "dist_to_tight_mm_mean": float(d.mean()), "dist_to_tight_mm_max": float(d.max()),
            })
        print(f"walk frame {t}: " + ", ".join(
            f"{key} {cpu:.2f} s" for key, (_, cpu, _) in out.items()), flush=True)
        data["summary"] = _walk_summary(data["rows"])
        save(data)
    return data


def _walk_summary(rows: list) -> list:
    out = []
    for tol, sub in sorted({(r["tol"], r.get("subspace", False)) for r in rows}):
        rr = [r for r in rows if r["tol"] == tol and r.get("subspace", False) == sub]
        cpu = np.array([r["cpu_seconds"] for r in rr])
        out.append({
            "tol": tol, "subspace": sub, "frames": len(rr), "cpu_s_mean": float(cpu.mean()),
            "cpu_s_median": float(np.median(cpu)), "cpu_s_max": float(cpu.max()),
            "iterations_mean": float(np.mean([r["iterations"] for r in rr])),
            "all_converged": bool(all(r["converged"] for r in rr)),
            "dist_mm_mean": float(np.mean([r["dist_to_tight_mm_mean"] for r in rr])),
            "dist_mm_max": float(max(r["dist_to_tight_mm_max"] for r in rr)),
            "dist_mm_max_median": float(np.median([r["dist_to_tight_mm_max"] for r in rr])),
            "eps_e_max": float(max(r["eps_e"] for r in rr)),
            "eps_c_max": float(max(r["eps_c"] for r in rr)),
        })
    return out


def chart_walk(data: dict, path: Path) -> None:
    import matplotlib.pyplot as plt

    summ = [s for s in data["summary"]
            if s["tol"] != data["tight_tol"] and s.get("subspace", True)]
    plain = [s for s in data["summary"] if not s.get("subspace", True)]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    cpu = [s["cpu_s_mean"] for s in summ]
    ax = axes[0]
    ax.loglog(cpu, [s["dist_mm_mean"] for s in summ], "o-", label="mean over vertices")
    ax.loglog(cpu, [s["dist_mm_max_median"] for s in summ], "s-",
              label="max over vertices (median frame)")
    ax.loglog(cpu, [s["dist_mm_max"] for s in summ], "^-", label="max over vertices (worst frame)")
    for s in summ:
        ax.annotate(f"tol {s['tol']:g}", (s["cpu_s_mean"], s["dist_mm_max"]), fontsize=7)
    for s in plain:
        for key, mark in (("dist_mm_mean", "o"), ("dist_mm_max_median", "s"),
                          ("dist_mm_max", "^")):
            ax.loglog([s["cpu_s_mean"]], [s[key]], mark, mfc="none", color="k")
        ax.annotate(f"plain Newton, tol {s['tol']:g}", (s["cpu_s_mean"], s["dist_mm_max"]),
                    fontsize=7)
    ax.axhline(1.0, color="gray", ls=":", lw=0.8)
    ax.set_xlabel("CPU seconds per frame, mean (1 thread)")
    ax.set_ylabel(f"distance to a tol {data['tight_tol']:g} solve (mm)")
    ax.set_title(f"{data['garment']} on the walk, {data['vertices']} vertices: per-frame replay",
                 fontsize=9)
    ax.legend(fontsize=7)
    ax = axes[1]
    keys = [(s["tol"], s.get("subspace", True)) for s in data["summary"]]
    ax.boxplot([[r["cpu_seconds"] for r in data["rows"]
                 if (r["tol"], r.get("subspace", True)) == k] for k in keys],
               tick_labels=[f"{t:g}" + ("" if sub else "\nplain") for t, sub in keys])
    ax.axhline(1.0, color="gray", ls=":", lw=0.8, label="target 1 s")
    ax.set_xlabel("tolerance (residual force / weight)")
    ax.set_ylabel("CPU seconds per dynamic frame")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ------------------------------------------------------------------ independent simulator

# Run by the interpreter given with --newton-python (an environment with newton >= 1.8 and
# warp-lang; never a dependency of polygeo). argv: n, seconds, out.npy, contact ke, substeps.
NEWTON_CHILD = r"""
import json, sys, time
import numpy as np
import warp as wp
import newton

n, T, out = int(sys.argv[1]), float(sys.argv[2]), sys.argv[3]
ke, sub = float(sys.argv[4]), int(sys.argv[5])
u, v = np.meshgrid(np.linspace(-0.5, 0.5, n), np.linspace(-0.5, 0.5, n), indexing="ij")
verts = np.stack([u.ravel(), v.ravel(), np.zeros(n * n)], 1)
a = np.array([i * n + j for i in range(n - 1) for j in range(n - 1)])
faces = np.concatenate([np.stack([a, a + n, a + 1], 1), np.stack([a + 1, a + n, a + n + 1], 1)])
h, rho, E, nu = 4.7e-4, 426.0, 0.7e5, 0.485
mu = E / (2 * (1 + nu)) * h  # N/m (newton's membrane is Neo-Hookean with these moduli)
lam = E * nu / (1 - nu * nu) * h
kb = 50 * E * h**3 / (12 * (1 - nu * nu))
edge_ke = kb / (4 / (n - 1))  # newton: ke l theta^2 / 2; ours: kb l^2 / (8 (A0 + A1)) theta^2
wp.config.quiet = True
b = newton.ModelBuilder()
b.add_shape_sphere(body=-1, xform=wp.transform(wp.vec3(0.0, 0.0, 0.0), wp.quat_identity()),
                   radius=0.3)
b.add_cloth_mesh(pos=wp.vec3(0.0, 0.0, 0.302), rot=wp.quat_identity(), scale=1.0,
                 vel=wp.vec3(0.0, 0.0, 0.0), vertices=[wp.vec3(*p) for p in verts],
                 indices=faces.ravel().tolist(), density=rho * h, tri_ke=mu, tri_ka=lam,
                 tri_kd=0.0, edge_ke=edge_ke, edge_kd=0.0, particle_radius=0.002)
c = (n // 2) * n + n // 2
b.particle_mass[c] = 0.0
b.particle_flags[c] = b.particle_flags[c] & ~newton.ParticleFlags.ACTIVE
b.color(include_bending=True)
model = b.finalize(device="cpu")
model.soft_contact_ke = ke
model.soft_contact_kd = 1.0e-2
model.soft_contact_mu = 0.0  # frictionless, as our contact
solver = newton.solvers.SolverVBD(model=model, iterations=10)
s0, s1 = model.state(), model.state()
ctrl = model.control()
pipe = newton.CollisionPipeline(model)
contacts = pipe.contacts()
fps = 60
dt = 1.0 / fps / sub
t0 = time.perf_counter()
for _ in range(int(T * fps) * sub):
    s0.clear_forces()
    pipe.collide(s0, contacts)
    solver.step(s0, s1, ctrl, contacts, dt)
    s0, s1 = s1, s0
wall = time.perf_counter() - t0
np.save(out, s0.particle_q.numpy().astype(np.float64))
speed = float(np.linalg.norm(s0.particle_qd.numpy(), axis=1).max())
print(json.dumps({"seconds": wall, "frames": int(T * fps), "substeps": sub,
                  "max_speed_m_s": speed}))
"""


def _ours_pinned_sheet(n: int, seconds: float) -> tuple[np.ndarray, float, np.ndarray, float]:
    import torch

    from draping import physics, reference

    v, f = grid_sheet(n)
    rest = physics.rest_state(v, f)
    x0 = v + np.array([0.0, 0.0, 0.302])
    centre = (n // 2) * n + n // 2
    q = reference.sphere_query([0.0, 0.0, 0.0], 0.3)
    t0 = time.perf_counter()
    st = reference.drape_static(
        rest, x0, q, reference.SolverSettings(tol=1e-4, max_iter=3000), pinned=[centre]
    )
    t_static = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = reference.drape_sequence(
        rest,
        x0,
        [q] * int(seconds * 30),
        1 / 30,
        reference.SolverSettings(tol=1e-3),
        pinned=[centre],
    )
    t_dyn = time.perf_counter() - t0
    del torch
    return st.x.numpy(), t_static, res[-1].x.numpy(), t_dyn


def section_newton(quick: bool, save, newton_python: str | None = None) -> dict:
    """A centre-pinned sheet dropped on a sphere: our solver against newton's VBD cloth."""
    import subprocess
    import sys
    import tempfile

    n, seconds = (15, 1.0) if quick else (21, 3.0)
    data = {"vertices": n * n, "sim_seconds": seconds, "sphere_radius_m": 0.3, "sheet_m": 1.0}
    if not newton_python:
        data["skipped"] = "no --newton-python interpreter given"
        return data
    with tempfile.TemporaryDirectory() as tmp:
        script = Path(tmp) / "newton_sheet.py"
        script.write_text(NEWTON_CHILD)
        out = Path(tmp) / "q.npy"
        proc = subprocess.run(
            [newton_python, str(script), str(n), str(seconds), str(out), "1000", "5"],
            capture_output=True,
            text=True,
            check=False,
        )
        if proc.returncode != 0:
            data["skipped"] = "newton run failed: " + proc.stderr[-500:]
            return data
        data["newton"] = json.loads(proc.stdout.strip().splitlines()[-1])
        q_newton = np.load(out)
    x_static, t_static, x_dyn, t_dyn = _ours_pinned_sheet(n, seconds)
    data["ours_static_seconds"] = t_static
    data["ours_dynamic_seconds"] = t_dyn
    for name, x in (("static", x_static), ("dynamic", x_dyn)):
        d = np.linalg.norm(x - q_newton, axis=1) * 100.0
        data[f"cm_to_newton_{name}"] = {
            "mean": float(d.mean()),
            "median": float(np.median(d)),
            "max": float(d.max()),
        }
    d = np.linalg.norm(x_static - x_dyn, axis=1) * 100.0
    data["cm_ours_static_to_dynamic"] = {"mean": float(d.mean()), "max": float(d.max())}
    del sys
    return data


def chart_newton(data: dict, path: Path) -> None:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.5))
    if "cm_to_newton_static" in data:
        names = ["ours static\nvs newton", "ours dynamic\nvs newton", "ours static\nvs dynamic"]
        means = [
            data["cm_to_newton_static"]["mean"],
            data["cm_to_newton_dynamic"]["mean"],
            data["cm_ours_static_to_dynamic"]["mean"],
        ]
        maxs = [
            data["cm_to_newton_static"]["max"],
            data["cm_to_newton_dynamic"]["max"],
            data["cm_ours_static_to_dynamic"]["max"],
        ]
        ax.bar(names, means, label="mean")
        ax.plot(names, maxs, "k^", label="max")
        ax.set_ylabel("vertex distance (cm)")
        ax.legend()
    ax.set_title(f"sheet on sphere, {data['vertices']} vertices")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ------------------------------------------------------------------ skinning and collision


def _garments_for_skinning(quick: bool):
    """T-shirts of about 2k, 5k and 10k vertices for the rest Anny body (5k: the shipped)."""
    import torch

    from draping import garments
    from draping.body import AnnyBody

    body = AnnyBody.load(dtype=torch.float64)
    out = []
    for n in (2000,) if quick else (2000, 5000, 10000):
        g = garments.garment("tshirt") if n == 5000 else garments.make_garment(
            "tshirt", body, n_vertices=n)
        out.append(g)
    return body, out


def section_skinning(quick: bool, save) -> dict:
    """Seconds and peak memory of each skinning method against the full body."""
    import tracemalloc

    import torch

    from draping.skinning import dense_body_weights, skinning_weights

    torch.set_num_threads(1)
    body, gs = _garments_for_skinning(quick)
    rv = body.rest_vertices.double().numpy()[0] if body.rest_vertices.ndim == 3 else \
        body.rest_vertices.double().numpy()
    wb = dense_body_weights((body.skin_indices.numpy(), body.skin_weights.double().numpy()),
                            body.num_vertices, body.num_bones)
    data = {"body_vertices": int(rv.shape[0]), "bones": int(body.num_bones), "runs": []}
    for g in gs:
        for method in ("nearest", "laplacian", "rbf"):
            def run(method=method, g=g):
                return skinning_weights(method, g.vertices, rv, wb, garment_faces=g.faces)

            run()  # warm (numba kernels, caches)
            walls, cpus = [], []
            for _ in range(1 if quick else 3):
                t0, c0 = time.perf_counter(), time.process_time()
                w = run()
                walls.append(time.perf_counter() - t0)
                cpus.append(time.process_time() - c0)
            tracemalloc.start()
            run()
            _, peak = tracemalloc.get_traced_memory()
            tracemalloc.stop()
            w = np.asarray(w)
            row = {
                "garment_vertices": int(len(g.vertices)),
                "method": method,
                "seconds_wall": min(walls),
                "seconds_cpu": min(cpus),
                "peak_mib": peak / 2**20,
                # the (G, J) result itself, and what a dense G x N_body matrix would take
                "result_mib": w.nbytes / 2**20,
                "dense_g_by_body_mib": len(g.vertices) * rv.shape[0] * 8 / 2**20,
                "bones_used_per_vertex_mean": float((w > 1e-6).sum(1).mean()),
            }
            data["runs"].append(row)
            print(json.dumps(row), flush=True)
            save(data)
    return data


def chart_skinning(data: dict, path: Path) -> None:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for method, mk in (("nearest", "o"), ("laplacian", "s"), ("rbf", "^")):
        rr = [r for r in data["runs"] if r["method"] == method]
        g = [r["garment_vertices"] for r in rr]
        axes[0].plot(g, [r["seconds_cpu"] for r in rr], mk + "-", label=method)
        axes[1].plot(g, [r["peak_mib"] for r in rr], mk + "-", label=method)
    rr = [r for r in data["runs"] if r["method"] == "rbf"]
    axes[1].plot([r["garment_vertices"] for r in rr], [r["dense_g_by_body_mib"] for r in rr],
                 "k:", label="a dense G x N_body float64 matrix")
    axes[0].set_ylabel("CPU seconds (1 thread)")
    axes[1].set_ylabel("peak traced memory (MiB)")
    axes[1].set_yscale("log")
    for ax in axes:
        ax.set_xlabel("garment vertices")
        ax.legend(fontsize=8)
    fig.suptitle(f"garment skinning weights against the {data['body_vertices']}-vertex body")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def section_collision(quick: bool, save) -> dict:
    """Signed-distance query time against body resolution (``bm_drape_body.bench_collision``).

    10k points 1 mm inside or outside the full body, queried against the 2.5k-vertex proxy,
    the full 13k-vertex body and a 4x subdivision; warm kernels, CPU time of one thread.
    """
    import sys

    import torch

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bm_drape_body import bench_collision

    from draping.body import AnnyBody

    torch.set_num_threads(1)
    n, rep = (2000, 2) if quick else (10000, 5)
    data = {"runs": bench_collision(AnnyBody.load(), n_points=n, repeat=rep, peers=False)}
    save(data)
    return data


def chart_collision(data: dict, path: Path) -> None:
    import matplotlib.pyplot as plt

    rr = data["runs"]
    fig, ax = plt.subplots(figsize=(5.5, 4))
    ax.plot([r["faces"] for r in rr], [r["query_cpu_ms"] for r in rr], "o-", label="CPU time")
    ax.plot([r["faces"] for r in rr], [r["query_wall_ms"] for r in rr], "o--",
            label="wall (shared machine)")
    ax.axhline(50, color="gray", ls=":", lw=0.8, label="target 50 ms")
    for r in rr:
        ax.annotate(r["mesh"], (r["faces"], r["query_cpu_ms"]), fontsize=7)
    ax.set_xscale("log")
    ax.set_xlabel("body triangles")
    ax.set_ylabel(f"ms for {rr[0]['points']} points")
    ax.set_title("signed distance + closest point + normal")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


SECTIONS = {
    "solver": (section_solver, chart_solver),
    "skinning": (section_skinning, chart_skinning),
    "collision": (section_collision, chart_collision),
    "newton": (section_newton, chart_newton),
    "walk": (section_walk, chart_walk),
}


def _machine() -> dict:
    """Machine, versions, date and load of this run (timings depend on all of them)."""
    import datetime

    import numba
    import scipy
    import torch

    return {
        "platform": platform.platform(),
        "processor": platform.machine(),
        "cpus": os.cpu_count(),
        "threads": 1,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "numba": numba.__version__,
        "torch": torch.__version__,
        "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "load_average": list(os.getloadavg()),
        "note": "shared, busy machine: CPU seconds are the comparable figure",
    }


def main(argv: list[str] | None = None) -> None:
    """Run the chosen sections and write JSON and charts."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument(
        "--sections",
        default=",".join(SECTIONS),
        help=f"comma-separated sections among {', '.join(SECTIONS)}",
    )
    p.add_argument("--quick", action="store_true", help="smallest sizes only")
    p.add_argument("--out", type=Path, default=RESULTS, help="results folder")
    p.add_argument("--walk-tols", default=None,
                   help="comma-separated tolerances of the walk section (default: "
                        f"{','.join(f'{t:g}' for t in WALK_TOLS)})")
    p.add_argument(
        "--newton-python",
        default=None,
        help="python of an environment with newton (section newton)",
    )
    a = p.parse_args(argv)
    names = [s.strip() for s in a.sections.split(",") if s.strip()]
    bad = [s for s in names if s not in SECTIONS]
    if bad:
        p.error(f"unknown sections {bad}; choose among {list(SECTIONS)}")
    a.out.mkdir(parents=True, exist_ok=True)
    path = a.out / "bm_drape.json"
    record = json.loads(path.read_text()) if path.exists() else {}
    record["machine"] = _machine()
    for name in names:
        run, chart = SECTIONS[name]
        t0 = time.perf_counter()
        command = (
            f"python benchmarks/bm_drape.py --sections {name}"
            + (" --quick" if a.quick else "")
            + (f" --walk-tols {a.walk_tols}" if name == "walk" and a.walk_tols else "")
            + (
                " --newton-python PYTHON_WITH_NEWTON"  # no machine paths in the record
                if name == "newton" and a.newton_python
                else ""
            )
        )

        def save(partial: dict, name: str = name, t0: float = t0, command: str = command) -> None:
            partial["command"] = command
            partial["seconds"] = time.perf_counter() - t0
            partial["load_average"] = list(os.getloadavg())
            record[name] = partial
            path.write_text(json.dumps(record, indent=1))

        kw = {"newton_python": a.newton_python} if name == "newton" else {}
        if name == "walk" and a.walk_tols:
            kw = {"tols": tuple(float(t) for t in a.walk_tols.split(","))}
        data = run(a.quick, save, **kw)
        save(data)
        chart(data, a.out / f"bm_drape_{name}.png")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
