"""Looking for a lost person behind someone: the people kept are painted out by their own masks
(their segmentation held near their skeleton), and a person found there counts only where most
of their limbs lie beside the paint. On the real capture (cam03): the man who walks behind the
woman is found again at once instead of at the detector's next run."""

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gst.detect.blazepose import LANDMARK_SIZE, BodyRoi, RegionLandmarks
from gst.detect.boxes import fill_where, mean_colour
from gst.detect.persons import LIMB_JOINTS
from gst.track.person_detector import (
    PersonModelConfig,
    paint_out_people,
    share_covered,
)
from tests.real_capture import LAB, NEEDS_LAB, NEEDS_MODELS
from tests.test_detect_blazepose import _stick


def _region(lm: np.ndarray, mask_logits: np.ndarray, origin=(0.0, 0.0)) -> RegionLandmarks:
    """A region whose crop is the image at `origin`, one pixel per crop pixel."""
    to_crop = np.array([[1.0, 0, -origin[0]], [0, 1.0, -origin[1]]])
    roi = BodyRoi((origin[0] + LANDMARK_SIZE / 2, origin[1] + LANDMARK_SIZE / 2), LANDMARK_SIZE, 0)
    z = np.zeros(33, np.float32)
    return RegionLandmarks(
        roi, 1.0, lm, z, z, np.zeros((33, 3), np.float32), mask_logits, to_crop, roi
    )


def test_painting_covers_the_persons_mask_near_their_skeleton_only():
    image = np.full((300, 400, 3), 200, np.uint8)
    image[:, 200:] = 20  # two halves: the fill is the image's mean colour
    lm = _stick(cx=100.0, top=20.0, height=200.0)
    logits = np.full((LANDMARK_SIZE, LANDMARK_SIZE), -5.0, np.float32)
    logits[10:230, 60:140] = 5.0  # the person ...
    logits[10:230, 200:250] = 5.0  # ... and someone else the model segmented in their region
    out, covered = paint_out_people(image, [_region(lm, logits)], skeleton_width=0.08, grow=0)
    assert covered[120, 100] and covered[30, 100]  # on the body
    assert not covered[120, 220] and not covered[120, 180]  # far from their skeleton: left alone
    assert not covered[260, 100]  # outside their mask
    mean = image.reshape(-1, 3).mean(axis=0)
    np.testing.assert_allclose(
        out[covered], np.broadcast_to(np.round(mean), out[covered].shape), atol=1
    )
    np.testing.assert_array_equal(out[~covered], image[~covered])
    # growing the mask covers a ring around it, and only grows the cover
    _, grown = paint_out_people(image, [_region(lm, logits)], skeleton_width=0.08, grow=9)
    assert grown.sum() > covered.sum() and (grown | covered).sum() == grown.sum()


def test_share_covered_counts_limb_landmarks_on_the_paint():
    covered = np.zeros((300, 400), bool)
    lm = _stick(cx=100.0, top=20.0, height=200.0)
    assert share_covered(lm, covered) == 0.0
    covered[:, :100] = True  # the stick figure's left side (x = 80) is painted
    left = [j for j in LIMB_JOINTS if lm[j, 0] < 100]
    assert share_covered(lm, covered) == pytest.approx(len(left) / len(LIMB_JOINTS))
    lm[:, 0] += 1000  # outside the image: not on the paint
    assert share_covered(lm, covered) == 0.0


def test_lost_retry_is_validated():
    with pytest.raises(ValueError, match="lost_retry"):
        PersonModelConfig(lost_retry=-1)
    with pytest.raises(ValueError, match="lost_max_covered"):
        PersonModelConfig(lost_max_covered=1.5)
    with pytest.raises(ValueError, match="continue_distance"):
        PersonModelConfig(continue_distance=-0.1)


@pytest.mark.parametrize("lost_retry", [0, 10])
@NEEDS_MODELS
@NEEDS_LAB
def test_the_man_who_walks_behind_the_woman_is_found_again_at_once(lost_retry):
    """cam03, frames 36-60: the man's own region loses him at frame 41 as he passes behind the
    woman, his head hidden by hers, and the detector (which finds people by the face) does not
    find him again until frame 51. Looked for in his last region with her painted out, he is
    back in the next frame, to her right."""
    from gst.track.person_detector import PersonModelDetector

    cap = cv2.VideoCapture(str(LAB / "cam03.mp4"))
    cap.set(cv2.CAP_PROP_POS_FRAMES, 36)
    det = PersonModelDetector(PersonModelConfig(lost_retry=lost_retry))
    found = [det.detect(cap.read()[1], i) for i in range(36, 61)]
    cap.release()
    counts = "".join(str(len(d)) for d in found)
    assert counts.startswith("22222")  # both, up to frame 40
    if lost_retry == 0:
        # only the woman, for most of the detector's interval: at least 9 frames on one host and
        # install, 7 on another (the last bits of the person model's arithmetic)
        assert "1" * 6 in counts
        return
    assert det.found_again >= 1
    assert counts.count("1") <= 2 and "11" not in counts and set(counts) <= {"1", "2"}
    for d in found[6:16]:  # where two are found, the man stands to the right of the woman
        if len(d) == 2:
            a, b = sorted(d, key=lambda p: p.landmarks[LIMB_JOINTS, 0].mean())
            assert b.landmarks[LIMB_JOINTS, 0].mean() > a.landmarks[LIMB_JOINTS, 0].mean() + 50


@settings(max_examples=30, deadline=None)
@given(st.integers(1, 40), st.integers(1, 40), st.integers(0, 2**32 - 1))
def test_mean_colour_and_fill_match_numpy(h, w, seed):
    rng = np.random.default_rng(seed)
    image = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    mask = rng.random((h, w)) < 0.4
    colour = mean_colour(image)
    np.testing.assert_allclose(colour, image.reshape(-1, 3).mean(axis=0), rtol=1e-12)
    expected = image.copy()
    expected[mask] = colour
    np.testing.assert_array_equal(fill_where(image, mask, colour), expected)
    np.testing.assert_array_equal(image, image.copy())  # the input is left as it was


def test_painting_around_regions_paints_what_they_see_as_the_whole_frame_would():
    image = np.random.default_rng(0).integers(0, 256, (400, 600, 3), dtype=np.uint8)
    lm = _stick(cx=100.0, top=20.0, height=200.0)
    logits = np.full((LANDMARK_SIZE, LANDMARK_SIZE), -5.0, np.float32)
    logits[10:230, 60:140] = 5.0
    person = _region(lm, logits)
    whole, covered = paint_out_people(image, [person], 0.08, 9)
    near = BodyRoi((150.0, 130.0), 120.0, 0.3)  # overlaps the person's mask
    part, part_covered = paint_out_people(image, [person], 0.08, 9, around=[near])
    corners = np.round(near.corners()).astype(int)
    x0, y0 = corners.min(axis=0)
    x1, y1 = corners.max(axis=0)
    np.testing.assert_array_equal(part[y0:y1, x0:x1], whole[y0:y1, x0:x1])
    np.testing.assert_array_equal(part_covered[y0:y1, x0:x1], covered[y0:y1, x0:x1])
    assert not part_covered[:, 400:].any() and covered.sum() > part_covered.sum() > 0


@pytest.mark.parametrize("continue_distance", [0.0, 0.05])
@NEEDS_MODELS
@NEEDS_LAB
def test_the_man_in_his_fast_turn_stays_tracked_while_his_skeleton_continues(continue_distance):
    """cam03, frames 44-62: the man, in plain view, turns fast with an arm up; the landmark
    model's presence for him falls to 0.09-0.45 in frames 51-52, 56-58 and 60 while his
    skeleton stays within 2 % of his size of the frame before's, limbs sure. He was dropped
    there (0: the old rule); continuing readings keep him."""
    from dataclasses import replace

    from gst.track.person_detector import PersonModelDetector
    from gst.track.scene import TrackSettings, person_model_config

    cap = cv2.VideoCapture(str(LAB / "cam03.mp4"))  # from the start: found by frame 44
    stage = person_model_config(TrackSettings(), fps=60.0)  # the detector every 20 frames
    det = PersonModelDetector(replace(stage, continue_distance=continue_distance))
    counts = "".join(str(len(det.detect(cap.read()[1], i))) for i in range(63))[44:]
    cap.release()
    if continue_distance == 0:  # dropped in >= 5 frames on one host and install, 4 on another
        assert counts.count("1") >= 3 and det.continued == 0
        return
    assert counts == "2" * 19 and det.continued >= 5
