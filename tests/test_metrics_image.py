"""PSNR, SSIM and SHERF-style box metrics against independent formulas (numpy, brute force,
ray casting)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from gst.metrics.image import (
    box_corners,
    masked_bbox_metrics,
    points_box_corners,
    project_box_region,
    psnr,
    ssim,
)
from gst.metrics.lpips_weights import default_weights_path


def _images(b=2, c=3, h=24, w=28, noise=0.1, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(b, c, h, w, generator=g, dtype=torch.float64)
    y = (x + noise * torch.randn(x.shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    return x, y


# --- PSNR ---------------------------------------------------------------------------------------


def test_psnr_matches_numpy_formula():
    x, y = _images()
    for i in range(2):
        mse = np.mean((x[i].numpy() - y[i].numpy()) ** 2)
        assert psnr(x, y)[i].item() == pytest.approx(10 * math.log10(1.0 / mse), abs=1e-9)
    assert psnr(x * 255, y * 255, data_range=255.0).tolist() == pytest.approx(
        psnr(x, y).tolist(), abs=1e-9
    )


def test_psnr_mask_uses_only_covered_pixels():
    x, y = _images(b=1)
    mask = torch.zeros(24, 28, dtype=torch.bool)
    mask[5:15, 3:20] = True
    sel = mask.numpy()
    mse = np.mean((x[0].numpy()[:, sel] - y[0].numpy()[:, sel]) ** 2)
    expected = 10 * math.log10(1.0 / mse)
    for m in (mask, mask[None], mask[None, None], mask.double()[None, None]):
        assert psnr(x, y, m).item() == pytest.approx(expected, abs=1e-9)
    # Pixels outside the mask do not matter.
    y2 = y.clone()
    y2[..., ~mask] = 1.0 - y2[..., ~mask]
    assert psnr(x, y2, mask).item() == pytest.approx(expected, abs=1e-9)


def test_psnr_edge_cases():
    x, _ = _images(b=1)
    assert psnr(x, x.clone()).item() == math.inf
    assert math.isnan(psnr(x, x + 0.1, torch.zeros(24, 28)).item())
    with pytest.raises(ValueError, match="mask has shape"):
        psnr(x, x, torch.ones(5, 5))
    with pytest.raises(ValueError, match="same shape"):
        psnr(x, x[..., :10])


def test_psnr_is_differentiable():
    x, y = _images(b=1)
    x.requires_grad_(True)
    psnr(x, y).sum().backward()
    assert torch.isfinite(x.grad).all()


# --- SSIM ---------------------------------------------------------------------------------------


def _ssim_brute_force(
    x: np.ndarray, y: np.ndarray, win: int = 11, sigma: float = 1.5, pad: str = "same"
) -> float:
    """Wang et al. 2004 SSIM, one Gaussian-weighted window at a time (float64).

    x, y: (C, H, W) in [0, 1].
    """
    c1, c2 = 0.01**2, 0.03**2
    r = win // 2
    g = np.exp(-((np.arange(win) - r) ** 2) / (2 * sigma**2))
    g = np.outer(g, g) / np.outer(g, g).sum()
    if pad == "same":  # numpy's 'reflect' mirrors without repeating the edge, as torch's does
        x, y = (np.pad(a, ((0, 0), (r, r), (r, r)), mode="reflect") for a in (x, y))
    vals = []
    for ch in range(x.shape[0]):
        for i in range(x.shape[1] - 2 * r):
            for j in range(x.shape[2] - 2 * r):
                a, b = x[ch, i : i + win, j : j + win], y[ch, i : i + win, j : j + win]
                ma, mb = (g * a).sum(), (g * b).sum()
                va, vb = (g * a * a).sum() - ma**2, (g * b * b).sum() - mb**2
                cov = (g * a * b).sum() - ma * mb
                vals.append(
                    (2 * ma * mb + c1) * (2 * cov + c2) / ((ma**2 + mb**2 + c1) * (va + vb + c2))
                )
    return float(np.mean(vals))


@pytest.mark.parametrize("padding", ["same", "valid"])
def test_ssim_matches_brute_force(padding):
    x, y = _images(b=2, h=20, w=23, noise=0.15)
    got = ssim(x, y, padding=padding)
    for i in range(2):
        ref = _ssim_brute_force(x[i].numpy(), y[i].numpy(), pad=padding)
        assert got[i].item() == pytest.approx(ref, abs=1e-9)


def test_ssim_float32_and_properties():
    x, y = _images(b=2, h=32, w=32, noise=0.2)
    x32, y32 = x.float(), y.float()
    assert ssim(x32, y32).tolist() == pytest.approx(ssim(x, y).tolist(), abs=1e-5)
    assert ssim(x32, x32.clone()).tolist() == pytest.approx([1.0, 1.0], abs=1e-6)
    assert ssim(x32, y32).tolist() == pytest.approx(ssim(y32, x32).tolist(), abs=1e-6)
    black = torch.zeros(1, 3, 16, 16)
    assert ssim(black, black).item() == pytest.approx(1.0, abs=1e-6)
    with pytest.raises(ValueError, match="smaller than the 11 px window"):
        ssim(x[..., :8, :8], y[..., :8, :8])


# --- projected body box -------------------------------------------------------------------------


def _camera(yaw_deg: float, pos: np.ndarray, w: int = 64, h: int = 48, f: float = 50.0):
    """World-to-camera R, t for a camera at `pos` looking along its rotated +z axis."""
    R = Rotation.from_euler("y", yaw_deg, degrees=True).as_matrix().T
    t = -R @ pos
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    return K, R, t, (w, h)


def _ray_cast_mask(lo, hi, K, R, t, size) -> np.ndarray:
    """Reference: pixel centres whose ray hits the box in front of the camera (slab test)."""
    w, h = size
    v, u = np.mgrid[0:h, 0:w]
    d_cam = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3) @ np.linalg.inv(K).T
    d = d_cam @ R  # camera -> world directions
    o = -R.T @ t
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - o) / d, (hi - o) / d
    tmin = np.nanmax(np.minimum(t1, t2), axis=1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=1)
    return ((tmax >= np.maximum(tmin, 0)) & (tmax > 0)).reshape(h, w)


@pytest.mark.parametrize(
    "yaw,pos",
    [
        (0.0, (0.0, 0.3, -4.0)),  # box in front
        (-25.0, (1.5, -0.2, -3.0)),  # seen obliquely
        (-20.0, (0.6, 0.0, -0.1)),  # camera beside the box: it crosses the camera plane
        (40.0, (0.1, 0.1, 0.0)),  # camera inside the box: everything is covered
    ],
)
def test_projected_box_matches_ray_casting(yaw, pos):
    lo, hi = np.array([-0.4, -0.9, -0.3]), np.array([0.4, 0.9, 0.3])
    K, R, t, size = _camera(yaw, np.array(pos), w=128, h=96, f=120.0)
    region = project_box_region(box_corners(lo, hi), K, R, t, size)
    ref = _ray_cast_mask(lo, hi, K, R, t, size)
    inter, union = (region.mask & ref).sum(), (region.mask | ref).sum()
    # fillPoly also paints the pixels its edges cross, so allow about half a pixel of border.
    assert union > 0 and inter / union > 0.95, (inter, union)
    ys, xs = np.nonzero(ref)
    x0, y0, x1, y1 = region.rect
    assert abs(x0 - xs.min()) <= 1 and abs(y0 - ys.min()) <= 1
    assert abs(x1 - 1 - xs.max()) <= 1 and abs(y1 - 1 - ys.max()) <= 1


def test_box_behind_camera_is_empty():
    K, R, t, size = _camera(180.0, np.array([0.0, 0.0, -4.0]))  # looking away from the box
    region = project_box_region(box_corners([-0.4, -0.9, -0.3], [0.4, 0.9, 0.3]), K, R, t, size)
    assert region.empty and not region.mask.any()


def test_points_box_corners_pads_and_checks():
    pts = np.array([[0.0, 0, 0], [1, 2, 3]])
    c = points_box_corners(pts, margin=0.05)
    np.testing.assert_allclose(c.min(0), [-0.05] * 3)
    np.testing.assert_allclose(c.max(0), [1.05, 2.05, 3.05])
    with pytest.raises(ValueError, match="NaN"):
        points_box_corners(np.array([[np.nan, 0, 0]]))
    with pytest.raises(ValueError, match=r"\(N>0, 3\)"):
        points_box_corners(np.zeros((0, 3)))


# --- SHERF-style metrics ------------------------------------------------------------------------


def _scene(b=2):
    K, R, t, size = _camera(10.0, np.array([0.2, 0.1, -4.0]), w=96, h=80, f=120.0)
    corners = box_corners([-0.5, -0.8, -0.3], [0.5, 0.8, 0.3])
    g = torch.Generator().manual_seed(3)
    target = torch.rand(b, 3, 80, 96, generator=g)
    pred = (target + 0.05 * torch.randn(target.shape, generator=g)).clamp(0, 1)
    return pred, target, corners, K, R, t, size


def test_bbox_metrics_equal_plain_metrics_on_region():
    pred, target, corners, K, R, t, size = _scene()
    region = project_box_region(corners, K, R, t, size)
    x0, y0, x1, y1 = region.rect
    m = masked_bbox_metrics(pred, target, corners, K, R, t)
    assert m.valid.all() and m.lpips is None
    assert m.rects.tolist() == [[x0, y0, x1, y1]] * 2
    expected_psnr = psnr(pred, target, torch.from_numpy(region.mask))
    torch.testing.assert_close(m.psnr, expected_psnr.double(), rtol=0, atol=1e-5)
    expected_ssim = ssim(pred[..., y0:y1, x0:x1], target[..., y0:y1, x0:x1])
    torch.testing.assert_close(m.ssim, expected_ssim.double(), rtol=0, atol=1e-6)
    rect = masked_bbox_metrics(pred, target, corners, K, R, t, region="rect")
    rect_mask = torch.zeros(80, 96, dtype=torch.bool)
    rect_mask[y0:y1, x0:x1] = True
    torch.testing.assert_close(rect.psnr, psnr(pred, target, rect_mask).double(), rtol=0, atol=1e-5)


def test_bbox_metrics_ignore_pixels_outside_the_box():
    pred, target, corners, K, R, t, _ = _scene()
    m1 = masked_bbox_metrics(pred, target, corners, K, R, t)
    x0, y0, x1, y1 = m1.rects[0].tolist()
    outside = torch.ones(80, 96, dtype=torch.bool)
    outside[y0:y1, x0:x1] = False
    pred2 = pred.clone()
    pred2[..., outside] = 0.0
    m2 = masked_bbox_metrics(pred2, target, corners, K, R, t)
    torch.testing.assert_close(m1.psnr, m2.psnr)
    torch.testing.assert_close(m1.ssim, m2.ssim)


def test_bbox_metrics_per_image_cameras_and_invisible_box():
    pred, target, corners, K, R, t, _ = _scene()
    turn = Rotation.from_euler("y", 180, degrees=True).as_matrix()  # same camera, turned around
    m = masked_bbox_metrics(
        pred,
        target,
        np.stack([corners, corners]),
        np.stack([K, K]),
        np.stack([R, turn @ R]),
        np.stack([t, turn @ t]),
    )
    assert m.valid.tolist() == [True, False]
    assert (
        math.isfinite(m.psnr[0].item())
        and math.isnan(m.psnr[1].item())
        and math.isnan(m.ssim[1].item())
    )
    with pytest.raises(ValueError, match="K has shape"):
        masked_bbox_metrics(pred, target, corners, np.eye(4), R, t)


def test_bbox_metrics_with_lpips():
    path = default_weights_path("alex")
    if not path.is_file():
        pytest.skip(
            f"LPIPS weights not cached at {path}; run `python -m gst.metrics.lpips fetch --net "
            "alex`"
        )
    from gst.metrics.lpips import LPIPS

    model = LPIPS("alex")
    pred, target, corners, K, R, t, _ = _scene()
    m = masked_bbox_metrics(pred, target, corners, K, R, t, lpips=model)
    x0, y0, x1, y1 = m.rects[0].tolist()
    expected = model(pred[..., y0:y1, x0:x1], target[..., y0:y1, x0:x1])
    torch.testing.assert_close(m.lpips, expected.double(), rtol=0, atol=1e-6)
    same = masked_bbox_metrics(target, target, corners, K, R, t, lpips=model)
    assert same.lpips.abs().max() < 1e-6 and (same.psnr == math.inf).all()


def test_ssim_takes_an_integer_data_range():
    """`data_range=255` as psnr takes it (kornia refused an int max_val: TypeError)."""
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 3, 16, 16, generator=g) * 255
    y = (x + torch.randn(2, 3, 16, 16, generator=g) * 5).clamp(0, 255)
    torch.testing.assert_close(
        ssim(x, y, data_range=255), ssim(x / 255, y / 255), atol=1e-5, rtol=0
    )


def test_8bit_images_need_their_data_range():
    """uint8 images with the default data_range=1 scored silently wrong (PSNR about -22 dB for
    a 26 dB pair, SSIM above 1 on flat images); with data_range=255 they score as floats do."""
    x, y = _images(h=32, w=32)
    x8, y8 = (x * 255).round().byte(), (y * 255).round().byte()
    for fn in (psnr, ssim):
        with pytest.raises(ValueError, match=r"pred is torch.uint8.*data_range=255"):
            fn(x8, y8)
        with pytest.raises(ValueError, match="target is torch.uint8"):
            fn(x8.double() / 255, y8)
        torch.testing.assert_close(
            fn(x8, y8, data_range=255).double(),
            fn(x8 / 255.0, y8 / 255.0).double(),
            atol=1e-4,
            rtol=0,
        )
    with pytest.raises(ValueError, match="pred is torch.uint8"):
        masked_bbox_metrics(x8, y8, np.zeros((8, 3)), np.eye(3), np.eye(3), np.zeros(3))


def test_silhouette_iou_leaves_the_ignored_pixels_out():
    from gst.metrics.image import silhouette_iou

    alpha = torch.zeros(1, 4, 4)
    alpha[0, :, :3] = 1  # 12 pixels drawn
    mask = torch.zeros(1, 4, 4)
    mask[0, :, :2] = 1  # 8 seen: column 2 is behind someone else
    ignore = torch.zeros(1, 4, 4)
    ignore[0, :, 2:] = 1
    assert float(silhouette_iou(alpha, mask)) == pytest.approx(8 / 12)
    assert float(silhouette_iou(alpha, mask, ignore=ignore)) == pytest.approx(1.0)
