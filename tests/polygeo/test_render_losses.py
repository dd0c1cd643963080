import numpy as np
import pytest
import torch

from polygeo.render import iou, rgb_loss, silhouette_loss, soft_iou


def test_silhouette_losses_analytic():
    p = np.array([[0.0, 0.5], [1.0, 0.25]])
    t = np.array([[0.0, 1.0], [1.0, 0.0]])
    assert silhouette_loss(p, t, kind="l2") == pytest.approx((0.25 + 0.0625) / 4)
    assert silhouette_loss(p, t, kind="l1") == pytest.approx((0.5 + 0.25) / 4)
    # soft IoU: inter = 0.5 + 1, union = (0.5 + 1 - 0.5) + 1 + 0.25
    assert soft_iou(p, t) == pytest.approx(1.5 / 2.25)
    assert silhouette_loss(p, t, kind="iou") == pytest.approx(1 - 1.5 / 2.25)


def test_masks_exclude_pixels():
    p = np.array([[0.0, 0.5], [1.0, 0.25]])
    t = np.array([[0.0, 1.0], [1.0, 0.0]])
    m = np.array([[1.0, 0.0], [1.0, 1.0]])
    assert silhouette_loss(p, t, m, kind="l1") == pytest.approx(0.25 / 3)
    assert silhouette_loss(p, t, np.zeros((2, 2))) == 0.0  # empty mask: defined, not NaN
    rgb_p = np.zeros((2, 2, 3))
    rgb_t = np.ones((2, 2, 3))
    rgb_t[0, 1] = 5.0
    assert rgb_loss(rgb_p, rgb_t, m) == pytest.approx(1.0)
    assert rgb_loss(rgb_p, rgb_t, m, kind="l2") == pytest.approx(1.0)
    assert rgb_loss(rgb_p, rgb_t) == pytest.approx((3 + 5) / 4)


def test_batched_reduction_and_mask_broadcast(rng):
    p = rng.uniform(0, 1, (3, 5, 4))
    t = (rng.uniform(0, 1, (3, 5, 4)) > 0.5).astype(float)
    m = (rng.uniform(0, 1, (5, 4)) > 0.3).astype(float)
    per = silhouette_loss(p, t, m, reduction="none")
    assert per.shape == (3,)
    for b in range(3):
        assert per[b] == pytest.approx(silhouette_loss(p[b], t[b], m))
    assert silhouette_loss(p, t, m) == pytest.approx(per.mean())
    rgb = rng.uniform(0, 1, (3, 5, 4, 3))
    per_rgb = rgb_loss(rgb, rgb * 0.5, m, reduction="none")
    for b in range(3):
        assert per_rgb[b] == pytest.approx(rgb_loss(rgb[b], rgb[b] * 0.5, m))


def test_hard_iou_and_empty():
    a = np.zeros((4, 4))
    b = np.zeros((4, 4))
    assert iou(a, b) == 1.0 and soft_iou(a, b) == 1.0
    a[:2] = 1
    b[1:3] = 1
    assert iou(a, b) == pytest.approx(4 / 12)


def test_losses_are_differentiable():
    p = torch.rand(2, 6, 5, dtype=torch.float64, requires_grad=True)
    t = (torch.rand(2, 6, 5, dtype=torch.float64) > 0.5).double()
    m = torch.rand(6, 5, dtype=torch.float64)
    for kind in ("l1", "l2", "iou"):
        assert torch.autograd.gradcheck(lambda x, k=kind: silhouette_loss(x, t, m, kind=k), (p,))
    q = torch.rand(2, 6, 5, 3, dtype=torch.float64, requires_grad=True)
    target = q.detach().clone() * 0.3
    assert torch.autograd.gradcheck(lambda x: rgb_loss(x, target, m, kind="l2"), (q,))
    assert isinstance(silhouette_loss(p, t), torch.Tensor)


@pytest.mark.parametrize(
    "call",
    [
        lambda: silhouette_loss(np.zeros((4, 4)), np.zeros((4, 5))),
        lambda: silhouette_loss(np.zeros(4), np.zeros(4)),
        lambda: silhouette_loss(np.zeros((4, 4)), np.zeros((4, 4)), np.ones((3, 4))),
        lambda: silhouette_loss(np.zeros((2, 4, 4)), np.zeros((2, 4, 4)), np.ones((3, 4, 4))),
        lambda: silhouette_loss(np.zeros((4, 4)), np.zeros((4, 4)), kind="l3"),
        lambda: silhouette_loss(np.zeros((4, 4)), np.zeros((4, 4)), reduction="sum"),
        lambda: rgb_loss(np.zeros((4, 4, 3)), np.zeros((4, 4, 2))),
        lambda: rgb_loss(np.zeros((4, 4, 3)), np.zeros((4, 4, 3)), kind="iou"),
        lambda: rgb_loss(np.zeros((4, 3)), np.zeros((4, 3))),
        lambda: soft_iou(np.zeros((4, 4)), np.zeros((5, 4))),
        lambda: iou(np.zeros((4, 4)), np.zeros((4, 3))),
    ],
)
def test_loss_validation(call):
    with pytest.raises(ValueError):
        call()
