"""bm_jets' methods besides polygeo: the NumPy baseline, the peer libraries, their isolation.

Split from ``bm_jets.py`` (house size limit). Every peer runs in a child forked from a clean
fork server (:func:`isolated`), so that a crash or hang is recorded instead of ending the
benchmark.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import sys
import tempfile
import time

import numpy as np


def numpy_baseline(P, k, order=2):
    """Plain vectorised NumPy jet fit (cKDTree, batched eigh, normal equations)."""
    from scipy.spatial import cKDTree

    t0 = time.perf_counter()
    c0 = time.process_time()
    _, idx = cKDTree(P).query(P, k, workers=-1)
    t1 = time.perf_counter()
    X = P[idx] - P[:, None, :]
    C = X - X.mean(1, keepdims=True)
    cov = np.einsum("qki,qkj->qij", C, C)
    _, vec = np.linalg.eigh(cov)
    e1, e3 = vec[:, :, 2], vec[:, :, 0]
    e2 = np.cross(e3, e1)
    R = np.stack([e1, e2, e3], -1)
    uvz = np.einsum("qki,qij->qkj", X, R)
    u, v, z = uvz[..., 0], uvz[..., 1], uvz[..., 2]
    h = np.sqrt((u**2 + v**2).max(1))[:, None]
    us, vs = u / h, v / h
    cols, degs = [], []
    for d in range(order + 1):
        for j in range(d + 1):
            cols.append(us ** (d - j) * vs**j)
            degs.append(d)
    A = np.stack(cols, -1)
    ata = np.einsum("qkm,qkn->qmn", A, A)
    atb = np.einsum("qkm,qk->qm", A, z)
    coef = np.linalg.solve(ata, atb[..., None])[..., 0] / h ** np.array(degs)[None, :]
    a10, a01 = coef[:, 1], coef[:, 2]
    a20, a11, a02 = (coef[:, 3], coef[:, 4], coef[:, 5]) if order >= 2 else (0 * a10,) * 3
    w = np.sqrt(1 + a10**2 + a01**2)
    n_loc = np.stack([-a10, -a01, np.ones_like(a10)], -1) / w[:, None]
    E_, F_, G_ = 1 + a10**2, a10 * a01, 1 + a01**2
    L, M, N = 2 * a20 / w, a11 / w, 2 * a02 / w
    det = E_ * G_ - F_**2
    H = (E_ * N - 2 * F_ * M + G_ * L) / (2 * det)
    K = (L * N - M**2) / det
    normals = np.einsum("qij,qj->qi", R, n_loc)
    t2 = time.perf_counter()
    return {"normals": normals, "H": H, "K": K, "t_knn": t1 - t0, "t_total": t2 - t0,
            "cpu_s": time.process_time() - c0}


def peer_cgal(P, F, k, degree=2):
    from CGAL.CGAL_Kernel import Point_3
    from CGAL.CGAL_Point_set_3 import Point_set_3
    from CGAL.CGAL_Point_set_processing_3 import jet_estimate_normals

    from polygeo.io import read_points

    with tempfile.TemporaryDirectory() as d:
        ps = Point_set_3()
        for x, y, z in P.tolist():
            ps.insert(Point_3(x, y, z))
        ps.add_normal_map()
        t = time.perf_counter()
        c = time.process_time()
        jet_estimate_normals(ps, int(k), degree_fitting=int(degree))
        dt = time.perf_counter() - t
        cpu = time.process_time() - c
        dst = os.path.join(d, "out.ply")
        ps.write(dst)
        back = read_points(dst)
    if back.points.shape != P.shape or not np.allclose(back.points, P, equal_nan=True):
        raise RuntimeError("CGAL reordered or dropped points")
    return {"normals": back.normals, "t_total": dt, "cpu_s": cpu}


def peer_open3d(P, F, k):
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
    t = time.perf_counter()
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(int(k)))
    dt = time.perf_counter() - t
    return {"normals": np.asarray(pc.normals).copy(), "t_total": dt}


def peer_igl(P, F, k, rings=2):
    import igl

    t = time.perf_counter()
    V = np.ascontiguousarray(P, dtype=np.float64)
    Fi = np.ascontiguousarray(F, dtype=np.int64)
    pd1, pd2, pv1, pv2, *_ = igl.principal_curvature(V, Fi, int(rings), True)
    normals = igl.per_vertex_normals(V, Fi)
    dt = time.perf_counter() - t
    # libigl: positive on a sphere with outward faces; polygeo: negative (bends away from n)
    k1, k2 = -np.asarray(pv2), -np.asarray(pv1)
    return {"normals": normals, "H": 0.5 * (k1 + k2), "K": k1 * k2, "t_total": dt}


def peer_pyvista(P, F, k):
    import pyvista as pv

    poly = pv.PolyData(P, np.c_[np.full(len(F), 3), F].ravel())
    t = time.perf_counter()
    H = -np.asarray(poly.curvature("mean"))  # pyvista: positive on a convex outward surface
    K = np.asarray(poly.curvature("gaussian"))
    normals = np.asarray(poly.compute_normals(auto_orient_normals=False).point_normals)
    dt = time.perf_counter() - t
    return {"normals": normals, "H": H, "K": K, "t_total": dt}


def peer_trimesh(P, F, k, n_query=2000, seed=0):
    import trimesh
    from scipy.spatial import cKDTree

    m = trimesh.Trimesh(P, F, process=False)
    rng = np.random.default_rng(seed)
    sel = np.sort(rng.choice(len(P), size=min(n_query, len(P)), replace=False))
    # ball radius: median distance to the k-th neighbour (same support as a k-NN fit)
    r = float(np.median(cKDTree(P).query(P[sel], int(k))[0][:, -1]))
    t = time.perf_counter()
    hm = trimesh.curvature.discrete_mean_curvature_measure(m, P[sel], r)
    km = trimesh.curvature.discrete_gaussian_curvature_measure(m, P[sel], r)
    normals = np.asarray(m.vertex_normals)
    dt = time.perf_counter() - t
    area = trimesh.curvature.sphere_ball_intersection(1.0, r) if r < 1 else np.pi * r * r
    H = np.full(len(P), np.nan)
    K = np.full(len(P), np.nan)
    H[sel] = -hm / area
    K[sel] = km / area
    return {"normals": normals, "H": H, "K": K, "t_total": dt, "sel": sel, "radius": r}


PEERS = {
    "cgal_jet_normals": peer_cgal,
    "open3d_pca_normals": peer_open3d,
    "libigl_principal_curvature": peer_igl,
    "pyvista_curvature": peer_pyvista,
    "trimesh_curvature_measure": peer_trimesh,
}
PEER_MODULES = {
    "cgal_jet_normals": "CGAL",
    "open3d_pca_normals": "open3d",
    "libigl_principal_curvature": "igl",
    "pyvista_curvature": "pyvista",
    "trimesh_curvature_measure": "trimesh",
}


def _child(conn, fn, args, kwargs):
    try:
        conn.send(("ok", fn(*args, **kwargs)))
    except BaseException as exc:  # report any exception as data
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
    finally:
        conn.close()


_CTX = None


def start_forkserver() -> None:
    """Start the fork server before any OpenMP runtime is used in this process.

    Peers run in children forked from that clean server: forking this process after numba or
    torch started OpenMP threads is unsafe (libgomp aborts the child), and a peer that
    segfaults must not end the benchmark.
    """
    global _CTX
    import importlib.util

    ctx = mp.get_context("forkserver")
    mods = ["numpy", "scipy.spatial", "polygeo.io", "bm_jets_peers", "bm_jets_robust"]
    mods += [m for m in ("CGAL", "open3d", "igl", "pyvista", "trimesh")
             if importlib.util.find_spec(m) is not None]
    main_mod = sys.modules.get("__main__")
    if main_mod is not None and getattr(main_mod, "__file__", None):
        mods = ["__main__", *mods]
    ctx.set_forkserver_preload(mods)
    _CTX = ctx


def isolated(fn, *args, timeout=300.0, **kwargs):
    """Run ``fn`` in a child process; return ('ok', result) / ('error', msg) / ('crash', msg)."""
    if _CTX is None:
        start_forkserver()
    ctx = _CTX
    a, b = ctx.Pipe(duplex=False)
    p = ctx.Process(target=_child, args=(b, fn, args, kwargs))
    p.start()
    b.close()
    result = None
    if a.poll(timeout):
        try:
            result = a.recv()
        except EOFError:
            result = None
    p.join(5)
    if p.is_alive():
        p.kill()
        p.join()
        return ("crash", f"hang (> {timeout:.0f} s)")
    if result is None:
        return ("crash", f"process died with exit code {p.exitcode}")
    return result


def available_peers() -> dict:
    import importlib.util

    out = {}
    for name, mod in PEER_MODULES.items():
        out[name] = importlib.util.find_spec(mod) is not None
    return out
