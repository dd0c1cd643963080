"""PNG charts of an SfT run (matplotlib, Agg backend)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["write_charts", "overlay_png"]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def write_charts(out: Path, rows: list[dict[str, Any]], losses_path: Path) -> list[Path]:
    """Write ``errors.png`` (per-frame errors) and ``losses.png`` (loss curves); return paths.

    Parameters
    ----------
    out : Path
        Output folder.
    rows : list of dict
        Per-frame records of :func:`sft.optimize.run_sft`.
    losses_path : Path
        ``losses.jsonl`` (one loss curve per window).
    """
    plt = _plt()
    written = []
    frames = [r["frame"] for r in rows]
    if rows and "e_3d" in rows[0]:
        fig, ax = plt.subplots(1, 3, figsize=(13, 3.6))
        for key, lab, a in (("e_3d", "e_3D", ax[0]), ("e_n", "e_n (deg)", ax[1]),
                            ("rmse", "RMSE (scene units)", ax[2])):
            a.plot(frames, [r[key] for r in rows], "o-", ms=3, label="reconstruction")
            a.plot(frames, [r[key + "_template"] for r in rows], "s--", ms=3, color="gray",
                   label="template kept fixed")
            a.set_xlabel("frame")
            a.set_ylabel(lab)
            a.grid(alpha=0.3)
        ax[0].legend()
        fig.suptitle("Per-frame reconstruction error")
        fig.tight_layout()
        p = out / "errors.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        written.append(p)
    if losses_path.is_file():
        curves = [json.loads(ln) for ln in losses_path.read_text().splitlines() if ln.strip()]
        fig, ax = plt.subplots(1, 2, figsize=(11, 3.6))
        cmap = plt.get_cmap("viridis")
        n = max(len(curves), 1)
        for i, c in enumerate(curves):
            ax[0].semilogy(c["loss"], color=cmap(i / n), lw=0.8)
        ax[0].set_xlabel("iteration in window")
        ax[0].set_ylabel("window loss")
        ax[0].set_title("Loss per window (colour = frame)")
        ax[0].grid(alpha=0.3)
        ax[1].bar([c["frame"] for c in curves], [c["iterations"] for c in curves], color="C1")
        ax[1].set_xlabel("frame")
        ax[1].set_ylabel("iterations")
        ax[1].set_title("Iterations per window (adaptive)")
        fig.tight_layout()
        p = out / "losses.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        written.append(p)
    return written


def overlay_png(path: Path, target: np.ndarray, rgb: np.ndarray, alpha: np.ndarray,
                err: tuple[np.ndarray, np.ndarray, float] | None) -> Path:
    """Frame | render | |render - frame| | per-vertex 3D error map (optional), side by side.

    Parameters
    ----------
    path : Path
        Output PNG.
    target, rgb : np.ndarray
        ``(H, W, 3)`` in ``[0, 1]``.
    alpha : np.ndarray
        ``(H, W)`` render coverage.
    err : (image, coverage, vmax) or None
        Rendered per-vertex error (fraction of ``vmax``) with its coverage, and ``vmax`` in
        scene units.
    """
    plt = _plt()
    n = 4 if err is not None else 3
    fig, ax = plt.subplots(1, n, figsize=(3.2 * n, 3.4))
    ax[0].imshow(np.clip(target, 0, 1))
    ax[0].set_title("frame")
    ax[1].imshow(np.clip(rgb, 0, 1))
    ax[1].set_title("render")
    diff = np.abs(rgb - target).mean(-1)
    im = ax[2].imshow(diff, cmap="magma", vmin=0, vmax=max(float(diff.max()), 1e-6))
    ax[2].set_title("|render - frame|")
    fig.colorbar(im, ax=ax[2], fraction=0.046)
    if err is not None:
        e, cov, vmax = err
        img = np.ma.masked_where(cov < 0.5, e * vmax * 1000.0)
        im = ax[3].imshow(img, cmap="viridis", vmin=0, vmax=vmax * 1000.0)
        ax[3].set_title("3D error (mm if metres)")
        fig.colorbar(im, ax=ax[3], fraction=0.046)
    for a in ax:
        a.set_xticks([])
        a.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)
