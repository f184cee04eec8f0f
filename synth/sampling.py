"""Bilinear lookups of many scattered points in an image (cv2.remap in blocks)."""

from __future__ import annotations

import cv2
import numpy as np

_BLOCK = 1024  # cv2.remap needs map dimensions below 32767 (SHRT_MAX)
_ROWS = 32000  # so at most this many rows of blocks go to one call


def sample_image(
    image: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    border: int = cv2.BORDER_CONSTANT,
    value: float = 0.0,
) -> np.ndarray:
    """Bilinear samples of a single-channel image at pixel coords (x, y) (centres at integers)."""
    x = np.asarray(x, dtype=np.float32).ravel()
    y = np.asarray(y, dtype=np.float32).ravel()
    n = len(x)
    if n == 0:
        return np.zeros(0, dtype=np.float32)
    pad = (-n) % _BLOCK
    mx = np.pad(x, (0, pad)).reshape(-1, _BLOCK)
    my = np.pad(y, (0, pad)).reshape(-1, _BLOCK)
    # in slabs of rows: one call over more than 32766 rows (33.5 M points, the floor pixels of
    # a camera beyond 8K) failed OpenCV's assertion
    out = np.concatenate(
        [
            cv2.remap(
                image,
                mx[s : s + _ROWS],
                my[s : s + _ROWS],
                cv2.INTER_LINEAR,
                borderMode=border,
                borderValue=value,
            )
            for s in range(0, len(mx), _ROWS)
        ]
    )
    return out.ravel()[:n]
