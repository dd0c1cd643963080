import numpy as np
import pytest
import torch
import trimesh

from draping.body import AnnyBody
from draping.collision import MeshQuery
from draping.garments import (
    DEFAULT_VERTICES,
    GARMENTS,
    Garment,
    check_garment,
    crossing_pairs,
    fit_garment_to_shape,
    garment,
    load_garment,
    make_garment,
    read_garment_npz,
    save_garment,
    template_path,
)

# Openings of each garment: neck, hem, sleeves, arm holes, waist, legs.
OPENINGS = {
    "tshirt": 4,
    "tank": 4,
    "longsleeve": 4,
    "dress": 4,
    "skirt": 2,
    "pants": 3,
    "shorts": 3,
}


@pytest.fixture(scope="module")
def body():
    return AnnyBody.load(dtype=torch.float64)


@pytest.fixture(scope="module")
def rest_query(body):
    v, _ = body.rest(None)
    q = MeshQuery(v.reshape(-1, 3), body.faces)
    return lambda p: tuple(q.query(np.asarray(p, float))[:3])


def _openings(f):
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    key, cnt = np.unique(np.sort(e, 1), axis=0, return_counts=True)
    rim = key[cnt == 1]
    g = trimesh.graph.connected_components(rim)
    return len(g)


def _height(v):
    return float(v[:, 2].max() - v[:, 2].min())


@pytest.mark.parametrize("name", GARMENTS)
def test_shipped_templates_are_clean_and_off_the_skin(name, rest_query):
    g = read_garment_npz(template_path(name))
    assert abs(len(g.vertices) - DEFAULT_VERTICES) < 0.05 * DEFAULT_VERTICES
    assert check_garment(g.vertices, g.faces, rest_query) == []
    gap = rest_query(g.vertices)[0]
    assert gap.min() > 1e-3  # at least a millimetre off the skin everywhere
    assert _openings(g.faces) == OPENINGS[name]
    # Wound away from the body: normals point along (vertex - closest body point).
    _, closest, _ = rest_query(g.vertices)
    n = trimesh.Trimesh(g.vertices, g.faces, process=False).vertex_normals
    assert np.mean(np.einsum("ij,ij->i", n, g.vertices - closest) > 0) > 0.95


@pytest.mark.parametrize(
    "name",
    [
        "tshirt",
        pytest.param("skirt", marks=pytest.mark.slow),
        pytest.param("pants", marks=pytest.mark.slow),
    ],
)
def test_generated_templates_are_clean(name, body, rest_query):
    g = make_garment(name, body, n_vertices=2000)
    assert abs(len(g.vertices) - 2000) < 100
    assert check_garment(g.vertices, g.faces, rest_query) == []
    assert _openings(g.faces) == OPENINGS[name]


class _Scaled:
    """The shipped body in centimetres (or any factor): same rig, scaled geometry."""

    def __init__(self, body, factor):
        self.body, self.factor = body, factor
        self.faces, self.bone_names = body.faces, body.bone_names
        self.skin_weights, self.skin_indices = body.skin_weights, body.skin_indices

    def rest(self, shape=None):
        v, j = self.body.rest(shape)
        return v * self.factor, j * self.factor


@pytest.mark.slow
def test_templates_do_not_depend_on_units(body):
    m = make_garment("tshirt", body, n_vertices=1500)
    cm = make_garment("tshirt", _Scaled(body, 100.0), n_vertices=1500)
    assert _openings(m.faces) == _openings(cm.faces)
    np.testing.assert_allclose(_height(cm.vertices), 100 * _height(m.vertices), rtol=0.03)
    np.testing.assert_allclose(cm.info["clearance"], 100 * m.info["clearance"], rtol=1e-9)


def _sheet(n=6):
    x, y = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float))
    v = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], 1)
    f = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            f += [(a, a + 1, a + n + 1), (a, a + n + 1, a + n)]
    return v, np.array(f)


def test_check_garment_names_each_problem():
    v, f = _sheet()
    assert check_garment(v, f) == []
    # A fin: a third triangle on an interior edge.
    fin_v = np.vstack([v, [[0.5, 0.5, 1.0]]])
    fin_f = np.vstack([f, [[0, 7, len(v)]]])
    assert any("non-manifold edges" in p for p in check_garment(fin_v, fin_f))
    # One triangle wound the other way.
    flipped = f.copy()
    flipped[3] = flipped[3, ::-1]
    assert any("inconsistent winding" in p for p in check_garment(v, flipped))
    # A zero-area triangle.
    deg_v = v.copy()
    deg_v[7] = deg_v[0]
    assert any("degenerate" in p for p in check_garment(deg_v, f))
    # Two sheets touching at one vertex only (a bow tie).
    v2 = v + np.array([5.0, 5.0, 0.0])
    bow_v = np.vstack([v, v2[1:]])
    f2 = f + len(v) - 1
    f2[f2 == len(v) - 1] = len(v) - 1  # vertex 0 of the second sheet is the first's last
    bow_f = np.vstack([f, np.where(f == 0, len(v) - 1, f + len(v) - 1)])
    assert any("non-manifold vertices" in p for p in check_garment(bow_v, bow_f))
    # A sheet crossing another.
    cross_v = np.vstack([v, v[:, [0, 2, 1]] + np.array([0.3, 2.3, -2.5])])
    cross_f = np.vstack([f, f + len(v)])
    assert len(crossing_pairs(cross_v, cross_f)) > 0
    assert any("intersect" in p for p in check_garment(cross_v, cross_f))

    # Inside a body: a unit sphere around the sheet's centre.
    def sphere(p):
        c = np.array([2.5, 2.5, 0.0])
        r = np.linalg.norm(p - c, axis=1)
        n = (p - c) / r[:, None]
        return r - 2.0, c + 2.0 * n, n

    assert any("inside the body" in p for p in check_garment(v, f, sphere))


def test_check_garment_refuses_malformed_arrays():
    v, f = _sheet()
    with pytest.raises(ValueError, match="vertices"):
        check_garment(v[:, :2], f)
    bad = v.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="vertices"):
        check_garment(bad, f)
    with pytest.raises(ValueError, match="faces"):
        check_garment(v, f + 100)


def test_load_garment_reads_other_writers_and_names_problems(tmp_path, rest_query):
    g = read_garment_npz(template_path("tshirt"))
    path = tmp_path / "shirt.obj"
    trimesh.Trimesh(g.vertices, g.faces, process=False).export(path)
    got = load_garment(path, rest_query)
    assert got.name == "shirt"
    assert len(got.faces) == len(g.faces)
    np.testing.assert_allclose(got.vertices, g.vertices, atol=1e-6)
    # A non-manifold file: a fin hung on an edge.
    fin = np.vstack([g.faces, [[g.faces[0, 0], g.faces[0, 1], g.faces[10, 2]]]])
    bad = tmp_path / "fin.ply"
    trimesh.Trimesh(g.vertices, fin, process=False).export(bad)
    with pytest.raises(ValueError, match=r"fin\.ply.*non-manifold"):
        load_garment(bad, rest_query)
    # A garment inside the body: shrunk towards its own centre.
    c = g.vertices.mean(0)
    inner = tmp_path / "inner.obj"
    trimesh.Trimesh(c + 0.5 * (g.vertices - c), g.faces, process=False).export(inner)
    with pytest.raises(ValueError, match="inside the body"):
        load_garment(inner, rest_query)
    with pytest.raises(FileNotFoundError):
        load_garment(tmp_path / "missing.obj")


def test_save_and_read_round_trip(tmp_path):
    g = Garment("x", *_sheet(), info={"a": 1})
    p = save_garment(tmp_path / "x.npz", g)
    back = read_garment_npz(p)
    np.testing.assert_array_equal(back.vertices, g.vertices)
    np.testing.assert_array_equal(back.faces, g.faces)
    assert back.info == {"a": 1}


def test_fit_to_another_shape_stays_off_the_new_body(body):
    g = garment("tshirt")
    tall = body.shape_from(height=1.0, weight=0.9)
    fitted = fit_garment_to_shape(g, body, tall)
    v, _ = body.rest(tall)
    q = MeshQuery(v.reshape(-1, 3), body.faces)
    assert q.query(fitted.vertices).distance.min() > 0
    assert check_garment(fitted.vertices, fitted.faces) == []
    # It moved with the body: its top follows the new neck.
    _, j0 = body.rest(None)
    _, j1 = body.rest(tall)
    neck = body.bone_names.index("neck01")
    dz = float(j1.reshape(-1, 3)[neck, 2] - j0.reshape(-1, 3)[neck, 2])
    assert abs((fitted.vertices[:, 2].max() - g.vertices[:, 2].max()) - dz) < 0.3 * abs(dz) + 5e-3


def test_bad_names_and_counts():
    with pytest.raises(ValueError, match="name"):
        garment("poncho")
    with pytest.raises(ValueError, match="n_vertices"):
        make_garment("tshirt", n_vertices=10)


def _hinge_and_corner_angles(v, f):
    """Independent of the library: largest dihedral angle between faces sharing an edge and
    smallest corner angle (degrees), by brute force over the edge-to-face map."""
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    owners = {}
    for i, t in enumerate(f):
        for a, b in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0])):
            owners.setdefault((min(a, b), max(a, b)), []).append(i)
    pairs = np.array([o for o in owners.values() if len(o) == 2])
    hinge = np.degrees(np.arccos(np.clip((n[pairs[:, 0]] * n[pairs[:, 1]]).sum(1), -1, 1)))
    corners = []
    for c in range(3):
        a = v[f[:, (c + 1) % 3]] - v[f[:, c]]
        b = v[f[:, (c + 2) % 3]] - v[f[:, c]]
        cos = (a * b).sum(1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
        corners.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    return hinge.max(), np.min(corners)


@pytest.mark.parametrize("name", ["pants", "shorts"])
def test_shipped_legged_templates_have_no_folds_or_slivers(name):
    """The pants' leg hems had a 163 degree hinge and a 0.6 degree sliver (fixed by
    ``garment_fit.smooth_defects``)."""
    g = read_garment_npz(template_path(name))
    hinge, corner = _hinge_and_corner_angles(g.vertices, g.faces)
    assert hinge <= 60.0
    assert corner >= 10.0


def test_tshirt_and_dress_templates_are_pinned():
    """GAPS's shipped models are tied to these two templates: their content must not change
    (regenerating them needs new models)."""
    import hashlib

    want = {
        "tshirt": "114421d2b2565cb8e93f524c84fad9a76171d195d6c34099d9d601e9ea7cdf93",
        "dress": "4d7060ff4ef0f83c66f5933a8b199e6fb1dfce9c22a7e6ac41366d16523a45ea",
    }
    for name, digest in want.items():
        g = read_garment_npz(template_path(name))
        data = (np.ascontiguousarray(g.vertices, np.float64).tobytes()
                + np.ascontiguousarray(g.faces, np.int64).tobytes())
        assert hashlib.sha256(data).hexdigest() == digest, name


def test_smooth_defects_removes_a_spike_and_leaves_the_rest():
    from draping.garment_fit import defect_faces, smooth_defects

    n = 15
    u, w = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    v = np.stack([u.ravel(), w.ravel(), np.full(n * n, 0.1)], 1)
    a = np.array([i * n + j for i in range(n - 1) for j in range(n - 1)])
    f = np.concatenate([np.stack([a, a + n, a + 1], 1), np.stack([a + 1, a + n, a + n + 1], 1)])
    assert not defect_faces(v, f).any()  # a flat even grid
    spiked = v.copy()
    spiked[7 * n + 7, 2] += 0.3  # a spike: hinges of about 80 degrees around it
    bad = defect_faces(spiked, f)
    assert bad.any() and set(np.unique(f[bad])) <= set(range(5 * n, 10 * n))

    def plane(points):  # the body: the half-space z < 0
        p = np.asarray(points, dtype=np.float64)
        closest = p * np.array([1.0, 1.0, 0.0])
        return p[:, 2], closest, np.tile([0.0, 0.0, 1.0], (len(p), 1))

    out = smooth_defects(spiked, f, plane, np.full(n * n, 0.05))
    assert not defect_faces(out, f).any()
    far = np.linalg.norm(v[:, :2] - v[7 * n + 7, :2], axis=1) > 0.45
    assert np.array_equal(out[far], spiked[far])  # local: the rest does not move
    assert out[:, 2].min() >= 0.05 - 1e-12  # nothing pushed closer than the room
    # a sliver is flagged too
    sliver = np.array([[0.0, 0, 0], [1, 0, 0], [0.5, 0.05, 0]])
    assert defect_faces(sliver, np.array([[0, 1, 2]])).all()
