"""Box overlap and painting out for the detectors and trackers, numpy and OpenCV only: the
person model's workers import it without torch."""

from __future__ import annotations

import cv2
import numpy as np


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, 4) x (M, 4) corner-convention boxes -> (N, M) intersection over union."""
    a, b = (
        np.asarray(a, dtype=np.float64).reshape(-1, 4),
        np.asarray(b, dtype=np.float64).reshape(-1, 4),
    )
    iw = np.clip(
        np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0]), 0, None
    )
    ih = np.clip(
        np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1]), 0, None
    )
    inter = iw * ih
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    union = area_a[:, None] + area_b[None, :] - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)


def containment(inner: np.ndarray, outer: np.ndarray) -> float:
    """Share of the `inner` box's area inside the `outer` box (corner-convention boxes)."""
    iw = min(inner[2], outer[2]) - max(inner[0], outer[0])
    ih = min(inner[3], outer[3]) - max(inner[1], outer[1])
    area = (inner[2] - inner[0]) * (inner[3] - inner[1])
    return float(max(iw, 0) * max(ih, 0) / area) if area > 0 else 0.0


def paint_out(image: np.ndarray, boxes, grow: float = 0.1) -> np.ndarray:
    """A copy of `image` with each corner-convention box (grown by `grow` of its size on every
    side) filled with the image's mean colour: the people in them hidden from a detector that
    finds few people per call (BlazePose's), so that it looks at the others."""
    out = image.copy()
    fill = mean_colour(image)
    for x0, y0, x1, y1 in boxes:
        gx, gy = grow * (x1 - x0), grow * (y1 - y0)
        window = pixel_window((x0 - gx, y0 - gy, x1 + gx, y1 + gy), image.shape[:2])
        if window is not None:
            out[window] = fill
    return out


def pixel_window(box, shape: tuple[int, int]) -> tuple[slice, slice] | None:
    """The (rows, columns) slices of the pixels that a corner-convention box touches (edges
    rounded outwards), clipped to an image of `shape` (h, w); None when none lie inside. Both
    ends are clipped: a box wholly above or left of the image has a negative far edge, which as
    a slice counts back from the other side (it painted nearly the whole frame)."""
    h, w = shape
    x0, y0, x1, y1 = box
    a, b = (int(np.clip(v, 0, w)) for v in (np.floor(x0), np.ceil(x1)))
    c, d = (int(np.clip(v, 0, h)) for v in (np.floor(y0), np.ceil(y1)))
    return (slice(c, d), slice(a, b)) if b > a and d > c else None


def mean_colour(image: np.ndarray) -> np.ndarray:
    """The (C,) mean colour of an (H, W, C) image, C <= 4 (OpenCV's: 50x quicker than numpy's
    strided mean on a 544 x 960 frame; equal to it within 1e-12); an (H, W) grey image's is
    (1,) (its last axis is its width: it took 4 values)."""
    return np.asarray(cv2.mean(image)[: 1 if image.ndim == 2 else image.shape[-1]])


def fill_where(image: np.ndarray, mask: np.ndarray, colour: np.ndarray) -> np.ndarray:
    """A copy of an (H, W, C) image with the (H, W) bool `mask` filled with `colour` (cast as
    numpy casts it into the image's type)."""
    out = image.copy()
    cv2.copyTo(np.full_like(image, colour), mask.view(np.uint8), out)
    return out


def shared(a: np.ndarray, b: np.ndarray) -> float:
    """How much two corner-convention boxes share: their intersection over the smaller one's
    area (1 when one lies inside the other)."""
    return max(containment(a, b), containment(b, a))
