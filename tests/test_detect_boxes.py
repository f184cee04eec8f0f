"""Box helpers of the detectors (gst.detect.boxes) that need no model: painting people out of a
frame for the person detector's second look, and the overlap of two boxes."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

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


@given(
    x0=st.floats(-300, 300), y0=st.floats(-300, 300),
    bw=st.floats(0, 200), bh=st.floats(0, 200), grow=st.floats(0, 0.5),
)  # fmt: skip
@settings(max_examples=200, deadline=None)
def test_paint_out_paints_exactly_the_grown_box_clipped_to_the_image(x0, y0, bw, bh, grow):
    """A box wholly above or left of the image has a negative far edge; sliced as it was, it
    counted back from the other side and painted nearly the whole frame (18,236 of 20,000 px)."""
    img = np.zeros((100, 200, 3), np.uint8)
    img[::2] = 200  # a mean colour of its own: painted pixels differ from both rows
    x1, y1 = x0 + bw, y0 + bh
    out = paint_out(img, [np.array([x0, y0, x1, y1])], grow=grow)
    gx, gy = grow * bw, grow * bh
    vv, uu = np.mgrid[0:100, 0:200]
    inside = (
        (uu >= np.floor(x0 - gx)) & (uu < np.ceil(x1 + gx))
        & (vv >= np.floor(y0 - gy)) & (vv < np.ceil(y1 + gy))
    )  # fmt: skip
    np.testing.assert_array_equal((out != img).any(-1), inside)


def test_a_hint_box_starting_left_of_the_frame_is_looked_at():
    """`_uncovered` sliced a hint with x < 0 from the frame's far edge: an empty slice, and the
    person at the left edge was never segmented."""
    from gst.detect.persons import PersonSegmenter, SegmenterConfig

    seg = PersonSegmenter.__new__(PersonSegmenter)  # no models: only the hint bookkeeping
    seg.config = SegmenterConfig(hint_covered=0.5)
    assert seg._uncovered(None, [(-10, 5, 30, 30)], (100, 200)) == [(-10, 5, 30, 30)]
    labels = np.zeros((100, 200), np.uint8)
    labels[:40, :25] = 1  # someone found there already covers it
    assert seg._uncovered(labels, [(-10, 5, 30, 30)], (100, 200)) == []


@settings(max_examples=200, deadline=None)
@given(
    st.floats(-40, 60, allow_nan=False),
    st.floats(-40, 60, allow_nan=False),
    st.floats(0, 50, allow_nan=False),
    st.floats(0, 50, allow_nan=False),
)
def test_pixel_window_covers_the_pixels_a_box_touches_inside_the_image(x0, y0, bw, bh):
    """The one box-to-slices rule of paint_out and the segmenter's hint test, against a
    per-pixel reference: pixel column i is touched when floor(x0) <= i < ceil(x1)."""
    from gst.detect.boxes import pixel_window

    h, w = 30, 40
    cols, rows = np.arange(w), np.arange(h)
    want = ((rows >= np.floor(y0)) & (rows < np.ceil(y0 + bh)))[:, None] & (
        (cols >= np.floor(x0)) & (cols < np.ceil(x0 + bw))
    )[None, :]
    window = pixel_window((x0, y0, x0 + bw, y0 + bh), (h, w))
    got = np.zeros((h, w), bool)
    if window is not None:
        got[window] = True
        assert got.any()
    np.testing.assert_array_equal(got, want)
