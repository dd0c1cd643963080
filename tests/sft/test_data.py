"""sft.data: the sequence format, its validation and a round trip."""

import json
import shutil

import cv2
import numpy as np
import pytest

from sft.data import (
    SequenceWriter,
    Template,
    load_camera,
    load_sequence,
    load_template,
    write_sequence,
)

H, W = 24, 32
K = np.array([[30.0, 0.0, 16.0], [0.0, 30.0, 12.0], [0.0, 0.0, 1.0]])


def _template(textured=True):
    a, b = np.meshgrid(np.linspace(-0.05, 0.05, 4), np.linspace(-0.04, 0.04, 3))
    verts = np.stack([a.ravel(), b.ravel(), np.full(a.size, 0.3)], 1)
    faces = []
    for j in range(2):
        for i in range(3):
            v = j * 4 + i
            faces += [[v, v + 1, v + 4], [v + 1, v + 5, v + 4]]
    faces = np.array(faces)
    if textured:
        uvs = np.stack([(a.ravel() + 0.05) / 0.1, (b.ravel() + 0.04) / 0.08], 1)
        tex = np.random.default_rng(1).random((8, 8, 3)).astype(np.float32)
        return Template(verts=verts, faces=faces, uvs=uvs, texture=tex)
    cols = np.random.default_rng(2).random((len(verts), 3)).astype(np.float32)
    return Template(verts=verts, faces=faces, colors=cols)


@pytest.fixture
def seq_dir(tmp_path, rng):
    t = _template()
    frames = [rng.random((H, W, 3)) for _ in range(3)]
    masks = [rng.random((H, W)) > 0.5 for _ in range(3)]
    gt = [t.verts + 0.001 * k for k in range(3)]
    return write_sequence(tmp_path / "seq", t, K, W, H, frames, masks, gt), t, frames, masks, gt


def test_round_trip(seq_dir):
    path, t, frames, masks, gt = seq_dir
    s = load_sequence(path)
    assert s.n_frames == 3 and s.has_masks and s.has_gt
    np.testing.assert_allclose(s.template.verts, t.verts, rtol=1e-8)
    np.testing.assert_array_equal(s.template.faces, t.faces)
    np.testing.assert_allclose(s.template.uvs, t.uvs, atol=1e-8)
    np.testing.assert_allclose(s.template.texture, t.texture, atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(s.K, K)
    assert (s.width, s.height) == (W, H)
    for i in range(3):
        np.testing.assert_allclose(s.frame(i), frames[i], atol=0.5 / 255 + 1e-6)
        np.testing.assert_array_equal(s.mask(i), masks[i].astype(np.float32))
        np.testing.assert_allclose(s.gt(i), gt[i], rtol=1e-6)  # float32 PLY


def test_round_trip_vertex_colours_no_masks(tmp_path, rng):
    t = _template(textured=False)
    frames = [rng.random((H, W, 3)) for _ in range(2)]
    p = write_sequence(tmp_path / "s", t, K, W, H, frames)
    s = load_sequence(p)
    assert not s.has_masks and not s.has_gt and s.mask(0) is None and s.gt(1) is None
    assert s.template.texture is None
    np.testing.assert_allclose(s.template.colors, t.colors, atol=1e-5)


def test_ply_template_with_colours(tmp_path):
    from polygeo.io import write_ply

    t = _template(textured=False)
    d = tmp_path / "s"
    write_sequence(d, t, K, W, H, [np.zeros((H, W, 3))])
    (d / "template.obj").unlink()
    cols = (255 * t.colors).astype(np.uint8)
    write_ply(d / "template.ply", t.verts, t.faces,
              {"red": cols[:, 0], "green": cols[:, 1], "blue": cols[:, 2]})
    s = load_sequence(d)
    np.testing.assert_allclose(s.template.colors, cols / 255.0, atol=1e-6)


def test_frames_in_other_png_layouts(seq_dir):
    """Grey, RGBA and 16-bit frames read as RGB in [0, 1]; an RGBA mask uses the colour
    channels, not the alpha (OpenCV reads grey + alpha PNGs as RGBA)."""
    path = seq_dir[0]
    rng = np.random.default_rng(3)
    g8 = rng.integers(0, 256, (H, W), dtype=np.uint8)
    alpha = np.full((H, W), 255, np.uint8)
    bgr8 = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    rgb16 = rng.integers(0, 65536, (H, W, 3), dtype=np.uint16)
    cases = [
        (g8, np.repeat(g8[..., None], 3, 2) / 255.0),
        (np.dstack([bgr8, alpha]), bgr8[..., ::-1] / 255.0),
        (rgb16[..., ::-1], rgb16 / 65535.0),
    ]
    for img, want in cases:
        cv2.imwrite(str(path / "frames" / "000001.png"), np.ascontiguousarray(img))
        np.testing.assert_allclose(load_sequence(path).frame(1), want, atol=1e-6)
    m = np.zeros((H, W), np.uint8)
    m[5:10, 4:20] = 255
    cv2.imwrite(str(path / "masks" / "000001.png"), np.dstack([m, m, m, alpha]))
    np.testing.assert_array_equal(load_sequence(path).mask(1), (m > 0).astype(np.float32))


def test_other_file_names_jpeg_frames_flat_K(seq_dir):
    """Any zero-padding, JPEG frames, hidden files and a flat K load as the same sequence."""
    path, t, frames, masks, gt = seq_dir
    yy, xx = np.mgrid[0:H, 0:W]
    smooth = np.stack([xx / W, yy / H, 0.5 + 0 * xx], -1)  # JPEG keeps a smooth image
    cv2.imwrite(str(path / "frames" / "000002.png"), (255 * smooth[..., ::-1]).astype(np.uint8))
    ref = load_sequence(path)
    ref_frames = [ref.frame(i) for i in range(3)]
    ref_masks = [ref.mask(i) for i in range(3)]
    jpg = path / "frames" / "2.jpg"
    cv2.imwrite(str(jpg), cv2.imread(str(path / "frames" / "000002.png")),
                [cv2.IMWRITE_JPEG_QUALITY, 100])
    (path / "frames" / "000002.png").unlink()
    for sub in ("frames", "masks", "gt"):
        for f in sorted((path / sub).iterdir()):
            f.rename(f.with_name(f"{int(f.stem)}{f.suffix}"))
    (path / "frames" / ".DS_Store").write_bytes(b"\0")
    cam = json.loads((path / "camera.json").read_text())
    cam["K"] = sum(cam["K"], [])
    (path / "camera.json").write_text(json.dumps(cam))
    s = load_sequence(path)
    assert [f.name for f in s.frame_paths] == ["0.png", "1.png", "2.jpg"]
    np.testing.assert_array_equal(s.K, ref.K)
    for i in range(3):
        np.testing.assert_array_equal(s.mask(i), ref_masks[i])
    for i in range(2):
        np.testing.assert_array_equal(s.frame(i), ref_frames[i])
    # JPEG is lossy: close to the PNG frame, not equal
    assert 0 < np.abs(s.frame(2) - ref_frames[2]).mean() < 0.02
    # the same index twice is refused, naming both files
    shutil.copy(path / "frames" / "1.png", path / "frames" / "0001.png")
    with pytest.raises(ValueError, match=r"frame 1 is given twice \(0001.png and 1.png\)"):
        load_sequence(path)


def test_camera_extra_keys_warn(seq_dir):
    path = seq_dir[0]
    cam = json.loads((path / "camera.json").read_text())
    cam["dist"] = [0.1, 0.0, 0.0, 0.0, 0.0]
    (path / "camera.json").write_text(json.dumps(cam))
    with pytest.warns(RuntimeWarning, match=r"key\(s\) \['dist'\] ignored"):
        load_sequence(path)


def test_writer_refuses_non_empty_folder(seq_dir):
    path, t, *_ = seq_dir
    with pytest.raises(FileExistsError, match="not empty"):
        SequenceWriter(path, t, K, W, H)


def test_writer_bad_sizes_and_partial_masks(tmp_path):
    t = _template()
    w = SequenceWriter(tmp_path / "s", t, K, W, H)
    with pytest.raises(ValueError, match="rgb: expected shape"):
        w.add_frame(np.zeros((H + 1, W, 3)))
    w.add_frame(np.zeros((H, W, 3)), mask=np.ones((H, W)))
    with pytest.raises(ValueError, match="some frames only"):
        w.add_frame(np.zeros((H, W, 3)))
    w.abort()
    assert not (tmp_path / "s").exists()


# ---------------------------------------------------------------- validation failures


def _break(path, what):
    if what == "missing_frame":
        (path / "frames" / "000001.png").unlink()
    elif what == "extra_file":
        (path / "frames" / "notes.txt").write_text("x")
    elif what == "size":
        cv2.imwrite(str(path / "frames" / "000002.png"), np.zeros((H, W + 2, 3), np.uint8))
    elif what == "mask_size":
        cv2.imwrite(str(path / "masks" / "000000.png"), np.zeros((H + 1, W), np.uint8))
    elif what == "mask_count":
        (path / "masks" / "000002.png").unlink()
    elif what == "gt_count":
        (path / "gt" / "000001.ply").unlink()
    elif what == "gt_vertices":
        from polygeo.io import write_ply

        write_ply(path / "gt" / "000001.ply", np.zeros((5, 3)))
    elif what == "singular_K":
        cam = json.loads((path / "camera.json").read_text())
        cam["K"][0][0] = 0.0
        (path / "camera.json").write_text(json.dumps(cam))
    elif what == "bad_K_row":
        cam = json.loads((path / "camera.json").read_text())
        cam["K"][2] = [0.0, 1.0, 1.0]
        (path / "camera.json").write_text(json.dumps(cam))
    elif what == "camera_key":
        cam = json.loads((path / "camera.json").read_text())
        del cam["width"]
        (path / "camera.json").write_text(json.dumps(cam))
    elif what == "camera_json":
        (path / "camera.json").write_text("{not json")
    elif what == "empty_template":
        (path / "template.obj").write_text("mtllib template.mtl\n")
    elif what == "face_range":
        with open(path / "template.obj", "a") as fh:
            fh.write("f 1/1 2/2 99/3\n")
    elif what == "texture_missing":
        (path / "texture.png").unlink()
    elif what == "both_templates":
        shutil.copy(path / "template.obj", path / "template.ply")
    elif what == "gt_nan":
        from polygeo.io import write_ply

        write_ply(path / "gt" / "000002.ply", np.full((12, 3), np.nan))
    elif what in ("behind", "off_image"):
        lines = (path / "template.obj").read_text().splitlines()
        shift = np.array([0.0, 0.0, -0.5]) if what == "behind" else np.array([1.0, 0.0, 0.0])
        out = []
        for ln in lines:
            if ln.startswith("v "):
                p = np.array([float(x) for x in ln.split()[1:4]]) + shift
                ln = "v " + " ".join(repr(float(x)) for x in p)
            out.append(ln)
        (path / "template.obj").write_text("\n".join(out) + "\n")
    elif what == "jpeg_mask":
        m = path / "masks" / "000001.png"
        cv2.imwrite(str(m.with_suffix(".jpg")), cv2.imread(str(m)))
        m.unlink()
    elif what == "obj_syntax":
        with open(path / "template.obj", "a") as fh:
            fh.write("v 1.0 abc 2.0\n")
    return path


@pytest.mark.parametrize(
    "what, exc, match",
    [
        ("missing_frame", ValueError, r"frames: missing frame \[1\]"),
        ("extra_file", ValueError, r"frames: unexpected frame file\(s\) \['notes.txt'\]"),
        ("size", ValueError, r"000002.png: image size 34x24 differs from camera.json 32x24"),
        ("mask_size", ValueError, r"masks/000000.png: mask size 32x25 differs"),
        ("mask_count", ValueError, r"masks: 2 masks for 3 frames"),
        ("gt_count", ValueError, r"gt: missing ground-truth \[1\]"),
        ("gt_vertices", ValueError, r"gt/000001.ply: 5 vertices, the template has 12"),
        ("singular_K", ValueError, r"camera.json: K is not invertible"),
        ("bad_K_row", ValueError, r"camera.json: expected K = "),
        ("camera_key", ValueError, r"camera.json: missing key\(s\) \['width'\]"),
        ("camera_json", ValueError, r"camera.json: not valid JSON"),
        ("empty_template", ValueError, r"template.obj: expected a non-empty \(V, 3\)"),
        ("face_range", ValueError, r"template.obj: face indices must lie in"),
        ("texture_missing", ValueError, r"template.mtl: texture 'texture.png' \(map_Kd\)"),
        ("both_templates", ValueError, r"both template.obj and template.ply"),
        ("obj_syntax", ValueError, r"template.obj:\d+: cannot parse"),
        ("gt_nan", ValueError, r"gt/000002.ply: 36 non-finite vertex coordinates"),
        ("behind", ValueError, r"template.obj: 12 of 12 vertices lie at or behind the camera"),
        ("off_image", ValueError, r"template.obj: no vertex projects into the 32x24 image"),
        ("jpeg_mask", ValueError, r"masks: unexpected mask file\(s\) \['000001.jpg'\]"),
    ],
)
def test_validation_errors_name_the_file(seq_dir, what, exc, match):
    path = _break(seq_dir[0], what)
    with pytest.raises(exc, match=match):
        load_sequence(path)


def test_missing_pieces(tmp_path, seq_dir):
    with pytest.raises(FileNotFoundError, match="sequence folder does not exist"):
        load_sequence(tmp_path / "nope")
    path = seq_dir[0]
    (path / "camera.json").unlink()
    with pytest.raises(FileNotFoundError, match="camera.json: camera file does not exist"):
        load_sequence(path)
    shutil.rmtree(path / "frames")
    with pytest.raises(FileNotFoundError):
        load_sequence(path)
    with pytest.raises(FileNotFoundError, match="template"):
        load_template(tmp_path / "none.obj")
    with pytest.raises(FileNotFoundError, match="camera"):
        load_camera(tmp_path / "none.json")


def seam_template():
    """The sheet of ``_template`` with its texture atlas cut at the second column of
    vertices: the first column of quads maps to the right end of the image, the rest to
    the left (a UV seam: those 3 vertices have two uvs each). Also returns the same
    template with its seam vertices duplicated (per-vertex uvs) and the vertex map."""
    t = _template()
    col = np.arange(12) % 4
    corner_col = col[t.faces]  # (F, 3)
    left = corner_col.max(1) <= 1  # faces of the first column of quads
    u = np.where(left[:, None], 0.8 + 0.2 * corner_col, 0.25 * (corner_col - 1))
    v = (t.verts[t.faces][..., 1] + 0.04) / 0.08
    uvs = np.stack([u, v], -1)  # (F, 3, 2)
    seam = Template(verts=t.verts, faces=t.faces, uvs=uvs, texture=t.texture)
    # duplicate the seam vertices (column 1) for the faces on the left of the seam
    dup = {j: 12 + k for k, j in enumerate(np.flatnonzero(col == 1))}
    faces = np.array([[dup[c] if (lf and c in dup) else c for c in f]
                      for f, lf in zip(t.faces, left)])
    vmap = np.concatenate([np.arange(12), np.flatnonzero(col == 1)])
    per_vertex = np.zeros((len(vmap), 2))
    per_vertex[faces.reshape(-1)] = uvs.reshape(-1, 2)
    dupl = Template(verts=t.verts[vmap], faces=faces, uvs=per_vertex, texture=t.texture)
    return seam, dupl, vmap


def test_uv_seams_load_as_face_corner_uvs(tmp_path, seq_dir):
    seam, _, _ = seam_template()
    assert seam.faces[0, 1] == seam.faces[2, 0] == 1  # vertex 1 is on the seam:
    assert not np.allclose(seam.uvs[0, 1], seam.uvs[2, 0])  # two uvs
    path = write_sequence(tmp_path / "seam", seam, K, W, H, [np.zeros((H, W, 3))])
    s = load_sequence(path)
    assert s.template.n_verts == 12 and s.template.uvs.shape == (12, 3, 2)
    np.testing.assert_allclose(s.template.uvs, seam.uvs, atol=1e-8)
    np.testing.assert_array_equal(s.template.faces, seam.faces)
    # a hand-edited file: vertex 1 gets a second texture coordinate in one more face
    path = seq_dir[0]
    text = (path / "template.obj").read_text().splitlines()
    text.append("vt 0.9 0.9")
    n_vt = sum(1 for ln in text if ln.startswith("vt "))
    text.append(f"f 1/{n_vt} 2/2 5/5")
    (path / "template.obj").write_text("\n".join(text) + "\n")
    t = load_sequence(path).template
    assert t.uvs.shape == (13, 3, 2)
    np.testing.assert_allclose(t.uvs[-1], [[0.9, 0.9], seq_dir[1].uvs[1], seq_dir[1].uvs[4]])
    np.testing.assert_allclose(t.uvs[:12], seq_dir[1].uvs[seq_dir[1].faces])
    with pytest.raises(ValueError, match="per face corner \\(F, 3, 2\\) = \\(12, 3, 2\\)"):
        SequenceWriter(tmp_path / "bad", Template(verts=seam.verts, faces=seam.faces,
                                                  uvs=seam.uvs[:5], texture=seam.texture),
                       K, W, H)


def test_template_without_appearance(tmp_path):
    t = _template()
    bad = Template(verts=t.verts, faces=t.faces)
    with pytest.raises(ValueError, match="neither a texture nor vertex colours"):
        SequenceWriter(tmp_path / "s", bad, K, W, H)
