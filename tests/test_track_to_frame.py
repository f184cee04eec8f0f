"""The person model reads a resized frame; its landmarks come back in the full frame's pixels
by the resize's own ratio per axis (gst.track.person_detector.to_frame). Reference: OpenCV's
own resize, on a blob whose true position is known."""

import cv2
import numpy as np
import pytest

from gst.track.person_detector import to_frame
from tests.real_capture import NEEDS_MODELS


def _blob(h: int, w: int, x: float, y: float, sigma: float = 6.0) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w]
    return np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * sigma**2)).astype(np.float32)


def _centroid(img: np.ndarray) -> tuple[float, float]:
    yy, xx = np.mgrid[0 : img.shape[0], 0 : img.shape[1]]
    m = img.sum()
    return float((img * xx).sum() / m), float((img * yy).sum() / m)


@pytest.mark.parametrize("w,h", [(2704, 1520), (4096, 2160), (1366, 768), (1920, 1080)])
def test_a_point_read_on_the_resized_frame_comes_back_where_it_is(w, h):
    """At 2704x1520 and 4096x2160 the rounded resize differs from the requested scale: mapped
    back by that scale, a point near the far corner landed a pixel off."""
    s = min(1.0, 640 / max(h, w))  # the detector's max_side
    small_wh = (round(w * s), round(h * s))
    x, y = w - 60.3, h - 60.7  # near the far corner, where the error is largest
    small = cv2.resize(_blob(h, w, x, y, sigma=8.0), small_wh, interpolation=cv2.INTER_AREA)
    u, v = _centroid(small)
    lm, box = to_frame(
        np.array([[u, v, 1.0]], np.float32),
        np.array([u - 5, v - 5, u + 5, v + 5]),
        small.shape[:2],
        (h, w),
    )
    assert lm[0, 0] == pytest.approx(x, abs=0.1) and lm[0, 1] == pytest.approx(y, abs=0.1)
    assert lm.dtype == np.float32 and lm[0, 2] == 1.0  # the rest of the landmark kept
    assert (box[:2] < [x, y]).all() and (box[2:] > [x, y]).all()
    assert (box >= 0).all() and box[2] <= w and box[3] <= h


@NEEDS_MODELS
@pytest.mark.parametrize("shape", [(1, 200, 3), (200, 1, 3)])
def test_a_strip_frame_is_resized_to_at_least_a_pixel(shape):
    """A frame one pixel thin and longer than `max_side` was resized to 0 pixels across, and
    OpenCV's resize failed ("inv_scale_x > 0"). (The smallest work size keeps it quick: at
    the default 960 px a 2000-px strip took 14 s of detector windows.)"""
    from gst.track.person_detector import PersonModelConfig, PersonModelDetector

    detector = PersonModelDetector(PersonModelConfig(max_side=64))
    assert detector.detect(np.full(shape, 100, np.uint8), 0) == []
