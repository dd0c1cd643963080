"""Benchmark of GAPS (issue 20): GAPS vs SNUG-like vs NCS-like, ablations, width/depth sweep.

Run ``python benchmarks/bm_gaps.py [--sections methods ablations sweep charts] [--quick]
[--steps N] [--frames T] [--cases turn/2000 random/2001] [--workers N] [--cache DIR]``.
Writes ``bm_gaps.json`` (sections merged into an existing file) and ``bm_gaps.png``
(+ ``bm_gaps_sweep.png``, ``bm_gaps_ablations.png``, ``bm_gaps_strip.png``) into
``benchmarks/results``.

Evaluation set (``datasets/make_gaps_eval.py``, held back from training): the T-shirt, the
dress and the skirt on two body shapes (phenotype draws with seeds 2000, 2001) moving through
the ``turn`` motion (never trained on) and ``random`` seed 2000 (training uses seeds < 1000),
``frames`` frames at 30 fps; ground truth: the reference solver (``draping.drape``), cached
outside the repository.

Sections (each a function):

* ``methods``: per garment, GAPS, SNUG-like and NCS-like (``draping.gaps`` methods) trained
  for the same number of steps; per method eps_e, eps_a, eps_c (%, frame mean and max over
  all frames of all cases), E_dist (cm) and E_norm (deg) against the reference, inference CPU
  ms per frame (the model alone, and with the body posing), training CPU and wall minutes.
* ``strain``: the methods' models on every selected case, eps_e, eps_a, eps_c only (no
  reference solves: cheap on the ``random`` motion, where the solver is slow).
* ``ablations``: GAPS with ``k_ext = 1`` and without L_inext (thesis Tables 4.2-4.3) on the
  T-shirt (``--ablation-garments``), same steps.
* ``sweep``: GAPS T-shirt over GRU width x depth, same steps; parsimony = the network with
  the fewest parameters whose held-out E_dist is within 10 % of the best.
* ``given``: models trained elsewhere on their own budget (``--extra-model PATH``, e.g. the
  weights h20 shipped), scored on the same cases and reported beside the methods' rows,
  marked ``not_equal_budget``.
* ``shipped``: only the shipped GAPS model of each garment, scored again; its row in the
  record's ``methods`` table is replaced (label and budget mark kept), the other rows are
  left as they were (for a new shipped model, without retraining the compared ones). The
  held-back references must be the record's (their eps figures are checked).
* ``charts``: the PNGs, from the JSON.

Several runs may share one JSON (one garment each, say, run side by side): sections are
merged per garment under a file lock. ``--only-train`` trains what the sections need and
stops; ``--wait-models`` solves the references and then waits for those models (so that
training and evaluation can run in separate processes).

Budget: by default every compared model is trained for the steps of the shipped GAPS model
of its garment (its recorded ``steps``; :class:`draping.gaps.TrainSettings` default where none
ships), and the shipped GAPS weights are used as they are. ``--steps N`` trains every compared
model, GAPS included, for ``N`` steps (an equal, smaller budget; the shipped model is then
reported beside them, marked as such). Trained models are cached (``--cache``), keyed by the
fingerprint of their settings and of their training data (``make_gaps_eval.data_digest``:
the template and the rest garments of the first training shapes, so that a changed template
or carry-over retrains); a larger ``--steps`` continues a cached run.

Timings: inference and training are CPU seconds of one thread (``time.process_time``); the
machine this ran on was shared, so wall times include waiting for a core.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("MPLBACKEND", "Agg")
for _k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_k, "1")

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent  # the repository
RESULTS = HERE / "results"
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "datasets"))

import make_gaps_eval as ev  # noqa: E402
from bm_gaps_record import merge_results  # noqa: E402
from run_env import environment, finish  # noqa: E402

SECTIONS = ("methods", "strain", "ablations", "sweep", "given", "shipped", "charts")
METHOD_NAMES = ("gaps", "snug", "ncs")
ABLATIONS = ("schedule", "one", "none")
SWEEP = ((32, 1), (64, 1), (64, 2), (128, 2), (256, 2), (128, 4))
QUICK_SWEEP = ((32, 1), (64, 1))
PARSIMONY = 0.10


# ------------------------------------------------------------------------------ models


def _portable(path) -> str:
    """A path for the record without machine paths (:func:`polygeo.runs.record_path`): a file
    of this repository relative to its root (``draping/data/gaps_tshirt.pt``), one under the
    home directory written as ``~``, any other as ``.../<folder>/<name>``."""
    from polygeo.runs import record_path

    return record_path(path, ROOT.resolve())


def _recorded(path: str) -> Path:
    """Inverse of :func:`_portable`: ``~`` expanded, repository paths resolved against it."""
    q = Path(path).expanduser()
    return q if q.is_absolute() else ROOT / q

def train_settings(garment: str, method: str = "gaps", inext: str = "auto",
                   width: int | None = None, depth: int | None = None):
    """The :class:`draping.gaps.TrainSettings` of a compared model (defaults elsewhere)."""
    from draping.gaps import GapsSettings, TrainSettings

    kw = {"garment": garment, "method": method, "inextensibility": inext}
    if width is not None:
        kw["width"] = width
    if depth is not None:
        kw["depth"] = depth
    return TrainSettings(GapsSettings(**kw))


def _run_key(settings) -> str:
    from polygeo.runs import fingerprint

    m = settings.model  # a garment file is keyed by its path (in the settings) alone
    data = "" if m.garment_file is not None else ev.data_digest(m.garment, settings.shapes,
                                                                settings.seed)
    return fingerprint({"settings": settings.key_dict(), "data": data})


def model_path(settings, steps: int, cache: Path) -> Path:
    """Where the model of ``settings`` trained for ``steps`` steps is cached."""
    m = settings.model
    name = f"{m.garment}_{m.method}_{m.inext_mode}_{m.width}x{m.depth}_{_run_key(settings)[:10]}"
    return Path(cache) / "models" / name / f"model_{steps}.pt"


def train_model(settings, steps: int, cache: Path, quiet: bool = True) -> Path:
    """Train (or continue, or re-use) a cached model; one thread."""
    import torch

    from draping.gaps import train
    from polygeo.runs import load_checkpoint

    torch.set_num_threads(1)
    out = model_path(settings, steps, cache)
    if out.is_file():
        return out
    folder = out.parent
    ck = folder / "checkpoint.pt"
    if ck.is_file() and int(load_checkpoint(ck).meta.get("step", 0)) > steps:
        folder = folder / f"from_scratch_{steps}"  # the shared run went past this budget
    cmd = f"bm_gaps.py train_model({settings.model}, steps={steps})"
    res = train(settings, folder, steps=steps, quiet=quiet, command=cmd)
    shutil.copyfile(res.model_path, out)
    return out


def _train_job(args) -> str:
    settings, steps, cache, quiet = args
    c0 = time.process_time()
    p = train_model(settings, steps, cache, quiet)
    return f"trained {p.parent.name} {steps} steps ({time.process_time() - c0:.0f} CPU s)"


def _ref_job(args) -> str:
    return ev._one(args)


def run_jobs(jobs: list, workers: int) -> None:
    """Run ``(function, args)`` jobs, in ``workers`` forked processes when ``workers > 1``."""
    if workers <= 1 or len(jobs) <= 1:
        for fn, a in jobs:
            print(fn(a), flush=True)
        return
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(min(workers, len(jobs)), mp_context=mp.get_context("fork")) as ex:
        futs = [ex.submit(fn, a) for fn, a in jobs]
        for f in futs:
            print(f.result(), flush=True)


def shipped_steps(garment: str) -> int | None:
    """Training steps recorded in the shipped GAPS model of a garment (None: none ships)."""
    from draping.gaps import load_model, shipped_model_path

    p = shipped_model_path(garment)
    if not p.is_file():
        return None
    return int(load_model(p).record.get("training", {}).get("steps", 0)) or None


def budget_of(garment: str, steps: int | None) -> int:
    """Steps of the compared models of a garment (see the module docstring)."""
    if steps is not None:
        return int(steps)
    return shipped_steps(garment) or train_settings(garment).steps


# -------------------------------------------------------------------------- evaluation


class Evaluator:
    """Held-back cases of each garment with their references; scores models on them."""

    def __init__(self, cases: list, cache: Path):
        from draping.body import AnnyBody

        self.cases, self.cache = cases, Path(cache)
        self.body = AnnyBody.load()
        self._refs: dict = {}
        self._shape_cases: dict = {}

    def garment_cases(self, garment: str) -> list:
        return [c for c in self.cases if c.garment == garment]

    def reference(self, case) -> dict:
        if case not in self._refs:
            self._refs[case] = ev.reference_drape(case, self.cache)
        return self._refs[case]

    def shape_case(self, model, case):
        import torch

        from draping.gaps import model_garment, shape_case

        k = (case.garment, case.shape)
        if k not in self._shape_cases:
            s = torch.tensor(case.shape, dtype=torch.float32)
            self._shape_cases[k] = shape_case(model_garment(model), self.body, s)
        return self._shape_cases[k]

    def drape(self, model, case):
        from draping.gaps import drape_motion

        mot = ev.case_motion(self.cache, case, self.body)
        sc = self.shape_case(model, case)
        best = None
        for _ in range(3):  # timing: the best of three runs (a shared machine)
            d = drape_motion(model, self.body, mot, case=sc)
            if best is None or d.seconds["with_posing"] < best.seconds["with_posing"]:
                best = d
        return best

    def score(self, model) -> dict:
        """Metrics of a model on its garment's cases (frame means and maxima, per case)."""
        from draping.gaps import frame_metrics
        from draping.metrics import distance_error, normal_error

        per = {k: [] for k in ("eps_e", "eps_a", "eps_c", "e_dist_cm", "e_norm_deg")}
        sec = {"model": 0.0, "with_posing": 0.0}
        n, rows = 0, []
        for c in self.garment_cases(model.settings.garment):
            d = self.drape(model, c)
            ref = self.reference(c)
            m = frame_metrics(d, self.body)
            x = d.x.double().numpy()
            m["e_dist_cm"] = np.asarray(distance_error(x, ref["x"])).tolist()
            m["e_norm_deg"] = np.asarray(normal_error(x, ref["x"], ref["faces"])).tolist()
            for k in per:
                per[k].extend(m[k])
            for k in sec:
                sec[k] += d.seconds[k]
            n += d.x.shape[0]
            rows.append({"case": c.label, **{k: float(np.mean(m[k])) for k in per},
                         "eps_c_max": float(np.max(m["eps_c"])),
                         "eps_e_max": float(np.max(m["eps_e"]))})
        return {**summary(per), "ms_per_frame": 1000.0 * sec["model"] / max(n, 1),
                "ms_per_frame_with_posing": 1000.0 * sec["with_posing"] / max(n, 1),
                "frames": n, "cases": rows}

    def strain(self, model) -> dict:
        """eps_e, eps_a, eps_c of a model on its garment's cases; no reference drape needed."""
        from draping.gaps import frame_metrics

        per = {k: [] for k in ("eps_e", "eps_a", "eps_c")}
        rows = []
        for c in self.garment_cases(model.settings.garment):
            m = frame_metrics(self.drape(model, c), self.body)
            for k in per:
                per[k].extend(m[k])
            rows.append({"case": c.label, **{k: float(np.mean(m[k])) for k in per},
                         "eps_c_max": float(np.max(m["eps_c"]))})
        return {**summary(per), "frames": len(per["eps_e"]), "cases": rows}

    def reference_summary(self, garment: str) -> dict:
        """The reference drapes' own eps metrics and solver CPU seconds per frame."""
        per = {"eps_e": [], "eps_a": [], "eps_c": []}
        cpu = []
        for c in self.garment_cases(garment):
            for r in self.reference(c)["rows"]:
                for k in per:
                    per[k].append(r[k])
                cpu.append(r["cpu_seconds"])
        return {**summary(per), "cpu_s_per_frame_median": float(np.median(cpu)),
                "cpu_s_per_frame_max": float(np.max(cpu))}


def summary(per: dict) -> dict:
    """``{k_mean, k_max}`` over frames for every metric list."""
    out = {}
    for k, v in per.items():
        out[f"{k}_mean"] = float(np.mean(v))
        out[f"{k}_max"] = float(np.max(v))
    return out


def model_record(path: Path, ev_: Evaluator, label: str) -> dict:
    """A model's training record and held-back scores."""
    from draping.gaps import load_model

    m = load_model(path)
    # a model trained in several runs (e.g. fine-tuned) records their sum as total_training
    tr = m.record.get("total_training", m.record.get("training", {}))
    n_par = sum(p.numel() for p in m.parameters())
    n_gru = sum(p.numel() for p in m.gru.parameters())
    return {"label": label, "garment": m.settings.garment, "method": m.settings.method,
            "inextensibility": m.settings.inext_mode, "width": m.settings.width,
            "depth": m.settings.depth, "rank": m.settings.rank, "params": int(n_par),
            "gru_params": int(n_gru), "steps": tr.get("steps"),
            "train_cpu_minutes": tr.get("cpu_minutes"),
            "train_wall_minutes": tr.get("wall_minutes"),
            "model": _portable(path), **ev_.score(m)}


# ---------------------------------------------------------------------------- sections


def plan(args, cases) -> dict:
    """The models each selected section needs: ``{key: (settings, steps, label)}``."""
    need = {}
    sec = set(args.sections)
    for g in args.garments:
        steps = budget_of(g, args.steps)
        if {"methods", "strain"} & sec:
            for meth in METHOD_NAMES:
                need[(g, meth)] = (train_settings(g, meth), steps, meth)
        if "ablations" in sec and g in args.ablation_garments:
            for inext in ABLATIONS:
                same = "auto" if inext == "schedule" else inext  # = the methods' GAPS model
                need[(g, "gaps", inext)] = (train_settings(g, "gaps", same), steps,
                                            f"gaps, inext={inext}")
    if "sweep" in sec and not args.sweep_models:
        steps = budget_of("tshirt", args.steps)
        for w, d in args.sweep:
            need[("sweep", w, d)] = (train_settings("tshirt", "gaps", "auto", w, d), steps,
                                     f"{w}x{d}")
    return need


def use_shipped(garment: str, args) -> bool:
    """GAPS of ``garment`` is the shipped model (default budget, one ships)."""
    from draping.gaps import shipped_model_path

    return args.steps is None and not args.no_shipped and shipped_model_path(garment).is_file()


def prepare_all(args, cases, cache: Path) -> dict:
    """Solve the references and train the models the sections need (``--workers``)."""
    need = plan(args, cases)
    jobs = []
    if {"methods", "ablations", "sweep"} & set(args.sections) and not args.only_train:
        jobs += [(_ref_job, (c, cache, True)) for c in cases]
    missing = []
    for key, (st, steps, _) in need.items():
        shipped = key[1:] in (("gaps",), ("gaps", "schedule")) and use_shipped(key[0], args)
        if not shipped and not model_path(st, steps, cache).is_file():
            missing.append(model_path(st, steps, cache))
            if not args.wait_models:
                jobs.append((_train_job, (st, steps, cache, args.quiet)))
    run_jobs(jobs, args.workers)
    while args.wait_models and not all(p.is_file() for p in missing):
        time.sleep(20)
    return need


def section_methods(args, ev_: Evaluator, need: dict, cache: Path) -> dict:
    """GAPS vs SNUG-like vs NCS-like per garment."""
    from draping.gaps import shipped_model_path

    out = {}
    for g in args.garments:
        rows = []
        for meth in METHOD_NAMES:
            st, steps, label = need[(g, meth)]
            if meth == "gaps" and use_shipped(g, args):
                rows.append(model_record(shipped_model_path(g), ev_, "gaps (shipped)"))
            else:
                rows.append(model_record(model_path(st, steps, cache), ev_, label))
        if args.steps is not None and shipped_model_path(g).is_file() and not args.no_shipped:
            r = model_record(shipped_model_path(g), ev_, "gaps (shipped, own budget)")
            r["not_equal_budget"] = True
            rows.append(r)
        out[g] = {"models": rows, "reference": ev_.reference_summary(g),
                  "steps": budget_of(g, args.steps)}
        _print_rows(g, rows)
    return out


def section_strain(args, ev_: Evaluator, need: dict, cache: Path) -> dict:
    """The methods' models on every selected case, eps metrics only (no reference solves).

    The reference solver is slow on the ``random`` motion (about 20 CPU s per T-shirt frame
    against 1.4 on ``turn``); eps_e, eps_a and eps_c need only the rest garment and the body.
    """
    from draping.gaps import load_model, shipped_model_path

    out = {}
    for g in args.garments:
        rows = []
        for meth in METHOD_NAMES:
            st, steps, label = need[(g, meth)]
            shipped = meth == "gaps" and use_shipped(g, args)
            p = shipped_model_path(g) if shipped else model_path(st, steps, cache)
            rows.append({"label": label, "method": meth, "steps": steps, "model": _portable(p),
                         **ev_.strain(load_model(p))})
        out[g] = {"models": rows, "steps": budget_of(g, args.steps)}
        print(f"\n{g} (eps only)")
        for r in rows:
            print(f"{r['label']:10s} eps_e {r['eps_e_mean']:.2f} eps_a {r['eps_a_mean']:.2f} "
                  f"eps_c {r['eps_c_mean']:.3f} | " + " ".join(
                      f"{c['case']} {c['eps_e']:.2f}/{c['eps_c']:.2f}" for c in r["cases"]),
                  flush=True)
    return out


def section_given(args, ev_: Evaluator, need: dict, cache: Path) -> dict:
    """Models given with ``--extra-model`` (trained on their own budget), per garment."""
    from draping.gaps import load_model

    out = {}
    for path in args.extra_model:
        g = load_model(path).settings.garment
        if g in args.garments:
            r = model_record(Path(path), ev_, "")
            r["label"] = f"{r['method']} ({r['steps']} steps, given)"
            r["not_equal_budget"] = True
            out.setdefault(g, []).append(r)
    for g, rows in out.items():
        _print_rows(g + " (given models)", rows)
    return out


def section_shipped(args, ev_: Evaluator, need: dict, cache: Path) -> dict:
    """The shipped GAPS model of each garment alone, with its references' summary."""
    from draping.gaps import shipped_model_path

    out = {}
    for g in args.garments:
        p = shipped_model_path(g)
        if not p.is_file():
            raise ValueError(f"garments: no shipped GAPS model for {g!r}")
        row = model_record(p, ev_, "gaps (shipped)")
        out[g] = {"row": row, "reference": ev_.reference_summary(g)}
        _print_rows(g + " (shipped, re-scored)", [row])
    return out


def section_ablations(args, ev_: Evaluator, need: dict, cache: Path) -> dict:
    """GAPS with the k_ext schedule, k_ext = 1, and no L_inext."""
    from draping.gaps import shipped_model_path

    out = {}
    for g in args.garments:
        if g not in args.ablation_garments:
            continue
        rows = []
        for inext in ABLATIONS:
            st, steps, label = need[(g, "gaps", inext)]
            p = (shipped_model_path(g) if inext == "schedule" and use_shipped(g, args)
                 else model_path(st, steps, cache))
            rows.append(model_record(p, ev_, label))
        out[g] = {"models": rows}
        _print_rows(g + " ablations", rows)
    return out


def section_sweep(args, ev_: Evaluator, need: dict, cache: Path) -> dict:
    """Width x depth of the GAPS T-shirt; parsimony within 10 % of the best E_dist.

    With ``--sweep-models``: the given model files instead (e.g. the shipped models of two
    sizes, each trained on its own recorded budget), parsimony per garment.
    """
    if args.sweep_models:
        return sweep_given(args.sweep_models, ev_, args.garments)
    rows = []
    for w, d in args.sweep:
        st, steps, label = need[("sweep", w, d)]
        rows.append(model_record(model_path(st, steps, cache), ev_, label))
    pick, best = parsimonious(rows)
    _print_rows("tshirt sweep", rows)
    print(f"parsimony: {pick['label']} ({pick['params']} parameters, E_dist "
          f"{pick['e_dist_cm_mean']:.3f} cm; best {best:.3f} cm)")
    return {"models": rows, "criterion": f"fewest parameters with E_dist <= {1 + PARSIMONY:g} x "
            "best", "best_e_dist_cm": best, "parsimonious": pick["label"]}


def sweep_given(paths: list, ev_: Evaluator, garments: list) -> dict:
    """Parsimony over given model files, per garment (``{"garments": {g: {...}}, ...}``)."""
    from draping.gaps import load_model

    out = {}
    for path in paths:
        m = load_model(path)
        g = m.settings.garment
        if g in garments:
            label = f"{m.settings.width}x{m.settings.depth}"
            out.setdefault(g, []).append(model_record(Path(path), ev_, label))
    res = {}
    for g, rows in out.items():
        pick, best = parsimonious(rows)
        _print_rows(f"{g} sweep (given models)", rows)
        print(f"parsimony: {pick['label']} ({pick['params']} parameters, E_dist "
              f"{pick['e_dist_cm_mean']:.3f} cm; best {best:.3f} cm)")
        res[g] = {"models": rows, "best_e_dist_cm": best, "parsimonious": pick["label"],
                  "within": {r["label"]: float(r["e_dist_cm_mean"]) / best - 1.0 for r in rows}}
    return {"garments": res, "given": True,
            "criterion": f"fewest parameters with E_dist <= {1 + PARSIMONY:g} x best"}


def parsimonious(rows: list, key: str = "e_dist_cm_mean", tol: float = PARSIMONY):
    """The row with the fewest ``params`` whose ``key`` is within ``tol`` of the best.

    Returns ``(row, best value)``; ties in size go to the lower error.
    """
    if not rows:
        raise ValueError("rows: expected at least one sweep result")
    best = min(float(r[key]) for r in rows)
    ok = [r for r in rows if float(r[key]) <= (1.0 + tol) * best]
    return min(ok, key=lambda r: (r["params"], float(r[key]))), best


def _print_rows(title: str, rows: list) -> None:
    print(f"\n{title}")
    print(f"{'model':30s} {'steps':>6s} {'eps_e':>6s} {'eps_a':>6s} {'eps_c':>6s} "
          f"{'c_max':>6s} {'E_dist':>7s} {'E_norm':>7s} {'ms':>6s} {'ms+pose':>7s} {'CPUmin':>6s}")
    for r in rows:
        print(f"{r['label']:30s} {r['steps'] or 0:6d} {r['eps_e_mean']:6.2f} "
              f"{r['eps_a_mean']:6.2f} {r['eps_c_mean']:6.2f} {r['eps_c_max']:6.2f} "
              f"{r['e_dist_cm_mean']:7.2f} {r['e_norm_deg_mean']:7.2f} {r['ms_per_frame']:6.2f} "
              f"{r['ms_per_frame_with_posing']:7.2f} {r['train_cpu_minutes'] or 0:6.1f}",
              flush=True)


# ------------------------------------------------------------------------------ charts

MARKERS = {"gaps": "o", "snug": "s", "ncs": "^"}


def chart_methods(res: dict, path: Path) -> None:
    """Error vs inference ms and vs training CPU minutes, one marker per method, per garment."""
    import matplotlib.pyplot as plt

    gs = [g for g in res if g in ev.GARMENTS and "models" in res[g]]
    fig, axes = plt.subplots(2, len(gs), figsize=(4.2 * len(gs), 7), squeeze=False, dpi=100)
    for j, g in enumerate(gs):
        for r in res[g].get("models", []) + res[g].get("given", []):
            mk = MARKERS.get(r["method"], "x")
            face = "none" if r.get("not_equal_budget") else None
            for i, xk in enumerate(("ms_per_frame", "train_cpu_minutes")):
                axes[i][j].scatter(r[xk] or 0, r["e_dist_cm_mean"], marker=mk, s=60,
                                   label=f"{r['label']} (eps_e {r['eps_e_mean']:.1f}%, "
                                   f"eps_c {r['eps_c_mean']:.2f}%)",
                                   facecolors=face, edgecolors="k" if face else None)
        for i, xl in enumerate(("inference CPU ms / frame (model + skinning)",
                                "training CPU minutes")):
            ax = axes[i][j]
            ax.set_xlabel(xl)
            ax.set_ylabel("E_dist to reference (cm)")
            ax.set_title(f"{g} ({res[g].get('steps')} steps)")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=6)
    fig.suptitle("GAPS vs SNUG-like vs NCS-like on held-back motions and shapes")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def chart_sweep(res: dict, path: Path) -> None:
    """E_dist against parameters per size; one panel per garment for a given-model sweep."""
    import matplotlib.pyplot as plt

    panels = res["garments"] if "garments" in res else {"tshirt": res}
    fig, axes = plt.subplots(1, len(panels), figsize=(6 * len(panels), 4), dpi=100,
                             squeeze=False)
    for ax, (g, r0) in zip(axes[0], panels.items()):
        for r in r0["models"]:
            pick = r["label"] == r0["parsimonious"]
            ax.scatter(r["params"], r["e_dist_cm_mean"], marker="*" if pick else "o",
                       s=160 if pick else 40, c="C3" if pick else "C0")
            ax.annotate(f"{r['label']} ({r['ms_per_frame']:.1f} ms, {r['steps']} steps)",
                        (r["params"], r["e_dist_cm_mean"]), fontsize=7)
        ax.axhline((1 + PARSIMONY) * r0["best_e_dist_cm"], ls="--", c="gray", lw=0.8,
                   label="best + 10 %")
        ax.set_xscale("log")
        ax.set_xlabel("parameters (GRU + output basis)")
        ax.set_ylabel("E_dist to reference (cm)")
        ax.set_title(f"GAPS {g}: GRU width x depth (star: parsimonious)", fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def chart_ablations(res: dict, path: Path) -> None:
    import matplotlib.pyplot as plt

    keys = (("eps_e_mean", "eps_e (%)"), ("eps_c_mean", "eps_c (%)"),
            ("e_dist_cm_mean", "E_dist (cm)"))
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.4), dpi=100)
    for i, (k, name) in enumerate(keys):
        for j, g in enumerate(g for g in res if g in ev.GARMENTS):
            rows = res[g]["models"]
            xs = np.arange(len(rows)) + 0.3 * j
            axes[i].bar(xs, [r[k] for r in rows], width=0.28, label=g)
            axes[i].set_xticks(np.arange(len(rows)), [r["inextensibility"] for r in rows])
        axes[i].set_title(name)
        axes[i].legend(fontsize=7)
    fig.suptitle("GAPS ablations: k_ext schedule / k_ext = 1 / no L_inext")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def strip(args, ev_: Evaluator, res: dict, cache: Path, path: Path) -> None:
    """The last frame of the first T-shirt case: reference, then each method.

    Another garment's when the run has no T-shirt case; nothing when it has no case of any
    garment in the record.
    """
    from draping import viz
    from draping.gaps import load_model

    have = [g for g in res if g in ev.GARMENTS and ev_.garment_cases(g)]
    if not have:  # e.g. ``--garments dress`` with only the T-shirt's rows in the record
        return
    g = "tshirt" if "tshirt" in have else have[0]
    case = ev_.garment_cases(g)[0]
    ref = ev_.reference(case)
    meshes, titles = [], []
    body_v = None
    for r in res[g]["models"]:
        if r.get("not_equal_budget"):
            continue
        d = ev_.drape(load_model(_recorded(r["model"])), case)
        body_v = d.body_vertices[-1].numpy()
        meshes.append((body_v, ev_.body.faces.numpy(), d.x[-1].numpy()))
        titles.append(r["label"])
    meshes.insert(0, (body_v, ev_.body.faces.numpy(), ref["x"][-1]))
    titles.insert(0, "reference")
    ims = viz.render_drapes(meshes, ref["faces"], titles=titles)
    viz.write_strip(ims, path)


# -------------------------------------------------------------------------------- main


def keep_pairs(cases: list, pairs) -> list:
    """The cases whose ``motion/shape_seed`` is in ``pairs`` (all of them when None).

    Raises
    ------
    ValueError
        A pair that is malformed or matches no case.
    """
    if pairs is None:
        return cases
    want = set()
    for p in pairs:
        m, _, k = p.partition("/")
        if not m or not k.isdigit():
            raise ValueError(f"cases: expected MOTION/SHAPE_SEED like turn/2000, got {p!r}")
        want.add((m, int(k)))
    out = [c for c in cases if (c.motion, c.shape_seed) in want]
    missing = want - {(c.motion, c.shape_seed) for c in out}
    if missing:
        raise ValueError(f"cases: no held-back case for {sorted(missing)}")
    return out


def _sweep_arg(text: str) -> tuple:
    return tuple(tuple(int(v) for v in item.split("x")) for item in text.split(","))


def parse(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sections", nargs="+", default=list(SECTIONS), choices=SECTIONS)
    ap.add_argument("--quick", action="store_true",
                    help="smoke run: one case per garment, 6 frames, 10 steps, 2 sweep points")
    ap.add_argument("--garments", nargs="+", default=list(ev.GARMENTS), choices=ev.GARMENTS)
    ap.add_argument("--ablation-garments", nargs="+", default=["tshirt"], choices=ev.GARMENTS)
    ap.add_argument("--frames", type=int, default=None, help="frames per case (default 30)")
    ap.add_argument("--steps", type=int, default=None,
                    help="equal training steps of every compared model (default: the shipped "
                    "GAPS model's steps, used as shipped)")
    ap.add_argument("--no-shipped", action="store_true", help="never use the shipped weights")
    ap.add_argument("--extra-model", action="append", default=[], metavar="PATH",
                    help="also score this model file (methods section, its garment), marked as "
                    "trained on another budget; repeatable")
    ap.add_argument("--sweep", type=_sweep_arg, default=None,
                    help="width x depth list, e.g. 32x1,64x2 (default: " +
                    ",".join(f"{w}x{d}" for w, d in SWEEP) + ")")
    ap.add_argument("--sweep-models", nargs="+", default=None, metavar="PATH",
                    help="sweep section: score these model files (any sizes, each on its own "
                    "recorded budget, e.g. shipped models) instead of training --sweep; "
                    "parsimony per garment")
    ap.add_argument("--workers", type=int, default=1, help="processes for training/references")
    ap.add_argument("--cache", type=Path, default=None, help="models and references")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--motions", nargs="+", default=None, choices=[m for m, _ in ev.MOTIONS],
                    help="keep these held-back motions (default both)")
    ap.add_argument("--shape-seeds", nargs="+", type=int, default=None, choices=ev.SHAPE_SEEDS,
                    help="keep these held-back shapes (default both)")
    ap.add_argument("--cases", nargs="+", default=None, metavar="MOTION/SHAPE_SEED",
                    help="keep these (motion, shape) pairs only, e.g. turn/2000 random/2001 "
                    "(default: every pair --motions x --shape-seeds)")
    ap.add_argument("--wait-models", action="store_true",
                    help="do not train: solve the references, then wait for the models "
                    "(trained by a concurrent --only-train run)")
    ap.add_argument("--only-train", action="store_true",
                    help="train the models the sections need, then stop (no references)")
    ap.add_argument("--quiet", action="store_true")
    a = ap.parse_args(argv)
    if a.frames is None:
        a.frames = 6 if a.quick else 30
    if a.steps is None and a.quick:
        a.steps = 10
    if a.sweep is None:
        a.sweep = QUICK_SWEEP if a.quick else SWEEP
    return a


def main(argv=None) -> dict:
    import torch

    torch.set_num_threads(1)
    args = parse(argv)
    env = environment()
    cache = ev.default_cache() if args.cache is None else args.cache
    cases = keep_pairs(ev.eval_cases(args.garments, args.frames, args.quick, args.motions,
                                     args.shape_seeds), args.cases)
    c0, t0 = time.process_time(), time.perf_counter()
    need = prepare_all(args, cases, cache)
    if args.only_train:
        return {}
    ev_ = Evaluator(cases, cache)
    args.out.mkdir(parents=True, exist_ok=True)
    jp = args.out / "bm_gaps.json"
    from polygeo.runs import record_command

    stamp = {"command": "python benchmarks/bm_gaps.py " + record_command(
        sys.argv[1:] if argv is None else argv, ROOT.resolve()),
        "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    new = {}
    runs = {"methods": section_methods, "strain": section_strain,
            "ablations": section_ablations, "sweep": section_sweep, "given": section_given,
            "shipped": section_shipped}
    for name, fn in runs.items():
        if name in args.sections:
            r = fn(args, ev_, need, cache)
            if name == "sweep":
                new[name] = {**r, **stamp}
            elif name == "given":
                new[name] = {g: [{**x, **stamp} for x in v] for g, v in r.items()}
            elif name == "shipped":
                new[name] = {g: {**v, "row": {**v["row"], **stamp}} for g, v in r.items()}
            else:
                new[name] = {g: {**v, **stamp} for g, v in r.items()}
    settings = {
        **stamp, "quick": args.quick, "frames": args.frames, "garments": args.garments,
        "cases": sorted({f"{c.motion}{c.seed}/shape{c.shape_seed} {c.shape}" for c in cases}),
        "steps": args.steps, "equal_budget": True,
        "budget_note": ("every compared model trained for the same number of steps"
                        + ("" if args.steps is None else f" ({args.steps}, smaller than the "
                           "script's default of the shipped GAPS model's steps)")),
        "held_back": ev.__doc__.split("\n\n")[2],
        "cpu_minutes_this_run": (time.process_time() - c0) / 60.0,
        "wall_minutes_this_run": (time.perf_counter() - t0) / 60.0,
        **finish(env)}
    res = merge_results(jp, new, settings)
    if "charts" in args.sections:
        if "methods" in res:
            chart_methods(res["methods"], args.out / "bm_gaps.png")
            strip(args, ev_, res["methods"], cache, args.out / "bm_gaps_strip.png")
        if "sweep" in res:
            chart_sweep(res["sweep"], args.out / "bm_gaps_sweep.png")
        if "ablations" in res:
            chart_ablations(res["ablations"], args.out / "bm_gaps_ablations.png")
    print(f"wrote {jp}")
    return res


if __name__ == "__main__":
    main()
