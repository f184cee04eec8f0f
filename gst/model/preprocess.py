"""Crop images to network input: resize the square crop, keep the central strip, normalise.

HMR2 feeds a 256x192 (H x W) window cut from the centre of a 256x256 crop; presets with other
input sizes resize the square crop to H first. The crop's intrinsics stay those of the square
crop: the network only looks at its central columns.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

IMAGENET_MEAN = torch.tensor([0.485, 0.456, 0.406])
IMAGENET_STD = torch.tensor([0.229, 0.224, 0.225])


def check_crops(crops: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
    """`crops` itself, after checking that it is (B, S, S, 3): square RGB images."""
    shape = tuple(crops.shape)
    if len(shape) != 4 or shape[-1] != 3 or shape[1] != shape[2]:
        raise ValueError(f"crops must be (B, S, S, 3) square RGB images, got shape {shape}")
    return crops


def check_intrinsics(K: np.ndarray | torch.Tensor, n: int) -> None:
    """Raise unless `K` is (n, 3, 3) with finite entries and positive focal lengths: one
    matrix per crop (a single one would be broadcast silently to every crop)."""
    K = torch.as_tensor(K)
    if tuple(K.shape) != (n, 3, 3):
        raise ValueError(f"K_crop must be ({n}, 3, 3), one per crop; got shape {tuple(K.shape)}")
    bad = ~torch.isfinite(K).all((-1, -2)) | (K[:, 0, 0] <= 0) | (K[:, 1, 1] <= 0)
    if bool(bad.any()):
        rows = torch.nonzero(bad).flatten()[:5].tolist()
        raise ValueError(
            f"K_crop of crop(s) {rows} is not an intrinsic matrix (entries not numbers, or "
            f"fx / fy <= 0): {K[rows[0]].tolist()}"
        )


def to_float_images(crops: np.ndarray | torch.Tensor) -> torch.Tensor:
    """(B, S, S, 3) uint8 or float in [0, 1] -> (B, 3, S, S) float32 in [0, 1]."""
    crops = check_crops(crops)
    if isinstance(crops, np.ndarray) and any(s < 0 for s in crops.strides):
        crops = np.ascontiguousarray(crops)  # e.g. BGR -> RGB as [..., ::-1]: torch refuses
    x = torch.as_tensor(crops)
    # Convert in the stored (channels-last) layout, then permute as a view: converting through
    # the permuted strides was ~10x slower on CPU.
    if x.dtype == torch.uint8:
        x = x.to(torch.float32).div_(255.0)
    elif not x.dtype.is_floating_point:  # a bool mask or int16 image passed by mistake
        raise ValueError(
            f"crops must be uint8 (0-255) or float in [0, 1], got {str(x.dtype).split('.')[-1]}"
        )
    else:
        x = x.float()
        finite = torch.isfinite(x).flatten(1).all(1) if x.numel() else torch.ones(0, dtype=bool)
        if not bool(finite.all()):  # NaN > 1 is False: they were blamed on body_pose, later
            bad = torch.nonzero(~finite).flatten()[:8].tolist()
            raise ValueError(f"float crops hold NaN or Inf (crops {bad})")
        top = float(x.max()) if x.numel() else 0.0
        if top > 1.0 + 1e-3:
            raise ValueError(
                f"float crops must hold values in [0, 1], got a maximum of {top:.4g} "
                "(0-255 images: pass them as uint8)"
            )
        low = float(x.min()) if x.numel() else 0.0
        if low < -1e-3:  # [-1, 1] images were normalised a second time: joints 26 cm off
            raise ValueError(
                f"float crops must hold values in [0, 1], got a minimum of {low:.4g} "
                "(images scaled to [-1, 1]: map them back with (x + 1) / 2)"
            )
    return x.permute(0, 3, 1, 2)


def network_input(images: torch.Tensor, image_size: tuple[int, int]) -> torch.Tensor:
    """(B, 3, S, S) in [0, 1] -> (B, 3, H, W) ImageNet-normalised central strip."""
    h, w = image_size
    if images.shape[-1] != h:
        images = F.interpolate(
            images, size=(h, h), mode="bilinear", align_corners=False, antialias=True
        )
    x0 = (h - w) // 2
    strip = images[..., x0 : x0 + w]
    mean, std = IMAGENET_MEAN.to(images), IMAGENET_STD.to(images)
    return (strip - mean[:, None, None]) / std[:, None, None]
