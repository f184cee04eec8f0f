"""The person model's tracking loop on real frames: the landmark model follows people from their
own landmarks and the detector runs only when needed; batched landmark calls give the same
numbers as one call per region; boxes and landmarks come back in full-frame pixels."""

import cv2
import numpy as np
import pytest

from tests.real_capture import LAB, NEEDS_MODELS_AND_LAB

pytestmark = NEEDS_MODELS_AND_LAB


@pytest.fixture(scope="module")
def frames():
    cap = cv2.VideoCapture(str(LAB / "cam02.mp4"))
    out = []
    for _ in range(12):
        ok, f = cap.read()
        assert ok
        out.append(f)
    cap.release()
    return out


def test_landmark_loop_runs_the_detector_only_when_needed(frames):
    from gst.track.person_detector import PersonModelConfig, PersonModelDetector

    det = PersonModelDetector(PersonModelConfig(detect_every=10, look_again_zoom=0))
    found = [det.detect(f, i) for i, f in enumerate(frames)]
    assert [len(d) for d in found] == [2] * len(frames)
    assert det.detector_runs == 2  # frame 0 and frame 10: nobody was lost
    # two regions per frame (computed, or kept for a person whose region did not change): frame
    # 10's detector hits are the tracked people, not segmented again
    assert det.regions + det.still_kept == 2 * len(frames)
    h, w = frames[0].shape[:2]
    for d in found[5]:
        x0, y0, x1, y1 = d.box
        assert 0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h and y1 - y0 > 0.3 * h
        sure = d.landmarks[:, 2] > 0.8
        u, v = d.landmarks[sure, 0], d.landmarks[sure, 1]
        assert sure.sum() > 15
        assert ((u >= x0 - 20) & (u <= x1 + 20) & (v >= y0 - 20) & (v <= y1 + 20)).mean() > 0.9
    # a jump back in the video restarts from the detector
    det.detect(frames[0], 0)
    assert det.detector_runs == 3


def test_a_still_person_keeps_their_landmarks_until_their_region_changes(frames):
    from gst.track.person_detector import PersonModelConfig, PersonModelDetector

    det = PersonModelDetector(
        PersonModelConfig(detect_every=100, still_refresh=4, look_again_zoom=0)
    )
    found = det.detect(frames[0], 0)
    # the detector's finds are confirmed in the regions their own landmarks give before they can
    # be kept: a still object mistaken for a person once must not stay
    first = det.detect(frames[0], 1)
    assert len(found) == len(first) == 2 and det.regions == 4 and det.still_kept == 0
    # the same picture again: nobody's region changed, so the landmark model does not run
    again = [det.detect(frames[0], i) for i in (2, 3, 4, 5)]
    assert det.regions == 4 and det.still_kept == 8
    for d in again:
        for a, b in zip(first, d, strict=True):
            np.testing.assert_array_equal(a.landmarks, b.landmarks)
            np.testing.assert_array_equal(a.box, b.box)
    # ... but at most `still_refresh` frames in a row
    det.detect(frames[0], 6)
    assert det.regions == 6
    # the part of one person's region that the other's does not hold is darkened: only the first
    # is looked at again (regions in work pixels, the frame at full resolution)
    scale = frames[0].shape[0] / 960
    ys, xs = np.mgrid[: frames[0].shape[0], : frames[0].shape[1]] / scale
    inside = []
    for i, roi in enumerate(det._people):
        half = roi.side / 2 + (0 if i == 0 else 8)  # a margin: resizing blurs the edge
        inside.append((abs(xs - roi.centre[0]) <= half) & (abs(ys - roi.centre[1]) <= half))
    only_first = inside[0] & ~np.logical_or.reduce(inside[1:])
    assert only_first.sum() > 10_000
    darker = frames[0].copy()
    darker[only_first] //= 2
    det.detect(darker, 7)
    assert det.regions == 7 and det.still_kept == 9
    # still_change 0: every frame computed
    off = PersonModelDetector(
        PersonModelConfig(detect_every=100, still_change=0, look_again_zoom=0)
    )
    for i in range(3):
        off.detect(frames[0], i)
    assert off.regions == 6 and off.still_kept == 0


def test_a_doubted_person_who_stands_still_stays_doubted(frames):
    """A reading continued though the model doubted it (presence below min_presence) was kept
    as a still person's: the next frame it came back as sure, and the detector stopped looking
    for a surer reading of them for up to `still_refresh` frames."""
    from dataclasses import replace

    from gst.track.person_detector import PersonModelConfig, PersonModelDetector

    det = PersonModelDetector(PersonModelConfig(look_again_zoom=0, detect_every=100))
    for i in range(2):
        det.detect(frames[0], i)
    real = det.landmarker
    det.landmarker = lambda image, rois: [replace(r, presence=0.3) for r in real(image, rois)]
    det.config = replace(det.config, still_change=0.0)  # frame 2: everyone read, and doubted
    det.detect(frames[0], 2)
    assert det.continued >= 1
    det.config = replace(det.config, still_change=4.0)  # the same picture: still people kept
    runs, still = det.detector_runs, det.still_kept
    det.detect(frames[0], 3)
    assert det.still_kept == still  # the doubted are read again, not kept as still
    assert det.detector_runs == runs + 1  # and the detector looks for surer readings


def test_looking_again_zoomed_in_finds_the_bystander_at_the_back_of_cam02(frames):
    """cam02 shows the bystander small at the back, beside the man: the usual detector windows
    never find her; the zoomed windows of the second look do. The anatomical skeleton model at
    the right edge, found there too, is not a person (its limb landmarks are unsure)."""
    from gst.track.person_detector import PersonModelConfig, PersonModelDetector

    def people(config):
        det = PersonModelDetector(config)
        return [d.box for i, f in enumerate(frames) for d in det.detect(f, i)]

    def at_the_back(box):
        cx, cy = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
        return 700 < cx < 900 and 400 < cy < 950 and box[3] - box[1] < 600

    zoomed = people(PersonModelConfig(zoom_per_run=10))
    assert sum(at_the_back(b) for b in zoomed) >= 2
    assert not any(b[0] > 950 for b in zoomed)  # the skeleton model stands at x > 980
    assert not any(at_the_back(b) for b in people(PersonModelConfig(look_again_zoom=0)))


def test_batched_landmarks_equal_one_call_per_region(frames):
    from gst.detect.blazepose import BatchedLandmarks, BlazePose, roi_from_alignment

    small = cv2.resize(frames[0], (544, 960), interpolation=cv2.INTER_AREA)
    rois = [roi_from_alignment(d.keypoints[0], d.keypoints[1]) for d in BlazePose().detect(small)]
    assert len(rois) >= 2
    lm = BatchedLandmarks()
    together = lm(small, rois)
    alone = [lm(small, [r])[0] for r in rois]
    for a, b in zip(together, alone, strict=True):
        np.testing.assert_allclose(a.landmarks, b.landmarks, atol=1e-4)
        np.testing.assert_allclose(a.mask_logits, b.mask_logits, atol=1e-3)
        assert abs(a.presence - b.presence) < 1e-5


def test_segmenter_follows_people_between_detector_runs(frames):
    """Extraction's phase 1 (gst.detect.persons.PersonSegmenter) with the detector every 10
    frames: the same two people in every frame as with the detector on every frame, one
    landmark-model call per person and frame, and the detector on frames 0 and 10 only."""
    from gst.detect.blazepose import BlazePose
    from gst.detect.persons import LIMB_JOINTS, PersonSegmenter, SegmenterConfig

    small = [cv2.resize(f, (544, 960), interpolation=cv2.INTER_AREA) for f in frames]
    model = BlazePose()
    calls = []
    segment = model.segment
    model.segment = lambda image, roi: calls.append(roi) or segment(image, roi)
    every = PersonSegmenter(model, SegmenterConfig(detect_every=1))
    sparse = PersonSegmenter(model, SegmenterConfig(detect_every=10))
    for f in small:
        _, reference = every.segment(f)
        n = len(calls)
        labels, people = sparse.segment(f)
        assert len(calls) - n == 2  # one call per person: detections of them are not repeated
        assert len(people) == len(reference) == 2
        assert set(np.unique(labels)) == {0, 1, 2}
        # The same people. Not to the last digit: where the every-frame run's detector places a
        # person's region beyond `same_region` of the tracked one (cam02 frame 2, with the
        # landmarks refined from the heatmaps), it keeps that region's answer, 1.3 px away.
        for p in people:
            d = min(
                np.median(
                    np.linalg.norm(
                        p.landmarks[LIMB_JOINTS, :2] - r.landmarks[LIMB_JOINTS, :2], axis=1
                    )
                )
                for r in reference
            )
            assert d < 2.0  # px; the other person is hundreds of pixels away
    assert every.detector_runs == len(small)
    assert sparse.detector_runs == 2


def test_looking_again_finds_the_bystander_the_detector_skips():
    """cam01: the man, the woman and, at the left wall, a bystander. BlazePose's detector (made
    for one person) returns the two in front; looking again with them painted out finds him,
    on the first frame and every frame after, with the detector still run only twice."""
    from gst.track.person_detector import PersonModelConfig, PersonModelDetector

    cap = cv2.VideoCapture(str(LAB / "cam01.mp4"))
    frames = [cap.read()[1] for _ in range(12)]
    cap.release()
    counts = {}
    for look_again in (False, True):
        det = PersonModelDetector(PersonModelConfig(detect_every=10, look_again=look_again))
        found = [det.detect(f, i) for i, f in enumerate(frames)]
        counts[look_again] = [len(d) for d in found]
        assert det.detector_runs == 2
    assert counts[False] == [2] * 12 and counts[True] == [3] * 12
    w = frames[0].shape[1]
    assert min(d.box[0] for d in found[0]) < 0.15 * w  # the new one stands at the left wall


def test_extraction_segmenter_zoomed_in_finds_the_bystander_and_confirms_her(frames):
    """`SegmenterConfig.zoom` (extraction's person masks, off by default): the first detector run
    scans every zoomed window, finds the bystander at the back of cam02 and keeps her once her
    own region confirms her; without zoom only the two subjects are found."""
    from gst.detect.blazepose import BlazePose
    from gst.detect.persons import PersonSegmenter, SegmenterConfig

    small = [cv2.resize(f, (544, 960), interpolation=cv2.INTER_AREA) for f in frames[:4]]
    model = BlazePose()
    zoomed = PersonSegmenter(model, SegmenterConfig(detect_every=10, zoom=2 / 3))
    plain = PersonSegmenter(model, SegmenterConfig(detect_every=10))
    for f in small:
        _, found = zoomed.segment(f)
        _, two = plain.segment(f)
        assert len(two) == 2
        assert len(found) == 3
        back = [p for p in found if 350 < np.median(p.landmarks[:, 0]) < 450]
        assert len(back) == 1 and np.ptp(back[0].landmarks[:, 1]) < 300  # small, at the back
    assert zoomed.zoom_found == 1 and zoomed.detector_runs == 1


def test_a_strided_video_keeps_the_landmark_loop(frames):
    """At stride 6 the detector sees frames 0, 6, 12, ...: the stage's settings count its gap in
    processed frames, so the landmark loop follows the people instead of restarting from the
    detector at every frame (before: max_gap 5 video frames, every call a restart)."""
    from gst.track.person_detector import PersonModelDetector
    from gst.track.scene import TrackSettings, person_model_config

    cap = cv2.VideoCapture(str(LAB / "cam02.mp4"))
    strided = []
    for i in range(19):
        ok, f = cap.read()
        assert ok
        if i % 6 == 0:
            strided.append((i, f))
    cap.release()
    config = person_model_config(TrackSettings(stride=6, detect_every=10, look_again_zoom=0))
    det = PersonModelDetector(config)
    found = [det.detect(f, i) for i, f in strided]
    assert [len(d) for d in found] == [2] * len(strided)
    assert det.detector_runs == 1  # frame 0 only: 6, 12 and 18 followed from the landmarks


def test_batched_landmarks_keep_a_few_interpreters_whatever_the_batch_sizes(frames):
    """One interpreter was kept per batch size seen, each holding its batch's working memory
    (sizes 1-8: +624 MiB); batches now run as calls of 8, 4, 2 and 1 with the same numbers."""
    from gst.detect.blazepose import BatchedLandmarks, BlazePose, roi_from_alignment

    small = cv2.resize(frames[0], (544, 960), interpolation=cv2.INTER_AREA)
    rois = [roi_from_alignment(d.keypoints[0], d.keypoints[1]) for d in BlazePose().detect(small)]
    many = (rois * 7)[:13]  # 13 = 8 + 4 + 1
    lm = BatchedLandmarks()
    alone = {id(r): lm(small, [r])[0] for r in rois}
    for n in (3, 5, 7, 13):
        for got, roi in zip(lm(small, many[:n]), many[:n], strict=True):
            np.testing.assert_allclose(got.landmarks, alone[id(roi)].landmarks, atol=1e-4)
    assert sorted(lm._by_batch) == [1, 2, 4, 8]


def test_grey_frames_find_the_people_colour_frames_do(frames):
    """A grey frame reached the painting out as a 2-D work image and crashed (a broadcast
    error naming no frame); the detector now converts it as the other readers do."""
    from gst.track.person_detector import PersonModelDetector

    colour, grey = PersonModelDetector(), PersonModelDetector()
    for i, f in enumerate(frames[:3]):
        g = cv2.cvtColor(f, cv2.COLOR_BGR2GRAY)
        assert len(grey.detect(g, i)) == len(colour.detect(cv2.cvtColor(g, cv2.COLOR_GRAY2BGR), i))
