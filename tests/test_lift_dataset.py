"""The landmark-world dataset: BlazePose's world landmarks, the .npz round trip, the world specs."""

import cv2
import numpy as np
import pytest

from gst.lift.dataset import FORMAT_VERSION, LandmarkWorld, world_spec
from tests.real_capture import LAB, NEEDS_LAB, NEEDS_MODELS


def _world(n: int = 5) -> LandmarkWorld:
    rng = np.random.default_rng(0)
    f32 = np.float32
    return LandmarkWorld(
        frame=np.arange(n, dtype=np.int32),
        person=np.ones(n, np.int16),
        camera=np.zeros(n, np.int16),
        camera_names=np.asarray(["00_00", "00_01"]),
        K_crop=np.tile(np.eye(3, dtype=f32), (n, 1, 1)),
        R=np.tile(np.eye(3, dtype=f32), (n, 1, 1)),
        t=rng.normal(size=(n, 3)).astype(f32),
        landmarks=rng.random((n, 33, 3)).astype(f32),
        presence=rng.random(n).astype(f32),
        world_landmarks=rng.normal(size=(n, 33, 3)).astype(f32),
        joints_world=rng.normal(size=(n, 24, 3)).astype(f32),
        joints2d=rng.normal(size=(n, 24, 2)).astype(f32),
        visible=rng.random((n, 24)) > 0.5,
        global_orient=rng.normal(size=(n, 3)).astype(f32),
        body_pose=rng.normal(size=(n, 23, 3)).astype(f32),
        betas=rng.normal(size=(n, 16)).astype(f32),
        transl=rng.normal(size=(n, 3)).astype(f32),
        crop_size=256,
        seed=5003,
        rig_kind="hall",
        fov_deg=55.5,
    )


def test_landmark_world_round_trip(tmp_path):
    w = _world()
    w.save(tmp_path / "world_5003.npz")
    assert not list(tmp_path.glob("*.tmp*"))  # written atomically, no leftovers
    back = LandmarkWorld.load(tmp_path / "world_5003.npz")
    assert len(back) == 5 and back.rig_kind == "hall" and back.seed == 5003
    assert back.crop_size == 256 and back.fov_deg == pytest.approx(55.5)
    for name in ("landmarks", "world_landmarks", "visible", "body_pose", "betas", "camera_names"):
        np.testing.assert_array_equal(getattr(back, name), getattr(w, name))


def test_landmark_world_rejects_other_versions_and_missing_keys(tmp_path):
    w = _world()
    w.save(tmp_path / "a.npz")
    with np.load(tmp_path / "a.npz") as z:
        d = dict(z)
    d["format_version"] = np.asarray(FORMAT_VERSION + 1)
    np.savez(tmp_path / "b.npz", **d)
    with pytest.raises(ValueError, match="format"):
        LandmarkWorld.load(tmp_path / "b.npz")
    d["format_version"] = np.asarray(FORMAT_VERSION)
    del d["presence"]
    np.savez(tmp_path / "c.npz", **d)
    with pytest.raises(ValueError, match="presence"):
        LandmarkWorld.load(tmp_path / "c.npz")


def test_world_specs_cycle_rigs_and_differ_by_seed():
    specs = [world_spec(k) for k in range(4)]
    assert [s.rig.kind for s in specs] == ["dome", "h36m", "hall", "dome"]
    assert [s.seed for s in specs] == [5000, 5001, 5002, 5003]
    assert specs[3].motions == [["random_static"]] * 2 and specs[0].motions is None
    assert len({s.rig.fov_deg for s in specs}) == 4
    assert all(40 <= s.rig.fov_deg <= 75 for s in specs)
    assert world_spec(2) == specs[2]  # deterministic


@NEEDS_MODELS
@NEEDS_LAB
def test_world_landmarks_are_hip_centred_metres_in_image_axes():
    from gst.detect.blazepose import BlazePose, roi_from_alignment

    model = BlazePose()
    cap = cv2.VideoCapture(str(LAB / "cam01.mp4"))
    ok, frame = cap.read()
    assert ok
    frame = cv2.resize(frame, (540, 960), interpolation=cv2.INTER_AREA)
    det = max(model.detect(frame), key=lambda d: d.score)
    seg = model.segment(frame, roi_from_alignment(det.keypoints[0], det.keypoints[1]))
    wl = seg.world_landmarks
    assert wl.shape == (33, 3) and wl.dtype == np.float32 and np.isfinite(wl).all()
    assert np.linalg.norm(wl[[23, 24]].mean(0)) < 0.03  # origin at the mid-hips
    # metres: a standing adult's shoulders 0.25-0.5 m apart, nose to ankles 1.2-1.9 m
    assert 0.25 < np.linalg.norm(wl[11] - wl[12]) < 0.5
    height = wl[[27, 28], 1].mean() - wl[0, 1]
    assert 1.2 < height < 1.9  # y points down the image (head above the ankles: smaller y)
    # the same person as the image landmarks: left-right along image x agrees in sign
    du_img = seg.landmarks[11, 0] - seg.landmarks[12, 0]
    assert np.sign(wl[11, 0] - wl[12, 0]) == np.sign(du_img)


def test_named_worlds_names_a_malformed_item():
    from gst.lift.dataset import named_worlds

    assert named_worlds([]) == {}
    with pytest.raises(SystemExit, match="NAME=PATH, got 'demo'"):
        named_worlds(["demo"])
