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


def to_float_images(crops: np.ndarray | torch.Tensor) -> torch.Tensor:
    """(B, S, S, 3) uint8 or float in [0, 1] -> (B, 3, S, S) float32 in [0, 1]."""
    x = torch.as_tensor(check_crops(crops))
    # Convert in the stored (channels-last) layout, then permute as a view: converting through
    # the permuted strides was ~10x slower on CPU.
    x = x.to(torch.float32).div_(255.0) if x.dtype == torch.uint8 else x.float()
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
