"""Where trained draping models leave garment vertices inside the body (issue 20's dress eps_c).

Not a benchmark of its own (``polygeo bench`` lists only ``bm_*.py``): a diagnosis beside
``bm_gaps.py``. For each model and case it drapes the motion, queries the full posed Anny body
at every garment vertex of every frame (``MeshQuery``, as ``eps_c`` does) and reports, for the
vertices inside (signed distance < 0):

* how many vertex-frames, over how many frames and distinct vertices, and how deep (mm);
* on which body part (``torso``, ``legL``, ``legR``, ``armL``, ``armR``: the dominant bone of the
  closest body face);
* how many of them are *pinched*: within ``--pinch`` (m) of another body part as well (cloth
  caught between the swinging arm and the hip, between the thighs), where no drape of a
  garment outside both parts exists;
* optionally (``--optimum N``) at the N worst frames of each model and case, whether the
  training loss's own minimiser of that frame (the model's output refined by L-BFGS on eq.
  (38)-(46), the previous two frames fixed) still has vertices inside: if not, the collisions
  are the network's misses, not the loss's;
* with ``--span`` also the same minimisation restricted to what the model can output at that
  frame: its ``rank`` output-basis coefficients (the input of the learnt ``rank -> 3 V``
  basis) instead of the free vertices. If vertices stay inside there, the model's own
  output space, not only its mapping from poses, misses the collision-free minimiser.

Usage::

    python benchmarks/gaps_contacts.py --models dress RUN/model.pt --labels gaps ncs \\
        --cases held_out --frames 60 --optimum 1 [--span]
    python benchmarks/gaps_contacts.py --models dress RUN/model.pt --cases random \\
        --seeds 506-705 --skip 540,568,586 --frames 60     # a wide screen (session 15)

Writes ``benchmarks/results/gaps_contacts_<name>.json`` and a PNG bar chart of the
vertex-frames inside per body part and model. One thread.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

from run_env import environment, finish  # noqa: E402

from draping.gaps.pinch import PARTS, body_part, face_parts  # noqa: E402,F401
from polygeo.runs import record_path  # noqa: E402


def contacts(drape, body, parts: np.ndarray, pinch: float, query=None) -> dict:
    """Inside vertex-frames of one drape, by body part, depth and pinch.

    ``query``: optionally, per frame the ``(distance (V,), face (V,))`` arrays of the drape's
    vertices against its posed body (``MeshQuery.query`` in float64), when the caller has
    them already (``bm_gaps_wide`` scores several models on one posed body); None: queried
    here.
    """
    import torch

    from draping.collision import MeshQuery

    faces = body.faces.numpy()
    x = drape.x.double()
    bv = drape.body_vertices.double()
    if query is not None and len(query) != x.shape[0]:
        raise ValueError(f"query: expected {x.shape[0]} frames, got {len(query)}")
    q = MeshQuery(bv[0], body.faces) if query is None else None
    per_part = {p: {"inside": 0, "pinched": 0} for p in PARTS}
    others: dict = {}  # per part, the body less that part: built once, refitted per frame
    depth, frames, verts, counts = [], [], set(), []
    for t in range(x.shape[0]):
        if query is None:
            q.update(bv[t])
            r = q.query(x[t])
            d, f = np.asarray(r.distance), np.asarray(r.face)
        else:
            d, f = (np.asarray(a) for a in query[t])
        ins = np.nonzero(d < 0)[0]
        counts.append(int(ins.size))
        if ins.size == 0:
            continue
        frames.append(t)
        verts.update(ins.tolist())
        depth.extend((-1000.0 * d[ins]).tolist())
        for p in PARTS:
            sel = ins[parts[f[ins]] == p]
            if sel.size == 0:
                continue
            other = others.get(p)
            if other is None:
                other = others[p] = MeshQuery(bv[t], torch.as_tensor(faces[parts != p]))
            else:
                other.update(bv[t])
            do = np.abs(np.asarray(other.query(x[t][sel], max_distance=2 * pinch).distance))
            per_part[p]["inside"] += int(sel.size)
            per_part[p]["pinched"] += int((do < pinch).sum())
    n = int(sum(counts))
    return {"inside_vertex_frames": n, "eps_c": 100.0 * n / (x.shape[0] * x.shape[1]),
            "frames_with_contact": len(frames), "distinct_vertices": len(verts),
            "depth_mm_mean": float(np.mean(depth)) if depth else 0.0,
            "depth_mm_max": float(np.max(depth)) if depth else 0.0,
            "pinched": int(sum(v["pinched"] for v in per_part.values())),
            "parts": per_part, "per_frame": counts}


def train_settings_of(model):
    """The training settings a model was trained with (its record), else the defaults.

    The loss re-solved at a frame must be the model's own: a dress trained with
    ``--collision-stiffness 1e5`` is judged with ``k_c = 1e5``, not the default.
    """
    from draping.gaps import TrainSettings

    rec = (getattr(model, "record", None) or {}).get("training", {}).get("settings")
    if rec is None:
        return TrainSettings(model=model.settings)
    return TrainSettings.from_dict(rec).replace(**dataclasses.asdict(model.settings))


def _frame_loss(model, drape, x0, bv, q):
    """Eq. (46) at the last of three frames ``x`` as a function of it (the k_ext schedule
    saturated, as at the end of training; the model's own training settings), and the
    contacts of a candidate last frame."""
    from draping.gaps import body_contacts, loss_terms

    ts = train_settings_of(model)
    epoch = 10 ** 6

    def contacts_of(last):
        return body_contacts(_with_last(x0[:2], last), bv, q, ts.query_radius)

    def total(last, ct):
        terms = loss_terms(_with_last(x0[:2], last)[None], drape.case, model.settings, ts, ct,
                           epoch, 1.0 / 30.0)
        return sum(v[0, 2] for v in terms.values())

    return total, contacts_of


def _with_last(first, last):
    """Frames ``first`` ``(2, V, 3)`` followed by ``last`` ``(V, 3)``."""
    import torch

    return torch.cat([first, last[None]])


def _minimise(params, x_of, total, contacts_of, rounds: int):
    """L-BFGS on ``params``; contacts re-queried between rounds. Returns the final frame."""
    import torch

    opt = torch.optim.LBFGS(params, lr=1, max_iter=20, line_search_fn="strong_wolfe")
    for _ in range(rounds):
        ct = contacts_of(x_of().detach())

        def closure(ct=ct):
            opt.zero_grad()
            loss = total(x_of(), ct)
            loss.backward()
            return loss

        opt.step(closure)
    with torch.no_grad():
        return x_of().detach().clone()


def _inside(q, body_frame, x) -> int:
    q.update(body_frame.double())
    return int((np.asarray(q.query(x.double()).distance) < 0).sum())


def loss_optimum(model, drape, body, frame: int, rounds: int = 15) -> dict:
    """Vertices inside at one frame before and after minimising the training loss there."""
    from draping.collision import MeshQuery

    t = max(int(frame), 2)
    x0 = drape.x[t - 2:t + 1].clone()
    bv = drape.body_vertices[t - 2:t + 1]
    q = MeshQuery(bv[0].double(), body.faces)
    total, contacts_of = _frame_loss(model, drape, x0, bv, q)
    before = float(total(x0[2], contacts_of(x0[2])))
    free = x0[2].clone().requires_grad_(True)
    x1 = _minimise([free], lambda: free, total, contacts_of, rounds)
    after = float(total(x1, contacts_of(x1)))
    q.update(bv[2].double())
    d0, d1 = (np.asarray(q.query(x.double()).distance) for x in (x0[2], x1))
    return {"frame": t, "inside_model": int((d0 < 0).sum()),
            "inside_optimum": int((d1 < 0).sum()), "loss_model_J": before,
            "loss_optimum_J": after, "min_distance_optimum_mm": 1000.0 * float(d1.min())}


def span_optimum(model, drape, body, case, frame: int, rounds: int = 10) -> dict:
    """As :func:`loss_optimum` over the model's output space at that frame.

    The unknowns are the ``rank`` coefficients that the network feeds its learnt output
    basis at frame ``frame`` of ``case`` (started from the network's own), the skinning and
    the rest of the pipeline as at inference; ``reconstruction_mm`` is the largest distance
    between the model's drape and the garment rebuilt from those coefficients (a check).

    Raises
    ------
    ValueError
        A model without an output basis (``rank = 0``).
    """
    import torch

    from draping.collision import MeshQuery
    from draping.gaps import motion_features, sequence_of

    if model.settings.rank <= 0:
        raise ValueError(f"model: expected an output basis (rank > 0), got rank "
                         f"{model.settings.rank}")
    t = max(int(frame), 2)
    seq = sequence_of(body, case.motion, case.frames, case.seed, case.speed)
    shape = drape.case.shape
    with torch.no_grad():
        posed = body.pose(shape, seq.rotations[t:t + 1], seq.translation[t:t + 1])
        f = motion_features(body, seq.rotations[None], seq.velocity[None], shape[None])
        z0 = model.coefficients(f)[0][0, t].clone()
    rest_v = torch.as_tensor(drape.case.garment.vertices, dtype=torch.float32)
    z = z0.clone().requires_grad_(True)

    def x_of():
        return model.skin((rest_v + model.displacement(z))[None], posed.transforms)[0]

    x0 = drape.x[t - 2:t + 1].clone()
    bv = drape.body_vertices[t - 2:t + 1]
    q = MeshQuery(bv[0].double(), body.faces)
    total, contacts_of = _frame_loss(model, drape, x0, bv, q)
    with torch.no_grad():
        rec = 1000.0 * float((x_of() - x0[2]).norm(dim=-1).max())
    before = float(total(x0[2], contacts_of(x0[2])))
    grads = [p.requires_grad for p in model.parameters()]
    model.requires_grad_(False)
    try:
        x1 = _minimise([z], x_of, total, contacts_of, rounds)
    finally:
        for p, g in zip(model.parameters(), grads):
            p.requires_grad_(g)
    after = float(total(x1, contacts_of(x1)))
    return {"frame": t, "inside_model": _inside(q, bv[2], x0[2]),
            "inside_span": _inside(q, bv[2], x1), "loss_model_J": before,
            "loss_span_J": after, "coefficient_change": float((z.detach() - z0).norm() / z0.norm()),
            "reconstruction_mm": rec}


def chart(res: dict, path: Path) -> None:
    """Inside vertex-frames per body part (stacked: pinched hatched) for each model."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = list(res["models"])
    fig, ax = plt.subplots(figsize=(1.6 + 1.4 * len(labels), 4.0))
    xs = np.arange(len(labels))
    bottom = np.zeros(len(labels))
    for p in PARTS:
        free = np.array([sum(c["parts"][p]["inside"] - c["parts"][p]["pinched"]
                             for c in res["models"][m]["cases"]) for m in labels], float)
        pin = np.array([sum(c["parts"][p]["pinched"] for c in res["models"][m]["cases"])
                        for m in labels], float)
        b = ax.bar(xs, free, bottom=bottom, label=p)
        bottom += free
        ax.bar(xs, pin, bottom=bottom, color=b.patches[0].get_facecolor(), hatch="//",
               edgecolor="k", linewidth=0.3)
        bottom += pin
    ax.set_xticks(xs, [f"{m}\neps_c {res['models'][m]['eps_c']:.3f} %" for m in labels])
    ax.set_ylabel("garment vertex-frames inside the body")
    ax.set_title(f"{res['set']} cases: contacts by body part\n(hatched: pinched)", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def parse_seeds(text: str, skip: str = "") -> list[int]:
    """Seeds from ``"506-705"`` or ``"509,642,811"`` (ranges inclusive), less those in ``skip``.

    Raises
    ------
    ValueError
        If an item is not an integer or an ascending ``A-B`` range.
    """
    def items(t: str) -> list[int]:
        out = []
        for part in (p.strip() for p in t.split(",") if p.strip()):
            a, sep, b = part.partition("-")
            try:
                lo, hi = int(a), int(b if sep else a)
            except ValueError:
                raise ValueError(f"seeds: expected integers or A-B ranges, got {part!r}") from None
            if hi < lo:
                raise ValueError(f"seeds: range {part!r} is not ascending")
            out.extend(range(lo, hi + 1))
        return out

    drop = set(items(skip))
    return [s for s in items(text) if s not in drop]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--models", nargs="+", required=True, help="model files or shipped names")
    p.add_argument("--labels", nargs="+", default=None)
    p.add_argument("--cases", default="held_out", choices=("held_out", "validation", "random"))
    p.add_argument("--seeds", default="506-705",
                   help="--cases random: seeds in [500, 999], e.g. 506-705 or 509,642,811")
    p.add_argument("--skip", default="", help="--cases random: seeds left out, e.g. 540,568,586")
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--pinch", type=float, default=0.01, help="pinch distance (m), default 1 cm")
    p.add_argument("--optimum", type=int, default=0, help="worst frames per case to re-solve")
    p.add_argument("--span", action="store_true",
                   help="also re-solve those frames within the model's output basis")
    p.add_argument("--name", default="dress")
    p.add_argument("--out", default=str(HERE / "results"))
    a = p.parse_args(argv)
    import torch

    from draping.body import AnnyBody
    from draping.gaps import (
        drape_case,
        held_out_cases,
        load_model,
        random_cases,
        validation_cases,
    )

    torch.set_num_threads(1)
    env = environment()
    labels = a.labels or a.models
    if len(labels) != len(a.models):
        raise SystemExit("--labels: one per model")
    body = AnnyBody.load()
    parts = face_parts(body)
    if a.cases == "random":
        cases = random_cases(parse_seeds(a.seeds, a.skip), a.frames)
    else:
        cases = (held_out_cases if a.cases == "held_out" else validation_cases)(a.frames)
    res = {"set": a.cases, "frames": a.frames, "pinch_m": a.pinch, "models": {}}
    if a.cases == "random":
        res["seeds"] = [c.seed for c in cases]
    c0 = time.process_time()
    for path, label in zip(a.models, labels):
        m = load_model(path)
        rows, opt = [], []
        for c in cases:
            d = drape_case(m, body, c)
            r = {"case": f"{c.motion}:{c.seed}:{c.speed:g}", **contacts(d, body, parts, a.pinch)}
            rows.append(r)
            worst = np.argsort(r["per_frame"])[::-1][:a.optimum]
            for t in (int(t) for t in worst if r["per_frame"][t] > 0):
                o = {"case": r["case"], **loss_optimum(m, d, body, t)}
                if a.span:
                    o["span"] = span_optimum(m, d, body, c, t)
                opt.append(o)
            print(f"{label:10s} {r['case']:16s} inside {r['inside_vertex_frames']:5d} "
                  f"(pinched {r['pinched']}) depth {r['depth_mm_mean']:.2f}/"
                  f"{r['depth_mm_max']:.2f} mm " + " ".join(
                      f"{k}:{v['inside']}" for k, v in r["parts"].items() if v["inside"]),
                  flush=True)
        n = sum(r["inside_vertex_frames"] for r in rows)
        tot = sum(len(r["per_frame"]) for r in rows) * int(m.template.shape[0])
        res["models"][label] = {"model": record_path(path, ROOT), "eps_c": 100.0 * n / tot,
                                "cases": rows, "loss_optimum": opt}
        for o in opt:
            print(f"{label:10s} {o['case']:16s} frame {o['frame']}: inside {o['inside_model']}"
                  f" -> loss minimiser {o['inside_optimum']}"
                  + (f", within the output basis {o['span']['inside_span']}" if "span" in o
                     else ""), flush=True)
    res["cpu_seconds"] = time.process_time() - c0
    res.update(finish(env))
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"gaps_contacts_{a.name}_{a.cases}"
    (out / f"{stem}.json").write_text(json.dumps(res, indent=1))
    chart(res, out / f"{stem}.png")
    print(f"wrote {out / stem}.json/.png ({res['cpu_seconds']:.0f} CPU s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
