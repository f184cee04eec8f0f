"""BlazePose person models: anchor layout, decoding, NMS, regions of interest, instance
composition, the pinned fetch, and (when the models and LiteRT are here) the models on real
footage and on a synthetic render."""

import hashlib
import math
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gst.detect.blazepose import (
    DETECTOR_SIZE,
    BodyRoi,
    PersonSegment,
    decode_detections,
    roi_from_alignment,
    roi_from_box,
    square_windows,
    ssd_anchors,
    weighted_nms,
    zoomed_windows,
)
from gst.detect.persons import (
    BONES as PERSON_BONES,
)
from gst.detect.persons import (
    HEAD,
    TORSO,
    PersonSegmenter,
    SegmenterConfig,
    compose_instances,
    distinct_people,
    same_person,
    skeleton_support,
)
from gst.detect.weights import (
    MEDIAPIPE_WHEEL,
    MODELS,
    BlazePoseModelsMissing,
    fetch_blazepose_models,
    model_paths,
)
from tests.real_capture import LAB, NEEDS_LAB, NEEDS_MODELS


def test_anchor_layout_matches_the_detector():
    a = ssd_anchors()
    assert a.shape == (2254, 2)
    # 28x28 cells x 2, then 14x14 x 2, then 7x7 x 6, row-major, centres of cells
    assert np.allclose(a[0], [0.5 / 28, 0.5 / 28]) and np.allclose(a[1], a[0])
    assert np.allclose(a[2], [1.5 / 28, 0.5 / 28])
    assert np.allclose(a[28 * 28 * 2], [0.5 / 14, 0.5 / 14])
    assert np.allclose(a[-1], [6.5 / 7, 6.5 / 7]) and np.allclose(a[-6], a[-1])
    assert a.min() > 0 and a.max() < 1


@settings(max_examples=30, deadline=None)
@given(
    st.integers(0, 2253),
    st.floats(-20, 20),
    st.floats(-20, 20),
    st.floats(10, 150),
    st.floats(10, 150),
)
def test_decode_puts_boxes_and_keypoints_at_anchor_plus_offset(idx, dx, dy, w, h):
    reg = np.zeros((2254, 12), np.float32)
    logits = np.full(2254, -50.0, np.float32)
    reg[idx, :4] = [dx, dy, w, h]
    reg[idx, 4:] = np.arange(8) - 4.0
    logits[idx] = 3.0
    scores, boxes, kps = decode_detections(reg, logits, 0.5)
    a = ssd_anchors()[idx]
    assert len(scores) == 1 and scores[0] == pytest.approx(1 / (1 + math.exp(-3)))
    centre = a + np.array([dx, dy]) / DETECTOR_SIZE
    assert np.allclose(
        boxes[0],
        np.r_[
            centre - np.array([w, h]) / 2 / DETECTOR_SIZE,
            centre + np.array([w, h]) / 2 / DETECTOR_SIZE,
        ],
        atol=1e-6,
    )
    assert np.allclose(kps[0], (np.arange(8) - 4.0).reshape(4, 2) / DETECTOR_SIZE + a, atol=1e-6)


def test_decode_rejects_wrong_shapes_and_survives_huge_logits():
    with pytest.raises(ValueError, match="2254"):
        decode_detections(np.zeros((100, 12)), np.zeros(100))
    s, _, _ = decode_detections(np.zeros((2254, 12), np.float32), np.full(2254, 1e6, np.float32))
    assert len(s) == 2254 and np.all(np.isfinite(s))


def test_weighted_nms_merges_overlaps_by_score_and_keeps_separate_people():
    boxes = np.array([[0, 0, 10, 10], [1, 0, 11, 10], [50, 50, 60, 60]], float)
    kps = np.stack([np.full((4, 2), v, float) for v in (0.0, 3.0, 100.0)])
    out = weighted_nms(np.array([0.9, 0.3, 0.8]), boxes, kps, iou=0.3)
    assert len(out) == 2
    assert out[0].score == 0.9 and np.allclose(
        out[0].box, [0.25, 0, 10.25, 10]
    )  # 0.75/0.25 weights
    assert np.allclose(out[0].keypoints, 0.75)
    assert np.allclose(out[1].box, boxes[2])


@pytest.mark.parametrize("w,h", [(540, 960), (960, 540), (500, 500), (400, 1000)])
def test_square_windows_cover_the_frame(w, h):
    wins = square_windows(w, h)
    full = wins[0]
    assert full[2] == max(w, h)
    tiles = wins[1:]
    if max(w, h) > 1.2 * min(w, h):
        assert len(tiles) >= 2
        covered = np.zeros(max(w, h), bool)
        for x0, y0, side in tiles:
            assert side == min(w, h)
            off = x0 if w > h else y0
            assert 0 <= off and off + side <= max(w, h)
            covered[off : off + side] = True
        assert covered.all()
    else:
        assert tiles == []


@settings(max_examples=60, deadline=None)
@given(st.integers(16, 2000), st.integers(16, 2000), st.floats(0.2, 0.95))
def test_zoomed_windows_cover_the_frame_with_half_overlap(w, h, fraction):
    wins = zoomed_windows(w, h, fraction)
    side = wins[0][2]
    assert side == max(1, round(fraction * min(w, h)))
    covered = np.zeros((h, w), bool)
    for x0, y0, s in wins:
        assert s == side and 0 <= x0 and 0 <= y0
        assert x0 + side <= max(w, side) and y0 + side <= max(h, side)
        covered[y0 : y0 + side, x0 : x0 + side] = True
    assert covered.all()
    # neighbours along an axis overlap by at least half a window (a person cut by one border
    # lies whole in the next window)
    for axis in (0, 1):
        starts = sorted({win[axis] for win in wins})
        assert all(b - a <= side / 2 + 1 for a, b in zip(starts[:-1], starts[1:], strict=True))


@settings(max_examples=40, deadline=None)
@given(st.floats(50, 500), st.floats(50, 500), st.floats(20, 200), st.floats(-math.pi, math.pi))
def test_roi_turns_the_body_axis_upright(cx, cy, r, theta):
    centre = np.array([cx, cy])
    scale_point = centre + r * np.array([math.cos(theta), math.sin(theta)])
    roi = roi_from_alignment(centre, scale_point)
    assert roi.side == pytest.approx(2 * r * 1.25)
    m = roi.to_crop(256)
    c = m @ np.r_[centre, 1]
    s = m @ np.r_[scale_point, 1]
    assert np.allclose(c, [128, 128], atol=1e-3)
    # the scale point lands straight above the centre in the crop, at r / side * 256 pixels
    assert np.allclose(s, [128, 128 - r / roi.side * 256], atol=1e-3)


def test_roi_from_box_is_upright_and_covers_the_box():
    roi = roi_from_box((100, 50, 40, 120))
    assert roi.angle == 0 and roi.centre == (120, 110) and roi.side == pytest.approx(150)
    m = roi.to_crop(256)
    for x, y in [(100, 50), (140, 170)]:
        u, v = m @ np.array([x, y, 1.0])
        assert 0 <= u <= 256 and 0 <= v <= 256


def _stick(cx: float, top: float, height: float) -> np.ndarray:
    """33 BlazePose landmarks of an upright stick figure (x, y, visibility)."""
    lm = np.zeros((33, 3), np.float32)
    lm[:, 0], lm[:, 2] = cx, 1.0
    s = height
    y = {
        0: 0.05,
        7: 0.05,
        8: 0.05,
        11: 0.18,
        12: 0.18,
        13: 0.33,
        14: 0.33,
        15: 0.47,
        16: 0.47,
        17: 0.5,
        18: 0.5,
        19: 0.5,
        20: 0.5,
        21: 0.49,
        22: 0.49,
        23: 0.5,
        24: 0.5,
        25: 0.72,
        26: 0.72,
        27: 0.93,
        28: 0.93,
        29: 0.95,
        30: 0.95,
        31: 0.97,
        32: 0.97,
    }
    for i, f in y.items():
        lm[i, 1] = top + f * s
    for i in (7, 11, 13, 15, 17, 19, 21, 23, 25, 27, 29, 31):
        lm[i, 0] = cx - 0.1 * s
    for i in (8, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30, 32):
        lm[i, 0] = cx + 0.1 * s
    return lm


def _segment(lm: np.ndarray, prob: np.ndarray, presence: float = 1.0) -> PersonSegment:
    return PersonSegment(presence, prob.astype(np.float32), lm, BodyRoi((0, 0), 1, 0))


def test_skeleton_support_covers_the_body_and_not_far_away():
    lm = _stick(100, 20, 200)
    sup = skeleton_support(lm, (260, 400), width=10)
    assert sup[120, 100] and sup[int(lm[27, 1]), int(lm[27, 0])]  # torso and ankle
    assert not sup[120, 300]  # far to the side
    assert sup.mean() < 0.25


def test_same_person_by_joints():
    a = _stick(100, 20, 200)
    assert same_person(a, a + np.array([5, 3, 0], np.float32), 0.15)
    assert not same_person(a, _stick(180, 20, 200), 0.15)


def test_compose_splits_overlapping_people_by_nearest_skeleton_and_drops_duplicates():
    h, w = 260, 400
    left, right = _stick(150, 20, 200), _stick(230, 20, 200)
    # The landmark model claims every person in its region: both probability maps cover both.
    both = np.zeros((h, w), np.float32)
    both[20:225, 110:275] = 0.9
    segs = [
        _segment(left, both),
        _segment(right, both),
        _segment(left + np.array([2, 1, 0], np.float32), both, presence=0.8),  # duplicate of left
        _segment(_stick(330, 20, 200), np.zeros((h, w)), presence=0.9),  # empty mask: not present
        _segment(_stick(60, 20, 200), both, presence=0.2),
    ]  # below min_presence
    labels, people = compose_instances(segs, SegmenterConfig(), h * w)
    assert len(people) == 2 and labels.max() == 2
    lab_left = labels[120, 150]
    lab_right = labels[120, 230]
    assert {lab_left, lab_right} == {1, 2}
    # the boundary lies half-way between the two skeletons' nearest lines
    assert labels[120, 185] == lab_left and labels[120, 195] == lab_right
    assert labels[5, 5] == 0


def _compose_whole_image(segs, config, area):
    """The labelling of compose_instances with skeleton distances over the whole image (the
    reference for the windowed one); the same distinct people."""
    kept = distinct_people(segs, config, area)
    if not kept:
        return None, []
    dist = []
    for k in kept:
        lines = np.full(k.probability.shape, 255, np.uint8)
        pts = np.round(k.landmarks[:, :2]).astype(np.int32)
        for a, b in PERSON_BONES + tuple(zip(TORSO, TORSO[1:] + TORSO[:1], strict=True)):
            cv2.line(lines, tuple(map(int, pts[a])), tuple(map(int, pts[b])), 0, thickness=1)
        head = tuple(map(int, pts[list(HEAD)].mean(axis=0)))
        cv2.line(lines, head, tuple(map(int, (pts[11] + pts[12]) // 2)), 0, thickness=1)
        dist.append(cv2.distanceTransform(lines, cv2.DIST_L2, 3))
    claimed = np.stack([k.probability > config.threshold for k in kept])
    best = np.where(claimed, np.stack(dist), np.inf).argmin(axis=0)
    owned = claimed.any(axis=0)
    areas = np.bincount(best[owned], minlength=len(kept))
    rank = np.argsort(-areas, kind="stable")
    lut = np.zeros(len(kept), np.uint8)
    lut[rank] = np.arange(1, len(kept) + 1, dtype=np.uint8)
    labels = np.where(owned, lut[best], 0).astype(np.uint8)
    return labels, [kept[r] for r in rank if areas[r] > 0]


@settings(max_examples=40, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.floats(-150, 550),  # skeleton centre x: people partly or wholly off the image
            st.floats(-100, 200),  # top
            st.floats(40, 400),  # height
            st.integers(0, 380),  # mask box x0
            st.integers(0, 240),  # y0
            st.integers(1, 200),  # width
            st.integers(1, 200),  # height
            st.floats(0.3, 1.0),  # presence
        ),
        min_size=1,
        max_size=4,
    )
)
def test_windowed_composition_equals_the_whole_image_one(people):
    """compose_instances works in the window of the claimed pixels and the skeletons: the same
    labels and people as over the whole image, also for skeletons reaching off the image."""
    h, w = 260, 400
    segs = []
    for cx, top, size, x0, y0, bw, bh, presence in people:
        prob = np.zeros((h, w), np.float32)
        prob[y0 : y0 + bh, x0 : x0 + bw] = 0.9
        segs.append(_segment(_stick(cx, top, size), prob, presence))
    config = SegmenterConfig(min_area=1e-4)
    want_labels, want_people = _compose_whole_image(segs, config, h * w)
    labels, got_people = compose_instances(segs, config, h * w)
    assert [id(p) for p in got_people] == [id(p) for p in want_people]
    if want_labels is None:
        assert labels is None
    else:
        assert np.array_equal(labels, want_labels)


class _HintModel:
    """A stand-in landmark model: nobody in any region, and no detections (counts the regions)."""

    def __init__(self):
        self.regions = 0

    def detect(self, image):
        return []

    def segment(self, image, roi):
        self.regions += 1
        h, w = image.shape[:2]
        return _segment(_stick(roi.centre[0], 0, 100), np.zeros((h, w)), presence=0.1)


def test_a_fruitless_hint_is_looked_at_again_only_after_hint_retry_frames_or_when_it_moves():
    model = _HintModel()
    seg = PersonSegmenter(model, SegmenterConfig(hint_retry=4))
    frame = np.zeros((200, 300, 3), np.uint8)
    still = (50.0, 40.0, 30.0, 80.0)  # a shadow: the same blob in every frame
    for _ in range(9):
        seg.segment(frame, [still])
    assert seg.hint_regions == 3  # frames 0, 4 and 8
    moved = (150.0, 40.0, 30.0, 80.0)
    seg.segment(frame, [still, moved])  # frame 9: the moved blob at once, the still one not
    assert seg.hint_regions == 4
    every = PersonSegmenter(_HintModel(), SegmenterConfig(hint_retry=1))
    for _ in range(5):
        every.segment(frame, [still])
    assert every.hint_regions == 5
    with pytest.raises(ValueError, match="hint_retry"):
        SegmenterConfig(hint_retry=0)


def test_compose_with_nobody():
    labels, people = compose_instances([], SegmenterConfig(), 100)
    assert labels is None and people == []


def test_segmenter_config_is_checked():
    with pytest.raises(ValueError, match="threshold"):
        SegmenterConfig(threshold=1.5)


def _fake_wheel(path: Path, payloads: dict[str, bytes]) -> None:
    with zipfile.ZipFile(path, "w") as zf:
        for member, data in payloads.items():
            zf.writestr(member, data)


def test_fetch_refuses_an_archive_with_the_wrong_hash(tmp_path):
    archives = tmp_path / "archives"
    archives.mkdir()
    _fake_wheel(
        archives / MEDIAPIPE_WHEEL.filename, {m.member: b"not a model" for m in MODELS.values()}
    )
    with pytest.raises(ValueError, match="SHA-256"):
        fetch_blazepose_models(tmp_path / "models", archive_dir=archives)
    assert not (tmp_path / "models").exists() or not any((tmp_path / "models").iterdir())


def test_fetch_from_a_folder_without_the_wheel_says_what_it_needs(tmp_path):
    with pytest.raises(FileNotFoundError, match=MEDIAPIPE_WHEEL.filename):
        fetch_blazepose_models(tmp_path / "models", archive_dir=tmp_path)


def test_missing_models_name_the_fix(tmp_path):
    """The fix names the folder that failed: the bare command filled the default cache."""
    with pytest.raises(
        BlazePoseModelsMissing, match=rf"python -m gst.detect fetch --models-dir {tmp_path}`"
    ):
        model_paths(tmp_path)


def test_pinned_model_hashes_are_well_formed():
    for m in MODELS.values():
        assert len(m.sha256) == 64 and int(m.sha256, 16) >= 0
    assert len(MEDIAPIPE_WHEEL.sha256) == 64 and MEDIAPIPE_WHEEL.platform


@NEEDS_MODELS
def test_a_damaged_cached_model_is_refused_and_fetched_again(tmp_path, capsys):
    """The pins were checked only while fetching: a model damaged in the cache was loaded (a
    few flipped bits give plausible wrong landmarks, more give NaN presence: people dropped),
    `fetch` reported success over it, and track's detection cache kept what it found."""
    import shutil

    from gst.detect.__main__ import main as detect_main
    from gst.detect.weights import BlazePoseModelsCorrupt

    models = tmp_path / "models"
    shutil.copytree(Path(model_paths()["landmarks"]).parent, models)
    landmarks = models / MODELS["landmarks"].name
    data = bytearray(landmarks.read_bytes())
    data[len(data) // 2] ^= 0xFF
    landmarks.write_bytes(bytes(data))
    with pytest.raises(BlazePoseModelsCorrupt, match=f"fetch --models-dir {models} --force"):
        model_paths(models)
    # fetch sees it and takes the models again (from a folder holding the pinned wheel's
    # members here: a fake wheel with the real model bytes)
    archives = tmp_path / "archives"
    archives.mkdir()
    real = {m.member: (Path(model_paths()[r])).read_bytes() for r, m in MODELS.items()}
    _fake_wheel(archives / MEDIAPIPE_WHEEL.filename, real)
    assert detect_main(["fetch", "--models-dir", str(models), "--from", str(archives)]) == 1
    assert "SHA-256" in capsys.readouterr().err  # the fake wheel is not the pinned wheel
    assert hashlib.sha256(landmarks.read_bytes()).hexdigest() != MODELS["landmarks"].sha256


@NEEDS_MODELS
def test_cached_models_match_their_pins():
    for role, p in model_paths().items():
        assert hashlib.sha256(p.read_bytes()).hexdigest() == MODELS[role].sha256


@NEEDS_MODELS
@NEEDS_LAB
def test_lab_frames_show_both_subjects_with_separate_full_masks():
    from gst.detect.blazepose import BlazePose
    from gst.detect.persons import PersonSegmenter

    model = BlazePose()
    cap = cv2.VideoCapture(str(LAB / "cam01.mp4"))
    seg = PersonSegmenter(model)
    counts = []
    for _ in range(12):
        ok, frame = cap.read()
        assert ok
        labels, people = seg.segment(cv2.resize(frame, (540, 960), interpolation=cv2.INTER_AREA))
        counts.append(len(people))
    # The man and the woman who barely moves (the background model never saw her whole).
    assert min(counts) == 2 and max(counts) == 2
    areas = np.bincount(labels.ravel(), minlength=3)[1:]
    assert areas.min() > 0.02 * labels.size  # whole bodies, not outlines
    for p in people:
        assert p.landmarks.shape == (33, 3) and 0.5 <= p.presence <= 1.0


@NEEDS_MODELS
@NEEDS_LAB
def test_lab_extraction_with_person_masks_keeps_two_ids(tmp_path):
    """Every 10th frame of the real capture: the man and the still woman, one id each, seen by
    at least two cameras in (nearly) every frame; masks cover most of each person's hull."""
    from calibration.formats import read_rig
    from gst.data import CropStore, ExtractOptions, extract_scene

    rig = read_rig(LAB / "Calib.qca.txt", "qualisys")
    videos = {p.stem: p for p in sorted(LAB.glob("cam0*.mp4"))}
    rep = extract_scene(
        videos,
        rig,
        tmp_path / "crops.h5",
        crop_size=64,
        frame_stride=10,
        options=ExtractOptions(persons=SegmenterConfig(), association_method="hull"),
    )
    assert rep.persons == 2
    assert rep.multiview_groups >= 18  # of 10 frames x 2 people
    support = np.asarray(
        CropStore(tmp_path / "crops.h5").index.column("mask_support").to_pylist(), float
    )
    assert np.nanmedian(support) > 0.6


@NEEDS_MODELS
@NEEDS_LAB
@pytest.mark.xfail(
    strict=True,
    reason="known, not corrected: landmarks are read half a crop pixel right of the person "
    "(median 0.9 crop px between a person and their mirror image). Correcting it "
    "(docs/person_models.md, last section) moved the demo, an unseen scene and the lab by "
    "about a millimetre both ways and changed the lab's tracking through occlusions, so it is "
    "not in",
)
def test_a_person_and_their_mirror_image_are_read_at_the_same_place():
    """The landmark model answers with pixel j spanning [j, j + 1) of its crop; read back with
    pixel centres at j, every landmark sits half a crop pixel right of the person: a region and
    its mirror image (the mirror's landmarks mapped back, left and right exchanged) disagree by
    0.93 crop px in x (median over lab people; an unbiased reading gives 0)."""
    from gst.body.markers import BLAZEPOSE_MIRROR
    from gst.detect.blazepose import LANDMARK_SIZE, BatchedLandmarks, BlazePose

    class Corners:  # a region given by its corners (the mirror's: right and left exchanged)
        def __init__(self, corners):
            self.c = np.asarray(corners, np.float32)

        def to_crop(self, size):
            return cv2.getAffineTransform(self.c[:3], np.float32([[0, 0], [size, 0], [0, size]]))

    detector, landmarks = BlazePose(), BatchedLandmarks()
    shifts = []
    for cam in ("cam01", "cam02", "cam03", "cam04"):
        cap = cv2.VideoCapture(str(LAB / f"{cam}.mp4"))
        for _ in range(20):
            ok, frame = cap.read()
        cap.release()
        assert ok
        img = cv2.resize(frame, (544, 960), interpolation=cv2.INTER_AREA)
        w = img.shape[1]
        mirror = np.ascontiguousarray(img[:, ::-1])
        for d in detector.detect(img):
            first = landmarks(img, [roi_from_alignment(d.keypoints[0], d.keypoints[1])])[0]
            if first.presence < 0.5:
                continue
            roi = first.next_roi
            seen = landmarks(img, [roi])[0].landmarks
            flipped = np.c_[w - 1 - roi.corners()[:, 0], roi.corners()[:, 1]][[1, 0, 3, 2]]
            back = landmarks(mirror, [Corners(flipped)])[0].landmarks[BLAZEPOSE_MIRROR]
            sure = (seen[:, 2] > 0.8) & (back[:, 2] > 0.8)
            dx = seen[sure, 0] - (w - 1 - back[sure, 0])
            shifts.append(np.median(dx) / (roi.side / LANDMARK_SIZE))
    assert len(shifts) >= 6
    assert abs(np.median(shifts)) < 0.4, shifts


@NEEDS_MODELS
@NEEDS_LAB
def test_person_detector_boxes_on_lab_video():
    from gst.track.person_detector import PersonModelDetector

    det = PersonModelDetector()
    cap = cv2.VideoCapture(str(LAB / "cam02.mp4"))
    counts = []
    for i in range(6):
        ok, frame = cap.read()
        found = det.detect(frame, i)
        counts.append(len(found))
        tall = 0
        for d in found:  # full-resolution boxes of standing people
            assert (
                0 <= d.box[0] < d.box[2] <= frame.shape[1]
                and 0 <= d.box[1] < d.box[3] <= frame.shape[0]
            )
            tall += d.box[3] - d.box[1] > 0.3 * frame.shape[0]
        assert tall == 2  # the two subjects; the third is the bystander, small at the back
    # the zoomed second look finds her from the first frame (`look_twice`)
    assert counts == [3] * 6


@settings(max_examples=40, deadline=None)
@given(st.floats(-500, 1500), st.floats(-500, 1500), st.floats(10, 900), st.floats(-3.2, 3.2))
def test_roi_corners_map_to_the_crops_corners(cx, cy, side, angle):
    roi = BodyRoi((cx, cy), side, angle)
    corners = roi.corners()
    crop = np.c_[corners, np.ones(4)] @ roi.to_crop(256).T
    np.testing.assert_allclose(crop, [[0, 0], [256, 0], [0, 256], [256, 256]], atol=1e-2)
    np.testing.assert_allclose(corners.mean(axis=0), (cx, cy), atol=1e-6 * (1 + abs(cx) + abs(cy)))


@pytest.mark.parametrize("shape", [(2, 64, 64, 1), (2, 64, 64, 4), (2, 64, 48, 3), (64, 64, 3)])
def test_crop_landmarks_refuse_what_is_not_square_colour_crops(shape):
    """A grey or RGBA crop had a channel read as colour (landmarks moved up to 53 px, no error);
    the check comes before the model is loaded."""
    from gst.detect.crops import detect_crop_landmarks

    with pytest.raises(ValueError, match=r"\(N, S, S, 3\)"):
        detect_crop_landmarks(np.zeros(shape, np.uint8), model=None, rgb=True)
    assert len(detect_crop_landmarks(np.zeros((0,)), model=object(), rgb=True)) == 0  # no crops


@pytest.mark.parametrize("masks_shape", [(1, 8, 8), (2, 4, 4), (2, 8, 8, 3)])
def test_crop_landmarks_refuse_masks_that_do_not_fit_the_crops(masks_shape):
    """Masks fewer than the crops, or of another size, failed mid-run with numpy's IndexError or
    broadcast error, naming neither; the check comes before the model is loaded."""
    from gst.detect.crops import detect_crop_landmarks

    with pytest.raises(ValueError, match=r"masks must be \(2, 8, 8\)"):
        detect_crop_landmarks(
            np.zeros((2, 8, 8, 3), np.uint8), None, rgb=True, masks=np.ones(masks_shape, bool)
        )


def _refine_reference(raw, heatmap, kernel=7, min_confidence=0.5):
    """MediaPipe's RefineLandmarksFromHeatmapCalculator, one landmark at a time (landmarks whose
    cell lies outside the heatmap left alone, as `refine_from_heatmaps` documents)."""
    out = raw.copy()
    h, w, p = heatmap.shape
    off = (kernel - 1) // 2
    for j in range(p):
        col, row = int(raw[j, 0] / 256 * w), int(raw[j, 1] / 256 * h)
        if not (0 <= col < w and 0 <= row < h):
            continue
        total = best = sx = sy = 0.0
        for r in range(max(0, row - off), min(h, row + off + 1)):
            for c in range(max(0, col - off), min(w, col + off + 1)):
                conf = 1 / (1 + math.exp(-heatmap[r, c, j]))
                total, best = total + conf, max(best, conf)
                sx, sy = sx + c * conf, sy + r * conf
        if best >= min_confidence and total > 0:
            out[j, 0], out[j, 1] = sx / w / total * 256, sy / h / total * 256
    return out


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(-3.0, 3.0))
def test_heatmap_refinement_matches_a_landmark_by_landmark_reference(seed, bias):
    from gst.detect.blazepose import refine_from_heatmaps

    rng = np.random.default_rng(seed)
    raw = rng.uniform(-30, 290, (2, 39, 5)).astype(np.float32)
    heat = (rng.normal(0, 2, (2, 64, 64, 39)) + bias).astype(np.float32)
    got = refine_from_heatmaps(raw, heat)
    for k in range(2):
        np.testing.assert_allclose(got[k], _refine_reference(raw[k], heat[k]), atol=1e-3)
    np.testing.assert_array_equal(got[..., 2:], raw[..., 2:])  # only x, y move


def test_heatmap_refinement_finds_a_peak_and_leaves_unsure_landmarks():
    from gst.detect.blazepose import refine_from_heatmaps

    heat = np.full((1, 64, 64, 2), -10.0, np.float32)
    heat[0, 20, 30, 0] = 10.0  # landmark 0: a sharp peak at cell (row 20, col 30)
    heat[0, 40, 10, 1] = -0.1  # landmark 1: its best cell under 50 % sure
    raw = np.array([[[121.0, 83.0, 0, 0, 0], [45.0, 161.0, 0, 0, 0]]], np.float32)
    got = refine_from_heatmaps(raw, heat)
    np.testing.assert_allclose(got[0, 0, :2], [30 / 64 * 256, 20 / 64 * 256], atol=1e-3)
    np.testing.assert_array_equal(got[0, 1], raw[0, 1])
    with pytest.raises(ValueError, match="heatmaps of shape"):
        refine_from_heatmaps(raw, heat[:, :, :, :1])


def test_look_twice_looks_again_only_where_a_sure_whole_person_was_doubted():
    from types import SimpleNamespace

    from gst.detect.persons import LIMB_JOINTS, look_twice

    def result(presence, confidence, x=50.0):
        lm = np.zeros((33, 3), np.float32)
        lm[:, 0], lm[:, 1] = x, np.linspace(10, 90, 33)
        lm[LIMB_JOINTS, 2] = confidence
        return SimpleNamespace(presence=presence, landmarks=lm, next_roi=("roi", presence, x))

    looked = []

    def look(rois):
        looked.extend(rois)
        return [result(0.99, 0.9) for _ in rois]

    results = [
        result(0.9, 0.9),  # present: kept
        result(0.2, 0.9),  # doubted, but sure and whole: looked at again
        result(0.2, 0.3),  # doubted and unsure of its limbs (a skeleton model): left
        result(0.2, 0.9, x=150.0),  # limbs beyond the 100-px-wide image: left
    ]
    out = look_twice(results, look, 0.5, (100, 100), 0.75)
    assert looked == [("roi", 0.2, 50.0)]
    assert out[0] is results[0] and out[2] is results[2] and out[3] is results[3]
    assert out[1].presence == 0.99
    assert look_twice(results[:1], look, 0.5, (100, 100), 0.75) == results[:1]


def test_frames_are_taken_as_uint8_bgr_or_refused():
    """A review: a uint16 frame gave no detection and a landmark reading 42 px off at presence
    0.997; grey and BGRA frames worked in one entry point and failed in another with LiteRT's
    or numpy's message. Grey and BGRA are converted, other dtypes refused by name."""
    from gst.detect.blazepose import as_bgr_frame
    from gst.detect.crops import detect_crop_landmarks

    bgr = np.random.default_rng(0).integers(0, 255, (6, 8, 3), dtype=np.uint8)
    assert as_bgr_frame(bgr) is bgr or np.shares_memory(as_bgr_frame(bgr), bgr)
    grey = bgr[..., 1].copy()
    np.testing.assert_array_equal(as_bgr_frame(grey), np.repeat(grey[..., None], 3, -1))
    np.testing.assert_array_equal(as_bgr_frame(grey[..., None]), as_bgr_frame(grey))
    bgra = np.concatenate([bgr, np.full((6, 8, 1), 7, np.uint8)], -1)
    np.testing.assert_array_equal(as_bgr_frame(bgra), bgr)
    for bad, message in (
        (bgr.astype(np.uint16) * 257, "uint8 .* got uint16"),
        (bgr / 255.0, "got float64"),
        (np.zeros((6, 8, 2), np.uint8), "grey or .* BGR, got shape"),
    ):
        with pytest.raises(ValueError, match=message):
            as_bgr_frame(bad)
    with pytest.raises(ValueError, match="crops must be uint8"):
        detect_crop_landmarks(np.zeros((1, 8, 8, 3), np.float32), object(), rgb=False)


@NEEDS_MODELS
def test_the_person_model_refuses_a_16_bit_frame():
    from gst.detect.blazepose import BlazePose, BodyRoi

    model = BlazePose(threads=1)
    frame = np.zeros((64, 48, 3), np.uint16)
    with pytest.raises(ValueError, match="uint16"):
        model.detect(frame)
    with pytest.raises(ValueError, match="uint16"):
        model.segment(frame, BodyRoi((24.0, 32.0), 40.0, 0.0))
    assert model.detect(np.zeros((64, 48), np.uint8)) == []  # grey: read as BGR


class _SquareFinder:
    """Warps as BlazePose.segment does and answers where a bright square lies in its input,
    edge-based as the landmark model's output is (0 = the input's left edge)."""

    def __init__(self):
        self.seen = []

    def segment(self, img, roi):
        from types import SimpleNamespace

        m = roi.to_crop(256)
        crop = cv2.warpAffine(img, m, (256, 256), flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT)  # fmt: skip
        self.seen.append(crop)
        g = crop[..., 1].astype(np.float64)
        vv, uu = np.mgrid[0:256, 0:256]
        centre = np.array([(g * uu).sum(), (g * vv).sum()]) / g.sum()
        xy = np.r_[centre + 0.5, 1.0] @ cv2.invertAffineTransform(m).T
        lms = np.zeros((33, 3), np.float32)
        lms[:, :2], lms[:, 2] = xy, 1.0
        return SimpleNamespace(landmarks=lms, world_landmarks=np.zeros((33, 3), np.float32),
                               presence=1.0)  # fmt: skip


@pytest.mark.parametrize("size", [256, 128, 200])
def test_a_crop_reaches_the_landmark_model_as_it_is_and_its_answer_comes_back_unshifted(size):
    """The whole-crop region sampled every pixel half a pixel up and left of itself: a blur with
    a half-dark first row and column. The answer is read back as on frames: half a model pixel
    right of and below the feature (0.5 x size / 256; docs/person_models.md)."""
    from gst.detect.crops import detect_crop_landmarks

    img = np.zeros((1, size, size, 3), np.uint8)
    img[0, 40:51, 70:77] = 255  # centre (73, 45)
    model = _SquareFinder()
    found = detect_crop_landmarks(img, model, rgb=False)
    half = 0.5 * size / 256
    np.testing.assert_allclose(found.landmarks[0, 0, :2], [73.0 + half, 45.0 + half], atol=0.06)
    if size == 256:
        np.testing.assert_array_equal(model.seen[0], img[0])
