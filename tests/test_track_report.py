"""Overlay video and joint-angle summary."""

import cv2
import numpy as np
import pytest

from gst.track import (
    SuppliedBoxes,
    TrackOptions,
    column_array,
    read_tracks,
)
from gst.track.baseline import REST_JOINTS
from gst.track.report import (
    SMPL_PARENTS,
    draw_key,
    draw_people,
    joint_angles,
    overlay_size,
    plot_joint_angles,
    write_overlay,
)
from gst.track.schema import SMPL_JOINT_NAMES
from gst.video import probe_video
from tests.track_synthetic import crossing_clip, track_boxes, write_boxes_csv

N = 16


@pytest.fixture(scope="module")
def tracked(tmp_path_factory):
    d = tmp_path_factory.mktemp("report")
    _, boxes, video = crossing_clip(d, N)
    det = SuppliedBoxes.from_file(write_boxes_csv(d / "boxes.csv", boxes, "clip"))
    res = track_boxes(video, d / "tracks", det, options=TrackOptions(stride=2))
    return d, video, res.path


def test_joint_angles_of_known_geometry():
    j = np.tile(REST_JOINTS, (2, 1, 1)).astype(np.float64)
    a = joint_angles(j)
    hip, knee, ankle = (
        REST_JOINTS[SMPL_JOINT_NAMES.index(n)] for n in ("left_hip", "left_knee", "left_ankle")
    )
    a_, b_, c_ = (
        np.linalg.norm(hip - knee),
        np.linalg.norm(ankle - knee),
        np.linalg.norm(hip - ankle),
    )
    law_of_cosines = np.degrees(np.arccos((a_**2 + b_**2 - c_**2) / (2 * a_ * b_)))
    assert a["left_knee"][0] == pytest.approx(law_of_cosines, abs=1e-6)
    # bend the right knee to a right angle: ankle straight forward of the knee
    knee = j[1, SMPL_JOINT_NAMES.index("right_knee")]
    hip = j[1, SMPL_JOINT_NAMES.index("right_hip")]
    thigh = knee - hip
    fwd = np.cross(thigh, [1.0, 0, 0])
    j[1, SMPL_JOINT_NAMES.index("right_ankle")] = knee + 0.4 * fwd / np.linalg.norm(fwd)
    assert joint_angles(j)["right_knee"][1] == pytest.approx(90.0, abs=1e-6)


def test_parents_form_a_tree_rooted_at_the_pelvis():
    assert SMPL_PARENTS[0] == -1 and all(p < c for c, p in enumerate(SMPL_PARENTS) if c)
    assert SMPL_JOINT_NAMES[SMPL_PARENTS[SMPL_JOINT_NAMES.index("left_wrist")]] == "left_elbow"


def test_an_overlay_of_a_panorama_fits_the_codec(tmp_path):
    """An 8400 px wide video (a stitched panorama) failed the overlay's MPEG-4 writer (at most
    8191 px a side) after the whole tracking, and the finished tracks were never published: the
    overlay is scaled down to 4096 px on its longer side, sides even."""
    _, boxes, video = crossing_clip(tmp_path, 3, width=8400, height=200)
    det = SuppliedBoxes.from_file(write_boxes_csv(tmp_path / "boxes.csv", boxes, "clip"))
    res = track_boxes(video, tmp_path / "tracks", det)
    info = probe_video(write_overlay(video, res.path, tmp_path / "overlay.mp4"))
    assert (info.width, info.height, info.frame_count) == (4096, 98, 3)
    assert overlay_size(320, 240) == (320, 240)  # what fits is kept as it is
    assert overlay_size(1, 1) == (16, 16) and overlay_size(41, 33) == (40, 32)


def test_overlay_draws_skeletons_at_their_joints(tracked):
    d, video, path = tracked
    out = write_overlay(video, path, d / "overlay.mp4")
    info = probe_video(out)
    assert (info.width, info.height, info.frame_count) == (
        320,
        240,
        N // 2,
    ) and info.fps == pytest.approx(15.0)
    t = read_tracks(path)
    first = t.filter(t.column("frame").to_numpy() == 0)
    blank = np.zeros((240, 320, 3), np.uint8)
    drawn = draw_people(blank, first)
    for joints in column_array(first, "joints2d"):
        inside = joints[
            (joints[:, 0] >= 0) & (joints[:, 0] < 319) & (joints[:, 1] >= 0) & (joints[:, 1] < 239)
        ]
        for u, v in np.round(inside).astype(int):
            assert drawn[v, u].max() > 0  # every visible joint is marked


def test_overlay_tells_left_from_right(tracked):
    """The network's right joints are dark dots, its left ones white: a body read the wrong way
    round shows on the overlay."""
    _, _, path = tracked
    t = read_tracks(path)
    first = t.filter(t.column("frame").to_numpy() == 0)
    drawn = draw_people(np.zeros((240, 320, 3), np.uint8), first)
    checked = {"left": 0, "right": 0}
    for joints in column_array(first, "joints2d"):
        for j, name in enumerate(SMPL_JOINT_NAMES):
            side = name.split("_")[0]
            u, v = np.round(joints[j]).astype(int)
            apart = np.delete(np.linalg.norm(joints - joints[j], axis=1), j).min() > 6
            if side not in checked or not apart or not (0 <= u < 320 and 0 <= v < 240):
                continue
            assert tuple(drawn[v, u]) == ((40, 40, 40) if side == "right" else (255, 255, 255))
            checked[side] += 1
    assert checked["left"] > 0 and checked["right"] > 0


def test_joint_angle_png(tracked):
    d, _, path = tracked
    png = plot_joint_angles(path, d / "angles.png", min_rows=2)
    img = cv2.imread(str(png))
    assert img is not None and img.shape[0] > 400 and img.shape[1] > 800


def test_overlay_key_names_both_skeletons_in_the_bottom_left_corner():
    blank = np.zeros((480, 640, 3), np.uint8)
    both = draw_key(blank.copy())
    network_only = draw_key(blank.copy(), with_landmarks=False)
    rows = np.flatnonzero(both.any(axis=(1, 2)))
    cols = np.flatnonzero(both.any(axis=(0, 2)))
    assert rows.min() > 480 // 2 and cols.max() < 640 * 3 // 4  # a corner, not the picture
    # without landmarks one line fewer: it starts lower
    assert np.flatnonzero(network_only.any(axis=(1, 2))).min() > rows.min()
