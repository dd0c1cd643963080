"""bm_jets' ``scans`` section: normals and mean curvature on real range scans (no analytic truth).

Data (not in the repository, nothing is downloaded): the Stanford bunny of the Stanford 3D
Scanning Repository (https://graphics.stanford.edu/data/3Dscanrep/), in a folder given with
``--scan-dir``:

* ``bun000.ply``, ``bun045.ply``: raw range scans (``x y z`` lines, metres; lines with another
  number of fields, such as a header or the scanner's range grid, are skipped);
* ``bun_zipper.ply``: the reconstruction zippered from about ten scans (ASCII PLY, 35,947
  vertices, 69,451 triangles), the reference.

Each scan is brought into the reference's frame (``bun000``: identity; ``bun045``: the
transform of the repository's ``bun.conf``, whose rotation lands on the reference read as
``x -> R(q)^T x + t``, refined by point-to-plane ICP against the reference; both recorded).
The estimates of each setting on the raw scan are compared at the nearest reference vertex
with the reference's normals (area-weighted face normals of the zippered mesh, independent
of polygeo's estimator) and with its mean curvature (an order-4 jet on the reference's
vertices, oriented by its faces: the best available, itself an estimate). Points compared
are well inside the scan: their ``BOUNDARY_K`` nearest scan points surround them (centroid
offset below ``BOUNDARY_OFFSET`` of their RMS distance) and the reference surface is within
``MAX_GAP`` (1 mm).

Metrics: median normal angle (degrees, unoriented), median ``|H - H_ref|`` over the median
``|H_ref|`` (scale-free), CPU seconds.

The reconstruction is coarser than a scan (median edge about 1.7 mm, scan spacing 0.5 mm), so
it favours settings that smooth as much as it does. A second, resolution-free reference
(``cross_scan``): the two scans overlap, and their noise is independent. Each scan's
estimates at the points of the overlap are compared with the other scan's at the same
places: a quadratic jet on the other scan's ``CROSS_REF`` nearest points (the least
smoothing of the candidates: little bias, much variance) evaluated at the compared point.
Independent noise adds the reference's variance equally to every setting's mean squared
difference, so that the mean squares rank the settings as their own errors would, up to
twice the product of the setting's bias and the reference's (small) bias. Metrics: RMS and
median normal angle (deg), RMS of ``H - H_ref`` over the RMS of ``H_ref`` and the median
ratio as above.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

#: Files the section needs in ``--scan-dir``.
FILES = ("bun000.ply", "bun045.ply", "bun_zipper.ply")
#: ``bun045``'s transform in ``bun.conf``: translation, quaternion ``(qx, qy, qz, qw)``.
BUN045_CONF = ((-0.0520211, -0.000383981, -0.0109223),
               (0.00548449, -0.294635, -0.0038555, 0.955586))
#: Largest distance from a compared scan point to the reference (metres).
MAX_GAP = 1e-3
#: Neighbours of the boundary test, and the largest centroid offset over the RMS distance.
BOUNDARY_K = 200
BOUNDARY_OFFSET = 0.2
#: Fixed settings compared besides the default (k=20, order 2) and the automatic one.
FIXED = ((50, 2), (100, 2), (200, 2), (20, 3), (50, 4), (100, 4))
#: Jet of the reference curvature (on the zippered mesh's vertices).
REF_JET = dict(k=40, order=4)
#: Jet of the cross-scan reference (on the other scan's raw points).
CROSS_REF = dict(k=12, order=2)


def missing(scan_dir) -> list[str]:
    """Files of :data:`FILES` absent from ``scan_dir``."""
    d = Path(scan_dir) if scan_dir else None
    return [f for f in FILES if d is None or not (d / f).is_file()]


def read_xyz_lines(path) -> np.ndarray:
    """``(N, 3)`` float64: the lines of ``path`` with exactly three numbers."""
    rows = []
    with open(path) as fh:
        for line in fh:
            parts = line.split()
            if len(parts) != 3:
                continue
            try:
                rows.append([float(p) for p in parts])
            except ValueError:
                continue
    return np.asarray(rows, dtype=np.float64)


def read_ascii_ply_mesh(path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices ``(V, 3)`` (the first three properties) and triangles of an ASCII PLY."""
    with open(path) as fh:
        header = []
        for line in fh:
            header.append(line.strip())
            if line.strip() == "end_header":
                break
        if not any(h.startswith("format ascii") for h in header):
            raise ValueError(f"{path}: not an ASCII PLY")
        counts = {h.split()[1]: int(h.split()[2]) for h in header if h.startswith("element")}
        nv, nf = counts.get("vertex", 0), counts.get("face", 0)
        V = np.array([fh.readline().split()[:3] for _ in range(nv)], dtype=np.float64)
        F = []
        for _ in range(nf):
            p = fh.readline().split()
            idx = [int(x) for x in p[1: 1 + int(p[0])]]
            F.extend([idx[0], idx[j], idx[j + 1]] for j in range(1, len(idx) - 1))
    return V, np.asarray(F, dtype=np.int64)


def vertex_normals(V, F) -> np.ndarray:
    """Area-weighted unit vertex normals of a triangle mesh (outward when its winding is)."""
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    n = np.zeros_like(V)
    for c in range(3):
        np.add.at(n, F[:, c], fn)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(norm > 0, norm, 1.0)


def quat_matrix(q) -> np.ndarray:
    """Rotation matrix of the unit quaternion ``(qx, qy, qz, qw)``."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def icp_point_to_plane(P, V, N, R, t, iters=30, trim=MAX_GAP * 3):
    """Refine ``x -> R x + t`` of the scan ``P`` onto the reference (vertices ``V``, normals
    ``N``) by point-to-plane ICP (pairs farther than ``trim`` dropped). Returns ``(R, t,
    history)`` with the RMS point-to-plane distance per iteration."""
    from scipy.spatial import cKDTree

    tree = cKDTree(V)
    hist = []
    for _ in range(iters):
        X = P @ R.T + t
        d, j = tree.query(X)
        keep = d < trim
        x, v, n = X[keep], V[j[keep]], N[j[keep]]
        r = np.einsum("ij,ij->i", x - v, n)
        hist.append(float(np.sqrt(np.mean(r * r))))
        A = np.c_[np.cross(x, n), n]
        sol = np.linalg.lstsq(A, -r, rcond=None)[0]
        a, b, c = sol[:3]
        dR = np.array([[1, -c, b], [c, 1, -a], [-b, a, 1]])
        u, _, vt = np.linalg.svd(dR)
        dR = u @ vt
        R, t = dR @ R, dR @ t + sol[3:]
        if np.linalg.norm(sol) < 1e-9:
            break
    return R, t, hist


def inside(P, k=BOUNDARY_K, offset=BOUNDARY_OFFSET) -> np.ndarray:
    """Points whose ``k`` nearest neighbours surround them (not at the scan's boundary)."""
    from scipy.spatial import cKDTree

    d, j = cKDTree(P).query(P, k + 1)
    c = P[j[:, 1:]].mean(1) - P
    rms = np.sqrt((d[:, 1:] ** 2).mean(1))
    return np.linalg.norm(c, axis=1) < offset * rms


def compare(res, sel, ref_n, ref_h, j, ref_nj=None) -> dict:
    """Errors of an estimate at the points ``sel`` against the reference at vertices ``j``
    (``ref_nj``: the normals of the reference's own jet, a second normal reference)."""
    n = np.asarray(res.normals)[sel]
    nr = ref_n[j]
    dot = np.einsum("ij,ij->i", n, nr)
    ang = np.degrees(np.arccos(np.clip(np.abs(dot), 0.0, 1.0)))
    h = np.asarray(res.mean_curvature)[sel] * np.sign(np.where(dot == 0, 1.0, dot))
    hr = ref_h[j]
    out = {"normal_median_deg": float(np.median(ang)),
           "normal_p90_deg": float(np.percentile(ang, 90)),
           "H_err_over_median_H": float(np.median(np.abs(h - hr)) / np.median(np.abs(hr)))}
    if ref_nj is not None:
        dj = np.abs(np.einsum("ij,ij->i", n, ref_nj[j]))
        out["normal_median_deg_jet_ref"] = float(np.median(np.degrees(np.arccos(
            np.clip(dj, 0.0, 1.0)))))
    return out


def jet_normals_at(res, rows, X) -> np.ndarray:
    """``(M, 3)``: normals of the jets of points ``rows`` of ``res`` at world points ``X``."""
    from polygeo.jets import evaluate

    fr, c = np.asarray(res.frame)[rows], np.asarray(res.coeffs)[rows]
    loc = np.einsum("nji,nj->ni", fr, X - np.asarray(res.points)[rows])
    uv = loc[:, None, :2]
    zu, zv = evaluate(c, uv, du=1)[:, 0], evaluate(c, uv, dv=1)[:, 0]
    n = np.stack([-zu, -zv, np.ones_like(zu)], 1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return np.einsum("nij,nj->ni", fr, n)


def cross_reference(A, B) -> dict:
    """The other scan ``B`` as the reference of ``A``'s points in the overlap.

    Points of ``A`` inside ``A`` whose nearest point of ``B`` is inside ``B`` and within
    :data:`MAX_GAP`; the :data:`CROSS_REF` jet of that point of ``B`` gives the normal at
    the point of ``A`` and its H (sign following that normal). Returns ``rows (M,)`` into
    ``A``, ``normals (M, 3)``, ``H (M,)``.
    """
    from scipy.spatial import cKDTree

    from polygeo.estimate import differential_quantities

    d, j = cKDTree(B).query(A)
    rows = np.flatnonzero(inside(A) & (d < MAX_GAP) & inside(B)[j])
    r = differential_quantities(B, orient="none", progress=False, **CROSS_REF)
    n = jet_normals_at(r, j[rows], A[rows])
    h = np.asarray(r.mean_curvature)[j[rows]] * np.sign(
        np.einsum("ij,ij->i", np.asarray(r.normals)[j[rows]], n))
    return {"rows": rows, "normals": n, "H": h}


def compare_cross(res, cross) -> dict:
    """Errors of an estimate against :func:`cross_reference`'s (RMS and median)."""
    rows = cross["rows"]
    dot = np.einsum("ij,ij->i", np.asarray(res.normals)[rows], cross["normals"])
    ang = np.degrees(np.arccos(np.clip(np.abs(dot), 0.0, 1.0)))
    h = np.asarray(res.mean_curvature)[rows] * np.sign(np.where(dot == 0, 1.0, dot))
    hr = cross["H"]
    return {"normal_rms_deg": float(np.sqrt(np.mean(ang * ang))),
            "normal_median_deg": float(np.median(ang)),
            "H_rms_over_rms_H": float(np.sqrt(np.mean((h - hr) ** 2) / np.mean(hr * hr))),
            "H_err_over_median_H": float(np.median(np.abs(h - hr)) / np.median(np.abs(hr)))}


def run_scan(name, P, V, ref_n, ref_h, settings, log=print, ref_nj=None, cross=None) -> dict:
    """Every setting on the scan ``P`` (already in the reference frame); with ``cross``
    (:func:`cross_reference`) also against the other scan."""
    from scipy.spatial import cKDTree

    from polygeo.estimate import differential_quantities

    gap, j = cKDTree(V).query(P)
    sel = inside(P) & (gap < MAX_GAP)
    out = {"scan": name, "n_points": int(len(P)), "n_compared": int(sel.sum()),
           "gap_median_m": float(np.median(gap)), "rows": []}
    for k, order in settings:
        c0, t0 = time.process_time(), time.perf_counter()
        r = differential_quantities(P, k=k, order=order, orient="none", progress=False)
        cpu, wall = time.process_time() - c0, time.perf_counter() - t0
        row = {"k": k, "order": order, "cpu_s": cpu, "wall_s": wall,
               "pts_per_cpu_s": len(P) / max(cpu, 1e-9),
               "flagged": int((np.asarray(r.status)[sel] != 0).sum()),
               "median_neighbours": float(np.median(np.asarray(r.n_neighbors)[sel])),
               "order_histogram": np.bincount(np.asarray(r.order)[sel], minlength=5).tolist(),
               **compare(r, sel, ref_n, ref_h, j[sel], ref_nj)}
        if cross is not None:
            row["cross_scan"] = compare_cross(r, cross)
        out["rows"].append(row)
        log(f"  {name} k={k} order={order}: normal {row['normal_median_deg']:.3f} deg, "
            f"H {row['H_err_over_median_H']:.3f}, {cpu:.1f} CPU s"
            + ("" if cross is None else
               f"; other scan: normal RMS {row['cross_scan']['normal_rms_deg']:.3f} deg, "
               f"H RMS {row['cross_scan']['H_rms_over_rms_H']:.3f}"))
    if cross is not None:
        out["cross_scan_compared"] = int(cross["rows"].size)
    return out


def scans_section(scan_dir, log=print) -> dict:
    """The section's record (``{"skipped": reason}`` when a file is missing)."""
    from scipy.spatial import cKDTree

    from polygeo.estimate import differential_quantities

    gone = missing(scan_dir)
    if gone:
        log(f"scans: --scan-dir {scan_dir!s} lacks {', '.join(gone)}")
        return {"skipped": f"files not found in --scan-dir: {', '.join(gone)} (the Stanford "
                           "bunny, Stanford 3D Scanning Repository; not shipped)"}
    d = Path(scan_dir)
    V, F = read_ascii_ply_mesh(d / "bun_zipper.ply")
    ref_n = vertex_normals(V, F)
    ref = differential_quantities(V, F, orient="mesh", progress=False, **REF_JET)
    ref_h = np.asarray(ref.mean_curvature) * np.sign(
        np.einsum("ij,ij->i", np.asarray(ref.normals), ref_n))
    settings = [(20, 2), ("auto", "auto")] + [s for s in FIXED]
    record = {"reference": {"file": "bun_zipper.ply", "vertices": int(len(V)),
                            "triangles": int(len(F)),
                            "normals": "area-weighted face normals (1-ring; "
                                       "normal_median_deg_jet_ref: the jet's below)",
                            "H": f"jet k={REF_JET['k']} order={REF_JET['order']} on its "
                                 "vertices, oriented by its faces"},
              "selection": {"max_gap_m": MAX_GAP, "boundary_k": BOUNDARY_K,
                            "boundary_offset": BOUNDARY_OFFSET},
              "scans": []}
    P0 = read_xyz_lines(d / "bun000.ply")
    ref_nj = np.asarray(ref.normals)
    P1 = read_xyz_lines(d / "bun045.ply")
    t, q = BUN045_CONF
    t = np.asarray(t)
    # the quaternion's convention: of x -> R x + t and x -> R^T x + t, the one that lands on
    # the reference
    tree = cKDTree(V)
    gaps = {c: float(np.median(tree.query(P1 @ Rc.T + t)[0]))
            for c, Rc in (("R(q)", quat_matrix(q)), ("R(q)^T", quat_matrix(q).T))}
    conv = min(gaps, key=gaps.get)
    R0 = quat_matrix(q) if conv == "R(q)" else quat_matrix(q).T
    R, tt, hist = icp_point_to_plane(P1, V, ref_n, R0, t)
    rot = np.degrees(np.arccos(np.clip((np.trace(R.T @ R0) - 1) / 2, -1, 1)))
    P1 = P1 @ R.T + tt
    record["cross_scan_reference"] = (
        f"the other scan: jet k={CROSS_REF['k']} order={CROSS_REF['order']} of its nearest "
        "point, evaluated at the compared point (overlap, both inside, gap below max_gap_m)")
    record["scans"].append(run_scan("bun000", P0, V, ref_n, ref_h, settings, log, ref_nj,
                                    cross_reference(P0, P1)))
    scan = run_scan("bun045", P1, V, ref_n, ref_h, settings, log, ref_nj,
                    cross_reference(P1, P0))
    scan["alignment"] = {"conf_convention": f"x -> {conv} x + t",
                         "conf_median_gap_m": gaps,
                         "conf_rms_point_to_plane_m": hist[0],
                         "icp_rms_point_to_plane_m": hist[-1], "icp_iterations": len(hist),
                         "icp_change_rotation_deg": float(rot),
                         "icp_change_translation_m": float(np.linalg.norm(tt - t))}
    record["scans"].append(scan)
    return record


def chart(record, png) -> None:
    """Normal and H errors per setting and scan (bars), against the reconstruction (top) and
    against the other scan (bottom, when measured)."""
    import matplotlib.pyplot as plt

    scans = record.get("scans", [])
    if not scans:
        return
    cross = all("cross_scan" in r for sc in scans for r in sc["rows"])
    fig, axes = plt.subplots(2 if cross else 1, 2, figsize=(12, 9 if cross else 4.5),
                             squeeze=False)
    names = [f"k={r['k']} o={r['order']}" for r in scans[0]["rows"]]
    x = np.arange(len(names))
    w = 0.8 / len(scans)
    panels = [(axes[0, 0], None, "normal_median_deg",
               "median normal angle to the reconstruction (deg)"),
              (axes[0, 1], None, "H_err_over_median_H",
               "median |H - H_ref| / median |H_ref| (reconstruction)")]
    if cross:
        panels += [(axes[1, 0], "cross_scan", "normal_rms_deg",
                    "RMS normal angle to the other scan (deg)"),
                   (axes[1, 1], "cross_scan", "H_rms_over_rms_H",
                    "RMS(H - H_ref) / RMS(H_ref) (other scan)")]
    for ax, sub, key, title in panels:
        for i, sc in enumerate(scans):
            vals = [(r[sub] if sub else r)[key] for r in sc["rows"]]
            n = sc.get("cross_scan_compared") if sub else sc["n_compared"]
            ax.bar(x + i * w, vals, w, label=f"{sc['scan']} ({n} points)")
        ax.set_xticks(x + 0.4 - w / 2, names, rotation=40, ha="right")
        ax.set_title(title)
        ax.legend()
    fig.suptitle("Stanford bunny raw scans: against the zippered reconstruction"
                 + (" and against each other (overlap)" if cross else ""))
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)
