import math

import numpy as np
import pytest
import torch

from polygeo.render import Camera, RasterSettings, checkerboard, render, rgb_loss, silhouette_loss


def _sheet(n, wave=0.2):
    u, v = np.meshgrid(np.linspace(-1, 1, n), np.linspace(-1, 1, n))
    verts = np.stack([u, v, wave * np.sin(3 * u) * np.cos(2 * v)], -1).reshape(-1, 3)
    idx = np.arange(n * n).reshape(n, n)
    a = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[:-1, 1:]], -1).reshape(-1, 3)
    b = np.stack([idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 3)
    uvs = np.stack([(u + 1) / 2, (v + 1) / 2], -1).reshape(-1, 2)
    return verts, np.concatenate([a, b]), uvs


def _rodrigues(r):
    theta = torch.sqrt((r * r).sum() + 1e-20)
    k = r / theta
    K = torch.zeros(3, 3, dtype=r.dtype)
    K[0, 1], K[0, 2], K[1, 0] = -k[2], k[1], k[2]
    K[1, 2], K[2, 0], K[2, 1] = -k[0], -k[1], k[0]
    return torch.eye(3, dtype=r.dtype) + torch.sin(theta) * K + (1 - torch.cos(theta)) * K @ K


def _pose(verts, r, t, log_s):
    # broadcast product rather than a (BLAS-threaded) matmul: fast on a busy 2-core machine
    return torch.exp(log_s) * (verts.unsqueeze(-2) * _rodrigues(r)).sum(-1) + t


@pytest.mark.slow
def test_gradient_descent_recovers_pose_and_scale():
    torch.manual_seed(0)
    verts_np, faces, uvs = _sheet(12)
    verts = torch.tensor(verts_np, dtype=torch.float32)
    tex = torch.tensor(checkerboard(64, 4, smooth=True), dtype=torch.float32)
    cam = Camera.look_at([0.0, 0.0, -3.0], [0, 0, 0], focal=48.0, width=64, height=64)
    s = RasterSettings(sigma=1.0, gamma=1e-3, zfar=10.0)
    r_true = torch.tensor([0.25, -0.2, 0.1])
    t_true = torch.tensor([0.1, -0.05, 0.2])
    ls_true = torch.tensor(math.log(0.9))
    with torch.no_grad():
        target = render(_pose(verts, r_true, t_true, ls_true), faces, cam, s, uvs=uvs, texture=tex)
    r = (r_true + torch.tensor([0.12, 0.1, -0.1])).requires_grad_(True)
    t = (t_true + torch.tensor([-0.12, 0.1, 0.25])).requires_grad_(True)
    ls = (ls_true + math.log(1.15)).clone().requires_grad_(True)
    opt = torch.optim.Adam([r, t, ls], lr=0.01)
    sched = torch.optim.lr_scheduler.StepLR(opt, step_size=150, gamma=0.3)
    first = None
    for _ in range(300):
        opt.zero_grad()
        out = render(_pose(verts, r, t, ls), faces, cam, s, uvs=uvs, texture=tex)
        loss = silhouette_loss(out.alpha, target.alpha) + rgb_loss(out.rgb, target.rgb)
        loss.backward()
        opt.step()
        sched.step()
        first = float(loss.detach()) if first is None else first
    rot_err = torch.linalg.norm(_rodrigues(r.detach()) @ _rodrigues(r_true).T - torch.eye(3))
    assert float(loss.detach()) < 0.01 * first
    assert math.degrees(float(rot_err)) < 0.5
    assert float((t.detach() - t_true).norm()) < 0.01
    assert abs(math.exp(float(ls.detach())) / 0.9 - 1) < 0.005
