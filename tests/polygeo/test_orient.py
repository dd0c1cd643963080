import numpy as np
import pytest
import torch
import trimesh

from polygeo import orient


def sphere_points(n, rng, center=(0, 0, 0)):
    p = rng.normal(size=(n, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    return p + np.asarray(center), p.copy()


def torus_points(n, rng, R=1.0, r=0.3):
    u, v = rng.uniform(0, 2 * np.pi, (2, n))
    p = np.stack(
        [(R + r * np.cos(v)) * np.cos(u), (R + r * np.cos(v)) * np.sin(u), r * np.sin(v)], 1
    )
    nrm = np.stack([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)], 1)
    return p, nrm


def random_signs(n, rng):
    return np.where(rng.random(n) < 0.5, -1.0, 1.0)[:, None]


def test_orient_to_reference(rng):
    n = rng.normal(size=(20, 3))
    ref = n * random_signs(20, rng)
    ref[3] = 0.0
    out = orient.orient_to_reference(n, ref)
    dots = np.einsum("ij,ij->i", out.normals, ref)
    assert (dots[np.arange(20) != 3] > 0).all()
    np.testing.assert_array_equal(out.normals[3], n[3])
    assert out.component[3] == -1 and out.sign[3] == 1


@pytest.mark.parametrize("maker", [sphere_points, torus_points])
def test_propagation_outward_on_closed_surfaces(maker, rng):
    p, nrm = maker(3000, rng)
    out = orient.propagate_orientation(p, nrm * random_signs(len(p), rng), k=10)
    assert (np.einsum("ij,ij->i", out.normals, nrm) > 0).all()
    assert (out.component == 0).all()


def test_propagation_per_component_and_nan_point(rng):
    a, na = sphere_points(800, rng)
    b, nb_ = sphere_points(800, rng, center=(5, 0, 0))
    p = np.concatenate([a, b])
    n = np.concatenate([na, nb_])
    p[10] = np.nan
    out = orient.propagate_orientation(p, n * random_signs(len(p), rng), k=8)
    ok = np.arange(len(p)) != 10
    assert (np.einsum("ij,ij->i", out.normals, n)[ok] > 0).all()
    assert out.component[10] == -1
    assert len(np.unique(out.component[ok])) == 2


def test_propagation_open_cylinder_is_consistent(rng):
    t, z = rng.uniform(0, 2 * np.pi, 2000), rng.uniform(-1, 1, 2000)
    p = np.stack([np.cos(t), np.sin(t), z], 1)
    n = np.stack([np.cos(t), np.sin(t), 0 * t], 1)
    out = orient.propagate_orientation(p, n * random_signs(2000, rng), k=10)
    d = np.einsum("ij,ij->i", out.normals, n)
    assert (d > 0).all()  # seeded on the side, where the outward normal is axis-aligned


def test_propagation_with_given_neighbors_and_torch_gradient(rng):
    p, nrm = sphere_points(500, rng)
    from polygeo.neighbors import knn

    idx = knn(p, 9).index
    nt = torch.tensor(nrm * random_signs(500, rng), requires_grad=True)
    out = orient.propagate_orientation(torch.from_numpy(p), nt, neighbors=torch.from_numpy(idx))
    assert isinstance(out.normals, torch.Tensor)
    assert (torch.einsum("ij,ij->i", out.normals.detach(), torch.from_numpy(nrm)) > 0).all()
    out.normals.sum().backward()
    np.testing.assert_allclose(nt.grad.numpy(), out.sign.numpy()[:, None].repeat(3, 1))


def test_mesh_reference_normals_half_flipped(rng):
    m = trimesh.creation.icosphere(subdivisions=3)
    v, f = np.asarray(m.vertices), np.asarray(m.faces).copy()
    fl = rng.random(len(f)) < 0.5
    f[fl] = f[fl][:, ::-1]
    nrm, valid = orient.mesh_reference_normals(v, f)
    assert valid.all()
    assert (np.einsum("ij,ij->i", nrm, v) > 0.99).all()


def test_mesh_reference_normals_nan_vertex():
    m = trimesh.creation.icosphere(subdivisions=2)
    v = np.asarray(m.vertices).copy()
    v[4] = np.nan
    nrm, valid = orient.mesh_reference_normals(v, np.asarray(m.faces))
    assert not valid[4] and valid.sum() == len(v) - 1
    assert np.isfinite(nrm).all()
    assert (np.einsum("ij,ij->i", nrm[valid], v[valid]) > 0.9).all()


@pytest.mark.parametrize(
    "call, exc",
    [
        (lambda: orient.orient_to_reference(np.zeros((3, 3)), np.zeros((4, 3))), ValueError),
        (lambda: orient.orient_to_reference(np.zeros((3, 2)), np.zeros((3, 2))), ValueError),
        (lambda: orient.propagate_orientation(np.zeros((3, 3)), np.zeros((2, 3))), ValueError),
        (lambda: orient.propagate_orientation(np.zeros((3, 3)), np.zeros((3, 3)), k=1), ValueError),
        (
            lambda: orient.propagate_orientation(
                np.zeros((3, 3)), np.zeros((3, 3)), neighbors=np.full((3, 2), 7)
            ),
            ValueError,
        ),
        (
            lambda: orient.mesh_reference_normals(np.zeros((3, 3)), np.array([[0, 1, 3]])),
            ValueError,
        ),
        (lambda: orient.mesh_reference_normals(np.zeros((3, 3)), np.zeros((1, 3))), TypeError),
    ],
)
def test_validators(call, exc):
    with pytest.raises(exc):
        call()
