"""Benchmark of the draping foundation: reference-solver speed against accuracy.

Run ``python benchmarks/bm_drape.py [--sections solver] [--quick] [--out DIR]``. Writes
``bm_drape.json`` and one PNG chart per section (``bm_drape_<section>.png``) into
``benchmarks/results``. Each section is one function; ``--sections`` picks them.

Section ``solver`` (issue 18, Benchmark): a square sheet (1 m, the default SNUG/GAPS fabric)
starts flat 1 cm above a sphere (radius 0.3 m) and falls onto it for ``frames`` implicit-Euler
frames of 1/30 s (:func:`draping.reference.drape_sequence`), for sheets of about 2k, 5k and 10k
vertices, with each minimiser (``newton``, ``pqn``, ``lbfgs``) and stopping tolerances
(residual force over weight, ``SolverSettings.tol``). Recorded per run: seconds per frame,
iterations per frame, whether every frame met the tolerance, the final energy and the
distance (mean and max over vertices, mm) of the last frame to a tight reference solve
(``newton``, tol 1e-4). The cloth buckles as it wraps the sphere, so the energy has many local
minima: two solvers may stop in different wrinkle patterns, which the distance shows.

Timings are wall-clock with one thread, on whatever machine runs this (a shared, busy CPU
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


def _drape(n: int, method: str, tol: float, frames: int, max_iter: int):
    import torch

    from draping import physics, reference

    v, f = grid_sheet(n)
    rest = physics.rest_state(v, f)
    query = reference.sphere_query([0.0, 0.0, 0.0], 0.3)
    x0 = torch.tensor(v) + torch.tensor([0.0, 0.0, 0.31], dtype=torch.float64)
    st = reference.SolverSettings(method=method, tol=tol, max_iter=max_iter)
    t0 = time.perf_counter()
    res = reference.drape_sequence(rest, x0, [query] * frames, 1 / 30, st)
    wall = time.perf_counter() - t0
    return res, wall


def section_solver(quick: bool, save) -> dict:
    """Seconds per frame against tolerance and accuracy, per minimiser and sheet size."""
    import torch

    torch.set_num_threads(1)
    sizes = [45] if quick else [45, 71, 100]
    frames = 2 if quick else 3
    data = {"frames": frames, "dt": 1 / 30, "reference_tol": 1e-4, "runs": []}
    runs = data["runs"]
    for n in sizes:
        ref, ref_wall = _drape(n, "newton", 1e-4, frames, 400)
        x_ref = ref[-1].x.numpy()
        runs.append(_record(n, "newton", 1e-4, ref, ref_wall, x_ref, reference_run=True))
        save(data)
        for method in ("newton", "pqn", "lbfgs"):
            for tol in (1e-2, 1e-3):
                if (method == "lbfgs" and n > 45) or (method == "pqn" and n > 71 and tol < 1e-2):
                    continue  # tens of minutes each on this machine; the smaller runs rank them
                res, wall = _drape(n, method, tol, frames, 300 if method == "newton" else 1500)
                runs.append(_record(n, method, tol, res, wall, x_ref))
                print(runs[-1], flush=True)
                save(data)
    return data


def _record(n, method, tol, res, wall, x_ref, reference_run=False) -> dict:
    x = res[-1].x.numpy()
    dist = np.linalg.norm(x - x_ref, axis=1) * 1e3
    return {
        "vertices": n * n,
        "method": method,
        "tol": tol,
        "reference": reference_run,
        "seconds_per_frame": wall / len(res),
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
                [r["seconds_per_frame"] for r in rr],
                [max(r["dist_to_reference_mm_mean"], 1e-4) for r in rr],
                mk + "-",
                label=method,
            )
            for r in rr:
                ax.annotate(
                    f"tol {r['tol']:g}",
                    (r["seconds_per_frame"], max(r["dist_to_reference_mm_mean"], 1e-4)),
                    fontsize=7,
                )
        ax.set_title(f"{nv} vertices, sheet onto sphere")
        ax.set_xlabel("seconds per frame (1 thread)")
        ax.set_ylabel("mean distance to tight solve (mm)")
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


SECTIONS = {"solver": (section_solver, chart_solver)}


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
    a = p.parse_args(argv)
    names = [s.strip() for s in a.sections.split(",") if s.strip()]
    bad = [s for s in names if s not in SECTIONS]
    if bad:
        p.error(f"unknown sections {bad}; choose among {list(SECTIONS)}")
    a.out.mkdir(parents=True, exist_ok=True)
    path = a.out / "bm_drape.json"
    record = json.loads(path.read_text()) if path.exists() else {}
    record["machine"] = {"platform": platform.platform(), "cpus": os.cpu_count(), "threads": 1}
    for name in names:
        run, chart = SECTIONS[name]
        t0 = time.perf_counter()
        command = f"python benchmarks/bm_drape.py --sections {name}" + (
            " --quick" if a.quick else ""
        )

        def save(partial: dict, name: str = name, t0: float = t0, command: str = command) -> None:
            partial["command"] = command
            partial["seconds"] = time.perf_counter() - t0
            record[name] = partial
            path.write_text(json.dumps(record, indent=1))

        data = run(a.quick, save)
        save(data)
        chart(data, a.out / f"bm_drape_{name}.png")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
