"""bm_gaps_wide: GAPS against its baselines on the wide held-out set (issue 20, session 16).

The wide set declared in ``docs/measurements/gaps.md`` before it was scored: the ``random``
motions with seeds 506-705 less the swing seeds 540 / 568 / 586 (197 motions that no run
trains on and that are not held out), each on the body shape drawn with its own seed
(:func:`draping.gaps.random_cases`), 60 frames. Every model given is draped on every case and
scored with :func:`draping.gaps.frame_metrics` (eps_e, eps_a, eps_c in %) and
``gaps_contacts.contacts`` (garment vertex-frames inside the full posed body, by body part,
and how many of them are pinched between two parts).

Per garment, the GAPS model (``--reference``) is compared with every other model of that
garment by the rule fixed before scoring: "better" only if both its mean eps_c and its mean
eps_e over the cases are lower. Paired per-case counts are reported beside (cases where it
has fewer / more / equally many inside vertex-frames, and where its eps_e is lower).

Cheap by sharing: per case one motion, one garment fit per garment
(:func:`draping.gaps.shape_case`, shared by every model of that garment) and one body
refit per frame shared by all models; one body query per model and frame feeds both
metrics. ``--merge`` adds models to an existing record without re-scoring the others.

Usage::

    python benchmarks/bm_gaps_wide.py gaps=dress:dress ncs=dress:RUN_B/model.pt \\
        gaps=tshirt:tshirt
    python benchmarks/bm_gaps_wide.py --merge snug=dress:RUN/model.pt

A model is ``LABEL=GARMENT:MODEL`` (``MODEL`` a ``model.pt`` of ``polygeo train-drape`` or
a shipped name, ``tshirt`` / ``dress``) or just a shipped name (label ``gaps``). Writes
``benchmarks/results/bm_gaps_wide.json`` and ``.png`` (``--out``). One thread.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

from gaps_contacts import PARTS, contacts, face_parts, parse_seeds  # noqa: E402
from run_env import environment, finish  # noqa: E402

SEEDS = "506-705"
SKIP = "540,568,586"
FRAMES = 60
PINCH = 0.01
OUT = HERE / "results" / "bm_gaps_wide.json"


class Spec(NamedTuple):
    """One model to score: its label, garment and file (or shipped name)."""

    label: str
    garment: str
    source: str


def parse_spec(text: str) -> Spec:
    """``LABEL=GARMENT:MODEL`` or a shipped garment name (label ``gaps``).

    Raises
    ------
    ValueError
        A malformed item or a garment outside :data:`draping.garments.GARMENTS`.
    """
    from draping.garments import GARMENTS

    label, eq, rest = text.partition("=")
    if not eq:
        label, rest = "gaps", f"{text}:{text}"
    garment, colon, source = rest.partition(":")
    if not (label and colon and source):
        raise ValueError(f"models: expected LABEL=GARMENT:MODEL or a shipped name, got {text!r}")
    if garment not in GARMENTS:
        raise ValueError(f"models: unknown garment {garment!r} in {text!r} "
                         f"(one of {', '.join(GARMENTS)})")
    return Spec(label, garment, source)


def load_specs(specs: list[Spec]) -> list:
    """The models of ``specs`` (:func:`draping.gaps.load_model`), checked against their garment.

    Raises
    ------
    FileNotFoundError
        A model file that does not exist.
    ValueError
        No models, a repeated ``garment/label``, or a model trained for another garment.
    """
    from draping.gaps import load_model

    if not specs:
        raise ValueError("models: expected at least one model")
    keys = [(s.garment, s.label) for s in specs]
    if len(set(keys)) != len(keys):
        raise ValueError(f"models: repeated garment/label in {keys}")
    out = []
    for s in specs:
        m = load_model(s.source)
        trained = getattr(m, "garment_name", m.settings.garment)
        if trained != s.garment:
            raise ValueError(f"models: {s.source!r} was trained for {trained!r}, "
                             f"not {s.garment!r}")
        out.append(m)
    return out


def _query_all(drapes: list, body) -> list:
    """Per drape, per frame ``(distance, face)`` against the posed body (one refit per frame).

    All drapes of a case share the posed body (``drapes[0].body_vertices``); each is queried
    as :func:`draping.gaps.frame_metrics` and ``contacts`` query it (float64).
    """
    from draping.collision import MeshQuery

    bv = drapes[0].body_vertices.double()
    q = MeshQuery(bv[0], body.faces)
    xs = [d.x.double() for d in drapes]
    out = [[] for _ in drapes]
    for t in range(bv.shape[0]):
        q.update(bv[t])
        for i, x in enumerate(xs):
            r = q.query(x[t])
            out[i].append((r.distance, np.asarray(r.face)))
    return out


def score_case(case, models: list, body, parts: np.ndarray, pinch: float = PINCH
               ) -> tuple[list[dict], dict]:
    """Drape one case with every model and score each drape.

    Returns
    -------
    rows : list of dict
        Per model: ``seed``, mean ``eps_e`` / ``eps_a`` / ``eps_c`` (%), ``inside``
        vertex-frames, ``pinched``, ``parts`` (inside per body part).
    seconds : dict
        CPU seconds: ``shared`` (motion, garment fits, body refits), ``models`` (draping,
        queries, metrics).
    """
    import torch

    from draping.gaps import drape_motion, frame_metrics, model_garment, sequence_of, shape_case
    from draping.gaps.infer import garment_key
    from draping.motion import Motion

    c0 = time.process_time()
    seq = sequence_of(body, case.motion, case.frames, case.seed, case.speed)
    motion = Motion(seq.rotations, seq.translation, 30.0)
    shape = torch.tensor(case.shape, dtype=torch.float32)
    fits = {}
    for m in models:
        k = garment_key(m.template.numpy(), m.faces.numpy())
        if k not in fits:
            fits[k] = shape_case(model_garment(m), body, shape)
    c1 = time.process_time()
    drapes = [drape_motion(m, body, motion, shape,
                           fits[garment_key(m.template.numpy(), m.faces.numpy())])
              for m in models]
    queries = _query_all(drapes, body)
    rows = []
    for d, qy in zip(drapes, queries):
        fm = frame_metrics(d, body, torch.stack([dist for dist, _ in qy]))
        ct = contacts(d, body, parts, pinch, qy)
        rows.append({"seed": case.seed,
                     **{k: float(np.mean(fm[k])) for k in ("eps_e", "eps_a", "eps_c")},
                     "inside": ct["inside_vertex_frames"], "pinched": ct["pinched"],
                     "parts": {p: v["inside"] for p, v in ct["parts"].items()}})
    return rows, {"shared": c1 - c0, "models": time.process_time() - c1}


def summary(rows: list[dict]) -> dict:
    """Means over the cases (eps in %), totals of inside vertex-frames, worst cases."""
    e = np.array([r["eps_e"] for r in rows])
    c = np.array([r["eps_c"] for r in rows])
    return {"cases": len(rows), "eps_e": float(e.mean()), "eps_c": float(c.mean()),
            "eps_a": float(np.mean([r["eps_a"] for r in rows])),
            "eps_e_max": float(e.max()), "eps_c_max": float(c.max()),
            "cases_eps_e_over_4": int((e > 4.0).sum()),
            "cases_eps_c_over_0.5": int((c > 0.5).sum()),
            "inside": int(sum(r["inside"] for r in rows)),
            "pinched": int(sum(r["pinched"] for r in rows)),
            "cases_with_contact": int(sum(r["inside"] > 0 for r in rows)),
            "parts": {p: int(sum(r["parts"][p] for r in rows)) for p in PARTS}}


def compare(ref: dict, other: dict) -> dict:
    """Paired per-case counts of ``ref`` against ``other`` and the pre-registered verdict.

    ``better``: both mean eps_c and mean eps_e of ``ref`` lower than ``other``'s.

    Raises
    ------
    ValueError
        The two were not scored on the same seeds.
    """
    a, b = ref["cases"], other["cases"]
    if [r["seed"] for r in a] != [r["seed"] for r in b]:
        raise ValueError("compare: the two models were scored on different seeds")
    ia, ib = np.array([r["inside"] for r in a]), np.array([r["inside"] for r in b])
    ea, eb = np.array([r["eps_e"] for r in a]), np.array([r["eps_e"] for r in b])
    sa, sb = ref["mean"], other["mean"]
    return {"fewer_contacts": int((ia < ib).sum()), "more_contacts": int((ia > ib).sum()),
            "equal_contacts": int((ia == ib).sum()), "lower_eps_e": int((ea < eb).sum()),
            "higher_eps_e": int((ea > eb).sum()),
            "eps_c_lower": sa["eps_c"] < sb["eps_c"], "eps_e_lower": sa["eps_e"] < sb["eps_e"],
            "better": bool(sa["eps_c"] < sb["eps_c"] and sa["eps_e"] < sb["eps_e"])}


def reference_label(models: dict, preferred: str = "gaps") -> str | None:
    """The label GAPS is compared under: ``preferred`` if present, else the first GAPS model."""
    if preferred in models:
        return preferred
    return next((k for k, v in models.items() if v["method"] == "gaps"), None)


def comparisons(res: dict, preferred: str = "gaps") -> None:
    """Fill ``res["garments"][g]["comparisons"]`` from the models' cases (in place)."""
    for rec in res["garments"].values():
        ref = reference_label(rec["models"], preferred)
        rec["reference"] = ref
        rec["comparisons"] = {} if ref is None else {
            other: compare(rec["models"][ref], rec["models"][other])
            for other in rec["models"] if other != ref}


def chart(res: dict, path: Path) -> None:
    """Per garment: mean eps_c against mean eps_e per model (top); per-case eps_e of the
    reference against each other model (bottom, the diagonal = equal)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    gs = list(res["garments"])
    labels = sorted({lab for g in gs for lab in res["garments"][g]["models"]})
    colour = {lab: f"C{i % 10}" for i, lab in enumerate(labels)}  # one colour per label
    fig, axes = plt.subplots(2, len(gs), figsize=(4.6 * len(gs), 8.0), squeeze=False)
    for j, g in enumerate(gs):
        rec = res["garments"][g]
        ax = axes[0, j]
        for lab, m in rec["models"].items():
            ax.scatter(m["mean"]["eps_e"], m["mean"]["eps_c"], s=40, color=colour[lab])
            ax.annotate(lab, (m["mean"]["eps_e"], m["mean"]["eps_c"]), fontsize=8,
                        xytext=(4, 4), textcoords="offset points")
        ax.set_ylim(bottom=0.0)
        ax.set_xlabel("mean eps_e (%)")
        ax.set_ylabel("mean eps_c (%)")
        ax.set_title(f"{g}: {len(res['seeds'])} unseen random motions x {res['frames']} "
                     "frames\nlower left is better", fontsize=9)
        ax = axes[1, j]
        ref = rec.get("reference")
        lo, hi = np.inf, -np.inf
        for lab, m in rec["models"].items():
            if ref is None or lab == ref:
                continue
            x = [r["eps_e"] for r in rec["models"][ref]["cases"]]
            y = [r["eps_e"] for r in m["cases"]]
            ax.scatter(x, y, s=8, label=lab, color=colour[lab])
            lo, hi = min(lo, *x, *y), max(hi, *x, *y)
        if np.isfinite(lo):
            ax.plot([lo, hi], [lo, hi], "k--", lw=0.8)
            ax.legend(fontsize=8)
        ax.set_xlabel(f"eps_e of {ref} per case (%)")
        ax.set_ylabel("eps_e of the baseline (%)")
        ax.set_title(f"{g}: above the diagonal, {ref} has the lower eps_e", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def score(specs: list[Spec], cases: list, quiet: bool = False) -> tuple[dict, dict]:
    """Score ``specs`` on ``cases``: ``{garment: {label: record}}`` and CPU seconds."""
    import torch

    from draping.body import AnnyBody
    from polygeo.runs import progress, record_path

    torch.set_num_threads(1)
    models = load_specs(specs)
    body = AnnyBody.load()
    parts = face_parts(body)
    rows = [[] for _ in specs]
    sec = {"shared": 0.0, "models": 0.0}
    bar = progress(cases, desc="bm_gaps_wide", quiet=quiet, unit="case")
    for case in bar:
        r, s = score_case(case, models, body, parts)
        for i, row in enumerate(r):
            rows[i].append(row)
        for k in sec:
            sec[k] += s[k]
        bar.set_postfix(seed=case.seed)
    out = {}
    for s, m, rs in zip(specs, models, rows):
        out.setdefault(s.garment, {})[s.label] = {
            "model": record_path(s.source, ROOT), "method": m.settings.method,
            "width": m.settings.width, "depth": m.settings.depth,
            "mean": summary(rs), "cases": rs}
    return out, sec


def _recorded(word: str, models: list[str]) -> str:
    """A command word for the record: a model item's file by :func:`polygeo.runs.record_path`."""
    from polygeo.runs import record_path

    if word not in models or "=" not in word:
        return word
    s = parse_spec(word)
    return f"{s.label}={s.garment}:{record_path(s.source, ROOT)}"


def _same_set(res: dict, seeds: list[int], frames: int, path: Path) -> dict:
    """``res`` if it was scored on ``seeds`` and ``frames``, else ``ValueError``."""
    if res.get("seeds") != seeds or res.get("frames") != frames:
        raise ValueError(f"--merge/--add: {path} was scored on other seeds or frames; give "
                         "the same --seeds/--skip/--frames")
    return res


def run(argv: list[str] | None = None) -> dict:
    """Command line: score, merge, write the JSON and the chart; returns the record."""
    from draping.gaps import random_cases
    from polygeo.runs import atomic_write_json, record_command

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("models", nargs="*",
                   help="LABEL=GARMENT:MODEL or a shipped name (default, without --add: "
                   "tshirt dress)")
    p.add_argument("--seeds", default=SEEDS, help=f"random seeds (default {SEEDS})")
    p.add_argument("--skip", default=SKIP, help=f"seeds left out (default {SKIP})")
    p.add_argument("--frames", type=int, default=FRAMES)
    p.add_argument("--reference", default="gaps", help="label compared with the others")
    p.add_argument("--merge", action="store_true",
                   help="keep the other models of an existing --out record")
    p.add_argument("--add", nargs="+", default=[], metavar="JSON",
                   help="also take the models and runs of these records (same seeds and "
                   "frames; scored by other processes), without re-scoring them")
    p.add_argument("--out", default=str(OUT), help="JSON path (the chart beside it, .png)")
    p.add_argument("--quiet", action="store_true")
    a = p.parse_args(argv)
    models = a.models if (a.models or a.add) else ["tshirt", "dress"]
    specs = [parse_spec(t) for t in models]
    cases = random_cases(parse_seeds(a.seeds, a.skip), a.frames)
    seeds = [c.seed for c in cases]
    out = Path(a.out)
    res = {"seeds": seeds, "frames": a.frames, "pinch_m": PINCH, "garments": {}, "runs": []}
    if a.merge and out.is_file():
        res = _same_set(json.loads(out.read_text()), seeds, a.frames, out)
    for extra in (Path(x) for x in a.add):
        other = _same_set(json.loads(extra.read_text()), seeds, a.frames, extra)
        for g, rec in other["garments"].items():
            res["garments"].setdefault(g, {"models": {}})["models"].update(rec["models"])
        res["runs"].extend(r for r in other["runs"] if r not in res["runs"])
    env = environment()
    c0 = time.process_time()
    scored, sec = score(specs, cases, a.quiet) if specs else ({}, {"shared": 0.0,
                                                                   "models": 0.0})
    for g, m in scored.items():
        res["garments"].setdefault(g, {"models": {}})["models"].update(m)
    comparisons(res, a.reference)
    if specs:
        res["runs"].append({
            "command": "python benchmarks/bm_gaps_wide.py " + record_command(
                [_recorded(w, a.models) for w in (sys.argv[1:] if argv is None else argv)],
                ROOT),
            "models": [f"{s.garment}/{s.label}" for s in specs],
            "cpu_seconds": time.process_time() - c0,
            "cpu_seconds_shared": sec["shared"], "cpu_seconds_models": sec["models"],
            "threads": 1, **finish(env)})
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out, res)
    chart(res, out.with_suffix(".png"))
    for g, rec in res["garments"].items():
        for lab, m in rec["models"].items():
            s = m["mean"]
            print(f"{g:7s} {lab:10s} eps_e {s['eps_e']:.2f} % eps_c {s['eps_c']:.4f} % "
                  f"inside {s['inside']} on {s['cases_with_contact']} cases")
        for other, c in rec["comparisons"].items():
            print(f"{g:7s} {rec['reference']} vs {other}: fewer contacts on "
                  f"{c['fewer_contacts']}, more on {c['more_contacts']}, lower eps_e on "
                  f"{c['lower_eps_e']}; better: {c['better']}")
    return res


if __name__ == "__main__":
    run()
