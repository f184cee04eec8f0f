"""A cheap appearance descriptor for re-identifying people between frames: a hue-saturation
histogram of the torso-and-legs core of the box (the border of a box is mostly background),
restricted to the person's mask when one is given. Compared with the Hellinger distance."""

from __future__ import annotations

import cv2
import numpy as np

HUE_BINS, SAT_BINS = 16, 8
DESCRIPTOR_SIZE = HUE_BINS * SAT_BINS
APPEARANCE_SAMPLES = 96  # pixels read along the longer side of a box (`box_histogram`)


def core_region(
    shape: tuple[int, int], box: np.ndarray, shrink_x: float = 0.25, shrink_y: float = 0.1
) -> tuple[slice, slice]:
    """(rows, cols) slices of an image of `shape` (height, width) covering `box` (x0, y0, x1,
    y1) shrunk by `shrink_x`/`shrink_y` of its width/height on each side, clipped to the image."""
    x0, y0, x1, y1 = np.asarray(box, np.float64)
    w, h = x1 - x0, y1 - y0
    c0, c1 = int(round(x0 + shrink_x * w)), int(round(x1 - shrink_x * w))
    r0, r1 = int(round(y0 + shrink_y * h)), int(round(y1 - shrink_y * h))
    rows, cols = shape[:2]
    clip = lambda v, n: min(max(v, 0), n)  # noqa: E731
    r0, r1, c0, c1 = clip(r0, rows), clip(r1, rows), clip(c0, cols), clip(c1, cols)
    return slice(r0, max(r1, r0)), slice(c0, max(c1, c0))


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


def box_histogram(
    frame_bgr: np.ndarray,
    box: np.ndarray,
    mask: np.ndarray | None = None,
    samples: int = APPEARANCE_SAMPLES,
) -> np.ndarray:
    """`colour_histogram` of a detection straight from its (raw, BGR) frame: the core of `box`
    (x0, y0, x1, y1, raw-frame pixels; the whole box when a frame-sized person `mask` says which
    pixels are the person), read every few pixels so that its longer side gives about `samples`
    of them. No crop is cut: tracking's appearance needs colours, not an undistorted, anti-
    aliased image, and cutting one cost more than the landmark model on 1088 x 1920 footage."""
    shrink = (0.25, 0.1) if mask is None else (0.0, 0.0)
    rows, cols = core_region(frame_bgr.shape, box, *shrink)
    step = max(1, round(max(rows.stop - rows.start, cols.stop - cols.start) / max(samples, 1)))
    rows, cols = slice(rows.start, rows.stop, step), slice(cols.start, cols.stop, step)
    patch = frame_bgr[rows, cols, ::-1]  # RGB
    if mask is None:
        return colour_histogram(patch)
    return colour_histogram(patch, (np.asarray(mask)[rows, cols] > 0).astype(np.uint8))


def hellinger(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hellinger distance in [0, 1] between histograms (..., D) that sum to 1; broadcasts."""
    bc = np.sum(np.sqrt(np.asarray(p)[..., :] * np.asarray(q)), axis=-1)
    return np.sqrt(np.clip(1.0 - bc, 0.0, 1.0))
