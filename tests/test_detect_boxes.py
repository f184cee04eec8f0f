"""Box helpers of the detectors (gst.detect.boxes) that need no model: painting people out of a
frame for the person detector's second look, and the overlap of two boxes."""

import numpy as np
import pytest

from gst.detect.boxes import paint_out, shared


def test_paint_out_hides_only_the_grown_boxes():
    img = np.zeros((100, 200, 3), np.uint8)
    img[:, 100:] = 200
    out = paint_out(img, [np.array([20.0, 20.0, 40.0, 60.0])], grow=0.1)
    # grown by 2 px across and 4 px down: columns 18-41, rows 16-63, in the image's mean colour
    assert (out[16:64, 18:42] == 100).all()
    changed = (out != img).any(axis=2)
    assert not changed[:16].any() and not changed[64:].any()
    assert not changed[:, :18].any() and not changed[:, 42:].any()
    assert (img[40, 30] == 0).all()  # the input is untouched


def test_shared_is_the_overlap_over_the_smaller_box():
    big, inside = np.array([0.0, 0, 10, 10]), np.array([2.0, 2, 4, 6])
    assert shared(big, inside) == shared(inside, big) == 1.0
    assert shared(big, np.array([20.0, 0, 30, 10])) == 0.0  # apart
    assert shared(big, np.array([5.0, 0, 15, 10])) == pytest.approx(0.5)  # half of each


def test_paint_out_of_a_grey_image_paints_its_mean():
    """mean_colour took the last axis of a grey image (its width) as its channels: 4 values, and
    a 4-pixel wide box painted with them (0s) instead of the mean."""
    img = np.full((4, 6), 100, np.uint8)
    out = paint_out(img, [np.array([1.0, 1.0, 3.0, 3.0])], grow=0.0)
    assert (out == 100).all()


def test_an_empty_frame_is_refused_by_name():
    from gst.detect.blazepose import as_bgr_frame

    for shape in [(0, 0, 3), (0, 10, 3), (10, 0), (0, 0)]:
        with pytest.raises(ValueError, match=r"empty frame of shape"):
            as_bgr_frame(np.zeros(shape, np.uint8))
