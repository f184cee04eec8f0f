"""Triangulated mask centres: exact on synthetic disks, robust to disagreement, held-out safe."""

import math

import cv2
import numpy as np
import torch

from gst.train.anchors import anchor_term, mask_centre_anchors, mask_centroids
from gst.train.views import CropSet

S = 96


def _ring_cameras(n: int):
    R, t = [], []
    for i in range(n):
        a = 2 * math.pi * i / n
        Ri = np.array([[math.cos(a), 0, -math.sin(a)], [0, 1, 0], [math.sin(a), 0, math.cos(a)]])
        R.append(Ri)
        t.append(np.array([0.0, 0.0, 4.0]))
    return R, t


def _crops(X: np.ndarray, shift_px: dict | None = None, n_cams: int = 3) -> CropSet:
    """One frame, one person: a disk mask centred on the projection of X in each camera's crop."""
    shift_px = shift_px or {}
    R, t = _ring_cameras(n_cams)
    K = np.array([[150.0, 0, (S - 1) / 2 + 3], [0, 150.0, (S - 1) / 2 - 2], [0, 0, 1]])
    masks = []
    for i in range(n_cams):
        p = K @ (R[i] @ X + t[i])
        u, v = p[:2] / p[2] + np.asarray(shift_px.get(i, (0, 0)))
        m = np.zeros(
            (S * 8, S * 8), np.uint8
        )  # drawn at 8x with sub-pixel centre, then area-averaged
        cv2.circle(
            m, (int(round((u + 0.5) * 8 - 0.5)), int(round((v + 0.5) * 8 - 0.5))), 15 * 8, 255, -1
        )
        masks.append(cv2.resize(m, (S, S), interpolation=cv2.INTER_AREA) / 255.0)
    n = n_cams
    return CropSet(
        images=torch.zeros(n, S, S, 3, dtype=torch.uint8),
        masks=torch.tensor(np.stack(masks)).float(),
        K=torch.tensor(K).float().repeat(n, 1, 1),
        R=torch.tensor(np.stack(R)).float(),
        t=torch.tensor(np.stack(t)).float(),
        camera=torch.arange(n),
        frame=torch.zeros(n, dtype=torch.long),
        person=torch.zeros(n, dtype=torch.long),
        camera_names=[f"c{i}" for i in range(n)],
    )


def test_centroid_of_a_disk_is_its_centre():
    m = np.zeros((S, S), np.float32)
    cv2.circle(m, (40, 55), 12, 1.0, -1)
    uv, ok = mask_centroids(torch.tensor(m)[None])
    assert ok.all() and torch.allclose(
        uv[0], torch.tensor([40.0, 55.0], dtype=torch.float64), atol=1e-6
    )
    _, ok = mask_centroids(torch.zeros(1, S, S))
    assert not ok.any()


def test_anchors_recover_the_3d_centre():
    X = np.array([0.1, -0.2, 0.3])
    a = mask_centre_anchors(_crops(X))
    assert torch.isfinite(a).all()
    assert np.allclose(a.numpy(), X[None], atol=0.01)  # every crop of the group gets the same point


def test_disagreeing_views_give_no_anchor_and_heldout_views_are_not_used():
    X = np.array([0.0, 0.1, -0.1])
    bad = _crops(X, shift_px={2: (30, 0)})
    assert torch.isnan(mask_centre_anchors(bad)).all()
    # with camera 2 held out, its (wrong) mask does not matter
    a = mask_centre_anchors(bad, cameras={0, 1})
    assert np.allclose(a[:2].numpy(), X[None], atol=0.01) and torch.isnan(a[2]).all()


def test_anchor_term_is_a_hinge_with_gradient():
    centres = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [5.0, 5.0, 5.0]], requires_grad=True)
    anchors = torch.tensor([[0.05, 0.0, 0.0], [0.0, 0.0, 0.0], [float("nan")] * 3])
    loss = anchor_term(centres, anchors, margin=0.1)
    assert math.isclose(float(loss.detach()), (0.0 + 0.9) / 2, rel_tol=1e-6)  # NaN rows are ignored
    loss.backward()
    assert (
        centres.grad[0].abs().sum() == 0
        and centres.grad[1, 0] > 0
        and centres.grad[2].abs().sum() == 0
    )
    none = anchor_term(centres, torch.full((3, 3), float("nan")))
    assert float(none.detach()) == 0.0
