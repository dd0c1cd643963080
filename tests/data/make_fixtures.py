"""Write the reader-matrix fixtures of tests/polygeo/test_io_formats.py with OTHER writers.

Every file holds the same surface: trimesh's icosphere of subdivision 1 (42 vertices on the
unit sphere, 80 triangles), written by pyvista/VTK, trimesh, meshio, plyfile or by hand where
the variant is a matter of text layout (quads, comments, separators). The tests check what
was read against the sphere (every point at distance 1 from the origin, the area of the
triangles, outward unit normals), never against a stored copy of our own output.

Run from the repository root:  python tests/data/make_fixtures.py
"""

from __future__ import annotations

import io
from pathlib import Path

import meshio
import numpy as np
import pyvista as pv
import trimesh
from plyfile import PlyData, PlyElement

HERE = Path(__file__).resolve().parent


def sphere(subdivisions: int = 1) -> tuple[np.ndarray, np.ndarray]:
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    return np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int64)


def poly(v: np.ndarray, f: np.ndarray) -> pv.PolyData:
    cells = np.hstack([np.full((len(f), 1), 3), f]).ravel()
    return pv.PolyData(v, cells)


def plyfile_variants(v: np.ndarray, f: np.ndarray) -> None:
    n = len(v)
    rgb = np.clip(np.rint((v + 1) * 127.5), 0, 255).astype(np.uint8)
    # big-endian double with normals, colours, an extra scalar, list types ushort/uint,
    # an extra element and comment / obj_info lines (what scanners write)
    vert = np.zeros(n, dtype=[("x", ">f8"), ("y", ">f8"), ("z", ">f8"), ("nx", ">f4"),
                              ("ny", ">f4"), ("nz", ">f4"), ("red", "u1"), ("green", "u1"),
                              ("blue", "u1"), ("quality", ">f4"), ("scan_id", ">i2")])
    for i, c in enumerate("xyz"):
        vert[c] = v[:, i]
        vert["n" + c] = v[:, i]
    vert["red"], vert["green"], vert["blue"] = rgb.T
    vert["quality"] = np.linspace(0, 1, n)
    vert["scan_id"] = np.arange(n) % 3
    face = np.zeros(len(f), dtype=[("vertex_indices", ">u4", (3,)), ("flags", "u1")])
    face["vertex_indices"] = f
    extra = np.zeros(2, dtype=[("id", "i4"), ("name_len", "f4")])
    elems = [
        PlyElement.describe(vert, "vertex"),
        PlyElement.describe(face, "face", len_types={"vertex_indices": "u2"},
                            val_types={"vertex_indices": "u4"}),
        PlyElement.describe(extra, "camera"),
    ]
    comments = ["scanner output", "units unknown"]
    PlyData(elems, text=False, byte_order=">", comments=comments,
            obj_info=["num_cols 7", "num_rows 6"]).write(str(HERE / "plyfile_be_double.ply"))
    # ASCII float with colours only, faces as list uchar int named vertex_index
    vert2 = np.zeros(n, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"),
                               ("green", "u1"), ("blue", "u1"), ("alpha", "u1")])
    for i, c in enumerate("xyz"):
        vert2[c] = v[:, i]
    vert2["red"], vert2["green"], vert2["blue"] = rgb.T
    vert2["alpha"] = 255
    face2 = np.zeros(len(f), dtype=[("vertex_index", "i4", (3,))])
    face2["vertex_index"] = f
    PlyData([PlyElement.describe(vert2, "vertex"),
             PlyElement.describe(face2, "face", len_types={"vertex_index": "u1"},
                                 val_types={"vertex_index": "i4"})],
            text=True, comments=["VCGLIB generated"]).write(str(HERE / "plyfile_ascii_rgb.ply"))
    # binary little-endian bare cloud of int16 coordinates? no: float, no faces, no normals
    vert3 = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<u2")])
    for i, c in enumerate("xyz"):
        vert3[c] = v[:, i]
    vert3["intensity"] = np.arange(n)
    PlyData([PlyElement.describe(vert3, "vertex")], text=False, byte_order="<").write(
        str(HERE / "plyfile_le_cloud.ply"))


def main() -> None:
    v, f = sphere()
    mesh = trimesh.Trimesh(v, f, process=False)
    # pyvista / VTK: ASCII and binary PLY, with normals; STL ASCII and binary
    pm = poly(v, f)
    pm.point_data["Normals"] = v
    pm.save(HERE / "vtk_ascii.ply", binary=False)
    pm.save(HERE / "vtk_binary.ply", binary=True)
    v0, f0 = sphere(0)  # STL repeats every corner: the 20-face icosahedron keeps it small
    poly(v0, f0).save(HERE / "vtk_ascii.stl", binary=False)
    poly(v0, f0).save(HERE / "vtk_binary.stl", binary=True)
    # trimesh: OBJ with normals and texture coordinates and an mtllib, OFF, PLY ASCII
    uv = np.stack([np.arctan2(v[:, 1], v[:, 0]) / (2 * np.pi) + 0.5, v[:, 2] * 0.5 + 0.5], 1)
    img = np.full((4, 4, 3), 200, np.uint8)
    from PIL import Image

    tex = trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(img))
    tm = trimesh.Trimesh(v, f, visual=tex, process=False)
    files = trimesh.exchange.obj.export_obj(tm, include_normals=True, include_texture=True,
                                            return_texture=True, mtl_name="trimesh_tex.mtl")
    text, assets = files
    (HERE / "trimesh_tex.obj").write_text(text)
    for name, blob in assets.items():
        (HERE / name).write_bytes(blob)
    mesh.export(HERE / "trimesh.off")
    mesh.export(HERE / "trimesh_ascii.ply", encoding="ascii")
    # meshio: binary PLY, OBJ, OFF, STL ascii
    mm = meshio.Mesh(v, [("triangle", f)])
    meshio.write(HERE / "meshio_binary.ply", mm, binary=True)
    meshio.write(HERE / "meshio.obj", mm)
    meshio.write(HERE / "meshio.off", mm)
    meshio.write(HERE / "meshio_ascii.stl", meshio.Mesh(v0, [("triangle", f0)]), binary=False)
    plyfile_variants(v, f)
    # by hand: an OBJ of quads and a pentagon (a cube, corners at distance sqrt(3))
    cube = ("# quads and a pentagon\nmtllib missing.mtl\no cube\n"
            + "".join(f"v {x} {y} {z}\n" for x in (-1, 1) for y in (-1, 1) for z in (-1, 1))
            + "v 1.5 0 0\n"  # a ninth vertex splitting the x=+1 face into a pentagon + triangle
            + "usemtl none\ns off\n"
            + "f 1 3 4 2\nf 1 2 6 5\nf 3 7 8 4\nf 1 5 7 3\nf 2 4 8 6\n"
            + "f 5 6 9 8 7\nf 6 8 9\n")
    (HERE / "hand_polygons.obj").write_text(cube)
    # text clouds: comma separated with a header of names; spaces with comment header
    # lines; x y z r g b (colours, not normals); x y z nx ny nz without a header
    rgb = np.clip(np.rint((v + 1) * 127.5), 0, 255)
    buf = io.StringIO()
    np.savetxt(buf, np.hstack([v, v]), delimiter=",", fmt="%.9g",
               header="X,Y,Z,Nx,Ny,Nz", comments="")
    (HERE / "header_names.csv").write_text(buf.getvalue())
    buf = io.StringIO()
    np.savetxt(buf, v, fmt="%.9g", header="exported by a scanner\n42 points", comments="// ")
    (HERE / "comments_space.txt").write_text(buf.getvalue())
    np.savetxt(HERE / "xyzrgb.xyz", np.hstack([v, rgb]), fmt="%.9g")
    np.savetxt(HERE / "xyz_normals.xyz", np.hstack([v, v]), fmt="%.9g")
    np.savetxt(HERE / "semicolon.csv", np.hstack([v, rgb[:, :1]]), delimiter=";", fmt="%.9g")
    np.save(HERE / "points.npy", v.astype(np.float32))
    np.savez(HERE / "mesh.npz", vertices=v, faces=f, normals=v)
    for p in sorted(HERE.iterdir()):
        if p.suffix != ".py":
            print(f"{p.name:<28} {p.stat().st_size:>7} bytes")


if __name__ == "__main__":
    main()
