"""End to end on real (synthetic) video files: ids, geometry, smoothing, partitioned output."""

import json

import numpy as np
import pyarrow as pa
import pyarrow.dataset as ds
import pyarrow.parquet as pq
import pytest
from scipy.spatial.transform import Rotation

from calibration import Camera
from gst.data.camera_view import TrackingView
from gst.track import (
    BoxDepthPredictor,
    Detection,
    OneEuroConfig,
    SuppliedBoxes,
    TrackOptions,
    column_array,
    long_format,
    read_metadata,
    read_tracks,
    track_video,
)
from gst.track.schema import METADATA_KEYS, SMPL_JOINT_NAMES
from gst.track.tracker import box_iou
from tests.track_synthetic import MODEL, H, W, crossing_clip, write_boxes_csv

N = 40


def occlusion_visibility(boxes, walkers, min_visible=0.6):
    """A walker is detected unless someone drawn in front covers more than 40% of its box."""
    vis = np.ones(boxes.shape[:2], bool)
    for i in range(len(boxes)):
        for k, wk in enumerate(walkers):
            area = np.prod(boxes[i, k, 2:] - boxes[i, k, :2])
            for m, wm in enumerate(walkers):
                if wm.depth_order > wk.depth_order:
                    lo, hi = (
                        np.maximum(boxes[i, k, :2], boxes[i, m, :2]),
                        np.minimum(boxes[i, k, 2:], boxes[i, m, 2:]),
                    )
                    if np.prod(np.clip(hi - lo, 0, None)) > (1 - min_visible) * area:
                        vis[i, k] = False
    return vis


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("scene")
    walkers, boxes, video = crossing_clip(d, N, W, H)
    vis = occlusion_visibility(boxes, walkers)
    csv = write_boxes_csv(d / "boxes.csv", boxes, "clip", vis)
    return {"dir": d, "video": video, "boxes": boxes, "visible": vis, "csv": csv}


def track_scene(scene, out, detector=None, predictor=None, model=MODEL, **kwargs):
    """`track_video` of the scene's clip into `out`; by default with its truth boxes (boxes.csv)
    and the box-depth baseline predictor."""
    if detector is None:
        detector = SuppliedBoxes.from_file(scene["csv"])
    if predictor is None:
        predictor = BoxDepthPredictor()
    return track_video(scene["video"], out, detector, predictor, model=model, **kwargs)


def truth_identity(table, boxes):
    """The walker each row's box belongs to (boxes come straight from the truth file)."""
    frames = table.column("frame").to_numpy()
    bb = column_array(table, "bbox")
    return np.array(
        [int(np.argmax(box_iou(b, boxes[f])[0])) for f, b in zip(frames, bb, strict=True)]
    )


def test_a_known_lens_sets_the_uncalibrated_camera(scene, tmp_path):
    """`focal_35mm` gives the default camera its focal length (diagonals matched): recorded in
    the file, still uncalibrated, and the bodies are seen through it (other depths, other
    projections); the agreement check rebuilds that camera from the file."""
    plain = track_scene(scene, tmp_path / "plain")
    lens = track_scene(scene, tmp_path / "lens", options=TrackOptions(focal_35mm=26.0))
    cal = read_metadata(lens.path)["calibration"]
    assert cal["calibrated"] is False
    assert cal["K"][0][0] == pytest.approx(26.0 / np.hypot(36, 24) * np.hypot(W, H))
    assert TrackingView.from_json(cal).camera.fx == pytest.approx(cal["K"][0][0])
    a, b = read_tracks(plain.path), read_tracks(lens.path)
    za = column_array(a, "transl_cam")[:, 2]
    zb = column_array(b, "transl_cam")[:, 2]
    # the same boxes at a shorter focal length: the same people stand nearer
    np.testing.assert_allclose(zb / za, 26.0 / np.hypot(36, 24), rtol=1e-3)
    with pytest.raises(ValueError, match="focal_35mm must be > 0"):
        TrackOptions(focal_35mm=0.0)


def test_crossing_people_keep_their_ids(scene, tmp_path):
    assert (~scene["visible"]).sum() >= 3, "the scene must contain occluded frames"
    res = track_scene(
        scene,
        tmp_path,
        SuppliedBoxes.from_file(scene["csv"], "clip"),
        options=TrackOptions(frames_per_group=9, batch_size=4),
    )
    t = read_tracks(res.path)
    assert t.num_rows == res.rows == scene["visible"].sum()
    who = truth_identity(t, scene["boxes"])
    pid = t.column("person_id").to_numpy()
    mapping = {w: set(pid[who == w]) for w in range(3)}
    assert all(len(v) == 1 for v in mapping.values()), f"id switches: {mapping}"
    assert len({next(iter(v)) for v in mapping.values()}) == 3 and res.persons == 3
    assert naive_iou_switches(t, who) > 0, (
        "the scene is too easy: frame-to-frame box overlap alone solves it"
    )


def naive_iou_switches(table, who):
    """Id switches of a naive tracker: each box takes the id of the most overlapping box of the
    previous processed frame (no motion, depth or appearance)."""
    frames = table.column("frame").to_numpy()
    boxes = column_array(table, "bbox")
    prev_boxes, prev_ids, next_id, switches, owner = None, None, 0, 0, {}
    for f in np.unique(frames):
        cur = boxes[frames == f]
        ids = []
        for b in cur:
            if prev_boxes is not None and len(prev_boxes) and box_iou(b, prev_boxes).max() > 0:
                ids.append(prev_ids[int(np.argmax(box_iou(b, prev_boxes)[0]))])
            else:
                ids.append(next_id)
                next_id += 1
        for i, w in zip(ids, who[frames == f], strict=True):
            switches += owner.setdefault(w, i) != i
            owner[w] = i
        prev_boxes, prev_ids = cur, ids
    return switches


def test_metadata_is_complete_and_self_describing(scene, tmp_path):
    res = track_scene(
        scene, tmp_path, model={**MODEL, "preset": "tiny"}, options=TrackOptions(stride=2)
    )
    schema = pq.read_schema(res.path)
    assert {k.decode() for k in schema.metadata} >= set(METADATA_KEYS)
    meta = read_metadata(res.path)
    assert meta["joint_names"] == list(SMPL_JOINT_NAMES) and len(meta["joint_names"]) == 24
    assert meta["fps"] == 30.0 and meta["model"] == {**MODEL, "preset": "tiny"}
    assert meta["units"]["joints3d"] == "m" and meta["units"]["joints2d"] == "px"
    assert meta["axes"]["joints3d"] == "camera" and "OpenCV" in meta["axes"]["camera"]
    cal = meta["calibration"]
    assert cal["calibrated"] is False and cal["K"][0][0] == pytest.approx(np.hypot(W, H))
    assert meta["video"]["stride"] == 2 and meta["video"]["frame_count"] == N
    assert (
        meta["stats"]["rows"] == pq.read_metadata(res.path).num_rows
        and meta["stats"]["frames"] == N // 2
    )
    assert meta["columns"]["joints3d"]["shape"] == [24, 3] and meta["smoothing"] is None
    for name in ("bbox", "joints3d", "joints2d", "body_pose", "betas"):
        field = schema.field(name)
        assert json.loads(field.metadata[b"shape"]) == meta["columns"][name]["shape"]
    t = read_tracks(res.path)
    assert sorted(set(t.column("frame").to_pylist())) == list(range(0, N, 2))
    assert t.column("transl_world").null_count == t.num_rows  # uncalibrated: no world values
    assert np.isnan(column_array(t, "transl_world")).all()
    lf = long_format(t)
    assert lf.num_rows == 24 * t.num_rows and lf.column("joint")[1].as_py() == "left_hip"


class RigidBodyPredictor:
    """An SMPL-consistent double: rest joints with a non-zero root J0, rotated about J0 by a
    per-crop orientation, then translated: joints = R (J - J0) + J0 + T."""

    J = np.random.default_rng(7).normal(0, 0.3, (24, 3)) + [0.0, 0.2, 0.0]
    BODY_POSE = np.random.default_rng(8).uniform(-1.0, 1.0, (23, 3))  # axis-angle, |angle| < pi

    def __call__(self, crops, K_crop):
        base = BoxDepthPredictor()(crops, K_crop)
        R = Rotation.from_rotvec(
            np.stack([[0.3, 2.5 + k[0, 2] * 1e-3, 0.2] for k in K_crop])
        ).as_matrix()
        J0 = self.J[0]
        T = base["transl_cam"] - J0  # pelvis lands where the baseline puts it
        joints = np.einsum("bij,nj->bni", R, self.J - J0) + J0 + T[:, None]
        rot = base["rotmats"].copy()
        rot[:, 0] = R
        rot[:, 1:] = Rotation.from_rotvec(self.BODY_POSE).as_matrix()
        return {
            "rotmats": rot,
            "betas": np.zeros((len(crops), 10)),
            "transl_cam": T,
            "joints_cam": joints,
        }


def tilted_camera():
    R = Rotation.from_euler("xyz", [-100, 5, 20], degrees=True).as_matrix()
    K = [[380.0, 0, 161.0], [0, 385.0, 118.0], [0, 0, 1]]
    return Camera.create(
        "cam01", K, [-0.2, 0.05, 0.001, 0.0, 0.0], R, -R @ np.array([1.0, -6.0, 1.5]), W, H
    )


def test_calibrated_camera_gives_consistent_world_values(scene, tmp_path):
    cam = tilted_camera()
    res = track_scene(
        scene, tmp_path, predictor=RigidBodyPredictor(), camera=cam, world_up=[0, 0, 1]
    )
    t = read_tracks(res.path)
    meta = read_metadata(res.path)
    assert meta["calibration"]["calibrated"] and meta["axes"]["joints3d"] == "world"
    assert meta["axes"]["world"]["up"] == [0, 0, 1]
    j3 = column_array(t, "joints3d").astype(np.float64)
    # joints2d is the calibrated camera's own projection (with distortion) of the world joints
    uv = cam.project(j3.reshape(-1, 3)).reshape(-1, 24, 2)
    np.testing.assert_allclose(column_array(t, "joints2d"), uv, atol=2e-2)
    # world orientation and transl_world drive the body model to the same world joints
    R_w = Rotation.from_rotvec(column_array(t, "global_orient")).as_matrix()
    R_c = Rotation.from_rotvec(column_array(t, "global_orient_cam")).as_matrix()
    np.testing.assert_allclose(R_w, cam.R.T @ R_c, atol=1e-5)
    body_pose = column_array(t, "body_pose")
    np.testing.assert_allclose(
        body_pose, np.broadcast_to(RigidBodyPredictor.BODY_POSE, body_pose.shape), atol=1e-6
    )
    J0 = RigidBodyPredictor.J[0]
    posed = (
        np.einsum("bij,nj->bni", R_w, RigidBodyPredictor.J - J0)
        + J0
        + column_array(t, "transl_world")[:, None]
    )
    np.testing.assert_allclose(posed, j3, atol=1e-4)
    # and the pelvis sits in front of the camera, projected into its box
    box = column_array(t, "bbox")
    pel = column_array(t, "joints2d")[:, 0]
    assert (
        (pel[:, 0] > box[:, 0])
        & (pel[:, 0] < box[:, 2])
        & (pel[:, 1] > box[:, 1])
        & (pel[:, 1] < box[:, 3])
    ).all()


class JitteryPredictor:
    """The baseline plus deterministic noise on the joints (seeded by the crop intrinsics)."""

    def __call__(self, crops, K_crop):
        out = BoxDepthPredictor()(crops, K_crop)
        for b, k in enumerate(K_crop):
            rng = np.random.default_rng(int(abs(k[0, 2] * 1000)) % 2**32)
            out["joints_cam"][b] += rng.normal(0, 0.05, (24, 3))
        return out


def test_smoothing_reduces_jitter(scene, tmp_path):
    def run(smoothing, sub):
        res = track_scene(
            scene,
            tmp_path / sub,
            predictor=JitteryPredictor(),
            options=TrackOptions(smoothing=smoothing),
        )
        t = read_tracks(res.path)
        j = column_array(t, "joints3d")
        pid = t.column("person_id").to_numpy()
        return np.mean(
            [np.abs(np.diff(j[pid == p], 2, axis=0)).mean() for p in np.unique(pid)]
        ), res.path

    raw, _ = run(None, "raw")
    smooth, path = run(OneEuroConfig(min_cutoff=0.5, beta=0.0, d_cutoff=1.0), "smooth")
    assert smooth < 0.5 * raw
    assert read_metadata(path)["smoothing"] == {"min_cutoff": 0.5, "beta": 0.0, "d_cutoff": 1.0}


def test_many_videos_form_a_hive_dataset(scene, tmp_path):
    det = SuppliedBoxes.from_file(scene["csv"])
    for name in ("cam 1", "cam2"):  # a space must survive the partition path
        track_scene(scene, tmp_path, det, video_name=name, options=TrackOptions(end_s=0.5))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["video=cam%201", "video=cam2"]
    dataset = ds.dataset(tmp_path, format="parquet", partitioning="hive")
    t = dataset.to_table()
    assert sorted(set(t.column("video").to_pylist())) == ["cam 1", "cam2"]
    assert t.num_rows == 2 * 15 * 3
    one = read_tracks(tmp_path, videos=["cam 1"])
    assert set(one.column("video").to_pylist()) == {"cam 1"} and one.num_rows == 45


def test_video_names_that_look_like_numbers_stay_text(scene, tmp_path):
    det = SuppliedBoxes.from_file(scene["csv"])
    for name in ("0001", "2"):  # an inferred partition type would make them integers 1 and 2
        track_scene(scene, tmp_path, det, video_name=name, options=TrackOptions(end_s=0.2))
    t = read_tracks(tmp_path)
    assert t.schema.field("video").type == pa.string()
    assert sorted(set(t.column("video").to_pylist())) == ["0001", "2"]
    assert read_tracks(tmp_path, videos=["0001"]).num_rows == t.num_rows // 2


class MaskingDetector:
    """Truth boxes plus full-frame masks of the box interiors."""

    def __init__(self, boxes):
        self.boxes = boxes

    def detect(self, frame_bgr, frame_index):
        out = []
        for b in self.boxes.detect(frame_bgr, frame_index):
            m = np.zeros(frame_bgr.shape[:2], bool)
            x0, y0, x1, y1 = b.box.astype(int)
            m[y0:y1, x0:x1] = True
            out.append(Detection(b.box, b.score, mask=m))
        return out


def test_detections_with_masks_track_the_same(scene, tmp_path):
    det = MaskingDetector(SuppliedBoxes.from_file(scene["csv"]))
    res = track_scene(scene, tmp_path, det)
    t = read_tracks(res.path)
    who = truth_identity(t, scene["boxes"])
    pid = t.column("person_id").to_numpy()
    assert all(len(set(pid[who == w])) == 1 for w in range(3)) and res.persons == 3


class EveryThirdFrame:
    """Truth boxes on frames 0, 3, 6, ...; nothing on the others (detector misses)."""

    def __init__(self, boxes):
        self.boxes = boxes

    def detect(self, frame_bgr, frame_index):
        return self.boxes.detect(frame_bgr, frame_index) if frame_index % 3 == 0 else []


def test_frames_without_detections(scene, tmp_path):
    res = track_scene(
        scene,
        tmp_path,
        EveryThirdFrame(SuppliedBoxes.from_file(scene["csv"])),
        options=TrackOptions(frames_per_group=4),
    )
    t = read_tracks(res.path)
    assert set(t.column("frame").to_pylist()) == set(range(0, N, 3)) and res.frames == N
    who = truth_identity(t, scene["boxes"])
    pid = t.column("person_id").to_numpy()
    assert all(len(set(pid[who == w])) == 1 for w in range(3))


def test_non_finite_predictions_are_dropped_and_counted(scene, tmp_path):
    class SometimesNaN(BoxDepthPredictor):
        calls = 0

        def __call__(self, crops, K_crop):
            out = super().__call__(crops, K_crop)
            SometimesNaN.calls += 1
            if SometimesNaN.calls % 3 == 0:
                out["joints_cam"][0, 5, 1] = np.nan
            return out

    res = track_scene(scene, tmp_path, predictor=SometimesNaN(), options=TrackOptions(batch_size=4))
    stats = read_metadata(res.path)["stats"]
    assert stats["dropped_nonfinite"] > 0
    assert (
        stats["rows"] + stats["dropped_nonfinite"] == stats["detections"] == scene["visible"].sum()
    )
    assert np.isfinite(column_array(read_tracks(res.path), "joints3d")).all()


def test_extra_outputs_reach_the_callback_per_row(scene, tmp_path):
    class WithGaussians(BoxDepthPredictor):
        def __call__(self, crops, K_crop):
            out = super().__call__(crops, K_crop)
            out["gaussian_means"] = out["joints_cam"][:, :1] + np.zeros(
                (len(crops), 5, 3)
            )  # stand-in payload
            return out

    class Shuffled:  # detection order differs from id order from frame 10 on
        boxes = SuppliedBoxes.from_file(scene["csv"])

        def detect(self, frame_bgr, frame_index):
            d = self.boxes.detect(frame_bgr, frame_index)
            return d[::-1] if frame_index >= 10 else d

    got = []
    res = track_scene(
        scene,
        tmp_path,
        Shuffled(),
        WithGaussians(),
        options=TrackOptions(batch_size=4, frames_per_group=6),
        on_extra=lambda f, p, extra: got.append((f, p, extra["gaussian_means"])),
    )
    t = read_tracks(res.path)
    assert [(f, p) for f, p, _ in got] == list(
        zip(t.column("frame").to_pylist(), t.column("person_id").to_pylist(), strict=True)
    )
    pelvis = column_array(t, "joints3d")[:, 0]
    np.testing.assert_allclose(np.stack([g[0] for _, _, g in got]), pelvis, atol=1e-5)


def test_video_with_nobody_gives_an_empty_valid_file(scene, tmp_path):
    class Nobody:
        def detect(self, frame_bgr, frame_index):
            return []

    res = track_scene(scene, tmp_path, Nobody(), options=TrackOptions(frames_per_group=16))
    t = read_tracks(res.path)
    assert t.num_rows == 0 and res.frames == N and read_metadata(res.path)["stats"]["frames"] == N
    assert column_array(t, "joints3d").shape == (0, 24, 3)


def test_predictor_with_wrong_betas_count_is_named(scene, tmp_path):
    class Eleven(BoxDepthPredictor):
        def __init__(self):
            super().__init__(num_betas=11)

    with pytest.raises(ValueError, match="returned 11 betas per person, expected num_betas = 10"):
        track_scene(scene, tmp_path, predictor=Eleven())


def test_a_group_answers_an_input_it_has_seen_without_the_network():
    """A person who stands still keeps their landmarks, so their network input repeats: the
    group predicts each distinct input once and gives repeats the same answer, in order."""
    from gst.track.baseline import BoxDepthPredictor
    from gst.track.frames import PreparedDetection
    from gst.track.loop import _Group

    calls = []
    inner = BoxDepthPredictor()

    def predictor(crops, K):
        calls.append(len(crops))
        return inner(crops, K)

    def det(f):
        K = np.array([[f, 0, 127.5], [0, f, 127.5], [0, 0, 1]])
        lms = np.full((33, 3), np.nan, np.float32)
        return PreparedDetection(np.zeros((256, 256, 3), np.uint8), K, np.zeros(8), lms)

    group = _Group(predictor, batch_size=4, num_betas=10)
    inputs = [det(500.0), det(600.0), det(500.0), det(500.0), det(700.0), det(600.0)]
    group.add(None, inputs)
    poses = group.predictions()
    assert calls == [2, 1]  # batch 1: 500 and 600 (two repeats of 500); batch 2: 700 (600 seen)
    assert group.reused == 3 and len(poses) == 6
    alone = inner(np.stack([d.crop_rgb for d in inputs]), np.stack([d.K_crop for d in inputs]))
    np.testing.assert_allclose(poses.transl_cam, alone["transl_cam"])
    # a new group (a resume starts at one) remembers nothing
    fresh = _Group(predictor, batch_size=4, num_betas=10)
    fresh.add(None, [det(500.0)])
    fresh.predictions()
    assert calls == [2, 1, 1]


def test_blank_crops_are_told_apart_by_their_camera_and_landmarks():
    """A crop not cut (pose from the landmarks) is keyed by name, not by its pixels: two blank
    inputs are one input only where their crop camera and landmarks agree too."""
    from gst.track.frames import PreparedDetection, _blank
    from gst.track.loop import _input_key

    K = np.array([[500.0, 0, 127.5], [0, 500.0, 127.5], [0, 0, 1]])
    lms = np.random.default_rng(0).uniform(0, 256, (33, 3)).astype(np.float32)

    def det(crop, K, lms):
        return _input_key(PreparedDetection(crop, K, np.zeros(8), lms))

    blank = _blank(256)
    assert det(blank, K, lms) == det(blank, K.copy(), lms.copy())
    assert det(blank, K * [[1.01], [1.01], [1]], lms) != det(blank, K, lms)
    moved = lms.copy()
    moved[5, 0] += 0.5
    assert det(blank, K, moved) != det(blank, K, lms)
    cut = np.zeros((256, 256, 3), np.uint8)  # a cut crop's pixels are read, even when black
    assert det(cut, K, lms) == det(cut.copy(), K, lms) != det(blank, K, lms)
