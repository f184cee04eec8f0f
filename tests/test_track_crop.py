"""Crop windows, crop intrinsics and crop pixels agree with the stated HMR2/OpenCV conventions."""

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration import Camera
from gst.data.camera_view import TrackingView, default_camera, focal_from_35mm
from gst.data.crop import (
    CropWindow,
    crop_intrinsics,
    crop_window,
    cut_crop,
    cut_undistorted_crop,
    distortion_maps,
)

finite = st.floats(-500, 2500, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(finite, finite, st.floats(5, 900), st.floats(5, 900), st.sampled_from([64, 192, 256]))
def test_window_is_centred_square_of_1_2_times_long_side(x0, y0, w, h, size):
    win = crop_window([x0, y0, x0 + w, y0 + h], size)
    assert win.side == pytest.approx(1.2 * max(w, h))
    assert win.x0 + win.side / 2 == pytest.approx(x0 + w / 2)
    assert win.y0 + win.side / 2 == pytest.approx(y0 + h / 2)
    # the window's corners (corner convention) land on the crop's outer pixel edges
    corners = (
        np.array([[win.x0, win.y0], [win.x0 + win.side, win.y0 + win.side]]) - 0.5
    )  # as centre coords
    np.testing.assert_allclose(
        win.to_crop(corners), [[-0.5, -0.5], [size - 0.5, size - 0.5]], atol=1e-6
    )
    np.testing.assert_allclose(win.to_frame(win.to_crop(corners)), corners, atol=1e-6)


@settings(max_examples=60, deadline=None)
@given(
    st.floats(300, 3000),
    st.floats(-0.01, 0.01),
    finite,
    finite,
    st.floats(10, 800),
    st.integers(0, 10_000),
)
def test_crop_intrinsics_project_like_the_affine_map(f, skew, bx, by, side, seed):
    K = np.array([[f, skew * f, 960.0], [0, f * 1.05, 540.0], [0, 0, 1]])
    win = CropWindow(bx, by, side, 256)
    K_crop = crop_intrinsics(K, win)
    pts = np.random.default_rng(seed).uniform([-3, -2, 1], [3, 2, 20], (20, 3))
    uv = (pts / pts[:, 2:]) @ K[:2].T
    uv_crop = (pts / pts[:, 2:]) @ K_crop[:2].T
    np.testing.assert_allclose(uv_crop, win.to_crop(uv), rtol=1e-9, atol=1e-6)
    # the formula of the convention, written out
    s = 256 / side
    np.testing.assert_allclose(uv_crop[:, 0], (uv[:, 0] - bx + 0.5) * s - 0.5, atol=1e-6)


def blob_image(h, w, centre, sigma):
    yy, xx = np.mgrid[0:h, 0:w]
    g = np.exp(-((xx - centre[0]) ** 2 + (yy - centre[1]) ** 2) / (2 * sigma**2))
    return (255 * g).astype(np.float32)


def centroid(img):
    yy, xx = np.mgrid[0 : img.shape[0], 0 : img.shape[1]]
    m = img.astype(np.float64)
    return np.array([(xx * m).sum() / m.sum(), (yy * m).sum() / m.sum()])


@pytest.mark.parametrize(
    "side", [40.0, 200.0, 900.0]
)  # up-scaling, mild and strong (pyramid) down-scaling
def test_crop_pixels_sit_where_the_map_says(side):
    h, w = 1080, 1920
    centre = np.array([811.3, 517.8])
    img = blob_image(h, w, centre, sigma=max(side / 40, 2.0))
    win = CropWindow(centre[0] - 0.37 * side, centre[1] - 0.61 * side, side, 128)
    crop = cut_crop(img, win)
    expected = win.to_crop(centre)[0]
    np.testing.assert_allclose(centroid(crop), expected, atol=0.05 * max(1, 128 / side) + 0.02)


def test_crop_matches_direct_resampling_and_zero_pads():
    rng = np.random.default_rng(1)
    img = cv2.GaussianBlur(rng.integers(0, 255, (300, 400, 3), dtype=np.uint8), (0, 0), 2)
    win = CropWindow(-50.25, 120.5, 230.0, 256)  # hangs over the left edge
    crop = cut_crop(img, win)
    # reference: invert the map for every crop pixel and sample with cv2.remap
    v, u = np.mgrid[0:256, 0:256].astype(np.float64)
    src = win.to_frame(np.stack([u.ravel(), v.ravel()], 1))
    ref = cv2.remap(
        img,
        src[:, 0].reshape(256, 256).astype(np.float32),
        src[:, 1].reshape(256, 256).astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )
    assert np.abs(crop.astype(int) - ref.astype(int)).max() <= 1
    left_of_frame = win.to_crop([[-1.0, 200.0]])[0, 0]
    assert crop[:, : int(left_of_frame) - 1].max() == 0


def distorted_camera():
    K = [[900.0, 0, 640.0], [0, 905.0, 360.0], [0, 0, 1]]
    return Camera.create(
        "c1", K, [-0.28, 0.09, 0.001, -0.0008, -0.01], np.eye(3), [0.1, 0.2, 3.0], 1280, 720
    )


def test_undistorted_crop_equals_crop_of_undistorted_frame():
    cam = distorted_camera()
    rng = np.random.default_rng(2)
    img = cv2.GaussianBlur(rng.integers(0, 255, (720, 1280, 3), dtype=np.uint8), (0, 0), 3)
    for win in (CropWindow(900.0, 60.0, 300.0, 256), CropWindow(200.0, 300.0, 600.0, 128)):
        ours = cut_undistorted_crop(img, cam, win).astype(int)
        ref = cut_crop(cam.undistort_image(img), win).astype(int)
        # compare away from the edge of the undistorted frame (cv2.undistort keeps only W x H;
        # the direct remap also sees raw pixels that undistort beyond it)
        inside = (
            cv2.erode(((ref > 0).all(-1) & (ours > 0).all(-1)).astype(np.uint8), np.ones((5, 5)))
            > 0
        )
        diff = np.abs(ours - ref)[inside]
        assert inside.mean() > 0.6
        assert np.median(diff) <= 2 and np.percentile(diff, 99) <= 12


def test_interpolated_distortion_maps_match_opencv():
    cam = distorted_camera()
    for win in (
        CropWindow(900.0, 60.0, 300.0, 256),
        CropWindow(-100.0, -50.0, 500.0, 192),
        CropWindow(600, 300, 50, 256),
    ):
        K_crop = crop_intrinsics(cam.K, win)
        ref_x, ref_y = cv2.initUndistortRectifyMap(
            cam.K, cam.dist, None, K_crop, (win.size, win.size), cv2.CV_32FC1
        )
        mx, my = distortion_maps(cam, K_crop, win.size)
        err_raw_px = max(np.abs(mx - ref_x).max(), np.abs(my - ref_y).max())
        assert err_raw_px * win.scale < 0.03  # in crop pixels, what resampling accuracy is about


def test_box_on_raw_frame_maps_to_enclosing_undistorted_box():
    cam = distorted_camera()
    view = TrackingView.for_video(1280, 720, cam)
    box = np.array([1000.0, 80.0, 1200.0, 500.0])  # near a corner: strong distortion
    ub = view.model_box(box)
    # every raw pixel centre inside the box undistorts into the model box
    xs, ys = np.meshgrid(np.arange(1000, 1200, 7) + 0.0, np.arange(80, 500, 7) + 0.0)
    xy = cam.undistort_points(np.stack([xs.ravel(), ys.ravel()], 1))
    uv = xy @ cam.K[:2, :2].T + cam.K[:2, 2]
    assert (uv[:, 0] >= ub[0] - 0.5).all() and (uv[:, 0] <= ub[2] - 0.5).all()
    assert (uv[:, 1] >= ub[1] - 0.5).all() and (uv[:, 1] <= ub[3] - 0.5).all()


def test_default_camera_and_size_check():
    cam = default_camera(1920, 1080)
    assert cam.fx == pytest.approx(np.hypot(1920, 1080)) and cam.cx == 959.5 and cam.cy == 539.5
    with pytest.raises(ValueError, match="1920x1080, but the calibration says 1280x720"):
        TrackingView.for_video(1920, 1080, distorted_camera(), video="match.mp4")


def test_focal_length_from_its_35mm_equivalent():
    """Diagonals matched: a 43.3 mm lens is the default's image diagonal; a phone's 26 mm main
    camera is 0.6 of it; nonsense is refused."""
    diagonal = np.hypot(1088, 1920)
    assert focal_from_35mm(np.hypot(36, 24), 1088, 1920) == pytest.approx(diagonal)
    assert focal_from_35mm(26.0, 1920, 1088) == pytest.approx(26.0 / 43.2666 * diagonal, rel=1e-4)
    cam = TrackingView.for_video(1088, 1920, focal_px=1680.0).camera
    assert cam.fx == cam.fy == 1680.0 and cam.cx == 543.5 and "given" in cam.meta["source"]
    with pytest.raises(ValueError, match="must be > 0"):
        focal_from_35mm(0.0, 1088, 1920)
    with pytest.raises(ValueError, match="must be > 0 px"):
        default_camera(1088, 1920, focal_px=-5.0)


def test_bad_box_is_rejected():
    with pytest.raises(ValueError, match="x1 > x0"):
        crop_window([10, 10, 5, 20])


def test_tracking_window_and_extraction_box_are_one_crop():
    """The tracking fast path (interpolated lens maps, pyramid anti-aliasing) cuts the same crop,
    with the same intrinsics, as extraction's exact path for the equivalent CropBox."""
    from gst.data.crop import extract_crop

    cam = distorted_camera()
    rng = np.random.default_rng(3)
    img = cv2.GaussianBlur(rng.integers(0, 255, (720, 1280, 3), dtype=np.uint8), (0, 0), 4)
    win = crop_window([700.0, 100.0, 900.0, 600.0], 128)
    np.testing.assert_allclose(
        crop_intrinsics(cam.K, win), crop_intrinsics(cam.K, win.box, win.size), atol=1e-12
    )
    fast = cut_undistorted_crop(img, cam, win).astype(int)
    exact = extract_crop(img, cam, win.box, win.size).astype(int)
    diff = np.abs(fast - exact)[8:-8, 8:-8]
    assert np.median(diff) <= 2 and np.percentile(diff, 99) <= 10


def test_a_landmark_beyond_where_the_lens_inverts_has_no_crop_position():
    """Tracking moves the person model's landmarks into the crop through the lens model: one
    outside the frame past where a barrel lens inverts came back hundreds of pixels off."""
    from gst.data.camera_view import TrackingView
    from gst.track.detection import Detection
    from gst.track.frames import prepare_detection

    K = [[1000, 0, 959.5], [0, 1000, 539.5], [0, 0, 1]]
    cam = Camera.create("c", K, [-0.1, 0, 0, 0, 0], np.eye(3), np.zeros(3), 1920, 1080)
    view = TrackingView.for_video(1920, 1080, camera=cam)
    lm = np.zeros((33, 3), np.float32)
    lm[:] = (1700.0, 900.0, 0.9)
    lm[5] = (2100.0, 1300.0, 0.9)
    frame = np.zeros((1080, 1920, 3), np.uint8)
    det = Detection(box=np.array([1500.0, 700.0, 1900.0, 1070.0]), landmarks=lm)
    got = prepare_detection(view, frame, det, 64, pixels=False).landmarks_crop
    assert np.isfinite(got[0, :2]).all() and np.isnan(got[5, :2]).all()
