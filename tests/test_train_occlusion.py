"""Occluder masks map other people's crop masks exactly, and ignored pixels give no gradient."""

import cv2
import numpy as np
import torch

from gst.train.occlusion import ignore_occluded, occluder_masks
from gst.train.views import CropSet

W, H, S = 320, 240, 64
K_FULL = np.array([[300.0, 0, W / 2], [0, 300.0, H / 2], [0, 0, 1]])


def _disk(cx, cy, r):
    img = np.zeros((H, W), np.uint8)
    cv2.circle(img, (cx, cy), r, 255, -1)
    return img


def _window(cx, cy, side):
    """Similarity full px -> crop px for a square window of `side` px centred at (cx, cy)."""
    s = S / side
    return np.array([[s, 0, S / 2 - s * cx], [0, s, S / 2 - s * cy], [0, 0, 1.0]])


def _crop(img, A):
    return cv2.warpAffine(img, A[:2], (S, S), flags=cv2.INTER_LINEAR)


def test_occluder_masks_equal_cropping_the_other_persons_full_frame_mask():
    people = {1: _disk(140, 120, 40), 2: _disk(185, 130, 45)}
    windows = {1: _window(140, 120, 110), 2: _window(190, 125, 150)}
    rows = [
        (0, 0, 1),
        (0, 0, 2),
        (0, 1, 1),
    ]  # (frame, camera, person); camera 1 sees person 1 alone
    masks, K = [], []
    for _, _, p in rows:
        masks.append(_crop(people[p], windows[p]) / 255.0)
        K.append(windows[p] @ K_FULL)
    n = len(rows)
    crops = CropSet(
        images=torch.zeros(n, S, S, 3, dtype=torch.uint8),
        masks=torch.tensor(np.stack(masks)).float(),
        K=torch.tensor(np.stack(K)).float(),
        R=torch.eye(3).repeat(n, 1, 1),
        t=torch.zeros(n, 3),
        camera=torch.tensor([r[1] for r in rows]),
        frame=torch.tensor([r[0] for r in rows]),
        person=torch.tensor([r[2] for r in rows]),
        camera_names=["a", "b"],
    )
    occ = occluder_masks(crops).numpy()
    for i, other in ((0, 2), (1, 1)):
        expected = _crop(people[other], windows[rows[i][2]]) / 255.0
        inter = np.minimum(occ[i] > 0.5, expected > 0.5).sum()
        union = np.maximum(occ[i] > 0.5, expected > 0.5).sum()
        assert union > 100 and inter / union > 0.95
    assert occ[2].max() == 0  # alone in its camera


def test_ignored_pixels_give_no_gradient_but_own_pixels_do():
    rgb = torch.rand(1, 1, 8, 8, 3, requires_grad=True)
    alpha = torch.rand(1, 1, 8, 8, requires_grad=True)
    target, mask = torch.rand(1, 1, 8, 8, 3), torch.zeros(1, 1, 8, 8)
    mask[..., :4] = 1  # the person: left half
    occ = torch.zeros(1, 1, 8, 8)
    occ[..., 2:6] = 1  # another person over columns 2..5 (2, 3 overlap the person's own mask)
    t2, m2 = ignore_occluded(rgb, alpha, target, mask, occ)
    loss = ((rgb - t2) ** 2).mean() + ((alpha - m2) ** 2).mean()
    loss.backward()
    g, ga = rgb.grad.abs().sum(-1)[0, 0], alpha.grad.abs()[0, 0]
    assert (g[:, 4:6] == 0).all() and (ga[:, 4:6] == 0).all()  # hidden by the other person
    assert (g[:, :4] > 0).all() and (g[:, 6:] > 0).all()  # own pixels and the free background


def test_training_psnr_counts_the_supervised_pixels_only():
    """The logged PSNR compared the render with a target into which `ignore_occluded` had pasted
    the render: ignored pixels counted as perfect (3 dB too high with half of them ignored)."""
    from gst.train.occlusion import supervised_psnr

    gen = torch.Generator().manual_seed(0)
    rgb = torch.rand(2, 8, 8, 3, generator=gen)
    target = torch.rand(2, 8, 8, 3, generator=gen)
    mask = torch.zeros(2, 8, 8)
    occluders = torch.zeros(2, 8, 8)
    occluders[..., :4] = 1  # half of every view hidden by someone else
    filled, _ = ignore_occluded(rgb, torch.zeros(2, 8, 8), target, mask, occluders)
    own = -10 * torch.log10(((rgb - target)[..., 4:, :] ** 2).mean())  # the supervised half
    ignored = (occluders * (1 - mask)).clamp(0, 1)
    assert torch.allclose(supervised_psnr(rgb, filled, ignored), own, atol=1e-5)
    naive = -10 * torch.log10(((rgb - filled) ** 2).mean())
    assert naive - own > 2.9  # what the log showed
    assert torch.allclose(
        supervised_psnr(rgb, target), -10 * torch.log10(((rgb - target) ** 2).mean())
    )


def test_every_other_view_is_a_target_before_any_repeats():
    """With fewer other views than targets, all were drawn with replacement: an available camera
    was left out in about a quarter of the samples while another was rendered three times."""
    from gst.train.views import sample_multiview
    from tests.test_train_recipe import crop_set

    crops = crop_set(n_frames=4, n_cams=3)
    groups = [torch.nonzero(crops.frame == f).flatten() for f in range(4)]
    batch = sample_multiview(crops, groups, torch.Generator().manual_seed(1), 64, 4, 32)
    for inp, tgt in zip(batch.input_index.tolist(), batch.target_index.tolist(), strict=True):
        group = set(torch.nonzero(crops.frame == crops.frame[inp]).flatten().tolist())
        assert tgt[0] == inp and set(tgt) == group  # the input, then both others, then a repeat
