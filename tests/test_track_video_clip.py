"""`track --video` on a real clip that is no camera of any scene: 20 frames cut from the lab
capture, renamed, tracked through `gst.track.scene.track_scene` with a small GST network built
here. The learned person model is chosen by default, each person visible gets one id over the
clip, the landmark model's 2D joints land inside the person masks of the landmark model's own
segmentation, and the file says what ran (detector, model, no world coordinates)."""

import json
import logging

import cv2
import numpy as np
import pyarrow.parquet as pq
import pytest

from gst.detect.blazepose import BlazePose
from gst.detect.persons import LIMB_JOINTS, PersonSegmenter, SegmenterConfig
from tests.real_capture import LAB, NEEDS_MODELS_AND_LAB

FIRST, N = 60, 20  # cam04 60..79: the man's arms over the woman, and a duplicate region (70-77)
SCALE = 0.5  # 544 x 960: the person model's work resolution, quicker to decode and crop

pytestmark = NEEDS_MODELS_AND_LAB


def _request(d, clip):
    """The request the clip is tracked with: the network and outputs in the fixture's folder."""
    from calibration.formats import read_rig
    from gst.track.scene import TrackRequest

    return TrackRequest(
        videos=[clip],
        checkpoint=d / "gst.pt",
        rig=read_rig(LAB / "Calib.qca.txt", "qualisys"),
        tracks_dir=d / "tracks",
        reports_dir=d / "reports",
        staging=d / "staging",
        scene="lab",
    )


@pytest.fixture(scope="module")
def tracked(tmp_path_factory):
    import torch

    from gst.body import load_body_model
    from gst.model.checkpoint import save_checkpoint
    from gst.model.presets import get_preset
    from gst.track.scene import TrackSettings, track_scene
    from gst.train.recipe import build_network

    d = tmp_path_factory.mktemp("clip")
    cap = cv2.VideoCapture(str(LAB / "cam04.mp4"))
    cap.set(cv2.CAP_PROP_POS_FRAMES, FIRST)
    frames = []
    for _ in range(N):
        ok, f = cap.read()
        assert ok
        frames.append(cv2.resize(f, None, fx=SCALE, fy=SCALE, interpolation=cv2.INTER_AREA))
    cap.release()
    h, w = frames[0].shape[:2]
    clip = d / "match.mp4"  # not a camera name of the lab rig
    vw = cv2.VideoWriter(str(clip), cv2.VideoWriter_fourcc(*"mp4v"), 60.0, (w, h))
    for f in frames:
        vw.write(f)
    vw.release()
    torch.manual_seed(0)
    net, ids, groups = build_network(get_preset("tiny"), load_body_model("anny"))
    save_checkpoint(d / "gst.pt", net, "anny", ids, groups)
    request = _request(d, clip)
    logger = logging.getLogger("gst.track")
    records: list[str] = []
    handler = logging.Handler()
    handler.emit = lambda r: records.append(r.getMessage())
    logger.addHandler(handler)
    old = logger.level
    logger.setLevel(logging.INFO)
    try:
        (outcome,) = track_scene(TrackSettings(overlay=False), request)
    finally:
        logger.removeHandler(handler)
        logger.setLevel(old)
    return outcome.result.path, frames, records


def test_learned_person_model_by_default_and_said_so(tracked):
    path, _, log = tracked
    meta = {k.decode(): json.loads(v) for k, v in pq.read_schema(path).metadata.items()}
    assert meta["gst.detector"]["name"] == "blazepose"
    assert "installed" in meta["gst.detector"]["why"]
    assert any(m.startswith("person detector: blazepose") for m in log)
    # a model that has not seen this camera does not pretend
    assert meta["gst.model"]["seen_this_camera"] is False
    assert meta["gst.model"]["trained_on"]["scene"] == "lab"
    # an image-only network (no landmark tokens) takes its pose from the image, and says so
    assert meta["gst.model"]["pose_input"] == "image"
    assert meta["gst.model"]["reprojection_feedback"] == 0
    assert any("pose from image" in m for m in log)
    assert meta["gst.calibration"]["calibrated"] is False
    assert meta["gst.axes"]["joints3d"] == "camera" and meta["gst.axes"]["world"] is None
    assert any("no world coordinates" in m for m in log)
    assert meta["gst.format_version"] == 2 and len(meta["gst.landmark_names"]) == 33


def test_one_id_per_person_visible(tracked):
    from gst.track import read_tracks

    t = read_tracks(tracked[0])
    frames, ids = t.column("frame").to_numpy(), t.column("person_id").to_numpy()
    # two people are visible (the bystander at the back is not found in cam04: small, hidden)
    assert sorted(set(ids.tolist())) == [0, 1]
    for p in (0, 1):
        np.testing.assert_array_equal(np.sort(frames[ids == p]), np.arange(N))


def test_landmarks_fall_inside_the_person_masks(tracked):
    from gst.track import column_array, read_tracks

    path, frames, _ = tracked
    t = read_tracks(path)
    f = t.column("frame").to_numpy()
    lm, conf = column_array(t, "landmarks2d"), column_array(t, "landmarks_conf")
    seg = PersonSegmenter(BlazePose(), SegmenterConfig())
    inside, total = 0, 0
    for i in (0, 10, 19):  # the landmark model's own segmentation, through the extraction path
        labels, _ = seg.segment(frames[i])
        mask = cv2.dilate((labels > 0).astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
        for r in np.flatnonzero(f == i):
            sure = conf[r, LIMB_JOINTS] >= 0.8
            uv = np.round(lm[r, LIMB_JOINTS][sure]).astype(int)
            ok = (uv >= 0).all(1) & (uv[:, 0] < mask.shape[1]) & (uv[:, 1] < mask.shape[0])
            inside += int(mask[uv[ok, 1], uv[ok, 0]].sum())
            total += len(uv)
    assert total >= 3 * 2 * 8  # most limb joints of both people are sure
    assert inside >= 0.9 * total


def test_a_finished_file_kept_from_an_earlier_run_claims_no_speed(tracked):
    """A rerun that finds the video's file finished with the same settings keeps it and tracks
    nothing: its summary said 7934 frames/s (frames over the time it took to notice)."""
    from gst.track.scene import TrackSettings, track_scene

    path = tracked[0]
    d = next(p for p in path.parents if (p / "gst.pt").is_file())  # the fixture's folder
    summary_path = d / "reports" / "match" / "summary.json"
    first = json.loads(summary_path.read_text())
    assert first["kept_from_earlier_run"] is False and 0 < first["fps"] < 1000
    (outcome,) = track_scene(TrackSettings(overlay=False), _request(d, d / "match.mp4"))
    assert outcome.result.path == path
    again = json.loads(summary_path.read_text())
    assert again["kept_from_earlier_run"] is True
    assert again["fps"] is None and again["seconds"] is None
    assert again["frames"] == first["frames"] and again["rows"] == first["rows"]
