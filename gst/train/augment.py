"""Crop augmentation for supervised training: box jitter (zoom and shift) and colour jitter.

Extraction's boxes are never the truth boxes the pretraining crops are cut with, and a network
that only ever saw one framing and one set of outfits memorises its world instead of learning
pose (a tiny model pretrained on 360 poses scored 87 mm on them and 304 mm on a fresh world).

The zoom/shift is an exact re-crop: warping the crop image by the similarity A (crop px ->
new crop px) is the same camera with intrinsics A @ K, so 3D truth is unchanged, 2D truth maps
by A, and the predicted translation stays metric. Random numbers come from the caller's
generator, so a resumed run draws the same augmentations.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from kornia.enhance import adjust_brightness, adjust_contrast, adjust_saturation
from kornia.geometry.transform import warp_affine

from gst.train.steps import SupervisedBatch


@dataclass(frozen=True)
class CropJitter:
    """Ranges of the random re-crop and colour change (0 turns a part off)."""

    zoom: float = 0.15  # log-uniform zoom in [exp(-zoom), exp(zoom)] about the crop centre
    shift: float = 0.08  # uniform shift of the content, as a fraction of the crop size
    brightness: float = 0.15  # added, in [0, 1] image units
    contrast: float = 0.25  # multiplied around the mean, factor in [1 - c, 1 + c]
    saturation: float = 0.3  # factor in [1 - s, 1 + s]

    def __post_init__(self):
        for name in ("zoom", "shift", "brightness", "contrast", "saturation"):
            value = getattr(self, name)
            if not 0 <= value < 1:
                raise ValueError(f"CropJitter.{name} must be in [0, 1), got {value}")


def similarity(zoom: torch.Tensor, shift: torch.Tensor, size: int) -> torch.Tensor:
    """(B, 3, 3) maps old crop pixels to new ones: zoom about the crop centre, then shift (px).
    Pixel centres at integers (OpenCV), so the centre is (size - 1) / 2."""
    c = (size - 1) / 2
    A = torch.zeros(zoom.shape[0], 3, 3, dtype=zoom.dtype)
    A[:, 0, 0] = A[:, 1, 1] = zoom
    A[:, :2, 2] = c - zoom[:, None] * c + shift
    A[:, 2, 2] = 1
    return A


def warp_crops(images: torch.Tensor, A: torch.Tensor) -> torch.Tensor:
    """Warp (B, S, S, 3) uint8 crops by A (old px -> new px); outside is black, like crop
    padding."""
    size = images.shape[1]
    x = images.permute(0, 3, 1, 2).float()
    out = warp_affine(
        x, A[:, :2].to(x), (size, size), mode="bilinear", padding_mode="zeros", align_corners=True
    )
    return out.round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).contiguous()


def jitter_batch(
    batch: SupervisedBatch, jitter: CropJitter, gen: torch.Generator
) -> SupervisedBatch:
    """A re-cropped, recoloured copy of `batch` with K and 2D truth moved to match."""
    b, size = batch.images.shape[0], batch.images.shape[1]

    def uniform(lo: float, hi: float, n: int = b) -> torch.Tensor:
        return lo + (hi - lo) * torch.rand(n, generator=gen)

    zoom = torch.exp(uniform(-jitter.zoom, jitter.zoom)).double()
    shift = (uniform(-jitter.shift, jitter.shift, 2 * b).reshape(b, 2) * size).double()
    A = similarity(zoom, shift, size)
    images = warp_crops(batch.images, A)
    colour = [
        uniform(-jitter.brightness, jitter.brightness),
        uniform(1 - jitter.contrast, 1 + jitter.contrast),
        uniform(1 - jitter.saturation, 1 + jitter.saturation),
    ]
    x = images.permute(0, 3, 1, 2).float() / 255
    x = adjust_brightness(x, colour[0])
    x = adjust_contrast(x, colour[1])
    x = adjust_saturation(x, colour[2])
    images = (x * 255).round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).contiguous()
    K = (A @ batch.K.double()).to(batch.K.dtype)
    joints2d = batch.joints2d
    if joints2d is not None:
        joints2d = (joints2d.double() * zoom[:, None, None] + A[:, None, :2, 2]).to(joints2d.dtype)
    visible = batch.visible
    if visible is not None and joints2d is not None:
        inside = ((joints2d >= -0.5) & (joints2d <= size - 0.5)).all(-1)
        visible = visible * inside.to(visible.dtype)  # joints pushed off the crop are not seen
    landmarks = batch.landmarks
    if landmarks is not None:  # detections move with the pixels (NaN stays NaN)
        landmarks = landmarks.clone()
        uv = landmarks[..., :2].double() * zoom[:, None, None] + A[:, None, :2, 2]
        landmarks[..., :2] = uv.to(landmarks.dtype)
    return replace(
        batch, images=images, K=K, joints2d=joints2d, visible=visible, landmarks=landmarks
    )
