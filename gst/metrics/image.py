"""Image metrics for novel-view evaluation: PSNR, SSIM, and SHERF-style metrics inside the
body's box.

Images are float tensors (B, C, H, W) with values in [0, data_range] (default [0, 1]).
All metrics return one value per image, shape (B,), so callers can break results down per
camera, frame or motion before averaging.

SHERF / Neural Body protocol (`masked_bbox_metrics`): the body's 3D bounding box (from its
vertices, padded by 5 cm) is projected into the evaluated camera. PSNR is taken over the pixels
inside the projected box (its six faces filled, as Neural Body's `get_bound_2d_mask` does, or the
axis-aligned 2D box); SSIM and LPIPS are taken on the crop to the 2D bounding rectangle.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import kornia
import numpy as np
import torch

__all__ = [
    "BoxMetrics",
    "BoxRegion",
    "box_corners",
    "masked_bbox_metrics",
    "points_box_corners",
    "project_box_region",
    "psnr",
    "silhouette_iou",
    "ssim",
]


def _check_pair(pred: torch.Tensor, target: torch.Tensor, fn: str, data_range: float = 1.0) -> None:
    if pred.ndim != 4:
        raise ValueError(f"{fn}: pred has shape {tuple(pred.shape)}, expected (B, C, H, W)")
    if pred.shape != target.shape:
        raise ValueError(
            f"{fn}: pred {tuple(pred.shape)} and target {tuple(target.shape)} must have the same "
            "shape"
        )
    # 8-bit images (0..255) with the default range 1 scored silently wrong: PSNR -22 dB for a
    # 26 dB pair, SSIM 1.29 for two flat images
    for name, t in (("pred", pred), ("target", target)):
        if not t.is_floating_point() and t.dtype != torch.bool and data_range <= 1:
            raise ValueError(
                f"{fn}: {name} is {t.dtype} with data_range={data_range}; integer images need "
                "their range (data_range=255 for 8-bit) or conversion to floats in [0, 1]"
            )


def psnr(
    pred: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor | None = None,
    data_range: float = 1.0,
) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB per image, (B,).

    `mask` (B, 1, H, W), (B, H, W) or (H, W), boolean or float weights, restricts the mean squared
    error to the pixels it covers (all channels). Identical images give +inf; an image whose mask
    is empty gives NaN (there is nothing to measure). Differentiable; the reduction runs in float64.
    """
    _check_pair(pred, target, "psnr", data_range)
    err = (pred.double() - target.double()) ** 2
    if mask is None:
        mse = err.mean(dim=(1, 2, 3))
    else:
        b, c, h, w = pred.shape
        m = mask.double()
        if m.shape == (h, w):
            m = m.expand(b, 1, h, w)
        elif m.shape == (b, h, w):
            m = m.unsqueeze(1)
        if m.shape != (b, 1, h, w):
            raise ValueError(
                f"psnr: mask has shape {tuple(mask.shape)}, expected ({b}, 1, {h}, {w}), "
                f"({b}, {h}, {w}) or ({h}, {w})"
            )
        mse = (err * m).sum(dim=(1, 2, 3)) / (
            m.sum(dim=(1, 2, 3)) * c
        )  # 0/0 -> NaN for empty masks
    return (10.0 * torch.log10(data_range**2 / mse)).to(
        pred.dtype if pred.is_floating_point() else torch.float32
    )


SSIM_WINDOW = 11  # px: the Gaussian window of SSIM (Wang et al. 2004)


def ssim(
    pred: torch.Tensor,
    target: torch.Tensor,
    window_size: int = SSIM_WINDOW,
    data_range: float = 1.0,
    padding: Literal["same", "valid"] = "same",
) -> torch.Tensor:
    """Mean SSIM per image, (B,), from `kornia.metrics.ssim`.

    Gaussian window, sigma 1.5, K1 0.01, K2 0.03. `padding="same"` (default, kornia's)
    reflect-pads the borders and averages over every pixel, as torchmetrics does (agrees to
    2e-7); `"valid"` averages only where the window fits, the MATLAB / scikit-image
    (gaussian_weights=True) convention. H and W must be at least `window_size`.
    """
    _check_pair(pred, target, "ssim", data_range)
    if min(pred.shape[-2:]) < window_size:
        raise ValueError(
            f"ssim: images of {tuple(pred.shape[-2:])} px are smaller than the {window_size} px "
            "window"
        )
    smap = kornia.metrics.ssim(
        pred, target, window_size, max_val=float(data_range), eps=0.0, padding=padding
    )
    return smap.mean(dim=(1, 2, 3))


# --- the body's box, projected -------------------------------------------------------------------

# Corner order: bit 0 -> x, bit 1 -> y, bit 2 -> z (0 = min, 1 = max).
_CORNER_BITS = np.array([[(i >> 0) & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)])
_FACES = ((0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5))


def silhouette_iou(
    alpha: torch.Tensor,
    mask: torch.Tensor,
    threshold: float = 0.5,
    ignore: torch.Tensor | None = None,
) -> torch.Tensor:
    """(B, H, W) rendered alpha and target mask -> (B,) IoU of the two silhouettes, each
    thresholded at `threshold` (0 where both are empty). `ignore` (B, H, W): pixels above
    `threshold` there count for neither (e.g. another person in front: what is behind is not
    known)."""
    a, m = alpha > threshold, mask > threshold
    if ignore is not None:
        keep = ignore <= threshold
        a, m = a & keep, m & keep
    inter = (a & m).flatten(1).sum(1).float()
    return inter / (a | m).flatten(1).sum(1).float().clamp_min(1)


def box_corners(min_xyz: np.ndarray, max_xyz: np.ndarray) -> np.ndarray:
    """The 8 corners (8, 3) of an axis-aligned box.

    Corner i takes the max on axis k when bit k of i is set.
    """
    lo, hi = np.asarray(min_xyz, dtype=np.float64), np.asarray(max_xyz, dtype=np.float64)
    if lo.shape != (3,) or hi.shape != (3,) or np.any(hi < lo):
        raise ValueError(f"box_corners: expected min_xyz <= max_xyz, both (3,), got {lo} and {hi}")
    return np.where(_CORNER_BITS == 1, hi, lo)


def points_box_corners(points: np.ndarray, margin: float = 0.05) -> np.ndarray:
    """Corners (8, 3) of the axis-aligned box around `points` (N, 3), padded by `margin`
    (SHERF: 0.05 m)."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise ValueError(f"points_box_corners: points has shape {pts.shape}, expected (N>0, 3)")
    if not np.isfinite(pts).all():
        raise ValueError("points_box_corners: points contain NaN or Inf")
    return box_corners(pts.min(0) - margin, pts.max(0) + margin)


@dataclass(frozen=True)
class BoxRegion:
    """Where a 3D box lands in an image: `mask` (H, W) bool of the filled faces and its bounding
    `rect` (x0, y0, x1, y1), end-exclusive, clipped to the image. Empty when nothing is visible."""

    mask: np.ndarray
    rect: tuple[int, int, int, int]

    @property
    def empty(self) -> bool:
        return self.rect[2] <= self.rect[0] or self.rect[3] <= self.rect[1]


def _clip_polygon_near(poly: np.ndarray, near: float) -> np.ndarray:
    """Sutherland-Hodgman clip of a camera-space polygon (N, 3) to z >= near."""
    out = []
    for a, b in zip(poly, np.roll(poly, -1, axis=0), strict=True):
        a_in, b_in = a[2] >= near, b[2] >= near
        if a_in:
            out.append(a)
        if a_in != b_in:
            s = (near - a[2]) / (b[2] - a[2])
            out.append(a + s * (b - a))
    return np.array(out).reshape(-1, 3)


def project_box_region(
    corners: np.ndarray,
    K: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    image_size: tuple[int, int],
    near: float = 1e-3,
) -> BoxRegion:
    """Project a 3D box (8 corners, ordered as `box_corners`) into a pinhole camera.

    K (3, 3); R (3, 3) and t (3,) map world to camera (x_cam = R x + t). image_size is (W, H).
    Faces crossing the camera plane are clipped at z = near first, so a box partly behind the
    camera still gives the right visible region. Lens distortion is not modelled: evaluate on
    undistorted images.
    """
    corners = np.asarray(corners, dtype=np.float64)
    K, R = np.asarray(K, dtype=np.float64), np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    for name, arr, shape in (
        ("corners", corners, (8, 3)),
        ("K", K, (3, 3)),
        ("R", R, (3, 3)),
        ("t", t, (3,)),
    ):
        if arr.shape != shape:
            raise ValueError(f"project_box_region: {name} has shape {arr.shape}, expected {shape}")
    w, h = (int(v) for v in image_size)
    if w <= 0 or h <= 0:
        raise ValueError(
            f"project_box_region: image_size must be positive (W, H), got {image_size}"
        )
    cam = corners @ R.T + t
    mask = np.zeros((h, w), dtype=np.uint8)
    polys = []
    for face in _FACES:
        poly = _clip_polygon_near(cam[list(face)], near)
        if len(poly) < 3:
            continue
        uv = (poly @ K.T)[:, :2] / poly[:, 2:3]
        # Points just in front of the camera project very far away; OpenCV clips lines itself,
        # the bound only keeps coordinates inside int32 with the 8-bit subpixel shift.
        polys.append(np.round(np.clip(uv, -2e6, 2e6) * 256).astype(np.int32))
    for poly in polys:  # one call per face: a single call would XOR where faces overlap
        cv2.fillPoly(mask, [poly], 1, lineType=cv2.LINE_8, shift=8)
    x, y, bw, bh = cv2.boundingRect(mask)
    return BoxRegion(mask=mask.astype(bool), rect=(x, y, x + bw, y + bh))


@dataclass
class BoxMetrics:
    """Per-image results of `masked_bbox_metrics`, each (B,). `valid` is False where the box is not
    visible (its metrics are NaN). `lpips` is None when no LPIPS model was given, and NaN where the
    crop is smaller than LPIPS accepts. `rects` (B, 4) holds x0, y0, x1, y1 (end-exclusive)."""

    psnr: torch.Tensor
    ssim: torch.Tensor
    lpips: torch.Tensor | None
    valid: torch.Tensor
    rects: torch.Tensor


def _per_image(
    arr: np.ndarray | torch.Tensor, b: int, shape: tuple[int, ...], name: str
) -> np.ndarray:
    a = arr.detach().cpu().numpy() if isinstance(arr, torch.Tensor) else np.asarray(arr)
    a = a.astype(np.float64)
    if a.shape == shape:
        return np.broadcast_to(a, (b, *shape))
    if a.shape == (b, *shape):
        return a
    if name == "t" and a.shape in ((3, 1), (b, 3, 1)):
        return _per_image(a[..., 0], b, shape, name)
    raise ValueError(
        f"masked_bbox_metrics: {name} has shape {a.shape}, expected {shape} or ({b}, "
        f"{', '.join(map(str, shape))})"
    )


def masked_bbox_metrics(
    pred: torch.Tensor,
    target: torch.Tensor,
    corners: np.ndarray | torch.Tensor,
    K: np.ndarray | torch.Tensor,
    R: np.ndarray | torch.Tensor,
    t: np.ndarray | torch.Tensor,
    lpips: torch.nn.Module | None = None,
    region: Literal["faces", "rect"] = "faces",
    window_size: int = SSIM_WINDOW,
    data_range: float = 1.0,
) -> BoxMetrics:
    """SHERF-style PSNR / SSIM / LPIPS inside the projected 3D body box.

    pred, target: (B, 3, H, W) in [0, data_range]. corners: (8, 3) or (B, 8, 3) world points, as
    from `points_box_corners(vertices)`. K, R, t: one camera or one per image (world to camera).
    region="faces" measures PSNR over the filled projected box (Neural Body / SHERF); "rect" over
    its 2D bounding rectangle. SSIM (window `window_size`) and LPIPS use the rectangle crop; they
    are NaN for a crop smaller than the SSIM window or than LPIPS's minimum size.
    """
    _check_pair(pred, target, "masked_bbox_metrics", data_range)
    if region not in ("faces", "rect"):
        raise ValueError(f"masked_bbox_metrics: region must be 'faces' or 'rect', got {region!r}")
    b, _, h, w = pred.shape
    corners_b = _per_image(corners, b, (8, 3), "corners")
    K_b, R_b, t_b = (
        _per_image(K, b, (3, 3), "K"),
        _per_image(R, b, (3, 3), "R"),
        _per_image(t, b, (3,), "t"),
    )

    nan = float("nan")
    out_psnr, out_ssim, out_lpips, valid, rects = [], [], [], [], []
    for i in range(b):
        reg = project_box_region(corners_b[i], K_b[i], R_b[i], t_b[i], (w, h))
        x0, y0, x1, y1 = reg.rect
        rects.append(reg.rect)
        valid.append(not reg.empty)
        if reg.empty:
            out_psnr.append(nan), out_ssim.append(nan), out_lpips.append(nan)
            continue
        if region == "faces":
            mask = torch.from_numpy(reg.mask).to(pred.device)
        else:
            mask = torch.zeros((h, w), dtype=torch.bool, device=pred.device)
            mask[y0:y1, x0:x1] = True
        p, g = pred[i : i + 1], target[i : i + 1]
        out_psnr.append(psnr(p, g, mask, data_range).item())
        pc, gc = p[..., y0:y1, x0:x1], g[..., y0:y1, x0:x1]
        if min(y1 - y0, x1 - x0) < window_size:
            out_ssim.append(nan)
        else:
            out_ssim.append(ssim(pc, gc, window_size, data_range).item())
        if lpips is not None:
            min_size = getattr(getattr(lpips, "spec", None), "min_size", 1)
            if min(y1 - y0, x1 - x0) < min_size:
                out_lpips.append(nan)
            else:
                with torch.no_grad():
                    out_lpips.append(lpips(pc / data_range, gc / data_range).item())
    dev = pred.device
    return BoxMetrics(
        psnr=torch.tensor(out_psnr, dtype=torch.float64, device=dev),
        ssim=torch.tensor(out_ssim, dtype=torch.float64, device=dev),
        lpips=torch.tensor(out_lpips, dtype=torch.float64, device=dev)
        if lpips is not None
        else None,
        valid=torch.tensor(valid, dtype=torch.bool, device=dev),
        rects=torch.tensor(rects, dtype=torch.long, device=dev).reshape(b, 4),
    )
