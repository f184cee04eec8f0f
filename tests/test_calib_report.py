"""Calibration report and rig checks, including the real Qualisys lab calibration."""

import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration.camera import Camera, Rig
from calibration.checks import CaptureVolume, check_rig, estimate_volume
from calibration.formats import read_rig
from calibration.report import coverage_fraction, write_calibration_report
from calibration.solve import calibrate_from_detections
from calibration.synthetic import make_scene, synthetic_detections

QCA = Path("/work/shared/real/pose2sim-multiperson/Calib.qca.txt")
LAB_VOLUME = CaptureVolume((-2.0, -2.0, 0.0), (2.0, 2.0, 2.0))  # the lab floor area, 2 m high


def test_real_qualisys_cameras_look_into_the_volume(tmp_path):
    rig = read_rig(QCA)
    assert all(c.center[2] > 1.0 for c in rig)  # mounted well above the floor
    for cam in rig:
        assert cam.optical_axis[2] < 0  # tilted down
        assert LAB_VOLUME.ray_hits(cam.center, cam.optical_axis), cam.name
        # The volume centre lies inside the image of every camera.
        uv = cam.project(np.array([[0.0, 0.0, 1.0]]))[0]
        assert (
            0 <= uv[0] < cam.width
            and 0 <= uv[1] < cam.height
            and cam.to_camera([[0, 0, 1.0]])[0, 2] > 0
        )
    assert check_rig(rig, LAB_VOLUME) == [] and check_rig(rig) == []
    md = write_calibration_report(rig, tmp_path, volume=LAB_VOLUME)
    text = md.read_text()
    assert "cam01" in text and "aimed into the capture volume" in text
    img = cv2.imread(str(tmp_path / "camera_poses.png"))
    assert img is not None and img.shape[0] > 400 and img.std() > 10


def test_checks_flag_cameras_below_floor_or_looking_away():
    rig = read_rig(QCA)
    flipped = rig.transformed(
        np.diag([1.0, -1.0, -1.0]), np.zeros(3), up=(0.0, 0.0, 1.0)
    )  # upside down
    problems = check_rig(flipped, LAB_VOLUME)
    assert any("below the floor" in p for p in problems)
    away = CaptureVolume((10.0, 10.0, 0.0), (11.0, 11.0, 2.0))
    assert any("miss the capture volume" in p for p in check_rig(rig, away))
    with pytest.raises(ValueError, match="lo < hi"):
        CaptureVolume((0, 0, 0), (0, 1, 1))


def _with_dist(cam, dist):
    return Camera.create(cam.name, cam.K, np.asarray(dist, float), cam.R, cam.t, cam.width,
                         cam.height)  # fmt: skip


@pytest.mark.parametrize(
    "dist, expected",
    [
        ([50.0, 0, 0, 0, 0], "the field at the image's corners 0.32 x"),  # a units slip: passed
        ([-5.0, 0, 0, 0, 0], "folds 26% of the way to the image's border"),  # turns back early
    ],
)
def test_a_distortion_no_lens_has_is_a_problem_naming_the_camera(dist, expected):
    rig = read_rig(QCA)
    bad = Rig([_with_dist(c, dist) if c.name == "cam02" else c for c in rig], up=rig.up)
    (problem,) = check_rig(bad, LAB_VOLUME)
    assert "camera 'cam02'" in problem and expected in problem


def test_a_model_poorly_held_at_the_corners_is_said_not_refused():
    """A board calibration that never saw the board near the corners folds there (the board-
    solved tcrowd_dome_7010 camera 00_04: k2 = -0.56, 70 % of the way along its worst
    direction): the check refused the rig and calibrate failed on a scene that fused before."""
    from calibration.checks import lens_findings, lens_warnings

    K = [[342.76, 0, 239.5], [0, 342.76, 179.5], [0, 0, 1]]
    base = read_rig(QCA).cameras[0]
    cam = Camera.create("00_04", K, [0.0046, -0.5573, -0.0033, 0.0072, 0.0], base.R, base.t,
                        480, 360)  # fmt: skip
    problem, warning = lens_findings(cam)
    assert problem is None and "00_04" in warning
    assert re.search(r"folds (69|70)% of the way", warning)
    rig = Rig([cam], up=(0.0, 0.0, 1.0))
    assert not any("00_04" in p for p in check_rig(rig, LAB_VOLUME))
    assert lens_warnings(rig) == [warning]


@settings(max_examples=40, deadline=None)
@given(
    k1=st.floats(-0.3, 0.1),
    k2=st.floats(0.0, 0.15),
    p=st.floats(-0.002, 0.002),
    corner=st.floats(0.3, 0.7),
)
def test_real_lenses_pass_the_lens_check(k1, k2, p, corner):
    """Lenses as calibrations give them (the lab's k1 -0.05 k2 0.14; a wide action camera's k1
    -0.3). For r <= 1, r_d = r (1 + k1 r^2 + k2 r^4) grows (its slope is at least 1 - 3 * 0.3)
    and stays within 0.7-1.25 x r; r_d(1) >= 0.7 >= the image corner's distorted radius, so the
    corner's ray lies within r <= 1 (about 45 degrees), and no draw may be called a problem.
    (k1 -0.25 with nothing else cannot reach a corner at r_d 1.0 at all: the check says so.)"""
    from calibration.checks import lens_findings

    base = read_rig(QCA).cameras[0]
    K = base.K.copy()
    K[0, 0] = K[1, 1] = np.hypot(base.width, base.height) / 2 / corner
    K[0, 2], K[1, 2] = base.width / 2, base.height / 2
    cam = Camera.create(base.name, K, [k1, k2, p, -p, 0.0], base.R, base.t, base.width,
                        base.height)  # fmt: skip
    assert lens_findings(cam) == (None, None)


def test_volume_estimate_contains_the_axes_meeting_point():
    rig = make_scene(n_cameras=6, n_frames=2).rig
    vol = estimate_volume(rig)
    c = vol.center
    assert np.hypot(c[0], c[1]) < 0.5 and vol.lo[2] == 0.0  # the ring looks at its centre


def test_board_calibration_report(tmp_path):
    scene = make_scene(n_cameras=4, n_frames=40, seed=2)
    dets = synthetic_detections(scene, noise_px=0.3, seed=2)
    result = calibrate_from_detections(
        dets, {c.name: (c.width, c.height) for c in scene.rig}, scene.board
    )
    md = write_calibration_report(result.rig, tmp_path / "report", result)
    text = md.read_text()
    for cam in result.rig:
        assert cam.name in text and (tmp_path / "report" / f"coverage_{cam.name}.png").exists()
        assert f"{result.rms_px[cam.name]:.3f}" in text
        assert f"{result.detections[cam.name]} / ?" in text  # frames searched unknown here
    assert "BA round" in text and "bundle_adjustment" in text
    png = cv2.imread(str(tmp_path / "report" / "coverage_cam00.png"))
    assert png is not None and png.std() > 5


def test_coverage_fraction():
    pts = np.array([[1.0, 1.0], [799.0, 599.0], [400.0, 300.0]])
    assert coverage_fraction(pts, 800, 600) == pytest.approx(3 / 48)
    assert coverage_fraction(np.zeros((0, 2)), 800, 600) == 0.0


def test_floor_overlay_on_real_footage(tmp_path):
    rig = read_rig(QCA)
    cap = cv2.VideoCapture(str(QCA.parent / "cam01.mp4"))
    ok, frame = cap.read()
    cap.release()
    assert ok and frame.shape[:2] == (1920, 1088)
    frames = {"cam01": frame, "cam02": frame[:1000]}  # cam02 given a wrongly sized frame
    md = write_calibration_report(rig, tmp_path, volume=LAB_VOLUME, frames=frames)
    text = md.read_text()
    assert "overlay_cam01.png" in text and "cam02: frame is 1088x1000" in text
    overlay = cv2.imread(str(tmp_path / "overlay_cam01.png"))
    assert overlay.shape[0] == 960
    # The world origin is drawn where the camera projects it (axis colours differ from the frame).
    u, v = rig["cam01"].project(np.zeros((1, 3)))[0] * 960 / 1920
    patch = overlay[int(v) - 3 : int(v) + 4, int(u) - 3 : int(u) + 4].reshape(-1, 3)
    small = cv2.resize(frame, (overlay.shape[1], overlay.shape[0]), interpolation=cv2.INTER_AREA)
    before = small[int(v) - 3 : int(v) + 4, int(u) - 3 : int(u) + 4].reshape(-1, 3)
    assert np.abs(patch.astype(int) - before.astype(int)).max() > 80


def test_cameras_whose_names_differ_only_in_unsafe_characters_keep_their_own_images(tmp_path):
    from calibration.report import _file_stems

    assert _file_stems(["cam01", "cam 1", "cam_1", "x|y"]) == {
        "cam01": "cam01", "cam 1": "cam_1-1", "cam_1": "cam_1-2", "x|y": "x_y",
    }  # fmt: skip
    rig = read_rig(QCA)
    names = ["cam 1", "cam_1", "cam03", "cam04"]
    rig = Rig(tuple(c.replace(name=n) for c, n in zip(rig.cameras, names, strict=True)), up=rig.up)
    frames = {
        n: np.full((c.height, c.width, 3), 40 * k, np.uint8)
        for k, (n, c) in enumerate(zip(names, rig.cameras, strict=True))
    }
    text = write_calibration_report(rig, tmp_path, frames=frames).read_text()
    assert "overlay_cam_1-0.png" in text and "overlay_cam_1-1.png" in text
    a, b = (cv2.imread(str(tmp_path / f"overlay_cam_1-{k}.png")) for k in (0, 1))
    assert a is not None and b is not None and not np.array_equal(a, b)


def test_file_stems_stay_unique_when_a_name_looks_like_an_indexed_one():
    from calibration.report import _file_stems

    stems = _file_stems(["cam_1-1", "cam 1", "cam_1"])
    assert len(set(stems.values())) == 3 and stems["cam_1-1"] == "cam_1-1"
