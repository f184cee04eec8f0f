"""One person, one id, from their first frame: a duplicate box on a person's legs never becomes a
second person, two people who really overlap keep two ids, and a person's rows start at the
frame they first appear (the frames they were tentative in are written once they are confirmed).
Hand-built detections with skeletons on a real video file, through the whole loop."""

import numpy as np
import pytest

from gst.detect.boxes import containment
from gst.detect.persons import LIMB_JOINTS
from gst.track import BoxDepthPredictor, Detection, TrackOptions, column_array, track_video
from gst.track.parts import PartConfig, is_part, skeleton_share
from gst.track.read import read_tracks
from gst.track.tracker import TrackerConfig
from tests.track_synthetic import (
    MODEL,
    H,
    W,
    Walker,
    render,
    track_boxes,
    walker_boxes,
    write_video,
)

N = 30

# Standing skeleton in box-relative coordinates (x, y in [0, 1]) for the 33 BlazePose landmarks.
_ANCHORS = {
    0: (0.5, 0.06), 11: (0.3, 0.2), 12: (0.7, 0.2), 13: (0.22, 0.38), 14: (0.78, 0.38),
    15: (0.2, 0.55), 16: (0.8, 0.55), 23: (0.38, 0.52), 24: (0.62, 0.52), 25: (0.38, 0.75),
    26: (0.62, 0.75), 27: (0.38, 0.96), 28: (0.62, 0.96),
}  # fmt: skip
_NEAREST = {  # the other landmarks sit on the nearest anchor
    **dict.fromkeys(range(1, 11), 0),
    **dict.fromkeys((17, 19, 21), 15),
    **dict.fromkeys((18, 20, 22), 16),
    **dict.fromkeys((29, 31), 27),
    **dict.fromkeys((30, 32), 28),
}


def skeleton(box: np.ndarray) -> np.ndarray:
    """(33, 3) landmarks of a person standing in `box`, confidence 1."""
    x0, y0, x1, y1 = box
    rel = np.array([_ANCHORS[_NEAREST.get(i, i)] for i in range(33)])
    return np.c_[x0 + rel[:, 0] * (x1 - x0), y0 + rel[:, 1] * (y1 - y0), np.ones(33)]


def leg_person(outer: np.ndarray) -> np.ndarray:
    """A 'person' the landmark model made of someone's legs: all of its limb joints lie on the
    outer skeleton's hips, knees and ankles (shoulders on the hips, and so on down)."""
    lm = outer.copy()
    hips, knees, ankles = outer[[23, 24]], outer[[25, 26]], outer[[27, 28]]
    lm[[11, 12]], lm[[13, 14]], lm[[15, 16]] = hips, (hips + knees) / 2, knees
    lm[[23, 24]], lm[[25, 26]], lm[[27, 28]] = knees, (knees + ankles) / 2, ankles
    return lm


class HandDetector:
    """Per frame: person A walking; from frame `start`, either a duplicate box on A's legs or a
    second person standing half behind A (box mostly inside A's, their own skeleton)."""

    def __init__(self, boxes: np.ndarray, case: str, start: int = 10):
        self.boxes, self.case, self.start = boxes, case, start

    def detect(self, frame, index):
        a = self.boxes[index, 0]
        la = skeleton(a)
        dets = [Detection(a, 0.9, landmarks=la)]
        if index >= self.start and self.case == "duplicate":
            legs = np.array([a[0] + 4, (a[1] + a[3]) / 2, a[2] - 4, a[3]])
            dets.append(Detection(legs, 0.8, landmarks=leg_person(la)))
        if index >= self.start and self.case == "overlap":
            w = a[2] - a[0]
            b = np.array([a[0] + 0.5 * w, a[1] + 20, a[2] + 0.2 * w, a[3] - 10])  # further back
            dets.append(Detection(b, 0.8, landmarks=skeleton(b)))
        return dets


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    d = tmp_path_factory.mktemp("parts")
    walker = [Walker((40, 40, 220), (100.0, 120.0), (3.0, 0.0), (60.0, 150.0))]
    boxes = walker_boxes(walker, N)
    return write_video(d / "clip.avi", render(walker, boxes, W, H), W, H), boxes


PARTS = PartConfig()


def _track(video, case, tmp_path, parts=PARTS):
    path, boxes = video
    res = track_boxes(
        path,
        tmp_path / case,
        HandDetector(boxes, case),
        options=TrackOptions(tracker=TrackerConfig(min_hits=3, parts=parts), frames_per_group=8),
    )
    t = read_tracks(res.path)
    frames, ids = t.column("frame").to_numpy(), t.column("person_id").to_numpy()
    return {int(p): frames[ids == p] for p in np.unique(ids)}, t


def test_hand_skeletons_are_what_the_cases_claim(video):
    boxes = video[1]
    a = boxes[12, 0]
    det = HandDetector(boxes, "duplicate").detect(None, 12)[1]
    assert containment(det.box, a) > 0.9
    assert skeleton_share(det.landmarks, skeleton(a), PartConfig()) == 1.0
    other = HandDetector(boxes, "overlap").detect(None, 12)[1]
    assert containment(other.box, a) >= PartConfig().containment
    assert skeleton_share(other.landmarks, skeleton(a), PartConfig()) < 0.5


def test_duplicate_box_on_the_legs_gives_one_id(video, tmp_path):
    by_id, t = _track(video, "duplicate", tmp_path)
    assert list(by_id) == [0]
    np.testing.assert_array_equal(by_id[0], np.arange(N))  # from frame 0, not min_hits - 1
    # without the part test the duplicate becomes a second person
    by_id_off, _ = _track(video, "duplicate", tmp_path / "off", parts=None)
    assert len(by_id_off) == 2


def test_two_people_overlapping_keep_two_ids_from_their_first_frame(video, tmp_path):
    by_id, t = _track(video, "overlap", tmp_path)
    assert sorted(by_id) == [0, 1]
    np.testing.assert_array_equal(by_id[0], np.arange(N))
    # the second person's rows start where they appeared (frame 10), though confirmed at 12
    np.testing.assert_array_equal(by_id[1], np.arange(10, N))
    lm = column_array(t, "landmarks2d")
    conf = column_array(t, "landmarks_conf")
    assert lm.shape == (len(t), 33, 2) and np.isfinite(lm).all() and (conf == 1).all()


def test_box_only_part_needs_appearance_and_position_to_disagree():
    cfg = PartConfig()
    outer, inner = np.array([0, 0, 100, 200.0]), np.array([10, 100, 90, 200.0])
    assert is_part(inner, outer, None, None, 0.1, True, cfg)  # same clothes: a part
    assert is_part(inner, outer, None, None, 0.9, False, cfg)  # same place: a part
    assert not is_part(inner, outer, None, None, 0.9, True, cfg)  # both differ: a person
    assert not is_part(np.array([60, 0, 160, 200.0]), outer, None, None, 0.1, False, cfg)


def test_unsure_joints_are_no_evidence():
    outer = skeleton(np.array([0, 0, 100, 200.0]))
    far = skeleton(np.array([300, 0, 400, 200.0]))
    far[LIMB_JOINTS, 2] = 0.1  # nothing confident: counts as lying on the outer person
    assert skeleton_share(far, outer, PartConfig()) == 1.0
    far[LIMB_JOINTS, 2] = 1.0
    assert skeleton_share(far, outer, PartConfig()) == 0.0


class LandmarkPredictor(BoxDepthPredictor):
    """A predictor that takes the crops' landmarks, and keeps what it was given."""

    accepts_landmarks = True

    def __init__(self):
        super().__init__()
        self.seen = []

    def __call__(self, crops, K_crop, landmarks=None):
        self.seen.append((K_crop.copy(), landmarks.copy()))
        return super().__call__(crops, K_crop)


def test_a_landmark_predictor_gets_the_crops_landmarks(video, tmp_path):
    path, boxes = video
    pred = LandmarkPredictor()
    track_video(
        path,
        tmp_path / "lm",
        HandDetector(boxes, "none"),
        pred,
        model=MODEL,
        options=TrackOptions(batch_size=4, frames_per_group=8),
    )
    K, lm = pred.seen[0]
    assert lm.shape == (4, 33, 3)
    # frame 0's person: the crop's landmarks map back to the frame's through K_crop and the
    # default camera (uncalibrated video: no distortion, crop = scaled and shifted frame)
    from gst.data.camera_view import default_camera

    Kf = default_camera(W, H).K
    frame_uv = (lm[0, :, :2] - K[0][:2, 2]) / K[0][0, 0] * Kf[0, 0] + Kf[:2, 2]
    np.testing.assert_allclose(frame_uv, skeleton(boxes[0, 0])[:, :2], atol=1e-3)
    np.testing.assert_array_equal(lm[..., 2], 1.0)


class UpPredictor(LandmarkPredictor):
    """A landmark predictor that also reads the camera's up direction, and keeps it."""

    accepts_up = True

    def __init__(self):
        super().__init__()
        self.ups = []

    def __call__(self, crops, K_crop, landmarks=None, up=None):
        self.ups.append(None if up is None else up.copy())
        return super().__call__(crops, K_crop, landmarks)


@pytest.mark.parametrize("calibrated", [True, False])
def test_the_camera_up_reaches_predictors_that_read_it_only_when_calibrated(
    video, tmp_path, calibrated
):
    from calibration.camera import Camera, look_at_rotation

    path, boxes = video
    R = look_at_rotation((0.0, -4.0, 3.0), (0.0, 0.0, 1.0))  # looks down at the floor's middle
    cam = Camera.create("c", [[300.0, 0, W / 2], [0, 300.0, H / 2], [0, 0, 1]], [], R,
                        -R @ np.array([0.0, -4.0, 3.0]), W, H)  # fmt: skip
    pred, plain = UpPredictor(), LandmarkPredictor()
    for p, name in ((pred, "up"), (plain, "plain")):  # the plain one is never handed `up`
        track_video(
            path, tmp_path / name, HandDetector(boxes, "none"), p, model=MODEL,
            camera=cam if calibrated else None, world_up=(0.0, 0.0, 1.0) if calibrated else None,
            options=TrackOptions(batch_size=4, frames_per_group=8),
        )  # fmt: skip
    assert plain.seen
    if not calibrated:
        assert pred.ups and all(u is None for u in pred.ups)
        return
    up = pred.ups[0]
    assert up.shape == (4, 3)
    np.testing.assert_allclose(up, np.repeat((R @ [0.0, 0.0, 1.0])[None], 4, 0), atol=1e-6)
    assert up[0, 1] < -0.5  # the world's up points up the image (-y) for this camera
