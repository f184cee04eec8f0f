"""A cheap appearance descriptor for re-identifying people between frames: a hue-saturation
histogram of the torso-and-legs core of the box (the border of a box is mostly background),
restricted to the person's mask when one is given. Compared with the Hellinger distance."""

from __future__ import annotations

import cv2
import numpy as np

HUE_BINS, SAT_BINS = 16, 8
DESCRIPTOR_SIZE = HUE_BINS * SAT_BINS


def core_region(
    size: int, box_in_crop: np.ndarray, shrink_x: float = 0.25, shrink_y: float = 0.1
) -> tuple[slice, slice]:
    """(rows, cols) slices of the crop covering the box shrunk by `shrink_x`/`shrink_y` of its
    width/height on each side, clipped to the crop."""
    x0, y0, x1, y1 = box_in_crop
    w, h = x1 - x0, y1 - y0
    c0, c1 = int(round(x0 + shrink_x * w)), int(round(x1 - shrink_x * w))
    r0, r1 = int(round(y0 + shrink_y * h)), int(round(y1 - shrink_y * h))
    clip = lambda v: min(max(v, 0), size)  # noqa: E731
    return slice(clip(r0), max(clip(r1), clip(r0))), slice(clip(c0), max(clip(c1), clip(c0)))


def colour_histogram(crop_rgb: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """(HUE_BINS * SAT_BINS,) float64 histogram summing to 1 (uniform when nothing is selected)."""
    if crop_rgb.size == 0:
        return np.full(DESCRIPTOR_SIZE, 1.0 / DESCRIPTOR_SIZE)
    hsv = cv2.cvtColor(np.ascontiguousarray(crop_rgb), cv2.COLOR_RGB2HSV)
    mask = None if mask is None else np.ascontiguousarray(mask, dtype=np.uint8)
    hist = (
        cv2.calcHist([hsv], [0, 1], mask, [HUE_BINS, SAT_BINS], [0, 180, 0, 256])
        .ravel()
        .astype(np.float64)
    )
    total = hist.sum()
    return hist / total if total > 0 else np.full(DESCRIPTOR_SIZE, 1.0 / DESCRIPTOR_SIZE)


def hellinger(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hellinger distance in [0, 1] between histograms (..., D) that sum to 1; broadcasts."""
    bc = np.sum(np.sqrt(np.asarray(p)[..., :] * np.asarray(q)), axis=-1)
    return np.sqrt(np.clip(1.0 - bc, 0.0, 1.0))
