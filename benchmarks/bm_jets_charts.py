"""bm_jets' accuracy chart: error against throughput per method, one column per noise level.

Split from ``bm_jets.py`` (house size limit); :func:`chart` draws what a record holds (a
partial run draws only its sections).
"""

from __future__ import annotations

import numpy as np

_STYLE = {}  # method -> (colour, marker), fixed on first use so that panels agree


def _style(method):
    if method not in _STYLE:
        i = len(_STYLE)
        _STYLE[method] = (f"C{i % 10}", "osD^v<>pXh*"[i % 11])
    return _STYLE[method]


def chart(record, png):
    """Error against throughput: one colour/marker per method, one column per noise level.

    Rows: median normal error, median relative error of H (torus, largest size), and the
    parsimony runs (fixed k at order 2 as a line, automatic settings as stars).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    acc = [a for a in record.get("accuracy", []) if "pts_per_s" in a and a["surface"] == "torus"]
    size = max((a["n"] for a in acc), default=0)
    acc = [a for a in acc if a["n"] == size]
    noises = sorted({a["noise"] for a in acc})
    pars = record.get("parsimony", {}).get("runs", [])
    p_noises = sorted({p.get("noise", 0.001) for p in pars})
    if not acc and not pars:  # a partial run: draw only what it measured
        _speed_chart(record, png, plt)
        return
    ncol = max(len(noises), len(p_noises), 1)
    n_acc = 2 if acc else 0
    nrows = n_acc + (1 if pars else 0)
    fig, axes = plt.subplots(nrows, ncol, figsize=(5.4 * ncol, 4.4 * nrows + 0.8),
                             squeeze=False)

    def label(a):
        m = a["method"]
        if m == "polygeo":
            return f"polygeo order {a['order']}"
        if m == "polygeo_auto":
            return "polygeo k=auto, order=auto"
        if m == "cgal_jet_normals":
            return f"CGAL jet degree {a['order']}"
        return m

    handles = {}
    for c, nz in enumerate(noises):
        rows = [a for a in acc if a["noise"] == nz]
        for r_i, key in enumerate(("normal_median_deg", "H_rel_median")):
            ax = axes[r_i, c]
            for a in rows:
                y = a.get(key)
                if y is None or not np.isfinite(y) or y <= 0:
                    continue
                lab = label(a)
                col, mk = _style(lab)
                star = a["method"] == "polygeo_auto"
                h = ax.scatter(a["pts_per_s"], y, color="k" if star else col,
                               marker="*" if star else mk, s=200 if star else 46,
                               alpha=0.85, zorder=3 if star else 2)
                handles.setdefault(lab, h)
                if a["method"] == "polygeo":
                    ax.annotate(f"k{a['k']}", (a["pts_per_s"], y), fontsize=6,
                                xytext=(3, 2), textcoords="offset points")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.grid(True, which="both", alpha=0.3)
            ax.set_xlabel("throughput [points/s]")
            ax.set_ylabel("median normal error [deg]" if r_i == 0
                          else "median relative error of H")
            ax.set_title(f"torus {size} vertices, noise {100 * nz:g}% of diagonal", fontsize=9)
    for c in range(len(noises) if acc else ncol, ncol if acc else 0):
        axes[0, c].axis("off")
        axes[1, c].axis("off")
    for c in range(ncol if pars else 0):
        ax = axes[n_acc, c]
        if c >= len(p_noises):
            ax.axis("off")
            continue
        nz = p_noises[c]
        runs = [p for p in pars if p.get("noise", 0.001) == nz]
        fixed = sorted([p for p in runs if p["k"] != "auto" and p["order"] != "auto"],
                       key=lambda p: p["k"])
        x = [p["pts_per_s"] for p in fixed]
        y = [p.get("H_rel_median") or np.nan for p in fixed]
        col, _ = _style("fixed k, order 2")
        h = ax.plot(x, y, "-", color=col, marker="o")[0]
        handles.setdefault("fixed k, order 2", h)
        for p in fixed:
            ax.annotate(f"k{p['k']}", (p["pts_per_s"], p.get("H_rel_median") or np.nan),
                        fontsize=7, xytext=(3, 2), textcoords="offset points")
        for p in runs:
            if p["k"] == "auto" or p["order"] == "auto":
                lab = f"k={p['k']}, order={p['order']}"
                col, _ = _style(lab)
                h = ax.scatter(p["pts_per_s"], p.get("H_rel_median") or np.nan, color=col,
                               marker="*", s=160)
                handles.setdefault(lab, h)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
        ax.set_xlabel("throughput [points/s]")
        ax.set_ylabel("median relative error of H")
        ax.set_title(f"parsimony: torus, noise {100 * nz:g}% (stars: automatic)", fontsize=9)
    fig.legend(list(handles.values()), list(handles.keys()), loc="lower center",
               ncol=max(1, min(5, len(handles))), fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    fig.savefig(png, dpi=100)
    plt.close(fig)


def _speed_chart(record, png, plt):
    """Throughput of each method in the speed section (a run without accuracy sections)."""
    speed = record.get("speed_reference", {})
    rows = []
    for method, rec in speed.items():
        if isinstance(rec, dict) and "pipeline_pts_per_s" in rec:
            rows.append((method, rec["pipeline_pts_per_s"]))
            if "pipeline_with_orientation_pts_per_s" in rec:
                rows.append((f"{method} (oriented)", rec["pipeline_with_orientation_pts_per_s"]))
    fig, ax = plt.subplots(figsize=(7, 0.5 * len(rows) + 1.5))
    ax.barh([r[0] for r in rows], [r[1] for r in rows], color="C0")
    ax.set_xscale("log")
    ax.set_xlabel("throughput [points/s]")
    n = speed.get("n_points", "?")
    ax.set_title(f"speed: torus, {n} points, k = {speed.get('k')}, order {speed.get('order')}",
                 fontsize=9)
    ax.grid(True, which="both", axis="x", alpha=0.3)
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)
