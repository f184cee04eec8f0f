"""From a raw foreground mask to clean, labelled person blobs.

Morphology removes speckle and closes seams, small holes (a shirt the colour of the wall) are
filled, and connected components that are too small or implausibly shaped are dropped. Sizes
are fractions of the image so one setting works at any resolution.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class MaskConfig:
    """Clean-up of foreground masks. Lengths are fractions of the image height, areas of its
    area."""

    open_radius: float = 0.002  # removes speckle
    close_radius: float = 0.004  # bridges thin seams inside a silhouette
    max_hole_area: float = 0.003  # holes smaller than this are filled
    min_area: float = 0.0015  # smaller components are noise
    min_fill: float = 0.08  # component area / its box area
    max_aspect: float = 12.0  # max(box w/h, h/w)
    max_blobs: int = 254  # labels are stored as uint8

    def __post_init__(self):
        for name in ("open_radius", "close_radius", "max_hole_area", "min_area", "min_fill"):
            if getattr(self, name) < 0:
                raise ValueError(f"mask config {name} must be >= 0, got {getattr(self, name)}")
        if not 1 <= self.max_blobs <= 254:
            raise ValueError(f"max_blobs must be in [1, 254], got {self.max_blobs}")


@dataclass(frozen=True)
class Blob:
    """One connected foreground component of a labelled mask (work-resolution pixels)."""

    label: int
    area: int
    box: tuple[int, int, int, int]  # x, y, w, h of the pixel bounding box
    centroid: tuple[float, float]


def _disk(radius_px: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius_px + 1, 2 * radius_px + 1))


def fill_small_holes(mask: np.ndarray, max_area_px: int) -> np.ndarray:
    """Fill background regions enclosed by foreground that are smaller than `max_area_px`."""
    h, w = mask.shape
    # Background reachable from the border is not a hole: flood it from a padded frame.
    padded = np.zeros((h + 2, w + 2), np.uint8)
    padded[1:-1, 1:-1] = mask
    cv2.floodFill(padded, None, (0, 0), 2)
    holes = padded[1:-1, 1:-1] == 0
    if not holes.any():
        return mask
    ys, xs = np.nonzero(holes)
    y0, x0 = ys.min(), xs.min()
    roi = holes[y0 : ys.max() + 1, x0 : xs.max() + 1]
    n, labels, stats, _ = cv2.connectedComponentsWithStats(roi.astype(np.uint8), connectivity=4)
    small = stats[:, cv2.CC_STAT_AREA] <= max_area_px
    small[0] = False
    out = mask.copy()
    out[y0 : ys.max() + 1, x0 : xs.max() + 1] |= small[labels]
    return out


def clean_mask(raw: np.ndarray, config: MaskConfig = MaskConfig()) -> tuple[np.ndarray, list[Blob]]:
    """Clean a boolean foreground mask and label its plausible components.

    Returns a uint8 label image (0 = background, 1..n = blobs, largest first) and the blobs.
    """
    h, w = raw.shape
    mask = raw.astype(np.uint8)
    r_open = int(round(config.open_radius * h))
    r_close = int(round(config.close_radius * h))
    if r_open > 0:
        mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, _disk(r_open))
    if r_close > 0:
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, _disk(r_close))
    filled = fill_small_holes(mask.astype(bool), int(config.max_hole_area * h * w))
    n, labels, stats, cents = cv2.connectedComponentsWithStats(
        filled.astype(np.uint8), connectivity=8
    )
    keep = []
    for i in range(1, n):
        x, y, bw, bh, area = (int(v) for v in stats[i])
        if area < config.min_area * h * w:
            continue
        if area < config.min_fill * bw * bh:
            continue
        if max(bw / bh, bh / bw) > config.max_aspect:
            continue
        keep.append((area, i, (x, y, bw, bh), (float(cents[i][0]), float(cents[i][1]))))
    keep.sort(key=lambda k: -k[0])
    keep = keep[: config.max_blobs]
    lut = np.zeros(n, dtype=np.uint8)
    blobs = []
    for new, (area, old, box, cen) in enumerate(keep, start=1):
        lut[old] = new
        blobs.append(Blob(new, area, box, cen))
    return lut[labels], blobs
