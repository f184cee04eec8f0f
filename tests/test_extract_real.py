"""Id linking, standing-height geometry, truthless proxies, and (when the real lab capture is
on this machine) id stability of single-camera tracking on it."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration import Camera
from calibration.camera import look_at_rotation
from calibration.triangulate import dlt_points
from gst.data.association import link_tracklets
from gst.data.ground import ground_seed
from gst.track.static_detector import group_boxes
from gst.track.tracker import Observation, Tracker, TrackerConfig
from tests.real_capture import LAB, NEEDS_LAB


def _walk(steps, start, velocity):
    return [(s, np.asarray(start, float) + np.asarray(velocity, float) * s / 60) for s in steps]


def test_link_joins_lost_and_interleaved_pieces_but_not_two_people():
    a = _walk(range(0, 30), [0, 0], [1, 0])
    a_again = _walk(range(45, 90), [0, 0], [1, 0])  # the same person after a 15-frame loss
    b = _walk(range(0, 90), [2, 2], [0, -0.5])  # another person, always there
    # one person whose id alternated between 5 and 6 every few frames
    c = _walk(range(0, 90), [-2, 0], [0, 1])
    c5 = [o for o in c if (o[0] // 4) % 2 == 0]
    c6 = [o for o in c if (o[0] // 4) % 2 == 1]
    link = link_tracklets(
        {1: a, 2: b, 3: a_again, 5: c5, 6: c6}, 1 / 60, speed=2.0, slack=0.5, max_gap=60
    )
    assert link == {1: 1, 2: 2, 3: 1, 5: 5, 6: 5}


def test_link_never_joins_pieces_seen_in_the_same_frame():
    a = _walk(range(0, 20), [0, 0], [0, 0])
    b = _walk(range(10, 40), [0.1, 0], [0, 0])  # overlaps a in frames 10..19
    assert link_tracklets({1: a, 2: b}, 1 / 60, 2.0, 0.5, 60) == {1: 1, 2: 2}


def _camera(pos, target=(0.0, 0.0, 1.0)):
    R = look_at_rotation(np.asarray(pos, float), np.asarray(target, float))
    return Camera.create(
        "c",
        [[1200.0, 0, 540.0], [0, 1200.0, 960.0], [0, 0, 1]],
        [-0.05, 0.1, 0, 0, 0],
        R,
        -R @ np.asarray(pos, float),
        1088,
        1920,
    )


@settings(max_examples=40, deadline=None)
@given(st.floats(-1.5, 1.5), st.floats(-1.5, 1.5), st.floats(1.2, 2.1))
def test_ground_seed_recovers_feet_and_height(x, y, height):
    cam = _camera([4.0, -3.0, 2.0])
    feet, head = np.array([x, y, 0.0]), np.array([x, y, height])
    uv = cam.project(np.stack([feet, head]))
    # a box whose bottom/top centres are exactly these pixel centres (corner convention +0.5)
    box = np.array([uv[0, 0] - 40 + 0.5, uv[1, 1] + 0.5, uv[0, 0] + 40 + 0.5, uv[0, 1] + 0.5])
    box[[0, 2]] = 0.5 * (uv[0, 0] + uv[1, 0]) + 0.5 + np.array([-40, 40])
    seed = ground_seed(cam, box, (0, 0, 1))
    assert seed is not None
    # one column for feet and head, while the vertical line projects slightly slanted: the
    # error stays small (the camera is 5 m away)
    assert np.linalg.norm(seed.ground[:2] - feet[:2]) < 0.15
    assert abs(seed.height - height) < 0.1


def test_ground_seed_rejects_rays_that_miss_the_floor():
    cam = _camera([4.0, -3.0, 2.0], target=(-4.0, 3.0, 3.0))  # looking up: top rows see the ceiling
    assert ground_seed(cam, np.array([500.0, 10.0, 560.0, 40.0]), (0, 0, 1)) is None


@settings(max_examples=30, deadline=None)
@given(st.floats(-2, 2), st.floats(-2, 2), st.floats(0, 2))
def test_dlt_triangulation_recovers_a_point(x, y, z):
    X = np.array([x, y, z])
    cams = [_camera(p) for p in ([4, -3, 2], [-4, -3, 2.2], [0, 5, 2.5])]
    P = np.stack([c.K @ np.c_[c.R, c.t.reshape(3, 1)] for c in cams])
    uv = np.stack([(Pi @ np.append(X, 1))[:2] / (Pi @ np.append(X, 1))[2] for Pi in P])
    np.testing.assert_allclose(dlt_points(P, uv[:, None, :])[0], X, atol=1e-6)


def test_group_boxes_joins_stacked_pieces_only():
    boxes = np.array(
        [
            [100, 100, 200, 300],  # torso
            [110, 310, 190, 500],  # legs, just below
            [400, 100, 500, 500],  # another person beside
            [120, 700, 180, 750],
        ]
    )  # far below: not the same body
    assert group_boxes(boxes) == [[0, 1], [2], [3]]


def _obs(x, t=0.0):
    return Observation(
        np.array([x, 100.0, x + 50, 300.0]), np.array([x / 100, 0.0, 5.0]), np.full(4, 0.25)
    )


def test_tentative_tracks_do_not_use_up_ids():
    tr = Tracker(TrackerConfig(min_hits=3, max_misses=5))
    got = []
    for k in range(8):
        obs = [_obs(100 + k)]
        if k in (1, 4):
            obs.append(_obs(900.0 + 37 * k))  # single-frame flicker far away
        got.append(tr.update(k / 30, obs))
    assert [g[0] for g in got] == [-1, -1, 0, 0, 0, 0, 0, 0]  # the id is born on the third hit
    assert got[1][1] == -1 and got[4][1] == -1  # flickers never get an id
    assert tr.next_id == 1
    state = tr.state_dict()
    again = Tracker(TrackerConfig(min_hits=3, max_misses=5))
    again.load_state_dict(state)
    assert again.update(8 / 30, [_obs(108)]) == tr.update(8 / 30, [_obs(108)]) == [0]


@NEEDS_LAB
def test_lab_camera_tracking_keeps_few_ids(tmp_path):
    """cam03 of the real capture, every 2nd frame: with the calibrated height check, blob
    grouping and tentative tracks, the two subjects keep a handful of ids (65..20 before)."""
    import pyarrow.parquet as pq

    from calibration.formats import read_rig
    from gst.track import TrackOptions
    from gst.track.static_detector import StaticCameraDetector
    from tests.track_synthetic import track_boxes

    rig = read_rig(LAB / "Calib.qca.txt", "qualisys")
    cam = rig["cam03"]
    video = LAB / "cam03.mp4"
    det = StaticCameraDetector(video, camera=cam, up=rig.up, background=None)
    res = track_boxes(
        video,
        tmp_path,
        det,
        camera=cam,
        options=TrackOptions(
            stride=2, prefetch=0, tracker=TrackerConfig(min_hits=3, max_misses=15)
        ),
    )
    t = pq.read_table(res.path).to_pandas()
    assert t["person_id"].nunique() <= 5
    assert t.groupby("frame").size().count() >= 35  # someone tracked in most of the 50 frames
