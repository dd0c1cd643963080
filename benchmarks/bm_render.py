"""Benchmark of the CPU soft rasterizer (polygeo.render) against the naive dense oracle.

Speed: forward and forward+backward wall time (median) of a soft silhouette and of a
textured RGB render (silhouette + colour in one call), on a wavy sheet filling about half of
the image (the SfT setting) at 64², 128² and 256² pixels with about 1k, 2k, 5k and 20k
faces, float32, against ``render_reference`` (every pixel against every face in torch,
autograd) measured in the same run. The dense oracle runs unchunked when its estimated
memory fits, else in checkpointed row bands, and is skipped (and recorded as such) when it
would take too long.

Memory: peak resident memory added by one forward+backward call (``/proc`` high-water mark
reset before the call) and the peak of Python/NumPy allocations (tracemalloc).

Accuracy: IoU of the soft silhouette (thresholded at 0.5, and the soft IoU) against an
independent hard rasterization (OpenCV ``fillPoly`` per projected triangle on a 15x
supersampled grid read at pixel centres) as a function of sigma, for the sheet and for a
closed icosphere; the fast path also equals the dense oracle (max abs difference recorded).

Kernels are compiled (or loaded from numba's cache) on a small scene before any timing; the
time it took is recorded apart (``warmup_s``).

Usage: python benchmarks/bm_render.py [--quick] [--out DIR] [--threads 1[,2]]
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import statistics
import sys
import time
import tracemalloc
from pathlib import Path

import numba
import numpy as np
import torch
from tqdm import tqdm

from polygeo.render import (
    Camera,
    RasterSettings,
    checkerboard,
    iou,
    project_faces,
    render,
    render_reference,
    render_silhouette,
    soft_iou,
)

sys.path.insert(0, str(Path(__file__).resolve().parent))
from run_env import environment, finish  # noqa: E402

# ------------------------------------------------------------------ scenes


def sheet(n: int, wave: float = 0.15):
    u, v = np.meshgrid(np.linspace(-1, 1, n), np.linspace(-1, 1, n))
    verts = np.stack([u, v, wave * np.sin(3 * u) * np.cos(2 * v)], -1).reshape(-1, 3)
    idx = np.arange(n * n).reshape(n, n)
    a = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[:-1, 1:]], -1).reshape(-1, 3)
    b = np.stack([idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 3)
    uvs = np.stack([(u + 1) / 2, (v + 1) / 2], -1).reshape(-1, 2)
    return verts, np.concatenate([a, b]), uvs


def sheet_camera(size: int) -> Camera:
    return Camera.look_at([0.3, 0.2, -3.2], [0, 0, 0], focal=150.0 * size / 128, width=size,
                          height=size)  # fmt: skip


GRID = {"1k": 23, "2k": 33, "5k": 51, "20k": 101}  # 968, 2048, 5000, 20000 faces

# ------------------------------------------------------------------ measuring


def _status_kb(key: str) -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    return -1


def _reset_hwm() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def _trim() -> None:
    """Give freed heap memory back to the OS (glibc), so that the next peak is visible."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def peak_memory(fn) -> dict:
    """Peak memory of one call: RSS high-water mark above the RSS before, and tracemalloc."""
    gc.collect()
    _trim()
    ok = _reset_hwm()
    rss0 = _status_kb("VmRSS")
    tracemalloc.start()
    fn()
    _, tm_peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    hwm = _status_kb("VmHWM")
    return {
        "rss_peak_delta_mb": (hwm - rss0) / 1024 if ok else None,
        "rss_peak_mb": hwm / 1024,
        "tracemalloc_peak_mb": tm_peak / 2**20,
    }


def timed(fn, reps: int, budget_s: float) -> dict:
    """Median wall time, and median CPU time of the calling thread (all of it with 1 thread)."""
    fn()  # warm-up (and JIT compile on the first call)
    walls, cpus = [], []
    t_start = time.perf_counter()
    for _ in range(reps):
        c0 = time.thread_time()
        t0 = time.perf_counter()
        fn()
        walls.append(time.perf_counter() - t0)
        cpus.append(time.thread_time() - c0)
        if time.perf_counter() - t_start > budget_s and len(walls) >= 3:
            break
    return {
        "median_ms": 1e3 * statistics.median(walls),
        "min_ms": 1e3 * min(walls),
        "thread_cpu_median_ms": 1e3 * statistics.median(cpus),
        "n": len(walls),
    }


def make_calls(impl, verts, faces, uvs, tex, cam, settings, mode, chunk_rows=None):
    """Forward-only and forward+backward closures for one configuration."""
    g = torch.Generator().manual_seed(0)
    H, W = cam.height, cam.width
    ga = torch.rand(H, W, generator=g)
    gr = torch.rand(H, W, 3, generator=g)
    kw = {} if impl is render else {"chunk_rows": chunk_rows}
    if mode == "rgb":
        kw.update(uvs=uvs, texture=tex)

    def fwd():
        with torch.no_grad():
            return impl(verts, faces, cam, settings, **kw)

    def fwd_bwd():
        v = verts.detach().requires_grad_(True)
        out = impl(v, faces, cam, settings, **kw)
        loss = (out.alpha * ga).sum()
        if mode == "rgb":
            loss = loss + (out.rgb * gr).sum()
        loss.backward()
        return out, v.grad

    return fwd, fwd_bwd


def dense_plan(pixels: int, faces: int, mode: str, max_pairs: float):
    """How to run the dense oracle: ("full" | "chunked" | "skip", rows per band, estimate)."""
    pairs = pixels * faces
    # bytes kept for autograd per (pixel, face) pair, float32, measured order of magnitude
    per_pair = 4 * (70 if mode == "rgb" else 40)
    est = pairs * per_pair
    if pairs > max_pairs:
        return "skip", None, est
    if est <= 2 * 2**30:
        return "full", None, est
    return "chunked", max(1, int(256 * 2**20 // (per_pair * faces * int(pixels**0.5)))), est


def faces_per_pixel(fv: torch.Tensor, H: int, W: int, s: RasterSettings, samples=3000, seed=0):
    """Mean number of faces within the blur margin of a pixel centre (over covered pixels)."""
    rng = np.random.default_rng(seed)
    idx = rng.choice(H * W, size=min(samples, H * W), replace=False)
    q = torch.from_numpy(np.stack([idx % W + 0.5, idx // W + 0.5], -1))
    f = fv[0].detach().double()
    cutoff = s.blur_margin**2
    counts = []
    for chunk in torch.split(q, 256):
        xy = f[None, :, :, :2] - chunk[:, None, None, :]  # (P, F, 3, 2)
        x, y = xy[..., 0], xy[..., 1]
        e = torch.stack([x[..., 1] * y[..., 2] - x[..., 2] * y[..., 1],
                         x[..., 2] * y[..., 0] - x[..., 0] * y[..., 2],
                         x[..., 0] * y[..., 1] - x[..., 1] * y[..., 0]], -1)  # fmt: skip
        inside = ((e >= 0).all(-1)) | ((e <= 0).all(-1))
        a = f[None, :, :, :2]
        b = torch.roll(a, -1, dims=-2)
        ed = b - a
        t = (((chunk[:, None, None, :] - a) * ed).sum(-1) / (ed * ed).sum(-1)).clamp(0, 1)
        r = chunk[:, None, None, :] - a - t[..., None] * ed
        d2 = (r * r).sum(-1).amin(-1)
        counts.append((inside | (d2 <= cutoff)).sum(-1))
    c = torch.cat(counts).double()
    covered = c > 0
    return float(c[covered].mean()) if covered.any() else 0.0, float(covered.double().mean())


# ------------------------------------------------------------------ accuracy: IoU vs sigma


def cv2_silhouette(uv: np.ndarray, faces: np.ndarray, H: int, W: int, ss: int = 15):
    import cv2

    img = np.zeros((H * ss, W * ss), np.uint8)
    for f in faces:
        pts = np.round((uv[f] * ss - 0.5) * 16).astype(np.int32)
        cv2.fillPoly(img, [pts], 1, lineType=cv2.LINE_8, shift=4)
    return img[ss // 2 :: ss, ss // 2 :: ss].astype(np.float64)


def iou_vs_sigma(sigmas, size=128):
    import trimesh

    scenes = {}
    v, f, _ = sheet(GRID["2k"])
    scenes["sheet_2k"] = (v, f, sheet_camera(size))
    ico = trimesh.creation.icosphere(subdivisions=3)
    scenes["icosphere_1280"] = (
        np.asarray(ico.vertices),
        np.asarray(ico.faces),
        Camera.look_at(
            [0, 0, -4.0], [0, 0, 0], focal=150.0 * size / 128, width=size, height=size
        ),  # fmt: skip
    )
    out = {}
    for name, (verts, faces, cam) in scenes.items():
        uv, _ = cam.project(verts)
        ref = cv2_silhouette(uv, faces, cam.height, cam.width)
        hard = render_silhouette(verts, faces, cam, RasterSettings(hard=True))
        rows = []
        for sg in sigmas:
            a = render_silhouette(verts, faces, cam, RasterSettings(sigma=sg))
            rows.append({"sigma_px2": sg, "iou_threshold_0.5": float(iou(a, ref)),
                         "soft_iou": float(soft_iou(a, ref))})  # fmt: skip
        out[name] = {"coverage": float(ref.mean()), "hard_mode_iou": float(iou(hard, ref)),
                     "rows": rows}  # fmt: skip
    return out


# ------------------------------------------------------------------ main


def scene(size: int, grid: str):
    v_np, f_np, uv_np = sheet(GRID[grid])
    verts = torch.tensor(v_np, dtype=torch.float32)
    faces = torch.tensor(f_np)
    uvs = torch.tensor(uv_np, dtype=torch.float32)
    tex = torch.tensor(checkerboard(256, 8, smooth=True), dtype=torch.float32)
    return verts, faces, uvs, tex, sheet_camera(size)


def child(kind: str, size: int, grid: str, mode: str, rows=None) -> dict:
    """Run one memory (and, for the dense oracle, time) measurement in a fresh process."""
    import subprocess
    import sys

    cmd = [sys.executable, __file__, "--child", kind, str(size), grid, mode, str(rows or 0)]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
    if res.returncode != 0:
        return {"error": res.stderr[-2000:]}
    return json.loads(res.stdout.strip().splitlines()[-1])


def run_child(kind: str, size: int, grid: str, mode: str, rows: int) -> dict:
    """In the child: warm the kernels up on a tiny scene, then measure one call."""
    torch.set_num_threads(1)
    default = RasterSettings()
    v, f, u, t, _ = scene(32, "1k")
    for m in ("silhouette", "rgb"):
        make_calls(render, v, f, u, t, sheet_camera(32), default, m)[1]()
    verts, faces, uvs, tex, cam = scene(size, grid)
    out = {}
    if kind == "fast":
        _, fb = make_calls(render, verts, faces, uvs, tex, cam, default, mode)
        out.update(peak_memory(fb))
        return out
    dfwd, dfb = make_calls(render_reference, verts, faces, uvs, tex, cam, default, mode,
                           chunk_rows=rows or None)  # fmt: skip
    res = {}
    t0 = time.perf_counter()
    out["memory"] = peak_memory(lambda: res.setdefault("out", dfb()))
    out["forward_backward_ms"] = 1e3 * (time.perf_counter() - t0)
    t0 = time.perf_counter()
    dfwd()
    out["forward_ms"] = 1e3 * (time.perf_counter() - t0)
    _, fb = make_calls(render, verts, faces, uvs, tex, cam, default, mode)
    (o1, g1), (o2, g2) = fb(), res["out"]
    out["max_abs_diff_alpha"] = float((o1.alpha - o2.alpha).detach().abs().max())
    if mode == "rgb":
        out["max_abs_diff_rgb"] = float((o1.rgb - o2.rgb).detach().abs().max())
    out["grad_rel_diff"] = float((g1 - g2).norm() / g2.norm().clamp_min(1e-30))
    return out


def main() -> int:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        kind, size, grid, mode, rows = sys.argv[2:7]
        print(json.dumps(run_child(kind, int(size), grid, mode, int(rows))))
        return 0
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller grid, fewer repetitions")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results"))
    ap.add_argument("--threads", default="1", help="comma-separated thread counts to time "
                    "(default 1)")
    ap.add_argument("--reps", type=int, default=None)
    args = ap.parse_args()
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)

    sizes = [64, 128] if args.quick else [64, 128, 256]
    grids = ["1k", "2k"] if args.quick else ["1k", "2k", "5k", "20k"]
    modes = ["silhouette", "rgb"]
    reps = args.reps or (5 if args.quick else 15)
    max_pairs = 1e7 if args.quick else 4e7
    threads = [int(t) for t in args.threads.split(",")]
    sigmas = [1e-3, 1e-2, 3e-2, 0.1, 0.3, 1.0, 3.0]
    default = RasterSettings()
    env = environment()
    # compile (or load from numba's cache) every kernel timed below before any timing
    t_warm = time.perf_counter()
    v, f, u, t, _ = scene(32, "1k")
    for nt in threads:
        numba.set_num_threads(min(nt, numba.config.NUMBA_NUM_THREADS))
        for m in modes:
            for call in make_calls(render, v, f, u, t, sheet_camera(32), default, m):
                call()
    warmup_s = time.perf_counter() - t_warm
    print(f"warm-up (kernel compilation or cache load): {warmup_s:.1f} s")
    record = {
        "benchmark": "render",
        **env,
        "quick": bool(args.quick),
        "warmup_s": warmup_s,
        "settings": {
            "sigma_px2": default.sigma,
            "gamma": default.gamma,
            "blur_threshold": default.blur_threshold,
            "blur_margin_px": default.blur_margin,
            "tile_size": default.tile_size,
            "dtype": "float32",
            "reps": reps,
            "threads": threads,
        },  # fmt: skip
        "scene": "wavy sheet, look-at camera, focal 150 px per 128 px of image (about half "
        "the image covered), checkerboard texture 256x256",
        "results": [],
    }
    jobs = [(sz, gr, md) for sz in sizes for gr in grids for md in modes]
    bar = tqdm(jobs, desc="render bench")
    for size, grid, mode in bar:
        bar.set_postfix_str(f"{size}px {grid} {mode}")
        verts, faces, uvs, tex, cam = scene(size, grid)
        f_np = faces.numpy()
        row = {"size": size, "faces": int(len(f_np)), "mode": mode}
        fv = project_faces(verts.double(), faces, cam, default)[None]  # (1, F, 3, 3)
        row["faces_per_pixel"], row["coverage"] = faces_per_pixel(fv, size, size, default)
        for nt in threads:
            numba.set_num_threads(min(nt, numba.config.NUMBA_NUM_THREADS))
            torch.set_num_threads(nt)
            fwd, fb = make_calls(render, verts, faces, uvs, tex, cam, default, mode)
            row[f"fast_t{nt}"] = {"forward": timed(fwd, reps, 3.0),
                                  "forward_backward": timed(fb, reps, 3.0)}  # fmt: skip
        plan, rows_per_band, est = dense_plan(size * size, len(f_np), mode, max_pairs)
        row["fast_memory"] = child("fast", size, grid, mode)
        row["dense"] = {"plan": plan, "estimated_full_memory_mb": est / 2**20,
                        "rows_per_band": rows_per_band, "threads": 1}  # fmt: skip
        if plan != "skip":
            row["dense"].update(child("dense", size, grid, mode, rows_per_band))
            fast = row["fast_t1"]["forward_backward"]["median_ms"]
            row["speedup_fwd_bwd_vs_dense"] = row["dense"]["forward_backward_ms"] / fast
        else:
            pairs = size * size * len(f_np)
            row["dense"]["reason"] = f"{pairs:.2e} pixel-face pairs > {max_pairs:.0e} (too slow)"
        record["results"].append(row)
        gc.collect()
    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    torch.set_num_threads(max(threads))

    record["iou_vs_sigma"] = iou_vs_sigma(sigmas)
    record.update(finish(env))
    record["targets"] = targets(record, default)

    out_json = out_dir / "bm_render.json"
    out_json.write_text(json.dumps(record, indent=2))
    chart(record, out_dir / "bm_render.png", default)
    summary(record)
    print(f"wrote {out_json} and {out_dir / 'bm_render.png'}")
    return 0


def _find(record, size, faces_key, mode):
    for r in record["results"]:
        if r["size"] == size and r["faces"] == faces_key and r["mode"] == mode:
            return r
    return None


def targets(record, default) -> dict:
    t = {}
    r = _find(record, 128, 2 * (GRID["2k"] - 1) ** 2, "rgb")
    if r is not None:
        best = min(r[k]["forward_backward"]["median_ms"] for k in r if k.startswith("fast_t"))
        t["128px_2k_rgb_fwd_bwd_ms"] = best
        if "fast_t1" in r:
            t["128px_2k_rgb_fwd_bwd_thread_cpu_ms"] = r["fast_t1"]["forward_backward"][
                "thread_cpu_median_ms"
            ]
        t["128px_2k_rgb_fwd_bwd_le_20ms"] = best <= 20.0
        if "speedup_fwd_bwd_vs_dense" in r:
            t["128px_2k_speedup_vs_dense"] = r["speedup_fwd_bwd_vs_dense"]
            t["128px_2k_speedup_ge_20"] = r["speedup_fwd_bwd_vs_dense"] >= 20.0
    r = _find(record, 256, 2 * (GRID["20k"] - 1) ** 2, "rgb")
    if r is not None:
        m = r["fast_memory"]
        t["256px_20k_rgb_peak_rss_mb"] = m["rss_peak_mb"]
        t["256px_20k_rgb_peak_rss_delta_mb"] = m["rss_peak_delta_mb"]
        t["256px_20k_within_1GiB"] = m["rss_peak_mb"] <= 1024.0
    for name, res in record["iou_vs_sigma"].items():
        row = min(res["rows"], key=lambda x: abs(x["sigma_px2"] - default.sigma))
        t[f"iou_default_sigma_{name}"] = row["iou_threshold_0.5"]
        t[f"iou_default_sigma_{name}_ge_0.99"] = row["iou_threshold_0.5"] >= 0.99
    return t


def summary(record) -> None:
    print(f"{'size':>5} {'faces':>6} {'mode':>10} {'fpp':>5} {'1thr ms':>8} {'cpu ms':>7} "
          f"{'2thr ms':>8} {'dense ms':>9} {'ratio':>6} {'mem MB':>7} {'dense MB':>8}")  # fmt: skip
    nan = float("nan")
    for r in record["results"]:
        f1 = r.get("fast_t1", {}).get("forward_backward", {})
        f2 = r.get("fast_t2", {}).get("forward_backward", {}).get("median_ms", nan)
        d = r["dense"].get("forward_backward_ms", nan)
        dm = r["dense"].get("memory", {}).get("rss_peak_delta_mb", nan)
        print(f"{r['size']:>5} {r['faces']:>6} {r['mode']:>10} {r['faces_per_pixel']:>5.1f} "
              f"{f1.get('median_ms', nan):>8.2f} {f1.get('thread_cpu_median_ms', nan):>7.2f} "
              f"{f2:>8.2f} {d:>9.1f} {r.get('speedup_fwd_bwd_vs_dense', nan):>6.0f} "
              f"{r['fast_memory'].get('rss_peak_delta_mb') or nan:>7.1f} "
              f"{dm or nan:>8.1f}")  # fmt: skip
    for k, v in record["targets"].items():
        print(f"  {k}: {v}")


def chart(record, path: Path, default) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(17, 5))
    nt = min(record["settings"]["threads"])
    colors = {64: "tab:blue", 128: "tab:orange", 256: "tab:green"}
    for size in sorted({r["size"] for r in record["results"]}):
        rows = [r for r in record["results"] if r["size"] == size and r["mode"] == "rgb"]
        x = [r["faces"] for r in rows]
        axes[0].plot(x, [r[f"fast_t{nt}"]["forward_backward"]["median_ms"] for r in rows], "o-",
                     color=colors[size], label=f"fast {size}²")  # fmt: skip
        dense = [r for r in rows if "forward_backward_ms" in r["dense"]]
        dx = [r["faces"] for r in dense]
        dy = [r["dense"]["forward_backward_ms"] for r in dense]
        if dx:
            axes[0].plot(dx, dy, "s--", color=colors[size], label=f"dense {size}²")
        axes[1].plot(x, [r["fast_memory"].get("rss_peak_delta_mb") or 0 for r in rows], "o-",
                     color=colors[size], label=f"fast {size}²")  # fmt: skip
        dm = [r["dense"]["memory"].get("rss_peak_delta_mb") or 0 for r in dense]
        if dx:
            axes[1].plot(dx, dm, "s--", color=colors[size], label=f"dense {size}²")
    axes[0].axhline(20.0, color="gray", lw=0.8, ls=":")
    axes[0].set(xscale="log", yscale="log", xlabel="faces", ylabel="forward+backward (ms)",
                title=f"textured RGB + silhouette, float32, {nt} thread(s)")  # fmt: skip
    axes[1].set(xscale="log", yscale="log", xlabel="faces", ylabel="peak RSS added (MB)",
                title="memory of one forward+backward")  # fmt: skip
    for name, res in record["iou_vs_sigma"].items():
        s = [r["sigma_px2"] for r in res["rows"]]
        axes[2].plot(
            s, [r["iou_threshold_0.5"] for r in res["rows"]], "o-", label=f"{name} (α>0.5)"
        )
        axes[2].plot(s, [r["soft_iou"] for r in res["rows"]], "x:", label=f"{name} (soft IoU)")
    axes[2].axvline(default.sigma, color="gray", lw=0.8, ls=":")
    axes[2].axhline(0.99, color="gray", lw=0.8, ls=":")
    axes[2].set(xscale="log", xlabel="sigma (px²)", ylabel="IoU vs OpenCV fillPoly",
                title="silhouette accuracy at 128²")  # fmt: skip
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
