"""bm_jets' ``robustness`` section: the issue's failure cases through polygeo and the peers.

Split from ``bm_jets.py`` (house size limit). Each peer runs in a forked child
(:func:`bm_jets_peers.isolated`), so that a crash is recorded instead of ending the benchmark.
"""

from __future__ import annotations

import numpy as np
from bm_jets_peers import PEERS, available_peers, isolated, numpy_baseline


def robustness_cases(seed=0):
    """The issue's failure cases, each with the clean input it should behave like.

    Every case has ``points``/``faces``/``k`` (the broken input), ``clean`` (points, faces)
    whose result it is compared with, ``map`` (row of the clean result for each point),
    ``skip`` (points not assessed: a fin vertex, stray unreferenced vertices) and ``nan``
    (points whose input is NaN: a finite, unflagged answer there is silently wrong).
    """
    from polygeo import synthetic as sy

    rng = np.random.default_rng(seed)
    s = sy.sphere(4000, seed=seed)
    n = len(s.points)
    none = np.zeros(n, bool)
    cloud = dict(clean=(s.points, None), map=np.arange(n), skip=none, nan=none, k=20)
    cases = {}
    # scan lines: latitude rings of 400 points; most 20-neighbourhoods lie on one ring. There
    # is no clean equivalent: compare with the analytic sphere (normals radial, H = -1).
    th = np.linspace(0.3, np.pi - 0.3, 20)
    ph = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    t, p = np.meshgrid(th, ph, indexing="ij")
    rp = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3)
    cases["scan_lines"] = dict(points=rp, faces=None, k=20, clean=None, truth_normals=rp,
                               truth_H=-np.ones(len(rp)), map=np.arange(len(rp)),
                               skip=np.zeros(len(rp), bool), nan=np.zeros(len(rp), bool))
    cases["points_repeated_10x"] = dict(cloud, points=np.repeat(s.points, 10, axis=0),
                                        faces=None, map=np.repeat(np.arange(n), 10),
                                        skip=np.zeros(10 * n, bool), nan=np.zeros(10 * n, bool))
    nan_last = np.r_[none, True]
    cases["one_nan_point"] = dict(cloud, points=np.vstack([s.points, [[np.nan] * 3]]),
                                  faces=None, map=np.r_[np.arange(n), 0], skip=nan_last,
                                  nan=nan_last)
    cases["shift_1e8"] = dict(cloud, points=s.points + 1e8, faces=None)
    cases["k_below_n_coeffs"] = dict(cloud, points=s.points, faces=None, k=4)
    m = sy.torus_mesh(100)
    nv = len(m.points)
    vnone = np.zeros(nv, bool)
    mesh = dict(clean=(m.points, m.faces), map=np.arange(nv), skip=vnone, nan=vnone, k=20)
    v = m.points.copy()
    v[5] = np.nan
    nan5 = vnone.copy()
    nan5[5] = True
    cases["mesh_nan_vertex"] = dict(mesh, points=v, faces=m.faces, skip=nan5, nan=nan5)
    e = m.faces[0]
    vf = np.vstack([m.points, m.points[e[0]] + 0.05 * m.normals[e[0]]])
    ff = np.vstack([m.faces, [[e[0], e[1], nv]]])
    cases["mesh_nonmanifold_fin"] = dict(mesh, points=vf, faces=ff, map=np.r_[np.arange(nv), 0],
                                         skip=np.r_[vnone, True], nan=np.r_[vnone, False])
    sv = m.points[m.faces].reshape(-1, 3)
    ns = len(sv)
    cases["mesh_unwelded_soup"] = dict(mesh, points=sv, faces=np.arange(ns).reshape(-1, 3),
                                       map=m.faces.reshape(-1), skip=np.zeros(ns, bool),
                                       nan=np.zeros(ns, bool))
    fl = m.faces.copy()
    flip = rng.random(len(fl)) < 0.5
    fl[flip] = fl[flip][:, ::-1]
    cases["mesh_half_faces_flipped"] = dict(mesh, points=m.points, faces=fl)
    vu = np.vstack([m.points, rng.normal(size=(50, 3)) * 0.001 + m.points[:50]])
    cases["mesh_unreferenced_vertices"] = dict(
        mesh, points=vu, faces=m.faces, map=np.r_[np.arange(nv), np.arange(50)],
        skip=np.r_[vnone, np.ones(50, bool)], nan=np.r_[vnone, np.zeros(50, bool)],
    )
    return cases


#: Methods whose normals (and curvature signs) carry an orientation.
ORIENTED = {"polygeo", "libigl_principal_curvature", "pyvista_curvature",
            "trimesh_curvature_measure"}


def classify(case, method, kind, res, ref, tol_deg=5.0, tol_h=0.2):
    """Outcome of a method on a broken input, against its own result on the clean input.

    ok: every assessed point agrees with the clean run (normals within ``tol_deg``, H within
    ``tol_h`` relative, same sign for oriented methods) and NaN inputs give NaN or a flag;
    reported: same, with the disagreeing points flagged by a status; error: a clear
    exception; crash: the process died or hung; silent_wrong: otherwise.
    """
    if kind == "crash":
        return {"outcome": "crash", "detail": str(res)[:200]}
    if kind == "error":
        return {"outcome": "error", "detail": str(res)[:200]}
    mp_ = case["map"]
    sel = res.get("sel")
    rows = np.arange(len(mp_)) if sel is None else sel
    status = res.get("status")
    flagged = np.zeros(len(mp_), bool) if status is None else np.asarray(status) != 0
    assess = ~case["skip"] & ~flagged
    wrong = np.zeros(len(mp_), bool)
    oriented = method in ORIENTED
    n = res.get("normals")
    if n is not None:
        n = np.asarray(n, dtype=np.float64)
        nref = ref["normals"][mp_] if ref is not None else case["truth_normals"]
        good = np.isfinite(n).all(1) & (np.linalg.norm(n, axis=1) > 1e-12)
        nn = n / np.where(good, np.linalg.norm(n, axis=1), 1)[:, None]
        nr = nref / np.maximum(np.linalg.norm(nref, axis=1), 1e-300)[:, None]
        d = np.einsum("ij,ij->i", np.where(good[:, None], nn, 0), np.nan_to_num(nr))
        d = d if (oriented and ref is not None) else np.abs(d)
        ang = np.degrees(np.arccos(np.clip(d, -1, 1)))
        wrong |= ~good | (ang > tol_deg)
    H = res.get("H")
    if H is not None:
        h = np.asarray(H, dtype=np.float64)
        href = ref["H"][mp_] if ref is not None else case["truth_H"]
        if ref is None or not oriented:
            h, href = np.abs(h), np.abs(href)
        rel = np.abs(h - href) / np.maximum(np.abs(href), 1e-12)
        wrong |= ~np.isfinite(h) | (rel > tol_h)
    wrong_rows = wrong[rows] & assess[rows]
    nan_in = case["nan"][rows]
    silent_nan = 0
    if nan_in.any():
        out_finite = np.ones(len(mp_), bool)
        if n is not None:
            out_finite &= np.isfinite(n).all(1)
        if H is not None:
            out_finite &= np.isfinite(np.asarray(H, dtype=np.float64))
        silent_nan = int((nan_in & out_finite[rows] & ~flagged[rows]).sum())
    detail = dict(assessed=int(assess[rows].sum()), disagree=int(wrong_rows.sum()),
                  flagged=int(flagged.sum()), nan_input_answered_silently=silent_nan)
    if wrong_rows.sum() > 0.01 * max(assess[rows].sum(), 1) or silent_nan:
        outcome = "silent_wrong"
    elif flagged.any():
        outcome = "reported"
    else:
        outcome = "ok"
    return {"outcome": outcome, **detail}


def _polygeo_payload(P, F, k):
    from polygeo.estimate import differential_quantities

    r = differential_quantities(P, F, k=k, order=2, progress=False)
    return {"normals": r.normals, "H": r.mean_curvature, "status": r.status}


def _numpy_payload(P, F, k):
    return numpy_baseline(P, k, 2)


def run_robustness(timeout=180.0):
    cases = robustness_cases()
    peers = available_peers()
    methods = {"polygeo": _polygeo_payload, "numpy_jets": _numpy_payload}
    methods.update({p: PEERS[p] for p, ok in peers.items() if ok})
    mesh_only = {"libigl_principal_curvature", "pyvista_curvature", "trimesh_curvature_measure"}
    table = {}
    clean_cache: dict = {}
    for name, case in cases.items():
        row = {}
        for method, fn in methods.items():
            if method in mesh_only and case["faces"] is None:
                row[method] = {"outcome": "n/a (needs a mesh)"}
                continue
            ref = None
            if case["clean"] is not None:
                key = (method, id(case["clean"][0]))
                if key not in clean_cache:
                    cp, cf = case["clean"]
                    if method == "polygeo":
                        clean_cache[key] = ("ok", fn(cp, cf, 20))
                    else:
                        clean_cache[key] = isolated(fn, cp, cf, 20, timeout=timeout)
                ck, ref = clean_cache[key]
                if ck != "ok":
                    row[method] = {"outcome": "clean run failed", "detail": str(ref)[:200]}
                    continue
            if method == "polygeo":  # ours runs in-process (it must not crash)
                try:
                    kind, res = "ok", fn(case["points"], case["faces"], case["k"])
                except (ValueError, TypeError) as exc:
                    kind, res = "error", f"{type(exc).__name__}: {exc}"
            else:
                kind, res = isolated(fn, case["points"], case["faces"], case["k"],
                                     timeout=timeout)
            row[method] = classify(case, method, kind, res, ref)
        table[name] = row
    return table


def print_robustness(table):
    methods = sorted({m for row in table.values() for m in row})
    print("robustness:")
    print("  " + "case".ljust(28) + "".join(m[:14].ljust(16) for m in methods))
    for case, row in table.items():
        print("  " + case.ljust(28) + "".join(
            str(row.get(m, {}).get("outcome", "-"))[:14].ljust(16) for m in methods))
