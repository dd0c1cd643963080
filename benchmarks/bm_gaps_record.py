"""The ``bm_gaps`` record (``benchmarks/results/bm_gaps.json``): runs merged into it.

Several ``bm_gaps`` runs (one garment each, say, side by side) share one JSON: each run's
sections are merged per garment under a file lock, keeping the others' rows.
"""

from __future__ import annotations

import json
from pathlib import Path


def merge_results(path: Path, new: dict, settings: dict) -> dict:
    """Merge sections (methods / ablations per garment) into the JSON at ``path``, locked.

    Several runs (one per garment, say) may write the same file; each keeps the others'.
    """
    import fcntl
    import tempfile

    from polygeo.runs import atomic_write_json

    path.parent.mkdir(parents=True, exist_ok=True)
    with open(Path(tempfile.gettempdir()) / f"{path.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        res = json.loads(path.read_text()) if path.is_file() else {}
        for name, v in new.items():
            if name == "sweep":
                res[name] = v
            elif name == "shipped":  # one row of the methods' table per garment
                for g, val in v.items():
                    replace_shipped_row(res, g, val)
            elif name == "given":  # rows beside the methods' of each garment
                for g, rows in v.items():
                    res.setdefault("methods", {}).setdefault(g, {})["given"] = rows
            else:
                for g, val in v.items():
                    keep = res.setdefault(name, {}).get(g, {}).get("given")
                    res[name][g] = {**({"given": keep} if keep else {}), **val}
        res.setdefault("runs", []).append(settings)
        res["settings"] = settings
        atomic_write_json(path, res)
    return res


def replace_shipped_row(res: dict, garment: str, new: dict) -> None:
    """Put the re-scored shipped row ``new["row"]`` in ``res["methods"][garment]["models"]``.

    The row whose label starts with ``gaps (shipped`` is replaced, keeping that label and its
    ``not_equal_budget`` mark; the other rows stay. Raises ValueError when the record has no
    such row, or when ``new["reference"]`` (eps means of the reference drapes) is not the
    record's: the rows would then be scored against different references.
    """
    rec = res.get("methods", {}).get(garment, {})
    rows = rec.get("models", [])
    idx = [i for i, r in enumerate(rows) if r["label"].startswith("gaps (shipped")]
    if not idx:
        raise ValueError(f"garment {garment!r}: the record has no shipped GAPS row to replace")
    ref = rec.get("reference", {})
    for k in ("eps_e_mean", "eps_a_mean", "eps_c_mean"):
        if k not in ref or abs(ref[k] - new["reference"][k]) > 1e-6 * max(1.0, abs(ref[k])):
            raise ValueError(f"garment {garment!r}: reference {k} {new['reference'].get(k)} "
                             f"is not the record's {ref.get(k)}; re-run the methods section")
    old = rows[idx[0]]
    row = {**new["row"], "label": old["label"]}
    if old.get("not_equal_budget"):
        row["not_equal_budget"] = True
    rows[idx[0]] = row
