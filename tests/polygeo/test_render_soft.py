import math

import cv2
import numpy as np
import pytest
import torch
import trimesh

from polygeo.render import (
    Camera,
    RasterSettings,
    checkerboard,
    iou,
    project_faces,
    rasterize_faces,
    render,
    render_reference,
    render_silhouette,
    sample_texture,
)
from polygeo.render.reference import nearest_face_dense, soft_rasterize_dense


def sheet(n, wave=0.15):
    u, v = np.meshgrid(np.linspace(-1, 1, n), np.linspace(-1, 1, n))
    verts = np.stack([u, v, wave * np.sin(3 * u) * np.cos(2 * v)], -1).reshape(-1, 3)
    idx = np.arange(n * n).reshape(n, n)
    a = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[:-1, 1:]], -1).reshape(-1, 3)
    b = np.stack([idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 3)
    uvs = np.stack([(u + 1) / 2, (v + 1) / 2], -1).reshape(-1, 2)
    return verts, np.concatenate([a, b]), uvs


def random_face_verts(rng, B, F, H, W, spread=1.2):
    """Screen-space triangles, some partly outside the image."""
    fv = np.zeros((B, F, 3, 3))
    centres = rng.uniform(-0.1, 1.1, (B, F, 1, 2)) * [W, H]
    fv[..., :2] = centres + rng.normal(0, spread * min(H, W) / 4, (B, F, 3, 2))
    fv[..., 2] = rng.uniform(1.0, 3.0, (B, F, 3))
    return torch.from_numpy(fv)


def _rand_grads(rng, *shapes):
    return [torch.from_numpy(rng.uniform(-1, 1, s)) for s in shapes]


# ------------------------------------------------------------------ kernels == dense oracle


@pytest.mark.parametrize("mode", ["silhouette", "vertex", "texture"])
@pytest.mark.parametrize("threshold", [1e-4, 0.0])
def test_kernels_match_dense_reference(rng, mode, threshold):
    B, F, H, W, C = 2, 7, 19, 23, 3
    fv = random_face_verts(rng, B, F, H, W)
    fv[0, 0, 0, 2] = 0.001  # crosses the near plane: culled
    fv[1, 1, 2, :2] = fv[1, 1, 0, :2]  # zero area: skipped
    s = RasterSettings(sigma=1.5, gamma=0.03, blur_threshold=threshold, tile_size=4,
                       background=(0.2, 0.4, 0.6))  # fmt: skip
    kw = {}
    if mode == "vertex":
        kw = dict(face_colors=torch.from_numpy(rng.uniform(0, 1, (B, F, 3, C))))
    elif mode == "texture":
        kw = dict(
            face_uvs=torch.from_numpy(rng.uniform(-0.1, 1.1, (1, F, 3, 2))),
            texture=torch.from_numpy(rng.uniform(0, 1, (5, 6, C))),
        )
    inputs = [fv, *kw.values()]
    for x in inputs:
        x.requires_grad_(True)
    a1, r1 = rasterize_faces(fv, H, W, s, **kw)
    a2, r2 = soft_rasterize_dense(fv, H, W, s, **kw)
    torch.testing.assert_close(a1, a2, rtol=0, atol=1e-12)
    assert float(a1.detach().max()) > 0.5  # the scene is not empty
    ga, gr = _rand_grads(rng, (B, H, W), (B, H, W, C))
    loss1 = (a1 * ga).sum()
    loss2 = (a2 * ga).sum()
    if mode != "silhouette":
        torch.testing.assert_close(r1, r2, rtol=0, atol=1e-12)
        loss1 = loss1 + (r1 * gr).sum()
        loss2 = loss2 + (r2 * gr).sum()
    else:
        assert r1 is None and r2 is None
    g1 = torch.autograd.grad(loss1, inputs)
    g2 = torch.autograd.grad(loss2, inputs)
    for x, y in zip(g1, g2):
        assert float(y.abs().max()) > 0
        torch.testing.assert_close(x, y, rtol=1e-9, atol=1e-9)
    # culled and degenerate faces get no gradient
    assert float(g1[0][0, 0].abs().max()) == 0.0
    assert float(g1[0][1, 1].abs().max()) == 0.0


def test_render_matches_reference_full_pipeline(rng):
    verts, faces, uvs = sheet(6)
    cam = Camera.look_at([0.4, -0.3, -3.0], [0, 0, 0], focal=20.0, width=24, height=20)
    s = RasterSettings(sigma=0.8, gamma=0.01, background=(1.0, 1.0, 1.0))
    tex = torch.from_numpy(checkerboard(16, 4, smooth=True))
    v = torch.from_numpy(verts).requires_grad_(True)
    t = tex.clone().requires_grad_(True)
    out = render(v, faces, cam, s, uvs=uvs, texture=t, return_depth=True, return_face_index=True)
    ref = render_reference(v, faces, cam, s, uvs=uvs, texture=t, return_depth=True,
                           return_face_index=True)  # fmt: skip
    for x, y in zip(out, ref):
        torch.testing.assert_close(x, y, rtol=0, atol=1e-12)
    g = _rand_grads(rng, (20, 24), (20, 24, 3), (20, 24))
    l1 = (out.alpha * g[0]).sum() + (out.rgb * g[1]).sum() + (out.depth * g[2]).sum()
    l2 = (ref.alpha * g[0]).sum() + (ref.rgb * g[1]).sum() + (ref.depth * g[2]).sum()
    for x, y in zip(torch.autograd.grad(l1, (v, t)), torch.autograd.grad(l2, (v, t))):
        torch.testing.assert_close(x, y, rtol=1e-9, atol=1e-10)


def test_nearest_face_kernel_matches_dense(rng):
    fv = random_face_verts(rng, 2, 12, 21, 17)
    out = render  # noqa: F841 - keep the public import used
    from polygeo.render.soft import _nearest

    idx = _nearest(fv, RasterSettings(), 21, 17, 0.0)
    ref = nearest_face_dense(fv, 21, 17)
    assert torch.equal(idx, ref)
    assert (idx >= 0).any() and (idx < 0).any()


# ------------------------------------------------------------------ gradcheck (float64)


def _tiny_scene():
    verts = torch.tensor(
        [[-0.6, -0.5, 3.0], [0.7, -0.4, 3.3], [-0.1, 0.6, 2.8], [0.8, 0.7, 3.6], [-0.9, 0.3, 3.9]],
        dtype=torch.float64,
    )
    faces = torch.tensor([[0, 1, 2], [1, 3, 2], [0, 2, 4]])
    cam = Camera.look_at([0.05, 0.02, 0.0], [0.05, 0.02, 3.0], focal=9.0, width=12, height=10)
    return verts, faces, cam


def test_gradcheck_silhouette():
    verts, faces, cam = _tiny_scene()
    s = RasterSettings(sigma=1.0, blur_threshold=0.0)
    v = verts.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: render_silhouette(x, faces, cam, s), (v,),
                                    eps=1e-6, atol=1e-6)  # fmt: skip


def test_gradcheck_rgb_vertex_colours():
    verts, faces, cam = _tiny_scene()
    s = RasterSettings(sigma=1.0, gamma=0.02, blur_threshold=0.0, zfar=10.0)
    cols = torch.linspace(0, 1, 15, dtype=torch.float64).reshape(5, 3).requires_grad_(True)
    v = verts.clone().requires_grad_(True)

    def f(x, c):
        out = render(x, faces, cam, s, colors=c)
        return out.alpha, out.rgb

    assert torch.autograd.gradcheck(f, (v, cols), eps=1e-6, atol=1e-6)


def test_gradcheck_rgb_texture():
    verts, faces, cam = _tiny_scene()
    s = RasterSettings(sigma=1.0, gamma=0.02, blur_threshold=0.0, zfar=10.0, background=(0.3,))
    uvs = torch.tensor(
        [[0.17, 0.21], [0.83, 0.16], [0.45, 0.8], [0.77, 0.71], [0.22, 0.6]], dtype=torch.float64
    ).requires_grad_(True)
    tex = torch.from_numpy(np.random.default_rng(3).uniform(0, 1, (4, 5, 2))).requires_grad_(True)
    v = verts.clone().requires_grad_(True)

    def f(x, u, t):
        out = render(x, faces, cam, s, uvs=u, texture=t)
        return out.alpha, out.rgb

    assert torch.autograd.gradcheck(f, (v, uvs, tex), eps=1e-6, atol=1e-6)


def test_gradcheck_hard_mode_interpolation():
    verts, faces, cam = _tiny_scene()
    s = RasterSettings(hard=True)
    cols = torch.linspace(0, 1, 15, dtype=torch.float64).reshape(5, 3)
    v = verts.clone().requires_grad_(True)
    out = render(v, faces, cam, s, colors=cols, return_depth=True)
    assert out.alpha.sum() > 10
    assert torch.autograd.gradcheck(
        lambda x: render(x, faces, cam, s, colors=cols, return_depth=True)[::2], (v,)
    )


# ------------------------------------------------------------------ independent hard rasterizer


def _cv2_silhouette(uv, faces, H, W, ss=15):
    """OpenCV fillPoly per projected triangle on a ss x supersampled grid, read at pixel centres."""
    img = np.zeros((H * ss, W * ss), np.uint8)
    for f in faces:
        pts = np.round((uv[f] * ss - 0.5) * 16).astype(np.int32)
        cv2.fillPoly(img, [pts], 1, lineType=cv2.LINE_8, shift=4)
    return img[ss // 2 :: ss, ss // 2 :: ss].astype(np.float64)


def test_small_sigma_matches_opencv_fillpoly(rng):
    base = trimesh.creation.icosphere(subdivisions=2)
    H, W = 72, 96
    ious, ious_hard = [], []
    for _ in range(6):
        verts = base.vertices * rng.uniform(0.5, 1.6, 3) + rng.normal(0, 0.04, base.vertices.shape)
        f = rng.uniform(50, 140)
        K = np.array([[f, rng.uniform(-2, 2), rng.uniform(25, 70)],
                      [0, f * rng.uniform(0.8, 1.2), rng.uniform(20, 50)], [0, 0, 1]])  # fmt: skip
        R = cv2.Rodrigues(rng.normal(size=3))[0]
        t = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(3.0, 5.0)])
        cam = Camera(K=K, R=R, t=t, width=W, height=H)
        uv, depth = cam.project(verts)
        assert (depth > 0).all()
        ref = _cv2_silhouette(uv, base.faces, H, W)
        soft = render_silhouette(verts, base.faces, cam, RasterSettings(sigma=1e-4))
        hard = render_silhouette(verts, base.faces, cam, RasterSettings(hard=True))
        ious.append(float(iou(soft, ref)))
        ious_hard.append(float(iou(hard, ref)))
    assert min(ious) >= 0.99, ious
    assert min(ious_hard) >= 0.99, ious_hard


def test_triangles_partly_outside_image():
    # one big triangle mostly outside: coverage equals the analytic clipped area
    cam = Camera(K=np.diag([1.0, 1.0, 1.0]), width=40, height=30)
    verts = np.array([[-20.0, -10.0, 1.0], [60.3, -10.0, 1.0], [-20.0, 70.3, 1.0]])
    a = render_silhouette(verts, [[0, 1, 2]], cam, RasterSettings(sigma=1e-4))
    jj, ii = np.meshgrid(np.arange(40) + 0.5, np.arange(30) + 0.5)
    inside = (jj + 20.0) / 80.3 + (ii + 10.0) / 80.3 <= 1.0
    assert float(iou(a, inside.astype(float))) >= 0.99


# ------------------------------------------------------------------ textured quad, analytic


def test_textured_planar_quad_analytic_positions():
    # a tilted planar quad: each pixel's texture coordinate must be the one of the point
    # where its ray meets the plane (perspective-correct), to a small fraction of a pixel.
    H, W, n = 64, 64, 64
    tex = np.zeros((n, n, 3))
    tex[..., 0] = ((np.arange(n) + 0.5) / n)[None, :]  # texel value = its own (u, v)
    tex[..., 1] = ((np.arange(n) + 0.5) / n)[:, None]
    tex[..., 2] = 1.0
    a = math.radians(55.0)
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float)
    verts = np.stack(
        [corners[:, 0], corners[:, 1] * math.cos(a), 3.0 + corners[:, 1] * math.sin(a)], -1
    )
    uvs = (corners + 1) / 2
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    cam = Camera(K=[[60.0, 0, 32.0], [0, 60.0, 32.0], [0, 0, 1]], width=W, height=H)
    # analytic: ray through pixel centre meets the plane through the quad
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    d = np.stack([(jj - 32.0) / 60.0, (ii - 32.0) / 60.0, np.ones_like(jj)], -1)
    normal = np.array([0.0, -math.sin(a), math.cos(a)])
    lam = (verts[0] @ normal) / (d @ normal)
    P = d * lam[..., None]
    u_true = (P[..., 0] + 1) / 2
    v_true = (P[..., 1] / math.cos(a) + 1) / 2
    lo, hi = 0.5 / n + 0.02, 1 - 0.5 / n - 0.02  # away from the texture's clamped border
    interior = (u_true > lo) & (u_true < hi) & (v_true > lo) & (v_true < hi)
    assert interior.sum() > 600
    # pixels per unit of u and v there (to express the error in pixels)
    du = np.hypot(*np.gradient(u_true)) + 1e-12
    dv = np.hypot(*np.gradient(v_true)) + 1e-12
    for s in (RasterSettings(hard=True), RasterSettings(sigma=1e-4, gamma=1e-4)):
        out = render(verts, faces, cam, s, uvs=uvs, texture=tex)
        err = np.maximum(
            np.abs(out.rgb[..., 0] - u_true) / du, np.abs(out.rgb[..., 1] - v_true) / dv
        )
        assert err[interior].max() < 0.02  # pixels
    # screen-linear (not perspective-correct) interpolation would be off by pixels here
    uv_proj, _ = cam.project(verts)
    from matplotlib.tri import LinearTriInterpolator, Triangulation

    tri = Triangulation(uv_proj[:, 0], uv_proj[:, 1], faces)
    u_aff = LinearTriInterpolator(tri, uvs[:, 0])(jj, ii)
    assert (np.abs(u_aff - u_true) / du)[interior].max() > 1.0


def test_depth_of_plane_is_analytic():
    cam = Camera(K=[[30.0, 0, 16.0], [0, 30.0, 12.0], [0, 0, 1]], width=32, height=24)
    verts = np.array([[-5.0, -5.0, 2.0], [5.0, -5.0, 2.0], [0.0, 5.0, 2.0]])
    out = render(verts, [[0, 1, 2]], cam, RasterSettings(hard=True), colors=np.ones((3, 3)),
                 return_depth=True, return_face_index=True)  # fmt: skip
    inside = out.face_index >= 0
    assert inside.sum() > 100
    np.testing.assert_allclose(out.depth[inside], 2.0, rtol=1e-12)
    assert (out.depth[~inside] == 0).all()


# ------------------------------------------------------------------ batching, types, culling


def test_batched_equals_per_item(rng):
    verts, faces, uvs = sheet(7)
    vb = np.stack([verts + rng.normal(0, 0.05, verts.shape) for _ in range(3)])
    cams = Camera(
        K=np.stack([np.array([[30.0 + 5 * b, 0, 16], [0, 30.0, 14], [0, 0, 1]]) for b in range(3)]),
        R=np.stack([cv2.Rodrigues(rng.normal(0, 0.2, 3))[0] for _ in range(3)]),
        t=np.stack([[0.0, 0.0, 3.5 + 0.3 * b] for b in range(3)]),
        width=32,
        height=28,
    )
    tex = checkerboard(32, 4)
    s = RasterSettings(sigma=0.5, gamma=0.01)
    out = render(vb, faces, cams, s, uvs=uvs, texture=tex, return_depth=True)
    assert out.rgb.shape == (3, 28, 32, 3) and out.alpha.shape == (3, 28, 32)
    for b in range(3):
        one = render(vb[b], faces, cams[b], s, uvs=uvs, texture=tex, return_depth=True)
        np.testing.assert_allclose(out.rgb[b], one.rgb, rtol=0, atol=1e-13)
        np.testing.assert_allclose(out.alpha[b], one.alpha, rtol=0, atol=1e-13)
        np.testing.assert_allclose(out.depth[b], one.depth, rtol=0, atol=1e-13)
    # shared vertices, batched camera
    shared = render(verts, faces, cams, s, uvs=uvs, texture=tex)
    np.testing.assert_allclose(
        shared.alpha[1], render(verts, faces, cams[1], s, uvs=uvs, texture=tex).alpha
    )


def test_numpy_in_numpy_out_and_float32():
    verts, faces, _ = sheet(5)
    cam = Camera.look_at([0, 0, -3.0], [0, 0, 0], focal=12.0, width=16, height=16)
    cols = np.tile([0.2, 0.5, 0.9], (len(verts), 1))
    out = render(verts, faces, cam, colors=cols)
    assert isinstance(out.rgb, np.ndarray) and isinstance(out.alpha, np.ndarray)
    out32 = render(torch.tensor(verts, dtype=torch.float32), faces, cam, colors=cols)
    assert out32.rgb.dtype == torch.float32 and out32.alpha.dtype == torch.float32
    np.testing.assert_allclose(out32.alpha.numpy(), out.alpha, atol=1e-5)
    # wherever a face contributes, the colour is the (constant) vertex colour: the
    # background term of the softmax vanishes at gamma = 1e-4
    inside = out.alpha > 0.5
    assert inside.sum() > 20
    np.testing.assert_allclose(
        out.rgb[inside], np.broadcast_to([0.2, 0.5, 0.9], out.rgb[inside].shape), atol=1e-9
    )


def test_camera_coords_equal_world_coords(rng):
    verts, faces, _ = sheet(5)
    cam = Camera.look_at([0.3, 0.1, -3.0], [0, 0, 0], focal=12.0, width=16, height=16)
    a = render_silhouette(verts, faces, cam)
    b = render_silhouette(cam.world_to_camera(verts), faces, cam, coords="camera")
    np.testing.assert_allclose(a, b, atol=1e-12)


def test_near_plane_culls_whole_faces():
    cam = Camera(K=[[10.0, 0, 8], [0, 10.0, 8], [0, 0, 1]], width=16, height=16)
    front = np.array([[-0.5, -0.5, 1.0], [0.5, -0.5, 1.0], [0.0, 0.5, 1.0]])
    crossing = np.array([[-0.5, -0.5, 1.0], [0.5, -0.5, 1.0], [0.0, 0.5, -0.5]])
    behind = front * [1, 1, -1]
    s = RasterSettings(sigma=0.3)
    assert render_silhouette(front, [[0, 1, 2]], cam, s).max() > 0.9
    for verts in (crossing, behind):
        v = torch.tensor(verts, requires_grad=True)
        a = render_silhouette(v, [[0, 1, 2]], cam, s)
        assert float(a.detach().abs().max()) == 0.0
        a.sum().backward()
        assert torch.isfinite(v.grad).all() and float(v.grad.abs().max()) == 0.0


def test_backface_culling():
    cam = Camera(K=[[10.0, 0, 8], [0, 10.0, 8], [0, 0, 1]], width=16, height=16)
    verts = np.array([[-0.5, -0.5, 1.0], [0.5, -0.5, 1.0], [0.0, 0.5, 1.0]])
    facing = [[0, 2, 1]]  # normal (right-hand rule) points to -z, towards the camera
    away = [[0, 1, 2]]
    s = RasterSettings(sigma=0.3, cull_backfaces=True)
    assert render_silhouette(verts, facing, cam, s).max() > 0.9
    assert render_silhouette(verts, away, cam, s).max() == 0.0
    assert render_silhouette(verts, away, cam, RasterSettings(sigma=0.3)).max() > 0.9


# ------------------------------------------------------------------ degenerate input


def test_empty_mesh_gives_background_and_zero_gradients():
    cam = Camera(K=np.diag([10.0, 10.0, 1.0]), width=8, height=6)
    for nv in (0, 4):
        v = torch.zeros((nv, 3), dtype=torch.float64, requires_grad=True)
        c = torch.ones((nv, 3), dtype=torch.float64, requires_grad=True)
        s = RasterSettings(background=(0.1, 0.2, 0.3))
        out = render(v, torch.zeros((0, 3), dtype=torch.long), cam, s, colors=c,
                     return_depth=True, return_face_index=True)  # fmt: skip
        assert float(out.alpha.detach().abs().max()) == 0.0
        torch.testing.assert_close(
            out.rgb, torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64).expand(6, 8, 3)
        )
        assert (out.face_index == -1).all() and float(out.depth.detach().abs().max()) == 0.0
        (out.rgb.sum() + out.alpha.sum()).backward()
        assert float(v.grad.abs().sum()) == 0.0


def test_zero_area_triangles_are_skipped():
    cam = Camera(K=[[10.0, 0, 8], [0, 10.0, 8], [0, 0, 1]], width=16, height=16)
    verts = torch.tensor([[-0.5, -0.5, 1.0], [0.5, 0.5, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]],
                         dtype=torch.float64, requires_grad=True)  # fmt: skip
    faces = [[0, 1, 2], [2, 3, 3]]  # collinear, and two coincident vertices
    out = render(
        verts, faces, cam, RasterSettings(sigma=0.5), colors=torch.ones(4, 3, dtype=torch.float64)
    )
    assert float(out.alpha.detach().max()) == 0.0
    (out.alpha.sum() + out.rgb.sum()).backward()
    assert torch.isfinite(verts.grad).all()


def test_stability_extreme_settings_and_geometry(rng):
    # the edge where the method fails: tiny sigma and gamma (the sigmoid and the softmax
    # saturate), slivers, and vertices just beyond the near plane (huge projections)
    verts, faces, uvs = sheet(8)
    verts = verts.copy()
    verts[:, 2] += 1.0
    verts[0, 2] = 0.0105  # projects ~100x farther than the others
    verts[1] = verts[2] + [1e-5, 0, 0]  # slivers
    cam = Camera(K=[[20.0, 0, 16], [0, 20.0, 16], [0, 0, 1]], width=32, height=32)
    v = torch.tensor(verts, requires_grad=True)
    for s in (RasterSettings(sigma=1e-7, gamma=1e-7), RasterSettings(sigma=50.0, gamma=10.0)):
        out = render(v, faces, cam, s, uvs=uvs, texture=checkerboard(16, 4))
        assert torch.isfinite(out.rgb).all() and torch.isfinite(out.alpha).all()
        alpha = out.alpha.detach()
        assert float(alpha.min()) >= 0.0 and float(alpha.max()) <= 1.0
        (out.rgb.sum() + out.alpha.sum()).backward()
        assert torch.isfinite(v.grad).all()
        v.grad = None


def test_texture_sampling_matches_texel_centres(rng):
    tex = rng.uniform(0, 1, (5, 7, 2))
    r, c = np.meshgrid(np.arange(5), np.arange(7), indexing="ij")
    uv = np.stack([(c + 0.5) / 7, (r + 0.5) / 5], -1)
    np.testing.assert_allclose(sample_texture(tex, uv), tex, atol=1e-12)
    mid = sample_texture(tex, np.array([[1.0 / 7, 0.5 / 5]]))  # half-way between texels 0 and 1
    np.testing.assert_allclose(mid[0], (tex[0, 0] + tex[0, 1]) / 2, atol=1e-12)
    np.testing.assert_allclose(sample_texture(tex, np.array([[-3.0, 9.0]]))[0], tex[4, 0])


# ------------------------------------------------------------------ validation


def _args():
    verts, faces, uvs = sheet(3)
    cam = Camera.look_at([0, 0, -3.0], [0, 0, 0], focal=8.0, width=8, height=8)
    return verts, faces, uvs, cam


@pytest.mark.parametrize(
    "change, exc, match",
    [
        (dict(vertices=np.zeros((4, 2))), ValueError, "vertices"),
        (dict(vertices=np.zeros((1, 2, 9, 3))), ValueError, "vertices"),
        (dict(vertices="nan"), ValueError, "vertices"),
        (dict(faces=np.array([[0, 1, 99]])), ValueError, "faces"),
        (dict(faces=np.array([[0, -1, 2]])), ValueError, "faces"),
        (dict(faces=np.array([[0.0, 1.0, 2.0]])), TypeError, "faces"),
        (dict(faces=np.array([0, 1, 2])), ValueError, "faces"),
        (dict(camera="cam"), TypeError, "camera"),
        (dict(settings=dict(sigma=1.0)), TypeError, "settings"),
        (dict(colors=np.ones((5, 3))), ValueError, "colors"),
        (dict(colors=np.full((9, 3), np.nan)), ValueError, "colors"),
        (dict(colors=np.ones((9, 3)), texture=np.ones((4, 4, 3))), ValueError, "colors"),
        (dict(texture=np.ones((4, 4, 3))), ValueError, "uvs"),
        (dict(uvs=np.ones((9, 2))), ValueError, "uvs"),
        (dict(texture=np.ones((4, 4)), uvs="ok"), ValueError, "texture"),
        (dict(texture=np.ones((0, 4, 3)), uvs="ok"), ValueError, "texture"),
        (dict(texture=np.ones((4, 4, 3)), uvs=np.ones((7, 2))), ValueError, "uvs"),
        (dict(colors=np.ones((9, 2))), ValueError, "background"),
        (dict(coords="screen"), ValueError, "coords"),
    ],
)
def test_render_validation(change, exc, match):
    verts, faces, uvs, cam = _args()
    args = dict(vertices=verts, faces=faces, camera=cam, settings=None)
    kw = {}
    for k, v in change.items():
        if k in args:
            args[k] = v
        else:
            kw[k] = uvs if (isinstance(v, str) and v == "ok") else v
    if isinstance(args["vertices"], str):
        args["vertices"] = verts.copy()
        args["vertices"][2, 1] = np.nan
    with pytest.raises(exc, match=match):
        render(**args, **kw)


def test_batch_mismatch_is_an_error():
    verts, faces, _, _ = _args()
    cams = Camera(K=np.stack([np.diag([8.0, 8.0, 1.0])] * 2), t=[0, 0, 3.0], width=8, height=8)
    with pytest.raises(ValueError, match="batch"):
        render_silhouette(np.stack([verts] * 3), faces, cams)


@pytest.mark.parametrize(
    "kwargs, exc",
    [
        (dict(sigma=0.0), ValueError),
        (dict(sigma=-1.0), ValueError),
        (dict(sigma="a"), TypeError),
        (dict(gamma=0.0), ValueError),
        (dict(blur_threshold=0.5), ValueError),
        (dict(blur_threshold=-1e-3), ValueError),
        (dict(tile_size=0), ValueError),
        (dict(tile_size=2.5), TypeError),
        (dict(znear=0.0), ValueError),
        (dict(znear=2.0, zfar=1.0), ValueError),
        (dict(background=()), ValueError),
        (dict(background=(0.0, np.nan, 0.0)), ValueError),
        (dict(background_depth=np.inf), ValueError),
        (dict(hard=1), TypeError),
        (dict(cull_backfaces="yes"), TypeError),
        (dict(min_area=-1.0), ValueError),
    ],
)
def test_settings_validation(kwargs, exc):
    with pytest.raises(exc):
        RasterSettings(**kwargs)


def test_settings_margin_and_softras_conversion():
    from polygeo.render import sigma_from_softras

    s = RasterSettings(sigma=0.5, blur_threshold=1e-4)
    # at the margin the coverage equals the threshold
    x = -(s.blur_margin**2) / s.sigma
    assert 1 / (1 + math.exp(-x)) == pytest.approx(1e-4, rel=1e-9)
    assert RasterSettings(blur_threshold=0.0).blur_margin == math.inf
    assert sigma_from_softras(1e-4, 256) == pytest.approx(1.6384)
    with pytest.raises(ValueError):
        sigma_from_softras(0.0, 64)


def test_texture_helpers_and_their_validation():
    from polygeo.render import flip_v

    uv = np.array([[0.25, 0.1], [0.5, 0.75]])
    np.testing.assert_allclose(flip_v(uv), [[0.25, 0.9], [0.5, 0.25]])
    np.testing.assert_allclose(flip_v(flip_v(uv)), uv)
    tex = checkerboard(8, 2, colors=((1.0, 0.0), (0.0, 1.0)))
    assert tex.shape == (8, 8, 2)
    np.testing.assert_allclose(tex[0, 0], [1.0, 0.0])
    np.testing.assert_allclose(tex[0, 4], [0.0, 1.0])
    np.testing.assert_allclose(tex[4, 4], [1.0, 0.0])
    with pytest.raises(ValueError, match="colors"):
        checkerboard(8, 2, colors=(1.0, 0.0))
    with pytest.raises(ValueError, match="size"):
        checkerboard(0)
    with pytest.raises(ValueError, match="texture"):
        sample_texture(np.ones((4, 4)), uv)
    with pytest.raises(ValueError, match="texture"):
        sample_texture(np.ones((0, 4, 3)), uv)
    with pytest.raises(ValueError, match="uv"):
        sample_texture(np.ones((4, 4, 3)), np.ones((3, 3)))
    with pytest.raises(ValueError, match="uv"):
        flip_v(np.ones(3))


def test_rasterize_faces_validation(rng):
    fv = random_face_verts(rng, 1, 3, 8, 8)
    with pytest.raises(ValueError, match="face_verts"):
        rasterize_faces(fv[..., :2], 8, 8)
    with pytest.raises(ValueError, match="face_uvs"):
        rasterize_faces(fv, 8, 8, texture=torch.ones(4, 4, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="face_colors"):
        rasterize_faces(fv, 8, 8, face_colors=torch.ones(1, 5, 3, 3, dtype=torch.float64))


def test_tile_size_does_not_change_the_result(rng):
    verts, faces, uvs = sheet(9)
    cam = Camera.look_at([0.2, -0.1, -3.0], [0, 0, 0], focal=25.0, width=37, height=29)
    tex = checkerboard(32, 4, smooth=True)
    outs, grads = [], []
    for ts in (3, 8, 16):
        v = torch.tensor(verts, requires_grad=True)
        out = render(v, faces, cam, RasterSettings(sigma=0.4, gamma=0.01, tile_size=ts), uvs=uvs,
                     texture=tex)  # fmt: skip
        (out.alpha.sum() + (out.rgb * torch.arange(3.0, dtype=torch.float64)).sum()).backward()
        outs.append(out)
        grads.append(v.grad)
    for out, g in zip(outs[1:], grads[1:]):
        assert torch.equal(out.alpha, outs[0].alpha) and torch.equal(out.rgb, outs[0].rgb)
        torch.testing.assert_close(g, grads[0], rtol=1e-12, atol=1e-12)


# ------------------------------------------------------------------ project_faces


def test_project_faces_is_the_pinhole_projection():
    cam = Camera(K=[[30.0, 0, 16.0], [0, 30.0, 12.0], [0, 0, 1]], width=32, height=24)
    v = np.array([[-1.0, -0.5, 2.0], [1.0, -0.5, 4.0], [0.0, 1.0, 3.0], [0.5, 0.5, 0.001]])
    f = np.array([[0, 1, 2], [2, 1, 3]])
    fv = project_faces(v, f, cam, coords="camera")
    assert isinstance(fv, np.ndarray) and fv.shape == (2, 3, 3)
    want = np.stack([30 * v[:, 0] / v[:, 2] + 16, 30 * v[:, 1] / v[:, 2] + 12, v[:, 2]], -1)
    np.testing.assert_allclose(fv[0], want[[0, 1, 2]], rtol=1e-12)
    # the vertex in front of the near plane keeps its depth, its projection stays finite
    assert np.isfinite(fv).all() and fv[1, 2, 2] == 0.001
    # batched torch input: torch out, differentiable, equal per item
    vt = torch.from_numpy(np.stack([v, v + [0.1, 0.0, 0.5]])).requires_grad_(True)
    fb = project_faces(vt, f, cam, coords="camera")
    assert fb.shape == (2, 2, 3, 3)
    np.testing.assert_allclose(fb[0].detach().numpy(), fv, rtol=1e-12)
    fb[..., :2].sum().backward()
    assert torch.isfinite(vt.grad).all() and vt.grad.abs().sum() > 0


def test_project_faces_validation():
    cam = Camera(K=[[30.0, 0, 16.0], [0, 30.0, 12.0], [0, 0, 1]], width=32, height=24)
    v = np.ones((3, 3))
    with pytest.raises(ValueError, match="faces"):
        project_faces(v, [[0, 1, 3]], cam)
    with pytest.raises(TypeError, match="camera"):
        project_faces(v, [[0, 1, 2]], "camera")
