"""``polygeo jets`` for LAS/LAZ files, large clouds (tiles), Dask and batches of files.

Plugged into ``polygeo._cli.jets`` by two hooks: :func:`add_arguments` (options) and
:func:`wants` / :func:`run` (taking over the run when one of these options, a LAS/LAZ file,
``--orient up`` or a glob pattern is used).
"""

from __future__ import annotations

import argparse
import glob
import shutil
import sys
import time
from pathlib import Path

import numpy as np

_LAS = (".las", ".laz")


def add_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group(
        "large clouds",
        "LAS/LAZ in and out (every input dimension kept; normal_x/y/z, k1, k2, "
        "mean_curvature, gaussian_curvature, d1_x..d2_z, jet_status added as extra "
        "dimensions), tiles with exact halos, Dask, batches ('scans/*.laz' -o out/)",
    )
    g.add_argument("--memory-limit", default=None,
                   help="process in spatial tiles so that peak memory stays under this size "
                        "(e.g. 4GB); results equal the in-memory run with --orient up/none "
                        "(default: none, in memory)")
    g.add_argument("--tile-points", type=int, default=None,
                   help="tiles of about this many points (instead of --memory-limit; "
                        "default: none)")
    g.add_argument("--dask", default=None,
                   help="run the tiles as Dask tasks: 'local:N' (LocalCluster of N workers) "
                        "or a scheduler address 'tcp://host:8786' (default: none, in this process)")
    g.add_argument("--keep-parts", action="store_true",
                   help="keep the run folder OUTPUT.parts/ (memory-mapped results, tile log) "
                        "after success; it is always kept after a failure so that a new run "
                        "resumes")


def wants(args: argparse.Namespace) -> bool:
    """True when this module runs the command."""
    inp, out = str(args.input), str(args.output)
    return (
        any(ch in inp for ch in "*?[")
        or Path(inp).suffix.lower() in _LAS
        or Path(out).suffix.lower() in _LAS
        or args.memory_limit is not None
        or args.tile_points is not None
        or args.dask is not None
        or args.orient == "up"
    )


def _settings(args):
    from polygeo.cli import int_or_auto
    from polygeo.tiling import TileSettings

    orient = args.orient
    if orient == "auto":
        orient = "up"
    if orient not in ("up", "none"):
        raise ValueError(f"--orient: tiled runs orient each point on its own: expected 'up' "
                         f"(towards +z, the default for tiles) or 'none', got {orient!r}")
    return TileSettings(
        k=int_or_auto(args.k, "k"), radius=args.radius, order=int_or_auto(args.order, "order"),
        weights=None if args.weights == "uniform" else "gaussian",
        interpolate=bool(args.interpolate), orient=orient,
    )


def _write(out: Path, src: Path, fields: dict, points=None) -> None:
    from polygeo.io import write_npz
    from polygeo.io_las import write_las

    if out.suffix.lower() in _LAS:
        if src.suffix.lower() not in _LAS:
            raise ValueError(f"-o/--output: a LAS/LAZ output needs a LAS/LAZ input (its "
                             f"dimensions are copied), got {str(src)!r}")
        write_las(out, src, fields)
    else:
        pts = points if points is not None else None
        write_npz(out, points=np.asarray(pts), **{k: np.asarray(v) for k, v in fields.items()})


def _check_output(out: Path) -> None:
    if out.suffix.lower() not in (".npz", *_LAS):
        raise ValueError(f"-o/--output: expected a .npz, .las or .laz path, got {str(out)!r}")


def _one(args, inp: Path, out: Path, client=None) -> str:
    from polygeo.estimate import differential_quantities
    from polygeo.io import read_points
    from polygeo.io_las import open_points, read_las

    _check_output(out)
    t0 = time.perf_counter()
    tiled = any(v is not None for v in (args.memory_limit, args.tile_points, args.dask)) \
        or client is not None
    if not tiled:
        data = read_las(inp) if inp.suffix.lower() in _LAS else read_points(
            inp, columns=getattr(args, "columns", None))
        st = _settings(args) if args.orient in ("up", "auto") and data.faces is None \
            and data.normals is None else None
        kw = st.estimator_kwargs() if st else {}
        if st is None:
            from polygeo.cli import int_or_auto

            kw = dict(k=int_or_auto(args.k, "k"), radius=args.radius,
                      order=int_or_auto(args.order, "order"),
                      weights=None if args.weights == "uniform" else "gaussian",
                      interpolate=bool(args.interpolate))
        ref, orient = data.normals, ("auto" if args.orient == "up" else args.orient)
        if st is not None and st.orient == "up":
            from polygeo.tiling import up_reference

            ref = up_reference(data.points)
            orient = "input"
        dq = differential_quantities(data.points, faces=data.faces, normals=ref,
                                     orient=orient, rings=args.rings,
                                     progress=False if args.quiet else None, **kw)
        fields = {f: getattr(dq, f) for f in ("normals", "k1", "k2", "mean_curvature",
                                              "gaussian_curvature", "d1", "d2")}
        fields["status"] = np.asarray(dq.status).astype(np.int64)
        _write(out, inp, fields, data.points)
        n = len(data.points)
        return f"{inp} -> {out}: {n} points in memory, {time.perf_counter() - t0:.1f} s"
    from polygeo.tiling import jets_dask, jets_tiled

    parts = out.with_name(out.name + ".parts")
    pts = open_points(inp, cache_dir=parts / "cache")
    kw = dict(memory_limit=args.memory_limit or "4GB", tile_points=args.tile_points,
              source=inp, quiet=True if args.quiet else None)
    if client is not None:
        res = jets_dask(pts, parts, _settings(args), dask=client, **kw)
    else:
        res = jets_tiled(pts, parts, _settings(args), **kw)
    fields = {f: res[f] for f in res.fields}
    _write(out, inp, fields, pts if out.suffix.lower() == ".npz" else None)
    if not args.keep_parts:
        shutil.rmtree(parts, ignore_errors=True)
    dt = time.perf_counter() - t0
    n = int(pts.shape[0])
    return (f"{inp} -> {out}: {n} points in {res.n_tiles} tiles ({res.n_resumed} resumed), "
            f"{dt:.1f} s ({n / max(dt, 1e-9):,.0f} points/s)")


def run(args: argparse.Namespace) -> int:
    from polygeo.tiling import dask_client

    inp = str(args.input)
    batch = any(ch in inp for ch in "*?[")
    if batch:
        files = sorted(Path(f) for f in glob.glob(inp))
        if not files:
            raise ValueError(f"input: the pattern {inp!r} matches no file")
        outdir = Path(args.output)
        if outdir.suffix:
            raise ValueError(f"-o/--output: with a pattern of inputs, expected a folder, got "
                             f"{str(outdir)!r}")
        jobs = [(f, outdir / (f.stem + "_jets" + (f.suffix if f.suffix.lower() in _LAS
                                                  else ".npz"))) for f in files]
    else:
        jobs = [(Path(inp), Path(args.output))]
    for f, _o in jobs:
        if not f.exists():
            raise FileNotFoundError(f"input: no such file {str(f)!r}")
    client, own = (None, False)
    if args.dask is not None:
        client, own = dask_client(args.dask)
    try:
        for f, o in jobs:
            line = _one(args, f, o, client)
            if not args.quiet:
                print("polygeo jets: " + line, file=sys.stdout)
    finally:
        if own:
            cluster = getattr(client, "cluster", None)
            client.close()
            if cluster is not None:
                cluster.close()
    return 0
